"""The fitter's fast keypoints + analytic Jacobian against their reference twins: the torch
`BodyKeypoints` forward and its autograd Jacobian, and finite differences of the objective."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar_core.body import lbs
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.synth.model_writer import ensure_models
from avatar_core.track.fit.camera import WebcamCamera
from avatar_core.track.fit.fitter import FrameFitter, _Problem, neutral_params
from avatar_core.track.fit.kinematics import rodrigues_and_left_jacobian
from avatar_core.track.fit.observations import empty_observations
from tests.fit_jacobian import assert_objective_jacobian

CAMERA = WebcamCamera(640, 480, 60.0)


@pytest.fixture(scope="module")
def fitter():
    files = ensure_models()
    package, model = synthetic_package(files.root, 0)
    return FrameFitter(model, np.asarray(package.body.betas))


def _reference(fitter: FrameFitter, full_pose: np.ndarray, expression: np.ndarray,
               transl: np.ndarray):
    """BodyKeypoints' layout from the torch model: points [K, 3], and the autograd Jacobians
    by the full pose [K, 3, 55, 3] and the expression [K, 3, E]."""
    kp = fitter.keypoints
    m = kp.model
    m.cache.clear()

    def points(pose: torch.Tensor, expr: torch.Tensor) -> torch.Tensor:
        out = m.skin(fitter.betas, expr[None], pose[None], torch.as_tensor(transl)[None])
        rows = torch.cat([out.joints, out.vertices, out.landmarks], 1)[0][kp.table]
        return torch.where(kp.available[:, None], rows, torch.nan)

    args = (torch.as_tensor(full_pose), torch.as_tensor(expression))
    m.cache.enabled = False
    try:
        pts = points(*args).numpy()
        d_pose, d_expr = torch.autograd.functional.jacobian(points, args)
    finally:
        m.cache.enabled = True
    return pts, d_pose.numpy(), d_expr.numpy()


POSES = {
    "random": lambda rng: rng.normal(0, 0.4, (55, 3)),
    "rest": lambda rng: np.zeros((55, 3)),  # every rotation on the Taylor branch
    "tiny": lambda rng: rng.normal(0, 1e-6, (55, 3)),
    "near_pi": lambda rng: rng.normal(0, 1, (55, 3)) * (3.1 / np.linalg.norm(
        rng.normal(0, 1, (55, 1, 3)), axis=-1)),
    "wound_many_turns": lambda rng: rng.normal(0, 20.0, (55, 3)),  # |theta| >> 2 pi
    "head_turned_far": lambda rng: np.pad(rng.normal(0, 0.2, (54, 3)), ((1, 0), (0, 0)))
    + np.array([0, 1.4, 0]),  # yaw past the contour table's end
}


@pytest.mark.parametrize("case", sorted(POSES))
def test_points_and_jacobian_match_the_torch_model_and_autograd(fitter, case):
    rng = np.random.default_rng(len(case))
    pose = POSES[case](rng)
    expr = rng.normal(0, 0.8, fitter.num_expression)
    transl = np.array([0.05, -0.4, -1.2])
    joints = list(range(55))
    pts, d_pose, d_expr = fitter.kinematics.evaluate(pose, expr, transl, joints, True)
    ref, ref_pose, ref_expr = _reference(fitter, pose, expr, transl)
    avail = fitter.kinematics.available
    assert np.array_equal(np.isnan(pts).any(1), ~avail)
    np.testing.assert_allclose(pts[avail], ref[avail], atol=1e-12)
    np.testing.assert_allclose(d_pose[avail], ref_pose[avail], atol=1e-10)
    np.testing.assert_allclose(d_expr[avail], ref_expr[avail], atol=1e-10)
    assert np.all(d_pose[~avail] == 0) or np.all(np.isnan(d_pose[~avail]))


def test_rodrigues_and_left_jacobian(fitter):
    rng = np.random.default_rng(3)
    theta = np.concatenate([rng.normal(0, 1, (20, 3)), np.zeros((1, 3)),
                            rng.normal(0, 1e-5, (3, 3))])
    rot, jl = rodrigues_and_left_jacobian(theta)
    ref = lbs.rodrigues(torch.as_tensor(theta)).numpy()
    np.testing.assert_allclose(rot, ref, atol=1e-13)
    # exp(theta + d) ~ exp(Jl d) exp(theta): the left Jacobian by central differences.
    eps = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        plus, _ = rodrigues_and_left_jacobian(theta + d)
        minus, _ = rodrigues_and_left_jacobian(theta - d)
        omega_hat = (plus - minus) / (2 * eps) @ rot.transpose(0, 2, 1)  # skew(Jl e_i)
        omega = np.stack([omega_hat[:, 2, 1], omega_hat[:, 0, 2], omega_hat[:, 1, 0]], -1)
        np.testing.assert_allclose(omega, jl[:, :, i], atol=1e-8)


def test_objective_jacobian_matches_finite_differences(fitter):
    """The whole residual vector (data, priors, active hinges, temporal term)."""
    rng = np.random.default_rng(7)
    p = neutral_params(fitter.keypoints.model)
    p["transl"] = np.array([0.0, -0.45, -1.1])
    x = fitter.pack(p) + rng.normal(0, 0.3, fitter.pack(p).size)
    x[fitter.layout["transl"][0]] = p["transl"]
    x[fitter.layout["expression"][0].start] = 2.0  # past the +-1.5 bound: an active hinge
    x[fitter.layout["jaw_pose"][0]] = [0.8, 0.0, 0.0]  # past the jaw's 30 deg
    pixels = fitter._data(x + rng.normal(0, 0.02, x.size), CAMERA, False).pixels
    target = np.nan_to_num(pixels)
    sqrt_w = np.where(fitter.kinematics.available, rng.uniform(0.5, 1.0, len(target)), 0.0)
    obs = empty_observations((640, 480))
    obs.depth[:] = rng.normal(0, 20.0, len(target))  # hand and face z: relative-depth pairs
    problem = _Problem(CAMERA, target, 6.4, x + 0.01, fitter._depth_pairs(obs, sqrt_w ** 2))
    assert problem.depth_pairs is not None and len(problem.depth_pairs[0]) == 2 * 20 + 50
    assert_objective_jacobian(fitter, x, problem, sqrt_w)


def test_non_finite_pose_gives_nan_points_not_a_crash(fitter):
    pose = np.zeros((55, 3))
    pose[15] = np.nan
    pts, d_pose, _ = fitter.kinematics.evaluate(pose, np.zeros(fitter.num_expression),
                                                np.zeros(3), [0, 15], True)
    assert np.isnan(pts[fitter.kinematics.available]).any()
    assert d_pose.shape[2:] == (2, 3)
