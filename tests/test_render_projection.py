"""EWA projection: gsplat conventions, culling, hard cases, input validation."""

import math

import numpy as np
import pytest
import torch

from avatar_core.render.camera import look_at
from avatar_core.render.contract import EPS2D
from avatar_core.render.projection import (
    check_finite,
    covariance_3d,
    project_gaussians,
    quat_to_rotmat,
)

CAM = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=64, height=48, fov_y_deg=40.0)


def _project(means, quats=None, scales=None, opac=None, cam=CAM, antialiased=False,
             dtype=torch.float64):
    n = len(means)
    means = torch.as_tensor(np.asarray(means, dtype=np.float64), dtype=dtype)
    quats = torch.tensor([[1.0, 0, 0, 0]] * n, dtype=dtype) if quats is None \
        else torch.as_tensor(np.asarray(quats, dtype=np.float64), dtype=dtype)
    scales = torch.full((n, 3), 0.05, dtype=dtype) if scales is None \
        else torch.as_tensor(np.asarray(scales, dtype=np.float64), dtype=dtype)
    opac = torch.full((n,), 0.8, dtype=dtype) if opac is None else torch.as_tensor(opac,
                                                                                 dtype=dtype)
    viewmat, K = cam.to_torch(dtype=dtype)
    return project_gaussians(means, quats, scales, opac, viewmat, K, cam.width, cam.height,
                             antialiased=antialiased)


def test_matches_a_direct_ewa_computation():
    rng = np.random.default_rng(0)
    mean = np.array([0.1, -0.05, 0.2])
    q = rng.normal(size=4)
    s = np.array([0.03, 0.08, 0.01])
    p = _project([mean], [q], [s])
    # independent numpy EWA
    w, x, y, z = q / np.linalg.norm(q)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    cov_w = R @ np.diag(s ** 2) @ R.T
    xc = CAM.R @ mean + CAM.t
    J = np.array([[CAM.fx / xc[2], 0, -CAM.fx * xc[0] / xc[2] ** 2],
                  [0, CAM.fy / xc[2], -CAM.fy * xc[1] / xc[2] ** 2]])
    cov2d = J @ CAM.R @ cov_w @ CAM.R.T @ J.T + EPS2D * np.eye(2)
    inv = np.linalg.inv(cov2d)
    assert np.allclose(p.conics[0].numpy(), [inv[0, 0], inv[0, 1], inv[1, 1]], rtol=1e-9)
    uv, depth = CAM.project(mean)
    assert np.allclose(p.means2d[0].numpy(), uv)
    assert np.isclose(p.depths[0].item(), depth)
    lam = np.linalg.eigvalsh(cov2d).max()
    assert p.radii[0].item() == math.ceil(3 * math.sqrt(lam))
    assert p.valid[0]


def test_jacobian_clamped_to_widened_frustum():
    # far off to the side: the Jacobian is evaluated at x/z = 1.3 tan(fov_x / 2)
    mean = np.array([40.0, 0.0, 0.0])  # camera space (40, 0, 2.5)
    p = _project([mean], scales=[[0.05, 0.05, 0.05]])
    xc = CAM.R @ mean + CAM.t
    lim = 1.3 * 0.5 * CAM.width / CAM.fx
    J = np.array([[CAM.fx / xc[2], 0, -CAM.fx * lim / xc[2]],
                  [0, CAM.fy / xc[2], 0]])
    cov2d = J @ (0.05 ** 2 * np.eye(3)) @ J.T + EPS2D * np.eye(2)
    inv = np.linalg.inv(cov2d)
    assert np.allclose(p.conics[0].numpy(), [inv[0, 0], inv[0, 1], inv[1, 1]], rtol=1e-9)


def test_culling_rules():
    means = [
        [0.0, 0.0, 0.0],        # visible
        [0.0, 0.0, 3.0],        # behind the camera
        [0.0, 0.0, 2.5],        # on the camera centre
        [0.0, 0.0, 2.495],      # in front of it, but nearer than the near plane (0.01)
        [0.0, 0.0, 2.48],       # just past the near plane: kept (huge, but finite)
        [50.0, 0.0, 0.0],       # off-screen
        [0.0, 0.0, -2e10],      # beyond the far plane
    ]
    p = _project(means)
    assert p.valid.tolist() == [True, False, False, False, True, False, False]
    for t in (p.means2d, p.conics, p.depths, p.opacities):
        assert torch.isfinite(t).all()
    assert (p.radii[~p.valid] == 0).all()
    assert p.radii.dtype == torch.int32


def test_hard_inputs_stay_finite_with_gradients():
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 2.5], [0.0, 0.0, 3.0], [0.0, 0.0, 2.495],
                          [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, -1e6]],
                         dtype=torch.float64, requires_grad=True)
    quats = torch.tensor([[0.0, 0, 0, 0], [1.0, 0, 0, 0], [1.0, 0, 0, 0], [1.0, 0, 0, 0],
                          [0.3, 0.2, 0.1, 0.9], [1.0, 0, 0, 0], [1.0, 0, 0, 0]],
                         dtype=torch.float64, requires_grad=True)
    scales = torch.tensor([[0.05] * 3, [0.05] * 3, [0.05] * 3, [1.0] * 3, [1e-8] * 3,
                           [1e3] * 3, [0.05] * 3], dtype=torch.float64, requires_grad=True)
    opac = torch.full((7,), 0.5, dtype=torch.float64, requires_grad=True)
    viewmat, K = CAM.to_torch(dtype=torch.float64)
    for aa in (False, True):
        p = project_gaussians(means, quats, scales, opac, viewmat, K, 64, 48, antialiased=aa)
        loss = (p.means2d.sum() + p.conics.sum() + p.opacities.sum() + p.depths.sum())
        grads = torch.autograd.grad(loss, (means, quats, scales, opac))
        for t in (p.means2d, p.conics, p.opacities, p.depths, *grads):
            assert torch.isfinite(t).all()


def test_zero_quaternion_is_identity():
    R = quat_to_rotmat(torch.zeros(2, 4))
    assert torch.equal(R, torch.eye(3).expand(2, 3, 3))
    q = torch.tensor([[2.0, 0.0, 0.0, 0.0]])  # normalised inside
    assert torch.allclose(quat_to_rotmat(q), torch.eye(3)[None])
    cov = covariance_3d(torch.zeros(1, 4), torch.tensor([[1.0, 2.0, 3.0]]))
    assert torch.allclose(cov[0], torch.diag(torch.tensor([1.0, 4.0, 9.0])))


def test_antialiased_compensation():
    p0 = _project([[0.0, 0.0, 0.0]], scales=[[0.004, 0.002, 0.003]])
    p1 = _project([[0.0, 0.0, 0.0]], scales=[[0.004, 0.002, 0.003]], antialiased=True)
    a, b, c = p0.conics[0].tolist()
    cov = np.linalg.inv([[a, b], [b, c]])  # dilated
    comp = math.sqrt(np.linalg.det(cov - EPS2D * np.eye(2)) / np.linalg.det(cov))
    assert 0 < comp < 1
    assert math.isclose(p1.opacities[0].item(), 0.8 * comp, rel_tol=1e-9)
    assert torch.equal(p0.conics, p1.conics)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_input_raises(bad):
    means = torch.zeros(3, 3)
    means[1, 2] = bad
    viewmat, K = CAM.to_torch()
    with pytest.raises(ValueError, match="means"):
        project_gaussians(means, torch.zeros(3, 4), torch.ones(3, 3), torch.ones(3), viewmat,
                          K, 64, 48)
    with pytest.raises(ValueError, match="opacities"):
        check_finite(opacities=torch.tensor([0.5, bad]))


def test_finite_check_is_not_fooled_by_overflowing_sums():
    big = torch.full((4,), 3e38)  # finite values whose float32 sum overflows
    check_finite(big=big)
    big[2] = float("-inf")
    with pytest.raises(ValueError, match="big"):
        check_finite(big=big)
    mixed = torch.tensor([float("inf"), float("-inf"), 1.0])  # sums to NaN
    with pytest.raises(ValueError):
        check_finite(mixed=mixed)
