"""How long should a merged tier be fitted before its level of detail is learned?

For each input (default: skull and fern) the merges ``clod-adapt`` builds for its tiers
(``--parent-share 0.5,0.15,0.04``: splat-transform 3.7.0's ``--decimate`` of the input, each next
tier merged from the fitted tier above it, :func:`clod_adapter.train.tiers.decimated`) are fine-tuned
at full detail on the fit views (:func:`clod_adapter.train.finetune.finetune_subset`, LightGaussian's
recovery rates, the schedule of :func:`clod_adapter.train.tiers.finetuned`), and scored on the
validation views (never in the fit, nor in the shared checkpoints' training) every ``--every``
steps up to ``--steps``. Printed: each merge's PSNR at each step against the input's, and the step
each merge scores best at. No goal is enforced (a study: exit 0)::

    python -m benchmarks.archive.tier_finetune                 # skull, fern; 400 steps
    python -m benchmarks.archive.tier_finetune --inputs skull --steps 600 --every 100
    python -m benchmarks.archive.tier_finetune --chain-steps 200   # each next merge from a 200-step fit

Written: ``runs/bench/tier_finetune/summary.md``. About 4 minutes per scene on 2 cores.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

from benchmarks.common import (add_inputs_args, load_input, scene_views, selected_inputs, setup_threads,  # noqa: E402
                    write_summary)

from clod_adapter.train import config, tiers  # noqa: E402
from clod_adapter.lod.draw import render_lod  # noqa: E402
from clod_adapter.train.finetune import FinetuneOptions, finetune_subset  # noqa: E402
from clod_adapter.metrics import psnr  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402


def val_psnr(model, cams, imgs) -> float:
    """Mean PSNR (dB, capped) of ``model`` at full detail on the views."""
    return statistics.mean(psnr(render_lod(model, c, None).image, gt, cap=True) for c, gt in zip(cams, imgs))


def study(name: str, shares, steps: int, every: int, chain_steps: int) -> list[str]:
    """One input's table rows: each merge's validation PSNR along its fine-tune."""
    g0, scene, _ = load_input(name, split="val")
    fit, val = scene_views(scene, "val")
    fit_imgs, val_imgs = [scene.load_image(c) for c in fit], [scene.load_image(c) for c in val]
    base = val_psnr(g0, val, val_imgs)
    rows, src, prev = [], g0, 1.0
    for share in shares:
        t = time.perf_counter()
        merged = tiers.decimated(src, share / prev)
        _, info = finetune_subset(merged, fit, fit_imgs, FinetuneOptions(iterations=steps, val_every=every),
                                  val=(val, val_imgs), return_info=True)
        curve = dict((int(s), p) for s, p in info.val_psnr)
        print(f"[{name}] {100 * share:g} % merge ({len(merged):,}): " + ", ".join(
            f"{s}: {p:.2f}" for s, p in curve.items()) + f" dB (input {base:.2f}) in {time.perf_counter() - t:.0f} s",
            flush=True)
        rows.append(f"| {name} | {100 * share:g} % ({len(merged):,}) | {base:.2f} | "
                    + " | ".join(f"{curve[s]:.2f} ({curve[s] - curve[0]:+.2f})" for s in sorted(curve))
                    + f" | {info.best_step} |")
        # the next tier is merged from this one fitted for ``chain_steps`` (the job's default)
        src, prev = tiers.finetuned(merged, fit, fit_imgs, chain_steps, background=(0.0, 0.0, 0.0)), share
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern"])
    ap.add_argument("--shares", type=float, nargs="+", default=list(config.DEFAULT_SHARES))
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--chain-steps", type=int, default=AdaptConfig().tier_finetune_steps,
                    help="fit steps of the merge each next one is merged from (default: clod-adapt's "
                         "--tier-finetune-steps)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    marks = list(range(0, args.steps + 1, args.every))
    if marks[-1] != args.steps:
        marks.append(args.steps)
    lines = ["| input | merge (Gaussians) | input, val PSNR | " + " | ".join(f"step {s}" for s in marks)
             + " | best step |", "|---|---|---:|" + "---:|" * len(marks) + "---:|"]
    for name in selected_inputs(args):
        lines += study(name, args.shares, args.steps, args.every, args.chain_steps)
    write_summary("tier_finetune", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
