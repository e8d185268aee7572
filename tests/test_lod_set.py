"""``clod-export --lod-meta``: the adapted model's levels as a PlayCanvas streamed-SOG LoD set,
built by the pinned splat-transform (3.7.0): splat-transform reads it back with the per-level
counts, and the PlayCanvas engine (npm ``playcanvas``, pinned) in headless chromium draws each
level (not blank, different between levels). Skips with the reason without the tools."""
from __future__ import annotations

import base64
import io
import json
import shutil
import time
from pathlib import Path
from urllib.parse import urlencode

import numpy as np
import pytest

from clod_adapter.export.bake import lod_set_s_vs
from clod_adapter.cli.export import main as export_main
from clod_adapter.io.splat_transform import SPLAT_TRANSFORM_ENV, find_splat_transform, read_info
from clod_adapter.export.web import find_playcanvas, playcanvas_pose
from conftest import err_line

TOOL = find_splat_transform()
needs_tool = pytest.mark.skipif(TOOL is None, reason="splat-transform not found: run `npm ci` in the repository root")
PAGE = Path(__file__).parent / "web" / "lod_set.html"
WAIT_S = 120  # software WebGL on 2 shared cores


def test_level_settings_halve_the_share():
    assert lod_set_s_vs(5.0) == [1.0, 1.5874, 2.5198, 4.0]
    assert lod_set_s_vs(1.0) == [1.0] and lod_set_s_vs(1.5) == [1.0]
    shares = [s ** -1.5 for s in lod_set_s_vs(30.0)]
    assert all(abs(b / a - 0.5) < 1e-3 for a, b in zip(shares, shares[1:]))


def test_lod_set_levels_are_a_trees_tiers_whole_or_the_models_cuts():
    import torch

    from clod_adapter.export.bake import lod_level, lod_set_levels
    from clod_adapter.io.synthetic import make_cameras
    from clod_adapter.lod import tree
    from clod_adapter.train import tiers
    from test_tiers import _adapted

    cams = make_cameras(2, 3)
    t1 = tiers.attach(_adapted(300, 2), _adapted(60, 3), 2.5, 1.5)
    g = tree.build(tiers.attach(_adapted(1200, 0), t1, 2.0, 1.25), cams)
    ts = tree.tiers_of(g)
    levels = lod_set_levels(g, cams, tree_levels="tiers")
    assert [len(lv) for lv, _ in levels] == [len(t) for t in ts] and len(levels) == 3
    assert all(s is None and lv.sigma_d is None for lv, s in levels)
    assert torch.equal(levels[1][0].means, ts[1].means)  # a tier whole, as fitted
    cut = lod_set_levels(g, cams)  # the default: the tree's own cut at the reference distances
    assert len(cut) == 3 and torch.equal(cut[0][0].means, ts[0].means) and cut[0][1] == 1.0
    assert all(0 < len(lv) <= len(t) for (lv, _), t in zip(cut[1:], ts[1:]))  # at most a tier's count
    assert cut[1][1] < cut[2][1] and all(lv.sigma_d is None for lv, _ in cut)
    rows = torch.cat([t.means for t in ts])
    assert all(bool((lv.means[:, None] == rows[None]).all(-1).any(-1).all()) for lv, _ in cut)  # nodes as they are
    with pytest.raises(ValueError, match="tree_levels"):
        lod_set_levels(g, cams, tree_levels="chain")
    plain = _adapted(1200, 0)
    levels = lod_set_levels(plain, cams)
    assert [s for _, s in levels] == lod_set_s_vs(plain.lod.max_sv)
    assert [len(lv) for lv, _ in levels] == [len(lod_level(plain, cams, s)) for s in lod_set_s_vs(plain.lod.max_sv)]


@pytest.fixture(scope="module")
def lod_set(tiny_adapted, tiny_model, tmp_path_factory) -> Path:
    """``clod-export ADAPTED -s SCENE --lod-meta DIR`` (DIR alone: the output folder too)."""
    if TOOL is None:
        pytest.skip("splat-transform not found: run `npm ci` in the repository root")
    out = tmp_path_factory.mktemp("lodset") / "web"
    assert export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "--lod-meta", str(out),
                        "--sog-sh-iterations", "2", "--quiet"]) == 0
    return out


@needs_tool
def test_lod_set_reads_back_with_its_level_counts(lod_set):
    rep = json.loads((lod_set / "export.json").read_text())
    levels = rep["lod_meta"]["levels"]
    counts = [lv["gaussians"] for lv in levels]
    assert [lv["s_v"] for lv in levels] == lod_set_s_vs(2.0)  # the tiny adaptation's max_sv
    assert len(counts) >= 2 and counts == sorted(counts, reverse=True) and counts[-1] < counts[0]
    info = read_info(lod_set / "lod-meta.json")
    assert info["format"] == "lod" and info["numLods"] == len(counts) and info["lodCounts"] == counts
    meta = json.loads((lod_set / "lod-meta.json").read_text())
    assert all((lod_set / f).is_file() for f in meta["filenames"])  # every chunk the index names
    assert "lod-meta.json" in rep["files"] and (lod_set / "point_cloud_clod.ply").is_file()
    assert not [p for p in lod_set.iterdir() if p.name.startswith(".")]  # no staging left


def test_lod_meta_without_the_tool_is_a_one_line_error(tiny_adapted, tiny_model, tmp_path, capfd, monkeypatch):
    monkeypatch.setenv(SPLAT_TRANSFORM_ENV, str(tmp_path / "no-such-tool"))
    out = tmp_path / "web"
    code = export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "--lod-meta", str(out), "--quiet"])
    line = err_line(capfd)
    assert code == 2 and "--lod-meta" in line and "npm ci" in line
    assert not out.exists()


def _frame(driver, url: str) -> tuple[np.ndarray, dict]:
    from PIL import Image
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get(url)
    WebDriverWait(driver, WAIT_S, poll_frequency=0.5).until(
        lambda d: (d.execute_script("return window.__state") or {}).get("phase") in ("ready", "error"))
    state = driver.execute_script("return window.__state")
    assert state["phase"] == "ready", state
    time.sleep(0.5)
    data = driver.execute_script("return document.getElementById('c').toDataURL('image/png')")
    img = Image.open(io.BytesIO(base64.b64decode(data.split(",", 1)[1]))).convert("RGB")
    return np.asarray(img, dtype=np.float32) / 255.0, state


@pytest.mark.slow
@needs_tool
def test_playcanvas_draws_each_level(lod_set, tiny_model, tmp_path):
    from browser import browser_missing, chromium_driver, serve_folder

    from clod_adapter.io.load import load_scene

    why = browser_missing(("selenium",))
    if why:
        pytest.skip(f"no headless browser: {why}")
    engine = find_playcanvas()
    if engine is None:
        pytest.skip("PlayCanvas engine not found: run `npm ci` in the repository root")
    site = tmp_path / "site"
    shutil.copytree(lod_set, site / "set")
    shutil.copy(PAGE, site / "index.html")
    shutil.copy(engine, site / engine.name)
    cam = load_scene(tiny_model["scene"]).train[0]
    pose = playcanvas_pose(cam)
    w, h = 4 * cam.width, 4 * cam.height
    counts = json.loads((lod_set / "export.json").read_text())["lod_meta"]["info"]["lodCounts"]
    frames = []
    driver = chromium_driver(tmp_path / "profile", window=(w + 40, h + 160))
    try:
        with serve_folder(site) as base:
            for level in range(len(counts)):
                q = {"src": "set/lod-meta.json", "level": level, "w": w, "h": h, "fov": pose["fov"],
                     "pos": ",".join(map(str, pose["position"])), "rot": ",".join(map(str, pose["rotation"]))}
                img, state = _frame(driver, f"{base}/index.html?{urlencode(q)}")
                assert state["gsplats"] == counts[level], (level, state)
                frames.append(img)
    finally:
        driver.quit()
    lit = [float((f.max(-1) > 4 / 255).mean()) for f in frames]
    assert min(lit) > 0.05, lit  # every level draws something where the camera looks
    for a, b in zip(frames, frames[1:]):
        assert float(np.abs(a - b).mean()) > 1e-3  # the levels differ


def test_sog_sh_iterations_needs_lod_meta(tiny_adapted, tiny_model, tmp_path, capfd):
    out = tmp_path / "x"
    code = export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "-o", str(out), "--sog-sh-iterations", "2",
                        "--quiet"])
    assert code == 2 and "--sog-sh-iterations applies to --lod-meta only" in err_line(capfd) and not out.exists()
    code = export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "--lod-meta", str(out),
                        "--sog-sh-iterations", "0", "--quiet"])
    assert code == 2 and "--sog-sh-iterations" in err_line(capfd) and not out.exists()
