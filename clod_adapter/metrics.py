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


def _blur(maps: Tensor) -> Tensor:
    """The SSIM window applied to [H, W, K] maps: the 11x11 Gaussian as two 1-D zero-padded "same"
    passes (rows, then columns; 22 taps a pixel instead of 121), each map on its own. It is its own
    adjoint (a symmetric kernel, zero padding), so :class:`_FusedSSIM`'s backward applies it again.
    float32 maps go through the convolution in channels-last layout, ~10x faster on CPU than
    channel-first for these depthwise passes (oneDNN); other dtypes channel-first (float64 has no
    fast channels-last path). Returns [H, W, K] of the dtype of ``maps``."""
    k = maps.shape[-1]
    g = _window(maps.dtype, maps.device)
    pad = SSIM_WINDOW // 2
    x = maps[None].permute(0, 3, 1, 2)  # [1, K, H, W], channels-last strides
    if maps.dtype != torch.float32 or maps.device.type != "cpu":
        x = x.contiguous()
    x = F.conv2d(x, g.view(1, 1, 1, -1).expand(k, 1, 1, SSIM_WINDOW), padding=(0, pad), groups=k)
    x = F.conv2d(x, g.view(1, 1, -1, 1).expand(k, 1, SSIM_WINDOW, 1), padding=(pad, 0), groups=k)
    return x[0].permute(1, 2, 0)


def _terms(img: Tensor, gt: Tensor) -> tuple:
    """The windowed moments and SSIM's four factors (all [H, W, C]): ``mu_x, mu_y, A1 = 2 mu_x mu_y
    + C1, A2 = 2 s_xy + C2, B1 = mu_x^2 + mu_y^2 + C1, B2 = s_xx + s_yy + C2``."""
    c = img.shape[-1]
    mu_x, mu_y, exx, eyy, exy = _blur(torch.cat([img, gt, img * img, gt * gt, img * gt], dim=-1)).split(c, dim=-1)
    a1 = 2 * mu_x * mu_y + _C1
    a2 = 2 * (exy - mu_x * mu_y) + _C2
    b1 = mu_x ** 2 + mu_y ** 2 + _C1
    b2 = (exx - mu_x ** 2) + (eyy - mu_y ** 2) + _C2
    return mu_x, mu_y, a1, a2, b1, b2


class _FusedSSIM(torch.autograd.Function):
    """SSIM map [H, W, C] of ``img`` against a constant ``gt`` with the closed-form gradient
    (as fused-ssim, Mallick et al. 2024, computes it on the GPU): with ``S = A1 A2 / (B1 B2)``
    and ``g`` the incoming gradient, ``dS/de_xy = 2 A1 / (B1 B2)``, ``dS/de_xx = -S / B2``,
    ``dS/dmu_x = 2 mu_y (A2 - A1) / (B1 B2) - 2 mu_x S (1/B1 - 1/B2)``, and
    ``d/dimg = blur(g dS/dmu_x) + 2 img blur(g dS/de_xx) + gt blur(g dS/de_xy)`` (the blur is
    self-adjoint). One blur of 3C maps in the backward instead of autograd's pass through five
    filtered images and a dozen elementwise nodes; :func:`_ssim_map_autograd` is its twin."""

    @staticmethod
    def forward(ctx, img: Tensor, gt: Tensor) -> Tensor:
        mu_x, mu_y, a1, a2, b1, b2 = _terms(img, gt)
        den = b1 * b2
        s = a1 * a2 / den
        ctx.save_for_backward(img, gt, mu_x, mu_y, a1, a2, b1, b2, s)
        return s

    @staticmethod
    def backward(ctx, grad: Tensor):
        img, gt, mu_x, mu_y, a1, a2, b1, b2, s = ctx.saved_tensors
        den = b1 * b2
        d_mu = (2 * mu_y * (a2 - a1) / den - 2 * mu_x * s * (1 / b1 - 1 / b2)) * grad
        d_xx = (-s / b2) * grad
        d_xy = (2 * a1 / den) * grad
        c = img.shape[-1]
        b_mu, b_xx, b_xy = _blur(torch.cat([d_mu, d_xx, d_xy], dim=-1)).split(c, dim=-1)
        return b_mu + 2 * img * b_xx + gt * b_xy, None


def _ssim_map_autograd(img: Tensor, gt: Tensor) -> Tensor:
    """:func:`ssim_map` through plain autograd (the twin :class:`_FusedSSIM` is tested against)."""
    _, _, a1, a2, b1, b2 = _terms(img, gt.to(img.dtype))
    return a1 * a2 / (b1 * b2)


def ssim_map(img: Tensor, gt: Tensor) -> Tensor:
    """Per-pixel SSIM map [H, W, C] of two [H, W, C] images (3DGS form, differentiable in ``img``;
    ``gt`` is a constant). The 11x11 window is applied as two 1-D passes (:func:`_blur`); the
    gradient is the closed form of :class:`_FusedSSIM`.

    Raises:
        ValueError: the images differ in shape or are not [H, W, C]."""
    if img.shape != gt.shape or img.ndim != 3:
        raise ValueError(f"ssim expects two [H, W, C] images of one shape, got {tuple(img.shape)} and {tuple(gt.shape)}")
    gt = gt.detach().to(img.dtype)
    if not img.requires_grad or not torch.is_grad_enabled():
        return _ssim_map_autograd(img, gt)
    return _FusedSSIM.apply(img.contiguous(), gt.contiguous())


def ssim(img: Tensor, gt: Tensor) -> Tensor:
    """Mean SSIM (scalar tensor, differentiable) of two [H, W, C] images in [0, 1] (3DGS form)."""
    return ssim_map(img, gt).mean()
