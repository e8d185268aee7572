"""Count budgets cut on each node's mean distance over the training views (the rule), or on its
own distance in the view: refitted and scored.

Every node's ``d'`` in a budget's cut is its mean over the fit views
(:func:`clod_adapter.lod.tree.reference_distances`, stored as ``d_ref`` by the tree's build), not
its distance in the view; here the tree is fitted and scored both ways. For each input (default:
skull and fern) the cached ``--holdout-val`` adaptation with ``clod-adapt``'s defaults
(``benchmarks.common.adapt_cached``) has its tree built again as the job built it
(``benchmarks.studies.tree_fit.unfitted_tree``) and fitted as the job fits it
(:func:`clod_adapter.train.tree_fit.finetune` with the job's settings, half of its steps on
count-budget cuts) once per ``--distances``: ``reference`` (the rule as it is: the count-budget
cuts, in the fit and in the scoring, on each node's stored mean ``d'`` over the fit views) and
``view`` (on each node's distance in the view, by :func:`benchmarks.studies.tier_cuts.rule_with`;
the cuts at a level keep the view's distances either way).
Scored on the validation views: the mean PSNR at count budgets of 50 / 30 / 15 / 8 / 4 / 2 % of
the Gaussians in view and at the levels ``s_v`` 1.5 / 2.5 / 4 / 6.4 / 10 / 16, and ``clod-eval``'s
popping along budgets and along ``s_v`` on every view (smallest / median). No goal is enforced (a
study: exit 0)::

    python -m benchmarks.studies.budget_distances --inputs skull fern

Written: ``runs/bench/budget_distances_val/summary.md``. About 3 minutes per fit and scene (2 threads),
after the adaptation.
"""
from __future__ import annotations

import statistics
import sys
import time

import torch

from benchmarks.common import adapt_cached, load_input, parse_inputs_args, scene_views, split_suffix, print_summary
from benchmarks.studies.compare_configs import COUNTS
from benchmarks.studies.tier_cuts import rule_with
from benchmarks.studies.tree_fit import unfitted_tree
from clod_adapter.evaluate.popping import popping_budget_ratio, popping_ratio
from clod_adapter.lod.budget import Budget
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.rankings import lightgaussian_significance
from clod_adapter.metrics import psnr
from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.tree_fit import finetune

#: the levels scored (the cuts at a level draw the view's own distances either way)
LEVELS = (1.5, 2.5, 4.0, 6.4, 10.0, 16.0)


def run_input(name: str, split: str, modes: list) -> list[str]:
    """The markdown rows of ``name``: one per ``modes`` entry (``view`` or ``reference``)."""
    cfg = AdaptConfig()
    g0, scene, gts = load_input(name, split)
    fit, cams = scene_views(scene, split)
    fit = list(fit)
    imgs = [scene.load_image(c) for c in fit]
    built = unfitted_tree(adapt_cached(name, cfg, "default", split=split), fit, scene, cfg)[0]
    sig = lightgaussian_significance(g0, fit)
    rows = []
    for mode in modes:
        with rule_with(distances="view" if mode == "view" else None, python=False):
            t = time.perf_counter()
            g = finetune(built, fit, imgs, cfg.tree_steps, background=cfg.background, seed=cfg.seed,
                         budget_steps=cfg.tree_budget_steps, grow=cfg.tree_grow, free_roots=cfg.tree_free_roots)
            sec = time.perf_counter() - t
            with torch.no_grad():
                at_count = [statistics.mean(psnr(render_lod(g, c, None, budget=Budget(in_view=k)).image.clamp(0, 1), gt)
                                            for c, gt in zip(cams, gts)) for k in COUNTS]
                at_level = [statistics.mean(psnr(render_lod(g, c, s).image.clamp(0, 1), gt)
                                            for c, gt in zip(cams, gts)) for s in LEVELS]
                pop_b = [float(popping_budget_ratio(g, g0, c, sig)["ratio"]) for c in cams]
                pop_s = [float(popping_ratio(g, g0, c, sig)["ratio"]) for c in cams]
        row = (f"| {name} ({len(cams)} views) | {mode} | " + " / ".join(f"{x:.2f}" for x in at_count) + " | "
               + " / ".join(f"{x:.2f}" for x in at_level)
               + f" | {min(pop_b):.2f} / {statistics.median(pop_b):.2f} | {min(pop_s):.2f} / {statistics.median(pop_s):.2f}"
               f" | {sec:.0f} s |")
        print(row, flush=True)
        rows.append(row)
    return rows


def main() -> int:
    a = parse_inputs_args(__doc__, inputs=("skull", "fern"), split="val", extra=[
        ("--distances", {"nargs": "+", "choices": ("view", "reference"), "default": ["view", "reference"],
                         "help": "what the count-budget cuts are drawn on (default: both)"})])
    md = ["| input | count budgets on | PSNR at " + " / ".join(f"{100 * k:g}" for k in COUNTS)
          + " % in view (dB) | at s_v " + " / ".join(f"{s:g}" for s in LEVELS)
          + " | popping along budgets, smallest / median | along s_v | fit |", "|---|---|---|---|---|---|---:|"]
    for name in a.inputs:
        md += run_input(name, a.split, a.distances)
    return print_summary("budget_distances" + split_suffix(a.split), md)


if __name__ == "__main__":
    sys.exit(main())
