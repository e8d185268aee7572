"""How long, on which cuts and at which resolution should a merge tree be fitted?

For each input (default: fern) the cached ``--holdout-val`` adaptation with ``clod-adapt``'s
defaults (``benchmarks.common.adapt_cached``, trained on the fit views only) is taken apart: its
tier 0 and its merged tiers as the job adapted them are linked again
(:func:`clod_adapter.train.tiers.link`, each hand-over set where the job set it) and built into a
tree (:func:`clod_adapter.lod.tree.build`), which reproduces the job's tree before its fit (the
node constants are checked equal to the cached model's). That tree is then fitted on its cuts
(:func:`clod_adapter.train.tree_fit.finetune`) for each of ``--steps`` on the fit views, drawing a
count budget's cut at ``--budget-steps`` of the steps, at the model's resolution or at half of it
(``--half``), and scored on the validation views: the popping ratio along ``s_v`` and along count budgets (``clod-eval``'s,
:mod:`clod_adapter.evaluate.popping`, from the first ``--popping-views`` views) and the mean PSNR
at count budgets of 75 / 50 / 30 / 15 / 8 / 3 % of the Gaussians in view and at the coarse levels
``s_v`` 30 / 55 / 110. No wall clock is scored except with ``--time`` (the fit's seconds are
printed for scale). No goal is enforced (a study: exit 0)::

    python -m benchmarks.studies.tree_fit --steps 0 250 500 1000 2000
    python -m benchmarks.studies.tree_fit --steps 1000 --budget-steps 0.5
    python -m benchmarks.studies.tree_fit --steps 1000 2000 --budget-steps 0.5 --half
    python -m benchmarks.studies.tree_fit --as-adapted --config tier_iteration_share=0.5
    python -m benchmarks.studies.tree_fit --steps 1000 --budget-steps 0.5 --spread 2 4
    python -m benchmarks.studies.tree_fit --steps 1000 --budget-steps 0.5 --hand-over 1.25 1.5 1.75
    python -m benchmarks.studies.tree_fit --inputs fern --steps 1000 --budget-steps 0.5 --morph 1.25 1.6
    python -m benchmarks.studies.tree_fit --inputs skull --as-adapted --morph 1.25 1.4 1.6 2 --popping-views 7
    python -m benchmarks.studies.tree_fit --steps 1000 --budget-steps 0.5 --exit-toward-parent 0 0.25 0.5 0.75 1
    python -m benchmarks.studies.tree_fit --inputs skull --steps 1000 --budget-steps 0.5 \\
        --grow none 1.25 1.1 1 --time --popping-views 7
    python -m benchmarks.studies.tree_fit --inputs skull fern maskgaussian --steps 1000 \\
        --budget-steps 0.5 --grow none 1 --free-roots 0 0.25 --time --popping-views 7
    python -m benchmarks.studies.tree_fit --inputs fern maskgaussian skull --steps 1000 \\
        --budget-steps 0.5 --popping-views 7 --rate 1 2 1,0.1 1,1,0.99
    python -m benchmarks.studies.tree_fit --inputs skull --steps 250 500 750 1000 1250 1500 \\
        --budget-steps 0.5 --popping-views 0 --rate 2 --held-out 10
    python -m benchmarks.studies.tree_fit --inputs fern --steps 250 500 750 1000 1250 1500 \\
        --budget-steps 0.5 --popping-views 0 --rate 2 --held-out 7
    python -m benchmarks.studies.tree_fit --inputs skull fern maskgaussian --steps 1000 \\
        --budget-steps 0.5 --popping-views 7 --lead mass
    python -m benchmarks.studies.tree_fit --inputs skull --as-adapted --popping-views 7
    python -m benchmarks.studies.tree_fit --inputs fern skull --steps 0 --popping-views 0
    python -m benchmarks.studies.tree_fit --inputs fern skull --steps 1000 --budget-steps 0.5 \\
        --popping-views 2 --cut-range 0.01,1e4 0.05,20 0.1,10

Every row ends with tier 1 drawn whole, as a plain model: its PSNR and its count over tier 0's.

``--cut-range LOWEST,CAP ...`` fits the tree on count budgets from ``LOWEST`` of the Gaussians in
view (:data:`clod_adapter.train.tree_fit.BUDGET_LOWEST`, 0.01) and on levels up to ``s_v = CAP``
(:data:`clod_adapter.train.tree_fit.LEVEL_CAP`; the coarsest level the views draw where lower), one
row per value: does a fit held to the middle of the range draw it better?

``--spread R ...`` builds the tree with each tier's hand-overs spread over a factor ``R`` of ``s_v``
(:func:`clod_adapter.lod.tree.build`'s ``spread``; default the adaptation's ``tree_spread``),
one set of rows per value.

``--exit-toward-parent B ...`` builds the tree with each non-lead child's exit moved the share ``B``
of the way toward its parent's entry (:func:`clod_adapter.lod.tree.build`'s ``exit_toward_parent``;
default the adaptation's ``tree_exit_toward_parent``), one set of rows per value.

``--hand-over F ...`` draws and fits the tree with a hand-over of width ``F`` in ``s_v``
(:data:`clod_adapter.lod.tree.HAND_OVER`, set for the run; the node constants do not depend on
it), one set of rows per value.

``--morph M ...`` draws and fits the tree with hand-overs and exits over at most a factor ``M``
of ``s_v`` (:data:`clod_adapter.lod.tree.MORPH`, set for the run), one set of rows per value
(with ``--as-adapted``: the job's fitted tree drawn at each ``M``).

``--grow G ...`` fits the tree with its merged nodes' scales grown by at most a factor ``G``
(:func:`clod_adapter.train.tree_fit.finetune`'s ``grow``; ``none``: unbounded; default the
adaptation's ``tree_grow``), one row per value; ``--free-roots S ...`` leaves the share ``S`` of
the roots, those that leave last, free to grow (``finetune``'s ``free_roots``), one row per value
and bound. ``--time`` adds to each row its frame time at the
counts splat-transform ``--decimate`` keeps at 30 / 15 / 8 % of the model, over the decimated
model's (:func:`count_times`: 5 shuffled interleaved rounds on the validation views, 2 threads).

``--rate SCALE[,FINAL[,EMA]] ...`` fits the tree with its learning rates (the official 3DGS
rates, positions at a tenth of theirs: :func:`clod_adapter.train.tree_fit.finetune`) times
``SCALE``, decayed log-linearly to ``FINAL`` times that at the last step, and with ``EMA`` in (0, 1)
the model returned the exponential moving average of the trained attributes over the steps
(``EMA`` per step) instead of their last values (:class:`RateAdam`, installed for the fit; default
``1``: the job's fit), one row per value.

``--held-out K`` fits on the fit views less every ``K``-th (from the ``K // 2``-th; the tree is
still built on all of them) and adds to each row the mean PSNR at the same count budgets on those
held-out training views: could a job stop its fit where the views it holds out stop gaining?

``--lead mass`` builds, fits and draws the tree with each parent's lead (the child that turns
into it, docs/lod_rule.md step 3) the child of largest mass ``sigmoid(opacity) s0 s1 s2`` (ties:
the first row) instead of the child nearest its family's mass-weighted centre
(:func:`mass_leads`, installed as ``lod.tree.choose_leads``, the build's choice, for the run;
default ``centre``, the rule).

``--tier0-rate R ...`` fits tier 0 too, at its rates times ``R``
(:func:`clod_adapter.train.tree_fit.finetune`'s ``tier0_rate``; 0, the job's: tier 0 unchanged), one
row per value, each ending with tier 0 drawn whole (full detail). ``--train-nodes stable`` fits only
the nodes a cut draws as themselves: the rows in a hand-over or fading out (``t < 1``) are drawn but
pass no gradient (:func:`node_gradients`, installed for the run; default ``all``, the job's fit).

``--tier1-rate S`` fits the first merged tier at its rates times ``S`` and the later tiers at
theirs (:func:`first_tier_rate`, installed for the run; default 1, the job's fit).

``--config KEY=VALUE ...`` takes the adaptation with those ``AdaptConfig`` settings (cached under
their tag) instead of the defaults; ``--as-adapted`` scores it as the job fitted its tree (one row,
no fit here) and prints, per tier, how many families would get another lead if it were chosen
again from the fitted attributes instead of read from the marks the build wrote
(:func:`rechosen_leads`).

Written: ``runs/bench/tree_fit[_TAG](_adapted|[_budgetB][_half])/summary.md`` (``TAG``: the
``--config`` settings' cache tag). The adaptation (about 20 minutes per scene on 2
cores) unless cached, then about 2 minutes per setting plus the fit.
"""
from __future__ import annotations

import argparse
import contextlib
import random
import statistics
import time
from dataclasses import replace

import torch

from benchmarks.common import (add_inputs_args, adapt_cached, load_input, metrics_of, parse_config,
                               resolve_input, scene_views, selected_inputs, setup_threads, table,
                               write_summary)
from clod_adapter.evaluate.popping import popping_budget_ratio, popping_ratio
from clod_adapter.io.load import load_model, load_scene
from clod_adapter.io.ply import read_ply
from clod_adapter.gaussians import Gaussians
from clod_adapter.lod import rule as lod_rule, tree
from clod_adapter.lod.budget import Budget
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.rankings import lightgaussian_significance
from clod_adapter.metrics import psnr
from clod_adapter.train import tiers, tree_fit
from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.tree_fit import finetune

#: count budgets scored, shares of the Gaussians in view
SHARES = (0.75, 0.5, 0.3, 0.15, 0.08, 0.03)
#: levels scored at the coarse end, where the last roots are drawn alone
COARSE_S_V = (30.0, 55.0, 110.0)
#: ``--time``: the shares of the model ``--decimate`` keeps, whose counts the frames are timed at
COUNT_SHARES = (0.3, 0.15, 0.08)


def job_hand_overs(linked, final):
    """``linked`` with each tier's hand-over settings (``tier_s_v``, ``tier_start``, ``tier_fade``)
    as the job chose them, from its model ``final``: the job chooses them on its tier scene (the
    images at ``tier_downscale``), which this study does not load. Raises ValueError where the
    two do not have the same number of tiers."""
    if (linked.parents is None) != (final.parents is None):
        raise ValueError("the relinked model and the job's do not have the same tiers")
    if linked.parents is None:
        return linked
    lod = replace(linked.lod, **{f: getattr(final.lod, f) for f in ("tier_s_v", "tier_start", "tier_fade")})
    return replace(linked, lod=lod, parents=job_hand_overs(linked.parents, final.parents))


def unfitted_tree(ply, fit: list, scene, cfg: AdaptConfig, spread=None, exit_toward_parent=None,
                  entry_toward_children=None):
    """The job's tree before its fit, from the cached adaptation ``ply``: its tier 0 and the
    merged tiers under ``parents/`` linked and built again on the fit views (``spread``,
    ``exit_toward_parent``, ``entry_toward_children``: as :func:`clod_adapter.lod.tree.build`'s;
    None: ``cfg``'s)."""
    final = load_model(ply)
    t0 = tree.own_model(final)
    dirs, p = [], ply.parent / "parents"
    while (p / "point_cloud.ply").is_file():
        dirs.append(p)
        p = p / "parents"
    cands = [read_ply(d / "point_cloud.ply", unlinked_tiers=True) for d in dirs]
    ch = tiers.choice_views(fit)
    linked, _ = tiers.link(t0, cands, ch, [scene.load_image(c) for c in ch], background=cfg.background)
    linked = job_hand_overs(linked, final)
    built = tree.build(linked, fit, spread=cfg.tree_spread if spread is None else spread,
                       exit_toward_parent=cfg.tree_exit_toward_parent if exit_toward_parent is None else exit_toward_parent,
                       entry_toward_children=cfg.tree_entry_toward_children if entry_toward_children is None
                       else entry_toward_children)
    a, b = tree.tiers_of(built), tree.tiers_of(final)
    same = len(a) == len(b) and all(len(x) == len(y) and torch.equal(x.sigma_d, y.sigma_d)
                                    and torch.equal(x.extra[tree.EXIT_KEY], y.extra[tree.EXIT_KEY]) for x, y in zip(a, b))
    return built, same


def scores(g, base, cams, gts, sig, n_pop: int) -> dict:
    """Popping ratios (per view) and mean PSNR at :data:`SHARES` of ``g`` on the views."""
    with torch.no_grad():
        out = {"budget_pop": [popping_budget_ratio(g, base, c, sig)["ratio"] for c in cams[:n_pop]],
               "s_v_pop": [popping_ratio(g, base, c, sig)["ratio"] for c in cams[:n_pop]]}
        out.update(zip(SHARES, shares_psnr(g, cams, gts)))
        out["coarse"] = [statistics.mean(psnr(render_lod(g, c, sv).image, gt, cap=True)
                                         for c, gt in zip(cams, gts)) for sv in COARSE_S_V]
        (p0, n0), (p1, n1) = tiers_whole(g, cams, gts)
        out["tier1"], out["tier0"] = f"{p1:.2f} ({n1 / max(n0, 1):.2f})", f"{p0:.2f}"
    return out


def tiers_whole(g, cams, gts, ks=(0, 1)) -> list[tuple[float, int]]:
    """Each tier ``k`` in ``ks`` of the tree ``g`` drawn whole as a plain model, once per view:
    ``(mean PSNR on the views in dB, drawn count summed over the views)`` per tier."""
    ts = tree.tiers_of(g)
    out = []
    with torch.no_grad():
        for k in ks:
            outs = [render_lod(ts[k].with_sigma_d(None), c) for c in cams]
            out.append((statistics.mean(psnr(o.image, gt, cap=True) for o, gt in zip(outs, gts)),
                        sum(o.n_rendered for o in outs)))
    return out


def shares_psnr(g, cams, gts) -> list[float]:
    """Mean PSNR of ``g`` on the views at count budgets of :data:`SHARES` of the Gaussians in view."""
    with torch.no_grad():
        return [statistics.mean(psnr(render_lod(g, c, budget=Budget(in_view=s)).image, gt, cap=True)
                                for c, gt in zip(cams, gts)) for s in SHARES]


def study(name: str, args) -> list[list]:
    """One input's rows: one per ``--steps`` value."""
    kw, tag = parse_config(args.config) if args.config else ({}, "default")
    cfg = AdaptConfig(**kw)
    ply = adapt_cached(name, cfg, tag, split="val")
    base, scene, gts = load_input(name, "val")
    fit, val = scene_views(scene, "val")
    if args.as_adapted:  # the job's own fit, drawn at each --morph
        sig = lightgaussian_significance(base, fit)
        fitted, g, rows, default_m = metrics_of(ply)["tier"].get("tree_fit", {}), load_model(ply), [], tree.MORPH
        print(f"[{name}] families of two children or more whose lead the fitted attributes would choose "
              f"again as another child: {rechosen_leads(g)}", flush=True)
        for m in args.morph or [default_m]:
            tree.MORPH = m
            try:
                r = scores(g, base, val, gts, sig, args.popping_views)
            finally:
                tree.MORPH = default_m
            row = [name, tag, f"{cfg.tree_spread:g}", f"{cfg.tree_exit_toward_parent:g}", f"{tree.HAND_OVER:g}", f"{m:g}",
                   fitted.get("steps", "-"), "1,1,0", f"{cfg.tree_budget_steps:g}", "full (job)",
                   bound(cfg.tree_grow, cfg.tree_free_roots), f"{fitted.get('seconds', 0):.0f}",
                   " / ".join(f"{x:.1f}" for x in r["budget_pop"]), " / ".join(f"{x:.1f}" for x in r["s_v_pop"]),
                   *[f"{r[s]:.2f}" for s in SHARES], " / ".join(f"{x:.2f}" for x in r["coarse"]), r["tier1"]]
            print(" | ".join(map(str, row)), flush=True)
            rows.append(row)
        return rows
    builds = [(r, b) for r in args.spread or [None] for b in args.exit_toward_parent or [None]]
    built, same = unfitted_tree(ply, fit, scene, cfg, *builds[0])
    print(f"[{name}] tree {[len(t) for t in tree.tiers_of(built)]}; node constants equal the cached "
          f"model's: {same}", flush=True)
    fit_cams, fit_scene = fit, scene
    if args.half:
        _, root, res = resolve_input(name)
        fit_scene = load_scene(root, resolution=2 * res)
        fit_cams = scene_views(fit_scene, "val")[0]
    held = []
    if args.held_out:
        held = list(fit_cams)[args.held_out // 2::args.held_out]
        fit_cams = [c for c in fit_cams if c not in held]
        held = (held, [fit_scene.load_image(c) for c in held])
        print(f"[{name}] fitting on {len(fit_cams)} views, {len(held[0])} held out", flush=True)
    fit_imgs = [fit_scene.load_image(c) for c in fit_cams]
    sig = lightgaussian_significance(base, fit)
    rows = []
    for spread, b in builds:
        if (spread, b) != builds[0]:
            built = unfitted_tree(ply, fit, scene, cfg, spread, b)[0]
        default, default_m = tree.HAND_OVER, tree.MORPH
        for F in args.hand_over or [default]:
            for m in args.morph or [default_m]:
                tree.HAND_OVER, tree.MORPH = F, m  # read by every function of the rule at its call
                try:
                    rows += fit_rows(name, tag, built, base, (fit_cams, fit_imgs), (val, gts), sig, cfg, args,
                                     (cfg.tree_spread if spread is None else spread,
                                      cfg.tree_exit_toward_parent if b is None else b), held)
                finally:
                    tree.HAND_OVER, tree.MORPH = default, default_m
    return rows


def rechosen_leads(g: Gaussians) -> str:
    """Per tier with parents, ``"tier k: n of m"``: of the ``m`` families with two children or
    more, the ``n`` whose marked lead (``lod.tree.leads``, the build's choice the fit trained)
    differs from ``lod.tree.choose_leads`` of the tier's attributes as they are now."""
    out = []
    for k, t in enumerate(tree.tiers_of(g)[:-1]):
        p = t.extra[tree.PARENT_KEY].long()
        big = torch.bincount(p) >= 2
        moved = torch.zeros_like(big).index_fill_(0, p[tree.leads(t) != tree.choose_leads(t)], True)
        out.append(f"tier {k}: {int((moved & big).sum()):,} of {int(big.sum()):,}")
    return "; ".join(out)


def fit_rows(name, tag, built, base, fit_views, val_views, sig, cfg: AdaptConfig, args, built_with,
             held=()) -> list[list]:
    """One row per ``--steps``, ``--rate`` and ``--grow`` value: ``built`` (with ``built_with``: its
    spread and exit share) fitted that long on ``fit_views`` (cameras, images) and scored on
    ``val_views``; with ``held`` (held-out training cameras, images), each row ends with the mean
    PSNR at :data:`SHARES` on them; with ``--time``, with its time at the decimator's counts
    (:func:`count_times`)."""
    (fit_cams, fit_imgs), (val, gts) = fit_views, val_views
    rows, fitted = [], []
    for n, rate, (lowest, cap), t0_rate in ((n, r, c, z) for n in args.steps for r in args.rate or [(1.0, 1.0, 0.0)]
                                            for c in args.cut_range or [(tree_fit.BUDGET_LOWEST, tree_fit.LEVEL_CAP)]
                                            for z in args.tier0_rate or [0.0]):
        for grow, free in dict.fromkeys((gr, fr if gr is not None else 0.0) for gr in args.grow or [cfg.tree_grow]
                                        for fr in args.free_roots or [cfg.tree_free_roots]):  # unbounded: none free
            t = time.perf_counter()
            default_range = tree_fit.BUDGET_LOWEST, tree_fit.LEVEL_CAP
            tree_fit.BUDGET_LOWEST, tree_fit.LEVEL_CAP = lowest, cap  # read by finetune at its call
            try:
                g = fit_at_rate(rate, built, fit_cams, fit_imgs, n, background=cfg.background, seed=cfg.seed,
                                budget_steps=args.budget_steps, grow=grow, free_roots=free, tier0_rate=t0_rate)
            finally:
                tree_fit.BUDGET_LOWEST, tree_fit.LEVEL_CAP = default_range
            sec = time.perf_counter() - t
            r = scores(g, base, val, gts, sig, args.popping_views)
            row = [name, tag, *(f"{x:g}" for x in built_with), f"{tree.HAND_OVER:g}", f"{tree.MORPH:g}",
                   n, ",".join(f"{x:g}" for x in rate),
                   f"{args.budget_steps:g}" + (f" (from {100 * lowest:g} %; s_v <= {cap:g})" if args.cut_range else ""),
                   "half" if args.half else "full",
                   bound(grow, free),
                   f"{sec:.0f}", " / ".join(f"{x:.1f}" for x in r["budget_pop"]),
                   " / ".join(f"{x:.1f}" for x in r["s_v_pop"]), *[f"{r[s]:.2f}" for s in SHARES],
                   " / ".join(f"{x:.2f}" for x in r["coarse"]), r["tier1"]]
            if args.tier0_rate:
                row += [f"{t0_rate:g}", r["tier0"]]
            if held:
                row.append(" / ".join(f"{x:.2f}" for x in shares_psnr(g, *held)))
            print(" | ".join(map(str, row)), flush=True)
            rows.append(row)
            fitted.append(g)
    if args.time:
        for row, ratios in zip(rows, count_times(fitted, base, val)):
            row.append(" / ".join(f"{x:.2f}" for x in ratios))
    return rows


class RateAdam(torch.optim.Adam):
    """``torch.optim.Adam`` as :func:`clod_adapter.train.tree_fit.finetune` builds it, its rates
    times ``SCALE`` decayed log-linearly to ``FINAL`` times that over ``STEPS`` steps, keeping the
    exponential moving average ``EMA`` (0: none) of its parameters in ``averages`` (class settings,
    set by :func:`fit_at_rate`; the last instance built is ``RateAdam.last``)."""

    SCALE, FINAL, EMA, STEPS, last = 1.0, 1.0, 0.0, 1, None

    def __init__(self, params, **kw):
        super().__init__(params, **kw)
        self.base_lr = [g["lr"] * self.SCALE for g in self.param_groups]
        self.done = 0
        self.averages = [[p.detach().clone() for p in g["params"]] for g in self.param_groups] if self.EMA else None
        RateAdam.last = self

    def step(self, closure=None):
        for g, lr in zip(self.param_groups, self.base_lr):
            g["lr"] = lr * self.FINAL ** (self.done / max(self.STEPS - 1, 1))
        out = super().step(closure)
        self.done += 1
        if self.averages is not None:
            with torch.no_grad():
                for g, avg in zip(self.param_groups, self.averages):
                    for p, a in zip(g["params"], avg):
                        a.mul_(self.EMA).add_(p.detach(), alpha=1.0 - self.EMA)
        return out


@contextlib.contextmanager
def first_tier_rate(scale: float):
    """``clod_adapter.train.tree_fit.official_groups`` for the run with the first merged tier's
    groups at ``scale`` times their rates (``--tier1-rate``): :func:`finetune` asks for the merged
    tiers' groups in order, tier 1 first, so each fit's first call is scaled (the count restarts at
    each fit: :func:`fit_at_rate`). Restored on exit; a scale of 1 installs nothing."""
    import clod_adapter.train.tree_fit as tf

    real = tf.official_groups

    def scaled(params, means, scale_all=1.0):
        first = first_tier_rate.calls == 0
        first_tier_rate.calls += 1
        f = scale if first else 1.0
        return real(params, means * f, scale_all * f)

    if scale != 1.0:
        tf.official_groups = scaled
    try:
        yield
    finally:
        tf.official_groups = real


first_tier_rate.calls = 0


def fit_at_rate(rate: tuple, built, fit_cams, fit_imgs, n: int, **kw):
    """:func:`finetune` of ``built`` for ``n`` steps with :class:`RateAdam` at ``rate`` (scale,
    final, ema) in place of its Adam; with an ``ema``, the returned model holds the averages (the
    returned tensors share the trained parameters' storage, which is checked)."""
    import clod_adapter.train.tree_fit as tf

    scale, final, ema = rate
    RateAdam.SCALE, RateAdam.FINAL, RateAdam.EMA, RateAdam.STEPS, RateAdam.last = scale, final, ema, n, None
    real, tf.torch.optim.Adam = tf.torch.optim.Adam, RateAdam
    first_tier_rate.calls = 0
    try:
        g = finetune(built, fit_cams, fit_imgs, n, **kw)
    finally:
        tf.torch.optim.Adam = real
    opt = RateAdam.last
    if ema and opt is not None:
        mine = {p.data_ptr() for grp in opt.param_groups for p in grp["params"]}
        if tree.tiers_of(g)[1].means.data_ptr() not in mine:
            raise RuntimeError("fit_at_rate: the fitted model does not share the parameters' storage")
        with torch.no_grad():
            for grp, avg in zip(opt.param_groups, opt.averages):
                for p, a in zip(grp["params"], avg):
                    p.copy_(a)
    return g


def mass_leads(tier: Gaussians) -> torch.Tensor:
    """[N] bool, ``lod.tree.choose_leads`` with each family's lead the child of largest mass
    ``sigmoid(opacity) s0 s1 s2`` (``--lead mass``; the family: the children of one parent,
    ``extra["parent"]``; ties: the first row). Cached per parent-index tensor, as the rule's."""
    def make(p: torch.Tensor) -> torch.Tensor:
        p = p.long()
        n = int(p.max()) + 1 if p.numel() else 0
        mass = torch.sigmoid(tier.opacity_logits.detach().double()) * torch.exp(tier.log_scales.detach().double().sum(-1))
        top = torch.full((n,), -1.0, dtype=torch.float64, device=p.device).scatter_reduce(0, p, mass, reduce="amax")
        rows = torch.arange(len(p), device=p.device)
        cand = mass == top[p]
        first = torch.full_like(top, float(len(p))).scatter_reduce(0, p[cand], rows[cand].double(), reduce="amin")
        return rows == first[p].long()

    return lod_rule.cached_value(tier.extra[tree.PARENT_KEY], "tree_leads_mass", make)


@contextlib.contextmanager
def lead_rule(lead: str):
    """``lod.tree.choose_leads`` (the leads the tree's build marks) as ``--lead`` says for the run
    (``centre``: the rule's), restored on exit."""
    rule = tree.choose_leads
    if lead == "mass":
        tree.choose_leads = mass_leads
    try:
        yield
    finally:
        tree.choose_leads = rule


@contextlib.contextmanager
def node_gradients(which: str):
    """``lod.tree.cut_attributes`` as ``--train-nodes`` says for the run (``all``: the rule's): with
    ``stable``, while autograd records, the rows of a cut in a hand-over or fading out (``t < 1``)
    are returned detached, so a fit trains only the nodes drawn as themselves. Restored on exit."""
    rule = tree.cut_attributes

    def stable_only(tiers, c, **kw):
        out = rule(tiers, c, **kw)
        if not torch.is_grad_enabled():
            return out
        moving = torch.cat([w < 1.0 for w in c.t])
        return tuple(torch.where(moving.reshape(-1, *([1] * (x.dim() - 1))), x.detach(), x) for x in out)

    if which == "stable":
        tree.cut_attributes = stable_only
    try:
        yield
    finally:
        tree.cut_attributes = rule


def parse_range(v: str) -> tuple:
    """``LOWEST,CAP`` as ``(float, float)``: the fit's smallest count budget (a share in (0, 1]) and
    its coarsest level (``s_v`` >= 1). Raises argparse.ArgumentTypeError otherwise."""
    try:
        lowest, cap = (float(x) for x in v.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOWEST,CAP, got {v!r}") from None
    if not (0.0 < lowest <= 1.0 and cap >= 1.0):
        raise argparse.ArgumentTypeError(f"LOWEST must be in (0, 1] and CAP >= 1, got {v!r}")
    return lowest, cap


def parse_rate(v: str) -> tuple:
    """``SCALE[,FINAL[,EMA]]`` -> (scale, final, ema)."""
    x = [float(a) for a in v.split(",")]
    if not 1 <= len(x) <= 3:
        raise argparse.ArgumentTypeError(f"--rate takes SCALE[,FINAL[,EMA]], got {v!r}")
    return tuple(x + [1.0, 0.0][len(x) - 1:])


def bound(grow, free: float) -> str:
    """The ``grow`` column: the fit's bound on the merged nodes' growth and the roots left free."""
    return "-" if grow is None else f"{grow:g}" + (f", {free:g} of the roots free" if free else "")


def count_times(models: list, base, cams, rounds: int = 5) -> list[list[float]]:
    """Each model's frame time at splat-transform ``--decimate``'s counts (:data:`COUNT_SHARES` of
    ``base``) over the decimated model's, per share: the cut of a count budget of the Gaussians the
    decimated model draws in each view, every frame timed in ``rounds`` shuffled interleaved
    rounds on the views, the ratio of the summed times."""
    decimated = [tiers.decimated(base, s) for s in COUNT_SHARES]
    rng, spent = random.Random(0), {}
    with torch.no_grad():
        for _ in range(rounds):
            for c in cams:
                counts = [render_lod(d, c).n_rendered for d in decimated]
                frames = [((None, j), lambda d=d: render_lod(d, c))
                          for j, d in enumerate(decimated)]
                frames += [((i, j), lambda g=g, k=k: render_lod(g, c, budget=Budget(count=k)))
                           for i, g in enumerate(models) for j, k in enumerate(counts)]
                rng.shuffle(frames)
                for key, draw in frames:
                    t = time.perf_counter()
                    draw()
                    spent[key] = spent.get(key, 0.0) + time.perf_counter() - t
    return [[spent[(i, j)] / spent[(None, j)] for j in range(len(COUNT_SHARES))]
            for i in range(len(models))]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["fern"])
    ap.add_argument("--steps", type=int, nargs="+", default=[0, 500, 1000, 2000])
    ap.add_argument("--budget-steps", type=float, default=0.0, help="share of steps on count-budget cuts")
    ap.add_argument("--half", action="store_true", help="fit at half the model's resolution")
    ap.add_argument("--popping-views", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--config", nargs="+", metavar="KEY=VALUE", help="the adaptation's AdaptConfig settings")
    ap.add_argument("--as-adapted", action="store_true", help="score the adaptation's own fit (no fit here)")
    ap.add_argument("--spread", type=float, nargs="+", help="the tree's hand-over spread R (default: tree.SPREAD)")
    ap.add_argument("--hand-over", type=float, nargs="+", help="the hand-over's width F (default: tree.HAND_OVER)")
    ap.add_argument("--morph", type=float, nargs="+",
                    help="the longest hand-over or exit M, a factor of s_v (default: tree.MORPH)")
    ap.add_argument("--exit-toward-parent", type=float, nargs="+",
                    help="share of the way a non-lead child's exit moves toward its parent's entry "
                         "(default: the adaptation's tree_exit_toward_parent)")
    ap.add_argument("--grow", type=lambda v: None if v == "none" else float(v), nargs="+",
                    help="the factor a merged node's scales may grow by in the fit, or none "
                         "(default: the adaptation's tree_grow)")
    ap.add_argument("--free-roots", type=float, nargs="+",
                    help="with --grow, the share of the roots (by exit, the last to leave) left free to grow "
                         "(default: the adaptation's tree_free_roots)")
    ap.add_argument("--rate", type=parse_rate, nargs="+", metavar="SCALE[,FINAL[,EMA]]",
                    help="the fit's learning rates times SCALE, decayed to FINAL times that at the last step, "
                         "the moving average EMA per step returned (default 1: the job's fit)")
    ap.add_argument("--lead", choices=("centre", "mass"), default="centre",
                    help="each parent's lead child: the nearest its family's centre (the rule) or the largest mass")
    ap.add_argument("--cut-range", type=parse_range, nargs="+", metavar="LOWEST,CAP",
                    help="fit on count budgets from LOWEST (a share in view) to 1 and on levels up to s_v CAP "
                         "(default: the job's, 0.01 and the coarsest level drawn)")
    ap.add_argument("--tier0-rate", type=float, nargs="+", metavar="R",
                    help="fit tier 0 too, at its rates times R (0: not fitted, the job's)")
    ap.add_argument("--tier1-rate", type=float, default=1.0, metavar="S",
                    help="fit the first merged tier at its rates times S (default 1: the job's)")
    ap.add_argument("--train-nodes", choices=("all", "stable"), default="all",
                    help="fit every drawn node (the job's) or only those drawn as themselves (t = 1)")
    ap.add_argument("--held-out", type=int, default=0, metavar="K",
                    help="fit without every K-th fit view and score each row on those views too")
    ap.add_argument("--time", action="store_true",
                    help="also time each fit at --decimate's counts against the decimated models")
    args = ap.parse_args(argv)
    if args.as_adapted and (args.rate or args.held_out or args.lead != "centre" or args.tier0_rate
                            or args.train_nodes != "all" or args.tier1_rate != 1.0):
        ap.error("--as-adapted scores the job's own tree and fit: --rate, --held-out, --lead, --tier0-rate, "
                 "--tier1-rate and --train-nodes refit or rebuild it")
    setup_threads(args.threads)
    with lead_rule(args.lead), node_gradients(args.train_nodes), first_tier_rate(args.tier1_rate):
        rows = [r for name in selected_inputs(args) for r in study(name, args)]
    head = ["input", "adaptation", "spread", "exit b", "F", "M", "steps", "rate, final, ema", "budget steps", "resolution",
            "grow", "fit s", "popping along budgets", "popping along s_v",
            *[f"PSNR {int(100 * s)} % in view" for s in SHARES],
            "PSNR at s_v " + " / ".join(f"{x:g}" for x in COARSE_S_V), "tier 1 whole: PSNR (its count over tier 0's)"]
    if args.tier0_rate and not args.as_adapted:
        head += ["tier 0 rate", "tier 0 whole (full detail): PSNR"]
    if args.held_out and not args.as_adapted:
        head.append("held-out training views: PSNR at " + " / ".join(f"{100 * s:g}" for s in SHARES) + " % in view")
    if args.time and not args.as_adapted:
        head.append("time at --decimate's count "
                    + " / ".join(f"{100 * s:g} %" for s in COUNT_SHARES))
    text = table(head, rows)
    name = ("tree_fit" + (f"_{parse_config(args.config)[1]}" if args.config else "")
            + ("_adapted" if args.as_adapted else (f"_budget{args.budget_steps:g}" if args.budget_steps else "")
               + ("_half" if args.half else "")
               + ("_spread" + "-".join(f"{x:g}" for x in args.spread) if args.spread else "")
               + ("_F" + "-".join(f"{x:g}" for x in args.hand_over) if args.hand_over else "")
               + ("_M" + "-".join(f"{x:g}" for x in args.morph) if args.morph else "")
               + ("_b" + "-".join(f"{x:g}" for x in args.exit_toward_parent) if args.exit_toward_parent else "")
               + ("_grow" + "-".join("none" if x is None else f"{x:g}" for x in args.grow) if args.grow else "")
               + ("_free" + "-".join(f"{x:g}" for x in args.free_roots) if args.free_roots else "")
               + ("_rate" + "-".join(",".join(f"{x:g}" for x in r) for r in args.rate) if args.rate else "")
               + ("_range" + "-".join(",".join(f"{x:g}" for x in r) for r in args.cut_range) if args.cut_range else "")
               + (f"_heldout{args.held_out}" if args.held_out else "")
               + ("_tier0-" + "-".join(f"{x:g}" for x in args.tier0_rate) if args.tier0_rate else "")
               + ("_lead-mass" if args.lead == "mass" else "")
               + ("_stable-nodes" if args.train_nodes == "stable" else "")
               + (f"_tier1-rate{args.tier1_rate:g}" if args.tier1_rate != 1.0 else "")))
    print(text)
    print(write_summary(name, text))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
