"""Shape and expression displacement fields per piece."""

from __future__ import annotations

import numpy as np

from .head import _BROW_Y, _MOUTH_X, _MOUTH_Y
from .mirror import _Mirrored
from .names import EXPRESSION_NAMES, SHAPE_NAMES
from .pieces import _Piece
from .primitives import _gauss, _smoothstep, _unit
from .proportions import _Body


def _shape_fields(pc: _Piece, b: _Body) -> np.ndarray:
    """Shape displacements of one piece per unit coefficient. [n, 3, 10]."""
    if pc.kind in ("eye", "ear"):  # rigid: move with the head's field at their anchor
        anchor = pc.attrs["center" if pc.kind == "eye" else "root"]
        return np.repeat(_field(b, "head", np.asarray(anchor)[None], {}), len(pc.verts), 0)
    return _field(b, pc.kind, pc.verts, pc.attrs)


def _field(b: _Body, kind: str, v: np.ndarray, attrs: dict) -> np.ndarray:
    j = b.j
    n = len(v)
    out = np.zeros((n, 3, len(SHAPE_NAMES)))
    x, y, z = v.T
    head_like = kind in ("head", "pocket", "teeth")
    # height: stretch about the pelvis, mostly vertically.
    out[:, :, 0] = v * [0.3 * 0.0235, 0.0235, 0.3 * 0.0235]
    # weight: girth grows about each part's axis; the belly pushes forward.
    if "axis" in attrs:
        k = {"torso": 0.10, "neck": 0.06, "arm": 0.09, "leg": 0.09}[kind]
        out[:, :, 1] = k * (v - attrs["axis"])
        if kind == "torso":
            belly = _gauss((y - 0.06 * b.height) ** 2, 0.09) * _smoothstep(0.0, 0.08, z)
            out[:, 2, 1] += 0.012 * belly
    elif kind in ("palm", "finger"):
        out[:, :, 1] = 0.02 * (v - b.j["left_wrist"]) * [0.0, 1.0, 1.0]
    elif kind == "head":
        lower = 1 - _smoothstep(b.head_o[1] - 0.03, b.head_o[1], y)
        out[:, 0, 1] = 0.04 * x * lower
    # shoulder_width: arms and hands slide out, the trunk's shoulders follow.
    if kind in ("arm", "palm", "finger"):
        out[:, 0, 2] = 0.015
    elif kind == "torso":
        out[:, 0, 2] = 0.015 * _smoothstep(0.04, 0.16, x) * _smoothstep(0.25 * b.height,
                                                                         0.38 * b.height, y)
    # head_size: scale the head about the top of the neck.
    c_hs = np.array([0.0, b.head_o[1] - 0.11 * b.head_s, -0.01])
    if head_like:
        out[:, :, 3] = 0.04 * (v - c_hs)
    elif kind == "neck":
        out[:, :, 3] = 0.04 * (v - c_hs) * _smoothstep(b.j["neck"][1], c_hs[1], y)[:, None]
    # arm_length: the forearm and hand move out along the arm.
    if kind == "arm":
        out[:, :, 4] = 0.05 * np.clip(attrs["s"], 0.0, attrs["sw"])[:, None] * _unit(
            j["left_wrist"] - j["left_shoulder"])
    elif kind in ("palm", "finger"):
        out[:, :, 4] = 0.05 * (j["left_wrist"] - j["left_shoulder"])
    # neck_length: the head rises, the neck stretches.
    if head_like:
        out[:, 1, 5] = 0.012
    elif kind == "neck":
        out[:, 1, 5] = 0.012 * _smoothstep(j["neck"][1], j["head"][1], y)
    # chest_depth.
    if kind == "torso":
        out[:, 2, 6] = 0.12 * (z - attrs["axis"][:, 2]) * _gauss((y - 0.29 * b.height) ** 2,
                                                                    0.09)
    # hip_width: the pelvis widens, the legs slide apart.
    if kind == "torso":
        out[:, 0, 7] = 0.08 * x * _gauss((y + 0.07 * b.height) ** 2, 0.07)
    elif kind in ("leg", "foot"):
        out[:, 0, 7] = 0.08 * j["left_hip"][0]
    # hand_size: scale the hand about the wrist.
    if kind in ("palm", "finger"):
        out[:, :, 8] = 0.05 * (v - j["left_wrist"])
    elif kind == "arm":
        ramp = _smoothstep(attrs["sw"] - 0.03, attrs["sw"], attrs["s"])
        out[:, :, 8] = 0.05 * (v - j["left_wrist"]) * ramp[:, None]
    # face_width: cheeks and jaw widen.
    if head_like:
        yl = (y - b.head_o[1]) / b.head_s
        out[:, 0, 9] = 0.05 * x * _gauss((yl - _MOUTH_Y - 0.02) ** 2, 0.035)
    return out


def _expression_fields(pc: _Piece, b: _Body) -> np.ndarray:
    """Expression displacements of the head surface (left half). [n, 3, 10]."""
    out = np.zeros((len(pc.verts), 3, len(EXPRESSION_NAMES)))
    if pc.kind != "head":
        return out
    p = pc.attrs["local"]
    x, y, z = p.T
    lower = pc.attrs["lower"] | (pc.attrs["design_y"] < _MOUTH_Y)
    s = b.head_s
    corner = np.array([_MOUTH_X, _MOUTH_Y, 0.0])
    d2c = (x - corner[0]) ** 2 + (y - corner[1]) ** 2
    front = _smoothstep(0.03, 0.06, z)
    lat = np.clip(1 - (x / _MOUTH_X) ** 2, 0.0, 1.0)
    lips = _gauss(np.maximum(np.abs(x) - _MOUTH_X, 0) ** 2 + (y - _MOUTH_Y) ** 2, 0.008) * front

    def put(i, d):
        out[:, :, i] = s * d

    g = _gauss(d2c, 0.011) * front
    cheek = _gauss((x - 0.042) ** 2 + (y + 0.035) ** 2, 0.014) * front
    put(0, g[:, None] * [0.0035, 0.0072, -0.0015] + cheek[:, None] * [0.0, 0.003, 0.0015])
    stretch = 0.42 * x * _gauss(np.maximum(x - _MOUTH_X, 0) ** 2 + (y - _MOUTH_Y) ** 2, 0.012)
    part_g = lat**0.7 * _gauss((y - _MOUTH_Y) ** 2, 0.009) * front
    put(1, np.stack([stretch, np.where(lower, -0.0015, 0.0015) * part_g,
                     -0.003 * g], 1))
    put(2, np.stack([0 * x, np.where(lower, -0.0036, 0.0024) * part_g, 0 * x], 1))
    put(3, np.stack([-0.35 * x * lips, np.where(lower, 0.0008, -0.0008) * lips,
                     0.008 * lips * (0.4 + 0.6 * lat)], 1))
    puff = _gauss((x - 0.048) ** 2 + (y + 0.058) ** 2 + 0.5 * (z - 0.055) ** 2, 0.016)
    radial = _unit(np.stack([x, 0 * x, z - 0.0], 1))
    put(4, 0.010 * puff[:, None] * radial)
    out[:, :, 5] = pc.attrs["blink"]
    brow_lat = 1 - _smoothstep(0.05, 0.07, x)
    above = np.where(y > _BROW_Y, _gauss((y - _BROW_Y) ** 2, 0.022),
                     _gauss((y - _BROW_Y) ** 2, 0.0075))
    raise_ = above * brow_lat * front * (1 - 0.6 * pc.attrs["in_eye"])
    put(7, raise_[:, None] * [0.0, 0.008, 0.001])
    inner = _gauss((y - _BROW_Y) ** 2, 0.009) * _gauss((x - 0.017) ** 2, 0.014) * front
    inner *= 1 - 0.7 * pc.attrs["in_eye"]
    put(8, inner[:, None] * [-0.0035, -0.005, 0.0012])
    put(9, g[:, None] * [0.0012, -0.0068, -0.0008] + (lips * lower)[:, None]
        * [0.0, -0.0008, 0.001])
    # Fields must be odd in x so the midline keeps x = 0.
    out[:, 0, :] *= _smoothstep(0.0, 0.006, x)[:, None]
    out[:, :, 6] = 0.0  # blink_right is the mirror of blink_left
    return out


def _expressions(pieces: list[_Piece], m: _Mirrored, b: _Body) -> np.ndarray:
    """Expression basis of all vertices: symmetric ones mirrored, blinks one-sided. [V, 3, 10]."""
    expr = m.field(np.concatenate([_expression_fields(p, b) for p in pieces]))
    nh = len(m.seam)
    i_left, i_right = EXPRESSION_NAMES.index("blink_left"), EXPRESSION_NAMES.index("blink_right")
    blink = np.zeros((len(m.verts), 3))
    blink[:nh] = expr[:nh, :, i_left]  # the half holds the left eye only
    expr[:, :, i_left] = blink
    expr[:, :, i_right] = blink[m.mirror] * [-1.0, 1.0, 1.0]
    return expr
