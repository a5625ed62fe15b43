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


def test_cpu_no_grad_path_matches_the_autograd_path():
    """Without gradients the cpu backend projects and colours in numba too."""
    gs = random_scene(300, 8)
    kw = dict(outputs=ALL, antialiased=True, background=(0.4, 0.4, 0.1), budget=200)
    fast = render(gs, "cpu", **kw)
    params = [t.clone().requires_grad_() for t in
              (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh)]
    slow = render(GaussianSet(*params), "cpu", **kw)
    assert fast.stats["n_rendered"] == slow.stats["n_rendered"] == 200
    assert (fast.rgb - slow.rgb).abs().max() <= 1e-5
    assert (fast.alpha - slow.alpha).abs().max() <= 1e-5
    m = slow.alpha > 1e-2
    assert torch.allclose(fast.depth[m], slow.depth[m], rtol=1e-5)


def test_numba_projection_and_sh_match_torch():
    from avatar_core.render.project_cpu import project_np, sh_rgb_np
    from avatar_core.render.projection import project_gaussians
    from avatar_core.render.sh import sh_to_rgb

    gs = random_scene(500, 9, spread=2.0, scale=(1e-4, 0.5))
    gs.quats[:5] = 0.0  # zero quaternions too
    viewmat, K = CAM.to_torch()
    for aa in (False, True):
        ref = project_gaussians(gs.means, gs.quats, gs.scales, gs.opacities, viewmat, K, 64,
                                48, antialiased=aa)
        m2, co, de, rad, op = project_np(*(t.numpy() for t in (gs.means, gs.quats, gs.scales,
                                                               gs.opacities)),
                                         CAM.viewmat(), CAM.K, 64, 48, antialiased=aa)
        v = ref.valid.numpy()
        assert (rad > 0).sum() == v.sum() > 100
        assert (abs(rad.astype(int) - ref.radii.numpy()) <= 1).all()  # ceil at rounding
        assert torch.allclose(torch.from_numpy(m2), ref.means2d, rtol=1e-5, atol=1e-3)
        assert torch.allclose(torch.from_numpy(de), ref.depths, rtol=1e-6)
        assert torch.allclose(torch.from_numpy(co)[v], ref.conics[v], rtol=1e-4, atol=1e-7)
        assert torch.allclose(torch.from_numpy(op)[v], ref.opacities[v], rtol=1e-4)
    for degree in range(4):
        out = torch.zeros(500, 4)
        sh_rgb_np(degree, gs.sh.numpy(), gs.means.numpy(), CAM.center, rad, out.numpy())
        cp = torch.as_tensor(CAM.center, dtype=torch.float32)
        ref = sh_to_rgb(degree, gs.sh, gs.means - cp)
        v = torch.from_numpy(rad > 0)
        assert torch.allclose(out[v, :3], ref[v], atol=1e-5)
        assert (out[~v] == 0).all()


def test_near_ties_keep_the_reference_order():
    """Issue 20: splats 4.5e-8 m apart in depth (a tie once rounded to float32) composite in
    the reference's order on every path, not by index."""
    far_first = GaussianSet(  # index 0 is the farther one: an index tie-break flips them
        means=torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 4.5e-8]], dtype=torch.float64),
        quats=torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64),
        scales=torch.full((2, 3), 0.2, dtype=torch.float64),
        opacities=torch.tensor([0.99, 0.99], dtype=torch.float64),
        sh=torch.tensor([[[2.0, -2.0, -2.0]], [[-2.0, -2.0, 2.0]]], dtype=torch.float64))
    assert float(torch.tensor(2.5 - 4.5e-8, dtype=torch.float32)) == 2.5  # a float32 tie
    ref = render(far_first, "torch", outputs=ALL)
    assert ref.rgb[24, 32, 2] > ref.rgb[24, 32, 0]  # the nearer (blue) one in front
    params = [t.clone().requires_grad_() for t in (far_first.means, far_first.quats,
                                                   far_first.scales, far_first.opacities,
                                                   far_first.sh)]
    for gs in (far_first, GaussianSet(*params)):  # numba projection, then autograd path
        out = render(gs, "cpu", outputs=ALL)
        assert (ref.rgb - out.rgb).abs().max() <= 1e-5
        assert psnr(ref.rgb.detach(), out.rgb.detach()) >= 100


@pytest.mark.parametrize(("dtype", "seed"), [(torch.float32, 0), (torch.float64, 1)])
def test_cpu_matches_torch_to_100_db_on_20k_scenes(dtype, seed):
    """Issue 20's bar: the backends agree to rounding on the random 20k-Gaussian scenes."""
    gs = random_scene(20_000, seed, dtype=dtype)
    cam = CAM.resized(256, 256)
    kw = dict(outputs=("rgb", "alpha"), background=(0.2, 0.3, 0.4))
    ref, out = render(gs, "torch", cam, **kw), render(gs, "cpu", cam, **kw)
    assert ref.stats["n_rendered"] == out.stats["n_rendered"] > 15_000
    assert psnr(ref.rgb, out.rgb) >= 100
    assert psnr(ref.alpha, out.alpha) >= 100
