"""How many Gaussians does a budget walking down a chain of tiers need to cost a tier's full detail?

A cost or time budget on a model with merged tiers (:func:`clod_adapter.lod.draw.budget_walk`)
compares each tier's full detail (its cost and count in view) with the budget, and a
``Budget(cost=...)`` share is a share of the model's full cost. Costed exactly, each tier is projected
whole for a test, most of a cheap frame's selection time. Costed from every n-th Gaussian by
index, with the widest share (``max(scales) / d'``) costed exactly
(:meth:`clod_adapter.lod.view.LodView.full_detail_estimate`, n =
:data:`clod_adapter.lod.cost.COST_SAMPLE_STEP`, the share
:data:`clod_adapter.lod.cost.COST_SAMPLE_TOP`), only about 1/n of it is.

For each input (default: skull, fern and MaskGaussian fern; the checkpoint as a user has it) and
each view of ``--split`` (default: the validation views), each step n in ``--steps`` and widest share in ``--tops``: the
estimate's time (median of ``--repeats``, 2 threads) and its error against the exact full cost and
count in view (mean and worst over the views). No goal is enforced (a study: exit 0)::

    python -m benchmarks.archive.cost_sample                      # validation views
    python -m benchmarks.archive.cost_sample --steps 1 8 --tops 0 0.03 --inputs skull
    python -m benchmarks.archive.cost_sample --frames --split test

``--frames``: instead, the default adaptation of each input (cached, benchmarks/common.py; adapted
on the fit views first for ``--split val``) drawn at the cost budgets of ``quality_vs_time.py``
(:data:`clod_adapter.evaluate.comparison.COST_SHARES`) from every view of ``--split``, with the tiers
costed exactly and from the sample, both in the same interleaved rounds
(:func:`clod_adapter.evaluate.timing.time_interleaved`, whole ``render_lod`` calls) with the input at full
detail: ms and share of the input's frame, and Gaussians drawn per view.

Written: ``runs/bench/cost_sample/summary.md`` (``cost_sample_frames`` with ``--frames``). Under a
minute per scene on 2 cores (``--frames``: a few minutes, with the adaptations cached).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from types import SimpleNamespace

from benchmarks.common import (SPLITS, adapt_cached, add_inputs_args, load_input, scene_views, selected_inputs,  # noqa: E402
                    setup_threads, write_summary)

from clod_adapter.lod import cost as lod_cost  # noqa: E402
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import view_lod  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.evaluate.comparison import COST_SHARES  # noqa: E402
from clod_adapter.evaluate.timing import time_interleaved  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402
from clod_adapter.lod.budget import Budget


def _timed(f, repeats: int):
    ts, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = f()
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts), out


def study(name: str, split: str, steps, tops, repeats: int) -> list[str]:
    """One table row per (step, widest share) for ``name``: ms, cost error mean / worst, count
    error mean / worst. The share is set by assigning ``lod_cost.COST_SAMPLE_TOP`` (restored)."""
    g, scene, _ = load_input(name, split)
    g = g.with_sigma_d(None)
    cams = scene_views(scene, split)[1]
    variants = [(n, t) for n in steps for t in (tops if n > 1 else tops[:1])]
    rows = {v: ([], [], []) for v in variants}
    keep = lod_cost.COST_SAMPLE_TOP
    try:
        for cam in cams:
            exact = view_lod(g, cam)
            ref = (exact.full_cost(), float(exact.n_in_view))
            for n, t in variants:
                lod_cost.COST_SAMPLE_TOP = t
                ms, (cost, count) = _timed(lambda: view_lod(g, cam).full_detail_estimate(n), repeats)
                rows[(n, t)][0].append(ms)
                rows[(n, t)][1].append(cost / ref[0] - 1.0)
                rows[(n, t)][2].append(count / ref[1] - 1.0)
    finally:
        lod_cost.COST_SAMPLE_TOP = keep
    out = []
    for v in variants:
        ms, ec, en = rows[v]
        n, t = v
        out.append(f"| {name} ({len(g):,}; {len(cams)} views) | {n} | {'-' if n == 1 else f'{100 * t:g} %'} | "
                   f"{statistics.median(ms):.1f} | "
                   f"{100 * statistics.mean(ec):+.1f} / {100 * max(ec, key=abs):+.1f} | "
                   f"{100 * statistics.mean(en):+.1f} / {100 * max(en, key=abs):+.1f} |")
    return out


def _frame(g, cam, exact: bool, **kw):
    """A zero-argument job for :func:`time_interleaved`: one whole ``render_lod`` call (ms as its
    raster time), the tiers costed exactly (``exact``: ``COST_SAMPLE_MIN`` above any tier) or from
    the sample; the constant is restored after the call."""
    def f():
        keep = lod_cost.COST_SAMPLE_MIN
        lod_cost.COST_SAMPLE_MIN = 1 << 62 if exact else keep
        try:
            t0 = time.perf_counter()
            r = render_lod(g, cam, **kw)
            ms = (time.perf_counter() - t0) * 1e3
        finally:
            lod_cost.COST_SAMPLE_MIN = keep
        f.drawn = r.n_rendered
        return SimpleNamespace(select_ms=0.0, raster_ms=ms)
    return f


def frames(name: str, split: str, repeats: int) -> list[str]:
    """Table rows for ``name``: per cost share, the frame exactly and sampled (ms, share of the
    input's frame, drawn per view)."""
    g = load_model(adapt_cached(name, AdaptConfig(), "default", split=split))
    base, scene, _ = load_input(name, split)
    cams = scene_views(scene, split)[1]
    jobs = {("input", None): [_frame(base, c, False) for c in cams]}
    for b in COST_SHARES:
        for exact in (True, False):
            jobs[(b, exact)] = [_frame(g, c, exact, budget=Budget(cost=b)) for c in cams]
    t = time_interleaved(jobs, repeats=repeats)
    ms0 = t[("input", None)]["ms_total"]
    out = []
    for b in COST_SHARES:
        cells = []
        for exact in (True, False):
            ms = t[(b, exact)]["ms_total"]
            drawn = statistics.mean(f.drawn for f in jobs[(b, exact)])
            cells.append(f"{ms:.1f} ({100 * ms / ms0:.0f} %), {drawn:,.0f}")
        ratio = t[(b, False)]["ms_total"] / t[(b, True)]["ms_total"]
        out.append(f"| {name} ({len(cams)} views; input {ms0:.1f} ms) | {b:g} | {cells[0]} | {cells[1]} | {ratio:.2f} |")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern", "maskgaussian"])
    ap.add_argument("--split", choices=SPLITS, default="val")
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 4, 8, 16])
    ap.add_argument("--tops", type=float, nargs="+", default=[0.0, 0.01, 0.03])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--frames", action="store_true", help="time cost-budget frames exactly and sampled")
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    if args.frames:
        lines = ["| input | cost share | exact: ms (of the input's frame), drawn / view | sampled: the same | "
                 "sampled / exact |", "|---|---:|---:|---:|---:|"]
        for name in selected_inputs(args):
            lines += frames(name, args.split, args.repeats)
        write_summary("cost_sample_frames", "\n".join(lines))
        print("\n".join(lines))
        return 0
    lines = ["| input | every n-th Gaussian | widest, costed exactly | ms (view + estimate, median) | "
             "cost error %, mean / worst | count in view error %, mean / worst |", "|---|---:|---:|---:|---:|---:|"]
    for name in selected_inputs(args):
        lines += study(name, args.split, args.steps, args.tops, args.repeats)
    write_summary("cost_sample", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
