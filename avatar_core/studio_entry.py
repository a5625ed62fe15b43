"""The studio's one entry point: what production code needs the studio to make.

Production never imports the studio (``avatar_core.synth``) or its demo-avatar builder
(``avatar_core.demo``); it asks this module, and only at start-up:

- :func:`synthetic_body_models`: the synthetic body-model family (stand-ins in the official
  formats), the body-model resolver's last resort (``avatar_core.body.model_paths``);
- :func:`trained_demo_avatar`: the trained demo avatar, the server's start-up demo avatar when
  configured as ``trained`` (``server.registry``);
- :func:`demo_build_plan` and :func:`install_trained_demo`: the same avatar built in the
  background while the server already runs (``server.jobs.demo_build``): where it is cached, the
  command that films its dataset, the training config, and installing the trained package.

Both import the studio inside the function, so importing this module (or anything that imports
it) never loads the studio. tests/test_import_rules.py names this module as the one exception
to "production imports no studio", and the two start-up paths as its only callers.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # annotations only: the writer imports model_paths, not the other way
    from .body.model_paths import BodyModelFiles

__all__ = ["DemoBuildPlan", "demo_build_plan", "install_trained_demo", "synthetic_body_models",
           "trained_demo_avatar"]


def synthetic_body_models(folder: str | Path | None = None, seed: int = 0) -> BodyModelFiles:
    """The synthetic family of ``seed`` in ``folder`` (default: the user cache), written there
    first if missing or written by another generator version."""
    from .synth.model_writer import ensure_models

    return ensure_models(None if folder is None else Path(folder), seed=seed)


def trained_demo_avatar(cache: str | Path | None = None) -> Path:
    """The trained demo avatar package (a folder) in the user cache (or ``cache``): filmed in
    the studio and trained on first use (minutes), found there afterwards."""
    from .demo import ensure_demo_avatar

    return Path(ensure_demo_avatar(None if cache is None else Path(cache)))


@dataclass(frozen=True)
class DemoBuildPlan:
    """How to build the trained demo avatar outside ``ensure_demo_avatar``'s one process."""

    root: Path                   # the demo cache folder
    ready: Path | None           # the trained package, when it is there already
    dataset: Path                # where the capture puts the dataset
    capture_command: list[str]   # films it (JSON progress lines on stdout)
    config: dict[str, Any]       # the training config (preset + iterations), a TrainConfig dict
    version: int                 # DEMO_VERSION


def demo_build_plan(cache: str | Path | None = None,
                    recipe: dict[str, Any] | None = None) -> DemoBuildPlan:
    """The plan for the demo in ``cache`` (default: the user cache) with ``recipe`` (DemoRecipe
    fields; None: the default recipe). ValueError for a bad recipe."""
    from dataclasses import replace

    from .demo import DEMO_VERSION, default_demo_dir, recipe_from_dict, trained_package
    from .train.config import config_to_dict, preset

    parsed = recipe_from_dict(recipe)
    root = Path(cache) if cache is not None else default_demo_dir()
    config = preset(parsed.preset)
    if parsed.iterations is not None:
        config = replace(config, iterations=parsed.iterations)
    command = [sys.executable, "-m", "avatar_core.demo", "capture", str(root),
               "--recipe", json.dumps(recipe or {})]
    return DemoBuildPlan(root=root, ready=trained_package(root), dataset=root / "dataset",
                         capture_command=command, config=config_to_dict(config),
                         version=DEMO_VERSION)


def install_trained_demo(root: str | Path, package: str | Path) -> Path:
    """Put a trained package in the demo cache ``root`` (where ``trained_demo_avatar`` and
    later starts find it); the installed folder."""
    from .demo import install_package

    return install_package(Path(root), Path(package))
