"""How long should the hand-overs and the coarsest tier's fade last, and where should the merged
tiers hand over? Popping against quality at equal frame time, on one adaptation per input, for
render settings of its chain of merged tiers.

For each input (default: fern, maskgaussian, skull; validation views by default, a design
question) it takes ``clod-adapt``'s default adaptation (cached under
``runs/bench/<input>/default<_val>``) and redraws it with each variant of :data:`VARIANTS`:
``tier_fade`` (the cross-fade from each tier to the next lasts from ``tier_s_v`` to ``tier_fade
tier_s_v``), the coarsest tier's window ``fade_width`` (how far in ``ln s_v`` each of its
Gaussians takes to leave; the finer tiers keep the model's) and an earlier hand-over out of every
merged tier (its ``tier_s_v``; the input's own hand-over to the first tier as chosen). Nothing is
trained again: all are drawing settings of the file (``clod_lod_tier`` comments). It also prints
the coarsest window ``clod-adapt``'s rule chose on the training views (``--popping-goal``,
:func:`clod_adapter.popping.tail_width`), so the rule can be judged on views it never saw.

Per variant it prints the popping ratio of ``clod-eval`` (one static switch against the largest
step of a 61-frame sweep from ``s_v = 1`` to ``1.2 max_sv`` times the chain's reach, on every
scored view: the median, the smallest and where that view's largest step is), and the
best PSNR within 75 / 50 / 25 / 10 % of the input's frame time with its margin over the best
static peer (LightGaussian and opacity cuts, splat-transform 3.7.0's decimators), every setting
timed in the same interleaved rounds. No goal is enforced (a study: exit 0)::

    python benchmarks/studies/tail_fade.py                     # validation views
    python benchmarks/studies/tail_fade.py --reuse default     # the cached validation adaptations

Written: ``runs/bench/tail_fade<_val>/summary.md``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: common.py
from common import (RUNS, adapt_cached, add_inputs_args, add_split_arg, load_input, parse_config,  # noqa: E402
                    scene_views, selected_inputs, setup_threads, split_suffix, write_summary)

from clod_adapter import quality_vs_time as qvt  # noqa: E402
from clod_adapter.baselines import lightgaussian_significance  # noqa: E402
from clod_adapter.camera_lod import tier_chain, tier_reach  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.lod import DEFAULT_FADE_WIDTH  # noqa: E402
from clod_adapter.popping import popping_curve, popping_sweep, tail_width, with_coarsest_width  # noqa: E402
from clod_adapter.tiers import choice_views  # noqa: E402
from clod_adapter.splat_transform import find_splat_transform  # noqa: E402
from clod_adapter.storage import ply_bytes  # noqa: E402
from clod_adapter.training import AdaptConfig  # noqa: E402

#: (tier_fade, the coarsest tier's fade_width, the merged tiers' tier_s_v); None: as the
#: adaptation wrote it (``tier_fade`` 1.25, ``tier_s_v`` where its ``tier_hand_over`` put it)
VARIANTS = ((None, 0.5, None), (None, 1.0, None), (None, 2.0, None), (None, 3.0, None), (None, 4.0, None),
            (1.4, 2.0, None), (None, 2.0, 1.6), (None, 2.0, 1.3))


def redrawn(model, tier_fade, last_width, later_s_v=None):
    """``model`` with every hand-over's ``tier_fade``, the coarsest tier's ``fade_width`` and
    the hand-over of every merged tier but the coarsest (``tier_s_v`` of tiers 1, 2, ...; the
    input's own to tier 1 as written) set (None: as written)."""
    chain = tier_chain(model)
    out = None
    for k in range(len(chain) - 1, -1, -1):
        st = chain[k].lod
        if tier_fade is not None and k + 1 < len(chain):
            st = replace(st, tier_fade=float(tier_fade))
        if last_width is not None and k == len(chain) - 1:
            st = replace(st, fade_width=float(last_width))
        if later_s_v is not None and 0 < k < len(chain) - 1:
            st = replace(st, tier_s_v=float(later_s_v))
        out = replace(chain[k], lod=st, parents=out)
    return out


def label(v) -> str:
    """A variant's row name in the summary."""
    return (("" if v[0] is None else f"`tier_fade` {v[0]:g}, ") + f"coarsest `fade_width` {v[1]:g}"
            + ("" if v[2] is None else f", merged tiers' `tier_s_v` {v[2]:g}"))


def popping(model, cams, base, sig, steps: int = 61):
    """(median ratio over ``cams``, smallest ratio, the s_v of that view's largest step)."""
    svs = popping_sweep(model.lod.max_sv, tier_reach(model), steps)
    worst, ratios = None, []
    for c in cams:
        p = popping_curve(model, c, svs, discrete_model=base, discrete_scores=sig)
        j = int(np.argmax(p["continuous_step"]))
        ratios.append(float(p["ratio"]))
        if worst is None or p["ratio"] < worst[0]:
            worst = (float(p["ratio"]), float(p["step_s_v"][j]))
    return (statistics.median(ratios), *worst)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["fern", "maskgaussian", "skull"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reuse", metavar="TAG", default=None,
                    help="draw the adaptation cached under runs/bench/<input>/TAG<_val> as it is, whatever "
                         "settings it was adapted with (printed), instead of clod-adapt's defaults")
    add_split_arg(ap, "val")
    args = ap.parse_args()
    setup_threads(args.threads)
    tool = find_splat_transform()
    if tool is None:
        sys.exit("tail_fade: splat-transform not found (`npm ci` in the repository root installs 3.7.0)")
    log = lambda *a: print(*a, flush=True)  # noqa: E731
    config, tag = parse_config([])
    md = []
    for name in selected_inputs(args):
        if args.reuse:
            ply = RUNS / name / (args.reuse + split_suffix(args.split)) / "point_cloud.ply"
            cfg = json.loads((ply.parent / "metrics.json").read_text())["config"]
            log(f"[{name}] reusing {ply.parent}: tier_finetune_steps {cfg.get('tier_finetune_steps')}, "
                f"tier_time_cap {cfg.get('tier_time_cap')}, popping_goal {cfg.get('popping_goal')}, "
                f"tier_hand_over {cfg.get('tier_hand_over', 0.0)}")
        else:
            ply = adapt_cached(name, AdaptConfig(**config), tag, split=args.split, log=log)
        adapted = load_model(ply)
        g0, scene, gts = load_input(name, args.split)
        fit, cams = scene_views(scene, args.split)
        sig = lightgaussian_significance(g0, fit)
        models = {v: redrawn(adapted, *v) for v in VARIANTS}
        pops = {v: popping(m, cams, g0, sig) for v, m in models.items()}
        # clod-adapt's rule from the tier's own narrow window, on its 4 training views
        rule = tail_width(with_coarsest_width(adapted, DEFAULT_FADE_WIDTH), g0, choice_views(fit)[::2], sig)[1]
        settings, ctx = qvt.build_settings(models[VARIANTS[0]], g0, fit, cams, merge_tool=tool,
                                           log=lambda m: log(f"[{name}] {m}"), significance=sig)
        peers = [s for s in settings if s.method != "clod"]
        own = {v: [qvt.Setting("clod", f"s_v={s:g}", [qvt.lod_render(m, c, s_v=s) for c in cams], ply_bytes(m))
                   for s in qvt.clod_s_vs(m)] for v, m in models.items()}
        qvt.score(peers + [p for v in VARIANTS for p in own[v]], gts)
        every = peers + [p for v in VARIANTS for p in own[v]]
        log(f"[{name}] {len(every)} settings x {len(gts)} views scored; timing x{args.repeats} ...")
        qvt.retime(every, args.repeats)
        picks = ", ".join(f"{w:g}: {med:.1f}x" for w, med, _ in rule["widths"])
        rows = [f"### {name}", "", f"`clod-adapt`'s rule on the training views (median popping of 4): {picks}; "
                f"chosen: coarsest `fade_width` {rule['chosen']}", "",
                "| variant | popping ratio: median, smallest (its largest step at s_v) | "
                "within 75 / 50 / 25 / 10 %: PSNR (margin dB) |", "|---|---|---|"]
        for v in VARIANTS:
            comp = qvt.Comparison(peers + own[v], [w.n_in_view for w in ctx.views], adapted.lod.max_sv, merge_run=True)
            cs = [c for c in qvt.cells(comp) if c.kind == "time"]
            rows.append(f"| {label(v)} | {pops[v][0]:.2f}, {pops[v][1]:.2f} ({pops[v][2]:.1f}) | "
                        + " / ".join("-" if c.ours is None else f"{c.ours[2]:.2f} ({c.margin_db:+.2f})" for c in cs)
                        + " |")
        md.append("\n".join(rows))
        log(md[-1])
    write_summary(f"tail_fade{split_suffix(args.split)}", "\n\n".join(md))
    print("\n\n".join(md))


if __name__ == "__main__":
    main()
