"""An avatar ready to animate: its package, the body model it is bound to and that model's files.

``load_avatar`` resolves an avatar spec (a package path, or ``synthetic[:IDENTITY]`` for an
untrained avatar on the synthetic model) for the render CLI, the evaluator and the server. The
body-model files come from ``avatar_core.body.model_paths.models_for_reference`` (the package's
body reference, then ``--body-models`` / ``$TELESPLAT_BODY_MODELS`` / the server setting), and the
package's fingerprint of the triangles it is bound to must match them.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..body.model_data import load_mano
from ..body.model_paths import (
    HOW_TO_GIVE,
    SYNTHETIC_REFERENCE,
    BodyModelFiles,
    models_for_reference,
)
from ..body.models import MANOModel
from ..body.upper_body import UpperBodyModel
from .animate import AvatarAnimator, synthetic_package
from .package import AvatarPackage, BodyReference, PackageError, faces_fingerprint, load_package

__all__ = ["BodyModelMismatch", "LoadedAvatar", "check_binding", "load_avatar", "mano_models",
           "upper_body_faces", "upper_body_model"]


class BodyModelMismatch(PackageError):
    """The avatar is bound to other body-model files than the ones it is loaded with.
    ``public``: the message without the folder, for a client of the server."""

    def __init__(self, message: str, *, public: str = "") -> None:
        super().__init__(message)
        self.public = public or message


@dataclass
class LoadedAvatar:
    package: AvatarPackage
    animator: AvatarAnimator
    files: BodyModelFiles


def load_avatar(spec: str, body_models: str | Path | None = None, *,
                setting: str | Path | None = None, **package_limits: Any) -> LoadedAvatar:
    """`synthetic[:IDENTITY]` for an untrained avatar on the synthetic model, or the path of a
    package. ``body_models``: the folder given explicitly (``--body-models``); ``setting``: the
    server's ``body_models``. ``package_limits``: ``max_bytes`` / ``npz_limits`` / ``ranges``
    for ``load_package``. BodyModelMismatch when the files are not the ones it was bound to."""
    if spec == "synthetic" or spec.startswith("synthetic:"):
        identity = int(spec.split(":", 1)[1]) if ":" in spec else 0
        files = models_for_reference(f"{SYNTHETIC_REFERENCE}0", body_models, setting=setting)
        package, model = synthetic_package(files.root, identity)
    else:
        package = load_package(spec, **package_limits)
        files = models_for_reference(package.body.model, body_models, setting=setting)
        model = UpperBodyModel.load(files.smplx_npz, files.segmentation)
        check_binding(package.body, files, model.faces.cpu().numpy(), spec)
    animator = AvatarAnimator(model, package.avatar, betas=np.asarray(package.body.betas))
    return LoadedAvatar(package, animator, files)


def check_binding(body: BodyReference, files: BodyModelFiles, faces: np.ndarray,
                  name: str = "the avatar") -> None:
    """BodyModelMismatch, naming both sides, unless ``faces`` [F, 3] (the upper body cut from
    ``files``) are the very triangles the package's Gaussians are bound to."""
    found = faces_fingerprint(faces)
    if len(faces) == body.num_faces and found == body.faces_sha256:
        return
    bound = (f"is bound to body model {body.model!r} ({body.num_faces} upper-body triangles, "
             f"fingerprint {body.faces_sha256[:16]})")
    given = f"give {len(faces)} triangles with fingerprint {found[:16]}"
    raise BodyModelMismatch(
        f"{name} {bound}, but the body models in use, {files.describe()} "
        f"({files.smplx_npz.name}), {given}: name the folder it was trained with "
        f"({HOW_TO_GIVE})",
        public=f"the avatar {bound}; this server's body models {given}")


def upper_body_faces(files: BodyModelFiles) -> np.ndarray:
    """[F, 3] triangles of the upper body cut from ``files``, cached while the files are
    unchanged (checking a package's binding need not load the model each time)."""
    files.require()
    stamp = tuple(p.stat().st_mtime_ns for p in (files.smplx_npz, files.segmentation))
    return _faces(str(files.root.resolve()), stamp)


@functools.lru_cache(maxsize=8)  # a server sees its folder and a synthetic family or two
def _faces(root: str, stamp: tuple[int, ...]) -> np.ndarray:
    faces = _model(root, stamp).faces.cpu().numpy().copy()
    faces.flags.writeable = False  # shared by every caller
    return faces


def upper_body_model(files: BodyModelFiles) -> UpperBodyModel:
    """The upper-body model of ``files``, cached while the files are unchanged and shared by
    every caller (read-only: pose it through an ``AvatarAnimator`` with a stage cache of its
    own). Checking an upload at its rest pose need not load the model each time (seconds for
    an SMPL-X-sized one)."""
    files.require()
    stamp = tuple(p.stat().st_mtime_ns for p in (files.smplx_npz, files.segmentation))
    return _model(str(files.root.resolve()), stamp)


@functools.lru_cache(maxsize=2)  # a server's folder and the synthetic family
def _model(root: str, stamp: tuple[int, ...]) -> UpperBodyModel:
    files = BodyModelFiles(Path(root))
    return UpperBodyModel.load(files.smplx_npz, files.segmentation)


def mano_models(loaded: LoadedAvatar) -> dict[str, MANOModel]:
    """The MANO models per side that exist beside the avatar's body model (same dtype), for
    fusing MANO hand parameters into SMPL-X."""
    dtype = loaded.animator.body_model.dtype
    out = {}
    for side in ("left", "right"):
        path = loaded.files.mano_pkl(side)
        if path.is_file():
            out[side] = MANOModel(load_mano(path), dtype=dtype)
    return out
