"""`_Piece`: one part of the half mesh with its per-vertex attributes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .primitives import _Grid


@dataclass
class _Piece:
    """One part of the half mesh with its per-vertex attributes (local vertex indices)."""

    kind: str
    verts: np.ndarray  # [n, 3]
    faces: np.ndarray  # [f, 3]
    seam: np.ndarray  # [n] bool: on x = 0, its own mirror
    part: np.ndarray  # [n]
    material: np.ndarray  # [n]
    weights: np.ndarray  # [n, 55]
    flame: np.ndarray  # [n] bool
    hand: np.ndarray  # [n] bool
    attrs: dict = field(default_factory=dict)


def _piece(kind, g: _Grid, part, material, weights, seam=None, flame=False, hand=False,
           **attrs) -> _Piece:
    n = len(g.verts)

    def arr(v, dtype):
        return np.broadcast_to(np.asarray(v, dtype=dtype), (n,)).copy()

    seam = np.zeros(n, dtype=bool) if seam is None else seam
    return _Piece(kind, g.verts, g.faces, seam, arr(part, np.int64), arr(material, np.int64),
                  weights, arr(flame, bool), arr(hand, bool), attrs)


def _half_seam(g: _Grid) -> np.ndarray:
    """Seam vertices of a half-ring grid: first and last columns and the poles."""
    return (g.col == 0) | (g.col == g.cols - 1) | (g.row < 0) | (g.row >= g.row.max())
