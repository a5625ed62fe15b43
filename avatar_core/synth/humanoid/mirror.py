"""Mirroring the half pieces into the full mesh (seam vertices shared)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .pieces import _Piece


@dataclass
class _Mirrored:
    """The half pieces followed by their mirror images (seam vertices shared)."""

    verts: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3]
    mirror: np.ndarray  # [V] mirror twin of each vertex
    seam: np.ndarray  # [Vh] bool, over the half
    off_seam: np.ndarray  # half vertices that got a mirrored copy (in copy order)
    start: dict  # id(piece) -> first vertex index
    face_start: dict  # id(piece) -> first face index
    num_half_faces: int

    def rows(self, a: np.ndarray) -> np.ndarray:
        """Extend a per-half-vertex array to all vertices (copies take their twin's value)."""
        return np.concatenate([a, a[self.off_seam]])

    def field(self, f: np.ndarray) -> np.ndarray:
        """Extend a mirror-symmetric displacement field [Vh, 3, k]: x is odd, y and z even."""
        f = f.copy()
        f[self.seam, 0] = 0.0
        return np.concatenate([f, f[self.off_seam] * np.array([-1.0, 1.0, 1.0])[:, None]])


def _mirror(pieces: list[_Piece]) -> _Mirrored:
    offs = np.cumsum([0] + [len(p.verts) for p in pieces])
    foffs = np.cumsum([0] + [len(p.faces) for p in pieces])
    nh = int(offs[-1])
    seam = np.concatenate([p.seam for p in pieces])
    vh = np.concatenate([p.verts for p in pieces])
    fh = np.concatenate([p.faces + o for p, o in zip(pieces, offs[:-1], strict=False)])
    twin = np.arange(nh)
    off_seam = np.flatnonzero(~seam)
    twin[off_seam] = nh + np.arange(len(off_seam))
    return _Mirrored(
        verts=np.concatenate([vh, vh[off_seam] * [-1.0, 1.0, 1.0]]),
        faces=np.concatenate([fh, twin[fh][:, [0, 2, 1]]]),  # reflected: winding reversed
        mirror=np.concatenate([twin, off_seam]), seam=seam, off_seam=off_seam,
        start={id(p): int(o) for p, o in zip(pieces, offs[:-1], strict=False)},
        face_start={id(p): int(o) for p, o in zip(pieces, foffs[:-1], strict=False)},
        num_half_faces=len(fh))
