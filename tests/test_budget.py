"""Exact budgets: critical s_v per Gaussian and the k-th-largest selection."""
from dataclasses import replace

import pytest
import torch

from clod_adapter.lod import rule as lod
from clod_adapter.lod.budget import Budget, as_budget, budget_count, critical_s_v, select_budget


def _rand(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.99 + 0.005
    d = torch.rand(n, generator=g, dtype=torch.float64)
    sigma = torch.rand(n, generator=g, dtype=torch.float64) * 1.5 - 0.1  # some dead (<= 0)
    return opac, d, sigma


def test_critical_is_the_root_of_the_margin():
    opac, d, sigma = _rand()
    crit = critical_s_v(opac, d, sigma)
    assert bool((crit > 0).all()) and torch.isfinite(crit).all()
    below = lod.lod_margin(opac, d, sigma, crit * (1 - 1e-7))
    above = lod.lod_margin(opac, d, sigma, crit * (1 + 1e-7))
    assert bool((below > 0).all()) and bool((above < 0).all())


def test_count_at_s_v_matches_critical():
    opac, d, sigma = _rand(seed=1)
    crit = critical_s_v(opac, d, sigma)
    for s in torch.linspace(0.5, 30, 50).tolist():
        mask = lod.lod_mask(opac, d, sigma, s)
        assert int(mask.sum()) == int((crit > s).sum())


def test_no_attenuation_closed_form():
    opac = torch.tensor([0.5, 0.9], dtype=torch.float64)
    crit = critical_s_v(opac, torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64), tau=0.01)
    torch.testing.assert_close(crit, opac / 0.01)


@pytest.mark.parametrize("k", [0, 1, 7, 199, 200])
def test_select_budget_exact_k(k):
    opac, d, sigma = _rand(200, seed=2)
    crit = critical_s_v(opac, d, sigma)
    idx, s_v = select_budget(crit, k)
    assert idx.numel() == k
    assert int((crit > s_v).sum()) == k
    if 0 < k < 200:
        assert crit[idx].min() >= crit[~torch.isin(torch.arange(200), idx)].max()


def test_select_budget_ties_and_candidates():
    crit = torch.tensor([3.0, 2.0, 2.0, 2.0, 1.0], dtype=torch.float64)
    idx, s_v = select_budget(crit, 2)
    assert idx.tolist() == [0, 1]  # tie broken by index
    assert s_v == 2.0
    cand = torch.tensor([False, True, True, False, True])
    idx, s_v = select_budget(crit, 2, cand)
    assert idx.tolist() == [1, 2]
    idx, _ = select_budget(crit, 10, cand)
    assert idx.tolist() == [1, 2, 4]


def test_budget_count():
    assert budget_count(0.25, 100) == 25
    assert budget_count(1.0, 100) == 100
    assert budget_count(30, 100) == 30
    assert budget_count(300, 100) == 100
    with pytest.raises(ValueError):
        budget_count(-1, 10)


def test_render_lod_budget_renders_exactly_k():
    from clod_adapter.lod.draw import render_lod
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth

    gt = make_ground_truth(600, seed=1)
    g = gt.with_sigma_d(torch.rand(600, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.05)
    cam = make_cameras(1, 1, 64, 48)[0]
    full = render_lod(g, cam, None).n_rendered
    for k in (0, 1, 50, 300, full, 10_000):
        out = render_lod(g, cam, budget=Budget(count=k, min_s_v=0.0))
        assert out.n_rendered == min(k, full)
        assert torch.isfinite(out.image).all()
    out = render_lod(g, cam, budget=Budget(share=0.5, min_s_v=0.0))
    assert out.n_rendered == min(300, full)


def test_one_budget_type_one_meaning():
    """A count of 1 is one Gaussian and a share of 1.0 all of them, through every way in; a
    Budget names one amount; the renderer hook's plain numbers read as an int count or a float
    share; ``in_view`` is a share of the Gaussians in view."""
    from clod_adapter.lod.draw import lod_subset, render_lod
    from clod_adapter.lod.view import view_lod
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth

    gt = make_ground_truth(600, seed=1)
    g = gt.with_sigma_d(torch.rand(600, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.05)
    cam = make_cameras(1, 1, 64, 48)[0]
    v = view_lod(g, cam)
    one, every = Budget(count=1, min_s_v=0.0), Budget(share=1.0, min_s_v=0.0)
    assert render_lod(g, cam, budget=one).n_rendered == 1 == lod_subset(g, cam, budget=one).indices.numel()
    assert render_lod(g, cam, budget=every).n_rendered == v.n_in_view > 1
    assert as_budget(1) == Budget(count=1) and as_budget(1.0) == Budget(share=1.0)
    assert as_budget(7, 0.0) == Budget(count=7, min_s_v=0.0) and as_budget(None) is None
    with pytest.raises(ValueError):
        as_budget(2.5)  # a float is a share
    with pytest.raises(TypeError):
        as_budget("10")
    half = Budget(in_view=0.5, min_s_v=0.0)
    assert half.of(600, v.n_in_view) == round(0.5 * v.n_in_view)
    assert render_lod(g, cam, budget=half).n_rendered == round(0.5 * v.n_in_view)
    with pytest.raises(ValueError):
        half.of(600)  # a share of the view needs the view
    with pytest.raises(ValueError):
        Budget(ms=5.0).of(600)  # a time budget is not a count
    assert Budget(cost=0.3).floored(2.0) == Budget(cost=0.3, min_s_v=2.0)
    assert (one.kind, one.counts, Budget(ms=3).kind, Budget(ms=3).counts) == ("count", True, "ms", False)


def test_render_lod_budget_is_a_cap_at_s_v_1():
    from clod_adapter.lod.draw import render_lod
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth

    gt = make_ground_truth(600, seed=1)
    g = gt.with_sigma_d(torch.rand(600, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.05)
    cam = make_cameras(1, 1, 64, 48)[0]
    at1 = render_lod(g, cam, 1.0).n_rendered
    assert 0 < at1 < render_lod(g, cam, None).n_rendered  # the decay cuts some at s_v = 1
    big = render_lod(g, cam, budget=Budget(count=10_000))
    assert big.s_v == 1.0 and big.n_rendered == at1  # capped at the full-detail level
    small = render_lod(g, cam, budget=Budget(count=at1 // 2))
    assert small.n_rendered == at1 // 2 and small.s_v > 1.0


def test_select_budget_matches_a_stable_sort():
    """The O(N) selection returns what a stable descending sort does (ties broken by index),
    over many ties, candidate masks and k."""
    from clod_adapter.lod.budget import _select_budget_sorted

    g = torch.Generator().manual_seed(0)
    for trial in range(60):
        n = int(torch.randint(1, 300, (1,), generator=g))
        vals = torch.randint(0, 12, (n,), generator=g).double() / 4  # many ties, zeros
        if trial % 3 == 0:
            vals = torch.rand(n, generator=g, dtype=torch.float64)
        cand = torch.rand(n, generator=g) < 0.7 if trial % 2 else None
        m = n if cand is None else int(cand.sum())
        for k in sorted({0, 1, m // 3, m // 2, max(m - 1, 0), m, m + 5}):
            idx, s_v = select_budget(vals, k, cand)
            pool = torch.arange(n) if cand is None else torch.arange(n)[cand]
            ref_idx, ref_s = _select_budget_sorted(pool, vals[pool], max(0, min(k, m))) if m else (pool, 1.0)
            assert torch.equal(idx, ref_idx), (trial, k)
            assert s_v == ref_s, (trial, k)


def _full_projection_first(view):
    """``view`` with its whole model projected (the path a budget took before it projected only
    a prefix of its order)."""
    view.visible
    return view


@pytest.mark.parametrize("fade", ["window", "eq2"])
def test_a_budget_projects_a_prefix_and_selects_what_the_whole_projection_selects(fade):
    """A count budget solved on a prefix of the order (only it projected) draws the same
    Gaussians at the same s_v as the budget solved on the whole model's projection, with many
    Gaussians behind the camera or off the image, a few with overflowing footprints (in the
    frustum, never in view) and ties; and projects fewer than the whole model for a small one."""
    from dataclasses import replace as dc_replace

    from clod_adapter.lod.view import view_lod
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth

    n = 3000
    gen = torch.Generator().manual_seed(3)
    gt = make_ground_truth(n, seed=4)
    cam = make_cameras(1, 1, 64, 48)[0]
    centre = lod.camera_center(cam.viewmat.to(gt.means.dtype))
    means = gt.means.clone()
    means[::2] = 2.0 * centre - means[::2]  # half of them mirrored behind the camera
    means[1::4, 0] += 50.0  # a quarter off to the side of the image
    forward = cam.viewmat.to(gt.means.dtype)[2, :3]
    means[:5] = centre + 2.0 * forward  # in the middle of the image, first in the order ...
    log_scales = gt.log_scales.clone()
    log_scales[:5] = 60.0  # ... with overflowing footprints: culled from view, in the frustum
    sigma = (torch.rand(n, generator=gen) * 0.5 + 0.05).to(gt.means.dtype)
    sigma[:5] = 50.0
    sigma[100:140] = sigma[100]  # ties in the order
    g = dc_replace(gt, means=means, log_scales=log_scales).with_sigma_d(sigma)
    g = dc_replace(g, lod=dc_replace(g.lod or lod.LodSettings(), fade=fade))
    ref_view = _full_projection_first(view_lod(g, cam))
    n_vis = ref_view.n_in_view
    assert 0 < n_vis < n // 3 and not bool(ref_view.visible[:5].any()) and bool(ref_view.frustum[:5].all())
    for k in (0, 1, 2, 6, 17, n_vis // 5, n_vis // 2, n_vis - 1, n_vis, n_vis + 1, n):
        for min_s_v in (0.0, 1.0, 3.0):
            fresh = view_lod(g, cam)
            a = fresh.select(budget=Budget(count=k, min_s_v=min_s_v))
            b = _full_projection_first(view_lod(g, cam)).select(budget=Budget(count=k, min_s_v=min_s_v))
            assert torch.equal(a.indices, b.indices), (k, min_s_v)
            assert a.s_v == b.s_v and torch.equal(a.opacities, b.opacities), (k, min_s_v)
            if k == 17 and min_s_v == 0.0:  # a small budget projects only its prefix
                assert fresh._proj[2] is not None and fresh._proj[0].ids.numel() < n // 4


def _window_model(n: int, seed: int, share_small: float = 0.5):
    """A window-fade model in which ``share_small`` of the Gaussians have a tiny ``sigma_d``, so
    their critical s_v is below 1 (the paper's mask drops them at s_v = 1; full detail draws them)."""
    from clod_adapter.io.synthetic import make_ground_truth

    g = make_ground_truth(n, seed=seed)
    gen = torch.Generator().manual_seed(seed + 3)
    sd = 0.2 + torch.rand(n, generator=gen)
    sd[torch.rand(n, generator=gen) < share_small] = 1e-3
    return replace(g.with_sigma_d(sd), lod=lod.LodSettings(fade="window"))


def test_a_window_budget_never_draws_more_than_k():
    """With the window fade, full detail draws every Gaussian in view, also those whose critical
    s_v is below 1 in the view. A budget between what the mask keeps at s_v = 1 and every Gaussian in
    view draws exactly k (at the solved s_v below 1), not full detail; one that holds every
    Gaussian in view draws full detail."""
    from clod_adapter.lod.draw import render_lod
    from clod_adapter.lod.view import view_lod
    from clod_adapter.io.synthetic import make_cameras

    g = _window_model(800, 0)
    cam = make_cameras(1, 1, 64, 48)[0]
    v = view_lod(g, cam)
    n, below = v.n_in_view, int(((v.critical <= 1.0) & v.visible).sum())
    assert n > 100 and below > n // 4
    full = render_lod(g, cam, 1.0)
    assert full.n_rendered == n
    for k in (n - 1, n - below // 2, n - below, n - below - 10, 5):
        r = render_lod(g, cam, budget=Budget(count=k))  # default min_s_v = 1
        assert r.n_rendered == k, (k, n, below)
        assert torch.isfinite(r.image).all()
    whole = render_lod(g, cam, budget=Budget(count=n))
    assert whole.s_v == 1.0 and torch.equal(whole.image, full.image)
