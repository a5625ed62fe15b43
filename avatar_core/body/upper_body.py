"""The upper-body model: SMPL-X cut to the torso, neck, head, arms and hands.

Vertices are selected by the part labels of the SMPL-X vertex segmentation
(`smplx_vert_segmentation.json`: part name -> vertex indices). Faces with a removed corner are
dropped and the rest re-indexed; seam vertices left without a face are dropped too. The model
keeps all 55 SMPL-X joints at the positions the full model gives them, so it takes exactly the
SMPL-X parameters and poses the kept vertices exactly as the full model does.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ModelFileError
from .model_data import ModelData, load_smplx
from .models import SMPLXModel
from .skeleton import UPPER_BODY_PARTS


def load_segmentation(path: str | Path, num_vertices: int | None = None) -> dict[str, np.ndarray]:
    """Part name -> vertex indices, validated."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"{path}: cannot read the vertex segmentation: {exc}") from exc
    if not isinstance(raw, dict) or not raw:
        raise ModelFileError(f"{path}: expected a JSON object of part name -> vertex indices")
    parts = {}
    for name, ids in raw.items():
        arr = np.asarray(ids)
        if arr.ndim != 1 or (arr.size and not np.issubdtype(arr.dtype, np.integer)):
            raise ModelFileError(f"{path}: part '{name}' must be a list of vertex indices")
        arr = arr.astype(np.int64)
        if arr.size and (arr.min() < 0 or (num_vertices is not None and arr.max() >= num_vertices)):
            raise ModelFileError(f"{path}: part '{name}' has vertex indices outside the model")
        parts[name] = arr
    return parts


def select_vertices(segmentation: dict[str, np.ndarray],
                    keep_parts: tuple[str, ...] = UPPER_BODY_PARTS) -> np.ndarray:
    """Sorted indices of the vertices in any of `keep_parts`."""
    missing = [p for p in keep_parts if p not in segmentation]
    if len(missing) == len(keep_parts):
        raise ModelFileError(f"none of the parts {list(keep_parts)} is in the segmentation, "
                             f"which has {sorted(segmentation)}")
    chosen = [segmentation[p] for p in keep_parts if p in segmentation]
    return np.unique(np.concatenate(chosen))


class UpperBodyModel(SMPLXModel):
    """SMPL-X restricted to the upper body. `vertex_ids` maps its vertices to SMPL-X's."""

    family = "SMPL-X upper body"

    def __init__(self, smplx_data: ModelData, segmentation: dict[str, np.ndarray], *,
                 keep_parts: tuple[str, ...] = UPPER_BODY_PARTS, **kwargs: Any) -> None:
        if smplx_data.family != "smplx":
            raise ModelFileError(f"the upper-body model cuts an SMPL-X model, got "
                                 f"{smplx_data.family}")
        keep = select_vertices(segmentation, keep_parts)
        if keep.max() >= smplx_data.num_vertices:
            raise ModelFileError("the segmentation indexes vertices outside the SMPL-X model")
        # Vertices on the seam whose every face is cut would be orphans: drop them too.
        inside = np.zeros(smplx_data.num_vertices, dtype=bool)
        inside[keep] = True
        kept_faces = smplx_data.faces[inside[smplx_data.faces].all(axis=1)]
        keep = np.unique(kept_faces)
        super().__init__(smplx_data.subset(keep), **kwargs)
        self.keep_parts = keep_parts

    @property
    def vertex_ids(self) -> np.ndarray:
        return self.data.vertex_ids

    @classmethod
    def load(cls, model_path: str | Path, segmentation_path: str | Path,
             **kwargs: Any) -> UpperBodyModel:
        data = load_smplx(model_path, **{k: kwargs.pop(k) for k in ("num_betas", "num_expression")
                                         if k in kwargs})
        return cls(data, load_segmentation(segmentation_path, data.num_vertices), **kwargs)
