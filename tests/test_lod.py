"""The CLoD-GS mechanism (clod_adapter.lod.rule): Eq. 2, the mask, eta estimators, L_reg, w_s."""

import math

import pytest
import torch

from clod_adapter.lod import rule as lod


def _setup(n=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    opac = torch.rand(n, generator=g) * 0.98 + 0.01
    d = torch.rand(n, generator=g)
    sigma = torch.rand(n, generator=g) * 2.0 + 0.05
    return opac, d, sigma


def test_eq2_matches_formula_and_bounds():
    opac, d, sigma = _setup()
    for s_v in (1.0, 2.5, 5.0):
        a = lod.lod_opacities(opac, d, sigma, s_v)
        ref = opac * torch.exp(-((d * s_v) ** 2) / (2 * sigma ** 2 + lod.DEFAULT_EPS))
        torch.testing.assert_close(a, ref, rtol=1e-6, atol=1e-7)
        assert bool((a >= 0).all()) and bool((a <= opac).all())


def test_relu_dead_zone_gives_zero_not_nan():
    opac = torch.tensor([0.5, 0.5])
    d = torch.tensor([0.3, 0.0])
    sigma = torch.tensor([-1.0, -1.0], requires_grad=True)
    a = lod.lod_opacities(opac, d, sigma, 3.0)
    assert a[0].item() == 0.0
    assert a[1].item() == pytest.approx(0.5)  # d' = 0: no attenuation
    a.sum().backward()
    assert torch.isfinite(sigma.grad).all()


def test_mask_is_threshold_and_monotone_in_s_v():
    opac, d, sigma = _setup(500)
    prev = None
    for s_v in torch.linspace(1, 20, 40).tolist():
        m = lod.lod_mask(opac, d, sigma, s_v, tau=0.005)
        a = lod.lod_opacities(opac, d, sigma, s_v)
        assert torch.equal(m, a > 0.005 * s_v) or int((m != (a > 0.005 * s_v)).sum()) <= 1
        if prev is not None:
            assert bool((m & ~prev).sum() == 0), "a Gaussian reappeared at a larger s_v"
        prev = m


def test_eta_estimators_value_and_gradient():
    opac, d, sigma0 = _setup(300)
    s_v = 4.0
    out = {}
    for est in lod.ETA_ESTIMATORS:
        sigma = sigma0.clone().requires_grad_(True)
        m = lod.lod_margin(opac, d, sigma, s_v)
        eta = lod.rendered_fraction(m, None, est)
        hard = (m > 0).float().mean().item()
        loss = lod.reg_loss(s_v, eta)
        if loss.requires_grad:
            loss.backward()
        grad = sigma.grad
        out[est] = (eta.item(), hard, 0.0 if grad is None else grad.abs().sum().item())
    assert out["paper"][0] == pytest.approx(out["paper"][1])
    assert out["paper"][2] == 0.0, "the paper's hard count must carry no gradient (the known trap)"
    assert out["ste"][0] == pytest.approx(out["ste"][1])  # value of the hard count
    assert out["ste"][2] > 0.0
    assert out["sigmoid"][2] > 0.0
    assert 0.0 <= out["sigmoid"][0] <= 1.0


def test_ste_gradient_pushes_sigma_d_down_when_too_many_rendered():
    opac = torch.full((100,), 0.9)
    d = torch.linspace(0.05, 1.0, 100)
    sigma = torch.full((100,), 3.0, requires_grad=True)
    s_v = 5.0
    m = lod.lod_margin(opac, d, sigma, s_v)
    eta = lod.rendered_fraction(m, None, "ste")
    assert eta.item() > lod.target_fraction(s_v)
    lod.reg_loss(s_v, eta).backward()
    assert bool((sigma.grad >= 0).all()) and sigma.grad.sum() > 0  # descent lowers sigma_d


def test_rendered_fraction_respects_frustum_and_empty():
    m = torch.tensor([1.0, -1.0, 2.0, -3.0])
    fr = torch.tensor([True, True, False, False])
    assert lod.rendered_fraction(m, fr, "paper").item() == pytest.approx(0.5)
    assert lod.rendered_fraction(m, torch.zeros(4, dtype=torch.bool), "ste").item() == 0.0
    with pytest.raises(ValueError):
        lod.rendered_fraction(m, None, "nope")


def test_reg_loss_and_weight():
    assert lod.reg_loss(1.0, torch.tensor(1.0)).item() == 0.0
    assert lod.reg_loss(4.0, torch.tensor(0.1)).item() == 0.0  # below target 4^-1.5 = 0.125
    assert lod.reg_loss(4.0, torch.tensor(0.5)).item() == pytest.approx(9 * (0.5 - 0.125) ** 2)
    assert lod.scale_weight(5.0, 5.0) == pytest.approx(0.25)
    assert lod.scale_weight(1.0, 5.0) == pytest.approx(0.81)


def test_sample_s_v_range_and_determinism():
    g1 = torch.Generator().manual_seed(3)
    g2 = torch.Generator().manual_seed(3)
    a = [lod.sample_s_v(5.0, g1) for _ in range(200)]
    b = [lod.sample_s_v(5.0, g2) for _ in range(200)]
    assert a == b
    assert min(a) >= 1.0 and max(a) <= 5.0 and max(a) - min(a) > 3.0
    with pytest.raises(ValueError):
        lod.sample_s_v(0.5)


def test_sample_s_v_log_spreads_steps_over_factors_of_s_v():
    """"log": ln s_v uniform, so [1, sqrt(max_sv)] gets half the steps (uniform: ~28 % at 5);
    same generator draws -> same u, so the two samplings are monotone maps of each other."""
    n = 4000
    gl, gu = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    lo = [lod.sample_s_v(5.0, gl, "log") for _ in range(n)]
    un = [lod.sample_s_v(5.0, gu, "uniform") for _ in range(n)]
    assert min(lo) >= 1.0 and max(lo) <= 5.0
    half = sum(s < 5.0 ** 0.5 for s in lo) / n
    assert abs(half - 0.5) < 0.03
    assert sum(s < 5.0 ** 0.5 for s in un) / n < 0.33
    assert all((a < b) == (c < d) for a, b, c, d in zip(lo, lo[1:], un, un[1:]))
    assert lod.sample_s_v(1.0, torch.Generator().manual_seed(1), "log") == 1.0
    with pytest.raises(ValueError, match="sampling"):
        lod.sample_s_v(5.0, None, "normal")


def test_normalized_distances_and_frustum():
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0], [0.0, 0.0, -5.0], [100.0, 0.0, 1.0]])
    vm = torch.eye(4)
    K = torch.tensor([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    fr = lod.in_frustum(means, vm, K, 100, 100)
    assert fr.tolist() == [True, True, False, False]
    d = lod.normalized_distances(means, lod.camera_center(vm), fr)
    torch.testing.assert_close(d[:2], torch.tensor([0.5, 1.0]))
    # empty frustum: normalise by the overall max, stay finite
    d2 = lod.normalized_distances(means, lod.camera_center(vm), torch.zeros(4, dtype=torch.bool))
    assert torch.isfinite(d2).all() and d2.max().item() == pytest.approx(1.0)
    # camera on every Gaussian: d' = 0, no NaN
    d3 = lod.normalized_distances(torch.zeros(3, 3), torch.zeros(3), torch.ones(3, dtype=torch.bool))
    assert torch.equal(d3, torch.zeros(3))


def test_init_sigma_d_keeps_attenuation_at_s_v_1():
    dmax = torch.rand(1000) * 0.9 + 0.1
    sd = lod.init_sigma_d(dmax, 0.995)
    d = dmax * torch.rand(1000)  # any view's d' <= its max
    att = lod.lod_opacities(torch.ones(1000), d, sd, 1.0)
    assert att.min().item() >= 0.995 - 1e-6
    att_max = lod.lod_opacities(torch.ones(1000), dmax, sd, 1.0)
    assert att_max.min().item() == pytest.approx(0.995, abs=1e-5)


def test_low_precision_evaluation_is_finite():
    opac, d, sigma = _setup(100)
    for dt in (torch.float16, torch.bfloat16):
        a = lod.lod_opacities(opac.to(dt), d.to(dt), sigma.to(dt), 1e4)
        m = lod.lod_margin(opac.to(dt), d.to(dt), sigma.to(dt), 1e4)
        assert a.dtype == dt and torch.isfinite(a.float()).all()
        assert bool((a.float() <= opac.to(dt).float() + 1e-3).all())
        assert not torch.isnan(m).any()


def test_lod_mask_equals_margin_sign():
    """lod.lod_mask (the per-frame test, rearranged and in place) agrees with its reference,
    ``lod_margin > 0``, including opacity 0, dead decays, d' = 0 and s_v far out."""
    g = torch.Generator().manual_seed(0)
    n = 20000
    opac = torch.rand(n, generator=g)
    opac[:50] = 0.0
    d = torch.rand(n, generator=g)
    d[50:100] = 0.0
    sigma = torch.randn(n, generator=g).abs() * 0.5
    sigma[100:200] = -sigma[100:200]
    for s_v in (1.0, 1.7, 5.0, 37.0, 1e4):
        ref = lod.lod_margin(opac, d, sigma, s_v) > 0
        got = lod.lod_mask(opac, d, sigma, s_v)
        assert got.dtype == torch.bool
        if s_v <= 5.0:  # a real mix of kept and dropped, so agreement means something
            assert 0 < int(ref.sum()) < n
        assert int((got != ref).sum()) == 0, f"s_v={s_v}: {int((got != ref).sum())} differ"


def _in_frustum_reference(means, vm, K, w, h, near=0.01):
    """The division form of the frustum test (the earlier implementation), float64."""
    pc = means.double() @ vm[:3, :3].double().T + vm[:3, 3].double()
    z = pc[:, 2]
    zs = torch.where(z > near, z, torch.ones_like(z))
    u = K[0, 0].double() * pc[:, 0] / zs + K[0, 2].double()
    v = K[1, 1].double() * pc[:, 1] / zs + K[1, 2].double()
    return (z > near) & (u >= 0) & (u < w) & (v >= 0) & (v < h)


def test_frustum_and_distances_fast_path_match_references():
    g = torch.Generator().manual_seed(3)
    means = torch.randn(5000, 3, generator=g, dtype=torch.float64) * 3
    means[:7] = torch.tensor([float("nan"), float("inf"), -float("inf"), 0, 0, 0, 0]).double()[:, None]
    ang = 0.3
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = torch.tensor([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
    vm[:3, 3] = torch.tensor([0.2, -0.1, 4.0])
    K = torch.tensor([[80.0, 0, 40], [0, 90.0, 30], [0, 0, 1]], dtype=torch.float64)
    fr = lod.in_frustum(means, vm, K, 80, 60)
    ref = _in_frustum_reference(means, vm, K, 80, 60)
    assert 500 < int(ref.sum()) < 5000 and not fr[:3].any()  # non-finite centres are outside
    assert torch.equal(fr, ref)
    # the no-gradient distances (cached rows) equal the autograd form
    c = lod.camera_center(vm)
    fast = lod.normalized_distances(means[7:], c, fr[7:])
    slow = lod.normalized_distances(means[7:].clone().requires_grad_(True), c, fr[7:]).detach()
    torch.testing.assert_close(fast, slow, rtol=1e-12, atol=1e-12)


def test_centre_columns_follow_in_place_updates():
    means = torch.rand(100, 3)
    a = lod.centre_columns(means, torch.float32)
    assert lod.centre_columns(means, torch.float32) is a  # cached
    means.add_(1.0)  # an optimiser step: the version changes, the rows are made again
    b = lod.centre_columns(means, torch.float32)
    assert b is not a and torch.equal(b, means.t())
    d = lod.normalized_distances(means, torch.zeros(3), torch.ones(100, dtype=torch.bool))
    torch.testing.assert_close(d * means.norm(dim=1).max(), means.norm(dim=1))
