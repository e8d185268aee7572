"""Each merged tier drawn whole against the tree's cut at the same count: where equal count loses
to a static model.

At equal count the adapted model trails the per-budget ceiling (one static model fine-tuned per
count; goal 5). For each input (default: fern, MaskGaussian fern, skull) the cached
``--holdout-val`` adaptation with ``clod-adapt``'s defaults (``benchmarks.common.adapt_cached``,
trained on the fit views only) is scored on the validation views, per merged tier ``k``:

* the tier drawn whole as a static model (every node at its own attributes, ``render_lod`` of the
  tier alone), before the tree's fit (the tree built again as the job built it,
  ``benchmarks.studies.tree_fit.unfitted_tree``) and after it (the job's model);
* the tree's count-budget cut at the tier's own share of the Gaussians in view
  (``Budget(in_view=...)``, the mean share over the views), before and after the fit;
* what that cut draws in the first view: the nodes of each tier, and how many of them are
  changing (``w < 1`` in docs/lod_rule.md step 5: turning into their parent, shrinking or fading);
* the job's cut at that count drawn two other ways, by the rule's Python twin with a module
  constant set (no refit): every change over the floor ``F`` instead of ``M``
  (``lod.tree.MORPH = F``), and every node's ``d'`` its distance in the view instead of its stored
  reference distance (``lod.tree.budget_frame`` as :func:`clod_adapter.lod.tree.frame`).

No goal is enforced (a study: exit 0)::

    python -m benchmarks.studies.tier_cuts

Written: ``runs/bench/tier_cuts_val/summary.md``. About a minute per input after the adaptation.
"""
from __future__ import annotations

import statistics
import sys
from contextlib import contextmanager

import torch

from benchmarks.common import adapt_cached, load_input, parse_inputs_args, scene_views, split_suffix, print_summary
from benchmarks.studies.tree_fit import unfitted_tree
from clod_adapter.io.load import load_model
from clod_adapter.lod import tree
from clod_adapter.lod.budget import Budget
from clod_adapter.lod.draw import render_lod
from clod_adapter.metrics import psnr
from clod_adapter.train.config import AdaptConfig


def _mean_psnr(g, cams, gts, budget=None) -> float:
    return statistics.mean(psnr(render_lod(g, c, None, budget=budget).image.clamp(0, 1), t) for c, t in zip(cams, gts))


def _composition(g, cam, share: float) -> str:
    """What the cut at ``share`` of the Gaussians in view draws from ``cam``: per tier, the drawn
    nodes in the frustum and how many of them are changing."""
    ts = tree.tiers_of(g)
    tt = tree.terms(ts, cam, at=tree.budget_frame(ts, cam))
    c = tree.cut(ts, cam, tree.budget_s_v(tt, share * int(tt.frustum[0].sum())), tt=tt)
    parts = []
    for k, (ids, w) in enumerate(zip(c.ids, c.t)):
        inside = tt.frustum[k][ids]
        if bool(inside.any()):
            parts.append(f"t{k} {int(inside.sum()):,} ({int((inside & (w < 1)).sum()):,})")
    return f"s_v {c.s_v:.2f}: " + ", ".join(parts)


@contextmanager
def rule_with(morph: float = None, distances=None, python: bool = True):
    """The rule with ``lod.tree.MORPH`` set to ``morph`` and every node's ``d'`` in the budgets'
    cuts (:func:`clod_adapter.lod.tree.budget_frame`; the cuts at a level keep the view's
    distances) replaced where given: ``"view"``, the view's own (:func:`clod_adapter.lod.tree.frame`);
    a list, those (per tier [N_k]). Drawn by its Python twin when ``python`` (else where the C++
    kernels run); restored on exit. For studies only."""
    native, morph0, frame0 = tree.CPP_KERNELS, tree.MORPH, tree.budget_frame

    def frame(tiers, camera):
        ds, frs = tree.frame(tiers, camera)
        return (ds if isinstance(distances, str) else [r.to(d.dtype) for r, d in zip(distances, ds)]), frs

    if python:
        tree.CPP_KERNELS = False
    tree.MORPH = morph0 if morph is None else morph
    tree.budget_frame = frame0 if distances is None else frame
    try:
        yield
    finally:
        tree.CPP_KERNELS, tree.MORPH, tree.budget_frame = native, morph0, frame0


def run_input(name: str, split: str) -> list[str]:
    """The markdown rows of ``name``: one per merged tier."""
    g0, scene, gts = load_input(name, split)
    fit, cams = scene_views(scene, split)
    ply = adapt_cached(name, AdaptConfig(), "default", split=split)
    fitted = load_model(ply)
    unfitted = unfitted_tree(ply, list(fit), scene, AdaptConfig())[0]
    rows = []
    with torch.no_grad():
        t_fit, t_unfit = tree.tiers_of(fitted), tree.tiers_of(unfitted)
        n_in = [int(tree.in_frustum(t_fit[0], c).sum()) for c in cams]
        for k in range(1, len(t_fit)):
            share = statistics.mean(int(tree.in_frustum(t_fit[k], c).sum()) / n for c, n in zip(cams, n_in))
            b = Budget(in_view=share)
            cells = [_mean_psnr(t_unfit[k], cams, gts), _mean_psnr(unfitted, cams, gts, b),
                     _mean_psnr(t_fit[k], cams, gts), _mean_psnr(fitted, cams, gts, b)]
            with rule_with(morph=tree.HAND_OVER):
                at_f = _mean_psnr(fitted, cams, gts, b)
            with rule_with(distances="view"):
                at_view = _mean_psnr(fitted, cams, gts, b)
            row = (f"| {name} | {k} ({len(t_fit[k]):,} nodes, {100 * share:.1f} % in view) | "
                   + " | ".join(f"{x:.2f}" for x in cells) + f" | {cells[0] - cells[3]:+.2f} | "
                   + _composition(fitted, cams[0], share) + f" | {at_f:.2f} | {at_view:.2f} |")
            print(row, flush=True)
            rows.append(row)
    return rows


def main() -> int:
    a = parse_inputs_args(__doc__, inputs=("fern", "maskgaussian", "skull"), split="val")
    md = ["| input | tier | whole tier, unfitted (dB) | cut at its count, unfitted | whole tier, fitted | "
          "cut at its count, fitted (the job's) | whole unfitted tier over the job's cut | the job's cut in the "
          "first view: nodes in view per tier (changing) | the job's cut, changes over F | the job's cut, d' of "
          "the view |", "|---|---|---:|---:|---:|---:|---:|---|---:|---:|"]
    for name in a.inputs:
        md += run_input(name, a.split)
    return print_summary("tier_cuts" + split_suffix(a.split), md)


if __name__ == "__main__":
    sys.exit(main())
