"""Triangle frames: orthonormal, right-handed, finite (values and grads) when degenerate."""

import pytest
import torch

from avatar_core.gaussians.frames import MIN_SCALE, triangle_frames


def _check_frames(rot, t, k):
    eye = torch.eye(3, dtype=rot.dtype)
    assert torch.isfinite(rot).all() and torch.isfinite(t).all() and torch.isfinite(k).all()
    assert torch.allclose(rot.transpose(-1, -2) @ rot, eye.expand_as(rot), atol=1e-6)
    assert torch.allclose(torch.linalg.det(rot), torch.ones_like(k), atol=1e-6)
    assert (k >= MIN_SCALE).all()


def test_frame_of_a_right_triangle():
    verts = torch.tensor([[0.0, 0, 0], [2, 0, 0], [0, 1, 0]], dtype=torch.float64)
    rot, t, k = triangle_frames(verts, torch.tensor([[0, 1, 2]]))
    assert torch.allclose(rot[0], torch.eye(3, dtype=torch.float64))  # edge x, normal z
    assert torch.allclose(t[0], torch.tensor([2 / 3, 1 / 3, 0], dtype=torch.float64))
    assert k[0].item() == pytest.approx(0.5 * (2.0 + 1.0))


@pytest.mark.parametrize("tri", [
    [[0.0, 0, 0], [0, 0, 0], [0, 0, 0]],        # all coincident
    [[0.0, 0, 0], [0, 0, 0], [1, 2, 3]],        # zero-length first edge
    [[0.0, 0, 0], [1, 1, 1], [2, 2, 2]],        # collinear
    [[1.0, 0, 0], [0, 1, 0], [1, 0, 0]],        # duplicate corner
    [[0.0, 0, 0], [1e-20, 0, 0], [0, 1e-20, 0]],  # vanishing
])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_triangles_give_finite_frames_and_gradients(tri, dtype):
    verts = torch.tensor(tri, dtype=dtype, requires_grad=True)
    rot, t, k = triangle_frames(verts, torch.tensor([[0, 1, 2]]))
    _check_frames(rot, t, k)
    (rot.sum() + t.sum() + k.sum()).backward()
    assert torch.isfinite(verts.grad).all()


def test_batched_random_meshes():
    g = torch.Generator().manual_seed(0)
    verts = torch.randn(4, 50, 3, generator=g)
    faces = torch.randint(0, 50, (80, 3), generator=g)
    rot, t, k = triangle_frames(verts, faces)
    assert rot.shape == (4, 80, 3, 3) and t.shape == (4, 80, 3) and k.shape == (4, 80)
    _check_frames(rot, t, k)
    # The normal column is perpendicular to both edges of non-degenerate faces.
    v = verts[:, faces]  # [4, F, 3, 3]
    e1, e2 = v[:, :, 1] - v[:, :, 0], v[:, :, 2] - v[:, :, 0]
    ok = torch.linalg.norm(torch.cross(e1, e2, dim=-1), dim=-1) > 1e-3
    n = rot[..., 2]
    assert ((n * e1).sum(-1).abs()[ok] < 1e-4).all() and ((n * e2).sum(-1).abs()[ok] < 1e-4).all()
