"""The rasteriser's colours from SH: the C++ pass (``csrc/sh_colors.cpp``) against its torch twin
(:func:`clod_adapter.render.cpu.sh_colors`, gsplat 1.5.3's ``spherical_harmonics`` + ``clamp_min(sh +
0.5, 0)``), and which one runs when."""
import pytest
import torch

from clod_adapter.render import native
from clod_adapter.render.cpu import sh_colors, sh_colors_rows

pytestmark = pytest.mark.skipif(not native.available(), reason="the C++ kernels do not build here")


def _rows(n, k, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 3
    coeffs = torch.randn(n, k, 3, generator=g, dtype=dtype) * 0.5
    means[0] = torch.tensor([1.0, -2.0, 0.5], dtype=dtype)  # at the camera centre: direction 0
    return means, coeffs, torch.tensor([1.0, -2.0, 0.5], dtype=dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree,k", [(0, 1), (1, 4), (2, 9), (3, 16), (1, 16)])
def test_the_cpp_colours_equal_the_torch_twin(dtype, degree, k):
    means, coeffs, campos = _rows(9000, k, dtype)  # more rows than one thread's grain
    with native.use_impl("cpp"):
        a = sh_colors(degree, means, coeffs, campos)
    with native.use_impl("torch"):
        b = sh_colors(degree, means, coeffs, campos)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert a.shape == b.shape == (9000, 3) and a.dtype == dtype
    assert torch.allclose(a, b, rtol=tol, atol=tol)
    assert (a == 0).any() and (a > 0.5).any()  # the clamp and the view dependence were exercised
    assert torch.isfinite(a).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree,k", [(0, 1), (2, 9), (3, 16), (1, 16)])
def test_colours_of_rows_read_in_place_equal_the_gathered_rows(dtype, degree, k):
    """sh_colors_rows (sh0 / shN read at the rows, no [V, K, 3] gather) against sh_colors of the
    gathered rows, in C++ and in its torch twin; a row outside the model is refused."""
    means, coeffs, campos = _rows(12000, k, dtype)
    sh0, shN = coeffs[:, :1].clone(), coeffs[:, 1:].clone()
    ids = torch.randperm(12000, generator=torch.Generator().manual_seed(1))[:9000].sort().values
    want = sh_colors(degree, means[ids], coeffs[ids], campos)
    for impl in ("cpp", "torch"):
        with native.use_impl(impl):
            got = sh_colors_rows(degree, means, sh0, shN, ids, campos)
        tol = 1e-5 if dtype == torch.float32 else 1e-12
        assert got.shape == (9000, 3) and got.dtype == dtype and torch.allclose(got, want, rtol=tol, atol=tol)
    with native.use_impl("cpp"), pytest.raises(RuntimeError, match="outside"):
        sh_colors_rows(degree, means, sh0, shN, torch.tensor([0, 12000]), campos)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree,k", [(0, 1), (1, 4), (2, 9), (3, 16), (2, 16)])
def test_the_cpp_gradients_equal_autograd_through_the_twin(dtype, degree, k):
    """The C++ backward gives the means' and the coefficients' gradients autograd gives through the
    torch form, the clamp included (rows whose colour is clamped to 0 pass none)."""
    means, coeffs, campos = _rows(6000, k, dtype, seed=2)
    v = torch.randn(6000, 3, generator=torch.Generator().manual_seed(5), dtype=dtype)
    grads = []
    for impl in ("cpp", "torch"):
        m, c = means.clone().requires_grad_(True), coeffs.clone().requires_grad_(True)
        with native.use_impl(impl):
            out = sh_colors(degree, m, c, campos)
        (out * v).sum().backward()
        grads.append((out.detach(), m.grad, c.grad))
    (oa, ma, ca), (ob, mb, cb) = grads
    tol = 2e-4 if dtype == torch.float32 else 1e-10
    assert torch.allclose(oa, ob, rtol=tol, atol=tol)
    assert torch.allclose(ca, cb, rtol=tol, atol=tol) and ca[:, (degree + 1) ** 2:].abs().sum() == 0
    if degree == 0:
        assert mb is None or mb.abs().sum() == 0
        assert ma is None or ma.abs().sum() == 0
    else:
        assert ma.abs().sum() > 0
        assert torch.allclose(ma[1:], mb[1:], rtol=tol, atol=tol)  # row 0 sits at the camera centre
    assert (oa == 0).any()  # some rows clamped


def test_the_torch_form_runs_where_the_camera_centre_needs_a_gradient():
    means, coeffs, campos = _rows(50, 16, torch.float32, seed=1)
    campos.requires_grad_(True)
    out = sh_colors(3, means, coeffs, campos)
    out.sum().backward()
    assert campos.grad is not None and campos.grad.abs().sum() > 0


@pytest.mark.parametrize("impl", ["cpp", "torch"])
def test_a_degree_the_coefficients_cannot_hold_is_a_value_error(impl):
    means, coeffs, campos = _rows(10, 4, torch.float32)
    with native.use_impl(impl), pytest.raises(ValueError, match="SH degree 2"):
        sh_colors(2, means, coeffs, campos)
