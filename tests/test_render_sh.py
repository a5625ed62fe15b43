"""Spherical harmonics: orthonormal bases, 3DGS conventions, gradients."""

import math

import pytest
import torch

from avatar_core.render.sh import (
    SH_C0,
    _sh_bases,
    eval_sh,
    rgb_to_sh0,
    sh0_to_rgb,
    sh_to_rgb,
)


def _fibonacci_sphere(n: int) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt(1.0 - z * z)
    phi = math.pi * (1.0 + math.sqrt(5.0)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def test_bases_are_orthonormal():
    dirs = _fibonacci_sphere(20000)
    Y = torch.stack(_sh_bases(3, dirs), dim=-1)  # [n, 16]
    gram = Y.T @ Y * (4.0 * math.pi / dirs.shape[0])
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=2e-3)


def test_known_values():
    # 3DGS: degree 1 is (-C1 y, C1 z, -C1 x)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    coeffs = torch.zeros(1, 4, 3, dtype=torch.float64)
    coeffs[0, 2] = 1.0
    assert torch.allclose(eval_sh(1, coeffs, d), torch.full((1, 3), 0.4886025119029199,
                                                            dtype=torch.float64))
    coeffs[0, 2] = 0.0
    coeffs[0, 1] = 1.0
    d = torch.tensor([[0.0, 2.0, 0.0]], dtype=torch.float64)  # normalised inside
    assert torch.allclose(eval_sh(1, coeffs, d), torch.full((1, 3), -0.4886025119029199,
                                                            dtype=torch.float64))


def test_degree_truncates_and_dc_roundtrip():
    g = torch.Generator().manual_seed(0)
    coeffs = torch.randn(50, 16, 3, generator=g)
    dirs = torch.randn(50, 3, generator=g)
    assert torch.allclose(eval_sh(0, coeffs, dirs), SH_C0 * coeffs[:, 0])
    assert torch.allclose(eval_sh(2, coeffs, dirs), eval_sh(2, coeffs[:, :9], dirs))
    rgb = torch.rand(10, 3, generator=g)
    assert torch.allclose(sh0_to_rgb(rgb_to_sh0(rgb)), rgb, atol=1e-6)
    assert torch.all(sh_to_rgb(3, coeffs, dirs) >= 0)


def test_bad_degree_and_shape():
    with pytest.raises(ValueError):
        eval_sh(4, torch.zeros(1, 25, 3), torch.ones(1, 3))
    with pytest.raises(ValueError):
        eval_sh(2, torch.zeros(1, 4, 3), torch.ones(1, 3))


def test_gradcheck():
    g = torch.Generator().manual_seed(1)
    coeffs = torch.randn(4, 16, 3, generator=g, dtype=torch.float64, requires_grad=True)
    dirs = torch.randn(4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, d: eval_sh(3, c, d), (coeffs, dirs))
