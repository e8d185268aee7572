"""A count budget between two merged tiers: one mixed frame, or the walk?

A count budget of ``k`` on a model with merged tiers walks down the chain: the next tier takes it
over where that tier's full detail draws at least :data:`clod_adapter.camera_lod.COUNT_TAKE_SHARE`
of ``k`` (then drawing fewer). Where the walk ends in a tier that draws more than ``k`` and the
next tier refused it, rule ``walk`` (``LodSettings.count_mix = False``) cuts that
tier's survivors to ``k``; rule ``mix`` (``count_mix = True``, :func:`clod_adapter.tier_mix.mix`) draws the nearer Gaussians of that
tier's full detail and the farther of the next tier's, exactly ``k`` together; rule ``mix1`` is
``mix`` with a take share of 1 (the next tier takes a budget only where it fills it, so every
budget between two tiers' counts is mixed).

For each input (default: skull, fern and MaskGaussian fern) the default adaptation (cached,
benchmarks/common.py; ``--split val``: fitted on the fit views only) is drawn by every rule at the
equal-count points of ``benchmarks/quality_vs_time.py`` (the count per view of splat-transform's
``--decimate`` and ``--decimate-adaptive`` outputs at 50 / 30 / 15 / 8 % of the input) and at
``--shares`` of the Gaussians in view; both rules and the input are timed in ``--rounds``
interleaved rounds (``render_lod``'s wall time, median over rounds of the mean over views, as a
share of the input's). Printed per point: the decimator's PSNR where there is one, and per rule
PSNR, drawn count over the budget and time share. ``--views fit`` scores on the views a user
has instead, the :func:`clod_adapter.tiers.choice_views` of the views the adaptation was fitted on
(does the verdict there match the held-out views'?). No goal is enforced (a study: exit 0)::

    python benchmarks/studies/count_mix.py --split val
    python benchmarks/studies/count_mix.py --split val --views fit --shares --rounds 1

Written: ``runs/bench/count_mix{_fit}/summary.md``. About 3 minutes for the three scenes on 2 cores (the
adaptations cached).
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: common.py
from common import (SPLITS, adapt_cached, add_inputs_args, load_input, load_model, scene_views,  # noqa: E402
                    selected_inputs, setup_threads, write_summary)

from clod_adapter import camera_lod, tiers  # noqa: E402
from clod_adapter.camera_lod import render_lod, view_lod  # noqa: E402
from clod_adapter.metrics import psnr  # noqa: E402
from clod_adapter.training import AdaptConfig  # noqa: E402

#: the decimators' shares of the input whose counts per view are budgets
POINTS = (0.5, 0.3, 0.15, 0.08)
#: rule -> (LodSettings.count_mix, camera_lod.COUNT_TAKE_SHARE)
RULES = {"walk": (False, 0.6), "mix": (True, 0.6), "mix1": (True, 1.0)}


def mean_psnr(images, gts) -> float:
    """Mean PSNR (dB, capped) of [H, W, 3] images against the views' images."""
    return statistics.mean(psnr(im, gt, cap=True) for im, gt in zip(images, gts))


def draw(model, cams, ks, rule):
    """(renders, mean wall ms per view) of ``model`` at count budgets ``ks`` (one per view) by ``rule``."""
    mix, camera_lod.COUNT_TAKE_SHARE = RULES[rule]
    model = replace(model, lod=replace(model.lod, count_mix=mix))
    t0 = time.perf_counter()
    outs = [render_lod(model, c, budget=k) for c, k in zip(cams, ks)]
    return outs, (time.perf_counter() - t0) * 1e3 / len(cams)


def study(name: str, split: str, shares, rounds: int, views: str = "scored") -> list[str]:
    """One input's table rows (``views``: ``"scored"``, the split's; ``"fit"``, the choice views of
    the fit views)."""
    base, scene, gts = load_input(name, split)
    fit, cams = scene_views(scene, split)
    if views == "fit":
        cams = tiers.choice_views(fit)
        gts = [scene.load_image(c) for c in cams]
    model = load_model(adapt_cached(name, AdaptConfig(), "default", split=split))
    n_in = [view_lod(base, c).n_in_view for c in cams]
    points = []
    for merge in tiers.MERGES:
        for share in POINTS:
            dec = tiers.decimated(base, share, merge=merge)
            outs = [render_lod(dec, c) for c in cams]
            points.append((f"{merge} {100 * share:g} %", [int(o.n_rendered) for o in outs],
                           f"{mean_psnr([o.image for o in outs], gts):.2f}"))
    points += [(f"{100 * s:g} % in view", [max(1, round(s * n)) for n in n_in], "-") for s in shares]
    keep = camera_lod.COUNT_TAKE_SHARE
    times = {(p, r): [] for p in range(len(points)) for r in RULES}
    t_in, got = [], {}
    try:
        for _ in range(rounds):
            t0 = time.perf_counter()
            for c in cams:
                render_lod(base, c)
            t_in.append((time.perf_counter() - t0) * 1e3 / len(cams))
            for p, (_, ks, _) in enumerate(points):
                for r in RULES:
                    got[p, r], ms = draw(model, cams, ks, r)
                    times[p, r].append(ms)
    finally:
        camera_lod.COUNT_TAKE_SHARE = keep
    full = statistics.median(t_in)
    rows = []
    for p, (label, ks, dec_psnr) in enumerate(points):
        in_view = 100 * statistics.mean(k / n for k, n in zip(ks, n_in))
        cells = []
        for r in RULES:
            outs = got[p, r]
            drawn = statistics.mean(o.n_rendered / k for o, k in zip(outs, ks))
            cells.append(f"{mean_psnr([o.image for o in outs], gts):.2f} ({drawn:.2f}, "
                         f"{100 * statistics.median(times[p, r]) / full:.0f} %)")
        rows.append(f"| {name} | {label} ({in_view:.1f} % in view) | {dec_psnr} | " + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern", "maskgaussian"])
    ap.add_argument("--split", choices=SPLITS, default="val")
    ap.add_argument("--views", choices=("scored", "fit"), default="scored",
                    help="score on the split's views (default) or on the choice views of the fit views")
    ap.add_argument("--shares", type=float, nargs="*", default=[0.9, 0.75, 0.6, 0.4, 0.25])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    cols = " | ".join(f"{r}: PSNR (drawn / budget, time)" for r in RULES)
    lines = [f"| input | count budget | decimator PSNR | {cols} |", "|---|---|---:|" + "---:|" * len(RULES)]
    for name in selected_inputs(args):
        lines += study(name, args.split, args.shares, args.rounds, args.views)
    write_summary("count_mix" + ("_fit" if args.views == "fit" else ""), "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
