"""A training step's level: the C++ cost and prefix against their torch forms, paired in one run.

The calibrated schedule draws each training view at a level, the longest prefix of the Gaussians
in view (by critical ``s_v``) whose ``cost^cost_exponent`` fits the level's share
(:func:`clod_adapter.train.loop.weighted_count`). Its costs come from one C++ pass over the model
(:func:`clod_adapter.lod.cost.base_costs`) and its prefix from a weighted selection
(:func:`clod_adapter.lod.cost.ordered_prefix_count`); their torch forms, the twins (the same call
under ``use_impl("torch")``), cost the rows in view with :func:`clod_adapter.lod.cost.splat_cost`
and sort them all. On the inputs (their training views) and on synthetic models of ``--sizes``
Gaussians (``benchmarks.studies.scale``'s scenes, built when missing) this times a step of
:func:`clod_adapter.train.loop.fit` (the default schedule, from ``prepare``, ``--steps`` steps) and
the level by each form on the same views and shares (shuffled, ``--rounds`` rounds, medians),
checks that both pick the same counts, and prints the share of a step the C++ forms save.

Goal (exit 1 when missed): the level by the C++ forms in at most 0.6x the torch forms' time on
every input, and the counts equal::

    python -m benchmarks.studies.step_level --inputs fern skull --sizes 1000000
"""
from __future__ import annotations

import argparse
import os
import random
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from benchmarks import common  # noqa: E402
from clod_adapter.render.native import use_impl  # noqa: E402
from clod_adapter.lod.view import view_lod  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
#: the goal: the level by the C++ forms at most this share of its torch forms' time
GOAL_RATIO = 0.6


def synthetic(n: int):
    """(model, scene) of ``benchmarks.studies.scale``'s synthetic scene of ``n`` Gaussians."""
    from benchmarks.studies import scale
    from clod_adapter.io.load import load_model, load_scene

    root = REPO / "runs" / "scale_scenes" / f"n{n}"
    scale.write_scene(n, root, argparse.Namespace(rows=4, cols=4, width=320, height=240))
    return load_model(root / "in.ply"), load_scene(root / "scene")


def measure(name: str, model, scene, steps: int, rounds: int) -> dict:
    """One input: ms per training step (the default forms, ``steps`` steps after ``prepare``), the
    level's ms by each form on the same views and shares (the first 8 training views at shares
    0.05 / 0.3 / 0.7, the two forms in shuffled order, ``rounds`` rounds; medians), and whether
    the two forms pick the same counts there."""
    from clod_adapter.io.view_images import ViewImages
    from clod_adapter.train.loop import fit, prepare, weighted_count

    cfg = AdaptConfig(max_sv=5.0, iterations=10 ** 6, seed=0)
    train = scene.train
    state = prepare(model, train, cfg)
    imgs = ViewImages(scene, train)
    fit(state, train, imgs, cfg, progress=False, max_steps=2)  # warm-up
    t0 = time.perf_counter()
    fit(state, train, imgs, cfg, progress=False, max_steps=steps)
    step_ms = (time.perf_counter() - t0) / steps * 1e3
    g = state.gaussians().detach()

    def torch_count(view, share, cost_exponent):  # the same function with every kernel's torch twin
        with use_impl("torch"):
            return weighted_count(view, share, cost_exponent)

    forms = {"C++": weighted_count, "torch": torch_count}
    per, same, gen = {k: [] for k in forms}, True, random.Random(0)
    for _ in range(rounds):
        for cam in train[:8]:
            view = view_lod(g, cam, tau=cfg.tau, eps=cfg.eps)
            view.critical  # the terms a step has before it asks for the level (not timed)
            for share in (0.05, 0.3, 0.7):
                ks = {}
                for k in gen.sample(list(forms), len(forms)):
                    t0 = time.perf_counter()
                    ks[k] = forms[k](view, share, cfg.cost_exponent)
                    per[k].append((time.perf_counter() - t0) * 1e3)
                same &= ks["C++"] == ks["torch"]
    ms = {k: statistics.median(v) for k, v in per.items()}
    return {"input": name, "n": len(model), "step_ms": step_ms, "ms": ms, "ratio": ms["C++"] / ms["torch"],
            "saved": (ms["torch"] - ms["C++"]) / step_ms, "same": same}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    common.add_inputs_args(ap, ["fern"])
    ap.add_argument("--sizes", type=int, nargs="*", default=[])
    ap.add_argument("--steps", type=int, default=10, help="training steps timed for the ms per step "
                                                          "(a fifth of them on the synthetic models)")
    ap.add_argument("--rounds", type=int, default=6, help="rounds of the level timed by each form, in shuffled order")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = []
    for name in common.selected_inputs(args):
        model, scene, _ = common.load_input(name, split="val")
        rows.append(measure(name, model, scene, args.steps, args.rounds))
        print(rows[-1], file=sys.stderr, flush=True)
    for n in args.sizes:
        model, scene = synthetic(n)
        rows.append(measure(f"synthetic {n:,}", model, scene, max(2, args.steps // 5), args.rounds))
        print(rows[-1], file=sys.stderr, flush=True)
    print("| input | Gaussians | ms per step | level ms, C++ | torch | C++ / torch | saved share of a step | same counts |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for r in rows:
        print(f"| {r['input']} | {r['n']:,} | {r['step_ms']:.1f} | {r['ms']['C++']:.2f} | {r['ms']['torch']:.2f} | "
              f"{r['ratio']:.2f} | {r['saved']:.1%} | {'yes' if r['same'] else 'no'} |")
    ok = all(r["ratio"] <= GOAL_RATIO and r["same"] for r in rows)
    print(f"\n{args.threads} threads, {args.rounds} rounds; goals {'met' if ok else 'missed'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
