"""Cost budgets on a model with a parent tier (a design study; validation views by default).

``render_lod(..., budget_cost=)`` / ``budget_ms=`` solve the model's own prefix; on a tiered model
they draw the parents alone, within the same budget, once that solution's ``s_v`` passes
``COST_BUDGET_SWITCH x tier_s_v`` (:func:`clod_adapter.camera_lod.cost_budget_parents`; default
``tier_fade``, 1.25, where the ``s_v`` rule draws the parents alone). For each
input (default skull and fern) this takes the adaptation trained without the validation views and
its 4 % parent tier (both cached by ``benchmarks/studies/merge_tier.py --parents 0.04``), attaches the
tier where ``tiers.choose`` puts it on the fit views, and draws every validation view at cost
budgets of 50 / 25 / 15 / 10 / 5 % of the full frame's cost: the model alone and the tiered model
at each switch factor in ``--switch``. Printed: mean PSNR, the mean drawn per view (parents
included) and the median ``raster_ms`` per setting (one pass; budgets cap predicted cost, so read
the PSNR at equal budget). No goal (exit 0)::

    python benchmarks/studies/budget_tier.py                      # skull, fern; validation views
    python benchmarks/studies/budget_tier.py --switch 1 1.25 1.5
"""
from __future__ import annotations

import argparse
import statistics
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: common.py
from common import (RUNS, adapt_cached, add_inputs_args, add_split_arg, load_input, scene_views,  # noqa: E402
                    selected_inputs, setup_threads, split_suffix)

import torch  # noqa: E402

from clod_adapter import camera_lod, tiers  # noqa: E402
from clod_adapter.camera_lod import render_lod  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.metrics import psnr  # noqa: E402
from clod_adapter.training import AdaptConfig  # noqa: E402

BUDGETS = (0.5, 0.25, 0.15, 0.1, 0.05)


def run_input(name: str, split: str, switches, log) -> list:
    ga = load_model(adapt_cached(name, AdaptConfig(parent_share=0.0), "notier", split=split, log=log))
    gp = load_model(RUNS / name / f"merge_tier_0.04{split_suffix(split)}" / "point_cloud.ply")
    _, scene, _ = load_input(name, split)
    fit, cams = scene_views(scene, split)
    sub = fit[:: max(1, len(fit) // tiers.CHOOSE_VIEWS)][: tiers.CHOOSE_VIEWS]
    ch = tiers.choose(ga, gp, sub, [scene.load_image(c) for c in sub])
    gt = tiers.attach(ga, gp, ch.tier_s_v, ch.tier_start)
    log(f"[{name}] tier at s_v = {ch.tier_s_v:g} (parents from {ch.tier_start:g}); {len(cams)} {split} views")
    gts = [scene.load_image(c) for c in cams]
    rows = []
    for b in BUDGETS:
        for label, model, k in [("alone", replace(ga, parents=None), None)] + [(f"tier x{k:g}", gt, k) for k in switches]:
            if k is not None:
                camera_lod.COST_BUDGET_SWITCH = k
            rs = [render_lod(model, c, budget_cost=b) for c in cams]
            rows.append((name, b, label, statistics.mean(psnr(r.image.clamp(0, 1), g) for r, g in zip(rs, gts)),
                         statistics.mean(r.n_rendered for r in rs), statistics.mean(r.n_parents for r in rs),
                         statistics.median(r.raster_ms for r in rs)))
            log(f"[{name}] budget {b:g} {label}: {rows[-1][3]:.2f} dB")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern"])
    ap.add_argument("--switch", nargs="+", type=float, default=[1.0, 1.25, 1.5])
    ap.add_argument("--threads", type=int, default=2)
    add_split_arg(ap, "val")
    a = ap.parse_args()
    inputs = selected_inputs(a)
    setup_threads(a.threads)
    log = lambda *x: print(*x, flush=True)  # noqa: E731
    rows = []
    with torch.no_grad():
        for n in inputs:
            rows += run_input(n, a.split, a.switch, log)
    lines = ["| input | cost budget | drawing | PSNR dB | drawn per view (parents) | raster ms (median) |",
             "|---|---:|---|---:|---:|---:|"]
    lines += [f"| {n} | {b:.0%} | {lab} | {p:.2f} | {d:,.0f} ({dp:,.0f}) | {ms:.1f} |" for n, b, lab, p, d, dp, ms in rows]
    print("\n".join(lines))


if __name__ == "__main__":
    main()
