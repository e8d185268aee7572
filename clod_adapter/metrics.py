"""Image quality metrics, in the forms the 3DGS literature reports.

* PSNR over all pixels and channels, images in [0, 1].
* SSIM as in the official 3DGS ``utils/loss_utils.ssim``: 11x11 Gaussian window (sigma 1.5),
  zero-padded "same" convolution per channel, C1 = 0.01^2, C2 = 0.03^2, mean over the map.
  It equals scikit-image's ``structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1)`` on the interior pixels (tests hold the two together).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_C1 = 0.01 ** 2
_C2 = 0.03 ** 2


#: the cap of ``psnr(..., cap=True)``: identical images score this instead of +inf.
PSNR_CAP_DB = 100.0


def psnr(img: Tensor, gt: Tensor, cap: bool = False) -> float:
    """PSNR in dB of ``img`` against ``gt`` (both [H, W, 3] or [..., H, W, C], values in [0, 1]).

    ``img`` is clamped to [0, 1] first, as 3DGS evaluation does. Identical images give +inf, or
    :data:`PSNR_CAP_DB` with ``cap`` (keeps differences between PSNRs finite).
    """
    mse = torch.mean((img.detach().clamp(0, 1).float() - gt.to(img.device).float()) ** 2).item()
    if cap:
        return min(PSNR_CAP_DB, -10.0 * math.log10(max(mse, 1e-10)))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def _window(dtype: torch.dtype, device: torch.device) -> Tensor:
    """The 1-D Gaussian of the SSIM window [SSIM_WINDOW] (the 11x11 window is its outer product)."""
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    g = torch.exp(-(x ** 2) / (2 * SSIM_SIGMA ** 2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def ssim_map(img: Tensor, gt: Tensor) -> Tensor:
    """Per-pixel SSIM map [H, W, C] of two [H, W, C] images (3DGS form, differentiable in img).

    The 11x11 window is applied as two 1-D passes (rows, then columns; the same zero-padded
    "same" filter, 22 taps a pixel instead of 121) over the five filtered images at once."""
    if img.shape != gt.shape or img.ndim != 3:
        raise ValueError(f"ssim expects two [H, W, C] images of one shape, got {tuple(img.shape)} and {tuple(gt.shape)}")
    c = img.shape[-1]
    x = img.permute(2, 0, 1)[None]
    y = gt.to(img.dtype).permute(2, 0, 1)[None]
    g = _window(img.dtype, img.device)
    pad = SSIM_WINDOW // 2
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [1, 5C, H, W]
    k = stack.shape[1]
    stack = F.conv2d(stack, g.view(1, 1, 1, -1).expand(k, 1, 1, SSIM_WINDOW), padding=(0, pad), groups=k)
    stack = F.conv2d(stack, g.view(1, 1, -1, 1).expand(k, 1, SSIM_WINDOW, 1), padding=(pad, 0), groups=k)
    mu_x, mu_y, exx, eyy, exy = stack.split(c, dim=1)
    sxx = exx - mu_x ** 2
    syy = eyy - mu_y ** 2
    sxy = exy - mu_x * mu_y
    num = (2 * mu_x * mu_y + _C1) * (2 * sxy + _C2)
    den = (mu_x ** 2 + mu_y ** 2 + _C1) * (sxx + syy + _C2)
    return (num / den)[0].permute(1, 2, 0)


def ssim(img: Tensor, gt: Tensor) -> Tensor:
    """Mean SSIM (scalar tensor, differentiable) of two [H, W, C] images in [0, 1] (3DGS form)."""
    return ssim_map(img, gt).mean()
