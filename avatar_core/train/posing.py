"""The body the avatar is trained on: model files, per-frame parameters on the device,
fine-tuned deltas, posing, and the initial colour of each triangle.

The model files are resolved from the dataset's ``body_model.source`` by
``avatar_core.body.model_paths.models_for_source``: ``synthetic-seedN`` uses the synthetic
family of that seed; any other source needs a body-model folder (``--body-models DIR``,
``$TELESPLAT_BODY_MODELS`` or the server setting ``body_models``) with the official file names
(``SMPLX_NEUTRAL.npz``, ``smplx_vert_segmentation.json``, optionally ``MANO_{LEFT,RIGHT}.pkl``
for hand fusion and ``FLAME_NEUTRAL.pkl`` + ``SMPL-X__FLAME_vertex_ids.npy`` for a FLAME shape).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import sparse
from torch import Tensor

from ..body.fusion import FusionModels
from ..body.model_data import ModelData, load_flame, load_mano, load_smplx
from ..body.model_paths import BodyModelFiles, models_for_source
from ..body.models import FLAMEModel, MANOModel
from ..body.upper_body import UpperBodyModel, load_segmentation
from ..dataset.loader import View
from ..gaussians.binding import FaceFrames, bind_gaussians_torch
from ..render.types import GaussianSet

__all__ = ["BodySetup", "face_part_ids", "fine_tune_deltas",
           "frame_inputs", "fusion_models", "project_face_colors", "resolve_body",
           "world_gaussians"]

log = logging.getLogger(__name__)

FINE_TUNED = ("transl", "expression", "body_pose")


@dataclass
class BodySetup:
    files: BodyModelFiles               # official file names, whichever family
    reference: str                      # BodyReference.model: "synthetic:seed0" or a file name
    data: ModelData                     # the full SMPL-X model data
    segmentation: dict[str, np.ndarray]  # part name -> SMPL-X vertex ids
    model: UpperBodyModel               # on the training device, float32
    hand_pca: int | None
    flat_hand_mean: bool


def resolve_body(meta_body: Mapping[str, Any], body_model_dir: str | Path | None,
                 device: torch.device) -> BodySetup:
    """The upper-body model a dataset's parameters drive (see the module docstring)."""
    if meta_body.get("type", "smplx") != "smplx":
        raise ValueError(f"training needs SMPL-X parameters, the dataset has "
                         f"{meta_body.get('type')!r}")
    if meta_body.get("root", "smplx") != "smplx":
        raise ValueError(f"body_model.root {meta_body.get('root')!r}: training supports "
                         "'smplx' (rotation about the pelvis) only; re-import with the model")
    files, reference = models_for_source(str(meta_body.get("source", "")), body_model_dir)
    files.require()
    data = load_smplx(files.smplx_npz)
    seg = load_segmentation(files.segmentation, data.num_vertices)
    hand_pca = meta_body.get("hand_pca")
    flat = bool(meta_body.get("flat_hand_mean", False))
    model = UpperBodyModel(data, seg, hand_pca=hand_pca, flat_hand_mean=flat, device=device)
    return BodySetup(files, reference, data, seg, model, hand_pca, flat)


def fusion_models(body: BodySetup, *, flame_shape: bool = False) -> FusionModels:
    """float64 CPU models for fusing FLAME/MANO keys into SMPL-X (hands only with full
    hand poses, ``hand_pca`` null, and the MANO files present; FLAME itself only when a
    ``flame_shape`` is to be carried over)."""
    smplx = UpperBodyModel(body.data, body.segmentation, flat_hand_mean=body.flat_hand_mean,
                           dtype=torch.float64)
    mano: dict[str, MANOModel] = {}
    if body.hand_pca is not None:
        log.warning("fusion: PCA hand poses (hand_pca=%s) are kept; MANO keys are not fused",
                    body.hand_pca)
    else:
        for side in ("left", "right"):
            path = body.files.mano_pkl(side)
            if path.is_file():
                mano[side] = MANOModel(load_mano(path), dtype=torch.float64)
    flame = corr = None
    if flame_shape and body.files.flame_pkl.is_file() \
            and body.files.flame_correspondence.is_file():
        flame = FLAMEModel(load_flame(body.files.flame_pkl), dtype=torch.float64)
        corr = np.load(body.files.flame_correspondence)
    return FusionModels(smplx=smplx, mano=mano, flame=flame, correspondence=corr)


def fine_tune_deltas(num_frames: int, model: UpperBodyModel, device: torch.device
                     ) -> dict[str, Tensor]:
    """Zero per-frame deltas: transl [T, 3], expression [T, E], body_pose [T, 21, 3]."""
    shapes = {"transl": (3,), "expression": (model.num_expression,), "body_pose": (21, 3)}
    return {k: torch.zeros(num_frames, *shapes[k], device=device) for k in FINE_TUNED}


def frame_inputs(base: Mapping[str, Tensor], deltas: Mapping[str, Tensor] | None,
                 frame: int) -> dict[str, Tensor]:
    """Batch-1 parameters of one frame: the sequence's [T, ...] tensors at ``frame``, plus
    the fine-tuned deltas (differentiable) where given."""
    p = {k: v[frame:frame + 1] for k, v in base.items()}
    for k, d in (deltas or {}).items():
        p[k] = d[frame:frame + 1] if k not in p else p[k] + d[frame:frame + 1]
    return p


def face_part_ids(model: UpperBodyModel, segmentation: Mapping[str, np.ndarray],
                  part_names: Sequence[str]) -> np.ndarray:
    """[F] index into ``part_names`` of each triangle's part (its corners' majority; the
    first corner's on a three-way tie), -1 where the part is not among the names."""
    vertex_part = np.full(int(model.vertex_ids.max()) + 1, -1, np.int64)
    index = {n: i for i, n in enumerate(part_names)}
    for name, ids in segmentation.items():
        ids = ids[ids < len(vertex_part)]
        vertex_part[ids] = index.get(name, -1)
    corners = vertex_part[model.vertex_ids][model.faces.cpu().numpy()]  # [F, 3]
    a, b, c = corners.T
    return np.where((b == c) & (a != b), b, a)


def project_face_colors(vertices: np.ndarray, faces: np.ndarray, face_parts: np.ndarray,
                        views: Sequence[View], min_alpha: float = 0.9) -> np.ndarray:
    """[F, 3] colour of each triangle sampled at its projected centroid, averaged over the
    views where the triangle faces the camera, the pixel is solid foreground and (with part
    labels) shows the triangle's part, a cheap stand-in for a depth test; NaN where no view
    passes. ``vertices`` [V, 3] posed at the views' frame."""
    tri = vertices[faces]  # [F, 3, 3]
    centroid = tri.mean(1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # outward (CCW)
    total = np.zeros((len(faces), 3))
    count = np.zeros(len(faces))
    for view in views:
        cam = view.camera
        uv, z = cam.project(centroid)
        facing = np.einsum("fi,fi->f", normal, cam.center - centroid) > 0
        px = np.floor(uv).astype(np.int64)
        inside = facing & (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < cam.width) \
            & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        f = np.flatnonzero(inside)
        x, y = px[f, 0], px[f, 1]
        ok = np.ones(len(f), bool)
        if view.alpha is not None:
            ok &= view.alpha[y, x] >= min_alpha
        if view.parts is not None:
            ok &= view.parts[y, x] == face_parts[f]
        f, x, y = f[ok], x[ok], y[ok]
        total[f] += view.rgb[y, x]
        count[f] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return total / count[:, None]


def fill_unseen_colors(colors: np.ndarray, faces: np.ndarray, face_parts: np.ndarray,
                       max_rings: int = 64) -> np.ndarray:
    """[F, 3] ``colors`` with the NaN rows (triangles no view saw) filled, ring by ring, with
    the mean of their already coloured neighbours (sharing a vertex) of the same part; rows
    still unreached after ``max_rings`` stay NaN. Unseen triangles (an armpit the training
    views never look into) otherwise keep a flat grey that no gradient ever corrects."""
    out = np.array(colors, dtype=np.float64)
    known = np.isfinite(out).all(1)
    n_faces, n_verts = len(faces), int(faces.max()) + 1
    incidence = sparse.csr_matrix((np.ones(faces.size), (np.repeat(np.arange(n_faces), 3),
                                                          faces.reshape(-1))),
                                  shape=(n_faces, n_verts))
    adjacency = (incidence @ incidence.T).tocsr()  # faces sharing a vertex
    same = face_parts[adjacency.nonzero()[0]] == face_parts[adjacency.nonzero()[1]]
    rows, cols = adjacency.nonzero()
    adjacency = sparse.csr_matrix((same.astype(np.float64), (rows, cols)),
                                  shape=(n_faces, n_faces))
    for _ in range(max_rings):
        todo = ~known
        if not todo.any():
            break
        weights = adjacency[todo][:, known]
        count = np.asarray(weights.sum(1)).ravel()
        reached = count > 0
        if not reached.any():
            break
        mean = (weights @ out[known]) / np.maximum(count, 1)[:, None]
        idx = np.flatnonzero(todo)[reached]
        out[idx] = mean[reached]
        known[idx] = True
    return out


# -- world Gaussians ----------------------------------------------------------------------


def world_gaussians(state: Mapping[str, Tensor], frames: FaceFrames,
                    sh_degree: int | None = None) -> GaussianSet:
    """World-space Gaussians of a training state (``avatar_state``'s leaves), bound by the
    differentiable :func:`avatar_core.gaussians.binding.bind_gaussians_torch`, with only the SH
    bands up to ``sh_degree`` (None: all) so the unused ones cost nothing."""
    means, quats, scales = bind_gaussians_torch(frames, state["parents"], state["local_means"],
                                                state["quats"], torch.exp(state["log_scales"]))
    rest = state["sh_rest"]
    if sh_degree is not None:
        rest = rest[:, :(sh_degree + 1) ** 2 - 1]
    sh = torch.cat([state["sh0"], rest], 1) if rest.shape[1] else state["sh0"]
    return GaussianSet(means=means, quats=quats, scales=scales,
                       opacities=torch.sigmoid(state["opacity_logits"]), sh=sh)
