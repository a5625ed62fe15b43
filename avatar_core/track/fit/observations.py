"""Tracker output -> the fitter's targets: pixels [K, 2] and confidence weights [K].

A landmark that is NaN, missing or below the visibility threshold gets weight 0; a group
(face, a hand, the torso) with too few usable landmarks counts as not seen this frame.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..types import TrackResult
from . import correspondence as cor

MIN_VISIBILITY = 0.5  # BlazePose visibility below this: the landmark is guessed, not seen
MIN_POINTS = {"face": 20, "left_hand": 8, "right_hand": 8, "pose": 2}
# Pose landmarks that count toward "the torso is seen" (shoulders, elbows, wrists).
POSE_ARM_IDS = (11, 12, 13, 14, 15, 16)


@dataclass
class Observations:
    pixels: np.ndarray                     # [K, 2] image px (0 where unused)
    weights: np.ndarray                    # [K] >= 0
    image_size: tuple[int, int]            # (w, h)
    seen: dict[str, bool] = field(default_factory=dict)  # group -> usable this frame
    # [K] MediaPipe's relative depth z (px, smaller is nearer; hands: 0 at the wrist), NaN
    # where not given.
    depth: np.ndarray | None = None
    # [2, 2] iris centres px (the person's right eye, then left; NaN: not read), or None.
    iris: np.ndarray | None = None
    # [33, 3] BlazePose's metric world landmarks (m, hip-centred, z away from the camera),
    # NaN where unused, or None when the tracker gave none.
    world: np.ndarray | None = None


def empty_observations(image_size: tuple[int, int]) -> Observations:
    return Observations(np.zeros((cor.NUM_KEYPOINTS, 2)), np.zeros(cor.NUM_KEYPOINTS),
                        image_size, {g: False for g in cor.GROUP_SLICES},
                        np.full(cor.NUM_KEYPOINTS, np.nan))


def _put(obs: Observations, group: str, points: np.ndarray, weights: np.ndarray) -> None:
    sl = cor.GROUP_SLICES[group]
    raw = np.asarray(points, dtype=np.float64)
    pts = raw[:, :2]
    w = np.where(np.isfinite(pts).all(axis=1), np.asarray(weights, dtype=np.float64), 0.0)
    obs.pixels[sl] = np.where(w[:, None] > 0, np.nan_to_num(pts), 0.0)
    if raw.shape[1] > 2:
        obs.depth[sl] = np.where(w > 0, raw[:, 2], np.nan)
    obs.weights[sl] = w
    obs.seen[group] = int((w > 0).sum()) >= MIN_POINTS[group]
    if not obs.seen[group]:
        obs.weights[sl] = 0.0


def from_landmarks(image_size: tuple[int, int], *, face: np.ndarray | None = None,
                   left_hand: np.ndarray | None = None, right_hand: np.ndarray | None = None,
                   pose: np.ndarray | None = None,
                   pose_visibility: np.ndarray | None = None,
                   pose_world: np.ndarray | None = None) -> Observations:
    """Observations from raw landmark arrays: face [468, 2+] (MediaPipe face mesh), hands
    [21, 2+], pose [33, 2+] with visibility [33] and world landmarks [33, 3] (m). None: not
    detected."""
    obs = empty_observations(image_size)
    if face is not None:
        face = np.asarray(face, dtype=np.float64)
        if face.shape[0] != 468:
            raise ValueError(f"face landmarks must be [468, 2+], got {list(face.shape)}")
        _put(obs, "face", cor.face_468_to_ibug68(face[:, :3]), np.ones(cor.NUM_FACE))
    for group, hand in (("left_hand", left_hand), ("right_hand", right_hand)):
        if hand is not None:
            _put(obs, group, hand, np.ones(cor.NUM_HAND))
    if pose is not None:
        vis = np.ones(cor.NUM_POSE) if pose_visibility is None else np.asarray(pose_visibility)
        mapped = np.array([name is not None for name in cor.POSE_MP_TO_SMPLX])
        w = np.where(mapped & (vis >= MIN_VISIBILITY), vis, 0.0)
        _put(obs, "pose", pose, w)
        arms = obs.weights[cor.POSE_SLICE][list(POSE_ARM_IDS)]
        obs.seen["pose"] = obs.seen["pose"] and int((arms > 0).sum()) >= 2
        if pose_world is not None:
            world = np.asarray(pose_world, dtype=np.float64)
            if world.shape != (cor.NUM_POSE, 3):
                raise ValueError(f"pose world landmarks must be [33, 3], got "
                                 f"{list(world.shape)}")
            used = (obs.weights[cor.POSE_SLICE] > 0) | (mapped & (vis >= MIN_VISIBILITY))
            obs.world = np.where(used[:, None] & np.isfinite(world), world, np.nan)
    return obs


POSE_WRISTS = {"left": 15, "right": 16}  # BlazePose: the person's own left / right wrist
# BlazePose's points of each hand (pinky, index, thumb): they place a hand that the hand
# landmark model declines (docs/tracking.md: it rejects most hands hanging in front view).
POSE_HAND_POINTS = {"left": (17, 19, 21), "right": (18, 20, 22)}
MIN_POSE_HAND_POINTS = 2  # fewer cannot turn the wrist


def pose_hand_seen(obs: Observations, side: str) -> bool:
    """The pose model's points of this hand are in use (`from_track_result`)."""
    rows = [cor.POSE_SLICE.start + i for i in POSE_HAND_POINTS[side]]
    return int((obs.weights[rows] > 0).sum()) >= MIN_POSE_HAND_POINTS


# BlazePose's arm points below the shoulder, per side: elbow, wrist, pinky, index, thumb.
POSE_ARM_POINTS = {"left": (13, 15, 17, 19, 21), "right": (14, 16, 18, 20, 22)}


def arm_seen(obs: Observations, side: str) -> bool:
    """Something below this shoulder is observed: the pose model's elbow, wrist or hand
    points, or the hand's own landmarks. Otherwise the arm is out of view (or unread) and
    nothing in the frame tells where it is."""
    rows = [cor.POSE_SLICE.start + i for i in POSE_ARM_POINTS[side]]
    return bool(obs.seen.get(f"{side}_hand")) or bool((obs.weights[rows] > 0).any())


def without_edge_arm_points(obs: Observations, margin_px: float) -> Observations:
    """A copy of `obs` whose arm points (`POSE_ARM_POINTS`) within `margin_px` of the image's
    border are unused: BlazePose puts a joint that is out of view on the border itself
    (docs/tracking.md: elbows below the frame 3-11 px above its bottom, visibility 0.55-0.68),
    which pulls the arm up into the picture. 0: `obs` as it is."""
    if margin_px <= 0:
        return obs
    w, h = obs.image_size
    rows = np.array([cor.POSE_SLICE.start + i for ids in POSE_ARM_POINTS.values() for i in ids])
    px = obs.pixels[rows]
    near = (px[:, 0] < margin_px) | (px[:, 0] >= w - margin_px) | (px[:, 1] < margin_px) | \
        (px[:, 1] >= h - margin_px)
    if not (near & (obs.weights[rows] > 0)).any():
        return obs
    weights = obs.weights.copy()
    weights[rows[near]] = 0.0
    return dataclasses.replace(obs, weights=weights)


def hand_sides(result: TrackResult) -> dict[str, np.ndarray]:
    """Each hand's landmarks [21, 3] by the person's side. The hand model's handedness label
    is wrong on ~20% of detections (docs/tracking.md: 58% while clapping), so when the body's
    wrists are seen, a hand goes to the nearer wrist (two hands: the cheaper of the two
    pairings); otherwise the best-scoring hand of each label is kept."""
    hands = sorted(result.hands, key=lambda h: h.score, reverse=True)[:2]
    pose = result.pose
    wrists = {}
    if pose is not None:
        for side, i in POSE_WRISTS.items():
            if pose.visibility[i] >= MIN_VISIBILITY and np.isfinite(pose.points[i, :2]).all():
                wrists[side] = pose.points[i, :2]
    if hands and len(wrists) == 2:
        def dist(hand, side):
            return float(np.linalg.norm(hand.points[0, :2] - wrists[side]))  # hand point 0: wrist

        if len(hands) == 1:
            side = min(wrists, key=lambda s: dist(hands[0], s))
            return {side: hands[0].points}
        a, b = hands
        keep = dist(a, "left") + dist(b, "right") <= dist(a, "right") + dist(b, "left")
        return {"left": a.points, "right": b.points} if keep else \
            {"left": b.points, "right": a.points}
    out: dict[str, np.ndarray] = {}
    for hand in reversed(hands):
        out[hand.handedness] = hand.points  # the higher score overwrites
    return out


# MediaPipe landmarks whose definition differs from the model keypoint they map to, measured on
# renders with known parameters (docs/tracking.md): the face-mesh jaw outline sits ~9 px wider
# and ~11 px higher than the model's contour, BlazePose's ears ~16 px above the ear vertices
# and its hips ~26 px wider than the hip joints. Fitting them tilts the head and leans the
# spine (head error 14.6 deg); left out, 7.3 deg.
MISMATCHED_ROWS = np.array([*range(cor.FACE_SLICE.start, cor.FACE_SLICE.start + 17),
                            *(cor.POSE_SLICE.start + i for i in (7, 8, 23, 24))])


def all_landmarks(result: TrackResult) -> Observations:
    """Every landmark the tracker found: the hands by side (:func:`hand_sides`), the face and
    the pose (with its world landmarks), at their own weights (the embedding builder reads
    them all)."""
    hands = hand_sides(result)
    pose = result.pose
    return from_landmarks(
        result.image_size, face=None if result.face is None else result.face.points,
        left_hand=hands.get("left"), right_hand=hands.get("right"),
        pose=None if pose is None else pose.points,
        pose_visibility=None if pose is None else pose.visibility,
        pose_world=None if pose is None else pose.world)


def without_pose_hands(obs: Observations) -> Observations:
    """A copy of `obs` with the pose model's hand points (`POSE_HAND_POINTS`) unused."""
    rows = [cor.POSE_SLICE.start + i for ids in POSE_HAND_POINTS.values() for i in ids]
    weights = obs.weights.copy()
    weights[rows] = 0.0
    return dataclasses.replace(obs, weights=weights)


def from_track_result(result: TrackResult, pose_hands: bool = False) -> Observations:
    """:func:`all_landmarks`, but landmarks that MediaPipe defines differently from the model
    (`MISMATCHED_ROWS`) get weight 0; the iris too, when the face has one. `pose_hands`: the
    pose model's points of a hand (`POSE_HAND_POINTS`) are kept while that hand's own
    landmarks are not seen, inside the image, and only with at least `MIN_POSE_HAND_POINTS`
    of them (off by default: measured worse, docs/tracking.md)."""
    obs = all_landmarks(result)
    obs.weights[MISMATCHED_ROWS] = 0.0
    w, h = obs.image_size
    for side, ids in POSE_HAND_POINTS.items():
        rows = [cor.POSE_SLICE.start + i for i in ids]
        px = obs.pixels[rows]
        outside = (px[:, 0] < 0) | (px[:, 0] >= w) | (px[:, 1] < 0) | (px[:, 1] >= h)
        obs.weights[np.array(rows)[outside]] = 0.0  # BlazePose's guess of a hand out of view
        if not pose_hands or obs.seen.get(f"{side}_hand") or not pose_hand_seen(obs, side):
            obs.weights[rows] = 0.0
    if result.face is not None and result.face.iris is not None and obs.seen.get("face"):
        obs.iris = np.asarray(result.face.iris[:, 0, :2], dtype=np.float64)
    return obs
