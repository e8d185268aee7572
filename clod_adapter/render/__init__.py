"""Rendering: gsplat-1.5.3-compatible rasterization on CPU (torch autograd front end plus a
per-pixel compositor) or on CUDA through gsplat."""
from .dispatch import rasterization
from .gsplat_backend import gsplat_available
from .projection import fully_fused_projection
from .sh import spherical_harmonics

__all__ = ["rasterization", "fully_fused_projection", "spherical_harmonics", "gsplat_available"]
