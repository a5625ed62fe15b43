"""Learning rates, Adam groups, SMPL-X fine-tuning groups and the local-frame regularisers."""

import math

import numpy as np
import pytest
import torch

from avatar_core.gaussians.avatar import GaussianAvatar
from avatar_core.train.optim import (
    DEFAULT_PARAM_LRS,
    GAUSSIAN_KEYS,
    GaussianLR,
    avatar_state,
    make_optimizer,
    make_param_optimizer,
    set_position_lr,
    state_to_avatar,
)
from avatar_core.train.regularizers import (
    RegularizerWeights,
    avatar_regularizers,
    position_loss,
    scaling_loss,
)


def _avatar(n_faces=5, sh_degree=3, dtype=torch.float32):
    faces = np.arange(3 * n_faces).reshape(n_faces, 3)
    return GaussianAvatar.from_mesh(faces, sh_degree=sh_degree, dtype=dtype)


# -- learning-rate schedule -------------------------------------------------------------


def test_position_schedule_endpoints_and_log_linear_middle():
    lr = GaussianLR(spatial_scale=2.0)
    assert lr.lr_at(0) == pytest.approx(5e-3 * 2.0, rel=1e-12)
    assert lr.lr_at(600_000) == pytest.approx(5e-5 * 2.0, rel=1e-12)
    assert lr.lr_at(10**9) == pytest.approx(5e-5 * 2.0, rel=1e-12)  # constant after the end
    assert lr.lr_at(300_000) == pytest.approx(math.sqrt(5e-3 * 5e-5) * 2.0, rel=1e-12)
    assert lr.lr_at(-1) == 0.0
    steps = [0, 1, 10, 1000, 100_000, 599_999, 600_000]
    values = [lr.lr_at(s) for s in steps]
    assert all(a >= b for a, b in zip(values, values[1:], strict=False))


def test_original_3dgs_rates_and_warmup():
    lr = GaussianLR.original_3dgs(extent=3.0)
    assert lr.lr_at(0) == pytest.approx(1.6e-4 * 3.0)
    assert lr.lr_at(30_000) == pytest.approx(1.6e-6 * 3.0)
    assert lr.scaling == 5e-3
    warm = GaussianLR(position_delay_steps=100, position_delay_mult=0.01)
    assert warm.lr_at(0) == pytest.approx(0.01 * 5e-3)
    assert warm.lr_at(100) == pytest.approx(GaussianLR().lr_at(100))


def test_bad_rates_refused():
    with pytest.raises(ValueError, match="position_init"):
        GaussianLR(position_init=0.0)
    with pytest.raises(ValueError, match="max_steps"):
        GaussianLR(position_max_steps=0)


# -- Gaussian optimizer -----------------------------------------------------------------


def test_make_optimizer_named_groups_with_gaussian_avatars_rates():
    state = avatar_state(_avatar())
    opt = make_optimizer(state, GaussianLR())
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert list(lrs) == list(GAUSSIAN_KEYS)
    assert lrs == pytest.approx({"local_means": 5e-3, "log_scales": 0.017, "quats": 1e-3,
                                 "opacity_logits": 0.05, "sh0": 2.5e-3,
                                 "sh_rest": 2.5e-3 / 20})
    for g in opt.param_groups:
        assert len(g["params"]) == 1 and g["params"][0] is state[g["name"]]
    assert opt.defaults["eps"] == 1e-15
    assert set_position_lr(opt, GaussianLR(), 600_000) == pytest.approx(5e-5)
    assert opt.param_groups[0]["lr"] == pytest.approx(5e-5)


def test_make_optimizer_refuses_unknown_missing_and_non_leaf():
    state = avatar_state(_avatar())
    with pytest.raises(ValueError, match="unknown"):
        make_optimizer({**state, "extra": torch.zeros(5, requires_grad=True)})
    sh = torch.cat([state.pop("sh0"), state.pop("sh_rest")], 1)
    with pytest.raises(ValueError, match="sh0"):
        make_optimizer({**state, "sh": sh})
    state = avatar_state(_avatar())
    state["quats"] = state["quats"] * 2  # not a leaf
    with pytest.raises(ValueError, match="leaf"):
        make_optimizer(state)
    with pytest.raises(ValueError, match="local_means"):
        set_position_lr(torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1),
                        GaussianLR(), 0)


@pytest.mark.parametrize("sh_degree", [0, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_state_round_trip_and_adam_step(sh_degree, dtype):
    avatar = _avatar(sh_degree=sh_degree, dtype=dtype)
    state = avatar_state(avatar)
    assert state["sh0"].shape == (5, 1, 3)
    assert state["sh_rest"].shape == (5, (sh_degree + 1) ** 2 - 1, 3)
    assert not state["parents"].requires_grad
    back = state_to_avatar(state)
    for k, v in avatar.tensors().items():
        assert torch.equal(back.tensors()[k].detach(), v)
    opt = make_optimizer(state)
    loss = sum((v.double() ** 2).sum() for k, v in state.items() if k != "parents")
    loss = loss + state_to_avatar(state).sh.sum()
    loss.backward()
    before = state["opacity_logits"].detach().clone()
    opt.step()
    # Adam's first step is lr * sign(grad): opacity logits move by 0.05
    assert torch.allclose(before - state["opacity_logits"].detach(),
                          torch.full_like(before, 0.05), rtol=1e-5)
    assert avatar.opacity_logits.equal(before)  # the avatar itself was not touched


# -- SMPL-X fine-tuning -----------------------------------------------------------------


def test_param_optimizer_defaults_override_and_switch():
    assert dict(DEFAULT_PARAM_LRS) == {"transl": 1e-8, "expression": 1e-4, "body_pose": 1e-6}
    with pytest.raises(TypeError):
        DEFAULT_PARAM_LRS["transl"] = 1.0  # read-only defaults
    params = {"transl": torch.zeros(2, 3), "expression": torch.zeros(2, 10),
              "body_pose": torch.zeros(2, 21, 3)}
    assert make_param_optimizer(params, enabled=False) is None
    assert not any(t.requires_grad for t in params.values())  # untouched when off
    opt = make_param_optimizer(params, {"expression": 1e-3})
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert lrs == {"transl": 1e-8, "expression": 1e-3, "body_pose": 1e-6}
    assert all(t.requires_grad for t in params.values())
    (params["transl"].sum() + params["expression"].sum() + params["body_pose"].sum()).backward()
    opt.step()
    assert torch.allclose(params["transl"], torch.full((2, 3), -1e-8))


def test_param_optimizer_refuses_missing_rates_and_bad_tensors():
    with pytest.raises(ValueError, match="jaw_pose"):
        make_param_optimizer({"jaw_pose": torch.zeros(1, 3)})
    assert make_param_optimizer({"jaw_pose": torch.zeros(1, 3)}, {"jaw_pose": 1e-5}) is not None
    with pytest.raises(ValueError, match="leaf"):
        make_param_optimizer({"transl": torch.zeros(3, requires_grad=True) * 2})
    with pytest.raises(ValueError, match="finite"):
        make_param_optimizer({"transl": torch.zeros(3)}, {"transl": float("nan")})
    with pytest.raises(ValueError, match="enabled=False"):
        make_param_optimizer({})


# -- regularisers -----------------------------------------------------------------------


def test_position_loss_hand_computed():
    mu = torch.tensor([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [0.0, 0.0, 0.5], [0.0, 2.0, 0.0]])
    # norms 0, 5, 0.5, 2 -> hinges 0, 4, 0, 1
    assert position_loss(mu).item() == pytest.approx(5.0 / 4)
    assert position_loss(mu, eps=2.0).item() == pytest.approx(3.0 / 4)


def test_scaling_loss_hand_computed_norm_of_axis_hinge():
    s = torch.log(torch.tensor([[1.0, 0.6, 0.1], [0.9, 1.0, 0.1], [0.5, 0.5, 0.5]]))
    # hinges (0.4, 0, 0), (0.3, 0.4, 0), 0 -> norms 0.4, 0.5, 0
    assert scaling_loss(s).item() == pytest.approx(0.3, rel=1e-5)


def test_zero_with_zero_finite_gradient_inside_eps_ball():
    mu = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.5, 0.1]], requires_grad=True)
    s = torch.log(torch.tensor([[0.6, 0.1, 0.2], [0.3, 0.3, 0.3]])).requires_grad_(True)
    terms = avatar_regularizers(mu, s)
    assert terms["pos"].item() == 0.0 and terms["scale"].item() == 0.0
    sum(terms.values()).backward()
    assert torch.equal(mu.grad, torch.zeros_like(mu))
    assert torch.equal(s.grad, torch.zeros_like(s))


def test_regulariser_weights_and_masks():
    mu = torch.tensor([[3.0, 4.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 7.0]])
    s = torch.log(torch.tensor([[1.6, 0.1, 0.1], [0.1, 0.1, 0.1], [0.1, 2.6, 0.1]]))
    mask = torch.tensor([True, False, True])
    assert position_loss(mu, weight=mask).item() == pytest.approx((4 + 6) / 2)
    assert scaling_loss(s, weight=mask).item() == pytest.approx((1.0 + 2.0) / 2, rel=1e-5)
    w = torch.tensor([1.0, 3.0, 0.0])
    assert position_loss(mu, weight=w).item() == pytest.approx((4 + 3 * 1) / 4)
    terms = avatar_regularizers(mu, s, mask, RegularizerWeights())
    assert terms["pos"].item() == pytest.approx(0.01 * 5)
    assert terms["scale"].item() == pytest.approx(1.5, rel=1e-5)
    with pytest.raises(ValueError, match="shape"):
        position_loss(mu, weight=mask[:2])
    with pytest.raises(ValueError, match=">= 0"):
        position_loss(mu, weight=-w)


def test_empty_selection_and_empty_avatar_give_zero_with_backward():
    mu = torch.randn(4, 3, requires_grad=True)
    s = torch.randn(4, 3, requires_grad=True)
    terms = avatar_regularizers(mu, s, torch.zeros(4, dtype=torch.bool))
    total = sum(terms.values())
    assert total.item() == 0.0
    total.backward()
    assert torch.isfinite(mu.grad).all() and torch.isfinite(s.grad).all()
    empty = torch.zeros(0, 3, requires_grad=True)
    assert position_loss(empty).item() == 0.0 and scaling_loss(empty).item() == 0.0


def test_regulariser_gradients_match_finite_differences():
    g = torch.Generator().manual_seed(3)
    mu = (2 * torch.randn(6, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    s = (torch.randn(6, 3, generator=g, dtype=torch.float64) * 0.5).requires_grad_(True)
    w = torch.rand(6, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda m: position_loss(m, weight=w), (mu,))
    assert torch.autograd.gradcheck(lambda x: scaling_loss(x, weight=w), (s,))


def test_nan_parameters_refused():
    bad = torch.zeros(3, 3)
    bad[1, 2] = float("nan")
    with pytest.raises(ValueError, match="local_means.*NaN"):
        position_loss(bad)
    with pytest.raises(ValueError, match="log_scales.*NaN"):
        scaling_loss(bad)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        position_loss(torch.zeros(3, 2))
