"""Placing seats' Gaussians in a shared scene (avatar_core.gaussians.placement): rigid moves
that transform each Gaussian's covariance as R Σ Rᵀ, and the union of seats."""

import math

import numpy as np
import pytest
import torch

from avatar_core.body.lbs import rodrigues
from avatar_core.gaussians.placement import place, placed_point, seat_transform, union
from avatar_core.render import RenderRequest, rasterize
from avatar_core.render.camera import look_at
from avatar_core.render.scenes import random_scene
from avatar_core.render.sh import sh_to_rgb
from avatar_core.render.types import GaussianSet
from avatar_core.rotations import quaternion_to_matrix

AXIS_ANGLE = (0.3, -1.1, 0.7)
SHIFT = (0.5, -0.2, 2.0)


def _covariances(g: GaussianSet) -> torch.Tensor:
    """[N, 3, 3] R_q diag(s²) R_qᵀ."""
    r = quaternion_to_matrix(g.quats)  # [N, 3, 3]
    return r @ torch.diag_embed(g.scales ** 2) @ r.transpose(-1, -2)


def _distances(means: torch.Tensor) -> torch.Tensor:
    return (means[:, None] - means[None]).norm(dim=-1)  # [N, N]


def _scene(n: int, seed: int, sh_degree: int = 3) -> GaussianSet:
    return random_scene(n, seed, sh_degree, dtype=torch.float64)


def _empty(sh_degree: int = 0) -> GaussianSet:
    z = torch.zeros
    k = (sh_degree + 1) ** 2
    return GaussianSet(z(0, 3, dtype=torch.float64), z(0, 4, dtype=torch.float64),
                       z(0, 3, dtype=torch.float64), z(0, dtype=torch.float64),
                       z(0, k, 3, dtype=torch.float64))


def test_placing_rotates_means_and_covariances():
    g = _scene(50, 0)  # quaternions of any norm
    R, t = seat_transform(AXIS_ANGLE, SHIFT, torch.float64, "cpu")
    placed = place(g, R, t)
    assert torch.allclose(placed.means, g.means @ R.T + t, atol=1e-12)
    assert torch.allclose(_covariances(placed), R @ _covariances(g) @ R.T, atol=1e-12)
    for name in ("scales", "opacities", "sh"):
        assert getattr(placed, name) is getattr(g, name)  # a rigid move keeps them
    # rigid: every distance between two means is kept
    assert torch.allclose(_distances(placed.means), _distances(g.means), atol=1e-12)


def test_seat_transform_is_rodrigues_and_the_identity_is_none():
    R, t = seat_transform((0.0, 0.0, math.pi / 2), (1.0, 2.0, 3.0), torch.float32, "cpu")
    assert R.dtype == torch.float32 and t.dtype == torch.float32
    assert torch.allclose(R @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]),
                          atol=1e-6)  # a quarter turn about z takes x to y
    assert torch.equal(R, rodrigues(torch.tensor([0.0, 0.0, math.pi / 2])))
    assert seat_transform((0, 0, 0), (0, 0, 0), torch.float32, "cpu") == (None, None)
    R, t = seat_transform(np.zeros(3), SHIFT, torch.float64, "cpu")
    assert R is None and t.tolist() == list(SHIFT)


def test_identity_placement_returns_the_same_set():
    g = _scene(10, 1)
    assert place(g, None, None) is g
    same = place(g, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    assert torch.equal(same.means, g.means) and torch.equal(same.quats, g.quats)


def test_placed_point_is_where_place_puts_a_mean():
    R, t = seat_transform(AXIS_ANGLE, SHIFT, torch.float64, "cpu")
    g = _scene(1, 2)
    point = g.means[0].numpy()
    assert np.allclose(placed_point(point, R, t), place(g, R, t).means[0].numpy(), atol=1e-12)
    assert np.allclose(placed_point(point, R, np.asarray(SHIFT)),
                       placed_point(point, R, t), atol=1e-12)
    assert placed_point(point, None, None).tolist() == point.tolist()


def test_union_keeps_order_and_pads_sh_with_zeros():
    low, high = _scene(4, 3, sh_degree=0), _scene(6, 4, sh_degree=2)
    both = union([low, high])
    assert both.num == 10 and both.sh_degree == 2
    assert torch.equal(both.means[:4], low.means) and torch.equal(both.means[4:], high.means)
    assert torch.equal(both.opacities, torch.cat([low.opacities, high.opacities]))
    assert torch.equal(both.sh[:4, :1], low.sh) and (both.sh[:4, 1:] == 0).all()
    assert torch.equal(both.sh[4:], high.sh)
    dirs = torch.randn(4, 3, dtype=torch.float64)
    assert torch.equal(sh_to_rgb(2, both.sh[:4], dirs), sh_to_rgb(0, low.sh, dirs))  # same colour


def test_union_of_one_is_that_set_and_of_none_raises():
    g = _scene(3, 0)
    assert union([g]) is g
    with pytest.raises(ValueError, match="at least one set"):
        union([])


def test_empty_sets_place_and_join():
    R, t = seat_transform(AXIS_ANGLE, SHIFT, torch.float64, "cpu")
    placed = place(_empty(), R, t)
    assert placed.means.shape == (0, 3) and placed.quats.shape == (0, 4)
    g = _scene(5, 1, sh_degree=1)
    joined = union([_empty(0), g, _empty(3)])
    assert joined.num == 5 and joined.sh_degree == 3
    assert torch.equal(joined.means, g.means)
    assert union([_empty(), _empty()]).num == 0


@pytest.mark.parametrize("rotation, translation, match", [
    ((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0), "rotation must be finite"),
    ((0.0, 0.0, 0.0), (0.0, math.inf, 0.0), "translation must be finite"),
    ((0.0, 1.0), (0.0, 0.0, 0.0), "rotation must be 3 numbers"),
])
def test_a_non_finite_or_malformed_placement_is_rejected(rotation, translation, match):
    with pytest.raises(ValueError, match=match):
        seat_transform(rotation, translation, torch.float32, "cpu")


def test_nan_in_a_rotation_given_to_place_reaches_the_renderer_as_an_error():
    """place does no check of its own (per frame, no GPU read-back): NaN spreads to every
    mean, and the renderer refuses it."""
    g = _scene(8, 0)
    R = torch.full((3, 3), math.nan, dtype=torch.float64)
    placed = place(g, R, None)
    assert placed.means.isnan().all()
    cam = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=16, height=16, fov_y_deg=40.0)
    with pytest.raises(ValueError, match="NaN or Inf"):
        rasterize(placed, cam, RenderRequest(backend="cpu"))
