"""Motion files: per-frame SMPL-X parameters from a .json / .npz file or a built-in clip.

Read by the render CLI (``telesplat render --motion``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..body.model_paths import BodyModelFiles
from ..body.rest_pose import rest_body_pose
from ..body.upper_body import UpperBodyModel
from .library import ALIASES, MOTIONS, demo_clip, motion, unknown_clip_message
from .rig import model_rig

__all__ = ["motion_frames"]


def motion_frames(spec: str, files: BodyModelFiles, model: UpperBodyModel, fps: float,
                  frames: int | None = None) -> list[dict[str, np.ndarray]]:
    """Per-frame SMPL-X parameters: a built-in clip name ('demo', 'rest' or a library clip:
    ``library.clip_names()``), a .json list of
    per-frame dicts, or an .npz of arrays with a leading frame axis. ``files`` and ``model``
    (the avatar's body model) rig the built-in clip."""
    if spec == "rest":  # the live rest pose (body/rest_pose.py), not the T-pose
        return [{"body_pose": rest_body_pose()} for _ in range(frames or 1)]
    if spec == "demo" or spec in MOTIONS or spec in ALIASES:
        clip = demo_clip() if spec == "demo" else motion(spec)
        rig = model_rig(files, model)
        n = frames or max(1, int(round(clip.duration * fps)))
        out = []
        for i in range(n):
            try:
                p = clip.sample(clip.duration * i / max(n - 1, 1), rig)
            except KeyError as exc:  # official model files name no expressions or gestures
                raise ValueError(f"the {spec!r} clip names what the body model in {files.root} "
                                 f"does not ({exc.args[0]}): use --motion rest or a "
                                 "parameter file") from None
            p.pop("betas")
            out.append(p)
        return out
    path = Path(spec)
    if not path.is_file():
        raise ValueError(unknown_clip_message(spec))
    if path.suffix == ".json":
        data = json.loads(path.read_text())
        if not isinstance(data, list) or not all(isinstance(d, dict) for d in data):
            raise ValueError(f"{path}: expected a JSON list of per-frame parameter objects")
        seq = [{k: np.asarray(v, dtype=np.float64) for k, v in d.items()} for d in data]
    elif path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        lengths = {len(v) for v in arrays.values()}
        if len(lengths) != 1:
            raise ValueError(f"{path}: arrays disagree on the number of frames: {lengths}")
        seq = [{k: v[i] for k, v in arrays.items()} for i in range(lengths.pop())]
    else:
        raise ValueError(f"{path}: motion files are .json or .npz")
    return seq[:frames] if frames else seq
