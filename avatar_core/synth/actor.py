"""The textured synthetic actor that the software capture studio films.

An `Actor` is one identity of the synthetic SMPL-X family (its betas and palette) with
everything needed to render ground-truth images of it:

- the full SMPL-X model (legs included: a real camera sees them; the part mask lets trainers
  drop them), faces and a part label per face (index into `SMPLX_PART_NAMES`);
- accessories the parametric mesh lacks, bound to body triangles (`accessories`): a hair
  volume over the scalp and a shirt collar round the neck, labelled with the part of the
  triangle they are bound to (head, neck);
- a procedural solid-texture appearance evaluated at canonical positions (`appearance`).

`pose(params)` runs once per frame and gives a `PosedActor` (world vertices and normals);
`render(posed, camera)` runs once per camera: z-buffer at `supersample` times the resolution
(`render_mesh` face ids and barycentrics), textures and world-fixed lighting on the covered
samples, then a box filter to the image. `alpha` is the covered fraction of each pixel and
`rgb` is exactly the object colour composited over the background with it; `parts` is the
majority part of the covered samples (ties: the one closest to the pixel centre, then
row-major), -1 exactly where alpha is 0. Rendering keeps no state: several cameras may render
one posed frame in threads. Same identity, parameters and camera: bit-identical images.
"""

from __future__ import annotations

import functools
import json
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from ..body.joint_limits import RELAXED_ARMS
from ..body.model_data import load_smplx
from ..body.model_paths import BodyModelFiles
from ..body.models import SMPLXModel
from ..body.skeleton import JOINT, SMPLX_NUM_BODY_JOINTS, SMPLX_PART_NAMES
from ..body.upper_body import load_segmentation
from ..render.camera import Camera, orbit
from . import appearance as app
from .accessories import (
    HAIR_STYLES,
    Binding,
    HairStyle,
    bind_points,
    collar,
    concat_bindings,
    hair_shell,
    mesh_adjacency,
    place_bound,
    smooth_vertex_field,
)
from .humanoid import MATERIALS, make_humanoid
from .mesh_render import numba_available, render_mesh, vertex_normals
from .model_writer import PALETTES, _vertex_order

__all__ = ["Actor", "ActorView", "PosedActor", "render_actor_preview"]

_TORSO_PARTS = ("spine1", "spine2", "leftShoulder", "rightShoulder")
# The head surface has slits (mouth, eyes) through which its inside can be seen, and grazing
# rays can slip under the hair shell's edge: never cull those. Every other body piece and the
# collar are closed and outward-oriented.
_OPEN_PARTS = ("head", "leftEye", "rightEye")


@dataclass(frozen=True)
class ActorView:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1]
    alpha: np.ndarray  # [H, W] float32 coverage in [0, 1]
    parts: np.ndarray  # [H, W] int16 index into SMPLX_PART_NAMES, -1 for background


@dataclass(frozen=True)
class PosedActor:
    vertices: np.ndarray  # [V + A, 3] float64 world: body then accessories
    normals: np.ndarray  # [V + A, 3] float32 unit smooth normals (world)
    joints: np.ndarray  # [55, 3] float64 posed SMPL-X joints
    num_body_vertices: int

    @property
    def body_vertices(self) -> np.ndarray:
        return self.vertices[: self.num_body_vertices]

    @property
    def accessory_vertices(self) -> np.ndarray:
        return self.vertices[self.num_body_vertices:]


@dataclass(frozen=True, eq=False)
class Actor:
    name: str
    identity: int
    betas: np.ndarray  # [10]
    model: SMPLXModel  # the full SMPL-X model (float64)
    faces: np.ndarray  # [F + Fa, 3] int64: body faces, then accessory faces (offset by V)
    face_parts: np.ndarray  # [F + Fa] int16 index into SMPLX_PART_NAMES
    num_body_faces: int
    binding: Binding  # accessory vertices on body triangles
    hair_vertices: np.ndarray  # [A] bool: accessory vertex belongs to the hair
    canonical: np.ndarray  # [V + A, 3] float32 rest-pose positions (texture coordinates)
    group_weights: np.ndarray  # [V + A, len(GROUPS)] float32 texture-group weights
    face_groups: np.ndarray  # [F + Fa] int8: the face's only texture group, -1 if it blends
    closed: np.ndarray  # [F + Fa] bool: face of a closed surface (back faces may be culled)
    appearance: app.Appearance
    rest_joints: np.ndarray  # [55, 3] float64 joints at rest with the identity's betas
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    @property
    def num_body_vertices(self) -> int:
        return self.model.num_vertices

    @classmethod
    def load(cls, files: BodyModelFiles, identity: int) -> Actor:
        """Identity `identity` of a written synthetic model family."""
        paths = files.identities()
        if not 0 <= identity < len(paths):
            raise ValueError(f"identity must be in [0, {len(paths)}), got {identity}")
        with np.load(paths[identity]) as ident:
            name, betas = str(ident["name"]), np.asarray(ident["betas"], dtype=np.float64)
        palette = next((p for p in PALETTES if p["name"] == name),
                       PALETTES[identity % len(PALETTES)])
        data = load_smplx(files.smplx_npz)
        model = SMPLXModel(data, dtype=torch.float64)
        materials = _materials(files, data.v_template)
        faces = np.asarray(data.faces, dtype=np.int64)
        face_parts = _face_parts(_vertex_parts(files, data.num_vertices), faces)
        with torch.no_grad():
            rest_out = model({"betas": betas})
        rest, joints = rest_out.vertices[0].numpy(), rest_out.joints[0].numpy()
        seed = int(json.loads(files.manifest.read_text()).get("seed", 0)) * 1000 + identity
        acc = _accessories(rest, faces, materials, face_parts, joints,
                           HAIR_STYLES[identity % len(HAIR_STYLES)], seed)
        weights = np.concatenate([_group_weights(materials, faces), acc.groups])
        all_faces = np.concatenate([faces, acc.faces + len(rest)])
        body_closed = ~np.isin(face_parts, [SMPLX_PART_NAMES.index(p) for p in _OPEN_PARTS])
        return cls(
            name=name, identity=identity, betas=betas, model=model, faces=all_faces,
            face_parts=np.concatenate([face_parts, acc.parts]).astype(np.int16),
            num_body_faces=len(faces), binding=acc.binding, hair_vertices=acc.hair,
            canonical=np.concatenate([rest, acc.vertices]).astype(np.float32),
            group_weights=weights, face_groups=_face_groups(weights, all_faces),
            closed=np.concatenate([body_closed, acc.closed]),
            appearance=app.make_appearance(palette, identity, rest, materials, joints, seed),
            rest_joints=np.asarray(joints, dtype=np.float64))

    def pose(self, params: dict[str, Any]) -> PosedActor:
        """World geometry for unbatched SMPL-X params (`motion.pose_to_params`); the actor's
        betas replace params["betas"]."""
        clean = {}
        for key, value in params.items():
            arr = np.asarray(value, dtype=np.float64)
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"actor '{self.name}': params['{key}'] contains NaN or inf")
            clean[key] = arr
        clean["betas"] = self.betas
        with self._lock, torch.no_grad():  # the model's stage cache is not thread-safe
            out = self.model(clean)
        body = out.vertices[0].numpy().astype(np.float64)
        faces = self.faces[: self.num_body_faces]
        verts = np.concatenate([body, place_bound(self.binding, body, faces)])
        return PosedActor(vertices=verts,
                          normals=vertex_normals(verts, self.faces).astype(np.float32),
                          joints=out.joints[0].numpy().astype(np.float64),
                          num_body_vertices=len(body))

    def render(self, posed: PosedActor, camera: Camera, *,
               background: tuple[float, float, float] = (1.0, 1.0, 1.0),
               supersample: int = 2) -> ActorView:
        """Ground-truth image, coverage and part mask of a posed frame seen by `camera`."""
        bg = np.asarray(background, dtype=np.float64)
        if bg.shape != (3,) or not np.all((bg >= 0.0) & (bg <= 1.0)):
            raise ValueError(f"background must be an RGB triple in [0, 1], got {background!r}")
        if isinstance(supersample, bool) or not isinstance(supersample, int) or not (
                1 <= supersample <= 8):
            raise ValueError(f"supersample must be an integer in [1, 8], got {supersample!r}")
        if len(posed.vertices) != len(self.canonical):
            raise ValueError("the posed frame does not belong to this actor")
        ss = supersample
        cam = camera if ss == 1 else camera.resized(camera.width * ss, camera.height * ss)
        mesh = render_mesh(posed.vertices, self.faces, cam, shading=False,
                           cull_back_faces=self.closed)
        face_id = mesh.face_id.reshape(-1)
        hit = np.flatnonzero(face_id >= 0)
        group = self.face_groups[face_id[hit]]
        order = np.argsort(group, kind="stable")  # one texture group = one slice of samples
        hit, group = hit[order], group[order]
        color = self._shade(posed, hit, group, face_id, mesh.bary.reshape(-1, 3))
        labels = np.full(cam.height * cam.width, -1, dtype=np.int16)
        labels[hit] = self.face_parts[face_id[hit]]
        acc = np.zeros((4, camera.height * camera.width))
        _kernel("accumulate")(hit, cam.width, ss, camera.width, color, acc)
        inv = 1.0 / (ss * ss)
        alpha = acc[0] * inv  # exact multiples of 1 / ss^2
        rgb = np.empty((camera.height * camera.width, 3), dtype=np.float32)
        rgb[:] = bg  # exactly the background where nothing is covered
        seen = np.flatnonzero(alpha > 0.0)
        for c in range(3):  # premultiplied object colour over the background
            rgb[seen, c] = acc[1 + c, seen] * inv + (1.0 - alpha[seen]) * bg[c]
        shape = (camera.height, camera.width)
        return ActorView(rgb=np.clip(rgb, 0.0, 1.0).reshape(*shape, 3),
                         alpha=alpha.astype(np.float32).reshape(shape),
                         parts=_majority(labels.reshape(cam.height, cam.width), ss))

    def _shade(self, posed: PosedActor, hit: np.ndarray, group: np.ndarray,
               face_id: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Lit colour [3, N] of the covered samples `hit` (flat indices into face_id [S] and
        bary [S, 3]), sorted by their face's texture group `group` [N] (-1: blended)."""
        gather = _kernel("gather")
        table = np.concatenate([self.canonical, posed.normals], axis=1)
        attr = np.empty((6, len(hit)), dtype=np.float32)
        gather(hit, face_id, bary, self.faces, table, attr)
        canon, normal = attr[:3], attr[3:]
        normal /= np.maximum(np.sqrt((normal * normal).sum(axis=0)), np.float32(1e-12))
        mixed = int(np.searchsorted(group, 0))  # the first samples blend texture groups
        w = np.empty((len(app.GROUPS), mixed), dtype=np.float32)
        gather(hit[:mixed], face_id, bary, self.faces, self.group_weights, w)
        w = np.maximum(w, 0.0)
        w = (w * w * w) ** 2  # sharpen: crisp but anti-aliased material borders
        w /= np.maximum(w.sum(axis=0), np.float32(1e-30))
        w[w < 1e-3] = 0.0  # skip textures with negligible weight
        w /= np.maximum(w.sum(axis=0), np.float32(1e-30))
        return app.shade_albedo(app.albedo(self.appearance, canon, group, w), normal)


def render_actor_preview(files: BodyModelFiles, identity: int, out_png: str | Path, *,
                         size: int = 384) -> Path:
    """A PNG for a person to look at: the actor in its relaxed stance, full body and head,
    from the front, the side and the back (two rows of three views)."""
    actor = Actor.load(files, identity)
    body_pose = np.zeros((SMPLX_NUM_BODY_JOINTS, 3))
    for name, aa in RELAXED_ARMS.items():
        body_pose[JOINT[name] - 1] = aa
    posed = actor.pose({"body_pose": body_pose})
    head = posed.joints[JOINT["head"]]
    rows = []
    for target, distance in (((0.0, -0.1, 0.0), 3.0), (head + [0.0, 0.06, 0.0], 0.9)):
        views = [actor.render(posed, orbit(target, yaw, 5.0, distance, width=size,
                                           height=size, fov_y_deg=35.0),
                              background=(0.93, 0.94, 0.96)).rgb for yaw in (0.0, 90.0, 180.0)]
        rows.append(np.concatenate(views, axis=1))
    image = (np.concatenate(rows, axis=0) * 255.0 + 0.5).astype(np.uint8)
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), image[..., ::-1]):
        raise OSError(f"could not write {out}")
    return out


# ------------------------------------------------------------------------------- helpers


@dataclass(frozen=True)
class _Accessories:
    vertices: np.ndarray  # [A, 3] rest pose: hair, then collar
    faces: np.ndarray  # [Fa, 3] into vertices
    binding: Binding
    hair: np.ndarray  # [A] bool
    parts: np.ndarray  # [Fa] part of the triangle each face's first corner is bound to
    closed: np.ndarray  # [Fa] bool: the collar is closed; rays can slip under the hair's edge
    groups: np.ndarray  # [A, len(GROUPS)] texture groups: hair, shirt


def _accessories(rest: np.ndarray, faces: np.ndarray, materials: np.ndarray,
                 face_parts: np.ndarray, joints: np.ndarray, style: HairStyle,
                 seed: int) -> _Accessories:
    """Hair shell bound to the scalp, collar bound to the neck, from the rest mesh."""
    hair_v, hair_f, scalp = hair_shell(rest, faces, materials == MATERIALS.index("hair"),
                                       style, seed)
    part = {p: i for i, p in enumerate(SMPLX_PART_NAMES)}
    neck = np.flatnonzero(face_parts == part["neck"])
    torso = np.flatnonzero(np.isin(face_parts, [part[p] for p in _TORSO_PARTS])
                           & (materials[faces] == MATERIALS.index("shirt")).all(axis=1))
    col_v, col_f = collar(rest, faces, neck, torso, joints[JOINT["neck"]])
    binding = concat_bindings(bind_points(hair_v, rest, faces, scalp),
                              bind_points(col_v, rest, faces, neck))
    acc_f = np.concatenate([hair_f, col_f + len(hair_v)])
    hair = np.arange(len(hair_v) + len(col_v)) < len(hair_v)
    groups = np.zeros((len(hair), len(app.GROUPS)), dtype=np.float32)
    groups[hair, app.GROUPS.index("hair")] = 1.0
    groups[~hair, app.GROUPS.index("shirt")] = 1.0
    return _Accessories(
        vertices=np.concatenate([hair_v, col_v]), faces=acc_f, binding=binding, hair=hair,
        parts=face_parts[binding.face[acc_f[:, 0]]],
        closed=np.concatenate([np.zeros(len(hair_f), bool), np.ones(len(col_f), bool)]),
        groups=groups)


def _gather_kernel(hit, face_id, bary, faces, table, out):  # pragma: no cover
    """out[c, n] = sum_k bary[s, k] * table[faces[face_id[s], k], c] with s = hit[n]."""
    for n in range(hit.shape[0]):
        s = hit[n]
        f = face_id[s]
        b0 = bary[s, 0]
        b1 = bary[s, 1]
        b2 = bary[s, 2]
        v0 = faces[f, 0]
        v1 = faces[f, 1]
        v2 = faces[f, 2]
        for c in range(table.shape[1]):
            out[c, n] = b0 * table[v0, c] + b1 * table[v1, c] + b2 * table[v2, c]


def _gather_reference(hit, face_id, bary, faces, table, out) -> None:
    """Numpy twin of :func:`_gather_kernel`."""
    fv = faces[face_id[hit]]
    b = bary[hit]
    for c in range(table.shape[1]):
        col = table[:, c]
        out[c] = b[:, 0] * col[fv[:, 0]] + b[:, 1] * col[fv[:, 1]] + b[:, 2] * col[fv[:, 2]]


def _accumulate_kernel(hit, width_s, ss, width, color, acc):  # pragma: no cover
    """acc[0, pixel] += 1 and acc[1 + c, pixel] += color[c, n] for each covered sample."""
    for n in range(hit.shape[0]):
        i = hit[n] // width_s
        j = hit[n] - i * width_s
        p = (i // ss) * width + j // ss
        acc[0, p] += 1.0
        for c in range(3):
            acc[1 + c, p] += color[c, n]


def _accumulate_reference(hit, width_s, ss, width, color, acc) -> None:
    """Numpy twin of :func:`_accumulate_kernel` (bincount adds in the same order)."""
    i = hit // width_s
    pixel = (i // ss) * width + (hit - i * width_s) // ss
    acc[0] += np.bincount(pixel, minlength=acc.shape[1])
    for c in range(3):
        acc[1 + c] += np.bincount(pixel, weights=color[c], minlength=acc.shape[1])


@functools.cache
def _kernel(name: str) -> Callable[..., None]:
    """A per-sample kernel, compiled by numba (GIL released) or its numpy twin without it."""
    kernels = {"gather": (_gather_kernel, _gather_reference),
               "accumulate": (_accumulate_kernel, _accumulate_reference)}
    compiled, reference = kernels[name]
    if not numba_available():
        return reference
    import numba

    return numba.njit(cache=True, nogil=True)(compiled)


def _materials(files: BodyModelFiles, v_template: np.ndarray) -> np.ndarray:
    """Per-vertex material of the written model (not stored in the files): rebuilt from the
    generator with the manifest's seed and resolution, checked against the template."""
    manifest = json.loads(files.manifest.read_text())
    h = make_humanoid(int(manifest["seed"]), float(manifest["resolution"]))
    order = _vertex_order(h)
    if h.vertices.shape != v_template.shape or not np.allclose(h.vertices[order], v_template,
                                                               atol=1e-9):
        raise ValueError(f"{files.root}: the SMPL-X template does not match the synthetic "
                         "generator; rewrite the model files")
    return h.materials[order]


def _vertex_parts(files: BodyModelFiles, num_vertices: int) -> np.ndarray:
    parts = np.full(num_vertices, -1, dtype=np.int64)
    for name, ids in load_segmentation(files.segmentation, num_vertices).items():
        if name in SMPLX_PART_NAMES:
            parts[ids] = SMPLX_PART_NAMES.index(name)
    if (parts < 0).any():
        raise ValueError(f"{files.segmentation}: {int((parts < 0).sum())} vertices have no part")
    return parts


def _face_parts(parts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Majority part of each face's corners (all differ: the first corner's)."""
    p = parts[faces]
    two = (p[:, 1] == p[:, 2]) & (p[:, 0] != p[:, 1])
    return np.where(two, p[:, 1], p[:, 0])


def _group_weights(materials: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-vertex texture-group weights [V, G], smoothed a little over the mesh so material
    borders become smooth curves instead of triangle staircases."""
    onehot = np.eye(len(app.GROUPS), dtype=np.float64)[np.asarray(app.MATERIAL_GROUP)[materials]]
    adj = mesh_adjacency(faces, len(materials))
    return smooth_vertex_field(adj, onehot, 5).astype(np.float32)


def _face_groups(weights: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The texture group of faces that render with one group only, else -1. That holds when
    one group has weight >= 0.76 at all three corners: inside the face the others stay
    <= 0.24, and `_shade`'s sharpening (power 6) leaves them below its 1e-3 cut-off."""
    solo = weights.argmax(axis=1)  # [V]
    pure = weights.max(axis=1) >= 0.76
    g = np.where(pure, solo, -1)[faces]  # [F, 3]
    same = (g[:, 0] >= 0) & (g[:, 0] == g[:, 1]) & (g[:, 0] == g[:, 2])
    return np.where(same, g[:, 0], -1).astype(np.int8)


def _majority(labels: np.ndarray, ss: int) -> np.ndarray:
    """Per pixel, the most frequent label among its covered samples (labels [Hs, Ws], -1
    empty); ties: the sample nearest the pixel centre, then row-major. -1 where all empty."""
    samples = [labels[i::ss, j::ss] for i in range(ss) for j in range(ss)]  # S x [h, w]
    first = samples[0]
    uniform = np.ones(first.shape, dtype=bool)
    for lab in samples[1:]:
        uniform &= lab == first
    out = first.copy()
    todo = np.nonzero(~uniform)
    if not len(todo[0]):
        return out
    lab = np.stack([s[todo] for s in samples], axis=1)  # [M, S]
    covered = lab >= 0
    c = (np.arange(ss) + 0.5) / ss - 0.5
    dist = (c[:, None] ** 2 + c[None, :] ** 2).reshape(-1)
    rank = np.argsort(np.argsort(dist, kind="stable"), kind="stable")  # 0: most central
    votes = np.zeros(lab.shape, dtype=np.int64)
    for k in range(ss * ss):
        votes += (lab == lab[:, k:k + 1]) & covered[:, k:k + 1]
    score = np.where(covered, votes * ss * ss - rank[None], -1)
    out[todo] = lab[np.arange(len(lab)), np.argmax(score, axis=1)]
    return out
