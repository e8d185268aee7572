"""The merge tree (clod_adapter.lod.tree): the tree is whole, a frame draws one cut of it, the children
composite to their parent at the switch, the frame's cost falls with the level and the budget,
the file round-trips, and every consumer draws what render_lod draws."""
from dataclasses import replace
import math

import numpy as np
import pytest
import torch

from clod_adapter.train import tiers
from clod_adapter.lod import neighbours, tree
from clod_adapter.lod.draw import lod_subset, render_lod
from clod_adapter.lod.cut import tree_node_costs, tree_select
from clod_adapter.io.ply import PlyFormatError, read_ply, write_ply
from clod_adapter.render import native
from clod_adapter.render.cpu import sh_colors
from clod_adapter.render.projection import camera_center
from clod_adapter.render.dispatch import rasterization
from clod_adapter.lod.budget import Budget, as_budget
from clod_adapter.io.synthetic import make_cameras

from test_tiers import _adapted

S_VS = np.geomspace(1.0, 80.0, 48)


@pytest.fixture(scope="module")
def model():
    t2 = _adapted(60, 3)
    t1 = tiers.attach(_adapted(300, 2), t2, 2.5, 1.5)
    return tree.build(tiers.attach(_adapted(1200, 0), t1, 2.0, 1.25), make_cameras(2, 3)), make_cameras(1, 2)


def _drawn_masks(ts, c):
    out = []
    for t, ids in zip(ts, c.ids):
        m = torch.zeros(len(t), dtype=torch.bool)
        m[ids] = True
        out.append(m)
    return out


def test_the_tree_is_whole(model):
    g, _ = model
    ts = tree.tiers_of(g)
    assert g.lod.tree and len(ts) == 3
    for below, above in zip(ts, ts[1:]):
        p = below.extra["parent"].long()
        assert p.min() >= 0 and p.max() < len(above)
        assert (torch.bincount(p, minlength=len(above)) > 0).all()  # every node is some node's parent
    assert "parent" not in ts[-1].extra
    # the tree draws no level gains, so it holds none (the tiers it was built from had them)
    assert _adapted(60, 3).has_gains and not any(t.has_gains for t in ts)


def test_the_k_d_tree_neighbours_equal_every_distance_and_give_the_builds_parents(model, monkeypatch):
    gen = torch.Generator().manual_seed(3)
    pts, qs = torch.randn(3000, 3, generator=gen), torch.randn(5000, 3, generator=gen) * 1.5
    dup = torch.cat([pts, pts[:100]])  # duplicate points: tied distances in any order, the same distances
    for k in (1, 16):
        a, b = neighbours.nearest(pts, qs, k), neighbours.nearest_torch(pts, qs, k)
        assert a.shape == (5000, k) and a.dtype == torch.int64 and bool((a == b).all())
        a, b = neighbours.nearest(dup, qs, k), neighbours.nearest_torch(dup, qs, k)
        da, db = (torch.linalg.vector_norm(qs[:, None].double() - dup[i].double(), dim=-1) for i in (a, b))
        torch.testing.assert_close(da, db, rtol=0, atol=1e-12)
        assert bool((da[:, 1:] >= da[:, :-1]).all())  # nearest first
    # the build's parents: the k-d tree's candidates give what every distance gives
    ts = tree.tiers_of(model[0])
    for below, above in zip(ts, ts[1:]):
        parent = tree.assign_parents(below, above)
        monkeypatch.setattr(tree, "nearest", neighbours.nearest_torch)
        assert bool((tree.assign_parents(below, above) == parent).all())
        monkeypatch.undo()
    for bad in (dict(points=pts[:, :2], queries=qs, k=1), dict(points=pts, queries=qs, k=0),
                dict(points=pts[:5], queries=qs, k=6)):
        with pytest.raises(ValueError, match="nearest"):
            neighbours.nearest(**bad)
        with pytest.raises(ValueError, match="nearest"):
            neighbours.nearest_torch(**bad)


def _with_exits(g, fn):
    """``g`` with each tier's exit but the last's replaced by ``fn(k, tier, exit)``."""
    ts = tree.tiers_of(g)
    return tree.linked([replace(t, extra={**t.extra, tree.EXIT_KEY: fn(k, t, t.extra[tree.EXIT_KEY])})
                        if k + 1 < len(ts) else t for k, t in enumerate(ts)])


def test_each_parent_has_one_lead_marked_and_the_fit_and_file_keep_it(model, tmp_path):
    """tree.build marks one child of each parent, its lead, by an exit of +inf, the build's choice
    (tree.choose_leads: the child nearest its family's mass-weighted centre); the fit moves the
    children but not the marks, and the file keeps them, so every consumer draws the lead the fit
    trained."""
    from clod_adapter.train.tree_fit import finetune

    g, _ = model
    ts = tree.tiers_of(g)
    for below, above in zip(ts, ts[1:]):
        lead = tree.leads(below)
        assert torch.equal(lead, torch.isposinf(below.extra[tree.EXIT_KEY]))
        assert torch.equal(lead, tree.choose_leads(below))
        assert bool((torch.bincount(below.extra["parent"].long()[lead], minlength=len(above)) == 1).all())
        assert bool(torch.isfinite(below.extra[tree.EXIT_KEY][~lead]).all())
    assert bool(torch.isfinite(ts[-1].extra[tree.EXIT_KEY]).all())  # the roots leave
    cams = make_cameras(2, 3)
    tuned = finetune(g, cams, [render_lod(g, c, 1.0).image.clamp(0, 1) for c in cams], 30, budget_steps=0.0)
    back = tree.tiers_of(read_ply(write_ply(tmp_path / "fitted.ply", tuned)))
    for k in range(len(ts) - 1):
        assert not torch.equal(tree.tiers_of(tuned)[k + 1].means, ts[k + 1].means)  # the fit moved them
        assert torch.equal(tree.leads(back[k]), tree.leads(ts[k]))


def test_a_tree_file_without_lead_marks_draws_the_builds_choice_and_bad_marks_are_refused(model, tmp_path):
    """A tree file whose exits hold no +inf (written before the marks) gets its leads from
    tree.choose_leads when drawn, one per parent, and draws what the same model with those leads
    marked draws; a file where a parent has no marked lead, or two, is refused, as is +inf in the
    roots' exits."""
    g, cams = model
    unmarked = _with_exits(g, lambda k, t, x: torch.where(torch.isposinf(x), torch.full_like(x, 50.0), x))
    back = read_ply(write_ply(tmp_path / "unmarked.ply", unmarked))
    for t, above in zip(tree.tiers_of(back)[:-1], tree.tiers_of(back)[1:]):
        assert bool(torch.isfinite(t.extra[tree.EXIT_KEY]).all())
        lead = tree.leads(t)
        assert torch.equal(lead, tree.choose_leads(t))
        assert bool((torch.bincount(t.extra["parent"].long()[lead], minlength=len(above)) == 1).all())
    marked = _with_exits(back, lambda k, t, x: torch.where(tree.choose_leads(t), torch.full_like(x, math.inf), x))
    for s in (1.5, 3.0, 6.0, 12.0):
        assert torch.equal(render_lod(back, cams[0], s).image, render_lod(marked, cams[0], s).image)
    t0 = tree.tiers_of(g)[0]
    p, lead = t0.extra["parent"].long(), tree.leads(t0)
    family = int(torch.nonzero(torch.bincount(p) >= 2)[0])  # a parent with two children or more
    one = int(torch.nonzero(lead & (p == family))[0])
    sibling = int(torch.nonzero(~lead & (p == family))[0])
    for i, (row, value) in enumerate(((one, 1.0), (sibling, math.inf))):  # no lead; two leads
        bad = _with_exits(g, lambda k, t, x: torch.where(torch.arange(len(x)) == row, torch.full_like(x, value), x)
                          if k == 0 else x)
        with pytest.raises(PlyFormatError, match=f"row {family} of 'lod_parent' has {2 * i} lead children"):
            read_ply(write_ply(tmp_path / f"bad_lead{i}.ply", bad))
    ts = tree.tiers_of(g)
    inf_root = tree.linked(ts[:-1] + [replace(ts[-1], extra={**ts[-1].extra, tree.EXIT_KEY: torch.full(
        (len(ts[-1]),), math.inf)})])
    with pytest.raises(PlyFormatError, match="exit"):
        read_ply(write_ply(tmp_path / "inf_root.ply", inf_root))


def test_each_path_crosses_the_cut_once(model):
    g, cams = model
    ts = tree.tiers_of(g)
    p1, p2 = ts[0].extra["parent"].long(), ts[1].extra["parent"].long()
    for cam in cams:
        tt = tree.terms(ts, cam)
        x_root = tt.upper[-1]
        for s in S_VS:
            d0, d1, d2 = _drawn_masks(ts, tree.cut(ts, cam, float(s), tt=tt))
            crossings = d0.long() + d1[p1].long() + d2[p2[p1]].long()
            assert bool((crossings <= 1).all())  # one set: no path drawn twice (a node may leave first)
            gone = x_root[p2[p1]] <= s  # the root of the path has left
            assert bool((crossings[gone] == 0).all())
        assert len(tree.cut(ts, cam, 1.0, tt=tt).ids[0]) == len(ts[0])  # s_v = 1: the model whole


def test_children_composite_to_the_parent_at_the_switch():
    parent = _adapted(1, 5)
    kids = _adapted(3, 6)
    g = tiers.attach(kids, parent, 2.0, 1.0)
    g = replace(g, extra={"parent": torch.zeros(3, dtype=torch.int32)}, lod=replace(g.lod, tree=True))
    ts = tree.tiers_of(g)
    cam = make_cameras(1, 1)[0]
    c = tree.TreeCut([torch.arange(3), torch.zeros(0, dtype=torch.long)],
                     [torch.zeros(3, dtype=torch.float64), torch.zeros(0, dtype=torch.float64)], 2.0, 3)
    means, quats, scales, ops, colors = tree.cut_attributes(ts, c)
    a_p = torch.sigmoid(parent.opacity_logits)
    lead = tree.leads(ts[0])
    assert torch.allclose(means[lead], parent.means) and torch.allclose(scales[lead], parent.scales)
    assert int(lead.sum()) == 1 and torch.allclose(ops[lead], a_p) and bool((ops[~lead] == 0).all())
    assert bool((scales[~lead] <= 1e-3 * kids.scales[~lead]).all())  # the siblings shrank to nothing
    args = (cam.viewmat[None], cam.K[None], cam.width, cam.height)
    img_kids = rasterization(means, quats, scales, ops, colors, *args, sh_degree=parent.sh_degree)[0]
    img_par = rasterization(parent.means, parent.quats, parent.scales, a_p, parent.colors, *args,
                            sh_degree=parent.sh_degree)[0]
    assert img_par.abs().max() > 0.05
    assert (img_kids - img_par).abs().max() < 1e-6  # the lead is the parent, its siblings faded out


def _footprint(means, quats, scales, ops, colors, cam):
    meta = rasterization(means, quats, scales, ops, colors, cam.viewmat[None], cam.K[None], cam.width, cam.height,
                         sh_degree=0)[2]
    r = meta["radii"].double()
    return float((r[..., 0] * r[..., 1]).sum()) if r.numel() else 0.0


def test_cost_falls_with_the_level_and_the_budget(model):
    g, cams = model
    ts = tree.tiers_of(g)
    for cam in cams:
        counts, feet = [], []
        for s in S_VS:
            c, attrs = tree_select(g, cam, float(s))
            counts.append(c.n_drawn)
            feet.append(_footprint(*attrs, cam))
        assert all(b <= a for a, b in zip(counts, counts[1:]))
        assert counts[0] == len(ts[0]) and counts[-1] < len(ts[-1])
        worst = max(max(feet[i + 1:]) / max(feet[i], 1.0) for i in range(len(feet) - 1))
        assert worst <= 1.05, worst  # no frame's footprint above 1.05x a more detailed frame's
        tt = tree.terms(ts, cam)
        ks = [1200, 900, 600, 300, 120, 40, 10]
        levels = [tree.budget_s_v(tt, k) for k in ks]
        assert all(b >= a for a, b in zip(levels, levels[1:]))  # a smaller budget: a coarser cut
        for k, s in zip(ks, levels):
            c = tree.cut(ts, cam, s, tt=tt)
            in_fr = sum(int(f[i].sum()) for f, i in zip(tt.frustum, c.ids))
            assert in_fr <= k


def test_render_lod_draws_the_cut_and_lod_subset_matches(model):
    g, cams = model
    cam = cams[0]
    for s in (1.0, 3.0, 9.0):
        r = render_lod(g, cam, s)
        sub = lod_subset(g, cam, s)
        c, _ = tree_select(g, cam, s)
        assert r.n_rendered <= c.n_drawn == len(sub.opacities)
        if s > 1.0:
            assert torch.equal(r.indices, c.ids[0]) and r.n_parents <= c.n_drawn - len(c.ids[0])
        else:  # s_v = 1: tier 0 whole, drawn as a plain model (its selection: the Gaussians in view)
            assert bool(torch.isin(r.indices, c.ids[0]).all()) and r.n_parents == 0 and r.s_v == 1.0
        img = rasterization(sub.means, sub.quats, sub.scales, sub.opacities, sub.colors, cam.viewmat[None],
                            cam.K[None], cam.width, cam.height, sh_degree=g.sh_degree)[0][0]
        assert torch.allclose(img, r.image, atol=1e-5)
    rb = render_lod(g, cam, budget=Budget(count=200))
    ts = tree.tiers_of(g)
    tt = tree.terms(ts, cam, at=tree.budget_frame(ts, cam))  # a budget's cut: every node at its d_ref (step 6)
    c = tree.cut(ts, cam, rb.s_v, tt=tt)
    assert rb.s_v > 1.0 and sum(int(f[i].sum()) for f, i in zip(tt.frustum, c.ids)) <= 200


def test_tree_file_round_trips_and_bad_parents_are_refused(model, tmp_path):
    g, cams = model
    p = write_ply(tmp_path / "tree.ply", g)
    back = read_ply(p)
    assert back.lod.tree and tree.is_tree(back)
    for a, b in zip(tree.tiers_of(g), tree.tiers_of(back)):
        if "parent" in a.extra:
            assert torch.equal(a.extra["parent"].long(), b.extra["parent"].long())
    assert torch.allclose(render_lod(back, cams[0], 4.0).image, render_lod(g, cams[0], 4.0).image, atol=1e-5)
    bad = replace(g, extra={"parent": torch.full((len(g),), 10_000, dtype=torch.int32)})
    with pytest.raises(PlyFormatError, match="parent"):
        read_ply(write_ply(tmp_path / "bad.ply", bad))
    for a, b in zip(tree.tiers_of(g), tree.tiers_of(back)):
        assert torch.equal(a.extra["d_ref"], b.extra["d_ref"])  # a budget's distances, as written
    no_ref = replace(g, extra={k: v for k, v in g.extra.items() if k != "d_ref"})
    with pytest.raises(PlyFormatError, match="d_ref"):
        read_ply(write_ply(tmp_path / "no_ref.ply", no_ref))


def test_a_budget_cuts_every_node_at_its_reference_distance(model):
    """build stores each node's mean d' over its cameras (``d_ref``); a count budget's cut is
    steps 2-5 on those distances with the view's frustum, and not the cut the view's own
    distances would give."""
    g, cams = model
    ts = tree.tiers_of(g)
    assert tree.NODE_KEYS == (tree.PARENT_KEY, tree.EXIT_KEY, tree.REFERENCE_KEY)
    assert all(k in t.extra for t in ts[:-1] for k in tree.NODE_KEYS)
    assert not any(k in g.with_sigma_d(None).extra for k in tree.NODE_KEYS)  # the plain model drops them
    for t, d in zip(ts, tree.reference_distances(ts, make_cameras(2, 3))):  # the fixture's build cameras
        assert torch.allclose(t.extra["d_ref"].double(), d, rtol=1e-6)
    differs = 0
    for cam in cams:
        ds, frs = tree.frame(ts, cam)
        refs = [t.extra["d_ref"] for t in ts]
        for k in (3, 17, 60, 200):
            c = tree.budget_cut(ts, cam, k)
            tt = tree.terms(ts, cam, at=(refs, frs))
            want = tree.cut(ts, cam, tree.budget_s_v(tt, k), tt=tt)
            assert c.s_v == pytest.approx(want.s_v) and all(torch.equal(x, y) for x, y in zip(c.ids, want.ids)), k
            tv = tree.terms(ts, cam, at=(ds, frs))
            view = tree.cut(ts, cam, tree.budget_s_v(tv, k), tt=tv)
            differs += not all(torch.equal(x, y) for x, y in zip(c.ids, view.ids))
    assert differs > 0


def test_every_tiers_settings_round_trip_through_the_file(tmp_path):
    """A tree of three tiers written and read back: each tier's rows and hand-over settings
    (``clod_lod_tier`` comments), a tier's own window width, the same cuts; ``ply_bytes`` is the
    file's size; a second tier's element without the first is refused, naming the file."""
    import plyfile

    from clod_adapter.evaluate.storage import ply_bytes

    t2 = _adapted(60, 3)
    t2 = replace(t2, lod=replace(t2.lod, fade_width=4.0))  # a tier may have a window of its own
    t1 = tiers.attach(_adapted(300, 2), t2, 2.5, 1.5)
    g = tree.build(tiers.attach(_adapted(1200, 0), t1, 2.0, 1.25), make_cameras(2, 3))
    path = write_ply(tmp_path / "tiers.ply", g)
    back = read_ply(path)
    got, want = tree.tiers_of(back), tree.tiers_of(g)
    assert [len(t) for t in got] == [len(t) for t in want] and len(got) == 3
    assert back.parents.lod.tier_s_v == 2.5 and back.parents.lod.tier_start == 1.5
    assert back.parents.parents.lod.tier_s_v == 0.0
    assert [t.lod.fade_width for t in got] == [g.lod.fade_width, g.lod.fade_width, 4.0] != [g.lod.fade_width] * 3
    for a, b in zip(got, want):
        assert torch.equal(a.sigma_d, b.sigma_d) and torch.equal(a.means, b.means)
    cam = make_cameras(1, 2)[0]
    for s in (1.5, 2.6, 4.6, 12.0):
        assert torch.equal(render_lod(back, cam, s).image, render_lod(g, cam, s).image)
    assert ply_bytes(g) == path.stat().st_size
    ply = plyfile.PlyData.read(str(path))
    bad = plyfile.PlyData([ply["vertex"], ply["lod_parent_2"]], text=False, comments=ply.comments)
    bad.write(str(tmp_path / "bad.ply"))
    with pytest.raises(PlyFormatError, match="bad.ply.*lod_parent_2.*without .lod_parent. before"):
        read_ply(tmp_path / "bad.ply")


def test_a_file_with_count_mix_from_an_earlier_version_still_reads(model, tmp_path):
    """Earlier versions wrote ``count_mix=True`` into the ``clod_lod`` comment (count budgets
    between two tiers mixed by distance, no longer drawn): such a file reads, and draws as the
    same tree without it; a malformed value is still refused with the file named."""
    g, cams = model
    path = write_ply(tmp_path / "old.ply", g)
    old = tmp_path / "with_mix.ply"
    old.write_bytes(path.read_bytes().replace(b"comment clod_lod ", b"comment clod_lod count_mix=True ", 1))
    assert b"count_mix=True" in old.read_bytes()[:4000]
    for kw in (dict(budget=Budget(share=0.3)), dict(s_v=4.0)):
        assert torch.equal(render_lod(read_ply(old), cams[0], **kw).image, render_lod(read_ply(path), cams[0], **kw).image)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(old.read_bytes().replace(b"count_mix=True", b"count_mix=yes!"))
    with pytest.raises(PlyFormatError, match="bad.ply.*count_mix"):
        read_ply(bad)


def test_the_reference_draws_what_the_library_draws(model, tmp_path):
    """examples/reference_lod.py (docs/lod_rule.md in numpy, no clod_adapter import) against
    lod_subset on the same file: the same nodes per tier, the same attributes to float32 rounding."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("reference_lod", Path(__file__).parents[1] / "examples"
                                                  / "reference_lod.py")
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    g, cams = model
    path = write_ply(tmp_path / "tree.ply", g)
    back, rt = read_ply(path), ref.read_tree(path)
    assert [len(t["means"]) for t in rt] == [len(t) for t in tree.tiers_of(back)]
    for cam in cams:
        for kw in [dict(s_v=float(s)) for s in (1.0, 1.3, 2.2, 3.0, 4.7, 7.5, 12.0, 30.0)] + [dict(budget=k) for k in
                                                                                              (1000, 300, 50)]:
            r = ref.draw(rt, cam.viewmat.numpy(), cam.K.numpy(), cam.width, cam.height, **kw)
            sub = lod_subset(back, cam, kw.get("s_v"), budget=Budget(count=kw["budget"]) if "budget" in kw else None)
            assert sub.s_v == pytest.approx(r["s_v"], rel=1e-6)
            ours = [sub.indices] + list(sub.tier_indices)
            assert all(np.array_equal(a.numpy(), b) for a, b in zip(ours, r["ids"])), kw
            np.testing.assert_allclose(sub.opacities.numpy(), r["opacities"], atol=2e-6)
            np.testing.assert_allclose(sub.means.numpy(), r["means"], atol=2e-5)
            # a shrinking sibling's log-scale holds ln w, which float32 carries to ~1e-4 at small w
            np.testing.assert_allclose(np.log(sub.scales.numpy()), r["log_scales"], atol=2e-4)
            np.testing.assert_allclose(sub.colors.numpy(), r["sh"], atol=2e-5)


def test_cost_and_time_budgets_are_cuts_of_the_tree(model):
    g, cams = model
    ts = tree.tiers_of(g)
    cam = cams[1]
    tt = tree.terms(ts, cam)
    costs = tree_node_costs(ts, cam, tt)
    full = float(costs[0].sum())
    levels = []
    for share in (1.0, 0.6, 0.3, 0.1, 0.02):
        c, _ = tree_select(g, cam, budget=Budget(cost=share))
        drawn = sum(float(x[i].sum()) for x, i in zip(costs, c.ids))
        assert drawn <= share * full + 1e-9
        levels.append(c.s_v)
    assert all(b >= a for a, b in zip(levels, levels[1:])) and levels[-1] > levels[0]
    ms = [render_lod(g, cam, budget=Budget(ms=b)).s_v for b in (50.0, 3.0, 2.6)]
    assert all(b >= a for a, b in zip(ms, ms[1:]))


def test_a_count_budget_that_holds_tier_0_draws_it_without_a_sweep(model, monkeypatch):
    """A count budget of every tier-0 node in the frustum (or more) is the level s_v = 1: drawn as
    s_v = 1 draws, found without the budget sweep; one node fewer is solved by the sweep and
    draws fewer."""
    g, cams = model
    cam = cams[0]
    n0 = int(tree.in_frustum(tree.tiers_of(g)[0], cam).sum())
    assert 1 < n0 < len(g)
    want = render_lod(g, cam, 1.0)
    calls = []
    real = tree.budget_cut
    monkeypatch.setattr(tree, "budget_cut", lambda *a, **k: calls.append(1) or real(*a, **k))
    for b in (Budget(in_view=1.0), Budget(count=n0), Budget(count=n0 + 5)):
        r = render_lod(g, cam, budget=b)
        assert r.s_v == 1.0 and torch.equal(r.image, want.image) and r.n_rendered == want.n_rendered
        assert tree_select(g, cam, budget=b)[0].s_v == 1.0
    assert not calls
    frames = []
    real_frame = tree.frame
    monkeypatch.setattr(tree, "frame", lambda *a, **k: frames.append(1) or real_frame(*a, **k))
    for b in (Budget(in_view=1.0), Budget(count=len(g)), Budget(share=1.0)):  # hold tier 0 whatever the view
        assert torch.equal(render_lod(g, cam, budget=b).image, want.image)
    assert not frames  # no per-node pass for them
    fewer = render_lod(g, cam, budget=Budget(count=n0 - 1))
    assert calls and fewer.s_v > 1.0 and fewer.n_rendered < want.n_rendered


def test_the_renderer_hook_draws_the_cut(model):
    from clod_adapter.lod.hook import clod_kwargs, clod_rasterization

    g, cams = model
    vm = torch.stack([c.viewmat for c in cams])
    Ks = torch.stack([c.K for c in cams])
    for kw in (dict(s_v=1.0), dict(s_v=3.3), dict(s_v=11.0), dict(budget=250), dict(budget=Budget(in_view=0.2))):
        col, _, meta = clod_rasterization(g.means, g.quats, g.scales, g.opacities, g.colors, vm, Ks, cams[0].width,
                                          cams[0].height, sh_degree=g.sh_degree, **clod_kwargs(g), **kw)
        ours = {k: as_budget(v) if k == "budget" else v for k, v in kw.items()}  # the hook's edge: 250 a count
        for c, cam in enumerate(cams):
            r = render_lod(g, cam, **ours)
            assert torch.allclose(col[c], r.image, atol=1e-5) and meta["lod_s_v"][c] == pytest.approx(r.s_v)
            assert bool(torch.isin(r.indices, meta["lod_indices"][c]).all())
            assert torch.equal(meta["lod_indices"][c], r.indices) or kw.get("s_v") == 1.0


def test_a_baked_level_holds_the_cut(model):
    from clod_adapter.export.bake import bake

    g, cams = model
    baked, info = bake(g, cams, 6.0, return_info=True)
    cuts = [tree_select(g, c, 6.0)[0] for c in cams]
    n_union = sum(len(torch.unique(torch.cat([c.ids[k] for c in cuts]))) for k in range(3))
    assert len(baked) == n_union and info.n_parents == n_union - len(torch.unique(torch.cat([c.ids[0] for c in cuts])))
    assert info.n_parents > 0 and baked.sigma_d is None


def test_fitting_on_cuts_trains_the_merged_tiers_only(model):
    """tree_fit.finetune: tier 0 (full detail) untouched, the merged tiers moved, and the cuts'
    error against the full-detail renders smaller after the fit than before."""
    from clod_adapter.train.losses import render_loss
    from clod_adapter.train.tree_fit import finetune

    g, _ = model
    cams = make_cameras(2, 3)
    imgs = [render_lod(g, c, 1.0).image.clamp(0, 1) for c in cams]

    def err(m):
        return sum(float(render_loss(render_lod(m, c, s).image.clamp(0, 1), im)) for c, im in zip(cams, imgs)
                   for s in (3.0, 6.0, 12.0))

    tuned = finetune(g, cams, imgs, 30, budget_steps=0.0)  # level cuts only
    a, b = tree.tiers_of(g), tree.tiers_of(tuned)
    assert torch.equal(a[0].means, b[0].means) and torch.equal(a[0].opacity_logits, b[0].opacity_logits)
    assert not torch.equal(a[1].means, b[1].means) and torch.equal(a[1].sigma_d, b[1].sigma_d)
    assert err(tuned) < err(g)


def test_fitting_on_budget_cuts(model):
    """tree_fit.finetune with budget_steps=1: every step draws a count budget's cut; tier 0 is
    untouched, the budget cuts' error falls, and a share outside [0, 1] is refused."""
    from clod_adapter.train.losses import render_loss
    from clod_adapter.train.tree_fit import finetune

    g, _ = model
    cams = make_cameras(2, 3)
    imgs = [render_lod(g, c, 1.0).image.clamp(0, 1) for c in cams]

    def err(m):
        return sum(float(render_loss(render_lod(m, c, budget=Budget(in_view=s)).image.clamp(0, 1), im))
                   for c, im in zip(cams, imgs) for s in (0.3, 0.1, 0.03))

    tuned = finetune(g, cams, imgs, 30, budget_steps=1.0)
    a, b = tree.tiers_of(g), tree.tiers_of(tuned)
    assert torch.equal(a[0].means, b[0].means) and not torch.equal(a[1].means, b[1].means)
    assert err(tuned) < err(g)
    levels = finetune(g, cams, imgs, 30, budget_steps=0.0)
    assert not torch.equal(tree.tiers_of(levels)[1].means, b[1].means)
    with pytest.raises(ValueError, match="budget_steps"):
        finetune(g, cams, imgs, 3, budget_steps=1.5)


def test_the_fits_level_cap_bounds_the_levels_it_draws(model, monkeypatch):
    """tree_fit.LEVEL_CAP: capped at s_v = 1, every level step draws tier 0 alone, so a fit on
    levels trains nothing; uncapped, the same fit moves the merged tiers."""
    from clod_adapter.train import tree_fit

    g, _ = model
    cams = make_cameras(2, 3)
    imgs = [render_lod(g, c, 1.0).image.clamp(0, 1) for c in cams]
    moved = tree.tiers_of(tree_fit.finetune(g, cams, imgs, 5, budget_steps=0.0))
    monkeypatch.setattr(tree_fit, "LEVEL_CAP", 1.0)
    held = tree.tiers_of(tree_fit.finetune(g, cams, imgs, 5, budget_steps=0.0))
    a = tree.tiers_of(g)
    assert not torch.equal(moved[1].means, a[1].means)
    assert all(torch.equal(x.means, y.means) and torch.equal(x.log_scales, y.log_scales) for x, y in zip(a, held))


def test_the_fits_tier0_rate_fits_tier_0_held_at_its_size(model):
    """tree_fit.finetune's ``tier0_rate``: 0 leaves tier 0 as it is (the job's fit); above 0 the
    same steps move tier 0 too, its scales held at most at their start (``grow`` 1) and the tree
    (parents, entries, exits) unchanged; a negative rate is refused."""
    from clod_adapter.train import tree_fit

    g, _ = model
    cams = make_cameras(2, 3)
    imgs = [render_lod(g, c, 1.0).image.clamp(0, 1) * 0.9 for c in cams]
    a = tree.tiers_of(g)
    kept = tree.tiers_of(tree_fit.finetune(g, cams, imgs, 8, budget_steps=0.5, tier0_rate=0.0))
    fitted = tree.tiers_of(tree_fit.finetune(g, cams, imgs, 8, budget_steps=0.5, tier0_rate=1.0, grow=1.0))
    assert torch.equal(kept[0].means, a[0].means) and torch.equal(kept[0].sh0, a[0].sh0)
    assert not torch.equal(fitted[0].sh0, a[0].sh0)
    assert bool((fitted[0].log_scales <= a[0].log_scales + 1e-6).all())
    for x, y in zip(a, fitted):
        assert torch.equal(x.sigma_d, y.sigma_d) and len(x) == len(y)
        for key in (tree.PARENT_KEY, tree.EXIT_KEY):
            if key in x.extra:
                assert torch.equal(x.extra[key], y.extra[key])
    with pytest.raises(ValueError, match="tier0_rate"):
        tree_fit.finetune(g, cams, imgs, 2, tier0_rate=-1.0)


def test_fitting_on_cuts_bounds_the_growth_of_merged_nodes(model):
    """tree_fit.finetune with ``grow``: no merged node's scale ends above its start times
    ``grow`` (unbounded, the same fit grows some), tier 0 is untouched, the merged nodes still
    move; the roots left free (``free_roots``) grow while the tiers below stay bounded; a bound
    under 1 and a share outside [0, 1] are refused."""
    from clod_adapter.train.config import AdaptConfig
    from clod_adapter.train.tree_fit import finetune

    g, _ = model
    cams = make_cameras(2, 3)
    imgs = [render_lod(g, c, 1.0).image.clamp(0, 1) for c in cams]
    free = finetune(g, cams, imgs, 30, budget_steps=0.5, grow=None)
    a, b = tree.tiers_of(g), tree.tiers_of(free)
    assert any(bool((y.log_scales > x.log_scales + 1e-6).any()) for x, y in zip(a[1:], b[1:]))
    for grow in (1.0, 1.1):
        held = tree.tiers_of(finetune(g, cams, imgs, 30, budget_steps=0.5, grow=grow, free_roots=0.0))
        for x, y in zip(a[1:], held[1:]):
            assert bool((y.log_scales <= x.log_scales + math.log(grow) + 1e-6).all())
            assert not torch.equal(x.means, y.means)
        assert torch.equal(held[0].log_scales, a[0].log_scales)
    # the roots that leave last (here all of them) left free: the tiers below stay bounded
    free = tree.tiers_of(finetune(g, cams, imgs, 30, budget_steps=0.5, grow=1.0, free_roots=1.0))
    assert bool((free[-1].log_scales > a[-1].log_scales + 1e-6).any())
    for x, y in zip(a[1:-1], free[1:-1]):
        assert bool((y.log_scales <= x.log_scales + 1e-6).all())
    with pytest.raises(ValueError, match="tree_grow"):
        AdaptConfig(tree_grow=0.9)
    with pytest.raises(ValueError, match="tree_free_roots"):
        AdaptConfig(tree_free_roots=1.5)
    with pytest.raises(ValueError, match="grow"):
        finetune(g, cams, imgs, 3, grow=0.5)
    with pytest.raises(ValueError, match="free_roots"):
        finetune(g, cams, imgs, 3, grow=1.0, free_roots=-0.1)


def test_export_of_a_tree(model, tmp_path, tiny_model):
    """clod-export of a tree: the extended .ply keeps the tree and splat-transform reads it (its
    vertex element, the model); the LoD set is the tree's cut at the reference distances, one level
    per tier."""
    import json

    from clod_adapter.cli.export import main as export_main
    from clod_adapter.io.splat_transform import find_splat_transform, read_info

    g, _ = model
    src = write_ply(tmp_path / "tree.ply", g)
    out = tmp_path / "out"
    lod = ["--lod-meta", str(out / "lod"), "--sog-sh-iterations", "2"] if find_splat_transform() else []
    assert export_main([str(src), "--images", str(tiny_model["scene"]), "-o", str(out), "--quiet", *lod]) == 0
    back = read_ply(out / "point_cloud_clod.ply")
    assert tree.is_tree(back) and [len(t) for t in tree.tiers_of(back)] == [len(t) for t in tree.tiers_of(g)]
    if not lod:
        pytest.skip("splat-transform not found: run `npm ci` in the repository root")
    info = read_info(out / "point_cloud_clod.ply")
    assert info["numGaussians"] == len(g) and any(c["name"] == "parent" for c in info["extraColumns"])
    rows = json.loads((out / "export.json").read_text())["lod_meta"]["levels"]
    sizes = [len(t) for t in tree.tiers_of(g)]  # the tree's cut, at most a merged tier's count per level
    assert len(rows) == len(sizes) and rows[0]["gaussians"] == sizes[0] and rows[0]["s_v"] == 1.0
    assert all(0 < r["gaussians"] <= n for r, n in zip(rows[1:], sizes[1:])) and rows[1]["s_v"] < rows[2]["s_v"]
    assert read_info(out / "lod" / "lod-meta.json")["lodCounts"] == [r["gaussians"] for r in rows]


def test_export_prune_and_ordered_of_a_tree(model, tmp_path):
    """clod-export --prune --ordered of a tree: the pruned file is still a tree (only tier-0 rows
    out of every training view go, the merged tiers and their links stay) and draws every level and
    budget of those views as before; ordered.ply is tier 0 alone, a model without tiers, read back."""
    from clod_adapter.cli.export import main as export_main
    from clod_adapter.io.colmap import write_colmap_scene
    from clod_adapter.io.load import load_scene
    from clod_adapter.io.synthetic import make_ground_truth
    from conftest import uint8_views

    g, _ = model
    zoom = torch.tensor([[3.0, 1.0, 1.0], [1.0, 3.0, 1.0], [1.0, 1.0, 1.0]])  # 3x the focal length
    cams = [replace(c, K=c.K * zoom) for c in make_cameras(1, 2)]  # part of tier 0 out of every view
    scene_dir = tmp_path / "scene"
    write_colmap_scene(scene_dir, cams, uint8_views(make_ground_truth(50, seed=1), cams))
    src = write_ply(tmp_path / "tree.ply", g)
    out = tmp_path / "out"
    assert export_main([str(src), "--images", str(scene_dir), "-o", str(out), "--quiet", "--prune",
                        "--ordered"]) == 0
    back = read_ply(out / "point_cloud_clod.ply")
    a, b = tree.tiers_of(g), tree.tiers_of(back)
    assert tree.is_tree(back) and len(b) == len(a) and 0 < len(b[0]) < len(a[0])
    assert [len(t) for t in b[1:]] == [len(t) for t in a[1:]]
    for cam in load_scene(scene_dir).train:
        for kw in ({"s_v": 1.0}, {"s_v": 2.2}, {"s_v": 6.0}, {"budget": Budget(in_view=0.3)}):
            x, y = render_lod(g, cam, **kw), render_lod(back, cam, **kw)
            assert x.n_rendered == y.n_rendered, kw
            torch.testing.assert_close(y.image, x.image, atol=1e-5, rtol=0, msg=str(kw))
    ordered = read_ply(out / "ordered.ply")
    assert ordered.parents is None and not tree.is_tree(ordered) and len(ordered) == len(b[0])
    assert "parent" not in ordered.extra


def test_the_web_page_of_a_tree(model, tmp_path, tiny_model):
    """clod-export --web of a tree: the page of one set (every tier's nodes in model.ply, the rule
    in clod_tree.mjs; its drawing against render_lod: tests/test_web_tree.py)."""
    import json

    from clod_adapter.cli.export import main as export_main
    from clod_adapter.export.web import find_playcanvas

    if find_playcanvas() is None:
        pytest.skip("PlayCanvas engine not found: run `npm ci` in the repository root")
    g = model[0]
    src = write_ply(tmp_path / "tree.ply", g)
    web = tmp_path / "web"
    assert export_main([str(src), "--images", str(tiny_model["scene"]), "-o", str(tmp_path / "o2"),
                        "--web", str(web), "--quiet"]) == 0
    cfg = json.loads((web / "clod.json").read_text())
    assert cfg["tree"]["counts"] == [len(t) for t in tree.tiers_of(g)] and (web / "clod_tree.mjs").is_file()
    assert json.loads((tmp_path / "o2" / "export.json").read_text())["web"]["static_cut"] is None


def test_walking_from_the_roots_gives_the_cut_of_every_node(model):
    g, cams = model
    ts = tree.tiers_of(g)
    for cam in cams:
        tt = tree.terms(ts, cam)
        for s in S_VS:
            a, b = tree.cut(ts, cam, float(s), tt=tt), tree.walk(ts, cam, float(s))
            assert all(torch.equal(x, y) for x, y in zip(a.ids, b.ids))
            assert all(torch.allclose(x, y) for x, y in zip(a.t, b.t)) and a.n_frustum == b.n_frustum
            assert all(torch.equal(x, y) for x, y in zip(a.fade, b.fade))


@pytest.mark.skipif(not native.available(), reason="the C++ kernels do not build here")
def test_the_cpp_cut_and_attributes_equal_their_torch_twins(model):
    g, cams = model
    ts = tree.tiers_of(g)
    handing = 0
    for cam in cams:
        with torch.no_grad():
            with native.use_impl("cpp"):
                ta = tree.terms(ts, cam)
            with native.use_impl("torch"):
                tb = tree.terms(ts, cam)
        for x, y in zip(ta.entry + ta.upper + ta.fade, tb.entry + tb.upper + tb.fade):
            assert torch.equal(x, y)
        for k in (0, 1, 7, 40, 300, 5000):  # a count budget, and a cost budget in pixels
            costs = [torch.rand(len(t), dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * 50
                     for t in ts]
            with native.use_impl("cpp"):
                sa, ca = tree.budget_s_v(ta, k), tree.budget_s_v(ta, 20 * k, costs)
            with native.use_impl("torch"):
                sb, cb = tree.budget_s_v(ta, k), tree.budget_s_v(ta, 20 * k, costs)
            assert sa == sb and ca == cb
        for s in S_VS:
            with torch.no_grad():
                with native.use_impl("cpp"):
                    a = tree.cut(ts, cam, float(s))
                    attrs_a = tree.cut_attributes(ts, a)
                with native.use_impl("torch"):
                    b = tree.cut(ts, cam, float(s))
                    attrs_b = tree.cut_attributes(ts, a)  # the same cut: w rounded alike
                full = tree.cut(ts, cam, float(s), tt=ta)  # every node's C++ terms: the walk skips none it draws
            assert all(torch.equal(x, y) for x, y in zip(a.ids, b.ids))
            assert all(torch.equal(x, y) for x, y in zip(a.fade, b.fade))
            assert all(torch.equal(x, y) for x, y in zip(a.ids, full.ids)) and all(
                torch.allclose(x, y, atol=1e-6) for x, y in zip(a.t, full.t))
            assert a.n_frustum == b.n_frustum == full.n_frustum
            assert all(torch.allclose(x, y, atol=1e-6) for x, y in zip(a.t, b.t))
            for x, y in zip(attrs_a, attrs_b):
                assert x.shape == y.shape and torch.allclose(x, y, rtol=1e-5, atol=1e-6)
            centre = camera_center(cam.viewmat.to(g.means.dtype))
            for deg in sorted({0, g.sh_degree}):  # colours seen from the camera, evaluated in the pass over the rows
                with torch.no_grad(), native.use_impl("cpp"):
                    rgb_a = tree.cut_attributes(ts, a, campos=centre, sh_degree=deg)
                with torch.no_grad(), native.use_impl("torch"):
                    rgb_b = tree.cut_attributes(ts, a, campos=centre, sh_degree=deg)
                assert rgb_a[4].shape == (attrs_a[0].shape[0], 3)
                assert all(torch.allclose(x, y, rtol=1e-5, atol=1e-6) for x, y in zip(rgb_a, rgb_b))
                assert torch.allclose(rgb_b[4], sh_colors(deg, attrs_b[0], attrs_b[4], centre), rtol=1e-5, atol=1e-6)
            handing += sum(int(((w < 1) & ~f).sum()) for w, f in zip(a.t[:-1], a.fade[:-1]))
    assert handing > 100  # the interpolation was compared, not only whole nodes


@pytest.mark.skipif(not native.available(), reason="the C++ kernels do not build here")
def test_the_one_call_budget_cut_equals_its_three_step_twin(model):
    """tree.budget_cut's C++ call (terms, level and cut at once) against terms + budget_s_v + cut:
    the same level, nodes, hand-over positions and fades, from every count to none."""
    g, cams = model
    ts = tree.tiers_of(g)
    levels = set()
    for cam in cams:
        n0 = int(tree.in_frustum(ts[0], cam).sum())
        with torch.no_grad(), native.use_impl("cpp"):  # the frustum alone, without the view's distances
            fa = tree.budget_frame(ts, cam)
        with torch.no_grad(), native.use_impl("torch"):
            fb = tree.budget_frame(ts, cam)
        assert all(torch.equal(x, y) for x, y in zip(fa[0] + fa[1], fb[0] + fb[1]))
        for k in (0, 1, 3, 17, 60, 200, n0 // 2, n0 - 1):
            with torch.no_grad():
                with native.use_impl("cpp"):
                    a = tree.budget_cut(ts, cam, k)
                with native.use_impl("torch"):
                    b = tree.budget_cut(ts, cam, k)
            assert a.s_v == b.s_v and a.n_frustum == b.n_frustum == n0, k
            if 0 < k < n0:  # a count budget's cut through tree_select: the count it solved from is its n_frustum
                with torch.no_grad():
                    sel = tree_select(g, cam, budget=Budget(count=k))[0]
                assert sel.n_frustum == n0 and all(torch.equal(x, y) for x, y in zip(sel.ids, a.ids)), k
            assert all(torch.equal(x, y) for x, y in zip(a.ids, b.ids)), k
            assert all(torch.equal(x, y) for x, y in zip(a.fade, b.fade)), k
            assert all(torch.allclose(x, y, atol=1e-6) for x, y in zip(a.t, b.t)), k
            assert sum(int(f[i].sum()) for f, i in zip(tree.frame(ts, cam)[1], a.ids)) <= k
            levels.add(round(a.s_v, 6))
    assert len(levels) > 8  # many levels, not one answer


@pytest.mark.skipif(not native.available(), reason="the C++ kernels do not build here")
def test_the_kept_budget_terms_follow_an_edited_model(model):
    """The C++ budget keeps every node's terms at its reference distance per model: an in-place
    edit of a ``sigma_d`` or an exit (an optimiser step), or another tensor, makes new ones, so the
    cut stays its twin's."""
    g, cams = model
    ts = [replace(t, sigma_d=t.sigma_d.clone(), extra=dict(t.extra)) for t in tree.tiers_of(g)]
    cam, k = cams[0], 40
    def both():
        with torch.no_grad():
            with native.use_impl("cpp"):
                a = tree.budget_cut(ts, cam, k)
            with native.use_impl("torch"):
                b = tree.budget_cut(ts, cam, k)
        assert a.s_v == b.s_v and all(torch.equal(x, y) for x, y in zip(a.ids, b.ids))
        return a.s_v
    first = both()
    with torch.no_grad():
        ts[1].sigma_d.mul_(3.0)  # in place: the same tensor, a new version
    second = both()
    ts[0].extra[tree.EXIT_KEY] = ts[0].extra[tree.EXIT_KEY] * 0.5  # another tensor
    third = both()
    assert len({first, second, third}) > 1  # the edits moved the level: the kept terms were not reused


@pytest.mark.skipif(not native.available(), reason="the C++ kernels do not build here")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_binned_budget_level_equals_a_full_sort(model, dtype):
    """``tree_budget`` sorts only the bins that may break the bound: on clustered positions (many
    equal, many within one bin, some past 1e6) it returns the level of the full sort (the twin)."""
    gen = torch.Generator().manual_seed(11)
    E, U, W = [], [], []
    for n in (3000, 1200, 300):
        e = torch.where(torch.rand(n, generator=gen) < 0.3, torch.full((n,), 1.25),
                        torch.exp(torch.rand(n, generator=gen) * 3)).to(dtype)
        e[:50] = 1.0 + torch.rand(50, generator=gen).to(dtype) * 1e-3  # one bin, many positions
        u = e * torch.where(torch.rand(n, generator=gen) < 0.2, torch.full((n,), 1.25),
                            1 + torch.rand(n, generator=gen) * 4).to(dtype)
        u[-5:] = 1e7
        E.append(e)
        U.append(u)
        W.append(torch.where(torch.rand(n, generator=gen) < 0.1, torch.zeros(n), torch.ones(n)).double())
    tt = tree.TreeTerms(E, U, [torch.zeros(len(e), dtype=torch.bool) for e in E], tree.tiers_of(model[0]), None, W)
    checked = 0
    for k in [0, 1, 2, 5, 17, 60, 200, 700, 1500, 2500, 3500, 4000, 10 ** 6]:
        for weights in (None, [w * torch.rand(len(w), generator=gen, dtype=torch.float64) * 30 for w in W]):
            kk = k if weights is None else 10.0 * k
            with native.use_impl("cpp"):
                a = tree.budget_s_v(tt, kk, weights)
            with native.use_impl("torch"):
                b = tree.budget_s_v(tt, kk, weights)
            assert a == b, (k, weights is None, a, b)
            checked += a > 1.0
    assert checked > 10  # levels past 1 were compared, not only the trivial answer


def test_the_hand_over_width_is_read_at_each_call(model, monkeypatch):
    """Every function of the rule takes ``F`` from ``hand_over`` or, left out, from
    ``tree.HAND_OVER`` as it is at the call (a study sets it): the same cut and positions both ways,
    and a wider hand-over puts more drawn rows part-way (0 < t < 1)."""
    g, cams = model
    ts, cam = tree.tiers_of(g), cams[0]

    def part_way(c):
        return sum(int(((t > 0) & (t < 1)).sum()) for t in c.t)

    for s in (2.2, 3.0, 4.7):
        explicit = tree.cut(ts, cam, s, hand_over=1.6)
        monkeypatch.setattr(tree, "HAND_OVER", 1.6)
        read = [tree.cut(ts, cam, s), tree.walk(ts, cam, s), tree.cut(ts, cam, s, tt=tree.terms(ts, cam))]
        monkeypatch.setattr(tree, "HAND_OVER", 1.25)
        for c in read:
            assert all(torch.equal(x, y) for x, y in zip(c.ids, explicit.ids))
            assert all(torch.allclose(x, y) for x, y in zip(c.t, explicit.t))
    assert sum(part_way(tree.cut(ts, cam, s, hand_over=1.6)) for s in S_VS) > \
        sum(part_way(tree.cut(ts, cam, s)) for s in S_VS)
    budget = tree.budget_cut(ts, cam, 300.0, hand_over=1.6)
    monkeypatch.setattr(tree, "HAND_OVER", 1.6)
    again = tree.budget_cut(ts, cam, 300.0)
    assert again.s_v == budget.s_v and all(torch.equal(x, y) for x, y in zip(again.ids, budget.ids))


def test_a_node_changes_over_at_most_the_morph_factor_of_its_interval(model, monkeypatch):
    """Step 5's ``w``: 1 until the last ``min(M, U / max(E, 1))`` of a drawn node's interval
    ``[E, U)``, then ``ln(U / s) / ln`` of that width, reaching 0 at ``U``; at ``M = F`` every change
    lasts exactly ``F`` (the rule before ``M``); a wider ``M`` puts more drawn rows part-way and
    leaves the cut's rows as they are, in the C++ kernels and their torch twin alike."""
    g, cams = model
    ts, cam = tree.tiers_of(g), cams[0]
    tt = tree.terms(ts, cam)
    checked = 0
    for s in S_VS:
        c = tree.cut(ts, cam, s, tt=tt)
        for n, u, ids, w in zip(tt.entry, tt.upper, c.ids, c.t):
            width = torch.clamp(u[ids] / n[ids].clamp_min(1.0), max=tree.MORPH)
            assert bool((width >= tree.HAND_OVER * (1 - 1e-6)).all())  # never shorter than F
            want = torch.clamp(torch.log(u[ids] / c.s_v) / torch.log(width), 0, 1)
            assert torch.allclose(w, want, atol=1e-6)
            checked += int(((width > tree.HAND_OVER * 1.01) & (w < 1)).sum())
    assert checked > 5  # rows whose change lasts longer than F were drawn part-way

    def part_way(m):
        monkeypatch.setattr(tree, "MORPH", m)
        out = []
        for impl in ("cpp", "torch"):
            with native.use_impl(impl):
                out.append([tree.cut(ts, cam, s) for s in S_VS])
        for a, b in zip(*out):  # the kernels and the twin agree at this M
            assert all(torch.equal(x, y) for x, y in zip(a.ids, b.ids))
            assert all(torch.allclose(x, y.to(x.dtype), atol=1e-5) for x, y in zip(a.t, b.t))
        return out[0], sum(int(((t > 0) & (t < 1)).sum()) for c in out[0] for t in c.t)

    (at_f, n_f), (at_m, n_m) = part_way(tree.HAND_OVER), part_way(1.6)
    for a, b in zip(at_f, at_m):
        assert all(torch.equal(x, y) for x, y in zip(a.ids, b.ids))  # the same rows drawn
    for c in at_f:  # M = F: every change over exactly F (the terms do not depend on M)
        for u, ids, w in zip(tt.upper, c.ids, c.t):
            assert torch.allclose(w, torch.clamp(torch.log(u[ids] / c.s_v) / math.log(tree.HAND_OVER), 0, 1), atol=1e-6)
    assert n_m > n_f


def test_a_child_leaves_between_its_own_exit_and_its_parents_entry():
    """``tree.build``'s exits: at ``exit_toward_parent = 0`` every node's exit is its own (where its
    tier's own level of detail drops it); at ``b`` a non-lead child's is ``own^(1 - b) sigma_p^b``,
    between its own and its parent's ``sigma_d``, while leads and roots keep their own; the tree and
    the entries do not change; ``b`` outside [0, 1] is refused."""
    t2 = _adapted(60, 3)
    linked = tiers.attach(_adapted(1200, 0), tiers.attach(_adapted(300, 2), t2, 2.5, 1.5), 2.0, 1.25)
    cams = make_cameras(2, 3)
    own, half = (tree.tiers_of(tree.build(linked, cams, exit_toward_parent=b, entry_toward_children=0.0))
                 for b in (0.0, 0.5))
    moved = 0
    for k, (a, h) in enumerate(zip(own, half)):
        assert torch.equal(a.sigma_d, h.sigma_d)
        x, y = a.extra[tree.EXIT_KEY].double(), h.extra[tree.EXIT_KEY].double()
        if k + 1 == len(own):  # the roots leave where their own level of detail drops them
            assert torch.equal(x, y)
            continue
        assert torch.equal(a.extra[tree.PARENT_KEY], h.extra[tree.PARENT_KEY])
        lead = tree.leads(a)
        assert torch.equal(x[lead], y[lead])
        s_p = own[k + 1].sigma_d.double()[a.extra[tree.PARENT_KEY].long()][~lead]
        assert torch.allclose(y[~lead], torch.sqrt(x[~lead] * s_p), rtol=1e-5)
        lo, hi = torch.minimum(x[~lead], s_p), torch.maximum(x[~lead], s_p)
        assert bool(((y[~lead] >= lo * (1 - 1e-5)) & (y[~lead] <= hi * (1 + 1e-5))).all())
        moved += int((~torch.isclose(x[~lead], y[~lead])).sum())
    assert moved > 100
    with pytest.raises(ValueError, match="exit_toward_parent"):
        tree.build(linked, cams, exit_toward_parent=1.5)


def test_a_parent_enters_toward_where_its_last_sibling_leaves():
    """``tree.build``'s entries: at ``entry_toward_children = a`` a merged node with children other
    than its lead has ``sigma_d = sigma^(1 - a) x_last^a``, ``x_last`` the largest own exit of
    those children (their exits at ``exit_toward_parent = 0``), between the two; a node whose only
    child is its lead keeps its entry, and so does every node at ``a = 0``; the tree and tier 0 do
    not change; ``a`` outside [0, 1] is refused."""
    t2 = _adapted(60, 3)
    linked = tiers.attach(_adapted(1200, 0), tiers.attach(_adapted(300, 2), t2, 2.5, 1.5), 2.0, 1.25)
    cams = make_cameras(2, 3)
    own, half = (tree.tiers_of(tree.build(linked, cams, exit_toward_parent=0.0, entry_toward_children=a))
                 for a in (0.0, 0.5))
    assert torch.equal(own[0].sigma_d, half[0].sigma_d)
    moved = 0
    for k in range(1, len(own)):
        child = own[k - 1]
        p, lead = child.extra[tree.PARENT_KEY].long(), tree.leads(child)
        assert torch.equal(p, half[k - 1].extra[tree.PARENT_KEY].long())
        x = child.extra[tree.EXIT_KEY].double()
        last = torch.zeros(len(own[k]), dtype=torch.float64).scatter_reduce(0, p[~lead], x[~lead], reduce="amax")
        has = torch.bincount(p[~lead], minlength=len(own[k])) > 0
        s0, s1 = own[k].sigma_d.double(), half[k].sigma_d.double()
        assert torch.allclose(s1[~has], s0[~has]) and bool(has.any())
        assert torch.allclose(s1[has], torch.sqrt(s0[has] * last[has]), rtol=1e-5)
        lo, hi = torch.minimum(s0[has], last[has]), torch.maximum(s0[has], last[has])
        assert bool(((s1[has] >= lo * (1 - 1e-5)) & (s1[has] <= hi * (1 + 1e-5))).all())
        moved += int((~torch.isclose(s0[has], s1[has])).sum())
    assert moved > 20
    with pytest.raises(ValueError, match="entry_toward_children"):
        tree.build(linked, cams, entry_toward_children=-0.5)
