"""Which score the pruned first tier (``AdaptConfig.tier_merge = "prune"``) keeps by: static cuts of the input.

For each input (default: fern) every Gaussian gets its blending weight summed over the fit views
(:func:`clod_adapter.train.pruning.blend_weights`) over ``(1 + cost)^p``, ``cost`` its drawing cost
over the same views (:func:`clod_adapter.train.tiers.prune_scores`); the input cut to 70 / 60 / 50 %
by each score (no fit) is scored at full detail on the validation views, with its predicted share
of the input's frame (:func:`clod_adapter.train.tiers.predicted_ms`, no wall clock). ``p = 0.5`` is
``train.tiers.PRUNE_COST_EXPONENT`` (docs/studies.md "The first tier pruned"). No goal (exit 0)::

    python -m benchmarks.studies.prune_cost
    python -m benchmarks.studies.prune_cost --inputs skull --exponents 0 0.5

Written: ``runs/bench/prune_cost/summary.md``. About 2 minutes per scene on 2 cores.
"""
from __future__ import annotations

import argparse
import statistics
import sys

from benchmarks.common import add_inputs_args, load_input, scene_views, selected_inputs, setup_threads, write_summary

from clod_adapter.lod.draw import render_lod
from clod_adapter.metrics import psnr
from clod_adapter.train.finetune import global_cut
from clod_adapter.train.tiers import predicted_ms, prune_scores

EXPONENTS = (0.0, 0.5, 1.0)
KEEPS = (0.7, 0.6, 0.5)


def _psnr(model, views, gts) -> float:
    return statistics.mean(float(psnr(render_lod(model, c, None).image.clamp(0, 1), gt)) for c, gt in zip(views, gts))


def run_input(name: str, exponents, keeps) -> list[str]:
    base, scene, gts = load_input(name, "val")
    fit, views = scene_views(scene, "val")
    g = base.with_sigma_d(None)
    base_ms = predicted_ms(g, fit)
    lines = [f"### {name}: input {_psnr(g, views, gts):.2f} dB ({len(views)} val views)", "",
             "| p | " + " | ".join(f"{k:.0%} kept: frame, dB" for k in keeps) + " |",
             "|---|" + "---|" * len(keeps)]
    for p in exponents:
        s = prune_scores(g, fit, exponent=p)
        cells = []
        for k in keeps:
            m = g.subset(global_cut(s, k))
            cells.append(f"{predicted_ms(m, fit) / base_ms:.0%}, {_psnr(m, views, gts):.2f}")
        lines.append(f"| {p:g} | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    return lines + [""]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["fern"])
    ap.add_argument("--exponents", type=float, nargs="+", default=list(EXPONENTS))
    ap.add_argument("--keeps", type=float, nargs="+", default=list(KEEPS))
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    lines = []
    for name in selected_inputs(args):
        lines += run_input(name, args.exponents, args.keeps)
    print(f"wrote {write_summary('prune_cost', chr(10).join(lines))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
