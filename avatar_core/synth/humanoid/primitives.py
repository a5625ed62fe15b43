"""Geometric primitives: smooth bands, knotted profiles, ring grids, tubes and lofted
cross-sections, and the weight blends used for skinning."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from .names import _NJ


def _smoothstep(e0: float, e1: float, x) -> np.ndarray:
    """0 at e0, 1 at e1 (either order), C1; exactly 0/1 outside the band."""
    t = np.clip((np.asarray(x, dtype=np.float64) - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _gauss(d2, sigma: float) -> np.ndarray:
    return np.exp(-0.5 * np.asarray(d2) / sigma**2)


def _count(n: int, res: float, lo: int = 1) -> int:
    """Sample count for `n` at resolution 1; areas scale ~linearly with `res`."""
    return max(lo, int(round(n * np.sqrt(res))))


def _knotted(knots, counts, res: float, lo=1) -> tuple[np.ndarray, list[int]]:
    """Samples from knots[0] to knots[-1] hitting every knot; returns samples, knot indices.
    `lo`: the least number of intervals per segment (one value or one per segment)."""
    out, idx = [np.array([knots[0]], dtype=np.float64)], [0]
    los = np.broadcast_to(lo, (len(counts),))
    for a, b, n, least in zip(knots[:-1], knots[1:], counts, los, strict=True):
        m = _count(n, res, int(least))
        out.append(np.linspace(a, b, m + 1)[1:])
        idx.append(idx[-1] + m)
    return np.concatenate(out), idx


def _pchip(xk, table) -> PchipInterpolator:
    """Monotone cubic through control rows (columns of `table`), for smooth profiles."""
    return PchipInterpolator(np.asarray(xk, float), np.asarray(table, float), axis=0,
                             extrapolate=True)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _one_hot(n: int, joint: int) -> np.ndarray:
    w = np.zeros((n, _NJ))
    w[:, joint] = 1.0
    return w


def _chain_weights(s: np.ndarray, joints, bands) -> np.ndarray:
    """Skinning along a chain: segment k (after joint k) follows joints[k]; band k = (a, b)
    hands joints[k] over to joints[k + 1] with a smoothstep (SMPL convention). [n, 55]."""
    w = np.zeros((len(s), _NJ))
    carry = np.ones(len(s))
    for k, (a, b) in enumerate(bands):
        step = _smoothstep(a, b, s)
        w[:, joints[k]] += carry * (1.0 - step)
        carry = carry * step
    w[:, joints[-1]] += carry
    return w


def _blend(w: np.ndarray, alpha: np.ndarray, joint: int) -> np.ndarray:
    """Mix weights toward a single joint by `alpha` in [0, 1]."""
    out = w * (1.0 - alpha)[:, None]
    out[:, joint] += alpha
    return out


@dataclass
class _Grid:
    """A rows x columns vertex grid with optional poles and slits (see `_grid_mesh`)."""

    verts: np.ndarray  # [n, 3]
    faces: np.ndarray  # [f, 3]
    row: np.ndarray  # [n] ring index (-1 bottom pole, R top pole)
    col: np.ndarray  # [n]
    dup: np.ndarray  # [n] bool: the lower copy of a slit vertex
    cols: int


def _grid_mesh(rings, bottom=None, top=None, wrap=False, slits=()) -> _Grid:
    """Triangulate stacked rings [R, C, 3] (around x along = outward) into a surface.

    A slit (row, cols) duplicates those vertices of `row`: the original is used by the quads
    above, the copy by the quads below, so the surface can open there. Quad (r, j) yields
    faces 2 * (r * J + j) + {0, 1}, J = C (wrap) or C - 1; pole fans come last.
    """
    rows_n, c = rings.shape[:2]
    grid = np.arange(rows_n * c).reshape(rows_n, c)
    up, down = grid.copy(), grid.copy()
    verts = [rings.reshape(-1, 3)]
    row, col = np.repeat(np.arange(rows_n), c), np.tile(np.arange(c), rows_n)
    dup = np.zeros(rows_n * c, dtype=bool)
    n = rows_n * c
    for r, cs in slits:
        cs = np.asarray(cs)
        down[r, cs] = n + np.arange(len(cs))
        n += len(cs)
        verts.append(rings[r, cs])
        row = np.concatenate([row, np.full(len(cs), r)])
        col = np.concatenate([col, cs])
        dup = np.concatenate([dup, np.ones(len(cs), dtype=bool)])
    jj = np.arange(c if wrap else c - 1)
    jn = (jj + 1) % c
    a, b = up[:-1][:, jj], up[:-1][:, jn]
    cc, d = down[1:][:, jn], down[1:][:, jj]
    faces = [np.stack([np.stack([a, b, cc], -1), np.stack([a, cc, d], -1)], axis=2).reshape(-1, 3)]
    for pole, r in ((bottom, 0), (top, rows_n - 1)):
        if pole is None:
            continue
        p = np.full(len(jj), n)
        faces.append(np.stack([p, down[0, jn], down[0, jj]], -1) if r == 0
                     else np.stack([p, up[r, jj], up[r, jn]], -1))
        verts.append(np.asarray(pole, float)[None])
        row = np.concatenate([row, [-1 if r == 0 else rows_n]])
        col = np.concatenate([col, [0]])
        dup = np.concatenate([dup, [False]])
        n += 1
    return _Grid(np.concatenate(verts), np.concatenate(faces).astype(np.int64), row, col, dup, c)


def _frames(centers: np.ndarray, up) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangent t and ring axes e1 (toward `up`), e2 = t x e1 along a path. [K, 3] each."""
    t = _unit(np.gradient(centers, axis=0))
    up = np.broadcast_to(np.asarray(up, float), t.shape)
    e1 = _unit(up - np.sum(up * t, axis=1, keepdims=True) * t)
    return t, e1, np.cross(t, e1)


def _tube(centers, ra, rb, n_around: int, up=(0.0, 1.0, 0.0), start=None, end=None,
          expo: float = 2.0, frames=None) -> _Grid:
    """Closed tube of (super)elliptic rings (radius ra along e1, rb along e2) with end poles."""
    t, e1, e2 = _frames(centers, up) if frames is None else frames
    al = 2.0 * np.pi * np.arange(n_around) / n_around
    c, s = np.cos(al), np.sin(al)
    c, s = np.sign(c) * np.abs(c) ** (2 / expo), np.sign(s) * np.abs(s) ** (2 / expo)
    rings = (centers[:, None] + np.asarray(ra)[:, None, None] * c[None, :, None] * e1[:, None]
             + np.asarray(rb)[:, None, None] * s[None, :, None] * e2[:, None])
    return _grid_mesh(rings, start, end, wrap=True)


def _along(points: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Positions at arc length `s` on a polyline (s = 0 at points[0], linear past the ends)."""
    seg = np.diff(points, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    u = (s - cum[i]) / (cum[i + 1] - cum[i])
    return points[i] + u[:, None] * seg[i]


def _sections(rx, zc, rzf, rzb, nf, nb, dense: int = 241):
    """Dense half cross-sections (front z+ -> +x side -> back) per row. Each [R, D]."""
    th = np.linspace(0.0, np.pi, dense)
    s, c = np.abs(np.sin(th)), np.cos(th)
    front = c >= 0
    n = np.where(front, np.asarray(nf)[:, None], np.asarray(nb)[:, None])
    rz = np.where(front, np.asarray(rzf)[:, None], np.asarray(rzb)[:, None])
    x = np.asarray(rx)[:, None] * s ** (2.0 / n)
    z = np.asarray(zc)[:, None] + np.sign(c) * rz * np.abs(c) ** (2.0 / n)
    arc = np.concatenate([np.zeros((len(x), 1)),
                          np.cumsum(np.hypot(np.diff(x, axis=1), np.diff(z, axis=1)), axis=1)], 1)
    return x, z, arc / arc[:, -1:]


def _loft_rings(y, prof, t) -> np.ndarray:
    """Half rings [R, C, 3] of an x-symmetric loft; columns at arc fractions `t` (0 front, 1
    back); prof = (rx, zc, rzf, rzb, nf, nb) per row. Seam columns get x = 0 exactly."""
    x, z, arc = _sections(*prof)
    out = np.empty((len(y), len(t), 3))
    for r in range(len(y)):
        out[r, :, 0] = np.interp(t, arc[r], x[r])
        out[r, :, 2] = np.interp(t, arc[r], z[r])
    out[:, :, 1] = np.asarray(y)[:, None]
    out[:, 0, 0] = 0.0
    out[:, -1, 0] = 0.0
    return out


def _t_at_x(prof_row, x: float) -> float:
    """Arc fraction on the front half of one cross-section where it reaches `x`."""
    xs, _, arc = _sections(*[np.atleast_1d(p) for p in prof_row])
    half = xs.shape[1] // 2 + 1
    return float(np.interp(x, xs[0, :half], arc[0, :half]))
