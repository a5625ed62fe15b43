"""Invariants of the procedural SMPL-X stand-in (`avatar_core.synth.humanoid`)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from avatar_core.body.skeleton import (
    JOINT,
    LEFT_HAND_JOINTS,
    RIGHT_HAND_JOINTS,
    SMPLX_PARENTS,
    SMPLX_PART_NAMES,
    mirrored_joint_index,
    swap_left_right,
)
from avatar_core.synth.humanoid import (
    EXPRESSION_NAMES,
    MATERIALS,
    SEMANTIC_NAMES,
    SHAPE_NAMES,
    Humanoid,
    make_humanoid,
)

FLIP = np.array([-1.0, 1.0, 1.0])
JMAP = np.array(mirrored_joint_index())
PMAP = np.array([SMPLX_PART_NAMES.index(swap_left_right(n)) for n in SMPLX_PART_NAMES])
FLAME_JOINTS = [JOINT[n] for n in ("neck", "head", "jaw", "left_eye_smplhf", "right_eye_smplhf")]
IBUG_FLIP = np.array(
    [16, 15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0,
     26, 25, 24, 23, 22, 21, 20, 19, 18, 17, 27, 28, 29, 30, 35, 34, 33, 32, 31,
     45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40,
     54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55, 64, 63, 62, 61, 60, 67, 66, 65])  # fmt: skip


@pytest.fixture(scope="module")
def h() -> Humanoid:
    return make_humanoid(seed=0, resolution=0.4)


@pytest.fixture(scope="module")
def full() -> Humanoid:
    return make_humanoid(seed=0, resolution=1.0)


@pytest.fixture(scope="module", params=[0.3, 0.4, 0.7])
def hr(request) -> Humanoid:
    return make_humanoid(seed=3, resolution=request.param)


def lbs(h: Humanoid, verts: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Plain linear blend skinning: rotate each joint about its rest position, chained."""
    j = h.joint_regressor @ verts
    rot = Rotation.from_rotvec(pose).as_matrix()
    g = np.zeros((55, 4, 4))
    for k, p in enumerate(SMPLX_PARENTS):
        local = np.eye(4)
        local[:3, :3] = rot[k]
        local[:3, 3] = j[k] - (j[p] if p >= 0 else 0.0)
        g[k] = g[p] @ local if p >= 0 else local
    g[:, :3, 3] -= np.einsum("kij,kj->ki", g[:, :3, :3], j)
    t = np.einsum("vk,kij->vij", h.skinning_weights, g)
    return np.einsum("vij,vj->vi", t[:, :3, :3], verts) + t[:, :3, 3]


def components(h: Humanoid) -> list[np.ndarray]:
    n = len(h.vertices)
    f = h.faces
    adj = coo_matrix((np.ones(3 * len(f)), (f.ravel(), np.roll(f, 1, axis=1).ravel())),
                     shape=(n, n))
    _, lab = connected_components(adj, directed=False)
    return [np.flatnonzero(lab == k) for k in range(lab.max() + 1)]


def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    tri = verts[faces] - verts[faces].reshape(-1, 3).mean(0)
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def ray_hits(origin: np.ndarray, direction: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Möller-Trumbore: distances along the ray to the triangles it crosses (t > 0)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-15
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - tri[:, 0]
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ direction) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
    return t[hit]


# ------------------------------------------------------------------------------- basics


def test_full_resolution_vertex_count(full, h):
    assert 10_475 <= len(full.vertices) <= 14_000
    assert len(h.vertices) < 0.6 * len(full.vertices)


def test_shapes_and_dtypes(h):
    v = len(h.vertices)
    assert h.vertices.shape == (v, 3) and h.vertices.dtype == np.float64
    assert h.faces.dtype == np.int64 and h.faces.shape[1] == 3
    assert h.joints.shape == (55, 3)
    assert h.joint_regressor.shape == (55, v)
    assert h.skinning_weights.shape == (v, 55)
    assert h.part_labels.shape == (v,) and h.part_labels.dtype == np.int64
    assert h.materials.shape == (v,) and h.materials.dtype == np.int64
    assert h.flame_region.dtype == bool and h.flame_region.shape == (v,)
    assert set(h.hand_region) == {"left", "right"}
    assert h.mirror_index.shape == (v,) and h.mirror_index.dtype == np.int64
    assert h.landmark_faces.shape == (51,) and h.landmark_bary.shape == (51, 3)
    assert h.contour_faces.shape == (17,) and h.contour_bary.shape == (17, 3)
    assert h.shape_basis.shape == (v, 3, 10) and h.expression_basis.shape == (v, 3, 10)
    assert h.shape_names == SHAPE_NAMES and len(set(SHAPE_NAMES)) == 10
    assert h.expression_names == EXPRESSION_NAMES == (
        "smile", "grin", "lips_part", "pucker", "cheek_puff", "blink_left", "blink_right",
        "brows_raise", "brows_lower", "frown")
    assert MATERIALS[0] == "skin" and len(MATERIALS) == 12


def test_deterministic_and_seeded():
    a, b = make_humanoid(seed=5, resolution=0.4), make_humanoid(seed=5, resolution=0.4)
    for name in ("vertices", "faces", "joints", "joint_regressor", "skinning_weights",
                 "shape_basis", "expression_basis", "landmark_bary"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    for k in a.hand_poses:
        assert np.array_equal(a.hand_poses[k], b.hand_poses[k])
    c = make_humanoid(seed=6, resolution=0.4)
    assert np.array_equal(a.faces, c.faces)  # same topology
    diff = np.abs(a.vertices - c.vertices).max()
    assert 1e-3 < diff < 0.1  # a different but similar person


def test_body_proportions(h):
    v = h.vertices
    assert -0.99 < v[:, 1].min() < -0.91 and 0.71 < v[:, 1].max() < 0.79
    assert np.linalg.norm(h.joints[JOINT["pelvis"]]) < 0.03
    span = v[:, 0].max() - v[:, 0].min()
    assert 1.5 < span < 1.9  # T-pose arm span ~ height
    j = h.joints
    assert j[JOINT["head"], 1] > j[JOINT["neck"], 1] > j[JOINT["spine3"], 1] > j[0, 1]
    assert j[JOINT["left_knee"], 1] < j[JOINT["left_hip"], 1]
    assert j[JOINT["left_ankle"], 1] < j[JOINT["left_knee"], 1]
    assert j[JOINT["left_wrist"], 0] > j[JOINT["left_elbow"], 0] > j[JOINT["left_shoulder"], 0]
    assert j[JOINT["left_foot"], 2] > j[JOINT["left_ankle"], 2] + 0.05
    jaw, head = j[JOINT["jaw"]], j[JOINT["head"]]
    assert abs(jaw[0]) < 1e-12 and jaw[1] > head[1] - 0.01
    eye = j[JOINT["left_eye_smplhf"]]
    assert eye[0] > 0.02 and eye[1] > jaw[1] and eye[2] > 0.05


# --------------------------------------------------------------------------- topology


def test_faces_valid_and_not_degenerate(hr):
    f, v = hr.faces, hr.vertices
    assert f.min() >= 0 and f.max() < len(v)
    assert (f[:, 0] != f[:, 1]).all() and (f[:, 1] != f[:, 2]).all() and (f[:, 0] != f[:, 2]).all()
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert area.min() > 1e-10
    assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f)
    assert np.isin(np.arange(len(v)), f).all()  # no stray vertices


def test_parts_are_closed_consistent_and_outward(hr):
    f = hr.faces
    volumes = []
    open_parts = 0
    for comp in components(hr):
        mask = np.isin(f[:, 0], comp)
        cf = f[mask]
        edges = np.concatenate([cf[:, [0, 1]], cf[:, [1, 2]], cf[:, [2, 0]]])
        directed = {tuple(e) for e in edges}
        assert len(directed) == len(edges)  # no directed edge twice: consistent winding
        undirected = np.unique(np.sort(edges, axis=1), axis=0, return_counts=True)[1]
        assert undirected.max() <= 2
        if undirected.min() == 1:
            open_parts += 1  # the head skin: open at the mouth and eye slits
        volumes.append(signed_volume(hr.vertices, cf))
    assert open_parts == 1
    assert min(volumes) > 0.0
    assert signed_volume(hr.vertices, f) > 0.05  # ~ a person's volume in m^3


def test_open_boundary_is_only_the_slits(h):
    f = h.faces
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    border = np.unique(uniq[counts == 1])
    assert h.flame_region[border].all()
    assert (h.part_labels[border] == SMPLX_PART_NAMES.index("head")).all()
    pos = h.vertices[border]
    left_eye = h.joints[JOINT["left_eye_smplhf"]]
    eye = np.where(pos[:, [0]] >= 0, left_eye, left_eye * FLIP)
    near_eye = np.linalg.norm(pos - eye, axis=1) < 0.025
    mouth = np.abs(pos[:, 0]) < 0.035
    assert (near_eye | mouth).all()


# ---------------------------------------------------------------------------- symmetry


def test_exact_mirror_symmetry(hr):
    m = hr.mirror_index
    assert np.array_equal(m[m], np.arange(len(m)))
    assert np.array_equal(hr.vertices[m], hr.vertices * FLIP)
    assert np.allclose(hr.skinning_weights[m][:, JMAP], hr.skinning_weights, atol=1e-12)
    assert np.allclose(hr.joint_regressor[JMAP][:, m], hr.joint_regressor, atol=1e-12)
    assert np.array_equal(PMAP[hr.part_labels[m]], hr.part_labels)
    assert np.array_equal(hr.materials[m], hr.materials)
    assert np.array_equal(hr.flame_region[m], hr.flame_region)
    assert np.array_equal(hr.hand_region["left"][m], hr.hand_region["right"])
    assert np.allclose(hr.joints[JMAP], hr.joints * FLIP, atol=1e-12)
    faces = {tuple(sorted(t)) for t in hr.faces.tolist()}
    assert {tuple(sorted(t)) for t in m[hr.faces].tolist()} == faces
    assert np.allclose(hr.shape_basis[m], hr.shape_basis * FLIP[:, None], atol=1e-15)
    e = hr.expression_basis
    keep = [i for i, n in enumerate(EXPRESSION_NAMES) if "blink" not in n]
    assert np.allclose(e[m][:, :, keep], e[:, :, keep] * FLIP[:, None], atol=1e-15)
    assert np.allclose(e[m][:, :, 5], e[:, :, 6] * FLIP, atol=1e-15)
    midline = m == np.arange(len(m))
    assert (hr.vertices[midline, 0] == 0.0).all() and (hr.vertices[~midline, 0] != 0.0).all()


def test_semantic_vertices_mirror(h):
    s = h.semantic_vertices
    assert set(s) == set(SEMANTIC_NAMES) and len(set(s.values())) == len(s)
    for name, idx in s.items():
        if name == "nose":
            assert h.mirror_index[idx] == idx
            continue
        other = {"l": "r", "r": "l", "L": "R", "R": "L"}[name[0]] + name[1:]
        assert h.mirror_index[idx] == s[other]
        left = name[0] in "lL"
        assert (h.vertices[idx, 0] > 0) == left


# ------------------------------------------------------------------ joints and skinning


def test_regressor_reproduces_joints(hr):
    r = hr.joint_regressor
    assert (r >= 0).all()
    assert np.allclose(r.sum(1), 1.0, atol=1e-12)
    assert np.allclose(r @ hr.vertices, hr.joints, atol=1e-9)
    assert ((r > 0).sum(1) <= 200).all()  # sparse rows


def test_regressor_regions(hr):
    r = hr.joint_regressor
    for j in FLAME_JOINTS:
        assert r[j, ~hr.flame_region].max(initial=0) == 0
    for side, hand_joints in (("left", LEFT_HAND_JOINTS), ("right", RIGHT_HAND_JOINTS)):
        wrist = JOINT[f"{side}_wrist"]
        for j in (wrist, *hand_joints):
            assert r[j, ~hr.hand_region[side]].max(initial=0) == 0


def test_skinning_weights(hr):
    w = hr.skinning_weights
    assert (w >= 0).all()
    assert np.allclose(w.sum(1), 1.0, atol=1e-12)
    others = np.setdiff1d(np.arange(55), FLAME_JOINTS)
    assert w[hr.flame_region][:, others].max() == 0
    for side, hand_joints in (("left", LEFT_HAND_JOINTS), ("right", RIGHT_HAND_JOINTS)):
        allowed = [JOINT[f"{side}_wrist"], *hand_joints]
        rest = np.setdiff1d(np.arange(55), allowed)
        assert w[hr.hand_region[side]][:, rest].max() == 0
        assert (w[hr.hand_region[side]][:, allowed].sum(1) > 1 - 1e-12).all()
    for eye, joint in (("leftEye", "left_eye_smplhf"), ("rightEye", "right_eye_smplhf")):
        ball = hr.part_labels == SMPLX_PART_NAMES.index(eye)
        assert ball.sum() > 20
        assert np.allclose(w[ball, JOINT[joint]], 1.0)


def test_skinning_follows_the_chain(h):
    w, v, j = h.skinning_weights, h.vertices, h.joints
    dom = w.argmax(1)
    labels = np.array(SMPLX_PART_NAMES)[h.part_labels]
    # Mid-segment vertices are driven by the segment's proximal joint (SMPL convention).
    for part, joint in (("leftArm", "left_shoulder"), ("leftForeArm", "left_elbow"),
                        ("leftUpLeg", "left_hip"), ("leftLeg", "left_knee")):
        sel = labels == part
        a, b = {"leftArm": ("left_shoulder", "left_elbow"),
                "leftForeArm": ("left_elbow", "left_wrist"), "leftUpLeg": ("left_hip", "left_knee"),
                "leftLeg": ("left_knee", "left_ankle")}[part]
        pa, pb = j[JOINT[a]], j[JOINT[b]]
        t = (v[sel] - pa) @ (pb - pa) / np.sum((pb - pa) ** 2)
        mid = (t > 0.3) & (t < 0.7)
        assert mid.sum() > 10 and (dom[sel][mid] == JOINT[joint]).all(), part
    # The jaw drives the chin, the head the forehead.
    head = labels == "head"
    front = head & (np.abs(v[:, 0]) < 0.01) & (v[:, 2] > 0.05)
    chin = front & (v[:, 1] < j[JOINT["jaw"], 1] - 0.06)
    brow = front & (v[:, 1] > j[JOINT["left_eye_smplhf"], 1] + 0.02)
    assert chin.any() and (w[chin, JOINT["jaw"]] > 0.9).all()
    assert brow.any() and (w[brow, JOINT["head"]] == 1).all()


def test_skinning_is_smooth(full):
    """Weights change gradually between mesh neighbours (blends span a few centimetres)."""
    w, f = full.skinning_weights, full.faces
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    jump = np.abs(w[edges[:, 0]] - w[edges[:, 1]]).sum(1)  # 2 = a complete switch
    assert np.quantile(jump, 0.99) < 1.3
    assert np.quantile(jump, 0.9) < 0.7
    body = ~full.hand_region["left"] & ~full.hand_region["right"] & ~full.flame_region
    inner = body[edges].all(1)
    assert jump[inner].max() < 1.8


def test_jaw_opens_the_mouth(h):
    pose = np.zeros((55, 3))
    pose[JOINT["jaw"], 0] = 0.3
    posed = lbs(h, h.vertices, pose)
    moved = np.linalg.norm(posed - h.vertices, axis=1)
    v = h.vertices
    # Coincident rest vertices on the lip line are the slit's upper/lower copies.
    lips = np.flatnonzero(h.materials == MATERIALS.index("lips"))
    key = {}
    pairs = []
    for i in lips:
        k = tuple(np.round(v[i], 12))
        if k in key:
            pairs.append((key[k], i))
        key[k] = i
    assert len(pairs) >= 3
    pairs = np.array(pairs)
    gap = np.abs(posed[pairs[:, 0], 1] - posed[pairs[:, 1], 1])
    assert gap.max() > 0.02
    assert moved[~h.flame_region].max() < 1e-12


# ------------------------------------------------------------------------- expressions


def test_expressions_stay_in_the_face(hr):
    e = hr.expression_basis
    assert np.abs(e[~hr.flame_region]).max() == 0
    eyes = np.isin(hr.part_labels, [SMPLX_PART_NAMES.index("leftEye"),
                                    SMPLX_PART_NAMES.index("rightEye")])
    assert np.abs(e[eyes]).max() == 0
    mag = np.linalg.norm(e, axis=1).max(0)  # [10]
    assert (mag > 0.003).all() and (mag < 0.03).all()
    for name, lo, hi in (("smile", 0.006, 0.012), ("cheek_puff", 0.008, 0.013),
                         ("brows_raise", 0.006, 0.011)):
        assert lo < mag[EXPRESSION_NAMES.index(name)] < hi, name


def test_blink_closes_only_the_left_eye(hr):
    e = hr.expression_basis
    blink = np.linalg.norm(e[:, :, EXPRESSION_NAMES.index("blink_left")], axis=1)
    moved = blink > 0
    eye = hr.joints[JOINT["left_eye_smplhf"]]
    assert moved.sum() > 5
    assert (hr.vertices[moved, 0] > 0).all()
    assert (np.linalg.norm(hr.vertices[moved] - eye, axis=1) < 0.03).all()
    skin_mats = [MATERIALS.index(n) for n in ("skin", "hair", "eyebrow", "lips")]
    skin = hr.faces[np.isin(hr.materials[hr.faces], skin_mats).all(1)]
    forward = np.array([0.0, 0.0, 1.0])
    for name, side, closes in (("blink_left", "left", True), ("blink_left", "right", False),
                               ("blink_right", "right", True)):
        coef = np.zeros(10)
        coef[EXPRESSION_NAMES.index(name)] = 1.0
        v = hr.vertices + hr.expression_basis @ coef
        ball = np.flatnonzero(hr.part_labels == SMPLX_PART_NAMES.index(f"{side}Eye"))
        centre = hr.joints[JOINT[f"{side}_eye_smplhf"]]
        front = ball[v[ball, 2] > centre[2] + 0.004]  # the part that can show through the lids
        seen = [len(ray_hits(v[i] + 1e-6 * forward, forward, v[skin])) == 0 for i in front]
        seen_rest = [len(ray_hits(hr.vertices[i] + 1e-6 * forward, forward,
                                  hr.vertices[skin])) == 0 for i in front]
        assert np.mean(seen_rest) > 0.4  # open eyes at rest: iris and pupil show
        assert hr.semantic_vertices[f"{side[0]}eye"] in front[np.array(seen_rest)]
        if closes:
            assert not any(seen), name
        else:
            assert seen == seen_rest, name


def test_lips_part_and_smile_directions(h):
    e, v = h.expression_basis, h.vertices
    lips = np.flatnonzero(h.materials == MATERIALS.index("lips"))
    mid = lips[np.abs(v[lips, 0]) < 1e-12]
    y0 = v[mid, 1]
    moved = v[mid] + e[mid][:, :, EXPRESSION_NAMES.index("lips_part")]
    # Coincident midline lip vertices (the slit) separate by a few millimetres.
    order = np.argsort(y0)
    same = np.flatnonzero(np.diff(y0[order]) == 0)
    assert len(same) >= 1
    a, b = mid[order][same[0]], mid[order][same[0] + 1]
    gap = np.abs(moved[mid.tolist().index(a), 1] - moved[mid.tolist().index(b), 1])
    assert 0.003 < gap < 0.012
    corner = lips[np.argmax(v[lips, 0])]
    smile = e[corner, :, EXPRESSION_NAMES.index("smile")]
    frown = e[corner, :, EXPRESSION_NAMES.index("frown")]
    grin = e[corner, :, EXPRESSION_NAMES.index("grin")]
    assert smile[1] > 0.004 and smile[0] > 0 and frown[1] < -0.004 and grin[0] > 0.005
    pucker = e[mid, :, EXPRESSION_NAMES.index("pucker")]
    assert (pucker[:, 2] > 0.003).all()
    raise_ = e[:, 1, EXPRESSION_NAMES.index("brows_raise")]
    brows = h.materials == MATERIALS.index("eyebrow")
    assert raise_[brows].mean() > 0.005
    lower = e[:, :, EXPRESSION_NAMES.index("brows_lower")]
    inner = brows & (np.abs(v[:, 0]) < 0.03)
    assert lower[inner, 1].mean() < -0.002 and (lower[inner, 0] * np.sign(v[inner, 0])).mean() < 0


# ------------------------------------------------------------------------ shape basis


def test_shape_basis_is_plausible(h):
    s = h.shape_basis
    height = s[:, :, SHAPE_NAMES.index("height")]
    for c in (-2.0, 2.0):
        v = h.vertices + c * height
        dh = (v[:, 1].max() - v[:, 1].min()) - (h.vertices[:, 1].max() - h.vertices[:, 1].min())
        assert 0.06 < abs(dh) < 0.1 and np.sign(dh) == np.sign(c)
    lengths0 = np.linalg.norm(h.joints[1:] - h.joints[list(SMPLX_PARENTS[1:])], axis=1)
    for k in range(10):
        for c in (-2.0, 2.0):
            v = h.vertices + c * s[:, :, k]
            j = h.joint_regressor @ v
            lengths = np.linalg.norm(j[1:] - j[list(SMPLX_PARENTS[1:])], axis=1)
            assert np.abs(lengths - lengths0).max() < 0.05, SHAPE_NAMES[k]
            assert np.abs(j - h.joints).max() < 0.1, SHAPE_NAMES[k]
        assert np.abs(s[:, :, k]).max() > 0.003, SHAPE_NAMES[k]


# ------------------------------------------------------------------ labels and regions


def test_part_labels(hr):
    names = np.array(SMPLX_PART_NAMES)
    present = set(names[np.unique(hr.part_labels)])
    assert present <= set(SMPLX_PART_NAMES)
    assert set(SMPLX_PART_NAMES) - present <= {"eyeballs"}  # eyes are leftEye / rightEye
    v = hr.vertices
    labels = names[hr.part_labels]
    waist = v[labels == "spine", 1].min()
    for part in ("hips", "leftUpLeg", "rightUpLeg", "leftLeg", "leftFoot", "leftToeBase"):
        assert v[labels == part, 1].max() <= waist + 1e-9, part
    assert v[labels == "head", 1].min() > v[labels == "spine2", 1].max() - 0.01
    assert (v[labels == "leftHandIndex1", 0] > v[labels == "leftForeArm", 0].max() - 0.05).all()
    for part in ("leftArm", "leftForeArm", "leftHand", "leftShoulder", "leftUpLeg", "leftEye"):
        assert (v[labels == part, 0] > 0).all(), part
    assert (v[labels == "leftToeBase", 2] > v[labels == "leftFoot", 2].mean()).all()


def test_materials(h):
    m = np.array(MATERIALS)[h.materials]
    assert set(m) == set(MATERIALS)
    v = h.vertices
    head = h.part_labels == SMPLX_PART_NAMES.index("head")
    assert (v[m == "hair", 1].mean() > v[head, 1].mean())
    assert (m[h.part_labels == SMPLX_PART_NAMES.index("leftEye")] != "skin").all()
    pupil = h.semantic_vertices["leye"]
    assert m[pupil] == "pupil"
    assert (m[np.isin(h.part_labels, [SMPLX_PART_NAMES.index(p) for p in ("leftFoot",
                                                                          "leftToeBase")])]
            != "skin").sum() > 0
    assert set(m[h.hand_region["left"]]) == {"skin"}
    assert (m[h.part_labels == SMPLX_PART_NAMES.index("leftUpLeg")] == "trousers").all()


def test_regions(h):
    labels = np.array(SMPLX_PART_NAMES)[h.part_labels]
    head_parts = np.isin(labels, ["head", "leftEye", "rightEye"])
    assert h.flame_region[head_parts].all()
    assert not h.flame_region[~np.isin(labels, ["head", "leftEye", "rightEye", "neck"])].any()
    neck = labels == "neck"
    assert h.flame_region[neck].any() and not h.flame_region[neck].all()
    left, right = h.hand_region["left"], h.hand_region["right"]
    assert not (left & right).any()
    assert left[np.isin(labels, ["leftHand", "leftHandIndex1"])].all()
    assert set(labels[left]) == {"leftHand", "leftHandIndex1", "leftForeArm"}
    wrist = h.joints[JOINT["left_wrist"], 0]
    assert h.vertices[left, 0].min() > wrist - 0.03  # only a short cuff of forearm


# ------------------------------------------------------------------- semantic vertices


def test_semantic_vertices(h):
    s, v = h.semantic_vertices, h.vertices
    labels = np.array(SMPLX_PART_NAMES)[h.part_labels]
    head = np.flatnonzero((labels == "head") & (np.abs(v[:, 0]) < 0.01))
    assert s["nose"] == head[np.argmax(v[head, 2])]
    assert v[s["nose"], 1] < h.joints[JOINT["left_eye_smplhf"], 1]
    assert np.allclose(v[s["leye"]], h.joints[JOINT["left_eye_smplhf"]] + [0, 0, 0.0118], atol=2e-3)
    ear = np.flatnonzero(labels == "head")
    assert s["lear"] == ear[np.argmax(v[ear, 0])]
    wrist = h.joints[JOINT["left_wrist"]]
    for f in ("thumb", "index", "middle", "ring", "pinky"):
        tip = v[s[f"l{f}"]]
        d3 = h.joints[JOINT[f"left_{f}3"]]
        along = (tip - d3) / np.linalg.norm(tip - d3)
        near = h.skinning_weights.argmax(1) == JOINT[f"left_{f}3"]
        assert ((v[near] - d3) @ along).max() <= (tip - d3) @ along + 1e-12, f
        assert np.linalg.norm(tip - wrist) > np.linalg.norm(d3 - wrist), f
    assert s["lmiddle"] == np.argmax(v[:, 0])
    toe, small, heel = v[s["LBigToe"]], v[s["LSmallToe"]], v[s["LHeel"]]
    assert toe[2] > h.joints[JOINT["left_foot"], 2] and small[2] > h.joints[JOINT["left_foot"], 2]
    assert toe[0] < small[0]  # the big toe is on the inner side
    assert heel[2] < h.joints[JOINT["left_ankle"], 2] and heel[1] < h.joints[JOINT["left_ankle"], 1]
    for k in ("LBigToe", "LSmallToe"):
        assert labels[s[k]] == "leftToeBase"
    assert labels[s["LHeel"]] == "leftFoot"


# --------------------------------------------------------------------------- landmarks


def landmark_points(h: Humanoid, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ijk->ik", bary, h.vertices[h.faces[faces]])


def test_landmarks(hr):
    faces = np.concatenate([hr.contour_faces, hr.landmark_faces])
    bary = np.concatenate([hr.contour_bary, hr.landmark_bary])
    assert (bary >= 0).all() and np.allclose(bary.sum(1), 1.0)
    assert hr.flame_region[hr.faces[faces]].all()
    assert (hr.part_labels[hr.faces[faces]] == SMPLX_PART_NAMES.index("head")).all()
    p = landmark_points(hr, faces, bary)  # [68, 3] in iBUG order
    assert np.allclose(p[IBUG_FLIP], p * FLIP, atol=1e-12)
    # Subject's right (image left, -x) first; eyes above nose above mouth above chin.
    assert p[0, 0] < 0 < p[16, 0] and p[36, 0] < 0 < p[45, 0] and p[48, 0] < 0 < p[54, 0]
    assert p[17:27, 1].min() > p[36:48, 1].max() > p[30, 1] > p[51, 1] > p[57, 1] > p[8, 1]
    assert p[30, 2] == p[:, 2].max()  # nose tip in front
    assert np.linalg.norm(p[30] - hr.vertices[hr.semantic_vertices["nose"]]) < 0.005
    assert p[37, 1] > p[41, 1] and p[44, 1] > p[46, 1]  # eyes are open
    assert abs(p[62, 1] - p[66, 1]) < 1e-9  # closed mouth: inner lips meet
    assert np.all(np.diff(p[8:17, 1]) > 0)  # the jaw line rises toward the ear


# -------------------------------------------------------------------------- hand poses


def test_hand_poses(h):
    names = {"flat", "relaxed", "fist", "point", "thumbs_up", "peace", "ok", "spread", "claw",
             "pinch"}
    assert names <= set(h.hand_poses)
    for p in h.hand_poses.values():
        assert p.shape == (15, 3) and np.isfinite(p).all()
    assert np.abs(h.hand_poses["flat"]).max() == 0
    s = h.semantic_vertices
    tips = [s[k] for k in ("rindex", "rmiddle", "rring", "rpinky", "rthumb")]
    wrist = h.joints[JOINT["right_wrist"]]

    def posed(name):
        pose = np.zeros((55, 3))
        pose[40:55] = h.hand_poses[name]
        v = lbs(h, h.vertices, pose)
        assert np.allclose(v[~h.hand_region["right"]], h.vertices[~h.hand_region["right"]],
                           atol=1e-12)
        return v[tips]

    flat = posed("flat")
    d_flat = np.linalg.norm(flat - wrist, axis=1)
    relaxed = posed("relaxed")
    assert (relaxed[:4, 1] < flat[:4, 1]).all()  # curling goes toward the palm (-y)
    fist = posed("fist")
    assert (np.linalg.norm(fist[:4] - wrist, axis=1) < 0.7 * d_flat[:4]).all()
    assert (fist[:4, 1] < wrist[1]).all()
    point = posed("point")
    d_point = np.linalg.norm(point - wrist, axis=1)
    assert d_point[0] > 0.95 * d_flat[0] and (d_point[1:4] < 0.7 * d_flat[1:4]).all()
    peace = posed("peace")
    d_peace = np.linalg.norm(peace - wrist, axis=1)
    assert (d_peace[:2] > 0.95 * d_flat[:2]).all() and (d_peace[2:4] < 0.7 * d_flat[2:4]).all()
    assert np.linalg.norm(peace[0] - peace[1]) > 1.3 * np.linalg.norm(flat[0] - flat[1])
    for name in ("ok", "pinch"):
        t = posed(name)
        assert np.linalg.norm(t[4] - t[0]) < 0.02, name
    spread = posed("spread")
    assert np.linalg.norm(spread[0] - spread[3]) > 1.3 * np.linalg.norm(flat[0] - flat[3])
    claw = posed("claw")
    assert (np.linalg.norm(claw[:4] - wrist, axis=1) < 0.9 * d_flat[:4]).all()
    up = posed("thumbs_up")
    assert np.linalg.norm(up[4] - wrist) > 0.9 * d_flat[4]
