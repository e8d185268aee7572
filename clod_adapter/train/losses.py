"""Training losses: the 3DGS photometric loss and the CLoD-GS total loss.

``L_render = 0.8 L1 + 0.2 (1 - SSIM)`` (Kerbl et al. 2023, lambda_dssim = 0.2);
``L = w_s (L_render + lambda_reg L_reg)`` (CLoD-GS, Cheng et al. ICLR 2026; ``w_s`` and ``L_reg``
live in :mod:`clod_adapter.lod.rule`).
"""
from __future__ import annotations

from torch import Tensor

from ..lod import rule as lod
from ..metrics import ssim

LAMBDA_DSSIM = 0.2


def render_loss(img: Tensor, gt: Tensor, lambda_dssim: float = LAMBDA_DSSIM) -> Tensor:
    """``(1 - lambda) L1 + lambda (1 - SSIM)`` for [H, W, 3] images in [0, 1]; scalar tensor."""
    l1 = (img - gt).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(img, gt))


def clod_loss(l_render: Tensor, eta: Tensor, s_v: float, max_sv: float,
              lambda_reg: float = 1.0) -> tuple[Tensor, Tensor]:
    """CLoD-GS total loss ``w_s (L_render + lambda_reg L_reg)``.

    Returns:
        (total, l_reg) scalar tensors.
    """
    l_reg = lod.reg_loss(s_v, eta)
    w_s = lod.scale_weight(s_v, max_sv)
    return w_s * (l_render + lambda_reg * l_reg), l_reg
