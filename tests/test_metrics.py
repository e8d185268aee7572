"""PSNR and the 3DGS SSIM, cross-checked against scikit-image; the photometric loss."""
import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from clod_adapter.train.losses import clod_loss, render_loss
from clod_adapter.metrics import _ssim_map_autograd, psnr, ssim, ssim_map


def _pair(seed=0, h=48, w=64):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    b = (a + 0.08 * torch.randn(h, w, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    return a, b


def test_ssim_matches_scikit_image_on_interior():
    a, b = _pair()
    ours = ssim_map(a, b).numpy()
    _, ref = structural_similarity(a.numpy(), b.numpy(), gaussian_weights=True, sigma=1.5,
                                   use_sample_covariance=False, data_range=1.0, channel_axis=2,
                                   full=True)
    np.testing.assert_allclose(ours[5:-5, 5:-5], ref[5:-5, 5:-5], atol=1e-10)


def test_ssim_identity_and_gradient():
    a, b = _pair(1)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-12)
    x = b.clone().requires_grad_(True)
    (1 - ssim(x, a)).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_ssim_gradient_equals_autograd_twin(dtype):
    a, b = _pair(3, h=37, w=53)  # odd sizes: the zero padding at every border
    a, b = a.to(dtype), b.to(dtype)
    w = torch.rand(a.shape, generator=torch.Generator().manual_seed(4), dtype=dtype)  # any upstream gradient
    grads = []
    for fn in (ssim_map, _ssim_map_autograd):
        x = b.clone().requires_grad_(True)
        m = fn(x, a)
        (m * w).sum().backward()
        grads.append((m.detach(), x.grad))
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    scale = float(grads[1][1].abs().max())
    assert scale > 0
    torch.testing.assert_close(grads[0][0], grads[1][0], atol=tol, rtol=0)
    torch.testing.assert_close(grads[0][1], grads[1][1], atol=tol * scale, rtol=0)
    if dtype == torch.float64:  # and both equal the numerical gradient
        x = b[:12, :13].clone().requires_grad_(True)
        assert torch.autograd.gradcheck(lambda t: ssim_map(t, a[:12, :13]), (x,))


def test_psnr_known_value():
    a = torch.zeros(10, 10, 3)
    b = torch.full((10, 10, 3), 0.1)
    assert psnr(b, a) == pytest.approx(20.0, abs=1e-4)
    assert psnr(a, a) == math.inf


def test_render_loss_and_clod_loss():
    a, b = _pair(2)
    l = render_loss(a, b)
    l1 = (a - b).abs().mean()
    assert l.item() == pytest.approx(0.8 * l1.item() + 0.2 * (1 - ssim(a, b).item()))
    total, reg = clod_loss(l, torch.tensor(0.5, dtype=torch.float64), 4.0, 5.0, 1.0)
    assert reg.item() == pytest.approx(9 * (0.5 - 0.125) ** 2)
    assert total.item() == pytest.approx((1 - 0.4) ** 2 * (l.item() + reg.item()))
