"""Does drawing the same share in every view pay at equal frame time? (Tried, not adopted.)

At a given ``s_v`` the rule (docs/lod_rule.md) keeps very different shares in different views of
a 360-degree capture: on skull's test views ``s_v = 3`` draws 2,410 to 26,830 Gaussians (5-55 %
of those in view), because ``d'`` is normalised by the farthest centre in each frustum. Training
draws every view at an exact share instead (``training.view_loss``: the level's share of the
view's weighted cost). This study evaluates the rule per view at the scale that draws
``s_v^-1.5`` of the frustum's Gaussians (``share``: the paper's target ``eta``, by count) or that
share of the view's weighted cost (``cost``: what training draws), against the rule at ``s_v``
itself (``distance``), on the default adaptation, every setting and the input timed in the same
interleaved rounds. On a single model the per-view scales are found before timing (a budget's exact
solve), so the times leave out that search and favour ``share`` and ``cost``; a merge tree draws
the two as its own budgets (``Budget(in_view=...)``, ``Budget(cost=...)``: that share of tier 0's
cost in view), the solve timed with the frame::

    python -m benchmarks.studies.view_share                  # skull, validation views
    python -m benchmarks.studies.view_share --inputs fern skull --split test

Printed per input and mode: PSNR / share of the input's frame at each ``s_v``, then the best PSNR
within 90 ... 10 % of the input's frame time (the frontier line of ``quality_vs_time.py``).
"""
from __future__ import annotations

import statistics
import sys

from benchmarks.common import adapt_cached, load_input, parse_inputs_args, scene_views  # noqa: E402
from benchmarks.studies.compare_configs import timed_render

import torch

from clod_adapter.lod import rule as lod, tree
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import view_lod
from clod_adapter.evaluate.frontier import Point, best_within
from clod_adapter.io.load import load_model
from clod_adapter.metrics import psnr
from clod_adapter.evaluate.timing import time_interleaved
from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.loop import weighted_count
from clod_adapter.lod.budget import Budget

S_VS = (1.5, 1.75, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 10.0, 15.0, 20.0, 30.0, 50.0)
SHARES = (0.9, 0.75, 0.6, 0.5, 0.4, 0.3, 0.25, 0.2, 0.15, 0.1)
MODES = ("distance", "share", "cost")


def view_scale(g, cam, s_v: float, mode: str, cost_exponent: float) -> float:
    """The scale the rule is evaluated at in this view for ``s_v`` under ``mode``."""
    if mode == "distance":
        return s_v
    v = view_lod(g, cam)
    if mode == "share":
        k = int(round(lod.target_fraction(s_v) * v.n_frustum))
    else:
        k = weighted_count(v, lod.target_fraction(s_v), cost_exponent)
    return max(float(v.select(budget=Budget(count=max(k, 1), min_s_v=0.0)).s_v), 1.0)


def frame_args(g, cam, s_v: float, mode: str, cost_exponent: float) -> dict:
    """``render_lod``'s level or budget for ``s_v`` under ``mode`` in this view: a merge tree's own
    budget for ``share`` / ``cost``, else the scale :func:`view_scale` finds."""
    if mode != "distance" and tree.is_tree(g):
        f = lod.target_fraction(s_v)
        return {"budget": Budget(in_view=f) if mode == "share" else Budget(cost=f)}
    return {"s_v": view_scale(g, cam, s_v, mode, cost_exponent)}


def run_input(name: str, split: str, repeats: int) -> None:
    cfg = AdaptConfig()
    g = load_model(adapt_cached(name, cfg, "default", split=split))
    g0, scene, gts = load_input(name, split)
    _, cams = scene_views(scene, split)
    jobs = {("input", 1.0): [timed_render(g0, c, None) for c in cams]}
    scores, drawn = {}, {}
    with torch.no_grad():
        for mode in MODES:
            for s in S_VS:
                args = [frame_args(g, c, s, mode, cfg.cost_exponent) for c in cams]
                outs = [render_lod(g, c, **a) for c, a in zip(cams, args)]
                scores[(mode, s)] = statistics.mean(psnr(o.image.clamp(0, 1), t) for o, t in zip(outs, gts))
                drawn[(mode, s)] = [o.n_rendered for o in outs]
                jobs[(mode, s)] = [timed_render(g, c, a.get("s_v"), a.get("budget")) for c, a in zip(cams, args)]
        res = time_interleaved(jobs, repeats=repeats, warmup=1)
    ms_in = res[("input", 1.0)]["ms_total"]
    print(f"[{name}] input {ms_in:.1f} ms ({len(cams)} {split} views)")
    for mode in MODES:
        pts = [Point(mode, f"s_v={s:g}", res[(mode, s)]["ms_total"], scores[(mode, s)]) for s in S_VS]
        print(f"[{name}] {mode:>8}: " + " ".join(
            f"{s:g}:{scores[(mode, s)]:.2f}/{100 * res[(mode, s)]['ms_total'] / ms_in:.0f}%"
            f"/{min(drawn[(mode, s)])}-{max(drawn[(mode, s)])}" for s in S_VS))
        print(f"[{name}] {mode:>8}: best within " + " / ".join(f"{100 * sh:.0f}" for sh in SHARES) + " %: "
              + " / ".join("-" if b is None else f"{b.psnr:.2f}" for b in (best_within(pts, sh * ms_in) for sh in SHARES))
              + " dB", flush=True)


def main() -> int:
    a = parse_inputs_args(__doc__, inputs=("skull",), split="val", extra=[
        ("--repeats", {"type": int, "default": 3, "help": "interleaved timing rounds (default 3)"})])
    for name in a.inputs:
        run_input(name, a.split, a.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
