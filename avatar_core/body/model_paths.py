"""Where the body-model files are: their official names, and the one resolver that finds them.

`resolve_body_models` takes, in order, an explicit folder (`--body-models DIR`),
`$TELESPLAT_BODY_MODELS`, the server setting `body_models` passed in by the caller, and finally
the synthetic family (the stand-ins the studio writes in the official formats, generated into
the user cache on first use).

What was made with a body model names it: a dataset's `body_model.source` ("synthetic-seedN" or
anything else) and an avatar package's body reference ("synthetic:seedN" or the model file's
name). `models_for_source` / `models_for_reference` turn those into files: the synthetic family
of that seed (the given folder when it holds that family, else the generated one), or for any
other model the given folder, and when none is given a `BodyModelsMissing` that says which
official files to put where.

Generating the synthetic family is the studio's work, so `synthetic_body_models` asks the
studio's one entry point (`avatar_core.studio_entry`, also the server's way to the trained
demo avatar) inside the function: lazy, so that importing `body` never loads the studio, and
named in tests/test_import_rules.py as that entry's start-up caller. (A generator injected by
the caller was the alternative; every caller would then import the studio itself, which is
what this avoids.)
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from .errors import ModelFileError

BODY_MODELS_ENV = "TELESPLAT_BODY_MODELS"
SYNTHETIC_SOURCE = "synthetic-seed"     # a dataset's body_model.source: "synthetic-seed0"
SYNTHETIC_REFERENCE = "synthetic:seed"  # an avatar package's body reference: "synthetic:seed0"
HOW_TO_GIVE = ("--body-models DIR, the environment variable TELESPLAT_BODY_MODELS or the "
               "server setting body_models")


class BodyModelsMissing(ModelFileError):
    """No body-model folder was given where real models are needed, or it lacks a file.
    ``public``: the message without the folder, for a client of the server."""

    def __init__(self, message: str, *, public: str = "") -> None:
        super().__init__(message)
        self.public = public or message


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

    def synthetic_seed(self) -> int | None:
        """The seed when the folder holds the studio's synthetic family (its manifest says
        so), else None: official folders have no manifest."""
        try:
            manifest = json.loads(self.manifest.read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(manifest, dict) or manifest.get("synthetic") is not True:
            return None
        seed = manifest.get("seed")
        return seed if isinstance(seed, int) and not isinstance(seed, bool) else None

    def describe(self) -> str:
        seed = self.synthetic_seed()
        return f"{self.root} (synthetic family, seed {seed})" if seed is not None \
            else str(self.root)

    def require(self, *paths: Path) -> None:
        """BodyModelsMissing naming every absent file of `paths` (default: what the upper body
        needs) and what the folder should hold."""
        missing = [p.name for p in paths or (self.smplx_npz, self.segmentation)
                   if not p.is_file()]
        if missing:
            lacks = f"lacks {', '.join(missing)}; {official_files_note()}"
            raise BodyModelsMissing(f"the body-model folder {self.root} {lacks}",
                                    public=f"the server's body-model folder {lacks}")


# (file name, what it is for, needed for the upper body) in the order a user should read them
OFFICIAL_FILES = (
    ("SMPLX_NEUTRAL.npz", "the SMPL-X model, smplx package layout", True),
    ("smplx_vert_segmentation.json", "SMPL-X part name -> vertex ids, Meshcapade's", True),
    ("MANO_LEFT.pkl, MANO_RIGHT.pkl", "MANO hands, to fuse MANO parameters", False),
    ("MANO_SMPLX_vertex_ids.pkl", "MANO -> SMPL-X vertex correspondence", False),
    ("FLAME_NEUTRAL.pkl", "FLAME head, to fuse FLAME parameters", False),
    ("SMPL-X__FLAME_vertex_ids.npy", "FLAME -> SMPL-X vertex correspondence", False),
)


def official_files_note() -> str:
    """Which official files go into the body-model folder, and how to name the folder."""
    needed = " and ".join(f"{name} ({what})" for name, what, req in OFFICIAL_FILES if req)
    optional = "; ".join(f"{name} ({what})" for name, what, req in OFFICIAL_FILES if not req)
    return (f"put {needed} in one folder, optionally also {optional}; and name the folder "
            f"with {HOW_TO_GIVE}")


def resolve_body_models(folder: str | Path | None = None, *, setting: str | Path | None = None,
                        seed: int = 0) -> BodyModelFiles:
    """The body-model files to use: `folder`, else `$TELESPLAT_BODY_MODELS`, else `setting`
    (the server's), else the synthetic family of `seed` (generated on first use)."""
    given = given_body_models(folder, setting=setting)  # an empty string means "not given"
    return given if given is not None else synthetic_body_models(seed=seed)


def given_body_models(folder: str | Path | None = None, *,
                      setting: str | Path | None = None) -> BodyModelFiles | None:
    """The resolver's order without its last resort: None when no folder was given."""
    for candidate in (folder, os.environ.get(BODY_MODELS_ENV), setting):
        if candidate:
            return BodyModelFiles(Path(candidate))
    return None


def _synthetic_or_given(seed: int, given: BodyModelFiles | None) -> BodyModelFiles:
    # A synthetic family can always be generated, so what was made with one uses it even
    # where the folder given holds other (e.g. the user's licensed) models.
    if given is not None and given.synthetic_seed() == seed:
        return given
    return synthetic_body_models(seed=seed)


def synthetic_seed_of(name: str, prefix: str) -> int | None:
    """N of "synthetic-seedN" / "synthetic:seedN" (with that `prefix`), else None."""
    rest = name.removeprefix(prefix) if name.startswith(prefix) else ""
    return int(rest) if rest.isdigit() else None


def models_for_source(source: str, folder: str | Path | None = None, *,
                      setting: str | Path | None = None) -> tuple[BodyModelFiles, str]:
    """The files a dataset's parameters (its `body_model.source`) drive, and the body
    reference an avatar trained on them records."""
    seed = synthetic_seed_of(source, SYNTHETIC_SOURCE)
    given = given_body_models(folder, setting=setting)
    if seed is not None:
        return _synthetic_or_given(seed, given), f"{SYNTHETIC_REFERENCE}{seed}"
    if given is None:
        raise BodyModelsMissing(f"the dataset's parameters come from body model {source!r} "
                                f"and no body-model folder is set: {official_files_note()}")
    given.require()
    return given, given.smplx_npz.name


def models_for_reference(reference: str, folder: str | Path | None = None, *,
                         setting: str | Path | None = None) -> BodyModelFiles:
    """The files to pose an avatar whose package records body reference `reference` with
    (whether they are the very model it was bound to is the caller's fingerprint check)."""
    seed = synthetic_seed_of(reference, SYNTHETIC_REFERENCE)
    given = given_body_models(folder, setting=setting)
    if seed is not None:
        return _synthetic_or_given(seed, given)
    if given is None:
        raise BodyModelsMissing(f"the avatar is bound to body model {reference!r} and no "
                                f"body-model folder is set: {official_files_note()}")
    given.require()
    return given


def synthetic_body_models(folder: str | Path | None = None, seed: int = 0) -> BodyModelFiles:
    """The synthetic family of `seed` in `folder` (default: the user cache), written there
    first if missing or written by another generator version."""
    from .. import studio_entry  # lazy: the studio loads only when this is called (above)

    return studio_entry.synthetic_body_models(folder, seed=seed)
