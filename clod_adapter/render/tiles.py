"""Tile binning (gsplat 1.5.3 ``isect_tiles`` / ``isect_offset_encode``, single camera),
fully vectorised.

For each Gaussian with both radii > 0 the covered tile rectangle is (``IntersectTile.cu``)
``[floor(mx/ts - rx/ts), ceil(mx/ts + rx/ts))`` x ``[floor(my/ts - ry/ts), ceil(my/ts + ry/ts))``
clamped to ``[0, tile_width] x [0, tile_height]``. Every (Gaussian, tile) pair gets the key
``tile_id << 32 | float32 bits of depth`` (monotone for positive depths), and the pairs are
sorted by key: per tile, front to back.
"""
from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor

__all__ = ["isect_tiles", "isect_offset_encode", "tile_rects", "TILE_SIZE"]

#: gsplat 1.5.3's default tile size (pixels per tile side): what every level-of-detail render and
#: cost bins with
TILE_SIZE = 16


@torch.no_grad()
def tile_rects(means2d: Tensor, radii: Tensor, tile_size: int, tile_width: int,
               tile_height: int) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per-Gaussian tile rectangle (x0, y0 inclusive; x1, y1 exclusive), int64 [N] each.

    Gaussians with a zero radius get an empty rectangle.
    """
    m = means2d.detach().float()
    r = radii.float()
    ts = float(tile_size)
    tx = m[:, 0] / ts
    ty = m[:, 1] / ts
    trx = r[:, 0] / ts
    try_ = r[:, 1] / ts
    x0 = torch.floor(tx - trx).clamp_(0, tile_width).long()
    y0 = torch.floor(ty - try_).clamp_(0, tile_height).long()
    x1 = torch.ceil(tx + trx).clamp_(0, tile_width).long()
    y1 = torch.ceil(ty + try_).clamp_(0, tile_height).long()
    valid = (radii[:, 0] > 0) & (radii[:, 1] > 0)
    x1 = torch.where(valid, x1, x0)
    y1 = torch.where(valid, y1, y0)
    return x0, y0, x1, y1


@torch.no_grad()
def isect_tiles(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    tile_size: int,
    tile_width: int,
    tile_height: int,
) -> Tuple[Tensor, Tensor, Tensor]:
    """Gaussian/tile intersections for one camera.

    Args:
        means2d: [N, 2] projected means (pixels).
        radii: [N, 2] int32 per-axis radii (0 = culled).
        depths: [N] camera-space z (positive for visible Gaussians).
        tile_size: tile edge in pixels; tile_width/tile_height: number of tiles.

    Returns:
        tiles_per_gauss [N] int32, isect_ids [M] int64 (sorted; ``tile_id << 32 | depth bits``),
        flatten_ids [M] int64 (index of the Gaussian of each intersection).
    """
    dev = means2d.device
    n = means2d.shape[0]
    x0, y0, x1, y1 = tile_rects(means2d, radii, tile_size, tile_width, tile_height)
    w = x1 - x0
    counts = w * (y1 - y0)
    tiles_per_gauss = counts.to(torch.int32)
    if n == 0:
        e = torch.empty(0, dtype=torch.int64, device=dev)
        return tiles_per_gauss, e, e.clone()
    # only Gaussians with at least one tile
    nz = counts.nonzero().squeeze(1)
    c = counts.index_select(0, nz)
    total = int(c.sum())
    if total == 0:
        e = torch.empty(0, dtype=torch.int64, device=dev)
        return tiles_per_gauss, e, e.clone()

    depth_bits = depths.detach().to(torch.float32).contiguous().view(torch.int32)
    depth_key = depth_bits.index_select(0, nz).to(torch.int64) & 0xFFFFFFFF
    # per-Gaussian base key for its first tile, and its rect width
    wv = w.index_select(0, nz)
    x0v = x0.index_select(0, nz)
    y0v = y0.index_select(0, nz)

    starts = torch.cumsum(c, 0) - c  # [V]
    g = torch.repeat_interleave(torch.arange(nz.numel(), device=dev), c, output_size=total)  # [M]
    k = torch.arange(total, dtype=torch.int64, device=dev) - starts.index_select(0, g)
    wg = wv.index_select(0, g)
    ky = torch.div(k, wg, rounding_mode="floor")
    kx = k - ky * wg
    tile_id = (y0v.index_select(0, g) + ky) * tile_width + (x0v.index_select(0, g) + kx)
    keys = (tile_id << 32) | depth_key.index_select(0, g)
    isect_ids, order = torch.sort(keys)
    flatten_ids = nz.index_select(0, g.index_select(0, order))
    return tiles_per_gauss, isect_ids, flatten_ids


@torch.no_grad()
def isect_offset_encode(isect_ids: Tensor, tile_width: int, tile_height: int) -> Tensor:
    """[tile_height, tile_width] int32: start of each tile's list in the sorted intersections
    (empty tiles point at the next non-empty tile's start, or at M)."""
    n_tiles = tile_width * tile_height
    tid = isect_ids >> 32
    counts = torch.bincount(tid, minlength=n_tiles)[:n_tiles]
    offsets = torch.cumsum(counts, 0) - counts
    return offsets.to(torch.int32).view(tile_height, tile_width)
