"""The gsplat adapter: argument mapping everywhere; rendering only with gsplat and CUDA."""

import pytest
import torch

from avatar_core.render import rasterize
from avatar_core.render.camera import look_at
from avatar_core.render.rasterize import available_backends, resolve_backend
from avatar_core.render.rasterize_gsplat import available, gsplat_arguments
from avatar_core.render.scenes import random_scene
from avatar_core.render.types import RenderRequest

CAM = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=64, height=48, fov_y_deg=40.0)
ALL = ("rgb", "alpha", "depth")


def test_argument_mapping():
    gs = random_scene(10, 0, sh_degree=3)
    kw = gsplat_arguments(gs, CAM, RenderRequest(outputs=ALL, antialiased=True,
                                                 background=(0.1, 0.2, 0.3)), sh_degree=1)
    assert kw["near_plane"] == 0.01 and kw["far_plane"] == 1e10
    assert kw["eps2d"] == 0.3 and kw["tile_size"] == 16
    assert kw["render_mode"] == "RGB+ED" and kw["rasterize_mode"] == "antialiased"
    assert kw["sh_degree"] == 1 and kw["colors"].shape == (10, 4, 3)
    assert kw["viewmats"].shape == (1, 4, 4) and kw["Ks"].shape == (1, 3, 3)
    assert torch.allclose(kw["backgrounds"], torch.tensor([[0.1, 0.2, 0.3]]))
    assert (kw["width"], kw["height"]) == (64, 48)
    assert gsplat_arguments(gs, CAM, RenderRequest(), 3)["render_mode"] == "RGB"
    assert gsplat_arguments(gs, CAM, RenderRequest(outputs=("alpha",)), 3)["render_mode"] == "ED"
    assert gsplat_arguments(gs, CAM, RenderRequest(), 3)["rasterize_mode"] == "classic"


def test_auto_never_picks_gsplat_for_cpu_tensors():
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"
    assert ("gsplat" in available_backends()) == available()


needs_gsplat = pytest.mark.skipif(not available(), reason="gsplat and CUDA not available")


@needs_gsplat
def test_gsplat_matches_the_reference():  # pragma: no cover (needs CUDA)
    gs = random_scene(300, 0)
    cuda = type(gs)(*(t.cuda() for t in (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh)))
    req = dict(outputs=ALL, background=(0.1, 0.3, 0.9))
    out = rasterize(cuda, CAM, RenderRequest(backend="auto", **req))
    ref = rasterize(gs, CAM, RenderRequest(backend="torch", **req))
    assert out.stats["backend"] == "gsplat"
    mse = ((out.rgb.cpu() - ref.rgb) ** 2).mean()
    assert -10 * torch.log10(mse) >= 35  # gsplat clamps alpha at 0.999, not 0.99
    assert (out.alpha.cpu() - ref.alpha).abs().mean() < 1e-2


def test_budget_subset_uses_the_shared_rule():
    from avatar_core.render.rasterize_gsplat import _apply_budget

    gs = random_scene(60, 2)
    sub, n = _apply_budget(gs, CAM, RenderRequest(budget=7))
    assert n == 7 and sub.means.shape == (7, 3) and sub.sh.shape == (7, 16, 3)
    # the same Gaussians the cpu backend renders under that budget
    ref = rasterize(gs, CAM, RenderRequest(backend="cpu", budget=7, outputs=ALL))
    out = rasterize(sub, CAM, RenderRequest(backend="cpu", outputs=ALL))
    assert torch.allclose(ref.rgb, out.rgb, atol=1e-6)


def test_gsplat_only_gets_sane_gaussians():
    """What reaches gsplat's float32 kernels: our projection's survivors, unit quaternions
    (zero -> identity), SH clamped (issue 13: absurd but finite avatars)."""
    from avatar_core.render.contract import SH_COEFF_MAX
    from avatar_core.render.rasterize_gsplat import _apply_budget

    gs = random_scene(6, 4)
    gs.scales[0] = 5.5e34        # log-scale 80: a veil, culled
    gs.means[1] = torch.tensor([1e30, 0.0, 0.0])
    gs.quats[2] = torch.tensor([3e38, 3e38, 0.0, 0.0])
    gs.quats[3] = 0.0
    gs.sh[4] = 1e30
    sub, n = _apply_budget(gs, CAM, RenderRequest())  # no budget: still filtered
    assert n == sub.means.shape[0] == 4 and torch.isfinite(sub.scales).all()
    kw = gsplat_arguments(sub, CAM, RenderRequest(), 3)
    norms = kw["quats"].norm(dim=-1)
    assert torch.allclose(norms, torch.ones_like(norms))
    assert torch.equal(kw["quats"][1], torch.tensor([1.0, 0.0, 0.0, 0.0]))  # the zero one
    assert kw["colors"].abs().max() == SH_COEFF_MAX
