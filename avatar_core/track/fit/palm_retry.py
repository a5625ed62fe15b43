"""The fitter's palm retry: a wrist fitted far from its palm's own rotation (`palm.py`) is
fitted again from that rotation, and the lower cost kept (`FitConfig.palm_retry_deg`)."""

from __future__ import annotations

import numpy as np

from .camera import WebcamCamera
from .observations import Observations
from .palm import PALM_LANDMARKS, axis_angle, palm_rotation, rotation_angle_deg

SIDES = ("left", "right")


def palm_targets(palm_hands: list, obs: Observations, camera: WebcamCamera, z_scale: float
                 ) -> dict[str, np.ndarray]:
    """Each hand's palm rotation (`palm_rotation`), side -> [3, 3], for the hands whose five
    palm landmarks and their z are usable (`palm_hands`: the fitter's per-hand table)."""
    out = {}
    if obs.depth is None:
        return out
    for side, (sl, _, _, _, rest) in zip(SIDES, palm_hands, strict=True):
        rows = sl.start + np.array(PALM_LANDMARKS)
        if (obs.weights[rows] <= 0).any():
            continue
        hand = np.concatenate([obs.pixels[sl], obs.depth[sl, None]], axis=1)
        target = palm_rotation(hand, rest, z_scale, camera.focal, camera.center)
        if target is not None:
            out[side] = target
    return out


def retry(fitter, x: np.ndarray, targets: dict[str, np.ndarray], problem, weight: np.ndarray,
          stats: dict) -> np.ndarray:
    """For each hand whose fitted wrist is more than `palm_retry_deg` from its palm rotation
    in `targets`: fit again from that wrist rotation and the mean hand (`fitter`: a
    `FrameFitter`), and keep whichever fit costs less."""
    cfg = fitter.config
    cost = None
    for side, (sl, wrist_cols, hand_cols, wrist, _) in zip(SIDES, fitter.palm_hands,
                                                            strict=True):
        target = targets.get(side)
        if target is None or weight[sl.start] <= 0 or rotation_angle_deg(
                fitter.world_rotation(x, wrist), target) <= cfg.palm_retry_deg:
            continue
        parent = fitter.world_rotation(x, int(fitter.kinematics.parents[wrist]))
        trial = x.copy()
        trial[wrist_cols] = axis_angle(parent.T @ target)
        trial[hand_cols] = 0.0  # the fingers bent to fit the other side start over
        trial = fitter._levenberg_marquardt(trial, np.ones(x.size, dtype=bool),
                                            cfg.palm_retry_iterations, problem, weight, stats)
        cost = fitter.robust_cost(x, problem, weight) if cost is None else cost
        trial_cost = fitter.robust_cost(trial, problem, weight)
        stats["palm_retries"] = stats.get("palm_retries", 0) + 1
        if trial_cost < cost:
            x, cost = trial, trial_cost
            stats["palm_kept"] = stats.get("palm_kept", 0) + 1
    return x
