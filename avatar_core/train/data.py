"""Training views and per-frame parameters.

A training view is the dataset's image made ready for the loss, once, then kept in a small
LRU cache (decoding three PNGs costs as much as a training step at 512 x 512):

- scaled to the training size (``DataConfig.scale`` or ``target_size``; area filter for RGB
  and alpha, nearest for part labels, the camera resized to match);
- the ground truth composited on the training background with its alpha,
  ``rgb * alpha + bg * (1 - alpha)`` (GaussianAvatars' ``gt_image * alpha + bg * (1 - alpha)``);
- a loss weight map: 1 on upper-body pixels and on background, 0 on the lower body (part
  labels not in ``upper_body_parts``), grown by one pixel so the anti-aliased edge of a leg
  does not leak into the loss. The avatar has no legs: those pixels are not its to explain.
  Without part labels every pixel counts. With ``lower_body = "background"`` the lower-body
  pixels are the background in the target instead, weighted 1 (only the grown rim where
  they meet the upper body stays 0): the avatar ends at the cut, so it must leave them
  clear; ignored, they let Gaussians of the cut's triangles fray past it unseen.
- with ``crop_to_subject``, the box of the pixels that are both foreground (alpha > 0) and
  weighted (i.e. the upper body; the masked legs are left out), plus ``crop_margin`` px,
  clipped to the image. Only this window is rendered (``Camera.cropped``) and scored, which
  is the main lever for throughput (two thirds of the pixels in the 17-camera studio take,
  where the upper body fills most of a 512 x 512 frame; less in wider shots, bench/train.py).
  Outside it the ground truth is background or masked
  legs; the render is background too, up to Gaussians that stray out of the box, which the
  position/scaling regularisers keep within about a triangle of the surface, so the margin
  covers them. A view with no weighted foreground is used whole.

Per-frame parameters are the SMPL-X keys of ``params.npz``. With ``fusion`` and FLAME/MANO
keys present, each sequence is fused once up front
(:func:`avatar_core.body.fusion.fuse_sequence` on a float64 copy of the model: the body
tracker's face and hands replaced by the face and hand trackers'), else the SMPL-X keys are
used as they are.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

from ..body.fusion import FusionModels, fuse_sequence
from ..dataset.loader import Dataset, View, ViewKey
from ..render.camera import Camera
from .config import DataConfig

__all__ = ["TrainView", "TrainingViews", "composite", "loss_weights", "lower_body_as_background",
           "prepare_view",
           "sequence_params", "subject_box", "training_size"]

log = logging.getLogger(__name__)


# -- one view -----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TrainView:
    """A view as the loss sees it (on the training device)."""

    key: ViewKey
    camera: Camera        # as rendered: scaled, then cropped
    target: Tensor        # [h, w, 3] ground truth on the training background
    weight: Tensor        # [h, w] float loss weights (0 on the lower body)
    weight_sum: float     # 0: nothing to learn from this view
    crop: tuple[int, int, int, int] | None  # (x0, y0, w, h) in the scaled image
    alpha: Tensor | None = None  # [h, w] the target's coverage (None: no alpha, opaque)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # the target's

    def on_background(self, background: tuple[float, float, float]) -> Tensor:
        """[h, w, 3] the target composited on ``background`` instead of its own."""
        if self.alpha is None or tuple(background) == tuple(self.background):
            return self.target
        shift = torch.tensor(background, dtype=self.target.dtype, device=self.target.device) \
            - torch.tensor(self.background, dtype=self.target.dtype, device=self.target.device)
        return self.target + (1.0 - self.alpha)[..., None] * shift


def training_size(width: int, height: int, config: DataConfig) -> tuple[int, int]:
    """(w, h) of a ``width x height`` image at training resolution."""
    s = config.scale if config.target_size is None else \
        min(1.0, config.target_size / max(width, height))
    return max(1, round(width * s)), max(1, round(height * s))


def composite(rgb: np.ndarray, alpha: np.ndarray | None,
              background: tuple[float, float, float]) -> np.ndarray:
    """[H, W, 3] float32: ``rgb * alpha + bg * (1 - alpha)``; rgb as is without alpha."""
    if alpha is None:
        return np.asarray(rgb, dtype=np.float32)
    a = alpha[..., None].astype(np.float32)
    bg = np.asarray(background, dtype=np.float32)
    return (rgb * a + bg * (1.0 - a)).astype(np.float32)


def loss_weights(parts: np.ndarray | None, upper_ids: tuple[int, ...], shape: tuple[int, int],
                 grow: int = 1) -> np.ndarray:
    """[H, W] float32: 1 on upper-body parts and background (-1), 0 on the other parts,
    whose region is grown by ``grow`` px. All ones without part labels."""
    if parts is None:
        return np.ones(shape, np.float32)
    lower = (parts >= 0) & ~np.isin(parts, np.asarray(upper_ids, dtype=parts.dtype))
    if grow > 0 and lower.any():
        kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)
        lower = cv2.dilate(lower.astype(np.uint8), kernel) > 0
    return (~lower).astype(np.float32)


def lower_body_as_background(target: np.ndarray, weight: np.ndarray, parts: np.ndarray,
                             upper_ids: tuple[int, ...], background: tuple[float, float, float]
                             ) -> tuple[np.ndarray, np.ndarray]:
    """(target, weight) with the lower-body pixels set to ``background`` and weighted 1; the
    rim that :func:`loss_weights` grew onto other pixels stays 0 (mixed colours)."""
    lower = (parts >= 0) & ~np.isin(parts, np.asarray(upper_ids, dtype=parts.dtype))
    target = np.where(lower[..., None], np.asarray(background, np.float32), target)
    weight = np.where(lower, np.float32(1.0), weight)
    return target.astype(np.float32), weight.astype(np.float32)


def subject_box(alpha: np.ndarray | None, weight: np.ndarray, margin: int
                ) -> tuple[int, int, int, int] | None:
    """(x0, y0, w, h) around the weighted foreground (alpha > 0 and weight > 0) plus
    ``margin``, clipped to the image; None when there is no such pixel (or no alpha)."""
    if alpha is None:
        return None
    ys, xs = np.nonzero((alpha > 0) & (weight > 0))
    if ys.size == 0:
        return None
    h, w = weight.shape
    x0, y0 = max(int(xs.min()) - margin, 0), max(int(ys.min()) - margin, 0)
    x1, y1 = min(int(xs.max()) + margin + 1, w), min(int(ys.max()) + margin + 1, h)
    return x0, y0, x1 - x0, y1 - y0


def _scaled(view: View, size: tuple[int, int]
            ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, Camera]:
    """rgb, alpha, parts and camera at ``size`` (w, h)."""
    w, h = size
    if (w, h) == (view.camera.width, view.camera.height):
        return view.rgb, view.alpha, view.parts, view.camera
    rgb = cv2.resize(view.rgb, (w, h), interpolation=cv2.INTER_AREA)
    alpha = None if view.alpha is None else cv2.resize(view.alpha, (w, h),
                                                       interpolation=cv2.INTER_AREA)
    parts = None if view.parts is None else cv2.resize(
        view.parts, (w, h), interpolation=cv2.INTER_NEAREST)
    return rgb, alpha, parts, view.camera.resized(w, h)


def prepare_view(view: View, config: DataConfig, device: torch.device | str) -> TrainView:
    """Scale, composite, weight and (optionally) crop one dataset view."""
    size = training_size(view.camera.width, view.camera.height, config)
    rgb, alpha, parts, camera = _scaled(view, size)
    target = composite(rgb, alpha, config.background)            # [H, W, 3]
    weight = loss_weights(parts, view.upper_body_ids, target.shape[:2])  # [H, W]
    box = subject_box(alpha, weight, config.crop_margin) if config.crop_to_subject else None
    if config.lower_body == "background" and parts is not None:
        target, weight = lower_body_as_background(target, weight, parts, view.upper_body_ids,
                                                  config.background)
        if alpha is not None:  # the legs are background now
            alpha = np.where(np.isin(parts, np.asarray(view.upper_body_ids, parts.dtype))
                             | (parts < 0), alpha, 0.0).astype(np.float32)
    if box is not None:
        x0, y0, w, h = box
        camera = camera.cropped(x0, y0, w, h)
        target, weight = target[y0:y0 + h, x0:x0 + w], weight[y0:y0 + h, x0:x0 + w]
        alpha = None if alpha is None else alpha[y0:y0 + h, x0:x0 + w]

    def tensor(a: np.ndarray) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(device)

    return TrainView(key=view.key, camera=camera, target=tensor(target), weight=tensor(weight),
                     weight_sum=float(weight.sum()), crop=box,
                     alpha=None if alpha is None else tensor(alpha),
                     background=tuple(config.background))


class TrainingViews:
    """The views of a split, decoded and prepared on first use; the last ``cache_views``
    prepared ones are kept (LRU)."""

    def __init__(self, dataset: Dataset, config: DataConfig,
                 device: torch.device | str = "cpu") -> None:
        self.dataset, self.config, self.device = dataset, config, torch.device(device)
        self.keys = dataset.views(config.split)
        if not self.keys:
            raise ValueError(f"split {config.split!r} of {dataset.root} has no views")
        self._cache: OrderedDict[ViewKey, TrainView] = OrderedDict()
        self.hits = self.misses = 0

    def __len__(self) -> int:
        return len(self.keys)

    def get(self, index: int) -> TrainView:
        key = self.keys[index]
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            self.hits += 1
            return hit
        self.misses += 1
        view = prepare_view(self.dataset.view(*key), self.config, self.device)
        self._cache[key] = view
        while len(self._cache) > self.config.cache_views:
            self._cache.popitem(last=False)
        return view


# -- per-frame parameters -----------------------------------------------------------------


def sequence_params(params: Mapping[str, np.ndarray], num_frames: int, *,
                    fusion: FusionModels | None = None) -> dict[str, np.ndarray]:
    """float64 SMPL-X arrays [T, ...] of one sequence, fused with its FLAME/MANO keys when
    ``fusion`` is given and they exist (:func:`avatar_core.body.fusion.fuse_sequence`)."""
    return fuse_sequence(params, num_frames, fusion)[0]
