"""Numerical stability of the CLoD mechanism, the budget solver and the CPU rasteriser
(the C++ compositor and its twin; gsplat is GPU-only and not exercised here).

Stiff and extreme cases: sigma_d <= 0 (the ReLU dead zone), sigma_d = 1e6, s_v = 1 .. 1e4, tiny
eps, d' = 0 (camera on a Gaussian), one / zero Gaussians, an empty frustum, everything behind the
camera, a small scene placed at 1e6 world units, needle / flat Gaussians (scale ratio 1e6),
quaternions of norm 0 and 1e-12, opacity logits of +-50, a huge focal length, and float16 /
bfloat16 evaluation of the LoD mechanism.

Asserted throughout: finite outputs and gradients, attenuation within [0, alpha], and the
rendered count non-increasing in s_v. See docs/robustness_numerics.md for the case count.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from clod_adapter.lod import rule as lod
from clod_adapter.lod.budget import Budget, critical_s_v, select_budget
from clod_adapter.lod_settings import EtaGradient
from clod_adapter.gaussians import Gaussians
from clod_adapter.lod.draw import render_lod
from clod_adapter.render import rasterization
from clod_adapter.render.composite import cpp_extension_available, use_impl

W, H = 32, 24
IMPLS = ["torch", pytest.param("cpp", marks=pytest.mark.skipif(
    not cpp_extension_available(), reason="C++ compositor does not build here"))]

# Bounded, reproducible property tests (the whole file runs in well under a minute on 2 cores).
SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
FAST = settings(max_examples=120, **SETTINGS)  # mechanism / budget: microseconds per example
RENDER = settings(max_examples=30, **SETTINGS)  # rasteriser: a few ms per example


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _cam(fx: float = 30.0, center=(0.0, 0.0, 0.0), dtype=torch.float32, width: int = W,
         height: int = H) -> SimpleNamespace:
    """Pinhole camera at ``center`` looking down +z (OpenCV axes)."""
    V = torch.eye(4, dtype=dtype)
    V[:3, 3] = -torch.as_tensor(center, dtype=dtype)
    K = torch.tensor([[fx, 0.0, width / 2], [0.0, fx, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return SimpleNamespace(viewmat=V, K=K, width=width, height=height)


def _model(means, log_scales=None, quats=None, logits=None, sigma_d=None, dtype=torch.float32,
           seed: int = 0) -> Gaussians:
    """A degree-1 model with leaf tensors that require grad."""
    means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
    n = means.shape[0]
    g = torch.Generator().manual_seed(seed)
    if log_scales is None:
        log_scales = torch.full((n, 3), -1.5)
    if quats is None:
        quats = torch.randn(n, 4, generator=g)
    if logits is None:
        logits = torch.full((n,), 2.0)
    if sigma_d is None:
        sigma_d = torch.full((n,), 0.5)
    t = lambda x, shape: torch.as_tensor(x, dtype=dtype).reshape(shape).clone().requires_grad_(True)  # noqa: E731
    return Gaussians(
        means=means.clone().requires_grad_(True),
        quats=t(quats, (n, 4)), log_scales=t(log_scales, (n, 3)), opacity_logits=t(logits, (n,)),
        sh0=t(torch.rand(n, 1, 3, generator=g) - 0.5, (n, 1, 3)),
        shN=t(0.1 * torch.randn(n, 3, 3, generator=g), (n, 3, 3)),
        sigma_d=t(sigma_d, (n,)),
    )


def _assert_finite_grads(tensors: dict, where: str = "") -> None:
    for name, t in tensors.items():
        if t.grad is not None:
            assert torch.isfinite(t.grad).all(), f"{where}: non-finite gradient of {name}: {t.grad}"


def _render_and_check(g: Gaussians, cam, s_v=None, impl="torch", budget=None, **kw):
    with use_impl(impl):
        out = render_lod(g, cam, s_v, backend="cpu", budget=budget, **kw)
    assert torch.isfinite(out.image).all(), "non-finite image"
    assert torch.isfinite(out.alpha).all() and (out.alpha >= 0).all() and (out.alpha <= 1).all()
    assert torch.isfinite(out.eta).all() and 0.0 <= float(out.eta.detach()) <= 1.0
    loss = out.image.sum() + out.alpha.sum() + out.eta
    if loss.requires_grad:
        loss.backward()
    _assert_finite_grads(g.tensors(), f"render_lod(s_v={s_v}, budget={budget}, impl={impl})")
    return out


# ----------------------------------------------------------------------------------------------
# strategies
# ----------------------------------------------------------------------------------------------
SIGMA_D = st.one_of(
    st.sampled_from([-1e6, -1.0, -1e-30, 0.0, 1e-30, 1e-6, 1e-3, 0.05, 1.0, 1e6]),
    st.floats(-10.0, 1e6, allow_nan=False, allow_infinity=False),
)
D_NORM = st.one_of(st.sampled_from([0.0, 1e-30, 1e-6, 0.5, 1.0, 10.0, 1e3]),
                   st.floats(0.0, 1e3, allow_nan=False))
OPACITY = st.one_of(st.sampled_from([0.0, 1.9e-22, 1 / 255, 0.005, 0.5, 1 - 1e-7, 1.0]),
                    st.floats(0.0, 1.0))
S_V = st.one_of(st.sampled_from([1.0, 1.0 + 1e-7, 2.0, 5.0, 100.0, 1e4]), st.floats(1.0, 1e4))
EPS = st.sampled_from([lod.DEFAULT_EPS, 1e-12, 1e-20, 1e-30, 1e-38, 1e-45])
ROWS = st.lists(st.tuples(OPACITY, D_NORM, SIGMA_D), min_size=0, max_size=8)


def _cols(rows, dtype):
    if not rows:
        z = torch.zeros(0, dtype=dtype)
        return z, z.clone(), z.clone()
    o, d, s = zip(*rows)
    return (torch.tensor(o, dtype=dtype), torch.tensor(d, dtype=dtype), torch.tensor(s, dtype=dtype))


# ----------------------------------------------------------------------------------------------
# 1. the mechanism (clod_adapter.lod.rule)
# ----------------------------------------------------------------------------------------------
@FAST
@given(rows=ROWS, s_v=S_V, eps=EPS, dtype=st.sampled_from([torch.float32, torch.float64]),
       estimator=st.sampled_from(["ste", "sigmoid"]))
def test_attenuation_bounded_and_gradients_finite(rows, s_v, eps, dtype, estimator):
    opac, d, sigma = (t.requires_grad_(True) for t in _cols(rows, dtype))
    a = lod.lod_opacities(opac, d, sigma, s_v, eps)
    assert a.dtype == dtype and torch.isfinite(a).all()
    assert bool((a >= 0).all()) and bool((a <= opac).all()), "attenuation outside [0, alpha]"
    m = lod.lod_margin(opac, d, sigma, s_v, eps=eps)
    assert not torch.isnan(m).any(), f"NaN margin: {m}"
    assert bool(torch.isfinite(m[opac.detach() > 0]).all()), "margin infinite for alpha > 0"
    eta = lod.rendered_fraction(m, None, estimator)
    (a.sum() + eta).backward()
    _assert_finite_grads({"opacities": opac, "d_norm": d, "sigma_d": sigma})


@FAST
@given(rows=ROWS, s_list=st.lists(S_V, min_size=2, max_size=6), eps=EPS)
def test_margin_and_count_non_increasing_in_s_v(rows, s_list, eps):
    opac, d, sigma = _cols(rows, torch.float32)
    prev_m, prev_n = None, None
    for s_v in sorted(s_list):
        m = lod.lod_margin(opac, d, sigma, s_v, eps=eps)
        n = int(lod.lod_mask(opac, d, sigma, s_v, eps=eps).sum())
        if prev_m is not None:
            assert bool((m <= prev_m).all()), "a margin grew with s_v"
            assert n <= prev_n, "rendered count grew with s_v"
        prev_m, prev_n = m, n


@FAST
@given(rows=ROWS, s_v=S_V, dtype=st.sampled_from([torch.float16, torch.bfloat16]))
def test_low_precision_evaluation(rows, s_v, dtype):
    o, d, s = (t.to(dtype) for t in _cols(rows, torch.float32))
    a = lod.lod_opacities(o, d, s, s_v)
    assert a.dtype == dtype and torch.isfinite(a.float()).all()
    assert bool((a.float() >= 0).all()) and bool((a.float() <= o.float()).all())
    m = lod.lod_margin(o, d, s, s_v)
    assert not torch.isnan(m).any()
    # the mask in low precision equals the float32 mask on the same (rounded) inputs
    m32 = lod.lod_margin(o.float(), d.float(), s.float(), s_v)
    assert torch.equal(m > 0, m32 > 0)


@FAST
@given(rows=ROWS, s_v=S_V)
def test_bfloat16_gradients_finite(rows, s_v):
    o, d, s = (t.to(torch.bfloat16).requires_grad_(True) for t in _cols(rows, torch.float32))
    lod.lod_opacities(o, d, s, s_v).float().sum().backward()
    _assert_finite_grads({"opacities": o, "d_norm": d, "sigma_d": s}, "bfloat16")


def test_float16_gradients_finite_in_its_range():
    """float16 gradients are finite while the true derivative fits float16 (|g| < 65504);
    d alpha''/d d' reaches ~ s_v / sigma_d, so e.g. s_v = 1e4 with sigma_d = 0.01 overflows
    float16 whatever the formula (use bfloat16 or float32 parameters for training)."""
    g = torch.Generator().manual_seed(0)
    o = torch.rand(500, generator=g).half().requires_grad_(True)
    d = (torch.rand(500, generator=g) * 1.5).half().requires_grad_(True)
    s = (torch.rand(500, generator=g) * 2 - 0.5).half()
    s[::7] = 0.0
    s = s.requires_grad_(True)
    for s_v in (1.0, 5.0, 50.0):
        lod.lod_opacities(o, d, s, s_v).float().sum().backward()
        _assert_finite_grads({"opacities": o, "d_norm": d, "sigma_d": s}, f"float16 s_v={s_v}")


@pytest.mark.parametrize("sigma_d", [-1e6, -1.0, -1e-6, 0.0])
@pytest.mark.parametrize("estimator", ["ste", "sigmoid"])
def test_dead_zone_has_no_gradient(sigma_d, estimator):
    """A Gaussian with sigma_d <= 0 and d' > 0 gets exactly zero gradient on sigma_d from both
    the render path (alpha'') and the count path (eta): ReLU'(x <= 0) = 0, so plain gradient
    descent can never bring it back (the measurement and the proposed floor are in
    docs/robustness_numerics.md)."""
    opac = torch.tensor([0.8, 0.8])
    d = torch.tensor([0.4, 0.7])
    sig = torch.tensor([sigma_d, 0.3], requires_grad=True)
    m = lod.lod_margin(opac, d, sig, 2.0)
    gm = torch.autograd.grad(m.sum(), sig)[0]
    assert torch.isfinite(gm).all() and gm[0] == 0.0 and gm[1] != 0.0
    loss = lod.lod_opacities(opac, d, sig, 2.0).sum() + lod.rendered_fraction(
        lod.lod_margin(opac, d, sig, 2.0), None, estimator)
    g = torch.autograd.grad(loss, sig)[0]
    assert torch.isfinite(g).all() and g[0] == 0.0


@pytest.mark.parametrize("sigma_min", [1e-3, 0.02, 0.1])
def test_floor_keeps_margin_gradient_alive(sigma_min):
    """With sigma_d clamped to >= sigma_min > 0 after each optimiser step, the margin's gradient
    with respect to sigma_d is non-zero (and positive: raising sigma_d raises the margin) for
    every d' > 0 and s_v in [1, 1e4]."""
    d = torch.tensor([1e-3, 0.1, 0.5, 1.0, 3.0]).repeat(3)
    s = torch.tensor([1.0, 5.0, 1e4]).repeat_interleave(5)
    sig = torch.full_like(d, -0.5)
    with torch.no_grad():
        sig.clamp_(min=sigma_min)  # the proposed floor
    sig.requires_grad_(True)
    m = lod.lod_margin(torch.full_like(d, 0.5), d, sig, s)
    g = torch.autograd.grad(m.sum(), sig)[0]
    assert torch.isfinite(g).all() and bool((g > 0).all()), g


def test_extreme_scalars_mechanism():
    one = torch.ones(1)
    # sigma_d = 1e6: no attenuation at any s_v <= 1e4
    assert lod.lod_opacities(one * 0.5, one, one * 1e6, 1e4).item() == pytest.approx(0.5, rel=1e-4)
    # d' = 0 (camera on the Gaussian): never attenuated, even when dead
    assert lod.lod_opacities(one * 0.5, one * 0, -one, 1e4).item() == 0.5
    # s_v = 1e4 with tau: nothing passes (tau s_v = 50 > 1)
    assert not lod.lod_mask(one, one * 0, one, 1e4).any()
    # zero Gaussians
    z = torch.zeros(0)
    assert lod.lod_opacities(z, z, z, 2.0).numel() == 0
    assert lod.rendered_fraction(lod.lod_margin(z, z, z, 2.0), None, "ste").item() == 0.0
    # normaliser: empty frustum, zero Gaussians, camera on every Gaussian
    c = torch.zeros(3)
    assert lod.normalized_distances(torch.zeros(0, 3), c, torch.zeros(0, dtype=torch.bool)).numel() == 0
    mu = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 2.0]], requires_grad=True)
    dn = lod.normalized_distances(mu, c, torch.zeros(2, dtype=torch.bool))
    assert dn.tolist() == pytest.approx([0.0, 1.0])
    dn.sum().backward()
    assert torch.isfinite(mu.grad).all()  # d ||mu - c|| at mu = c: subgradient 0, not NaN


# ----------------------------------------------------------------------------------------------
# 2. the budget solver (clod_adapter.lod.budget)
# ----------------------------------------------------------------------------------------------
@FAST
@given(rows=ROWS, eps=EPS, s_list=st.lists(S_V, min_size=1, max_size=4))
def test_critical_s_v_finite_and_consistent_with_mask(rows, eps, s_list):
    opac, d, sigma = _cols(rows, torch.float64)
    crit = critical_s_v(opac, d, sigma, eps=eps)
    assert crit.dtype == torch.float64 and torch.isfinite(crit).all() and bool((crit >= 0).all())
    for s_v in s_list:
        m = lod.lod_margin(opac, d, sigma, s_v, eps=eps)
        clear = (crit - s_v).abs() > 1e-6 * s_v  # away from the boundary
        assert torch.equal((m > 0)[clear], (crit > s_v)[clear]), (crit, m, s_v)
    # exact budget: k largest critical scales, and the solved s_v renders exactly those
    k = len(rows) // 2
    idx, s_v = select_budget(crit, k)
    assert idx.numel() == k and math.isfinite(s_v) and s_v > 0


def test_critical_s_v_converges_for_stiff_decay():
    """Huge a = d'^2 / (2 ReLU(sigma_d)^2 + eps) (dead Gaussian, tiny eps): the root is found,
    not just approached at Newton's -0.5 per step."""
    opac = torch.full((4,), 0.9, dtype=torch.float64)
    d = torch.tensor([1.0, 1.0, 0.5, 0.0], dtype=torch.float64)
    sigma = torch.tensor([0.0, 1e-12, -3.0, 0.0], dtype=torch.float64)
    for eps in (1e-8, 1e-30, 1e-45, 1e-300):
        crit = critical_s_v(opac, d, sigma, eps=eps)
        assert torch.isfinite(crit).all() and bool((crit > 0).all())
        assert crit[3].item() == pytest.approx(0.9 / lod.DEFAULT_TAU)  # d' = 0: alpha / tau
        live = crit[:3]
        below = lod.lod_margin(opac[:3], d[:3], sigma[:3], live * (1 - 1e-6), eps=eps)
        above = lod.lod_margin(opac[:3], d[:3], sigma[:3], live * (1 + 1e-6), eps=eps)
        assert bool((below > 0).all()) and bool((above < 0).all()), (eps, crit)


def test_critical_s_v_extremes():
    opac = torch.tensor([0.0, 1.9e-22, 1.0, 0.5, 0.5], dtype=torch.float64)
    d = torch.tensor([0.5, 0.5, 0.5, 0.5, 1e3], dtype=torch.float64)
    sigma = torch.tensor([1.0, 1.0, 1e6, -1.0, 1e6], dtype=torch.float64)
    crit = critical_s_v(opac, d, sigma)
    assert torch.isfinite(crit).all()
    assert crit[0] == 0.0 and crit[1] < 1.0 and crit[2] == pytest.approx(200.0, rel=1e-6)
    assert crit[3] < 1.0  # dead: not rendered at any s_v >= 1
    z = torch.zeros(0, dtype=torch.float64)
    assert critical_s_v(z, z, z).numel() == 0
    idx, s_v = select_budget(z, 5)
    assert idx.numel() == 0 and s_v == 1.0


# ----------------------------------------------------------------------------------------------
# 3. the rasteriser (CPU backend, both compositors)
# ----------------------------------------------------------------------------------------------
POS = st.sampled_from(["front", "front", "front", "behind", "on_camera", "near_plane", "far_side"])
QUAT = st.sampled_from(["random", "random", "zero", "tiny", "huge"])
GAUSS = st.tuples(
    POS, st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(1.5, 6.0),  # placement
    st.floats(-6.0, 1.0),  # base log-scale
    st.sampled_from([0.0, 0.0, math.log(1e6), -math.log(1e6), math.log(1e3)]),  # anisotropy
    QUAT, st.one_of(st.sampled_from([-50.0, 50.0]), st.floats(-50.0, 50.0)),
)


def _build(gs, offset=0.0):
    means, ls, qs, lg = [], [], [], []
    g = torch.Generator().manual_seed(len(gs))
    for pos, x, y, z, base, aniso, quat, logit in gs:
        p = {"front": (x * z * 0.4, y * z * 0.3, z), "behind": (x, y, -z), "on_camera": (0.0, 0.0, 0.0),
             "near_plane": (x * 0.004, y * 0.003, 0.01), "far_side": (x * 1e3, y * 1e3, 1e3)}[pos]
        means.append([c + offset for c in p])
        ls.append([base + aniso, base, base - 0.5 * abs(aniso)])
        q = torch.randn(4, generator=g)
        q = {"random": q, "zero": torch.zeros(4), "tiny": q / q.norm() * 1e-12, "huge": q * 1e12}[quat]
        qs.append(q.tolist())
        lg.append(logit)
    n = len(gs)
    return (torch.tensor(means, dtype=torch.float32).reshape(n, 3), torch.tensor(ls).reshape(n, 3),
            torch.tensor(qs).reshape(n, 4), torch.tensor(lg).reshape(n))


@RENDER
@given(gs=st.lists(GAUSS, min_size=0, max_size=5),
       fx=st.sampled_from([30.0, 30.0, 1e3, 1e6, 1e8]), impl=st.sampled_from(["torch", "cpp"]))
def test_rasterizer_extreme_gaussians_finite(gs, fx, impl):
    if impl == "cpp" and not cpp_extension_available():
        impl = "torch"
    means, ls, qs, lg = _build(gs)
    g = _model(means, ls, qs, lg, seed=len(gs))
    cam = _cam(fx)
    with use_impl(impl):
        cols, alphas, meta = rasterization(
            g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat[None], cam.K[None], W, H,
            sh_degree=1, backend="cpu")
    assert torch.isfinite(cols).all() and torch.isfinite(alphas).all()
    assert bool((alphas >= 0).all()) and bool((alphas <= 1).all())
    assert bool((meta["radii"] >= 0).all()), "negative radius (int32 overflow?)"
    loss = cols.sum() + alphas.sum()
    if loss.requires_grad:
        loss.backward()
    _assert_finite_grads(g.tensors(), f"rasterization(impl={impl}, fx={fx})")


@RENDER
@given(gs=st.lists(GAUSS, min_size=1, max_size=4), fx=st.sampled_from([30.0, 1e3]))
def test_cpp_and_torch_compositors_agree_on_extreme_gaussians(gs, fx):
    if not cpp_extension_available():
        pytest.skip("C++ compositor does not build here")
    means, ls, qs, lg = _build(gs)
    cam = _cam(fx)
    res = {}
    for impl in ("torch", "cpp"):
        g = _model(means, ls, qs, lg, seed=len(gs))
        with use_impl(impl):
            c, a, _ = rasterization(g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat[None],
                                    cam.K[None], W, H, sh_degree=1, backend="cpu")
            loss = c.sum() + a.sum()
            if not loss.requires_grad:
                return
            loss.backward()
        res[impl] = (c.detach(), a.detach(), g.opacity_logits.grad.clone(), g.sh0.grad.clone())
    for x, y in zip(res["torch"], res["cpp"]):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("fx", [1e6, 1e8])
def test_huge_focal_length(impl, fx):
    g = _model([[0.0, 0.0, 3.0], [1e-6, -1e-6, 2.0]], log_scales=torch.zeros(2, 3))
    out = _render_and_check(g, _cam(fx), None, impl)
    assert out.n_rendered == 2 and out.alpha.min() > 0.5  # both cover the whole image


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("length", [3.0, 300.0])
@pytest.mark.parametrize("kind", ["needle", "flat"])
def test_needle_and_flat_gaussians_are_drawn(impl, kind, length):
    """Scale ratio 1e6: the 2D covariance's determinant must not cancel to <= 0 in float32
    (the Gaussian would be culled or get a non-positive-definite conic)."""
    big, small = math.log(length), math.log(length * 1e-6)
    ls = [[big, small, small]] if kind == "needle" else [[big, big, small]]
    for q in ([1.0, 0.0, 0.0, 0.0], [0.9, 0.1, 0.3, 0.2], [0.3, -0.4, 0.8, 0.1]):
        g = _model([[0.1, -0.05, 3.0]], log_scales=ls, quats=[q], logits=[4.0])
        out = _render_and_check(g, _cam(), None, impl)
        assert out.n_rendered == 1
        assert out.alpha.max() > 0.5, f"{kind} Gaussian vanished (q={q})"


@pytest.mark.parametrize("length", [3.0, 300.0, 3e3, 3e4])
def test_needle_conic_float32_matches_float64(length):
    """Needle of scale ratio 1e6 (length up to 3e4 world units at depth 3): the float32 conic
    equals the float64 one. With det = c00 c11 - c01^2 the float32 conic was 27 % off at
    length 300 and the needle was culled (radii 0) from length 3e3 on."""
    from clod_adapter.render import fully_fused_projection
    V, K = torch.eye(4), torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    q = torch.tensor([[0.9, 0.1, 0.3, 0.2]])
    s = torch.tensor([[length, length * 1e-6, length * 1e-6]])
    m = torch.tensor([[0.1, -0.05, 3.0]])
    r32, _, _, c32 = fully_fused_projection(m, q, s, None, V, K, W, H)
    r64, _, _, c64 = fully_fused_projection(m.double(), q.double(), s.double(), None, V.double(),
                                            K.double(), W, H)
    assert bool((r32 > 0).all()) and bool(((r32 - r64).abs() <= 1).all())  # ceil() rounding
    torch.testing.assert_close(c32.double(), c64, rtol=1e-4, atol=1e-7)


# ----------------------------------------------------------------------------------------------
# 4. the whole chain: render_lod (LoD mask + rasteriser), both compositors
# ----------------------------------------------------------------------------------------------
SV_SWEEP = [1.0, 1.5, 2.0, 5.0, 100.0, 1e4]


def _scene(kind: str):
    """(model, camera) for one named extreme case."""
    g = torch.Generator().manual_seed(7)
    n = 12
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([2.0, 1.5])
    z = 2.0 + 4.0 * torch.rand(n, 1, generator=g)
    means = torch.cat([xy * z / 2.0, z], 1)
    sig = torch.rand(n, generator=g) * 0.8 + 0.05
    kw = {}
    cam = _cam()
    if kind == "zero":
        means, sig = means[:0], sig[:0]
    elif kind == "one":
        means, sig = means[:1], sig[:1]
    elif kind == "dead":
        sig = torch.where(torch.arange(n) % 2 == 0, -sig, torch.zeros(n))
    elif kind == "sigma_1e6":
        sig = torch.full((n,), 1e6)
    elif kind == "behind":
        means = means * torch.tensor([1.0, 1.0, -1.0])
    elif kind == "outside_frustum":  # centres off-image (max over an empty frustum set)
        means = means + torch.tensor([40.0, 0.0, 0.0])
    elif kind == "on_camera":
        means = torch.cat([torch.zeros(1, 3), means[1:]])
    elif kind == "all_on_camera":
        means = torch.zeros(3, 3)
        sig = sig[:3]
    elif kind == "far_1e6":
        means = means + 1e6
        cam = _cam(center=(1e6, 1e6, 1e6))
    elif kind == "opacity_50":
        kw["logits"] = torch.where(torch.arange(n) % 2 == 0, 50.0, -50.0)
    elif kind == "quats_degenerate":
        q = torch.randn(n, 4, generator=g)
        q[::2] = 0.0
        q[1::2] = q[1::2] / q[1::2].norm(dim=1, keepdim=True) * 1e-12
        kw["quats"] = q
    elif kind == "needle_flat":
        ls = torch.full((n, 3), math.log(3e-6))
        ls[:, 0] = math.log(3.0)
        ls[1::2, 1] = math.log(3.0)
        kw["log_scales"] = ls
    elif kind == "huge_focal":
        cam = _cam(fx=1e6)
    else:
        raise AssertionError(kind)
    return _model(means, sigma_d=sig, **kw), cam


SCENES = ["zero", "one", "dead", "sigma_1e6", "behind", "outside_frustum", "on_camera",
          "all_on_camera", "far_1e6", "opacity_50", "quats_degenerate", "needle_flat", "huge_focal"]


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("kind", SCENES)
def test_render_lod_extreme_scenes(kind, impl):
    model, cam = _scene(kind)
    counts = []
    for s_v in [None] + SV_SWEEP:
        g = _model(model.means.detach(), model.log_scales.detach(), model.quats.detach(),
                   model.opacity_logits.detach(), model.sigma_d.detach())
        out = _render_and_check(g, cam, s_v, impl)
        counts.append(out.n_rendered)
    assert counts[1] <= counts[0]
    assert all(b <= a for a, b in zip(counts[1:], counts[2:])), f"count grew with s_v: {counts}"
    assert counts[-1] == 0  # tau * 1e4 = 50 > 1: nothing passes
    if kind in ("behind", "zero"):
        assert counts[0] == 0
    if kind == "dead":  # only the d' = 0 ones could survive; none is at the camera
        assert counts[1] == 0
    for k in (0, 1, len(model)):
        g = _model(model.means.detach(), model.log_scales.detach(), model.quats.detach(),
                   model.opacity_logits.detach(), model.sigma_d.detach())
        out = _render_and_check(g, cam, None, impl, budget=Budget(count=k, min_s_v=0.0))
        assert out.n_rendered == min(k, counts[0])  # exactly k (capped by what is in view)
        g = _model(model.means.detach(), model.log_scales.detach(), model.quats.detach(),
                   model.opacity_logits.detach(), model.sigma_d.detach())
        out = _render_and_check(g, cam, None, impl, budget=Budget(count=k))  # default: capped at s_v = 1
        assert out.n_rendered == min(k, counts[1]) and out.s_v >= 1.0


def test_far_scene_matches_scene_at_origin_float64():
    """A small scene at 1e6 world units renders like the same scene at the origin (float64)."""
    base, _ = _scene("sigma_1e6")
    outs = []
    for off in (0.0, 1e6):
        g = _model(base.means.detach().double() + off, base.log_scales.detach(), base.quats.detach(),
                   base.opacity_logits.detach(), torch.rand(len(base), generator=torch.Generator().manual_seed(1)),
                   dtype=torch.float64)
        cam = _cam(center=(off, off, off), dtype=torch.float64)
        with use_impl("torch"):
            outs.append(render_lod(g, cam, 2.0, backend="cpu"))
    assert outs[0].n_rendered == outs[1].n_rendered > 0
    torch.testing.assert_close(outs[0].image, outs[1].image, rtol=1e-6, atol=1e-6)


@RENDER
@given(rows=st.lists(st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.5, 8.0), SIGMA_D,
                               st.floats(-50.0, 50.0)), min_size=0, max_size=6),
       s_list=st.lists(S_V, min_size=2, max_size=4), impl=st.sampled_from(["torch", "cpp"]),
       estimator=st.sampled_from(["ste", "sigmoid"]), sigma_only=st.booleans())
def test_render_lod_count_non_increasing_and_finite(rows, s_list, impl, estimator, sigma_only):
    if impl == "cpp" and not cpp_extension_available():
        impl = "torch"
    n = len(rows)
    means = torch.tensor([[x * z * 0.5, y * z * 0.4, z] for x, y, z, _, _ in rows]).reshape(n, 3)
    sig = torch.tensor([r[3] for r in rows]).reshape(n)
    lg = torch.tensor([r[4] for r in rows]).reshape(n)
    prev = None
    for s_v in sorted(s_list):
        g = _model(means, logits=lg, sigma_d=sig, seed=n)
        out = _render_and_check(g, _cam(), s_v, impl, eta_grad=EtaGradient(estimator, sigma_only=sigma_only))
        if prev is not None:
            assert out.n_rendered <= prev
        prev = out.n_rendered
