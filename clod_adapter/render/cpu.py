"""CPU rasterization front end with gsplat 1.5.3 ``rasterization`` semantics
(``packed=False``, ``rasterize_mode="classic"``, pinhole cameras, no compensation).

Pipeline per camera: :func:`project_visible` (EWA projection + culling) -> SH colours for the
visible Gaussians (``clamp_min(sh + 0.5, 0)``) -> tile binning on the visible Gaussians
-> the per-pixel compositor ``clod_adapter.render.composite.rasterize_to_pixels``.
Only visible Gaussians (radii > 0) reach the compositor, so the cost follows what is on screen.
"""
from __future__ import annotations

import math
from typing import Any, Dict, Optional, Tuple

import torch
from torch import Tensor

from .composite import rasterize_to_pixels
from .projection import project_visible
from .sh import spherical_harmonics
from .tiles import isect_offset_encode, isect_tiles

__all__ = ["rasterization_cpu", "rasterize_projected", "sh_colors", "sh_colors_rows"]


class _ShColors(torch.autograd.Function):
    """``csrc/sh_colors.cpp``'s forward and backward as one autograd node (the gradients of the
    means and the coefficients; the camera centre is a constant)."""

    @staticmethod
    def forward(ctx, means: Tensor, coeffs: Tensor, campos: list, degree: int) -> Tensor:
        from .native import load

        ctx.save_for_backward(means, coeffs)
        ctx.campos, ctx.degree = campos, degree
        return load().sh_colors(means, coeffs, campos, degree)

    @staticmethod
    def backward(ctx, v_colors: Tensor):
        from .native import load

        means, coeffs = ctx.saved_tensors
        v_means, v_coeffs = load().sh_colors_backward(means, coeffs, ctx.campos, ctx.degree, v_colors)
        return (v_means if ctx.needs_input_grad[0] else None, v_coeffs if ctx.needs_input_grad[1] else None,
                None, None)


def sh_colors(sh_degree: int, means: Tensor, coeffs: Tensor, campos: Tensor) -> Tensor:
    """[V, 3] colours of SH coefficients ``coeffs`` [V, K, 3] seen from ``campos`` [3] (the
    direction ``means - campos``; ``means`` [V, 3], world units), gsplat's ``clamp_min(sh + 0.5,
    0)``, in the dtype of ``means``. Where the C++ kernels run
    (:func:`clod_adapter.render.native.wanted`) and ``campos`` needs no gradient, one pass of
    ``csrc/sh_colors.cpp`` each way (the backward gives the means' and the coefficients'
    gradients); else this torch form (its twin, equal to float rounding: ``tests/test_sh.py``).

    Raises:
        ValueError: ``sh_degree`` outside 0..3 or more than ``coeffs`` holds (K < (degree + 1)^2),
            or ``coeffs`` not [V, K, 3].
    """
    from .native import load, wanted

    if not 0 <= int(sh_degree) <= 3 or coeffs.ndim != 3 or coeffs.shape[-1] != 3 or \
            coeffs.shape[1] < (int(sh_degree) + 1) ** 2:
        raise ValueError(f"SH degree {sh_degree} needs [V, >= {(int(sh_degree) + 1) ** 2}, 3] coefficients, "
                         f"got {tuple(coeffs.shape)}")
    if (not (torch.is_grad_enabled() and campos.requires_grad)
            and means.dtype in (torch.float32, torch.float64) and coeffs.dtype == means.dtype
            and means.device.type == "cpu" and coeffs.device.type == "cpu" and wanted(True)):
        centre = [float(v) for v in campos.detach().to(means.dtype).tolist()]
        if torch.is_grad_enabled() and (means.requires_grad or coeffs.requires_grad):
            return _ShColors.apply(means, coeffs, centre, int(sh_degree))
        return load().sh_colors(means, coeffs, centre, int(sh_degree))
    col = spherical_harmonics(sh_degree, means - campos, coeffs)
    return torch.clamp_min(col + 0.5, 0.0)


def sh_colors_rows(sh_degree: int, means: Tensor, sh0: Tensor, shN: Tensor, ids: Tensor, campos: Tensor) -> Tensor:
    """[V, 3] :func:`sh_colors` of the rows ``ids`` [V] int64 of a model whose SH is stored as
    ``sh0`` [N, 1, 3] and ``shN`` [N, K-1, 3] (``means`` [N, 3], ``campos`` [3]): where the C++
    kernels run and nothing records autograd, each row's coefficients read in place
    (``csrc/sh_colors.cpp``), no [V, K, 3] gather; else :func:`sh_colors` of the gathered rows, its
    twin (``tests/test_sh.py``). Raises ValueError as :func:`sh_colors`; a row outside ``[0, N)``:
    RuntimeError (C++) or IndexError (torch)."""
    from .native import load, no_grad_cpu

    if (0 <= int(sh_degree) <= 3 and shN.ndim == 3 and (int(sh_degree) + 1) ** 2 <= sh0.shape[1] + shN.shape[1] <= 16
            and not (torch.is_grad_enabled() and campos.requires_grad) and no_grad_cpu(means, sh0, shN)):
        centre = [float(v) for v in campos.detach().to(means.dtype).tolist()]
        return load().sh_colors_rows(means, sh0, shN, ids.to(torch.int64), centre, int(sh_degree))
    coeffs = torch.cat([sh0.index_select(0, ids), shN.index_select(0, ids)], dim=1)
    return sh_colors(sh_degree, means.index_select(0, ids), coeffs, campos)


def rasterize_projected(proj, colors: Tensor, opacities: Tensor, width: int, height: int,
                        tile_size: int = 16, background: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Tile binning and compositing of an already projected set (one camera).

    Args:
        proj: :class:`clod_adapter.render.projection.VisibleProjection` of V Gaussians.
        colors: [V, D] features (e.g. :func:`sh_colors`), opacities: [V], aligned with ``proj``.
        background: [D] or None.

    Returns:
        (colors [H, W, D], alphas [H, W, 1], isect_offsets [th, tw] int32, flatten_ids [M] int64).
    """
    tile_width = math.ceil(width / tile_size)
    tile_height = math.ceil(height / tile_size)
    _, isect_ids, flatten_ids = isect_tiles(proj.means2d, proj.radii, proj.depths, tile_size,
                                            tile_width, tile_height)
    offsets = isect_offset_encode(isect_ids, tile_width, tile_height)
    rc, ra = rasterize_to_pixels(proj.means2d, proj.conics, colors, opacities, width, height, tile_size, offsets,
                                 flatten_ids, background)
    return rc, ra, offsets, flatten_ids


def rasterization_cpu(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    tile_size: int = 16,
    backgrounds: Optional[Tensor] = None,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Render C pinhole cameras on the CPU, gsplat.rasterization semantics.

    Args:
        means [N, 3], quats [N, 4] (wxyz, unnormalised), scales [N, 3] (activated),
        opacities [N] (activated).
        colors: [N, D] (or [C, N, D]) precomputed features when ``sh_degree`` is None,
            else [N, K, 3] SH coefficients with K >= (sh_degree + 1)^2.
        viewmats [C, 4, 4] world-to-camera, Ks [C, 3, 3].
        backgrounds: [C, D] or None.

    Returns:
        render_colors [C, H, W, D], render_alphas [C, H, W, 1], meta dict (see module docs:
        radii [C, N, 2], means2d [C, N, 2] (non-leaf; call ``retain_grad()`` on it before
        backward to read 2D mean gradients), depths [C, N], conics [C, N, 3], opacities [C, N],
        tile_width, tile_height, tile_size, isect_offsets [C, th, tw], flatten_ids (list of
        per-camera [M_c] int64, indices into the visible set ``visible_ids[c]``),
        visible_ids (list of [V_c] int64), width, height, n_visible [C], n_cameras).
    """
    N = means.shape[0]
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must be [C, 4, 4], got {tuple(viewmats.shape)}")
    C = viewmats.shape[0]
    if tuple(Ks.shape) != (C, 3, 3):
        raise ValueError(f"Ks must be [{C}, 3, 3], got {tuple(Ks.shape)}")
    if tuple(opacities.shape) != (N,):
        raise ValueError(f"opacities must be [{N}], got {tuple(opacities.shape)}")
    if sh_degree is None:
        if colors.ndim == 2 and colors.shape[0] == N:
            per_cam_colors = False
        elif colors.ndim == 3 and colors.shape[:2] == (C, N):
            per_cam_colors = True
        else:
            raise ValueError(f"colors must be [N, D] or [C, N, D] without sh_degree, got {tuple(colors.shape)}")
        D = colors.shape[-1]
    else:
        if colors.ndim != 3 or colors.shape[0] != N or colors.shape[2] != 3:
            raise ValueError(f"SH colors must be [N, K, 3], got {tuple(colors.shape)}")
        if not 0 <= sh_degree <= 3 or (sh_degree + 1) ** 2 > colors.shape[1]:
            raise ValueError(f"sh_degree {sh_degree} incompatible with K={colors.shape[1]}")
        D = 3
    if backgrounds is not None and tuple(backgrounds.shape) != (C, D):
        raise ValueError(f"backgrounds must be [{C}, {D}], got {tuple(backgrounds.shape)}")

    dt = means.dtype
    dev = means.device
    tile_width = math.ceil(width / tile_size)
    tile_height = math.ceil(height / tile_size)

    if sh_degree is not None:
        campos = torch.linalg.inv(viewmats.detach().to(dt))[:, :3, 3]  # [C, 3]

    # project every camera first so meta["means2d"] is one tensor upstream of the compositor
    projs = []
    for c in range(C):
        projs.append(project_visible(means, quats, scales, opacities, viewmats[c], Ks[c],
                                     width, height, eps2d, near_plane, far_plane, radius_clip))
    means2d_full = torch.stack([
        torch.zeros(N, 2, dtype=dt, device=dev).index_copy(0, p.ids, p.means2d) for p in projs
    ])  # [C, N, 2]

    out_colors, out_alphas = [], []
    radii_full = torch.zeros(C, N, 2, dtype=torch.int32, device=dev)
    depths_l, conics_l, offsets_l, flat_l, n_vis = [], [], [], [], []
    for c, p in enumerate(projs):
        ids = p.ids
        radii_full[c, ids] = p.radii
        p = p._replace(means2d=means2d_full[c].index_select(0, ids))
        op = opacities.index_select(0, ids)
        if sh_degree is None:
            col = (colors[c] if per_cam_colors else colors).index_select(0, ids)
        else:
            col = sh_colors(sh_degree, means.index_select(0, ids), colors.index_select(0, ids), campos[c])
        bg = backgrounds[c] if backgrounds is not None else None
        rc, ra, offsets, flatten_ids = rasterize_projected(p, col, op, width, height, tile_size, bg)
        out_colors.append(rc)
        out_alphas.append(ra)
        depths_l.append(torch.zeros(N, dtype=dt, device=dev).index_copy(0, ids, p.depths.detach()))
        conics_l.append(torch.zeros(N, 3, dtype=dt, device=dev).index_copy(0, ids, p.conics.detach()))
        offsets_l.append(offsets)
        flat_l.append(flatten_ids)
        n_vis.append(ids.numel())

    render_colors = torch.stack(out_colors)
    render_alphas = torch.stack(out_alphas)
    meta: Dict[str, Any] = {
        "radii": radii_full,
        "means2d": means2d_full,
        "depths": torch.stack(depths_l) if C else torch.zeros(0, N, dtype=dt),
        "conics": torch.stack(conics_l) if C else torch.zeros(0, N, 3, dtype=dt),
        "opacities": opacities.detach()[None].expand(C, N),
        "tile_width": tile_width,
        "tile_height": tile_height,
        "tile_size": tile_size,
        "isect_offsets": torch.stack(offsets_l) if C else torch.zeros(0, tile_height, tile_width, dtype=torch.int32),
        "flatten_ids": flat_l,
        "visible_ids": [p.ids for p in projs],
        "width": width,
        "height": height,
        "n_cameras": C,
        "n_visible": torch.tensor(n_vis, dtype=torch.int64),
    }
    return render_colors, render_alphas, meta
