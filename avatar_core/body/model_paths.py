"""Where the body-model files are: their official names, and the one resolver that finds them.

`resolve_body_models` takes, in order, an explicit folder, `$TELESPLAT_BODY_MODELS`, the server
setting passed in by the caller, and finally the synthetic family (the stand-ins the studio
writes in the official formats, generated into the user cache on first use).

Generating the synthetic family is the studio's work, so `synthetic_body_models` imports
`avatar_core.synth.model_writer` inside the function: the one import of the studio from a
production package, lazy so that importing `body` never loads the studio, and listed as an
allowed exception in tests/test_import_rules.py. (A generator injected by the caller was the
alternative; every caller would then import the studio itself, which is what this avoids.)
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

BODY_MODELS_ENV = "TELESPLAT_BODY_MODELS"


@dataclass(frozen=True)
class BodyModelFiles:
    """Paths of one family of body-model files under the official file names. `gestures`,
    `manifest` and `identities` exist only in the synthetic family."""

    root: Path

    @property
    def smplx_npz(self) -> Path:
        return self.root / "SMPLX_NEUTRAL.npz"

    @property
    def smplx_pkl(self) -> Path:
        return self.root / "SMPLX_NEUTRAL.pkl"

    @property
    def segmentation(self) -> Path:
        return self.root / "smplx_vert_segmentation.json"

    @property
    def flame_pkl(self) -> Path:
        return self.root / "FLAME_NEUTRAL.pkl"

    @property
    def flame_static_embedding(self) -> Path:
        return self.root / "flame_static_embedding.pkl"

    @property
    def flame_dynamic_embedding(self) -> Path:
        return self.root / "flame_dynamic_embedding.npy"

    @property
    def flame_correspondence(self) -> Path:
        return self.root / "SMPL-X__FLAME_vertex_ids.npy"

    def mano_pkl(self, side: str) -> Path:
        return self.root / f"MANO_{side.upper()}.pkl"

    @property
    def mano_correspondence(self) -> Path:
        return self.root / "MANO_SMPLX_vertex_ids.pkl"

    @property
    def gestures(self) -> Path:
        return self.root / "gestures.npz"

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    def identities(self) -> list[Path]:
        return sorted((self.root / "identities").glob("identity_*.npz"))


def resolve_body_models(folder: str | Path | None = None, *, setting: str | Path | None = None,
                        seed: int = 0) -> BodyModelFiles:
    """The body-model files to use: `folder`, else `$TELESPLAT_BODY_MODELS`, else `setting`
    (the server's), else the synthetic family of `seed` (generated on first use)."""
    for candidate in (folder, os.environ.get(BODY_MODELS_ENV), setting):
        if candidate:  # an empty string or variable means "not given"
            return BodyModelFiles(Path(candidate))
    return synthetic_body_models(seed=seed)


def synthetic_body_models(folder: str | Path | None = None, seed: int = 0) -> BodyModelFiles:
    """The synthetic family of `seed` in `folder` (default: the user cache), written there
    first if missing or written by another generator version."""
    from ..synth.model_writer import ensure_models  # the allowed lazy studio import (above)

    return ensure_models(None if folder is None else Path(folder), seed=seed)
