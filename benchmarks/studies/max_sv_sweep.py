"""Does ``--max-sv`` mean something? Train max_sv = 1, 3, 5, 7 and compare quality against
Gaussians drawn, with the static cuts of the input model at the same budgets.

For each input and each max_sv: ``clod-adapt``'s job with its defaults (cached, common.py), then
the scored views (``--split``: ``val``, the default, the validation views, trained without them
(``clod-adapt --holdout-val``), to choose max_sv; ``test``, the test views, to report) at s_v = 1, along an s_v sweep (1 .. max_sv) and at a grid of budgets (fractions of
the model, down to 3.5 %), scored with PSNR / SSIM / LPIPS-alex. The input model is cut to the
same budgets by opacity ranking, LightGaussian significance and (when installed) splat-transform's
merging decimator. Writes ``runs/bench/<name>.csv``, ``<name>.md`` and ``<name>.png`` (PSNR vs
Gaussians drawn, one curve per max_sv plus the static cuts, one panel per input, max_sv^-1.5
marked):

    python -m benchmarks.studies.max_sv_sweep                          # fern, max_sv 1 3 5 7, validation views
    python -m benchmarks.studies.max_sv_sweep --inputs fern demo --max-svs 3 5
    python -m benchmarks.studies.max_sv_sweep --split test             # the table in docs/studies.md (test views)

With ``--split val`` the outputs are ``<name>_val.*``. robustness.py (a report, beside this file) defaults to
``--split test``.
"""
from __future__ import annotations

import argparse
import sys
import csv
import time
from pathlib import Path

import torch

from benchmarks.common import (LABELS, RUNS, adapt_cached, add_inputs_args, add_split_arg, fmt_pct, load_input,  # noqa: E402
                    metrics_of, scene_views, selected_inputs, setup_threads, split_suffix, table)

from clod_adapter.train.config import AdaptConfig
from clod_adapter.io.splat_transform import find_splat_transform
from clod_adapter.lod.rankings import lightgaussian_significance, merge_decimate, ranking_selection, render_subset
from clod_adapter.lod.budget import budget_count
from clod_adapter.io.ply import read_ply
from clod_adapter.lod.draw import render_lod
from clod_adapter.metrics import psnr, ssim
from clod_adapter.jobs.eval import resolve_lpips
from clod_adapter.lod.budget import Budget

#: budgets evaluated (fractions of the model): the table's, each max_sv^-1.5, and a dense grid.
BUDGETS = (1.0, 0.5, 0.35, 0.25, 0.192, 0.15, 0.1, 0.0894, 0.07, 0.0544, 0.05, 0.035)
TABLE_BUDGETS = (1.0, 0.5, 0.25, 0.1, 0.05)
STATIC = ("opacity", "lightgaussian", "merge")


def _score(imgs, gts, lp):
    p = sum(psnr(i.clamp(0, 1), g) for i, g in zip(imgs, gts)) / len(gts)
    s = sum(float(ssim(i.clamp(0, 1), g)) for i, g in zip(imgs, gts)) / len(gts)
    lpv = None if lp is None else sum(float(lp(i.clamp(0, 1), g)) for i, g in zip(imgs, gts)) / len(gts)
    return p, s, lpv


@torch.no_grad()
def sweep(name: str, max_svs, iterations: int, lp, tool, log=print, split: str = "test") -> list[dict]:
    """Rows (dicts) for one input: each max_sv's model along s_v and budgets, and the static cuts,
    scored on the views of ``split`` (common.scene_views)."""
    pre, scene, gts = load_input(name, split)
    fit_cams, cams = scene_views(scene, split)
    n = len(pre)
    rows = []

    def add(method, m, setting, s_v, budget, imgs, counts):
        p, s, lpv = _score(imgs, gts, lp)
        g = sum(counts) / len(counts)
        rows.append({"input": name, "method": method, "max_sv": m, "setting": setting, "s_v": s_v,
                     "budget": budget, "gaussians": g, "fraction": g / n, "psnr": p, "ssim": s, "lpips": lpv})

    add("input", "", "full", None, None, [render_lod(pre, c).image for c in cams],
        [render_lod(pre, c).n_rendered for c in cams])
    for m in max_svs:
        cfg = AdaptConfig(max_sv=float(m), iterations=iterations)
        ply = adapt_cached(name, cfg, f"calibrated_M{m:g}_it{iterations}", split=split, log=log)
        met = metrics_of(ply)
        model = read_ply(ply)
        t = time.perf_counter()
        for s in sorted({1.0, *[float(x) for x in torch.linspace(1, max(m, 1.0), 5).tolist()]}):
            outs = [render_lod(model, c, s) for c in cams]
            add("clod", m, f"s_v={s:g}", s, None, [o.image for o in outs], [o.n_rendered for o in outs])
        for b in BUDGETS:
            outs = [render_lod(model, c, budget=Budget(share=b)) for c in cams]
            add("clod_budget", m, f"budget={b:g}", sum(o.s_v for o in outs) / len(outs), b,
                [o.image for o in outs], [o.n_rendered for o in outs])
        log(f"[{name}/M{m:g}] {met['train_seconds']:.0f} s training; evaluated in {time.perf_counter() - t:.0f} s")
    scores = {"opacity": pre.opacities, "lightgaussian": lightgaussian_significance(pre, fit_cams)}
    for b in BUDGETS:
        k = budget_count(b, n)
        for meth, sc in scores.items():
            sels = [ranking_selection(pre, c, sc, k) for c in cams]
            add(meth, "", f"budget={b:g}", None, b,
                [render_subset(pre, c, s.indices, s.opacities).image for c, s in zip(cams, sels)],
                [s.indices.numel() for s in sels])
        if tool is not None and b < 1.0:
            merged = merge_decimate(pre, max(1, k), tool=tool)
            outs = [render_lod(merged, c) for c in cams]
            add("merge", "", f"budget={b:g}", None, b, [o.image for o in outs], [o.n_rendered for o in outs])
    return rows


def markdown(rows: list[dict], max_svs, split: str = "test") -> str:
    out = []
    for name in dict.fromkeys(r["input"] for r in rows):
        rs = [r for r in rows if r["input"] == name]
        inp = next(r for r in rs if r["method"] == "input")
        get = lambda meth, m, b: next((r for r in rs if r["method"] == meth and r["max_sv"] == m  # noqa: E731
                                       and r["budget"] is not None and abs(r["budget"] - b) < 1e-9), None)
        head = ["model", "s_v = 1"] + [fmt_pct(b) for b in TABLE_BUDGETS] + ["at max_sv^-1.5"]
        body = []
        for m in max_svs:
            s1 = next(r for r in rs if r["method"] == "clod" and r["max_sv"] == m and r["s_v"] == 1.0)
            low = min((r for r in rs if r["method"] == "clod_budget" and r["max_sv"] == m
                       and r["budget"] >= m ** -1.5 - 1e-3), key=lambda r: r["budget"])
            cells = [f"{get('clod_budget', m, b)['psnr']:.2f}" for b in TABLE_BUDGETS]
            body.append([f"adapted, max_sv = {m:g}", f"{s1['psnr']:.2f}"] + cells
                        + [f"{low['psnr']:.2f} ({fmt_pct(low['budget'])})"])
        for meth in STATIC:
            if any(r["method"] == meth for r in rs):
                body.append([f"input cut by {meth}", f"{inp['psnr']:.2f}"]
                            + [f"{get(meth, '', b)['psnr']:.2f}" if get(meth, "", b) else "-" for b in TABLE_BUDGETS] + [""])
        views = "validation views" if split == "val" else "test views"
        out += [f"### {LABELS.get(name, name)}: PSNR (dB) on the {views}", "",
                f"Input model {inp['psnr']:.2f} dB, {inp['gaussians']:,.0f} Gaussians in view.", "",
                table(head, body), ""]
    return "\n".join(out)


def plot(rows: list[dict], max_svs, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["input"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(6.2 * len(names), 4.4), squeeze=False)
    for ax, name in zip(axes[0], names):
        rs = [r for r in rows if r["input"] == name]
        for i, m in enumerate(max_svs):
            c = plt.cm.viridis(i / max(len(max_svs) - 1, 1))
            cur = sorted((r for r in rs if r["method"] == "clod_budget" and r["max_sv"] == m), key=lambda r: r["gaussians"])
            ax.plot([r["gaussians"] for r in cur], [r["psnr"] for r in cur], "-o", ms=3.5, color=c,
                    label=f"adapted, max_sv = {m:g}")
            if m > 1:
                ax.axvline(rs[0]["gaussians"] / rs[0]["fraction"] * m ** -1.5, color=c, ls=":", lw=0.9)
        for meth, st in (("opacity", "k--"), ("lightgaussian", "--"), ("merge", "-.")):
            cur = sorted((r for r in rs if r["method"] == meth), key=lambda r: r["gaussians"])
            if cur:
                ax.plot([r["gaussians"] for r in cur], [r["psnr"] for r in cur], st, marker="x", ms=4,
                        label=f"input cut: {meth}", color="0.25" if meth == "opacity" else None)
        inp = next(r for r in rs if r["method"] == "input")
        ax.plot([inp["gaussians"]], [inp["psnr"]], "k*", ms=11, label="input model")
        ax.set_xscale("log")
        ax.set_xlabel("Gaussians drawn per view (mean over the scored views; dotted: max_sv^-1.5)")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(LABELS.get(name, name), fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_sweep(inputs, max_svs, iterations, out_name: str, split: str = "test") -> None:
    lp, note = resolve_lpips("auto")
    print(note)
    tool = find_splat_transform()
    if tool is None:  # a missing peer fails the benchmark instead of vanishing from it
        sys.exit("benchmark: splat-transform not found (`npm ci` in the repository root installs 3.7.0)")
    rows = []
    for name in inputs:
        it = iterations or (400 if name == "demo" else 1000)
        rows += sweep(name, max_svs, it, lp, tool, split=split)
    out_name += split_suffix(split)
    RUNS.mkdir(parents=True, exist_ok=True)
    with open(RUNS / f"{out_name}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    md = markdown(rows, max_svs, split)
    (RUNS / f"{out_name}.md").write_text(md)
    plot(rows, max_svs, RUNS / f"{out_name}.png")
    print(md)
    print(f"wrote {RUNS / out_name}.csv / .md / .png")


def main(default_inputs=("fern",), out_name="max_sv_sweep", default_split="val") -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_inputs_args(ap, default_inputs)
    ap.add_argument("--max-svs", nargs="+", type=float, default=[1, 3, 5, 7])
    ap.add_argument("--iterations", type=int, default=None, help="default: clod-adapt's (1000; demo 400)")
    ap.add_argument("--threads", type=int, default=2)
    add_split_arg(ap, default_split)
    args = ap.parse_args()
    inputs = selected_inputs(args)
    setup_threads(args.threads)
    run_sweep(inputs, [float(m) for m in args.max_svs], args.iterations, out_name, args.split)


if __name__ == "__main__":
    main()
