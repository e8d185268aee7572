"""Would merged Gaussians pay? A study of a coarse tier of *merged* Gaussians beside the adapted
model, at equal frame time (coarse levels drawn from merged Gaussians rather than survivors only).

For each input (default: skull and fern; validation views by default, a design question) it
builds the settings of ``benchmarks/quality_vs_time.py`` (:func:`clod_adapter.evaluate.comparison.build_settings`:
the input, the adapted model without a tier along the ``s_v`` grid and at cost budgets, the static
peers: LightGaussian and opacity cuts, splat-transform 3.7.0's ``--decimate`` and
``--decimate-adaptive``), and adds, for each ``--parents`` share ``f``, a *parent tier*:
``splat-transform --decimate`` of the input to ``f`` of its Gaussians (moment-matched merges of
nearest pairs), adapted by ``clod-adapt`` with its defaults as if it were an input (cached in
``runs/bench/<input>/merge_tier_<f><_val>``), drawn along the same ``s_v`` grid. Every setting
of every method is scored and timed in the same interleaved rounds.

Printed per input: the best PSNR within 75 / 50 / 25 / 15 / 10 % of the input's frame time of

* the adapted model alone (today's one model),
* the adapted model and the parent tier together: the better of the two at each time (what one
  model holding both, drawing the parents' level once the children's is worse, would reach
  *at best*: the cross-fade between the two, where both are drawn, is not modelled, and the
  parents add ``f`` to the file),
* the best static cut,

and the goal margins of ``quality_vs_time.py`` at 50 / 25 / 10 % (ours >= best static + 1 dB)
for each. No goal is enforced (a study: exit 0)::

    python -m benchmarks.archive.merge_tier                        # skull, fern; validation views
    python -m benchmarks.archive.merge_tier --inputs skull --parents 0.04 0.08 0.15 --split test

Written: ``runs/bench/merge_tier<_val>/{<input>.csv, summary.md}``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from benchmarks.common import (RUNS, adapt_cached, add_inputs_args, add_split_arg, load_input, resolve_input,  # noqa: E402
                    scene_views, selected_inputs, setup_threads, split_suffix)

from clod_adapter.evaluate import comparison as qvt  # noqa: E402
from clod_adapter.train import tiers  # noqa: E402
from clod_adapter.lod.rankings import merge_decimate  # noqa: E402
from clod_adapter.evaluate.frontier import Point, best_within  # noqa: E402
from clod_adapter.io.atomic import atomic_write  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.io.ply import write_ply  # noqa: E402
from clod_adapter.io.splat_transform import find_splat_transform  # noqa: E402
from clod_adapter.evaluate.storage import ply_bytes  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402

SHARES = (0.75, 0.5, 0.25, 0.15, 0.1)
#: the goals' margin over the best static cut (``benchmarks/quality_vs_time.py``).
MARGIN_DB = 1.0


def adapt_parents(name: str, parents, share: float, split: str, log) -> "object":
    """The parent tier: the decimated input adapted with clod-adapt's defaults (cached)."""
    from clod_adapter.jobs.adapt import AdaptOptions, run

    _, scene, res = resolve_input(name)
    out = RUNS / name / f"merge_tier_{share:g}{split_suffix(split)}"
    ply = out / "point_cloud.ply"
    if (out / "metrics.json").is_file() and ply.is_file():
        log(f"[{name}] reusing the parent tier {out}")
        return load_model(ply)
    out.mkdir(parents=True, exist_ok=True)
    src = out.parent / f"merge_tier_{share:g}_input.ply"
    write_ply(src, parents)
    for p in out.iterdir():
        if p.is_file():
            p.unlink()
    t = time.perf_counter()
    log(f"[{name}] adapting the parent tier ({len(parents):,} merged Gaussians) ...")
    run(src, scene, out, AdaptConfig(parent_share=0.0),
        AdaptOptions(resolution=res, progress=False, log=lambda *a: None, holdout_val=split == "val"))
    log(f"[{name}] parent tier adapted in {time.perf_counter() - t:.0f} s")
    return load_model(ply)


def line(points, inp_ms: float) -> list:
    return [best_within(points, sh * inp_ms) for sh in SHARES]


def fmt(best: list) -> str:
    return " / ".join("-" if p is None else f"{p.psnr:.2f}" for p in best)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern"])
    ap.add_argument("--parents", nargs="+", type=float, default=[0.04, 0.15],
                    help="shares of the input's Gaussians the parent tiers hold (default 0.04 0.15)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    add_split_arg(ap, "val")
    args = ap.parse_args()
    inputs = selected_inputs(args)
    setup_threads(args.threads)
    tool = find_splat_transform()
    if tool is None:  # the decimators are the peers and the parents
        sys.exit("merge_tier: splat-transform not found (`npm ci` in the repository root installs 3.7.0)")
    out = RUNS / f"merge_tier{split_suffix(args.split)}"
    out.mkdir(parents=True, exist_ok=True)
    log = lambda *a: print(*a, flush=True)  # noqa: E731
    md = []
    for name in inputs:
        t0 = time.perf_counter()
        cfg = AdaptConfig(parent_share=0.0)  # the adapted model without a tier
        ga = load_model(adapt_cached(name, cfg, "notier", split=args.split, log=log))
        g0, scene, gts = load_input(name, args.split)
        fit, cams = scene_views(scene, args.split)
        settings, ctx = qvt.build_settings(ga, g0, fit, cams, merge_tool=tool,
                                           log=lambda msg, name=name: log(f"[{name}] {msg}"))
        chosen = {}
        for f in args.parents:
            m = merge_decimate(g0, max(1, int(round(f * len(g0)))), mode="decimate", tool=tool)
            gp = adapt_parents(name, m, f, args.split, log)
            size = ply_bytes(gp)
            for s in qvt.S_VS:
                settings.append(qvt.Setting(f"tier{f:g}", f"s_v={s:g}", [qvt.lod_render(gp, c, s_v=s) for c in cams],
                                            size))
            # the one model clod-adapt builds: the switch chosen on fit views (never the scored ones)
            sub = tiers.choice_views(fit)
            ch = tiers.choose(ga, gp, sub, [scene.load_image(c) for c in sub],
                              log=lambda msg, name=name: log(f"[{name}] {msg}"))
            if ch.tier_s_v is not None:
                gt = tiers.attach(ga, gp, ch.tier_s_v, ch.tier_start)
                chosen[f] = (ch.tier_s_v, ch.tier_start)
                for s in qvt.S_VS:
                    settings.append(qvt.Setting(f"tiered{f:g}", f"s_v={s:g}",
                                                [qvt.lod_render(gt, c, s_v=s) for c in cams], ply_bytes(ga) + size))
        qvt.score(settings, gts)
        log(f"[{name}] {len(settings)} settings x {len(gts)} views scored; timing x{args.repeats} ...")
        qvt.retime(settings, args.repeats)
        comp = qvt.Comparison(settings, [v.n_in_view for v in ctx.views], cfg.max_sv, merge_run=True)
        inp = comp.input
        with atomic_write(out / f"{name}.csv", "w") as fh:
            fh.write(qvt.csv_text(comp))
        pts = lambda pred: [Point(s.method, s.setting, s.ms, s.psnr) for s in settings if pred(s)]  # noqa: E731
        ours = pts(lambda s: s.method == "clod" and s.setting.startswith("s_v="))
        static = pts(lambda s: s.method in qvt.PEERS and not s.setting.startswith("match:"))
        rows = [("adapted model alone", line(ours, inp.ms))]
        for f in args.parents:
            tier = pts(lambda s, f=f: s.method == f"tier{f:g}")
            rows.append((f"with a parent tier of {100 * f:g} % (upper bound)", line(ours + tier, inp.ms)))
            rows.append((f"the parent tier alone ({100 * f:g} %)", line(tier, inp.ms)))
            if f in chosen:
                one = pts(lambda s, f=f: s.method == f"tiered{f:g}")
                rows.append((f"one model with the tier ({100 * f:g} %, switch s_v = {chosen[f][0]:g}, "
                             f"parents from {chosen[f][1]:g})", line(one, inp.ms)))
        rows.append(("best static cut", line(static, inp.ms)))
        log(f"[{name}] input {inp.psnr:.2f} dB in {inp.ms:.1f} ms ({len(gts)} {args.split} views, "
            f"{time.perf_counter() - t0:.0f} s); best PSNR within "
            f"{' / '.join(f'{100 * s:g}' for s in SHARES)} % of its frame:")
        st = dict(rows)["best static cut"]
        tab = ["| model | " + " | ".join(f"within {100 * s:g} %" for s in SHARES) + " | goals 50 / 25 / 10 % (margin dB) |",
               "|---|" + "---:|" * len(SHARES) + "---|"]
        for label, best in rows:
            marg = []
            for i, sh in enumerate(SHARES):
                if sh in (0.5, 0.25, 0.1) and label != "best static cut":
                    a, b = best[i], st[i]
                    marg.append("-" if a is None else f"{a.psnr - (b.psnr if b else -99) - MARGIN_DB:+.2f}")
            log(f"  {label:48s} {fmt(best)}" + (f"   goal margins {' / '.join(marg)}" if marg else ""))
            tab.append(f"| {label} | " + " | ".join("-" if p is None else f"{p.psnr:.2f} ({p.method} {p.setting})"
                                                   for p in best) + f" | {' / '.join(marg)} |")
        md.append(f"### {name} ({args.split} views; input {inp.psnr:.2f} dB in {inp.ms:.1f} ms)\n\n" + "\n".join(tab) + "\n")
    with atomic_write(out / "summary.md", "w") as fh:
        fh.write("\n".join(md))
    (out / "args.json").write_text(json.dumps(vars(args)))
    log(f"-> {out}")


if __name__ == "__main__":
    main()
