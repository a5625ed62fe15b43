"""Gradients against finite differences: the float64 reference pipeline, and the cpu kernels."""

import torch

from avatar_core.render import rasterize
from avatar_core.render.camera import look_at
from avatar_core.render.scenes import random_scene
from avatar_core.render.types import GaussianSet, RenderRequest

CAM = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=14, height=11, fov_y_deg=10.0)
ALL = ("rgb", "alpha", "depth")


def _scene(dtype):
    # a few overlapping, moderately opaque Gaussians, each covering the whole image with
    # alpha well above 1/255 and T well above 1e-4: no threshold is near, the picture is smooth
    gs = random_scene(4, 11, sh_degree=1, spread=0.04, scale=(0.3, 0.5), dtype=dtype)
    gs.opacities = 0.2 + 0.5 * gs.opacities
    return gs


def _loss_fn(backend, weights, dtype):
    def loss(means, quats, scales, opacities, sh):
        out = rasterize(GaussianSet(means, quats, scales, opacities, sh), CAM,
                        RenderRequest(backend=backend, outputs=ALL, background=(0.2, 0.4, 0.6),
                                      antialiased=True))
        return sum((getattr(out, k).to(dtype) * w).sum() for k, w in weights.items())
    return loss


def _weights(dtype):
    g = torch.Generator().manual_seed(0)
    return {"rgb": torch.randn(11, 14, 3, generator=g, dtype=dtype),
            "alpha": torch.randn(11, 14, generator=g, dtype=dtype),
            "depth": 0.1 * torch.randn(11, 14, generator=g, dtype=dtype)}


def test_reference_pipeline_gradcheck():
    gs = _scene(torch.float64)
    inputs = tuple(t.clone().requires_grad_() for t in
                   (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh))
    loss = _loss_fn("torch", _weights(torch.float64), torch.float64)
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_cpu_backend_against_finite_differences():
    """The float32 kernels: central differences in float64 parameters (the kernels round to
    float32, so the step is larger and the tolerance looser than for the reference)."""
    gs = _scene(torch.float64)
    params = [t.clone().requires_grad_() for t in
              (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh)]
    loss = _loss_fn("cpu", _weights(torch.float64), torch.float64)
    loss(*params).backward()
    eps = 1e-3
    checked = 0
    for k, p in enumerate(params):
        flat = p.detach().reshape(-1)
        grad = p.grad.reshape(-1)
        for i in torch.argsort(grad.abs(), descending=True)[:6].tolist():  # the largest ones
            vals = [t.detach().clone() for t in params]
            vals[k].view(-1)[i] = flat[i] + eps
            up = loss(*vals).item()
            vals[k].view(-1)[i] = flat[i] - eps
            down = loss(*vals).item()
            fd = (up - down) / (2 * eps)
            assert abs(fd - grad[i].item()) <= 2e-2 * abs(grad[i].item()) + 1e-3, (k, i, fd,
                                                                                   grad[i])
            checked += 1
    assert checked == 6 + 6 + 6 + 4 + 6
