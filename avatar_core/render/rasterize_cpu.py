"""Fast CPU rasterizer: numba kernels for tile binning, compositing and its backward pass.

Renders the picture of :mod:`avatar_core.render.rasterize_torch` (same tile lists, same
order, same per-pixel rules), so the two agree to float rounding. What makes it fast:

* **Binning** keeps gsplat's tile range (the radius box) but drops the tiles in which the
  splat cannot reach ``alpha >= 1/255`` at any pixel centre: ``sigma`` is minimised exactly
  over the tile's rectangle of pixel centres and compared with the splat's cut-off
  ``sigma_max = log(255 * opacity)``. Those tiles would composite nothing from that splat, so
  the picture is unchanged while the lists shrink. Lists come from one stable radix sort by
  depth and a stable, parallel counting sort by tile.
* **Splat-major, SIMD compositing** inside a tile: splats are visited front to back; for
  each, only the rows its ``sigma <= sigma_max`` ellipse reaches are visited, and a row (16
  pixels, or the 8 the ellipse's x-extent needs) is one branch-free, vectorized pass with a
  polynomial ``exp``. Each pixel still sees its splats in depth order, so the result equals
  gsplat's per-pixel loop; finished rows are skipped and a tile stops when all its pixels
  are done (``T`` would fall to ``1e-4``).
* **Backward** replays each pixel back to front from its final transmittance, skipping the
  splats at and after the one that ended it (gsplat's ``rasterize_to_pixels`` backward), with
  the same loop interchange. Each (tile, splat) pair owns one gradient row, so threads never
  collide; a final pass sums the rows per Gaussian.

Kernels run in parallel over tiles (``prange``), interleaved so both cores get a mix of busy
and empty tiles. :class:`RasterizeCPU` wraps them in a ``torch.autograd.Function`` so that
projection and colour stay in torch and autograd chains through; without gradients,
:func:`composite_np` is called directly on numpy arrays (see ``rasterize``).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from .contract import ALPHA_MAX, ALPHA_MIN, MAX_TILE_PAIRS, T_MIN, TILE_SIZE
from .cost import check_pairs, clamp_int, tile_box
from .rasterize_torch import pack_features

__all__ = ["RasterizeCPU", "bin_tiles", "composite_np", "pairs_allocated",
           "rasterize_to_pixels"]

_TS = TILE_SIZE
_SMAX_REL = 1e-4  # widen the sigma cut-off used for culling / spans: never drops a pixel
_SMAX_ABS = 1e-4


# ---------------------------------------------------------------------------------------------
# binning
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _tile_reaches(tx, ty, mx, my, a, b, c, smax, width, height):
    """Whether min over the tile's pixel centres of sigma can be <= smax (exact min over the
    rectangle of centres, which contains every centre)."""
    x0 = tx * _TS + 0.5
    x1 = min(tx * _TS + _TS, width) - 0.5
    y0 = ty * _TS + 0.5
    y1 = min(ty * _TS + _TS, height) - 0.5
    dx0, dx1, dy0, dy1 = x0 - mx, x1 - mx, y0 - my, y1 - my
    if dx0 <= 0.0 <= dx1 and dy0 <= 0.0 <= dy1:
        return True
    best = np.inf
    for dx in (dx0, dx1):  # vertical edges: minimise over dy
        dy = min(max(-b * dx / c, dy0), dy1)
        best = min(best, 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
    for dy in (dy0, dy1):  # horizontal edges: minimise over dx
        dx = min(max(-b * dy / a, dx0), dx1)
        best = min(best, 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
    return best <= smax


@njit(cache=True, inline="always")
def _drawable(mx, my, a, b, c):
    """Finite mean and a positive definite conic: what every extent below divides by. The
    projection emits nothing else; direct callers' degenerate splats are skipped."""
    return (math.isfinite(mx) and math.isfinite(my) and math.isfinite(b) and a > 0.0
            and c > 0.0 and math.isfinite(a) and math.isfinite(c) and a * c - b * b > 0.0)


_MASK_TILES = 64  # tile boxes up to this size keep their hits in a bit mask


@njit(parallel=True, cache=True)
def _find_hits(means2d, conics, opacities, radii, width, height, smax, boxes, masks, counts):
    """Per Gaussian: sigma cut-off, tile box, and which tiles of the box it reaches (bit
    ``(ty - y0) * box_width + (tx - x0)`` of ``masks``; boxes of more than 64 tiles are
    re-tested when the lists are built)."""
    tw, th = (width + _TS - 1) // _TS, (height + _TS - 1) // _TS
    for g in prange(means2d.shape[0]):
        counts[g] = 0
        op = float(opacities[g])
        mx, my = float(means2d[g, 0]), float(means2d[g, 1])
        a, b, c = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2])
        boxes[g, 0] = boxes[g, 1] = boxes[g, 2] = boxes[g, 3] = 0
        masks[g] = 0
        if radii[g] <= 0 or not (ALPHA_MIN <= op < np.inf) or not _drawable(mx, my, a, b, c):
            smax[g] = -1.0
            continue
        s = math.log(op / ALPHA_MIN)
        s = s + _SMAX_REL * s + _SMAX_ABS
        smax[g] = s
        x0, x1, y0, y1 = tile_box(mx, my, float(radii[g]), tw, th)
        boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3] = x0, x1, y0, y1
        bits = np.uint64(0)
        n = 0
        bit = 0
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                if _tile_reaches(tx, ty, mx, my, a, b, c, s, width, height):
                    n += 1
                    if bit < _MASK_TILES:
                        bits |= np.uint64(1) << np.uint64(bit)
                bit += 1
        masks[g] = bits
        counts[g] = n


@njit(cache=True, inline="always")
def _reaches(g, bit, tx, ty, boxes, masks, means2d, conics, smax, width, height):
    """Tile (tx, ty), bit ``bit`` of g's box: from the mask, or re-tested for big boxes."""
    if (boxes[g, 1] - boxes[g, 0]) * (boxes[g, 3] - boxes[g, 2]) <= _MASK_TILES:
        return (masks[g] >> np.uint64(bit)) & np.uint64(1) != 0
    return _tile_reaches(tx, ty, float(means2d[g, 0]), float(means2d[g, 1]),
                         float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2]),
                         smax[g], width, height)


@njit(parallel=True, cache=True)
def _fill_lists(order, boxes, masks, means2d, conics, smax, width, height, n_blocks, offsets,
                ids):
    """Stable parallel counting sort of the (tile, Gaussian) pairs by tile, Gaussians taken
    in depth ``order``: each block of the order counts its pairs per tile, a prefix sum over
    (tile, block) gives each block its slots, then each block writes its pairs."""
    tw = (width + _TS - 1) // _TS
    n_tiles = offsets.shape[0] - 1
    hist = np.zeros((n_blocks, n_tiles), np.int64)
    n = order.shape[0]
    for blk in prange(n_blocks):
        for k in range(blk * n // n_blocks, (blk + 1) * n // n_blocks):
            g = order[k]
            x0, x1, y0, y1 = boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3]
            bit = 0
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    if _reaches(g, bit, tx, ty, boxes, masks, means2d, conics, smax, width,
                                height):
                        hist[blk, ty * tw + tx] += 1
                    bit += 1
    total = 0
    offsets[0] = 0
    for t in range(n_tiles):  # hist becomes each block's first slot in each tile
        for blk in range(n_blocks):
            total, hist[blk, t] = total + hist[blk, t], total
        offsets[t + 1] = total
    for blk in prange(n_blocks):
        for k in range(blk * n // n_blocks, (blk + 1) * n // n_blocks):
            g = order[k]
            x0, x1, y0, y1 = boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3]
            bit = 0
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    if _reaches(g, bit, tx, ty, boxes, masks, means2d, conics, smax, width,
                                height):
                        t = ty * tw + tx
                        ids[hist[blk, t]] = g
                        hist[blk, t] += 1
                    bit += 1


_SIGN64 = np.uint64(1) << np.uint64(63)


@njit(cache=True)
def _depth_order(depths, counts):
    """Indices of the Gaussians with tile pairs, front to back by the float64 key
    ``depths``; ties keep index order (as torch's stable sort). An LSD radix sort (6 x 11
    bits) of the bit patterns mapped to sort like the values: negatives all bits flipped,
    others the sign bit."""
    bits = depths.view(np.uint64)
    idx = np.nonzero(counts > 0)[0].astype(np.int32)
    keys = np.empty(bits.shape[0], np.uint64)
    for i in idx:
        keys[i] = ~bits[i] if bits[i] & _SIGN64 else bits[i] | _SIGN64
    tmp = np.empty_like(idx)
    hist = np.zeros(2048, np.int64)
    mask = np.uint64(2047)
    for shift in range(0, 64, 11):
        sh = np.uint64(shift)
        hist[:] = 0
        for i in idx:
            hist[(keys[i] >> sh) & mask] += 1
        total = 0
        for d in range(2048):
            total, hist[d] = total + hist[d], total
        for i in idx:
            d = (keys[i] >> sh) & mask
            tmp[hist[d]] = i
            hist[d] += 1
        idx, tmp = tmp, idx
    return idx


def bin_tiles(means2d: np.ndarray, conics: np.ndarray, opacities: np.ndarray,
              depths: np.ndarray, radii: np.ndarray, width: int, height: int,
              max_pairs: int | None = MAX_TILE_PAIRS):
    """Per-tile front-to-back lists -> ``(offsets [n_tiles + 1], ids [n_pairs], smax [N])``
    (int64, int32, float64); only tiles the splat can reach with ``alpha >= 1/255``.
    ``depths``: the sort key, float64 (``projection.depth_key``). The pairs are counted
    first: more than ``max_pairs`` (None: ``MAX_TILE_PAIRS``) raise ``RenderTooExpensive``
    before the lists are allocated. The tile tests themselves cost one step per pair of the
    radius boxes, which ``rasterize`` has already bounded (cost.tile_pairs_np)."""
    n = means2d.shape[0]
    n_tiles = ((width + _TS - 1) // _TS) * ((height + _TS - 1) // _TS)
    counts = np.empty(n, np.int64)
    smax = np.empty(n, np.float64)
    boxes = np.empty((n, 4), np.int32)
    masks = np.empty(n, np.uint64)
    _find_hits(means2d, conics, opacities, radii, width, height, smax, boxes, masks, counts)
    n_pairs = int(counts.sum())
    check_pairs(n_pairs, max_pairs, width, height)  # count first, allocate after
    order = _depth_order(np.ascontiguousarray(depths, np.float64), counts)
    offsets = np.empty(n_tiles + 1, np.int64)
    ids = np.empty(n_pairs, np.int32)
    n_blocks = 4 * max(1, numba.get_num_threads())
    _fill_lists(order, boxes, masks, means2d, conics, smax, width, height, n_blocks, offsets,
                ids)
    return offsets, ids, smax


def _tile_order(n_tiles: int) -> np.ndarray:
    """Tiles interleaved across threads (prange splits its range into contiguous blocks)."""
    nt = max(1, numba.get_num_threads())
    t = np.arange(n_tiles, dtype=np.int64)
    return np.argsort(t % nt, kind="stable")


# ---------------------------------------------------------------------------------------------
# compositing: a tile row (16 px) is one SIMD vector; every loop over `l` below vectorizes
# ---------------------------------------------------------------------------------------------

_F = np.float32
_ZERO, _HALF, _ONE = _F(0.0), _F(0.5), _F(1.0)
_AMAX, _AMIN, _TMIN = _F(ALPHA_MAX), _F(ALPHA_MIN), _F(T_MIN)
_LOG2E = _F(1.4426950408889634)
_LN2_HI, _LN2_LO = _F(0.693145751953125), _F(1.428606765330187e-06)
_E0, _E1, _E2, _E3 = _F(1.0), _F(1.0), _F(1.0 / 2), _F(1.0 / 6)
_E4, _E5, _E6, _E7 = _F(1.0 / 24), _F(1.0 / 120), _F(1.0 / 720), _F(1.0 / 5040)
_S_CAP = 87.0  # exp(-87) is near the smallest normal float32


@njit(cache=True, inline="always")
def _exp_neg(s):
    """exp(-s) in float32 for s in [0, 87], branch-free so that it vectorizes (libm's exp
    does not): s = n ln2 - r, exp(-s) = 2^-n * exp(r), |r| <= ln2 / 2, Taylor degree 7.
    Relative error ~1e-7, like expf."""
    n = np.floor(s * _LOG2E + _HALF)
    r = (n * _LN2_HI - s) + n * _LN2_LO
    p = ((((((_E7 * r + _E6) * r + _E5) * r + _E4) * r + _E3) * r + _E2) * r + _E1) * r + _E0
    scale = np.int32((np.int32(127) - np.int32(n)) << np.int32(23)).view(np.float32)  # 2^-n
    return p * scale


@njit(cache=True, inline="always")
def _rows(my, a, c, detc, s, ty0, ty1):
    """Rows [r0, r1] (clamped to [ty0, ty1)) whose centres can lie inside sigma <= s."""
    ey = math.sqrt(max(2.0 * s * a / detc, 0.0))  # y half-extent: sqrt(2 s cov_yy)
    # clamped as floats (see clamp_int); an empty range stays empty
    return (clamp_int(np.ceil(my - ey - 0.5), ty0, ty1),
            clamp_int(np.floor(my + ey - 0.5), ty0 - 1, ty1 - 1))


@njit(cache=True, inline="always")
def _splat(means2d, conics, opacities, smax, g):
    """float32 parameters of splat g, and its sigma cap: beyond smax + 1 the alpha is below
    1/255 whatever exp returns, so capping sigma there changes nothing."""
    s = smax[g]
    return (means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2],
            opacities[g], s, _F(min(s + 1.0, _S_CAP)))


_LIVE = np.int32(2**31 - 1)  # stop index of a pixel still compositing
_REFRESH = 8  # recount the live rows of a tile every this many splats


@njit(cache=True, inline="always")
def _pixel_centres(tx0, lanes):
    pxc = np.empty(lanes, np.float32)
    for l in range(lanes):
        pxc[l] = _F(tx0 + l) + _HALF
    return pxc


@njit(cache=True, inline="always")
def _lane_window(mx, c, detc, s, tx0):
    """First lane and lane count (8 or 16) covering the columns where the splat's
    ``sigma <= s`` ellipse meets the tile: small splats take half a row, half the work.
    The per-pixel alpha test stays exact either way."""
    ex = math.sqrt(max(2.0 * s * c / detc, 0.0))  # x half-extent: sqrt(2 s cov_xx)
    lo = mx - ex - 0.5 - tx0  # lane of the left-most centre that can be inside
    hi = mx + ex - 0.5 - tx0
    half = _TS // 2
    if hi < half:
        return 0, half
    if lo > half - 1.0:
        return half, half
    return 0, _TS


@njit(parallel=True, cache=True)
def _forward_kernel(means2d, conics, opacities, feats, smax, offsets, ids, tiles, width,
                    height, background, out_feats, out_T, out_stop):
    """Composite every tile. feats [N, 4] (unused channels zero), out_feats [H, W, 4] (with
    background [4]), out_T [H, W] final transmittance, out_stop [H, W] index into ``ids`` of
    the splat that ended the pixel (``_LIVE`` if none did)."""
    tw = (width + _TS - 1) // _TS
    tp = _TS * _TS
    for k in prange(tiles.shape[0]):
        t = tiles[k]
        tx0, ty0 = (t % tw) * _TS, (t // tw) * _TS
        tx1, ty1 = min(tx0 + _TS, width), min(ty0 + _TS, height)
        if offsets[t] == offsets[t + 1]:  # empty tile: background, no scratch arrays
            for py in range(ty0, ty1):
                for px in range(tx0, tx1):
                    for ch in range(4):
                        out_feats[py, px, ch] = background[ch]
                    out_T[py, px] = 1.0
                    out_stop[py, px] = _LIVE
            continue
        T = np.ones(tp, np.float32)
        stop = np.full(tp, -1, np.int32)  # -1: outside the image, never composited
        for r in range(ty1 - ty0):
            stop[r * _TS:r * _TS + tx1 - tx0] = _LIVE
        acc0, acc1 = np.zeros(tp, np.float32), np.zeros(tp, np.float32)
        acc2, acc3 = np.zeros(tp, np.float32), np.zeros(tp, np.float32)
        pxc = _pixel_centres(tx0, _TS)
        row_live = np.zeros(_TS, np.bool_)
        row_live[:ty1 - ty0] = True
        first = offsets[t]
        for i in range(first, offsets[t + 1]):
            g = ids[i]
            mx, my, a, b, c, op, s, s_cap = _splat(means2d, conics, opacities, smax, g)
            f0, f1, f2, f3 = feats[g, 0], feats[g, 1], feats[g, 2], feats[g, 3]
            detc = float(a) * c - float(b) * b
            r0, r1 = _rows(float(my), float(a), float(c), detc, s, ty0, ty1)
            l0, nl = _lane_window(float(mx), float(c), detc, s, tx0)
            ul0, unl = np.uint64(l0), np.uint64(nl)
            ii = np.int32(i)
            for py in range(r0, r1 + 1):
                r = py - ty0
                if not row_live[r]:
                    continue
                dy = (_F(py) + _HALF) - my
                cdy2, bdy = c * dy * dy, b * dy
                base = np.uint64(r * _TS) + ul0
                # one SIMD pass over the lanes; branch-free so that LLVM vectorizes it
                # (unsigned indices: numba skips the negative-index wrap that blocks it;
                # a run-time trip count: a constant one gets unrolled into scalar code)
                for l in range(unl):
                    j = base + l
                    dx = pxc[ul0 + l] - mx
                    sigma = _HALF * (a * dx * dx + cdy2) + bdy * dx
                    alpha = min(_AMAX, op * _exp_neg(min(max(sigma, _ZERO), s_cap)))
                    Tj = T[j]
                    next_T = Tj * (_ONE - alpha)
                    ok = (stop[j] == _LIVE) & (sigma >= _ZERO) & (alpha >= _AMIN)
                    add = ok & (next_T > _TMIN)
                    w = alpha * Tj if add else _ZERO
                    acc0[j] += w * f0
                    acc1[j] += w * f1
                    acc2[j] += w * f2
                    acc3[j] += w * f3
                    T[j] = next_T if add else Tj
                    stop[j] = ii if ok & (next_T <= _TMIN) else stop[j]
            if (i - first) % _REFRESH == _REFRESH - 1:  # drop finished rows, maybe the tile
                live_rows = 0
                for r in range(ty1 - ty0):
                    live = False
                    for l in range(tx1 - tx0):
                        live |= stop[r * _TS + l] == _LIVE
                    row_live[r] = live
                    live_rows += live
                if live_rows == 0:
                    break
        for py in range(ty0, ty1):
            for px in range(tx0, tx1):
                j = (py - ty0) * _TS + px - tx0
                out_feats[py, px, 0] = acc0[j] + T[j] * background[0]
                out_feats[py, px, 1] = acc1[j] + T[j] * background[1]
                out_feats[py, px, 2] = acc2[j] + T[j] * background[2]
                out_feats[py, px, 3] = acc3[j] + T[j] * background[3]
                out_T[py, px] = T[j]
                out_stop[py, px] = stop[j]


@njit(parallel=True, cache=True)
def _backward_kernel(means2d, conics, opacities, feats, smax, offsets, ids, tiles, width,
                     height, background, out_T, out_stop, v_feats_out, v_alpha_out,
                     pair_grads):
    """pair_grads [n_pairs, 10]: per (tile, splat) pair, d loss / d (mean x, mean y, conic a,
    b, c, opacity, 4 features). Each pixel is replayed back to front from its final
    transmittance, skipping the splats at and after the one that ended it (gsplat's
    backward; splats between its last contribution and that one were skipped anyway)."""
    tw = (width + _TS - 1) // _TS
    tp = _TS * _TS
    for k in prange(tiles.shape[0]):
        t = tiles[k]
        start, end = offsets[t], offsets[t + 1]
        if start == end:
            continue
        tx0, ty0 = (t % tw) * _TS, (t // tw) * _TS
        tx1, ty1 = min(tx0 + _TS, width), min(ty0 + _TS, height)
        T = np.zeros(tp, np.float32)
        tfa = np.zeros(tp, np.float32)  # T_final * (v_alpha - background . v_color)
        stop = np.full(tp, -1, np.int32)
        v0, v1 = np.zeros(tp, np.float32), np.zeros(tp, np.float32)  # d loss / d feats
        v2, v3 = np.zeros(tp, np.float32), np.zeros(tp, np.float32)
        b0, b1 = np.zeros(tp, np.float32), np.zeros(tp, np.float32)  # composited behind
        b2, b3 = np.zeros(tp, np.float32), np.zeros(tp, np.float32)
        row_last = np.full(_TS, -1, np.int64)  # last splat to replay, per row
        for py in range(ty0, ty1):
            r = py - ty0
            for px in range(tx0, tx1):
                j = r * _TS + px - tx0
                T[j] = out_T[py, px]
                stop[j] = out_stop[py, px]
                row_last[r] = max(row_last[r], min(int(stop[j]), end) - 1)
                v0[j], v1[j] = v_feats_out[py, px, 0], v_feats_out[py, px, 1]
                v2[j], v3[j] = v_feats_out[py, px, 2], v_feats_out[py, px, 3]
                bg_dot = (background[0] * v0[j] + background[1] * v1[j]
                          + background[2] * v2[j] + background[3] * v3[j])
                tfa[j] = _F(out_T[py, px] * (v_alpha_out[py, px] - bg_dot))
        pxc = _pixel_centres(tx0, _TS)
        # per-lane partial sums, summed once per splat (a lane sum is not vectorizable):
        # rows 0-9 = d mean x, mean y, conic a, b, c, opacity, feats 0-3
        lane = np.zeros((10, _TS), np.float32)
        for i in range(row_last.max(), start - 1, -1):
            g = ids[i]
            mx, my, a, b, c, op, s, s_cap = _splat(means2d, conics, opacities, smax, g)
            f0, f1, f2, f3 = feats[g, 0], feats[g, 1], feats[g, 2], feats[g, 3]
            detc = float(a) * c - float(b) * b
            r0, r1 = _rows(float(my), float(a), float(c), detc, s, ty0, ty1)
            l0, nl = _lane_window(float(mx), float(c), detc, s, tx0)
            ul0, unl = np.uint64(l0), np.uint64(nl)
            lane[:, :] = _ZERO
            ii = np.int32(i)
            for py in range(r0, r1 + 1):
                r = py - ty0
                if row_last[r] < i:
                    continue
                dy = (_F(py) + _HALF) - my
                cdy2, bdy = c * dy * dy, b * dy
                base = np.uint64(r * _TS) + ul0
                for l in range(unl):  # un-composite splat i from each pixel (SIMD)
                    j = base + l
                    lj = ul0 + l
                    dx = pxc[lj] - mx
                    sigma = _HALF * (a * dx * dx + cdy2) + bdy * dx
                    vis = _exp_neg(min(max(sigma, _ZERO), s_cap))
                    alpha = min(_AMAX, op * vis)
                    ok = (ii < stop[j]) & (sigma >= _ZERO) & (alpha >= _AMIN)
                    ra = _ONE / (_ONE - alpha)
                    Tj = T[j] * ra  # transmittance in front of splat i
                    T[j] = Tj if ok else T[j]
                    fac = alpha * Tj if ok else _ZERO  # its weight at this pixel
                    v_alpha = (tfa[j] * ra
                               + (f0 * Tj - b0[j] * ra) * v0[j] + (f1 * Tj - b1[j] * ra) * v1[j]
                               + (f2 * Tj - b2[j] * ra) * v2[j] + (f3 * Tj - b3[j] * ra) * v3[j])
                    b0[j] += f0 * fac
                    b1[j] += f1 * fac
                    b2[j] += f2 * fac
                    b3[j] += f3 * fac
                    # d alpha -> d sigma -> conic, mean, opacity (none where alpha clamped)
                    v_op = vis * v_alpha if ok & (op * vis <= _AMAX) else _ZERO
                    v_sig = -op * v_op
                    lane[0, lj] -= v_sig * (a * dx + bdy)  # d sigma / d mean = -Conic d
                    lane[1, lj] -= v_sig * (b * dx + c * dy)
                    lane[2, lj] += _HALF * v_sig * dx * dx
                    lane[3, lj] += v_sig * dx * dy
                    lane[4, lj] += _HALF * v_sig * dy * dy
                    lane[5, lj] += v_op
                    lane[6, lj] += fac * v0[j]
                    lane[7, lj] += fac * v1[j]
                    lane[8, lj] += fac * v2[j]
                    lane[9, lj] += fac * v3[j]
            for q in range(10):
                tot = 0.0
                for l in range(_TS):
                    tot += lane[q, l]
                pair_grads[i, q] = tot


@njit(cache=True)
def _reduce_pairs(ids, pair_grads, grads):
    """grads [N, 6 + C] += pair_grads rows, by Gaussian."""
    for p in range(ids.shape[0]):
        g = ids[p]
        for k in range(pair_grads.shape[1]):
            grads[g, k] += pair_grads[p, k]


# ---------------------------------------------------------------------------------------------
# torch wrapper
# ---------------------------------------------------------------------------------------------

def _np32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


_MAX_FEATS = 4  # rgb + depth; the kernels carry four feature channels


def composite_np(means2d, conics, opacities, feats, depths, radii, width, height, background,
                 max_pairs: int | None = MAX_TILE_PAIRS):
    """numpy float32 in (feats [N, 4], background [4]; ``depths`` the float64 sort key) ->
    (feats image [H, W, 4] with background, final transmittance [H, W], the state the
    backward pass needs: :func:`pairs_allocated` reads its pair count). ``max_pairs``: see
    :func:`bin_tiles`."""
    offsets, ids, smax = bin_tiles(means2d, conics, opacities, depths, radii, width, height,
                                   max_pairs)
    tiles = _tile_order(offsets.shape[0] - 1)
    out = np.empty((height, width, _MAX_FEATS), np.float32)
    T = np.empty((height, width), np.float32)
    stop = np.empty((height, width), np.int32)
    _forward_kernel(means2d, conics, opacities, feats, smax, offsets, ids, tiles, width, height,
                    background, out, T, stop)
    state = (means2d, conics, opacities, feats, smax, offsets, ids, tiles, width, height,
             background, T, stop)
    return out, T, state


def pairs_allocated(state) -> int:
    """The (tile, Gaussian) pairs the tile lists of ``composite_np``'s ``state`` hold."""
    return int(state[6].shape[0])  # ids


class RasterizeCPU(torch.autograd.Function):
    """(means2d, conics, feats [N, C <= 4], opacities) -> (feats image [H, W, C] incl.
    background [C], alpha [H, W]); depths are only the sort key (append them to feats to
    accumulate them)."""

    @staticmethod
    def forward(ctx, means2d, conics, feats, opacities, depths, radii, width, height,
                background, max_pairs):
        n, nc = feats.shape
        m2, co, op = _np32(means2d), _np32(conics), _np32(opacities)
        fe = np.zeros((n, _MAX_FEATS), np.float32)
        fe[:, :nc] = feats.detach().cpu().numpy()
        bg = np.zeros(_MAX_FEATS)
        bg[:nc] = background.detach().cpu().double().numpy()
        rad = np.ascontiguousarray(radii.detach().cpu().numpy().astype(np.int32))
        keys = np.ascontiguousarray(depths.detach().cpu().double().numpy())
        out, T, state = composite_np(m2, co, op, fe, keys, rad, width, height, bg, max_pairs)
        ctx.state = state
        ctx.dtype = dtype = means2d.dtype
        ctx.nc = nc
        return torch.from_numpy(out[..., :nc]).to(dtype), torch.from_numpy(1.0 - T).to(dtype)

    @staticmethod
    def backward(ctx, v_out, v_alpha):
        m2, co, op, fe, smax, offsets, ids, tiles, width, height, bg, T, stop = ctx.state
        nc = ctx.nc
        v4 = np.zeros((height, width, _MAX_FEATS), np.float32)
        if v_out is not None:
            v4[..., :nc] = v_out.detach().cpu().numpy()
        v_alpha = np.zeros((height, width), np.float32) if v_alpha is None else _np32(v_alpha)
        pair_grads = np.empty((ids.shape[0], 6 + _MAX_FEATS), np.float32)
        pair_grads[:] = 0.0  # pairs behind finished pixels are never visited
        _backward_kernel(m2, co, op, fe, smax, offsets, ids, tiles, width, height, bg, T, stop,
                         v4, v_alpha, pair_grads)
        grads = np.zeros((m2.shape[0], 6 + _MAX_FEATS), np.float64)
        _reduce_pairs(ids, pair_grads, grads)
        g = torch.from_numpy(grads).to(ctx.dtype)
        return (g[:, 0:2], g[:, 2:5], g[:, 6:6 + nc], g[:, 5], None, None, None, None, None,
                None)


def rasterize_to_pixels(
    means2d: Tensor,     # [N, 2]
    conics: Tensor,      # [N, 3]
    colors: Tensor | None,  # [N, C] or None
    opacities: Tensor,   # [N]
    depths: Tensor,      # [N]
    radii: Tensor,       # [N] int, 0 = culled
    width: int,
    height: int,
    background: Tensor | None = None,  # [C]
    with_depth: bool = False,
    sort_keys: Tensor | None = None,  # [N] front-to-back key; None: depths
    max_pairs: int | None = MAX_TILE_PAIRS,  # RenderTooExpensive past it, before allocating
) -> tuple[Tensor | None, Tensor, Tensor | None]:
    """Same contract as :func:`avatar_core.render.rasterize_torch.rasterize_to_pixels`
    (float32 inside, float64 sort keys; outputs and gradients in the inputs' dtype)."""
    n = means2d.shape[0]
    feats, n_col = pack_features(colors, depths, with_depth, n, means2d)  # [N, C']
    if feats.shape[1] > _MAX_FEATS:
        raise ValueError(f"the cpu backend carries at most {_MAX_FEATS} channels (colour + "
                         f"depth), got {feats.shape[1]}")
    bg = torch.zeros(feats.shape[1], dtype=torch.float64)
    if background is not None and n_col:
        bg[:n_col] = background.detach().cpu().double()
    keys = depths if sort_keys is None else sort_keys
    out, alpha = RasterizeCPU.apply(means2d, conics, feats, opacities, keys, radii,
                                    int(width), int(height), bg, max_pairs)
    out, alpha = out.to(means2d.device), alpha.to(means2d.device)
    rgb = out[..., :n_col] if n_col else None
    depth = out[..., n_col] if with_depth else None
    return rgb, alpha, depth
