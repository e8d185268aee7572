"""Real spherical harmonics (degree 0..3), exactly gsplat 1.5.3's ``spherical_harmonics``.

Constants and signs follow gsplat's ``_eval_sh_bases_fast`` / ``sh_coeffs_to_color_fast``
(Sloan, "Efficient Spherical Harmonic Evaluation", JCGT 2013). The ``+ 0.5`` offset and the
``clamp_min(0)`` are NOT applied here; :func:`clod_adapter.render.rasterization` applies them,
as gsplat's ``rendering.py`` does.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["spherical_harmonics", "sh_bases"]

_C0 = 0.2820947917738781
_C1 = 0.48860251190292


def sh_bases(degree: int, dirs: Tensor) -> Tensor:
    """[..., (degree+1)^2] real SH bases at UNIT directions ``dirs`` [..., 3] (gsplat order)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    # contiguous [n] rows make the ~40 elementwise ops below cheap
    x, y, z = dirs.reshape(-1, 3).t().contiguous().unbind(0)
    lead = dirs.shape[:-1]
    cols = [torch.full_like(x, _C0)]
    if degree >= 1:
        cols += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        z2 = z * z
        fTmpB = -1.092548430592079 * z
        fC1 = x * x - y * y
        fS1 = 2.0 * x * y
        cols += [
            0.5462742152960395 * fS1,  # 4
            fTmpB * y,  # 5
            0.9461746957575601 * z2 - 0.3153915652525201,  # 6
            fTmpB * x,  # 7
            0.5462742152960395 * fC1,  # 8
        ]
    if degree >= 3:
        fTmpC = -2.285228997322329 * z2 + 0.4570457994644658
        fTmpB3 = 1.445305721320277 * z
        fC2 = x * fC1 - y * fS1
        fS2 = x * fS1 + y * fC1
        cols += [
            -0.5900435899266435 * fS2,  # 9
            fTmpB3 * fS1,  # 10
            fTmpC * y,  # 11
            z * (1.865881662950577 * z2 - 1.119528997770346),  # 12
            fTmpC * x,  # 13
            fTmpB3 * fC1,  # 14
            -0.5900435899266435 * fC2,  # 15
        ]
    return torch.stack(cols, dim=-1).reshape(*lead, len(cols))


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Evaluate view-dependent colour from SH coefficients (gsplat semantics).

    Args:
        degree: SH degree to use, 0..3; only the first (degree+1)^2 coefficients are read.
        dirs: [..., 3] view directions (need not be normalised; normalised here).
        coeffs: [..., K, 3] SH coefficients, K >= (degree+1)^2.

    Returns:
        [..., 3] colours (raw SH value; no +0.5 offset, no clamp).
    """
    nb = (degree + 1) ** 2
    if coeffs.shape[-2] < nb:
        raise ValueError(f"SH degree {degree} needs {nb} coefficients, got K={coeffs.shape[-2]}")
    if coeffs.shape[-1] != 3:
        raise ValueError(f"coeffs must be [..., K, 3], got {tuple(coeffs.shape)}")
    if degree == 0:
        return _C0 * coeffs[..., 0, :]
    # gsplat CUDA: inorm = rsqrt(x^2 + y^2 + z^2); torch impl: F.normalize (eps 1e-12)
    dirs = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True).clamp_min(1e-12)
    bases = sh_bases(degree, dirs)  # [..., nb]
    c = coeffs[..., :nb, :]
    # (bases[..., None] * c).sum(-2) as a batched 1 x nb @ nb x 3 product
    return torch.matmul(bases.unsqueeze(-2), c).squeeze(-2)
