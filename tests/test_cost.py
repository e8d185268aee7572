"""Cost budgets: per-Gaussian splat cost, cost prefixes, budgets in cost and in predicted ms."""
from dataclasses import replace

import pytest
import torch

from clod_adapter.lod import rule as lod
from clod_adapter.lod.cost import FrameTimeModel, cost_prefix, cost_units, splat_cost
from clod_adapter.io.synthetic import make_cameras, make_ground_truth
from clod_adapter.lod.draw import lod_subset, render_lod
from clod_adapter.lod.view import view_lod
from clod_adapter.lod.budget import Budget


def _model(n=1500, seed=0, window=False, gains=False):
    g = make_ground_truth(n, seed=seed)
    gen = torch.Generator().manual_seed(seed + 7)
    g = g.with_sigma_d(0.2 + torch.rand(len(g), generator=gen))
    if gains:
        g = replace(g, log_scale_gain=0.6 * torch.rand(len(g), generator=gen),
                    opacity_logit_gain=torch.randn(len(g), generator=gen))
    if window:
        g = replace(g, lod=lod.LodSettings(fade="window"))
    return g


@pytest.fixture(scope="module")
def scene():
    return _model(), make_cameras(1, 2)


def _drawn_cost(view, sel, unit="ellipse_px"):
    """The cost a budget is measured in: what is drawn (Eq. 2), the base footprints (window fade:
    the level gains' growth is not part of the budget, see ``LodView.cost_count``)."""
    if view.settings.fade == "window":
        return float(splat_cost(view, sel.indices, unit=unit).sum())
    return float(splat_cost(view, sel.indices, level=sel.level, opacities=sel.opacities, unit=unit).sum())


@pytest.mark.parametrize("window,gains", [(False, False), (True, False), (True, True)])
def test_drawn_cost_within_budget(window, gains):
    g = _model(window=window, gains=gains)
    view = view_lod(g, make_cameras(1, 1)[0])
    total = float(splat_cost(view).sum())
    for share in (0.05, 0.2, 0.5, 0.9):
        sel = view.select(budget=Budget(cost=share, min_s_v=0.0))
        assert 0 < sel.indices.numel() < view.n_in_view
        assert _drawn_cost(view, sel) <= share * total + 1e-6
    absolute = 0.3 * total
    sel = view.select(budget=Budget(cost=absolute, min_s_v=0.0))
    assert _drawn_cost(view, sel) <= absolute + 1e-6


def test_count_monotone_and_nested(scene):
    g, cams = scene
    for cam in cams:
        view = view_lod(g, cam)
        prev = None
        for share in torch.linspace(0.02, 1.0, 10).tolist():
            sel = view.select(budget=Budget(cost=share, min_s_v=0.0))
            if prev is not None:
                assert sel.indices.numel() >= prev.numel()
                assert bool(torch.isin(prev, sel.indices).all())
            prev = sel.indices


def test_full_share_draws_every_gaussian_in_view(scene):
    g, cams = scene
    for cam in cams:
        view = view_lod(g, cam)
        sel = view.select(budget=Budget(cost=1.0, min_s_v=0.0))
        assert torch.equal(sel.mask, view.visible)
        r = render_lod(g, cam, budget=Budget(cost=1.0, min_s_v=0.0))
        assert r.n_rendered == view.n_in_view


def test_prefix_of_the_count_order(scene):
    """A cost budget draws exactly what the count budget of the same size draws (same s_v)."""
    g, cams = scene
    view = view_lod(g, cams[0])
    for share in (0.1, 0.3, 0.7):
        for min_s_v in (0.0, 1.0):
            sel = view.select(budget=Budget(cost=share, min_s_v=min_s_v))
            k = view.cost_count(Budget(cost=share, min_s_v=min_s_v))
            ref = view.select(budget=Budget(count=k, min_s_v=min_s_v))
            assert torch.equal(sel.indices, ref.indices) and sel.s_v == ref.s_v
            if min_s_v == 0.0:
                assert sel.indices.numel() == k
                # and it is a prefix of the critical order
                order = torch.sort(-view.critical[view.visible], stable=True).indices
                pool = torch.nonzero(view.visible).squeeze(1)
                assert torch.equal(torch.sort(pool[order[:k]]).values, sel.indices)


def test_budget_ms_monotone_and_consistent(scene):
    g, cams = scene
    view = view_lod(g, cams[1])
    tm = FrameTimeModel(c0_ms=1.0, per_cost_ms=2e-4, per_gaussian_ms=1e-3)
    prev = -1
    for ms in (0.5, 1.0, 2.0, 5.0, 10.0, 50.0, 1e4):
        sel = view.select(budget=Budget(ms=ms, min_s_v=0.0, time_model=tm))
        k = sel.indices.numel()
        assert k >= prev
        prev = k
        cost = _drawn_cost(view, sel)
        assert tm.ms(cost, k) <= ms + 1e-9 or k == 0
    assert prev == view.n_in_view
    assert view.select(budget=Budget(ms=0.5, min_s_v=0.0, time_model=tm)).indices.numel() == 0
    # cost_for_ms inverts ms
    assert tm.ms(tm.cost_for_ms(7.0, 100), 100) == pytest.approx(7.0)


def test_two_budgets_raise(scene):
    """A Budget names one amount; a frame takes a level or a budget; a bare number is refused (an
    int count and a float share would read alike)."""
    g, cams = scene
    cam = cams[0]
    for kw in ({"count": 100, "cost": 0.5}, {"cost": 0.5, "ms": 10.0}, {"share": 0.5, "ms": 10.0}, {},
               {"cost": -1.0}, {"share": 1.5}, {"count": 2.5}, {"in_view": 0.3, "time_model": object()}):
        with pytest.raises(ValueError):
            Budget(**kw)
    with pytest.raises(ValueError):
        render_lod(g, cam, 2.0, budget=Budget(cost=0.5))
    with pytest.raises(ValueError):
        lod_subset(g, cam, 2.0, budget=Budget(count=100))
    for bare in (100, 0.5):
        with pytest.raises(TypeError):
            render_lod(g, cam, budget=bare)
        with pytest.raises(TypeError):
            lod_subset(g, cam, budget=bare)


def test_splat_cost_matches_the_rasteriser(scene):
    """The tile cost of a drawn selection is the rasteriser's own tile-intersection count, and the
    ellipse cost is that of its projection (meta)."""
    g, cams = scene
    for window in (False, True):
        gg = replace(_model(gains=True), lod=lod.LodSettings(fade="window")) if window else g
        view = view_lod(gg, cams[0])
        for sel in (view.select(s_v=2.0), view.select(budget=Budget(cost=0.4, min_s_v=0.0)), view.select()):
            _, _, meta = view.rasterize(sel)
            ids = meta["visible_ids"]
            tiles = torch.zeros(gg.means.shape[0], dtype=torch.float64)
            tiles.index_add_(0, ids, torch.bincount(meta["flatten_ids"], minlength=ids.numel()).double())
            got = splat_cost(view, sel.indices, level=sel.level, opacities=sel.opacities, unit="tiles")
            assert torch.equal(got, tiles[sel.indices])
            ell = splat_cost(view, sel.indices, level=sel.level, opacities=sel.opacities)
            op = sel.opacities[torch.searchsorted(sel.indices, ids)]
            from clod_adapter.render.projection import VisibleProjection
            proj = VisibleProjection(ids, meta["radii"], meta["means2d"], meta["depths"], meta["conics"])
            ref = torch.zeros(gg.means.shape[0], dtype=torch.float64)
            ref[ids] = cost_units(proj, op, view.width, view.height)["ellipse_px"]
            torch.testing.assert_close(ell, ref[sel.indices], rtol=1e-6, atol=1e-4)  # float32 rounding, two paths


def test_base_opacity_cost_bounds_the_drawn_cost():
    """Selecting with the opacities before the fade over-estimates (never under-estimates) the cost."""
    g = _model(window=True, gains=True)
    view = view_lod(g, make_cameras(1, 1)[0])
    for share in (0.1, 0.5):
        sel = view.select(budget=Budget(cost=share, min_s_v=0.0))
        est = splat_cost(view, sel.indices, level=sel.level)
        drawn = splat_cost(view, sel.indices, level=sel.level, opacities=sel.opacities)
        # the drawn opacities come from the C++ kernel in double (lod.window_opacities): within
        # float32 rounding of the base ones where the fade is 1
        assert bool((drawn <= est * (1 + 1e-5) + 1e-9).all())
        assert bool((drawn < est * 0.99).any())  # the fade shrinks some footprints


def test_cost_prefix_static_cut():
    gen = torch.Generator().manual_seed(3)
    n = 200
    scores = torch.rand(n, generator=gen)
    cost = torch.rand(n, generator=gen, dtype=torch.float64) * 10
    visible = torch.rand(n, generator=gen) > 0.3
    prev = torch.empty(0, dtype=torch.long)
    for b in (0.0, 5.0, 50.0, 200.0, 1e9):
        idx = cost_prefix(scores, cost, visible, b)
        assert float(cost[idx].sum()) <= b
        assert bool(visible[idx].all()) and bool(torch.isin(prev, idx).all())
        if 0 < idx.numel() < int(visible.sum()):
            # a prefix of the score order: everything chosen outranks everything left in view
            rest = visible.clone()
            rest[idx] = False
            assert float(scores[idx].min()) >= float(scores[rest].max())
        prev = idx
    assert prev.numel() == int(visible.sum())
    # [V] costs aligned with visible.nonzero() give the same cut
    pool = torch.nonzero(visible).squeeze(1)
    assert torch.equal(cost_prefix(scores, cost[pool], visible, 50.0), cost_prefix(scores, cost, visible, 50.0))


def test_lod_subset_accepts_cost_budgets(scene):
    g, cams = scene
    a = lod_subset(g, cams[0], budget=Budget(cost=0.3, min_s_v=0.0))
    b = render_lod(g, cams[0], budget=Budget(cost=0.3, min_s_v=0.0))
    assert torch.equal(a.indices, torch.nonzero(b.mask).squeeze(1))
    c = lod_subset(g, cams[0], budget=Budget(ms=3.0))
    assert c.indices.numel() <= a.n_in_view


def test_eq2_cost_budget_is_exact(scene):
    """Eq. 2 drawing: the count is the largest whose drawn prefix (alpha'' at its own s_v) fits."""
    g, cams = scene
    view = view_lod(g, cams[0])
    total = float(splat_cost(view).sum())
    for share in (0.05, 0.3, 0.6):
        b = share * total
        sel = view.select(budget=Budget(cost=share, min_s_v=0.0))
        k = sel.indices.numel()
        assert _drawn_cost(view, sel) <= b + 1e-6
        nxt = view.select(budget=Budget(count=k + 1, min_s_v=0.0))
        assert _drawn_cost(view, nxt) > b


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_cost_kernel_equals_its_twin(dtype):
    """render/csrc/splat_cost.cpp (the merge tree's node costs) against splat_cost at level 0, on
    a model with Gaussians behind the camera, past the image's edge, under 1/255 opacity, needles,
    flats and huge ones: the same culls and the same pixels (rounding aside: a radius on an integer
    boundary may round to the other side in the twin's dtype)."""
    from types import SimpleNamespace

    from clod_adapter.lod.cut import node_costs_native
    from clod_adapter.render.native import load

    if load() is None:
        pytest.skip("the C++ kernels do not build here")
    g = _model(n=3000, seed=5)
    gen = torch.Generator().manual_seed(11)
    n = len(g)
    log_scales = g.log_scales + torch.randn(n, 3, generator=gen) * 1.5  # needles, flats, huge
    logits = torch.randn(n, generator=gen) * 4.0  # some below 1/255
    means = g.means + torch.randn(n, 3, generator=gen) * 2.0  # some behind, some off-image
    quats = torch.randn(n, 4, generator=gen)
    g = replace(g, means=means, log_scales=log_scales, opacity_logits=logits, quats=quats).to(dtype)
    for cam in make_cameras(1, 2):
        cam = SimpleNamespace(viewmat=cam.viewmat.to(dtype), K=cam.K.to(dtype), width=cam.width, height=cam.height)
        ours = node_costs_native(g, cam)
        twin = splat_cost(view_lod(g.with_sigma_d(None), cam), torch.arange(n))
        assert ours.dtype == twin.dtype == torch.float64 and ours.shape == (n,)
        assert 0 < int((twin > 0).sum()) < n and int((ours > 0).sum()) > 0  # culls on both sides
        same = torch.isclose(ours, twin, rtol=1e-5 if dtype == torch.float64 else 2e-3, atol=1e-9)
        assert int((~same).sum()) <= max(1, n // 500), (ours[~same][:5], twin[~same][:5])
        assert float(ours.sum()) == pytest.approx(float(twin.sum()), rel=1e-3)


def test_the_ordered_prefix_by_selection_equals_the_sorted_prefix():
    """``ordered_prefix_count``'s C++ selection and its twin (a stable sort of every score) give the
    same prefix: ties by position, NaN last, zero weights, budgets halfway between two sorted prefix
    sums at least 1e-3 apart (where the order of the sums' rounding cannot move the answer) and at
    the ends."""
    from clod_adapter.lod.cost import ordered_prefix_count, prefix_count
    from clod_adapter.render.native import load, use_impl

    if load() is None:
        pytest.skip("the C++ kernels do not build here")
    gen = torch.Generator().manual_seed(4)
    for m in (1, 50, 3000, 40000):
        s = torch.randn(m, generator=gen, dtype=torch.float64)
        s[torch.rand(m, generator=gen) < 0.2] = 0.5  # ties: broken by position
        s[torch.rand(m, generator=gen) < 0.01] = float("nan")  # last
        s[torch.rand(m, generator=gen) < 0.01] = float("inf")
        w = torch.rand(m, generator=gen, dtype=torch.float64) ** 3
        w[torch.rand(m, generator=gen) < 0.1] = 0.0
        ws = w[torch.sort(-s, stable=True).indices]
        cum = torch.cumsum(ws, 0)
        mids = ((torch.cat([cum.new_zeros(1), cum[:-1]]) + cum) / 2)[ws > 1e-3]  # half a weight from either sum
        picks = mids[torch.randint(len(mids), (40,), generator=gen)].tolist()
        for budget in picks + [-1.0, 0.0, float(cum[-1]) * 2]:
            with use_impl("torch"):
                twin = ordered_prefix_count(s, w, budget)
            assert twin == prefix_count(w[torch.sort(-s, stable=True).indices], budget)
            assert ordered_prefix_count(s, w, budget) == twin, (m, budget)
    assert ordered_prefix_count(torch.zeros(0), torch.zeros(0), 1.0) == 0


def test_base_costs_equal_their_twin():
    """``base_costs`` (one C++ pass over the model) is ``splat_cost`` at level 0 with the base
    opacities, to rounding, on the rows asked for."""
    from clod_adapter.lod.cost import base_costs
    from clod_adapter.render.native import load, use_impl

    if load() is None:
        pytest.skip("the C++ kernels do not build here")
    g = _model(n=3000, seed=6, gains=True)
    for cam in make_cameras(1, 2):
        v = view_lod(g, cam)
        idx = torch.nonzero(v.visible).squeeze(1).flip(0)  # any order
        ours = base_costs(v, idx)
        with use_impl("torch"):
            twin = base_costs(v, idx)
        torch.testing.assert_close(twin, splat_cost(v, idx))
        assert ours.shape == idx.shape and ours.dtype == torch.float64 and int((ours > 0).sum()) > len(idx) // 2
        same = torch.isclose(ours, twin, rtol=2e-3, atol=1e-9)
        assert int((~same).sum()) <= max(1, len(idx) // 500)
