"""Where the web page's popping differs from ``render_lod``'s: step by step.

For each input (default: fern) the default adaptation's ``clod-export --web`` page is opened in
headless chromium (SwiftShader) at the first test view, and the 31-step ``s_v`` sweep of the
popping measure (:func:`browser.web_viewer_popping`) is taken from the page and through
``render_lod`` (float frames, and the same frames rounded to 8 bits); then one step of 0.001 at
``s_v = 1.5`` (the level of the gains moving) and 4.5 (the level at 1), page against ``render_lod``.
Printed per step: ``s_v``,
the level of the gains, the page's and the CPU's mean |dI|, and the ratios (the page's static
switch over each sweep's largest step). ``--query KEY=VALUE ...`` adds page options (e.g.
``blend=16``: blending in a half-float target)::

    python -m benchmarks.studies.web_popping_steps --inputs fern
    python -m benchmarks.studies.web_popping_steps --inputs fern --query blend=16
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from urllib.parse import urlencode

from benchmarks.common import adapt_cached, load_input, parse_inputs_args, scene_views  # noqa: E402

import torch

from clod_adapter.lod.rankings import lightgaussian_significance
from clod_adapter.lod.draw import render_lod
from clod_adapter.io.load import load_model
from clod_adapter.jobs.eval import image_change
from clod_adapter.train.config import AdaptConfig
from clod_adapter.export.web import find_playcanvas, write_web_viewer

from tests.browser import (browser_missing, chromium_driver, frame_change, open_web_viewer, serve_folder,  # noqa: E402
                     web_viewer_frame, web_viewer_popping)


def run_input(name: str, split: str, query: dict) -> None:
    g = load_model(adapt_cached(name, AdaptConfig(), "default", split=split))
    _, scene, _ = load_input(name, split)
    fit, cams = scene_views(scene, split)
    cam = cams[0]
    with tempfile.TemporaryDirectory(prefix="clod-webpop-") as d, torch.no_grad():
        site = Path(d) / "site"
        write_web_viewer(g, site, cams, lightgaussian_significance(g.with_sigma_d(None), fit))
        driver = chromium_driver(Path(d) / "profile", window=(cam.width + 60, cam.height + 240))
        try:
            with serve_folder(site) as base:
                open_web_viewer(driver, f"{base}/index.html?{urlencode({'w': cam.width, 'h': cam.height, 'cam': 0, **query})}")
                pop = web_viewer_popping(driver, g.lod.max_sv)
                small = []  # the page's change for a step of 0.001 in s_v, while the level moves and after
                for s0 in (1.5, 4.5):
                    a, _ = web_viewer_frame(driver, s_v=s0)
                    b, _ = web_viewer_frame(driver, s_v=s0 + 1e-3)
                    cpu_ab = [render_lod(g, cam, s).image.clamp(0, 1) for s in (s0, s0 + 1e-3)]
                    small.append((s0, frame_change(a, b), image_change(*cpu_ab)))
        finally:
            driver.quit()
        outs = [render_lod(g, cam, s) for s in pop["s_v"]]
    cpu = [o.image.clamp(0, 1) for o in outs]
    q8 = [torch.round(f * 255) / 255 for f in cpu]
    step_cpu = [image_change(a, b) for a, b in zip(cpu, cpu[1:])]
    step_q8 = [image_change(a, b) for a, b in zip(q8, q8[1:])]
    print(f"[{name}] page options {query or 'default'}")
    print(f"[{name}] {cam.name}: static switch {pop['jump']:.5f}; ratio page {pop['ratio']:.2f}, render_lod "
          f"{pop['jump'] / max(step_cpu):.2f}, render_lod in 8 bits {pop['jump'] / max(step_q8):.2f}")
    for s0, page, cpu_d in small:
        print(f"[{name}] s_v {s0} -> {s0 + 1e-3:.3f}: page {page:.5f}, render_lod {cpu_d:.5f} (mean |dI|)")
    print(f"[{name}]   s_v  level (page, render_lod)   page  render_lod  8-bit  page/render_lod   (steps x 1e3)")
    for i, (s, o) in enumerate(zip(pop["s_v"][:-1], outs)):
        print(f"[{name}] {s:5.2f}  {pop['level'][i]:5.3f} {o.level:5.3f}  {1e3 * pop['step'][i]:5.2f}  {1e3 * step_cpu[i]:10.2f}  "
              f"{1e3 * step_q8[i]:5.2f}  {pop['step'][i] / max(step_cpu[i], 1e-12):15.2f}")


def main() -> int:
    a = parse_inputs_args(__doc__, inputs=("fern",), extra=[("--query", {"nargs": "*", "default": [],
                                                                       "help": "page options KEY=VALUE"})])
    why = browser_missing(("selenium",))
    if why or find_playcanvas() is None:
        sys.exit(f"web_popping_steps: {why or 'PlayCanvas engine not found (`npm ci`)'}")
    for name in a.inputs:
        run_input(name, a.split, dict(kv.split("=", 1) for kv in a.query))
    return 0


if __name__ == "__main__":
    sys.exit(main())
