"""What every render starts with: the request and the Gaussians checked, the contract's opacity
range enforced, the camera size and SH degree the request asks for.

:func:`avatar_core.render.render_views` and its one-camera case
:func:`avatar_core.render.rasterize` both begin here, so every path (one camera or a batch, any
backend) accepts, rejects and normalises the same inputs.
"""

from __future__ import annotations

from .camera import Camera
from .projection import check_finite
from .types import OUTPUTS, GaussianSet, RenderRequest

__all__ = ["check_gaussians", "check_request", "clamp_opacities", "rendered_sh_degree",
           "sized_camera"]


def check_request(request: RenderRequest) -> None:
    """``ValueError`` for outputs outside ``OUTPUTS``, a bad budget, pair bound, SH degree or
    background."""
    outs = tuple(request.outputs)
    if not outs or any(o not in OUTPUTS for o in outs):
        raise ValueError(f"outputs must be a non-empty subset of {OUTPUTS}, got {outs!r}")
    budget = request.budget
    if budget is not None:
        if isinstance(budget, bool) or not isinstance(budget, (int, float)):
            raise ValueError(f"budget must be an int count or a float fraction, got {budget!r}")
        if isinstance(budget, int) and budget < 0:
            raise ValueError(f"budget count must be >= 0, got {budget}")
        if isinstance(budget, float) and not 0.0 < budget <= 1.0:
            raise ValueError(f"budget fraction must be in (0, 1], got {budget}")
    pairs = request.max_tile_pairs
    if pairs is not None and (isinstance(pairs, bool) or not isinstance(pairs, int)
                              or pairs < 0):
        raise ValueError(f"max_tile_pairs must be an int >= 0 or None, got {pairs!r}")
    if request.sh_degree is not None and not 0 <= request.sh_degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {request.sh_degree}")
    if len(request.background) != 3:
        raise ValueError(f"background must be an RGB triple, got {request.background!r}")


def check_gaussians(g: GaussianSet, finite: bool = True) -> None:
    """``ValueError`` for shapes other than :class:`GaussianSet`'s and, with ``finite``, for
    NaN/Inf values (a host round trip per tensor on CUDA)."""
    n = g.means.shape[0] if g.means.ndim == 2 else -1
    shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
    for name, shape in shapes.items():
        t = getattr(g, name)
        if tuple(t.shape) != shape:
            raise ValueError(f"gaussians.{name} must have shape {shape}, got {tuple(t.shape)}")
    if g.sh.ndim != 3 or g.sh.shape[0] != n or g.sh.shape[2] != 3 \
            or g.sh.shape[1] not in (1, 4, 9, 16):
        raise ValueError(f"gaussians.sh must be [N, K in (1, 4, 9, 16), 3], got "
                         f"{tuple(g.sh.shape)}")
    if finite:
        check_finite(means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities,
                     sh=g.sh)


def clamp_opacities(g: GaussianSet) -> GaussianSet:
    """The same Gaussians with opacities clamped to the contract's [0, 1]."""
    # a huge opacity times a vanishing Gaussian overflows the gradients (Inf * 0); the clamp's
    # gradient is 1 inside, so training is unaffected
    return GaussianSet(g.means, g.quats, g.scales, g.opacities.clamp(0.0, 1.0), g.sh)


def sized_camera(camera: Camera, request: RenderRequest) -> Camera:
    """``camera`` resized to the request's width and height (each None: the camera's)."""
    if request.width is None and request.height is None:
        return camera
    return camera.resized(request.width or camera.width, request.height or camera.height)


def rendered_sh_degree(g: GaussianSet, request: RenderRequest) -> int:
    """The SH degree to render: the request's, at most what the Gaussians carry."""
    if request.sh_degree is None:
        return g.sh_degree
    return min(request.sh_degree, g.sh_degree)
