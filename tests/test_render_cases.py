"""Hard inputs, requested effects and the entry point's contract, on both CPU backends."""

import math

import pytest
import torch

from avatar_core.render import rasterize
from avatar_core.render.camera import look_at
from avatar_core.render.projection import project_gaussians
from avatar_core.render.rasterize import resolve_backend
from avatar_core.render.scenes import random_scene
from avatar_core.render.types import GaussianSet, RenderRequest

CAM = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=40, height=30, fov_y_deg=40.0)
ALL = ("rgb", "alpha", "depth")
BACKENDS = ["torch", "cpu"]


def render(gs, backend, cam=CAM, **kw):
    return rasterize(gs, cam, RenderRequest(backend=backend, **kw))


def hard_scene() -> GaussianSet:
    """Each row a hard case (camera at z = 2.5 looking toward -z)."""
    rows = [  # mean, quat, scale, opacity
        ((0.0, 0.0, 0.0), (1, 0, 0, 0), 0.1, 0.7),        # ordinary
        ((0.0, 0.0, 3.0), (1, 0, 0, 0), 0.1, 0.9),        # behind the camera
        ((0.0, 0.0, 2.5), (1, 0, 0, 0), 0.1, 0.9),        # on the camera centre
        ((0.0, 0.0, 2.495), (1, 0, 0, 0), 0.5, 0.9),      # nearer than the near plane
        ((0.05, 0.0, 2.4), (1, 0, 0, 0), 0.3, 0.5),       # straddles the near plane
        ((0.0, 0.0, -1e6), (1, 0, 0, 0), 10.0, 0.9),      # very far away
        ((0.0, 0.0, -1e11), (1, 0, 0, 0), 10.0, 0.9),     # beyond the far plane
        ((0.1, 0.1, 0.0), (1, 0, 0, 0), 1e-8, 0.9),       # tiny
        ((0.0, 0.0, -5.0), (1, 0, 0, 0), 1e3, 0.2),       # huge
        ((-0.2, 0.1, 0.2), (0, 0, 0, 0), 0.08, 0.8),      # zero quaternion
        ((0.2, -0.1, 0.1), (0.3, 0.1, -0.5, 0.8), 0.08, 0.0),  # opacity 0
        ((0.1, -0.2, 0.3), (0.6, 0.3, 0.2, 0.1), 0.05, 1.0),   # opacity 1
    ]
    g = torch.Generator().manual_seed(0)
    n = len(rows)
    return GaussianSet(
        means=torch.tensor([r[0] for r in rows], dtype=torch.float32),
        quats=torch.tensor([r[1] for r in rows], dtype=torch.float32),
        scales=torch.tensor([[r[2]] * 3 for r in rows], dtype=torch.float32)
        * torch.tensor([1.0, 0.7, 0.4]),
        opacities=torch.tensor([r[3] for r in rows], dtype=torch.float32),
        sh=torch.randn(n, 16, 3, generator=g) * 0.4,
    )


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("aa", [False, True])
def test_hard_cases_stay_finite(backend, aa):
    gs = hard_scene()
    params = [t.clone().requires_grad_() for t in
              (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh)]
    out = render(GaussianSet(*params), backend, outputs=ALL, antialiased=aa)
    for t in (out.rgb, out.alpha, out.depth):
        assert torch.isfinite(t).all()
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    for p in params:
        assert torch.isfinite(p.grad).all()
    # behind / on the camera / too near / too far are culled
    assert out.stats["n_visible"] == 12 - 4
    assert params[0].grad[[1, 2, 3, 6]].abs().sum() == 0


def test_hard_cases_agree_between_backends():
    gs = hard_scene()
    ref, out = (render(gs, b, outputs=ALL, background=(0.2, 0.2, 0.2)) for b in BACKENDS)
    assert (ref.rgb - out.rgb).abs().max() < 1e-4
    assert (ref.alpha - out.alpha).abs().max() < 1e-4


@pytest.mark.parametrize("backend", BACKENDS)
def test_nan_input_raises(backend):
    gs = random_scene(5, 0)
    gs.scales[2, 1] = float("nan")
    with pytest.raises(ValueError, match="scales.*NaN or Inf"):
        render(gs, backend)
    gs = random_scene(5, 0)
    gs.sh[0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="sh"):
        render(gs, backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_and_one_gaussian(backend):
    empty = random_scene(0, 0)
    out = render(empty, backend, outputs=ALL, background=(0.1, 0.2, 0.3))
    assert torch.equal(out.rgb, torch.tensor([0.1, 0.2, 0.3]).expand(30, 40, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    assert out.stats["n_rendered"] == 0
    one = GaussianSet(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]),
                      torch.full((1, 3), 0.1), torch.tensor([0.9]), torch.zeros(1, 1, 3))
    out = render(one, backend, outputs=ALL, width=41, height=31)  # a pixel centre on the mean
    assert out.alpha.max() == out.alpha[15, 20] == pytest.approx(0.9, abs=1e-6)
    assert torch.allclose(out.rgb, 0.5 * out.alpha[..., None])  # grey: SH DC 0 -> 0.5
    hit = out.alpha > 0
    assert torch.allclose(out.depth[hit], torch.tensor(2.5))


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_pixel_image(backend):
    gs = random_scene(50, 1)
    out = render(gs, backend, outputs=ALL, width=1, height=1)
    assert out.rgb.shape == (1, 1, 3) and out.alpha.shape == (1, 1)
    ref = render(gs, "torch", CAM.resized(1, 1), outputs=ALL)
    assert torch.allclose(out.rgb, ref.rgb, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_requested_subsets_equal_the_full_render(backend):
    gs = random_scene(120, 2)
    full = render(gs, backend, outputs=ALL, background=(0.3, 0.1, 0.7))
    for outs in [("rgb",), ("alpha",), ("depth",), ("rgb", "alpha"), ("alpha", "depth")]:
        sub = render(gs, backend, outputs=outs, background=(0.3, 0.1, 0.7))
        for name in ALL:
            if name in outs:
                assert torch.equal(getattr(sub, name), getattr(full, name)), (outs, name)
            else:
                assert getattr(sub, name) is None


@pytest.mark.parametrize("backend", BACKENDS)
def test_budget(backend):
    gs = random_scene(100, 3)
    full = render(gs, backend, outputs=ALL)
    n_vis = full.stats["n_visible"]
    for b in (n_vis, 10**6, 1.0):
        out = render(gs, backend, outputs=ALL, budget=b)
        assert out.stats["n_rendered"] == n_vis
        assert torch.equal(out.rgb, full.rgb) and torch.equal(out.depth, full.depth)
    assert render(gs, backend, budget=17).stats["n_rendered"] == 17
    assert render(gs, backend, budget=0.25).stats["n_rendered"] == math.ceil(0.25 * n_vis)
    assert render(gs, backend, budget=0, outputs=("alpha",)).alpha.max() == 0


def test_budget_keeps_the_most_important():
    # a big opaque Gaussian and a faint small one: budget 1 keeps the big one
    gs = GaussianSet(torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.1, 0.5]]),
                     torch.tensor([[1.0, 0, 0, 0]] * 2), torch.tensor([[0.2] * 3, [0.02] * 3]),
                     torch.tensor([0.9, 0.3]), torch.zeros(2, 1, 3))
    big = GaussianSet(*(t[:1] for t in (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh)))
    out = render(gs, "cpu", budget=1, outputs=ALL)
    assert torch.equal(out.rgb, render(big, "cpu", outputs=ALL).rgb)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sh_degree_zero_is_the_dc_term(backend):
    gs = random_scene(100, 4, sh_degree=3)
    dc = GaussianSet(gs.means, gs.quats, gs.scales, gs.opacities, gs.sh[:, :1])
    a = render(gs, backend, sh_degree=0).rgb
    assert torch.equal(a, render(dc, backend).rgb)
    assert not torch.equal(a, render(gs, backend).rgb)
    d1 = GaussianSet(gs.means, gs.quats, gs.scales, gs.opacities, gs.sh[:, :4])
    assert torch.equal(render(gs, backend, sh_degree=1).rgb, render(d1, backend).rgb)


@pytest.mark.parametrize("backend", BACKENDS)
def test_background(backend):
    gs = random_scene(30, 5, spread=0.2, scale=(0.01, 0.03))
    bg = torch.tensor([0.2, 0.5, 0.8])
    black = render(gs, backend, outputs=("rgb", "alpha"))
    out = render(gs, backend, outputs=("rgb", "alpha"), background=tuple(bg.tolist()))
    empty = out.alpha == 0
    assert empty.any() and (~empty).any()
    assert torch.equal(out.rgb[empty], bg.expand(int(empty.sum()), 3))
    assert torch.allclose(out.rgb, black.rgb + (1 - out.alpha)[..., None] * bg, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_antialiased_scales_opacity(backend):
    gs = random_scene(60, 6, scale=(0.002, 0.01))
    viewmat, K = CAM.to_torch()
    p0 = project_gaussians(gs.means, gs.quats, gs.scales, gs.opacities, viewmat, K, 40, 30)
    p1 = project_gaussians(gs.means, gs.quats, gs.scales, gs.opacities, viewmat, K, 40, 30,
                           antialiased=True)
    comp = p1.opacities / p0.opacities
    assert (comp[p0.valid] < 1).all()
    pre = GaussianSet(gs.means, gs.quats, gs.scales, p1.opacities, gs.sh)
    aa = render(gs, backend, outputs=ALL, antialiased=True)
    assert torch.allclose(aa.rgb, render(pre, backend, outputs=ALL).rgb, atol=1e-6)
    assert aa.alpha.sum() < render(gs, backend, outputs=ALL).alpha.sum()


def test_resolution_and_stats():
    gs = random_scene(80, 7)
    out = render(gs, "cpu", outputs=ALL, width=23, height=19)
    assert out.rgb.shape == (19, 23, 3) and out.depth.shape == (19, 23)
    same = render(gs, "cpu", CAM.resized(23, 19), outputs=ALL)
    assert torch.equal(out.rgb, same.rgb)
    for key in ("backend", "n_rendered", "n_visible", "project_ms", "color_ms", "raster_ms",
                "total_ms"):
        assert key in out.stats
    assert out.rgb.dtype == torch.float32


def test_auto_backend_and_bad_requests():
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"
    assert render(random_scene(3, 0), "auto").stats["backend"] == "cpu"
    gs = random_scene(3, 0)
    for bad in (dict(outputs=()), dict(outputs=("normals",)), dict(backend="vulkan"),
                dict(budget=-1), dict(budget=1.5), dict(budget=True), dict(sh_degree=4)):
        kw = {"backend": "cpu", **bad}
        with pytest.raises(ValueError):
            rasterize(gs, CAM, RenderRequest(**kw))
    with pytest.raises(ValueError, match="sh"):
        rasterize(GaussianSet(gs.means, gs.quats, gs.scales, gs.opacities,
                              torch.zeros(3, 5, 3)), CAM)


def test_sh_degree_above_the_available_is_clamped():
    gs = random_scene(40, 8, sh_degree=1)
    assert torch.equal(render(gs, "cpu", sh_degree=3).rgb, render(gs, "cpu").rgb)


def test_torch_reference_chunking_does_not_change_the_picture(monkeypatch):
    import avatar_core.render.rasterize_torch as rt

    gs = random_scene(150, 9)
    params = [t.clone().requires_grad_() for t in
              (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh)]
    one = render(GaussianSet(*params), "torch", outputs=ALL)
    (one.rgb.sum() + one.depth.sum()).backward()
    g_one = [p.grad.clone() for p in params]
    monkeypatch.setattr(rt, "_CHUNK_ELEMS", 256 * 16)  # about one tile per chunk
    for p in params:
        p.grad = None
    many = render(GaussianSet(*params), "torch", outputs=ALL)
    (many.rgb.sum() + many.depth.sum()).backward()
    for name in ALL:
        assert torch.allclose(getattr(one, name), getattr(many, name), atol=1e-6)
    for a, p in zip(g_one, params, strict=True):
        assert torch.allclose(a, p.grad, rtol=1e-4, atol=1e-6)
