"""Reference rasterizer in pure PyTorch: tile binning and front-to-back compositing.

Simple and obviously correct rather than fast; differentiable by autograd, device-agnostic.
Every other backend is tested against it. Conventions (gsplat's ``rasterize_to_pixels``):

* tiles of 16 x 16 px. A Gaussian with radius ``r`` belongs to tiles ``floor((m - r) / 16)``
  up to (excluding) ``ceil((m + r) / 16)`` in x and y, clamped to the image (gsplat's
  ``isect_tiles``); each tile's list is sorted by depth (``rasterize`` passes the float64
  ``projection.depth_key``, as to every backend; ties: lower index first);
* pixel ``(j, i)`` is sampled at ``(j + 0.5, i + 0.5)``; ``sigma = 0.5 d^T Conic d``,
  ``alpha = min(0.99, opacity * exp(-sigma))``; splats with ``sigma < 0`` or
  ``alpha < 1/255`` are skipped;
* front to back, ``T`` starts at 1; a splat whose ``T * (1 - alpha) <= 1e-4`` ends the pixel
  without being added; ``colour = sum_i alpha_i T_i c_i + T_final * background``,
  ``alpha_out = 1 - T_final``, ``depth_acc = sum_i alpha_i T_i z_i``.

Tiles are evaluated densely (every pixel of a tile against every Gaussian of its list), a chunk
of tiles at a time. With gradients enabled each chunk is checkpointed (recomputed in the
backward pass), so memory stays bounded by one chunk.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .contract import ALPHA_MAX, ALPHA_MIN, MAX_TILE_PAIRS, T_MIN, TILE_SIZE
from .cost import check_pairs

__all__ = ["isect_tiles", "pack_features", "rasterize_to_pixels"]

_CHUNK_ELEMS = 1 << 21  # pixels x list entries evaluated at once


def isect_tiles(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int,
                tile_size: int = TILE_SIZE,
                max_pairs: int | None = MAX_TILE_PAIRS) -> tuple[Tensor, Tensor]:
    """Tile lists: ``offsets [n_tiles + 1]`` (int64) and ``ids [n_pairs]`` (int64) such that tile
    ``t`` (row-major, ``ceil(W / 16)`` per row) holds Gaussians ``ids[offsets[t]:offsets[t+1]]``
    in front-to-back order. ``n_pairs`` is ``cost.tile_pairs(...).sum()``; more than
    ``max_pairs`` (None: ``MAX_TILE_PAIRS``) raise ``RenderTooExpensive`` before any list is
    allocated."""
    device = means2d.device
    tw, th = -(-width // tile_size), -(-height // tile_size)
    with torch.no_grad():
        # a non-finite mean would make a tile range of garbage: not drawn (as the cpu kernels)
        vis = torch.nonzero((radii > 0) & torch.isfinite(means2d).all(-1)).squeeze(1)  # [V]
        m = means2d[vis].double()  # [V, 2]; float64 so the tile range is exact
        r = radii[vis].double()[:, None]  # [V, 1]
        lo = torch.floor((m - r) / tile_size)
        hi = torch.ceil((m + r) / tile_size)
        lim = torch.tensor([tw, th], dtype=m.dtype, device=device)
        lo = torch.minimum(lo.clamp_min(0), lim).long()
        hi = torch.minimum(hi.clamp_min(0), lim).long()
        nx, ny = (hi - lo).unbind(-1)  # [V]
        counts = nx * ny  # [V]
        check_pairs(int(counts.sum()), max_pairs, width, height)  # count first, then allocate
        gid = torch.repeat_interleave(vis, counts)  # [P]
        local = torch.arange(gid.numel(), device=device) - torch.repeat_interleave(
            torch.cumsum(counts, 0) - counts, counts)  # [P] index within its Gaussian's box
        rep_nx = torch.repeat_interleave(nx, counts).clamp_min(1)
        tx = torch.repeat_interleave(lo[:, 0], counts) + local % rep_nx
        ty = torch.repeat_interleave(lo[:, 1], counts) + local // rep_nx
        tile = ty * tw + tx  # [P]
        n = depths.numel()
        rank = torch.empty(n, dtype=torch.long, device=device)
        rank[torch.sort(depths.detach(), stable=True).indices] = torch.arange(n, device=device)
        order = torch.argsort(tile * n + rank[gid])  # keys are unique
        ids = gid[order]
        tile_counts = torch.bincount(tile, minlength=tw * th)
        offsets = torch.zeros(tw * th + 1, dtype=torch.long, device=device)
        offsets[1:] = torch.cumsum(tile_counts, 0)
    return offsets, ids


def _composite(pix: Tensor, pmask: Tensor, ids: Tensor, lmask: Tensor, means2d: Tensor,
               conics: Tensor, opacities: Tensor, feats: Tensor) -> tuple[Tensor, Tensor]:
    """Dense compositing of a chunk of tiles.

    pix [T, P, 2] pixel centres, pmask [T, P], ids [T, L] list entries (padding masked by
    lmask [T, L]), feats [N, C] -> (features [T, P, C], final transmittance [T, P]).
    """
    mean = means2d[ids]  # [T, L, 2]
    con = conics[ids]  # [T, L, 3]
    d = pix[:, :, None, :] - mean[:, None, :, :]  # [T, P, L, 2]
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = (con[..., k][:, None, :] for k in range(3))  # [T, 1, L]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy  # [T, P, L]
    alpha = torch.clamp(opacities[ids][:, None, :] * torch.exp(-sigma), max=ALPHA_MAX)
    ok = (sigma >= 0) & (alpha >= ALPHA_MIN) & lmask[:, None, :] & pmask[:, :, None]
    alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    T_incl = torch.cumprod(one_minus, dim=-1)  # T after each splat
    T_excl = torch.cat([torch.ones_like(T_incl[..., :1]), T_incl[..., :-1]], dim=-1)
    alive = torch.cumsum((T_incl <= T_MIN).to(torch.int32), dim=-1) == 0  # before the stop
    w = alpha * T_excl * alive  # [T, P, L]
    out = torch.einsum("tpl,tlc->tpc", w, feats[ids])  # [T, P, C]
    T_final = torch.where(alive, one_minus, torch.ones_like(one_minus)).prod(dim=-1)  # [T, P]
    return out, T_final


def pack_features(colors: Tensor | None, depths: Tensor, with_depth: bool, n: int,
                  like: Tensor) -> tuple[Tensor, int]:
    """Colours and (when asked) depth as one per-Gaussian feature block, composited together.

    -> features [N, C'], the number of colour channels C.
    """
    feats = [] if colors is None else [colors]
    if with_depth:
        feats.append(depths[:, None])
    n_col = 0 if colors is None else colors.shape[1]
    return (torch.cat(feats, dim=1) if feats else like.new_zeros(n, 0)), n_col


def rasterize_to_pixels(
    means2d: Tensor,     # [N, 2]
    conics: Tensor,      # [N, 3]
    colors: Tensor | None,  # [N, C] or None (no colour channels)
    opacities: Tensor,   # [N]
    depths: Tensor,      # [N] camera z: the sort key, and accumulated if with_depth
    radii: Tensor,       # [N] int, 0 = culled
    width: int,
    height: int,
    background: Tensor | None = None,  # [C]
    with_depth: bool = False,
    tile_size: int = TILE_SIZE,
    sort_keys: Tensor | None = None,  # [N] front-to-back key (projection.depth_key); None: depths
    max_pairs: int | None = MAX_TILE_PAIRS,  # RenderTooExpensive past it (isect_tiles)
) -> tuple[Tensor | None, Tensor, Tensor | None]:
    """Composite the projected Gaussians -> ``(colors [H, W, C] | None, alphas [H, W],
    depth_acc [H, W] | None)``; ``depth_acc = sum_i w_i z_i`` (divide by alpha for the
    expected depth)."""
    device, dtype = means2d.device, means2d.dtype
    n = means2d.shape[0]
    feats, n_col = pack_features(colors, depths, with_depth, n, means2d)  # [N, C']
    keys = depths if sort_keys is None else sort_keys
    offsets, ids = isect_tiles(means2d, radii, keys, width, height, tile_size, max_pairs)

    tw, th = -(-width // tile_size), -(-height // tile_size)
    n_tiles, tp = tw * th, tile_size * tile_size
    ly, lx = torch.meshgrid(torch.arange(tile_size, device=device),
                            torch.arange(tile_size, device=device), indexing="ij")
    lx, ly = lx.reshape(-1), ly.reshape(-1)  # [P]
    tiles = torch.arange(n_tiles, device=device)
    px = (tiles % tw)[:, None] * tile_size + lx  # [n_tiles, P]
    py = (tiles // tw)[:, None] * tile_size + ly
    pmask_all = (px < width) & (py < height)
    pix_all = torch.stack([px, py], dim=-1).to(dtype) + 0.5  # [n_tiles, P, 2]

    lens = (offsets[1:] - offsets[:-1]).tolist()
    outs, Ts = [], []
    start = 0
    while start < n_tiles:  # greedy chunks of tiles under the element budget
        stop, lmax = start + 1, lens[start]
        while stop < n_tiles and (stop + 1 - start) * max(lmax, lens[stop]) * tp <= _CHUNK_ELEMS:
            lmax = max(lmax, lens[stop])
            stop += 1
        nt = stop - start
        if lmax == 0:
            outs.append(feats.new_zeros(nt, tp, feats.shape[1]))
            Ts.append(feats.new_ones(nt, tp))
            start = stop
            continue
        j = torch.arange(lmax, device=device)
        first = offsets[start:stop, None]  # [nt, 1]
        lmask = first + j < offsets[start + 1:stop + 1, None]  # [nt, L]
        idx = ids[torch.where(lmask, first + j, torch.zeros_like(first + j))]  # [nt, L]
        args = (pix_all[start:stop], pmask_all[start:stop], idx, lmask, means2d, conics,
                opacities, feats)
        if torch.is_grad_enabled() and any(t.requires_grad for t in args[4:]):
            out, T = checkpoint(_composite, *args, use_reentrant=False)
        else:
            out, T = _composite(*args)
        outs.append(out)
        Ts.append(T)
        start = stop

    # tile-major rows -> image rows
    out = torch.cat(outs).reshape(n_tiles * tp, -1)  # [n_tiles * P, C']
    T = torch.cat(Ts).reshape(-1)
    pix_id = (py * width + px).reshape(-1)
    keep = pmask_all.reshape(-1)
    perm = torch.empty(height * width, dtype=torch.long, device=device)
    perm[pix_id[keep]] = torch.nonzero(keep).squeeze(1)
    out, T = out[perm], T[perm]  # [H * W, C'], [H * W]

    rgb = depth = None
    if n_col:
        rgb = out[:, :n_col]
        if background is not None:
            rgb = rgb + T[:, None] * background.to(dtype)
        rgb = rgb.reshape(height, width, n_col)
    if with_depth:
        depth = out[:, n_col].reshape(height, width)
    return rgb, (1.0 - T).reshape(height, width), depth
