"""Does L_reg act? The paper's hard-count L_reg against our straight-through (STE) and sigmoid
relaxations, on fern (``--inputs``; ``--input NAME=PLY:SCENE[:RES]`` for any checkpoint).

Each estimator fine-tunes the same pretrained model for the same number of steps with the same
seed on the fit views; the rendered fraction of the validation views (``--split val``, the
default; ``--split test``: trained on the training views, the test views) at several s_v is
printed before and after, with PSNR. With the paper's as-written estimator L_reg has no gradient, so sigma_d is moved by the
rendering loss alone and the fraction does not fall; with ours it does.

    python -m benchmarks.studies.lreg_ablation [--iterations 300] [--inputs fern] [--split val]
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")

import torch  # noqa: E402

from benchmarks.common import add_inputs_args, add_split_arg, resolve_input, scene_views, selected_inputs  # noqa: E402

from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.loop import fit, prepare  # noqa: E402
from clod_adapter.evaluate.level_metrics import evaluate_level  # noqa: E402
from clod_adapter.io.load import load_model, load_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_inputs_args(ap, ["fern"])
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--max-sv", type=float, default=5.0)
    ap.add_argument("--estimators", default="paper,ste,sigmoid")
    add_split_arg(ap)
    args = ap.parse_args()
    torch.set_num_threads(2)
    for name in selected_inputs(args):
        run_input(name, args)


def run_input(name: str, args) -> None:
    """Fine-tune ``name``'s pretrained model once per estimator; print the fractions before and after."""
    ply, scene_root, res = resolve_input(name)
    g = load_model(ply)
    sc = load_scene(scene_root, resolution=res)
    fit_cams, eval_cams = scene_views(sc, args.split)
    tr = [sc.load_image(c) for c in fit_cams]
    te = [sc.load_image(c) for c in eval_cams]
    levels = [1.0, 2.0, 3.0, args.max_sv]
    print(f"{name}: {len(g)} Gaussians, {args.iterations} steps per estimator on {len(fit_cams)} views, "
          f"{len(eval_cams)} {args.split} views scored, max_sv {args.max_sv}, "
          f"{torch.get_num_threads()} threads")
    print(f"{'estimator':>10} {'when':>6} " + " ".join(f"{'s_v=' + format(s, 'g'):>16}" for s in levels))
    for est in args.estimators.split(","):
        cfg = AdaptConfig(max_sv=args.max_sv, iterations=args.iterations, schedule="paper", eta_estimator=est, seed=0)
        st = prepare(g, fit_cams, cfg, tr)
        rows = {}
        rows["before"] = [evaluate_level(st.gaussians().detach(), eval_cams, te, s) for s in levels]
        t = time.perf_counter()
        fit(st, fit_cams, tr, cfg, progress=False)
        dt = time.perf_counter() - t
        rows["after"] = [evaluate_level(st.gaussians().detach(), eval_cams, te, s) for s in levels]
        for when, lv in rows.items():
            cells = " ".join(f"{100 * r.fraction:6.1f}% {r.psnr:6.2f}dB" for r in lv)
            print(f"{est:>10} {when:>6} {cells}")
        b5, a5 = rows["before"][-1].fraction, rows["after"][-1].fraction
        print(f"{est:>10} rendered fraction at s_v={args.max_sv:g}: {100 * b5:.1f}% -> {100 * a5:.1f}% "
              f"(ratio {a5 / b5:.3f}) in {dt:.0f} s", flush=True)


if __name__ == "__main__":
    main()
