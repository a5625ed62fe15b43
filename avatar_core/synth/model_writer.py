"""Write a synthetic body-model family in the official file formats.

No licensed SMPL-X, FLAME or MANO file can be fetched here, so this writes stand-ins for them
from the procedural humanoid (`synth.humanoid`), in the very formats the official releases use:

- `SMPLX_NEUTRAL.npz` and `SMPLX_NEUTRAL.pkl` (v1.1 layout: 10 shape + 10 expression columns;
  the .pkl stores `shapedirs` as a chumpy object and `J_regressor` as a sparse matrix, as
  official pickles do), and `smplx_vert_segmentation.json` (part name -> vertex indices).
- `FLAME_NEUTRAL.pkl` (300 shape + 100 expression columns), `flame_static_embedding.pkl`,
  `flame_dynamic_embedding.npy` and `SMPL-X__FLAME_vertex_ids.npy`.
- `MANO_RIGHT.pkl`, `MANO_LEFT.pkl` and `MANO_SMPLX_vertex_ids.pkl`.
- `identities/identity_<i>.npz`: betas, vertex colours and a name per identity.
- `gestures.npz`: right-hand finger poses by name (absolute axis-angle [15, 3]).

The siblings are cut from the SMPL-X-format model, so fusion can be tested exactly: the FLAME
expression basis is SMPL-X's, restricted to the head; joints, skinning weights and pose
correctives correspond. Vertices named in `smplx`'s hard-coded vertex ids (nose, eyes, ears,
fingertips, toes) are placed at those indices when the mesh has enough vertices.
Everything is deterministic from the seed.
"""

from __future__ import annotations

import json
import os
import pickle
import sys
import tempfile
import types
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import scipy.sparse

from ..body.model_paths import BodyModelFiles
from ..body.skeleton import (
    FLAME_PARENTS,
    FLAME_TO_SMPLX_JOINT,
    MANO_PARENTS,
    MANO_TO_SMPLX_JOINT,
    SMPLX_PARENTS,
    SMPLX_PART_NAMES,
)
from .humanoid import MATERIALS, Humanoid, make_humanoid
from .mesh_render import vertex_normals

# `smplx.vertex_ids.vertex_ids['smplx']`: vertices the smplx package reads as extra joints.
SMPLX_SEMANTIC_VERTEX_IDS = {
    "nose": 9120, "reye": 9929, "leye": 9448, "rear": 616, "lear": 6,
    "rthumb": 8079, "rindex": 7669, "rmiddle": 7794, "rring": 7905, "rpinky": 8022,
    "lthumb": 5361, "lindex": 4933, "lmiddle": 5058, "lring": 5169, "lpinky": 5286,
    "LBigToe": 5770, "LSmallToe": 5780, "LHeel": 8846, "RBigToe": 8463, "RSmallToe": 8474,
    "RHeel": 8635,
}  # fmt: skip
FLAME_SHAPE_COLUMNS, FLAME_EXPRESSION_COLUMNS = 300, 100
NUM_CONTOUR_ROWS = 79  # head-yaw bins of the face-contour look-up table
ROOT_PARENT = np.uint32(2**32 - 1)  # how official kintree tables mark the root
# Pose-corrective bulge at a bent joint, metres per unit of (3 - trace R).
CORRECTIVE_BULGE = 0.006
# Bumped whenever the written files change (2: gestures three, four, L, heart_half, cupped), so
# that caches written by an older generator are rewritten (`ensure_models`).
GENERATOR_VERSION = 2

PALETTES = (
    {"name": "ada", "skin": (0.87, 0.68, 0.56), "hair": (0.23, 0.14, 0.08),
     "iris": (0.25, 0.42, 0.62), "shirt": (0.20, 0.33, 0.55), "lips": (0.72, 0.40, 0.40),
     "trousers": (0.18, 0.18, 0.22)},
    {"name": "bo", "skin": (0.55, 0.38, 0.27), "hair": (0.06, 0.05, 0.05),
     "iris": (0.30, 0.20, 0.10), "shirt": (0.72, 0.28, 0.20), "lips": (0.50, 0.28, 0.26),
     "trousers": (0.30, 0.26, 0.20)},
    {"name": "cy", "skin": (0.95, 0.80, 0.70), "hair": (0.80, 0.62, 0.30),
     "iris": (0.35, 0.50, 0.30), "shirt": (0.25, 0.55, 0.35), "lips": (0.80, 0.48, 0.50),
     "trousers": (0.12, 0.14, 0.30)},
)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Official-format pickles


@contextmanager
def _chumpy_class() -> Iterator[type]:
    """A class that pickles as `chumpy.ch.Ch`, as official model pickles reference it."""
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch")}
    pkg, mod = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    ch_class = type("Ch", (), {"__module__": "chumpy.ch"})
    mod.Ch, pkg.ch = ch_class, mod
    sys.modules.update({"chumpy": pkg, "chumpy.ch": mod})
    try:
        yield ch_class
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


def _write_official_pickle(path: Path, data: dict, chumpy_keys: tuple[str, ...] = (),
                           sparse_keys: tuple[str, ...] = ()) -> None:
    with _chumpy_class() as ch_class:
        out = dict(data)
        for k in chumpy_keys:
            obj = ch_class.__new__(ch_class)
            obj.__dict__.update({"x": np.asarray(out[k], dtype=np.float64), "_dirty_vars": set(),
                                 "_itr": None, "_depends_on_deps": {}, "_make_dense": False,
                                 "_make_sparse": False})
            out[k] = obj
        for k in sparse_keys:
            out[k] = scipy.sparse.csc_matrix(out[k])
        with path.open("wb") as f:
            pickle.dump(out, f, protocol=2)


# ---------------------------------------------------------------------------------------------
# Model arrays


def _kintree(parents: tuple[int, ...]) -> np.ndarray:
    row0 = np.array([ROOT_PARENT if p < 0 else p for p in parents], dtype=np.uint32)
    return np.stack([row0, np.arange(len(parents), dtype=np.uint32)])


def _pose_correctives(h: Humanoid) -> np.ndarray:
    """Bulges along the normal where a bent joint blends into its parent. [V, 3, 9 * 54]."""
    v = len(h.vertices)
    normals = vertex_normals(h.vertices, h.faces)
    posedirs = np.zeros((v, 3, 9 * (len(SMPLX_PARENTS) - 1)))
    for j in range(1, len(SMPLX_PARENTS)):
        blend = h.skinning_weights[:, j] * h.skinning_weights[:, SMPLX_PARENTS[j]]  # [V]
        # Features (R - I) flattened; the diagonal sums to trace(R) - 3 = 2 (cos t - 1) <= 0.
        for diag in (0, 4, 8):
            posedirs[:, :, 9 * (j - 1) + diag] = -CORRECTIVE_BULGE * blend[:, None] * normals
    return posedirs


def _hand_pca(h: Humanoid, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Right-hand PCA components [45, 45] (rows) and the mean (relaxed) hand [45]."""
    mean = h.hand_poses["relaxed"].reshape(45)
    gestures = np.stack([p.reshape(45) for p in h.hand_poses.values()])  # [G, 45]
    mix = rng.dirichlet(np.full(len(gestures), 0.3), size=4000)  # [N, G]
    samples = mix @ gestures + rng.normal(0.0, 0.04, size=(4000, 45))
    _, _, vt = np.linalg.svd(samples - mean, full_matrices=False)
    return vt, mean


def mirror_hand_pose(pose: np.ndarray) -> np.ndarray:
    """Reflect axis-angle hand poses through x = 0: (x, y, z) -> (x, -y, -z). [..., 45]."""
    return (pose.reshape(*pose.shape[:-1], 15, 3) * np.array([1.0, -1.0, -1.0])).reshape(
        pose.shape)


def _vertex_order(h: Humanoid) -> np.ndarray:
    """Permutation putting smplx's named vertices at its hard-coded indices (when they fit)."""
    v = len(h.vertices)
    if v <= max(SMPLX_SEMANTIC_VERTEX_IDS.values()):
        return np.arange(v)
    order = np.full(v, -1, dtype=np.int64)
    placed = {}
    for name, new_idx in SMPLX_SEMANTIC_VERTEX_IDS.items():
        order[new_idx] = h.semantic_vertices[name]
        placed[h.semantic_vertices[name]] = new_idx
    rest = np.array([i for i in range(v) if i not in placed], dtype=np.int64)
    order[order < 0] = rest
    return order


def _region_faces(faces: np.ndarray, ids: np.ndarray, num_vertices: int) -> tuple[np.ndarray,
                                                                                  np.ndarray]:
    """Faces lying wholly in the vertex set `ids`, re-indexed; and their original indices."""
    remap = np.full(num_vertices, -1, dtype=np.int64)
    remap[ids] = np.arange(len(ids))
    inside = np.flatnonzero((remap[faces] >= 0).all(axis=1))
    return remap[faces[inside]], inside


def _local_basis(basis: np.ndarray) -> np.ndarray:
    """A region's part of a body shape basis, without its rigid translation. [V, 3, K]."""
    return basis - basis.mean(axis=0, keepdims=True)


def _sub_model(verts, faces, weights, regressor, posedirs, ids, joints, feature_joints):
    """Template, faces, weights, regressor and correctives of a vertex region for a sibling
    model whose joints are the SMPL-X `joints` (its root first)."""
    w = weights[ids][:, joints]
    lost = 1.0 - w.sum(axis=1)
    if np.abs(lost).max() > 1e-9:
        raise ValueError(f"region vertices are skinned to joints outside {list(joints)}")
    cols = [9 * (j - 1) + k for j in feature_joints for k in range(9)]
    rest = np.setdiff1d(np.arange(posedirs.shape[-1]), cols)
    if np.abs(posedirs[ids][:, :, rest]).max() > 0:
        raise ValueError("region vertices have pose correctives from joints the sibling lacks")
    sub_faces, face_idx = _region_faces(faces, ids, len(verts))
    return {"v_template": verts[ids], "f": sub_faces.astype(np.uint32), "weights": w,
            "J_regressor": regressor[list(joints)][:, ids], "posedirs": posedirs[ids][:, :, cols],
            "bs_style": "lbs", "bs_type": "lrotmin"}, face_idx


def _identity_colors(h: Humanoid, palette: dict, rng: np.random.Generator) -> np.ndarray:
    base = {"skin": palette["skin"], "hair": palette["hair"], "eyebrow": palette["hair"],
            "lips": palette["lips"], "eye_white": (0.93, 0.92, 0.90), "iris": palette["iris"],
            "pupil": (0.03, 0.03, 0.03), "mouth_interior": (0.35, 0.08, 0.10),
            "teeth": (0.92, 0.90, 0.84), "shirt": palette["shirt"],
            "trousers": palette["trousers"], "shoes": (0.10, 0.08, 0.07)}
    colors = np.array([base[m] for m in MATERIALS])[h.materials]  # [V, 3]
    # Low-frequency variation (skin blotches, cloth shading) so the surface is not flat.
    freq = rng.normal(0.0, 12.0, size=(3, 3))
    phase = rng.uniform(0, 2 * np.pi, size=3)
    wave = np.sin(h.vertices @ freq + phase).mean(axis=1, keepdims=True)  # [V, 1]
    return np.clip(colors * (1.0 + 0.06 * wave), 0.0, 1.0).astype(np.float32)


def _identity_betas(index: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 7919, index])
    betas = np.clip(rng.normal(0.0, 0.9, size=10), -2.0, 2.0)
    betas[index % 10] += 1.2 if index % 2 == 0 else -1.2  # identities differ for sure
    return betas


def write_synthetic_models(out_dir: str | Path, *, seed: int = 0, resolution: float = 1.0,
                           num_identities: int = 2) -> BodyModelFiles:
    """Generate and write the synthetic SMPL-X / FLAME / MANO family into `out_dir`."""
    if num_identities < 1:
        raise ValueError("num_identities must be at least 1")
    files = BodyModelFiles(Path(out_dir))
    files.root.mkdir(parents=True, exist_ok=True)
    (files.root / "identities").mkdir(exist_ok=True)
    h = make_humanoid(seed=seed, resolution=resolution)
    rng = np.random.default_rng([seed, 31337])

    order = _vertex_order(h)  # new index -> old index
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    v = len(order)
    verts = h.vertices[order]
    faces = inverse[h.faces]
    weights = h.skinning_weights[order]
    regressor = h.joint_regressor[:, order]
    posedirs = _pose_correctives(h)[order]
    shapedirs = np.concatenate([h.shape_basis, h.expression_basis], axis=2)[order]  # [V, 3, 20]
    flame_ids = np.flatnonzero(h.flame_region[order])
    hand_ids = {"right": np.flatnonzero(h.hand_region["right"][order])}
    mirror = inverse[h.mirror_index[order]]
    hand_ids["left"] = mirror[hand_ids["right"]]  # left vertex k mirrors right vertex k
    comps_r, mean_r = _hand_pca(h, rng)
    comps = {"right": comps_r, "left": mirror_hand_pose(comps_r)}
    means = {"right": mean_r, "left": mirror_hand_pose(mean_r)}
    contour_faces = np.repeat(h.contour_faces[None], NUM_CONTOUR_ROWS, axis=0)
    contour_bary = np.repeat(h.contour_bary[None], NUM_CONTOUR_ROWS, axis=0)

    smplx = {
        "v_template": verts, "f": faces.astype(np.int32), "shapedirs": shapedirs,
        "posedirs": posedirs, "J_regressor": regressor, "kintree_table": _kintree(SMPLX_PARENTS),
        "weights": weights, "hands_componentsl": comps["left"], "hands_componentsr": comps["right"],
        "hands_meanl": means["left"], "hands_meanr": means["right"],
        "lmk_faces_idx": h.landmark_faces.astype(np.int64), "lmk_bary_coords": h.landmark_bary,
        "dynamic_lmk_faces_idx": contour_faces.astype(np.int64),
        "dynamic_lmk_bary_coords": contour_bary,
    }
    np.savez(files.smplx_npz, **smplx)
    _write_official_pickle(files.smplx_pkl, smplx, chumpy_keys=("shapedirs",),
                           sparse_keys=("J_regressor",))
    labels = h.part_labels[order]
    segmentation = {name: np.flatnonzero(labels == i).tolist()
                    for i, name in enumerate(SMPLX_PART_NAMES) if (labels == i).any()}
    files.segmentation.write_text(json.dumps(segmentation))

    # FLAME sibling: the head region, FLAME's five joints, 300 shape + 100 expression columns.
    flame, flame_face_idx = _sub_model(verts, faces, weights, regressor, posedirs, flame_ids,
                                       FLAME_TO_SMPLX_JOINT, FLAME_TO_SMPLX_JOINT[1:])
    flame_dirs = np.zeros((len(flame_ids), 3, FLAME_SHAPE_COLUMNS + FLAME_EXPRESSION_COLUMNS))
    flame_dirs[..., :10] = _local_basis(h.shape_basis[order][flame_ids])
    flame_dirs[..., 300:310] = h.expression_basis[order][flame_ids]
    flame.update(shapedirs=flame_dirs, kintree_table=_kintree(FLAME_PARENTS))
    _write_official_pickle(files.flame_pkl, flame, chumpy_keys=("shapedirs",),
                           sparse_keys=("J_regressor",))
    face_lookup = np.full(len(faces), -1, dtype=np.int64)
    face_lookup[flame_face_idx] = np.arange(len(flame_face_idx))
    if (face_lookup[h.landmark_faces] < 0).any() or (face_lookup[h.contour_faces] < 0).any():
        raise ValueError("face landmarks must lie on faces inside the FLAME region")
    _write_official_pickle(files.flame_static_embedding, {
        "lmk_face_idx": face_lookup[h.landmark_faces].astype(np.uint32),
        "lmk_b_coords": h.landmark_bary})
    np.save(files.flame_dynamic_embedding, np.array({
        "lmk_face_idx": face_lookup[contour_faces].astype(np.uint32),
        "lmk_b_coords": contour_bary}, dtype=object), allow_pickle=True)
    np.save(files.flame_correspondence, flame_ids.astype(np.int64))

    # MANO siblings: each hand region, wrist + 15 finger joints, 10 shape columns.
    for side in ("right", "left"):
        ids = hand_ids[side]
        joints = MANO_TO_SMPLX_JOINT[side]
        mano, _ = _sub_model(verts, faces, weights, regressor, posedirs, ids, joints, joints[1:])
        mano.update(shapedirs=_local_basis(h.shape_basis[order][ids]),
                    kintree_table=_kintree(MANO_PARENTS), hands_components=comps[side],
                    hands_mean=means[side], J=regressor[list(joints)][:, ids] @ verts[ids])
        _write_official_pickle(files.mano_pkl(side), mano, chumpy_keys=("shapedirs",),
                               sparse_keys=("J_regressor",))
    _write_official_pickle(files.mano_correspondence, {"left_hand": hand_ids["left"],
                                                       "right_hand": hand_ids["right"]})

    for i in range(num_identities):
        palette = PALETTES[i % len(PALETTES)]
        colors = _identity_colors(h, palette, np.random.default_rng([seed, 4242, i]))
        np.savez(files.root / "identities" / f"identity_{i}.npz", name=np.array(palette["name"]),
                 betas=_identity_betas(i, seed), vertex_colors=colors[order])

    np.savez(files.gestures, **{k: np.asarray(p, dtype=np.float64).reshape(15, 3)
                                for k, p in h.hand_poses.items()})
    files.manifest.write_text(json.dumps({
        "generator": "telesplat.synth.model_files", "generator_version": GENERATOR_VERSION,
        "synthetic": True, "seed": seed,
        "resolution": resolution, "smplx_vertices": v, "smplx_faces": int(len(faces)),
        "flame_vertices": int(len(flame_ids)), "mano_vertices": int(len(hand_ids["right"])),
        "shape_names": list(h.shape_names), "expression_names": list(h.expression_names),
        "hand_poses": sorted(h.hand_poses), "identities": num_identities,
        "note": "Procedural stand-ins in the official formats; not the licensed models.",
    }, indent=2))
    return files


# ---------------------------------------------------------------------------------------------
# The cache of written families


def default_model_dir(seed: int = 0) -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "telesplat" / f"synthetic-seed{seed}"


def ensure_models(model_dir: Path | None = None, seed: int = 0) -> BodyModelFiles:
    """The synthetic model files in `model_dir`, written first if they are not there yet or
    were written by another generator version (an old cache lacks newer gestures)."""
    files = BodyModelFiles(model_dir or default_model_dir(seed))
    if generator_version(files) != GENERATOR_VERSION:
        _rewrite(files.root, seed)
    return files


def generator_version(files: BodyModelFiles) -> int | None:
    """The generator version a folder's manifest records; None without a readable manifest."""
    try:
        version = json.loads(files.manifest.read_text()).get("generator_version")
    except (OSError, ValueError, AttributeError):
        return None
    return version if isinstance(version, int) else None


def synthetic_family(num_identities: int, model_dir: Path | None = None) -> Path:
    """A synthetic family with at least `num_identities` identities (written once, under
    the default cache's folder: same seed, same topology as the served model; its first
    identities are the default family's, whose betas and colours depend on the index)."""
    root = model_dir or default_model_dir(0).parent / f"embedding-family-{num_identities}"
    if not (root / "identities" / f"identity_{num_identities - 1}.npz").is_file():
        write_synthetic_models(root, seed=0, num_identities=num_identities)
    return root


def _rewrite(root: Path, seed: int) -> None:
    """Write the family into a scratch folder inside `root`, then move each file into place
    (atomic per file, the manifest last): a process reading the cache meanwhile never sees a
    half-written file, and other files in `root` are left alone."""
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".writing-", dir=root) as scratch:
        write_synthetic_models(scratch, seed=seed)
        names = sorted(p.relative_to(scratch) for p in Path(scratch).rglob("*") if p.is_file())
        names.sort(key=lambda rel: rel.name == "manifest.json")  # stable: the manifest last
        for rel in names:
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(Path(scratch) / rel, root / rel)
