"""Training checkpoints: ``OUT/checkpoints/iter_XXXXXX.pt`` plus the resolved ``config.json``.

A checkpoint is one ``torch.save`` of plain containers (tensors on the CPU, dicts, lists,
numbers, strings), so it loads with ``weights_only=True``: nothing in it can run code.
Files are written to a temporary name and renamed, so a crash mid-write never leaves a
truncated checkpoint that ``latest_checkpoint`` would pick.
"""

from __future__ import annotations

import os
import pickle
import re
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

__all__ = ["CHECKPOINT_DIR", "checkpoint_path", "latest_checkpoint", "load_checkpoint",
           "save_checkpoint", "to_cpu"]

CHECKPOINT_DIR = "checkpoints"
FORMAT_VERSION = 1
_NAME = re.compile(r"^iter_(\d{6,})\.pt$")


def checkpoint_path(out_dir: str | Path, iteration: int) -> Path:
    return Path(out_dir) / CHECKPOINT_DIR / f"iter_{iteration:06d}.pt"


def latest_checkpoint(out_dir: str | Path) -> Path | None:
    """The checkpoint with the highest iteration in ``out_dir``, None if there is none."""
    folder = Path(out_dir) / CHECKPOINT_DIR
    found = [(int(m.group(1)), p) for p in folder.glob("iter_*.pt")
             if (m := _NAME.match(p.name))] if folder.is_dir() else []
    return max(found)[1] if found else None


def to_cpu(obj: Any) -> Any:
    """A copy of nested dicts/lists/tuples with every tensor detached onto the CPU."""
    if isinstance(obj, Tensor):
        return obj.detach().cpu().clone()
    if isinstance(obj, dict):
        return {k: to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(to_cpu(v) for v in obj)
    return obj


def save_checkpoint(payload: dict[str, Any], out_dir: str | Path, iteration: int) -> Path:
    path = checkpoint_path(out_dir, iteration)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".pt.tmp")
    torch.save({"format_version": FORMAT_VERSION, **to_cpu(payload)}, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """The payload (tensors on the CPU); ValueError for a file of another format."""
    try:
        payload = torch.load(Path(path), map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, pickle.UnpicklingError) as exc:
        raise ValueError(f"{path}: not a readable training checkpoint: {exc}") from exc
    version = payload.get("format_version") if isinstance(payload, dict) else None
    if version != FORMAT_VERSION:
        raise ValueError(f"{path}: checkpoint format {version!r}, this build reads "
                         f"{FORMAT_VERSION}")
    return payload
