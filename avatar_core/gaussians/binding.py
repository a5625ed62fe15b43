"""Binding: the triangle frames of a posed mesh carry the Gaussians into world space.

Each Gaussian lives in its parent triangle's frame (R, T, k) (:func:`frames.triangle_frames`):

    mean'  = k R mean + T      # [N, 3]
    quat'  = q(R) * quat       # [N, 4] (w, x, y, z)
    scale' = k scale           # [N, 3]

One entry point, :func:`bind_gaussians`, dispatches between two twins that compute the same
thing: :func:`bind_gaussians_torch`, the reference (differentiable, any device: training and
CUDA), and :func:`bind_gaussians_numba`, forward-only on the CPU (streaming). The torch version
spends its time in per-op overhead on dozens of small elementwise ops; the numba twin runs one
parallel loop over the faces (frame R, T, k and the rotation's quaternion, once per face) and
one over the Gaussians. Its formulas are those of :func:`frames.triangle_frames`,
:func:`rotations.matrix_to_quaternion` and :func:`rotations.quaternion_multiply`, with the same
degenerate-triangle fallbacks, the same comparisons (a NaN fails every `>` test and so takes the
fallback, as in `torch.where`), NaN propagated through the k floor as `clamp` does, and NaN
winning `argmax`/`argmin` as in torch.

The numba twin computes in float64 inside, the output has the input dtype. In float64 it equals
the torch reference to rounding (~1e-15). In float32 it equals it to float32 rounding (~1e-7)
except where float32 itself breaks down in the reference: squared edge or cross-product lengths
that overflow float32 (triangles over ~1e9 in size) or nearly collinear corners whose normal
float32 rounding decides; there the twin gives the float64 answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ..rotations import matrix_to_quaternion, quaternion_multiply
from .frames import COLLINEAR_SIN, MIN_SCALE, triangle_frames

__all__ = ["BACKENDS", "FaceFrames", "bind_gaussians", "bind_gaussians_np",
           "bind_gaussians_numba", "bind_gaussians_torch", "can_use_numba"]

BACKENDS = ("auto", "torch", "numba")


# -- the torch reference ------------------------------------------------------------------


@dataclass(frozen=True)
class FaceFrames:
    """Per-triangle frames of a posed mesh (``triangle_frames``) and their quaternions."""

    rot: Tensor    # [F, 3, 3]
    quat: Tensor   # [F, 4] (w, x, y, z), w >= 0
    trans: Tensor  # [F, 3]
    scale: Tensor  # [F]

    @classmethod
    def of_mesh(cls, vertices: Tensor, faces: Tensor) -> FaceFrames:
        """Frames of ``vertices`` [V, 3] on ``faces`` [F, 3]. The corners are gathered with
        ``index_select`` into a triangle soup first: the backward of ``vertices[idx]`` with
        repeated indices (inside ``triangle_frames``) accumulates in a thread-dependent
        order on the CPU, index_select's does not, so fine-tuning stays bit-reproducible."""
        soup = torch.index_select(vertices, 0, faces.reshape(-1))  # [3F, 3]
        corners = torch.arange(soup.shape[0], device=faces.device).view(-1, 3)
        return cls.of_frames(*triangle_frames(soup, corners))

    @classmethod
    def of_frames(cls, rot: Tensor, trans: Tensor, scale: Tensor) -> FaceFrames:
        """Frames given as rot [F, 3, 3], trans [F, 3], scale [F]."""
        return cls(rot, matrix_to_quaternion(rot), trans, scale)


def bind_gaussians_torch(frames: FaceFrames, parents: Tensor, local_means: Tensor,
                         quats: Tensor, scales: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The reference: world means [N, 3], quaternions [N, 4] and scales [N, 3] of Gaussians
    with ``parents`` [N], ``local_means`` [N, 3], ``quats`` [N, 4] and linear ``scales`` [N, 3]
    (exp of the log-scales). Face quaternions are computed once per triangle, not per
    Gaussian; gathers use ``index_select``, whose backward is reproducible (see ``of_mesh``)."""

    def take(x: Tensor) -> Tensor:  # x[parents]
        return torch.index_select(x, 0, parents)

    r, t, k = take(frames.rot), take(frames.trans), take(frames.scale)  # [N, 3, 3], [N, 3], [N]
    local = (r * local_means[:, None, :]).sum(-1)  # [N, 3] = R mean
    return (k[:, None] * local + t, quaternion_multiply(take(frames.quat), quats),
            k[:, None] * scales)


# -- the numba twin -----------------------------------------------------------------------


_EPS = 1e-12   # triangle_frames' default eps
_TINY = 1e-30  # frames._TINY
_COLLINEAR_SQ = COLLINEAR_SIN * COLLINEAR_SIN
_f64 = np.float64  # float() of a float32 stays float32 in numba: widen explicitly


@njit(cache=True, nogil=True, inline="always")
def _norm(x, y, z):
    return math.sqrt(x * x + y * y + z * z + _TINY)


@njit(cache=True, nogil=True, inline="always")
def _argmax3(a, b, c):
    """torch.argmax over 3 values: the first NaN, else the first maximum."""
    if a != a:
        return 0
    if b != b:
        return 1
    if c != c:
        return 2
    i, m = 0, a
    if b > m:
        i, m = 1, b
    if c > m:
        i = 2
    return i


@njit(cache=True, nogil=True, inline="always")
def _argmin3(a, b, c):
    """torch.argmin over 3 values: the first NaN, else the first minimum."""
    return _argmax3(-a, -b, -c)  # negation keeps NaN and the order of ties


@njit(cache=True, nogil=True, inline="always")
def _perpendicular(ux, uy, uz):
    """frames._perpendicular: u x (the axis least aligned to u), normalised."""
    j = _argmin3(abs(ux), abs(uy), abs(uz))
    if j == 0:    # u x (1, 0, 0)
        px, py, pz = 0.0, uz, -uy
    elif j == 1:  # u x (0, 1, 0)
        px, py, pz = -uz, 0.0, ux
    else:         # u x (0, 0, 1)
        px, py, pz = uy, -ux, 0.0
    n = _norm(px, py, pz)
    return px / n, py / n, pz / n


@njit(cache=True, nogil=True, inline="always")
def _index(i, n):
    """A torch-style index (negative counts from the end), or -1 when out of range."""
    if i < 0:
        i += n
    return i if 0 <= i < n else -1


@njit(parallel=True, cache=True, nogil=True)
def _face_kernel(vertices, faces, frames):
    """frames [F, 17] float64: R row-major (9), T (3), k (1), q (w, x, y, z) (4).
    Returns the number of faces with an out-of-range corner index (left unwritten)."""
    nv = vertices.shape[0]
    bad = 0
    for f in prange(faces.shape[0]):
        i0, i1, i2 = _index(faces[f, 0], nv), _index(faces[f, 1], nv), _index(faces[f, 2], nv)
        if i0 < 0 or i1 < 0 or i2 < 0:
            bad += 1
            continue
        ax, ay, az = _f64(vertices[i0, 0]), _f64(vertices[i0, 1]), _f64(vertices[i0, 2])
        bx, by, bz = _f64(vertices[i1, 0]), _f64(vertices[i1, 1]), _f64(vertices[i1, 2])
        cx, cy, cz = _f64(vertices[i2, 0]), _f64(vertices[i2, 1]), _f64(vertices[i2, 2])
        e01x, e01y, e01z = bx - ax, by - ay, bz - az
        e02x, e02y, e02z = cx - ax, cy - ay, cz - az
        e12x, e12y, e12z = cx - bx, cy - by, cz - bz
        n01 = _norm(e01x, e01y, e01z)
        # edge: e01, else the longest edge, else +x
        if n01 > _EPS:
            d = n01 if n01 > _EPS else _EPS
            ex, ey, ez = e01x / d, e01y / d, e01z / d
        else:
            j = _argmax3(n01, _norm(e02x, e02y, e02z), _norm(e12x, e12y, e12z))
            if j == 0:
                lx, ly, lz = e01x, e01y, e01z
            elif j == 1:
                lx, ly, lz = e02x, e02y, e02z
            else:
                lx, ly, lz = e12x, e12y, e12z
            nl = _norm(lx, ly, lz)
            if nl > _EPS:
                ex, ey, ez = lx / nl, ly / nl, lz / nl
            else:
                ex, ey, ez = 1.0, 0.0, 0.0
        # normal: e01 x e02, else perpendicular to the edge
        crx = e01y * e02z - e01z * e02y
        cry = e01z * e02x - e01x * e02z
        crz = e01x * e02y - e01y * e02x
        nc = _norm(crx, cry, crz)
        cross_sq = crx * crx + cry * cry + crz * crz
        span_sq = (e01x * e01x + e01y * e01y + e01z * e01z) * (
            e02x * e02x + e02y * e02y + e02z * e02z)
        if cross_sq <= _COLLINEAR_SQ * span_sq:  # collinear corners (NaN: not flat, as torch)
            nx, ny, nz = _perpendicular(ex, ey, ez)
        else:
            nx, ny, nz = crx / nc, cry / nc, crz / nc
        # re-orthogonalise against the edge
        dot = nx * ex + ny * ey + nz * ez
        nx, ny, nz = nx - dot * ex, ny - dot * ey, nz - dot * ez
        nn = _norm(nx, ny, nz)
        if nn > _EPS:
            nx, ny, nz = nx / nn, ny / nn, nz / nn
        else:
            nx, ny, nz = _perpendicular(ex, ey, ez)
        # binormal = normal x edge
        bnx = ny * ez - nz * ey
        bny = nz * ex - nx * ez
        bnz = nx * ey - ny * ex
        # R's columns: edge, binormal, normal
        m00, m01, m02 = ex, bnx, nx
        m10, m11, m12 = ey, bny, ny
        m20, m21, m22 = ez, bnz, nz
        frames[f, 0], frames[f, 1], frames[f, 2] = m00, m01, m02
        frames[f, 3], frames[f, 4], frames[f, 5] = m10, m11, m12
        frames[f, 6], frames[f, 7], frames[f, 8] = m20, m21, m22
        frames[f, 9] = (ax + bx + cx) / 3.0
        frames[f, 10] = (ay + by + cy) / 3.0
        frames[f, 11] = (az + bz + cz) / 3.0
        edge_len = n01
        height = nc / (edge_len if not (edge_len < _EPS) else _EPS)  # clamp keeps NaN
        k = 0.5 * (edge_len + height)
        frames[f, 12] = k if not (k < MIN_SCALE) else MIN_SCALE
        # matrix_to_quaternion: Shepperd, the best-conditioned of four, then w >= 0
        c0 = 1.0 + m00 + m11 + m22
        c1 = 1.0 + m00 - m11 - m22
        c2 = 1.0 - m00 + m11 - m22
        c3 = 1.0 - m00 - m11 + m22
        q0 = math.sqrt(c0) if c0 > 0 else 0.0
        q1 = math.sqrt(c1) if c1 > 0 else 0.0
        q2 = math.sqrt(c2) if c2 > 0 else 0.0
        q3 = math.sqrt(c3) if c3 > 0 else 0.0
        d21, d02, d10 = m21 - m12, m02 - m20, m10 - m01
        s10, s02, s21 = m10 + m01, m02 + m20, m21 + m12
        # first maximum (q_abs is never NaN: a NaN candidate fails `> 0` and gives 0)
        best, qa = 0, q0
        if q1 > qa:
            best, qa = 1, q1
        if q2 > qa:
            best, qa = 2, q2
        if q3 > qa:
            best, qa = 3, q3
        if best == 0:
            w, x, y, z = q0 * q0, d21, d02, d10
        elif best == 1:
            w, x, y, z = d21, q1 * q1, s10, s02
        elif best == 2:
            w, x, y, z = d02, s10, q2 * q2, s21
        else:
            w, x, y, z = d10, s02, s21, q3 * q3
        den = 2.0 * (qa if not (qa < 0.1) else 0.1)
        w, x, y, z = w / den, x / den, y / den, z / den
        if w < 0:
            w, x, y, z = -w, -x, -y, -z
        frames[f, 13], frames[f, 14], frames[f, 15], frames[f, 16] = w, x, y, z
    return bad


@njit(parallel=True, cache=True, nogil=True)
def _gaussian_kernel(fr, parents, local_means, scales, quats, means_out, quats_out,
                     scales_out):
    """World means, quaternions (q_face * q_local) and scales (k * scale) of each Gaussian.
    Returns the number of Gaussians with an out-of-range parent (left unwritten)."""
    nf = fr.shape[0]
    bad = 0
    for g in prange(parents.shape[0]):
        f = _index(parents[g], nf)
        if f < 0:
            bad += 1
            continue
        k = fr[f, 12]
        mx, my, mz = _f64(local_means[g, 0]), _f64(local_means[g, 1]), _f64(local_means[g, 2])
        means_out[g, 0] = k * (fr[f, 0] * mx + fr[f, 1] * my + fr[f, 2] * mz) + fr[f, 9]
        means_out[g, 1] = k * (fr[f, 3] * mx + fr[f, 4] * my + fr[f, 5] * mz) + fr[f, 10]
        means_out[g, 2] = k * (fr[f, 6] * mx + fr[f, 7] * my + fr[f, 8] * mz) + fr[f, 11]
        aw, ax, ay, az = fr[f, 13], fr[f, 14], fr[f, 15], fr[f, 16]
        bw, bx, by, bz = (_f64(quats[g, 0]), _f64(quats[g, 1]), _f64(quats[g, 2]),
                          _f64(quats[g, 3]))
        quats_out[g, 0] = aw * bw - ax * bx - ay * by - az * bz
        quats_out[g, 1] = aw * bx + ax * bw + ay * bz - az * by
        quats_out[g, 2] = aw * by - ax * bz + ay * bw + az * bx
        quats_out[g, 3] = aw * bz + ax * by - ay * bx + az * bw
        scales_out[g, 0] = k * _f64(scales[g, 0])
        scales_out[g, 1] = k * _f64(scales[g, 1])
        scales_out[g, 2] = k * _f64(scales[g, 2])
    return bad


def bind_gaussians_np(vertices: np.ndarray, faces: np.ndarray, parents: np.ndarray,
                      local_means: np.ndarray, scales: np.ndarray, quats: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World means [N, 3], quaternions [N, 4] and scales [N, 3] (the dtype of `local_means`).

    vertices [V, 3], faces [F, 3] int, parents [N] int, local_means [N, 3], scales [N, 3]
    (linear, exp of the log-scales), quats [N, 4] (w, x, y, z). Indices follow torch: negative
    ones count from the end; out-of-range ones raise IndexError.
    """
    dtype = local_means.dtype
    n = parents.shape[0]
    frames = np.empty((faces.shape[0], 17), dtype=np.float64)
    means = np.empty((n, 3), dtype=dtype)
    quats_out = np.empty((n, 4), dtype=dtype)
    scales_out = np.empty((n, 3), dtype=dtype)
    if faces.shape[0] and _face_kernel(vertices, faces, frames):
        raise IndexError(f"faces index outside the {vertices.shape[0]} vertices")
    if n and _gaussian_kernel(frames, parents, local_means, scales, quats, means, quats_out,
                              scales_out):
        raise IndexError(f"parents index outside the {faces.shape[0]} faces")
    return means, quats_out, scales_out


def can_use_numba(tensors: tuple[Tensor, ...], vertices: Tensor, faces: Tensor) -> bool:
    """The numba twin computes exactly what the torch reference does for these inputs, and no
    gradient is asked for: CPU tensors, vertices [V, 3] of the Gaussians' (float) dtype."""
    if vertices.device.type != "cpu" or faces.device.type != "cpu" or vertices.dim() != 2 \
            or vertices.shape[-1] != 3 or faces.dim() != 2 or faces.shape[-1] != 3 \
            or faces.dtype not in (torch.int64, torch.int32) \
            or vertices.dtype not in (torch.float32, torch.float64):
        return False
    if torch.is_grad_enabled() and (vertices.requires_grad
                                    or any(t.requires_grad for t in tensors)):
        return False
    return all(t.device.type == "cpu" and (t.dtype == vertices.dtype or not t.is_floating_point())
               for t in tensors)


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def bind_gaussians_numba(vertices: Tensor, faces: Tensor, parents: Tensor, local_means: Tensor,
                         quats: Tensor, scales: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The twin on torch tensors (see :func:`can_use_numba`): vertices [V, 3], faces [F, 3],
    the rest as :func:`bind_gaussians_torch`."""
    means, q, s = bind_gaussians_np(_np(vertices), _np(faces), _np(parents), _np(local_means),
                                    _np(scales), _np(quats))
    return torch.from_numpy(means), torch.from_numpy(q), torch.from_numpy(s)


# -- dispatch -----------------------------------------------------------------------------


def bind_gaussians(vertices: Tensor, faces: Tensor, parents: Tensor, local_means: Tensor,
                   quats: Tensor, scales: Tensor, *, backend: str = "auto"
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """World means [N, 3], quaternions [N, 4] and scales [N, 3] of Gaussians bound to the
    mesh ``vertices`` [V, 3], ``faces`` [F, 3]. ``backend`` "auto": the numba twin on the CPU
    when no gradient is asked for (:func:`can_use_numba`), else the torch reference."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    tensors = (parents, local_means, quats, scales)
    if backend == "numba" or (backend == "auto" and can_use_numba(tensors, vertices, faces)):
        return bind_gaussians_numba(vertices, faces, parents, local_means, quats, scales)
    # torch indexing semantics, as the twin's: negative indices count from the end
    faces, parents = _wrap(faces, vertices.shape[0]), _wrap(parents, faces.shape[0])
    return bind_gaussians_torch(FaceFrames.of_mesh(vertices, faces), parents, local_means,
                                quats, scales)


def _wrap(index: Tensor, n: int) -> Tensor:
    """Negative indices from the end (index_select takes none); out-of-range ones stay so and
    raise IndexError there."""
    return torch.where(index < 0, index + n, index)
