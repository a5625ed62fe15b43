"""Ground-truth triangle-mesh renderer (z-buffer rasterizer), independent of any splatting code.

Pipeline
--------
1. Vertices go to camera space (``x_cam = R @ x + t``). Faces whose three vertices are
   (numerically) collinear or coincident are skipped.
2. Near-plane **clipping**: each triangle is clipped against ``z = near`` in camera space
   (Sutherland-Hodgman). A triangle with one vertex behind becomes a quad (two triangles),
   one with two vertices behind shrinks to one triangle, one with all three behind is
   dropped. Nothing at ``z < near`` is ever drawn. Clipped pieces carry the barycentric
   coordinates of their corners with respect to the original face, so attributes are
   interpolated exactly as for the unclipped face.
3. Rasterization in gsplat's pixel convention (see :mod:`avatar_core.render.camera`): the
   sample of pixel ``(col j, row i)`` is the point ``(j + 0.5, i + 0.5)``. A pixel is
   covered when its centre is inside or *on the boundary* of the projected triangle
   (inclusive edge test, so meshes have no cracks); both windings are drawn (meshes may be
   open) unless ``cull_back_faces`` asks to skip faces turned away from the camera (decided
   in camera space before clipping). The depth test keeps the smallest camera ``z``; on exact
   ties the lower face index wins (triangles are drawn in face order with a strict ``<``).
   Depth and barycentrics are perspective-correct: ``1/z`` is interpolated linearly in
   screen space. Projected triangles with twice their signed area ``<= 1e-9`` pixel^2 in
   magnitude (edge-on) draw nothing.
4. Deferred shading on covered pixels: vertex colours and area-weighted smooth vertex
   normals are interpolated with the perspective-correct barycentrics; colour is
   ``albedo * (ambient + (1 - ambient) * |n . l|)`` (two-sided Lambert) with a directional
   light given in camera space. Empty pixels get ``background``. The face id and the
   original-face barycentrics of every pixel are returned as well, so callers can shade or
   texture the surface themselves.

Steps 3 and 4 each have two implementations: numba ``@njit`` kernels (a per-triangle
bounding-box loop and a per-pixel shading loop; single-threaded, deterministic, release the
GIL so several cameras can render in threads) and pure-numpy reference twins (a Python loop
over triangles vectorised over each bounding box, and vectorised shading). The raster twins
perform the same floating-point operations in the same order; tests check that the outputs
agree. numba is optional: without it ``backend="auto"`` falls back to the (much slower)
reference path with a warning.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from avatar_core.render.camera import Camera

__all__ = [
    "DEFAULT_LIGHT_DIR",
    "DEFAULT_VERTEX_COLOR",
    "MeshRenderOutput",
    "face_label_image",
    "numba_available",
    "render_mesh",
    "vertex_normals",
]

DEFAULT_VERTEX_COLOR = (0.8, 0.8, 0.8)
# Direction from the surface toward the light, in camera coordinates (x right, y down,
# z forward): a headlight slightly above and to the right of the camera.
DEFAULT_LIGHT_DIR = (0.25, -0.35, -1.0)
_AREA_EPS = 1e-9  # projected triangles with |2 * area| <= this (pixel^2) are skipped
_DEGENERATE_REL = 1e-12  # |e1 x e2| <= this * (|e1|^2 + |e2|^2): collinear face


@dataclass
class MeshRenderOutput:
    """Result of :func:`render_mesh`.

    rgb: [H, W, 3] float32 in [0, 1] (``background`` where empty).
    alpha: [H, W] float32, 1 where a triangle covers the pixel centre, else 0.
    depth: [H, W] float32 camera-space z, ``inf`` where empty.
    face_id: [H, W] int32 index into ``faces``, -1 where empty.
    labels: [H, W] int32 ``face_labels[face_id]`` (``-1`` where empty) when ``face_labels``
        was given, else None.
    bary: [H, W, 3] float32 perspective-correct barycentrics of the pixel centre with respect
        to the three vertices of the original face ``faces[face_id]`` (also for pieces of
        near-clipped faces), 0 where empty; for texturing and attribute lookups.
    """

    rgb: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    face_id: np.ndarray
    labels: np.ndarray | None = None
    bary: np.ndarray | None = None


def face_label_image(face_id: np.ndarray, face_labels: Any, empty: int = -1) -> np.ndarray:
    """Map a face-id image (``-1`` = empty) to per-pixel labels (``empty`` where empty)."""
    face_id = np.asarray(face_id)
    labels = np.asarray(face_labels)
    out = np.full(face_id.shape, empty, dtype=np.int32)
    hit = face_id >= 0
    out[hit] = labels[face_id[hit]]
    return out


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [V, 3] (zero for vertices with no usable face)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    out = np.zeros_like(v)
    if len(f) == 0:
        return out
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # |fn| = 2 * area
    idx = f.reshape(-1)
    for c in range(3):
        out[:, c] = np.bincount(idx, weights=np.repeat(fn[:, c], 3), minlength=len(v))
    n = np.linalg.norm(out, axis=1, keepdims=True)
    np.divide(out, n, out=out, where=n > 1e-300)
    out[n[:, 0] <= 1e-300] = 0.0
    return out


# ---------------------------------------------------------------------------------------
# Triangle setup: degenerate removal, near-plane clipping, projection
# ---------------------------------------------------------------------------------------


@dataclass
class _Triangles:
    uv: np.ndarray  # [T, 3, 2] float64 screen positions (pixel units)
    z: np.ndarray  # [T, 3] float64 camera depth (>= near)
    bary: np.ndarray  # [T, 3, 3] corner k of piece -> weights on the face's vertices
    face: np.ndarray  # [T] int64 index of the source face
    clipped: np.ndarray  # [T] bool: piece of a clipped face (bary is not the identity)


def _setup_triangles(vc: np.ndarray, faces: np.ndarray, K: np.ndarray, near: float,
                     cull: np.ndarray | bool = False) -> _Triangles:
    """Clip camera-space faces against z = near and project them (see module docstring).
    cull: drop faces (all, or those marked in a [F] mask) whose counter-clockwise normal
    points away from the camera."""
    P = vc[faces]  # [F, 3, 3]
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    cross = np.cross(e1, e2)
    cross_n = np.linalg.norm(cross, axis=1)
    scale = np.einsum("ij,ij->i", e1, e1) + np.einsum("ij,ij->i", e2, e2)
    valid = cross_n > _DEGENERATE_REL * scale
    if np.any(cull):  # front faces see the camera centre (the origin) on their positive side
        valid &= ~cull | (np.einsum("ij,ij->i", cross, P[:, 0]) < 0.0)
    behind = P[:, :, 2] < near
    nb = behind.sum(axis=1)
    eye = np.eye(3)

    pos: list[np.ndarray] = []
    bary: list[np.ndarray] = []
    fid: list[np.ndarray] = []
    sub: list[np.ndarray] = []

    # Fully in front: unchanged.
    idx = np.nonzero(valid & (nb == 0))[0]
    pos.append(P[idx])
    bary.append(np.broadcast_to(eye, (len(idx), 3, 3)))
    fid.append(idx)
    sub.append(np.zeros(len(idx), dtype=np.int64))

    def rolled(sel: np.ndarray, first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Cyclically rotate each face so vertex `first` comes first (keeps the winding).
        order = (first[:, None] + np.arange(3)[None, :]) % 3
        return np.take_along_axis(P[sel], order[:, :, None], axis=1), eye[order]

    def cut(pa, pb, ba, bb):
        # Point on segment a-b where z == near (z_a, z_b on opposite sides of near).
        s = (near - pa[:, 2]) / (pb[:, 2] - pa[:, 2])
        p = pa + s[:, None] * (pb - pa)
        p[:, 2] = near
        return p, ba + s[:, None] * (bb - ba)

    # One vertex behind: quad (p01, v1, v2, p02) -> triangles (p01, v1, v2), (p01, v2, p02).
    idx = np.nonzero(valid & (nb == 1))[0]
    if len(idx):
        q, b = rolled(idx, np.argmax(behind[idx], axis=1))
        p01, b01 = cut(q[:, 0], q[:, 1], b[:, 0], b[:, 1])
        p02, b02 = cut(q[:, 0], q[:, 2], b[:, 0], b[:, 2])
        pos.append(np.stack([p01, q[:, 1], q[:, 2]], axis=1))
        bary.append(np.stack([b01, b[:, 1], b[:, 2]], axis=1))
        pos.append(np.stack([p01, q[:, 2], p02], axis=1))
        bary.append(np.stack([b01, b[:, 2], b02], axis=1))
        fid += [idx, idx]
        sub += [np.zeros(len(idx), dtype=np.int64), np.ones(len(idx), dtype=np.int64)]

    # Two vertices behind: triangle (v0, p01, p02) with v0 the one in front.
    idx = np.nonzero(valid & (nb == 2))[0]
    if len(idx):
        q, b = rolled(idx, np.argmin(behind[idx], axis=1))
        p01, b01 = cut(q[:, 0], q[:, 1], b[:, 0], b[:, 1])
        p02, b02 = cut(q[:, 0], q[:, 2], b[:, 0], b[:, 2])
        pos.append(np.stack([q[:, 0], p01, p02], axis=1))
        bary.append(np.stack([b[:, 0], b01, b02], axis=1))
        fid.append(idx)
        sub.append(np.zeros(len(idx), dtype=np.int64))

    n_whole = len(fid[0])
    pos_a = np.concatenate(pos).reshape(-1, 3, 3)
    bary_a = np.concatenate(bary).reshape(-1, 3, 3)
    fid_a = np.concatenate(fid).astype(np.int64)
    sub_a = np.concatenate(sub)
    clipped = np.arange(len(fid_a)) >= n_whole
    if n_whole < len(fid_a):  # whole faces come sorted; pieces must join them in face order
        order = np.lexsort((sub_a, fid_a))  # draw in face order: deterministic tie-breaking
        pos_a, bary_a, fid_a, clipped = pos_a[order], bary_a[order], fid_a[order], clipped[order]

    z = np.ascontiguousarray(pos_a[:, :, 2])
    x, y = pos_a[:, :, 0], pos_a[:, :, 1]
    uv = np.empty(z.shape + (2,))
    uv[:, :, 0] = (K[0, 0] * x + K[0, 1] * y + K[0, 2] * z) / z  # (K @ p)[:2] / z, elementwise
    uv[:, :, 1] = (K[1, 0] * x + K[1, 1] * y + K[1, 2] * z) / z
    return _Triangles(uv=uv, z=z, bary=np.ascontiguousarray(bary_a), face=fid_a, clipped=clipped)


# ---------------------------------------------------------------------------------------
# Rasterization kernels. Both write, per pixel, the nearest depth, the index of the winning
# triangle piece and its perspective-correct barycentrics. Keep their arithmetic identical.
# ---------------------------------------------------------------------------------------


def _raster_kernel(uv, z, width, height, area_eps, depth, tri, bary):  # pragma: no cover
    """Scalar z-buffer loop; compiled with numba (running it uncompiled is far too slow)."""
    for t in range(uv.shape[0]):
        x0 = uv[t, 0, 0]
        y0 = uv[t, 0, 1]
        x1 = uv[t, 1, 0]
        y1 = uv[t, 1, 1]
        x2 = uv[t, 2, 0]
        y2 = uv[t, 2, 1]
        area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        if not abs(area) > area_eps:
            continue
        # Pixel-centre range of the bounding box, kept in floats until clamped.
        jlo = np.ceil(min(x0, x1, x2) - 0.5)
        jhi = np.floor(max(x0, x1, x2) - 0.5)
        ilo = np.ceil(min(y0, y1, y2) - 0.5)
        ihi = np.floor(max(y0, y1, y2) - 0.5)
        if jhi < 0.0 or ihi < 0.0 or jlo > width - 1.0 or ilo > height - 1.0:
            continue
        j0 = int(max(jlo, 0.0))
        j1 = int(min(jhi, width - 1.0))
        i0 = int(max(ilo, 0.0))
        i1 = int(min(ihi, height - 1.0))
        z0 = z[t, 0]
        z1 = z[t, 1]
        z2 = z[t, 2]
        for i in range(i0, i1 + 1):
            py = i + 0.5
            for j in range(j0, j1 + 1):
                px = j + 0.5
                w0 = (x2 - x1) * (py - y1) - (y2 - y1) * (px - x1)
                w1 = (x0 - x2) * (py - y2) - (y0 - y2) * (px - x2)
                w2 = (x1 - x0) * (py - y0) - (y1 - y0) * (px - x0)
                if area > 0.0:
                    if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                        continue
                elif w0 > 0.0 or w1 > 0.0 or w2 > 0.0:
                    continue
                q0 = (w0 / area) / z0
                q1 = (w1 / area) / z1
                q2 = (w2 / area) / z2
                zz = 1.0 / (q0 + q1 + q2)
                if zz < depth[i, j]:
                    depth[i, j] = zz
                    tri[i, j] = t
                    bary[i, j, 0] = q0 * zz
                    bary[i, j, 1] = q1 * zz
                    bary[i, j, 2] = q2 * zz


def _raster_reference(uv, z, width, height, area_eps, depth, tri, bary) -> None:
    """Pure-numpy twin of :func:`_raster_kernel` (same operations, same order)."""
    for t in range(uv.shape[0]):
        (x0, y0), (x1, y1), (x2, y2) = (tuple(float(c) for c in p) for p in uv[t])
        area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        if not abs(area) > area_eps:
            continue
        jlo = math.ceil(min(x0, x1, x2) - 0.5)  # Python ints: exact, no overflow
        jhi = math.floor(max(x0, x1, x2) - 0.5)
        ilo = math.ceil(min(y0, y1, y2) - 0.5)
        ihi = math.floor(max(y0, y1, y2) - 0.5)
        if jhi < 0 or ihi < 0 or jlo > width - 1 or ilo > height - 1:
            continue
        j0, j1 = max(jlo, 0), min(jhi, width - 1)
        i0, i1 = max(ilo, 0), min(ihi, height - 1)
        z0, z1, z2 = (float(c) for c in z[t])
        py = (np.arange(i0, i1 + 1, dtype=np.float64) + 0.5)[:, None]
        px = (np.arange(j0, j1 + 1, dtype=np.float64) + 0.5)[None, :]
        w0 = (x2 - x1) * (py - y1) - (y2 - y1) * (px - x1)
        w1 = (x0 - x2) * (py - y2) - (y0 - y2) * (px - x2)
        w2 = (x1 - x0) * (py - y0) - (y1 - y0) * (px - x0)
        if area > 0.0:
            inside = (w0 >= 0.0) & (w1 >= 0.0) & (w2 >= 0.0)
        else:
            inside = (w0 <= 0.0) & (w1 <= 0.0) & (w2 <= 0.0)
        q0 = (w0 / area) / z0
        q1 = (w1 / area) / z1
        q2 = (w2 / area) / z2
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            zz = 1.0 / (q0 + q1 + q2)
        win = (slice(i0, i1 + 1), slice(j0, j1 + 1))
        closer = inside & (zz < depth[win])
        depth[win][closer] = zz[closer]
        tri[win][closer] = t
        b = bary[win]
        b[closer] = np.stack([q0 * zz, q1 * zz, q2 * zz], axis=-1)[closer]


# ---------------------------------------------------------------------------------------
# Shading (deferred, on covered pixels). Same twin arrangement: a numba kernel and a numpy
# reference; they agree to float rounding (not bit-exact: summation orders differ).
# ---------------------------------------------------------------------------------------


def _shade_kernel(
    tri,
    bary,
    tri_face,
    tri_bary,
    tri_clipped,
    faces,
    colors,
    vn,
    vc,
    light,
    ambient,
    bg,
    rgb,
    face_id,
    face_bary,
    do_color,
):  # pragma: no cover
    """Per pixel: original-face barycentrics, albedo, smooth normal, two-sided Lambert."""
    H, W = tri.shape
    for i in range(H):
        for j in range(W):
            t = tri[i, j]
            if t < 0:
                if do_color:
                    for c in range(3):
                        rgb[i, j, c] = min(max(bg[c], 0.0), 1.0)
                continue
            f = tri_face[t]
            face_id[i, j] = f
            b0 = bary[i, j, 0]
            b1 = bary[i, j, 1]
            b2 = bary[i, j, 2]
            if tri_clipped[t]:
                m = tri_bary[t]
                c0 = b0 * m[0, 0] + b1 * m[1, 0] + b2 * m[2, 0]
                c1 = b0 * m[0, 1] + b1 * m[1, 1] + b2 * m[2, 1]
                c2 = b0 * m[0, 2] + b1 * m[1, 2] + b2 * m[2, 2]
                b0, b1, b2 = c0, c1, c2
            face_bary[i, j, 0] = b0
            face_bary[i, j, 1] = b1
            face_bary[i, j, 2] = b2
            if not do_color:
                continue
            va = faces[f, 0]
            vb = faces[f, 1]
            vv = faces[f, 2]
            nx = b0 * vn[va, 0] + b1 * vn[vb, 0] + b2 * vn[vv, 0]
            ny = b0 * vn[va, 1] + b1 * vn[vb, 1] + b2 * vn[vv, 1]
            nz = b0 * vn[va, 2] + b1 * vn[vb, 2] + b2 * vn[vv, 2]
            nl = math.sqrt(nx * nx + ny * ny + nz * nz)
            if nl < 1e-6:  # smooth normals cancel: use the geometric face normal
                e1x = vc[vb, 0] - vc[va, 0]
                e1y = vc[vb, 1] - vc[va, 1]
                e1z = vc[vb, 2] - vc[va, 2]
                e2x = vc[vv, 0] - vc[va, 0]
                e2y = vc[vv, 1] - vc[va, 1]
                e2z = vc[vv, 2] - vc[va, 2]
                nx = e1y * e2z - e1z * e2y
                ny = e1z * e2x - e1x * e2z
                nz = e1x * e2y - e1y * e2x
                nl = math.sqrt(nx * nx + ny * ny + nz * nz)
            shade = ambient + (1.0 - ambient) * abs(
                (nx * light[0] + ny * light[1] + nz * light[2]) / nl
            )
            for c in range(3):
                a = b0 * colors[va, c] + b1 * colors[vb, c] + b2 * colors[vv, c]
                rgb[i, j, c] = min(max(a * shade, 0.0), 1.0)


def _interpolate(b: np.ndarray, attr: np.ndarray, fv: np.ndarray) -> np.ndarray:
    """``sum_k b[:, k] * attr[fv[:, k]]`` for barycentrics [N, 3] and vertex attributes."""
    out = b[:, 0:1] * attr[fv[:, 0]]
    out += b[:, 1:2] * attr[fv[:, 1]]
    out += b[:, 2:3] * attr[fv[:, 2]]
    return out


def _shade_reference(
    tri,
    bary,
    tri_face,
    tri_bary,
    tri_clipped,
    faces,
    colors,
    vn,
    vc,
    light,
    ambient,
    bg,
    rgb,
    face_id,
    face_bary,
    do_color,
) -> None:
    """Pure-numpy twin of :func:`_shade_kernel`."""
    hit = tri >= 0
    if do_color:
        rgb[...] = np.clip(bg, 0.0, 1.0)
    if not hit.any():
        return
    t_hit = tri[hit]
    f_hit = tri_face[t_hit]
    face_id[hit] = f_hit
    b = bary[hit]
    clip = tri_clipped[t_hit]
    if clip.any():  # barycentrics of clipped pieces -> those of the original face
        b[clip] = np.einsum("nk,nkc->nc", b[clip], tri_bary[t_hit[clip]])
    face_bary[hit] = b
    if not do_color:
        return
    fv = faces[f_hit]  # [N, 3]
    n = _interpolate(b, vn, fv)
    n_len = np.linalg.norm(n, axis=1)
    weak = n_len < 1e-6
    if weak.any():  # smooth normals cancel: use the geometric face normal
        p = vc[fv[weak]]
        n[weak] = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        n_len[weak] = np.linalg.norm(n[weak], axis=1)
    shade = ambient + (1.0 - ambient) * np.abs((n @ light) / n_len)
    rgb[hit] = np.clip(_interpolate(b, colors, fv) * shade[:, None], 0.0, 1.0)


_KERNELS: dict[str, tuple[Callable[..., None], Callable[..., None]]] = {
    "reference": (_raster_reference, _shade_reference),
}
_numba_error: str | None = None


def _numba_kernels() -> tuple[Callable[..., None], Callable[..., None]] | None:
    """The compiled (raster, shade) kernels, or None when numba is not importable."""
    global _numba_error
    if "numba" not in _KERNELS and _numba_error is None:
        try:
            import numba
        except ImportError as exc:  # pragma: no cover - depends on the environment
            _numba_error = str(exc)
        else:
            jit = numba.njit(cache=True, nogil=True)
            _KERNELS["numba"] = (jit(_raster_kernel), jit(_shade_kernel))
    return _KERNELS.get("numba")


def numba_available() -> bool:
    """Whether the numba kernels can be used."""
    return _numba_kernels() is not None


# ---------------------------------------------------------------------------------------
# Public entry point
# ---------------------------------------------------------------------------------------


def _as_float_array(x: Any, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    if type(x).__module__.split(".")[0] == "torch":
        x = x.detach().cpu().numpy()
    arr = np.array(x, dtype=np.float64, order="C")  # a private, writable, contiguous copy
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise ValueError(
            f"{name} must have shape [N, {', '.join(map(str, shape_tail))}], got {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def render_mesh(
    vertices: Any,
    faces: Any,
    camera: Camera,
    *,
    vertex_colors: Any = None,
    face_labels: Any = None,
    background: Any = (1.0, 1.0, 1.0),
    light_dir: Any = None,
    ambient: float = 0.35,
    near: float = 0.01,
    backend: str = "auto",
    shading: bool = True,
    cull_back_faces: bool = False,
) -> MeshRenderOutput:
    """Render a triangle mesh with a z-buffer (see the module docstring for the exact rules).

    Args:
        vertices: [V, 3] world positions (metres).
        faces: [F, 3] integer vertex indices.
        camera: the :class:`~avatar_core.render.camera.Camera`.
        vertex_colors: [V, 3] albedo in [0, 1]; default light grey ``DEFAULT_VERTEX_COLOR``.
        face_labels: optional [F] integer labels; fills ``MeshRenderOutput.labels``.
        background: RGB for empty pixels.
        light_dir: direction toward the light in *camera* coordinates (x right, y down,
            z forward); default ``DEFAULT_LIGHT_DIR`` (a headlight). Its sign does not
            matter: shading is two-sided, ``|n . l|``.
        ambient: in [0, 1]; 1 renders the unshaded albedo.
        near: near-plane depth (> 0); geometry at ``z < near`` is clipped away.
        backend: ``"numba"``, ``"reference"`` (pure numpy, slow) or ``"auto"`` (numba when
            importable, else the reference with a warning).
        shading: False skips normals and colours for callers that shade the surface
            themselves from ``face_id`` and ``bary``; ``rgb`` is then a read-only view of
            ``background`` everywhere.
        cull_back_faces: skip faces whose counter-clockwise (right-hand) normal points away
            from the camera: True for all faces, or a [F] bool mask of the faces it applies
            to. Right for closed, outward-oriented meshes; about halves the rasterization.
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
    V = _as_float_array(vertices, (3,), "vertices")
    F_raw = faces.detach().cpu().numpy() if type(faces).__module__.startswith("torch") else faces
    F = np.asarray(F_raw)
    if F.size == 0:
        F = F.reshape(0, 3)
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"faces must have shape [F, 3], got {F.shape}")
    if F.size and not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"faces must be integers, got dtype {F.dtype}")
    F = F.astype(np.int64)
    if F.size and (F.min() < 0 or F.max() >= len(V)):
        raise ValueError(f"faces index outside [0, {len(V)})")
    if vertex_colors is None:
        colors = np.tile(np.asarray(DEFAULT_VERTEX_COLOR, dtype=np.float64), (len(V), 1))
    else:
        colors = _as_float_array(vertex_colors, (3,), "vertex_colors")
        if len(colors) != len(V):
            raise ValueError(f"vertex_colors has {len(colors)} rows for {len(V)} vertices")
    labels_arr = None
    if face_labels is not None:
        labels_arr = np.asarray(face_labels)
        if labels_arr.shape != (len(F),):
            raise ValueError(f"face_labels must have shape [{len(F)}], got {labels_arr.shape}")
    bg = np.asarray(background, dtype=np.float64)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise ValueError(f"background must be an RGB triple, got {background!r}")
    light = np.asarray(DEFAULT_LIGHT_DIR if light_dir is None else light_dir, dtype=np.float64)
    if light.shape != (3,) or not np.all(np.isfinite(light)) or np.linalg.norm(light) == 0.0:
        raise ValueError(f"light_dir must be a non-zero 3-vector, got {light_dir!r}")
    light = light / np.linalg.norm(light)
    ambient = float(ambient)
    if not 0.0 <= ambient <= 1.0:
        raise ValueError(f"ambient must be in [0, 1], got {ambient}")
    near = float(near)
    if not (near > 0.0 and math.isfinite(near)):
        raise ValueError(f"near must be positive, got {near}")
    cull = np.asarray(cull_back_faces)
    if cull.dtype != bool or cull.shape not in ((), (len(F),)):
        raise ValueError(f"cull_back_faces must be a bool or a [{len(F)}] bool mask")

    if backend == "auto":
        kernels = _numba_kernels()
        if kernels is None:
            warnings.warn(
                f"numba unavailable ({_numba_error}); using the slow numpy reference rasterizer",
                RuntimeWarning,
                stacklevel=2,
            )
            kernels = _KERNELS["reference"]
    elif backend == "numba":
        kernels = _numba_kernels()
        if kernels is None:
            raise ImportError(f"backend='numba' requested but numba is unavailable: {_numba_error}")
    elif backend == "reference":
        kernels = _KERNELS["reference"]
    else:
        raise ValueError(f"backend must be 'auto', 'numba' or 'reference', got {backend!r}")
    raster, shade = kernels

    W, H = camera.width, camera.height
    depth = np.full((H, W), np.inf, dtype=np.float64)
    tri = np.full((H, W), -1, dtype=np.int64)
    bary = np.empty((H, W, 3), dtype=np.float64)  # read only where tri >= 0
    vc = camera.world_to_camera(V)
    tris = _setup_triangles(vc, F, camera.K, near, cull=cull)
    if len(tris.face):
        raster(tris.uv, tris.z, W, H, _AREA_EPS, depth, tri, bary)

    rgb = np.empty((H, W, 3) if shading else (0, 0, 3), dtype=np.float32)
    face_id = np.full((H, W), -1, dtype=np.int32)
    face_bary = np.zeros((H, W, 3), dtype=np.float32)
    normals = vertex_normals(vc, F) if shading else np.zeros_like(vc)
    shade(
        tri, bary, tris.face, tris.bary, tris.clipped, F, colors, normals, vc,
        light, ambient, bg, rgb, face_id, face_bary, bool(shading),
    )  # fmt: skip
    if not shading:
        rgb = np.broadcast_to(np.clip(bg, 0.0, 1.0).astype(np.float32), (H, W, 3))
    out = MeshRenderOutput(
        rgb=rgb,
        alpha=(tri >= 0).astype(np.float32),
        depth=depth.astype(np.float32),
        face_id=face_id,
        bary=face_bary,
    )
    if labels_arr is not None:
        out.labels = face_label_image(face_id, labels_arr)
    return out
