"""Where should each merged tier take over? The hand-over rules of the chain of merged tiers, on one
adaptation, at equal frame time and at equal count.

Archived 2026-11-26: it links the tiers again by each rule and draws them as the cross-fade chain
(``--tier-draw chain``), which is no longer drawn (tiers not linked into a merge tree draw as the model
alone); it runs at commit 207ff0d. Its study: docs/archive/studies_chain.md.

For each input (default: skull and fern; validation views by default, a design question; ``--split
test`` reports what the tiers buy on the test views) it takes the default adaptation (``clod-adapt``'s
defaults, tiers of ``--parent-share 0.5,0.15,0.04``, cached under ``runs/bench/<input>/default<_val>``
as ``benchmarks/quality_vs_time.py`` caches it: the model and each merged tier adapted in
``parents/``, ``parents/parents/``, ...), detaches every tier and links them again, from the
coarsest up, by each rule of :data:`VARIANTS`:

* ``default``: :func:`clod_adapter.train.tiers.link` (by predicted time, the tier at full detail, within
  ``CHOOSE_MARGIN_DB`` = 1.5 dB of the tier above on the fit views; else the coarsest tier by PSNR);
* ``margin 1.0``: the same with a 1 dB margin;
* ``psnr``: each tier where some level of it first scores at least the tier above in no more
  predicted time (``tiers.choose(rule="psnr")``), the next tier down only;
* ``4 % tier``: the coarsest tier alone, by PSNR (one parent tier, as a single tier is linked);
* ``no tier``: the adapted model alone.

Every variant, the input and the static peers of ``benchmarks/quality_vs_time.py`` (LightGaussian
and opacity cuts, splat-transform 3.7.0's decimators) are scored and timed in the same interleaved
rounds; the hand-overs are chosen on 8 fit views, never on the scored ones. Printed per input and
variant: the chain (Gaussians per tier, each hand-over's ``tier_s_v`` / ``tier_start``), the best
PSNR within 75 / 50 / 25 / 10 % of the input's frame time with its margin over the best peer, and
the margins at equal count. No goal is enforced (a study: exit 0)::

    python -m benchmarks.archive.tier_rule                     # skull, fern; validation views
    python -m benchmarks.archive.tier_rule --inputs fern maskgaussian skull --split test

Written: ``runs/bench/tier_rule<_val>/summary.md``.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from benchmarks.common import (adapt_cached, add_inputs_args, add_split_arg, load_input,  # noqa: E402
                    scene_views, selected_inputs, setup_threads, split_suffix, write_summary)

from clod_adapter.evaluate import comparison as qvt  # noqa: E402
from clod_adapter.train import tiers  # noqa: E402
from clod_adapter.lod.draw import tier_chain  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.io.splat_transform import find_splat_transform  # noqa: E402
from clod_adapter.evaluate.storage import ply_bytes  # noqa: E402
from clod_adapter.train.config import AdaptConfig  # noqa: E402

VARIANTS = ("default", "margin 1.0", "psnr", "4 % tier", "no tier")


def linked(variant: str, model, below: list, cams, imgs, log):
    """``model`` with its tiers ``below`` (finest first, each bare) linked by ``variant``."""
    if variant == "no tier" or not below:
        return model
    if variant == "4 % tier":
        return tiers.link(model, [below[-1]], cams, imgs, margin_db=-1e9, log=log)[0]  # "time" never, then psnr
    built = [below[-1]]  # each tier with its chain, coarsest first
    for above in reversed([model] + below[:-1]):
        if variant == "psnr":
            ch = tiers.choose(above, built[-1], cams, imgs, rule="psnr", log=log)
            built.append(above if ch.tier_s_v is None else tiers.attach(above, built[-1], ch.tier_s_v, ch.tier_start))
        else:
            margin = 1.0 if variant == "margin 1.0" else tiers.CHOOSE_MARGIN_DB
            built.append(tiers.link(above, built[::-1], cams, imgs, margin_db=margin, log=log)[0])
    return built[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_inputs_args(ap, ["skull", "fern"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    add_split_arg(ap, "val")
    args = ap.parse_args()
    inputs = selected_inputs(args)
    setup_threads(args.threads)
    tool = find_splat_transform()
    if tool is None:
        sys.exit("tier_rule: splat-transform not found (`npm ci` in the repository root installs 3.7.0)")
    log = lambda *a: print(*a, flush=True)  # noqa: E731
    md = []
    for name in inputs:
        ply = adapt_cached(name, AdaptConfig(), "default", split=args.split, log=log)
        dirs = [ply.parent]
        while (dirs[-1] / "parents" / "point_cloud.ply").is_file():
            dirs.append(dirs[-1] / "parents")
        bare = [replace(load_model(d / "point_cloud.ply"), parents=None) for d in dirs]
        g0, scene, gts = load_input(name, args.split)
        fit, cams = scene_views(scene, args.split)
        sub = tiers.choice_views(fit)
        imgs = [scene.load_image(c) for c in sub]
        models = {v: linked(v, bare[0], bare[1:], sub, imgs, lambda m, v=v: log(f"[{name}] {v}: {m}"))
                  for v in VARIANTS}
        settings, ctx = qvt.build_settings(models["no tier"], g0, fit, cams, merge_tool=tool,
                                           log=lambda m: log(f"[{name}] {m}"))
        peers = [s for s in settings if s.method != "clod"]
        qvt.score(peers, gts)  # the equal-count points take the decimators' drawn counts
        own = {}
        for v, m in models.items():
            size = ply_bytes(m)
            pts = [qvt.Setting("clod", f"s_v={s:g}", [qvt.lod_render(m, c, s_v=s) for c in cams], size)
                   for s in qvt.clod_s_vs(m)]
            pts += qvt.matched_settings(peers, replace(ctx, adapted=m), bare[0].lod.max_sv)
            own[v] = [p for p in pts if p.method == "clod"]
        every = peers + [p for v in VARIANTS for p in own[v]]
        qvt.score([p for v in VARIANTS for p in own[v]], gts)
        log(f"[{name}] {len(every)} settings x {len(gts)} views scored; timing x{args.repeats} ...")
        qvt.retime(every, args.repeats)
        rows = [f"### {name}", "", "| variant | tiers (Gaussians) | hand-overs (tier_s_v / tier_start) | MB | "
                "within 75 / 50 / 25 / 10 %: PSNR (margin dB) | equal count: margins (dB) |", "|---|---|---|---:|---|---|"]
        for v in VARIANTS:
            comp = qvt.Comparison(peers + own[v], [w.n_in_view for w in ctx.views], bare[0].lod.max_sv, merge_run=True)
            cs = qvt.cells(comp)
            chain = tier_chain(models[v])
            rows.append(f"| {v} | {' / '.join(f'{len(t):,}' for t in chain)} | "
                        f"{', '.join(f'{t.lod.tier_s_v:g} / {t.lod.tier_start:g}' for t in chain[:-1]) or '-'} | "
                        f"{ply_bytes(models[v]) / 1e6:.1f} | "
                        + " / ".join("-" if c.ours is None else f"{c.ours[2]:.2f} ({c.margin_db:+.2f})"
                                     for c in cs if c.kind == "time")
                        + " | " + " / ".join(f"{c.margin_db:+.2f}" for c in cs if c.kind == "count") + " |")
        md.append("\n".join(rows))
        log(md[-1])
    write_summary(f"tier_rule{split_suffix(args.split)}", "\n\n".join(md))
    print("\n\n".join(md))


if __name__ == "__main__":
    main()
