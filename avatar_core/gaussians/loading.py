"""An avatar ready to animate: its package, the body model it is bound to and that model's files.

``load_avatar`` resolves an avatar spec (a package path, or ``synthetic[:IDENTITY]`` for an
untrained avatar on the synthetic model) for the render CLI, the evaluator and the server.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..body.model_data import load_mano
from ..body.model_paths import BodyModelFiles, synthetic_body_models
from ..body.models import MANOModel
from .animate import AvatarAnimator, synthetic_package
from .package import AvatarPackage, load_package

__all__ = ["LoadedAvatar", "load_avatar", "mano_models"]


@dataclass
class LoadedAvatar:
    package: AvatarPackage
    animator: AvatarAnimator
    files: BodyModelFiles


def load_avatar(spec: str, model_dir: Path | None = None, **package_limits: Any
                ) -> LoadedAvatar:
    """`synthetic[:IDENTITY]` for an untrained avatar on the synthetic model, or the path of a
    package bound to the synthetic model (its body reference says which seed).
    ``package_limits``: ``max_bytes`` / ``npz_limits`` for ``load_package``."""
    if spec == "synthetic" or spec.startswith("synthetic:"):
        identity = int(spec.split(":", 1)[1]) if ":" in spec else 0
        files = synthetic_body_models(model_dir)
        package, model = synthetic_package(files.root, identity)
    else:
        package = load_package(spec, **package_limits)
        ref = package.body.model
        if not ref.startswith("synthetic:seed"):
            raise ValueError(f"{spec}: bound to body model {ref!r}; only synthetic models can be "
                             "resolved here (the licensed SMPL-X files are not available)")
        files = synthetic_body_models(model_dir, seed=int(ref.removeprefix("synthetic:seed")))
        _, model = synthetic_package(files.root, 0)
        package.body.check_faces(model.faces.cpu().numpy())
    animator = AvatarAnimator(model, package.avatar, betas=np.asarray(package.body.betas))
    return LoadedAvatar(package, animator, files)


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
