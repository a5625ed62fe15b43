"""The trunk: torso and neck."""

from __future__ import annotations

import numpy as np

from avatar_core.body.skeleton import JOINT

from .names import _MAT, _PART
from .pieces import _half_seam, _Piece, _piece
from .primitives import (
    _blend,
    _chain_weights,
    _grid_mesh,
    _knotted,
    _loft_rings,
    _pchip,
    _smoothstep,
)
from .proportions import _Body

_TORSO = np.array([  # y, rx, zc, rzf, rzb, n (superellipse exponent)
    (-0.160, 0.060, 0.000, 0.050, 0.060, 2.0),
    (-0.145, 0.100, -0.008, 0.048, 0.078, 2.2),
    (-0.120, 0.140, -0.008, 0.068, 0.098, 2.3),
    (-0.080, 0.158, -0.008, 0.082, 0.108, 2.4),
    (-0.030, 0.162, -0.006, 0.088, 0.104, 2.4),
    (0.030, 0.151, -0.004, 0.090, 0.092, 2.4),
    (0.085, 0.142, -0.004, 0.092, 0.085, 2.4),
    (0.150, 0.146, -0.002, 0.098, 0.086, 2.5),
    (0.220, 0.156, 0.000, 0.110, 0.090, 2.5),
    (0.290, 0.162, 0.000, 0.115, 0.093, 2.6),
    (0.350, 0.168, -0.004, 0.105, 0.092, 2.7),
    (0.400, 0.178, -0.010, 0.086, 0.085, 2.8),
    (0.428, 0.182, -0.014, 0.070, 0.072, 3.0),
    (0.448, 0.160, -0.016, 0.060, 0.064, 3.0),
    (0.468, 0.125, -0.018, 0.056, 0.062, 2.8),
    (0.482, 0.072, -0.018, 0.054, 0.060, 2.4),
])


def _torso_profile(b: _Body, y: np.ndarray):
    """Cross-section parameters of the trunk at heights y (world)."""
    tab = _TORSO.copy()
    tab[:, 0] *= b.height
    p = _pchip(tab[:, 0], tab[:, 1:])(y)
    wide = np.interp(y, [0.0, 0.25], [b.hips, b.shoulders])
    rx = p[:, 0] * wide * (0.5 + 0.5 * b.girth)
    return rx, p[:, 1], p[:, 2] * b.girth, p[:, 3] * b.girth, p[:, 4], p[:, 4]


def _torso(b: _Body, res: float) -> _Piece:
    h, j = b.height, b.j
    knots = [-0.160 * h, j["left_hip"][1], 0.0, j["spine1"][1], j["spine2"][1], j["spine3"][1],
             0.40 * h, 0.482 * h]
    y, _ = _knotted(knots, [6, 6, 7, 8, 4, 9, 9], res)
    prof = _torso_profile(b, y)
    t, _ = _knotted([0.0, 1.0], [20], res, lo=8)
    g = _grid_mesh(_loft_rings(y, prof, t), bottom=(0.0, -0.166 * h, -0.002),
                   top=(0.0, 0.488 * h, -0.018), slits=())
    v = g.verts
    x, yy = v[:, 0], v[:, 1]
    part = np.select([yy < 0.06 * h, yy < 0.17 * h, yy < 0.28 * h], [_PART["hips"],
                     _PART["spine"], _PART["spine1"]], _PART["spine2"])
    part = np.where((x > 0.075 * b.shoulders) & (yy > 0.40 * h), _PART["leftShoulder"], part)
    material = np.where(yy > 0.02 * h, _MAT["shirt"], _MAT["trousers"])
    w = _chain_weights(yy, [JOINT["pelvis"], JOINT["spine1"], JOINT["spine2"], JOINT["spine3"]],
                       [(j["spine1"][1] - 0.04, j["spine1"][1] + 0.03),
                        (j["spine2"][1] - 0.04, j["spine2"][1] + 0.02),
                        (j["spine3"][1] - 0.02, j["spine3"][1] + 0.04)])
    # The buttocks follow the thigh; the top of the shoulder follows collar and shoulder.
    hip_y = j["left_hip"][1]
    w = _blend(w, 0.6 * _smoothstep(hip_y + 0.04, hip_y - 0.06, yy) * _smoothstep(0.02, 0.09, x),
               JOINT["left_hip"])
    top = _smoothstep(j["left_shoulder"][1] - 0.11, j["left_shoulder"][1] - 0.03, yy)
    sx = j["left_shoulder"][0]
    w = _blend(w, top * _smoothstep(0.035, 0.10, x) * (1 - _smoothstep(sx - 0.04, sx + 0.01, x)),
               JOINT["left_collar"])
    w = _blend(w, top * _smoothstep(sx - 0.04, sx + 0.01, x), JOINT["left_shoulder"])
    axis = np.stack([np.zeros_like(yy), yy, _torso_profile(b, yy)[1]], 1)
    return _piece("torso", g, part, material, w, seam=_half_seam(g), axis=axis)


def _neck(b: _Body, res: float) -> _Piece:
    yn, yh = b.j["neck"][1], b.j["head"][1]
    y, _ = _knotted([0.43 * b.height, yn - 0.045, yn - 0.009, yn, yn + 0.009, yh, yh + 0.02],
                    [2, 3, 1, 1, 4, 2], res)
    u = (y - y[0]) / (y[-1] - y[0])
    s = b.head_s * (0.5 + 0.5 * b.girth)
    rx = s * (0.057 - 0.005 * u)
    zc = np.interp(y, [y[0], yn, yh], [b.j["neck"][2] + 0.002, b.j["neck"][2], -0.008])
    prof = (rx, zc, s * (0.052 - 0.002 * u), s * (0.060 - 0.004 * u), np.full_like(y, 2.1),
            np.full_like(y, 2.1))
    t, _ = _knotted([0.0, 1.0], [12], res, lo=6)
    g = _grid_mesh(_loft_rings(y, prof, t), bottom=(0.0, y[0] - 0.006, zc[0]),
                   top=(0.0, y[-1] + 0.006, zc[-1]))
    yy = g.verts[:, 1]
    w = _chain_weights(yy, [JOINT["spine3"], JOINT["neck"], JOINT["head"]],
                       [(yn - 0.045, yn - 0.0105), (yh - 0.02, yh + 0.02)])
    axis = np.stack([np.zeros_like(yy), yy, np.interp(yy, y, zc)], 1)
    return _piece("neck", g, _PART["neck"], _MAT["skin"], w, seam=_half_seam(g),
                  flame=yy >= yn - 0.0095, axis=axis)
