"""Where a child leaves and when its parent takes over: a merge tree's exits moved toward the
parents' entries, and the entries toward the children's exits, at equal frame time.

For each input (default: fern, MaskGaussian fern, skull) the cached ``--holdout-val`` adaptation
built with its children's exits where their own level of detail drops them and its entries where
the tier's spread puts them (``tree_exit_toward_parent = 0``, ``tree_entry_toward_children = 0``;
``benchmarks.common.adapt_cached``, trained on the fit views only) is taken apart as
``benchmarks.studies.tree_fit`` does, and its tree is built again once per ``--exits B``
(:func:`clod_adapter.lod.tree.build`'s ``exit_toward_parent``; ``B@K``: tiers below ``K`` keep
their own exits; ``BeA``: and ``entry_toward_children = A``, else 0; ``BeA:K``: tiers below
``K`` keep their entries) and fitted as the job fits it (``tree_steps`` steps, half of
them on count-budget cuts, seed 0). Each fitted tree is scored on the validation views: the
popping ratio along count budgets and along ``s_v`` (``clod-eval``'s, on the first
``--popping-views`` views; 0: none), the mean PSNR at count budgets of 75 / 50 / 30 / 15 / 8 / 3 %
of the Gaussians in view, and, every tree and the input timed in the same interleaved rounds
along the ``s_v`` grid of ``quality_vs_time.py``, the best PSNR within 90 / 75 / 50 / 25 / 15 /
10 % of the input's frame and each level's PSNR and share of the input's frame. No goal is
enforced (a study: exit 0)::

    python -m benchmarks.studies.tree_exits --inputs skull --exits 0 0.5 --popping-views 7
    python -m benchmarks.studies.tree_exits --inputs fern maskgaussian --exits 0 0.5@1 0.25 --popping-views 2
    python -m benchmarks.studies.tree_exits --inputs fern maskgaussian --exits 0.25 0.25e0.5 0.25e1 --popping-views 2
    python -m benchmarks.studies.tree_exits --inputs skull --exits 0.25 0.25e0.5 --popping-views 3

Written: ``runs/bench/tree_exits[_val]/summary.md``. About 2 minutes per tree for the fit, plus
the popping sweeps (about 1 minute per view and tree) and the timing.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import replace

import torch

from benchmarks.common import adapt_cached, load_input, parse_inputs_args, scene_views, split_suffix, table, write_summary
from benchmarks.studies.compare_configs import SHARES as TIME_SHARES, timed_render
from benchmarks.studies.tree_fit import SHARES, scores, unfitted_tree
from clod_adapter.evaluate.comparison import clod_s_vs
from clod_adapter.evaluate.frontier import Point, best_within
from clod_adapter.evaluate.timing import time_interleaved
from clod_adapter.lod import tree
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.rankings import lightgaussian_significance
from clod_adapter.metrics import psnr
from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.tree_fit import finetune


def _with_exits(ply, fit, scene, cfg: AdaptConfig, spec: str):
    """The unfitted tree with exits ``spec`` (``B`` or ``B@K``: tiers below ``K`` keep their own;
    a suffix ``eA``: entries ``A`` of the way toward the children's exits, else 0; ``eA:K``:
    tiers below ``K`` keep their entries)."""
    spec, a = (spec.split("e")[0], spec.split("e")[1]) if "e" in spec else (spec, "0")
    a, first = (float(a.split(":")[0]), int(a.split(":")[1])) if ":" in a else (float(a), 1)
    b, keep = (float(spec.split("@")[0]), int(spec.split("@")[1])) if "@" in spec else (float(spec), 0)
    built = unfitted_tree(ply, fit, scene, cfg, None, b, a)[0]
    if first > 1:  # tiers below ``first`` enter where their spread puts them (their children's exits with them)
        ts, at0 = tree.tiers_of(built), tree.tiers_of(unfitted_tree(ply, fit, scene, cfg, None, b, 0.0)[0])
        for k in range(1, first):
            ts[k] = replace(ts[k], sigma_d=at0[k].sigma_d)
            ts[k - 1] = replace(ts[k - 1], extra={**ts[k - 1].extra, tree.EXIT_KEY: at0[k - 1].extra[tree.EXIT_KEY]})
        built = tree.linked(ts)
    if not keep:
        return built
    own = tree.tiers_of(unfitted_tree(ply, fit, scene, cfg, None, 0.0)[0])
    ts = tree.tiers_of(built)
    for k in range(keep):
        ts[k] = replace(ts[k], extra={**ts[k].extra, tree.EXIT_KEY: own[k].extra[tree.EXIT_KEY]})
    return tree.linked(ts)


def study(name: str, args) -> list[list]:
    """One input's rows, one per ``--exits`` value."""
    cfg = AdaptConfig(tree_exit_toward_parent=0.0, tree_entry_toward_children=0.0)  # the cached adaptation
    ply = adapt_cached(name, cfg, "exits0", split=args.split)
    g0, scene, gts = load_input(name, args.split)
    fit, val = scene_views(scene, args.split)
    fit_imgs = [scene.load_image(c) for c in fit]
    sig = lightgaussian_significance(g0, fit)
    models, rows = {}, {}
    for spec in args.exits:
        t = time.perf_counter()
        models[spec] = finetune(_with_exits(ply, fit, scene, cfg, spec), fit, fit_imgs, cfg.tree_steps,
                                background=cfg.background, seed=cfg.seed, budget_steps=cfg.tree_budget_steps,
                                grow=cfg.tree_grow, free_roots=cfg.tree_free_roots)
        r = scores(models[spec], g0, val, gts, sig, args.popping_views)
        rows[spec] = [name, spec, f"{time.perf_counter() - t:.0f}", " / ".join(f"{x:.1f}" for x in r["budget_pop"]) or "-",
                      " / ".join(f"{x:.1f}" for x in r["s_v_pop"]) or "-", " / ".join(f"{r[s]:.2f}" for s in SHARES)]
        print(" | ".join(rows[spec]), flush=True)
    sets, psnrs = {("input", 1.0): [timed_render(g0, c, None) for c in val]}, {}
    with torch.no_grad():
        for spec, g in models.items():
            for s in clod_s_vs(g):
                sets[(spec, s)] = [timed_render(g, c, s) for c in val]
                psnrs[(spec, s)] = statistics.mean(psnr(render_lod(g, c, s).image.clamp(0, 1), gt) for c, gt in zip(val, gts))
        res = time_interleaved(sets, repeats=5, warmup=1)
    ms_in = res[("input", 1.0)]["ms_total"]
    out = []
    for spec, g in models.items():
        pts = [Point("clod", f"s_v={s:g}", res[(spec, s)]["ms_total"], psnrs[(spec, s)]) for s in clod_s_vs(g)]
        best = [best_within(pts, sh * ms_in) for sh in TIME_SHARES]
        levels = " ".join(f"{s:.3g}:{psnrs[(spec, s)]:.2f}/{100 * res[(spec, s)]['ms_total'] / ms_in:.0f}%" for s in clod_s_vs(g))
        print(f"[{name}] {spec}: {levels}", flush=True)
        out.append(rows[spec] + [" / ".join("-" if x is None else f"{x.psnr:.2f}" for x in best)])
    return out


def main(argv=None) -> int:
    args = parse_inputs_args(__doc__, argv, inputs=("fern", "maskgaussian", "skull"), split="val", extra=[
        ("--exits", {"nargs": "+", "default": ["0", "0.25"], "metavar": "B[@K]",
                     "help": "exit shares toward the parent (B@K: tiers below K keep their own exits; "
                             "BeA: entries A of the way toward the children's exits)"}),
        ("--popping-views", {"type": int, "default": 2})])
    head = ["input", "exits", "fit + score s", "popping along budgets", "popping along s_v",
            "PSNR at " + " / ".join(f"{100 * s:g}" for s in SHARES) + " % in view",
            "best within " + " / ".join(f"{100 * s:g}" for s in TIME_SHARES) + " % of the input's frame"]
    text = table(head, [r for name in args.inputs for r in study(name, args)])
    print(text)
    print(write_summary("tree_exits" + split_suffix(args.split), text))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
