"""Body-model data in one form for all three families, and the loaders of the official files.

Conventions honoured (as in the official files and the `smplx` package):
- `shapedirs` [V, 3, K] holds shape and expression columns together. SMPL-X: fewer than 400
  columns means 10 shape + 10 expression (v1.1), else 300 shape + 100 expression (2020).
  FLAME: columns [0, 300) are shape, [300, 400) expression.
- `posedirs` [V, 3, 9 (J - 1)] are stored as [9 (J - 1), V * 3] for a single matmul.
- `kintree_table[0]` lists parents (the root's is -1 or 2**32 - 1).
- Hands: `hands_components*` [45, 45] PCA rows and `hands_mean*` [45] (the relaxed hand);
  a model with `flat_hand_mean=False` adds the mean, so a zero pose is the relaxed hand.
Joint positions are kept as blend shapes of their own (`joint_template + joint_shapedirs
@ betas`), exactly equal to regressing them from the full mesh, so a vertex subset (the
upper-body cut) still has the joints of the full model.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ModelFileError
from .model_reader import read_model_file, require, to_array

FLAME_SHAPE_SPACE = 300
SMPLX_SHAPE_SPACE, SMPLX_EXPRESSION_SPACE = 300, 100


@dataclass(frozen=True)
class ModelData:
    family: str                      # "smplx" | "flame" | "mano"
    v_template: np.ndarray           # [V, 3]
    faces: np.ndarray                # [F, 3] int64
    shapedirs: np.ndarray            # [V, 3, S]
    exprdirs: np.ndarray             # [V, 3, E] (E may be 0)
    posedirs: np.ndarray             # [P, V * 3]
    joint_regressor: np.ndarray      # [J, V]
    parents: tuple[int, ...]         # [J]
    weights: np.ndarray              # [V, J]
    joint_template: np.ndarray       # [J, 3]
    joint_shapedirs: np.ndarray      # [J, 3, S]
    joint_exprdirs: np.ndarray       # [J, 3, E]
    hand_components: dict[str, np.ndarray] = field(default_factory=dict)  # side -> [45, 45]
    hand_mean: dict[str, np.ndarray] = field(default_factory=dict)        # side -> [45]
    lmk_faces: np.ndarray | None = None        # [L] static landmarks
    lmk_bary: np.ndarray | None = None         # [L, 3]
    dynamic_lmk_faces: np.ndarray | None = None  # [79, 17] face-contour look-up by head yaw
    dynamic_lmk_bary: np.ndarray | None = None   # [79, 17, 3]
    vertex_ids: np.ndarray | None = None  # [V] indices into the source model (after a subset)
    source: str = ""

    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def num_joints(self) -> int:
        return len(self.parents)

    def subset(self, keep: np.ndarray) -> ModelData:
        """The model restricted to the vertices `keep` (bool [V] or indices); faces re-indexed.

        Faces with a removed corner are dropped. Joints are unchanged (their blend shapes were
        computed on the full mesh); the regressor keeps only the kept columns.
        """
        keep_idx = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep)
        keep_idx = np.unique(keep_idx.astype(np.int64))
        remap = np.full(self.num_vertices, -1, dtype=np.int64)
        remap[keep_idx] = np.arange(len(keep_idx))
        face_kept = (remap[self.faces] >= 0).all(axis=1)
        face_remap = np.full(len(self.faces), -1, dtype=np.int64)
        face_remap[face_kept] = np.arange(int(face_kept.sum()))

        def faces_of(idx: np.ndarray | None) -> np.ndarray | None:
            if idx is None:
                return None
            new = face_remap[idx]
            if (new < 0).any():
                raise ModelFileError("a landmark lies on a face that the subset removes")
            return new

        v = self.num_vertices
        # np.take gives a C-ordered [P, K, 3] (a fancy index here does not, and the reshape
        # then copies it again): 6x faster on the 130 MB of SMPL-X correctives
        posedirs = np.take(self.posedirs.reshape(-1, v, 3), keep_idx, axis=1).reshape(
            len(self.posedirs), -1)
        base_ids = self.vertex_ids if self.vertex_ids is not None else np.arange(v)
        return dataclasses.replace(
            self,
            v_template=self.v_template[keep_idx], faces=remap[self.faces[face_kept]],
            shapedirs=self.shapedirs[keep_idx], exprdirs=self.exprdirs[keep_idx],
            posedirs=posedirs, joint_regressor=self.joint_regressor[:, keep_idx],
            weights=self.weights[keep_idx],
            lmk_faces=faces_of(self.lmk_faces), dynamic_lmk_faces=faces_of(self.dynamic_lmk_faces),
            vertex_ids=base_ids[keep_idx],
        )


def _parents(kintree: np.ndarray) -> tuple[int, ...]:
    raw = kintree[0].astype(np.int64)
    parents = tuple(-1 if (i == 0 or p < 0 or p >= 2**31) else int(p) for i, p in enumerate(raw))
    for j, p in enumerate(parents[1:], start=1):
        if not 0 <= p < j:
            raise ModelFileError(f"kintree_table: joint {j} has parent {p}, which is not before it")
    return parents


def _build(family: str, data: dict, path: Path, *, shape_cols: slice, expr_cols: slice,
           hand_components: dict | None = None, hand_mean: dict | None = None,
           lmk: tuple | None = None, dynamic_lmk: tuple | None = None) -> ModelData:
    v_template = require(data, "v_template", path, shape=(None, 3)).astype(np.float64)
    v = v_template.shape[0]
    faces = require(data, "f", path, shape=(None, 3)).astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= v):
        raise ModelFileError(f"{path}: 'f' indexes vertices outside [0, {v})")
    kintree = require(data, "kintree_table", path, shape=(2, None))
    parents = _parents(kintree)
    j = len(parents)
    shapedirs_all = require(data, "shapedirs", path, shape=(v, 3, None)).astype(np.float64)
    posedirs = require(data, "posedirs", path, shape=(v, 3, 9 * (j - 1))).astype(np.float64)
    regressor = require(data, "J_regressor", path, shape=(j, v)).astype(np.float64)
    weights = require(data, "weights", path, shape=(v, j)).astype(np.float64)
    for name, arr in (("v_template", v_template), ("shapedirs", shapedirs_all),
                      ("posedirs", posedirs), ("J_regressor", regressor), ("weights", weights)):
        if not np.isfinite(arr).all():
            raise ModelFileError(f"{path}: '{name}' contains NaN or Inf")
    shapedirs, exprdirs = shapedirs_all[..., shape_cols], shapedirs_all[..., expr_cols]
    return ModelData(
        family=family, v_template=v_template, faces=faces, shapedirs=shapedirs,
        exprdirs=exprdirs, posedirs=posedirs.reshape(v * 3, -1).T.copy(),
        joint_regressor=regressor, parents=parents, weights=weights,
        joint_template=regressor @ v_template,
        joint_shapedirs=np.einsum("jv,vck->jck", regressor, shapedirs),
        joint_exprdirs=np.einsum("jv,vck->jck", regressor, exprdirs),
        hand_components=hand_components or {}, hand_mean=hand_mean or {},
        lmk_faces=None if lmk is None else lmk[0], lmk_bary=None if lmk is None else lmk[1],
        dynamic_lmk_faces=None if dynamic_lmk is None else dynamic_lmk[0],
        dynamic_lmk_bary=None if dynamic_lmk is None else dynamic_lmk[1],
        source=str(path),
    )


def _hands(data: dict, path: Path, suffixes: dict[str, str]) -> tuple[dict, dict]:
    comps, means = {}, {}
    for side, suffix in suffixes.items():
        comps[side] = require(data, f"hands_components{suffix}", path, shape=(None, 45))
        means[side] = require(data, f"hands_mean{suffix}", path, shape=(45,)).astype(np.float64)
    return comps, means


def _landmarks(data: dict, path: Path, faces_key: str, bary_key: str, n_faces: int,
               lead: tuple[int | None, ...] = (None,)) -> tuple[np.ndarray, np.ndarray]:
    idx = require(data, faces_key, path, shape=lead).astype(np.int64)
    bary = require(data, bary_key, path, shape=(*idx.shape, 3)).astype(np.float64)
    if idx.size and (idx.min() < 0 or idx.max() >= n_faces):
        raise ModelFileError(f"{path}: '{faces_key}' indexes faces outside [0, {n_faces})")
    return idx, bary


def load_smplx(path: str | Path, *, num_betas: int = 10, num_expression: int = 10) -> ModelData:
    """An SMPL-X model file (.npz or .pkl), e.g. SMPLX_NEUTRAL.npz."""
    path = Path(path)
    data = read_model_file(path)
    cols = require(data, "shapedirs", path, ndim=3).shape[-1]
    if cols < SMPLX_SHAPE_SPACE + SMPLX_EXPRESSION_SPACE:  # v1.1 layout: 10 + 10
        shape_cols = slice(0, min(num_betas, 10))
        expr_cols = slice(10, 10 + min(num_expression, max(cols - 10, 0)))
    else:
        shape_cols = slice(0, min(num_betas, SMPLX_SHAPE_SPACE))
        expr_cols = slice(SMPLX_SHAPE_SPACE, SMPLX_SHAPE_SPACE + min(num_expression, 100))
    comps, means = _hands(data, path, {"left": "l", "right": "r"})
    n_faces = require(data, "f", path, ndim=2).shape[0]
    lmk = _landmarks(data, path, "lmk_faces_idx", "lmk_bary_coords", n_faces)
    dyn = None
    if "dynamic_lmk_faces_idx" in data and "dynamic_lmk_bary_coords" in data:
        dyn = _landmarks(data, path, "dynamic_lmk_faces_idx", "dynamic_lmk_bary_coords",
                         n_faces, lead=(None, None))
    model = _build("smplx", data, path, shape_cols=shape_cols, expr_cols=expr_cols,
                   hand_components=comps, hand_mean=means, lmk=lmk, dynamic_lmk=dyn)
    if model.num_joints != 55:
        raise ModelFileError(f"{path}: an SMPL-X model has 55 joints, got {model.num_joints}")
    return model


def load_flame(path: str | Path, *, static_landmarks: str | Path | None = None,
               dynamic_landmarks: str | Path | None = None, num_shape: int = 300,
               num_expression: int = 100) -> ModelData:
    """A FLAME model pickle (generic_model.pkl / flame2023.pkl), optionally with its landmark
    embeddings: `flame_static_embedding.pkl` (lmk_face_idx, lmk_b_coords), or DECA's
    `landmark_embedding.npy` (static_lmk_faces_idx, ...), and `flame_dynamic_embedding.npy`."""
    path = Path(path)
    data = read_model_file(path)
    cols = require(data, "shapedirs", path, ndim=3).shape[-1]
    shape_cols = slice(0, min(num_shape, FLAME_SHAPE_SPACE, cols))
    expr_cols = slice(FLAME_SHAPE_SPACE, FLAME_SHAPE_SPACE + min(num_expression,
                                                                 max(cols - FLAME_SHAPE_SPACE, 0)))
    n_faces = require(data, "f", path, ndim=2).shape[0]
    lmk = dyn = None
    if static_landmarks is not None:
        lpath = Path(static_landmarks)
        emb = read_model_file(lpath)
        if "static_lmk_faces_idx" in emb:  # DECA's combined landmark_embedding.npy
            lmk = _landmarks(emb, lpath, "static_lmk_faces_idx", "static_lmk_bary_coords", n_faces)
            if "dynamic_lmk_faces_idx" in emb:
                dyn = _landmarks(emb, lpath, "dynamic_lmk_faces_idx", "dynamic_lmk_bary_coords",
                                 n_faces, lead=(None, None))
        else:
            lmk = _landmarks(emb, lpath, "lmk_face_idx", "lmk_b_coords", n_faces)
    if dynamic_landmarks is not None:
        dpath = Path(dynamic_landmarks)
        dyn = _landmarks(read_model_file(dpath), dpath, "lmk_face_idx", "lmk_b_coords", n_faces,
                         lead=(None, None))
    model = _build("flame", data, path, shape_cols=shape_cols, expr_cols=expr_cols, lmk=lmk,
                   dynamic_lmk=dyn)
    if model.num_joints != 5:
        raise ModelFileError(f"{path}: a FLAME model has 5 joints, got {model.num_joints}")
    return model


def load_mano(path: str | Path, *, side: str | None = None) -> ModelData:
    """A MANO model pickle (MANO_RIGHT.pkl / MANO_LEFT.pkl). The side comes from the file name
    unless given; the files themselves do not record it."""
    path = Path(path)
    if side is None:
        name = path.name.upper()
        side = "left" if "LEFT" in name else "right" if "RIGHT" in name else None
        if side is None:
            raise ModelFileError(f"{path}: cannot tell the hand from the file name; pass side=")
    if side not in ("left", "right"):
        raise ModelFileError(f"side must be 'left' or 'right', got {side!r}")
    data = read_model_file(path)
    comps, means = _hands(data, path, {side: ""})
    model = _build("mano", data, path, shape_cols=slice(0, 10), expr_cols=slice(0, 0),
                   hand_components=comps, hand_mean=means)
    if model.num_joints != 16:
        raise ModelFileError(f"{path}: a MANO model has 16 joints, got {model.num_joints}")
    return model


def load_correspondence(path: str | Path) -> dict[str, np.ndarray]:
    """Vertex correspondences into SMPL-X: `SMPL-X__FLAME_vertex_ids.npy` ([5023] for real FLAME)
    -> {"flame": ids}; `MANO_SMPLX_vertex_ids.pkl` -> {"left_hand": ids, "right_hand": ids}."""
    path = Path(path)
    if path.suffix == ".npy":
        ids = np.load(path, allow_pickle=False)
        return {"flame": ids.astype(np.int64)}
    data = read_model_file(path)
    return {k: to_array(v, k, path).astype(np.int64) for k, v in data.items()}
