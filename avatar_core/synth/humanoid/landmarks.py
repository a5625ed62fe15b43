"""iBUG-68 face landmarks placed on the head grid."""

from __future__ import annotations

import numpy as np

from .head import _BROW_Y, _MOUTH_X, _MOUTH_Y, _brow_center, _HeadGrid
from .names import _IBUG_FLIP
from .primitives import _t_at_x


def _landmarks(hg: _HeadGrid, head_face0: int, nfh: int):
    """iBUG-68 points on the head grid: left/midline ones placed, right ones mirrored.
    Returns (faces [68], bary [68, 3]) in full-mesh face indices."""
    r_of_y = lambda y: float(np.interp(y, hg.y, np.arange(len(hg.y))))  # noqa: E731
    c_of_t = lambda t: float(np.interp(t, hg.t, np.arange(len(hg.t))))  # noqa: E731

    def at_x(y, x):
        row = [np.interp(r_of_y(y), np.arange(len(hg.y)), p) for p in hg.prof]
        return c_of_t(_t_at_x(row, x))

    ncq = len(hg.t) - 1

    def loc(r, c, below=False):
        ri = int(np.floor(r + 1e-12))
        u = r - ri
        if below and u < 1e-12:
            ri, u = ri - 1, 1.0
        ci = int(min(np.floor(c + 1e-12), ncq - 1))
        v = c - ci
        q = 2 * (ri * ncq + ci)
        if u <= v:
            return head_face0 + q, (1 - v, v - u, u)
        return head_face0 + q + 1, (1 - u, v, u - v)

    rm, re_ = hg.row_mouth, hg.row_eye
    ci, co = hg.col_eye_in, hg.col_eye_out
    pts = {}
    brow_x = np.linspace(0.014, 0.052, 5)
    for k, xb in enumerate(brow_x):  # 22 (inner) .. 26 (outer)
        pts[22 + k] = (r_of_y(float(_brow_center(np.array([xb]))[0])), at_x(_BROW_Y, xb))
    for k, yl in enumerate([0.004, -0.0095, -0.021, -0.030]):  # 27..30 bridge to tip
        pts[27 + k] = (r_of_y(yl), 0.0)
    pts[33] = (r_of_y(-0.0405), 0.0)
    pts[34] = (r_of_y(-0.038), at_x(-0.038, 0.0065))
    pts[35] = (r_of_y(-0.0355), at_x(-0.0355, 0.0125))
    pts[42] = (re_, ci)
    pts[45] = (re_, co)
    pts[43] = (re_, ci + (co - ci) / 3)
    pts[44] = (re_, ci + 2 * (co - ci) / 3)
    pts[46] = (re_, ci + 2 * (co - ci) / 3, True)
    pts[47] = (re_, ci + (co - ci) / 3, True)
    pts[51] = (r_of_y(_MOUTH_Y + 0.0085), 0.0)
    pts[52] = (r_of_y(_MOUTH_Y + 0.0088), at_x(_MOUTH_Y + 0.0088, 0.009))
    pts[53] = (r_of_y(_MOUTH_Y + 0.005), at_x(_MOUTH_Y + 0.005, 0.019))
    pts[54] = (rm, at_x(_MOUTH_Y, _MOUTH_X + 0.002))
    pts[55] = (r_of_y(_MOUTH_Y - 0.0065), at_x(_MOUTH_Y - 0.0065, 0.018))
    pts[56] = (r_of_y(_MOUTH_Y - 0.009), at_x(_MOUTH_Y - 0.009, 0.009))
    pts[57] = (r_of_y(_MOUTH_Y - 0.0095), 0.0)
    pts[62] = (rm, 0.0)
    pts[63] = (rm, at_x(_MOUTH_Y, 0.012))
    pts[64] = (rm, float(hg.col_mouth))
    pts[65] = (rm, at_x(_MOUTH_Y, 0.012), True)
    pts[66] = (rm, 0.0, True)
    contour = [(-0.1195, 0.0), (-0.117, 0.05), (-0.112, 0.10), (-0.104, 0.15), (-0.094, 0.20),
               (-0.080, 0.245), (-0.062, 0.27), (-0.042, 0.285), (-0.020, 0.295)]
    for k, (yl, t) in enumerate(contour):  # 8 (chin) .. 16 (left ear)
        pts[8 + k] = (r_of_y(yl), c_of_t(t))
    faces = np.zeros(68, dtype=np.int64)
    bary = np.zeros((68, 3))
    for i, spec in pts.items():
        f, w = loc(*spec)
        faces[i], bary[i] = f, w
        m = _IBUG_FLIP[i]
        if m != i:  # the mirrored face has its winding reversed
            faces[m], bary[m] = f + nfh, (w[0], w[2], w[1])
    return faces, bary
