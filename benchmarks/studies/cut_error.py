"""Where a count budget's cut of a merge tree loses against full detail: by the kind of node that
draws each pixel.

For each input (default: fern and skull) the cached adaptation with ``clod-adapt``'s defaults
(``benchmarks.common.adapt_cached``; ``--split val``: trained on the fit views only, the default) is
drawn on every evaluation view at count budgets of 75 / 50 / 30 / 15 % of the Gaussians in view
(:func:`clod_adapter.lod.draw.render_lod`) and at full detail (``s_v = 1``). A pixel's *excess* is
the cut's squared error against the photograph minus full detail's (mean over the channels, [0, 1]
units). The cut's nodes (:func:`clod_adapter.lod.cut.tree_cut`) are sorted into :data:`KINDS`: drawn
as themselves (``t = 1``) in tier 0, tier 1 or a later tier, or changing (``t < 1``: turning into
the parent, shrinking or fading out; docs/lod_rule.md step 5) in tier 0 or a merged tier; the cut is
drawn again with each kind's one-hot code as its colour (the same opacities, positions and sizes),
so each pixel's blending weights split it among the kinds. Printed per scene and budget: the
excess per pixel, and per kind the share of the pixels it draws, its share of the excess and its
excess per pixel it draws. With ``--unfitted`` the tree is the job's before its fit on its cuts
(:func:`benchmarks.studies.tree_fit.unfitted_tree`: tier 0 and the merged tiers linked and built
again as the job built them). No goal is enforced (a study: exit 0)::

    python -m benchmarks.studies.cut_error --inputs fern skull
    python -m benchmarks.studies.cut_error --inputs fern skull --unfitted

Written: ``runs/bench/cut_error<_unfitted><_val>/summary.md``. About a minute per scene on 2 threads.
"""
from __future__ import annotations

import sys

import torch

from benchmarks.common import load_input, adapt_cached, parse_inputs_args, print_summary, scene_views, split_suffix
from clod_adapter.io.load import load_model
from clod_adapter.lod import tree
from clod_adapter.lod.budget import Budget
from clod_adapter.lod.cut import tree_cut
from clod_adapter.lod.draw import render_lod
from clod_adapter.render.dispatch import rasterization
from clod_adapter.train.config import AdaptConfig

#: the count budgets scored, shares of the Gaussians in view
SHARES = (0.75, 0.5, 0.3, 0.15)
#: the kinds of drawn node, in their one-hot order
KINDS = ("tier 0 as itself", "tier 1 as itself", "tier 2+ as itself", "tier 0 changing", "merged changing")


def kinds_of(c) -> torch.Tensor:
    """[k] int64: the :data:`KINDS` index of each row of the cut ``c`` (tier 0's rows first, as
    :func:`clod_adapter.lod.tree.cut_attributes` orders them)."""
    out = []
    for k, (ids, w) in enumerate(zip(c.ids, c.t)):
        still = torch.full_like(ids, min(k, 2))
        out.append(torch.where(w < 1.0, torch.full_like(ids, 3 if k == 0 else 4), still))
    return torch.cat(out)


@torch.no_grad()
def kind_weights(g, camera, c) -> torch.Tensor:
    """[H, W, len(KINDS)] float: each pixel's blending weight of each kind of node in the cut ``c``
    of ``g`` (the cut drawn with one-hot colours, three kinds per frame), normalised to sum to 1
    where anything is drawn."""
    m, q, s, o, _ = tree.cut_attributes(tree.tiers_of(g), c)
    onehot = torch.nn.functional.one_hot(kinds_of(c), len(KINDS)).to(m.dtype)
    parts = []
    for j in range(0, len(KINDS), 3):
        block = torch.nn.functional.pad(onehot[:, j:j + 3], (0, 3 - onehot[:, j:j + 3].shape[1]))
        im = rasterization(m, q, s, o, block, camera.viewmat[None], camera.K[None], int(camera.width),
                           int(camera.height), sh_degree=None)[0][0]
        parts.append(im[..., :min(3, len(KINDS) - j)])
    w = torch.cat(parts, -1)
    return w / w.sum(-1, keepdim=True).clamp_min(1e-6)


def run_input(name: str, split: str, unfitted: bool = False) -> list[str]:
    """``name``'s markdown rows: one per budget and kind (``unfitted``: the job's tree before its fit)."""
    cfg = AdaptConfig()
    ply = adapt_cached(name, cfg, "default", split=split)
    _, scene, gts = load_input(name, split)
    fit, cams = scene_views(scene, split)
    if unfitted:
        from benchmarks.studies.tree_fit import unfitted_tree

        g, same = unfitted_tree(ply, fit, scene, cfg)
        if not same:
            raise RuntimeError(f"{name}: the rebuilt tree's node constants differ from the job's")
    else:
        g = load_model(ply)
    rows = []
    with torch.no_grad():
        full_err = [((render_lod(g, cam, 1.0).image.clamp(0, 1) - gt) ** 2).mean(-1) for cam, gt in zip(cams, gts)]
        for share in SHARES:
            excess, cover, total, pixels = torch.zeros(len(KINDS)), torch.zeros(len(KINDS)), 0.0, 0
            for cam, gt, err in zip(cams, gts, full_err):
                img = render_lod(g, cam, budget=Budget(in_view=share)).image.clamp(0, 1)
                w = kind_weights(g, cam, tree_cut(g, cam, budget=Budget(in_view=share)))
                e = ((img - gt) ** 2).mean(-1) - err
                excess += (e[..., None] * w).sum((0, 1)).float()
                cover += w.sum((0, 1)).float()
                total, pixels = total + float(e.sum()), pixels + e.numel()
            cells = [f"{float(cv) / pixels:.2f} / {float(x) / total:+.2f} / {float(x) / max(float(cv), 1.0):+.1e}"
                     for x, cv in zip(excess, cover)]
            line = f"| {name} | {100 * share:g} % | {total / pixels:+.1e} | " + " | ".join(cells) + " |"
            print(line, flush=True)
            rows.append(line)
    return rows


def main(argv=None) -> int:
    args = parse_inputs_args(__doc__, argv, inputs=("fern", "skull"), split="val",
                             extra=[("--unfitted", {"action": "store_true",
                                                    "help": "draw the job's tree before its fit on its cuts"})])
    head = ["| scene | budget in view | excess per pixel | " + " | ".join(KINDS) + " |",
            "|---|---|---:|" + "---|" * len(KINDS)]
    rows = [r for name in args.inputs for r in run_input(name, args.split, args.unfitted)]
    return print_summary("cut_error" + ("_unfitted" if args.unfitted else "") + split_suffix(args.split), head + rows)


if __name__ == "__main__":
    sys.exit(main())
