"""Landmarks with known answers: the body model's own keypoints for given parameters,
projected into the webcam and written in MediaPipe's layouts (468 face mesh, 21 per hand,
33 pose), with optional pixel noise. Fitting them back measures the fitter alone, whatever
the landmark models make of a rendered image.
"""

from __future__ import annotations

import numpy as np
import torch

from . import correspondence as cor
from .camera import WebcamCamera
from .fitter import FrameFitter
from .observations import Observations, from_landmarks


def project_params(fitter: FrameFitter, params: dict[str, np.ndarray],
                   camera: WebcamCamera) -> np.ndarray:
    """[K, 2] pixels of the model's keypoints (NaN where the model has none)."""
    dt = fitter.config.dtype
    p = {k: torch.as_tensor(np.asarray(v, dtype=np.float64), dtype=dt)[None]
         for k, v in params.items()}
    p["betas"] = fitter.betas
    with torch.no_grad():
        return fitter.project(p, camera)[0].double().numpy()


def as_mediapipe(keypoints_px: np.ndarray) -> dict[str, np.ndarray]:
    """Fitter-layout pixels [K, 2] -> MediaPipe arrays: face [468, 3] (NaN off the iBUG
    correspondence), hands [21, 3], pose [33, 3] and its visibility [33] (0 where unmapped)."""
    face = np.full((468, 3), np.nan)
    for ibug, ids in enumerate(cor.FACE_MP_TO_IBUG68):
        face[list(ids), :2] = keypoints_px[cor.FACE_SLICE][ibug]
        face[list(ids), 2] = 0.0
    pad = lambda a: np.concatenate([a, np.zeros((len(a), 1))], axis=1)  # noqa: E731
    pose = pad(keypoints_px[cor.POSE_SLICE])
    visibility = np.array([float(n is not None) for n in cor.POSE_MP_TO_SMPLX])
    visibility[~np.isfinite(pose).all(axis=1)] = 0.0
    return {"face": face, "left_hand": pad(keypoints_px[cor.LEFT_HAND_SLICE]),
            "right_hand": pad(keypoints_px[cor.RIGHT_HAND_SLICE]), "pose": pose,
            "pose_visibility": visibility}


def synthetic_observations(fitter: FrameFitter, params: dict[str, np.ndarray],
                           camera: WebcamCamera, noise_px: float = 0.0,
                           rng: np.random.Generator | None = None,
                           drop: tuple[str, ...] = ()) -> tuple[Observations, np.ndarray]:
    """Observations of `params` with Gaussian pixel noise (sigma `noise_px`), without the
    groups named in `drop` ("face", "left_hand", "right_hand", "pose"); and the noise-free
    keypoints [K, 2]."""
    clean = project_params(fitter, params, camera)
    noisy = clean.copy()
    if noise_px > 0:
        noisy = noisy + (rng or np.random.default_rng(0)).normal(0, noise_px, noisy.shape)
    mp = as_mediapipe(noisy)
    obs = from_landmarks(
        (camera.width, camera.height),
        face=None if "face" in drop else mp["face"],
        left_hand=None if "left_hand" in drop else mp["left_hand"],
        right_hand=None if "right_hand" in drop else mp["right_hand"],
        pose=None if "pose" in drop else mp["pose"],
        pose_visibility=mp["pose_visibility"])
    return obs, clean
