"""``clod-export --web``: the continuous LoD drawn per frame on the GPU by the PlayCanvas engine in
a static page, tested in headless chromium (SwiftShader: software WebGL on the CPU) on the fern
adaptation: the frame at s_v = 1 against our CPU render of the same camera, frames at s_v = 1, 2, 5
following the drawn count, the popping along a 31-step sweep against one switch between two
static levels, and the browser's frame time along it. The page's own checks (files, data layout,
refusals) run without a browser."""
from __future__ import annotations

import json
import math
import shutil
from urllib.parse import urlencode

import numpy as np
import pytest
import torch

from clod_adapter.cli.export import main as export_main
from clod_adapter.export.web import DATA_NAME, WEB_STREAMS, find_playcanvas, web_streams
from conftest import err_line, shared_path

ENGINE = find_playcanvas()
needs_engine = pytest.mark.skipif(ENGINE is None, reason="PlayCanvas engine not found: run `npm ci` in the repository root")
#: the frame at s_v = 1 against our CPU render (issue 19's goal is 25 dB): measured 35.95 dB on this
#: test's short adaptation, fern's first test view, with gsplat's kernel, its 0.3 px^2 low-pass
#: filter, its Jacobian clamp and no cap on the extent in the engine's splat shaders (26.07 dB with
#: the engine's quarter-size filter, 35.74 with its extent cap)
MIN_PSNR_DB = 33.0
#: the popping ratio (one static switch over the largest step of the 31-step sweep) this test's
#: 300-step adaptation (no tier, the faint left out) must reach in the page: measured 9.99 / 10.13 /
#: 10.07 over three adaptations (render_lod on the same sweep 10.29 / 10.46 / 10.40; the adaptation
#: is not bit-reproducible across runs, and 600 steps gave 9.89 / 10.61), so the floor sits below
#: them. The 10x goal is measured on the default adaptations (benchmarks/quality_vs_time.py,
#: clod-eval; the trained models' pages: benchmarks/studies/web_viewer.py). The page is also held to
#: render_lod's ratio on the same sweep (PAGE_POPPING_SHARE; measured 0.963-0.971).
MIN_POPPING_RATIO = 9.5
PAGE_POPPING_SHARE = 0.95


@needs_engine
def test_web_export_files_and_data(tiny_adapted, tiny_model, tmp_path):
    from clod_adapter.io.load import load_model

    out = tmp_path / "web"
    assert export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "--web", str(out), "--quiet"]) == 0
    names = {"index.html", "clod.mjs", "playcanvas.min.mjs", "model.ply", DATA_NAME, "clod.json", "export.json"}
    assert names <= {p.name for p in out.iterdir()}
    cfg = json.loads((out / "clod.json").read_text())
    g = load_model(tiny_adapted / "point_cloud.ply")
    n = len(g)
    assert cfg["count"] == n and cfg["streams"] == list(WEB_STREAMS) and cfg["settings"]["max_sv"] == g.lod.max_sv
    raw = np.fromfile(out / DATA_NAME, dtype=np.float32).reshape(len(WEB_STREAMS), n)
    col = dict(zip(WEB_STREAMS, raw))
    assert np.array_equal(col["sigma_d"], g.sigma_d.numpy()) and np.array_equal(col["x"], g.means[:, 0].numpy())
    assert sorted(col["static_rank"].tolist()) == list(range(n))  # a permutation
    assert len(cfg["cameras"]) >= 1 and len(cfg["cameras"][0]["K"]) == 4
    assert "<script type=\"module\" src=\"clod.mjs\">" in (out / "index.html").read_text()
    assert json.loads((out / "export.json").read_text())["web"]["dir"] == str(out)


def test_static_rank_follows_the_scores():
    from clod_adapter.io.synthetic import make_ground_truth

    g = make_ground_truth(50, seed=1)
    g = g.with_sigma_d(torch.ones(50))
    scores = torch.rand(50, generator=torch.Generator().manual_seed(0))
    rank = web_streams(g, scores)["static_rank"]
    assert rank[int(scores.argmax())] == 0 and rank[int(scores.argmin())] == 49


def test_web_without_the_engine_is_a_one_line_error(tiny_adapted, tiny_model, tmp_path, capfd, monkeypatch):
    import clod_adapter.export.web as web

    monkeypatch.setattr(web, "find_playcanvas", lambda: None)
    out = tmp_path / "web"
    code = export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "--web", str(out), "--quiet"])
    line = err_line(capfd)
    assert code == 2 and "--web" in line and "npm ci" in line and not out.exists()


@pytest.fixture(scope="module")
def fern_web(tmp_path_factory) -> dict:
    """A short adaptation of fern's checkpoint (300 steps: enough training for the rule to pop
    about 10x less than a static switch, see MIN_POPPING_RATIO) and its ``clod-export --web``
    page."""
    from clod_adapter.cli.adapt import main as adapt_main

    fern = shared_path("fern")
    root = tmp_path_factory.mktemp("fernweb")
    ad = root / "adapted"
    assert adapt_main([str(shared_path("fern", "pretrained")), "-s", str(fern), "-r", "2", "-o", str(ad),
                       "--iterations", "300", "--timing-repeats", "0", "--parent-share", "0", "--quiet"]) == 0
    web = root / "web"
    assert export_main([str(ad), "-s", str(fern), "-r", "2", "--web", str(web), "--quiet"]) == 0
    return {"adapted": ad / "point_cloud.ply", "web": web, "scene": fern}


@pytest.mark.slow
@needs_engine
def test_continuous_lod_in_headless_chromium(fern_web, tmp_path):
    from browser import (browser_missing, chromium_driver, compare_frames, frame_change, open_web_viewer,
                         serve_folder, web_viewer_frame, web_viewer_popping)

    from clod_adapter.lod.draw import render_lod
    from clod_adapter.lod.view import view_lod
    from clod_adapter.io.load import load_model, load_scene

    why = browser_missing(("selenium",))
    if why:
        pytest.skip(f"no headless browser: {why}")
    g = load_model(fern_web["adapted"])
    cam = load_scene(fern_web["scene"], resolution=2).test[0]
    w, h = cam.width, cam.height
    max_sv = g.lod.max_sv
    driver = chromium_driver(tmp_path / "profile", window=(w + 60, h + 240))
    try:
        with serve_folder(fern_web["web"]) as base:
            open_web_viewer(driver, f"{base}/index.html?{urlencode({'w': w, 'h': h, 'cam': 0})}")
            frames, states = {}, {}
            for s in (1.0, 2.0, 5.0):
                frames[s], states[s] = web_viewer_frame(driver, s_v=s)
            _, states[3 * max_sv] = web_viewer_frame(driver, s_v=3 * max_sv, settle=1)
            pop = web_viewer_popping(driver, max_sv)
            engine = driver.execute_script("return window.clod.engine()")
            # ?blend=16: blending in a half-float target (slower, finer), the same rule
            open_web_viewer(driver, f"{base}/index.html?{urlencode({'w': w, 'h': h, 'cam': 0, 'blend': 16})}")
            engine16 = driver.execute_script("return window.clod.engine()")
            frame16, _ = web_viewer_frame(driver, s_v=1.0)
        # the same page for a model whose gains grow past level 1 (LodSettings.level_max = 2)
        web2 = tmp_path / "web_level_max"
        shutil.copytree(fern_web["web"], web2)
        cfg = json.loads((web2 / "clod.json").read_text())
        cfg["settings"]["level_max"] = 2.0
        (web2 / "clod.json").write_text(json.dumps(cfg))
        with serve_folder(web2) as base:
            open_web_viewer(driver, f"{base}/index.html?{urlencode({'w': w, 'h': h, 'cam': 0})}")
            _, state2 = web_viewer_frame(driver, s_v=3 * max_sv, settle=1)
    finally:
        driver.quit()
    # half-float work buffer (the default 8-bit one quantises the level's continuous change) and no
    # size culling; blending in the canvas by default, in a half-float target with ?blend=16
    assert engine["dataFormat"] == "large" and engine["minPixelSize"] == 0, engine
    assert engine["halfFloatBlend"] is False and engine["blendFormat"] is None, engine
    assert engine16["halfFloatBlend"] is True, engine16
    # the page's ramp from full detail is the view's (lod.ramp_s_v; its share from the centres in the frustum)
    assert states[2.0]["ramp"] == pytest.approx(view_lod(g, cam).ramp_s_v, rel=0.02)
    full = compare_frames(render_lod(g, cam, 1.0).image.clamp(0, 1).numpy(), frames[1.0])
    print(f"web vs CPU at s_v = 1: {full['psnr']:.2f} dB")
    assert full["psnr"] >= MIN_PSNR_DB, full
    full16 = compare_frames(render_lod(g, cam, 1.0).image.clamp(0, 1).numpy(), frame16)
    assert full["psnr"] - 0.5 < full16["psnr"] and full16["psnr"] >= MIN_PSNR_DB, (full16, full)
    # the page's level of the gains: lod.level_of_fraction of its drawn share (past the view's
    # ramp, so not scaled down), held at 1 beyond max_sv or growing on up to level_max
    from clod_adapter.lod import rule as lod

    for s, st_, lm in ((5.0, states[5.0], 1.0), (3 * max_sv, states[3 * max_sv], 1.0), (3 * max_sv, state2, 2.0)):
        want = lod.level_of_fraction(st_["drawn"] / st_["inFrustum"], max_sv, lm)
        assert st_["level"] == pytest.approx(want, rel=1e-4, abs=1e-6), (s, lm, st_)
    assert g.lod.level_max == 1.0 and states[3 * max_sv]["level"] == 1.0 and 1.0 < state2["level"] <= 2.0
    drawn = [states[s]["drawn"] for s in (1.0, 2.0, 5.0)]
    assert drawn[0] > drawn[1] > drawn[2] > 0, drawn
    cpu = render_lod(g, cam, 2.0)
    assert abs(states[2.0]["drawn"] - cpu.n_rendered) <= 0.1 * cpu.n_rendered  # the page's count is the rule's
    d12, d15 = frame_change(frames[1.0], frames[2.0]), frame_change(frames[1.0], frames[5.0])
    assert 1e-3 < d12 < d15  # fewer drawn, further from full detail
    print(f"popping: largest step {max(pop['step']):.5f}, static switch {pop['jump']:.5f}, ratio {pop['ratio']:.1f}; "
          f"frame ms along the sweep {min(pop['ms']):.0f}-{max(pop['ms']):.0f}")
    from clod_adapter.jobs.eval import image_change

    sweep = [render_lod(g, cam, s).image.clamp(0, 1) for s in pop["s_v"]]
    cpu_ratio = pop["jump"] / max(image_change(a, b) for a, b in zip(sweep, sweep[1:]))
    print(f"popping ratio: page {pop['ratio']:.2f}, render_lod on the same sweep {cpu_ratio:.2f}")
    assert pop["ratio"] >= MIN_POPPING_RATIO and pop["ratio"] >= PAGE_POPPING_SHARE * cpu_ratio, (pop["ratio"], cpu_ratio)
    assert pop["drawn"] == sorted(pop["drawn"], reverse=True) and all(t > 0 and math.isfinite(t) for t in pop["ms"])


@pytest.mark.slow
@needs_engine
def test_page_draws_splats_larger_than_the_screen(tiny_adapted, tiny_model, tmp_path):
    # a faint Gaussian far larger than the view, around the scene (skull's model has a dark one):
    # render_lod (gsplat) draws it uncapped; the engine caps a quad at the viewport, which squeezed
    # it into a blob (17.9 dB here; skull's test view 49 was 28.8 dB from render_lod). The page
    # lifts the cap and clamps the Jacobian as gsplat does (without the clamp the uncapped engine
    # smeared a thin splat beside skull's view 09 over the frame: benchmarks/studies/web_viewer.py)
    from dataclasses import replace

    from browser import browser_missing, chromium_driver, compare_frames, open_web_viewer, serve_folder, web_viewer_frame

    from clod_adapter.lod.draw import render_lod
    from clod_adapter.io.load import load_model, load_scene
    from clod_adapter.io.ply import write_ply

    why = browser_missing(("selenium",))
    if why:
        pytest.skip(f"no headless browser: {why}")
    g = load_model(tiny_adapted / "point_cloud.ply")
    cam = load_scene(tiny_model["scene"]).test[0]
    centre = g.means.mean(0)
    extent = float((g.means - centre).norm(dim=1).max())
    big = g.subset(torch.zeros(1, dtype=torch.long))
    big = replace(big, means=centre[None].clone(), log_scales=torch.full((1, 3), math.log(20 * extent)),
                  quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]), opacity_logits=torch.full((1,), -1.0),
                  sh0=torch.full((1, 1, 3), 1.0), shN=torch.zeros_like(big.shN),
                  sigma_d=torch.full((1,), 1e3))
    g2 = replace(g, **{k: torch.cat([getattr(g, k), getattr(big, k)]) for k in g.tensors()},
                 extra={k: torch.cat([v, big.extra[k]]) for k, v in g.extra.items()})
    model = tmp_path / "model"
    model.mkdir()
    write_ply(model / "point_cloud.ply", g2)
    web = tmp_path / "web"
    assert export_main([str(model / "point_cloud.ply"), "-s", str(tiny_model["scene"]), "--web", str(web), "--quiet"]) == 0
    w, h = cam.width, cam.height
    driver = chromium_driver(tmp_path / "profile", window=(w + 60, h + 240))
    try:
        with serve_folder(web) as base:
            open_web_viewer(driver, f"{base}/index.html?{urlencode({'w': w, 'h': h, 'cam': 0})}")
            frame, _ = web_viewer_frame(driver, s_v=1.0)
    finally:
        driver.quit()
    ref = render_lod(g2, cam, 1.0).image.clamp(0, 1).numpy()
    alone = render_lod(g, cam, 1.0).image.clamp(0, 1).numpy()
    assert compare_frames(ref, alone)["psnr"] < 25  # the giant veils the frame ...
    got = compare_frames(ref, frame)
    print(f"page vs render_lod with a giant splat: {got['psnr']:.2f} dB")
    assert got["psnr"] >= 33, got  # ... and the page draws it as render_lod does


# --- merged tiers not linked into a merge tree (the tree's page: tests/test_web_tree.py) -------------------
@needs_engine
def test_web_files_of_a_model_whose_tiers_are_not_linked(tmp_path):
    """A model whose merged tiers are attached but not linked into a merge tree: its page is the
    model's own (its tiers are not drawn, so not written), byte for byte the page of the model
    without them but for the settings' hand-over."""
    from test_tiers import _adapted

    from clod_adapter.train import tiers
    from clod_adapter.io.synthetic import make_cameras
    from clod_adapter.export.web import write_web_viewer

    children = _adapted(400, 0)
    g = tiers.attach(children, _adapted(60, 1), 2.0, 1.5)
    cams = make_cameras(1, 2)
    names = write_web_viewer(g, tmp_path / "tier", cams, g.opacity_logits)
    plain = write_web_viewer(children, tmp_path / "plain", cams, children.opacity_logits)
    assert names == plain and {p.name for p in (tmp_path / "tier").iterdir()} == set(names)
    assert not [n for n in names if n.startswith("parents")]
    cfg, ref = (json.loads((tmp_path / d / "clod.json").read_text()) for d in ("tier", "plain"))
    assert "tier" not in cfg and "tree" not in cfg and cfg["count"] == 400 and cfg["settings"]["tier_s_v"] == 2.0
    assert {**cfg, "settings": None} == {**ref, "settings": None}
    for name in ("model.ply", DATA_NAME):
        assert (tmp_path / "tier" / name).read_bytes() == (tmp_path / "plain" / name).read_bytes()
