"""What each choice of the calibrated schedule buys, in dB at 100 / 25 / 10 %, on one input.

Each variant is a full ``clod-adapt`` run (cached, common.py) that changes one thing against the
default, plus the paper's recipe; every variant is scored at s_v = 1 and at the budgets 25 % /
10 % of the model (s_v solved per view) on the validation views (``--split val``, the default:
trained without them, ``clod-adapt --holdout-val``; the choice never sees a test view) or on
the test views (``--split test``, to report):

    python -m benchmarks.archive.ablation                  # fern, 1000 steps, validation views
    python -m benchmarks.archive.ablation --inputs demo --iterations 400
    python -m benchmarks.archive.ablation --split test     # the table in docs/archive/studies_superseded.md

Writes ``runs/bench/ablation_val.md`` / ``.csv`` (``ablation.md`` / ``.csv`` with ``--split test``).
"""
from __future__ import annotations

import argparse
import csv

import torch

from benchmarks.common import (LABELS, RUNS, adapt_cached, add_inputs_args, add_split_arg, load_input,  # noqa: E402
                    metrics_of, scene_views, selected_inputs, setup_threads, split_suffix, table)

from clod_adapter.train.config import AdaptConfig  # noqa: E402
from clod_adapter.io.ply import read_ply  # noqa: E402
from clod_adapter.lod.draw import render_lod  # noqa: E402
from clod_adapter.metrics import psnr  # noqa: E402
from clod_adapter.lod.budget import Budget

#: (tag, description, AdaptConfig overrides); "default" first.
VARIANTS = (
    ("default", "calibrated schedule, defaults", {}),
    ("paper", "the paper's recipe (Eq. 2 fading, L_reg, lambda_reg 0.05, other lr x0.1)", {"schedule": "paper"}),
    ("paper_lambda1", "the paper's recipe with the paper's lambda_reg = 1", {"schedule": "paper", "lambda_reg": 1.0}),
    ("static", "calibration only: LightGaussian order, window fade, no training", {"iterations": 0, "gains": ""}),
    ("no_gains", "no level gains (sigma_d learned)", {"gains": ""}),
    ("gain_o", "opacity gain only", {"gains": "o"}),
    ("gain_os", "opacity + scale gains", {"gains": "os"}),
    ("eq2_fade", "Eq. 2 fading instead of the window", {"fade": "eq2"}),
    ("recal_100", "recalibrate sigma_d every 100 steps (default: only after the last)", {"recalibrate_every": 100}),
    ("opacity_rank", "start from the opacity ranking", {"ranking": "opacity"}),
    ("ws_paper", "the paper's level weighting w_s", {"level_weighting": "paper"}),
    ("other_lr_0.1", "base attributes at 0.1 x the official learning rates", {"other_lr_scale": 0.1}),
    ("other_lr_0.02", "base attributes at 0.02 x the official learning rates", {"other_lr_scale": 0.02}),
)


@torch.no_grad()
def score(model, cams, gts, **kw):
    outs = [render_lod(model, c, **kw) for c in cams]
    p = sum(psnr(o.image.clamp(0, 1), g) for o, g in zip(outs, gts)) / len(gts)
    return p, sum(o.n_rendered for o in outs) / len(outs) / len(model)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_inputs_args(ap, ["fern"])
    ap.add_argument("--iterations", type=int, default=None, help="default 1000 (demo 400)")
    ap.add_argument("--max-sv", type=float, default=5.0)
    ap.add_argument("--only", nargs="*", default=None, help="variant tags to run (default: all)")
    ap.add_argument("--threads", type=int, default=2)
    add_split_arg(ap, "val")
    args = ap.parse_args()
    inputs = selected_inputs(args)
    setup_threads(args.threads)
    views = "validation views" if args.split == "val" else "test views"
    rows, md = [], ["# Ablation", "", f"PSNR on the {views} (--split {args.split}).", ""]
    for name in inputs:
        it = args.iterations or (400 if name == "demo" else 1000)
        pre, scene, gts = load_input(name, args.split)
        _, cams = scene_views(scene, args.split)
        base, _ = score(pre, cams, gts)
        body = []
        for tag, desc, over in VARIANTS:
            if args.only and tag not in args.only:
                continue
            cfg = AdaptConfig(**{"max_sv": args.max_sv, "iterations": it, **over})
            ply = adapt_cached(name, cfg, f"{tag}_M{args.max_sv:g}_it{it}" if tag != "default"
                               else f"calibrated_M{args.max_sv:g}_it{it}", split=args.split)
            model = read_ply(ply)
            p1, f1 = score(model, cams, gts, s_v=1.0)
            p25, _ = score(model, cams, gts, budget=Budget(share=0.25))
            p10, _ = score(model, cams, gts, budget=Budget(share=0.10))
            met = metrics_of(ply)
            r = {"input": name, "variant": tag, "description": desc, "psnr_s1": p1, "fraction_s1": f1,
                 "psnr_25": p25, "psnr_10": p10, "train_seconds": met["train_seconds"]}
            rows.append(r)
            print(r, flush=True)
        d = next((r for r in rows if r["input"] == name and r["variant"] == "default"), None)
        for r in (r for r in rows if r["input"] == name):
            rel = (lambda k: f" ({r[k] - d[k]:+.2f})" if d is not None and r is not d else "")  # noqa: E731
            body.append([r["variant"], r["description"], f"{r['psnr_s1']:.2f}{rel('psnr_s1')}",
                         f"{r['psnr_25']:.2f}{rel('psnr_25')}", f"{r['psnr_10']:.2f}{rel('psnr_10')}",
                         f"{r['train_seconds']:.0f}"])
        md += [f"## {LABELS.get(name, name)} (input {base:.2f} dB; {it} steps, max_sv {args.max_sv:g})", "",
               table(["variant", "what changes", "PSNR s_v=1 (vs default)", "25 %", "10 %", "train s"], body), ""]
    RUNS.mkdir(parents=True, exist_ok=True)
    out = RUNS / f"ablation{split_suffix(args.split)}"
    out.with_suffix(".md").write_text("\n".join(md))
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print("\n".join(md))


if __name__ == "__main__":
    main()
