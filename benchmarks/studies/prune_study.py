"""Leaving out what a scene does not need: what static pruning (and pruning + recovery) buys in
frame time, on validation views.

Rankings of the input's Gaussians over the fit views: ``weight`` (each Gaussian's blending weight
``alpha T`` summed over every pixel of every fit view: the gradient of the rendered image's sum
with respect to a constant per-Gaussian colour), ``weight_per_cost`` (that over its footprint
pixels, :func:`clod_adapter.lod.cost.splat_cost`), LightGaussian significance and opacity. Each cut
keeps the top ``--keeps`` of the model; with ``--recover N`` the ``weight`` cut at the first keep
is then fine-tuned (every attribute, LightGaussian's recovery schedule,
:func:`clod_adapter.train.finetune.finetune_subset`) for N steps on the fit views. Every model is
scored on the validation views (PSNR; the input fits them, it was trained on them), or with
``--split test`` on the test views (the recovery then fits every training view), and timed
against the input in the same interleaved rounds (2 threads)::

    python -m benchmarks.studies.prune_study --inputs fern --recover 600
    python -m benchmarks.studies.prune_study --inputs fern --split test --keeps 0.6 0.7 --recover 1000

``clod-adapt --keep-share`` (:mod:`clod_adapter.train.pruning`) is the ``weight`` cut with this
recovery, kept when it beats the cut on held-out training views. ``--coverages 0.99 ...`` adds
``weight`` cuts sized by blending-weight coverage (the fewest Gaussians carrying that share of the
fit views' total weight): a rule that needs no held-out view.
"""
from __future__ import annotations

import statistics

from benchmarks.common import load_input, parse_inputs_args, scene_views  # noqa: E402
from benchmarks.studies.compare_configs import timed_render

import torch

from clod_adapter.lod.rankings import lightgaussian_significance
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import view_lod
from clod_adapter.lod.cost import splat_cost
from clod_adapter.train.finetune import FinetuneOptions, finetune_subset, global_cut
from clod_adapter.metrics import psnr
from clod_adapter.train.pruning import blend_weights
from clod_adapter.evaluate.timing import time_interleaved


def blend_weight(g, cameras) -> tuple:
    """([N] summed blending weight (:func:`clod_adapter.train.pruning.blend_weights`), [N] summed
    footprint pixels) over ``cameras``."""
    cost = torch.zeros(len(g), dtype=torch.float64)
    for c in cameras:
        v = view_lod(g, c)
        ids = torch.nonzero(v.visible).squeeze(1)
        cost.index_add_(0, ids, splat_cost(v, ids).double())
    return blend_weights(g, cameras), cost


def coverage_share(w: torch.Tensor, coverage: float) -> float:
    """The smallest share of the model whose largest blending weights carry ``coverage`` of the
    total (a rule a user's checkpoint can apply: it needs only the training views)."""
    c = torch.cumsum(torch.sort(w.double(), descending=True).values, 0)
    k = int(torch.searchsorted(c, coverage * c[-1]).item()) + 1
    return min(k, len(w)) / len(w)


def run_input(name: str, split: str, keeps: list, recover: int, coverages=()) -> None:
    g0, scene, gts = load_input(name, split)
    fit, cams = scene_views(scene, split)
    w, cost = blend_weight(g0, fit)
    scores = {"weight": w, "weight_per_cost": w / cost.clamp_min(1.0),
              "lightgaussian": lightgaussian_significance(g0, fit), "opacity": g0.opacities.detach()}
    models = {"input": g0}
    for cov in coverages:
        share = coverage_share(w, cov)
        models[f"weight coverage {cov:g} (keep {share:.3f})"] = g0.subset(global_cut(w, share))
    for k, s in scores.items():
        for keep in keeps:
            models[f"{k} keep {keep:g}"] = g0.subset(global_cut(s, keep))
    if recover:
        imgs = [scene.load_image(c) for c in fit]
        models[f"weight keep {keeps[0]:g} + {recover} recovery steps"] = finetune_subset(
            models[f"weight keep {keeps[0]:g}"], fit, imgs, FinetuneOptions(iterations=recover))
    with torch.no_grad():
        ps = {k: statistics.mean(psnr(render_lod(m, c).image.clamp(0, 1), t) for c, t in zip(cams, gts))
              for k, m in models.items()}
        r = time_interleaved({k: [timed_render(m, c, None) for c in cams] for k, m in models.items()}, repeats=3, warmup=1)
    base = r["input"]["per_round"]
    print(f"[{name}] {len(cams)} {split} views; input {ps['input']:.2f} dB")
    for k, m in models.items():
        share = statistics.median(b / a for a, b in zip(base, r[k]["per_round"]))
        print(f"[{name}] {k:42s} {len(m):7,} Gaussians  {ps[k]:6.2f} dB ({ps[k] - ps['input']:+.2f})  "
              f"{100 * share:4.0f} % of the input's frame")


def main() -> None:
    a = parse_inputs_args(__doc__, inputs=("fern",), split="val", extra=[
        ("--keeps", {"type": float, "nargs": "+", "default": [0.6, 0.7, 0.85], "help": "shares of the model kept"}),
        ("--recover", {"type": int, "default": 0, "help": "recovery steps for the weight cut at the first keep"}),
        ("--coverages", {"type": float, "nargs": "*", "default": [],
                         "help": "also cut by blending-weight coverage: keep the fewest Gaussians carrying this share "
                                 "of the fit views' total weight"})])
    for name in a.inputs:
        run_input(name, a.split, a.keeps, a.recover, a.coverages)


if __name__ == "__main__":
    main()
