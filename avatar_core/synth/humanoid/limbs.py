"""The limbs: arm, palm, fingers, leg and foot."""

from __future__ import annotations

import numpy as np

from avatar_core.body.skeleton import JOINT

from .names import _FINGER_NAMES, _MAT, _PART
from .pieces import _Piece, _piece
from .primitives import (
    _along,
    _chain_weights,
    _count,
    _frames,
    _gauss,
    _knotted,
    _one_hot,
    _pchip,
    _smoothstep,
    _tube,
)
from .proportions import _Body


def _profile(s, knots_s, values) -> np.ndarray:
    return _pchip(knots_s, values)(s)


def _arm(b: _Body, res: float) -> _Piece:
    j = b.j
    pts = np.stack([j["left_shoulder"], j["left_elbow"], j["left_wrist"]])
    lu = float(np.linalg.norm(pts[1] - pts[0]))
    sw = lu + float(np.linalg.norm(pts[2] - pts[1]))
    s_sleeve = 0.55 * lu
    s, _ = _knotted([-0.055, 0.0, s_sleeve, lu, sw - 0.05, sw - 0.018, sw, sw + 0.028],
                    [3, 6, 6, 11, 2, 2, 3], res, lo=[1, 1, 1, 1, 2, 1, 1])
    g_ = b.girth
    ks = [-0.06, -0.025, 0.0, 0.15 * lu, 0.35 * lu, 0.6 * lu, 0.85 * lu, lu,
          lu + 0.2 * (sw - lu), lu + 0.45 * (sw - lu), lu + 0.75 * (sw - lu), sw, sw + 0.015,
          sw + 0.03]
    ra = _profile(s, ks, [0.030, 0.040, 0.044, 0.044, 0.040, 0.038, 0.036, 0.035, 0.037, 0.033,
                          0.026, 0.0195, 0.017, 0.013])
    rb = _profile(s, ks, [0.036, 0.046, 0.050, 0.047, 0.043, 0.042, 0.039, 0.038, 0.043, 0.039,
                          0.032, 0.0285, 0.026, 0.020])
    sleeve = 0.004 * (1 - _smoothstep(s_sleeve - 0.004, s_sleeve + 0.001, s))
    ra, rb = ra * g_ + sleeve, rb * g_ + sleeve
    centers = _along(pts, s)
    g = _tube(centers, ra, rb, 2 * _count(8, res, 5), start=_along(pts, np.array([-0.062]))[0],
              end=_along(pts, np.array([sw + 0.034]))[0])
    sv = np.where(g.row < 0, -0.062, np.where(g.row >= len(s), sw + 0.034,
                                             s[np.clip(g.row, 0, len(s) - 1)]))
    part = np.select([sv < lu, sv < sw], [_PART["leftArm"], _PART["leftForeArm"]],
                     _PART["leftHand"])
    mat = np.where(sv < s_sleeve, _MAT["shirt"], _MAT["skin"])
    w = _chain_weights(sv, [JOINT["left_collar"], JOINT["left_shoulder"], JOINT["left_elbow"],
                            JOINT["left_wrist"]],
                       [(-0.03, 0.02), (lu - 0.03, lu + 0.03), (sw - 0.05, sw - 0.022)])
    return _piece("arm", g, part, mat, w, hand=sv >= sw - 0.021, s=sv,
                  axis=_along(pts, sv), lu=lu, sw=sw)


def _palm(b: _Body, res: float) -> _Piece:
    wr = b.j["left_wrist"]
    hs = b.hand_s
    xs = np.array([-0.017, -0.008, 0.0, 0.02, 0.045, 0.07, 0.088, 0.097])
    thick = np.array([0.0155, 0.017, 0.017, 0.016, 0.0148, 0.0138, 0.0125, 0.0105])
    half_w = np.array([0.024, 0.028, 0.031, 0.036, 0.041, 0.0435, 0.043, 0.036])
    xs_s, _ = _knotted([xs[0], xs[-1]], [11], res, lo=5)
    centers = wr + hs * np.stack([xs_s, np.full_like(xs_s, -0.001), np.full_like(xs_s, -0.003)], 1)
    g = _tube(centers, hs * np.interp(xs_s, xs, thick), hs * np.interp(xs_s, xs, half_w),
              2 * _count(7, res, 5), expo=3.0, start=wr + hs * np.array([-0.0205, -0.001, -0.003]),
              end=wr + hs * np.array([0.100, -0.001, -0.003]))
    v = g.verts
    loc = (v - wr) / hs
    # Slant the knuckle line: index knuckle further out than the pinky's.
    v[:, 0] += hs * 0.12 * (loc[:, 2] + 0.003) * _smoothstep(0.05, 0.09, loc[:, 0])
    w = _one_hot(len(v), JOINT["left_wrist"])
    fingers = b.fingers
    # Knuckle region follows the nearest finger's first joint (partition over fingers).
    kern = np.stack([_gauss((v[:, 2] - f[0][2]) ** 2, 0.011 * hs) for f in fingers[:4]], 1)
    kern /= kern.sum(1, keepdims=True)
    for k, name in enumerate(_FINGER_NAMES[:4]):
        x1 = fingers[k][0][0]
        alpha = _smoothstep(x1 - 0.026 * hs, x1 + 0.004 * hs, v[:, 0]) * kern[:, k]
        w[:, JOINT["left_wrist"]] -= alpha
        w[:, JOINT[f"left_{name}1"]] += alpha
    # Thenar region (the thumb's ball) follows the thumb's first joint a little.
    tb = fingers[4]
    d = np.linalg.norm(v - (tb[0] + 0.5 * (tb[1] - tb[0])), axis=1)
    alpha = 0.6 * _gauss(d**2, 0.014 * hs) * w[:, JOINT["left_wrist"]]
    w[:, JOINT["left_wrist"]] -= alpha
    w[:, JOINT["left_thumb1"]] += alpha
    return _piece("palm", g, _PART["leftHand"], _MAT["skin"], w, hand=True)


def _finger(b: _Body, res: float, k: int) -> _Piece:
    name = _FINGER_NAMES[k]
    p1, p2, p3, tip, r, d = b.fingers[k]
    l1, l2 = np.linalg.norm(p2 - p1), np.linalg.norm(p3 - p2)
    lt = np.linalg.norm(tip - p1)
    rt = 0.85 * r
    thumb = name == "thumb"
    back = 0.018 * b.hand_s if thumb else 0.014 * b.hand_s
    s, _ = _knotted([-back, 0.0, l1, l1 + l2, lt - rt], [2, 4, 3, 3], res)
    cap = lt - rt + rt * np.sin(np.linspace(0, np.pi / 2, _count(4, res, 2) + 2)[1:-1])
    s = np.concatenate([s, cap])
    ks = [-back, 0.0, 0.5 * l1, l1, l1 + 0.5 * l2, l1 + l2, lt - rt]
    base = [1.7, 1.6, 1.3] if thumb else [1.0, 1.0, 0.9]  # the thumb's ball (thenar)
    rr = _profile(s, ks, r * np.array([*base, 0.93, 0.84, 0.85, 0.8]))
    rr = np.where(s > lt - rt, rt * np.sqrt(np.clip(1 - ((s - lt + rt) / rt) ** 2, 0, 1)), rr)
    rr = np.maximum(rr, 0.18 * rt)
    centers = p1 + s[:, None] * d
    up = np.array([0.0, 1.0, 0.0]) if not thumb else np.array([0.0, 0.55, -0.85])
    g = _tube(centers, 0.86 * rr, rr, 2 * _count(4, res, 3), up=up, start=p1 - (back + 0.003) * d,
              end=tip)
    sv = np.where(g.row < 0, -back - 0.003, np.where(g.row >= len(s), lt, s[np.clip(g.row, 0,
                                                                                  len(s) - 1)]))
    joints = [JOINT["left_wrist"]] + [JOINT[f"left_{name}{i}"] for i in (1, 2, 3)]
    bw = 0.007 * b.hand_s
    w = _chain_weights(sv, joints, [(-0.012 * b.hand_s, 0.004 * b.hand_s), (l1 - bw, l1 + bw),
                                    (l1 + l2 - bw, l1 + l2 + bw)])
    return _piece("finger", g, _PART["leftHandIndex1"], _MAT["skin"], w, hand=True, s=sv,
                  finger=k)


def _leg(b: _Body, res: float) -> _Piece:
    j = b.j
    pts = np.stack([j["left_hip"], j["left_knee"], j["left_ankle"]])
    l1 = float(np.linalg.norm(pts[1] - pts[0]))
    la = l1 + float(np.linalg.norm(pts[2] - pts[1]))
    s, _ = _knotted([-0.07, 0.0, l1, la, la + 0.035], [4, 18, 18, 3], res)
    l2 = la - l1
    ks = np.array([-0.075, -0.04, 0.0, 0.1 * l1, 0.35 * l1, 0.65 * l1, 0.9 * l1, l1,
                   l1 + 0.12 * l2, l1 + 0.3 * l2, l1 + 0.55 * l2, l1 + 0.85 * l2, la,
                   la + 0.04])
    ra = _profile(s, ks, [0.058, 0.075, 0.080, 0.079, 0.070, 0.060, 0.050, 0.048, 0.048, 0.051,
                          0.043, 0.034, 0.032, 0.028]) * b.girth
    rb = _profile(s, ks, [0.062, 0.078, 0.082, 0.079, 0.068, 0.058, 0.051, 0.050, 0.051, 0.056,
                          0.046, 0.036, 0.034, 0.030]) * b.girth
    off_x = _profile(s, ks, [0.012, 0.013, 0.012, 0.011, 0.006, 0.002, 0.0, 0.0, 0.0, 0.0, 0.0,
                             0.0, 0.0, 0.0])
    off_z = _profile(s, ks, [-0.004, 0.0, 0.004, 0.006, 0.006, 0.004, 0.002, 0.0, -0.003,
                             -0.009, -0.006, -0.002, 0.0, 0.0])
    axis = _along(pts, s)
    frames = _frames(axis, (1.0, 0.0, 0.0))  # offsets stay in the ring planes
    centers = axis + off_x[:, None] * frames[1] + off_z[:, None] * frames[2]
    g = _tube(centers, ra, rb, 2 * _count(10, res, 6), frames=frames,
              start=_along(pts, np.array([-0.078]))[0] + [0.012, 0, 0],
              end=_along(pts, np.array([la + 0.04]))[0])
    sv = np.where(g.row < 0, -0.078, np.where(g.row >= len(s), la + 0.04,
                                             s[np.clip(g.row, 0, len(s) - 1)]))
    part = np.select([sv < l1, sv < la], [_PART["leftUpLeg"], _PART["leftLeg"]],
                     _PART["leftFoot"])
    w = _chain_weights(sv, [JOINT["pelvis"], JOINT["left_hip"], JOINT["left_knee"],
                            JOINT["left_ankle"]],
                       [(-0.05, 0.03), (l1 - 0.04, l1 + 0.04), (la - 0.035, la + 0.015)])
    return _piece("leg", g, part, _MAT["trousers"], w, s=sv, axis=_along(pts, sv))


def _foot_profile(b: _Body):
    """Foot stations (z relative to the ankle) -> half width, sole and top heights, x shift."""
    z = np.array([-0.064, -0.055, -0.04, -0.02, 0.0, 0.03, 0.06, 0.09, 0.12, 0.14, 0.158,
                  0.172, 0.181, 0.186])
    w = [0.020, 0.028, 0.032, 0.034, 0.035, 0.038, 0.042, 0.046, 0.048, 0.046, 0.041, 0.033,
         0.024, 0.014]
    top = [0.040, 0.062, 0.080, 0.090, 0.092, 0.085, 0.070, 0.057, 0.046, 0.040, 0.034, 0.029,
           0.025, 0.021]
    bot = [0.010, 0.004, 0.001, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.001, 0.003, 0.006]
    dx = [0.004, 0.004, 0.005, 0.006, 0.008, 0.011, 0.014, 0.016, 0.015, 0.012, 0.008, 0.004,
          0.000, -0.004]
    s = b.height
    return z * s, _pchip(z * s, np.stack([w, top, bot, dx], 1) * s)


def _foot(b: _Body, res: float) -> _Piece:
    ank = b.j["left_ankle"]
    zk, prof = _foot_profile(b)
    z_toe = 0.12 * b.height
    z, _ = _knotted([zk[0], 0.0, z_toe, zk[-2]], [6, 10, 7], res)
    w, top, bot, dx = prof(z).T
    centers = np.stack([ank[0] + dx, b.floor + 0.5 * (top + bot), ank[2] + z], 1)
    k = len(z)
    frames = (np.tile([0.0, 0.0, 1.0], (k, 1)), np.tile([1.0, 0.0, 0.0], (k, 1)),
              np.tile([0.0, 1.0, 0.0], (k, 1)))
    pole_s = prof(np.array([zk[0] - 0.004, zk[-1]]))
    g = _tube(centers, w, 0.5 * (top - bot), 2 * _count(9, res, 5), expo=3.0, frames=frames,
              start=[ank[0] + pole_s[0, 3], b.floor + 0.03, ank[2] + zk[0] - 0.004],
              end=[ank[0] + pole_s[1, 3], b.floor + 0.012, ank[2] + zk[-1]])
    zr = g.verts[:, 2] - ank[2]
    part = np.where(zr < z_toe - 0.01, _PART["leftFoot"], _PART["leftToeBase"])
    wt = _chain_weights(zr, [JOINT["left_ankle"], JOINT["left_foot"]],
                        [(z_toe - 0.025, z_toe + 0.01)])
    return _piece("foot", g, part, _MAT["shoes"], wt, z_toe=z_toe)
