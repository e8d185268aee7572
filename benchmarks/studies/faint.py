"""How much of a checkpoint can be left out before anything is learned, at no cost at full detail?

For each input (default: MaskGaussian fern, fern, skull) the Gaussians whose blending weight
summed over the fit views is under a share of one view's pixels
(:func:`clod_adapter.train.pruning.faint`, ``AdaptConfig.faint_share``) are left out, with no recovery.
The fit views are what the shared checkpoints were trained on, as a user's checkpoint is trained on
all its training views; the validation views were in neither. Printed per share: how many are left
out, the change in validation PSNR at full detail, and the frame time against the input's
(:func:`clod_adapter.evaluate.timing.time_interleaved`, interleaved rounds on the validation views, one
run). The default share is the largest that costs no input 0.02 dB. No goal is enforced (a study:
exit 0)::

    python -m benchmarks.studies.faint
    python -m benchmarks.studies.faint --inputs skull --shares 1e-5 4e-5

Written: ``runs/bench/faint/summary.md``. About 2 minutes in all on 2 cores.
"""
from __future__ import annotations

import argparse
import statistics
import sys

from benchmarks.common import (add_inputs_args, load_input, scene_views, selected_inputs, setup_threads,  # noqa: E402
                    write_summary)

from clod_adapter.lod.draw import render_lod  # noqa: E402
from clod_adapter.metrics import psnr  # noqa: E402
from clod_adapter.train.config import FAINT_SHARE  # noqa: E402
from clod_adapter.train.pruning import faint  # noqa: E402
from clod_adapter.evaluate.timing import time_interleaved  # noqa: E402

SHARES = (5e-6, FAINT_SHARE, 2e-5, 4e-5)


def study(name: str, shares, repeats: int) -> list[str]:
    """One input's table rows."""
    model, scene, imgs = load_input(name, split="val")
    fit, val = scene_views(scene, "val")
    plain = model.with_sigma_d(None)

    def val_psnr(m) -> float:
        return statistics.mean(psnr(render_lod(m, c, None).image, gt, cap=True) for c, gt in zip(val, imgs))

    base, kept = val_psnr(plain), {}
    jobs = {"input": [lambda c=c: render_lod(plain, c, None) for c in val]}
    for share in shares:
        out, px = faint(plain, fit, share)
        kept[share] = (plain.subset(~out), int(out.sum()), px)
        jobs[share] = [lambda c=c, m=kept[share][0]: render_lod(m, c, None) for c in val]
    t = time_interleaved(jobs, repeats=repeats)
    rows = []
    for share in shares:
        m, k, px = kept[share]
        d = val_psnr(m) - base
        ratio = t[share]["ms_total"] / t["input"]["ms_total"]
        print(f"[{name}] share {share:g} ({px:.2f} px): {k:,} of {len(plain):,} left out, val PSNR {d:+.3f} dB, "
              f"{100 * ratio:.1f} % of the input's frame", flush=True)
        rows.append(f"| {name} | {share:g} ({px:.2f} px) | {k:,} of {len(plain):,} ({100 * k / len(plain):.1f} %) | "
                    f"{base:.2f} | {d:+.3f} | {100 * ratio:.1f} % |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["maskgaussian", "fern", "skull"])
    ap.add_argument("--shares", type=float, nargs="+", default=list(SHARES))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    lines = ["| input | share of a view (px) | left out | input, val PSNR | change, dB | frame time |",
             "|---|---|---:|---:|---:|---:|"]
    for name in selected_inputs(args):
        lines += study(name, args.shares, args.repeats)
    write_summary("faint", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
