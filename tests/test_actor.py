import dataclasses
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from avatar_core.body.skeleton import LOWER_BODY_PARTS, SMPLX_PART_NAMES
from avatar_core.motion.keyframes import Pose, pose_to_params
from avatar_core.motion.rig import model_rig
from avatar_core.render.camera import Camera, look_at, orbit
from avatar_core.synth.actor import Actor, _majority, render_actor_preview
from avatar_core.synth.appearance import MATERIAL_GROUP
from avatar_core.synth.humanoid import MATERIALS

PART = {name: i for i, name in enumerate(SMPLX_PART_NAMES)}
BG = (0.2, 0.4, 0.6)


@pytest.fixture(scope="module")
def actors(synthetic_files):
    return [Actor.load(synthetic_files, i) for i in (0, 1)]


@pytest.fixture(scope="module")
def rig(synthetic_files, actors):
    return model_rig(synthetic_files, actors[0].model)


def _params(rig, joints=None, **kwargs):
    return pose_to_params(Pose(joints or {}, **kwargs), rig)


def _head_camera(size=160, yaw=25.0, pitch=5.0, distance=0.9):
    return orbit((0.0, 0.55, 0.0), yaw, pitch, distance, width=size, height=size, fov_y_deg=35)


def _body_camera(size=160):
    return orbit((0.0, -0.1, 0.0), 10.0, 5.0, 3.2, width=size, height=size, fov_y_deg=40)


def _rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t with b ~ a @ R.T + t (Kabsch)."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - ca @ r.T


def test_load_structure(actors):
    a = actors[0]
    nv = a.num_body_vertices
    assert a.model.num_vertices == nv and a.betas.shape == (10,)
    assert len(a.faces) == len(a.face_parts) and a.faces.max() == len(a.canonical) - 1
    assert set(np.unique(a.face_parts)) >= {PART[p] for p in ("head", "neck", "leftFoot")}
    # Accessory faces: hair bound to the scalp (head), the collar to the neck.
    acc = a.faces[a.num_body_faces:]
    hair = a.hair_vertices[acc[:, 0] - nv]
    assert hair.any() and (~hair).any()
    np.testing.assert_array_equal(a.face_parts[a.num_body_faces:][hair], PART["head"])
    np.testing.assert_array_equal(a.face_parts[a.num_body_faces:][~hair], PART["neck"])
    np.testing.assert_allclose(a.group_weights.sum(1), 1.0, atol=1e-5)
    assert len(MATERIAL_GROUP) == len(MATERIALS)


def test_render_is_deterministic_and_thread_safe(actors, rig, synthetic_files):
    a = actors[0]
    params = _params(rig, {"head": (0.1, 0.3, 0.0)}, expression={"smile": 0.6})
    cams = [_head_camera(yaw=y) for y in (-40.0, 0.0, 40.0, 160.0)]
    posed = a.pose(params)
    serial = [a.render(posed, c, background=BG) for c in cams]
    with ThreadPoolExecutor(2) as pool:
        threaded = list(pool.map(lambda c: a.render(a.pose(params), c, background=BG), cams))
    again = Actor.load(synthetic_files, 0)
    fresh = again.render(again.pose(params), cams[1], background=BG)
    for x, y in [*zip(serial, threaded, strict=True), (serial[1], fresh)]:
        for k in ("rgb", "alpha", "parts"):
            np.testing.assert_array_equal(getattr(x, k), getattr(y, k))


def test_alpha_parts_and_rgb_agree(actors, rig):
    a = actors[0]
    posed = a.pose(_params(rig))
    cam = _head_camera(size=128)
    view = a.render(posed, cam, background=BG)
    assert view.rgb.shape == (128, 128, 3) and view.rgb.dtype == np.float32
    assert view.alpha.dtype == np.float32 and view.parts.dtype == np.int16
    assert 0.0 <= view.rgb.min() and view.rgb.max() <= 1.0
    empty = view.alpha == 0
    np.testing.assert_array_equal(view.parts == -1, empty)
    assert np.all(view.parts[view.alpha > 0.5] >= 0)
    np.testing.assert_array_equal(view.rgb[empty], np.tile(np.float32(BG), (empty.sum(), 1)))
    # Coverage comes in quarters (2 x 2 samples) and is fractional along the silhouette.
    np.testing.assert_array_equal(view.alpha * 4, np.round(view.alpha * 4))
    edge = (view.alpha > 0) & (view.alpha < 1)
    assert edge.sum() > 100
    # rgb = alpha * object + (1 - alpha) * background: two backgrounds differ by exactly
    # (1 - alpha) times their difference, and nothing else changes.
    other = a.render(posed, cam, background=(1.0, 0.9, 0.0))
    np.testing.assert_array_equal(other.alpha, view.alpha)
    np.testing.assert_array_equal(other.parts, view.parts)
    expected = (1.0 - view.alpha)[..., None] * (np.float32([1.0, 0.9, 0.0]) - np.float32(BG))
    np.testing.assert_allclose(other.rgb - view.rgb, expected, atol=2e-6)
    # Without supersampling the coverage is binary; with 3 x 3 it comes in ninths.
    hard = a.render(posed, cam, background=BG, supersample=1)
    assert set(np.unique(hard.alpha)) == {0.0, 1.0}
    np.testing.assert_array_equal(hard.parts == -1, hard.alpha == 0)
    nine = a.render(posed, cam, background=BG, supersample=3)
    np.testing.assert_allclose(nine.alpha * 9, np.round(nine.alpha * 9), atol=1e-5)
    np.testing.assert_array_equal(nine.parts == -1, nine.alpha == 0)
    assert abs(nine.alpha.sum() - view.alpha.sum()) < 0.02 * view.alpha.sum()


def test_numpy_twins_of_the_sample_kernels(actors, rig, monkeypatch):
    from avatar_core.synth import actor as actor_module

    a = actors[0]
    posed = a.pose(_params(rig, {"head": (0.0, 0.4, 0.0)}))
    cam = _head_camera(size=96)
    compiled = a.render(posed, cam, background=BG)
    twins = {"gather": actor_module._gather_reference,
             "accumulate": actor_module._accumulate_reference}
    monkeypatch.setattr(actor_module, "_kernel", twins.__getitem__)
    reference = a.render(posed, cam, background=BG)
    np.testing.assert_array_equal(reference.alpha, compiled.alpha)
    np.testing.assert_array_equal(reference.parts, compiled.parts)
    np.testing.assert_allclose(reference.rgb, compiled.rgb, atol=1e-5)


def test_majority_part_label():
    lab = np.array([[3, 3, 5, 5, -1, -1, 7, 9],
                    [5, -1, 5, 3, -1, -1, 9, 7]], dtype=np.int16)
    # Pixels (2 x 2 samples): {3,3,5,-1} -> 3; {5,5,5,3} -> 5; empty -> -1; tie {7,9,9,7}
    # -> the top-left sample's label.
    np.testing.assert_array_equal(_majority(lab, 2), [[3, 5, -1, 7]])
    np.testing.assert_array_equal(_majority(lab[:1], 1), lab[:1])


def test_back_face_culling_never_changes_the_image(actors, rig):
    a = actors[1]
    open_all = dataclasses.replace(a, closed=np.zeros_like(a.closed))
    posed = a.pose(_params(rig, {"jaw": (0.3, 0.0, 0.0), "head": (0.2, 0.6, 0.1)}))
    for cam in (_head_camera(128, 50.0, 10.0, 0.5), _head_camera(128, 170.0, -30.0, 0.7),
                _body_camera(128)):
        x, y = a.render(posed, cam), open_all.render(posed, cam)
        for k in ("rgb", "alpha", "parts"):
            np.testing.assert_array_equal(getattr(x, k), getattr(y, k))


def test_hair_and_collar_follow_the_body(actors, rig):
    a = actors[0]
    nv = a.num_body_vertices
    rest = a.pose(_params(rig))
    turned = a.pose(_params(rig, {"neck": (0.1, 0.3, 0.0), "head": (0.2, 0.5, 0.1)}))
    head = np.unique(a.faces[: a.num_body_faces][a.face_parts[: a.num_body_faces]
                                                 == PART["head"]])
    r, t = _rigid_fit(rest.vertices[head], turned.vertices[head])
    hair = nv + np.flatnonzero(a.hair_vertices)
    moved = np.linalg.norm(turned.vertices[hair] - rest.vertices[hair], axis=1)
    assert moved.max() > 0.05  # the head really turned
    np.testing.assert_allclose(turned.vertices[hair], rest.vertices[hair] @ r.T + t, atol=2e-3)
    # The hair's centroid keeps its place relative to the head joint.
    c0, c1 = rest.vertices[hair].mean(0), turned.vertices[hair].mean(0)
    np.testing.assert_allclose(c1 - turned.joints[15], r @ (c0 - rest.joints[15]), atol=2e-3)
    # The collar stays around the neck: its distance to the neck surface barely changes.
    collar = nv + np.flatnonzero(~a.hair_vertices)
    neck = np.unique(a.faces[: a.num_body_faces][a.face_parts[: a.num_body_faces]
                                                 == PART["neck"]])

    def gap(p):
        d = np.linalg.norm(p.vertices[collar][:, None] - p.vertices[neck][None], axis=2)
        return d.min(axis=1)

    np.testing.assert_allclose(gap(turned), gap(rest), atol=4e-3)
    # A whole-body motion moves every accessory vertex rigidly with it.
    spun = a.pose({**_params(rig), "global_orient": np.array([0.0, 1.2, 0.0]),
                   "transl": np.array([0.3, 0.1, -0.2])})
    r, t = _rigid_fit(rest.body_vertices, spun.body_vertices)
    np.testing.assert_allclose(spun.accessory_vertices, rest.accessory_vertices @ r.T + t,
                               atol=1e-6)


def test_texture_sticks_to_the_surface(actors, rig):
    # Translating the body and the camera together shows the same canonical points at the
    # same pixels: a solid texture evaluated in the rest pose gives them the same colour (the
    # world-fixed lights see unchanged normals).
    a = actors[0]
    shift = np.array([0.4, -0.1, 0.25])
    base = _head_camera(size=128, yaw=30.0)
    moved_cam = Camera(base.K, base.R, base.t - base.R @ shift, base.width, base.height)
    x = a.render(a.pose(_params(rig)), base, background=BG)
    y = a.render(a.pose({**_params(rig), "transl": shift}), moved_cam, background=BG)
    same = (x.alpha == 1) & (y.alpha == 1)
    assert same.mean() > 0.3
    diff = np.abs(x.rgb - y.rgb)[same].max(axis=1)
    assert np.mean(diff < 2e-3) > 0.99
    # Turning the body in place keeps the pattern on it: the colour under a canonical point
    # changes by shading only, so the shirt's texture contrast survives in the new view.
    turned = a.render(a.pose({**_params(rig), "global_orient": np.array([0.0, 0.6, 0.0])}),
                      base, background=BG)
    shirt = (turned.parts == PART["spine2"]) & (turned.alpha == 1)
    assert shirt.sum() > 200 and turned.rgb[shirt].std(axis=0).max() > 0.03


def test_identities_look_different(actors, rig):
    cam = _head_camera(size=128, yaw=0.0)
    views = [a.render(a.pose(_params(rig)), cam, background=BG) for a in actors]
    assert actors[0].name != actors[1].name
    assert not np.array_equal(actors[0].betas, actors[1].betas)
    both = (views[0].alpha == 1) & (views[1].alpha == 1)
    assert np.abs(views[0].rgb - views[1].rgb)[both].mean() > 0.1
    # Identity 0 wears fuller hair than identity 1: hair height over the scalp (metres).
    thickness = [_hair_height(a) for a in actors]
    assert np.percentile(thickness[0], 90) > 1.5 * np.percentile(thickness[1], 90)
    assert 0.02 < np.percentile(thickness[0], 90) < 0.045
    assert 0.01 < np.percentile(thickness[1], 90) < 0.02


def _hair_height(a: Actor) -> np.ndarray:
    n = int(a.hair_vertices.sum())
    hair = a.canonical[a.num_body_vertices:][: n]
    foot = np.einsum("ak,akc->ac", a.binding.bary[:n], a.canonical[a.faces[a.binding.face[:n]]])
    return np.linalg.norm(hair - foot, axis=1)


def test_lower_body_in_the_part_mask(actors, rig):
    a = actors[0]
    view = a.render(a.pose(_params(rig)), _body_camera(), background=BG)
    seen = {SMPLX_PART_NAMES[p] for p in np.unique(view.parts) if p >= 0}
    assert {"leftUpLeg", "rightLeg", "leftFoot", "hips", "head", "leftHand"} <= seen
    assert set(LOWER_BODY_PARTS) & seen


def test_camera_looking_away_sees_nothing(actors, rig):
    a = actors[0]
    cam = look_at((0.0, 0.5, 2.5), (0.0, 0.5, 5.0), width=64, height=48)
    view = a.render(a.pose(_params(rig)), cam, background=BG)
    assert view.alpha.max() == 0 and np.all(view.parts == -1)
    np.testing.assert_array_equal(view.rgb, np.broadcast_to(np.float32(BG), (48, 64, 3)))


def test_invalid_input_raises(actors, rig, synthetic_files):
    a = actors[0]
    params = _params(rig)
    params["body_pose"] = params["body_pose"].copy()
    params["body_pose"][3, 1] = np.nan
    with pytest.raises(ValueError, match="body_pose.*NaN"):
        a.pose(params)
    posed = a.pose(_params(rig))
    cam = _head_camera(size=32)
    with pytest.raises(ValueError, match="background"):
        a.render(posed, cam, background=(2.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="supersample"):
        a.render(posed, cam, supersample=0)
    with pytest.raises(ValueError, match="does not belong"):
        actors[1].render(dataclasses.replace(posed, vertices=posed.vertices[:-1]), cam)
    with pytest.raises(ValueError, match="identity"):
        Actor.load(synthetic_files, 5)


def test_preview_png(synthetic_files, tmp_path):
    import cv2

    out = render_actor_preview(synthetic_files, 1, tmp_path / "preview" / "actor.png", size=48)
    image = cv2.imread(str(out))
    assert image.shape == (96, 144, 3)
    assert (image.std(axis=(0, 1)) > 10).all()  # the actor, not an empty background
