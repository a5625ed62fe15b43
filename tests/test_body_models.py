"""Body-model objects: rest pose, kinematics, the stage cache, dtypes, batching, errors."""

import numpy as np
import pytest
import torch

from avatar_core.body import lbs
from avatar_core.body.errors import ParameterError
from avatar_core.body.models import FLAMEModel, MANOModel, SMPLXModel
from avatar_core.body.skeleton import JOINT, SMPLX_PARENTS
from tests.conftest import random_smplx_params


def _descendants(joint: int) -> set[int]:
    out = {joint}
    for j, p in enumerate(SMPLX_PARENTS):
        if p in out:
            out.add(j)
    return out


def test_rest_pose_reproduces_the_template(smplx_data, flame_data, mano_data):
    out = SMPLXModel(smplx_data, flat_hand_mean=True, dtype=torch.float64)({})
    assert np.allclose(out.vertices[0].numpy(), smplx_data.v_template, atol=1e-12)
    assert np.allclose(out.joints[0].numpy(), smplx_data.joint_template, atol=1e-12)
    flame = FLAMEModel(flame_data, dtype=torch.float64)({})
    assert np.allclose(flame.vertices[0].numpy(), flame_data.v_template, atol=1e-12)
    mano = MANOModel(mano_data["right"], flat_hand_mean=True, dtype=torch.float64)({})
    assert np.allclose(mano.vertices[0].numpy(), mano_data["right"].v_template, atol=1e-12)


@pytest.mark.parametrize("joint", ["spine2", "left_elbow", "right_wrist", "jaw", "left_index1",
                                   "neck", "right_knee"])
def test_rotating_one_joint_moves_only_its_descendants(smplx_data, joint):
    model = SMPLXModel(smplx_data, flat_hand_mean=True, dtype=torch.float64)
    j = JOINT[joint]
    params = {}
    aa = np.array([0.4, -0.7, 0.5])
    if joint == "jaw":
        params["jaw_pose"] = aa
    elif j >= 25:
        side = "left" if j < 40 else "right"
        pose = np.zeros((15, 3))
        pose[(j - 25) % 15] = aa
        params[f"{side}_hand_pose"] = pose
    else:
        pose = np.zeros((21, 3))
        pose[j - 1] = aa
        params["body_pose"] = pose
    out = model(params)
    rest = model({})
    desc = sorted(_descendants(j))
    moved_joints = (out.joints - rest.joints).abs().amax(-1)[0] > 1e-12
    assert set(np.flatnonzero(moved_joints.numpy())) <= set(desc) - {j}
    assert moved_joints.any() == (len(desc) > 1)
    influenced = smplx_data.weights[:, desc].sum(1) > 0
    moved = ((out.vertices - rest.vertices).abs().amax(-1)[0] > 1e-12).numpy()
    assert moved.any()
    assert not (moved & ~influenced).any()


def test_cache_reuses_pose_work_and_matches_uncached(smplx_data):
    cached = SMPLXModel(smplx_data, dtype=torch.float64)
    plain = SMPLXModel(smplx_data, dtype=torch.float64, cache=False)
    params = random_smplx_params(2, seed=5)
    with torch.no_grad():
        cached(params)
        for k in range(3):
            params["expression"] = np.random.default_rng(k).normal(0, 1, (2, 10))
            a, b = cached(params), plain(params)
            assert torch.equal(a.vertices, b.vertices) and torch.equal(a.joints, b.joints)
            assert torch.equal(a.landmarks, b.landmarks)
        assert cached.cache.hits["pose"] == 3 and cached.cache.hits["shape"] == 3
        assert cached.cache.misses["expression"] == 4
        params["betas"] = params["betas"] + 0.1
        a, b = cached(params), plain(params)
        assert torch.equal(a.vertices, b.vertices)
        assert cached.cache.misses["shape"] == 2


def test_cache_is_bypassed_for_differentiable_inputs(smplx_data):
    model = SMPLXModel(smplx_data, dtype=torch.float64)
    pose = torch.zeros(1, 21, 3, dtype=torch.float64, requires_grad=True)
    for _ in range(2):
        out = model({"body_pose": pose})
        out.vertices.sum().backward()
        assert torch.isfinite(pose.grad).all()
    assert model.cache.hits["pose"] == 0


def test_float32_agrees_with_float64_and_batches_with_singles(smplx_data):
    params = random_smplx_params(3, seed=8)
    m64 = SMPLXModel(smplx_data, dtype=torch.float64)
    m32 = SMPLXModel(smplx_data, dtype=torch.float32)
    v64 = m64(params).vertices
    assert (m32(params).vertices.double() - v64).abs().max() < 1e-4
    for i in range(3):
        single = {k: v[i] for k, v in params.items()}
        assert torch.allclose(m64(single).vertices[0], v64[i], atol=1e-12)


def test_gradients_stay_finite_at_extreme_poses(smplx_data):
    model = SMPLXModel(smplx_data, dtype=torch.float32)
    for scale in (0.0, np.pi, 50.0):
        pose = torch.full((1, 21, 3), scale / np.sqrt(3), requires_grad=True)
        betas = torch.full((1, 10), 5.0, requires_grad=True)
        out = model({"body_pose": pose, "betas": betas})
        assert torch.isfinite(out.vertices).all()
        out.vertices.square().sum().backward()
        assert torch.isfinite(pose.grad).all() and torch.isfinite(betas.grad).all()


@pytest.mark.parametrize("bad", [
    {"body_pose": np.zeros((1, 22, 3))},
    {"expression": np.full((1, 10), np.nan)},
    {"global_orient": [0.0, np.inf, 0.0]},
    {"left_hand_pose": np.zeros((1, 6))},
])
def test_bad_parameters_raise_a_clear_error(smplx_data, bad):
    with pytest.raises(ParameterError, match=next(iter(bad))):
        SMPLXModel(smplx_data)(bad)


def test_device_move_clears_the_cache(smplx_data):
    model = SMPLXModel(smplx_data)
    with torch.no_grad():
        model({})
        model.double()
        out = model({})
    assert out.vertices.dtype == torch.float64


def test_cached_staged_model_matches_the_plain_lbs_reference(smplx_data):
    """The model's shortcuts (joint blend shapes, pruned correctives, stage cache) are exact."""
    params = random_smplx_params(2, seed=9, scale=0.5)
    model = SMPLXModel(smplx_data, dtype=torch.float64)
    out = model(params)
    t = {k: torch.as_tensor(v) for k, v in params.items()}
    coeffs = torch.cat([t["betas"], t["expression"]], 1)
    dirs = torch.as_tensor(np.concatenate([smplx_data.shapedirs, smplx_data.exprdirs], 2))
    verts, joints = lbs.lbs(coeffs, out.full_pose, torch.as_tensor(smplx_data.v_template), dirs,
                            torch.as_tensor(smplx_data.posedirs),
                            torch.as_tensor(smplx_data.joint_regressor), smplx_data.parents,
                            torch.as_tensor(smplx_data.weights))
    transl = t["transl"][:, None]
    assert torch.allclose(out.vertices, verts + transl, atol=1e-12)
    assert torch.allclose(out.joints, joints + transl, atol=1e-12)
