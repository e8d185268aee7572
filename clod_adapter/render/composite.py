"""Per-pixel alpha compositing of projected 2D Gaussians (CPU).

Single-camera equivalent of gsplat 1.5.3 ``rasterize_to_pixels`` (classic
mode): the C++/OpenMP kernel (``csrc/composite.cpp``, built with the project's
other kernels by :mod:`clod_adapter.render.native`), or, when it cannot be built,
its pure-PyTorch reference twin
:func:`clod_adapter.render._torch_impl.rasterize_to_pixels_torch` (one-time
warning). Tests and benchmarks hold the two against each other with
:func:`use_impl` (:func:`clod_adapter.render.native.use_impl`: one switch for
every kernel, as gsplat's ``cuda/_torch_impl.py``); it is not a user option.

Rules (gsplat ``RasterizeToPixels3DGSFwd.cu``): pixel (x, y) centre is
(x + 0.5, y + 0.5); delta = mean - centre; sigma = 0.5 (a dx^2 + c dy^2) + b dx dy;
alpha = min(0.999, opacity * exp(-sigma)); a Gaussian is skipped when
sigma < 0 or alpha < 1/255; next_T = T (1 - alpha); when next_T <= 1e-4 the
pixel stops *without* adding that Gaussian; otherwise color += alpha T c and
T = next_T.  render_alphas = 1 - T_final, render_colors += T_final * bg.
"""
from __future__ import annotations

import contextlib
import os
import warnings
from typing import Optional, Tuple

import torch
from torch import Tensor

__all__ = [
    "rasterize_to_pixels",
    "cpp_extension_available",
    "deterministic_enabled",
    "deterministic_override",
    "set_deterministic",
    "simd_rows",
]

from ._torch_impl import ALPHA_THRESHOLD, MAX_ALPHA, TRANSMITTANCE_THRESHOLD, rasterize_to_pixels_torch  # noqa: F401

from .native import available as _available, error as _error, impl as _impl, load as _load, wanted as _wanted
from .native import use_impl  # noqa: F401  (one switch for every kernel and its twin)

_WARNED = False


def cpp_extension_available() -> bool:
    """True when the C++ compositor builds/loads on this machine."""
    return _available()


#: None: follow the ``CLOD_DETERMINISTIC`` environment variable; True/False: override it.
_DETERMINISTIC: Optional[bool] = None


def set_deterministic(flag: Optional[bool]) -> None:
    """Force the C++ backward's deterministic mode on or off (None: follow the environment).

    Deterministic mode gives each per-thread gradient buffer a fixed set of tiles (static
    schedule, increasing tile order) and reduces the buffers in a fixed order, so gradients
    are bit-identical from run to run for a given thread count (``torch.get_num_threads()``).
    The default dynamic schedule balances load better but its float sums vary in the last
    bits. The forward and the PyTorch twin are deterministic either way."""
    global _DETERMINISTIC
    _DETERMINISTIC = None if flag is None else bool(flag)


def deterministic_override() -> Optional[bool]:
    """What :func:`set_deterministic` last set (None: the environment decides), to restore it."""
    return _DETERMINISTIC


def deterministic_enabled() -> bool:
    """True when :func:`set_deterministic` or ``CLOD_DETERMINISTIC`` (any value but empty,
    0, false, no, off) asks for the deterministic backward."""
    if _DETERMINISTIC is not None:
        return _DETERMINISTIC
    v = os.environ.get("CLOD_DETERMINISTIC", "").strip().lower()
    return v not in ("", "0", "false", "no", "off")


@contextlib.contextmanager
def simd_rows(on: bool):
    """Within the block the C++ compositor runs its vector rows (``on``, the default where GCC built
    it for an x86-64 CPU with AVX2 and FMA and their exp matches this process's ``expf``) or its
    scalar rows only, their
    twin: the two give bit-identical results (``csrc/composite_simd.cpp``). Yields whether the
    vector rows run. For tests and benchmarks; not a user option.

    Raises:
        RuntimeError: the C++ compositor did not build (:func:`cpp_extension_available`)."""
    ext = _load()
    if ext is None:
        raise RuntimeError(f"the C++ compositor did not build: {_error()!r}")
    prev = bool(ext.composite_simd(-1))
    try:
        yield bool(ext.composite_simd(1 if on else 0))
    finally:
        ext.composite_simd(1 if prev else 0)


def _num_threads() -> int:
    return max(1, torch.get_num_threads())


def _prep(means2d, conics, colors, opacities, isect_offsets, flatten_ids, backgrounds):
    dtype = means2d.dtype
    means2d = means2d.contiguous()
    conics = conics.to(dtype).contiguous()
    colors = colors.to(dtype).contiguous()
    opacities = opacities.to(dtype).reshape(-1).contiguous()
    offsets = isect_offsets.to(torch.int64).contiguous()
    ids = flatten_ids.to(torch.int64).reshape(-1).contiguous()
    if backgrounds is not None:
        backgrounds = backgrounds.to(dtype).reshape(-1).contiguous()
    return means2d, conics, colors, opacities, offsets, ids, backgrounds


class _CompositeCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, backgrounds,
                width, height, tile_size, offsets, ids, with_state=True):
        ext = _load()
        # with_state False (nothing will ask for gradients): the per-pixel T and last index the
        # backward reads are not written (a third of the per-pixel output)
        out_col, out_alpha, T_final, last_ids = ext.forward(
            means2d, conics, colors, opacities, backgrounds,
            int(width), int(height), int(tile_size), offsets, ids, _num_threads(), bool(with_state))
        ctx.dims = (int(width), int(height), int(tile_size))
        ctx.has_bg = backgrounds is not None
        ctx.save_for_backward(means2d, conics, colors, opacities,
                              backgrounds if backgrounds is not None else torch.empty(0),
                              offsets, ids, T_final, last_ids)
        return out_col, out_alpha

    @staticmethod
    def backward(ctx, v_col, v_alpha):
        (means2d, conics, colors, opacities, bg, offsets, ids,
         T_final, last_ids) = ctx.saved_tensors
        width, height, tile_size = ctx.dims
        bg_opt = bg if ctx.has_bg else None
        if v_col is None:
            v_col = torch.zeros(height, width, colors.shape[1], dtype=means2d.dtype)
        ext = _load()
        g_means, g_conics, g_colors, g_opac = ext.backward(
            means2d, conics, colors, opacities, bg_opt,
            width, height, tile_size, offsets, ids, T_final, last_ids,
            v_col.contiguous(), None if v_alpha is None else v_alpha.contiguous(),
            _num_threads(), deterministic_enabled())
        g_bg = None
        if ctx.has_bg and ctx.needs_input_grad[4]:
            g_bg = (v_col * T_final.unsqueeze(-1)).sum(dim=(0, 1))
        return (g_means, g_conics, g_colors, g_opac, g_bg,
                None, None, None, None, None, None)


def _rasterize_cpp(means2d, conics, colors, opacities, width, height, tile_size,
                   isect_offsets, flatten_ids, backgrounds):
    m, c, col, op, off, ids, bg = _prep(means2d, conics, colors, opacities,
                                        isect_offsets, flatten_ids, backgrounds)
    with_state = torch.is_grad_enabled() and any(x is not None and x.requires_grad for x in (m, c, col, op, bg))
    return _CompositeCpp.apply(m, c, col, op, bg, width, height, tile_size, off, ids, with_state)


# ----------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------
def rasterize_to_pixels(
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
) -> Tuple[Tensor, Tensor]:
    """Composite sorted per-tile Gaussian lists into an image (the C++ compositor, or its twin
    where it cannot be built).

    Args:
        means2d: [N, 2] pixel-space centres.  conics: [N, 3] (a, b, c) of the
        inverse 2D covariance.  colors: [N, D].  opacities: [N].
        width, height, tile_size: image and tile size in pixels.
        isect_offsets: [tile_height, tile_width] start of each tile's list in
        ``flatten_ids``.  flatten_ids: [M] Gaussian ids, front to back per tile.
        backgrounds: optional [D].

    Returns:
        render_colors [H, W, D], render_alphas [H, W, 1].
    """
    global _WARNED
    th = (int(height) + int(tile_size) - 1) // int(tile_size)
    tw = (int(width) + int(tile_size) - 1) // int(tile_size)
    if tuple(isect_offsets.shape[-2:]) != (th, tw):
        raise ValueError(
            f"isect_offsets has shape {tuple(isect_offsets.shape)}, expected ({th}, {tw})")
    if means2d.dtype not in (torch.float32, torch.float64):
        raise TypeError("means2d must be float32 or float64")
    use_cpp = _wanted(means2d.device.type == "cpu")
    if not use_cpp and _impl() == "auto" and _error() is not None and not _WARNED:
        _WARNED = True
        warnings.warn(
            "clod_adapter: C++ compositor unavailable "
            f"({_error()!r}); falling back to the slower PyTorch twin.",
            RuntimeWarning, stacklevel=2)
    if use_cpp:
        return _rasterize_cpp(means2d, conics, colors, opacities, width, height,
                              tile_size, isect_offsets, flatten_ids, backgrounds)
    return rasterize_to_pixels_torch(means2d, conics, colors, opacities, width, height,
                                     tile_size, isect_offsets, flatten_ids, backgrounds)
