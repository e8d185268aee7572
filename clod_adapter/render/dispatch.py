"""Backend dispatch: gsplat (CUDA) when the tensors live on CUDA and gsplat imports,
else the CPU rasterizer."""
from __future__ import annotations

from typing import Any, Dict, Literal, Optional, Tuple

from torch import Tensor

from .cpu import rasterization_cpu
from .gsplat_backend import gsplat_unavailable_reason, rasterization_gsplat

__all__ = ["rasterization", "resolve_backend", "Backend"]

#: rasteriser backends: gsplat for CUDA tensors ("auto"), or forced.
Backend = Literal["auto", "cpu", "gsplat"]
_BACKENDS = ("auto", "cpu", "gsplat")


def resolve_backend(backend: Backend, means: Tensor) -> Literal["cpu", "gsplat"]:
    """``"cpu"`` or ``"gsplat"`` for tensors like ``means``: gsplat for ``backend="gsplat"`` or
    for CUDA tensors with ``"auto"``, else the CPU rasteriser.

    Raises:
        ValueError: unknown backend.
        RuntimeError: gsplat asked for (or CUDA tensors) but gsplat or CUDA is missing; CPU
            asked for with CUDA tensors.
    """
    if backend not in _BACKENDS:
        raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
    on_cuda = means.is_cuda
    if backend == "gsplat" or (backend == "auto" and on_cuda):
        reason = gsplat_unavailable_reason()
        if reason is not None:
            raise RuntimeError(
                f"gsplat backend requested (backend={backend!r}, tensors on {means.device}) but {reason}. "
                "Move the tensors to the CPU or use backend='cpu'."
            )
        if not on_cuda:
            raise RuntimeError(f"gsplat backend needs CUDA tensors, got tensors on {means.device}")
        return "gsplat"
    if on_cuda:
        raise RuntimeError("backend='cpu' needs CPU tensors; got CUDA tensors (call .cpu()).")
    return "cpu"


def rasterization(
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
    backend: Backend = "auto",
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """gsplat.rasterization-compatible renderer (classic mode, unpacked, pinhole).

    backend: "auto" (gsplat if the tensors are on CUDA and gsplat imports, else CPU),
    "cpu", or "gsplat".

    Raises:
        RuntimeError: backend="gsplat" without CUDA/gsplat, backend="cpu" with CUDA tensors,
            or tensors on CUDA with backend="auto" but gsplat missing.
        ValueError: unknown backend.
    """
    kw = dict(near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d,
              sh_degree=sh_degree, tile_size=tile_size, backgrounds=backgrounds)
    args = (means, quats, scales, opacities, colors, viewmats, Ks, width, height)
    if resolve_backend(backend, means) == "gsplat":
        return rasterization_gsplat(*args, **kw)
    return rasterization_cpu(*args, **kw)
