"""Thin wrapper around ``gsplat.rasterization`` (gsplat 1.5.3, CUDA), same arguments and
return triple as :func:`clod_adapter.render.cpu.rasterization_cpu`. gsplat is imported lazily."""
from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import torch
from torch import Tensor

__all__ = ["gsplat_available", "gsplat_unavailable_reason", "rasterization_gsplat"]


def gsplat_unavailable_reason() -> Optional[str]:
    """None when gsplat can be used, else a human-readable reason."""
    if not torch.cuda.is_available():
        return "CUDA is not available (torch.cuda.is_available() is False)"
    try:
        import gsplat  # noqa: F401
    except Exception as e:  # ImportError or a broken CUDA build
        return f"gsplat cannot be imported ({type(e).__name__}: {e}); install clod-adapter[gpu]"
    return None


def gsplat_available() -> bool:
    """True when CUDA is available and gsplat imports."""
    return gsplat_unavailable_reason() is None


def rasterization_gsplat(
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
    """``gsplat.rasterization`` (gsplat 1.5.3, CUDA) with our conventions fixed: unpacked,
    classic mode, RGB. Shapes as :func:`clod_adapter.render.rasterization`: means [N, 3],
    quats [N, 4] wxyz, activated scales [N, 3] and opacities [N], colors [N, D] or SH [N, K, 3],
    viewmats [C, 4, 4], Ks [C, 3, 3] (pixels); returns colours [C, H, W, D], alphas [C, H, W, 1]
    and gsplat's meta plus ``n_visible`` [C].

    Raises:
        RuntimeError: no CUDA device or gsplat does not import (the message says which).
    """
    reason = gsplat_unavailable_reason()
    if reason is not None:
        raise RuntimeError(f"gsplat backend unavailable: {reason}")
    from gsplat import rasterization

    render_colors, render_alphas, meta = rasterization(
        means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
        viewmats=viewmats, Ks=Ks, width=width, height=height,
        near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d,
        sh_degree=sh_degree, packed=False, tile_size=tile_size, backgrounds=backgrounds,
        render_mode="RGB", rasterize_mode="classic", absgrad=False, sparse_grad=False,
    )
    meta = dict(meta)
    radii = meta.get("radii")
    if radii is not None:
        vis = (radii > 0).all(dim=-1) if radii.ndim == 3 else radii > 0
        meta["n_visible"] = vis.sum(dim=-1).cpu()
    return render_colors, render_alphas, meta
