"""The rig: skinning weights of the full mesh, joints, the joint regressor and the semantic
vertices."""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from avatar_core.body.skeleton import JOINT, SMPLX_JOINT_NAMES, mirrored_joint_index

from .limbs import _foot_profile
from .mirror import _Mirrored
from .names import _FINGER_NAMES, _NJ, SEMANTIC_NAMES
from .pieces import _Piece
from .proportions import _Body


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


def _mirrored_weights(w_half: np.ndarray, m: _Mirrored) -> np.ndarray:
    """Skinning weights of all vertices; mirrored copies swap left and right joints."""
    jmap = np.array(mirrored_joint_index())
    w = w_half.copy()
    w[m.seam] = 0.5 * (w[m.seam] + w[m.seam][:, jmap])  # seam vertices are their own mirror
    w = np.concatenate([w, w[m.off_seam][:, jmap]])
    w[w < 1e-12] = 0.0
    return w / w.sum(1, keepdims=True)


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
