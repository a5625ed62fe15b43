"""The rasterizer contract's numbers: every backend imports them from here, none writes its own.

The conventions are gsplat's / 3DGS's (shared/ARCHITECTURE.md, "The rasterizer contract"); the
guards below them keep absurd but finite inputs from overflowing float32 / int32 in any
backend. Plain Python numbers: numba kernels read them as compile-time constants.
"""

from __future__ import annotations

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "EIG_FLOOR",
    "EPS2D",
    "FAR_PLANE",
    "FRUSTUM_MARGIN",
    "MAX_BOUND_PX",
    "MAX_SCREEN_PX",
    "MAX_SIGMA_PX",
    "MAX_TILE_PAIRS",
    "NEAR_PLANE",
    "RADIUS_SIGMAS",
    "SH_COEFF_MAX",
    "TILE_SIZE",
    "T_MIN",
]

# ---- projection
NEAR_PLANE = 0.01  # Gaussians at camera z <= this are culled (their Jacobian explodes)
FAR_PLANE = 1e10  # and at z >= this (gsplat's default far plane)
EPS2D = 0.3  # low-pass dilation added to the 2D covariance, px^2 (a splat covers ~1 px)
# the Jacobian is evaluated with x/z, y/z clamped to the frustum widened by this fraction of the
# half-FOV tangents on each side, so off-screen Gaussians do not blow up
FRUSTUM_MARGIN = 0.3
RADIUS_SIGMAS = 3.0  # screen radius of a splat in standard deviations (its tile extent)
# floor of b^2 - det under the square root of the largest 2D eigenvalue (gsplat's), so a
# round splat still gets a radius
EIG_FLOOR = 0.01

# ---- compositing
TILE_SIZE = 16  # px; splats are binned and depth-sorted per tile of this side
ALPHA_MAX = 0.99  # alpha clamp (3DGS), so no single splat makes a pixel opaque
ALPHA_MIN = 1.0 / 255.0  # splats below this alpha at a pixel are skipped (invisible in 8 bits)
T_MIN = 1e-4  # a pixel is done when its transmittance would fall to this or below

# ---- render cost (avatar_core/render/cost.py)
# Most (Gaussian, tile) pairs one frame composites when its request names no bound: past it
# the quality budget drops the least important splats until the pairs fit (a compositor
# handed longer lists directly refuses them: RenderTooExpensive). A pair is a slot in the
# tile lists (cpu: 4 B, and 40 B more in the backward pass; the torch reference ~100 B) and
# up to a tile of compositing (measured on the cpu backend, one thread: 0.1 us for splats
# that cover their tiles at once, 1.5-3 us for semi-transparent ones), so this bounds a
# frame's memory (cpu: 64 MiB of lists, 640 MiB more for gradients) and time whatever the
# Gaussians. Legitimate frames stay far below: the 16k-Gaussian synthetic avatar needs 0.1 M
# pairs at 1920 x 1080 (0.3 M in a close-up); a trainer-capped 200k-Gaussian avatar a few
# million while its splats are still large early in training. An in-range "render bomb"
# (16k splats of log-scale 6) needs 134 M there. Servers bound frames much tighter (setting
# max_tile_pairs).
MAX_TILE_PAIRS = 1 << 24  # 16,777,216

# ---- guards against absurd but finite inputs
# Wider splats are culled: over any image they are a uniform veil, and beyond this float32
# conics lose their precision; the 3-sigma radius stays far below int32's range.
MAX_SIGMA_PX = 1e7
# Projected means farther out cannot reach an image (radius <= 3 MAX_SIGMA_PX): culled, so
# pixel offsets stay finite in float32.
MAX_SCREEN_PX = 1e9
# Upper bound of the 2D standard deviation (f / z (1 + lim) max scale) above which a Gaussian
# is culled before its covariance is formed: keeps cov2d and its determinant inside float32.
MAX_BOUND_PX = 1e9
# SH coefficients are clamped to +-this when colouring: a sum of huge ones overflows float32
# (Inf, or NaN from Inf - Inf) and a NaN colour poisons every pixel it is weighed into.
# Trained coefficients are a few units at most.
SH_COEFF_MAX = 1e6
