"""Adaptation settings against each other on every evaluation view: popping along both sweeps and
PSNR at equal count, untimed.

``compare_configs.py`` times the settings and scores popping from the first view only; goal 6
asks for every view. For each input (default: skull and fern) the cached adaptation with
``clod-adapt``'s defaults and with each ``--config KEY=VALUE ...`` (``benchmarks.common.adapt_cached``;
``--split val``: trained on the fit views only, the default) is scored on every evaluation view:
``clod-eval``'s popping ratio along ``s_v`` and along count budgets from 100 % to 1 % of the
Gaussians in view (:func:`clod_adapter.evaluate.popping.popping_ratio`,
:func:`clod_adapter.evaluate.popping.popping_budget_ratio`; the smallest, the median and each
view's), the mean PSNR at full detail and at count budgets of 50 / 30 / 15 / 8 / 4 / 2 % of the
Gaussians in view. No goal is enforced (a study: exit 0)::

    python -m benchmarks.studies.popping_views --inputs skull fern --config tier_downscale=1

Written: ``runs/bench/popping_views/<tags><_val>/summary.md``. About 3 minutes per model on skull's 7
validation views (2 threads), after the adaptations.
"""
from __future__ import annotations

import statistics
import sys

import torch

from benchmarks.common import (adapt_cached, load_input, parse_config, parse_inputs_args, print_summary, scene_views,
                               split_suffix)
from benchmarks.studies.compare_configs import COUNTS
from clod_adapter.evaluate.popping import popping_budget_ratio, popping_ratio
from clod_adapter.io.load import load_model
from clod_adapter.lod.budget import Budget
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.rankings import lightgaussian_significance
from clod_adapter.metrics import psnr
from clod_adapter.train.config import AdaptConfig


def run_input(name: str, split: str, configs: dict) -> list[str]:
    """Score ``configs`` {tag: AdaptConfig keywords} on ``name``'s evaluation views; returns the
    markdown table rows (one per setting)."""
    g0, scene, gts = load_input(name, split)
    fit, cams = scene_views(scene, split)
    scores = lightgaussian_significance(g0, list(fit))
    rows = []
    for tag, kw in configs.items():
        g = load_model(adapt_cached(name, AdaptConfig(**kw), tag, split=split))
        with torch.no_grad():
            full = statistics.mean(psnr(render_lod(g, c, 1.0).image.clamp(0, 1), t) for c, t in zip(cams, gts))
            at_count = [statistics.mean(psnr(render_lod(g, c, None, budget=Budget(in_view=k)).image.clamp(0, 1), t)
                                        for c, t in zip(cams, gts)) for k in COUNTS]
            pop_s = [float(popping_ratio(g, g0, c, scores)["ratio"]) for c in cams]
            pop_b = [float(popping_budget_ratio(g, g0, c, scores)["ratio"]) for c in cams]
        line = (f"| {tag} | {full:.2f} | " + " / ".join(f"{p:.2f}" for p in at_count)
                + f" | {min(pop_s):.2f} / {statistics.median(pop_s):.2f} | {min(pop_b):.2f} / {statistics.median(pop_b):.2f}"
                + " | " + " ".join(f"{p:.1f}" for p in pop_s) + " | " + " ".join(f"{p:.1f}" for p in pop_b) + " |")
        print(f"[{name}] {line}", flush=True)
        rows.append(line)
    return rows


def main() -> int:
    a = parse_inputs_args(__doc__, inputs=("skull", "fern"), split="val", extra=[
        ("--config", {"nargs": "+", "action": "append", "default": [], "metavar": "KEY=VALUE",
                      "help": "one variant's AdaptConfig settings (repeat for more variants)"})])
    configs = {"default": {}}
    for items in a.config:
        kw, tag = parse_config(items)
        configs[tag] = kw
    md = []
    for name in a.inputs:
        md += [f"### {name} ({a.split} views)", "",
               "| setting | full detail (dB) | PSNR at " + " / ".join(f"{100 * k:g}" for k in COUNTS)
               + " % of the Gaussians in view | popping along s_v, smallest / median | along count budgets"
               " | each view along s_v | each view along budgets |", "|---|---:|---|---|---|---|---|"]
        md += run_input(name, a.split, configs) + [""]
    tags = "+".join(t for t in configs if t != "default") or "default"
    return print_summary("popping_views/" + tags + split_suffix(a.split), md)


if __name__ == "__main__":
    sys.exit(main())
