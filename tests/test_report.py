"""clod-eval: baselines render exactly k Gaussians, the popping measurement, the report's CSV
schema and outputs on a tiny synthetic scene, and the CLI's bad-input handling."""
import csv
import json
import math

import numpy as np
import pytest
import torch

from clod_adapter.cli.eval import main
from clod_adapter.lod.rankings import constant_sigma_selection, lightgaussian_significance, random_scores, ranking_selection, render_subset, volume_factor
from clod_adapter.io.ply import write_ply
from clod_adapter.io.colmap import load_colmap_scene, write_colmap_scene
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import in_view
from clod_adapter.jobs.eval import CSV_COLUMNS, OUTPUT_NAMES, PER_VIEW_COLUMNS, EvalOptions, evaluate_report, popping_curve
from clod_adapter.jobs.eval_methods import BASELINES
from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb
from clod_adapter.lod.budget import Budget
from conftest import uint8_views


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Pretrained stand-in, an "adapted" copy with a random sigma_d, a written COLMAP scene."""
    root = tmp_path_factory.mktemp("eval")
    gt = make_ground_truth(600, seed=3)
    cams = make_cameras(2, 5, width=48, height=36)  # llffhold 8: 2 test views, 8 train
    imgs = uint8_views(gt, cams)
    write_colmap_scene(root / "scene", cams, imgs)
    pre = perturb(gt, 5)
    g = torch.Generator().manual_seed(0)
    ad = pre.with_sigma_d(0.2 + 0.6 * torch.rand(len(pre), generator=g))
    write_ply(root / "pre.ply", pre)
    (root / "ad").mkdir()
    write_ply(root / "ad" / "point_cloud.ply", ad)
    return {"root": root, "pre": pre, "ad": ad, "cams": cams, "scene": load_colmap_scene(root / "scene")}


@pytest.fixture(scope="module")
def report(tiny):
    out = tiny["root"] / "report"
    out.mkdir()
    rep = evaluate_report(tiny["root"] / "ad" / "point_cloud.ply", tiny["scene"], out, EvalOptions(
        pretrained=tiny["root"] / "pre.ply", budgets=[1.0, 0.5, 0.1, 50], sv_steps=6, max_sv=3.0,
        popping_steps=9, lpips=None, progress=False, log=None))
    return rep, out


# --- baselines -------------------------------------------------------------------------------
@pytest.mark.parametrize("k", [0, 1, 37, 10**6])
def test_baselines_render_exactly_k(tiny, k):
    pre, cam = tiny["pre"], tiny["cams"][0]
    vis = in_view(pre, cam.viewmat, cam.K, cam.width, cam.height)
    n_vis = int(vis.sum())
    want = min(k, n_vis)
    sels = {
        "constant_sigma": constant_sigma_selection(pre, cam, k, 0.3),
        "lightgaussian": ranking_selection(pre, cam, lightgaussian_significance(pre, tiny["cams"][1:]), k),
        "random": ranking_selection(pre, cam, random_scores(len(pre), 0), k),
    }
    for name, sel in sels.items():
        assert sel.indices.numel() == want, name
        assert bool(vis[sel.indices].all()), name  # the same in-view population as render_lod
        assert sel.indices.unique().numel() == want, name
        assert sel.opacities.shape == (want,)
        assert render_subset(pre, cam, sel.indices, sel.opacities, backend="cpu").n_rendered == want
    # baselines except constant sigma keep the original opacities
    assert torch.equal(sels["random"].opacities, pre.opacities[sels["random"].indices])


def test_constant_sigma_matches_render_lod_budget(tiny):
    """Baseline (a) is render_lod's exact budget on the model with sigma_d = c everywhere."""
    pre, cam = tiny["pre"], tiny["cams"][1]
    c = 0.25
    sel = constant_sigma_selection(pre, cam, 100, c, fade=True)
    ref = render_lod(pre.with_sigma_d(torch.full((len(pre),), c)), cam, budget=Budget(count=100), backend="cpu")
    assert torch.equal(sel.indices, torch.nonzero(ref.mask).squeeze(1))
    assert sel.s_v == pytest.approx(ref.s_v)
    img = render_subset(pre, cam, sel.indices, sel.opacities, backend="cpu").image
    assert torch.allclose(img, ref.image, atol=1e-5)
    # default: the same selection drawn with the original opacities
    plain = constant_sigma_selection(pre, cam, 100, c)
    assert torch.equal(plain.indices, sel.indices)
    assert torch.equal(plain.opacities, pre.opacities[sel.indices])


def test_ties_and_random_seed(tiny):
    pre, cam = tiny["pre"], tiny["cams"][0]
    flat = torch.ones(len(pre))  # all tied: lowest indices in view win
    sel = ranking_selection(pre, cam, flat, 5)
    vis = torch.nonzero(in_view(pre, cam.viewmat, cam.K, cam.width, cam.height)).squeeze(1)
    assert torch.equal(sel.indices, vis[:5])
    assert torch.equal(random_scores(50, 3), random_scores(50, 3))
    assert not torch.equal(random_scores(50, 3), random_scores(50, 4))


def test_lightgaussian_volume_and_score(tiny):
    pre = tiny["pre"]
    vf = volume_factor(pre)
    vol = torch.prod(pre.scales.double(), 1)
    ref = torch.sort(vol, descending=True).values[int(0.9 * len(vol))]
    assert torch.allclose(vf.double(), (vol / ref) ** 0.1, rtol=1e-5)
    s = lightgaussian_significance(pre, tiny["cams"])
    assert s.shape == (len(pre),) and bool((s >= 0).all()) and float(s.max()) > 0


# --- popping ---------------------------------------------------------------------------------
def test_popping_ratio_finite(tiny):
    pop = popping_curve(tiny["ad"], tiny["cams"][0], np.linspace(1, 3, 9), backend="cpu")
    assert len(pop["continuous_step"]) == len(pop["discrete_step"]) == 8
    assert sum(1 for d in pop["discrete_step"] if d > 0) == 1
    assert pop["continuous_max"] > 0 and math.isfinite(pop["ratio"])
    assert pop["ratio"] == pytest.approx(pop["discrete_max"] / pop["continuous_max"])
    assert pop["ratio"] > 1  # the sweep's largest step is smaller than one static switch
    assert pop["gaussians"][0] >= pop["gaussians"][-1]


# --- report ----------------------------------------------------------------------------------
def _read_csv(path):
    with open(path, newline="") as f:
        r = csv.DictReader(f)
        return r.fieldnames, list(r)


@pytest.mark.slow
def test_report_outputs_and_csv_schema(report, tiny):
    rep, out = report
    for n in OUTPUT_NAMES:
        assert (out / n).is_file() and (out / n).stat().st_size > 0, n
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temp files left
    cols, rows = _read_csv(out / "report.csv")
    assert tuple(cols) == CSV_COLUMNS
    keys = [(r["method"], r["setting"]) for r in rows]
    assert len(keys) == len(set(keys))  # one row per method x setting
    budgets = ["budget=1", "budget=0.5", "budget=0.1", "budget=50"]
    expected = {("pretrained", "full")} | {("clod", f"s_v={s:g}") for s in np.linspace(1, 3.6, 6)}
    expected |= {(m, b) for m in ("clod_budget",) + BASELINES for b in budgets}
    assert set(keys) == expected
    pcols, prow = _read_csv(out / "report_per_view.csv")
    assert tuple(pcols) == PER_VIEW_COLUMNS
    n_views = len(tiny["scene"].test)
    assert n_views == 2 and len(prow) == n_views * len(rows)
    assert all(r["views"] == str(n_views) for r in rows)
    assert all(r["lpips"] == "" for r in rows)  # lpips=None: skipped, empty cells
    js = json.loads((out / "report.json").read_text())
    assert js["columns"] == list(CSV_COLUMNS) and len(js["rows"]) == len(rows)
    assert any("LPIPS skipped" in n for n in js["notes"])
    md = (out / "report.md").read_text()
    assert "| clod_budget |" in md and "Popping" in md and md.count("\n| 1.00 |") == 1


@pytest.mark.slow
def test_report_baselines_match_clod_counts(report, tiny):
    rep, _ = report
    pv = rep["per_view"]
    for r in pv:
        if r["method"] in BASELINES:
            twin = [q for q in pv if q["method"] == "clod_budget" and q["setting"] == r["setting"]
                    and q["view"] == r["view"]]
            assert twin and twin[0]["gaussians"] == r["gaussians"]
    b50 = [r for r in rep["rows"] if r["setting"] == "budget=50"]
    assert all(r["gaussians"] == 50 for r in b50)
    bpg = rep["bytes_per_gaussian"]
    # the .ply row strides (SH degree 1): 26 floats plain, + sigma_d adapted (no level gains here)
    assert bpg == {"adapted": 4 * (26 + 1), "pretrained": 4 * 26}
    st = rep["storage"]  # storage is the bytes of the files, not a float count
    assert st["adapted_bytes"] == (tiny["root"] / "ad" / "point_cloud.ply").stat().st_size
    assert st["pretrained_bytes"] == (tiny["root"] / "pre.ply").stat().st_size
    for r in rep["rows"]:
        per = bpg["adapted"] if r["method"].startswith("clod") else bpg["pretrained"]
        assert r["bytes"] == pytest.approx(r["gaussians"] * per)
        assert math.isfinite(r["psnr"]) and 0 < r["ssim"] <= 1
    assert math.isfinite(rep["popping"]["ratio"])


# --- CLI -------------------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_runs(tiny, tmp_path, capsys):
    out = tmp_path / "rep"
    r = tiny["root"]
    code = main([str(r / "ad" / "point_cloud.ply"), "--images", str(r / "scene"), "--pretrained",
                 str(r / "pre.ply"), "--budgets", "1,0.25", "--sv-steps", "3", "--popping-steps", "3",
                 "--max-sv", "2", "--no-lpips", "--quiet", "--no-merge", "--dlod-iterations", "3",
                 "-o", str(out)])
    assert code == 0, capsys.readouterr().err
    _, rows = _read_csv(out / "report.csv")
    assert len(rows) == 1 + 3 + 2 * 4 + 1  # + dlod_finetuned at 25 % (none at 100 %: that is the input)
    dl = [r for r in rows if r["method"] == "dlod_finetuned"]
    assert [r["setting"] for r in dl] == ["budget=0.25"]
    js = json.loads((out / "report.json").read_text())
    assert js["storage"]["dlod_bytes"] > js["storage"]["pretrained_bytes"]
    assert "popping" in capsys.readouterr().out


# --- splat-transform's decimators in the report --------------------------------------------------
@pytest.mark.slow
def test_report_runs_both_decimators_and_a_failing_peer_stops_it(tiny, tmp_path):
    from clod_adapter.io.splat_transform import PeerError, find_splat_transform

    tool = find_splat_transform()
    if tool is None:
        pytest.skip("splat-transform not installed (`npm ci` in the repository root installs 3.7.0)")
    out = tmp_path / "dec"
    out.mkdir()
    rep = evaluate_report(tiny["root"] / "ad" / "point_cloud.ply", tiny["scene"], out, EvalOptions(
        pretrained=tiny["root"] / "pre.ply", budgets=[0.5, 0.2], sv_steps=3, max_sv=3.0, popping_steps=5,
        lpips=None, progress=False, log=None, merge_tool=tool, timing_repeats=1))
    got = {(r["method"], r["setting"]) for r in rep["rows"]}
    for m in ("decimate", "decimate_adaptive"):
        assert {(m, "budget=0.5"), (m, "budget=0.2")} <= got
    assert rep["storage"]["decimated_sizes"]["decimate budget=0.5"] == round(0.5 * len(tiny["pre"]))
    bad = tmp_path / "fail.sh"
    bad.write_text("#!/bin/sh\necho broken >&2\nexit 3\n")
    bad.chmod(0o755)
    with pytest.raises(PeerError, match="exited 3"):
        evaluate_report(tiny["root"] / "ad" / "point_cloud.ply", tiny["scene"], tmp_path / "dec2", EvalOptions(
            pretrained=tiny["root"] / "pre.ply", budgets=[0.5], sv_steps=3, max_sv=3.0, popping_steps=5,
            lpips=None, progress=False, log=None, merge_tool=str(bad), timing_repeats=0))


def test_format_table_columns_never_run_into_each_other():
    """A long method name and setting stay two words (``decimate_adaptive budget=0.0894427``)."""
    from clod_adapter.jobs.eval_report import format_table

    rows = [{"method": "decimate_adaptive", "setting": "budget=0.0894427", "s_v": None, "gaussians": 514.0,
             "fraction": 0.086, "psnr": 17.8, "ssim": 0.5467, "lpips": None, "ms_total": 3.1}]
    head, line = format_table(rows).splitlines()
    assert line.split()[:3] == ["decimate_adaptive", "budget=0.0894427", "-"]
    assert head.split()[:2] == ["method", "setting"]


def test_frame_times_count_a_plain_frames_projection(monkeypatch):
    """A plain frame projects the whole model before selecting (``project_ms``); clod-eval's and
    clod-adapt's level tables count it, as a merge-tree cut's projection is in its raster_ms."""
    from clod_adapter.evaluate import level_metrics
    from clod_adapter.jobs import eval as eval_job
    from clod_adapter.lod.draw import LodRender
    from clod_adapter.lod.view import LodSelection

    def fake(*a, **k):
        sel = LodSelection(torch.arange(3), torch.ones(3), None, None, 0.0, torch.tensor(1.0), n=3)
        return LodRender(image=torch.zeros(4, 4, 3), alpha=torch.zeros(4, 4, 1), selection=sel, n_rendered=3,
                         n_frustum=3, eta=torch.tensor(1.0), project_ms=5.0, select_ms=1.0, raster_ms=2.0)

    monkeypatch.setattr(level_metrics, "render_lod", fake)
    monkeypatch.setattr(eval_job, "render_lod", fake)
    m = level_metrics.evaluate_level([0, 1, 2], [object()], [torch.zeros(4, 4, 3)], None)  # len() only
    assert (m.ms_per_frame, m.select_ms, m.raster_ms) == (8.0, 6.0, 2.0)
    s = eval_job._render_lod(None, object(), None, 0.005)
    assert (s.select_ms, s.raster_ms) == (6.0, 2.0)
