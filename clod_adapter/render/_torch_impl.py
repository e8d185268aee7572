"""Pure-PyTorch reference twin of the C++ compositor (:mod:`clod_adapter.render.composite`),
as gsplat keeps ``cuda/_torch_impl.py``: the same rules (see that module's docstring), written
with torch ops so autograd gives its backward. Tests hold the C++ compositor to it; it is also
the fallback where the extension cannot be built."""
from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import Tensor

__all__ = ["rasterize_to_pixels_torch", "MAX_ALPHA", "ALPHA_THRESHOLD", "TRANSMITTANCE_THRESHOLD"]

#: gsplat 1.5.3's compositing rules (RasterizeToPixels3DGSFwd.cu), shared with the C++ compositor
MAX_ALPHA = 0.999
ALPHA_THRESHOLD = 1.0 / 255.0
TRANSMITTANCE_THRESHOLD = 1e-4


# ----------------------------------------------------------------------------
def _composite_tiles(mx, my, ca, cb, cc, op, col, valid, px, py):
    """Composite a batch of B tiles.

    mx..op: [B, L]; col: [B, L, D]; valid: [B, L] bool (padding mask);
    px, py: [B, P] pixel centres.  Returns colors [B, P, D] and T_final [B, P].
    """
    dx = mx[:, None, :] - px[:, :, None]  # [B, P, L]
    dy = my[:, None, :] - py[:, :, None]
    sigma = 0.5 * (ca[:, None, :] * dx * dx + cc[:, None, :] * dy * dy) \
        + cb[:, None, :] * dx * dy
    alpha = torch.clamp(op[:, None, :] * torch.exp(-sigma), max=MAX_ALPHA)
    with torch.no_grad():
        keep = valid[:, None, :] & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
        a_det = torch.where(keep, alpha, torch.zeros((), dtype=alpha.dtype))
        # inclusive transmittance; monotone non-increasing, so "stop at the
        # first next_T <= 1e-4 and exclude it and everything behind" is exactly
        # the mask T_incl > 1e-4.
        T_incl = torch.cumprod(1.0 - a_det, dim=-1)
        keep &= T_incl > TRANSMITTANCE_THRESHOLD
    alpha = torch.where(keep, alpha, torch.zeros((), dtype=alpha.dtype))
    one_minus = 1.0 - alpha
    T_excl = torch.cumprod(
        torch.cat([torch.ones_like(one_minus[..., :1]), one_minus[..., :-1]], dim=-1),
        dim=-1)
    w = alpha * T_excl
    out = torch.bmm(w, col)  # [B, P, D]
    T_final = T_excl[..., -1] * one_minus[..., -1]
    return out, T_final


def rasterize_to_pixels_torch(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    width: int,
    height: int,
    tile_size: int,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    backgrounds: Optional[Tensor] = None,
    *,
    max_batch_elems: int = 1 << 21,
) -> Tuple[Tensor, Tensor]:
    """Vectorised PyTorch compositor (autograd through torch ops).

    Tiles are grouped by list length into batches of about ``max_batch_elems``
    pixel x Gaussian pairs; when gradients are needed each batch is
    recomputed in the backward (activation checkpointing) to bound memory.
    """
    dtype = means2d.dtype
    device = means2d.device
    D = colors.shape[-1]
    th, tw = int(isect_offsets.shape[0]), int(isect_offsets.shape[1])
    ntiles = th * tw
    ts = int(tile_size)
    P = ts * ts
    ids = flatten_ids.reshape(-1).to(torch.int64)
    M = ids.numel()
    starts = isect_offsets.reshape(-1).to(torch.int64)
    ends = torch.cat([starts[1:], torch.tensor([M], dtype=torch.int64, device=device)])
    starts = starts.clamp(0, M)
    ends = ends.clamp(0, M)
    counts = (ends - starts).clamp_min(0)
    opac = opacities.reshape(-1)

    # pixel centres of every tile: [ntiles, P]
    ly = torch.arange(ts, device=device).repeat_interleave(ts)
    lx = torch.arange(ts, device=device).repeat(ts)
    tyy = torch.arange(th, device=device).repeat_interleave(tw)
    txx = torch.arange(tw, device=device).repeat(th)
    pix_x = (txx[:, None] * ts + lx[None, :])
    pix_y = (tyy[:, None] * ts + ly[None, :])
    px_all = pix_x.to(dtype) + 0.5
    py_all = pix_y.to(dtype) + 0.5

    need_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, colors, opacities))

    order = torch.argsort(counts, stable=True)
    counts_sorted = counts[order].tolist()
    pieces_col = []
    pieces_T = []
    pieces_tiles = []
    zero_tiles = [int(t) for t, c in zip(order.tolist(), counts_sorted) if c == 0]
    if zero_tiles:
        zt = torch.tensor(zero_tiles, dtype=torch.int64, device=device)
        pieces_tiles.append(zt)
        pieces_col.append(torch.zeros(len(zero_tiles), P, D, dtype=dtype, device=device))
        pieces_T.append(torch.ones(len(zero_tiles), P, dtype=dtype, device=device))
    i = len(zero_tiles)
    order_l = order.tolist()
    while i < ntiles:
        # grow the batch while (count of tiles) * P * (max length) fits
        j = i + 1
        while j < ntiles and (j + 1 - i) * P * counts_sorted[j] <= max_batch_elems:
            j += 1
        tiles = torch.tensor(order_l[i:j], dtype=torch.int64, device=device)
        L = counts_sorted[j - 1]
        ar = torch.arange(L, device=device)
        pos = starts[tiles][:, None] + ar[None, :]
        valid = ar[None, :] < counts[tiles][:, None]
        g = ids[pos.clamp(max=max(M - 1, 0))]
        g = torch.where(valid, g, torch.zeros_like(g))
        args = (means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2],
                opac[g], colors[g], valid, px_all[tiles], py_all[tiles])
        if need_grad:
            from torch.utils.checkpoint import checkpoint
            out, T = checkpoint(_composite_tiles, *args, use_reentrant=False)
        else:
            out, T = _composite_tiles(*args)
        pieces_tiles.append(tiles)
        pieces_col.append(out)
        pieces_T.append(T)
        i = j

    tiles_cat = torch.cat(pieces_tiles)
    inv = torch.empty_like(tiles_cat)
    inv[tiles_cat] = torch.arange(ntiles, device=device)
    col_t = torch.cat(pieces_col)[inv]  # [ntiles, P, D]
    T_t = torch.cat(pieces_T)[inv]  # [ntiles, P]

    img = col_t.reshape(th, tw, ts, ts, D).permute(0, 2, 1, 3, 4).reshape(th * ts, tw * ts, D)
    T_img = T_t.reshape(th, tw, ts, ts).permute(0, 2, 1, 3).reshape(th * ts, tw * ts)
    img = img[:height, :width]
    T_img = T_img[:height, :width]
    if backgrounds is not None:
        img = img + T_img[..., None] * backgrounds.reshape(1, 1, D).to(dtype)
    return img, (1.0 - T_img)[..., None]
