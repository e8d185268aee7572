"""clod_rasterization: the gsplat-style renderer hook equals render_lod and plain rasterization."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from clod_adapter.lod.draw import render_lod
from clod_adapter import clod_rasterization, rasterization
from clod_adapter.io.synthetic import make_cameras, make_ground_truth
from clod_adapter.lod.budget import Budget, as_budget

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene():
    gt = make_ground_truth(400, seed=3)
    g = torch.Generator().manual_seed(0)
    model = gt.with_sigma_d(0.2 + 0.6 * torch.rand(len(gt), generator=g))
    cams = make_cameras(1, 3, width=48, height=36)
    return model, cams


def _args(m, cams):
    vms = torch.stack([c.viewmat for c in cams])
    Ks = torch.stack([c.K for c in cams])
    return (m.means, m.quats, m.scales, m.opacities, m.colors, vms, Ks,
            cams[0].width, cams[0].height)


@pytest.mark.parametrize("s_v", [1.0, 2.0, 4.0])
def test_equals_render_lod_s_v(scene, s_v):
    m, cams = scene
    cam = cams[1]
    ref = render_lod(m, cam, s_v=s_v, backend="cpu")
    col, alp, meta = clod_rasterization(*_args(m, [cam]), sh_degree=m.sh_degree, sigma_d=m.sigma_d,
                                        s_v=s_v, backend="cpu")
    assert meta["lod_n_rendered"] == [ref.n_rendered]
    assert torch.equal(meta["lod_indices"][0], torch.nonzero(ref.mask).squeeze(1))
    assert meta["lod_s_v"] == [s_v]
    torch.testing.assert_close(col[0], ref.image, rtol=0, atol=1e-6)
    torch.testing.assert_close(alp[0], ref.alpha, rtol=0, atol=1e-6)


def test_fewer_gaussians_farther(scene):
    m, cams = scene
    n = [clod_rasterization(*_args(m, cams[:1]), sh_degree=m.sh_degree, sigma_d=m.sigma_d, s_v=s,
                            backend="cpu")[2]["lod_n_rendered"][0] for s in (1.0, 2.0, 4.0)]
    assert n[0] >= n[1] >= n[2] and n[0] > n[2]


@pytest.mark.parametrize("budget", [50, 0.3, Budget(in_view=0.4)])
def test_equals_render_lod_budget(scene, budget):
    """The hook's budget keyword: an int a count, a float a share of the model (converted to a
    Budget at its edge), or a Budget; as render_lod draws it."""
    m, cams = scene
    cam = cams[0]
    ref = render_lod(m, cam, budget=as_budget(budget), backend="cpu")
    col, _, meta = clod_rasterization(*_args(m, [cam]), sh_degree=m.sh_degree, sigma_d=m.sigma_d,
                                      budget=budget, backend="cpu")
    assert meta["lod_n_rendered"] == [ref.n_rendered]
    assert meta["lod_s_v"][0] == pytest.approx(ref.s_v)
    assert torch.equal(meta["lod_indices"][0], torch.nonzero(ref.mask).squeeze(1))
    torch.testing.assert_close(col[0], ref.image, rtol=0, atol=1e-6)


def test_budget_exact_k(scene):
    m, cams = scene
    for k in (0, 1, 37, 120):
        _, _, meta = clod_rasterization(*_args(m, cams[:1]), sh_degree=m.sh_degree,
                                        sigma_d=m.sigma_d, budget=k, min_s_v=0.0, backend="cpu")
        assert meta["lod_n_rendered"] == [k]
        assert meta["lod_indices"][0].numel() == k


def test_without_lod_equals_rasterization(scene):
    m, cams = scene
    ref_c, ref_a, _ = rasterization(*_args(m, cams), sh_degree=m.sh_degree, backend="cpu")
    for kw in ({}, {"sigma_d": m.sigma_d}, {"s_v": 2.0}, {"budget": 10}):
        col, alp, meta = clod_rasterization(*_args(m, cams), sh_degree=m.sh_degree, backend="cpu", **kw)
        assert torch.equal(col, ref_c) and torch.equal(alp, ref_a)
        assert "lod_s_v" not in meta


def test_multi_camera(scene):
    m, cams = scene
    two = [cams[0], cams[2]]
    bg = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0]])
    col, alp, meta = clod_rasterization(*_args(m, two), sh_degree=m.sh_degree, sigma_d=m.sigma_d,
                                        s_v=2.0, backgrounds=bg, backend="cpu")
    assert col.shape == (2, 36, 48, 3) and alp.shape == (2, 36, 48, 1)
    assert len(meta["cameras"]) == 2 and len(meta["lod_indices"]) == 2
    for i, cam in enumerate(two):
        ref = render_lod(m, cam, s_v=2.0, background=bg[i], backend="cpu")
        assert meta["lod_n_rendered"][i] == ref.n_rendered
        torch.testing.assert_close(col[i], ref.image, rtol=0, atol=1e-6)


def test_bad_arguments(scene):
    m, cams = scene
    a = _args(m, cams[:1])
    with pytest.raises(ValueError):
        clod_rasterization(*a, sh_degree=1, sigma_d=m.sigma_d, s_v=2.0, budget=10, backend="cpu")
    with pytest.raises(ValueError):
        clod_rasterization(*a, sh_degree=1, sigma_d=m.sigma_d, s_v=0.5, backend="cpu")
    with pytest.raises(ValueError):
        clod_rasterization(*a, sh_degree=1, render_mode="RGB+D", backend="cpu")
    with pytest.raises(TypeError):
        clod_rasterization(*a, sh_degree=1, not_a_gsplat_arg=1, backend="cpu")
    # gsplat keywords at their defaults are accepted
    clod_rasterization(*a, sh_degree=1, absgrad=False, packed=False, backend="cpu")


def test_example_script_runs(tmp_path):
    out = tmp_path / "demo.png"
    r = subprocess.run([sys.executable, str(REPO / "examples" / "render_hook.py"), "--synthetic",
                        "--n", "300", "--width", "48", "--height", "36", "--out", str(out)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    import re

    import numpy as np
    from PIL import Image

    drawn = {m[1]: int(m[2]) for m in re.finditer(r"^\s*(\S+): +(\d+) Gaussians rendered", r.stdout, re.M)}
    assert list(drawn)[:3] == ["s_v=1", "s_v=2", "s_v=4"], r.stdout
    assert drawn["s_v=1"] >= drawn["s_v=2"] >= drawn["s_v=4"] and drawn["s_v=1"] > drawn["s_v=4"]  # fewer as s_v grows
    (k, n), = [(int(lab.split("=")[1]), n) for lab, n in drawn.items() if lab.startswith("budget=")]
    assert k == max(1, drawn["s_v=1"] // 4) and 0 < n <= k  # a budget draws at most its count
    sheet = np.asarray(Image.open(out).convert("RGB"), dtype=np.float32)
    assert sheet.shape[1] >= 4 * 48 and sheet.std() > 1.0  # four panels, not a blank image
