"""clod-view without a browser: cameras, what is sent per camera, max_sv, the CLI.

The real-browser test is tests/test_viewer_browser.py.
"""
from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from clod_adapter.lod.rankings import ranking_selection
from clod_adapter.lod.draw import lod_subset
from clod_adapter.lod.view import in_view
from clod_adapter.render.sh import spherical_harmonics
from clod_adapter.io.synthetic import make_cameras, make_ground_truth
from clod_adapter.viewer import (BYTES_PER_GAUSSIAN, DEFAULT_MAX_SV, camera_from_pose, covariances,
                                 default_start_view, model_max_sv, pose_from_camera, view_payload)
from clod_adapter.viewer.cameras import robust_bounds, scene_start_view
from clod_adapter.lod.budget import Budget

REPO = Path(__file__).resolve().parents[1]


def lod_model(n: int = 1500, seed: int = 0):
    """A small synthetic model with a spread of distance decays (log-uniform 0.3 .. 4), so the
    count falls steadily from s_v = 1 to 10."""
    g = make_ground_truth(n, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    sd = torch.exp(math.log(0.3) + math.log(4 / 0.3) * torch.rand(len(g), generator=gen))
    return g.with_sigma_d(sd)


def start_camera(g, w: int = 160, h: int = 120):
    p = default_start_view(g)
    return camera_from_pose(p.wxyz, p.position, p.fov, w, h)


# --- cameras ---------------------------------------------------------------------------------
def test_pose_round_trip_reproduces_a_scene_camera():
    cam = make_cameras(3, 5, width=160, height=120)[7]
    cam.K[0, 0] = cam.K[1, 1]  # viser has one focal length and a centred principal point
    p = pose_from_camera(cam)
    back = camera_from_pose(p.wxyz, p.position, p.fov, cam.width, cam.height)
    assert torch.allclose(back.viewmat, cam.viewmat, atol=1e-5)
    assert torch.allclose(back.K, cam.K, atol=1e-3)
    assert np.allclose(p.up, -cam.viewmat[1, :3].numpy(), atol=1e-6)  # up = -y of the camera


def test_camera_from_pose_axes_and_errors():
    # identity pose at the origin: a point 2 units along +z projects to the image centre
    c = camera_from_pose((1, 0, 0, 0), (0, 0, 0), math.radians(60), 200, 100)
    x = c.K @ (c.viewmat[:3, :3] @ torch.tensor([0.0, 0.0, 2.0]) + c.viewmat[:3, 3])
    assert torch.allclose(x[:2] / x[2], torch.tensor([100.0, 50.0]))
    assert float(c.K[1, 1]) == pytest.approx(50 / math.tan(math.radians(30)), rel=1e-6)
    with pytest.raises(ValueError, match="fov"):
        camera_from_pose((1, 0, 0, 0), (0, 0, 0), 0.0, 10, 10)
    with pytest.raises(ValueError, match="size"):
        camera_from_pose((1, 0, 0, 0), (0, 0, 0), 1.0, 0, 10)


def test_default_start_view_is_outside_the_box_and_aims_at_its_centre():
    g = lod_model()
    lo, hi = robust_bounds(g.means)
    p = default_start_view(g)
    assert not np.all((p.position >= lo) & (p.position <= hi))
    assert np.linalg.norm(p.position - 0.5 * (lo + hi)) > 0.5 * np.linalg.norm(hi - lo)
    cam = camera_from_pose(p.wxyz, p.position, p.fov, 160, 120)
    c = torch.from_numpy(0.5 * (lo + hi)).float()
    x = cam.K @ (cam.viewmat[:3, :3] @ c + cam.viewmat[:3, 3])
    assert torch.allclose(x[:2] / x[2], torch.tensor([80.0, 60.0]), atol=1e-2)
    assert int(in_view(g, cam.viewmat, cam.K, 160, 120).sum()) > 0.9 * len(g)


def test_scene_start_view_keeps_the_camera():
    g = lod_model()
    cam = make_cameras(2, 3, width=160, height=120)[0]
    p = scene_start_view(cam, g)
    back = camera_from_pose(p.wxyz, p.position, p.fov, 160, 120)
    assert torch.allclose(back.viewmat, cam.viewmat, atol=1e-5)
    fwd = cam.viewmat[2, :3].double().numpy()
    assert np.dot(p.look_at - p.position, fwd) > 0  # the orbit centre is ahead


# --- what is sent --------------------------------------------------------------------------
def test_payload_is_lod_subset_with_view_colours():
    g = lod_model()
    cam = start_camera(g)
    for sv in (1.0, 4.0, 10.0):
        p = view_payload(g, cam, s_v=sv)
        sub = lod_subset(g, cam, s_v=sv)
        assert torch.equal(p.indices, sub.indices) and p.method == "clod" and p.s_v == sub.s_v
        assert np.array_equal(p.opacities[:, 0], sub.opacities.numpy())
        assert np.array_equal(p.means, sub.means.numpy())
        campos = cam.center
        want = torch.clamp_min(spherical_harmonics(g.sh_degree, sub.means - campos, sub.colors) + 0.5, 0)
        assert np.allclose(p.rgbs, want.numpy(), atol=1e-6)
        assert p.message_bytes == BYTES_PER_GAUSSIAN * p.n_drawn
    counts = [view_payload(g, cam, s_v=sv).n_drawn for sv in (1.0, 2.0, 5.0, 10.0)]
    assert counts == sorted(counts, reverse=True) and counts[-1] < 0.5 * counts[0]
    b = view_payload(g, cam, budget=Budget(share=0.1))
    assert b.n_drawn == lod_subset(g, cam, budget=Budget(share=0.1)).indices.numel() == round(0.1 * len(g))


def test_a_merge_tree_is_sent_as_its_cut():
    """clod-view draws a merge tree as render_lod does (lod_subset's rows: tier 0's, then the
    merged nodes of the cut), and its slider reaches where the last tier is at 2 max_sv."""
    from dataclasses import replace

    from clod_adapter.lod import rule as lod, tree
    from clod_adapter.train import tiers
    from clod_adapter.viewer.app import LodViewer

    g = replace(lod_model(), lod=lod.LodSettings(fade="window"))
    t = tree.build(tiers.attach(g, replace(lod_model(300, seed=1), lod=g.lod), 3.0, 1.5), [start_camera(g)])
    cam = start_camera(t)
    merged = []
    for sv in (1.0, 3.3, 12.0):
        p, sub = view_payload(t, cam, s_v=sv), lod_subset(t, cam, s_v=sv)
        assert p.n_level == p.n_drawn == sub.means.shape[0] and np.array_equal(p.means, sub.means.numpy())
        assert torch.equal(p.indices, sub.indices)
        merged.append(sub.parent_indices.numel())
    assert merged[0] == 0 < merged[-1]  # full detail is tier 0; far down the range merged nodes are drawn
    assert LodViewer(t, calibrate=False).sv_max == pytest.approx(2 * 5.0 * 1.25 * 3.0 / 1.5)  # the last tier's reach
    assert LodViewer(g, calibrate=False).sv_max == 10.0


def test_covariances_match_rotation_and_scales():
    g = make_ground_truth(50, seed=3)
    cov = covariances(g.quats, g.scales)
    q = torch.nn.functional.normalize(g.quats, dim=1).double()
    w, x, y, z = q.unbind(1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)
    want = R @ torch.diag_embed(g.scales.double() ** 2) @ R.transpose(1, 2)
    assert torch.allclose(cov.double(), want, rtol=1e-4, atol=1e-9)


def test_compare_is_the_static_opacity_cut_at_the_same_count():
    g = lod_model()
    cam = start_camera(g)
    lod = view_payload(g, cam, s_v=5.0)
    cut = view_payload(g, cam, s_v=5.0, compare=True)
    assert cut.method == "static_opacity_cut" and cut.n_drawn == lod.n_drawn
    sel = ranking_selection(g.with_sigma_d(None), cam, g.opacities, lod.n_drawn)
    assert torch.equal(cut.indices, sel.indices)
    assert np.array_equal(cut.opacities[:, 0], g.opacities[sel.indices].numpy())  # original opacities
    assert not torch.equal(cut.indices, lod.indices)


def test_cap_uses_the_budget_solver():
    g = lod_model()
    cam = start_camera(g)
    full = view_payload(g, cam, s_v=1.0)
    cap = full.n_drawn // 3
    p = view_payload(g, cam, s_v=1.0, max_drawn=cap)
    assert p.capped and p.n_drawn == cap and p.n_level == full.n_drawn and p.s_v > 1.0
    assert torch.equal(p.indices, lod_subset(g, cam, budget=Budget(count=cap)).indices)
    assert not view_payload(g, cam, s_v=1.0, max_drawn=full.n_drawn).capped


def test_plain_model_sends_everything_in_view():
    g = make_ground_truth(800, seed=2)  # no sigma_d
    from clod_adapter.viewer.app import LodViewer

    assert "no `sigma_d`" in LodViewer(g, calibrate=False).model_note  # the panel says why
    assert LodViewer(lod_model(), calibrate=False).model_note == ""
    cam = start_camera(g)
    p = view_payload(g, cam, s_v=3.0, compare=True)  # LoD settings are ignored
    vis = in_view(g, cam.viewmat, cam.K, cam.width, cam.height)
    assert p.method == "all_in_view" and p.s_v is None and p.n_drawn == int(vis.sum())
    capped = view_payload(g, cam, max_drawn=100)
    assert capped.capped and capped.n_drawn == 100
    assert torch.equal(capped.indices, ranking_selection(g, cam, g.opacities, 100).indices)


# --- max_sv ----------------------------------------------------------------------------------
def test_model_max_sv_from_state_file(tmp_path):
    from safetensors.torch import save_file

    ply = tmp_path / "point_cloud.ply"
    assert model_max_sv(ply) == DEFAULT_MAX_SV == 5.0  # no state file
    save_file({"x": torch.zeros(1)}, str(tmp_path / "adapt_state.safetensors"),
              metadata={"config": json.dumps({"max_sv": 3.5})})
    assert model_max_sv(ply) == 3.5
    (tmp_path / "adapt_state.safetensors").write_bytes(b"garbage")
    assert model_max_sv(ply) == 5.0


def test_readout_carries_the_numbers():
    from clod_adapter.viewer.app import _readout_html

    g = lod_model()
    p = view_payload(g, start_camera(g), s_v=2.0)
    h = _readout_html(p, None, "timing our rasteriser ...")
    assert f'data-drawn="{p.n_drawn}"' in h and f'data-total="{len(g)}"' in h and 'data-sv="2.0"' in h
    assert "est. CPU raster ms" in h and f"{100 * p.n_drawn / len(g):.1f} %" in h


def test_raster_time_model_is_fitted_on_the_model():
    from clod_adapter.viewer import calibrate_raster_time

    g = lod_model()
    t = calibrate_raster_time(g, start_camera(g), repeats=1)
    assert t is not None and t.counts[0] > t.counts[1] > t.counts[2] > 0 and min(t.times_ms) > 0
    assert t.per_gaussian_ms >= 0 and t.intercept_ms >= 0
    assert t.estimate_ms(t.counts[0]) >= t.estimate_ms(t.counts[1])
    assert "our CPU rasteriser" in t.label()


# --- CLI ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", ["missing", "not_ply", "truncated", "bad_scene", "bad_host", "bad_max_drawn"])
def test_cli_bad_input_one_line_exit_2(tmp_path, case, capsys):
    pytest.importorskip("viser")
    from clod_adapter.cli.view import main

    from clod_adapter.io.ply import write_ply

    good = tmp_path / "m.ply"
    write_ply(good, lod_model(200))
    args = {
        "missing": [tmp_path / "nope.ply"],
        "not_ply": [tmp_path / "x.ply"],
        "truncated": [tmp_path / "t.ply"],
        "bad_scene": [good, "--images", tmp_path / "no_scene"],
        "bad_host": [good, "--host", "203.0.113.7", "--port", "0"],
        "bad_max_drawn": [good, "--max-drawn", "0"],
    }[case]
    (tmp_path / "x.ply").write_text("hello\n")
    (tmp_path / "t.ply").write_bytes(good.read_bytes()[:600])
    code = main([*map(str, args), "--no-timing"])
    out, err = capsys.readouterr()
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("clod-view: error: "), err
    assert "http://" not in out


def test_cli_serves_the_viewer_and_stops_on_sigterm(tmp_path):
    pytest.importorskip("viser")
    from clod_adapter.io.ply import write_ply

    ply = tmp_path / "m.ply"
    write_ply(ply, make_ground_truth(300, seed=1))  # a plain 3DGS model works too
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "clod_adapter.cli.view", str(ply), "--port", "0", "--no-timing"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    try:
        url = None
        for line in proc.stdout:  # the line with the address comes once the server listens
            m = re.search(r"at (http://127\.0\.0\.1:\d+)", line)
            if m:
                url = m.group(1)
                assert "no sigma_d" in line and "300 Gaussians" in line
                break
        assert url is not None, proc.stderr.read()
        page = urllib.request.urlopen(url + "/", timeout=30).read().decode("utf-8", "replace")
        assert "<html" in page.lower() and "script" in page.lower()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
