"""How many Gaussians does a budget walking down a chain of tiers need to cost a tier's full detail?

A cost or time budget on a model with merged tiers (:func:`clod_adapter.camera_lod.budget_walk`)
compares each tier's full detail (its cost and count in view) with the budget, and a
``budget_cost`` share is a share of the model's full cost. Costed exactly, each tier is projected
whole for a test, most of a cheap frame's selection time. Costed from every n-th Gaussian by
index, with the widest share (``max(scales) / d'``) costed exactly
(:meth:`clod_adapter.camera_lod.LodView.full_detail_estimate`, n =
:data:`clod_adapter.camera_lod.COST_SAMPLE_STEP`, the share
:data:`clod_adapter.camera_lod.COST_SAMPLE_TOP`), only about 1/n of it is.

For each input (default: skull, fern and MaskGaussian fern; the checkpoint as a user has it) and
each view of ``--split`` (default: the validation views), each step n in ``--steps`` and widest share in ``--tops``: the
estimate's time (median of ``--repeats``, 2 threads) and its error against the exact full cost and
count in view (mean and worst over the views). No goal is enforced (a study: exit 0)::

    python benchmarks/studies/cost_sample.py                      # validation views
    python benchmarks/studies/cost_sample.py --steps 1 8 --tops 0 0.03 --inputs skull

Written: ``runs/bench/cost_sample/summary.md``. Under a minute per scene on 2 cores.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: common.py
from common import SPLITS, add_inputs_args, load_input, scene_views, selected_inputs, setup_threads, write_summary  # noqa: E402

from clod_adapter import camera_lod  # noqa: E402
from clod_adapter.camera_lod import view_lod  # noqa: E402


def _timed(f, repeats: int):
    ts, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = f()
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts), out


def study(name: str, split: str, steps, tops, repeats: int) -> list[str]:
    """One table row per (step, widest share) for ``name``: ms, cost error mean / worst, count
    error mean / worst. The share is set by assigning ``camera_lod.COST_SAMPLE_TOP`` (restored)."""
    g, scene, _ = load_input(name, split)
    g = g.with_sigma_d(None)
    cams = scene_views(scene, split)[1]
    variants = [(n, t) for n in steps for t in (tops if n > 1 else tops[:1])]
    rows = {v: ([], [], []) for v in variants}
    keep = camera_lod.COST_SAMPLE_TOP
    try:
        for cam in cams:
            exact = view_lod(g, cam)
            ref = (exact.full_cost(), float(exact.n_in_view))
            for n, t in variants:
                camera_lod.COST_SAMPLE_TOP = t
                ms, (cost, count) = _timed(lambda: view_lod(g, cam).full_detail_estimate(n), repeats)
                rows[(n, t)][0].append(ms)
                rows[(n, t)][1].append(cost / ref[0] - 1.0)
                rows[(n, t)][2].append(count / ref[1] - 1.0)
    finally:
        camera_lod.COST_SAMPLE_TOP = keep
    out = []
    for v in variants:
        ms, ec, en = rows[v]
        n, t = v
        out.append(f"| {name} ({len(g):,}; {len(cams)} views) | {n} | {'-' if n == 1 else f'{100 * t:g} %'} | "
                   f"{statistics.median(ms):.1f} | "
                   f"{100 * statistics.mean(ec):+.1f} / {100 * max(ec, key=abs):+.1f} | "
                   f"{100 * statistics.mean(en):+.1f} / {100 * max(en, key=abs):+.1f} |")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern", "maskgaussian"])
    ap.add_argument("--split", choices=SPLITS, default="val")
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 4, 8, 16])
    ap.add_argument("--tops", type=float, nargs="+", default=[0.0, 0.01, 0.03])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    lines = ["| input | every n-th Gaussian | widest, costed exactly | ms (view + estimate, median) | "
             "cost error %, mean / worst | count in view error %, mean / worst |", "|---|---:|---:|---:|---:|---:|"]
    for name in selected_inputs(args):
        lines += study(name, args.split, args.steps, args.tops, args.repeats)
    write_summary("cost_sample", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
