"""Adaptive density control of triangle-bound Gaussians (3DGS, as adapted by GaussianAvatars).

The avatar is a dict of per-Gaussian tensors (:func:`avatar_core.train.optim.avatar_state`:
``parents`` plus the optimised leaves). Every operation here builds new tensors from an
index into the old rows and repoints the Adam optimiser at them, moving its per-row state
with the rows: kept Gaussians keep their moments, new ones (clones, split children) start at
zero, as in 3DGS's ``cat_tensors_to_optimizer`` / ``_prune_optimizer``.

Densification statistic (:class:`DensityStats`): the norm of the loss gradient with respect
to each Gaussian's projected 2D mean, in 3DGS's NDC-like units (pixel gradient times
(W/2, H/2), the ``ddelx_dx = 0.5 W`` of 3DGS's backward pass and gsplat's
``DefaultStrategy``), averaged over the views where the Gaussian was visible, so
``grad_threshold = 0.0002`` means what it means in 3DGS. Our :func:`rasterize` does not
return the 2D means, so :func:`screen_grad_norm` recovers that gradient from the gradient of
the world-space means: the loss gradient for a shift of the projected mean at fixed depth
(exact for everything that flows through the 2D mean; see its docstring).

Scales are compared in the triangle's local frame (``exp(log_scales)``, units of the
triangle's k) unless ``face_scales`` (k per triangle) is given: then in world units,
``k[parent] * exp(log_scales)``, as GaussianAvatars' ``get_scaling`` does.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from ..render.camera import Camera
from ..render.contract import NEAR_PLANE
from ..render.projection import project_gaussians
from ..render.types import GaussianSet
from ..rotations import quaternion_to_matrix

__all__ = [
    "DensifyResult",
    "DensityStats",
    "densify_and_prune",
    "reset_opacity",
    "screen_grad_norm",
    "screen_visibility",
]

N_SPLIT = 2              # children per split Gaussian (3DGS)
SPLIT_SCALE_DIV = 0.8 * N_SPLIT  # children's scale = parent's / (0.8 N) (3DGS)
BIG_WORLD_FRACTION = 0.1  # 3DGS prunes scales above 0.1 x extent (with max_screen_size)
REQUIRED = ("parents", "local_means", "log_scales", "quats", "opacity_logits")


# -- statistics -------------------------------------------------------------------------


@dataclass
class DensityStats:
    """Per-Gaussian accumulators between two densifications."""

    grad_accum: Tensor  # [N] summed view-space gradient norms (NDC units)
    count: Tensor       # [N] views in which the Gaussian was visible
    max_radii: Tensor   # [N] largest screen radius seen, px

    @classmethod
    def zeros(cls, n: int, *, device: torch.device | str | None = None,
              dtype: torch.dtype = torch.float32) -> DensityStats:
        z = torch.zeros(n, device=device, dtype=dtype)
        return cls(grad_accum=z, count=z.clone(), max_radii=z.clone())

    @property
    def num(self) -> int:
        return self.grad_accum.shape[0]

    def update(self, grad_norm: Tensor, visible: Tensor, radii: Tensor | None = None,
               *, check: bool = True) -> None:
        """Add one view: ``grad_norm`` [N] (NDC units), ``visible`` [N] bool, ``radii`` [N]
        px (optional, for the screen-size prune). Non-finite gradients are refused: they
        would poison the averages for the rest of the interval."""
        n = self.num
        if grad_norm.shape != (n,) or visible.shape != (n,):
            raise ValueError(f"grad_norm and visible must have shape [{n}], got "
                             f"{list(grad_norm.shape)} and {list(visible.shape)}")
        if visible.dtype != torch.bool:
            raise ValueError(f"visible must be a bool mask, got {visible.dtype}")
        g = grad_norm.detach().to(self.grad_accum)
        # check=False (the CUDA trainer, no host read): its caller masks non-finite rows out
        # of ``visible``, and where() never lets a masked NaN through
        if check and not bool(torch.isfinite(g).all()):
            raise ValueError("grad_norm contains NaN or Inf")
        vis = visible.to(self.grad_accum.device)
        self.grad_accum = self.grad_accum + torch.where(vis, g, torch.zeros_like(g))
        self.count = self.count + vis.to(self.count.dtype)
        if radii is not None:
            if radii.shape != (n,):
                raise ValueError(f"radii must have shape [{n}], got {list(radii.shape)}")
            r = torch.where(vis, radii.detach().to(self.max_radii), self.max_radii)
            self.max_radii = torch.maximum(self.max_radii, r)

    def mean_grad(self) -> Tensor:
        """[N] average gradient norm over the visible views, 0 where never visible."""
        seen = self.count > 0
        return torch.where(seen, self.grad_accum / self.count.clamp_min(1), 0.0)

    def reset(self, n: int | None = None) -> None:
        """Zero the accumulators (resized to ``n`` Gaussians when given)."""
        fresh = DensityStats.zeros(self.num if n is None else n,
                                   device=self.grad_accum.device, dtype=self.grad_accum.dtype)
        self.grad_accum, self.count, self.max_radii = (fresh.grad_accum, fresh.count,
                                                       fresh.max_radii)


def screen_grad_norm(means: Tensor, means_grad: Tensor, camera: Camera, *,
                     n_views: int = 1) -> Tensor:
    """[N] norm of dL/d(projected mean), NDC units, from dL/d(world mean) ``means_grad``.

    The projected mean moves by a pixel offset d when the camera-space mean moves by
    ``z A^-1 d`` at fixed depth z (A = K[:2, :2]), so ``dL/dd = z A^-T (R g)[:2]``. This
    equals 3DGS's ``viewspace_points.grad`` exactly when the loss reaches the mean only
    through its 2D projection; the small parts that reach it through the Jacobian in the
    2D covariance and the SH view direction are included too (3DGS leaves them out), the
    depth part is not (fixed depth). ``means`` [N, 3] are the world means that were
    rendered, ``means_grad`` [N, 3] their gradient (``retain_grad()`` on the non-leaf
    world means, or ``torch.autograd.grad``). Multiply by the number of views the loss
    averages over (``n_views``, gsplat's ``n_cameras``) to undo that averaging.
    """
    if means.shape != means_grad.shape or means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means and means_grad must both be [N, 3], got "
                         f"{list(means.shape)} and {list(means_grad.shape)}")
    viewmat, K = camera.to_torch(means.device, means.dtype)
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    z = means.detach() @ rot[2] + trans[2]  # [N] camera depth
    g_cam = means_grad.detach() @ rot.T     # [N, 3] = R g per row
    fx, skew, fy = K[0, 0], K[0, 1], K[1, 1]
    # solve A^T y = g_cam[:2] with A = [[fx, skew], [0, fy]] (upper triangular)
    gx = g_cam[:, 0] / fx
    gy = (g_cam[:, 1] - skew * gx) / fy
    half = torch.tensor([0.5 * camera.width, 0.5 * camera.height], dtype=means.dtype,
                        device=means.device)
    g_ndc = z[:, None] * torch.stack([gx, gy], -1) * half * n_views  # [N, 2]
    return torch.linalg.vector_norm(g_ndc, dim=-1)


def screen_visibility(gaussians: GaussianSet, camera: Camera, *,
                      antialiased: bool = False, validate: bool = True
                      ) -> tuple[Tensor, Tensor]:
    """(visible [N] bool, radii [N] px) of the shared projection (no grad): the
    ``visibility_filter`` and ``radii`` 3DGS's renderer returns. Pass the camera as
    rendered (after any resize of the request)."""
    with torch.no_grad():
        viewmat, K = camera.to_torch(gaussians.means.device, gaussians.means.dtype)
        proj = project_gaussians(gaussians.means, gaussians.quats, gaussians.scales,
                                 gaussians.opacities, viewmat, K, camera.width,
                                 camera.height, NEAR_PLANE, antialiased, validate=validate)
    return proj.valid, proj.radii.to(gaussians.means.dtype)


# -- state checks and optimiser surgery -------------------------------------------------


def _check_state(state: Mapping[str, Tensor], what: str) -> int:
    """N of a valid state; ValueError naming the problem otherwise."""
    missing = [k for k in REQUIRED if k not in state]
    if missing:
        raise ValueError(f"{what}: state lacks {missing}")
    parents = state["parents"]
    if parents.ndim != 1 or parents.dtype != torch.long:
        raise ValueError(f"{what}: parents must be a 1-D long tensor")
    n = parents.shape[0]
    if n == 0:
        raise ValueError(f"{what}: the avatar has no Gaussians (N = 0); it needs at least "
                         "one per triangle")
    for k, t in state.items():
        if t.ndim == 0 or t.shape[0] != n:
            raise ValueError(f"{what}: {k!r} has {list(t.shape)}, expected {n} rows")
        if t.is_floating_point() and not bool(torch.isfinite(t.detach()).all()):
            raise ValueError(f"{what}: {k!r} contains NaN or Inf")
    if bool((parents < 0).any()):
        raise ValueError(f"{what}: parents must be >= 0")
    return n


def _remap_rows(v: Tensor, src: Tensor, fresh: Tensor) -> Tensor:
    """Rows ``src`` of v, zero where ``fresh``."""
    out = v[src]
    return torch.where(fresh.view(-1, *([1] * (out.ndim - 1))), torch.zeros_like(out), out)


def _swap_in_optimizer(optimizer: torch.optim.Optimizer | None, old: Tensor, new: Tensor,
                       src: Tensor, fresh: Tensor) -> None:
    """Point ``optimizer`` at ``new`` instead of ``old``; per-row state follows ``src``,
    rows flagged ``fresh`` restart from zero, scalar state (Adam's step) is kept."""
    if optimizer is None:
        return
    n_old = old.shape[0]
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is not old:
                continue
            group["params"][i] = new
            st = optimizer.state.pop(old, None)
            if st:
                optimizer.state[new] = {
                    k: _remap_rows(v, src, fresh)
                    if isinstance(v, Tensor) and v.ndim > 0 and v.shape[0] == n_old else v
                    for k, v in st.items()}


def _rebuild(state: Mapping[str, Tensor], rows: Mapping[str, Tensor],
             optimizer: torch.optim.Optimizer | None, src: Tensor,
             fresh: Tensor) -> dict[str, Tensor]:
    """New leaves from ``rows`` (same keys as ``state``) swapped into the optimizer."""
    out = {}
    for k, old in state.items():
        new = rows[k].detach().requires_grad_(old.requires_grad)  # fresh tensors already
        _swap_in_optimizer(optimizer, old, new, src, fresh)
        out[k] = new
    return out


# -- densify and prune ------------------------------------------------------------------


@dataclass
class DensifyResult:
    state: dict[str, Tensor]  # the new per-Gaussian tensors (leaves where the input's were)
    source: Tensor            # [M] long, input row each output row was made from
    is_new: Tensor            # [M] bool, clones and split children (zero Adam moments)
    n_cloned: int
    n_split: int              # Gaussians replaced by N_SPLIT children each
    n_pruned: int


def _max_scale(log_scales: Tensor, parents: Tensor, face_scales: Tensor | None) -> Tensor:
    """[N] largest axis, local (triangle-k) units, or world units with ``face_scales``."""
    s = torch.exp(log_scales.detach()).amax(-1)
    return s if face_scales is None else s * face_scales.to(s)[parents]


def _cap(clone: Tensor, split: Tensor, grads: Tensor, n: int,
         max_gaussians: int | None) -> tuple[Tensor, Tensor]:
    """Keep the largest-gradient candidates that fit: a clone or a split adds one."""
    if max_gaussians is None:
        return clone, split
    cand = clone | split
    room = max(max_gaussians - n, 0)
    if int(cand.sum()) <= room:
        return clone, split
    score = torch.where(cand, grads, torch.full_like(grads, -math.inf))
    top = torch.sort(score, descending=True, stable=True).indices[:room]
    chosen = torch.zeros_like(cand)
    chosen[top] = True
    return clone & chosen, split & chosen


def _split_children(means: Tensor, log_scales: Tensor, quats: Tensor,
                    generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """N_SPLIT children per row, drawn from the parent's local Gaussian
    N(mean, R S^2 R^T): means [N_SPLIT * S, 3], log-scales shrunk by 0.8 N_SPLIT. The
    local Gaussian maps to the world one by the triangle's similarity, so sampling here is
    sampling the rendered Gaussian. (GaussianAvatars' ``densify_and_split`` draws with the
    world-scaled std and without adding the parent's local mean; we follow 3DGS's rule in
    the local frame instead, which is what that code means to do.)"""
    reps = (N_SPLIT, 1)
    m = means.shape[0] * N_SPLIT
    # drawn on the generator's device: one generator gives the same avatar on CPU and CUDA
    gen_device = generator.device if generator is not None else means.device
    eps = torch.randn(m, 3, generator=generator, device=gen_device, dtype=means.dtype)
    eps = eps.to(means.device)  # [M, 3]
    rot = quaternion_to_matrix(quats).repeat(N_SPLIT, 1, 1)  # [M, 3, 3]
    offset = (rot @ (torch.exp(log_scales).repeat(*reps) * eps)[..., None])[..., 0]
    return means.repeat(*reps) + offset, log_scales.repeat(*reps) - math.log(SPLIT_SCALE_DIV)


def _keep_one_per_triangle(prune: Tensor, parents: Tensor, opacity_logits: Tensor) -> Tensor:
    """``prune`` with, for every triangle it would empty, that triangle's most opaque
    Gaussian (lowest row on ties) kept."""
    n_tri = int(parents.max()) + 1
    had = torch.bincount(parents, minlength=n_tri) > 0  # [F]
    kept = torch.bincount(parents[~prune], minlength=n_tri) > 0
    orphan = had & ~kept
    if not bool(orphan.any()):
        return prune
    cand = orphan[parents]  # [M] rows on triangles about to be emptied
    score = torch.where(cand, opacity_logits, torch.full_like(opacity_logits, -math.inf))
    best = torch.full((n_tri,), -math.inf, dtype=score.dtype, device=score.device)
    best = best.scatter_reduce(0, parents, score, "amax")
    rows = torch.arange(parents.shape[0], device=parents.device)
    is_best = cand & (score == best[parents])
    first = torch.full((n_tri,), parents.shape[0], dtype=torch.long, device=parents.device)
    first = first.scatter_reduce(0, parents, torch.where(is_best, rows, parents.shape[0]),
                                 "amin")
    prune = prune.clone()
    prune[first[orphan]] = False
    return prune


def _check_options(grad_threshold: float, percent_dense: float, extent: float,
                   min_opacity: float, max_screen_size: float | None,
                   max_gaussians: int | None) -> None:
    if not (math.isfinite(grad_threshold) and grad_threshold > 0):
        raise ValueError(f"grad_threshold must be positive, got {grad_threshold}")
    if not (math.isfinite(percent_dense) and percent_dense >= 0):
        raise ValueError(f"percent_dense must be >= 0, got {percent_dense}")
    if not (math.isfinite(extent) and extent > 0):
        raise ValueError(f"extent must be positive, got {extent}")
    if not 0 <= min_opacity < 1:
        raise ValueError(f"min_opacity must be in [0, 1), got {min_opacity}")
    if max_screen_size is not None and not max_screen_size > 0:
        raise ValueError(f"max_screen_size must be positive, got {max_screen_size}")
    if max_gaussians is not None and max_gaussians < 1:
        raise ValueError(f"max_gaussians must be >= 1, got {max_gaussians}")


def densify_and_prune(state: Mapping[str, Tensor], stats: DensityStats,
                      optimizer: torch.optim.Optimizer | None, *,
                      grad_threshold: float = 2e-4, percent_dense: float = 0.01,
                      extent: float = 1.0, min_opacity: float = 0.005,
                      max_screen_size: float | None = None,
                      max_gaussians: int | None = None, face_scales: Tensor | None = None,
                      generator: torch.Generator | None = None) -> DensifyResult:
    """One 3DGS densification step on a triangle-bound avatar.

    Gaussians whose mean view-space gradient (``stats``, NDC units) reaches
    ``grad_threshold`` are cloned (largest scale <= ``percent_dense * extent``: an exact
    copy, same parent) or split (larger: ``N_SPLIT`` children drawn from the parent's
    Gaussian, scales / 1.6, same parent; the parent goes). ``max_gaussians`` caps the
    growth (largest gradients first); the result never exceeds ``max(N, max_gaussians)``.
    Then Gaussians with opacity < ``min_opacity`` are pruned, and with ``max_screen_size``
    also those whose screen radius exceeded it (old rows only: new ones have not been seen)
    or whose largest scale exceeds 0.1 ``extent``. A triangle never loses its last
    Gaussian: where the prune would empty one, its most opaque Gaussian stays.

    ``extent`` is in the units of the comparison: local triangle units (k), or world units
    with ``face_scales`` [F] (k of each triangle, GaussianAvatars' comparison).
    Returns the new state (the optimizer now holds its leaves; kept rows keep their Adam
    moments, new rows start at zero) and resets ``stats`` to the new N. Deterministic for
    a given ``generator`` (split sampling is the only randomness).
    """
    n = _check_state(state, "densify_and_prune")
    _check_options(grad_threshold, percent_dense, extent, min_opacity, max_screen_size,
                   max_gaussians)
    if stats.num != n:
        raise ValueError(f"stats track {stats.num} Gaussians, the state has {n}")
    parents = state["parents"]
    device = parents.device
    if face_scales is not None and (face_scales.ndim != 1
                                    or face_scales.shape[0] <= int(parents.max())):
        raise ValueError(f"face_scales must be [F] covering every parent, got "
                         f"{list(face_scales.shape)}")
    grads = stats.mean_grad().to(device)  # [N]
    big = _max_scale(state["log_scales"], parents, face_scales) > percent_dense * extent
    hot = grads >= grad_threshold
    clone, split = _cap(hot & ~big, hot & big, grads, n, max_gaussians)

    rows = torch.arange(n, device=device)
    clone_idx, split_idx = rows[clone], rows[split]
    n_keep, n_clone, n_split = n - split_idx.numel(), clone_idx.numel(), split_idx.numel()
    src = torch.cat([rows[~split], clone_idx, split_idx.repeat(N_SPLIT)])  # [M]
    fresh = torch.arange(src.numel(), device=device) >= n_keep            # [M]
    out = {k: v.detach()[src] for k, v in state.items()}
    if n_split:
        means, log_scales = _split_children(
            state["local_means"].detach()[split_idx], state["log_scales"].detach()[split_idx],
            state["quats"].detach()[split_idx], generator)
        out["local_means"][n_keep + n_clone:] = means
        out["log_scales"][n_keep + n_clone:] = log_scales

    prune = torch.sigmoid(out["opacity_logits"]) < min_opacity  # [M]
    if max_screen_size is not None:
        # 3DGS zeroes max_radii2D in densification_postfix before this test, which leaves
        # its screen-size prune inert; we keep the radii seen by the old rows
        radii = torch.where(fresh, 0.0, stats.max_radii.to(device)[src])
        prune |= radii > max_screen_size
        prune |= _max_scale(out["log_scales"], out["parents"], face_scales) \
            > BIG_WORLD_FRACTION * extent
    prune = _keep_one_per_triangle(prune, out["parents"], out["opacity_logits"])
    keep = ~prune
    src, fresh = src[keep], fresh[keep]
    new_state = _rebuild(state, {k: v[keep] for k, v in out.items()}, optimizer, src, fresh)
    stats.reset(src.numel())
    return DensifyResult(state=new_state, source=src, is_new=fresh, n_cloned=n_clone,
                         n_split=n_split, n_pruned=int(prune.sum()))


def reset_opacity(state: Mapping[str, Tensor], optimizer: torch.optim.Optimizer | None,
                  max_opacity: float = 0.01) -> dict[str, Tensor]:
    """3DGS's opacity reset: opacities clamped to at most ``max_opacity`` (in logit space:
    ``min(logit, logit(max_opacity))``), their Adam moments zeroed. Returns the new state
    (the other tensors are the same objects)."""
    n = _check_state(state, "reset_opacity")
    if not 0 < max_opacity < 1:
        raise ValueError(f"max_opacity must be in (0, 1), got {max_opacity}")
    old = state["opacity_logits"]
    cap = math.log(max_opacity / (1 - max_opacity))
    new = old.detach().clamp(max=cap).requires_grad_(old.requires_grad)
    rows = torch.arange(n, device=old.device)
    _swap_in_optimizer(optimizer, old, new, rows, torch.ones_like(rows, dtype=torch.bool))
    return {**state, "opacity_logits": new}
