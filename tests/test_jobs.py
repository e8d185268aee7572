"""The jobs' shared layer (issue 12): model folders, the scene-match check on real pairs, plain-line
logs, interleaved timings, the official output layout, clod-render and the exports' round trips
(their refusals of bad input: tests/test_bad_input.py)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from clod_adapter.cli.adapt import main as adapt_main
from clod_adapter.cli.export import main as export_main
from clod_adapter.io.ply import read_ply
from conftest import FAST, REPO, err_line, shared_path



# --- model folders -------------------------------------------------------------------------------
def test_model_folder_latest_iteration_is_used(tiny_adapted, tiny_model):
    m = json.loads((tiny_adapted / "metrics.json").read_text())
    assert m["input_ply"].endswith(os.path.join("iteration_30", "point_cloud.ply"))


def test_resolve_model_path_cases(tiny_model, tmp_path):
    from clod_adapter.io.load import resolve_model_path
    from clod_adapter.io.ply import PlyFormatError

    model = tiny_model["model"]
    assert resolve_model_path(model) == model / "point_cloud" / "iteration_30" / "point_cloud.ply"
    assert resolve_model_path(model, 10) == model / "point_cloud" / "iteration_10" / "point_cloud.ply"
    with pytest.raises(PlyFormatError, match="iteration_7/.*iterations: 10, 30"):
        resolve_model_path(model, 7)
    it_dir = model / "point_cloud" / "iteration_10"
    assert resolve_model_path(it_dir) == it_dir / "point_cloud.ply"  # a folder holding one .ply
    two = tmp_path / "two"
    two.mkdir()
    shutil.copy(tiny_model["ply"], two / "a.ply")
    shutil.copy(tiny_model["ply"], two / "b.ply")
    with pytest.raises(PlyFormatError, match="is a folder, expected .* 2 model files"):
        resolve_model_path(two)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(PlyFormatError, match="is a folder, expected a .ply file"):
        resolve_model_path(empty)


def test_real_official_model_folder():
    """fern/pretrained is an official -m folder: its latest iteration and training size."""
    from clod_adapter.io.load import resolve_model_path, training_size
    from clod_adapter.jobs.adapt_inputs import resolution_note

    folder = shared_path("fern", "pretrained")
    ply = resolve_model_path(folder)
    assert ply == folder / "point_cloud" / "iteration_7000" / "point_cloud.ply"
    assert training_size(ply) == (497, 372)
    assert resolution_note(training_size(ply), (497, 372), "x") is None
    note = resolution_note(training_size(ply), (124, 93), "cameras.json")
    assert note is not None and "trained at 497x372" in note and "124x93" in note and "alias" in note


# --- the scene-match check ------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("which,resolution", [("pretrained", 2), ("pretrained", 8), ("maskgaussian", 2)])
def test_real_pairs_match(which, resolution):
    """The check cannot misfire on fern's own checkpoints, even at a resolution it was not trained at."""
    import torch

    from clod_adapter.io.load import load_model, resolve_model_path
    from clod_adapter.io.load import load_scene
    from clod_adapter.jobs.adapt_inputs import MISMATCH_MARGIN_DB, scene_match

    g = load_model(resolve_model_path(shared_path("fern", which)))
    scene = load_scene(shared_path("fern"), resolution=resolution)
    imgs = [scene.load_image(c) for c in scene.train]
    with torch.no_grad():
        m = scene_match(g, scene.train, imgs, background=(0.0, 0.0, 0.0))
    assert m["margin_db"] > MISMATCH_MARGIN_DB + 4.0, m
    assert m["in_view_fraction"] > 0.9


def test_synthetic_scene_matches(tiny_model):
    import torch

    from clod_adapter.io.colmap import load_colmap_scene
    from clod_adapter.jobs.adapt_inputs import MISMATCH_MARGIN_DB, scene_match

    scene = load_colmap_scene(tiny_model["scene"])
    with torch.no_grad():
        m = scene_match(read_ply(tiny_model["ply"]), scene.train, [scene.load_image(c) for c in scene.train],
                        background=(0.0, 0.0, 0.0))
    assert m["margin_db"] > MISMATCH_MARGIN_DB + 4.0, m


# --- logs ------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_non_tty_log_has_plain_lines(tiny_model, tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "clod_adapter.cli.adapt", str(tiny_model["ply"]), "--images", str(tiny_model["scene"]),
                        "-o", str(out), "--iterations", "20", "--max-sv", "2", "--timing-repeats", "1"],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "\r" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("clod-adapt: ") and " it (" in ln]
    assert len(lines) == 10, r.stderr  # one every 10 %
    assert lines[-1].startswith("clod-adapt: 20/20 it (100 %)")
    assert "frac=" in lines[-1] and "eta=" not in r.stderr


def test_line_progress_every_ten_percent():
    import io

    from clod_adapter.jobs import LineProgress, progress_bar

    buf = io.StringIO()
    bar = progress_bar(37, "job", file=buf)
    assert isinstance(bar, LineProgress)  # a StringIO is not a terminal
    for _ in range(37):
        bar.set_postfix(frac="0.5")
        bar.update(1)
    bar.close()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 10 and lines[-1].startswith("job: 37/37 it (100 %)") and "frac=0.5" in lines[-1]


def test_line_progress_nested_and_slow_stays_one_line_per_ten_percent():
    """A bar opened inside another (clod-eval's ceiling inside its render bar) writes no cursor
    moves, and tqdm's monitor thread, which drops ``miniters`` to 1 for a bar that has not
    printed for ``maxinterval`` seconds, never fires for a log bar."""
    import io

    from clod_adapter.jobs import progress_bar

    buf = io.StringIO()
    outer = progress_bar(10, "outer", file=buf)
    inner = progress_bar(50, "inner", file=buf)
    assert inner.maxinterval == float("inf")  # (cur_t - last_print_t) >= maxinterval: never
    for _ in range(50):
        inner.update(1)
    inner.close()
    outer.update(1)
    outer.close()
    text = buf.getvalue()
    assert "\x1b" not in text and "[A" not in text
    inner_lines = [ln for ln in text.splitlines() if ln.startswith("inner:")]
    assert len(inner_lines) == 10 and inner_lines[-1].startswith("inner: 50/50 it (100 %)")


# --- messages --------------------------------------------------------------------------------------
def test_help_has_an_example_and_every_flag_has_help(capsys):
    from clod_adapter.cli import adapt, eval as eval_cli, export, render

    for mod in (adapt, eval_cli, export, render):
        p = mod.build_parser()
        assert "example:" in p.format_help() and "--version" in p.format_help()
        for a in p._actions:
            assert a.help, (mod.__name__, a.option_strings)
    with pytest.raises(SystemExit):
        adapt_main(["--help"])
    out = capsys.readouterr().out
    assert "example:" in out and "-s" in out and "--model_path" in out
    with pytest.raises(SystemExit):
        adapt_main(["--version"])
    assert "clod-adapt 0." in capsys.readouterr().out


def test_clod_adapt_flag_defaults_are_the_configs():
    """Every clod-adapt flag with a literal default that names an AdaptConfig field has the
    config's default (``--max-sv`` 5, ``--recovery-steps`` 1000, ...): the two cannot drift."""
    import dataclasses

    from clod_adapter.cli import adapt
    from clod_adapter.train.config import AdaptConfig

    cfg, fields = AdaptConfig(), {f.name for f in dataclasses.fields(AdaptConfig)}
    checked = []
    for a in adapt.build_parser()._actions:
        if a.dest in fields and a.default is not None and a.dest != "background":  # a colour name, parsed later
            assert a.default == getattr(cfg, a.dest), (a.dest, a.default, getattr(cfg, a.dest))
            checked.append(a.dest)
    assert {"max_sv", "level_max", "keep_share", "recovery_steps"} <= set(checked)


# --- timings ---------------------------------------------------------------------------------------
def test_time_interleaved_rounds_and_order():
    from types import SimpleNamespace

    from clod_adapter.evaluate.timing import time_interleaved

    calls = []

    def job(name, ms):
        def f():
            calls.append(name)
            return SimpleNamespace(select_ms=1.0, raster_ms=ms)
        return f

    res = time_interleaved({"a": [job("a", 10.0), job("a", 30.0)], "b": [job("b", 5.0)]}, repeats=4, warmup=1)
    assert calls.count("a") == 2 * 5 and calls.count("b") == 5
    first_b = calls.index("b")
    assert first_b < calls.count("a")  # interleaved: b runs before all of a's renders are done
    assert res["a"]["ms_total"] == pytest.approx(21.0) and res["b"]["ms_total"] == pytest.approx(6.0)
    # every round times the same 21 ms per frame: the spread over rounds is none
    assert res["a"]["ms_total_min"] == pytest.approx(21.0) and res["a"]["ms_total_max"] == pytest.approx(21.0)
    assert res["a"]["per_view"][1]["ms_raster"] == pytest.approx(30.0)
    # a LodRender's lead_ms (a plain frame's projection and its selection) is read in place of select_ms
    lead = time_interleaved({"p": [lambda: SimpleNamespace(select_ms=1.0, lead_ms=4.0, raster_ms=10.0)]}, repeats=2)
    assert lead["p"]["ms_select"] == pytest.approx(4.0) and lead["p"]["ms_total"] == pytest.approx(14.0)


def test_metrics_timing_spread(tiny_adapted):
    m = json.loads((tiny_adapted / "metrics.json").read_text())
    assert m["timing"]["method"] == "interleaved"
    for d in [m["input_model"]] + m["levels"]:
        assert 0 < d["ms_per_frame_min"] <= d["ms_per_frame"] <= d["ms_per_frame_max"] < 1e4


# --- outputs ---------------------------------------------------------------------------------------
def test_outputs_and_inria_layout(tiny_adapted, tiny_model):
    from clod_adapter.io.load import resolve_model_path

    names = {p.name for p in tiny_adapted.iterdir()}
    assert {"point_cloud.ply", "metrics.json", "lod_strip.png", "training.png", "cameras.json", "cfg_args",
            "point_cloud"} <= names
    plain = tiny_adapted / "point_cloud" / "iteration_32" / "point_cloud.ply"  # input iteration 30 + 2 steps
    g = read_ply(plain)
    faint = json.loads((tiny_adapted / "metrics.json").read_text())["faint"]
    assert g.sigma_d is None and len(g) == 300 - faint["left_out"]  # exact INRIA layout (SIBR reads a fixed struct)
    cams = json.loads((tiny_adapted / "cameras.json").read_text())
    assert len(cams) == 10 and {"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"} <= set(cams[0])
    assert (cams[0]["width"], cams[0]["height"]) == (64, 48)
    assert "source_path=" in (tiny_adapted / "cfg_args").read_text()
    # the clod tools take the output folder and use the extended file, not the plain copy
    assert resolve_model_path(tiny_adapted, prefer="point_cloud.ply") == tiny_adapted / "point_cloud.ply"
    strip = Image.open(tiny_adapted / "lod_strip.png")
    assert strip.width >= 3 * 240  # ground truth + s_v = 1, 2, each enlarged to >= 240 px


def test_clod_render_views_and_video(tiny_adapted, tiny_model, tmp_path, capsys):
    ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="clod-render's MP4 needs the [video] extra (imageio-ffmpeg)")

    from clod_adapter.cli.render import main as render_main

    out = tmp_path / "render"
    code = render_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "-o", str(out), "--frames", "12",
                        "--path", "orbit", "--quiet"])
    assert code == 0, capsys.readouterr().err
    assert sorted(p.name for p in (out / "views").iterdir()) == ["view000.png", "view008.png"]
    n_frames, secs = ffmpeg.count_frames_and_secs(str(out / "lod_orbit.mp4"))
    assert n_frames == 12 and secs == pytest.approx(12 / 30, abs=0.05)
    rep = json.loads((out / "render.json").read_text())
    assert max(rep["video"]["s_v"]) == pytest.approx(2.0, abs=0.05) and min(rep["video"]["s_v"]) == 1.0
    assert np.isfinite([v["psnr"] for v in rep["views"]]).all()
    # a model with a merge tree: the sweep goes on (in ln s_v) to where its last tier reaches max_sv
    import torch

    from clod_adapter.io.load import load_scene
    from clod_adapter.io.ply import write_ply
    from clod_adapter.lod import tree
    from clod_adapter.train import tiers

    g = read_ply(tiny_adapted / "point_cloud.ply")
    linked = tree.build(tiers.attach(g, g.subset(torch.arange(0, len(g), 5)), 2.0, 1.0),
                        load_scene(tiny_model["scene"]).train)
    tiered = write_ply(tmp_path / "tiered.ply", linked)
    out = tmp_path / "render_tier"
    assert render_main([str(tiered), "-s", str(tiny_model["scene"]), "-o", str(out), "--frames", "8", "--quiet"]) == 0
    vid = json.loads((out / "render.json").read_text())["video"]
    top = g.lod.max_sv * 1.25 * 2.0 / 1.0  # the last tier at max_sv (tier_reach: tier_fade 1.25 x 2 / 1)
    assert max(vid["s_v"]) == pytest.approx(top) and min(vid["s_v"]) == 1.0
    assert vid["s_v"][2] == pytest.approx(top ** 0.5)  # a quarter of the way: sqrt of the top


def test_export_spz_round_trip(tiny_adapted, tiny_model, tmp_path):
    """--spz through gsply (optional extra [spz]: numba + llvmlite, ~300 MB, so not in [test])."""
    gsply = pytest.importorskip("gsply", reason="clod-export --spz needs the [spz] extra (gsply)")
    out = tmp_path / "exp"
    assert export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "-o", str(out), "--spz", "--quiet"]) == 0
    spz = out / "point_cloud_clod.spz"
    assert spz.stat().st_size < (out / "point_cloud_clod.ply").stat().st_size / 3
    back = gsply.read_spz(spz)
    g = read_ply(out / "point_cloud_clod.ply")
    assert np.abs(np.asarray(back.means) - g.means.numpy()).max() < 1e-3  # 12 fractional bits
    assert back.shN.shape[0] == len(g)


def test_tensorboard_flag(tiny_model, tmp_path, capfd):
    out = tmp_path / "out"
    args = [str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), "-o", str(out), "--tensorboard", *FAST]
    try:
        import torch.utils.tensorboard  # noqa: F401
    except Exception:
        assert adapt_main(args) == 2
        assert "--tensorboard: the tensorboard package is not installed" in err_line(capfd)
        assert not out.exists()
        return
    assert adapt_main(args) == 0
    assert any((out / "tensorboard").iterdir())


def test_level_max_flag_reaches_the_model_header(tiny_model, tmp_path):
    from clod_adapter.io.load import load_model

    out = tmp_path / "lm"
    assert adapt_main([str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), "-o", str(out),
                       "--level-max", "2", *FAST]) == 0
    g = load_model(out / "point_cloud.ply")
    assert g.lod.level_max == 2.0 and g.lod.max_sv == 2.0
