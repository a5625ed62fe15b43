"""The studio's one entry point: what production code needs the studio to make.

Production never imports the studio (``avatar_core.synth``) or its demo-avatar builder
(``avatar_core.demo``); it asks this module, and only at start-up:

- :func:`synthetic_body_models`: the synthetic body-model family (stand-ins in the official
  formats), the body-model resolver's last resort (``avatar_core.body.model_paths``);
- :func:`trained_demo_avatar`: the trained demo avatar, the server's start-up demo avatar when
  configured as ``trained`` (``server.registry``).

Both import the studio inside the function, so importing this module (or anything that imports
it) never loads the studio. tests/test_import_rules.py names this module as the one exception
to "production imports no studio", and the two start-up paths as its only callers.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: the writer imports model_paths, not the other way
    from .body.model_paths import BodyModelFiles

__all__ = ["synthetic_body_models", "trained_demo_avatar"]


def synthetic_body_models(folder: str | Path | None = None, seed: int = 0) -> BodyModelFiles:
    """The synthetic family of ``seed`` in ``folder`` (default: the user cache), written there
    first if missing or written by another generator version."""
    from .synth.model_writer import ensure_models

    return ensure_models(None if folder is None else Path(folder), seed=seed)


def trained_demo_avatar() -> Path:
    """The trained demo avatar package (a folder) in the user cache: filmed in the studio and
    trained on first use (minutes), found there afterwards."""
    from .demo import ensure_demo_avatar

    return Path(ensure_demo_avatar())
