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
