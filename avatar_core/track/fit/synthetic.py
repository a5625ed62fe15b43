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
from .fitter import (
    DEPTH_FACE,
    DEPTH_HANDS,
    FACE_DEPTH_REF,
    FACE_Z_SCALE,
    HAND_Z_SCALE,
    FrameFitter,
)
from .observations import Observations, from_landmarks


def model_keypoints(fitter: FrameFitter, params: dict[str, np.ndarray]) -> torch.Tensor:
    """[K, 3] model-space keypoints of `params` from the reference (torch) model."""
    dt = fitter.config.dtype
    p = {k: torch.as_tensor(np.asarray(v, dtype=np.float64), dtype=dt)[None]
         for k, v in params.items()}
    p["betas"] = fitter.betas
    with torch.no_grad():
        return fitter.keypoints(p)[0].double()


def project_params(fitter: FrameFitter, params: dict[str, np.ndarray],
                   camera: WebcamCamera) -> np.ndarray:
    """[K, 2] pixels of the model's keypoints (NaN where the model has none)."""
    return camera.project(model_keypoints(fitter, params)).numpy()


def relative_depth_px(fitter: FrameFitter, params: dict[str, np.ndarray],
                      camera: WebcamCamera) -> np.ndarray:
    """[K] MediaPipe-style z as the fitter reads it: each hand point's depth minus its
    wrist's and each face point's minus the nose tip's, in pixels at the reference's distance
    (f (d - d_ref) / d_ref), divided by the fitter's z scales (MediaPipe's z is that much
    flatter / deeper than the truth); NaN elsewhere."""
    depth = -model_keypoints(fitter, params)[:, 2].numpy()
    out = np.full(cor.NUM_KEYPOINTS, np.nan)
    for rows, ref, z_scale in ((DEPTH_HANDS[0], DEPTH_HANDS[0][0], HAND_Z_SCALE),
                               (DEPTH_HANDS[1], DEPTH_HANDS[1][0], HAND_Z_SCALE),
                               (DEPTH_FACE, FACE_DEPTH_REF, FACE_Z_SCALE)):
        out[rows] = camera.focal * (depth[rows] / depth[ref] - 1.0) / z_scale
    out[FACE_DEPTH_REF] = 0.0
    return out


def as_mediapipe(keypoints_px: np.ndarray, depth_px: np.ndarray | None = None
                 ) -> dict[str, np.ndarray]:
    """Fitter-layout pixels [K, 2] (and z [K], `relative_depth_px`) -> MediaPipe arrays:
    face [468, 3] (NaN off the iBUG correspondence), hands [21, 3], pose [33, 3] (z 0
    without `depth_px`) and the pose's visibility [33] (0 where unmapped)."""
    z = np.zeros(cor.NUM_KEYPOINTS) if depth_px is None else np.nan_to_num(depth_px)
    face = np.full((468, 3), np.nan)
    for ibug, ids in enumerate(cor.FACE_MP_TO_IBUG68):
        face[list(ids), :2] = keypoints_px[cor.FACE_SLICE][ibug]
        face[list(ids), 2] = z[cor.FACE_SLICE][ibug]

    def pad(sl: slice) -> np.ndarray:
        return np.concatenate([keypoints_px[sl], z[sl, None]], axis=1)

    pose = pad(cor.POSE_SLICE)
    visibility = np.array([float(n is not None) for n in cor.POSE_MP_TO_SMPLX])
    visibility[~np.isfinite(pose).all(axis=1)] = 0.0
    return {"face": face, "left_hand": pad(cor.LEFT_HAND_SLICE),
            "right_hand": pad(cor.RIGHT_HAND_SLICE), "pose": pose,
            "pose_visibility": visibility}


def synthetic_observations(fitter: FrameFitter, params: dict[str, np.ndarray],
                           camera: WebcamCamera, noise_px: float = 0.0,
                           rng: np.random.Generator | None = None,
                           drop: tuple[str, ...] = ()) -> tuple[Observations, np.ndarray]:
    """Observations of `params` with Gaussian pixel noise (sigma `noise_px`), without the
    groups named in `drop` ("face", "left_hand", "right_hand", "pose"); and the noise-free
    keypoints [K, 2]."""
    clean = project_params(fitter, params, camera)
    depth = relative_depth_px(fitter, params, camera)
    noisy = clean.copy()
    if noise_px > 0:
        rng = rng or np.random.default_rng(0)
        noisy = noisy + rng.normal(0, noise_px, noisy.shape)
        depth = depth + rng.normal(0, noise_px, depth.shape)
    mp = as_mediapipe(noisy, depth)
    obs = from_landmarks(
        (camera.width, camera.height),
        face=None if "face" in drop else mp["face"],
        left_hand=None if "left_hand" in drop else mp["left_hand"],
        right_hand=None if "right_hand" in drop else mp["right_hand"],
        pose=None if "pose" in drop else mp["pose"],
        pose_visibility=mp["pose_visibility"])
    return obs, clean
