"""The demo avatar: trained by this pipeline on the synthetic studio, cached after the first run.

``ensure_demo_avatar()`` returns the folder of a trained avatar package. The first call films
the synthetic actor (17 cameras, expressions and gestures), trains on it with the ``demo``
preset and exports the package; later calls return the cached package at once. Each stage is
resumable: an interrupted capture is filmed again, an interrupted training resumes from its
last checkpoint. Timings on this 2-core machine are in docs/results.md.

    telesplat demo-avatar [--cache DIR]       # build (or find) it, with progress bars
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

# Bump when DemoRecipe's defaults change: an old cache is rebuilt, never silently reused.
DEMO_VERSION = 2

# (stage, done, total) with stage "capture" | "train"
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class DemoRecipe:
    motions: str = "smile+grin+mouth_open+thumbs_up,peace+talk_calm+heart+brows_raised"
    resolution: int = 512
    frames: int = 40          # per sequence
    preset: str = "demo"
    iterations: int | None = None  # None: the preset's


def default_demo_dir() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "telesplat" / f"demo-avatar-v{DEMO_VERSION}"


def _capture(root: Path, recipe: DemoRecipe, model_dir: Path | None,
             progress: Progress | None) -> Path:
    from .synth.capture import CaptureSpec, capture, parse_sequences

    data = root / "dataset"
    if (data / "dataset.json").is_file():  # written last: the capture finished
        return data
    shutil.rmtree(data, ignore_errors=True)
    spec = CaptureSpec(sequences=parse_sequences(recipe.motions), resolution=recipe.resolution,
                       max_frames=recipe.frames, holdout_sequences=0)

    def tick(done: int, total: int) -> None:
        if progress:
            progress("capture", done, total)

    return capture(data, spec, model_dir=model_dir, progress=tick)


def _train(root: Path, data: Path, recipe: DemoRecipe, model_dir: Path | None,
           progress: Progress | None) -> Path:
    from .train.checkpoint import latest_checkpoint
    from .train.config import preset
    from .train.trainer import Trainer

    work = root / "train"

    def on_event(event: dict) -> None:
        if progress:
            progress("train", int(event["iteration"]), int(event["total"]))

    if latest_checkpoint(work) is not None:
        trainer = Trainer.resume(work, data, body_model=model_dir, progress=on_event)
    else:
        shutil.rmtree(work, ignore_errors=True)
        config = preset(recipe.preset)
        if recipe.iterations is not None:
            config = replace(config, iterations=recipe.iterations)
        trainer = Trainer(data, config, work, body_model=model_dir, progress=on_event)
    return trainer.train()


def ensure_demo_avatar(cache: Path | None = None, progress: Progress | None = None,
                       recipe: DemoRecipe | None = None, model_dir: Path | None = None) -> Path:
    """The trained demo avatar package (a folder), built on first use. ``model_dir``: the
    synthetic body-model folder (default: the cached family)."""
    root = cache or default_demo_dir()
    recipe = recipe or DemoRecipe()
    final = root / "avatar"
    if (final / "avatar.json").is_file():
        return final
    root.mkdir(parents=True, exist_ok=True)
    data = _capture(root, recipe, model_dir, progress)
    package = _train(root, data, recipe, model_dir, progress)
    staging = root / ".avatar-staging"
    shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(package, staging)
    manifest = json.loads((staging / "avatar.json").read_text())
    manifest.setdefault("metadata", {})["demo_version"] = DEMO_VERSION
    (staging / "avatar.json").write_text(json.dumps(manifest, indent=2))
    staging.rename(final)  # atomic: a reader sees no package or a whole one
    return final
