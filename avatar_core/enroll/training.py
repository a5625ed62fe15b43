"""The monocular training run: the ``enroll`` preset scaled to the run's length and frame
count, then the MVFGA trainer on the one-camera dataset."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..train.config import TrainConfig, preset
from ..train.optim import GaussianLR
from .config import EnrollConfig


def enroll_train_config(config: EnrollConfig, frames: int) -> TrainConfig:
    """The ``enroll`` preset for ``config.iterations`` over ``frames`` training frames:
    densification from 10 % to 80 % of the run, every max(one pass over the frames, 1/20 of
    the run) iterations so each densification has seen about every frame's gradients;
    fine-tuning and the mask loss per the switches."""
    base = preset("enroll")
    it = config.iterations
    interval = max(1, min(max(frames, it // 20), max(it // 4, 1)))
    densify = replace(base.densify, from_iter=max(1, it // 10), until_iter=max(2, it * 8 // 10),
                      interval=interval)
    loss = base.loss if config.masks else replace(base.loss, lambda_mask=0.0)
    if config.iterations < 1_000:  # short (test) runs: no LPIPS download, SH degree 0
        loss = replace(loss, lpips=False)
    return replace(
        base, iterations=it, seed=config.seed,
        checkpoint_interval=max(1, min(base.checkpoint_interval, it)),
        sh_interval=max(1, it // 6), progress_interval=max(1, min(10, it // 10)),
        lr=GaussianLR(position_max_steps=it), densify=densify, loss=loss,
        data=replace(base.data, target_size=config.resolution,
                     crop_to_subject=config.masks),
        finetune=replace(base.finetune, enabled=config.fine_tune))


def train_take(dataset: Path, out_dir: Path, config: TrainConfig, body_models,
               progress: Callable[[dict[str, Any]], None] | None = None
               ) -> tuple[Path, dict[str, Any]]:
    from ..train.trainer import Trainer

    trainer = Trainer(dataset, config, out_dir, body_model=body_models, progress=progress)
    package = trainer.train()
    stats = {"iterations": trainer.iteration, "seconds": round(trainer.train_time_s, 2),
             "gaussians": trainer.num_gaussians, "loss": trainer._last_loss,
             "skipped_views": trainer.skipped, "fine_tuned": bool(trainer.deltas)}
    return package, stats
