"""Which merge should a tier start from: splat-transform's ``--decimate`` or its
``--decimate-adaptive``?

For each input (default: skull and fern) the chain of merges ``clod-adapt`` builds for its tiers
(``--parent-share 0.5,0.15,0.04``, each next tier merged from the fitted tier above it, each fitted
for ``--tier-finetune-steps`` steps on the fit views, :func:`clod_adapter.train.tiers.finetuned`) is built
once with each of splat-transform 3.7.0's merging decimators (:data:`clod_adapter.train.config.MERGES`).
Every merge is scored at full detail on the validation views (never in the fit, nor in the shared
checkpoints' training), and the input and every merge are timed at full detail in the same
interleaved rounds. Printed per merge: validation PSNR before and after the fit, frame time as a
share of the input's, and bytes. No goal is enforced (a study: exit 0)::

    python -m benchmarks.archive.tier_merge                    # skull, fern

Written: ``runs/bench/tier_merge/summary.md``. About 3 minutes per scene on 2 cores.
"""
from __future__ import annotations

import argparse
import sys

from benchmarks.common import (add_inputs_args, load_input, scene_views, selected_inputs, setup_threads,  # noqa: E402
                    write_summary)

from clod_adapter.evaluate import comparison as qvt  # noqa: E402
from clod_adapter.train import config, tiers  # noqa: E402
from clod_adapter.evaluate.storage import ply_bytes  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402


def study(name: str, shares, steps: int, repeats: int, log) -> list[str]:
    """One input's table rows: each merge of each decimator, fitted, at full detail."""
    g0, scene, val_imgs = load_input(name, split="val")
    fit, val = scene_views(scene, "val")
    fit_imgs = [scene.load_image(c) for c in fit]

    def setting(label: str, model):
        return qvt.Setting(label, "s_v=1", [qvt.lod_render(model, c, s_v=None) for c in val], ply_bytes(model))

    every, raw = [setting("input", g0)], {}
    for merge in config.MERGES:
        src, prev = g0, 1.0
        for share in shares:
            merged = tiers.decimated(src, share / prev, merge=merge)
            raw[(merge, share)] = setting("unfitted", merged)
            src, prev = tiers.finetuned(merged, fit, fit_imgs, steps, background=(0.0, 0.0, 0.0)), share
            every.append(setting(f"{merge} {100 * share:g} %", src))
            log(f"[{name}] {merge} {100 * share:g} %: {len(src):,} Gaussians merged and fitted ({steps} steps)")
    qvt.score(every + list(raw.values()), val_imgs)
    log(f"[{name}] timing {len(every)} models x {len(val)} views x{repeats} ...")
    qvt.retime(every, repeats)
    inp = every[0]
    rows = [f"| {name} | input | {inp.psnr:.2f} | - | 100 % | {inp.storage / 1e6:.1f} |"]
    for s in every[1:]:
        merge, share = s.method.split(" ")[0], float(s.method.split(" ")[1]) / 100
        rows.append(f"| {name} | {s.method} | {s.psnr:.2f} ({s.psnr - inp.psnr:+.2f}) | "
                    f"{raw[(merge, share)].psnr:.2f} | {100 * s.ms / inp.ms:.0f} % | {s.storage / 1e6:.1f} |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern"])
    ap.add_argument("--shares", type=float, nargs="+", default=list(config.DEFAULT_SHARES),
                    help="the chain's shares of the input, descending (default: clod-adapt's)")
    ap.add_argument("--steps", type=int, default=AdaptConfig().tier_finetune_steps,
                    help="fit steps per merge (default: clod-adapt's --tier-finetune-steps)")
    ap.add_argument("--repeats", type=int, default=5, help="interleaved timing rounds (default 5)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    log = lambda m: print(m, flush=True)  # noqa: E731
    lines = ["| input | merge | val PSNR, fitted (vs input) | unfitted | frame time | MB |",
             "|---|---|---:|---:|---:|---:|"]
    for name in selected_inputs(args):
        lines += study(name, args.shares, args.steps, args.repeats, log)
    write_summary("tier_merge", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
