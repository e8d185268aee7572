"""The merge tree against the chain of cross-faded tiers: cost along the level and quality at equal time.

Archived 2026-11-26: it needs the ``tier_draw = chain`` adaptation and the chain's drawing, both
removed; it runs at commit 207ff0d. Its study: docs/archive/studies_chain.md "The merge tree".

For each input (default: fern, skull and MaskGaussian fern) the ``tier_draw = chain`` adaptation
(cached, benchmarks/common.py: the tiers cross-faded whole at each hand-over) is drawn as it is
(``chain``) and with the same tiers linked into a merge tree and fitted on its cuts on the fit views,
as ``--tier-draw tree`` does after the same tiers (``tree``: :func:`clod_adapter.lod.tree.build`,
:func:`clod_adapter.train.tree_fit.finetune`, ``--fit-steps``, seed 0), and not fitted (``unfit``). All,
and the input, are drawn
on the scored views at ``--steps`` log-spaced ``s_v`` from 1 to past the coarsest tier and at count
budgets from 100 % to 1 % of the Gaussians in view, and timed in ``--rounds`` interleaved rounds
(``render_lod``'s wall time, median over rounds of the median over views). Printed per input:

* per level and budget: ms, PSNR, Gaussians drawn, for both;
* the worst cost step: the largest frame time over the frame time of any more detailed frame of the
  same sweep (goal: <= 1.05), and the largest frame time over the input's (goal: <= 1);
* the best PSNR within 75 / 50 / 25 / 10 % of the input's frame, for both;
* the best PSNR of splat-transform's two decimators (``qvt.DECIMATE_SHARES`` of the input, static
  models; when ``npx splat-transform`` is installed) within the same shares of the frame;
* ``clod-eval``'s popping ratio (:func:`clod_adapter.evaluate.popping.popping_ratio`) on every scored view,
  the median and the smallest.

No goal is enforced (a study: exit 0)::

    python -m benchmarks.archive.tree_draw --split val
    python -m benchmarks.archive.tree_draw --split val --inputs fern --rounds 3

Written: ``runs/bench/tree_draw/summary.md``. The adaptation takes 12-15 minutes per scene when not
cached; the fit about 3 minutes and the sweep about 5 per scene on 2 cores.
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from benchmarks.common import (SPLITS, adapt_cached, add_inputs_args, load_input, load_model, scene_views,  # noqa: E402
                    selected_inputs, setup_threads, write_summary)

from clod_adapter.evaluate import comparison as qvt
from clod_adapter.lod import tree  # noqa: E402
from clod_adapter.train.tree_fit import TREE_STEPS, finetune, level_range  # noqa: E402
from clod_adapter.lod.rankings import lightgaussian_significance  # noqa: E402
from clod_adapter.lod.draw import tier_reach  # noqa: E402
from clod_adapter.evaluate.popping import popping_ratio  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402
from clod_adapter.lod.budget import Budget

SHARES = (1.0, 0.75, 0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01)
WITHIN = (0.75, 0.5, 0.25, 0.1)


def worst_step(ms: list) -> float:
    """The largest ``ms[j] / ms[i]`` with ``i < j`` (a coarser frame against a more detailed one)."""
    best = math.inf
    worst = 0.0
    for m in ms:
        if best < math.inf:
            worst = max(worst, m / best)
        best = min(best, m)
    return worst


def run_input(name: str, args) -> list[str]:
    chain = load_model(adapt_cached(name, AdaptConfig(tier_draw="chain", tree_steps=0), "chain", split=args.split))
    base, scene, gts = load_input(name, args.split)
    fit, cams = scene_views(scene, args.split)
    unfit = tree.build(chain, fit)  # the chain's tiers as a tree, not fitted on its cuts
    t0 = time.perf_counter()
    model = finetune(unfit, fit, [scene.load_image(c) for c in fit], args.fit_steps, budget_steps=0.0)
    print(f"[{name}] tree fitted on its cuts: {args.fit_steps} steps in {time.perf_counter() - t0:.0f} s", flush=True)
    top = max(chain.lod.max_sv * tier_reach(chain) * 2.0, level_range(model, cams))
    s_vs = [float(s) for s in np.geomspace(1.0, top, args.steps)]
    settings = [qvt.Setting("input", "full", [qvt.lod_render(base, c) for c in cams], 0)]
    for label, g in (("chain", chain), ("tree", model), ("unfit", unfit)):
        for s in s_vs:
            settings.append(qvt.Setting(label, f"s_v={s:.4g}", [qvt.lod_render(g, c, s_v=s) for c in cams], 0))
        for b in SHARES:
            settings.append(qvt.Setting(label, f"budget={b:g}", [qvt.lod_render(g, c, budget=Budget(in_view=b))
                                                                 for c in cams], 0))
    from clod_adapter.lod.rankings import merge_decimate
    from clod_adapter.io.splat_transform import find_splat_transform

    tool = find_splat_transform()
    for method, mode in (qvt.DECIMATORS.items() if tool is not None else ()):  # the decimators, static
        for share in qvt.DECIMATE_SHARES:
            m = merge_decimate(base, max(1, int(round(share * len(base)))), mode=mode, tool=tool)
            settings.append(qvt.Setting("static", f"{method}={share:g}", [qvt.lod_render(m, c) for c in cams], 0))
    qvt.score(settings, gts)
    qvt.retime(settings, args.rounds)
    t_in = settings[0].ms
    lines = [f"## {name} ({args.split} views, {len(cams)}; input {t_in:.1f} ms, {settings[0].psnr:.2f} dB; "
             f"tree tiers {[len(t) for t in tree.tiers_of(model)]})", "",
             "| setting | chain ms | chain dB | chain drawn | tree ms | tree dB | tree drawn | not fitted dB |",
             "|---|---|---|---|---|---|---|---|"]
    by = {(s.method, s.setting): s for s in settings}
    keys = [f"s_v={s:.4g}" for s in s_vs] + [f"budget={b:g}" for b in SHARES]
    for k in keys:
        a, b, u = by[("chain", k)], by[("tree", k)], by[("unfit", k)]
        lines.append(f"| {k} | {a.ms:.1f} | {a.psnr:.2f} | {np.mean(a.drawn):.0f} | {b.ms:.1f} | {b.psnr:.2f} | "
                     f"{np.mean(b.drawn):.0f} | {u.psnr:.2f} |")
    lines.append("")
    scores = lightgaussian_significance(base, list(fit))
    pops = {label: [float(popping_ratio(g, base, c, scores)["ratio"]) for c in cams]
            for label, g in (("chain", chain), ("tree", model))}
    static = [(st.ms, st.psnr) for st in settings if st.method == "static"]
    if static:
        best = [max([p for m, p in static if m <= w * t_in], default=float("nan")) for w in WITHIN]
        lines.append(f"- splat-transform's decimators ({', '.join(f'{x:g}' for x in qvt.DECIMATE_SHARES)} of the "
                     f"input), best static dB within {' / '.join(f'{int(w * 100)}' for w in WITHIN)} % of the "
                     f"input's frame: {' / '.join(f'{b:.2f}' for b in best)}")
    for label in ("chain", "tree", "unfit"):
        sweep = [by[(label, f"s_v={s:.4g}")].ms for s in s_vs]
        bud = [by[(label, f"budget={b:g}")].ms for b in SHARES]
        pts = [(st.ms, st.psnr) for st in settings if st.method == label]
        best = [max([p for m, p in pts if m <= w * t_in], default=float("nan")) for w in WITHIN]
        lines.append(f"- {label}: worst cost step along s_v {worst_step(sweep):.2f}x, along budgets "
                     f"{worst_step(bud):.2f}x; largest frame {max(sweep + bud) / t_in:.2f}x the input's; best dB "
                     f"within {' / '.join(f'{int(w * 100)}' for w in WITHIN)} % of the input's frame: "
                     f"{' / '.join(f'{b:.2f}' for b in best)}" + (
                         f"; popping median {np.median(pops[label]):.1f}x, smallest {min(pops[label]):.1f}x"
                         if label in pops else ""))
    return lines + [""]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_inputs_args(ap, ("fern", "skull", "maskgaussian"))
    ap.add_argument("--split", choices=SPLITS, default="val")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--fit-steps", type=int, default=TREE_STEPS)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    setup_threads(args.threads)
    out = ["# The merge tree against the chain of tiers", ""]
    for name in selected_inputs(args):
        out += run_input(name, args)
        print("\n".join(out[-(args.steps + len(SHARES) + 10):]), flush=True)
    write_summary("tree_draw", "\n".join(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
