"""When should a count budget pass to the next merged tier?

A count budget of ``k`` on a model with merged tiers walks down the chain
(:func:`clod_adapter.lod.draw.budget_walk`): the next tier takes it over where that tier, as the
``s_v`` rule first draws it alone, draws at least :data:`clod_adapter.lod.draw.COUNT_TAKE_SHARE`
of ``k``. At 1 a tier takes only budgets it fills, so a budget between two tiers' sizes is the
finer tier cut to ``k``; below 1 it may be the coarser tier drawn whole, fewer than ``k``.

For each input (default: skull, fern and MaskGaussian fern) the default adaptation (cached, benchmarks/common.py;
``--split val``: fitted on the fit views only) is drawn at the equal-count points of
``benchmarks/quality_vs_time.py`` (the count per view of splat-transform's ``--decimate`` and
``--decimate-adaptive`` outputs at 50 / 30 / 15 / 8 % of the input) with each share in
``--shares``. Printed per point: the decimator's PSNR, and per share the adapted model's PSNR and
drawn count over the budget. No goal is enforced (a study: exit 0)::

    python -m benchmarks.archive.count_take_share --split val          # skull, fern, MaskGaussian fern
    python -m benchmarks.archive.count_take_share --split val --inputs skull --shares 1 0.6 0.4

Written: ``runs/bench/count_take_share/summary.md``. About 2 minutes per scene on 2 cores.
"""
from __future__ import annotations

import argparse
import statistics
import sys

from benchmarks.common import (SPLITS, adapt_cached, add_inputs_args, load_input, load_model, scene_views,  # noqa: E402
                    selected_inputs, setup_threads, write_summary)

from clod_adapter.lod import draw as camera_lod
from clod_adapter.train import tiers  # noqa: E402
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import view_lod  # noqa: E402
from clod_adapter.metrics import psnr  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402
from clod_adapter.lod.budget import Budget

#: the decimators' shares of the input whose counts per view are the budgets
POINTS = (0.5, 0.3, 0.15, 0.08)


def mean_psnr(images, gts) -> float:
    """Mean PSNR (dB, capped) of [H, W, 3] images against the views' images."""
    return statistics.mean(psnr(im, gt, cap=True) for im, gt in zip(images, gts))


def study(name: str, split: str, shares) -> list[str]:
    """One input's table rows: per decimator point, the peer and the adapted model per share."""
    base, scene, gts = load_input(name, split)
    cams = scene_views(scene, split)[1]
    model = load_model(adapt_cached(name, AdaptConfig(), "default", split=split))
    n_in = [view_lod(base, c).n_in_view for c in cams]
    keep, rows = camera_lod.COUNT_TAKE_SHARE, []
    try:
        for merge in tiers.MERGES:
            for share in POINTS:
                dec = tiers.decimated(base, share, merge=merge)
                outs = [render_lod(dec, c) for c in cams]
                ks = [int(o.n_rendered) for o in outs]
                cells = []
                for rho in shares:
                    camera_lod.COUNT_TAKE_SHARE = rho
                    got = [render_lod(model, c, budget=Budget(count=k)) for c, k in zip(cams, ks)]
                    drawn = statistics.mean(r.n_rendered / k for r, k in zip(got, ks))
                    cells.append(f"{mean_psnr([r.image for r in got], gts):.2f} ({drawn:.2f})")
                in_view = 100 * statistics.mean(k / n for k, n in zip(ks, n_in))
                rows.append(f"| {name} | {merge} {100 * share:g} % ({in_view:.1f} % in view) | "
                            f"{mean_psnr([o.image for o in outs], gts):.2f} | " + " | ".join(cells) + " |")
                print(rows[-1], flush=True)
    finally:
        camera_lod.COUNT_TAKE_SHARE = keep
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern", "maskgaussian"])
    ap.add_argument("--split", choices=SPLITS, default="val")
    ap.add_argument("--shares", type=float, nargs="+", default=[1.0, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3])
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    lines = ["| input | count budget: the decimator's count per view | decimator PSNR | "
             + " | ".join(f"share {s:g}: PSNR (drawn / budget)" for s in args.shares) + " |",
             "|---|---|---:|" + "---:|" * len(args.shares)]
    for name in selected_inputs(args):
        lines += study(name, args.split, args.shares)
    write_summary("count_take_share", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
