"""NeRF-synthetic (Blender) scenes: cameras, split, background compositing, no pycolmap, clod-adapt."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from clod_adapter.io.blender import load_blender_scene
from clod_adapter.io.scene import SceneError
from clod_adapter.io.load import load_scene, scene_format
from clod_adapter.render import rasterization
from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb

REPO = Path(__file__).resolve().parents[1]
W, H = 40, 30


def write_blender_scene(root: Path, n: int = 300, seed: int = 5):
    """A tiny NeRF-synthetic scene: 4 train + 2 test RGBA views of a synthetic model.

    Returns (root, source cameras {name: Camera}, alpha {name: [H, W] float}, ground truth).
    """
    gt = make_ground_truth(n, seed=seed)
    cams = make_cameras(2, 3, width=W, height=H)
    fx = float(cams[0].K[0, 0])
    fovx = 2.0 * math.atan(0.5 * W / fx)
    gl_to_cv = np.diag([1.0, -1.0, -1.0, 1.0])
    src, alphas = {}, {}
    splits = {"train": cams[:4], "test": cams[4:]}
    for split, cs in splits.items():
        (root / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i, c in enumerate(cs):
            with torch.no_grad():
                col, alp, _ = rasterization(gt.means, gt.quats, gt.scales, gt.opacities, gt.colors,
                                            c.viewmat[None], c.K[None], W, H, sh_degree=gt.sh_degree,
                                            backend="cpu")
            a = alp[0, ..., 0].clamp(0, 1).numpy()
            straight = (col[0].numpy() / np.maximum(a[..., None], 1e-6)).clip(0, 1)
            rgba = np.concatenate([straight, a[..., None]], -1)
            rgba = (rgba * 255 + 0.5).astype(np.uint8)
            rgba[H // 2:, : W // 4, 3] = 0  # a fully transparent patch
            rgba[:4, :, 3] = 128  # and a half-transparent band
            Image.fromarray(rgba, "RGBA").save(root / split / f"r_{i}.png")
            c2w_gl = np.linalg.inv(c.viewmat.double().numpy()) @ gl_to_cv
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0,
                           "transform_matrix": c2w_gl.tolist()})
            src[f"{split}/r_{i}.png"] = c
            alphas[f"{split}/r_{i}.png"] = rgba[..., 3].astype(np.float32) / 255.0
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fovx, "frames": frames}))
    # a val split that must be ignored
    (root / "transforms_val.json").write_text(json.dumps({"camera_angle_x": fovx, "frames": []}))
    return root, src, alphas, gt


@pytest.fixture(scope="module")
def blender(tmp_path_factory):
    return write_blender_scene(tmp_path_factory.mktemp("lego"))


def test_cameras_match_source(blender):
    root, src, _, _ = blender
    s = load_blender_scene(root)
    assert scene_format(root) == "blender"
    assert [c.name for c in s.train] == [f"train/r_{i}.png" for i in range(4)]
    assert [c.name for c in s.test] == ["test/r_0.png", "test/r_1.png"]
    for c in s.cameras:
        ref = src[c.name]
        torch.testing.assert_close(c.viewmat, ref.viewmat, rtol=0, atol=1e-5)
        torch.testing.assert_close(c.K, ref.K, rtol=0, atol=1e-4)
        assert (c.width, c.height) == (W, H)
        assert c.image_path == root / c.name
        torch.testing.assert_close(c.center, ref.center, rtol=0, atol=1e-5)


def test_resolution_scales_K(blender):
    root, src, _, _ = blender
    s = load_blender_scene(root, resolution=2)
    c = s.train[0]
    assert (c.width, c.height) == (W // 2, H // 2)
    torch.testing.assert_close(c.K[:2], src[c.name].K[:2] / 2, rtol=0, atol=1e-4)
    assert s.load_image(c).shape == (H // 2, W // 2, 3)


def test_background_compositing(blender):
    root, _, alphas, _ = blender
    black = load_scene(root, background=(0, 0, 0))
    white = load_scene(root, background=(1, 1, 1))
    assert black.background == (0.0, 0.0, 0.0) and white.background == (1.0, 1.0, 1.0)
    for cb, cw in zip(black.cameras, white.cameras):
        ib, iw = black.load_image(cb), white.load_image(cw)
        a = torch.from_numpy(alphas[cb.name])[..., None]
        torch.testing.assert_close(iw - ib, (1 - a).expand_as(ib), rtol=0, atol=1e-5)
        assert float(ib[H // 2:, : W // 4].abs().max()) == 0.0
        assert float(iw[H // 2:, : W // 4].min()) == 1.0
        assert ib.min() >= 0 and iw.max() <= 1


def test_bad_scenes(tmp_path, blender):
    root = blender[0]
    with pytest.raises(SceneError):
        load_blender_scene(tmp_path)  # no transforms_train.json
    with pytest.raises(SceneError):
        load_blender_scene(root, background=(2, 0, 0))
    with pytest.raises(SceneError):
        load_blender_scene(root, resolution=3)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "transforms_train.json").write_text("{not json")
    with pytest.raises(SceneError):
        load_scene(bad)
    (bad / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "frames": [{"file_path": "./train/missing", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(SceneError, match="missing.png"):
        load_scene(bad)


def test_no_pycolmap_import(blender):
    root = blender[0]
    code = (
        "import sys\n"
        "from clod_adapter.io.load import load_scene\n"
        "import clod_adapter.jobs.adapt, clod_adapter.cli.adapt, clod_adapter.cli.eval\n"
        f"s = load_scene({str(root)!r}, background=(1, 1, 1))\n"
        "s.load_image(s.train[0])\n"
        "assert 'pycolmap' not in sys.modules, 'pycolmap imported'\n"
        "print('ok', len(s.train), len(s.test))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok 4 2"


def test_colmap_still_dispatched(tmp_path):
    from clod_adapter.io.colmap import write_colmap_scene

    cams = make_cameras(1, 2, width=16, height=12)
    imgs = [np.zeros((12, 16, 3), np.uint8) for _ in cams]
    write_colmap_scene(tmp_path / "s", cams, imgs)
    assert scene_format(tmp_path / "s") == "colmap"
    s = load_scene(tmp_path / "s", llffhold=0)
    assert len(s.train) == 2 and s.background == (0.0, 0.0, 0.0)


@pytest.mark.slow
def test_clod_adapt_end_to_end(tmp_path, blender):
    from clod_adapter.cli.adapt import main
    from clod_adapter.io.ply import read_ply, write_ply

    root, _, _, gt = blender
    ply = tmp_path / "in.ply"
    write_ply(ply, perturb(gt, 6))
    out = tmp_path / "out"
    rc = main([str(ply), "--images", str(root), "-o", str(out), "--iterations", "2", "--max-sv", "2",
               "--faint-share", "0", "--quiet", "--device", "cpu"])
    assert rc == 0
    m = read_ply(out / "point_cloud.ply")
    assert m.sigma_d is not None and len(m) == len(gt)
