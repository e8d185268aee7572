"""A merge tree's parents at scale: the k-d tree's candidates against every distance.

:func:`clod_adapter.lod.tree.assign_parents` scores, for each Gaussian of a tier, its 16 nearest
centres of the next tier. Those candidates come from a k-d tree
(:func:`clod_adapter.lod.neighbours.nearest`, ``scipy.spatial.cKDTree``); its twin
(:func:`clod_adapter.lod.neighbours.nearest_torch`) computes every child-parent distance in chunks,
``O(N M)``. For each size N this times both on a synthetic model
(:func:`clod_adapter.io.synthetic.make_ground_truth`, N Gaussians) whose every other Gaussian is
the parent tier (M = N / 2), checks that both give every child the same parent, and prints the
seconds and the fitted exponent ``b`` of ``time ~ N^b`` over the sizes.

The k-d tree is timed as the median of three calls. Goal (exit 1 when missed): the same parents at
every size, and the k-d tree's exponent at most 1.5 (``N log N`` is about 1.1 over these sizes,
every distance 2)::

    python -m benchmarks.studies.tree_parents --sizes 40000 80000 160000
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")

import torch  # noqa: E402

from clod_adapter.io.synthetic import make_ground_truth  # noqa: E402
from clod_adapter.lod import neighbours, tree  # noqa: E402

#: the k-d tree's largest fitted exponent of time against N: near ``N log N`` (about 1.1 over these
#: sizes), far from every distance's 2, with room for a busy 2-core machine's noise
GOAL_EXPONENT = 1.5


def exponent(xs, ys) -> float:
    """Least-squares slope of log y against log x."""
    lx, ly = [math.log(x) for x in xs], [math.log(max(y, 1e-9)) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[40000, 80000, 160000])
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows, same = [], True
    warm = make_ground_truth(2000)
    tree.assign_parents(warm, warm.subset(torch.arange(0, 2000, 2)))  # imports and first-call costs
    print("| N | parents M | k-d tree s | every distance s | same parents |\n|---:|---:|---:|---:|---|")
    for n in args.sizes:
        g = make_ground_truth(n)
        p = g.subset(torch.arange(0, n, 2))
        runs = []
        for _ in range(3):
            t0 = time.perf_counter()
            fast = tree.assign_parents(g, p)
            runs.append(time.perf_counter() - t0)
        t_fast = sorted(runs)[1]
        t1 = time.perf_counter()
        tree.nearest = neighbours.nearest_torch  # the twin, for this call only
        try:
            slow = tree.assign_parents(g, p)
        finally:
            tree.nearest = neighbours.nearest
        t2 = time.perf_counter()
        eq = bool((fast == slow).all())
        same &= eq
        rows.append((n, t_fast, t2 - t1))
        print(f"| {n:,} | {len(p):,} | {t_fast:.2f} | {t2 - t1:.2f} | {'yes' if eq else 'no'} |", flush=True)
    ok = same
    if len(rows) > 1:
        bf, bs = exponent([r[0] for r in rows], [r[1] for r in rows]), exponent([r[0] for r in rows], [r[2] for r in rows])
        print(f"\nfitted exponent b (time ~ N^b): k-d tree {bf:.2f} (goal at most {GOAL_EXPONENT}), every distance {bs:.2f}; "
              f"{args.threads} threads")
        ok &= bf <= GOAL_EXPONENT
    print("goals met" if ok else "goal missed", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
