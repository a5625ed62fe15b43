"""Evaluating an avatar on a dataset split: ``evaluate(avatar, dataset, protocol) -> EvalResult``.

Protocols (``telesplat eval --protocol``) and the split each reads (docs/dataset.md):

* ``novel-view`` (``novel_view``): the training motion seen by held-out cameras;
* ``self-reenactment`` (``self_reenactment``): held-out motion of the same subject;
* ``cross-identity`` (``cross_identity``): another identity's motion drives *this* avatar
  (its own betas from the package). No image of this avatar doing that exists, so only AKD
  is computed; image metrics and TJE are null with the reason in ``notes``.

Parameters. A frame's parameters are the dataset's SMPL-X keys, fused with its FLAME and MANO
keys (``avatar_core.body.fusion.fuse_sequence``, world-frame head and wrists) when ``fusion``
is on and those keys exist; with ``fusion=False`` the SMPL-X keys drive the avatar as they are (the
no-fusion ablation). For novel-view and self-reenactment the dataset's betas are used (same
subject); they are checked against the package's and a mismatch is warned about.

Image metrics (novel-view, self-reenactment) compare the render, clamped to [0, 1] on the
dataset's background colour, with the ground truth over foreground *and* background, with the
lower body left out as in training: pixels labelled with a part outside
``upper_body_parts`` are set to the background colour in both images (so SSIM and LPIPS
windows cannot see them) and weighted 0 in L1 / PSNR / SSIM / TJE. Each metric is the mean
over views; TJE is per camera over consecutive evaluated frames, then the mean over cameras.

AKD uses the body model's keypoints (``metrics.keypoints``), not a detector: the ground truth
is the model posed with the fused (true) parameters, the prediction the model posed with the
parameters that drove the avatar, both projected with the view's camera. With fusion they are
equal in novel-view and self-reenactment (AKD 0), so there AKD measures what the no-fusion
ablation loses; in cross-identity the prediction has the avatar's betas and the ground truth
the driver's. An AKD of keypoints detected in the rendered images comes with the tracking
issue. LPIPS needs offline weights (``perceptual.lpips_metric``); CSIM needs a face-identity
network that cannot be downloaded here: both are null with the reason when off.
"""

from __future__ import annotations

import itertools
import re
import time
import warnings
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from ..body.fusion import FusionModels, fuse_sequence
from ..body.models import BodyOutput
from ..dataset import Dataset, View, ViewKey, load_dataset
from ..dataset.preview import write_png
from ..gaussians.loading import LoadedAvatar, load_avatar, mano_models
from ..render.camera import Camera
from ..render.rasterize import rasterize
from ..render.types import RenderRequest
from .image import l1, psnr, ssim
from .keypoints import GROUPS, body_akd
from .perceptual import lpips_metric, lpips_unavailable_reason
from .report import PROTOCOLS, EvalResult, side_by_side, write_result
from .temporal import tje

__all__ = ["EvalResult", "PROTOCOLS", "blank_excluded", "estimate_background", "evaluate",
           "evaluation_mask", "protocol_split"]

Progress = Callable[[int, int], None]
IMAGE_KEYS = ("l1", "psnr", "ssim", "lpips")
CSIM_REASON = ("no face-identity network (e.g. ArcFace) can be downloaded here, so the cosine "
               "identity similarity is not computed")
CROSS_REASON = ("cross-identity has no ground-truth image of this avatar performing the "
                "driver's motion: comparing with the driver's video would score the identity "
                "difference, not the avatar")
AKD_NOTE = ("body-model keypoints, pixels at the evaluation size: ground truth = the model "
            "posed with the fused (true) parameters, prediction = the model posed with the "
            "parameters that drove the avatar; equal with fusion in novel-view and "
            "self-reenactment (AKD 0), so AKD shows what the no-fusion ablation loses. An AKD "
            "of keypoints detected in the renders comes with the tracking issue")
AKD_CROSS_NOTE = ("body-model keypoints, pixels at the evaluation size: the avatar's body "
                  "(its betas) driven by the driver's parameters vs the driver's body posed "
                  "with its fused (true) parameters, both seen by the view's camera")
MASK_NOTE = ("lower-body pixels (parts outside upper_body_parts) are set to the background "
             "colour in both images and weighted 0; background pixels count")


# -- protocol and dataset checks -----------------------------------------------------------


def protocol_split(protocol: str, dataset: Dataset | None = None) -> str:
    """The split a protocol reads; ValueError for an unknown protocol or a missing split."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; expected one of {list(PROTOCOLS)}")
    split = PROTOCOLS[protocol]
    if dataset is not None and split not in dataset.splits:
        raise ValueError(f"dataset {dataset.root} has no {split!r} split for the {protocol} "
                         f"protocol (splits: {sorted(dataset.splits)})")
    return split


def _check_body_model(meta: Mapping[str, Any]) -> None:
    """The avatar's model takes full 45-D hands relative to the mean, smplx-style root."""
    if meta.get("type") != "smplx":
        raise ValueError(f"evaluation needs SMPL-X parameters, the dataset has "
                         f"{meta.get('type')!r}")
    if meta.get("hand_pca") is not None or meta.get("flat_hand_mean", False):
        raise ValueError("evaluation reads full hand poses relative to the mean hand "
                         "(hand_pca null, flat_hand_mean false)")
    if meta.get("root", "smplx") != "smplx":
        raise ValueError(f"evaluation needs body_model.root 'smplx', got {meta.get('root')!r}")


def _seed_mismatch(dataset_source: str, avatar_model: str) -> str | None:
    """A warning when a synthetic dataset and a synthetic avatar use different model seeds."""
    a = re.fullmatch(r"synthetic-seed(\d+)", dataset_source or "")
    b = re.fullmatch(r"synthetic:seed(\d+)", avatar_model or "")
    if a and b and a.group(1) != b.group(1):
        return (f"the dataset was filmed with synthetic model seed {a.group(1)}, the avatar "
                f"is bound to seed {b.group(1)}")
    return None


# -- pixels --------------------------------------------------------------------------------


def evaluation_mask(view: View) -> np.ndarray:
    """bool [H, W]: the pixels scored, i.e. all but those of lower-body parts (background and
    upper body count). All True without part labels."""
    if view.parts is None:
        return np.ones(view.rgb.shape[:2], dtype=bool)
    return (view.parts < 0) | view.upper_body_mask


def estimate_background(view: View) -> tuple[float, float, float]:
    """The studio background: median colour of the unlabelled, uncovered pixels (white when
    there are none or no labels)."""
    empty = np.zeros(view.rgb.shape[:2], dtype=bool)
    if view.parts is not None:
        empty = view.parts < 0
        if view.alpha is not None:
            empty &= view.alpha == 0  # silhouette edges mix in the subject
    if not empty.any():
        return (1.0, 1.0, 1.0)
    r, g, b = np.median(view.rgb[empty], axis=0)
    return (float(r), float(g), float(b))


def blank_excluded(image: np.ndarray, keep: np.ndarray,
                   background: Sequence[float]) -> np.ndarray:
    """``image [H, W, 3]`` with the pixels outside ``keep [H, W]`` set to ``background``."""
    bg = np.asarray(background, dtype=image.dtype)
    return np.where(keep[..., None], image, bg)


def _at_size(view: View, keep: np.ndarray, size: int | None
             ) -> tuple[np.ndarray, np.ndarray, Camera]:
    """GT rgb, keep mask and camera at width ``size`` (None: as stored)."""
    cam = view.camera
    if size is None or size == cam.width:
        return view.rgb, keep, cam
    h = max(1, round(size * cam.height / cam.width))
    rgb = cv2.resize(view.rgb, (size, h), interpolation=cv2.INTER_AREA)
    keep = cv2.resize(keep.astype(np.uint8), (size, h), interpolation=cv2.INTER_NEAREST) > 0
    return rgb, keep, cam.resized(size, h)


def image_scores(render: np.ndarray, gt: np.ndarray, keep: np.ndarray,
                 lpips_fn: Callable[..., torch.Tensor] | None = None) -> dict[str, float | None]:
    """L1, PSNR, SSIM (masked by ``keep``) and LPIPS of one view; images already blanked."""
    p, g, m = torch.from_numpy(render), torch.from_numpy(gt), torch.from_numpy(keep)
    return {"l1": float(l1(p, g, m)), "psnr": float(psnr(p, g, m)), "ssim": float(ssim(p, g, m)),
            "lpips": None if lpips_fn is None else float(lpips_fn(p, g))}


# -- parameters ----------------------------------------------------------------------------


def _rows(params: Mapping[str, np.ndarray], rows: Sequence[int]) -> dict[str, np.ndarray]:
    return {k: v[list(rows)] for k, v in params.items()}


def _output_row(out: BodyOutput, i: int) -> BodyOutput:
    """Row ``i`` of a batched BodyOutput, still batched ([1, ...])."""
    return BodyOutput(**{f.name: None if getattr(out, f.name) is None
                         else getattr(out, f.name)[i:i + 1] for f in fields(BodyOutput)})


@dataclass
class _SequenceData:
    """Parameters of one sequence at its evaluated frames."""

    frames: list[int]                    # dataset frame numbers evaluated
    driven: dict[str, np.ndarray]        # [F, ...] what drives the avatar
    truth_out: BodyOutput                # [F, ...] the true body (keypoint ground truth)
    driven_out: BodyOutput               # [F, ...] the driven body (keypoint prediction)
    fused: bool

    def params(self, frame: int) -> dict[str, np.ndarray]:
        i = self.frames.index(frame)
        return {k: v[i] for k, v in self.driven.items()}

    def akd(self, frame: int, camera: Camera) -> dict[str, float]:
        i = self.frames.index(frame)
        return body_akd(_output_row(self.driven_out, i), _output_row(self.truth_out, i), camera)


# -- the evaluation ------------------------------------------------------------------------


def _nanmean(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None and not np.isnan(v)]
    return float(np.mean(vals)) if vals else None


def _image_keys(keys: Sequence[ViewKey], limit: int) -> list[ViewKey]:
    """First evaluated frame of each sequence x each camera, at most ``limit``."""
    first: dict[str, int] = {}
    for k in keys:
        first.setdefault(k.sequence, k.frame)
    return [k for k in keys if first[k.sequence] == k.frame][:limit]


def _frames_by_sequence(keys: Sequence[ViewKey]) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for k in keys:
        frames = out.setdefault(k.sequence, [])
        if k.frame not in frames:
            frames.append(k.frame)
    return out


def _warn(message: str, collected: list[str]) -> None:
    warnings.warn(message, stacklevel=3)
    collected.append(message)


@dataclass
class _Run:
    """What every view of one evaluation shares."""

    loaded: LoadedAvatar
    src: Dataset                      # the dataset the split's views come from
    cross: bool
    fusion: bool
    frame_stride: int
    size: int | None
    request: RenderRequest
    lpips_fn: Callable[..., torch.Tensor] | None
    fusion_models: FusionModels       # the avatar's body model and its MANO models
    warnings: list[str]
    drive: Mapping[str, Mapping[str, np.ndarray]] | None = None  # per sequence, [T, ...]
    truth: Mapping[str, Mapping[str, np.ndarray]] | None = None

    @property
    def avatar_betas(self) -> np.ndarray:
        return np.asarray(self.loaded.package.body.betas, dtype=np.float64)


def _check_betas(run: _Run, seq: str, raw: Mapping[str, np.ndarray]) -> None:
    """Novel-view / self-reenactment film the avatar's own subject: warn when they differ."""
    mine = run.avatar_betas
    if run.cross or not mine.size or "betas" not in raw:
        return
    theirs = np.asarray(raw["betas"], dtype=np.float64)
    theirs = theirs.reshape(-1, theirs.shape[-1])  # [1 or T, B]
    if theirs.shape[-1] != mine.size or not np.allclose(theirs, mine, atol=1e-4):
        _warn(f"sequence {seq!r}: the dataset's betas differ from the avatar package's "
              "(another subject?); the dataset's are used", run.warnings)


def _sequence_data(run: _Run, seq: str, frames: list[int]) -> _SequenceData:
    """Truth and driving parameters of a sequence at ``frames``, and both posed bodies."""
    raw = run.src.params(seq)
    _check_betas(run, seq, raw)
    model = run.loaded.animator.body_model
    n = run.src.sequences[seq]
    fused_all, fused = fuse_sequence(raw, n, run.fusion_models, strict=True)
    truth_all = fused_all
    if run.truth is not None and seq in run.truth:
        truth_all = fuse_sequence(run.truth[seq], n, None)[0]
    truth = _rows(truth_all, frames)
    if run.drive is not None and seq in run.drive:
        driven = _rows(fuse_sequence(run.drive[seq], n, None)[0], frames)
    elif run.fusion:
        driven = truth if truth_all is fused_all else _rows(fused_all, frames)
    else:
        driven = _rows(fuse_sequence(raw, n, None)[0], frames)
    if run.cross:  # this avatar's body, the driver's motion
        betas = np.repeat(run.avatar_betas[None], len(frames), axis=0)  # [F, B]
        driven = {**driven, "betas": betas}
    with torch.no_grad():
        truth_out = model(truth)
        driven_out = truth_out if driven is truth else model(driven)
    return _SequenceData(frames, driven, truth_out, driven_out, fused and run.fusion)


class _TemporalJitter:
    """TJE per camera, one frame pair at a time (only the previous frame is kept)."""

    def __init__(self, stride: int) -> None:
        self.stride = stride
        self.pairs: dict[str, list[float]] = defaultdict(list)
        self._last: dict[str, tuple[ViewKey, np.ndarray, np.ndarray, np.ndarray]] = {}

    def add(self, key: ViewKey, pred: np.ndarray, gt: np.ndarray, keep: np.ndarray) -> None:
        last = self._last.get(key.camera)
        if last and last[0].sequence == key.sequence and \
                last[0].frame == key.frame - self.stride:
            pair = tje(np.stack([last[1], pred]), np.stack([last[2], gt]),
                       np.stack([last[3], keep]))
            self.pairs[key.camera].append(float(pair))
        self._last[key.camera] = (key, pred, gt, keep)


@dataclass
class _Scored:
    record: dict[str, Any]
    gt: np.ndarray       # [H, W, 3] at the evaluation size
    render: np.ndarray   # [H, W, 3] clamped to [0, 1]
    keep: np.ndarray     # [H, W] pixels scored


def _score_view(run: _Run, key: ViewKey, posed: Any, data: _SequenceData,
                jitter: _TemporalJitter) -> _Scored:
    """Render one view and measure it (image metrics and TJE unless cross-identity)."""
    view = run.src.view(*key)
    gt, keep, cam = _at_size(view, evaluation_mask(view), run.size)
    t0 = time.perf_counter()
    out = rasterize(posed.gaussians, cam, run.request)
    render_ms = (time.perf_counter() - t0) * 1e3
    render = out.rgb.clamp(0.0, 1.0).cpu().numpy().astype(np.float32)
    rec: dict[str, Any] = {"sequence": key.sequence, "frame": key.frame, "camera": key.camera,
                           "render_ms": render_ms}
    rec.update({f"akd_{g}": v for g, v in data.akd(key.frame, cam).items()})
    if not run.cross:
        bg = run.request.background
        gt_b, pred_b = blank_excluded(gt, keep, bg), blank_excluded(render, keep, bg)
        rec.update(image_scores(pred_b, gt_b, keep, run.lpips_fn))
        jitter.add(key, pred_b, gt_b, keep)
    return _Scored(rec, gt, render, keep)


def evaluate(avatar: str | Path | LoadedAvatar, dataset: str | Path | Dataset, protocol: str,
             *, fusion: bool = True, max_views: int | None = None, frame_stride: int = 1,
             out_dir: str | Path | None = None, size: int | None = None,
             progress: Progress | None = None, model_dir: Path | None = None,
             max_images: int = 12, budget: int | float | None = None,
             drive: Mapping[str, Mapping[str, np.ndarray]] | None = None,
             truth: Mapping[str, Mapping[str, np.ndarray]] | None = None) -> EvalResult:
    """Evaluate an avatar (package path, ``synthetic[:I]`` or a LoadedAvatar) on the split of
    ``protocol`` (see the module docstring). Views are the split's in dataset order (sequence,
    frame, camera), every ``frame_stride``-th frame, the first ``max_views`` of them; images
    are rendered at width ``size`` (None: the dataset's). With ``out_dir``, writes
    ``metrics.json``, ``metrics.md`` and ``images/*.png`` (at most ``max_images``).
    ``budget``: render only the K (or that fraction of the visible) most important Gaussians
    (:class:`RenderRequest`), for accuracy-against-render-time curves. ``drive`` / ``truth``:
    per-sequence SMPL-X arrays [T, ...] that drive the avatar (e.g. the fine-tuned ones) /
    are the true body for AKD (e.g. a noisy-tracker capture's truth), instead of the
    dataset's (fused) parameters, for the sequences they name."""
    if frame_stride < 1 or (max_views is not None and max_views < 1) or max_images < 0:
        raise ValueError("frame_stride and max_views must be at least 1, max_images >= 0")
    protocol_split(protocol)  # the cheap checks first: before anything is loaded
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    split = protocol_split(protocol, ds)
    _check_body_model(ds.meta["body_model"])
    cross = protocol == "cross-identity"
    keys = [k for k in ds.views(split) if k.frame % frame_stride == 0][:max_views]
    if not keys:
        raise ValueError(f"split {split!r} of {ds.root} has no views to evaluate")
    loaded = avatar if isinstance(avatar, LoadedAvatar) else load_avatar(str(avatar), model_dir)
    if cross and not loaded.package.body.betas:
        raise ValueError("the avatar package records no betas to drive cross-identity with")

    src = ds.source(split)
    first = src.view(*keys[0])
    eval_cam = _at_size(first, evaluation_mask(first), size)[2]
    lpips_reason = None if cross else lpips_unavailable_reason()
    run = _Run(loaded, src, cross, fusion, frame_stride, size,
               RenderRequest(background=estimate_background(first), budget=budget),
               None if cross or lpips_reason else lpips_metric(),
               FusionModels(loaded.animator.body_model, mano_models(loaded)), [], drive,
               truth)
    mismatch = _seed_mismatch(ds.meta["body_model"].get("source", ""), loaded.package.body.model)
    if mismatch:
        _warn(mismatch, run.warnings)
    if not ds.has_parts:
        _warn("the dataset has no part labels: lower-body pixels cannot be excluded",
              run.warnings)

    frames = _frames_by_sequence(keys)
    show = set(_image_keys(keys, max_images)) if out_dir is not None else set()
    animator = loaded.animator
    seqs: dict[str, _SequenceData] = {}
    jitter = _TemporalJitter(frame_stride)
    records: list[dict[str, Any]] = []
    pose_ms: list[float] = []
    images: list[str] = []
    start = time.perf_counter()
    with torch.no_grad():
        for (seq, frame), group in itertools.groupby(keys, key=lambda k: (k.sequence, k.frame)):
            if seq not in seqs:
                seqs[seq] = _sequence_data(run, seq, frames[seq])
            if not records:  # untimed warm-up (JIT compilation, caches) in the rest pose,
                # which also keeps the first frame's timed pose out of the animator's cache
                rasterize(animator.pose({}).gaussians, eval_cam, run.request)
            t0 = time.perf_counter()
            posed = animator.pose(seqs[seq].params(frame))
            pose_ms.append((time.perf_counter() - t0) * 1e3)
            for key in group:
                scored = _score_view(run, key, posed, seqs[seq], jitter)
                if key in show:
                    name = f"{key.sequence}_{key.frame:05d}_{key.camera}.png"
                    write_png(Path(out_dir) / "images" / name,
                              side_by_side(scored.gt, scored.render, scored.keep,
                                           error=not cross))
                    images.append(f"images/{name}")
                records.append(scored.record)
                if progress:
                    progress(len(records), len(keys))
    total_s = time.perf_counter() - start

    summary = _summarise(records, jitter.pairs, cross=cross, lpips_reason=lpips_reason)
    renders = [r["render_ms"] for r in records]
    notes = {**summary["notes"], "akd": AKD_CROSS_NOTE if cross else AKD_NOTE,
             **({} if cross else {"mask": MASK_NOTE}),
             "timing": "render_ms: rasterizing one view, after one untimed warm-up render; "
                       "pose_ms: posing body and Gaussians, once per frame"}
    result = EvalResult(
        protocol=protocol, split=split, avatar=loaded.package.name, dataset=ds.name,
        fusion=fusion, fused=any(d.fused for d in seqs.values()), num_views=len(records),
        num_gaussians=loaded.package.avatar.num, image_size=[eval_cam.height, eval_cam.width],
        frame_stride=frame_stride, metrics=summary["metrics"],
        per_camera=summary["per_camera"],
        timing={"render_ms_mean": float(np.mean(renders)),
                "render_ms_median": float(np.median(renders)),
                "render_ms_p95": float(np.percentile(renders, 95)),
                "pose_ms_mean": float(np.mean(pose_ms)), "total_s": total_s},
        notes=notes, warnings=run.warnings, images=images, views=records)
    if out_dir is not None:
        write_result(result, out_dir)
    return result


def _summarise(records: list[dict[str, Any]], tje_pairs: Mapping[str, list[float]], *,
               cross: bool, lpips_reason: str | None) -> dict[str, Any]:
    """Means over views (TJE: per camera, then over cameras) and why a metric is null."""
    akd_keys = [f"akd_{g}" for g in GROUPS]
    per_camera: dict[str, dict[str, float | None]] = {}
    for cam in dict.fromkeys(r["camera"] for r in records):
        rows = [r for r in records if r["camera"] == cam]
        row = {k: _nanmean([r.get(k) for r in rows]) for k in (*IMAGE_KEYS, *akd_keys)}
        row["tje"] = _nanmean(tje_pairs.get(cam, []))
        row["views"] = len(rows)
        per_camera[cam] = row
    metrics = {k: _nanmean([r.get(k) for r in records]) for k in (*IMAGE_KEYS, *akd_keys)}
    metrics["tje"] = _nanmean([row["tje"] for row in per_camera.values()])
    metrics["csim"] = None
    notes = {"csim": CSIM_REASON}
    if cross:
        notes.update({k: CROSS_REASON for k in (*IMAGE_KEYS, "tje")})
    else:
        if lpips_reason:
            notes["lpips"] = f"LPIPS off: {lpips_reason}"
        notes["tje"] = ("per camera over consecutive evaluated frames, then the mean over "
                        "cameras" + ("" if metrics["tje"] is not None else
                                     "; null: no camera has two consecutive evaluated frames"))
    return {"metrics": {k: metrics.get(k) for k in (*IMAGE_KEYS, *akd_keys, "tje", "csim")},
            "per_camera": per_camera, "notes": notes}
