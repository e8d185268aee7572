"""What a count budget costs: solved on a prefix of its order against the whole model projected.

A count budget of ``k`` draws the ``k`` Gaussians in view with the largest critical ``s_v``, so
it needs to know which Gaussians are in view. ``LodView.select`` finds them by projecting only a
prefix of the order (every Gaussian whose critical ``s_v`` is at least the ``k``-th largest among
the centres in the frustum, cut further on while it holds too few in view:
``LodView._visible_prefix``); before, every budget frame projected the whole model, and on a model
with merged tiers every tier down to the one that took the budget. Both forms draw the same
Gaussians at the same ``s_v``; this study holds them to the same image and times both, as
``clod-eval``'s equal-count comparison asks them (``render_lod(budget=Budget(count=k, min_s_v=0))``, ``k`` a
share of the input's Gaussians in each test view), in interleaved shuffled rounds in one run
(:func:`clod_adapter.evaluate.timing.time_interleaved`, wall time of the whole ``render_lod`` call), on
each input's default adaptation (cached: ``benchmarks/common.adapt_cached``).

Goal (exit 1 when missed): every image equal, and the prefix form no slower than the whole
projection at any share (a ratio above 1.05 of the median frame)::

    python -m benchmarks.studies.budget_frames
    python -m benchmarks.studies.budget_frames --inputs skull --repeats 7

Written: ``runs/bench/budget_frames/summary.md``. About 1 minute per input on 2 cores once the
adaptations are cached (each is a whole ``clod-adapt`` run otherwise).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

from benchmarks.common import (LABELS, adapt_cached, add_inputs_args, load_input, selected_inputs, setup_threads,  # noqa: E402
                    table, write_summary)

import torch  # noqa: E402
from dataclasses import replace  # noqa: E402

from clod_adapter.lod import view as lod_view  # noqa: E402
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import view_lod  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.evaluate.timing import time_interleaved  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402
from clod_adapter.lod.budget import Budget

#: budgets as shares of the input's Gaussians in each view (the decimators' points of clod-eval)
SHARES = (0.5, 0.3, 0.15, 0.08, 0.04)
#: the prefix form may take at most this much of the whole projection's median frame
MAX_RATIO = 1.05


class _Timed:  # what time_interleaved reads from a render: the wall time of the whole call
    def __init__(self, ms: float, out) -> None:
        self.select_ms, self.raster_ms, self.out = 0.0, ms, out


def _render(model, cam, k: int, prefix: bool):
    tries = lod_view.PREFIX_TRIES
    lod_view.PREFIX_TRIES = tries if prefix else 0  # 0: the whole model projected, as before
    try:
        t0 = time.perf_counter()
        out = render_lod(model, cam, budget=Budget(count=k, min_s_v=0.0))
        return _Timed((time.perf_counter() - t0) * 1e3, out)
    finally:
        lod_view.PREFIX_TRIES = tries


def study(name: str, repeats: int) -> tuple[list[list], bool]:
    """One input's table rows and whether its goal is met."""
    ply = adapt_cached(name, AdaptConfig(), "default", split="test")
    # tier 0 alone: a model without merged tiers (an input under PARENT_MIN_GAUSSIANS, or
    # --parent-share 0) draws a count budget this way; a merge tree draws it as one cut instead
    model = replace(load_model(ply), parents=None)
    base, scene, _ = load_input(name, split="test")
    cams = list(scene.test) or list(scene.train[:1])
    n_vis = [view_lod(base, c).n_in_view for c in cams]
    jobs, drawn, same = {}, {}, True
    for share in SHARES:
        ks = [max(2, int(round(share * n))) for n in n_vis]
        for c, k in zip(cams, ks):
            a, b = _render(model, c, k, True).out, _render(model, c, k, False).out
            same &= bool(torch.equal(a.image, b.image)) and a.n_rendered == b.n_rendered and a.s_v == b.s_v
        for prefix in (True, False):
            jobs[(share, prefix)] = [lambda c=c, k=k, p=prefix: _render(model, c, k, p) for c, k in zip(cams, ks)]
        drawn[share] = ks
    timed = time_interleaved(jobs, repeats=repeats)
    rows, ok = [], same
    for share in SHARES:
        ms_p, ms_w = timed[(share, True)]["ms_total"], timed[(share, False)]["ms_total"]
        ratio = ms_p / ms_w
        ok &= ratio <= MAX_RATIO
        rows.append([LABELS.get(name, name), f"{100 * share:g} %", f"{statistics.mean(drawn[share]):,.0f}",
                     f"{ms_p:.1f}", f"{ms_w:.1f}", f"{ratio:.2f}", "yes" if ratio <= MAX_RATIO else "**no**"])
    print(f"{name}: images {'equal' if same else 'DIFFERENT'}", flush=True)
    return rows, ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ("fern", "maskgaussian", "skull"))
    ap.add_argument("--repeats", type=int, default=5, help="interleaved timing rounds (default 5)")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    names = selected_inputs(a)
    setup_threads(a.threads)
    rows, ok = [], True
    with torch.no_grad():
        for name in names:
            r, good = study(name, a.repeats)
            rows += r
            ok &= good
    text = table(["input", "budget (of the Gaussians in view)", "drawn / view", "prefix (ms)", "whole (ms)",
                  "ratio", "met"], rows, "---|---:|---:|---:|---:|---:|---|")
    print(text)
    path = write_summary("budget_frames", f"# Count budgets: a prefix projected against the whole model\n\n{text}\n")
    print(f"wrote {path}; goal {'met' if ok else 'MISSED'} (every image equal, ratio <= {MAX_RATIO:g})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
