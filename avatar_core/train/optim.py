"""Learning rates and Adam optimisers for the Gaussians and the SMPL-X fine-tuning.

Gaussian learning rates are GaussianAvatars' values for Gaussians bound to mesh triangles
(ShenhanQian/GaussianAvatars, ``arguments/__init__.py``, ``OptimizationParams``): the
positions live in the triangle's k-scaled local frame, so position and scaling rates are
larger than 3DGS's world-space ones (``position_lr_init`` 5e-3 vs 1.6e-4, ``scaling_lr``
0.017 vs 0.005). As in 3DGS/GaussianAvatars the position rate decays exponentially
(log-linear) from ``position_init`` to ``position_final`` over ``position_max_steps`` and is
multiplied by ``spatial_scale`` (GaussianAvatars passes the cameras' extent there, 1.1 x the
largest camera distance from the rig centre; 1.0 here by default). SH rest coefficients get
``feature / 20`` and Adam uses ``eps = 1e-15`` (``scene/gaussian_model.py: training_setup``).

The trainer keeps the avatar as a dict of leaf tensors (:func:`avatar_state`): the
GaussianAvatar fields with ``sh`` split into ``sh0`` [N, 1, 3] and ``sh_rest`` [N, K-1, 3]
(one Adam group per tensor, and the two SH parts need different rates) plus the ``parents``
index, which is carried along but never optimised.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import torch
from torch import Tensor

from ..gaussians.avatar import GaussianAvatar

__all__ = [
    "DEFAULT_PARAM_LRS",
    "GAUSSIAN_KEYS",
    "GaussianLR",
    "avatar_state",
    "make_optimizer",
    "make_param_optimizer",
    "set_position_lr",
    "state_to_avatar",
]

# Optimised per-Gaussian tensors, in the order of the Adam groups.
GAUSSIAN_KEYS = ("local_means", "log_scales", "quats", "opacity_logits", "sh0", "sh_rest")
INDEX_KEY = "parents"  # carried in the state dict, not optimised

# SMPL-X fine-tuning rates of the MVFGA paper (as given in the project brief). translation
# 1e-8 is the paper's number, not a typo of ours: it all but freezes the root translation
# (GaussianAvatars' FLAME defaults are translation 1e-6, expression 1e-3, pose 1e-5).
# Read-only, so no caller can change the defaults of another.
DEFAULT_PARAM_LRS: Mapping[str, float] = MappingProxyType({
    "transl": 1e-8,
    "expression": 1e-4,
    "body_pose": 1e-6,
})
ADAM_EPS = 1e-15  # 3DGS / GaussianAvatars


@dataclass(frozen=True)
class GaussianLR:
    """Learning rates of the Gaussian parameters (defaults: GaussianAvatars, bound to mesh)."""

    position_init: float = 5e-3      # local (k-scaled) units; 3DGS: 1.6e-4 world units
    position_final: float = 5e-5     # 3DGS: 1.6e-6
    position_max_steps: int = 600_000  # 3DGS: 30_000
    position_delay_steps: int = 0    # 3DGS/GaussianAvatars: 0, i.e. no warm-up
    position_delay_mult: float = 0.01
    spatial_scale: float = 1.0       # multiplies both position rates (scene extent)
    scaling: float = 0.017           # 3DGS: 0.005
    rotation: float = 1e-3
    opacity: float = 0.05
    feature: float = 2.5e-3          # SH degree 0
    feature_rest_div: float = 20.0   # SH degree >= 1 get feature / 20

    def __post_init__(self) -> None:
        for name in ("position_init", "position_final", "spatial_scale"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"GaussianLR.{name} must be positive, got {getattr(self, name)}")
        if self.position_max_steps <= 0:
            raise ValueError(f"position_max_steps must be positive, got "
                             f"{self.position_max_steps}")

    @classmethod
    def original_3dgs(cls, extent: float) -> GaussianLR:
        """The unbound 3DGS rates (``arguments/__init__.py`` of graphdeco-inria/
        gaussian-splatting): world-space positions scaled by the scene extent."""
        return cls(position_init=1.6e-4, position_final=1.6e-6, position_max_steps=30_000,
                   spatial_scale=extent, scaling=5e-3)

    def lr_at(self, step: int) -> float:
        """Position learning rate at ``step`` (3DGS ``get_expon_lr_func``): log-linear from
        init to final over ``position_max_steps``, constant after; optional sine warm-up."""
        if step < 0:
            return 0.0
        if self.position_delay_steps > 0:
            ramp = min(step / self.position_delay_steps, 1.0)
            delay = self.position_delay_mult + (1 - self.position_delay_mult) * math.sin(
                0.5 * math.pi * ramp)
        else:
            delay = 1.0
        t = min(step / self.position_max_steps, 1.0)
        log_lr = math.log(self.position_init) * (1 - t) + math.log(self.position_final) * t
        return delay * self.spatial_scale * math.exp(log_lr)

    def group_lrs(self) -> dict[str, float]:
        """Initial rate of every Gaussian group, by name."""
        return {"local_means": self.lr_at(0), "log_scales": self.scaling,
                "quats": self.rotation, "opacity_logits": self.opacity, "sh0": self.feature,
                "sh_rest": self.feature / self.feature_rest_div}


def avatar_state(avatar: GaussianAvatar) -> dict[str, Tensor]:
    """Fresh leaf tensors (requires_grad) of an avatar, ``sh`` split into ``sh0`` and
    ``sh_rest``, plus its ``parents`` (no grad). Detached copies: the avatar is untouched."""
    t = {k: v.detach().clone() for k, v in avatar.tensors().items()}
    sh = t.pop("sh")  # [N, K, 3]
    t["sh0"], t["sh_rest"] = sh[:, :1].contiguous(), sh[:, 1:].contiguous()
    return {k: v if k == INDEX_KEY else v.requires_grad_(True) for k, v in t.items()}


def state_to_avatar(state: Mapping[str, Tensor]) -> GaussianAvatar:
    """The avatar the state describes (differentiable: rendering it reaches the leaves)."""
    return GaussianAvatar(parents=state["parents"], local_means=state["local_means"],
                          log_scales=state["log_scales"], quats=state["quats"],
                          opacity_logits=state["opacity_logits"],
                          sh=torch.cat([state["sh0"], state["sh_rest"]], 1))


def _check_leaf(name: str, t: Tensor) -> None:
    if not isinstance(t, Tensor) or not t.is_floating_point():
        raise ValueError(f"{name!r} must be a floating-point tensor")
    if not (t.is_leaf and t.requires_grad):
        raise ValueError(f"{name!r} must be a leaf tensor with requires_grad=True "
                         "(see avatar_state)")


def make_optimizer(avatar_params: Mapping[str, Tensor],
                   lr: GaussianLR = GaussianLR(),  # noqa: B008
                   *, fused: bool = False) -> torch.optim.Adam:
    """Adam with one named group per Gaussian tensor (``group["name"]`` = its key).
    ``fused``: torch's fused kernel (the CUDA trainer: it takes a device-side ``found_inf``
    flag, so a step is skipped without reading anything back to the host).

    ``avatar_params`` holds exactly :data:`GAUSSIAN_KEYS` (and optionally ``parents``, which
    is skipped); anything else is refused, so no tensor silently trains at a wrong rate.
    """
    names = [k for k in avatar_params if k != INDEX_KEY]
    unknown, missing = set(names) - set(GAUSSIAN_KEYS), set(GAUSSIAN_KEYS) - set(names)
    if unknown or missing:
        raise ValueError(f"expected the tensors {list(GAUSSIAN_KEYS)}; unknown "
                         f"{sorted(unknown)}, missing {sorted(missing)} (split 'sh' into "
                         "'sh0' and 'sh_rest', see avatar_state)")
    rates = lr.group_lrs()
    groups = []
    for name in GAUSSIAN_KEYS:
        _check_leaf(name, avatar_params[name])
        groups.append({"params": [avatar_params[name]], "lr": rates[name], "name": name})
    return torch.optim.Adam(groups, lr=0.0, eps=ADAM_EPS, fused=fused or None)


def set_position_lr(optimizer: torch.optim.Optimizer, lr: GaussianLR, step: int) -> float:
    """Apply the position schedule at ``step`` to the ``local_means`` group; returns it."""
    value = lr.lr_at(step)
    hits = [g for g in optimizer.param_groups if g.get("name") == "local_means"]
    if not hits:
        raise ValueError("the optimizer has no group named 'local_means'")
    for group in hits:
        group["lr"] = value
    return value


def make_param_optimizer(params: Mapping[str, Tensor],
                         lrs: Mapping[str, float] | None = None, *,
                         enabled: bool = True, fused: bool = False) -> torch.optim.Adam | None:
    """Adam over the SMPL-X parameters being fine-tuned, one named group per tensor.

    ``lrs`` overrides :data:`DEFAULT_PARAM_LRS` per name; every tensor of ``params`` needs a
    rate (``ValueError`` naming the ones without). ``enabled=False`` turns fine-tuning off:
    returns ``None`` and leaves the tensors alone (the caller keeps them without grad).
    The tensors must be floating-point leaves; they are switched to ``requires_grad=True``,
    as GaussianAvatars does for the FLAME parameters it fine-tunes.
    """
    if not enabled:
        return None
    if not params:
        raise ValueError("no SMPL-X parameters to fine-tune (pass enabled=False instead)")
    rates = {**DEFAULT_PARAM_LRS, **(lrs or {})}
    no_rate = sorted(set(params) - set(rates))
    if no_rate:
        raise ValueError(f"no learning rate for {no_rate}; defaults exist for "
                         f"{sorted(DEFAULT_PARAM_LRS)}")
    groups = []
    for name, t in params.items():
        if not isinstance(t, Tensor) or not t.is_floating_point() or not t.is_leaf:
            raise ValueError(f"SMPL-X parameter {name!r} must be a floating-point leaf tensor")
        rate = float(rates[name])
        if not (math.isfinite(rate) and rate >= 0):
            raise ValueError(f"learning rate of {name!r} must be finite and >= 0, got {rate}")
        groups.append({"params": [t.requires_grad_(True)], "lr": rate, "name": name})
    return torch.optim.Adam(groups, lr=0.0, eps=ADAM_EPS, fused=fused or None)
