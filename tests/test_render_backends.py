"""The numba cpu backend renders the reference (torch) picture, forward and backward."""

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from avatar_core.render import rasterize
from avatar_core.render.camera import look_at
from avatar_core.render.scenes import random_scene
from avatar_core.render.types import GaussianSet, RenderRequest

CAM = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=64, height=48, fov_y_deg=40.0)
ALL = ("rgb", "alpha", "depth")


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.double() - b.double()) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()


def render(gs, backend, cam=CAM, **kw):
    return rasterize(gs, cam, RenderRequest(backend=backend, **kw))


def assert_agree(ref, out, *, min_psnr=50.0):
    assert psnr(ref.rgb, out.rgb) >= min_psnr
    assert (ref.alpha - out.alpha).abs().max() <= 1e-4
    # expected depth: compare where the pixel is covered enough for the ratio to be stable
    m = ref.alpha > 1e-2
    assert torch.allclose(ref.depth[m], out.depth[m], rtol=1e-4, atol=1e-4)
    assert torch.equal(ref.depth == 0, out.depth == 0) or (ref.alpha[ref.depth != (
        out.depth)] < 1e-3).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_images_agree_on_random_scenes(seed):
    gs = random_scene(300, seed)
    bg = (0.1, 0.3, 0.9)
    ref = render(gs, "torch", outputs=ALL, background=bg)
    out = render(gs, "cpu", outputs=ALL, background=bg)
    assert ref.stats["n_rendered"] == out.stats["n_rendered"] > 250
    assert out.stats["backend"] == "cpu" and ref.stats["backend"] == "torch"
    assert_agree(ref, out)


@pytest.mark.parametrize("size", [(37, 29), (16, 17), (33, 1), (1, 1)])
def test_images_agree_on_odd_sizes(size):
    gs = random_scene(200, 5, scale=(0.02, 0.3))
    cam = CAM.resized(*size)
    ref = render(gs, "torch", cam, outputs=ALL)
    out = render(gs, "cpu", cam, outputs=ALL)
    assert out.rgb.shape == (size[1], size[0], 3)
    assert_agree(ref, out)


def _grads(gs, backend, weights, cam=CAM, **kw):
    params = [t.detach().clone().requires_grad_() for t in
              (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh)]
    out = rasterize(GaussianSet(*params), cam, RenderRequest(backend=backend, **kw))
    loss = sum((getattr(out, k) * w).sum() for k, w in weights.items() if getattr(out, k)
               is not None)
    loss.backward()
    return [p.grad for p in params]


@pytest.mark.parametrize("seed", [0, 3])
def test_gradients_agree_through_the_pipeline(seed):
    gs = random_scene(250, seed)
    g = torch.Generator().manual_seed(seed)
    ref_alpha = render(gs, "torch", outputs=("alpha",)).alpha
    weights = {"rgb": torch.randn(48, 64, 3, generator=g),
               "alpha": torch.randn(48, 64, generator=g),
               # depth weighted by coverage: where alpha is tiny its ratio is ill-conditioned
               "depth": torch.randn(48, 64, generator=g) * (ref_alpha > 0.05)}
    kw = dict(outputs=ALL, background=(0.5, 0.2, 0.1))
    ref = _grads(gs, "torch", weights, **kw)
    out = _grads(gs, "cpu", weights, **kw)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "sh"), ref, out,
                          strict=True):
        rel = ((a - b).norm() / a.norm()).item()
        assert rel <= 1e-4, (name, rel)


def test_gradients_agree_rgb_only_and_antialiased():
    gs = random_scene(150, 7)
    w = {"rgb": torch.randn(48, 64, 3, generator=torch.Generator().manual_seed(0))}
    ref = _grads(gs, "torch", w, antialiased=True, sh_degree=2)
    out = _grads(gs, "cpu", w, antialiased=True, sh_degree=2)
    for a, b in zip(ref, out, strict=True):
        assert ((a - b).norm() / a.norm()).item() <= 1e-4


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(0, 25), w=st.integers(1, 40), h=st.integers(1, 40),
       seed=st.integers(0, 10_000), degree=st.integers(0, 3), aa=st.booleans(),
       spread=st.floats(0.05, 1.5), big=st.floats(0.01, 0.5))
def test_property_cpu_matches_torch(n, w, h, seed, degree, aa, spread, big):
    gs = random_scene(n, seed, degree, spread=spread, scale=(0.005, big))
    cam = CAM.resized(w, h)
    kw = dict(outputs=ALL, antialiased=aa, background=(0.3, 0.6, 0.9))
    ref = render(gs, "torch", cam, **kw)
    out = render(gs, "cpu", cam, **kw)
    assert (ref.rgb - out.rgb).abs().max() <= 1e-3
    assert psnr(ref.rgb, out.rgb) >= 50
    assert (ref.alpha - out.alpha).abs().max() <= 1e-4
