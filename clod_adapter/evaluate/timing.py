"""Render timings that load on a shared machine cannot turn into a speed-up.

:func:`time_interleaved` times several settings (methods, levels) the same way: after untimed
warm-up rounds, ``repeats`` rounds each render every (setting, view) once in a shuffled order, so
a burst of load from another process hits all settings alike instead of one; a setting's time is
the median over rounds of the per-round median over views, and the spread is the smallest and
largest per-round median. Times are wall-clock milliseconds of the selection (LoD or baseline)
and of the rasterisation, as the render functions report them (``select_ms``, ``raster_ms``; a
:class:`clod_adapter.lod.draw.LodRender`'s ``lead_ms``, its selection with the projection before
it, in place of ``select_ms``).
"""
from __future__ import annotations

import random
import statistics
from typing import Callable, Hashable, Mapping, Sequence

#: timed rounds by default (each renders every setting and view once).
DEFAULT_REPEATS = 3


def time_interleaved(jobs: Mapping[Hashable, Sequence[Callable[[], object]]], *, repeats: int = DEFAULT_REPEATS,
                     warmup: int = 1, seed: int = 0, on_render: Callable[[], None] | None = None) -> dict:
    """Time every job's renders, interleaved.

    Args:
        jobs: setting key -> one zero-argument callable per view; each call renders once and
            returns an object with ``select_ms`` and ``raster_ms`` (ms), e.g.
            the result of :func:`clod_adapter.lod.draw.render_lod` (whose ``lead_ms``, the
            selection and a plain frame's projection, is read in place of ``select_ms``).
        repeats: timed rounds (>= 1).
        warmup: untimed rounds first (one-off costs: extension load, allocator, caches).
        seed: seed of the per-round shuffle.
        on_render: called after each render (progress).

    Returns:
        key -> ``{"ms_total", "ms_select", "ms_raster"}`` (median over rounds of the median over
        views), ``"ms_total_min"``, ``"ms_total_max"`` (smallest / largest per-round median),
        ``"repeats"``, ``"per_round"`` ([repeats] per-round medians over views, in round order:
        the paired comparison of two settings is the per-round ratio), and ``"per_view"``: [V]
        dicts of the same three medians over rounds.

    Raises:
        ValueError: ``repeats`` < 1.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    order = [(k, v) for k, fns in jobs.items() for v in range(len(fns))]
    rng = random.Random(seed)
    times = {k: [[None] * repeats for _ in fns] for k, fns in jobs.items()}  # key -> view -> round -> (sel, ras)
    for r in range(-warmup, repeats):
        sequence = order[:]
        rng.shuffle(sequence)
        for k, v in sequence:
            out = jobs[k][v]()
            if on_render is not None:
                on_render()
            if r >= 0:
                times[k][v][r] = (float(getattr(out, "lead_ms", out.select_ms)), float(out.raster_ms))
    res = {}
    for k, views in times.items():
        if not views:
            continue
        per_round = []
        for r in range(repeats):
            per_round.append((statistics.median(views[v][r][0] for v in range(len(views))),
                              statistics.median(views[v][r][1] for v in range(len(views))),
                              statistics.median(sum(views[v][r]) for v in range(len(views)))))
        totals = [t for _, _, t in per_round]
        res[k] = {
            "ms_total": statistics.median(totals),
            "ms_select": statistics.median(s for s, _, _ in per_round),
            "ms_raster": statistics.median(x for _, x, _ in per_round),
            "ms_total_min": min(totals), "ms_total_max": max(totals), "repeats": repeats,
            "per_round": totals,
            "per_view": [{"ms_total": statistics.median(sum(t) for t in rounds),
                          "ms_select": statistics.median(t[0] for t in rounds),
                          "ms_raster": statistics.median(t[1] for t in rounds)} for rounds in views],
        }
    return res
