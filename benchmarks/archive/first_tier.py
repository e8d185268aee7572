"""Does the first merged tier save time, and which share does ``--tier-time-cap`` give it?

For each input (default: fern, maskgaussian, skull) the input is merged by splat-transform's
``--decimate`` to 50 % of its Gaussians and to 0.7x and 0.49x that (the shares
:func:`clod_adapter.train.tiers.first_share` tries). Printed per merge: the frame time that
``clod-adapt`` predicts for it at full detail (the fitted frame-time model on the 8 training views
the job chooses on: the fit views, the validation views held out) as a share of the input's, the
frame time measured at full detail on the validation views (the input and every merge timed in the
same interleaved rounds), and the share the default cap (``train.config.TIER_TIME_CAP``) picks. The merges
are not fitted here (the job fits the one it picks). No goal is enforced (a study: exit 0)::

    python -m benchmarks.archive.first_tier                    # fern, maskgaussian, skull

The quality each first share buys is measured by ``benchmarks/studies/compare_configs.py``
(docs/archive/studies_superseded.md "A first tier that saves time"). Written:
``runs/bench/first_tier/summary.md``. About 1 minute per scene on 2 cores.
"""
from __future__ import annotations

import argparse
import sys

from benchmarks.common import add_inputs_args, load_input, scene_views, selected_inputs, setup_threads, write_summary  # noqa: E402

from clod_adapter.evaluate import comparison as qvt  # noqa: E402
from clod_adapter.train import config, tiers  # noqa: E402


def study(name: str, cap: float, repeats: int, log) -> list[str]:
    """One input's table rows: each share tried, predicted and measured."""
    g0, scene, _ = load_input(name, split="val")
    fit, val = scene_views(scene, "val")
    cams = tiers.choice_views(fit)  # as clod-adapt's job
    base = tiers.predicted_ms(g0, cams)
    picked, _, _ = tiers.first_share(g0, config.DEFAULT_SHARES[0], cams, cap=cap, floor=config.DEFAULT_SHARES[1])
    shares = [config.DEFAULT_SHARES[0] * tiers.TIER_SHARE_STEP ** k for k in range(3)]
    every = [qvt.Setting("input", "s_v=1", [qvt.lod_render(g0, c, s_v=None) for c in val], 0)]
    predicted = {}
    for share in shares:
        merged = tiers.decimated(g0, share)
        predicted[share] = tiers.predicted_ms(merged, cams) / base
        every.append(qvt.Setting(f"{share:.3g}", "s_v=1", [qvt.lod_render(merged, c, s_v=None) for c in val], 0))
        log(f"[{name}] {share:.3g}: {len(merged):,} Gaussians, predicted {predicted[share]:.0%} of the input's frame")
    log(f"[{name}] timing {len(every)} models x {len(val)} views x{repeats} ...")
    qvt.retime(every, repeats)
    rows = []
    for s, share in zip(every[1:], shares):
        rows.append(f"| {name} | {100 * share:.3g} % | {100 * predicted[share]:.0f} % | "
                    f"{100 * s.ms / every[0].ms:.0f} % | {'**picked**' if abs(share - picked) < 1e-9 else ''} |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["fern", "maskgaussian", "skull"])
    ap.add_argument("--cap", type=float, default=config.TIER_TIME_CAP,
                    help=f"the predicted share of the input's frame a first merge may take "
                         f"(default clod-adapt's --tier-time-cap, {config.TIER_TIME_CAP:g})")
    ap.add_argument("--repeats", type=int, default=5, help="interleaved timing rounds (default 5)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    log = lambda m: print(m, flush=True)  # noqa: E731
    lines = [f"| input | first merge | predicted frame (fit views) | measured frame (val views) | cap {args.cap:g} |",
             "|---|---:|---:|---:|---|"]
    for name in selected_inputs(args):
        lines += study(name, args.cap, args.repeats, log)
    write_summary("first_tier", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
