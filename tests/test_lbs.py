"""The pure LBS functions: Rodrigues' hard cases, the kinematic chain against a naive twin."""

import math

import pytest
import torch

from avatar_core.body import lbs
from avatar_core.body.skeleton import SMPLX_PARENTS


def _orthonormality_error(rot: torch.Tensor) -> float:
    eye = torch.eye(3, dtype=rot.dtype)
    return float((rot.transpose(-1, -2) @ rot - eye).abs().max().detach())


def test_rodrigues_matches_matrix_exponential():
    r = torch.randn(500, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 2
    expected = torch.linalg.matrix_exp(lbs.skew(r))
    assert torch.allclose(lbs.rodrigues(r), expected, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-7, 1e-4, 1e-3])
def test_rodrigues_near_zero_is_exact_with_finite_gradient(dtype, angle):
    axis = torch.tensor([0.3, -0.5, 0.81], dtype=torch.float64)
    axis = axis / axis.norm()
    r = (axis * angle).to(dtype).requires_grad_(True)
    rot = lbs.rodrigues(r)
    expected = torch.linalg.matrix_exp(lbs.skew(r.detach().double()))
    assert torch.allclose(rot.double(), expected, atol=1e-7 if dtype == torch.float32 else 1e-14)
    rot.sum().backward()
    assert torch.isfinite(r.grad).all()
    if angle == 0.0:
        # d/dr sum(I + K + ...) at 0 is the sum of the skew generators' entries: zero.
        assert torch.allclose(r.grad, torch.zeros(3, dtype=dtype))


def test_rodrigues_gradient_at_zero_is_the_skew_generator():
    r = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    jac = torch.autograd.functional.jacobian(lambda x: lbs.rodrigues(x), r)  # [3, 3, 3]
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = 1
        assert torch.allclose(jac[..., k], lbs.skew(e))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rodrigues_near_pi(dtype):
    axis = torch.tensor([1.0, 2.0, -2.0], dtype=torch.float64) / 3.0
    for angle in (math.pi - 1e-6, math.pi, math.pi + 1e-6):
        r = (axis * angle).to(dtype).requires_grad_(True)
        rot = lbs.rodrigues(r)
        assert _orthonormality_error(rot) < (1e-5 if dtype == torch.float32 else 1e-12)
        # Rotating by ~pi about the axis flips every perpendicular vector.
        assert torch.allclose((rot.double() @ axis), axis, atol=1e-5)
        rot.sum().backward()
        assert torch.isfinite(r.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("angle", [50.0, 1e3, 1e6])
def test_rodrigues_huge_angles_stay_rotations(dtype, angle):
    axis = torch.tensor([0.6, 0.0, 0.8], dtype=dtype)
    r = (axis * angle).requires_grad_(True)
    rot = lbs.rodrigues(r)
    assert torch.isfinite(rot).all()
    assert _orthonormality_error(rot) < (1e-4 if dtype == torch.float32 else 1e-9)
    assert abs(float(torch.linalg.det(rot.detach())) - 1.0) < 1e-4
    rot.sum().backward()
    assert torch.isfinite(r.grad).all()


def test_rotation_to_axis_angle_round_trip_including_pi():
    g = torch.Generator().manual_seed(1)
    axis = torch.randn(300, 3, dtype=torch.float64, generator=g)
    axis = axis / axis.norm(dim=1, keepdim=True)
    angle = torch.rand(300, 1, dtype=torch.float64, generator=g) * math.pi
    angle[:3] = torch.tensor([[0.0], [math.pi], [1e-10]], dtype=torch.float64)
    r = axis * angle
    back = lbs.rotation_to_axis_angle(lbs.rodrigues(r))
    assert torch.allclose(lbs.rodrigues(back), lbs.rodrigues(r), atol=1e-12)


def _naive_rigid_transforms(rot_mats, joints, parents):
    """The reference twin: one joint at a time, as in the SMPL paper."""
    world = []
    for j, p in enumerate(parents):
        t = joints[:, j] - (joints[:, p] if p >= 0 else 0)
        local = lbs.homogeneous(rot_mats[:, j], t)
        world.append(local if p < 0 else world[p] @ local)
    world = torch.stack(world, 1)
    posed = world[..., :3, 3]
    rest = torch.cat([joints, torch.zeros_like(joints[..., :1])], -1)[..., None]  # [B, J, 4, 1]
    skin = world.clone()
    skin[..., :, 3:] = world[..., :, 3:] - world @ rest
    return posed, skin


def test_levelwise_chain_matches_naive_twin():
    g = torch.Generator().manual_seed(2)
    rot = lbs.rodrigues(torch.randn(3, 55, 3, dtype=torch.float64, generator=g))
    joints = torch.randn(3, 55, 3, dtype=torch.float64, generator=g)
    posed, transforms = lbs.rigid_transforms(rot, joints, SMPLX_PARENTS)
    posed_ref, transforms_ref = _naive_rigid_transforms(rot, joints, SMPLX_PARENTS)
    assert torch.allclose(posed, posed_ref, atol=1e-12)
    assert torch.allclose(transforms, transforms_ref, atol=1e-12)
    world_rot = lbs.global_rotations(rot, SMPLX_PARENTS)
    assert torch.allclose(world_rot, lbs.global_transforms(rot, joints, SMPLX_PARENTS)[..., :3, :3])


def test_kinematic_levels_reject_a_parent_after_its_child():
    with pytest.raises(ValueError, match="parent"):
        lbs.kinematic_levels((-1, 2, 0))


def test_landmarks_are_barycentric_points():
    verts = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    faces = torch.tensor([[0, 1, 2]])
    lmk = lbs.vertices_to_landmarks(verts, faces, torch.tensor([0]),
                                    torch.tensor([[0.2, 0.3, 0.5]]))
    assert torch.allclose(lmk, torch.tensor([[[0.3, 0.5, 0.0]]]))
