"""The continuous LoD in the browser (``clod-export --web``), measured in headless chromium.

For each input (default: fern and skull) this writes the web page of the default adaptation
(cached, common.py; the static cut ranked by LightGaussian significance on the fit views, as
``clod-export --web`` does), opens it in Debian's chromium with SwiftShader (software WebGL: the
frame time is a CPU proxy for fill cost, not a GPU figure) at each evaluation view's size and
intrinsics, and measures against our CPU renderer (``render_lod``) of the same camera:

* the frame at ``s_v = 1`` (PSNR, every evaluation view; goal >= 25 dB);
* the frames at ``s_v = 1, 2, 5``: the page's drawn count and PSNR against ``render_lod``;
* popping (the first view): 31 frames at ``s_v`` from 1 to max_sv (linear, as ``clod-eval``),
  the largest frame-to-frame mean |dI| against one switch between the page's static cuts at the
  first and last counts (goal: ratio >= 10), beside the same sweep on the CPU; a merge tree's page
  (no static cut) along ``clod-eval``'s ``s_v`` sweep through every tier and along count budgets
  from 100 % to 1 % of tier 0's centres in view (the page's budget field), 31 frames each, against
  :func:`clod_adapter.evaluate.popping.popping_curve`'s switch (the input cut by LightGaussian
  significance), beside ``render_lod`` on the same sweeps (:func:`tree_popping`);
* the page's frame time along the ``s_v`` sweep (median of its last 30 frames after each step);
* what blending in half floats (``?blend=16``) costs and buys: the page's frame time at ``s_v = 1``
  and max_sv with it and without (the default: straight to the 8-bit canvas), interleaved rounds,
  each one's frame at ``s_v = 1`` against ``render_lod``, and its popping ratio on the first view.

``--full-detail-only`` measures only the frames at ``s_v = 1`` (every view; a few minutes), and
``--config KEY=VALUE`` draws the adaptation with those ``AdaptConfig`` settings (cached as
``quality_vs_time.py --config`` caches it; at ``s_v = 1`` every adaptation is the input).

Writes ``runs/bench/web_viewer{_val}/summary.md``, ``docs/web_viewer.png`` (the first view of the
first input at s_v = 1, 2, 5 and the static cut at s_v = 5's count) and ``docs/web_viewer_page.png``
(the page at s_v = 2, its panel included). Exits 1 when a goal is missed::

    python -m benchmarks.studies.web_viewer                 # fern and skull, test views
    python -m benchmarks.studies.web_viewer --split val     # validation views (the --holdout-val adaptations)
    python -m benchmarks.studies.web_viewer --full-detail-only --config level_max=2
"""
from __future__ import annotations

import statistics
import sys
import tempfile
from pathlib import Path
from typing import Optional
from urllib.parse import urlencode

from benchmarks.common import REPO, RUNS, adapt_cached, load_input, parse_config, parse_inputs_args, scene_views, split_suffix  # noqa: E402

import numpy as np
import torch

from clod_adapter.evaluate.popping import BUDGET_LOWEST, popping_curve, popping_sweep
from clod_adapter.lod.budget import Budget
from clod_adapter.lod.rankings import lightgaussian_significance
from clod_adapter.lod.draw import render_lod, tier_reach
from clod_adapter.lod.tree import is_tree
from clod_adapter.io.load import load_model
from clod_adapter.jobs.eval import image_change
from clod_adapter.train.config import AdaptConfig
from clod_adapter.export.web import find_playcanvas, write_web_viewer

from tests.browser import (browser_missing, chromium_driver, compare_frames, open_web_viewer,  # noqa: E402
                     serve_folder, web_viewer_frame, web_viewer_popping)

MIN_PSNR_DB = 25.0
MIN_POPPING_RATIO = 10.0
LEVELS = (1.0, 2.0, 5.0)
#: frames of a merge tree's popping sweeps in the page (``clod-eval``'s ``s_v`` sweep has 61)
POP_STEPS = 31


def cpu_popping(g, cam, max_sv: float, steps: int = 31) -> float:
    """The largest step (mean |dI|) of the same sweep through ``render_lod``; the CPU ratio is the
    page's static switch over it."""
    frames = [render_lod(g, cam, 1.0 + (max_sv - 1.0) * i / (steps - 1)).image for i in range(steps)]
    return max(image_change(a, b) for a, b in zip(frames, frames[1:]))


def tree_popping(driver, g, base, sig, cam) -> dict:
    """A merge tree's popping in the page from its current camera, along ``s_v`` (``clod-eval``'s
    sweep through every tier, :func:`clod_adapter.evaluate.popping.popping_sweep`, 31 frames) and
    along count budgets (31 log-spaced shares of tier 0's centres in view, 100 % to 1 %): the
    largest step of the page's frames and of ``render_lod``'s on the same sweep, each against the
    one static switch of :func:`clod_adapter.evaluate.popping.popping_curve` (``base`` cut by
    LightGaussian significance ``sig`` at the sweep's first and last counts).

    Returns:
        the ``s_v`` sweep's dict (``ratio``: the page's; ``cpu_ratio``, ``cpu_max_step``:
        ``render_lod``'s; ``jump``, ``step`` [30], ``ms`` [31], ``drawn`` [31], ``s_vs`` [31]) with
        the budget sweep's under ``"budget"`` (``s_vs``: the budgets, nodes in view)."""
    out = {}
    s_vs = popping_sweep(g.lod.max_sv, tier_reach(g), POP_STEPS)
    _, st = web_viewer_frame(driver, s_v=1.0)
    shares = [float(x) for x in np.geomspace(1.0, BUDGET_LOWEST, POP_STEPS)]
    for what, kw, page_kw in (("s_v", {}, {"s_vs": s_vs}),
                              ("budget", {"budgets": True}, {"budgets": [Budget(in_view=x).of(len(g), st["inFrustum"])
                                                                         for x in shares]})):
        cpu = popping_curve(g, cam, shares if kw else s_vs, discrete_model=base, discrete_scores=sig, **kw)
        page = web_viewer_popping(driver, g.lod.max_sv, **page_kw)
        jump = cpu["discrete_max"]
        out[what] = {"ratio": jump / max(max(page["step"]), 1e-12), "cpu_ratio": cpu["ratio"], "jump": jump,
                     "cpu_max_step": cpu["continuous_max"], "step": page["step"], "ms": page["ms"],
                     "drawn": page["drawn"], "s_vs": page["s_v"]}
    return {**out["s_v"], "budget": out["budget"]}


def run_input(name: str, split: str, log, shots: list, config: dict, tag: str = "default",
              full_only: bool = False) -> dict:
    ply = adapt_cached(name, AdaptConfig(**config), tag, split=split, log=log)
    inp, scene, _ = load_input(name, split)
    fit, cams = scene_views(scene, split)
    g = load_model(ply)
    sig = lightgaussian_significance(inp, fit) if is_tree(g) else None
    max_sv = g.lod.max_sv
    res = {"name": name, "views": [], "n": len(g)}
    with tempfile.TemporaryDirectory(prefix="clod-web-") as d, torch.no_grad():
        site = Path(d) / "site"
        write_web_viewer(g, site, cams, lightgaussian_significance(g.with_sigma_d(None), fit))
        w0, h0 = cams[0].width, cams[0].height
        driver = chromium_driver(Path(d) / "profile", window=(w0 + 60, h0 + 240))
        try:
            with serve_folder(site) as base:
                for i, cam in enumerate(cams):
                    open_web_viewer(driver, f"{base}/index.html?{urlencode({'w': cam.width, 'h': cam.height, 'cam': i})}")
                    row = {"view": cam.name}
                    first = i == 0 and not shots and not full_only  # the figure: the first view of the first input
                    for s in LEVELS[:1] if full_only else LEVELS:
                        img, st = web_viewer_frame(driver, s_v=s)
                        cpu = render_lod(g, cam, s)
                        row[s] = {"psnr": compare_frames(cpu.image.clamp(0, 1).numpy(), img)["psnr"],
                                  "drawn": st["drawn"], "cpu_drawn": cpu.n_rendered}
                        if first:
                            shots.append((f"s_v = {s:g}: {st['drawn']:,} drawn", img))
                    if first and is_tree(g):
                        k = row[5.0]["drawn"]
                        img, st = web_viewer_frame(driver, budget=k)
                        shots.append((f"budget {k:,} in view: s_v {st['sv']:.2f}", img))
                        web_viewer_frame(driver, s_v=2.0)
                        driver.save_screenshot(str(REPO / "docs" / "web_viewer_page.png"))
                    elif first:
                        img, st = web_viewer_frame(driver, s_v=5.0, static=True)
                        shots.append((f"static cut, {st['drawn']:,} drawn", img))
                        web_viewer_frame(driver, s_v=2.0, static=False)
                        driver.save_screenshot(str(REPO / "docs" / "web_viewer_page.png"))
                    if i == 0 and not full_only and is_tree(g):
                        res["popping"] = tree_popping(driver, g, inp, sig, cam)
                    elif i == 0 and not full_only:
                        pop = web_viewer_popping(driver, max_sv)
                        res["popping"] = {k: pop[k] for k in ("step", "jump", "ratio", "ms", "drawn")}
                        res["popping"]["cpu_max_step"] = cpu_popping(g, cam, max_sv)
                    res["views"].append(row)
                    log(f"[{name}] {cam.name}: s_v=1 {row[1.0]['psnr']:.2f} dB vs render_lod")
                if full_only:
                    return res
                cam = cams[0]
                pop = res["popping"]
                res["blend"] = blend_cost(driver, f"{base}/index.html?{urlencode({'w': cam.width, 'h': cam.height, 'cam': 0})}",
                                          render_lod(g, cam, 1.0).image.clamp(0, 1).numpy(), max_sv,
                                          tree_sweep=(pop["s_vs"], pop["jump"]) if is_tree(g) else None)
                b = res["blend"]
                log(f"[{name}] blending: frame ms s_v = 1 / max_sv, half-float target {b['16f'][0]:.0f} / {b['16f'][1]:.0f}, "
                    f"8-bit canvas {b['8'][0]:.0f} / {b['8'][1]:.0f}; s_v = 1 vs render_lod {b['psnr16f']:.2f} / {b['psnr8']:.2f} dB; "
                    f"popping with the half-float target {b['ratio16f']:.1f}")
        finally:
            driver.quit()
    return res


def blend_cost(driver, url: str, ref: np.ndarray, max_sv: float, rounds: int = 3, settle: int = 30,
               tree_sweep: Optional[tuple] = None) -> dict:
    """The page's frame time drawn straight to its 8-bit canvas (the default) and with ``?blend=16``
    (blending in a half-float target): median over ``rounds`` interleaved rounds of the page's own median frame
    time after ``settle`` frames at ``s_v = 1`` and at max_sv; and each frame at ``s_v = 1``
    against ``ref`` (render_lod's, [H, W, 3] in [0, 1]); then the popping ratio with ``?blend=16``
    (a merge tree: ``tree_sweep`` = (its ``s_v`` sweep, the static switch's mean |dI|))."""
    ms: dict = {"16f": ([], []), "8": ([], [])}
    psnr = {}
    for _ in range(rounds):
        for mode in ("16f", "8"):
            open_web_viewer(driver, url + ("&blend=16" if mode == "16f" else ""))
            for j, s in enumerate((1.0, max_sv)):
                img, st = web_viewer_frame(driver, s_v=s, settle=settle)
                ms[mode][j].append(st["frameMs"])
                if j == 0:
                    psnr[mode] = compare_frames(ref, img)["psnr"]
    open_web_viewer(driver, url + "&blend=16")
    if tree_sweep is None:
        ratio16 = web_viewer_popping(driver, max_sv)["ratio"]
    else:
        ratio16 = tree_sweep[1] / max(max(web_viewer_popping(driver, max_sv, s_vs=tree_sweep[0])["step"]), 1e-12)
    return {"16f": [statistics.median(x) for x in ms["16f"]], "8": [statistics.median(x) for x in ms["8"]],
            "psnr16f": psnr["16f"], "psnr8": psnr["8"], "ratio16f": ratio16}


def figure(shots: list, path: Path, split: str = "test") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(shots), figsize=(3.2 * len(shots), 2.6))
    for ax, (title, img) in zip(np.atleast_1d(axes), shots):
        ax.imshow(img)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle("clod-export --web: PlayCanvas in headless chromium (SwiftShader), "
                 f"fern {'validation' if split == 'val' else 'test'} view", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    a = parse_inputs_args(__doc__, argv, extra=(
        ("--full-detail-only", {"action": "store_true", "help": "only the frames at s_v = 1, every view"}),
        ("--config", {"nargs": "*", "default": [], "metavar": "KEY=VALUE", "help": "AdaptConfig settings"})))
    config, tag = parse_config(a.config)
    why = browser_missing(("selenium",))
    if why or find_playcanvas() is None:
        sys.exit(f"web_viewer: {why or 'PlayCanvas engine not found (`npm ci`)'}")
    log = lambda *x: print(*x, flush=True)  # noqa: E731
    shots: list = []
    results = [run_input(n, a.split, log, shots, config, tag, a.full_detail_only) for n in a.inputs]
    if a.full_detail_only:
        lines = ["| input | views | s_v = 1 PSNR vs render_lod, each view | min / median |", "|---|---:|---|---|"]
        p1s = []
        for r in results:
            p1 = [v[1.0]["psnr"] for v in r["views"]]
            p1s.append(min(p1))
            lines.append(f"| {r['name']} | {len(p1)} | " + " / ".join(f"{p:.2f}" for p in p1)
                         + f" | {min(p1):.2f} / {statistics.median(p1):.2f} |")
        print("\n".join(lines))
        met = sum(p >= MIN_PSNR_DB for p in p1s)
        print(f"goal (PSNR >= {MIN_PSNR_DB} dB on every view): {met} of {len(results)} inputs met")
        return 0 if met == len(results) else 1
    lines, missed = [], 0
    lines += ["| input | views | s_v = 1 PSNR vs render_lod (min / median) | s_v = 2 | s_v = 5 | drawn s_v = 1 / 2 / 5 "
              "(page; render_lod) | popping ratio (CPU same sweep) | frame ms along the sweep | "
              "blending: frame ms s_v = 1 / max_sv and s_v = 1 PSNR, ?blend=16 (half-float target, and its popping ratio); default 8-bit canvas |",
              "|---|---:|---|---|---|---|---|---|---|"]
    for r in results:
        p1 = [v[1.0]["psnr"] for v in r["views"]]
        med = {s: statistics.median(v[s]["psnr"] for v in r["views"]) for s in LEVELS}
        v0 = r["views"][0]
        pop, b = r["popping"], r["blend"]
        cpu_ratio = pop["jump"] / max(pop["cpu_max_step"], 1e-12)
        bud = pop.get("budget")
        ok = (min(p1) >= MIN_PSNR_DB and pop["ratio"] >= MIN_POPPING_RATIO
              and (bud is None or bud["ratio"] >= MIN_POPPING_RATIO))
        missed += not ok
        lines.append(f"| {r['name']} | {len(r['views'])} | {min(p1):.2f} / {med[1.0]:.2f} | {med[2.0]:.2f} | "
                     f"{med[5.0]:.2f} | " + " / ".join(f"{v0[s]['drawn']:,}" for s in LEVELS) + "; "
                     + " / ".join(f"{v0[s]['cpu_drawn']:,}" for s in LEVELS)
                     + f" | {pop['ratio']:.1f} (largest step {max(pop['step']):.4f}, switch {pop['jump']:.4f}; "
                     f"CPU {cpu_ratio:.1f})"
                     + ("" if bud is None else f"; along count budgets {bud['ratio']:.1f} (CPU {bud['cpu_ratio']:.1f})")
                     + f" | {pop['ms'][0]:.0f} -> {pop['ms'][-1]:.0f} (min {min(pop['ms']):.0f}) | "
                     f"{b['16f'][0]:.0f} / {b['16f'][1]:.0f} ms, {b['psnr16f']:.2f} dB, popping {b['ratio16f']:.1f}; "
                     f"{b['8'][0]:.0f} / {b['8'][1]:.0f} ms, {b['psnr8']:.2f} dB |")
    out = RUNS / f"web_viewer{split_suffix(a.split)}"
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    if shots:
        figure(shots, REPO / "docs" / "web_viewer.png", a.split)
    print("\n".join(lines))
    print(f"goals (PSNR >= {MIN_PSNR_DB} dB on every view, popping ratio >= {MIN_POPPING_RATIO}): "
          f"{len(results) - missed} of {len(results)} inputs met")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
