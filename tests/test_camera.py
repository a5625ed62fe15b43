import json
import math

import numpy as np
import pytest

from avatar_core.render.camera import Camera, intrinsics_from_fov, look_at, orbit


def _rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _cam(**kw) -> Camera:
    base = dict(
        K=np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]]),
        R=_rot_y(20.0),
        t=np.array([0.1, -0.2, 3.0]),
        width=640,
        height=480,
    )
    base.update(kw)
    return Camera(**base)


def test_intrinsics_from_fov():
    K = intrinsics_from_fov(640, 480, 60.0)
    f = 240.0 / math.tan(math.radians(30.0))
    np.testing.assert_allclose(K, [[f, 0, 320], [0, f, 240], [0, 0, 1]])
    with pytest.raises(ValueError, match="fov"):
        intrinsics_from_fov(64, 64, 180.0)


def test_look_at_centres_target_with_positive_depth():
    target = np.array([0.3, 1.2, -0.4])
    cam = look_at([1.0, 2.0, 2.5], target, width=321, height=200, fov_y_deg=40.0)
    uv, z = cam.project(target)
    np.testing.assert_allclose(uv, [321 / 2, 100.0], atol=1e-9)
    assert z > 0
    np.testing.assert_allclose(z, np.linalg.norm(target - [1.0, 2.0, 2.5]))
    np.testing.assert_allclose(cam.center, [1.0, 2.0, 2.5], atol=1e-12)


def test_look_at_up_is_image_top_and_not_mirrored():
    # Camera on +z looking at the origin (front view of a y-up body facing +z).
    cam = look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], width=100, height=100)
    np.testing.assert_allclose(cam.R, np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    (u_right, v_right), _ = cam.project([0.2, 0.0, 0.0])  # world +x = the subject's left
    (u_up, v_up), _ = cam.project([0.0, 0.2, 0.0])
    assert u_right > 50 and abs(v_right - 50) < 1e-9  # subject's left -> image RIGHT
    assert v_up < 50 and abs(u_up - 50) < 1e-9  # world up -> image TOP (smaller v)


def test_look_at_rejects_degenerate():
    with pytest.raises(ValueError, match="coincide"):
        look_at([1, 1, 1], [1, 1, 1], width=10, height=10)
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 5, 0], [0, 0, 0], width=10, height=10)


@pytest.mark.parametrize("yaw,pitch", [(0, 0), (35, 10), (-120, -30), (200, 80)])
def test_orbit_matches_look_at(yaw, pitch):
    target = np.array([0.1, 1.3, 0.05])
    cam = orbit(target, yaw, pitch, 2.5, width=64, height=48, fov_y_deg=25.0)
    ref = look_at(cam.center, target, width=64, height=48, fov_y_deg=25.0)
    np.testing.assert_allclose(cam.R, ref.R, atol=1e-12)
    np.testing.assert_allclose(cam.t, ref.t, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(cam.center - target), 2.5)
    uv, z = cam.project(target)
    np.testing.assert_allclose(uv, [32.0, 24.0], atol=1e-9)
    np.testing.assert_allclose(z, 2.5)


def test_orbit_directions():
    o = np.zeros(3)
    np.testing.assert_allclose(orbit(o, 0, 0, 2.0, width=8, height=8).center, [0, 0, 2], atol=1e-12)
    np.testing.assert_allclose(
        orbit(o, 90, 0, 2.0, width=8, height=8).center, [2, 0, 0], atol=1e-12
    )
    np.testing.assert_allclose(
        orbit(o, 0, 30, 2.0, width=8, height=8).center, [0, 1.0, math.sqrt(3)], atol=1e-12
    )
    # Straight down is well defined; the camera looks along -y.
    top = orbit(o, 0, 90, 2.0, width=8, height=8)
    np.testing.assert_allclose(top.center, [0, 2, 0], atol=1e-12)
    np.testing.assert_allclose(top.R[2], [0, -1, 0], atol=1e-12)


def test_world_to_camera_and_project_match_K_R_t():
    cam = _cam()
    rng = np.random.default_rng(0)
    p = rng.normal(size=(4, 5, 3))
    xc = cam.world_to_camera(p)
    np.testing.assert_allclose(xc, np.einsum("ij,abj->abi", cam.R, p) + cam.t)
    uv, z = cam.project(p)
    assert uv.shape == (4, 5, 2) and z.shape == (4, 5)
    hom = np.einsum("ij,abj->abi", cam.K, xc)
    np.testing.assert_allclose(uv, hom[..., :2] / hom[..., 2:])
    np.testing.assert_allclose(z, xc[..., 2])
    np.testing.assert_allclose(cam.viewmat() @ np.append(p[0, 0], 1.0), np.append(xc[0, 0], 1))
    np.testing.assert_allclose(cam.world_to_camera(cam.center), 0.0, atol=1e-12)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500.0, 480.0, 320.0, 240.0)


def test_torch_inputs():
    torch = pytest.importorskip("torch")
    cam = _cam()
    p = np.random.default_rng(1).normal(size=(6, 3))
    uv_t, z_t = cam.project(torch.tensor(p, dtype=torch.float64))
    uv, z = cam.project(p)
    assert isinstance(uv_t, torch.Tensor)
    np.testing.assert_allclose(uv_t.numpy(), uv)
    np.testing.assert_allclose(z_t.numpy(), z)
    viewmat, K = cam.to_torch()
    assert viewmat.shape == (4, 4) and K.dtype == torch.float32
    # Tensors are accepted when constructing, too.
    K_t, R_t, t_t = (torch.tensor(a.copy()) for a in (cam.K, cam.R, cam.t))
    cam2 = Camera(K_t, R_t, t_t, 640, 480)
    assert cam2 == cam


def test_resized_scales_intrinsics():
    cam = _cam()
    small = cam.resized(160, 96)
    np.testing.assert_allclose(small.K, [[125.0, 0, 80.0], [0, 96.0, 48.0], [0, 0, 1]])
    assert (small.width, small.height) == (160, 96)
    np.testing.assert_array_equal(small.R, cam.R)
    # A point projects to the same *relative* image position (corner-origin convention).
    p = np.array([0.3, -0.2, 1.0])
    uv, _ = cam.project(p)
    uv_s, _ = small.project(p)
    np.testing.assert_allclose(uv_s / [160, 96], uv / [640, 480])
    # Pixel centres map onto pixel centres when downsampling by an integer factor 2:
    # the centre of 2x2 block (0,0) is (1, 1) at full size and (0.5, 0.5) at half size.
    half = cam.resized(320, 240)
    ray = np.linalg.solve(cam.K, [1.0, 1.0, 1.0])
    world = cam.R.T @ (ray * 2.0 - cam.t)
    np.testing.assert_allclose(half.project(world)[0], [0.5, 0.5], atol=1e-9)


def test_cropped_shifts_principal_point():
    cam = _cam()
    c = cam.cropped(100, 40, 200, 150)
    np.testing.assert_allclose(c.K[:, 2], [220.0, 200.0, 1.0])
    np.testing.assert_allclose(c.K[:2, :2], cam.K[:2, :2])
    p = np.array([0.2, 0.1, 1.5])
    np.testing.assert_allclose(c.project(p)[0], cam.project(p)[0] - [100, 40])
    assert (c.width, c.height) == (200, 150)


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(K=np.full((3, 3), np.nan)), "non-finite"),
        (dict(t=np.array([0.0, np.inf, 0.0])), "non-finite"),
        (dict(R=np.eye(3) * 1.01), "orthonormal"),
        (dict(R=np.diag([1.0, 1.0, -1.0])), "det"),
        (dict(width=0), "width"),
        (dict(height=-3), "height"),
        (dict(width=12.5), "width"),
        (dict(K=np.eye(2)), "shape"),
        (dict(t=np.zeros(4)), "shape"),
        (dict(K=np.diag([-1.0, 1.0, 1.0])), "focal"),
        (dict(K=np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 1.0, 1.0]])), "last row"),
    ],
)
def test_validation_errors(kw, match):
    with pytest.raises(ValueError, match=match):
        _cam(**kw)


def test_camera_is_immutable():
    cam = _cam()
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0  # read-only array
    with pytest.raises(AttributeError):
        cam.width = 3  # frozen dataclass


def test_dict_round_trip():
    cam = _cam()
    d = json.loads(json.dumps(cam.to_dict()))
    back = Camera.from_dict(d)
    assert back == cam
    np.testing.assert_array_equal(back.K, cam.K)
    assert isinstance(back.width, int)
    with pytest.raises(ValueError, match="missing"):
        Camera.from_dict({"K": d["K"]})
