"""The demo avatar: trained by this pipeline on the synthetic studio, cached after the first run.

``ensure_demo_avatar()`` returns the folder of a trained avatar package. The first call films
the synthetic actor (17 cameras, expressions and gestures), trains on it with the ``demo``
preset and exports the package; later calls return the cached package at once. Each stage is
resumable: an interrupted capture is filmed again, an interrupted training resumes from its
last checkpoint. Timings on this 2-core machine are in docs/results.md.

    telesplat demo-avatar [--cache DIR]       # build (or find) it, with progress bars

The server builds it in the background instead (server/jobs/demo_build.py): the capture in a
process of its own (``python -m avatar_core.demo capture ROOT --recipe JSON``, one JSON
progress line per frame filmed), the training as a job of its job service, and
:func:`install_package` puts the job's package where :func:`ensure_demo_avatar` finds it.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

# Bump when DemoRecipe's defaults change: an old cache is rebuilt, never silently reused.
DEMO_VERSION = 3  # 3: the recipe's artefact fixes (docs/results.md)

# (stage, done, total) with stage "capture" | "train"
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class DemoRecipe:
    motions: str = "smile+grin+mouth_open+thumbs_up,peace+talk_calm+heart+brows_raised"
    resolution: int = 512
    frames: int = 40          # per sequence
    preset: str = "demo"
    iterations: int | None = None  # None: the preset's


def recipe_from_dict(values: dict | None) -> DemoRecipe:
    """A recipe from its fields (None: the default one); ValueError naming an unknown key."""
    values = dict(values or {})
    known = set(DemoRecipe.__dataclass_fields__)
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown demo recipe key(s) {unknown}; known: {sorted(known)}")
    return DemoRecipe(**values)


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
    return install_package(root, package)


def trained_package(root: Path | None = None) -> Path | None:
    """The trained demo package under ``root`` (default cache) when it is there."""
    final = (root or default_demo_dir()) / "avatar"
    return final if (final / "avatar.json").is_file() else None


def install_package(root: Path, package: Path) -> Path:
    """Copy a trained package to ``root/avatar`` (atomically, marked with DEMO_VERSION)."""
    final = root / "avatar"
    staging = root / ".avatar-staging"
    shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(package, staging)
    manifest = json.loads((staging / "avatar.json").read_text())
    manifest.setdefault("metadata", {}).update(demo_version=DEMO_VERSION, trained=True)
    (staging / "avatar.json").write_text(json.dumps(manifest, indent=2))
    if (final / "avatar.json").is_file():  # installed meanwhile (another builder)
        shutil.rmtree(staging, ignore_errors=True)
        return final
    shutil.rmtree(final, ignore_errors=True)  # a partial one from before
    staging.rename(final)  # atomic: a reader sees no package or a whole one
    return final


def main(argv: list[str] | None = None) -> int:
    """``python -m avatar_core.demo capture ROOT [--recipe JSON] [--models DIR]``: film the
    demo's dataset into ``ROOT/dataset`` (kept if already complete), printing one JSON line
    ``{"stage": "capture", "done": d, "total": t}`` per frame filmed."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m avatar_core.demo")
    parser.add_argument("command", choices=["capture"])
    parser.add_argument("root", type=Path)
    parser.add_argument("--recipe", default=None, help="DemoRecipe fields as JSON")
    parser.add_argument("--models", type=Path, default=None)
    args = parser.parse_args(argv)
    recipe = recipe_from_dict(json.loads(args.recipe) if args.recipe else None)

    def progress(stage: str, done: int, total: int) -> None:
        print(json.dumps({"stage": stage, "done": done, "total": total}), flush=True)

    args.root.mkdir(parents=True, exist_ok=True)
    data = _capture(args.root, recipe, args.models, progress)
    print(json.dumps({"stage": "captured", "dataset": str(data)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
