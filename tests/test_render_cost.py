"""A frame's render cost, counted before anything per pair is allocated (issue 25, finding 2).

The cost is the number of (Gaussian, tile) pairs of the splats' radius boxes: the torch
reference and its numba twin count the same, and the torch reference's tile lists hold
exactly that many (the cpu backend's, at most that many). Over its bound a frame is degraded
by the quality budget's rule (the least important splats go until the rest fit), the same
way on every backend; a compositor handed longer lists directly refuses them before it
allocates (``RenderTooExpensive``)."""

import numpy as np
import pytest
import torch

from avatar_core.render import rasterize
from avatar_core.render.budget import (
    drop_over_budget_np,
    footprint_area,
    kept_within_pairs,
    select_rendered,
)
from avatar_core.render.camera import look_at
from avatar_core.render.contract import MAX_TILE_PAIRS, NEAR_PLANE
from avatar_core.render.cost import (
    RenderTooExpensive,
    frame_tile_pairs,
    pair_bound,
    tile_pairs,
    tile_pairs_np,
)
from avatar_core.render.project_cpu import project_np
from avatar_core.render.projection import Projected, depth_key, project_gaussians
from avatar_core.render.rasterize_cpu import bin_tiles, composite_np
from avatar_core.render.rasterize_cpu import rasterize_to_pixels as cpu_to_pixels
from avatar_core.render.rasterize_torch import isect_tiles
from avatar_core.render.rasterize_torch import rasterize_to_pixels as torch_to_pixels
from avatar_core.render.scenes import random_scene
from avatar_core.render.types import GaussianSet, RenderRequest

CAM = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=80, height=56, fov_y_deg=40.0)
BACKENDS = ["torch", "cpu"]


def _project(gs: GaussianSet, cam=CAM) -> Projected:
    viewmat, K = cam.to_torch(torch.device("cpu"), torch.float32)
    return project_gaussians(gs.means, gs.quats, gs.scales, gs.opacities, viewmat, K,
                             cam.width, cam.height)


def bomb(n: int = 300, scale: float = 30.0, opacity: float = 0.6, seed: int = 0) -> GaussianSet:
    """``n`` splats each far wider than the picture, in front of the camera (an in-range
    avatar of log-scale 6 looks like this to the rasterizer), plus a few ordinary ones."""
    gs = random_scene(n, seed)
    scales = gs.scales.clone()
    scales[: n - 20] = scale
    opac = gs.opacities.clone()
    opac[: n - 20] = opacity
    return GaussianSet(gs.means, gs.quats, scales, opac, gs.sh)


# -- the count ---------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("size", [(80, 56), (17, 33), (1, 1)])
def test_the_twins_count_the_pairs_the_reference_lists_hold(seed, size):
    cam = CAM.resized(*size)
    gs = random_scene(400, seed) if seed < 2 else bomb(seed=seed)
    p = _project(gs, cam)
    pairs = tile_pairs(p.means2d, p.radii, *size)  # [N]
    twin = tile_pairs_np(p.means2d.numpy(), p.radii.numpy(), *size)
    assert pairs.dtype == torch.int64 and np.array_equal(pairs.numpy(), twin)
    assert int(pairs[~p.valid].sum()) == 0
    keys = depth_key(gs.means, cam.viewmat())
    _, ids = isect_tiles(p.means2d, p.radii, keys, *size)
    assert ids.numel() == int(pairs.sum())  # the torch reference allocates exactly these
    _, cpu_ids, _ = bin_tiles(p.means2d.numpy(), p.conics.numpy(), p.opacities.numpy(),
                              keys.numpy(), p.radii.numpy(), *size)
    assert cpu_ids.size <= int(pairs.sum())  # the cpu backend leaves out unreachable tiles


def test_hard_cases_count_what_can_be_drawn_and_nothing_else():
    w, h = 64, 40  # 4 x 3 tiles (the last row half a tile)
    inf, nan = float("inf"), float("nan")
    means2d = torch.tensor([
        [32.0, 20.0],        # 0 on a tile column's edge, radius 1: the two tiles beside it
        [32.0, 20.0],        # 1 radius 2**30 (the projection's clamp): every tile
        [-500.0, 20.0],      # 2 off the left edge, not reaching it
        [nan, 20.0],         # 3 NaN mean
        [inf, 20.0],         # 4 Inf mean
        [32.0, 20.0],        # 5 culled (radius 0)
        [32.0, 20.0],        # 6 negative radius
        [1e9, -1e9],         # 7 huge but finite mean, huge radius: clipped to the image
        [15.5, 15.5],        # 8 on a tile corner, radius 1: four tiles
    ], dtype=torch.float32)
    radii = torch.tensor([1, 2**30, 10, 5, 5, 0, -3, 2**30, 1], dtype=torch.int32)
    pairs = tile_pairs(means2d, radii, w, h)
    twin = tile_pairs_np(means2d.numpy(), radii.numpy(), w, h)
    assert pairs.tolist() == twin.tolist()
    assert pairs.tolist() == [2, 12, 0, 0, 0, 0, 0, 12, 4]
    empty = torch.zeros(0, 2)
    assert tile_pairs(empty, torch.zeros(0, dtype=torch.int32), w, h).numel() == 0
    assert tile_pairs_np(empty.numpy(), np.zeros(0, np.int32), w, h).size == 0


def test_splats_behind_the_camera_cost_nothing():
    gs = random_scene(50, 0)
    behind = GaussianSet(gs.means + torch.tensor([0.0, 0.0, 10.0]), gs.quats,
                         gs.scales * 100, gs.opacities, gs.sh)  # camera at z = 2.5, facing -z
    assert frame_tile_pairs(behind, CAM) == 0
    out = rasterize(behind, CAM, RenderRequest(backend="cpu", max_tile_pairs=0))
    assert out.stats["tile_pairs"] == 0 and out.stats["n_cost_dropped"] == 0


def test_the_frame_count_is_what_an_unbounded_frame_composites():
    gs = bomb()
    for backend in BACKENDS:
        out = rasterize(gs, CAM, RenderRequest(backend=backend, max_tile_pairs=10**9))
        assert out.stats["n_cost_dropped"] == 0
        assert out.stats["tile_pairs"] == frame_tile_pairs(gs, CAM) > 300 * 15
    assert pair_bound(None) == MAX_TILE_PAIRS and pair_bound(7) == 7


# -- the selection -----------------------------------------------------------------------------


def _numba_projected(gs: GaussianSet, cam=CAM):
    arrays = project_np(*(t.float().numpy() for t in (gs.means, gs.quats, gs.scales,
                                                        gs.opacities)),
                        cam.viewmat(), cam.K, cam.width, cam.height, NEAR_PLANE)
    m2, co, de, rad, op = arrays
    proj = Projected(means2d=torch.from_numpy(m2), conics=torch.from_numpy(co),
                     depths=torch.from_numpy(de), radii=torch.from_numpy(rad),
                     opacities=torch.from_numpy(op), valid=torch.from_numpy(rad > 0))
    return arrays, proj


@pytest.mark.parametrize("seed", [0, 3])
@pytest.mark.parametrize("max_pairs", [0, 1, 15, 500, 2000, 10**9])
@pytest.mark.parametrize("budget", [None, 40, 0.5])
def test_the_bound_keeps_the_most_important_splats_that_fit(seed, max_pairs, budget):
    gs = bomb(seed=seed)
    (m2, co, _, rad, op), proj = _numba_projected(gs)
    pairs = tile_pairs(proj.means2d, proj.radii, CAM.width, CAM.height)
    sel, n_visible = select_rendered(proj, budget, pairs, max_pairs)
    radii = rad.copy()
    n_vis_np, kept = drop_over_budget_np(co, op, radii, budget,
                                         tile_pairs_np(m2, rad, CAM.width, CAM.height),
                                         max_pairs)
    assert (n_vis_np, kept) == (n_visible, sel.numel())
    assert np.array_equal(np.flatnonzero(radii > 0), sel.numpy())  # the twins agree
    assert int(pairs[sel].sum()) <= max_pairs
    # what is kept is a run of the most important: the next one would not fit, or the
    # budget's count is reached
    importance = (proj.opacities * footprint_area(proj.conics))
    vis = torch.nonzero(proj.valid).squeeze(1)
    order = vis[torch.sort(importance[vis], descending=True, stable=True).indices]
    assert sorted(order[: sel.numel()].tolist()) == sel.tolist()
    if sel.numel() < n_visible and (budget is None or sel.numel() < 40):
        nxt = order[sel.numel()]
        assert int(pairs[sel].sum() + pairs[nxt]) > max_pairs
    if budget is None:
        mask = kept_within_pairs(proj, pairs, max_pairs)  # gsplat's device-side mask
        assert torch.nonzero(mask).squeeze(1).tolist() == sel.tolist()


# -- the frame ---------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_render_bomb_is_degraded_to_its_bound_not_allocated(backend):
    gs = bomb()
    bound = 1000  # the bomb needs ~15 x as many pairs
    out = rasterize(gs, CAM, RenderRequest(backend=backend, max_tile_pairs=bound,
                                           outputs=("rgb", "alpha", "depth")))
    st = out.stats
    assert 0 < st["tile_pairs"] <= bound
    assert st["n_cost_dropped"] > 0 and st["n_rendered"] + st["n_cost_dropped"] == st["n_visible"]
    if backend == "cpu":
        assert st["pairs_allocated"] <= bound  # the lists the frame really allocated
    assert all(torch.isfinite(t).all() for t in (out.rgb, out.alpha, out.depth))


def test_both_backends_degrade_a_bomb_the_same_way():
    gs = bomb(seed=1)
    req = dict(max_tile_pairs=1200, outputs=("rgb", "alpha"))
    cpu = rasterize(gs, CAM, RenderRequest(backend="cpu", **req))
    ref = rasterize(gs, CAM, RenderRequest(backend="torch", **req))
    for key in ("n_visible", "n_rendered", "tile_pairs", "n_cost_dropped"):
        assert cpu.stats[key] == ref.stats[key], key
    assert torch.allclose(cpu.rgb, ref.rgb, atol=1e-4)
    assert torch.allclose(cpu.alpha, ref.alpha, atol=1e-4)


def test_a_bound_of_zero_renders_the_background_and_bad_bounds_are_refused():
    gs = bomb()
    out = rasterize(gs, CAM, RenderRequest(backend="cpu", max_tile_pairs=0,
                                           background=(0.2, 0.3, 0.4)))
    assert out.stats["n_rendered"] == 0 and out.stats["tile_pairs"] == 0
    assert torch.allclose(out.rgb, torch.tensor([0.2, 0.3, 0.4]).expand_as(out.rgb))
    for bad in (-1, True, 2.5, "10"):
        with pytest.raises(ValueError, match="max_tile_pairs"):
            rasterize(gs, CAM, RenderRequest(max_tile_pairs=bad))


def test_gradients_flow_through_a_degraded_frame():
    gs = bomb(n=60)
    leaves = [t.clone().requires_grad_(True) for t in (gs.means, gs.scales, gs.opacities,
                                                        gs.sh)]
    g = GaussianSet(leaves[0], gs.quats, leaves[1], leaves[2], leaves[3])
    out = rasterize(g, CAM, RenderRequest(backend="cpu", max_tile_pairs=300))
    assert out.stats["n_cost_dropped"] > 0
    out.rgb.sum().backward()
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in leaves)
    assert float(leaves[2].grad.abs().sum()) > 0


# -- the compositors' own guard -----------------------------------------------------------------


def test_compositors_refuse_lists_over_their_bound_before_allocating():
    gs = bomb()
    p = _project(gs)
    keys = depth_key(gs.means, CAM.viewmat())
    n = int(tile_pairs(p.means2d, p.radii, CAM.width, CAM.height).sum())
    args = (p.means2d.numpy(), p.conics.numpy(), p.opacities.numpy())
    with pytest.raises(RenderTooExpensive, match=f"needs \\d+ \\(Gaussian, tile\\) pairs, more "
                                                 f"than the bound of {n // 4}"):
        bin_tiles(*args, keys.numpy(), p.radii.numpy(), CAM.width, CAM.height, n // 4)
    with pytest.raises(RenderTooExpensive):
        composite_np(*args, np.zeros((gs.num, 4), np.float32), keys.numpy(), p.radii.numpy(),
                     CAM.width, CAM.height, np.zeros(4), n // 4)
    with pytest.raises(RenderTooExpensive, match=f"{n} \\(Gaussian, tile\\) pairs"):
        isect_tiles(p.means2d, p.radii, keys, CAM.width, CAM.height, max_pairs=n - 1)
    colors = torch.rand(gs.num, 3)
    for to_pixels in (cpu_to_pixels, torch_to_pixels):
        with pytest.raises(RenderTooExpensive):
            to_pixels(p.means2d, p.conics, colors, p.opacities, p.depths, p.radii,
                      CAM.width, CAM.height, sort_keys=keys, max_pairs=10)
    assert issubclass(RenderTooExpensive, ValueError)
    offsets, ids = isect_tiles(p.means2d, p.radii, keys, CAM.width, CAM.height, max_pairs=n)
    assert ids.numel() == n and int(offsets[-1]) == n  # exactly at the bound: allowed
