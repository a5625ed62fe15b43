"""Geometry the parametric body lacks: a hair volume over the scalp and a shirt collar.

Both are built once from the actor's rest mesh and *bound* to body triangles: each accessory
vertex stores a triangle, barycentric coordinates of its foot point in that triangle's plane
and its offset in the triangle's frame (`triangle_frames`: edge, in-plane perpendicular,
normal). Posing rebuilds it from the posed triangle, so accessories follow the body exactly.

- Hair: the scalp (faces whose corners all have the hair material) copied and pushed out along
  smoothed normals by 1-4 cm. The thickness tapers to a few millimetres at an irregular,
  identity-dependent outline inside the hairline, so shell and scalp close into one volume
  seen from any side; lock-sized lumps make the silhouette irregular.
- Collar: a closed band (rectangular cross-section) around the neck base, sunk into the shirt at
  the bottom and standing up 1.5-3.5 cm (lower in front), a little off the neck.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import torch
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from ..gaussians.frames import triangle_frames
from .appearance import wave_bank, waves
from .mesh_render import vertex_normals

__all__ = ["HAIR_STYLES", "Binding", "HairStyle", "bind_points", "collar", "concat_bindings",
           "hair_shell", "mesh_adjacency", "place_bound", "smooth_vertex_field"]


@dataclass(frozen=True)
class HairStyle:
    thickness: float  # metres of hair on top of the head
    side: float  # thickness at the temples, relative
    back: float  # at the back of the head, relative
    front: float  # at the forehead, relative
    lumps: float  # relative amplitude of lock-sized bumps
    inset: float  # metres between the hairline and the start of the volume
    taper: float  # metres over which the volume rises from the outline


HAIR_STYLES = (
    HairStyle(0.034, 0.5, 0.85, 0.8, 0.22, 0.004, 0.022),  # full
    HairStyle(0.013, 0.75, 0.9, 0.8, 0.12, 0.010, 0.012),  # short
    HairStyle(0.026, 0.6, 0.95, 0.6, 0.3, 0.006, 0.018),  # medium, tousled
)
_MIN_OFFSET = 0.002  # shell edge stays this far above the scalp: no z-fighting


@dataclass(frozen=True)
class Binding:
    """Accessory vertices bound to body triangles."""

    face: np.ndarray  # [A] body face index
    bary: np.ndarray  # [A, 3] foot point in the face's plane (may lie a little outside it)
    offset: np.ndarray  # [A, 3] point - foot, in the face's frame


def _frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle rotations [F, 3, 3] (columns edge, perpendicular, normal), float64."""
    rot, _, _ = triangle_frames(torch.from_numpy(np.asarray(vertices, dtype=np.float64)),
                                torch.from_numpy(np.asarray(faces, dtype=np.int64)))
    return rot.numpy()


def bind_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                candidates: np.ndarray, k: int = 8) -> Binding:
    """Bind points [A, 3] to the nearest of the candidate faces (indices into faces [F, 3]) of
    the rest mesh: among the k nearest by centroid, the one whose plane foot point lies inside
    it (or nearest the inside) and closest."""
    tri = vertices[faces[candidates]]  # [C, 3, 3]
    _, near = cKDTree(tri.mean(axis=1)).query(points, k=min(k, len(candidates)))
    near = near.reshape(len(points), -1)  # [A, k]
    t = tri[near]  # [A, k, 3, 3]
    e1, e2 = t[:, :, 1] - t[:, :, 0], t[:, :, 2] - t[:, :, 0]
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    d = points[:, None] - t[:, :, 0]
    foot = d - (d * n).sum(-1, keepdims=True) * n  # in-plane part
    g11, g12, g22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    r1, r2 = (foot * e1).sum(-1), (foot * e2).sum(-1)
    det = g11 * g22 - g12 * g12
    b1, b2 = (g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det
    bary = np.stack([1.0 - b1 - b2, b1, b2], -1)  # [A, k, 3]
    outside = np.maximum(-bary, 0.0).sum(-1)
    dist = np.abs((d * n).sum(-1))
    best = np.argmin(dist + 0.05 * outside + 1e3 * (outside > 0.05), axis=1)  # metres-ish
    rows = np.arange(len(points))
    face = candidates[near[rows, best]]
    b = bary[rows, best]
    foot_pt = np.einsum("ak,akc->ac", b, vertices[faces[face]])
    rot = _frames(vertices, faces[face])
    offset = np.einsum("aji,aj->ai", rot, points - foot_pt)  # R^T (p - foot)
    return Binding(face=face, bary=b, offset=offset)


def concat_bindings(*bindings: Binding) -> Binding:
    return Binding(face=np.concatenate([b.face for b in bindings]),
                   bary=np.concatenate([b.bary for b in bindings]),
                   offset=np.concatenate([b.offset for b in bindings]))


def place_bound(binding: Binding, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Positions [A, 3] of bound points on the posed mesh vertices [V, 3]."""
    f = faces[binding.face]
    foot = np.einsum("ak,akc->ac", binding.bary, vertices[f])
    return foot + np.einsum("aij,aj->ai", _frames(vertices, f), binding.offset)


# ----------------------------------------------------------------------------------- hair


def mesh_adjacency(faces: np.ndarray, n: int) -> scipy.sparse.csr_matrix:
    """Vertex adjacency [n, n] (1 where two vertices share an edge) of a triangle mesh."""
    i = faces[:, [0, 1, 2, 1, 2, 0]].reshape(-1)
    j = faces[:, [1, 2, 0, 0, 1, 2]].reshape(-1)
    a = scipy.sparse.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    a.data[:] = 1.0
    return a


def smooth_vertex_field(adj: scipy.sparse.csr_matrix, x: np.ndarray, iterations: int
                        ) -> np.ndarray:
    """Half-step umbrella smoothing of a per-vertex field [n, ...] over a mesh graph."""
    deg = np.asarray(adj.sum(axis=1)).reshape(-1, *([1] * (x.ndim - 1)))
    for _ in range(iterations):
        x = 0.5 * x + 0.5 * (adj @ x) / np.maximum(deg, 1.0)
    return x


def _scalp(faces: np.ndarray, hair: np.ndarray) -> np.ndarray:
    """Indices of the faces of the largest connected patch whose corners are all hair."""
    idx = np.flatnonzero(hair[faces].all(axis=1))
    n = int(faces.max()) + 1
    _, label = connected_components(mesh_adjacency(faces[idx], n), directed=False)
    comp = label[faces[idx, 0]]
    return idx[comp == np.bincount(comp).argmax()]


def _edge_distance(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance along mesh edges from every vertex to the open boundary [V]."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    border = np.unique(uniq[count == 1])
    length = np.linalg.norm(vertices[uniq[:, 0]] - vertices[uniq[:, 1]], axis=1)
    n = len(vertices)
    graph = scipy.sparse.csr_matrix((length, (uniq[:, 0], uniq[:, 1])), shape=(n, n))
    return dijkstra(graph, directed=False, indices=border, min_only=True)


def hair_shell(rest: np.ndarray, faces: np.ndarray, hair: np.ndarray, style: HairStyle,
               seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hair volume over the scalp. rest [V, 3], faces [F, 3], hair [V] bool (hair material).
    Returns shell vertices [S, 3] (rest pose), shell faces [T, 3] (into them, outward) and
    the scalp faces (indices into faces) to bind them to."""
    scalp = _scalp(faces, hair)
    used, local = np.unique(faces[scalp], return_inverse=True)
    sub_faces = local.reshape(-1, 3)
    v = rest[used]
    adj = mesh_adjacency(sub_faces, len(used))
    normals = smooth_vertex_field(adj, vertex_normals(rest, faces)[used], 4)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rng = np.random.default_rng([seed, 4711])
    p32 = np.ascontiguousarray(v.T, dtype=np.float32)  # [3, S]
    outline = style.inset + 0.006 * (1.0 + waves(wave_bank(rng, (0.05, 0.025), (0.6, 0.4)),
                                                 p32))
    rise = np.clip((_edge_distance(v, sub_faces) - outline) / style.taper, 0.0, 1.0)
    rise = rise * rise * (3.0 - 2.0 * rise)
    nx, ny, nz = normals.T
    rel = (np.maximum(ny, 0) ** 2 + style.side * nx**2 + style.back * np.maximum(-nz, 0) ** 2
           + style.front * np.maximum(nz, 0) ** 2 + style.back * np.minimum(ny, 0) ** 2)
    lumps = 1.0 + style.lumps * waves(wave_bank(rng, (0.06, 0.03), (0.7, 0.3)), p32)
    # Thinner toward the nape, so the back of the head does not end in a ledge.
    low = v[:, 1].min()
    nape = np.clip((v[:, 1] - low) / 0.08, 0.0, 1.0)
    nape = 0.2 + 0.8 * nape * nape * (3.0 - 2.0 * nape)
    thick = smooth_vertex_field(adj, style.thickness * rel * lumps * rise * nape, 2)
    return v + (_MIN_OFFSET + thick)[:, None] * normals, sub_faces, scalp


# --------------------------------------------------------------------------------- collar


def _ray_hits(origins: np.ndarray, dirs: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Nearest positive ray parameter [R] against triangles [T, 3, 3] (inf: no hit)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(dirs[:, None], e2[None])  # [R, T, 3]
    det = (h * e1[None]).sum(-1)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origins[:, None] - tri[None, :, 0]
    u = (h * s).sum(-1) * inv
    q = np.cross(s, e1[None])
    w = (q * dirs[:, None]).sum(-1) * inv
    t = (q * e2[None]).sum(-1) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 1e-9)
    return np.where(hit, t, np.inf).min(axis=1)


def collar(rest: np.ndarray, faces: np.ndarray, neck: np.ndarray, torso: np.ndarray,
           neck_joint: np.ndarray, n_around: int = 56) -> tuple[np.ndarray, np.ndarray]:
    """A standing band collar. neck, torso: indices of the neck's and the shirt torso's faces;
    neck_joint [3] (rest). Returns collar vertices [4 n, 3] and outward faces [8 n, 3]."""
    theta = np.linspace(0.0, 2.0 * np.pi, n_around, endpoint=False)  # 0: front (+z)
    out = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], 1)
    tri_neck, tri_torso = rest[faces[neck]], rest[faces[torso]]
    axis = np.array([neck_joint[0], neck_joint[1] - 0.02, neck_joint[2]])
    r_neck = _ray_hits(np.repeat(axis[None], n_around, 0), out, tri_neck)
    r_neck = np.where(np.isfinite(r_neck), r_neck, np.nanmedian(r_neck[np.isfinite(r_neck)]))
    gap = 0.008
    down = np.tile([0.0, -1.0, 0.0], (n_around, 1))

    def shirt_height(radius: np.ndarray) -> np.ndarray:
        """Height of the torso surface below points at `radius` around the neck axis."""
        above = axis + radius[:, None] * out + [0.0, 0.08, 0.0]
        t = _ray_hits(above, down, tri_torso)
        return above[:, 1] - np.where(np.isfinite(t), t, np.median(t[np.isfinite(t)]))

    # Where the neck leaves the shirt: the torso top just inside the neck. The top edge is
    # that line smoothed around the neck, the bottom edge sinks below the shirt everywhere.
    junction = shirt_height(r_neck - 0.003)
    kernel = np.exp(-0.5 * (np.minimum(np.arange(n_around), n_around - np.arange(n_around))
                            * (2 * np.pi / n_around) / 0.4) ** 2)
    smooth = np.real(np.fft.ifft(np.fft.fft(junction) * np.fft.fft(kernel / kernel.sum())))
    back = 0.5 * (1.0 - np.cos(theta))  # 0 in front, 1 at the back
    top = smooth + 0.012 + 0.014 * back
    bottom = junction - 0.012
    ring = axis[None] * [1.0, 0.0, 1.0]
    # Cross-section: inner bottom, inner top, outer top, outer bottom (a closed loop). The
    # band leans in to end inside the neck, so it closes against the neck where the torso
    # falls away (chest, upper back) and hides in the shirt elsewhere.
    radius = np.stack([r_neck - 0.008, r_neck + gap, r_neck + gap + 0.006, r_neck - 0.002],
                      1)  # [n, 4]
    y = np.stack([bottom, top, top, bottom], 1)
    verts = ring[:, None] + radius[..., None] * out[:, None] + y[..., None] * [0.0, 1.0, 0.0]
    verts = verts.reshape(-1, 4, 3)  # [n, 4, 3]
    i = np.arange(n_around)[:, None]
    k = np.arange(4)[None]
    a, b = 4 * i + k, 4 * ((i + 1) % n_around) + k
    c, d = 4 * ((i + 1) % n_around) + (k + 1) % 4, 4 * i + (k + 1) % 4
    quads = np.stack([a, b, c, d], -1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    flat = verts.reshape(-1, 3)
    # Orient outward from the band's cross-section centre line.
    centre = np.repeat(verts.mean(axis=1), 4, axis=0)
    fn = np.cross(flat[tris[:, 1]] - flat[tris[:, 0]], flat[tris[:, 2]] - flat[tris[:, 0]])
    away = flat[tris].mean(axis=1) - centre[tris[:, 0]]
    flip = (fn * away).sum(-1) < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return flat, tris
