"""One body shape for the whole take, fitted jointly with every frame's pose.

The per-frame fits (``tracking``) start from the mean shape. Here one ``betas`` vector (SMPL-X's
shape covers the face and hands too), the focal length (unless the video's metadata gave it)
and per-frame corrections of the placement, body, jaw and expression are optimised together
(Adam) so that the model's keypoints reproject onto every frame's landmarks:

    mean_t,k w_tk rho(|project(keypoint_tk) - landmark_tk| / s)     (s = max(W, H) / 100)
  + beta_prior |betas|^2 + correction_prior |delta_t|^2 + smooth |delta_t - delta_t-1|^2
  + focal_prior (log f - log f0)^2

(rho: pseudo-Huber). The camera is fixed at the origin looking down -z (the fitter's webcam),
so the person's motion is all in the per-frame placement.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..track.fit.keypoints import BodyKeypoints
from ..track.fit.observations import Observations

CORRECTED = ("global_orient", "transl", "body_pose", "jaw_pose", "expression")
HUBER_PX = 8.0
BETA_PRIOR = 1e-3
CORRECTION_PRIOR = {"global_orient": 1.0, "transl": 100.0, "body_pose": 1.0,
                    "jaw_pose": 1.0, "expression": 0.1}
SMOOTH = 1.0
FOCAL_PRIOR = 1.0   # per (log focal)^2: a prior of ~60 deg, loose


@dataclass
class ShapeFit:
    betas: np.ndarray                       # [B]
    params: list[dict[str, np.ndarray]]     # per frame, refined
    focal_px: float                         # at the tracking size
    reprojection_px: float                  # mean over used landmarks, after
    reprojection_px_before: float


def _project(points: torch.Tensor, focal: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    depth = (-points[..., 2]).clamp(min=0.05)
    u = focal * points[..., 0] / depth + 0.5 * size[0]
    v = -focal * points[..., 1] / depth + 0.5 * size[1]
    return torch.stack([u, v], dim=-1)


def fit_shape(model, params: Sequence[dict[str, np.ndarray]], observations: Sequence[Observations],
              size: tuple[int, int], focal_px: float, *, fit_focal: bool, iterations: int,
              progress: Callable[[float], None] | None = None, lr: float = 0.01) -> ShapeFit:
    dtype = torch.float32
    kp = BodyKeypoints(model, dtype=dtype)
    nb = kp.model.num_betas
    t = len(params)
    base = {k: torch.as_tensor(np.stack([p[k] for p in params]), dtype=dtype)
            for k in params[0]}
    target = torch.as_tensor(np.stack([o.pixels for o in observations]), dtype=dtype)
    weight = torch.as_tensor(np.stack([o.weights for o in observations]), dtype=dtype)
    weight = weight * kp.available[None].to(dtype)
    scale = max(size) / 100.0
    betas = torch.zeros(nb, dtype=dtype, requires_grad=True)
    deltas = {k: torch.zeros_like(base[k], requires_grad=True) for k in CORRECTED if k in base}
    log_f0 = math.log(focal_px)
    log_f = torch.tensor(log_f0, dtype=dtype, requires_grad=fit_focal)
    leaves = [betas, *deltas.values()] + ([log_f] if fit_focal else [])
    opt = torch.optim.Adam(leaves, lr=lr)

    def residual_px() -> tuple[torch.Tensor, torch.Tensor]:
        inputs = dict(base)
        for k, d in deltas.items():
            inputs[k] = base[k] + d
        inputs["betas"] = betas[None].expand(t, nb)
        points = kp(inputs)
        proj = _project(torch.nan_to_num(points), log_f.exp(), size)
        return (proj - target).norm(dim=-1), inputs

    def data_term(err: torch.Tensor) -> torch.Tensor:
        rho = HUBER_PX ** 2 * (torch.sqrt(1 + (err / HUBER_PX) ** 2) - 1)
        return (weight * rho).sum() / weight.sum().clamp(min=1) / scale ** 2

    with torch.no_grad():
        before = float((residual_px()[0] * weight).sum() / weight.sum().clamp(min=1))
    for i in range(iterations):
        opt.zero_grad()
        err, _ = residual_px()
        loss = data_term(err) + BETA_PRIOR * (betas ** 2).sum()
        for k, d in deltas.items():
            loss = loss + CORRECTION_PRIOR[k] * (d ** 2).sum() / t
            if t > 1:
                loss = loss + SMOOTH * CORRECTION_PRIOR[k] * ((d[1:] - d[:-1]) ** 2).sum() / t
        if fit_focal:
            loss = loss + FOCAL_PRIOR * (log_f - log_f0) ** 2
        loss.backward()
        opt.step()
        if progress and (i + 1) % 10 == 0:
            progress((i + 1) / iterations)
    with torch.no_grad():
        err, inputs = residual_px()
        after = float((err * weight).sum() / weight.sum().clamp(min=1))
    out = [{k: inputs[k][j].double().numpy() for k in base} for j in range(t)]
    return ShapeFit(betas.detach().double().numpy(), out, float(log_f.detach().exp()), after,
                    before)
