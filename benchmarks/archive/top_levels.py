"""Why the levels near full detail lose to a static significance cut (docs/archive/studies_superseded.md).

On the validation views of each input's default validation adaptation (``--split val``,
common.py) this renders, at ``s_v`` = 1.12 ... 3:

* ``adapted``: ``render_lod`` as it is (each view's ``d'``);
* ``adapted, d_ref``: the same rule with each Gaussian's reference distance (the calibration's mean
  ``d'`` over the fit views) in place of the view's ``d'``: is the per-view reordering the cause?
* static cuts at the adapted level's count per view, drawn with the level's gains and no fade:
  ``LG`` (LightGaussian significance), ``own`` (the trained order: the critical ``s_v`` at the
  reference distance) and ``merged`` (the trained order for its top 30 %, LightGaussian's for the
  rest): is the trained order the cause?

Prints one line per ``s_v`` (PSNR, mean drawn share of the Gaussians in view)::

    python -m benchmarks.archive.top_levels --inputs fern skull
"""
from __future__ import annotations


from benchmarks.common import adapt_cached, load_input, run_per_input, scene_views  # noqa: E402

import torch

from clod_adapter.lod.rankings import lightgaussian_significance, topk_in_view
from clod_adapter.lod.budget import critical_s_v
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import view_lod
from clod_adapter.io.load import load_model
from clod_adapter.metrics import psnr
from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.loop import reference_distances

S_VS = (1.12, 1.25, 1.5, 2.0, 3.0)
MERGE_TOP = 0.3


def quantiles(score):
    n = score.numel()
    q = torch.empty(n, dtype=torch.float64)
    q[torch.sort(-score.double(), stable=True).indices] = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    return q


def static_cut(view, order, k: int, level: float):
    idx = topk_in_view(order, view.visible, k)
    op = view.opacity_logits.index_select(0, idx)
    if "opacity_logit_gain" in view.gains:
        op = op + level * view.gains["opacity_logit_gain"].index_select(0, idx)
    sel = view.subset(idx, torch.sigmoid(op))
    sel.level = level
    return view.rasterize(sel)[0]


def run_input(name: str) -> None:
    ply = adapt_cached(name, AdaptConfig(), "default", split="val")
    g0, scene, gts = load_input(name, "val")
    fit, cams = scene_views(scene, "val")
    g = load_model(ply)
    d_ref = reference_distances(g, fit)
    q_own = quantiles(critical_s_v(g.opacities, d_ref, g.sigma_d, g.lod.tau, g.lod.eps))
    q_lg = quantiles(lightgaussian_significance(g.with_sigma_d(None), fit))  # the kept Gaussians (faint left out)
    orders = {"LG": -q_lg, "own": -q_own, "merged": -torch.where(q_own < MERGE_TOP, q_own, 1.0 + q_lg)}
    print(f"{name}: full detail {sum(psnr(render_lod(g, c).image, t) for c, t in zip(cams, gts)) / len(cams):.2f} dB")
    for s in S_VS:
        acc = {k: [] for k in ("adapted", "adapted, d_ref", "share", *orders)}
        for cam, gt in zip(cams, gts):
            v = view_lod(g, cam)
            r = render_lod(g, cam, s, view=v)
            acc["adapted"].append(psnr(r.image, gt))
            acc["share"].append(r.n_rendered / max(v.n_in_view, 1))
            vr = view_lod(g, cam)
            vr._d_norm = d_ref  # the rule with the reference distance (a probe, not an API)
            acc["adapted, d_ref"].append(psnr(render_lod(g, cam, s, view=vr).image, gt))
            for k, order in orders.items():
                acc[k].append(psnr(static_cut(v, order, r.n_rendered, r.level), gt))
        print(f"  s_v {s:4.2f} ({100 * sum(acc['share']) / len(cams):4.1f} % drawn): "
              + ", ".join(f"{k} {sum(x) / len(x):.2f}" for k, x in acc.items() if k != "share"), flush=True)


def main(argv=None) -> None:
    run_per_input(__doc__, run_input, argv)


if __name__ == "__main__":
    main()
