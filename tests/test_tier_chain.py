"""A chain of merged tiers (model -> parents -> their parents): the hand-over rule, continuity
across every hand-over, the .ply elements, budgets, and every consumer against render_lod."""
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from clod_adapter.train import tiers
from clod_adapter.lod.draw import COUNT_TAKE_SHARE, chain_weights, lod_subset, render_lod, tier_chain, tier_reach
from clod_adapter.lod.view import view_lod
from clod_adapter.lod.budget import Budget
from clod_adapter.io.ply import PlyFormatError, read_ply, write_ply
from clod_adapter.io.synthetic import make_cameras

from test_tiers import _adapted

#: the chain's hand-overs: model -> tier 1 from s_v 2 (tier 1 at its own 1.25), tier 1 -> tier 2
#: from its own s_v 2.5 (tier 2 at 1.5)
SWITCHES = ((2.0, 1.25), (2.5, 1.5))


#: the coarsest tier's own window width (a tier may fade over a window of its own: docs/lod_rule.md)
COARSE_FADE = 4.0


@pytest.fixture(scope="module")
def chain():
    t2 = _adapted(60, 3)
    t2 = replace(t2, lod=replace(t2.lod, fade_width=COARSE_FADE))
    t1 = tiers.attach(_adapted(300, 2), t2, *SWITCHES[1])
    return tiers.attach(_adapted(1200, 0), t1, *SWITCHES[0]), make_cameras(1, 2)


FADE = 1.25  # tiers.attach's tier_fade


def _model_s_v_of_tier1(s1: float) -> float:
    """The model's s_v where tier 1 is at its own ``s1 >= 1.25`` (past the first cross-fade)."""
    return s1 * FADE * SWITCHES[0][0] / SWITCHES[0][1]


def _model_s_v_of_tier2(s2: float) -> float:
    """The model's s_v where tier 2 is at its own ``s2 >= 1.5`` (past both cross-fades)."""
    return _model_s_v_of_tier1(s2 * FADE * SWITCHES[1][0] / SWITCHES[1][1])


def test_weights_sum_to_one_and_only_neighbours_share_the_image(chain):
    g, _ = chain
    settings = [m.lod for m in tier_chain(g)]
    assert len(settings) == 3 and tier_reach(g) == pytest.approx(_model_s_v_of_tier2(1.0))
    for s in np.geomspace(1.0, 40.0, 80):
        ws = chain_weights(float(s), settings)
        w = [x for x, _ in ws]
        assert sum(w) == pytest.approx(1.0) and all(x >= 0 for x in w)
        drawn = [k for k, x in enumerate(w) if x > 0]
        assert drawn == list(range(drawn[0], drawn[-1] + 1)) and len(drawn) <= 2
    assert [x for x, _ in chain_weights(1.5, settings)] == [1.0, 0.0, 0.0]
    deep = chain_weights(_model_s_v_of_tier2(3.0), settings)
    assert deep[2][0] == pytest.approx(1.0) and deep[2][1] == pytest.approx(3.0)


def test_each_tier_drawn_alone_between_the_hand_overs(chain):
    g, cams = chain
    t1, t2 = g.parents, g.parents.parents
    for cam in cams:
        # tier 1 alone (past the first cross-fade, before its own): model s_v 2.6 -> tier 1 at 1.3
        r1 = render_lod(g, cam, 2.6)
        assert torch.equal(r1.image, render_lod(replace(t1, parents=None), cam, 1.3).image)
        assert r1.indices.numel() == 0 and r1.n_parents == r1.n_rendered > 0
        # tier 2 alone far down the range
        s = _model_s_v_of_tier2(2.0)
        r2 = render_lod(g, cam, s)
        assert torch.equal(r2.image, render_lod(t2, cam, 2.0).image) and r2.n_parents == r2.n_rendered
        # in tier 1's own cross-fade both tier 1 and tier 2 are drawn, the model is not
        mid = render_lod(g, cam, _model_s_v_of_tier1(2.5 * 1.1))
        sub = lod_subset(g, cam, _model_s_v_of_tier1(2.5 * 1.1))
        assert sub.indices.numel() == 0 and sub.tier_indices[0].numel() > 0 and sub.tier_indices[1].numel() > 0
        assert mid.n_parents == sub.tier_indices[0].numel() + sub.tier_indices[1].numel() == mid.n_rendered


def test_every_hand_over_is_continuous(chain):
    """The image changes by small steps across each hand-over (cross-fade in ln s_v): the largest
    step of a fine sweep through both is far below the jump of switching at once."""
    g, cams = chain
    cam = cams[0]
    for lo, hi in ((2.0, 2.5), (_model_s_v_of_tier1(2.5), _model_s_v_of_tier1(2.5 * FADE))):
        svs = np.geomspace(lo * 0.98, hi * 1.02, 41)
        imgs = [render_lod(g, cam, float(s)).image for s in svs]
        steps = [float((a - b).abs().mean()) for a, b in zip(imgs, imgs[1:])]
        jump = float((imgs[0] - imgs[-1]).abs().mean())
        assert jump > 0 and max(steps) < jump / 5, (lo, max(steps), jump)


def test_ply_round_trip_keeps_the_chain(chain, tmp_path):
    g, cams = chain
    path = write_ply(tmp_path / "chain.ply", g)
    back = read_ply(path)
    got, want = tier_chain(back), tier_chain(g)
    assert [len(t) for t in got] == [len(t) for t in want] == [1200, 300, 60]
    assert back.parents.lod.tier_s_v == SWITCHES[1][0] and back.parents.lod.tier_start == SWITCHES[1][1]
    assert back.parents.parents.lod.tier_s_v == 0.0
    # each tier's own window width: the coarsest tier's is its own, the others the model's
    assert [t.lod.fade_width for t in got] == [g.lod.fade_width, g.lod.fade_width, COARSE_FADE] != \
        [g.lod.fade_width] * 3
    for a, b in zip(got, want):
        assert torch.equal(a.sigma_d, b.sigma_d) and torch.equal(a.means, b.means)
    for s in (1.5, 2.2, 3.5, 4.6, 12.0):
        assert torch.equal(render_lod(back, cams[0], s).image, render_lod(g, cams[0], s).image)
    t2 = back.parents.parents
    narrow = replace(back, parents=replace(back.parents, parents=replace(t2, lod=replace(t2.lod, fade_width=0.5))))
    far = _model_s_v_of_tier2(3.0)  # the coarsest tier alone: its window width is what is drawn
    assert not torch.equal(render_lod(narrow, cams[0], far).image, render_lod(back, cams[0], far).image)
    from clod_adapter.evaluate.storage import ply_bytes

    assert ply_bytes(g) == path.stat().st_size
    # a second tier's element without the first: refused, naming the file
    import plyfile

    ply = plyfile.PlyData.read(str(path))
    bad = plyfile.PlyData([ply["vertex"], ply["lod_parent_2"]], text=False, comments=ply.comments)
    bad.write(str(tmp_path / "bad.ply"))
    with pytest.raises(PlyFormatError, match="bad.ply.*lod_parent_2.*without .lod_parent. before"):
        read_ply(tmp_path / "bad.ply")


def test_cost_budgets_walk_down_the_chain_and_fit(chain):
    """Cost budgets on a chain: the drawn tier only gets coarser as the budget shrinks, a tier
    drawn is drawn within the same absolute budget, and a small budget lands on the last tier."""
    g, cams = chain
    cam = cams[0]
    full = view_lod(replace(g, parents=None), cam).full_cost()
    depth_prev, shares = 0, [0.9, 0.6, 0.3, 0.15, 0.08, 0.04, 0.02, 0.01]
    for b in shares:
        sub = lod_subset(g, cam, budget=Budget(cost=b))
        depth = 0 if sub.indices.numel() else 1 + [i for i, t in enumerate(sub.tier_indices) if t is not None][0]
        assert depth >= depth_prev, (b, depth, depth_prev)
        depth_prev = depth
        r = render_lod(g, cam, budget=Budget(cost=b))
        assert r.n_rendered == sub.means.shape[0]
        if depth:
            tier = tier_chain(g)[depth]
            v = view_lod(tier, cam)
            idx = sub.tier_indices[depth - 1]
            # the tier's own cost-budget solution for the same absolute budget (its fit: test_budget.py)
            sel = v.select(budget=Budget(cost=max(b * full, 1 + 1e-6), min_s_v=tier_chain(g)[depth - 1].lod.tier_start))
            assert torch.equal(sel.indices, idx)
    assert depth_prev == 2


@pytest.mark.parametrize("s_v", [1.5, 2.2, 2.6, 3.3, 4.6, 12.0])
def test_consumers_draw_what_render_lod_draws(chain, s_v):
    """The renderer hook, lod_subset, bake and the numpy reference draw render_lod's rows on a
    chain, below, in and past each hand-over."""
    import importlib.util
    from pathlib import Path

    from clod_adapter import clod_kwargs, clod_rasterization

    g, cams = chain
    cam = cams[0]
    ref = render_lod(g, cam, s_v, backend="cpu")
    col, alp, meta = clod_rasterization(g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat[None],
                                        cam.K[None], cam.width, cam.height, sh_degree=g.sh_degree,
                                        **clod_kwargs(g), s_v=s_v, backend="cpu")
    torch.testing.assert_close(col[0], ref.image, rtol=0, atol=1e-6)
    assert meta["lod_n_rendered"] == [ref.n_rendered] and meta["lod_n_parents"] == [ref.n_parents]
    sub = lod_subset(g, cam, s_v)
    assert sub.means.shape[0] == ref.n_rendered and len(sub.tier_indices) == 2
    for a, b in zip(meta["lod_tier_indices"][0], sub.tier_indices):
        assert torch.equal(a, b if b is not None else a.new_zeros(0))
    spec = importlib.util.spec_from_file_location("reference_lod", Path(__file__).parents[1] / "examples"
                                                  / "reference_lod_chain.py")
    refmod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(refmod)
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        m = refmod.read_model(write_ply(Path(d) / "c.ply", g))
    out = refmod.draw_tiered(m, cam.viewmat.double().numpy(), cam.K.double().numpy(), cam.width, cam.height, s_v)
    got = [out["model"]] + out["tiers"]
    want = [sub.indices] + sub.tier_indices
    ops = torch.split(sub.opacities, [0 if w is None else w.numel() for w in want])
    for d, w, o in zip(got, want, ops):
        assert (d is None) == (w is None or (w.numel() == 0 and d is None))
        if d is not None and w is not None:
            assert set(d["ids"].tolist()) == set(w.tolist())
            order = np.argsort(d["ids"])
            np.testing.assert_allclose(d["opacities"][order], o.double().numpy()[np.argsort(w.numpy())],
                                       rtol=1e-4, atol=1e-6)
    from clod_adapter.export.bake import bake

    baked, info = bake(g, [cam], s_v=s_v, opacity="mean", return_info=True)
    assert info.n_parents == ref.n_parents and len(baked) == ref.n_rendered


def test_adapt_config_takes_descending_shares():
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().parent_share == tiers.DEFAULT_SHARES
    assert AdaptConfig(parent_share=0.1).parent_share == (0.1,)
    assert AdaptConfig(parent_share=0).parent_share == () and AdaptConfig(schedule="paper").parent_share == ()
    for bad in ((0.1, 0.3), (1.2,), (0.5, 0.5)):
        with pytest.raises(ValueError, match="parent_share"):
            AdaptConfig(parent_share=bad)


def test_count_budgets_hand_over_in_every_consumer(chain):
    """A count budget past a hand-over draws the next tier (from its tier_start level on), alone,
    never more than the budget: render_lod, lod_subset, the renderer hook and bake agree; a budget of every Gaussian
    in view draws the model's own."""
    from clod_adapter import clod_kwargs, clod_rasterization
    from clod_adapter.export.bake import bake

    g, cams = chain
    cam = cams[0]
    every = view_lod(replace(g, parents=None), cam).n_in_view
    big = render_lod(g, cam, budget=Budget(count=every))
    assert big.n_parents == 0 and torch.equal(big.image, render_lod(replace(g, parents=None), cam, budget=Budget(count=every)).image)
    depths = []
    for b in (0.8, 0.5, 0.2, 0.05, 0.01):
        own = view_lod(replace(g, parents=None), cam).select(budget=Budget(share=b))
        r = render_lod(g, cam, budget=Budget(share=b))
        sub = lod_subset(g, cam, budget=Budget(share=b))
        drawn = [0] * bool(sub.indices.numel()) + [1 + i for i, t in enumerate(sub.tier_indices) if t is not None]
        depths.append(drawn[-1])
        assert len(drawn) == 1, drawn  # one tier
        assert r.n_rendered <= own.indices.numel() and len(sub.means) == r.n_rendered
        col, _, meta = clod_rasterization(g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat[None],
                                          cam.K[None], cam.width, cam.height, sh_degree=g.sh_degree,
                                          **clod_kwargs(g), budget=b, backend="cpu")
        torch.testing.assert_close(col[0], r.image, rtol=0, atol=1e-6)
        assert meta["lod_n_parents"] == [r.n_parents] and meta["lod_s_v"][0] == pytest.approx(r.s_v)
        baked, info = bake(g, [cam], budget=Budget(share=b), opacity="mean", return_info=True)
        assert info.n_parents == r.n_parents and len(baked) == r.n_rendered
    assert depths == sorted(depths) and depths[-1] >= 1


def _budget(kind: str, v) -> Budget:
    """One parametrised budget: ``"count"`` an int count or a float share of the model."""
    if kind == "count":
        return Budget(count=v) if isinstance(v, int) else Budget(share=v)
    return Budget(**{kind: v})


def _walk_solving_every_tier(g, cam, budget: Budget):
    """docs/lod_rule.md's budget hand-over, literally: solve the budget in each tier, and pass it to
    the next tier while that tier, as the s_v rule first draws it alone, holds it (count: draws at
    least COUNT_TAKE_SHARE of the count tier 0 draws, and is asked for that count; cost: costs at
    least the budget; ms: predicted at least that long). A start at the tier's full detail
    (tier_start <= 1) and a cost share's full cost, where the budget passes on, are estimated from
    a sample (LodView.full_detail_estimate; models of COST_SAMPLE_MIN or more). Returns
    ``[(depth, selection)]``, the one tier drawn."""
    from clod_adapter.lod.cost import DEFAULT_FRAME_TIME_MODEL, splat_cost

    tiers_ = tier_chain(g)
    views = [view_lod(replace(t, parents=None), cam) for t in tiers_]

    def estimate(k):  # tier k's full detail as the walk costs it (its accuracy: test_tiers.py)
        return views[k].full_detail_estimate()

    b = budget.cost
    sel, depth = views[0].select(budget=budget), 0
    if b is not None and b <= 1.0:
        b = max(b * estimate(0)[0], 1.0 + 1e-6)  # absolute from the first tier below on
    k0 = int(sel.indices.numel())  # a count budget: tier 0's count, asked of every tier below
    while depth + 1 < len(tiers_):
        start_s = tiers_[depth].lod.tier_start
        start = views[depth + 1].select(start_s)
        if start_s <= 1.0:
            cost, drawn = estimate(depth + 1)
        else:
            cost = float(splat_cost(views[depth + 1], start.indices, level=start.level,
                                    opacities=start.opacities).sum())
            drawn = int(start.indices.numel())
        kw = dict(cost=b) if b is not None else dict(ms=budget.ms)
        if budget.counts:  # taken over where the tier draws at least COUNT_TAKE_SHARE of it
            fits = start.indices.numel() >= min(k0, max(1, math.ceil(COUNT_TAKE_SHARE * k0 - 1e-9)))
            kw = dict(count=k0)
        elif b is not None:
            fits = b <= cost
        else:
            fits = budget.ms <= DEFAULT_FRAME_TIME_MODEL.ms(cost, drawn)
        if not fits:
            break
        depth += 1
        sel = views[depth].select(budget=Budget(**kw, min_s_v=start_s))
    return [(depth, sel)]


def _rows(sub, depth):
    """The rows of tier ``depth`` a LodSubset draws (None: none)."""
    return sub.indices if depth == 0 else sub.tier_indices[depth - 1]


@pytest.mark.parametrize("kind,values", [("count", [900, 400, 150, 60, 20, 3, 0.3, 0.02]),
                                         ("cost", [0.9, 0.5, 0.2, 0.08, 0.03, 0.01]),
                                         ("ms", [40.0, 5.0, 2.5, 2.0, 1.0, 0.1])])
@pytest.mark.parametrize("starts", ["chain", (1.0, 1.0), "sampled"])
def test_budgets_solve_only_the_tier_they_end_in_as_the_rule_walks(chain, kind, values, starts, monkeypatch):
    """render_lod's budget walk solves only the tier it ends in (and passes a count on without
    solving it where the rule gives it: each tier first drawn alone at its full detail,
    ``tier_start`` 1, as ``clod-adapt`` links them): the same tiers, rows and opacities as solving
    the budget in every tier on the way, at every depth of the chain; a count budget between two
    tiers draws the next tier alone or cuts the finer one. ``"sampled"``: the tiers handed over at
    their full detail and costed from every 3rd Gaussian (the chain's tiers are below
    COST_SAMPLE_MIN, lowered here so the estimate is what is walked)."""
    from clod_adapter.lod import cost as lod_cost

    g, cams = chain
    if starts == "sampled":
        monkeypatch.setattr(lod_cost, "COST_SAMPLE_MIN", 50)
        monkeypatch.setattr(lod_cost, "COST_SAMPLE_STEP", 3)
        starts = (1.0, 1.0)
    if starts != "chain":  # the same tiers handed over at their full detail
        t1 = g.parents
        t1 = replace(t1, lod=replace(t1.lod, tier_start=starts[1]))
        g = replace(g, parents=t1, lod=replace(g.lod, tier_start=starts[0]))
    depths = set()
    for cam in cams:
        for v in values:
            ref = _walk_solving_every_tier(g, cam, _budget(kind, v))
            r = render_lod(g, cam, budget=_budget(kind, v), backend="cpu")
            depths |= {d for d, _ in ref}
            sub = lod_subset(g, cam, budget=_budget(kind, v))
            for depth, sel in ref:
                got = r.selection.indices if (depth == 0 and len(ref) == 1) else _rows(sub, depth)
                assert got is not None and torch.equal(got, sel.indices), (kind, v, depth)
            n = sum(int(sel.indices.numel()) for _, sel in ref)
            assert r.n_rendered == n and r.n_parents == sum(int(s.indices.numel()) for d, s in ref if d), (kind, v)
            if ref[-1][0]:  # the tiers' rows drawn with the tiers' own opacities
                torch.testing.assert_close(sub.opacities, torch.cat([s.opacities for _, s in ref]), rtol=0, atol=0)
            if kind == "count":  # the renderer hook walks the same way (count budgets are its only budgets)
                from clod_adapter import clod_kwargs, clod_rasterization

                _, _, meta = clod_rasterization(g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat[None],
                                                cam.K[None], cam.width, cam.height, sh_degree=g.sh_degree,
                                                **clod_kwargs(g), budget=v, backend="cpu")
                for depth, sel in ref:
                    hook = meta["lod_indices"][0] if depth == 0 else meta["lod_tier_indices"][0][depth - 1]
                    assert torch.equal(hook, sel.indices), (v, depth)
    assert depths == {0, 1, 2}, depths


def test_export_of_a_chain(tiny_adapted, tiny_model, tmp_path):
    """clod-export of a model with two merged tiers: the extended .ply keeps the chain (read back by
    splat-transform's --info), the LoD set's levels are the model then each tier, the web page gets
    every tier, and export.json counts them."""
    import json

    from clod_adapter.cli.export import main as export_main
    from clod_adapter.io.splat_transform import find_splat_transform, read_info
    from clod_adapter.viewer.web import find_playcanvas

    if find_splat_transform() is None:
        pytest.skip("splat-transform not found: run `npm ci` in the repository root")
    g = read_ply(tiny_adapted / "point_cloud.ply")
    t1 = g.subset(torch.arange(0, len(g), 3))
    t2 = t1.subset(torch.arange(0, len(t1), 3))
    chain = tiers.attach(g, tiers.attach(t1, t2, 1.6, 1.2), 1.5, 1.2)
    src = write_ply(tmp_path / "chain.ply", chain)
    info = read_info(src)  # splat-transform reads the vertex element: the model, the tiers left out
    assert info["numGaussians"] == len(g) and any(c["name"] == "sigma_d" for c in info["extraColumns"])
    out = tmp_path / "exp"
    web = ["--web", str(out / "web")] if find_playcanvas() is not None else []
    assert export_main([str(src), "-s", str(tiny_model["scene"]), "-o", str(out), "--quiet", "--s-v", "2.2",
                        "--lod-meta", str(out / "lod"), "--sog-sh-iterations", "2", *web]) == 0
    rep = json.loads((out / "export.json").read_text())
    assert rep["tier"]["tiers"] == [len(t1), len(t2)]
    ext = read_ply(out / "point_cloud_clod.ply")
    assert [len(t) for t in tier_chain(ext)] == [len(g), len(t1), len(t2)]
    rows = rep["lod_meta"]["levels"]
    assert [r["tier"] for r in rows[:3]] == [0, 1, 2] and rows[0]["gaussians"] == len(g)
    assert rows[1]["gaussians"] <= len(t1) and rows[2]["gaussians"] <= len(t2)
    lod_info = read_info(out / "lod" / "lod-meta.json")
    assert lod_info["numLods"] == len(rows) and lod_info["lodCounts"] == [r["gaussians"] for r in rows]
    if web:
        cfg = json.loads((out / "web" / "clod.json").read_text())
        assert cfg["tier"]["count"] == len(t1) and cfg["tier"]["tier"]["count"] == len(t2)
        assert (out / "web" / "parents_2.ply").is_file() and (out / "web" / "parents_2.bin").is_file()


def test_the_comparison_samples_each_tier_where_it_is_first_drawn_alone(chain):
    """quality_vs_time.clod_s_vs: beside the grid, each tier's entry (the end of the cross-fade
    into it), where that tier is drawn alone at its tier_start level, its full detail."""
    from clod_adapter.evaluate import comparison as qvt

    g, cams = chain
    s_vs = qvt.clod_s_vs(g)
    entries = [FADE * SWITCHES[0][0], _model_s_v_of_tier1(FADE * SWITCHES[1][0])]
    assert all(any(abs(s - e) < 1e-3 for s in s_vs) for e in entries) and s_vs == sorted(s_vs)
    t2 = g.parents.parents
    r = render_lod(g, cams[0], entries[1])
    assert torch.equal(r.image, render_lod(t2, cams[0], SWITCHES[1][1]).image)


def test_a_count_budget_passes_through_a_tier_without_its_critical_order(chain):
    """A count budget that a deeper tier takes over is known in the tiers it passes through by
    projecting only that many of their centres in the frustum: their critical ``s_v`` (the
    budget's order) is never computed, only that of the tier the walk ends in (and of a deeper
    one that refused it); the count and tier are those of the step-by-step walk."""
    from clod_adapter.lod.draw import count_budget_walk

    g, cams = chain
    g = replace(g, parents=replace(g.parents, lod=replace(g.parents.lod, tier_start=1.0)),
                lod=replace(g.lod, tier_start=1.0))
    models = tier_chain(g)
    seen = set()
    for cam in cams:
        for v in (900, 400, 150, 60, 20, 3):
            views = {}

            def view_of(k, cam=cam, views=views):
                views.setdefault(k, view_lod(models[k], cam))
                return views[k]

            sel, par = count_budget_walk([m.lod for m in models], view_of, view_of(0), Budget(count=v))
            ref = _walk_solving_every_tier(g, cam, Budget(count=v))
            got = [(0, sel)] if par is None else [(d, s) for d, _, s in par.parts()]
            assert [d for d, _ in got] == [d for d, _ in ref], v
            assert all(torch.equal(a.indices, b.indices) for (_, a), (_, b) in zip(got, ref)), v
            depth = ref[-1][0]
            for k, view in views.items():  # the tiers passed through (or mixed whole) never had their order
                assert (view._critical is not None) == (k == depth and len(ref) == 1) or k > depth, (v, k, depth)
            seen |= {d for d, _ in ref}
    assert {0, 1, 2} <= seen, seen


def test_a_file_with_count_mix_from_an_earlier_version_still_reads(chain, tmp_path):
    """Earlier versions wrote ``count_mix=True`` into the ``clod_lod`` comment (count budgets
    between two tiers mixed by distance, no longer drawn): such a file reads, and draws as the
    same model without it; a malformed value is still refused with the file named."""
    g, cams = chain
    path = write_ply(tmp_path / "old.ply", g)
    old = tmp_path / "with_mix.ply"
    old.write_bytes(path.read_bytes().replace(b"comment clod_lod ", b"comment clod_lod count_mix=True ", 1))
    assert b"count_mix=True" in old.read_bytes()[:4000]
    a, b = render_lod(read_ply(old), cams[0], budget=Budget(share=0.3)), render_lod(g, cams[0], budget=Budget(share=0.3))
    assert torch.equal(a.image, b.image)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(old.read_bytes().replace(b"count_mix=True", b"count_mix=yes!"))
    with pytest.raises(PlyFormatError, match="bad.ply.*count_mix"):
        read_ply(bad)
