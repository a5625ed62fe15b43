"""The webcam protocol on the studio (``telesplat synth webcam-eval``): what a viewer sees when
a webcam drives the avatar, with the truth known at every joint.

A take of >= 10 s with the arms moving (`TAKE`: wave, clap, point, hands at the face, an arm
out of the frame and back) is played by each identity and filmed by the fitter's 640x480 webcam
in each framing (`FRAMINGS`: head-and-shoulders, waist-up), over a noisy static background
with sensor noise, JPEG-encoded as a browser sends it. The frames go through the live path
(`Tracker` with the server's palm interval and irises, `from_track_result`, `SequenceFit`
with the actor's betas) once per *drive*:

* ``live``: the tracked landmarks; ``embedding``: the same through the learned landmark
  embedding and BlazePose's image z;
* ``true_body``, ``true_body_face``, ``true_all``: the same, with the tracked 2D landmarks of
  the pose model, then also the face, then also the hands replaced by the truth (the model's
  own keypoints of the true parameters, projected; points outside the image dropped) and
  refitted: the part-attribution table (which landmarks cost what);
* ``*_depth``: the true depth of one part's body landmarks given as well (`protocol_drives`).

Each drive's parameters, without ``transl`` (the avatar stays at its own place, as on the
server), pose the same textured actor at a *score* camera `SCORE_ANGLE_DEG` to the side of the
webcam; PSNR is against the actor posed by the true parameters, over the pixels either covers.
The studio actor is the ideal avatar, so PSNR here is tracking error alone (driving it with the
true parameters is exact). Also per drive: joint angle errors (root in the world; shoulders and
elbows local; neck/head as the head's rotation relative to the chest), keypoint jitter (TJE, px
at the score camera), fit ms per frame; per take the landmark groups' presence.

The unsmoothed fit of each frame is kept, so the One Euro settings' jitter-vs-lag curve is
computed afterwards on the same frames (`temporal_curve`): smoothing does not feed back into
the fit (`SequenceFit` warm-starts from its unsmoothed output).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from avatar_core.body.skeleton import JOINT
from avatar_core.render.camera import Camera, look_at
from avatar_core.track.fit.correspondence import POSE_SLICE
from avatar_core.track.fit.world_correction import bone_directions, with_bone_directions
from avatar_core.track.fit.world_cues import WORLD_TO_CAMERA, torso_axis

from .metrics import GROUPS, Posed, aa_to_matrix, evaluate_params, geodesic_deg
from .protocol_drives import (
    DEFAULT_DRIVES,
    DRIVES,
    check_drives,
    drive_config,
    true_world,
    with_shoulder_line,
    with_torso_axis,
)
from .scene import FOV_X_DEG, background, render_frame, webcam_camera

TAKE = ("wave", "clapping", "pointing", "hands_to_face", "reach_out")
MIN_TAKE_S = 10.0
# Framing: the image's top at the head joint + HEAD_TOP_M, its bottom at this joint's height
# (+ offset, m): head-and-shoulders ends at the chest, waist-up at the pelvis (BlazePose's hips
# fall just below the frame), hips-in-view 15 cm below it (both hips in the picture).
FRAMINGS = {"head_shoulders": ("spine3", -0.05), "waist_up": ("pelvis", 0.0),
            "hips_in_view": ("pelvis", -0.15)}
DEFAULT_FRAMINGS = ("head_shoulders", "waist_up")  # the protocol's; hips_in_view on request
HEAD_TOP_M = 0.30
FRAMING_MARGIN = 1.05
SCORE_ANGLE_DEG = 30.0
JPEG_QUALITY = 90
SENSOR_NOISE = 2 / 255
ANGLE_JOINTS = {"shoulders": ("left_shoulder", "right_shoulder"),
                "elbows": ("left_elbow", "right_elbow"),
                "wrists": ("left_wrist", "right_wrist")}
# One Euro settings for the jitter-vs-lag curve (min_cutoff Hz, beta); None: no smoothing.
CURVE_SETTINGS: tuple[tuple[float, float] | None, ...] = (
    None, (6.0, 0.3), (4.0, 0.3), (3.0, 0.3), (2.0, 0.3), (1.5, 0.3), (1.0, 0.1), (0.5, 0.05),
    (0.25, 0.02))
MAX_LAG_S = 0.5
LAG_STEP_S = 0.005

Progress = Callable[[str, int, int], None]


@dataclass
class Condition:
    """One identity filmed in one framing, its whole body turned `turn_deg` about the vertical
    (positive: toward its own left; the protocol's takes face the webcam) and leaned
    `lean_deg` about its own left-right axis (positive: forward, toward the webcam)."""

    identity: int
    framing: str
    turn_deg: float = 0.0
    lean_deg: float = 0.0

    @property
    def name(self) -> str:
        turn = f"_turn{self.turn_deg:+g}" if self.turn_deg else ""
        lean = f"_lean{self.lean_deg:+g}" if self.lean_deg else ""
        return f"{self.identity}_{self.framing}{turn}{lean}"

    @property
    def framing_label(self) -> str:
        """The framing and, where set, the turn and lean, in words (the reports' column)."""
        turn = f" turned {self.turn_deg:+g} deg" if self.turn_deg else ""
        lean = f" leaned {self.lean_deg:+g} deg" if self.lean_deg else ""
        return f"{self.framing}{turn}{lean}"


@dataclass
class RunResult:
    condition: Condition
    fps: float
    truth: list[dict[str, np.ndarray]]
    raw: dict[str, list[dict[str, np.ndarray]]]      # drive -> unsmoothed fit per frame
    smooth: dict[str, list[dict[str, np.ndarray]]]   # drive -> what drives the avatar
    fit_ms: dict[str, list[float]]
    track_ms: list[float]
    psnr: dict[str, list[float]]
    seen: dict[str, np.ndarray]                      # group -> [T] bool (live tracker)
    in_view: dict[str, np.ndarray]                   # hand -> [T] all true keypoints inside
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    # hand -> [T] bool: placed by the live tracker, by its own landmarks or by the pose
    # model's points of it (`observations.pose_hand_seen`)
    placed: dict[str, np.ndarray] = field(default_factory=dict)
    curve: list[dict[str, float]] = field(default_factory=list)  # `temporal_curve`
    start_frame: int = 0


def framed_transl(actor, camera: Camera, framing: str) -> np.ndarray:
    """`transl` that fills the webcam's height from above the head down to the framing's
    bottom joint, centred on the pelvis horizontally."""
    if framing not in FRAMINGS:
        raise ValueError(f"unknown framing {framing!r}; known: {', '.join(FRAMINGS)}")
    joint, offset = FRAMINGS[framing]
    with torch.no_grad():
        joints = actor.model({"betas": actor.betas}).joints[0].numpy()
    top = joints[JOINT["head"], 1] + HEAD_TOP_M
    bottom = joints[JOINT[joint], 1] + offset
    fov_y = 2 * math.atan(0.5 * camera.height / camera.fy)
    distance = FRAMING_MARGIN * (top - bottom) / (2 * math.tan(fov_y / 2))
    return np.array([-joints[JOINT["pelvis"], 0], -0.5 * (top + bottom),
                     -distance - joints[JOINT["head"], 2]])


def score_camera(transl: np.ndarray, actor, width: int, height: int,
                 angle_deg: float = SCORE_ANGLE_DEG) -> Camera:
    """The held-out camera: the webcam turned `angle_deg` about the vertical through the
    subject's spine3 joint, looking at it."""
    with torch.no_grad():
        chest = actor.model({"betas": actor.betas}).joints[0, JOINT["spine3"]].numpy() + transl
    a = math.radians(angle_deg)
    rot = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0],
                    [-math.sin(a), 0.0, math.cos(a)]])
    eye = chest + rot @ (np.zeros(3) - chest)
    webcam = webcam_camera(width, height)
    fov_y = 2 * math.degrees(math.atan(0.5 * height / webcam.fy))
    return look_at(tuple(eye), tuple(chest), width=width, height=height, fov_y_deg=fov_y)


def take_params(actor, rig, transl: np.ndarray, fps: float, max_frames: int | None = None,
                names: Sequence[str] = TAKE, start_frame: int = 0, turn_deg: float = 0.0,
                lean_deg: float = 0.0) -> list[dict[str, np.ndarray]]:
    """The true parameters of frames [start_frame, max_frames) of the take at `fps`, the body
    leaned `lean_deg` forward, then turned `turn_deg` about the vertical (both through its
    root joint)."""
    from scipy.spatial.transform import Rotation

    from avatar_core.motion.library import motion_sequence

    track = motion_sequence(list(names))
    n = int(math.floor(track.duration * fps + 1e-9)) + 1
    n = n if max_frames is None else min(n, max_frames)
    betas = np.asarray(actor.betas, dtype=np.float64)
    # the body faces +z: a positive rotation about x brings its head forward
    whole_body = Rotation.from_euler("y", turn_deg, degrees=True) \
        * Rotation.from_euler("x", lean_deg, degrees=True)
    out = []
    for i in range(start_frame, n):
        params = {**track.sample(i / fps, rig), "transl": transl.copy(), "betas": betas}
        if turn_deg or lean_deg:
            root = Rotation.from_rotvec(np.asarray(params["global_orient"]).reshape(3))
            params["global_orient"] = (whole_body * root).as_rotvec()
        out.append(params)
    return out


def motion_of_frames(names: Sequence[str], fps: float, frames: int, start_frame: int = 0
                     ) -> list[str]:
    """The take's motion playing at each frame (a crossfade counts to the motion it leads
    into)."""
    from avatar_core.motion.library import motion_sequence

    take = motion_sequence(list(names))
    ends, t = [], 0.0
    for track in take.tracks:
        t += track.duration
        ends.append(t)
        t += take.crossfade
    out = []
    for i in range(start_frame, start_frame + frames):
        k = next((j for j, end in enumerate(ends) if i / fps <= end), len(ends) - 1)
        out.append(names[k])
    return out


def _true_observations(fitter, params: dict[str, np.ndarray], wcam):
    """The truth in the tracker's place: the model's keypoints of `params` projected, points
    outside the image and the rows the live path ignores given weight 0."""
    from avatar_core.track.fit import correspondence as cor
    from avatar_core.track.fit.observations import MISMATCHED_ROWS
    from avatar_core.track.fit.synthetic import synthetic_observations

    obs, clean = synthetic_observations(fitter, {k: v for k, v in params.items()
                                                 if k != "betas"}, wcam)
    inside = np.isfinite(clean).all(-1) & (clean[:, 0] >= 0) & (clean[:, 0] < wcam.width) \
        & (clean[:, 1] >= 0) & (clean[:, 1] < wcam.height)
    obs.weights[~inside] = 0.0
    obs.weights[MISMATCHED_ROWS] = 0.0
    return obs, cor


def _true_pose_points(fitter, params: dict[str, np.ndarray]) -> np.ndarray:
    """[33, 3] the fitter's pose keypoints of the true parameters, in the model (camera)
    frame; NaN where BlazePose has no model point."""
    from avatar_core.track.fit import correspondence as cor
    from avatar_core.track.fit.synthetic import model_keypoints

    return model_keypoints(fitter, {k: v for k, v in params.items() if k != "betas"}
                           ).numpy()[cor.POSE_SLICE]


def mix_observations(live, truth, parts: Sequence[str]):
    """`live` with the landmark groups in `parts` taken from `truth` (pixels, weights, depth,
    seen); a new object, `live` untouched."""
    from avatar_core.track.fit import correspondence as cor
    from avatar_core.track.fit.observations import MIN_POINTS, POSE_ARM_IDS

    out = type(live)(live.pixels.copy(), live.weights.copy(), live.image_size,
                     dict(live.seen), None if live.depth is None else live.depth.copy(),
                     live.iris, None if live.world is None else live.world.copy())
    for g in parts:
        sl = cor.GROUP_SLICES[g]
        out.pixels[sl], out.weights[sl] = truth.pixels[sl], truth.weights[sl]
        if out.depth is not None and truth.depth is not None:
            out.depth[sl] = truth.depth[sl]
        seen = int((out.weights[sl] > 0).sum()) >= MIN_POINTS[g]
        if g == "pose":
            seen = seen and int((out.weights[sl][list(POSE_ARM_IDS)] > 0).sum()) >= 2
        out.seen[g] = seen
        if not seen:
            out.weights[sl] = 0.0
    return out


def _psnr(pred, truth) -> float:
    """PSNR over the pixels either render covers."""
    keep = (pred.alpha > 1e-3) | (truth.alpha > 1e-3)
    if not keep.any():
        return float("nan")
    mse = float(((pred.rgb - truth.rgb) ** 2)[keep].mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


@dataclass
class Recording:
    """One condition filmed and tracked once, so that every drive (and every fit variant)
    is fitted on the very same landmarks: per frame the live observations, the truth in the
    tracker's place and the true pose points (model frame)."""

    condition: Condition
    fps: float
    truth: list[dict[str, np.ndarray]]
    live: list                                       # Observations per frame
    true_obs: list                                   # Observations per frame
    true_points: list[np.ndarray]                    # [33, 3] per frame
    track_ms: list[float]
    seen: dict[str, np.ndarray]
    placed: dict[str, np.ndarray]
    in_view: dict[str, np.ndarray]
    start_frame: int = 0


def _actor_setup(condition: Condition, fps: float, max_frames, take, start_frame, model_dir):
    from avatar_core.motion.rig import model_rig
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models

    files = ensure_models(model_dir)
    actor = Actor.load(files, condition.identity)
    cam = webcam_camera()
    transl = framed_transl(actor, cam, condition.framing)
    truth = take_params(actor, model_rig(files, actor.model), transl, fps, max_frames, take,
                        start_frame, condition.turn_deg, condition.lean_deg)
    if len(truth) < 2:
        raise ValueError(f"the protocol needs at least 2 frames, got {len(truth)}")
    return files, actor, cam, transl, truth


def record_condition(condition: Condition, fps: float, *, max_frames: int | None = None,
                     model_dir=None, take: Sequence[str] = TAKE, start_frame: int = 0,
                     progress: Progress | None = None) -> Recording:
    """Film and track one identity in one framing (the live path's landmarks), with the
    truth in the tracker's place beside them."""
    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.track.fit.camera import WebcamCamera
    from avatar_core.track.fit.fitter import FrameFitter
    from avatar_core.track.fit.observations import from_track_result, pose_hand_seen
    from avatar_core.track.image import decode_image
    from avatar_core.track.tracker import LIVE_PALM_INTERVAL, Tracker

    files, actor, cam, transl, truth = _actor_setup(condition, fps, max_frames, take,
                                                    start_frame, model_dir)
    bg = background(cam.width, cam.height)
    wcam = WebcamCamera(cam.width, cam.height, FOV_X_DEG)
    betas = np.asarray(actor.betas, dtype=np.float64)
    fitter = FrameFitter(synthetic_package(files.root, condition.identity)[1], betas)
    tracker = Tracker(threads=1, palm_interval=LIVE_PALM_INTERVAL, iris=True)
    rng = np.random.default_rng([23, condition.identity, len(condition.framing)])
    n = len(truth)
    rec = Recording(condition, fps, truth, [], [], [], [],
                    {g: np.zeros(n, bool) for g in GROUPS},
                    {f"{s}_hand": np.zeros(n, bool) for s in ("left", "right")}, {},
                    start_frame)
    try:
        for i, params in enumerate(truth):
            frame = render_frame(actor, params, cam, bg, SENSOR_NOISE, rng)
            ok, jpeg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise RuntimeError("JPEG encoding failed")
            t0 = time.perf_counter()
            # With the pose's hand points: drives without them (`pose_hands`) drop them.
            live = from_track_result(tracker.track(decode_image(jpeg.tobytes())),
                                     pose_hands=True)
            rec.track_ms.append((time.perf_counter() - t0) * 1e3)
            for g in GROUPS:
                rec.seen[g][i] = bool(live.seen.get(g))
            for side in ("left", "right"):
                rec.placed[f"{side}_hand"][i] = bool(live.seen.get(f"{side}_hand")) or \
                    pose_hand_seen(live, side)
            rec.live.append(live)
            rec.true_obs.append(_true_observations(fitter, params, wcam)[0])
            rec.true_points.append(_true_pose_points(fitter, params))
            if progress:
                progress(f"{condition.identity}/{condition.framing}", i + 1, n)
    finally:
        tracker.close()
    truth_web = evaluate_params(actor, truth, cam)
    rec.in_view = {g: truth_web.visible[g].all(-1) for g in ("left_hand", "right_hand")}
    return rec


def drive_observations(rec: Recording, i: int, drive: str):
    """Frame i's observations as `drive` feeds them to the fit."""
    spec = DRIVES[drive]
    obs = rec.live[i]
    if not (spec.true_2d or spec.true_depth or spec.true_world or spec.true_bones
            or spec.true_pose_rows or spec.true_torso_axis or spec.true_shoulder_line):
        return obs
    obs = mix_observations(obs, rec.true_obs[i], spec.true_2d)
    points = np.asarray(rec.true_points[i], dtype=np.float64)
    if spec.true_depth:
        obs.world = true_world(points, spec.true_depth)
    if spec.true_world:  # the fit's camera frame -> BlazePose's world axes
        obs.world = points * WORLD_TO_CAMERA
    if spec.true_bones and obs.world is not None:
        # the other bones keep BlazePose's direction from wherever their near end moves to
        unit, length = bone_directions(obs.world * WORLD_TO_CAMERA)
        true_bones = list(spec.true_bones)
        unit[true_bones] = bone_directions(points)[0][true_bones]
        obs.world = with_bone_directions(obs.world, unit, length)
    if spec.true_shoulder_line and obs.world is not None:
        line = points[11] - points[12]  # right shoulder to left (world_cues.SHOULDER_LINE)
        obs.world = with_shoulder_line(obs.world, line * WORLD_TO_CAMERA / np.linalg.norm(line))
    if spec.true_torso_axis and obs.world is not None:
        axis = torso_axis(points) * WORLD_TO_CAMERA
        obs.world = with_torso_axis(obs.world, axis / np.linalg.norm(axis))
    true = rec.true_obs[i]
    for row in spec.true_pose_rows:  # where both the tracker and the truth have the point
        k = POSE_SLICE.start + row
        if obs.weights[k] > 0 and true.weights[k] > 0:
            obs.pixels[k] = true.pixels[k]
    return obs


def with_variant(config, changes: dict):
    """`config` (a SequenceFitConfig, as its drive fits) with a variant's `changes`: its
    fields, and under "fit" a dict of FitConfig fields changed on the drive's own fit. Applied
    after the drive's configuration, so that a variant of `arm_cues` naming
    `world_direction_bones` changes them instead of being overwritten by the drive's cues."""
    top = {k: v for k, v in changes.items() if k != "fit"}
    fit = dataclasses.replace(config.fit, **changes.get("fit", {}))
    return dataclasses.replace(config, **top, fit=fit)


def fit_recording(rec: Recording, *, drives: Sequence[str] = DEFAULT_DRIVES,
                  score_size: tuple[int, int] = (320, 240), model_dir=None,
                  fit_config=None, curve: bool = True,
                  variants: dict[str, dict] | None = None,
                  progress: Progress | None = None) -> RunResult:
    """Fit every drive on the recorded frames and score it (`run_condition`'s second half).
    `variants`: label -> `SequenceFitConfig` fields to change over each drive's own
    configuration (`with_variant`); each drive is fitted once per variant, frame by frame side
    by side, as "drive" (label "") or "drive+label"; or, where `drives` names "drive+label"
    entries itself, just those."""
    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models
    from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig

    explicit = any("+" in d for d in drives)
    check_drives([d.partition("+")[0] for d in drives])
    condition, truth = rec.condition, rec.truth
    files = ensure_models(model_dir)
    actor = Actor.load(files, condition.identity)
    transl = np.asarray(truth[0]["transl"])
    score_cam = score_camera(transl, actor, *score_size)
    betas = np.asarray(actor.betas, dtype=np.float64)
    cfg = fit_config or SequenceFitConfig(fov_x_deg=FOV_X_DEG)
    body_model = synthetic_package(files.root, condition.identity)[1]  # the avatar's, as live
    variants = {"": {}, **(variants or {})}
    pairs = [d.partition("+")[::2] for d in drives] if explicit else \
        [(d, label) for d in drives for label in variants]
    unknown = sorted({label for _, label in pairs if label not in variants})
    if unknown:
        raise ValueError(f"unknown fit variant(s) {unknown}; known: {sorted(variants)}")
    fits, inputs = {}, {}
    for d, label in pairs:
        name = f"{d}+{label}" if label else d
        config = with_variant(drive_config(d, cfg), variants[label])
        fits[name], inputs[name] = SequenceFit(body_model, betas, config), d
    res = RunResult(condition, rec.fps, truth, {d: [] for d in fits},
                    {d: [] for d in fits}, {d: [] for d in fits}, list(rec.track_ms),
                    {d: [] for d in fits}, rec.seen, rec.in_view, {}, dict(rec.placed))
    for i, params in enumerate(truth):
        with torch.no_grad():
            reference = actor.render(actor.pose(params), score_cam, background=(0, 0, 0),
                                     supersample=1)
        for d in fits:
            obs = drive_observations(rec, i, inputs[d])
            t1 = time.perf_counter()
            out = fits[d].step(obs, (rec.start_frame + i) / rec.fps)
            res.fit_ms[d].append((time.perf_counter() - t1) * 1e3)
            res.raw[d].append({k: np.array(v) for k, v in fits[d].current.items()})
            driven = {**out.params, "transl": transl, "betas": betas}
            res.smooth[d].append({k: np.array(v) for k, v in driven.items()})
            with torch.no_grad():
                view = actor.render(actor.pose(driven), score_cam, background=(0, 0, 0),
                                    supersample=1)
            res.psnr[d].append(_psnr(view, reference))
        if progress:
            progress(f"{condition.identity}/{condition.framing}", i + 1, len(truth))
    res.start_frame = rec.start_frame
    res.metrics = run_metrics(actor, res, score_cam)
    if curve and "live" in drives:
        res.curve = temporal_curve(actor, res, score_cam, rec.start_frame)
    return res


def run_condition(condition: Condition, fps: float, *, max_frames: int | None = None,
                  score_size: tuple[int, int] = (320, 240),
                  drives: Sequence[str] = DEFAULT_DRIVES, model_dir=None,
                  take: Sequence[str] = TAKE, fit_config=None,
                  curve: bool = True, start_frame: int = 0,
                  progress: Progress | None = None) -> RunResult:
    """Film, track, fit (every drive) and score one identity in one framing; `curve`: also
    the One Euro jitter-vs-lag curve of the live drive (`temporal_curve`)."""
    check_drives(drives)
    rec = record_condition(condition, fps, max_frames=max_frames, model_dir=model_dir,
                           take=take, start_frame=start_frame)
    return fit_recording(rec, drives=drives, score_size=score_size, model_dir=model_dir,
                         fit_config=fit_config, curve=curve, progress=progress)


# -- metrics ---------------------------------------------------------------------------------


def joint_errors(pred: list[dict], truth: list[dict]) -> dict[str, float]:
    """Mean geodesic errors (deg): root (global_orient: the webcam is the model frame),
    shoulders, elbows and wrists (local rotations), neck/head (neck then head: the head relative to
    the chest, whichever of the two joints carries it)."""
    def rows(ps, name):
        return aa_to_matrix(np.stack([np.asarray(p["body_pose"])[JOINT[name] - 1] for p in ps]))

    out = {"root": float(geodesic_deg(
        aa_to_matrix(np.stack([p["global_orient"] for p in pred])),
        aa_to_matrix(np.stack([p["global_orient"] for p in truth]))).mean())}
    for label, names in ANGLE_JOINTS.items():
        out[label] = float(np.mean([geodesic_deg(rows(pred, n), rows(truth, n)).mean()
                                    for n in names]))
    neck_head = [rows(ps, "neck") @ rows(ps, "head") for ps in (pred, truth)]
    out["neck_head"] = float(geodesic_deg(*neck_head).mean())
    return out


BONES = {"upper_arms": (("left_shoulder", "left_elbow"), ("right_shoulder", "right_elbow")),
         "forearms": (("left_elbow", "left_wrist"), ("right_elbow", "right_wrist"))}


def bone_direction_errors(actor, pred: Posed, truth: Posed) -> dict[str, float]:
    """Mean angle (deg) between fitted and true world directions of the upper arms and
    forearms: where the arm points, free of the twist that landmarks cannot see (a turn of
    the upper arm about itself traded for the elbow's own axis leaves the bones in place but
    moves the local angles of both joints)."""
    rest = actor.rest_joints
    out = {}
    for label, bones in BONES.items():
        errs = []
        for a, b in bones:
            bone = rest[JOINT[b]] - rest[JOINT[a]]
            d = [r[:, JOINT[a]] @ bone for r in (pred.rotations, truth.rotations)]
            cos = np.einsum("ti,ti->t", *d) / (np.linalg.norm(d[0], axis=-1)
                                               * np.linalg.norm(d[1], axis=-1))
            errs.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        out[label] = float(np.mean(errs))
    return out


def _tracks(posed: Posed) -> tuple[np.ndarray, np.ndarray]:
    groups = ("face", "left_hand", "right_hand", "torso")
    return (np.concatenate([posed.uv[g] for g in groups], 1),
            np.concatenate([posed.visible[g] for g in groups], 1))


def jitter_px(pred: Posed, truth: Posed) -> float:
    """Keypoint TJE (px): frame-to-frame motion that the truth does not have."""
    from avatar_core.metrics.temporal import keypoint_tje

    uv_p, _ = _tracks(pred)
    uv_t, vis = _tracks(truth)
    vis = vis & np.isfinite(uv_p).all(-1)
    return keypoint_tje(np.nan_to_num(uv_p), uv_t, vis)


def lag_ms(smoothed: Posed, raw: Posed, fps: float) -> float:
    """The delay (ms) that best aligns the smoothed keypoint tracks with the unsmoothed ones
    (raw linearly interpolated at t - lag): what the filter adds to the fit's own delay."""
    uv_s, vis = _tracks(smoothed)
    uv_r, _ = _tracks(raw)
    vis = vis & np.isfinite(uv_s).all(-1) & np.isfinite(uv_r).all(-1)
    t = len(uv_s)
    best, best_err = 0.0, float("inf")
    for lag in np.arange(0.0, MAX_LAG_S + 1e-9, LAG_STEP_S):
        shift = lag * fps
        k, frac = int(math.floor(shift)), shift - math.floor(shift)
        if t - k - 1 < 3:
            break
        prev = uv_r[:t - k - 1] * frac + uv_r[1:t - k] * (1 - frac)  # raw at (i - shift)
        cur = uv_s[k + 1:]
        use = vis[k + 1:] & vis[:t - k - 1] & vis[1:t - k]
        err = float(np.linalg.norm(cur - prev, axis=-1)[use].mean()) if use.any() else np.inf
        if err < best_err:
            best, best_err = float(lag), err
    return 1e3 * best


def run_metrics(actor, res: RunResult, score_cam: Camera) -> dict[str, dict[str, float]]:
    truth = evaluate_params(actor, res.truth, score_cam)
    out: dict[str, dict[str, float]] = {}
    for d in res.smooth:
        pred = evaluate_params(actor, res.smooth[d], score_cam)
        psnr = np.asarray(res.psnr[d])
        row = {"psnr": float(psnr[np.isfinite(psnr)].mean()) if np.isfinite(psnr).any()
               else float("nan"),
               **joint_errors(res.smooth[d], res.truth),
               **bone_direction_errors(actor, pred, truth),
               "jitter_px": jitter_px(pred, truth),
               "fit_ms": float(np.median(res.fit_ms[d][1:] or res.fit_ms[d]))}
        out[d] = row
    return out


def temporal_curve(actor, res: RunResult, score_cam: Camera, start_frame: int = 0,
                   drive: str = "live", settings=CURVE_SETTINGS) -> list[dict[str, float]]:
    """Jitter (px), lag (ms) and joint errors of each One Euro setting applied to the drive's
    unsmoothed fits (transl and betas the truth's, as the avatar is driven)."""
    from avatar_core.track.fit.one_euro import ParamSmoother

    truth = evaluate_params(actor, res.truth, score_cam)
    fixed = {"transl": res.truth[0]["transl"], "betas": res.truth[0]["betas"]}
    raw = [{**p, **fixed} for p in res.raw[drive]]
    raw_posed = evaluate_params(actor, raw, score_cam)
    rows = []
    for setting in settings:
        if setting is None:
            seq = raw
        else:
            smoother = ParamSmoother(*setting)
            seq = [{**smoother({k: v for k, v in p.items() if k not in fixed},
                               (start_frame + i) / res.fps),
                    **fixed} for i, p in enumerate(raw)]
        posed = raw_posed if setting is None else evaluate_params(actor, seq, score_cam)
        uv_p, _ = _tracks(posed)
        uv_t, vis = _tracks(truth)
        err = np.linalg.norm(uv_p - uv_t, axis=-1)[vis & np.isfinite(uv_p).all(-1)]
        rows.append({"min_cutoff": None if setting is None else setting[0],
                     "beta": None if setting is None else setting[1],
                     "jitter_px": jitter_px(posed, truth),
                     "lag_ms": 0.0 if setting is None else lag_ms(posed, raw_posed, res.fps),
                     "keypoint_px": float(err.mean()), **joint_errors(seq, res.truth)})
    return rows
