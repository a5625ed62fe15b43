"""The training loop: Gaussians bound to the upper-body mesh, fitted to multi-view video.

Per iteration (GaussianAvatars' ``train.py`` with MVFGA's additions):

1. the position learning rate follows its schedule; the rendered SH degree is
   ``min(sh_degree, iteration // sh_interval)`` (3DGS: +1 every 1000 iterations);
2. the next training view: a fresh permutation of all views each epoch, drawn from the
   trainer's own numpy Generator (seeded; its state is checkpointed);
3. the upper body posed with the frame's (fused) parameters, plus the fine-tuned per-frame
   deltas of transl / expression / body_pose when enabled, then triangle frames -> world
   Gaussians; ``retain_grad`` on the world means gives the view-space gradient;
4. rasterize on the training background (only the subject's box with ``crop_to_subject``);
5. loss = photometric (L1 + D-SSIM under the weight map) + gamma LPIPS (when it can run)
   + position/scaling hinges over the Gaussians visible in the view;
6. backward; a loss or a gradient that is not finite skips the view (warning; gradients
   dropped; no optimiser step, no density statistics), so one bad image never reaches the
   model;
7. density statistics, both Adam steps, then on schedule densify/prune and opacity reset.
   (3DGS densifies before its optimiser step, which then has no gradients to apply; here the
   step comes first, so no iteration's gradient is lost.)

Initial colours: the synthetic captures have no texture, so each triangle's Gaussian takes
the colour sampled at its centroid's projection in the first frame of the first training
sequence, averaged over the training cameras that see that triangle (it faces the camera
and the pixel shows its body part); triangles seen by none stay grey, or take the mean of
their coloured neighbours of the same part with ``init_unseen = "neighbours"``
(``init_color = "grey"`` gives grey everywhere). This starts the photometric loss near its
floor instead of spending the first thousand iterations on flat colour.

Checkpoints hold everything the next iteration depends on (Gaussians, both optimisers, the
density statistics, the fine-tuned deltas, the view order and both generators), so a
resumed run is the uninterrupted run: bit-identical on CPU (tested). No global RNG is
used or touched.
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..dataset.loader import Dataset, ViewKey, load_dataset
from ..gaussians.avatar import DEFAULT_COLOR, GaussianAvatar
from ..gaussians.binding import FaceFrames
from ..gaussians.package import AvatarPackage, BodyReference, faces_fingerprint, save_package
from ..metrics.image import psnr
from ..metrics.perceptual import lpips_metric, lpips_unavailable_reason
from ..render.camera import Camera
from ..render.contract import NEAR_PLANE
from ..render.project_cpu import project_np
from ..render.rasterize import rasterize
from ..render.sh import rgb_to_sh0
from ..render.types import GaussianSet, RenderRequest
from .checkpoint import CHECKPOINT_DIR, latest_checkpoint, load_checkpoint, save_checkpoint
from .config import TrainConfig, config_from_dict, config_to_dict, save_config
from .data import TrainingViews, TrainView, prepare_view, sequence_params
from .density import (
    DensityStats,
    densify_and_prune,
    reset_opacity,
    screen_grad_norm,
    screen_visibility,
)
from .device_step import DeviceTally, fit_on_device
from .optim import (
    GAUSSIAN_KEYS,
    avatar_state,
    make_optimizer,
    make_param_optimizer,
    set_position_lr,
    state_to_avatar,
)
from .photometric import photometric_loss_fast
from .posing import (
    face_part_ids,
    fill_unseen_colors,
    fine_tune_deltas,
    frame_inputs,
    fusion_models,
    project_face_colors,
    resolve_body,
    world_gaussians,
)
from .regularizers import RegularizerWeights, avatar_regularizers, mask_loss

__all__ = ["PACKAGE_DIR", "StepResult", "Trainer", "camera_extent", "resolve_device",
           "visibility"]

log = logging.getLogger(__name__)

PACKAGE_DIR = "avatar"
Progress = Callable[[dict[str, Any]], None]
_FRAME_CACHE = 64  # posed-mesh frames kept when the mesh is fixed (~0.8 MB each at 16k faces)


@dataclass
class StepResult:
    iteration: int
    loss: float | None         # None when the view was skipped
    skipped: str | None = None  # why


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def camera_extent(centers: np.ndarray) -> float:
    """3DGS's scene extent: 1.1 x the largest distance of a camera from their mean."""
    c = np.asarray(centers, dtype=np.float64)  # [C, 3]
    radius = float(np.linalg.norm(c - c.mean(0), axis=1).max()) if len(c) > 1 else 1.0
    return 1.1 * (radius if radius > 0 else 1.0)


def visibility(gaussians: GaussianSet, camera: Camera) -> tuple[Tensor, Tensor]:
    """(visible [N] bool, radii [N] px): :func:`screen_visibility`, through the renderer's
    numba projection twin on the CPU (same radii, ~8x faster than the torch projection)."""
    means = gaussians.means
    if means.device.type != "cpu":
        return screen_visibility(gaussians, camera)
    arrays = [np.ascontiguousarray(t.detach().to(torch.float32).numpy()) for t in
              (means, gaussians.quats, gaussians.scales, gaussians.opacities)]
    radii = project_np(*arrays, camera.viewmat(), camera.K, camera.width, camera.height,
                       NEAR_PLANE, False)[3]
    radii = torch.from_numpy(radii).to(means.dtype)
    return radii > 0, radii


class _Phases:
    """Summed wall time per phase of a step (profiling only: it synchronises CUDA)."""

    def __init__(self, enabled: bool, device: torch.device) -> None:
        self.enabled, self.device = enabled, device
        self.totals: defaultdict[str, float] = defaultdict(float)
        self._t = 0.0

    def start(self) -> None:
        if self.enabled:
            self._sync()
            self._t = time.perf_counter()

    def mark(self, name: str) -> None:
        if self.enabled:
            self._sync()
            now = time.perf_counter()
            self.totals[name] += now - self._t
            self._t = now

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)


class Trainer:
    """Trains one avatar on a dataset's training split (see the module docstring).

    ``body_model``: the folder of the body-model files (None: the synthetic family named by
    the dataset, from the cache). ``progress`` receives JSON-serialisable event dicts
    ``{"type": "progress" | "densify" | "checkpoint" | "done", "iteration", "total", "loss",
    "psnr", "num_gaussians", "elapsed_s", "its_per_s", ...}``.
    """

    def __init__(self, dataset: Dataset | str | Path, config: TrainConfig,
                 out_dir: str | Path, body_model: str | Path | None = None,
                 progress: Progress | None = None, *, checkpoint: dict[str, Any] | None = None,
                 profile: bool = False, device_resident: bool | None = None) -> None:
        self.dataset = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
        self.config = config
        self.out_dir = Path(out_dir)
        self.progress = progress
        self.device = resolve_device(config.device)
        self.body_model_dir = None if body_model is None else str(body_model)
        self.body = resolve_body(self.dataset.meta["body_model"], body_model, self.device)
        self.faces = self.body.model.faces  # [F, 3]
        self.views = TrainingViews(self.dataset, config.data, self.device)
        self.sequences = list(dict.fromkeys(k.sequence for k in self.views.keys))
        self.num_frames = len({(k.sequence, k.frame) for k in self.views.keys})
        self.fused = False
        self.params = self._sequence_tensors()
        cams = {k.camera for k in self.views.keys}
        self.extent = config.densify.extent or camera_extent(
            np.stack([self.dataset.cameras[c].camera.center for c in sorted(cams)]))
        self.regularizer = RegularizerWeights(
            lambda_pos=config.loss.lambda_pos, eps_pos=config.loss.eps_pos,
            lambda_scale=config.loss.lambda_scale, eps_scale=config.loss.eps_scale)
        self.lpips = self._setup_lpips()
        self.phases = _Phases(profile, self.device)
        # CUDA: the iteration without host reads (device_step; None: on CUDA only)
        if device_resident is None:
            device_resident = self.device.type == "cuda"
        self.tally = DeviceTally(self.device) if device_resident else None
        self._frame_cache: OrderedDict[tuple[str, int], FaceFrames] = OrderedDict()
        self._posed_k: Tensor | None = None
        self._last: tuple[Tensor, TrainView] | None = None
        self._last_loss: float | None = None
        now = time.perf_counter()
        self._window: dict[str, Any] = {"iteration": 0, "time": now, "losses": [],
                                        "session_start": now}
        if checkpoint is None:
            if latest_checkpoint(self.out_dir) is not None:
                raise ValueError(f"{self.out_dir} already holds checkpoints: resume from them "
                                 "or train into another folder")
            self._init_fresh()
        else:
            self._restore(checkpoint)

    # -- set-up --------------------------------------------------------------------------

    def _sequence_tensors(self) -> dict[str, dict[str, Tensor]]:
        """Per training sequence: float32 [T, ...] SMPL-X tensors on the device, fused once
        when configured and the FLAME/MANO keys exist."""
        raw = {s: self.dataset.params(s) for s in self.sequences}
        has_trackers = any(k.startswith(("flame_", "mano_")) for p in raw.values() for k in p)
        models = self._fusion = None
        if self.config.data.fusion and has_trackers:
            shape = any("flame_shape" in p for p in raw.values())
            models = self._fusion = fusion_models(self.body, flame_shape=shape)
            self.fused = True
        log.info("parameters: %s", "FLAME/MANO fused into SMPL-X" if self.fused else
                 "SMPL-X as stored" + (" (fusion off)" if has_trackers else ""))
        out = {}
        for seq, params in raw.items():
            arrays = sequence_params(params, self.dataset.sequences[seq], fusion=models)
            out[seq] = {k: torch.as_tensor(v, dtype=torch.float32, device=self.device)
                        for k, v in arrays.items()}
        return out

    def _setup_lpips(self) -> Callable[..., Tensor] | None:
        cfg = self.config.loss
        if not cfg.lpips or cfg.lambda_lpips == 0:
            log.info("LPIPS loss off: disabled in the config")
            return None
        reason = lpips_unavailable_reason(cfg.lpips_net)
        if reason is not None:
            log.warning("LPIPS loss off: %s", reason)
            return None
        log.info("LPIPS loss on: %s, weight %g", cfg.lpips_net, cfg.lambda_lpips)
        return lpips_metric(cfg.lpips_net, device=self.device)

    def _init_fresh(self) -> None:
        cfg = self.config
        avatar = GaussianAvatar.from_mesh(self.faces.cpu().numpy(), sh_degree=cfg.sh_degree)
        if cfg.init_color == "project":
            avatar.sh[:, 0] = rgb_to_sh0(torch.as_tensor(self._projected_colors(),
                                                         dtype=avatar.sh.dtype))
        self.state = avatar_state(avatar.to(self.device))
        self.optimizer = make_optimizer(self.state, cfg.lr, fused=self.tally is not None)
        self.deltas: dict[str, dict[str, Tensor]] = {}
        if cfg.finetune.enabled:
            self.deltas = {s: fine_tune_deltas(self.dataset.sequences[s], self.body.model,
                                               self.device) for s in self.sequences}
        self.param_optimizer = self._make_param_optimizer()
        self.stats = DensityStats.zeros(self.num_gaussians, device=self.device)
        self.iteration = 0
        self.skipped = 0
        self.train_time_s = 0.0
        self.view_rng = np.random.default_rng(cfg.seed)
        self.order: list[int] = []
        self.split_generator = torch.Generator().manual_seed(cfg.seed)

    def _make_param_optimizer(self) -> torch.optim.Optimizer | None:
        named = {f"{s}/{k}": t for s, d in self.deltas.items() for k, t in d.items()}
        rates = self.config.finetune.lrs()
        return make_param_optimizer(named, {n: rates[n.rsplit("/", 1)[1]] for n in named},
                                    enabled=bool(named), fused=self.tally is not None)

    def _set_finetune_lrs(self, it: int) -> None:
        """The fine-tuning rates of this iteration (FineTuneConfig.lrs_at)."""
        if self.param_optimizer is None:
            return
        rates = self.config.finetune.lrs_at(it, self.config.iterations, self.num_frames)
        for group in self.param_optimizer.param_groups:
            group["lr"] = rates[group["name"].rsplit("/", 1)[1]]

    def _projected_colors(self) -> np.ndarray:
        """[F, 3] initial colours (see the module docstring)."""
        seq = self.sequences[0]
        cams = list(dict.fromkeys(k.camera for k in self.views.keys if k.sequence == seq))
        views = [self.dataset.view(seq, 0, c) for c in cams]
        with torch.no_grad():
            verts = self.body.model(frame_inputs(self.params[seq], None, 0)).vertices[0]
        faces = self.faces.cpu().numpy()
        parts = face_part_ids(self.body.model, self.body.segmentation, self.dataset.part_names)
        colors = project_face_colors(verts.cpu().double().numpy(), faces, parts, views)
        seen = np.isfinite(colors).all(1)
        if self.config.init_unseen == "neighbours":
            colors = fill_unseen_colors(colors, faces, parts)
        filled = np.isfinite(colors).all(1)
        log.info("initial colours: %d of %d triangles seen in %d views of %s frame 0, %d "
                 "more from their neighbours, the rest grey", int(seen.sum()), len(faces),
                 len(views), seq, int(filled.sum() - seen.sum()))
        colors[~filled] = DEFAULT_COLOR
        return colors

    # -- checkpoints ---------------------------------------------------------------------

    def _payload(self) -> dict[str, Any]:
        self._flush_tally()  # the skip count, read back before it is saved
        return {
            "iteration": self.iteration,
            "config": config_to_dict(self.config),
            "dataset": str(self.dataset.root),
            "body_model_dir": self.body_model_dir,
            "state": dict(self.state),
            "optimizer": self.optimizer.state_dict(),
            "deltas": self.deltas,
            "param_optimizer": (None if self.param_optimizer is None
                                else self.param_optimizer.state_dict()),
            "density": {"grad_accum": self.stats.grad_accum, "count": self.stats.count,
                        "max_radii": self.stats.max_radii},
            "rng": {"views": self.view_rng.bit_generator.state, "order": list(self.order),
                    "split": self.split_generator.get_state()},
            "skipped": self.skipped,
            "train_time_s": self.train_time_s,
        }

    def save_checkpoint(self) -> Path:
        save_config(self.config, self.out_dir / CHECKPOINT_DIR / "config.json")
        return save_checkpoint(self._payload(), self.out_dir, self.iteration)

    def _restore(self, ckpt: dict[str, Any]) -> None:
        dev = self.device
        self.state = {k: v.to(dev).requires_grad_(k in GAUSSIAN_KEYS)
                      for k, v in ckpt["state"].items()}
        if int(self.state["parents"].max()) >= self.faces.shape[0]:
            raise ValueError("the checkpoint's Gaussians are bound to another mesh")
        self.optimizer = make_optimizer(self.state, self.config.lr,
                                        fused=self.tally is not None)
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.deltas = {s: {k: t.to(dev) for k, t in d.items()}
                       for s, d in ckpt["deltas"].items()}
        self.param_optimizer = self._make_param_optimizer()
        if self.param_optimizer is not None:
            self.param_optimizer.load_state_dict(ckpt["param_optimizer"])
        d = ckpt["density"]
        self.stats = DensityStats(grad_accum=d["grad_accum"].to(dev), count=d["count"].to(dev),
                                  max_radii=d["max_radii"].to(dev))
        self.iteration = int(ckpt["iteration"])
        self.skipped = int(ckpt["skipped"])
        self.train_time_s = float(ckpt["train_time_s"])
        self.view_rng = np.random.default_rng()
        self.view_rng.bit_generator.state = ckpt["rng"]["views"]
        self.order = [int(i) for i in ckpt["rng"]["order"]]
        self.split_generator = torch.Generator()
        self.split_generator.set_state(ckpt["rng"]["split"])

    @classmethod
    def resume(cls, out_dir: str | Path, dataset: Dataset | str | Path | None = None, *,
               body_model: str | Path | None = None, progress: Progress | None = None,
               iterations: int | None = None, device: str | None = None,
               profile: bool = False) -> Trainer:
        """The trainer of the latest checkpoint in ``out_dir``, with its config (optionally
        a new total of ``iterations`` or another ``device``) and dataset (unless given)."""
        path = latest_checkpoint(out_dir)
        if path is None:
            raise FileNotFoundError(f"no checkpoint in {Path(out_dir) / CHECKPOINT_DIR}")
        ckpt = load_checkpoint(path)
        config = config_from_dict(ckpt["config"])
        if iterations is not None:
            config = replace(config, iterations=iterations)
        if device is not None:
            config = replace(config, device=device)
        log.info("resuming from %s (iteration %d)", path, ckpt["iteration"])
        return cls(dataset if dataset is not None else ckpt["dataset"], config, out_dir,
                   body_model if body_model is not None else ckpt.get("body_model_dir"),
                   progress, checkpoint=ckpt, profile=profile)

    # -- one iteration -------------------------------------------------------------------

    @property
    def num_gaussians(self) -> int:
        return int(self.state["parents"].shape[0])

    def _next_view(self) -> int:
        if not self.order:
            self.order = self.view_rng.permutation(len(self.views)).tolist()
        return self.order.pop()

    def _frames(self, seq: str, frame: int) -> FaceFrames:
        """Triangle frames of a training frame; cached while the mesh is fixed (no
        fine-tuning), differentiable in the deltas otherwise."""
        key = (seq, frame)
        if not self.deltas:
            hit = self._frame_cache.get(key)
            if hit is not None:
                self._frame_cache.move_to_end(key)
                return hit
        with torch.set_grad_enabled(bool(self.deltas)):
            inputs = frame_inputs(self.params[seq], self.deltas.get(seq), frame)
            frames = FaceFrames.of_mesh(self.body.model(inputs).vertices[0], self.faces)
        if not self.deltas:
            self._frame_cache[key] = frames
            while len(self._frame_cache) > _FRAME_CACHE:
                self._frame_cache.popitem(last=False)
        return frames

    def background(self, it: int) -> tuple[float, float, float]:
        """The background of iteration ``it``: the configured one, or with
        ``random_background`` a colour drawn from (seed, it), so a resumed run draws the
        same colours without any generator state to checkpoint."""
        data = self.config.data
        if not data.random_background:
            return data.background
        r, g, b = np.random.default_rng([self.config.seed, it]).random(3).tolist()
        return (r, g, b)

    def _outputs(self, view: TrainView) -> tuple[str, ...]:
        """The render's outputs: alpha too when the mask loss is on and the view has one."""
        use = self.config.loss.lambda_mask > 0 and view.alpha is not None
        return ("rgb", "alpha") if use else ("rgb",)

    def _loss(self, pred: Tensor, view: TrainView, visible: Tensor,
              alpha: Tensor | None = None) -> Tensor:
        cfg = self.config.loss
        loss = photometric_loss_fast(pred, view.target, view.weight, cfg.lambda_dssim)
        if alpha is not None:
            loss = loss + cfg.lambda_mask * mask_loss(alpha, view.alpha, view.weight)
        if self.lpips is not None:
            # LPIPS takes no mask: the masked pixels of the render are replaced by the GT
            keep = view.weight[..., None] > 0
            loss = loss + cfg.lambda_lpips * self.lpips(torch.where(keep, pred, view.target),
                                                        view.target)
        reg = avatar_regularizers(self.state["local_means"], self.state["log_scales"],
                                  weight=visible, config=self.regularizer)
        return loss + reg["pos"] + reg["scale"]

    def _leaves(self) -> list[Tensor]:
        deltas = [t for d in self.deltas.values() for t in d.values()]
        return [self.state[k] for k in GAUSSIAN_KEYS] + deltas

    def _drop_grads(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        if self.param_optimizer is not None:
            self.param_optimizer.zero_grad(set_to_none=True)

    def _skip(self, why: str, view: TrainView) -> StepResult:
        self._drop_grads()
        self.skipped += 1
        log.warning("iteration %d: skipped view %s/%05d/%s: %s", self.iteration,
                    view.key.sequence, view.key.frame, view.key.camera, why)
        return StepResult(self.iteration, None, why)

    def step(self) -> StepResult:
        """One training iteration (see the module docstring)."""
        cfg, ph = self.config, self.phases
        self.iteration = it = self.iteration + 1
        ph.start()
        set_position_lr(self.optimizer, cfg.lr, it)
        self._set_finetune_lrs(it)
        view = self.views.get(self._next_view())
        self._posed_k = None
        ph.mark("data")
        if self.tally is None:
            result = self._fit(view, it)
        else:  # no loss on the host: it is read at the next report
            result = fit_on_device(self, view, it) or StepResult(it, None)
        self._densify(it, view)  # on schedule even when the view was skipped
        ph.mark("densify")
        return result

    def _fit(self, view: TrainView, it: int) -> StepResult:
        """Render, score and step on one view; skipped (model untouched) when it cannot
        teach anything or its loss/gradients are not finite."""
        cfg, ph = self.config, self.phases
        if view.weight_sum <= 0:
            return self._skip("empty loss mask (only masked-out pixels)", view)
        frames = self._frames(view.key.sequence, view.key.frame)
        self._posed_k = frames.scale.detach()
        ph.mark("pose")
        gaussians = world_gaussians(self.state, frames, cfg.active_sh_degree(it))
        gaussians.means.retain_grad()
        background = self.background(it)
        view = replace(view, target=view.on_background(background), background=background)
        request = RenderRequest(outputs=self._outputs(view), background=background)
        out = rasterize(gaussians, view.camera, request)
        pred = out.rgb  # [h, w, 3]
        ph.mark("render")
        visible, radii = visibility(gaussians, view.camera)  # [N], [N]
        loss = self._loss(pred, view, visible, out.alpha)
        value = float(loss.detach())
        ph.mark("loss")
        if not math.isfinite(value):
            return self._skip(f"loss is {value}", view)
        loss.backward()
        ph.mark("backward")
        # one reduction: NaN and Inf survive a sum (an overflow to Inf is skipped too)
        if not bool(torch.stack([t.grad.sum() for t in self._leaves()
                                 if t.grad is not None]).sum().isfinite()):
            return self._skip("non-finite gradients", view)
        with torch.no_grad():
            if cfg.densify.enabled and it < cfg.densify.until_iter:
                grad = screen_grad_norm(gaussians.means, gaussians.means.grad, view.camera)
                self.stats.update(grad, visible, radii)
            self.optimizer.step()
            if self.param_optimizer is not None:
                self.param_optimizer.step()
        self._drop_grads()
        self._last = (pred.detach(), view)
        ph.mark("optimizer")
        return StepResult(it, value)

    def _densify(self, it: int, view: TrainView) -> None:
        d = self.config.densify
        if not d.enabled or it >= d.until_iter:
            return
        if it > d.from_iter and it % d.interval == 0:
            if self._posed_k is None:  # this view was skipped before posing
                with torch.no_grad():
                    self._posed_k = self._frames(view.key.sequence,
                                                 view.key.frame).scale.detach()
            before = self.num_gaussians
            res = densify_and_prune(
                self.state, self.stats, self.optimizer, grad_threshold=d.grad_threshold,
                percent_dense=d.percent_dense, extent=self.extent, min_opacity=d.min_opacity,
                max_screen_size=d.max_screen_size if it > d.opacity_reset_interval else None,
                max_gaussians=d.max_gaussians, face_scales=self._posed_k,
                generator=self.split_generator)
            self.state = res.state
            self._emit("densify", before=before, cloned=res.n_cloned, split=res.n_split,
                       pruned=res.n_pruned)
        if it % d.opacity_reset_interval == 0:
            self.state = reset_opacity(self.state, self.optimizer)

    # -- the run -------------------------------------------------------------------------

    def _flush_tally(self) -> None:
        """The device path's tally into the host-side window and skip count."""
        if self.tally is None:
            return
        loss_sum, steps, skipped = self.tally.take()
        window = self._window
        window["loss_sum"] = window.get("loss_sum", 0.0) + loss_sum
        window["steps"] = window.get("steps", 0) + steps
        if steps:
            self._last_loss = loss_sum / steps
        if skipped:
            self.skipped += skipped
            log.warning("%d view(s) skipped before iteration %d: non-finite loss or gradients",
                        skipped, self.iteration)

    def _emit(self, kind: str, **extra: Any) -> None:
        self._flush_tally()
        if self.progress is None:
            return
        psnr_value = None
        if self._last is not None:
            pred, view = self._last
            with torch.no_grad():
                p = float(psnr(pred, view.target, view.weight))
            psnr_value = p if math.isfinite(p) else None
        window = self._window
        now = time.perf_counter()
        its = self.iteration - window["iteration"]
        losses = window["losses"]
        if window.get("steps"):
            mean_loss: float | None = window["loss_sum"] / window["steps"]
        else:
            mean_loss = float(np.mean(losses)) if losses else self._last_loss
        event = {"type": kind, "iteration": self.iteration, "total": self.config.iterations,
                 "loss": mean_loss,
                 "psnr": psnr_value,
                 "num_gaussians": self.num_gaussians,
                 "elapsed_s": round(self.train_time_s + now - window["session_start"], 3),
                 "its_per_s": round(its / (now - window["time"]), 3) if its > 0 else None,
                 **extra}
        if kind == "progress":
            window.update(iteration=self.iteration, time=now, losses=[], loss_sum=0.0,
                          steps=0)
        self.progress(event)

    def train(self, stop_at: int | None = None) -> Path | None:
        """Run to ``config.iterations`` (or stop after iteration ``stop_at``, with a
        checkpoint there); at the end, the avatar package is written and its path returned
        (None when stopped early)."""
        cfg = self.config
        end = cfg.iterations if stop_at is None else min(stop_at, cfg.iterations)
        start = time.perf_counter()
        self._window = {"iteration": self.iteration, "time": start, "losses": [],
                        "session_start": start}
        saved_at = None
        while self.iteration < end:
            result = self.step()
            if result.loss is not None:
                self._window["losses"].append(result.loss)
                self._last_loss = result.loss
            it = self.iteration
            if it % cfg.progress_interval == 0 or it == end:
                self._emit("progress")
            if it % cfg.checkpoint_interval == 0 or it == end:
                path = self._save_timed(start)
                start = time.perf_counter()
                self._window["session_start"] = start
                saved_at = it
                self._emit("checkpoint", path=str(path))
        if saved_at != self.iteration and self.iteration > 0:
            self._save_timed(start)
            start = time.perf_counter()
        if self.iteration < cfg.iterations:
            return None
        package = self.export()
        self._window["session_start"] = time.perf_counter()
        self._emit("done", path=str(package), skipped=self.skipped)
        return package

    def _save_timed(self, start: float) -> Path:
        self.train_time_s += time.perf_counter() - start
        return self.save_checkpoint()

    def render_view(self, key: ViewKey, *, crop: bool = False) -> tuple[Tensor, TrainView]:
        """(render [h, w, 3], the prepared view) of any view of the dataset at training
        resolution, whole (or cropped like training), without gradients. Frames of training
        sequences are posed with their fine-tuned deltas."""
        data = replace(self.config.data, crop_to_subject=crop)
        view = prepare_view(self.dataset.view(*key), data, self.device)
        base = self.params.get(key.sequence)
        with torch.no_grad():
            if base is None:
                raw = sequence_params(self.dataset.params(key.sequence),
                                      self.dataset.sequences[key.sequence],
                                      fusion=self._fusion)
                base = {k: torch.as_tensor(v[key.frame:key.frame + 1], dtype=torch.float32,
                                           device=self.device) for k, v in raw.items()}
                inputs = frame_inputs(base, None, 0)
            else:
                inputs = frame_inputs(base, self.deltas.get(key.sequence), key.frame)
            frames = FaceFrames.of_mesh(self.body.model(inputs).vertices[0], self.faces)
            gaussians = world_gaussians(self.state, frames,
                                        self.config.active_sh_degree(self.iteration))
            request = RenderRequest(outputs=("rgb",), background=self.config.data.background)
            return rasterize(gaussians, view.camera, request).rgb, view

    def fine_tuned_params(self, sequence: str) -> dict[str, np.ndarray]:
        """The sequence's per-frame SMPL-X parameters with the fine-tuned deltas added."""
        base = {k: v.detach() for k, v in self.params[sequence].items()}
        for k, d in self.deltas.get(sequence, {}).items():
            base[k] = base[k] + d.detach() if k in base else d.detach()
        return {k: v.cpu().numpy() for k, v in base.items()}

    def export(self, path: str | Path | None = None) -> Path:
        """Write the avatar package (default ``out_dir/avatar``) and, with fine-tuning,
        ``out_dir/finetuned_params/<sequence>.npz``."""
        avatar = state_to_avatar({k: v.detach() for k, v in self.state.items()}).to("cpu")
        faces = self.faces.cpu().numpy()
        betas = self.params[self.sequences[0]].get("betas")
        body = BodyReference(model=self.body.reference, parts=list(self.body.model.keep_parts),
                             num_faces=len(faces), faces_sha256=faces_fingerprint(faces),
                             betas=[] if betas is None else betas[0].cpu().tolist())
        subject = self.dataset.meta.get("subject", {})
        package = AvatarPackage(
            avatar=avatar, body=body, name=f"{subject.get('identity', self.dataset.name)}",
            metadata={"trained": True, "dataset": self.dataset.name,
                      "dataset_path": str(self.dataset.root), "split": self.config.data.split,
                      "identity": subject.get("identity")},
            training={"config": config_to_dict(self.config), "iterations": self.iteration,
                      "time_s": round(self.train_time_s, 3), "skipped_views": self.skipped,
                      "num_gaussians": self.num_gaussians, "lpips": self.lpips is not None,
                      "fused": self.fused, "fine_tuned": bool(self.deltas)})
        out = save_package(package, self.out_dir / PACKAGE_DIR if path is None else path)
        if self.deltas:
            folder = self.out_dir / "finetuned_params"
            folder.mkdir(parents=True, exist_ok=True)
            for seq in self.deltas:
                np.savez(folder / f"{seq}.npz", **self.fine_tuned_params(seq))
        return out
