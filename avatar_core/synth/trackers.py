"""What a real studio's trackers would report for a synthetic take.

A real capture has no ground-truth SMPL-X: a body tracker fits SMPL-X with a weak face and
coarse hands, while a face tracker (FLAME) and hand trackers (MANO) see those parts well.
MVFGA fuses the three. The studio simulates that split, so that fusion and its ablation mean
the same here as on real data:

- SMPL-X (body tracker): the true body, but no expression, jaw or eye motion, hands projected
  onto the model's first `hand_pca` PCA components, and `noise_deg` of rotation noise on the
  neck, head and wrists (the joints a body tracker sees worst);
- FLAME (face tracker): exact `expr`, `jaw_pose`, `eyes_pose`, `neck_pose` (the SMPL-X head
  joint's local rotation) and `rotation` (the neck joint's world rotation);
- MANO (hand trackers): exact `hand_pose` (relative to the MANO mean, which the synthetic
  MANO files share with SMPL-X) and `global_orient` (the wrist's world rotation).

`avatar_core.body.fusion.fuse` with world-frame head and wrist rotations turns these back
into the true parameters (tested).

Real trackers also make errors that fusion cannot remove. :class:`TrackerNoise` adds them,
each switchable (0 = off, the default), so a benchmark can give fine-tuning something to
correct and measure how much of it reaches the picture (docs/results.md):

- face tracker: per-frame noise on the FLAME expression and jaw;
- body tracker: per-frame noise on spine, collars, shoulders and elbows (fusion replaces only
  the head and wrist rotations) and a lag of a few frames on the root and body joints;
- hand trackers: a few frames with left and right swapped, a run of frames where one hand is
  lost and its last pose held;
- calibration: one small rigid error (rotation, translation) of the whole take's world frame.

:meth:`TrackerNoise.studio` sets the benchmark's figures, with their sources.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..body.skeleton import JOINT, SMPLX_PARENTS

__all__ = ["TrackerNoise", "parse_tracker_noise", "simulate_trackers", "world_rotation"]

_NOISY_JOINTS = ("neck", "head", "left_wrist", "right_wrist")
# Body joints whose errors survive fusion (it sets the head's and wrists' world rotations).
_BODY_NOISE_JOINTS = ("spine1", "spine2", "spine3", "left_collar", "right_collar",
                      "left_shoulder", "right_shoulder", "left_elbow", "right_elbow")
_MIRROR = np.array([1.0, -1.0, -1.0])  # axis-angle of a joint mirrored left <-> right


@dataclass(frozen=True)
class TrackerNoise:
    """Tracker errors that survive fusion; every field 0 = that effect off (the default).

    Angles are the standard deviation per axis of per-frame Gaussian noise, in degrees;
    ``expression_std`` in the model's expression units (the library's expressions reach
    about 1); frame counts per take."""

    expression_std: float = 0.0   # face tracker: FLAME expression, per coefficient
    jaw_deg: float = 0.0          # face tracker: jaw rotation
    body_deg: float = 0.0         # body tracker: spine, collars, shoulders, elbows
    body_lag_frames: int = 0      # body tracker: root, transl and body joints this late
    hand_swap_frames: int = 0     # hand trackers: frames with left and right swapped
    hand_lost_frames: int = 0     # hand trackers: one run of frames holding a lost hand
    calibration_deg: float = 0.0  # rig calibration: one rotation of the world, per take
    calibration_mm: float = 0.0   # rig calibration: one translation, per take

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type == "int" or isinstance(v, bool):
                ok = isinstance(v, int) and not isinstance(v, bool) and v >= 0
            else:
                ok = isinstance(v, (int, float)) and math.isfinite(v) and v >= 0
            if not ok:
                raise ValueError(f"tracker noise {f.name} must be a finite number >= 0"
                                 f"{' (an integer)' if f.type == 'int' else ''}, got {v!r}")

    @property
    def enabled(self) -> bool:
        return any(getattr(self, f.name) for f in fields(self))

    @classmethod
    def studio(cls) -> TrackerNoise:
        """The noisy-tracker benchmark's errors. Sources: our own monocular tracking of
        renders (docs/tracking.md, nine clips: head 4.8 deg, jaw 4.3 deg, elbow flexion 18 deg,
        wrists 44 deg) is what one camera gives; a studio fits with many cameras, so the
        per-frame figures here are about half of those for the face (jaw 2 deg, expression
        0.1 of the library's range) and less for the body: 1 deg per axis on each of the nine
        joints fusion keeps, which the chain from spine to elbow adds up to ~3 cm at the
        hands (the order of multi-view markerless body trackers' joint errors), and 1 frame
        of lag (a 30 fps tracker with temporal smoothing). Handedness
        swaps and lost hands are what MediaPipe-style hand trackers do on crossing or
        occluded hands (2 swapped and 3 lost frames a take); the calibration error (0.5 deg,
        5 mm) is the order a checkerboard calibration leaves on a studio rig. These are
        chosen figures of that order, not a fit to any one published evaluation."""
        return cls(expression_std=0.1, jaw_deg=2.0, body_deg=1.0, body_lag_frames=1,
                   hand_swap_frames=2, hand_lost_frames=3, calibration_deg=0.5,
                   calibration_mm=5.0)

    def with_overrides(self, text: str) -> TrackerNoise:
        """'jaw_deg=0,body_lag_frames=2' -> a copy with those fields set (CLI)."""
        names = {f.name: f.type for f in fields(self)}
        values: dict[str, float | int] = {}
        for item in filter(None, (t.strip() for t in text.split(","))):
            key, sep, raw = item.partition("=")
            key = key.strip()
            if not sep or key not in names:
                raise ValueError(f"tracker noise {item!r}: expected NAME=VALUE with NAME one "
                                 f"of {sorted(names)}")
            try:
                values[key] = int(raw) if names[key] == "int" else float(raw)
            except ValueError:
                raise ValueError(f"tracker noise {key}: not a number: {raw!r}") from None
        return replace(self, **values)


def parse_tracker_noise(text: str) -> TrackerNoise:
    """'' (none), 'studio', 'jaw_deg=2,...' or 'studio,jaw_deg=0' -> TrackerNoise."""
    items = [t.strip() for t in text.split(",") if t.strip()]
    base = TrackerNoise()
    if items and items[0] == "studio":
        base, items = TrackerNoise.studio(), items[1:]
    return base.with_overrides(",".join(items))


def _full_pose(p: dict[str, np.ndarray]) -> np.ndarray:
    """[T, 22, 3] root + body joints (enough for every chain up to the wrists)."""
    return np.concatenate([p["global_orient"][:, None], p["body_pose"]], axis=1)


def world_rotation(p: dict[str, np.ndarray], joint: int) -> np.ndarray:
    """Axis-angle [T, 3] of `joint`'s world rotation (root to joint, body joints only)."""
    full = _full_pose(p)
    chain, j = [], joint
    while j != -1:
        chain.append(j)
        j = SMPLX_PARENTS[j]
    rot = Rotation.from_rotvec(full[:, chain[-1]])
    for j in reversed(chain[:-1]):
        rot = rot * Rotation.from_rotvec(full[:, j])
    return rot.as_rotvec()


def _project_hand(pose: np.ndarray, components: np.ndarray, k: int) -> np.ndarray:
    """[T, 15, 3] pose relative to the mean, kept to its first k PCA components."""
    basis = components[:k]  # [k, 45]
    flat = pose.reshape(len(pose), 45)
    coeffs = flat @ np.linalg.pinv(basis)  # least squares: robust to non-orthonormal rows
    return (coeffs @ basis).reshape(-1, 15, 3)


def simulate_trackers(truth: dict[str, np.ndarray], hand_components: dict[str, np.ndarray],
                      *, hand_pca: int = 6, noise_deg: float = 2.0,
                      rng: np.random.Generator,
                      noise: TrackerNoise | None = None) -> dict[str, np.ndarray]:
    """params.npz arrays for a take whose true per-frame SMPL-X parameters are `truth`
    (arrays [T, ...], hands relative to the model's mean; `betas` shared); `noise` adds the
    errors that survive fusion (:class:`TrackerNoise`)."""
    if hand_pca < 0 or noise_deg < 0:
        raise ValueError("hand_pca and noise_deg must be non-negative")
    t = len(truth["body_pose"])
    body = {k: np.array(v, dtype=np.float64, copy=True) for k, v in truth.items()}
    body["expression"] = np.zeros_like(body["expression"])
    for key in ("jaw_pose", "leye_pose", "reye_pose"):
        body[key] = np.zeros_like(body[key])
    for side in ("left", "right"):
        body[f"{side}_hand_pose"] = _project_hand(body[f"{side}_hand_pose"],
                                                  hand_components[side], hand_pca)
    for name in _NOISY_JOINTS:
        body["body_pose"][:, JOINT[name] - 1] += rng.normal(0.0, np.deg2rad(noise_deg), (t, 3))

    out = dict(body)
    out.update(
        flame_expr=np.array(truth["expression"], dtype=np.float64),
        flame_jaw_pose=np.array(truth["jaw_pose"], dtype=np.float64),
        flame_eyes_pose=np.concatenate([truth["leye_pose"], truth["reye_pose"]], axis=1),
        flame_neck_pose=np.array(truth["body_pose"][:, JOINT["head"] - 1], dtype=np.float64),
        flame_rotation=world_rotation(truth, JOINT["neck"]),
        flame_translation=np.zeros((t, 3)),
    )
    for side in ("left", "right"):
        out[f"mano_{side}_hand_pose"] = np.array(truth[f"{side}_hand_pose"], dtype=np.float64)
        out[f"mano_{side}_global_orient"] = world_rotation(truth, JOINT[f"{side}_wrist"])
    if noise is not None and noise.enabled:
        _add_residual_errors(out, noise, rng)
    return out


def _add_residual_errors(out: dict[str, np.ndarray], noise: TrackerNoise,
                         rng: np.random.Generator) -> None:
    """Apply `noise` to the tracker arrays in place. Every effect draws its random numbers
    whether on or off, so switching one off leaves the others' draws unchanged."""
    t = len(out["body_pose"])
    expr = rng.normal(0.0, 1.0, out["flame_expr"].shape)
    jaw = rng.normal(0.0, 1.0, (t, 3))
    body = rng.normal(0.0, 1.0, (t, len(_BODY_NOISE_JOINTS), 3))
    swapped = rng.permutation(t)[:min(noise.hand_swap_frames, t)]
    lost_side = ("left", "right")[int(rng.integers(2))]
    lost_start = int(rng.integers(1, t)) if t > 1 else 0
    axis = rng.normal(0.0, 1.0, 3)
    shift = rng.normal(0.0, 1.0, 3)

    out["flame_expr"] = out["flame_expr"] + noise.expression_std * expr
    out["flame_jaw_pose"] = out["flame_jaw_pose"] + np.deg2rad(noise.jaw_deg) * jaw
    ids = [JOINT[n] - 1 for n in _BODY_NOISE_JOINTS]
    out["body_pose"][:, ids] += np.deg2rad(noise.body_deg) * body
    if noise.body_lag_frames:
        late = np.maximum(np.arange(t) - noise.body_lag_frames, 0)
        for key in ("global_orient", "body_pose", "transl"):
            out[key] = out[key][late]
    _swap_hands(out, swapped)
    if noise.hand_lost_frames and lost_start:  # hold the pose seen just before the run
        run = slice(lost_start, min(lost_start + noise.hand_lost_frames, t))
        for key in ("hand_pose", "global_orient"):
            k = f"mano_{lost_side}_{key}"
            out[k][run] = out[k][lost_start - 1]
    if noise.calibration_deg or noise.calibration_mm:
        # The trackers share the rig: every world rotation turns by one small rotation and
        # the root moves with it (about the origin, not the pelvis: a few mm more).
        axis = axis / max(float(np.linalg.norm(axis)), 1e-12)
        calib = Rotation.from_rotvec(axis * np.deg2rad(noise.calibration_deg))
        if noise.calibration_deg:
            for key in ("global_orient", "flame_rotation", "mano_left_global_orient",
                        "mano_right_global_orient"):
                out[key] = (calib * Rotation.from_rotvec(out[key])).as_rotvec()
            out["transl"] = calib.apply(out["transl"])
        direction = shift / max(float(np.linalg.norm(shift)), 1e-12)
        out["transl"] = out["transl"] + direction * noise.calibration_mm * 1e-3


def _swap_hands(out: dict[str, np.ndarray], frames: np.ndarray) -> None:
    """Left and right MANO exchanged at `frames`, each mirrored onto the other side (what a
    handedness mistake gives: each hand shows the other's articulation)."""
    if not len(frames):
        return
    for key in ("hand_pose", "global_orient"):
        left, right = out[f"mano_left_{key}"], out[f"mano_right_{key}"]
        left_f, right_f = left[frames].copy(), right[frames].copy()
        left[frames] = right_f * _MIRROR
        right[frames] = left_f * _MIRROR
