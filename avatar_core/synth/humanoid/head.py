"""The head: its design grid and surface (mouth and eye slits), eyes, ears, the mouth pocket
and teeth."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatar_core.body.skeleton import JOINT

from .names import _MAT, _PART
from .pieces import _half_seam, _Piece, _piece
from .primitives import (
    _blend,
    _count,
    _gauss,
    _Grid,
    _grid_mesh,
    _knotted,
    _loft_rings,
    _one_hot,
    _pchip,
    _smoothstep,
    _t_at_x,
    _tube,
    _unit,
)
from .proportions import _EYE_R, _HEAD_LOCAL_JOINTS, _Body

_HEAD_ROWS = np.array([  # head-local: y, rx, zc, rzf, rzb, nf, nb, intervals to the next row
    (-0.1265, 0.020, 0.032, 0.028, 0.028, 2.0, 2.0, 1),
    (-0.1245, 0.032, 0.030, 0.044, 0.042, 2.0, 2.0, 1),
    (-0.1185, 0.041, 0.026, 0.057, 0.052, 1.9, 2.0, 2),
    (-0.1040, 0.048, 0.021, 0.067, 0.058, 1.9, 2.0, 2),
    (-0.0890, 0.053, 0.017, 0.071, 0.063, 2.0, 2.0, 2),
    (-0.0780, 0.057, 0.013, 0.077, 0.070, 2.1, 2.0, 2),
    (-0.0680, 0.060, 0.010, 0.080, 0.076, 2.2, 2.0, 2),  # mouth
    (-0.0560, 0.063, 0.008, 0.081, 0.084, 2.3, 2.0, 3),
    (-0.0400, 0.066, 0.006, 0.080, 0.092, 2.4, 2.1, 2),  # nose base
    (-0.0300, 0.068, 0.005, 0.081, 0.096, 2.5, 2.2, 3),  # nose tip
    (-0.0150, 0.071, 0.003, 0.083, 0.099, 2.6, 2.2, 4),
    (0.0000, 0.073, 0.001, 0.085, 0.101, 2.6, 2.3, 5),  # eyes
    (0.0180, 0.075, 0.000, 0.088, 0.103, 2.6, 2.3, 4),  # brows
    (0.0450, 0.076, -0.002, 0.086, 0.104, 2.5, 2.3, 3),
    (0.0700, 0.073, -0.005, 0.078, 0.102, 2.4, 2.3, 2),
    (0.0880, 0.063, -0.008, 0.063, 0.092, 2.2, 2.2, 2),
    (0.1000, 0.047, -0.010, 0.045, 0.071, 2.1, 2.1, 1),
    (0.1060, 0.027, -0.010, 0.026, 0.042, 2.0, 2.0, 0),
])
_ROW_MOUTH, _ROW_NOSE_TIP, _ROW_EYE = 6, 9, 11
_HEAD_POLES = ((0.0, -0.1285, 0.030), (0.0, 0.1090, -0.011))
_MOUTH_Y, _MOUTH_X = -0.068, 0.025  # lip line height and corner half-width (head-local)
_EYE_X, _EYE_IN, _EYE_OUT = 0.0325, 0.0185, 0.0465
_BROW_Y = 0.018


@dataclass
class _HeadGrid:
    """Design coordinates of the head grid, for placing landmarks on it."""

    y: np.ndarray  # [R] design height of each ring (head-local)
    t: np.ndarray  # [C] arc fraction of each column
    prof: tuple  # per-ring profile arrays
    row_mouth: int
    row_eye: int
    col_mouth: int
    col_eye_in: int
    col_eye_out: int


def _head_grid(res: float) -> _HeadGrid:
    k = np.arange(len(_HEAD_ROWS))
    steps = [np.linspace(i, i + 1, _count(int(n), res, 3 if i in (10, 11) else 1) + 1)[:-1]
             for i, n in zip(k[:-1], _HEAD_ROWS[:-1, 7], strict=True)]
    kk = np.concatenate(steps + [k[-1:]])
    rows = _pchip(k, _HEAD_ROWS[:, :7])(kk)
    rows[:, 0] = np.interp(kk, k, _HEAD_ROWS[:, 0])  # rows at the exact feature heights
    r_mouth = int(np.flatnonzero(kk == _ROW_MOUTH)[0])
    r_eye = int(np.flatnonzero(kk == _ROW_EYE)[0])
    prof = tuple(rows[:, i] for i in range(1, 7))
    eye_row = [p[r_eye] for p in prof]
    t_in, t_out = _t_at_x(eye_row, _EYE_IN), _t_at_x(eye_row, _EYE_OUT)
    t_mouth = _t_at_x([p[r_mouth] for p in prof], _MOUTH_X)
    t, idx = _knotted([0.0, t_in, t_mouth, t_out, 0.33, 0.45, 0.62, 1.0],
                      [6, 3, 4, 4, 5, 4, 6], res, lo=[2, 1, 2, 2, 1, 1, 1])
    return _HeadGrid(rows[:, 0], t, prof, r_mouth, r_eye, idx[2], idx[1], idx[3])


def _hairline(t: np.ndarray) -> np.ndarray:
    """Head-local height of the hairline at arc fraction t (0 forehead, 1 nape)."""
    return np.interp(t, [0.0, 0.12, 0.22, 0.30, 0.36, 0.47, 0.53, 0.62, 0.8, 1.0],
                     [0.062, 0.058, 0.048, 0.032, 0.016, 0.016, -0.010, -0.045, -0.062, -0.066])


def _brow_center(x: np.ndarray) -> np.ndarray:
    """Head-local height of the eyebrow centre line."""
    u = np.clip((x - 0.011) / 0.046, 0.0, 1.0)
    return _BROW_Y - 0.002 + 0.007 * np.sin(np.pi * u**0.8) - 0.003 * u


def _eye_open(s: np.ndarray, closure: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertical offsets of the upper and lower lid edges across the eye (s in [0, 1])."""
    base = np.sin(np.pi * np.clip(s, 0.0, 1.0))
    upper, lower = 0.0050 * base**0.8 * (1.0 + 0.2 * (0.5 - s)), -0.0036 * base**1.1
    shut = 0.6 * lower
    return (1 - closure) * upper + closure * shut, (1 - closure) * lower + closure * shut


def _head_surface(hg: _HeadGrid, closure: float = 0.0) -> tuple[_Grid, dict]:
    """Head-local skin surface of the left half: a loft with nose, lips, chin, brows, cheeks,
    eye sockets and lids, hair volume; slits along the lip line and the eyes."""
    base = _loft_rings(hg.y, hg.prof, hg.t)  # [R, C, 3]
    mouth_cols = np.arange(hg.col_mouth)
    eye_cols = np.arange(hg.col_eye_in + 1, hg.col_eye_out)
    g = _grid_mesh(base, bottom=_HEAD_POLES[0], top=_HEAD_POLES[1],
                   slits=[(hg.row_mouth, mouth_cols), (hg.row_eye, eye_cols)])
    p = g.verts.copy()
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    in_grid = (g.row >= 0) & (g.row < len(hg.y))
    tcol = np.where(in_grid, hg.t[np.clip(g.col, 0, len(hg.t) - 1)], 0.0)
    face = _smoothstep(0.02, 0.05, z)
    # Nose: a ridge from the root to a rounded tip, tucked under to the base; nostril wings.
    ny = [0.006, -0.008, -0.022, -0.030, -0.036, -0.041]
    height = np.interp(y, ny[::-1], [0.0, 0.010, 0.018, 0.021, 0.012, 0.0][::-1])
    width = np.interp(y, ny[::-1], [0.0075, 0.0080, 0.0095, 0.0110, 0.0150, 0.0150][::-1])
    u = np.clip(x / width, 0.0, 1.0)
    dz = height * (1 - u**2) ** 2
    dz += 0.0055 * _gauss((x - 0.0125) ** 2 + 1.6 * (y + 0.035) ** 2, 0.0045)
    # Lips (with a rolled-in lip line and recessed corners), chin, brow ridge.
    lat = np.clip(1 - (x / (_MOUTH_X + 0.002)) ** 2, 0.0, 1.0)
    dz += lat**0.6 * (0.0035 * _gauss((y - _MOUTH_Y - 0.0045) ** 2, 0.0035)
                      + 0.0042 * _gauss((y - _MOUTH_Y + 0.0055) ** 2, 0.004))
    on_mouth_row = g.row == hg.row_mouth
    dz -= 0.0015 * on_mouth_row * lat
    dz -= 0.0025 * _gauss((x - _MOUTH_X) ** 2 + (y - _MOUTH_Y) ** 2, 0.004)
    dz += 0.0045 * _gauss((y + 0.104) ** 2, 0.009) * _gauss(x**2, 0.017)
    dz -= 0.0022 * _gauss((y + 0.089) ** 2, 0.004) * _gauss(x**2, 0.02)
    dz += 0.0032 * _gauss((y - 0.017) ** 2, 0.007) * (1 - _smoothstep(0.045, 0.062, x))
    p[:, 2] += dz * face
    # Cheekbones push outward.
    cheek = 0.004 * _gauss((x - 0.050) ** 2 + (y + 0.018) ** 2, 0.012)
    p[:, 0] += cheek * 0.8
    p[:, 2] += cheek * 0.6 * face
    # Eye opening: lids move apart along the eye slit, then wrap onto a sphere round the eye.
    eye_c = np.array(_HEAD_LOCAL_JOINTS["left_eye_smplhf"])
    ti, to = hg.t[hg.col_eye_in], hg.t[hg.col_eye_out]
    s_eye = (tcol - ti) / (to - ti)
    in_eye = in_grid & (g.col > hg.col_eye_in) & (g.col < hg.col_eye_out)
    upper_side = (g.row > hg.row_eye) | ((g.row == hg.row_eye) & ~g.dup)
    e_up, e_lo = _eye_open(s_eye, closure)
    band = np.clip(1 - np.abs(y) / 0.011, 0.0, 1.0)
    dy = np.where(in_eye, band * np.where(upper_side, e_up, e_lo), 0.0)
    d_eye = np.hypot(x - eye_c[0], 1.25 * y)
    w_sock = 1 - _smoothstep(0.0135, 0.023, d_eye)
    q = p + np.stack([np.zeros_like(dy), dy, np.zeros_like(dy)], 1)
    proj = eye_c + (_EYE_R + 0.0015) * _unit(q - eye_c)
    p = q + w_sock[:, None] * (proj - q)
    # Hair volume and brows stand slightly off the skin.
    hair_w = _smoothstep(_hairline(tcol), _hairline(tcol) + 0.012, y) * in_grid
    hair_w = np.where(g.row >= len(hg.y), 1.0, hair_w)
    thick = 0.005 + 0.009 * _smoothstep(0.03, 0.11, y) + 0.003 * _smoothstep(0.4, 0.8, tcol)
    radial = _unit((p - [0.0, -0.01, -0.005]) / [0.075**2, 0.11**2, 0.095**2])
    brow_w = _gauss((y - _brow_center(x)) ** 2, 0.003) * _smoothstep(0.008, 0.014, x) * (
        1 - _smoothstep(0.052, 0.06, x)) * face
    p += radial * (hair_w * thick + 0.0012 * brow_w)[:, None]
    p[_half_seam(g), 0] = 0.0  # features are even in x; keep the midline exactly on x = 0
    g.verts = p
    info = {"design_y": np.where(in_grid, hg.y[np.clip(g.row, 0, len(hg.y) - 1)], y), "t": tcol,
            "hair": hair_w, "brow": brow_w, "in_eye": in_eye, "lower": g.dup & on_mouth_row,
            "upper_side_eye": upper_side, "w_sock": w_sock}
    return g, info


def _to_world(b: _Body, p: np.ndarray) -> np.ndarray:
    return b.head_o + b.head_s * p


def _head_materials(g: _Grid, info: dict) -> np.ndarray:
    x, y = g.verts[:, 0], info["design_y"]
    mat = np.full(len(x), _MAT["skin"])
    lat = np.clip(1 - (x / (_MOUTH_X + 0.0025)) ** 2, 0.0, 1.0)
    upper = (y > _MOUTH_Y) | ((y == _MOUTH_Y) & ~info["lower"])
    lip_h = np.where(upper, 0.0085 * lat**0.45, 0.0095 * lat**0.55)
    mat[(np.abs(y - _MOUTH_Y) <= lip_h + 1e-9) & (lat > 0) & (g.verts[:, 2] > 0.03)] = _MAT["lips"]
    mat[info["brow"] > 0.55] = _MAT["eyebrow"]
    mat[info["hair"] > 0.5] = _MAT["hair"]
    return mat


def _jaw_weight(g: _Grid, info: dict) -> np.ndarray:
    """How much each head-surface vertex follows the jaw: the lower face below the lip slit,
    fading toward the cheeks above the mouth corners and toward the ears and neck."""
    x, z, y = g.verts[:, 0], g.verts[:, 2], info["design_y"]
    below = (y < _MOUTH_Y) | info["lower"]
    lateral = _smoothstep(_MOUTH_X - 0.008, _MOUTH_X + 0.008, x)
    up = (1 - _smoothstep(_MOUTH_Y, _MOUTH_Y + 0.022, y)) * lateral
    vert = np.where(below, 1.0, up)
    zj = _HEAD_LOCAL_JOINTS["jaw"][2]
    return vert * _smoothstep(zj - 0.012, zj + 0.035, z)


def _head(b: _Body, hg: _HeadGrid) -> _Piece:
    g, info = _head_surface(hg)
    closed, _ = _head_surface(hg, closure=1.0)
    mat = _head_materials(g, info)
    wj = _jaw_weight(g, info)
    w = _blend(_one_hot(len(wj), JOINT["head"]), wj, JOINT["jaw"])
    local = g.verts.copy()
    g.verts = _to_world(b, local)
    blink = b.head_s * (closed.verts - local)
    seam = _half_seam(g) | (g.dup & (g.col == 0))
    return _piece("head", g, _PART["head"], mat, w, seam=seam, flame=True, local=local,
                  blink=blink, **info)


def _eye(b: _Body, res: float) -> _Piece:
    """Eyeball with its polar axis along +z; the front pole is the pupil centre."""
    back = np.linspace(np.pi, 0.62, _count(6, res, 3) + 1)[1:]
    theta = np.concatenate([back, [0.5, 0.42, 0.3, 0.205, 0.1]])
    c = np.array(_HEAD_LOCAL_JOINTS["left_eye_smplhf"])
    centers = c + _EYE_R * np.cos(theta)[:, None] * [0.0, 0.0, 1.0]
    r = _EYE_R * np.sin(theta)
    frames = (np.tile([0.0, 0.0, 1.0], (len(theta), 1)), np.tile([1.0, 0.0, 0.0], (len(theta), 1)),
              np.tile([0.0, 1.0, 0.0], (len(theta), 1)))
    g = _tube(centers, r, r, 2 * _count(8, res, 5), start=c - [0, 0, _EYE_R],
              end=c + [0, 0, _EYE_R], frames=frames)
    th = np.arccos(np.clip((g.verts[:, 2] - c[2]) / _EYE_R, -1.0, 1.0))
    mat = np.select([th < 0.21, th < 0.505], [_MAT["pupil"], _MAT["iris"]], _MAT["eye_white"])
    g.verts = _to_world(b, g.verts)
    return _piece("eye", g, _PART["leftEye"], mat, _one_hot(len(th), JOINT["left_eye_smplhf"]),
                  flame=True, center=_to_world(b, c))


def _ear(b: _Body, res: float, hg: _HeadGrid) -> _Piece:
    """A flattened, dished oval on the side of the head, standing off at the back."""
    k = _count(9, res, 5)
    u = np.linspace(-1, 1, k + 2)[1:-1]
    axis = _unit(np.array([0.0, 1.0, -0.28]))
    out = np.array([1.0, 0.0, 0.45])
    e1 = _unit(out - out @ axis * axis)
    e2 = np.cross(axis, e1)
    ry = -0.021
    rx_row = float(np.interp(ry, hg.y, hg.prof[0]))
    center = np.array([rx_row + 0.007, ry, -0.014])
    h, wdt, th = 0.031, 0.021, 0.005
    centers = center + (h * u)[:, None] * axis + (0.003 * (1 - u))[:, None] * e2
    prof = np.sqrt(1 - u**2)
    wid = wdt * prof * (0.78 + 0.22 * u)
    frames = (np.tile(axis, (k, 1)), np.tile(e1, (k, 1)), np.tile(e2, (k, 1)))
    n_around = 2 * _count(6, res, 4)
    g = _tube(centers, th * prof**0.5, wid, n_around, start=center - h * axis,
              end=center + h * axis, frames=frames)
    # Dish the outer face: pull its middle in, leaving a rim.
    rel = g.verts - center
    a1, a2 = rel @ e1, rel @ e2
    ring = np.clip(np.abs(a2) / np.maximum(wid[np.clip(g.row, 0, k - 1)], 1e-9), 0.0, 1.0)
    dish = np.where(a1 > 0, 1.2 * th * (1 - ring**2) * prof[np.clip(g.row, 0, k - 1)], 0.0)
    dish = np.where((g.row < 0) | (g.row >= k), 0.0, dish)
    g.verts = _to_world(b, g.verts - dish[:, None] * e1)
    return _piece("ear", g, _PART["head"], _MAT["skin"], _one_hot(len(dish), JOINT["head"]),
                  flame=True, root=_to_world(b, center))


def _mouth_pocket(b: _Body, res: float, lips_z: float) -> _Piece:
    """Closed pocket behind the lip slit (what shows when the mouth opens)."""
    beta = np.linspace(-np.pi / 2, np.pi / 2, _count(8, res, 4) + 1)[1:-1]
    rx, ry, rz = 0.027, 0.017, 0.020
    zc = lips_z - 0.029
    y = _MOUTH_Y + ry * np.sin(beta)
    cb = np.cos(beta)
    prof = (rx * cb, np.full_like(cb, zc), rz * cb, rz * cb, np.full_like(cb, 2.0),
            np.full_like(cb, 2.0))
    t, _ = _knotted([0.0, 1.0], [8], res, lo=4)
    g = _grid_mesh(_loft_rings(y, prof, t), bottom=(0.0, _MOUTH_Y - ry, zc),
                   top=(0.0, _MOUTH_Y + ry, zc))
    wj = 1 - _smoothstep(_MOUTH_Y - 0.006, _MOUTH_Y + 0.006, g.verts[:, 1])
    w = _blend(_one_hot(len(wj), JOINT["head"]), wj, JOINT["jaw"])
    seam = _half_seam(g)
    g.verts = _to_world(b, g.verts)
    return _piece("pocket", g, _PART["head"], _MAT["mouth_interior"], w, seam=seam, flame=True)


def _teeth(b: _Body, res: float, lips_z: float, upper: bool) -> _Piece:
    """One row of teeth: a thin arch from the midline (seam) round to the side."""
    s = np.linspace(0.0, 1.15, _count(7, res, 3) + 1)
    ra, rb = 0.021, 0.019
    zf = lips_z - 0.0055
    sign = 1.0 if upper else -1.0
    yc = _MOUTH_Y + sign * 0.0048
    centers = np.stack([ra * np.sin(s), np.full_like(s, yc), zf - rb * (1 - np.cos(s))], 1)
    t = _unit(np.stack([ra * np.cos(s), np.zeros_like(s), -rb * np.sin(s)], 1))
    e1 = np.tile([0.0, 1.0, 0.0], (len(s), 1))
    g = _tube(centers, np.full_like(s, 0.0042), np.full_like(s, 0.0014), 6, expo=4.0,
              end=centers[-1] + 0.0012 * t[-1], frames=(t, e1, np.cross(t, e1)))
    seam = g.row == 0
    g.verts[seam, 0] = 0.0
    g.verts = _to_world(b, g.verts)
    joint = JOINT["head"] if upper else JOINT["jaw"]
    return _piece("teeth", g, _PART["head"], _MAT["teeth"], _one_hot(len(seam), joint),
                  seam=seam, flame=True)
