"""A body model's rig: what turns a pose description into that model's parameters."""

from __future__ import annotations

import json

import numpy as np

from ..body.model_paths import BodyModelFiles
from ..body.upper_body import UpperBodyModel
from .keyframes import Rig


def model_rig(files: BodyModelFiles, model: UpperBodyModel) -> Rig:
    """Expression names, gestures and hand means of a model, for pose descriptions. Only the
    synthetic family names its expressions and gestures (manifest, gestures.npz); official
    files have neither, so their rig poses joints and hands by value only."""
    names: tuple[str, ...] = ()
    if files.manifest.is_file():
        names = tuple(json.loads(files.manifest.read_text()).get("expression_names", ()))
    gestures = {}
    if files.gestures.is_file():
        with np.load(files.gestures) as g:
            gestures = {k: g[k] for k in g.files}
    means = {s: getattr(model, f"{s}_hand_mean").cpu().numpy() for s in ("left", "right")}
    return Rig(names, gestures, means, model.num_betas)
