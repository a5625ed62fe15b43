"""Procedural stand-in for the SMPL-X body: a stylised humanoid in the SMPL-X rest pose.

The mesh is assembled from simple parts (lofted cross-sections and tubes) that may
interpenetrate but are each closed, except the head, whose surface has slits for the mouth and
the eyes. Only the left half (+x) and the midline are modelled; the right half is an exact
mirror, so every attribute is symmetric by construction.

Conventions: metres, y up, the face looks toward +z, the subject's left is +x, T-pose with the
palms down. The pelvis joint sits near the origin; the soles are near y = -0.95.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.optimize import least_squares, nnls
from scipy.spatial.transform import Rotation

from avatar_core.body.skeleton import (
    JOINT,
    SMPLX_JOINT_NAMES,
    SMPLX_NUM_JOINTS,
    SMPLX_PART_NAMES,
    mirrored_joint_index,
    swap_left_right,
)

__all__ = ["EXPRESSION_NAMES", "MATERIALS", "SHAPE_NAMES", "Humanoid", "make_humanoid"]

MATERIALS: tuple[str, ...] = ("skin", "hair", "eyebrow", "lips", "eye_white", "iris", "pupil",
                              "mouth_interior", "teeth", "shirt", "trousers", "shoes")
SHAPE_NAMES: tuple[str, ...] = ("height", "weight", "shoulder_width", "head_size", "arm_length",
                                "neck_length", "chest_depth", "hip_width", "hand_size",
                                "face_width")
EXPRESSION_NAMES: tuple[str, ...] = ("smile", "grin", "lips_part", "pucker", "cheek_puff",
                                     "blink_left", "blink_right", "brows_raise", "brows_lower",
                                     "frown")
SEMANTIC_NAMES: tuple[str, ...] = (
    "nose", "reye", "leye", "rear", "lear", "rthumb", "rindex", "rmiddle", "rring", "rpinky",
    "lthumb", "lindex", "lmiddle", "lring", "lpinky", "LBigToe", "LSmallToe", "LHeel",
    "RBigToe", "RSmallToe", "RHeel",
)  # fmt: skip

_MAT = {name: i for i, name in enumerate(MATERIALS)}
_PART = {name: i for i, name in enumerate(SMPLX_PART_NAMES)}
_NJ = SMPLX_NUM_JOINTS
# SMPL-X hand joint order: index, middle, pinky, ring, thumb (three joints each).
_FINGER_NAMES = ("index", "middle", "pinky", "ring", "thumb")
# iBUG-68 left/right flip; landmarks are iBUG 17..67, the contour iBUG 0..16.
_IBUG_FLIP = np.array(
    [16, 15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0,
     26, 25, 24, 23, 22, 21, 20, 19, 18, 17, 27, 28, 29, 30, 35, 34, 33, 32, 31,
     45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40,
     54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55, 64, 63, 62, 61, 60, 67, 66, 65])  # fmt: skip


@dataclass(frozen=True)
class Humanoid:
    """A rest-pose body mesh with everything a parametric body model file needs."""

    vertices: np.ndarray  # [V, 3] float64, rest pose
    faces: np.ndarray  # [F, 3] int64, outward CCW
    joints: np.ndarray  # [55, 3] rest joints, SMPL-X order
    joint_regressor: np.ndarray  # [55, V] convex rows, joint_regressor @ vertices == joints
    skinning_weights: np.ndarray  # [V, 55] convex rows
    part_labels: np.ndarray  # [V] index into SMPLX_PART_NAMES
    materials: np.ndarray  # [V] index into MATERIALS
    flame_region: np.ndarray  # [V] bool: head (eyes, ears, mouth interior) + upper neck
    hand_region: dict[str, np.ndarray]  # {"left", "right"}: [V] bool, hand + wrist cuff
    mirror_index: np.ndarray  # [V] vertex reflected by x -> -x
    semantic_vertices: dict[str, int]
    landmark_faces: np.ndarray  # [51] iBUG 17..67
    landmark_bary: np.ndarray  # [51, 3]
    contour_faces: np.ndarray  # [17] iBUG 0..16
    contour_bary: np.ndarray  # [17, 3]
    shape_basis: np.ndarray  # [V, 3, 10]
    shape_names: tuple[str, ...]
    expression_basis: np.ndarray  # [V, 3, 10], zero outside flame_region
    expression_names: tuple[str, ...]
    hand_poses: dict[str, np.ndarray]  # right hand, name -> [15, 3] axis-angle


# ----------------------------------------------------------------------------- small helpers


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


# ------------------------------------------------------------------------ mesh construction


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


# --------------------------------------------------------------------------------- the body


@dataclass(frozen=True)
class _Body:
    """Anatomical numbers of one (seeded) individual, left side and midline."""

    j: dict  # joint name -> [3] nominal rest position
    height: float  # vertical scale of trunk and legs
    girth: float
    shoulders: float
    hips: float
    head_o: np.ndarray  # [3] origin of the head-local frame (eye level, midline)
    head_s: float  # head-local -> world scale
    hand_s: float
    floor: float
    fingers: tuple  # per finger (j1, j2, j3, tip, radius, direction), SMPL-X order


_TEMPLATE = {  # nominal joints (metres) before the seeded proportions
    "pelvis": (0.0, 0.0, 0.0), "left_hip": (0.072, -0.085, 0.0),
    "left_knee": (0.092, -0.49, 0.008), "left_ankle": (0.085, -0.875, -0.012),
    "spine1": (0.0, 0.105, -0.012), "spine2": (0.0, 0.235, -0.008), "spine3": (0.0, 0.29, 0.0),
    "neck": (0.0, 0.49, -0.016), "left_collar": (0.07, 0.42, -0.015),
    "left_shoulder": (0.172, 0.425, -0.02), "left_elbow": (0.43, 0.425, -0.03),
    "left_wrist": (0.68, 0.425, -0.025),
}  # fmt: skip
_HEAD_EYE_Y = 0.645  # head-local origin height
_HEAD_LOCAL_JOINTS = {"head": (0.0, -0.060, -0.008), "jaw": (0.0, -0.043, 0.008),
                      "left_eye_smplhf": (0.0325, 0.0, 0.0705)}
_EYE_R = 0.0118
# name, MCP offset from the wrist (left hand), direction, segment lengths, radius
_FINGERS = (
    ("index", (0.094, 0.001, 0.026), (1.0, 0.0, 0.05), (0.039, 0.023, 0.021), 0.0088),
    ("middle", (0.097, 0.001, 0.006), (1.0, 0.0, 0.0), (0.043, 0.026, 0.022), 0.0092),
    ("pinky", (0.085, -0.001, -0.032), (1.0, 0.0, -0.09), (0.032, 0.020, 0.020), 0.0075),
    ("ring", (0.092, 0.0, -0.013), (1.0, 0.0, -0.04), (0.040, 0.025, 0.021), 0.0086),
    ("thumb", (0.020, -0.008, 0.012), (1.0, -0.15, 0.62), (0.046, 0.034, 0.028), 0.0105),
)


def _body(seed: int) -> _Body:
    """Seeded proportions (a few % each) applied to the template skeleton."""
    rng = np.random.default_rng(seed)
    height, shoulders, hips, girth, head, arms, legs, hands = 1.0 + 0.03 * rng.uniform(-1, 1, 8)
    legs *= height
    t = {k: np.array(v, dtype=np.float64) for k, v in _TEMPLATE.items()}
    j = {}
    for name in ("pelvis", "spine1", "spine2", "spine3", "neck"):
        j[name] = t[name] * [1.0, height, 1.0]
    j["left_hip"] = t["left_hip"] * [hips, height, 1.0]
    for name in ("left_knee", "left_ankle"):
        j[name] = j["left_hip"] + (t[name] - t["left_hip"]) * [hips, legs, 1.0]
    j["left_collar"] = t["left_collar"] * [shoulders, height, 1.0]
    j["left_shoulder"] = t["left_shoulder"] * [shoulders, height, 1.0]
    for name in ("left_elbow", "left_wrist"):
        j[name] = j["left_shoulder"] + (t[name] - t["left_shoulder"]) * arms * height
    head_o = np.array([0.0, _HEAD_EYE_Y * height, 0.0])
    head_s = head * (0.5 + 0.5 * height)
    for name, p in _HEAD_LOCAL_JOINTS.items():
        j[name] = head_o + head_s * np.array(p)
    hand_s = hands * height
    fingers = []
    for _, off, d, lengths, r in _FINGERS:
        d = _unit(np.array(d))
        p1 = j["left_wrist"] + hand_s * np.array(off)
        p2 = p1 + hand_s * lengths[0] * d
        p3 = p2 + hand_s * lengths[1] * d
        tip = p3 + hand_s * lengths[2] * d
        fingers.append((p1, p2, p3, tip, hand_s * r, d))
    floor = float(j["left_ankle"][1] - 0.075 * legs)
    return _Body(j, float(height), float(girth), float(shoulders), float(hips), head_o,
                 float(head_s), float(hand_s), floor, tuple(fingers))


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


# --------------------------------------------------------------------------------- the trunk

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


# ---------------------------------------------------------------------------------- the head

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


def _jaw_weight(g: _Grid, info: dict, hg: _HeadGrid) -> np.ndarray:
    """How much each head-surface vertex follows the jaw: the lower face below the lip slit,
    fading toward the cheeks above the mouth corners and toward the ears and neck."""
    x, z, y = g.verts[:, 0], g.verts[:, 2], info["design_y"]
    below = (y < _MOUTH_Y) | info["lower"]
    lateral = _smoothstep(_MOUTH_X - 0.008, _MOUTH_X + 0.008, x)
    up = (1 - _smoothstep(_MOUTH_Y, _MOUTH_Y + 0.022, y)) * lateral
    vert = np.where(below, 1.0, up)
    zj = _HEAD_LOCAL_JOINTS["jaw"][2]
    return vert * _smoothstep(zj - 0.012, zj + 0.035, z)


def _head(b: _Body, res: float, hg: _HeadGrid) -> _Piece:
    g, info = _head_surface(hg)
    closed, _ = _head_surface(hg, closure=1.0)
    mat = _head_materials(g, info)
    wj = _jaw_weight(g, info, hg)
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


# ---------------------------------------------------------------------------------- the limbs


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


# ------------------------------------------------------------------------- fields and blends


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


# ------------------------------------------------------------------------------- assembling


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


def _regress(verts: np.ndarray, cand: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Convex weights on `cand` vertices reproducing `target`, close to uniform. [len(cand)]."""
    a = np.vstack([verts[cand].T, np.ones(len(cand))])  # [4, k]
    bb = np.append(target, 1.0)
    w0 = np.full(len(cand), 1.0 / len(cand))
    w = w0 + np.linalg.lstsq(a, bb - a @ w0, rcond=1e-12)[0]  # least change from uniform
    if w.min() < 0 or np.abs(a @ w - bb).max() > 1e-9:
        scale = 1.0 / max(np.ptp(verts[cand], axis=0).max(), 1e-6)
        w, _ = nnls(np.vstack([a[:3] * scale, 10.0 * a[3:]]), np.append(target * scale, 10.0))
        if abs(w.sum() - 1) > 1e-3 or np.abs(a[:3] @ w - target).max() > 1e-6:
            raise RuntimeError("joint outside the hull of its regressor vertices")
    return w / w.sum()


def _fk_hand(rest: np.ndarray, tips: np.ndarray, rotvecs: np.ndarray) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    """Posed right-hand joints [16, 3] (wrist first) and fingertips [5, 3] for [15, 3] poses."""
    rot = Rotation.from_rotvec(rotvecs).as_matrix()
    pos = [rest[0]]
    out_tips = []
    for f in range(5):
        gp, pp = np.eye(3), rest[0]
        for i in range(3):
            k = 1 + 3 * f + i
            parent = 0 if i == 0 else k - 1
            pp = pp + gp @ (rest[k] - rest[parent])
            gp = gp @ rot[k - 1]
            pos.append(pp)
        out_tips.append(pp + gp @ (tips[f] - rest[3 + 3 * f]))
    return np.asarray(pos), np.asarray(out_tips)


def _hand_poses(joints: np.ndarray, tips: np.ndarray) -> dict[str, np.ndarray]:
    """Right-hand gestures as [15, 3] axis-angles. The right hand points along -x with the
    palm toward -y, so flexion toward the palm is a positive rotation about +z and spreading
    toward the thumb a positive rotation about +y."""
    rest = joints[[JOINT["right_wrist"], *range(40, 55)]]  # [16, 3]
    t_dir = _unit(rest[14] - rest[13])
    t_flex = _unit(np.cross(t_dir, [0.0, -1.0, 0.0]))

    def fingers(curls, spreads=(0.0, 0.0, 0.0, 0.0)):
        pose = np.zeros((15, 3))
        for f in range(4):
            c1, c2, c3 = curls[f]
            r1 = Rotation.from_rotvec([0, 0, c1]) * Rotation.from_rotvec([0, spreads[f], 0])
            pose[3 * f] = r1.as_rotvec()
            pose[3 * f + 1] = [0, 0, c2]
            pose[3 * f + 2] = [0, 0, c3]
        return pose

    def thumb(pose, opp, f1, f2):
        r1 = Rotation.from_rotvec(t_flex * f1) * Rotation.from_rotvec([0.0, -opp, 0.0])
        pose[12] = r1.as_rotvec()
        pose[13] = t_flex * f2
        pose[14] = t_flex * 0.8 * f2
        return pose

    def fit_thumb(pose, target_fn, x0=(0.6, 0.3, 0.4)):
        def resid(q):
            pj, pt = _fk_hand(rest, tips, thumb(pose.copy(), *q))
            return np.concatenate([pt[4] - target_fn(pj, pt), 0.002 * np.asarray(q)])

        q = least_squares(resid, x0, bounds=([-0.5, -0.6, -0.3], [1.6, 1.6, 1.6])).x
        return thumb(pose, *q)

    fist_c = [(1.35, 1.55, 0.75)] * 4
    below = np.array([0.0, -0.012, 0.0])
    out = {"flat": np.zeros((15, 3))}
    out["relaxed"] = thumb(fingers([(0.12, 0.22, 0.10), (0.16, 0.28, 0.12), (0.26, 0.38, 0.16),
                                    (0.21, 0.33, 0.14)], (0.04, 0.0, -0.08, -0.04)),
                           0.10, 0.10, 0.15)
    fist = fingers(fist_c)
    out["fist"] = fit_thumb(fist, lambda pj, pt: 0.5 * (pj[2] + pj[5]) + below * 1.3)
    out["point"] = fit_thumb(fingers([(0.0, 0.0, 0.0)] + fist_c[1:]),
                             lambda pj, pt: pj[5] + below * 1.3)
    out["thumbs_up"] = thumb(fingers(fist_c), -0.15, -0.2, 0.0)
    peace = fingers([(0.0, 0.0, 0.0), (0.0, 0.0, 0.0)] + fist_c[2:], (0.16, -0.12, 0.0, 0.0))
    out["peace"] = fit_thumb(peace, lambda pj, pt: 0.5 * (pj[8] + pj[11]) + below * 1.3)
    ok = fingers([(0.75, 1.0, 0.6), (0.05, 0.08, 0.04), (0.10, 0.10, 0.05),
                  (0.08, 0.10, 0.05)], (0.05, -0.05, -0.25, -0.15))
    out["ok"] = fit_thumb(ok, lambda pj, pt: pt[0])
    out["spread"] = thumb(fingers([(0.0, 0.0, 0.0)] * 4, (0.28, 0.04, -0.45, -0.20)),
                          -0.35, -0.25, 0.0)
    out["claw"] = thumb(fingers([(0.15, 1.25, 1.0), (0.15, 1.25, 1.0), (0.15, 1.25, 1.0),
                                 (0.15, 1.25, 1.0)], (0.1, 0.0, -0.15, -0.07)), 0.5, 0.3, 0.9)
    pinch = fingers([(0.85, 0.9, 0.45), (0.40, 0.70, 0.35), (0.55, 0.85, 0.45),
                     (0.48, 0.78, 0.40)])
    out["pinch"] = fit_thumb(pinch, lambda pj, pt: pt[0])
    out.update(_more_poses(rest, tips, fingers, thumb, fit_thumb, fist_c))
    return out


def _more_poses(rest, tips, fingers, thumb, fit_thumb, fist_c) -> dict[str, np.ndarray]:
    """Counting gestures (three, four, L) and the halves of two-hand gestures (heart_half,
    cupped). `fingers`, `thumb` and `fit_thumb` are `_hand_poses`' builders for the right hand,
    whose fingers point along -x (`along`), thumb side +z (`side`), palm toward -y (`palm`)."""
    along = _unit(rest[4] - rest[0])  # wrist -> middle knuckle
    side, palm = np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0])
    t_len = float(np.linalg.norm(np.diff([*rest[13:16], tips[4]], axis=0), axis=1).sum())
    straight = (0.0, 0.0, 0.0)
    out = {}
    # Index, middle and ring up; the thumb holds the curled pinky down.
    three = fingers([straight, straight, fist_c[2], straight], (0.14, 0.0, 0.0, -0.12))
    out["three"] = fit_thumb(three, lambda pj, pt: pj[8] + 0.016 * palm)
    # Four fingers up and spread a little; the thumb folded across the palm toward the ring
    # finger's knuckle (as far as it reaches: it stops about 1 cm off the palm).
    four = fingers([straight] * 4, (0.14, 0.0, -0.22, -0.10))
    out["four"] = fit_thumb(four, lambda pj, pt: pj[10] + 0.012 * palm, x0=(1.0, 0.6, 0.3))
    # Thumb abducted in the palm plane, about a right angle from the straight index.
    out["L"] = thumb(fingers([straight] + fist_c[1:], (0.05, 0.0, 0.0, 0.0)), -0.85, -0.05, 0.0)
    # Fingers together and hooked toward the palm (the heart's upper lobe); the thumb straight
    # and raised off the palm so its tip closes the heart at the bottom.
    heart = fingers([(0.55, 0.85, 0.5), (0.55, 0.85, 0.5), (0.6, 0.85, 0.5), (0.58, 0.85, 0.5)],
                    (-0.06, 0.0, 0.12, 0.06))
    out["heart_half"] = fit_thumb(
        heart, lambda pj, pt: pj[13] + t_len * _unit(palm + 0.5 * side - 0.2 * along),
        x0=(0.2, 0.8, 0.0))
    # Slightly curved and together; the thumb tip beside the index tip, equally deep below the
    # palm, so that all five tips lie near one plane and can press against the other hand's.
    cupped = fingers([(0.22, 0.30, 0.15), (0.22, 0.30, 0.15), (0.26, 0.32, 0.16),
                      (0.24, 0.31, 0.15)], (-0.05, 0.0, 0.10, 0.05))
    out["cupped"] = fit_thumb(cupped, lambda pj, pt: pt[0] + 0.025 * side - 0.035 * along,
                              x0=(0.3, 0.5, 0.2))
    return out


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


def make_humanoid(seed: int = 0, resolution: float = 1.0) -> Humanoid:
    """Build the humanoid; `seed` perturbs proportions, `resolution` scales the vertex count
    (1.0 gives slightly more vertices than SMPL-X's 10,475)."""
    if not 0.1 <= resolution <= 2.0:
        raise ValueError("resolution must lie in [0.1, 2.0]")
    res = float(resolution)
    b = _body(seed)
    hg = _head_grid(res)
    head = _head(b, res, hg)
    loc = head.attrs["local"]
    lips_z = float(loc[(head.attrs["design_y"] == _MOUTH_Y) & (loc[:, 0] == 0.0), 2].max())
    pieces = [_torso(b, res), _neck(b, res), head, _eye(b, res), _ear(b, res, hg),
              _mouth_pocket(b, res, lips_z), _teeth(b, res, lips_z, True),
              _teeth(b, res, lips_z, False), _arm(b, res), _palm(b, res),
              *[_finger(b, res, k) for k in range(5)], _leg(b, res), _foot(b, res)]
    m = _mirror(pieces)
    weights = _mirrored_weights(np.concatenate([p.weights for p in pieces]), m)
    part_h = np.concatenate([p.part for p in pieces])
    pmap = np.array([_PART[swap_left_right(n)] for n in SMPLX_PART_NAMES])
    hand_left = np.concatenate([np.concatenate([p.hand for p in pieces]),
                                np.zeros(len(m.off_seam), dtype=bool)])
    regressor, joints = _joints(m, pieces, b)
    sem = _semantic(pieces, m, b)
    lf, lb = _landmarks(hg, m.face_start[id(head)], m.num_half_faces)
    tips = m.verts[[sem[f"r{f}"] for f in _FINGER_NAMES]]
    return Humanoid(
        vertices=m.verts, faces=m.faces, joints=joints, joint_regressor=regressor,
        skinning_weights=weights,
        part_labels=np.concatenate([part_h, pmap[part_h[m.off_seam]]]).astype(np.int64),
        materials=m.rows(np.concatenate([p.material for p in pieces])).astype(np.int64),
        flame_region=m.rows(np.concatenate([p.flame for p in pieces])),
        hand_region={"left": hand_left, "right": hand_left[m.mirror]}, mirror_index=m.mirror,
        semantic_vertices=sem, landmark_faces=lf[17:], landmark_bary=lb[17:],
        contour_faces=lf[:17], contour_bary=lb[:17],
        shape_basis=m.field(np.concatenate([_shape_fields(p, b) for p in pieces])),
        shape_names=SHAPE_NAMES, expression_basis=_expressions(pieces, m, b),
        expression_names=EXPRESSION_NAMES, hand_poses=_hand_poses(joints, tips),
    )


def _mirrored_weights(w_half: np.ndarray, m: _Mirrored) -> np.ndarray:
    """Skinning weights of all vertices; mirrored copies swap left and right joints."""
    jmap = np.array(mirrored_joint_index())
    w = w_half.copy()
    w[m.seam] = 0.5 * (w[m.seam] + w[m.seam][:, jmap])  # seam vertices are their own mirror
    w = np.concatenate([w, w[m.off_seam][:, jmap]])
    w[w < 1e-12] = 0.0
    return w / w.sum(1, keepdims=True)


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


def _joints(m: _Mirrored, pieces: list[_Piece], b: _Body) -> tuple[np.ndarray, np.ndarray]:
    """Joint regressor [55, V] and the joints it regresses [55, 3] (exactly symmetric)."""
    jmap = np.array(mirrored_joint_index())
    jn = np.zeros((_NJ, 3))  # nominal: left and midline from the body, right reflected
    for name, p in b.j.items():
        jn[JOINT[name]] = p
    for k, f in enumerate(_FINGER_NAMES):
        for i in range(3):
            jn[JOINT[f"left_{f}{i + 1}"]] = b.fingers[k][i]
    jn[JOINT["left_foot"]] = _foot_joint(b)
    left = [k for k, n in enumerate(SMPLX_JOINT_NAMES) if n.startswith("left")]
    jn[jmap[left]] = jn[left] * [-1.0, 1.0, 1.0]
    regressor = _regressor(m.verts, pieces, m.start, jn, b, m.mirror, jmap)
    joints = regressor @ m.verts
    joints[jmap == np.arange(_NJ), 0] = 0.0
    joints[jmap[left]] = joints[left] * [-1.0, 1.0, 1.0]
    return regressor, joints


def _foot_joint(b: _Body) -> np.ndarray:
    zk, prof = _foot_profile(b)
    z_toe = 0.12 * b.height
    w, top, bot, dx = prof(np.array([z_toe]))[0]
    ank = b.j["left_ankle"]
    return np.array([ank[0] + dx, b.floor + 0.5 * (top + bot), ank[2] + z_toe])


def _regressor(verts, pieces, start, jn, b: _Body, mirror, jmap) -> np.ndarray:
    """Sparse convex rows: each joint from a ring (or shell) of vertices of its own part."""
    reg = np.zeros((_NJ, len(verts)))
    v = verts

    def idx(p):  # the piece's vertices on the left half and their mirrors
        own = start[id(p)] + np.arange(len(p.verts))
        return own, np.unique(np.concatenate([own, mirror[own]]))

    def put(name, cand):
        reg[JOINT[name], cand] = _regress(v, cand, jn[JOINT[name]])

    kinds = {}
    for p in pieces:
        kinds.setdefault(p.kind, []).append(p)
    _, torso = idx(kinds["torso"][0])
    for name in ("pelvis", "spine1", "spine2", "spine3"):  # rings at the joint heights
        put(name, torso[np.abs(v[torso, 1] - jn[JOINT[name]][1]) < 1e-9])
    col = jn[JOINT["left_collar"]]  # inside the top of the trunk
    put("left_collar", torso[(np.abs(v[torso, 1] - col[1]) < 0.03) & (v[torso, 0] >= 0)
                             & (v[torso, 0] < 2 * col[0])])
    _, neck = idx(kinds["neck"][0])
    for name in ("neck", "head"):
        put(name, neck[np.abs(v[neck, 1] - jn[JOINT[name]][1]) < 1e-9])
    _, head = idx(kinds["head"][0])
    jaw = jn[JOINT["jaw"]]  # between the two sides of the head at the hinge
    put("jaw", head[(np.abs(v[head, 1] - jaw[1]) < 0.02) & (np.abs(v[head, 2] - jaw[2]) < 0.025)
                    & (np.abs(v[head, 0]) > 0.03)])
    put("left_eye_smplhf", idx(kinds["eye"][0])[0])
    foot = kinds["foot"][0]
    zr = foot.verts[:, 2] - b.j["left_ankle"][2]
    put("left_foot", idx(foot)[0][np.abs(zr - foot.attrs["z_toe"]) < 1e-9])
    lu, sw = kinds["arm"][0].attrs["lu"], kinds["arm"][0].attrs["sw"]
    l1 = float(np.linalg.norm(b.j["left_knee"] - b.j["left_hip"]))
    la = l1 + float(np.linalg.norm(b.j["left_ankle"] - b.j["left_knee"]))
    rings = [(kinds["arm"][0], (("left_shoulder", 0.0), ("left_elbow", lu), ("left_wrist", sw))),
             (kinds["leg"][0], (("left_hip", 0.0), ("left_knee", l1), ("left_ankle", la)))]
    for k, f in enumerate(_FINGER_NAMES):
        l1f = np.linalg.norm(b.fingers[k][1] - b.fingers[k][0])
        l2f = np.linalg.norm(b.fingers[k][2] - b.fingers[k][1])
        rings.append((kinds["finger"][k], ((f"left_{f}1", 0.0), (f"left_{f}2", l1f),
                                           (f"left_{f}3", l1f + l2f))))
    for p, stations in rings:  # tube rings at the joint stations
        own, _ = idx(p)
        for name, s0 in stations:
            put(name, own[np.abs(p.attrs["s"] - s0) < 1e-9])
    # Midline rows symmetric; right rows mirror the left ones.
    for k in range(_NJ):
        if jmap[k] == k:
            reg[k] = 0.5 * (reg[k] + reg[k][mirror])
        elif SMPLX_JOINT_NAMES[k].startswith("left"):
            reg[jmap[k]] = reg[k][mirror]
    return reg


def _semantic(pieces: list[_Piece], m: _Mirrored, b: _Body) -> dict[str, int]:
    """Named vertices (SMPL-X's `vertex_ids` keys) on the left, mirrored to the right."""
    first = {}
    for p in pieces:
        first.setdefault(p.kind, []).append(p)

    def gid(p, local):
        return int(m.start[id(p)] + local)

    head = first["head"][0]
    loc = head.attrs["local"]
    mid = np.abs(loc[:, 0]) < 1e-12
    nose = int(np.flatnonzero(mid)[np.argmax(loc[mid, 2])])
    sem = {"nose": gid(head, nose)}
    eye = first["eye"][0]
    sem["leye"] = gid(eye, np.argmax(eye.verts[:, 2]))
    ear = first["ear"][0]
    sem["lear"] = gid(ear, np.argmax(ear.verts[:, 0]))
    for k, f in enumerate(_FINGER_NAMES):
        p = first["finger"][k]
        sem[f"l{f}"] = gid(p, np.argmax(p.attrs["s"]))
    foot = first["foot"][0]
    fv = foot.verts
    xc = b.j["left_ankle"][0]
    fwd = fv[:, 2] - fv[:, 2].max()
    sem["LBigToe"] = gid(foot, np.argmax(fwd - 0.35 * (fv[:, 0] - xc)))
    sem["LSmallToe"] = gid(foot, np.argmax(fwd + 1.3 * (fv[:, 0] - xc) - 0.5 * (
        fv[:, 1] - b.floor)))
    sem["LHeel"] = gid(foot, np.argmin(fv[:, 2] + 1.5 * (fv[:, 1] - b.floor)))
    for name in list(sem):
        if name == "nose":
            continue
        other = "r" + name[1:] if name[0] == "l" else "R" + name[1:]
        sem[other] = int(m.mirror[sem[name]])
    return {k: sem[k] for k in SEMANTIC_NAMES}
