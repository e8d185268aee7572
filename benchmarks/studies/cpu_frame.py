"""A CPU frame without gradients: its C++ passes against their torch twins, paired in one run.

Two of a frame's stages have a C++ form for frames that record no autograd:

* the projection (``csrc/projection.cpp``: :func:`clod_adapter.render.projection.project_geometry`
  and :func:`clod_adapter.render.projection.finish_projection`, in double) and the colours read from
  ``sh0`` / ``shN`` in place (:func:`clod_adapter.render.cpu.sh_colors_rows`), against the torch
  forms (the stages' own code; the SH rows gathered and concatenated, then
  :func:`clod_adapter.render.cpu.sh_colors`): whole frames of :func:`clod_adapter.lod.draw.render_lod`,
  the input at full detail and the adapted model at ``s_v`` levels and count budgets;
* the merge tree's cut at a level, walked from the roots (:func:`clod_adapter.lod.tree.cut`, C++
  ``tree_cut``), against every node's C++ terms and the cut of them (:func:`clod_adapter.lod.tree.terms`
  + :func:`clod_adapter.lod.tree.cut` with ``tt``: every node's frustum, ``d'`` and terms in C++, the
  drawn nodes picked in torch) and against the torch walk
  (:func:`clod_adapter.lod.tree.walk`).

The input's cached adaptation (``benchmarks.common.adapt_cached``, the defaults, trained without the
validation views for ``--split val``, the default; made when missing, about 13 minutes) and the
split's views, 2 threads (``--threads``), ``OMP_WAIT_POLICY=PASSIVE``,
the forms shuffled within each round; medians over rounds of the median over views.

Goals (exit 1 when one is missed): the input's frame with the C++ projection at most 0.92x the
torch projection's; the walked cut at the coarsest level at most 0.5x the cut from every node's
terms::

    python -m benchmarks.studies.cpu_frame                  # fern
    python -m benchmarks.studies.cpu_frame --inputs skull --rounds 5
"""
from __future__ import annotations

import os
import random
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from benchmarks import common  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.lod import tree  # noqa: E402
from clod_adapter.lod.budget import Budget  # noqa: E402
from clod_adapter.lod.draw import render_lod  # noqa: E402
from clod_adapter.render import cpu, projection  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402

LEVELS = (1.5, 3.0, 8.0, 20.0, 60.0, 227.0)
BUDGETS = (0.5, 0.15, 0.04)
#: the input's frame with the C++ projection over the torch projection's, at most
PROJECTION_GOAL = 0.92
#: the walked cut over the cut from every node's terms at the coarsest level, at most
WALK_GOAL = 0.5


def _gathered_rows(deg, means, sh0, shN, ids, campos):
    coeffs = torch.cat([sh0.index_select(0, ids), shN.index_select(0, ids)], dim=1)
    return cpu.sh_colors(deg, means.index_select(0, ids), coeffs, campos)


class _TorchProjection:
    """Within the block the projection and the colours of rows run their torch forms."""

    def __enter__(self):
        self.kernel, self.rows = projection._kernel, cpu.sh_colors_rows
        projection._kernel, cpu.sh_colors_rows = (lambda *a: False), _gathered_rows

    def __exit__(self, *exc):
        projection._kernel, cpu.sh_colors_rows = self.kernel, self.rows


def _ms(f) -> float:
    t0 = time.perf_counter()
    f()
    return 1e3 * (time.perf_counter() - t0)


def frames(g0, model, cams, rounds: int) -> dict:
    """(frame, form) -> median over rounds of the median over views, ms."""
    jobs = [("input", lambda c: render_lod(g0, c))]
    jobs += [(f"s_v={s:g}", lambda c, s=s: render_lod(model, c, s)) for s in LEVELS]
    jobs += [(f"in_view={b:g}", lambda c, b=b: render_lod(model, c, budget=Budget(in_view=b))) for b in BUDGETS]
    for c in cams:  # warm the caches
        for _, f in jobs:
            f(c)
    per = {}
    for _ in range(rounds):
        order = [(name, f, form) for name, f in jobs for form in ("cpp", "torch")]
        random.shuffle(order)
        for name, f, form in order:
            ms = []
            for c in cams:
                if form == "torch":
                    with _TorchProjection():
                        ms.append(_ms(lambda: f(c)))
                else:
                    ms.append(_ms(lambda: f(c)))
            per.setdefault((name, form), []).append(statistics.median(ms))
    return {k: statistics.median(v) for k, v in per.items()}


def cuts(model, cams, rounds: int) -> dict:
    """(level, form) -> ms of the cut alone (median over rounds and views)."""
    ts = tree.tiers_of(model)
    forms = {"walk (C++)": lambda c, s: tree.cut(ts, c, s),
             "every node (C++ terms)": lambda c, s: tree.cut(ts, c, s, tt=tree.terms(ts, c)),
             "walk (torch)": lambda c, s: tree.walk(ts, c, s)}
    per = {}
    for _ in range(rounds):
        order = [(s, name) for s in LEVELS for name in forms]
        random.shuffle(order)
        for s, name in order:
            with torch.no_grad():
                ms = [_ms(lambda: forms[name](c, s)) for c in cams]
            per.setdefault((s, name), []).append(statistics.median(ms))
    return {k: statistics.median(v) for k, v in per.items()}


def main(argv=None) -> int:
    args = common.parse_inputs_args(__doc__, argv, inputs=("fern",), split="val", extra=[
        ("--rounds", {"type": int, "default": 9, "help": "interleaved rounds (default 9)"})])
    ok = True
    for name in args.inputs:
        ply = common.adapt_cached(name, AdaptConfig(), "default", split=args.split, log=print)
        g0, scene, _ = common.load_input(name, split=args.split)
        _, cams = common.scene_views(scene, args.split)
        model = load_model(ply)
        fr = frames(g0, model, cams, args.rounds)
        print(f"\n{name}: whole frames, ms ({args.split} views, {args.rounds} rounds)\n")
        print("| frame | torch projection | C++ projection | ratio | share of the input's frame: torch -> C++ |")
        print("|---|---:|---:|---:|---|")
        base_t, base_c = fr[("input", "torch")], fr[("input", "cpp")]
        for key in ["input"] + [f"s_v={s:g}" for s in LEVELS] + [f"in_view={b:g}" for b in BUDGETS]:
            t, c = fr[(key, "torch")], fr[(key, "cpp")]
            print(f"| {key} | {t:.1f} | {c:.1f} | {c / t:.2f} | {t / base_t:.3f} -> {c / base_c:.3f} |")
        cu = cuts(model, cams, args.rounds)
        print(f"\n{name}: the cut alone at a level, ms\n")
        print("| s_v | " + " | ".join(f for f in ("walk (C++)", "every node (C++ terms)", "walk (torch)")) + " |")
        print("|---:|---:|---:|---:|")
        for s in LEVELS:
            print(f"| {s:g} | " + " | ".join(f"{cu[(s, f)]:.2f}" for f in ("walk (C++)", "every node (C++ terms)",
                                                                           "walk (torch)")) + " |")
        r_proj = base_c / base_t
        r_walk = cu[(LEVELS[-1], "walk (C++)")] / cu[(LEVELS[-1], "every node (C++ terms)")]
        for what, v, goal in (("input's frame, C++ over torch projection", r_proj, PROJECTION_GOAL),
                              (f"cut at s_v {LEVELS[-1]:g}, walked over every node's terms", r_walk, WALK_GOAL)):
            met = v <= goal
            ok &= met
            print(f"[{name}] {'ok  ' if met else 'MISS'} {what}: {v:.2f} (at most {goal})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
