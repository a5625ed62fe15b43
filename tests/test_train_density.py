"""Adaptive density control: Adam surgery, clone/split/prune, triangle coverage, statistics."""

import math

import numpy as np
import pytest
import torch

from avatar_core.gaussians.avatar import GaussianAvatar, to_world
from avatar_core.render import rasterize
from avatar_core.render.camera import Camera, look_at
from avatar_core.render.projection import project_gaussians
from avatar_core.render.scenes import random_scene
from avatar_core.render.types import RenderRequest
from avatar_core.rotations import quaternion_to_matrix
from avatar_core.train.density import (
    DensityStats,
    densify_and_prune,
    reset_opacity,
    screen_grad_norm,
    screen_visibility,
)
from avatar_core.train.optim import avatar_state, make_optimizer, state_to_avatar

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
PARAMS = ("local_means", "log_scales", "quats", "opacity_logits", "sh0", "sh_rest")


def _state(n_faces, n_extra, seed, dtype=torch.float32, device="cpu"):
    """Every triangle has one Gaussian (rows 0..F-1) plus n_extra on random triangles."""
    g = torch.Generator().manual_seed(seed)
    n = n_faces + n_extra
    parents = torch.cat([torch.arange(n_faces),
                         torch.randint(0, n_faces, (n_extra,), generator=g)])
    state = {
        "parents": parents,
        "local_means": 0.3 * torch.randn(n, 3, generator=g, dtype=dtype),
        "log_scales": math.log(0.3) + 0.8 * torch.randn(n, 3, generator=g, dtype=dtype),
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "opacity_logits": 3 * torch.randn(n, generator=g, dtype=dtype),
        "sh0": torch.randn(n, 1, 3, generator=g, dtype=dtype),
        "sh_rest": torch.randn(n, 3, 3, generator=g, dtype=dtype),
    }
    return {k: v.to(device) if k == "parents" else v.to(device).requires_grad_(True)
            for k, v in state.items()}


def _warm_optimizer(state, steps=2, seed=0):
    """An Adam optimiser with non-zero, row-distinct moments."""
    opt = make_optimizer(state)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        opt.zero_grad()
        for k in PARAMS:
            state[k].grad = torch.randn(state[k].shape, generator=g,
                                        dtype=state[k].dtype).to(state[k].device)
        opt.step()
    return opt


def _stats(n, grads, dtype=torch.float32, device="cpu"):
    stats = DensityStats.zeros(n, device=device, dtype=dtype)
    stats.update(grads.to(device, dtype), torch.ones(n, dtype=torch.bool, device=device))
    return stats


def _snapshot(state, opt):
    return ({k: v.detach().clone() for k, v in state.items()},
            {k: {m: t.clone() for m, t in opt.state[state[k]].items()} for k in PARAMS})


# -- Adam surgery -----------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_surgery_keeps_moments_aligned(device, dtype):
    state = _state(6, 14, seed=1, dtype=dtype, device=device)
    with torch.no_grad():
        state["opacity_logits"][-4:] = -9.0  # transparent, on triangles with others
    opt = _warm_optimizer(state)
    old, old_moments = _snapshot(state, opt)
    n = state["parents"].shape[0]
    grads = torch.where(torch.arange(n) % 3 == 0, 1.0, 0.0)  # every third one densifies
    res = densify_and_prune(state, _stats(n, grads, dtype, device), opt, percent_dense=0.6,
                            generator=torch.Generator().manual_seed(0))
    assert res.n_cloned > 0 and res.n_split > 0 and res.n_pruned > 0
    new, m = res.state, res.state["parents"].shape[0]
    kept = ~res.is_new
    for k in PARAMS:
        t = new[k]
        assert t.shape[0] == m and t.dtype == dtype and t.device.type == device
        assert t.is_leaf and t.requires_grad
        group = next(g for g in opt.param_groups if g["name"] == k)
        assert group["params"][0] is t
        st = opt.state[t]
        assert torch.equal(st["step"], old_moments[k]["step"])
        for moment in ("exp_avg", "exp_avg_sq"):
            assert st[moment].shape == t.shape
            assert torch.equal(st[moment][kept], old_moments[k][moment][res.source[kept]])
            assert not st[moment][res.is_new].any()
        assert torch.equal(t.detach()[kept], old[k][res.source[kept]])
    assert torch.equal(new["parents"], old["parents"][res.source])
    assert len(opt.state) == len(PARAMS)  # the old tensors' state is gone
    for k, v in state.items():  # the input tensors are left as they were
        assert torch.equal(v.detach(), old[k])
    # the optimiser still steps on the new tensors
    sum((new[k].double() ** 2).sum() for k in PARAMS).backward()
    opt.step()


def test_clone_is_an_exact_copy_on_the_same_triangle():
    state = _state(3, 0, seed=2)
    with torch.no_grad():
        state["log_scales"].fill_(math.log(0.005))  # small: clone
        state["opacity_logits"].fill_(2.0)
    opt = _warm_optimizer(state)
    res = densify_and_prune(state, _stats(3, torch.tensor([0.0, 1e-3, 0.0])), opt)
    assert (res.n_cloned, res.n_split, res.n_pruned) == (1, 0, 0)
    assert res.source.tolist() == [0, 1, 2, 1]
    assert res.is_new.tolist() == [False, False, False, True]
    for k in PARAMS:
        assert torch.equal(res.state[k][3], res.state[k][1])
    assert res.state["parents"].tolist() == [0, 1, 2, 1]


def test_split_children_follow_the_parents_local_gaussian():
    state = _state(4, 0, seed=3, dtype=torch.float64)
    with torch.no_grad():
        state["log_scales"][:] = torch.log(torch.tensor([0.5, 0.2, 0.05], dtype=torch.float64))
        state["opacity_logits"].fill_(2.0)
    grads = torch.tensor([0.0, 1.0, 0.0, 1.0])
    res = densify_and_prune(state, _stats(4, grads, torch.float64), None,
                            generator=torch.Generator().manual_seed(7))
    assert (res.n_cloned, res.n_split) == (0, 2)
    assert res.source.tolist() == [0, 2, 1, 3, 1, 3]  # the split parents are gone
    assert res.state["parents"].tolist() == [0, 2, 1, 3, 1, 3]
    # replay the draw: child = mean + R(q) (scale * eps), eps from the same generator
    eps = torch.randn(4, 3, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    src = torch.tensor([1, 3, 1, 3])
    rot = quaternion_to_matrix(state["quats"].detach()[src])
    scale = torch.exp(state["log_scales"].detach()[src])
    expected = state["local_means"].detach()[src] + (rot @ (scale * eps)[..., None])[..., 0]
    assert torch.allclose(res.state["local_means"][2:], expected, atol=1e-12)
    assert torch.allclose(res.state["log_scales"][2:],
                          state["log_scales"].detach()[src] - math.log(1.6), atol=1e-12)
    for k in ("quats", "opacity_logits", "sh0", "sh_rest"):
        assert torch.equal(res.state[k][2:], state[k].detach()[src])


def test_split_children_covariance_matches_the_parent():
    n = 4000
    q = torch.tensor([0.9, 0.2, -0.3, 0.1], dtype=torch.float64)
    s = torch.tensor([0.5, 0.2, 0.05], dtype=torch.float64)
    state = {"parents": torch.zeros(n, dtype=torch.long),
             "local_means": torch.tensor([0.1, 0.2, 0.0], dtype=torch.float64).repeat(n, 1),
             "log_scales": torch.log(s).repeat(n, 1), "quats": q.repeat(n, 1),
             "opacity_logits": torch.full((n,), 2.0, dtype=torch.float64)}
    res = densify_and_prune(state, _stats(n, torch.ones(n), torch.float64), None,
                            generator=torch.Generator().manual_seed(0))
    x = res.state["local_means"]
    assert x.shape == (2 * n, 3)
    R = quaternion_to_matrix(q)
    cov = R @ torch.diag(s ** 2) @ R.T
    assert torch.allclose(x.mean(0), state["local_means"][0], atol=0.02)
    assert torch.allclose(torch.cov(x.T), cov, atol=0.01)


def test_low_opacity_pruned_but_each_triangle_keeps_its_most_opaque():
    # triangle 0: all three transparent -> the most opaque (row 3) stays
    # triangle 1: one opaque -> the transparent one goes
    parents = torch.tensor([0, 0, 1, 0, 1])
    logits = torch.tensor([-9.0, -8.0, 3.0, -6.0, -9.0])
    state = {"parents": parents, "local_means": torch.zeros(5, 3),
             "log_scales": torch.full((5, 3), -3.0), "quats": torch.tensor([1.0, 0, 0, 0])
             .repeat(5, 1), "opacity_logits": logits}
    res = densify_and_prune(state, _stats(5, torch.zeros(5)), None)
    assert res.source.tolist() == [2, 3]
    assert res.n_pruned == 3


def test_tied_opacities_keep_the_lowest_row():
    state = {"parents": torch.tensor([1, 1, 0, 1]), "local_means": torch.zeros(4, 3),
             "log_scales": torch.full((4, 3), -3.0),
             "quats": torch.tensor([1.0, 0, 0, 0]).repeat(4, 1),
             "opacity_logits": torch.tensor([-9.0, -7.0, 3.0, -7.0])}
    res = densify_and_prune(state, _stats(4, torch.zeros(4)), None)
    assert res.source.tolist() == [1, 2]


@pytest.mark.parametrize("seed", range(40))
def test_random_stats_keep_every_triangle_and_every_binding(seed):
    rng = np.random.default_rng(seed)
    n_faces, n_extra = int(rng.integers(1, 12)), int(rng.integers(0, 30))
    state = _state(n_faces, n_extra, seed=seed)
    n = n_faces + n_extra
    with torch.no_grad():  # many below min_opacity, some whole triangles
        state["opacity_logits"].sub_(float(rng.uniform(0, 8)))
    opt = _warm_optimizer(state, steps=1, seed=seed)
    old, old_moments = _snapshot(state, opt)
    stats = DensityStats.zeros(n)
    for _ in range(3):
        stats.update(torch.as_tensor(rng.exponential(3e-4, n), dtype=torch.float32),
                     torch.as_tensor(rng.random(n) < 0.7),
                     torch.as_tensor(rng.uniform(0, 40, n), dtype=torch.float32))
    cap = int(rng.integers(1, 2 * n)) if rng.random() < 0.5 else None
    res = densify_and_prune(
        state, stats, opt, percent_dense=float(rng.uniform(0, 0.5)), extent=1.0,
        max_screen_size=float(rng.uniform(5, 30)) if rng.random() < 0.5 else None,
        max_gaussians=cap, generator=torch.Generator().manual_seed(seed))
    parents = res.state["parents"]
    assert set(parents.tolist()) == set(range(n_faces))  # no triangle lost
    assert torch.equal(parents, old["parents"][res.source])  # children inherit
    m = parents.shape[0]
    assert m == n + res.n_cloned + res.n_split - res.n_pruned
    if cap is not None:
        assert m <= max(n, cap)
    kept = ~res.is_new
    for k in PARAMS:
        assert res.state[k].shape[0] == m
        assert torch.equal(res.state[k].detach()[kept], old[k][res.source[kept]])
        assert torch.equal(opt.state[res.state[k]]["exp_avg"][kept],
                           old_moments[k]["exp_avg"][res.source[kept]])
    assert stats.num == m and not stats.count.any()  # reset to the new N


def test_deterministic_for_a_generator():
    def run(seed):
        state = _state(5, 20, seed=4)
        n = state["parents"].shape[0]
        res = densify_and_prune(state, _stats(n, torch.ones(n)), None, percent_dense=0.0,
                                generator=torch.Generator().manual_seed(seed))
        return res.state["local_means"]

    assert torch.equal(run(11), run(11))
    assert not torch.equal(run(11), run(12))


def test_growth_cap_takes_the_largest_gradients():
    state = _state(4, 0, seed=5)
    with torch.no_grad():
        state["log_scales"].fill_(math.log(0.001))
        state["opacity_logits"].fill_(2.0)
    grads = torch.tensor([1e-3, 5e-3, 2e-3, 4e-3])
    res = densify_and_prune(state, _stats(4, grads), None, max_gaussians=6)
    assert res.n_cloned == 2 and res.source.tolist() == [0, 1, 2, 3, 1, 3]
    res = densify_and_prune(_state(4, 0, seed=5), _stats(4, grads), None, max_gaussians=2,
                            min_opacity=0.0)
    assert res.n_cloned == 0 and res.source.numel() == 4  # over the cap: no growth


def test_screen_size_and_world_size_prunes():
    state = {"parents": torch.tensor([0, 0, 1, 1]), "local_means": torch.zeros(4, 3),
             "log_scales": torch.log(torch.tensor([[0.01] * 3, [0.01] * 3, [0.01] * 3,
                                                   [0.5, 0.01, 0.01]])),
             "quats": torch.tensor([1.0, 0, 0, 0]).repeat(4, 1),
             "opacity_logits": torch.full((4,), 2.0)}
    stats = DensityStats.zeros(4)
    stats.update(torch.zeros(4), torch.ones(4, dtype=torch.bool), torch.tensor([30.0, 5, 5, 5]))
    res = densify_and_prune(state, stats, None, max_screen_size=20, extent=1.0)
    assert res.source.tolist() == [1, 2]  # row 0 too big on screen, row 3 in the world
    stats = DensityStats.zeros(4)
    stats.update(torch.zeros(4), torch.ones(4, dtype=torch.bool), torch.tensor([30.0, 5, 5, 5]))
    res = densify_and_prune(state, stats, None)  # without max_screen_size: no size prune
    assert res.source.tolist() == [0, 1, 2, 3]


def test_face_scales_compare_in_world_units():
    state = _state(2, 0, seed=6)
    with torch.no_grad():
        state["log_scales"].fill_(math.log(0.4))
        state["opacity_logits"].fill_(2.0)
    grads = torch.ones(2)
    local = densify_and_prune(state, _stats(2, grads), None, percent_dense=0.01)
    assert (local.n_cloned, local.n_split) == (0, 2)  # 0.4 > 0.01 in triangle units
    world = densify_and_prune(state, _stats(2, grads), None, percent_dense=0.01,
                              face_scales=torch.tensor([0.01, 1.0]))
    # 0.4 * 0.01 m is small, 0.4 * 1 m is large
    assert (world.n_cloned, world.n_split) == (1, 1)
    with pytest.raises(ValueError, match="face_scales"):
        densify_and_prune(state, _stats(2, grads), None, face_scales=torch.ones(1))


def test_refuses_empty_nan_and_mismatched_inputs():
    empty = {k: v[:0] for k, v in _state(2, 0, seed=0).items()}
    with pytest.raises(ValueError, match="N = 0"):
        densify_and_prune(empty, DensityStats.zeros(0), None)
    bad = _state(2, 0, seed=0)
    with torch.no_grad():
        bad["local_means"][1, 0] = float("nan")
    with pytest.raises(ValueError, match="local_means.*NaN"):
        densify_and_prune(bad, DensityStats.zeros(2), None)
    with pytest.raises(ValueError, match="stats track 3"):
        densify_and_prune(_state(2, 0, seed=0), DensityStats.zeros(3), None)
    with pytest.raises(ValueError, match="lacks"):
        densify_and_prune({"parents": torch.zeros(2, dtype=torch.long)}, DensityStats.zeros(2),
                          None)
    with pytest.raises(ValueError, match="grad_threshold"):
        densify_and_prune(_state(2, 0, seed=0), DensityStats.zeros(2), None, grad_threshold=0)
    with pytest.raises(ValueError, match="rows"):
        densify_and_prune({**_state(2, 0, seed=0), "quats": torch.zeros(3, 4)},
                          DensityStats.zeros(2), None)


# -- opacity reset ----------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_reset_opacity_bounds_and_fresh_moments(dtype):
    state = _state(5, 5, seed=8, dtype=dtype)
    with torch.no_grad():
        state["opacity_logits"][:2] = torch.tensor([-6.0, -5.0])  # already below 0.01
    opt = _warm_optimizer(state)
    old, old_moments = _snapshot(state, opt)
    new = reset_opacity(state, opt, max_opacity=0.01)
    op = torch.sigmoid(new["opacity_logits"].detach())
    assert (op <= 0.01 * (1 + 1e-6)).all()
    low = torch.sigmoid(old["opacity_logits"]) < 0.01
    assert low.any() and torch.equal(new["opacity_logits"].detach()[low],
                                     old["opacity_logits"][low])  # already below: untouched
    assert torch.allclose(op[~low], torch.full_like(op[~low], 0.01))
    t = new["opacity_logits"]
    assert t.is_leaf and t.requires_grad
    assert opt.param_groups[3]["params"][0] is t
    assert not opt.state[t]["exp_avg"].any() and not opt.state[t]["exp_avg_sq"].any()
    assert torch.equal(opt.state[t]["step"], old_moments["opacity_logits"]["step"])
    for k in PARAMS:
        if k != "opacity_logits":
            assert new[k] is state[k]
            assert torch.equal(opt.state[new[k]]["exp_avg"], old_moments[k]["exp_avg"])
    with pytest.raises(ValueError, match="max_opacity"):
        reset_opacity(state, opt, max_opacity=1.0)


# -- statistics and view-space gradients ------------------------------------------------


def test_density_stats_accumulate_visible_views_only():
    stats = DensityStats.zeros(3)
    stats.update(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([True, False, True]),
                 torch.tensor([4.0, 9.0, 1.0]))
    stats.update(torch.tensor([3.0, 2.0, 5.0]), torch.tensor([True, False, False]),
                 torch.tensor([2.0, 9.0, 7.0]))
    assert stats.mean_grad().tolist() == [2.0, 0.0, 3.0]  # unseen -> 0, not NaN
    assert stats.count.tolist() == [2.0, 0.0, 1.0]
    assert stats.max_radii.tolist() == [4.0, 0.0, 1.0]
    with pytest.raises(ValueError, match="NaN"):
        stats.update(torch.tensor([float("nan"), 0, 0]), torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="shape"):
        stats.update(torch.zeros(2), torch.ones(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="bool"):
        stats.update(torch.zeros(3), torch.ones(3))
    stats.reset(5)
    assert stats.num == 5 and not stats.grad_accum.any()


def _skewed_camera():
    cam = look_at((0.3, 0.2, 2.0), (0.0, 0.0, 0.0), width=40, height=30, fov_y_deg=40.0)
    K = cam.K.copy()
    K[0, 1] = 3.0  # a skewed pinhole exercises the full A^-T
    K[1, 1] *= 1.2
    return Camera(K, cam.R, cam.t, cam.width, cam.height)


def test_screen_grad_norm_recovers_the_projected_mean_gradient():
    cam = _skewed_camera()
    g = torch.Generator().manual_seed(0)
    means = (0.3 * torch.randn(20, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    ones = torch.ones(20, dtype=torch.float64)
    viewmat, K = cam.to_torch(dtype=torch.float64)
    proj = project_gaussians(means, torch.tensor([1.0, 0, 0, 0]).repeat(20, 1).double(),
                             0.01 * torch.ones(20, 3).double(), ones, viewmat, K, 40, 30)
    w = torch.randn(20, 2, generator=g, dtype=torch.float64)
    (w * proj.means2d).sum().backward()  # dL/d(means2d) = w exactly
    got = screen_grad_norm(means.detach(), means.grad, cam)
    expected = (w * torch.tensor([20.0, 15.0], dtype=torch.float64)).norm(dim=-1)  # NDC
    assert torch.allclose(got, expected, rtol=1e-10)
    assert torch.allclose(screen_grad_norm(means.detach(), means.grad, cam, n_views=3),
                          3 * expected, rtol=1e-10)
    # a depth-only loss does not move the projected mean
    means.grad = None
    proj = project_gaussians(means, torch.tensor([1.0, 0, 0, 0]).repeat(20, 1).double(),
                             0.01 * torch.ones(20, 3).double(), ones, viewmat, K, 40, 30)
    proj.depths.sum().backward()
    assert screen_grad_norm(means.detach(), means.grad, cam).abs().max() < 1e-9
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        screen_grad_norm(means.detach(), means.grad[:, :2], cam)


def test_training_step_end_to_end_on_an_identity_bound_avatar():
    """Render -> loss -> view-space stats -> densify -> Adam step, on the torch backend."""
    gs = random_scene(12, 3, sh_degree=1, spread=0.2, scale=(0.05, 0.1))
    n_faces = 4
    avatar = GaussianAvatar(parents=torch.arange(12) % n_faces, local_means=gs.means,
                            log_scales=torch.log(gs.scales), quats=gs.quats,
                            opacity_logits=torch.logit(gs.opacities.clamp(0.05, 0.95)),
                            sh=gs.sh)
    rot, trans = torch.eye(3).expand(n_faces, 3, 3), torch.zeros(n_faces, 3)
    scale = torch.ones(n_faces)
    cam = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=24, height=20, fov_y_deg=40.0)
    state = avatar_state(avatar)
    opt = make_optimizer(state)
    stats = DensityStats.zeros(12)
    for _ in range(2):
        world = to_world(state_to_avatar(state), rot, trans, scale)
        world.means.retain_grad()
        out = rasterize(world, cam, RenderRequest(backend="torch"))
        out.rgb.square().mean().backward()
        visible, radii = screen_visibility(world, cam)
        grad = screen_grad_norm(world.means, world.means.grad, cam)
        assert torch.isfinite(grad).all() and (grad[visible] > 0).any()
        assert not grad[~visible].any()  # culled Gaussians get no gradient
        stats.update(grad, visible, radii)
        opt.step()
        opt.zero_grad()
    threshold = float(stats.mean_grad().median())
    res = densify_and_prune(state, stats, opt, grad_threshold=max(threshold, 1e-12),
                            percent_dense=0.05, generator=torch.Generator().manual_seed(0))
    assert res.n_cloned + res.n_split > 0
    world = to_world(state_to_avatar(res.state), rot, trans, scale)
    rasterize(world, cam, RenderRequest(backend="torch")).rgb.mean().backward()
    opt.step()  # moments and parameters agree in shape after the surgery
    assert set(res.state["parents"].tolist()) == set(range(n_faces))
