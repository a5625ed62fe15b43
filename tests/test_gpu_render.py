"""render_views (several cameras, one call) and the batched gsplat mapping; the gsplat-vs-cpu
checks of the shared scenes run only on CUDA (marked ``gpu``)."""

import dataclasses
import math

import pytest
import torch

from avatar_core.render import render_views
from avatar_core.render.camera import look_at, orbit
from avatar_core.render.rasterize import rasterize
from avatar_core.render.rasterize_gsplat import gsplat_arguments, gsplat_views_arguments
from avatar_core.render.scenes import avatar_camera, avatar_like_scene, random_scene
from avatar_core.render.types import GaussianSet, RenderRequest

ALL = ("rgb", "alpha", "depth")


def _cams(n: int, width: int = 40, height: int = 32):
    return [orbit((0.0, 0.0, 0.0), yaw, 10.0, 2.5, width=width, height=height, fov_y_deg=40.0)
            for yaw in torch.linspace(-60, 60, n).tolist()]


@pytest.mark.parametrize("backend", ["cpu", "torch"])
@pytest.mark.parametrize("request_kw", [
    dict(outputs=ALL, background=(0.2, 0.1, 0.0)),
    dict(outputs=("rgb",), budget=0.5, sh_degree=1),
    dict(outputs=("alpha", "depth"), width=24, height=20, antialiased=True),
])
def test_views_equal_one_by_one(backend, request_kw):
    gs = random_scene(80, 3)
    req = RenderRequest(backend=backend, **request_kw)
    cams = _cams(3)
    outs = render_views(gs, cams, req)
    assert len(outs) == 3
    for cam, out in zip(cams, outs, strict=True):
        ref = rasterize(gs, cam, req)
        for name in ALL:
            a, b = getattr(out, name), getattr(ref, name)
            assert (a is None) == (b is None)
            if a is not None:
                assert torch.equal(a, b), name


def test_views_need_a_camera():
    with pytest.raises(ValueError, match="at least one camera"):
        render_views(random_scene(4, 0), [], RenderRequest())


def test_views_reject_what_rasterize_rejects():
    gs = random_scene(4, 0)
    gs.means[0, 0] = float("nan")
    with pytest.raises(ValueError):
        render_views(gs, _cams(2), RenderRequest(backend="cpu"))


@pytest.fixture
def gsplat_batches(monkeypatch):
    """The batched gsplat path up to its kernel, on the CPU: ``render_views`` sees "gsplat" and
    each batch (Gaussians, cameras, request, sh degree) is recorded instead of rendered."""
    import avatar_core.render.rasterize_gsplat as rg
    import avatar_core.render.views as views

    batches = []

    def record(gaussians, cameras, request, sh_degree, t_start):
        batches.append((gaussians, list(cameras), request, sh_degree))
        return [f"picture of {cam.size}" for cam in cameras]

    monkeypatch.setattr(views, "resolve_backend", lambda name, device: "gsplat")
    monkeypatch.setattr(rg, "rasterize_gsplat_views", record)
    return batches


@pytest.mark.parametrize("bad", [
    dict(request=RenderRequest(outputs=("normals",)), match="outputs"),
    dict(request=RenderRequest(budget=1.5), match="budget fraction"),
    dict(request=RenderRequest(sh_degree=4), match="sh_degree"),
    dict(nan=True, match="NaN or Inf"),
    dict(drop_sh=True, match="gaussians.sh"),
])
def test_batched_views_reject_what_rasterize_rejects(gsplat_batches, bad):
    """The batched path and the one-camera path share their checks: the same message."""
    gs = random_scene(6, 0)
    if bad.get("nan"):
        gs.opacities[2] = float("nan")
    if bad.get("drop_sh"):
        gs = GaussianSet(gs.means, gs.quats, gs.scales, gs.opacities, gs.sh[:, :2])
    req = bad.get("request", RenderRequest())
    with pytest.raises(ValueError, match=bad["match"]):
        rasterize(gs, _cams(1)[0], dataclasses.replace(req, backend="cpu"))
    with pytest.raises(ValueError, match=bad["match"]):
        render_views(gs, _cams(2), req)
    assert gsplat_batches == []


def test_batched_views_prepare_as_rasterize_does(gsplat_batches):
    """One batch per image size, in camera order; opacities clamped to [0, 1], cameras resized
    to the request, the SH degree capped by what the Gaussians carry."""
    gs = random_scene(8, 1)  # SH degree 3
    gs.opacities[0], gs.opacities[1] = 7.0, -2.0
    wide, narrow = _cams(2, width=40), _cams(1, width=24)
    outs = render_views(gs, [wide[0], narrow[0], wide[1]], RenderRequest(sh_degree=2))
    assert outs == ["picture of (40, 32)", "picture of (24, 32)", "picture of (40, 32)"]
    assert [[c.size for c in cams] for _, cams, _, _ in gsplat_batches] == [
        [(40, 32), (40, 32)], [(24, 32)]]
    clamped = gsplat_batches[0][0].opacities
    assert clamped[0] == 1.0 and clamped[1] == 0.0 and torch.equal(clamped[2:], gs.opacities[2:])
    assert gsplat_batches[0][3] == 2

    gsplat_batches.clear()
    render_views(random_scene(8, 1, sh_degree=1), _cams(2),
                 RenderRequest(width=20, height=16, sh_degree=3))
    assert [c.size for c in gsplat_batches[0][1]] == [(20, 16), (20, 16)]
    assert gsplat_batches[0][3] == 1


def test_batched_gsplat_arguments_mask_each_camera():
    """One entry per camera over the union of kept Gaussians; a Gaussian culled in camera c
    (behind it) has opacity 0 in entry c only."""
    gs = random_scene(30, 1)
    front = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=40, height=32, fov_y_deg=40.0)
    back = look_at((0.0, 0.0, -2.5), (0.0, 0.0, 0.0), width=40, height=32, fov_y_deg=40.0)
    gs.means[1] = torch.tensor([0.0, 0.0, 2.6])  # behind the front camera: only back sees it
    req = RenderRequest(outputs=ALL, background=(0.1, 0.2, 0.3), antialiased=True)
    kw, counts = gsplat_views_arguments(gs, [front, back], req, sh_degree=2)
    M = kw["means"].shape[1]
    assert kw["means"].shape == (2, M, 3) and kw["quats"].shape == (2, M, 4)
    assert kw["scales"].shape == (2, M, 3) and kw["opacities"].shape == (2, M)
    assert kw["colors"].shape == (2, M, 9, 3) and kw["sh_degree"] == 2
    assert kw["viewmats"].shape == (2, 1, 4, 4) and kw["Ks"].shape == (2, 1, 3, 3)
    assert kw["backgrounds"].shape == (2, 1, 3)
    assert (kw["near_plane"], kw["eps2d"], kw["tile_size"]) == (0.01, 0.3, 16)
    assert kw["render_mode"] == "RGB+ED" and kw["rasterize_mode"] == "antialiased"
    assert torch.equal((kw["opacities"] > 0).sum(1), counts)
    from avatar_core.render.rasterize_gsplat import _kept_masks

    masks = _kept_masks(gs, [front, back], req)
    assert not masks[0, 1] and masks[1, 1]
    row = int(masks.any(0)[:1].sum())  # Gaussian 1's row in the union
    assert kw["opacities"][0, row] == 0 and kw["opacities"][1, row] > 0
    assert torch.allclose(kw["means"][0, row], torch.tensor(front.center, dtype=torch.float32))
    # each entry keeps exactly what the single-camera mapping keeps
    from avatar_core.render.rasterize_gsplat import _apply_budget

    for c, cam in enumerate((front, back)):
        sub, n = _apply_budget(gs, cam, req)
        assert n == int(counts[c])
        one = gsplat_arguments(sub, cam, req, 2)
        kept = kw["opacities"][c] > 0
        assert torch.equal(kw["means"][c][kept], one["means"])
        assert torch.equal(kw["colors"][c][kept], one["colors"])
        assert torch.equal(kw["viewmats"][c, 0], one["viewmats"][0])


def test_masked_culling_keeps_the_picture():
    """The training path's no-round-trip subset (culled Gaussians at the camera centre,
    opacity 0) renders what the Gaussians themselves render."""
    from avatar_core.render.rasterize_gsplat import _mask_culled

    gs = random_scene(60, 5)
    gs.means[:5, 2] = 3.0  # behind the camera
    gs.scales[5] = 5.5e34  # a veil: culled
    cam = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=40, height=32, fov_y_deg=40.0)
    masked, n = _mask_culled(gs, cam, RenderRequest())
    ref = rasterize(gs, cam, RenderRequest(backend="torch", outputs=ALL))
    assert int(n) == ref.stats["n_rendered"] and masked.means.shape == gs.means.shape
    assert torch.isfinite(masked.scales).all() and (masked.opacities[:6] == 0).all()
    out = rasterize(masked, cam, RenderRequest(backend="torch", outputs=ALL))
    for name in ALL:
        assert torch.allclose(getattr(out, name), getattr(ref, name), atol=1e-6), name


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("max_tile_pairs", [None, 40])
def test_batched_masks_equal_the_camera_by_camera_rule(antialiased, max_tile_pairs):
    """The vectorised masks (every camera in one pass) keep exactly what the single-camera
    rule keeps, hard cases included: behind or on a camera's plane, a veil, a degenerate
    (zero-scale, zero-quaternion) splat, and a pair bound that drops splats."""
    from avatar_core.render.budget import select_rendered
    from avatar_core.render.cost import pair_bound, tile_pairs
    from avatar_core.render.projection import project_gaussians
    from avatar_core.render.rasterize_gsplat import kept_masks_batched

    gs = random_scene(120, 7)
    gs.means[:4, 2] = 2.6  # behind the front cameras
    gs.means[4] = torch.tensor([0.0, 0.0, 2.5])  # on the first camera's centre
    gs.scales[5] = 5.5e34  # a veil: culled
    gs.scales[6] = 0.0
    gs.quats[7] = 0.0
    cams = _cams(5) + [look_at((0.0, 0.0, -2.5), (0.0, 0.0, 0.0), width=40, height=32)]
    req = RenderRequest(antialiased=antialiased, max_tile_pairs=max_tile_pairs)
    masks = kept_masks_batched(gs, cams, req)
    assert masks.shape == (len(cams), gs.num) and masks.dtype == torch.bool
    for c, cam in enumerate(cams):
        viewmat, K = cam.to_torch(gs.means.device, gs.means.dtype)
        p = project_gaussians(gs.means, gs.quats, gs.scales, gs.opacities, viewmat, K,
                              cam.width, cam.height, antialiased=antialiased)
        pairs = tile_pairs(p.means2d, p.radii, cam.width, cam.height)
        sel, _ = select_rendered(p, None, pairs, pair_bound(max_tile_pairs))
        assert masks[c].nonzero().squeeze(1).tolist() == sel.tolist(), c
    assert not masks[:, 5].any()
    if max_tile_pairs is not None:  # the bound dropped splats that the cameras see
        unbounded = kept_masks_batched(gs, cams, RenderRequest(antialiased=antialiased))
        assert not (masks & ~unbounded).any() and (masks.sum(1) < unbounded.sum(1)).any()


def test_batched_gsplat_budget_is_per_camera():
    gs = random_scene(50, 2)
    kw, counts = gsplat_views_arguments(gs, _cams(3), RenderRequest(budget=5), 3)
    assert counts.tolist() == [5, 5, 5]
    assert ((kw["opacities"] > 0).sum(1) == 5).all()
    assert kw["backgrounds"].shape == (3, 1, 3) and kw["render_mode"] == "RGB"


def test_batched_gsplat_edge_cases():
    gs = random_scene(10, 0)
    with pytest.raises(ValueError, match="one image size"):
        gsplat_views_arguments(gs, [_cams(1)[0], _cams(1, width=64)[0]], RenderRequest(), 3)
    behind = GaussianSet(gs.means + torch.tensor([0.0, 0.0, 10.0]), gs.quats, gs.scales,
                         gs.opacities, gs.sh)  # all behind every camera
    kw, counts = gsplat_views_arguments(behind, _cams(2), RenderRequest(), 3)
    assert kw == {} and counts.tolist() == [0, 0]
    kw, _ = gsplat_views_arguments(gs, _cams(2), RenderRequest(outputs=("alpha",)), 3)
    assert kw["backgrounds"] is None and kw["render_mode"] == "ED"


# ---- CUDA only (make gpu-check) ----------------------------------------------------------

def _cuda(g: GaussianSet, grad: bool = False) -> GaussianSet:
    return GaussianSet(*(t.detach().cuda().requires_grad_(grad)
                         for t in (g.means, g.quats, g.scales, g.opacities, g.sh)))


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.float().cpu() - b.float().cpu()) ** 2).mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


@pytest.mark.gpu
@pytest.mark.parametrize("scene", ["avatar", "random"])
def test_gsplat_matches_cpu_on_the_shared_scenes(scene):  # pragma: no cover (needs CUDA)
    pytest.importorskip("gsplat", reason="gsplat not installed (the cuda extra)")
    if scene == "avatar":
        gs, cam = avatar_like_scene(20_000, 0), avatar_camera(256)
    else:
        gs, cam = random_scene(2_000, 0), look_at((0, 0, 2.5), (0, 0, 0), width=160,
                                                  height=120, fov_y_deg=40.0)
    req = dict(outputs=ALL, background=(0.1, 0.3, 0.9))
    out = rasterize(_cuda(gs), cam, RenderRequest(backend="gsplat", **req))
    ref = rasterize(gs, cam, RenderRequest(backend="cpu", **req))
    assert out.stats["backend"] == "gsplat"
    assert _psnr(out.rgb.clamp(0, 1), ref.rgb.clamp(0, 1)) >= 40.0
    assert _psnr(out.alpha, ref.alpha) >= 40.0


@pytest.mark.gpu
def test_gsplat_gradients_agree_with_the_reference():  # pragma: no cover (needs CUDA)
    pytest.importorskip("gsplat", reason="gsplat not installed (the cuda extra)")
    gs, cam = avatar_like_scene(3_000, 1), avatar_camera(96)
    target = torch.rand(96, 96, 3, generator=torch.Generator().manual_seed(0))
    grads = {}
    for backend, g in (("gsplat", _cuda(gs, True)),
                       ("torch", GaussianSet(*(t.clone().requires_grad_(True) for t in (
                           gs.means, gs.quats, gs.scales, gs.opacities, gs.sh))))):
        out = rasterize(g, cam, RenderRequest(backend=backend, outputs=("rgb", "alpha")))
        loss = (out.rgb - target.to(out.rgb.device)).abs().mean() + out.alpha.mean()
        loss.backward()
        grads[backend] = {n: getattr(g, n).grad.detach().cpu().flatten()
                          for n in ("means", "scales", "opacities", "sh")}
    for name in ("means", "scales", "opacities", "sh"):
        cos = torch.nn.functional.cosine_similarity(grads["gsplat"][name],
                                                    grads["torch"][name], dim=0)
        assert cos >= 0.9, (name, float(cos))


@pytest.mark.gpu
def test_gsplat_batched_views_equal_single_renders():  # pragma: no cover (needs CUDA)
    pytest.importorskip("gsplat", reason="gsplat not installed (the cuda extra)")
    gs = _cuda(avatar_like_scene(10_000, 2))
    cams = [orbit((0.0, 0.08, 0.0), yaw, 5.0, 2.0, width=128, height=128, fov_y_deg=30.0)
            for yaw in (-40.0, -10.0, 0.0, 25.0, 70.0)]
    for req in (RenderRequest(outputs=ALL, backend="gsplat"),
                RenderRequest(outputs=("rgb",), budget=0.3, backend="gsplat")):
        outs = render_views(gs, cams, req)
        assert outs[0].stats["n_views"] == len(cams)
        for cam, out in zip(cams, outs, strict=True):
            one = rasterize(gs, cam, req)
            for name in req.outputs:
                assert torch.allclose(getattr(out, name), getattr(one, name), atol=1e-4)
