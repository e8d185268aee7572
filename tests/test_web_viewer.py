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
from clod_adapter.viewer.web import DATA_NAME, WEB_STREAMS, find_playcanvas, web_streams
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
    import clod_adapter.viewer.web as web

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


# --- the parent tier (clod_adapter.train.tiers) on the page ----------------------------------------------------
@needs_engine
def test_web_files_of_a_tiered_model(tmp_path):
    from dataclasses import replace

    from test_tiers import _adapted

    from clod_adapter.train import tiers
    from clod_adapter.io.ply import read_ply
    from clod_adapter.io.synthetic import make_cameras
    from clod_adapter.viewer.web import write_web_viewer

    children, parents = _adapted(400, 0), replace(_adapted(60, 1), lod=None)
    parents = replace(parents, lod=replace(children.lod, max_sv=3.0, level_max=1.5))
    g = tiers.attach(children, parents, 2.0, 1.5)
    cams = make_cameras(1, 2)
    names = write_web_viewer(g, tmp_path / "tier", cams, g.opacity_logits)
    assert {"parents.ply", "parents.bin"} <= set(names) and {p.name for p in (tmp_path / "tier").iterdir()} == set(names)
    cfg = json.loads((tmp_path / "tier" / "clod.json").read_text())
    assert cfg["settings"]["tier_s_v"] == 2.0 and cfg["settings"]["tier_start"] == 1.5 and cfg["count"] == 400
    tier = cfg["tier"]
    assert tier["model"] == "parents.ply" and tier["data"] == "parents.bin" and tier["count"] == 60
    assert tier["settings"]["max_sv"] == 3.0 and tier["settings"]["level_max"] == 1.5 and "fade_ramp_s_v" in tier["settings"]
    col = dict(zip(WEB_STREAMS, np.fromfile(tmp_path / "tier" / "parents.bin", dtype=np.float32).reshape(len(WEB_STREAMS), 60)))
    assert np.array_equal(col["sigma_d"], g.parents.sigma_d.numpy()) and np.array_equal(col["z"], g.parents.means[:, 2].numpy())
    assert np.array_equal(col["opacity_gain"], g.parents.opacity_logit_gain.numpy())
    back = read_ply(tmp_path / "tier" / "parents.ply")  # a plain 3DGS model, as model.ply
    assert back.sigma_d is None and back.parents is None and torch.equal(back.means, g.parents.means)
    assert read_ply(tmp_path / "tier" / "model.ply").parents is None
    # without a tier (none, or parents whose settings say none): no tier written, as before
    for k, plain in enumerate((children, replace(g, lod=replace(g.lod, tier_s_v=0.0)))):
        out = tmp_path / f"plain{k}"
        names = write_web_viewer(plain, out, cams, plain.opacity_logits)
        assert "tier" not in json.loads((out / "clod.json").read_text()) and not (out / "parents.ply").exists()
        assert not (out / "parents.bin").exists() and "parents.ply" not in names


#: the tiered page (tiered_web) against render_lod on its two test views (96 x 72): measured 47.7-47.9 dB
#: below the switch (s_v = 1.3), 52.0-52.5 in the cross-fade (1.7, u = 0.56), 54.5-58.8 beyond it (2.2, 3).
#: render_lod of the model without its tier is 16.3-17.7 dB from the tiered one beyond the switch
#: (TIER_APART_DB). The parents' drawn count: 6-7 % under render_lod's n_parents inside their ramp
#: (1.7), 0-3 % beyond (the page counts centres in the frame, render_lod footprints reaching it)
TIER_MIN_PSNR_DB = 40.0
TIER_APART_DB = 30.0


@pytest.fixture(scope="module")
def tiered_web(tmp_path_factory) -> dict:
    """A tiered model of two quick adaptations on a tiny synthetic scene (1,000 Gaussians, 96 x 72
    views): the model (max_sv 2) and, as its parents, every third of its Gaussians (a stand-in for
    merged ones) adapted with max_sv 3, their sigma_d then scaled by 0.7 so that the mask at s_v = 1
    keeps ~60 % of them and their ramp from full detail (lod.ramp_s_v) reaches ~1.6: the cross-fade's
    first frames draw them inside it, as skull's parents are. Switch at s_v = 1.5, the parents
    starting at their s_v = 1.2. Its page is written by write_web_viewer."""
    from conftest import FAST, write_tiny_scene

    from clod_adapter.train import tiers
    from clod_adapter.cli.adapt import main as adapt_main
    from clod_adapter.io.load import load_model, load_scene
    from clod_adapter.io.ply import write_ply
    from clod_adapter.viewer.web import write_web_viewer

    root = tmp_path_factory.mktemp("tierweb")
    scene, ply = write_tiny_scene(root, n=1000, width=96, height=72)
    g = load_model(ply)
    sub = g.subset(torch.arange(0, len(g), 3))
    write_ply(root / "merged.ply", sub)
    for name, src, more in (("model", ply, []), ("parents", root / "merged.ply", ["--max-sv", "3", "--allow-mismatch"])):
        assert adapt_main([str(src), "-s", str(scene), "-o", str(root / name), *FAST, *more]) == 0
    parents = load_model(root / "parents" / "point_cloud.ply")
    model = tiers.attach(load_model(root / "model" / "point_cloud.ply"), parents.with_sigma_d(0.7 * parents.sigma_d), 1.5, 1.2)
    cams = load_scene(scene).test
    write_web_viewer(model, root / "web", cams, model.opacity_logits)
    return {"model": model, "cameras": cams, "web": root / "web"}


@pytest.mark.slow
@needs_engine
def test_tiered_page_in_headless_chromium(tiered_web, tmp_path):
    from dataclasses import replace

    from browser import browser_missing, chromium_driver, compare_frames, open_web_viewer, serve_folder, web_viewer_frame

    from clod_adapter.lod import rule as lod
    from clod_adapter.lod.draw import render_lod

    why = browser_missing(("selenium",))
    if why:
        pytest.skip(f"no headless browser: {why}")
    g, cams = tiered_web["model"], tiered_web["cameras"]
    assert g.lod.max_sv == 2.0 and g.parents.lod.max_sv == 3.0
    svs = (1.3, 1.7, 2.2, 3.0)  # below the switch (1.5), in the cross-fade (to 1.875), beyond
    w, h = cams[0].width, cams[0].height
    driver = chromium_driver(tmp_path / "profile", window=(w + 60, h + 240))
    got = {}
    try:
        with serve_folder(tiered_web["web"]) as base:
            open_web_viewer(driver, f"{base}/index.html?{urlencode({'w': w, 'h': h, 'cam': 0})}")
            sv_max = driver.execute_script("return window.clod.svMax")
            budget_row = driver.execute_script("return getComputedStyle(document.getElementById('budgetrow')).display")
            for i in range(len(cams)):
                driver.execute_script(f"window.clod.setCamera({i})")
                for s in svs:
                    got[i, s] = web_viewer_frame(driver, s_v=s)
                got[i, "static"] = web_viewer_frame(driver, s_v=2.2, static=True)
                got[i, "back"] = web_viewer_frame(driver, s_v=1.3, static=False)  # the model drawn again
    finally:
        driver.quit()
    # the slider reaches 1.2 x the parents' max_sv at their s_v: 1.25 x 1.5 x 1.2 x 3 / 1.2
    assert sv_max == pytest.approx(5.625) and budget_row == "none"  # the budget field: merge trees only
    children = replace(g, parents=None)
    for i, cam in enumerate(cams):
        for s in svs:
            frame, st = got[i, s]
            ref = render_lod(g, cam, s)
            u, s_p = lod.tier_weight(s, g.lod)
            c = compare_frames(ref.image.clamp(0, 1).numpy(), frame)
            print(f"view {i} s_v = {s}: u {u:.3f}, page vs render_lod {c['psnr']:.2f} dB; parents drawn "
                  f"{st['drawnParents']} (render_lod {ref.n_parents}), own {st['drawn']} ({ref.n_rendered - ref.n_parents})")
            assert c["psnr"] >= TIER_MIN_PSNR_DB, (i, s, c)
            assert st["tierU"] == pytest.approx(u, abs=1e-9) and st["parentSv"] == pytest.approx(s_p, rel=1e-9)
            assert abs(st["drawnParents"] - ref.n_parents) <= 0.1 * ref.n_parents, (i, s, st, ref.n_parents)
            own = ref.n_rendered - ref.n_parents
            if u < 1:
                assert own > 0 and abs(st["drawn"] - own) <= 0.1 * own, (i, s, st, own)
            else:
                assert st["drawn"] == 0 and ref.n_parents > 0, (i, s, st)
                alone = render_lod(children, cam, s).image.clamp(0, 1).numpy()
                assert compare_frames(alone, frame)["psnr"] < TIER_APART_DB  # the parents are what is drawn
            if u > 0:  # the parents' ramp: at s_v = 1.7 (theirs 1.36) every parent in view is drawn
                assert (st["parents"]["ramp"] > s_p) == (s < 2.5), (i, s, st["parents"])
        # the static cut: the model's own Gaussians, the parents hidden
        frame, st = got[i, "static"]
        assert st["drawnParents"] == 0 and st["drawn"] > 0 and st["tierU"] == 1.0
        assert compare_frames(got[i, 2.2][0], frame)["psnr"] < TIER_APART_DB
        # below the switch again after the parents alone: the same frame as before
        assert st["static"] is True and got[i, "back"][1]["drawnParents"] == 0
        assert compare_frames(got[i, 1.3][0], got[i, "back"][0])["psnr"] > 60


@pytest.mark.slow
@needs_engine
def test_chain_of_tiers_page_in_headless_chromium(tiered_web, tmp_path):
    """A chain of three tiers (the tiered model's parents with a tier of their own: every second
    parent): the page writes parents_2.ply and draws what render_lod draws in the second
    hand-over and past it, every tier's drawn count summed as render_lod's n_parents."""
    from dataclasses import replace

    from browser import browser_missing, chromium_driver, compare_frames, open_web_viewer, serve_folder, web_viewer_frame

    from clod_adapter.train import tiers
    from clod_adapter.lod.draw import chain_weights, render_lod, tier_chain
    from clod_adapter.viewer.web import write_web_viewer

    why = browser_missing(("selenium",))
    if why:
        pytest.skip(f"no headless browser: {why}")
    g, cams = tiered_web["model"], tiered_web["cameras"]
    p = g.parents
    chain = replace(g, parents=tiers.attach(p, p.subset(torch.arange(0, len(p), 2)), 1.6, 1.2))
    out = tmp_path / "web"
    names = write_web_viewer(chain, out, cams, chain.opacity_logits)
    cfg = json.loads((out / "clod.json").read_text())
    assert "parents_2.ply" in names and cfg["tier"]["tier"]["count"] == len(chain.parents.parents)
    # tier 1 at its own 1.79 (hand-over to tier 2 from 1.6 to 2.0, tier 2 held at 1.2), 2.18, 2.56
    svs = (2.8, 3.4, 4.0)
    w, h = cams[0].width, cams[0].height
    driver = chromium_driver(tmp_path / "profile", window=(w + 60, h + 240))
    got = {}
    try:
        with serve_folder(out) as base:
            open_web_viewer(driver, f"{base}/index.html?{urlencode({'w': w, 'h': h, 'cam': 0})}")
            for s in svs:
                got[s] = web_viewer_frame(driver, s_v=s)
    finally:
        driver.quit()
    settings = [m.lod for m in tier_chain(chain)]
    for s in svs:
        frame, st = got[s]
        ref = render_lod(chain, cams[0], s)
        c = compare_frames(ref.image.clamp(0, 1).numpy(), frame)
        ws = chain_weights(s, settings)
        print(f"chain s_v = {s}: weights {[round(x, 3) for x, _ in ws]}, page vs render_lod {c['psnr']:.2f} dB, "
              f"tiers drawn {st['drawnParents']} (render_lod {ref.n_parents})")
        assert c["psnr"] >= TIER_MIN_PSNR_DB, (s, c)
        assert [t["weight"] for t in st["tiers"]] == pytest.approx([x for x, _ in ws], abs=1e-9)
        assert abs(st["drawnParents"] - ref.n_parents) <= 0.1 * ref.n_parents, (s, st, ref.n_parents)
    assert got[2.8][1]["tiers"][2]["weight"] > 0 and got[4.0][1]["tiers"][2]["weight"] == pytest.approx(1.0)
