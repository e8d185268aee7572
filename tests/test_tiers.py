"""The merged tiers (clod_adapter.train.tiers): their settings, the .ply elements, the choice and the
link, the job that builds them; tiers not linked into a merge tree are not drawn (the tree:
tests/test_tree.py)."""
from dataclasses import replace

import pytest
import torch

from clod_adapter.lod import rule as lod
from clod_adapter.train import config, tiers
from clod_adapter.lod.draw import render_lod
from clod_adapter.io.ply import PlyFormatError, lod_comment, read_ply, write_ply
from clod_adapter.io.synthetic import make_cameras, make_ground_truth
from clod_adapter.lod.budget import Budget


def _adapted(n, seed):
    g = make_ground_truth(n, seed=seed)
    gen = torch.Generator().manual_seed(seed + 7)
    g = g.with_sigma_d(0.2 + torch.rand(len(g), generator=gen))
    return replace(g, lod=lod.LodSettings(fade="window"),
                   log_scale_gain=0.3 * torch.rand(len(g), generator=gen),
                   opacity_logit_gain=torch.randn(len(g), generator=gen))


@pytest.fixture(scope="module")
def tiered():
    children, parents = _adapted(1200, 0), _adapted(150, 1)
    return tiers.attach(children, parents, 3.0, 1.5), make_cameras(1, 2)


def test_tier_settings_are_checked():
    st = lod.LodSettings(fade="window", tier_s_v=4.0, tier_start=1.5, tier_fade=1.25)
    assert (st.tier_s_v, st.tier_start, st.tier_fade) == (4.0, 1.5, 1.25) and lod.LodSettings().tier_s_v == 0.0
    for bad in (dict(tier_s_v=0.5), dict(tier_s_v=2.0, tier_start=0.9), dict(tier_s_v=2.0, tier_fade=1.0)):
        with pytest.raises(ValueError):
            lod.LodSettings(**bad)


@pytest.mark.parametrize("kw", [dict(s_v=1.0), dict(s_v=2.9), dict(s_v=4.0), dict(s_v=9.0),
                                dict(budget=Budget(share=0.3)), dict(budget=Budget(count=40))])
def test_tiers_not_linked_into_a_tree_are_not_drawn(tiered, kw):
    """A model whose merged tiers are attached but not linked into a merge tree (tiers.attach
    before lod.tree.build) is drawn as its own Gaussians by render_lod, lod_subset, the renderer
    hook and bake, at every s_v (also past its tier_s_v) and within budgets."""
    from clod_adapter import clod_kwargs, clod_rasterization
    from clod_adapter.export.bake import bake
    from clod_adapter.lod.draw import lod_subset

    g, cams = tiered
    children = replace(g, parents=None)
    cam = cams[0]
    r, own = render_lod(g, cam, **kw), render_lod(children, cam, **kw)
    assert torch.equal(r.image, own.image) and r.n_parents == 0 and r.n_rendered == own.n_rendered > 0
    sub = lod_subset(g, cam, **kw)
    assert torch.equal(sub.indices, own.indices) and sub.parent_indices is None and len(sub.means) == own.n_rendered
    col, _, meta = clod_rasterization(g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat[None],
                                      cam.K[None], cam.width, cam.height, sh_degree=g.sh_degree,
                                      **clod_kwargs(g), **kw, backend="cpu")
    torch.testing.assert_close(col[0], own.image, rtol=0, atol=1e-6)
    assert meta["lod_n_parents"] == [0] and meta["lod_tier_indices"] == [[]]
    baked, info = bake(g, [cam], opacity="mean", return_info=True, **kw)
    assert info.n_parents == 0 and len(baked) == own.n_rendered


def test_ply_round_trip_keeps_the_tier(tiered, tmp_path):
    g, cams = tiered
    p = write_ply(tmp_path / "t.ply", g)
    back = read_ply(p, unlinked_tiers=True)  # tiers not linked into a merge tree: read only when asked
    assert back.parents is not None and len(back.parents) == len(g.parents)
    assert back.lod.tier_s_v == 3.0 and back.lod.tier_start == 1.5 and back.parents.lod.tier_s_v == 0.0
    assert torch.equal(back.parents.sigma_d, g.parents.sigma_d) and torch.equal(back.parents.means, g.parents.means)
    # a model without a tier writes the header it always did
    assert "tier" not in lod_comment(lod.LodSettings(fade="window"))
    # the element alone, without a tier in the header: refused, naming the file
    bad = replace(g, lod=replace(g.lod, tier_s_v=0.0))
    with pytest.raises(ValueError):
        write_ply(tmp_path / "bad.ply", bad)
    import plyfile

    ply = plyfile.PlyData.read(str(p))
    ply.comments = [c.replace("tier_s_v=3.0", "tier_s_v=0.0") for c in ply.comments]
    ply.write(str(tmp_path / "bad2.ply"))
    with pytest.raises(PlyFormatError, match="bad2.ply.*lod_parent"):
        read_ply(tmp_path / "bad2.ply", unlinked_tiers=True)


def test_a_file_whose_tiers_are_not_linked_into_a_tree_is_refused(tiny_adapted, tiny_model, tmp_path, capfd):
    """A file written with ``--tier-draw chain`` (merged tiers attached, ``tree=True`` absent: the
    cross-fade chain, no longer drawn) is refused where it is read for drawing, with one line naming
    the file: read_ply, load_model, clod-render, clod-eval and clod-export exit 2 without a
    traceback. ``read_ply(unlinked_tiers=True)`` reads it (clod-adapt, for a merged tier's own file)."""
    from clod_adapter.cli.eval import main as eval_main
    from clod_adapter.cli.export import main as export_main
    from clod_adapter.cli.render import main as render_main
    from clod_adapter.errors import InputError
    from clod_adapter.io.load import load_model
    from clod_adapter.io.ply import UNLINKED_TIERS
    from conftest import err_line

    g = read_ply(tiny_adapted / "point_cloud.ply")
    old = write_ply(tmp_path / "chain.ply", tiers.attach(g, g.subset(torch.arange(0, len(g), 5)), 2.0, 1.0))
    assert b"tree=True" not in old.read_bytes()[:4000]
    for read in (read_ply, load_model):
        with pytest.raises(InputError, match="chain.ply: its merged tiers are not linked into a merge tree") as e:
            read(old)
        assert str(e.value) == f"{old}: {UNLINKED_TIERS}" and "--tier-draw chain" in str(e.value)
    assert len(read_ply(old, unlinked_tiers=True).parents) == len(g.subset(torch.arange(0, len(g), 5)))
    scene = str(tiny_model["scene"])
    for prog, main, extra in (("clod-render", render_main, ["--frames", "2"]), ("clod-eval", eval_main, ["--no-lpips"]),
                              ("clod-export", export_main, [])):
        out = tmp_path / prog
        assert main([str(old), "--images", scene, "-o", str(out), "--quiet", *extra]) == 2, prog
        line = err_line(capfd)
        assert "chain.ply" in line and "not linked into a merge tree" in line, (prog, line)


def test_model_operations_carry_or_drop_the_tier(tiered):
    g, _ = tiered
    assert g.detach().parents is not None and g.clone().parents is not None
    assert g.subset(torch.arange(10)).parents is None and g.with_sigma_d(None).parents is None


def test_choose_takes_over_where_the_parents_are_as_good(tiered):
    g, cams = tiered
    children = replace(g, parents=None)
    imgs = [render_lod(make_ground_truth(1200, seed=0), c).image.clamp(0, 1) for c in cams]
    same = tiers.choose(children, children, cams, imgs)  # parents identical to the model: the first switch
    assert same.tier_s_v == tiers.SWITCH_S_V[0] and same.tier_start == 1.0  # taken over at full detail
    by_psnr = tiers.choose(children, children, cams, imgs, rule="psnr")
    assert by_psnr.tier_s_v == tiers.SWITCH_S_V[0] and by_psnr.tier_start >= tiers.SWITCH_S_V[0]
    assert len(same.curves["gaussians"]) == len(tiers.SWITCH_S_V)
    assert len(same.curves["parents"]) == len(tiers.PARENT_S_V)
    dark = replace(children, opacity_logits=torch.full_like(children.opacity_logits, -12.0))
    none = tiers.choose(children, dark, cams, imgs)  # parents that draw nothing never pay
    assert none.tier_s_v is None


def test_attach_refuses_a_plain_model():
    plain = make_ground_truth(50, seed=3)
    with pytest.raises(ValueError, match="adapted"):
        tiers.attach(plain, _adapted(20, 4), 3.0)


def test_storage_counts_the_parent_element(tiered, tmp_path):
    from clod_adapter.evaluate.storage import ply_bytes

    g, _ = tiered
    assert ply_bytes(g) == write_ply(tmp_path / "s.ply", g).stat().st_size > ply_bytes(replace(g, parents=None))


def test_finetuned_fits_a_merge_to_the_training_views():
    """tiers.finetuned: a merge (here a perturbed model) fitted at full detail scores higher on
    the views it was fitted to; same count and SH degree; 0 steps is the merge itself."""
    from clod_adapter.metrics import psnr
    from clod_adapter.io.synthetic import perturb

    gt = make_ground_truth(300, seed=3)
    cams = make_cameras(1, 3, width=48, height=36)
    imgs = [render_lod(gt, c, None).image for c in cams]
    merged = perturb(gt, seed=4, strength=1.0)
    assert tiers.finetuned(merged, cams, imgs, 0) is merged
    fitted = tiers.finetuned(merged, cams, imgs, 60)
    assert len(fitted) == len(merged) and fitted.sh_degree == merged.sh_degree and fitted.sigma_d is None

    def score(m):
        return sum(psnr(render_lod(m, c, None).image, gt_img) for c, gt_img in zip(cams, imgs)) / len(cams)

    assert score(fitted) > score(merged) + 0.5


def test_tier_finetune_steps_must_be_a_count():
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().tier_finetune_steps == 400
    with pytest.raises(ValueError, match="tier_finetune_steps"):
        AdaptConfig(tier_finetune_steps=-1)


def test_tier_merge_names_a_decimator():
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().tier_merge == "prune"
    assert AdaptConfig(tier_merge="decimate").tier_merge == "decimate"
    assert AdaptConfig(tier_merge="adaptive").tier_merge == "adaptive"
    with pytest.raises(ValueError, match="tier_merge"):
        AdaptConfig(tier_merge="voxel")
    g = make_ground_truth(n=40, seed=0)
    with pytest.raises(ValueError, match="merge must be one of"):
        tiers.decimated(g, 0.5, merge="voxel")


def test_decimated_asks_splat_transform_for_the_named_merge(monkeypatch):
    asked = []
    monkeypatch.setattr(tiers, "merge_decimate", lambda g, n, mode, tool=None: asked.append((n, mode)) or g)
    g = make_ground_truth(n=40, seed=0)
    for merge in ("decimate", "adaptive"):
        tiers.decimated(g, 0.25, merge=merge)
    assert asked == [(10, "decimate"), (10, "adaptive")]


def test_a_pruned_tier_keeps_the_largest_weights_without_splat_transform(monkeypatch):
    monkeypatch.setattr(tiers, "merge_decimate", lambda *a, **k: pytest.fail("splat-transform asked"))
    g = make_ground_truth(n=40, seed=0)
    w = torch.arange(40, dtype=torch.float64).flip(0)  # Gaussian 0 weighs most
    out = tiers.decimated(g, 0.25, merge="prune", weights=w)
    assert len(out) == 10 and out.sigma_d is None
    assert torch.equal(out.means, g.means[:10])
    with pytest.raises(ValueError, match="blending weight"):
        tiers.decimated(g, 0.25, merge="prune")
    with pytest.raises(ValueError, match="blending weight"):
        tiers.decimated(g, 0.25, merge="prune", weights=w[:5])


def test_prune_scores_put_a_large_faint_splat_after_a_small_one_of_equal_weight(monkeypatch):
    """Weight over the square root of cost: two Gaussians that paint the same weight, the one that
    costs four times the pixels scores half."""
    from clod_adapter.train import pruning

    g = make_ground_truth(n=300, seed=0)
    cams = make_cameras(3, 2)
    monkeypatch.setattr(pruning, "blend_weights", lambda m, c: torch.ones(len(m), dtype=torch.float64))
    s = tiers.prune_scores(g, cams)
    cost = torch.zeros(300, dtype=torch.float64)
    for c in cams:
        v = tiers.view_lod(g.with_sigma_d(None), c)
        idx = torch.nonzero(v.visible, as_tuple=False).squeeze(1)
        cost[idx] += tiers.splat_cost(v, idx)
    assert bool((cost > 0).any())
    assert torch.allclose(s, 1.0 / torch.sqrt(1.0 + cost))
    with pytest.raises(ValueError, match="no cameras"):
        tiers.prune_scores(g, [])


def test_a_pruned_first_tier_needs_splat_transform_when_tiers_follow(tmp_path, monkeypatch):
    """Without splat-transform no tier is built (the job notes why), as with a merged first tier:
    the later tiers are merges of the first; a ladder of one pruned tier needs no tool."""
    from clod_adapter.io.splat_transform import SPLAT_TRANSFORM_ENV
    from clod_adapter.jobs import adapt as job
    from clod_adapter.train.config import AdaptConfig

    monkeypatch.setenv(SPLAT_TRANSFORM_ENV, str(tmp_path / "no-such-splat-transform"))
    g, cams = make_ground_truth(n=200, seed=0), make_cameras(3, 2)
    info = {}
    with pytest.raises(RuntimeError, match="npm ci"):
        job._tier_start(g, 0.5, (0.15,), cams, cams, AdaptConfig(), job.AdaptOptions(), False, info)
    share, first = job._tier_start(g, 0.5, (), cams, cams, AdaptConfig(tier_time_cap=0.0), job.AdaptOptions(),
                                   False, info)
    assert share == 0.5 and len(first) == 100 and info["time_cap"]["tried"] == []


def test_choice_views_are_evenly_spaced_training_views():
    assert tiers.choice_views(range(20)) == [0, 2, 4, 6, 8, 10, 12, 14]
    assert tiers.choice_views(range(64)) == list(range(0, 64, 8))
    assert tiers.choice_views(range(5)) == [0, 1, 2, 3, 4]


def test_predicted_ms_is_the_time_model_of_every_gaussian_in_view():
    g = make_ground_truth(n=300, seed=0)
    cams = make_cameras(3, 2)
    ms = tiers.predicted_ms(g, cams)
    assert ms == tiers.predicted_ms(g, cams)  # no wall clock
    half = g.subset(torch.arange(0, 300, 2))
    assert 0 < tiers.predicted_ms(half, cams) < ms
    free = tiers.FrameTimeModel(c0_ms=1.0)
    assert tiers.predicted_ms(g, cams, time_model=free) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="no cameras"):
        tiers.predicted_ms(g, [])


def test_first_share_lowers_a_slow_first_merge(monkeypatch):
    """The first tier's share drops by TIER_SHARE_STEP while its merge is predicted over the cap,
    never to the next share and at most TIER_SHARE_TRIES times; cap 0 predicts nothing."""
    g = make_ground_truth(n=1000, seed=0)
    merged = []
    monkeypatch.setattr(tiers, "decimated", lambda src, share, merge="decimate", tool=None, weights=None:
                        merged.append(round(share, 6)) or src.subset(torch.arange(round(share * len(src)))))
    # predicted ms: 40 + count / 10 (the input 140 ms, its 50 % merge 90 ms: 64 %, 35 %: 54 %)
    monkeypatch.setattr(tiers, "predicted_ms", lambda m, cams, time_model=None: 40.0 + len(m) / 10)
    share, m, tried = tiers.first_share(g, 0.5, [None], cap=0.6)
    assert share == pytest.approx(0.35) and len(m) == 350
    assert tried == [(0.5, pytest.approx(90 / 140)), (pytest.approx(0.35), pytest.approx(75 / 140))]
    share, m, tried = tiers.first_share(g, 0.5, [None], cap=90 / 140)  # at the cap: kept
    assert share == 0.5 and len(m) == 500 and len(tried) == 1
    share, _, tried = tiers.first_share(g, 0.5, [None], cap=0.3)  # never under the cap: three tries
    assert share == pytest.approx(0.5 * tiers.TIER_SHARE_STEP ** 3) and len(tried) == 1 + tiers.TIER_SHARE_TRIES
    share, _, tried = tiers.first_share(g, 0.5, [None], cap=0.3, floor=0.3)  # not down to the next share
    assert share == pytest.approx(0.35) and len(tried) == 2
    merged.clear()
    share, m, tried = tiers.first_share(g, 0.5, [None], cap=0.0)
    assert (share, len(m), tried, merged) == (0.5, 500, [], [0.5])
    with pytest.raises(ValueError, match="tier_time_cap"):
        tiers.first_share(g, 0.5, [None], cap=-0.1)


def test_tier_time_cap_is_a_share_of_the_frame():
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().tier_time_cap == config.TIER_TIME_CAP == 0.8
    assert AdaptConfig(schedule="paper").tier_time_cap == 0.0
    assert AdaptConfig(tier_time_cap=0).tier_time_cap == 0.0
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="tier_time_cap"):
            AdaptConfig(tier_time_cap=bad)


def test_link_hands_a_merged_tier_over_no_later_than_asked(tiered, monkeypatch):
    """tiers.link(max_tier_s_v=S): the rule's hand-over where it is at or before S, else S; 0
    keeps the rule's; a tier the rule leaves out stays out; the record keeps both."""
    g, cams = tiered
    model, parents = replace(g, parents=None), g.parents
    said = []
    for rule_s_v, cap, want in ((2.5, 1.6, 1.6), (2.5, 0.0, 2.5), (1.25, 1.6, 1.25), (None, 1.6, None)):
        monkeypatch.setattr(tiers, "choose", lambda *a, s=rule_s_v, **k: tiers.TierChoice(s, 1.0, {}))
        linked, tried = tiers.link(model, [parents], cams, [None], max_tier_s_v=cap, log=said.append)
        assert tried[0]["rule_s_v"] == rule_s_v and tried[0]["tier_s_v"] == want
        if want is None:
            assert linked.parents is None and len(tried) == 2  # the time rule, then the psnr rule
        else:
            assert linked.lod.tier_s_v == want and linked.parents is parents
    assert sum("hands over at s_v = 1.6" in m for m in said) == 1  # only where the cap moved it
    for bad in (1.0, 0.5, -1.0, float("nan")):
        with pytest.raises(ValueError, match="max_tier_s_v"):
            tiers.link(model, [parents], cams, [None], max_tier_s_v=bad)


def test_tier_hand_over_is_an_s_v_or_the_time_rule():
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().tier_hand_over == config.TIER_HAND_OVER == 1.6
    assert AdaptConfig(schedule="paper").tier_hand_over == 0.0
    assert AdaptConfig(tier_hand_over=0).tier_hand_over == 0.0 and AdaptConfig(tier_hand_over=3).tier_hand_over == 3.0
    for bad in (1.0, 0.5, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="tier_hand_over"):
            AdaptConfig(tier_hand_over=bad)


def test_adapt_job_caps_only_the_merged_tiers_hand_overs(tiny_model, tmp_path, monkeypatch):
    """The adaptation job with two merged tiers: the first tier's own link (to the second) is capped
    at ``tier_hand_over``, the input's link to the first tier is not."""
    from clod_adapter.io.splat_transform import find_splat_transform
    from clod_adapter.jobs.adapt import AdaptOptions, run
    from clod_adapter.train.config import AdaptConfig

    if find_splat_transform() is None:
        pytest.skip("splat-transform is not installed (npm ci): the tier's merge needs it")
    monkeypatch.setattr(tiers, "PARENT_MIN_GAUSSIANS", 100)
    caps, link = [], tiers.link

    def spy(*a, max_tier_s_v=0.0, **k):
        caps.append(max_tier_s_v)
        return link(*a, max_tier_s_v=max_tier_s_v, **k)

    monkeypatch.setattr(tiers, "link", spy)
    cfg = AdaptConfig(iterations=2, max_sv=2.0, parent_share=(0.4, 0.2), tier_finetune_steps=0, tier_time_cap=0,
                      tier_hand_over=1.3)
    run(tiny_model["ply"], tiny_model["scene"], tmp_path / "two", cfg, AdaptOptions(progress=False, timing_repeats=1))
    assert caps == [1.3, 0.0]  # the first tier's link (to the second) first, then the input's


def test_clod_adapt_has_one_tier_option():
    """Of the merged tiers, clod-adapt shows a user their shares alone (``--parent-share``); how
    each tier is built, fitted and handed over is AdaptConfig's (the benchmarks' ``--config``)."""
    from clod_adapter.cli.adapt import build_parser

    flags = {f for a in build_parser()._actions for f in a.option_strings}
    assert {f for f in flags if f.startswith(("--tier", "--tree", "--parent"))} == {"--parent-share"}
    with pytest.raises(SystemExit):
        build_parser().parse_args(["m.ply", "--tier-merge", "decimate"])


def test_tier_iteration_share_sets_each_tiers_steps():
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().tier_iterations() == AdaptConfig().iterations // 2  # the default: half
    assert AdaptConfig(tier_iteration_share=1).tier_iterations() == AdaptConfig().iterations
    assert AdaptConfig(iterations=1000, tier_iteration_share=0.5).tier_iterations() == 500
    assert AdaptConfig(iterations=3, tier_iteration_share=0.01).tier_iterations() == 1
    assert AdaptConfig(iterations=0, tier_iteration_share=0.5).tier_iterations() == 0
    for bad in (0.0, -0.5, 1.5, float("nan")):
        with pytest.raises(ValueError, match="tier_iteration_share"):
            AdaptConfig(tier_iteration_share=bad)


def test_tree_spread_is_a_factor_above_one():
    from clod_adapter.lod.tree import SPREAD
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().tree_spread == SPREAD == 2.0 and AdaptConfig(tree_spread=3).tree_spread == 3.0
    for bad in (1.0, 0.5, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="tree_spread"):
            AdaptConfig(tree_spread=bad)


@pytest.mark.parametrize("key", ["tree_budget_steps", "tree_exit_toward_parent", "tree_entry_toward_children"])
def test_tree_shares_are_checked(key):
    """The tree's shares default to their module constants and take values in [0, 1] only."""
    from clod_adapter.lod.tree import ENTRY_TOWARD_CHILDREN, EXIT_TOWARD_PARENT
    from clod_adapter.train.config import AdaptConfig
    from clod_adapter.train.config import TREE_BUDGET_STEPS

    default = {"tree_budget_steps": TREE_BUDGET_STEPS, "tree_exit_toward_parent": EXIT_TOWARD_PARENT,
               "tree_entry_toward_children": ENTRY_TOWARD_CHILDREN}[key]
    assert getattr(AdaptConfig(), key) == default == {"tree_budget_steps": 0.5, "tree_exit_toward_parent": 0.25,
                                                      "tree_entry_toward_children": 0.5}[key]
    assert getattr(AdaptConfig(**{key: 0}), key) == 0.0
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match=key):
            AdaptConfig(**{key: bad})


def test_tier_downscale_sets_the_later_tiers_resolution():
    """``tier_downscale``: the later tiers' scene resolution factor, the model's times it, at most 8."""
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().tier_downscale == 2
    assert [AdaptConfig().tier_resolution(r) for r in (1, 2, 4, 8)] == [2, 4, 8, 8]
    assert AdaptConfig(tier_downscale=1).tier_resolution(2) == 2
    for bad in (0, 3, 16):
        with pytest.raises(ValueError, match="tier_downscale"):
            AdaptConfig(tier_downscale=bad)


def test_adapt_job_builds_the_tier_or_says_why_not(tiny_model, tmp_path, monkeypatch):
    """clod-adapt: under PARENT_MIN_GAUSSIANS no tier (and metrics.json says why); over it, the
    merged input is adapted into OUT/parents and, when it pays, stored as the lod_parent element,
    linked into a merge tree."""
    import json

    from clod_adapter.cli.adapt import main
    from clod_adapter.io.splat_transform import find_splat_transform
    from clod_adapter.train.config import AdaptConfig
    from conftest import FAST

    args = [str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), *FAST]
    assert main(args + ["-o", str(tmp_path / "small")]) == 0
    small = json.loads((tmp_path / "small" / "metrics.json").read_text())
    tier = small["tier"]
    assert tier["used"] is False and "under 10,000" in tier["why"]
    assert list(small)[-1] == "job_seconds" and small["job_seconds"] >= small["train_seconds"] > 0
    assert read_ply(tmp_path / "small" / "point_cloud.ply").parents is None
    if find_splat_transform() is None:
        pytest.skip("splat-transform is not installed (npm ci): the tier's merge needs it")
    monkeypatch.setattr(tiers, "PARENT_MIN_GAUSSIANS", 100)
    from clod_adapter.jobs import adapt_inputs

    reads, read = [], adapt_inputs.load_model  # every checkpoint the job reads, as it reads it
    monkeypatch.setattr(adapt_inputs, "load_model", lambda path, *a, **k: reads.append(str(path)) or read(path, *a, **k))
    from clod_adapter.lod import tree as tree_mod

    spreads, build = [], tree_mod.build  # the tree is built with the config's spread and exits
    monkeypatch.setattr(tree_mod, "build", lambda *a, **k: spreads.append(
        (k.get("spread"), k.get("exit_toward_parent"), k.get("entry_toward_children"))) or build(*a, **k))
    out = tmp_path / "tier"
    assert main(args + ["-o", str(out), "--parent-share", "0.2,0.1"]) == 0
    # read once each: the input, then each tier's merged input by the adaptation of that tier
    assert reads == [str(tiny_model["ply"]), str(out / "parents_input.ply"),
                     str(out / "parents" / "parents_input.ply")], reads
    top = json.loads((out / "metrics.json").read_text())
    tier = top["tier"]
    assert top["job_seconds"] >= top["train_seconds"] + tier["seconds"]  # the whole job, every tier included
    pm = json.loads((out / "parents" / "metrics.json").read_text())
    assert "job_seconds" not in pm  # the top job's only
    # the tier's own test evaluation is untimed (the top job times the linked model); the top job's is timed
    assert pm["timing"]["repeats"] == 0 and top["timing"]["repeats"] == 1 and top["timing"]["method"] == "interleaved"
    # tier_downscale 2: the first tier is trained at the model's resolution, the next at half of it
    ppm = json.loads((out / "parents" / "parents" / "metrics.json").read_text())
    assert pm["resolution"] == tier["resolution"] == top["resolution"] and pm["image_size"] == top["image_size"]
    assert ppm["resolution"] == pm["tier"]["resolution"] == 2 * top["resolution"]
    assert all(abs(2 * a - b) <= 1 for a, b in zip(ppm["image_size"], top["image_size"]))
    tried = tier["time_cap"]["tried"]  # the first merge's share, lowered while predicted over the cap
    assert tier["time_cap"]["cap"] == config.TIER_TIME_CAP and tried[0][0] == 0.2
    assert tier["parent_share"] == tried[-1][0] and all(r > config.TIER_TIME_CAP for _, r in tried[:-1])
    n_parents = round(tier["parent_share"] * 300)
    assert tier["finetune"]["steps"] == 2  # tier_finetune_steps 400, at most --iterations 2
    steps = json.loads((out / "metrics.json").read_text())["config"]["iterations"]
    assert json.loads((out / "parents" / "metrics.json").read_text())["config"]["iterations"] == round(steps / 2)
    assert tier["parents"] == n_parents and (out / "parents" / "point_cloud.ply").is_file()
    assert len(tier["curves"]["gaussians"]) == len(tiers.SWITCH_S_V)
    g = read_ply(out / "point_cloud.ply")
    assert tier["used"], tier.get("why")  # the fixture's merges pay: the tier is attached
    # the tiers linked into one merge tree, its sizes recorded
    assert g.lod.tier_s_v == tier["tier_s_v"] and len(g.parents) == n_parents and g.lod.tree
    assert tier["tree"][:2] == [len(g), n_parents] and tier["tree_fit"]["steps"] == 2  # at most --iterations
    assert tier["tree_fit"]["budget_steps"] == 0.5  # the default: half the fit's steps on budget cuts
    assert tier["tree_fit"]["grow"] == 1.0 and tier["tree_fit"]["free_roots"] == 0.25  # bounded but the last roots
    c = AdaptConfig()
    assert spreads == [(c.tree_spread, c.tree_exit_toward_parent, c.tree_entry_toward_children)] == [
        (tree_mod.SPREAD, tree_mod.EXIT_TOWARD_PARENT, tree_mod.ENTRY_TOWARD_CHILDREN)]


def test_adapt_job_builds_a_tree_from_a_pruned_tier(tiny_model, tmp_path, monkeypatch):
    """clod-adapt with one pruned tier (``--parent-share X``, the default ``--tier-merge prune``)
    builds the merge tree without splat-transform, reading the input, the scene and each model it
    wrote once: the written model is a tree, every node's parent in the next tier, each tier with its
    reference distances, and a coarse level draws fewer nodes than s_v = 1."""
    import json

    from clod_adapter.cli.adapt import main
    from clod_adapter.io import splat_transform
    from clod_adapter.jobs import adapt as job, adapt_inputs
    from clod_adapter.lod import tree
    from clod_adapter.io.load import load_scene
    from conftest import FAST

    def no_tool(*a, **k):
        raise AssertionError("splat-transform was called")

    monkeypatch.setattr(splat_transform, "find_splat_transform", lambda: None)  # as without node_modules
    monkeypatch.setattr(splat_transform, "run_splat_transform", no_tool)
    monkeypatch.setattr(tiers, "PARENT_MIN_GAUSSIANS", 100)
    monkeypatch.setattr(tiers, "choose", lambda g, p, *a, **k: tiers.TierChoice(1.5, 1.0, {}))  # the tier pays
    reads, scenes, own = [], [], []  # the checkpoints, scene folders and adapted models the job reads
    for mod, name, log in ((adapt_inputs, "load_model", reads), (adapt_inputs, "load_scene", scenes),
                           (job, "read_ply", own)):
        monkeypatch.setattr(mod, name, lambda p, *a, f=getattr(mod, name), log=log, **k: log.append(p) or f(p, *a, **k))
    out = tmp_path / "pruned"
    assert main([str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), *FAST, "-o", str(out),
                 "--parent-share", "0.4"]) == 0
    # read once each: the input, the scene, the tier's input (by its adaptation) and the tier's model
    assert reads == [tiny_model["ply"], out / "parents_input.ply"] and scenes == [tiny_model["scene"]]
    assert own == [out / "parents" / "point_cloud.ply"]
    tier = json.loads((out / "metrics.json").read_text())["tier"]
    g = read_ply(out / "point_cloud.ply")
    assert tier["used"] and tree.is_tree(g) and tier["tree"] == [len(t) for t in tree.tiers_of(g)]
    ts = tree.tiers_of(g)
    assert len(ts) == 2 and len(ts[1]) == tier["parents"] < len(ts[0])
    for below, above in zip(ts, ts[1:]):
        par = below.extra["parent"].long()
        assert par.min() >= 0 and par.max() < len(above)  # every node's parent in the next tier
        assert torch.bincount(par, minlength=len(above)).min() > 0  # and every merged node a parent
    assert "exit" in ts[-1].extra
    assert all(tree.REFERENCE_KEY in t.extra and len(t.extra[tree.REFERENCE_KEY]) == len(t) for t in ts)
    cam = load_scene(tiny_model["scene"]).train[0]
    full, coarse = render_lod(g, cam, 1.0), render_lod(g, cam, 20.0)
    assert coarse.n_parents > 0 and coarse.n_rendered < full.n_rendered
    # metrics.json's levels are the tree's as written (measured once, after the tier is attached);
    # the tier's own run measures none
    from clod_adapter.evaluate.level_metrics import evaluate_levels
    m = json.loads((out / "metrics.json").read_text())
    sc = load_scene(tiny_model["scene"])
    ev = evaluate_levels(g, sc.test, [sc.load_image(c) for c in sc.test], [lv["s_v"] for lv in m["levels"]],
                         tau=m["config"]["tau"])
    assert len(m["levels"]) > 1 and m["timing"]["method"] == "interleaved"
    assert [lv["gaussians"] for lv in m["levels"]] == pytest.approx([e.gaussians for e in ev])
    assert [lv["psnr"] for lv in m["levels"]] == pytest.approx([e.psnr for e in ev], abs=1e-3)
    assert json.loads((out / "parents" / "metrics.json").read_text())["levels"] == []


def test_a_signal_while_the_tree_is_measured_stops_the_job(tiny_model, tmp_path, monkeypatch):
    """A job that builds merged tiers measures its levels once they are attached; a signal then
    stops it at once (exit status 130), the merge tree written and ``metrics.json``
    without levels."""
    import json
    import os
    import signal

    from clod_adapter.cli.adapt import main
    from clod_adapter.io import splat_transform
    from clod_adapter.jobs import adapt_levels
    from clod_adapter.lod import tree
    from conftest import FAST

    monkeypatch.setattr(splat_transform, "find_splat_transform", lambda: None)
    monkeypatch.setattr(tiers, "PARENT_MIN_GAUSSIANS", 100)
    monkeypatch.setattr(tiers, "choose", lambda g, p, *a, **k: tiers.TierChoice(1.5, 1.0, {}))
    measured = []
    real = adapt_levels.evaluate_levels

    def interrupted(*a, **k):
        measured.append(1)
        os.kill(os.getpid(), signal.SIGINT)  # arrives while the tree is measured
        return real(*a, **k)

    monkeypatch.setattr(adapt_levels, "evaluate_levels", interrupted)
    out = tmp_path / "stopped"
    assert main([str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), *FAST, "-o", str(out),
                 "--parent-share", "0.4"]) == 130
    assert measured == [1]  # the top model's levels only, after the tier (the tier's own run measures none)
    assert tree.is_tree(read_ply(out / "point_cloud.ply"))
    assert json.loads((out / "metrics.json").read_text())["levels"] == []


@pytest.mark.slow
def test_adapt_job_builds_a_tree(tiny_model, tmp_path, monkeypatch):
    """clod-adapt with merged tiers: the tiers linked into a merge tree (written whole, every node's
    parent in the next tier), fitted on its cuts for at most --iterations steps, and lod_strip.png
    drawn through it."""
    import json

    from clod_adapter.lod import tree
    from clod_adapter.cli.adapt import main
    from clod_adapter.io.splat_transform import find_splat_transform
    from clod_adapter.train.config import AdaptConfig
    from conftest import FAST

    if find_splat_transform() is None:
        pytest.skip("splat-transform is not installed (npm ci): the tier's merge needs it")
    monkeypatch.setattr(tiers, "PARENT_MIN_GAUSSIANS", 100)
    monkeypatch.setattr(tiers, "choose", lambda g, p, *a, **k: tiers.TierChoice(1.5, 1.0, {}))  # every tier pays
    out = tmp_path / "tree"
    assert main([str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), *FAST, "-o", str(out),
                 "--parent-share", "0.5,0.2"]) == 0
    tier = json.loads((out / "metrics.json").read_text())["tier"]
    assert tier["tree_fit"]["budget_steps"] == AdaptConfig().tree_budget_steps == 0.5  # the config's reaches the fit
    g = read_ply(out / "point_cloud.ply")
    assert tier["used"] and g.lod.tree and tree.is_tree(g) and tier["tree"] == [len(t) for t in tree.tiers_of(g)]
    assert len(tier["tree"]) == 3 and tier["tree_fit"]["steps"] == 2  # --tree-steps 1000, at most --iterations 2
    ts = tree.tiers_of(g)
    for below, above in zip(ts, ts[1:]):
        assert torch.bincount(below.extra["parent"].long(), minlength=len(above)).min() > 0
    assert "exit" in ts[-1].extra
    # lod_strip.png redrawn through the tree: more panels than the model's own levels (1, 2 = --max-sv)
    from PIL import Image

    with Image.open(out / "lod_strip.png") as im, Image.open(out / "parents" / "lod_strip.png") as own:
        assert im.width > own.width


def test_export_carries_the_tree(tiny_adapted, tiny_model, tmp_path):
    """clod-export of a model whose merged tier is linked into a merge tree: the extended .ply keeps
    the tree (SH-reduced with the model), a level baked past the hand-over holds the merged nodes
    it draws and renders close to render_lod; export.json says which is which."""
    import json

    from clod_adapter.cli.export import main as export_main
    from clod_adapter.io.load import load_scene
    from clod_adapter.lod import tree
    from clod_adapter.metrics import psnr
    from clod_adapter.export.web import find_playcanvas

    g = read_ply(tiny_adapted / "point_cloud.ply")
    scene = load_scene(tiny_model["scene"])
    linked = tree.build(tiers.attach(g, g.subset(torch.arange(0, len(g), 5)), 2.0, 1.0), scene.train)
    src = write_ply(tmp_path / "tree.ply", linked)
    out = tmp_path / "exp"
    web = ["--web", str(out / "web")] if find_playcanvas() is not None else []
    assert export_main([str(src), "-s", str(tiny_model["scene"]), "-o", str(out), "--quiet", "--s-v", "3.0",
                        "--sh-max-drop-db", "0.5", *web]) == 0
    rep = json.loads((out / "export.json").read_text())
    assert rep["tier"]["parents_in"] == len(linked.parents) and rep["tier"]["tier_s_v"] == 2.0
    ext = read_ply(out / "point_cloud_clod.ply")
    assert tree.is_tree(ext) and len(ext.parents) == rep["tier"]["parents_out"] == len(linked.parents) > 0
    assert ext.parents.sh_degree == ext.sh_degree == rep["sh_degree_out"]
    if web:  # the page draws the tree as one set (its drawing: tests/test_web_tree.py)
        cfg = json.loads((out / "web" / "clod.json").read_text())
        assert cfg["tree"]["counts"] == [len(t) for t in tree.tiers_of(ext)] and "tier" not in cfg
    baked = read_ply(out / rep["baked"]["file"])
    n_par = rep["baked"]["of_them_parents"]
    assert 0 < n_par < len(baked) and baked.sigma_d is None  # past the hand-over: tier 0 and merged nodes
    cam = scene.train[0]
    ref = render_lod(ext, cam, 3.0).image
    # measured 26.5 dB for the baked file (the union over the training views, a node in a hand-over
    # baked as itself); 20.8 dB for tier 0 drawn alone at the same s_v
    baked_db = psnr(render_lod(baked, cam).image, ref.clamp(0, 1))
    assert baked_db > 24.0 and psnr(render_lod(replace(ext, parents=None), cam, 3.0).image, ref.clamp(0, 1)) < baked_db - 3.0


def test_renderer_hook_refuses_incomplete_parents(tiered):
    """A merge tree's tier passed to the renderer hook without one of its tensors: a ValueError
    naming it, at an s_v and within a budget."""
    from clod_adapter import clod_kwargs, clod_rasterization
    from clod_adapter.lod import tree

    g, cams = tiered
    g = tree.build(g, make_cameras(2, 3))
    cam = cams[0]
    kw = clod_kwargs(g)
    del kw["parents"]["sigma_d"]
    with pytest.raises(ValueError, match="parents needs sigma_d"):
        clod_rasterization(g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat[None], cam.K[None],
                           cam.width, cam.height, sh_degree=g.sh_degree, **kw, s_v=4.0, backend="cpu")
    with pytest.raises(ValueError, match="parents needs sigma_d"):
        clod_rasterization(g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat[None], cam.K[None],
                           cam.width, cam.height, sh_degree=g.sh_degree, **kw, budget=Budget(count=50), backend="cpu")
    with pytest.raises(ValueError, match="no sigma_d"):
        clod_kwargs(make_ground_truth(10, seed=2))


def test_eval_sweep_reaches_the_parents_range():
    """clod-eval's default s_v sweep: the even part to 1.2 max_sv, then a tiered model's levels
    from the middle of its first hand-over to where the last tier is at 1.2 x its max_sv."""
    from clod_adapter.jobs.eval import sv_grid

    plain = sv_grid(5.0, 25)
    st = lod.LodSettings(fade="window", tier_s_v=5.0, tier_start=1.25)
    g = sv_grid(5.0, 25, lod_settings=st)
    assert g[:25] == plain and len(g) > 25 and g[-1] == pytest.approx(1.2 * 5.0 * 1.25 * 5.0 / 1.25)
    assert all(b > a for a, b in zip(g, g[1:])) and sv_grid(5.0, 25, lod_settings=lod.LodSettings()) == plain
    fern_like = sv_grid(5.0, 25, lod_settings=replace(st, tier_s_v=7.5, tier_start=3.0))
    assert fern_like[25] == pytest.approx(7.5 * 1.25 ** 0.5) and len(fern_like) == 31


def test_popping_sweep_runs_through_every_tier():
    """clod-eval's popping sweep: even to 1.2 max_sv without tiers; with merged tiers (reach > 1)
    evenly in ln s_v from 1 to 1.2 max_sv x reach."""
    import math

    from clod_adapter.jobs.eval import popping_sweep

    plain = popping_sweep(5.0, 1.0, 31)
    assert len(plain) == 31 and plain[0] == 1.0 and plain[-1] == pytest.approx(6.0)
    assert plain[1] - plain[0] == pytest.approx(plain[-1] - plain[-2])
    tiered = popping_sweep(5.0, 17.0, 31)
    assert tiered[0] == pytest.approx(1.0) and tiered[-1] == pytest.approx(6.0 * 17.0)
    ratios = [b / a for a, b in zip(tiered, tiered[1:])]
    assert max(ratios) == pytest.approx(min(ratios)) and ratios[0] == pytest.approx(math.exp(math.log(102.0) / 30))
    with pytest.raises(ValueError, match="steps"):
        popping_sweep(5.0, 1.0, 1)


def test_adapt_config_takes_descending_shares():
    from clod_adapter.train.config import AdaptConfig

    assert AdaptConfig().parent_share == config.DEFAULT_SHARES
    assert AdaptConfig(parent_share=0.1).parent_share == (0.1,)
    assert AdaptConfig(parent_share=0).parent_share == () and AdaptConfig(schedule="paper").parent_share == ()
    for bad in ((0.1, 0.3), (1.2,), (0.5, 0.5)):
        with pytest.raises(ValueError, match="parent_share"):
            AdaptConfig(parent_share=bad)
