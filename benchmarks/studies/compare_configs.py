"""Adaptation settings against each other at equal frame time, and their popping.

For choosing a default, and for the ablation at equal time: each input (default: skull and fern)
is adapted with ``clod-adapt``'s defaults and with each ``--config KEY=VALUE ...`` (one variant
per ``--config``; cached, common.py; ``--split val``: fit views only), and every model is
rendered from the evaluation views along the same ``s_v`` grid as ``quality_vs_time.py`` (its
:func:`clod_adapter.evaluate.comparison.clod_s_vs`: past every tier's hand-over), every
setting of every model and the input timed in the same interleaved rounds.
Printed per input: each model's best PSNR within 90 / 75 / 50 / 25 / 15 / 10 % of the input's
frame time (the frontier line of ``quality_vs_time.py``), its mean PSNR at equal count per view
(``Budget(in_view=...)`` at 50 / 30 / 15 / 8 / 4 / 2 % of the Gaussians in view; untimed) and the
popping of ``clod-eval`` from the first view (the largest of 31 steps of its sweep,
:func:`clod_adapter.jobs.eval.popping_sweep`, mean |dI|, and the switch between the opacity cuts at
the first and last counts over it)::

    python -m benchmarks.studies.compare_configs --config fade_width=0.75            # validation views
    python -m benchmarks.studies.compare_configs --config gains= --config fade=eq2   # two variants

Also written: ``runs/bench/compare_configs/<tags><_val>.csv`` (input, variant, s_v, PSNR, ms,
share of the input's frame) and ``.md`` (the frontier lines).
"""
from __future__ import annotations

import csv
import statistics
import sys
import time

from benchmarks.common import RUNS, adapt_cached, load_input, parse_config, parse_inputs_args, scene_views, split_suffix  # noqa: E402

import torch  # noqa: E402

from clod_adapter.lod.budget import Budget  # noqa: E402
from clod_adapter.lod.draw import render_lod  # noqa: E402
from clod_adapter.evaluate.frontier import Point, best_within  # noqa: E402
from clod_adapter.evaluate.level_metrics import evaluate_level  # noqa: E402
from clod_adapter.io.atomic import atomic_write  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.jobs.eval import popping_curve, popping_sweep  # noqa: E402
from clod_adapter.metrics import psnr  # noqa: E402
from clod_adapter.evaluate.timing import time_interleaved  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402

from clod_adapter.lod.draw import tier_reach  # noqa: E402
from clod_adapter.evaluate.comparison import clod_s_vs  # noqa: E402  (the s_v grid of benchmarks/quality_vs_time.py)

SHARES = (0.9, 0.75, 0.5, 0.25, 0.15, 0.1)
#: shares of the Gaussians in view of the equal-count scores (the decimators' points span 8-50 %)
COUNTS = (0.5, 0.3, 0.15, 0.08, 0.04, 0.02)


class _Timed:
    def __init__(self, ms: float) -> None:
        self.select_ms, self.raster_ms = 0.0, ms


def timed_render(g, cam, s_v, budget=None):
    """A zero-argument job for :func:`clod_adapter.evaluate.timing.time_interleaved`: one whole
    ``render_lod(g, cam, s_v, budget=budget)`` frame, its budget's solve included, timed as raster
    ms (``s_v`` and ``budget`` None: the model as it is)."""
    def f():
        t0 = time.perf_counter()
        render_lod(g, cam, s_v, budget=budget)
        return _Timed((time.perf_counter() - t0) * 1e3)
    return f


def run_input(name: str, split: str, configs: dict, repeats: int) -> tuple[list, list]:
    """Adapt (cached), render and time ``configs`` {tag: AdaptConfig keywords} on ``name``.
    Returns (CSV rows, markdown lines of the frontier)."""
    g0, scene, gts = load_input(name, split)
    fit, cams = scene_views(scene, split)
    models = {tag: load_model(adapt_cached(name, AdaptConfig(**kw), tag, split=split)) for tag, kw in configs.items()}
    sets = {("input", 1.0): [timed_render(g0, c, None) for c in cams]}
    scores = {}
    with torch.no_grad():
        grids = {tag: clod_s_vs(g) for tag, g in models.items()}
        for tag, g in models.items():
            for s in grids[tag]:
                sets[(tag, s)] = [timed_render(g, c, s) for c in cams]
                scores[(tag, s)] = statistics.mean(psnr(render_lod(g, c, s).image.clamp(0, 1), t)
                                                   for c, t in zip(cams, gts))
        p_in = statistics.mean(psnr(render_lod(g0, c).image.clamp(0, 1), t) for c, t in zip(cams, gts))
        res = time_interleaved(sets, repeats=repeats, warmup=1)
        ms_in = res[("input", 1.0)]["ms_total"]
        print(f"[{name}] input {p_in:.2f} dB, {ms_in:.1f} ms ({len(cams)} {split} views)")
        rows = [{"input": name, "variant": "input", "s_v": 1.0, "psnr": round(p_in, 3), "ms": round(ms_in, 2),
                 "time_share": 1.0}]
        md = [f"### {name}: input {p_in:.2f} dB in {ms_in:.1f} ms ({len(cams)} {split} views)", "",
              "| variant | best within " + " / ".join(f"{100 * sh:.0f}" for sh in SHARES) + " % of the input's time |",
              "|---|---|"]
        md_count = ["| variant | PSNR at " + " / ".join(f"{100 * c:g}" for c in COUNTS) + " % of the Gaussians in view |",
                    "|---|---|"]
        for tag, g in models.items():
            rows += [{"input": name, "variant": tag, "s_v": s, "psnr": round(scores[(tag, s)], 3),
                      "ms": round(res[(tag, s)]["ms_total"], 2),
                      "time_share": round(res[(tag, s)]["ms_total"] / ms_in, 4)} for s in grids[tag]]
            pts = [Point("clod", f"s_v={s:g}", res[(tag, s)]["ms_total"], scores[(tag, s)]) for s in grids[tag]]
            best = [best_within(pts, sh * ms_in) for sh in SHARES]
            pop = popping_curve(g, cams[0], popping_sweep(g.lod.max_sv, tier_reach(g), 31))
            print(f"[{name}] {tag:>24}: best within " + " / ".join(f"{100 * sh:.0f}" for sh in SHARES) + " %: "
                  + " / ".join("-" if b is None else f"{b.psnr:.2f}" for b in best)
                  + f" dB; popping {pop['continuous_max']:.5f} vs switch {pop['discrete_max']:.5f}: {pop['ratio']:.1f}x")
            print(f"[{name}] {tag:>24}: " + " ".join(f"{s:g}:{scores[(tag, s)]:.2f}/{100 * res[(tag, s)]['ms_total'] / ms_in:.0f}%"
                                                for s in grids[tag]))
            md.append(f"| {tag} | " + " / ".join("-" if b is None else f"{b.psnr:.2f}" for b in best) + " |")
            at_count = [evaluate_level(g, cams, gts, None, budget=Budget(in_view=k)).psnr for k in COUNTS]
            print(f"[{name}] {tag:>24}: equal count " + " / ".join(f"{100 * k:g}" for k in COUNTS) + " % in view: "
                  + " / ".join(f"{p:.2f}" for p in at_count) + " dB")
            md_count.append(f"| {tag} | " + " / ".join(f"{p:.2f}" for p in at_count) + " |")
    return rows, md + [""] + md_count + [""]


def write_csv(path, rows: list) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def write_text(path, text: str) -> None:
    with atomic_write(path, "w") as f:
        f.write(text)


def main() -> int:
    a = parse_inputs_args(__doc__, inputs=("skull", "fern"), split="val", extra=[
        ("--config", {"nargs": "+", "required": True, "action": "append", "metavar": "KEY=VALUE",
                      "help": "one variant's AdaptConfig settings (repeat for more variants)"}),
        ("--repeats", {"type": int, "default": 5, "help": "interleaved timing rounds (default 5)"})])
    configs = {"default": {}}
    for items in a.config:
        kw, tag = parse_config(items)
        configs[tag] = kw
    rows, md = [], []
    for name in a.inputs:
        r, m = run_input(name, a.split, configs, a.repeats)
        rows += r
        md += m
    out = RUNS / "compare_configs" / ("+".join(t for t in configs if t != "default") + split_suffix(a.split))
    write_csv(out.parent / f"{out.name}.csv", rows)  # not with_suffix: tags hold dots (level_max-2.0)
    write_text(out.parent / f"{out.name}.md", "\n".join(md))
    print("\n".join(md))
    print(f"wrote {out}.csv / .md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
