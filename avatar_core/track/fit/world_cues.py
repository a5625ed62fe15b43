"""3D cues against foreshortening: BlazePose's metric world landmarks and its per-landmark z.

A monocular fit reads a short-looking upper arm as one pointing at the camera or away from
it, and 2D landmarks cannot tell which; BlazePose's z can. For pairs of body landmarks (each
bone of the arms, the shoulders' line, the nose against a shoulder) the model's depth
difference is pulled toward BlazePose's:

    world:  f ((d_k - d_ref) - s_w (zw_k - zw_ref)) / d_ref      (zw metres)
    image:  f (d_k / d_ref - 1) - s_i (z_k - z_ref)              (z px, the image landmarks')

both in pixels at the reference's distance (the data term's unit), weighted per term
(`FitConfig.world_weight`, `image_z_weight`; set on held-out renders, docs/tracking.md).
"""

from __future__ import annotations

import numpy as np

from . import correspondence as cor
from .camera import MIN_DEPTH_M

# (landmark, reference) in BlazePose's numbering.
DEPTH_PAIRS = ((13, 11), (15, 13), (14, 12), (16, 14), (12, 11), (0, 11), (0, 12))


def pose_pairs(obs, weight: np.ndarray, values: np.ndarray | None, scale: float, w: float
               ) -> tuple[np.ndarray, ...] | None:
    """(keypoint rows, reference rows, target dz [D], sqrt weight [D]) of the pairs whose two
    landmarks are used and have a finite z in `values` [33] (world or image z); None: none."""
    if w <= 0 or values is None:
        return None
    base = cor.POSE_SLICE.start
    k, ref = (np.array([base + p[i] for p in DEPTH_PAIRS]) for i in (0, 1))
    lm, lr = (np.array([p[i] for p in DEPTH_PAIRS]) for i in (0, 1))
    ok = (weight[k] > 0) & (weight[ref] > 0) & np.isfinite(values[lm]) & np.isfinite(
        values[lr])
    if not ok.any():
        return None
    return (k[ok], ref[ok], scale * (values[lm[ok]] - values[lr[ok]]),
            np.full(int(ok.sum()), np.sqrt(w)))


def world_residuals(depth, d_depth, pairs, focal: float, px_scale: float, jacobian: bool):
    """Residuals [D] (and Jacobian [D, N]) of the world term for `pairs` (`pose_pairs`)."""
    k, ref, target, sqrt_w = pairs
    d_ref = np.maximum(depth[ref], MIN_DEPTH_M)
    gap = depth[k] - depth[ref] - target
    r = sqrt_w * focal * gap / d_ref / px_scale
    jac = None
    if jacobian:
        jac = (sqrt_w * focal / px_scale)[:, None] * (
            (d_depth[k] - d_depth[ref]) / d_ref[:, None]
            - (gap / d_ref ** 2)[:, None] * d_depth[ref])
    return np.nan_to_num(r), jac


# Bones whose world direction the direction term pulls toward BlazePose's: (from, to), each
# end one landmark in its numbering or two (their midpoint). The upper arms and forearms; the
# shoulders' line (it carries the torso's yaw); the torso's axis, the hips' midpoint to the
# shoulders' (it carries the lean, which 2D points cannot tell toward the camera from away from
# it: docs/results.md "The root's lean and BlazePose's torso axis").
ARM_BONES = ((11, 13), (13, 15), (12, 14), (14, 16))
SHOULDER_LINE = ((12, 11),)
TORSO_AXIS = (((23, 24), (11, 12)),)
# Landmarks left out of the 2D fit (observations.MISMATCHED_ROWS: BlazePose's hips lie ~26 px
# wider than the hip joints) whose world points a bone may still use (the width cancels in
# their midpoint), while their image points lie at least WORLD_ONLY_MARGIN (of the image's
# longer side) inside the picture: BlazePose also places hips below the frame, with
# visibility over 0.5, and there the torso's axis cost up to 1.8 dB where with the hips in
# view it gained 2.1-2.7 dB (docs/results.md).
WORLD_ONLY = frozenset((23, 24))
WORLD_ONLY_MARGIN = 0.02
MAX_END_LANDMARKS = 2
# BlazePose's world shoulders' line turns 0.26-0.91 of the body's turn about the vertical
# (median 0.6 over two identities, two framings, +-15 and +-30 deg; 0.3 on a trained avatar's
# take: docs/results.md "The shoulders' line turns too little"); the fit multiplies its turn
# by `FitConfig.shoulder_line_yaw_gain`, to at most this (deg).
MAX_LINE_TURN_DEG = 75.0
# BlazePose's world axes (x right, y down, z away from the camera) -> the fit's camera frame
# (x right, y up, z toward the camera): measured on the studio recordings, where this sign
# choice puts the shoulders' line 3-6 deg from the truth and every other choice >= 170 deg.
WORLD_TO_CAMERA = np.array([1.0, -1.0, -1.0])


def torso_axis(points: np.ndarray) -> np.ndarray:
    """[3] the hips' midpoint to the shoulders' (`TORSO_AXIS`) of [33, 3] pose points, in
    their own frame."""
    ((hips, shoulders),) = TORSO_AXIS
    return points[list(shoulders)].mean(axis=0) - points[list(hips)].mean(axis=0)


def bone_end(end) -> tuple[int, ...]:
    """A bone's end as its landmarks: an int is one, a tuple its own."""
    return (int(end),) if isinstance(end, int | np.integer) else tuple(int(i) for i in end)


def valid_bone(bone) -> bool:
    """(from, to), each end 1-2 distinct BlazePose landmarks, the two ends different."""
    if len(bone) != 2:
        return False
    try:
        ends = [bone_end(e) for e in bone]
    except (TypeError, ValueError):
        return False
    return (all(1 <= len(e) <= MAX_END_LANDMARKS and len(set(e)) == len(e)
                and all(0 <= i < cor.NUM_POSE for i in e) for e in ends)
            and set(ends[0]) != set(ends[1]))


def turned_line(v: np.ndarray, gain: float) -> np.ndarray:
    """[3] the shoulders' line `v` (camera frame, right shoulder to left) with its turn about
    the vertical multiplied by `gain`, at most `MAX_LINE_TURN_DEG` either way; its rise and
    its length in the horizontal plane kept."""
    horizontal = float(np.hypot(v[0], v[2]))
    turn = float(np.clip(gain * np.arctan2(v[2], v[0]), -np.radians(MAX_LINE_TURN_DEG),
                         np.radians(MAX_LINE_TURN_DEG)))
    return np.array([horizontal * np.cos(turn), v[1], horizontal * np.sin(turn)])


def direction_pairs(obs, weight: np.ndarray, w: float, bones=ARM_BONES,
                    line_yaw_gain: float = 1.0, world_only_in_view: bool = True
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(from rows [D, 2], to rows [D, 2] (an end's keypoint rows, their mean its point; one
    landmark is its row twice), target unit directions [D, 3] in the camera frame, sqrt
    weight [D]) of the `bones` whose landmarks are all used (or `WORLD_ONLY` and in view) and
    have finite world points, distinct ends; None: none (or `w` 0, or no world landmarks).
    The shoulders' line (`SHOULDER_LINE`) turned by `line_yaw_gain` (`turned_line`);
    `world_only_in_view` False: `WORLD_ONLY` landmarks count wherever their image points are."""
    if w <= 0 or obs.world is None:
        return None
    base = cor.POSE_SLICE.start
    rows = []
    w_img, h_img = obs.image_size
    margin = WORLD_ONLY_MARGIN * max(w_img, h_img)

    def in_view(row: int) -> bool:
        if not world_only_in_view:
            return True
        x, y = obs.pixels[row, :2]
        return bool(margin <= x < w_img - margin and margin <= y < h_img - margin)

    for bone in bones:
        ends = [bone_end(e) for e in bone]
        if any(weight[base + i] <= 0 and not (i in WORLD_ONLY and in_view(base + i))
               for e in ends for i in e):
            continue
        a, b = (obs.world[list(e)].mean(axis=0) for e in ends)
        v = (b - a) * WORLD_TO_CAMERA
        if line_yaw_gain != 1.0 and bone == SHOULDER_LINE[0]:
            v = turned_line(v, line_yaw_gain)
        n = float(np.linalg.norm(v))
        if np.isfinite(n) and n > 1e-6:
            rows.append(tuple(np.resize(np.asarray(e) + base, MAX_END_LANDMARKS)
                              for e in ends) + (v / n,))
    if not rows:
        return None
    a, b, u = zip(*rows, strict=True)
    return np.stack(a), np.stack(b), np.stack(u), np.full(len(rows), np.sqrt(w))


def joined_pairs(*pairs):
    """`direction_pairs` results as one (the Nones left out); None: all None."""
    given = [p for p in pairs if p is not None]
    if len(given) < 2:
        return given[0] if given else None
    return tuple(np.concatenate(parts) for parts in zip(*given, strict=True))


def direction_residuals(points, d_points, pairs, jacobian: bool):
    """Residuals [3D] (and Jacobian [3D, N]): each bone's unit direction in the model minus
    BlazePose's, weighted. `points` [K, 3] the model's keypoints (camera frame), `d_points`
    [K, 3, N] their derivatives."""
    a, b, target, sqrt_w = pairs
    v = points[b].mean(axis=1) - points[a].mean(axis=1)             # [D, 3]
    length = np.maximum(np.linalg.norm(v, axis=1), 1e-9)
    u = v / length[:, None]
    r = (sqrt_w[:, None] * (u - target)).reshape(-1)
    jac = None
    if jacobian:
        # d(v/|v|) = (I - u u^T) dv / |v|
        proj = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / length[:, None, None]
        dv = d_points[b].mean(axis=1) - d_points[a].mean(axis=1)    # [D, 3, N]
        jac = (sqrt_w[:, None, None] * np.einsum("dij,djn->din", proj, dv)).reshape(
            -1, dv.shape[-1])
    return np.nan_to_num(r), jac
