"""Tests for clod_adapter.io.scene."""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from clod_adapter.io.scene import Camera, Scene, SceneError
from clod_adapter.io.colmap import load_colmap_scene, write_colmap_scene
from conftest import shared_path


def _look_at(center, target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """World-to-camera [4,4] (OpenCV axes) for a camera at ``center`` looking at ``target``."""
    c = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ c
    return torch.tensor(V, dtype=torch.float32)


def _synthetic_cameras(n=10, w=64, h=48):
    cams, imgs = [], []
    rng = np.random.default_rng(0)
    for i in range(n):
        a = 2 * math.pi * i / n
        K = torch.tensor([[60.0 + i, 0, w / 2 + 0.25], [0, 61.0, h / 2 - 0.5], [0, 0, 1]], dtype=torch.float32)
        cams.append(Camera(f"view{i:03d}.png", None, _look_at([3 * math.cos(a), 0.5, 3 * math.sin(a)]), K, w, h))
        imgs.append(rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    return cams, imgs


# --- fern ---------------------------------------------------------------------------------------
def test_fern_full_resolution():
    root = shared_path("fern")
    s = load_colmap_scene(root)
    assert len(s.train) + len(s.test) == 20 and len(s.train) == 17
    assert [c.name for c in s.test] == ["image000.jpg", "image008.jpg", "image016.jpg"]
    assert not {c.name for c in s.test} & {c.name for c in s.train}
    c = s.train[0]
    assert (c.width, c.height) == (994, 745)
    assert c.image_path == root / "images" / c.name
    torch.testing.assert_close(c.K, torch.tensor([[828.8328, 0, 497.0], [0, 828.8328, 372.5], [0, 0, 1]]))
    for cam in s.cameras:
        assert cam.viewmat.dtype == torch.float32 and cam.viewmat.shape == (4, 4)
        R = cam.viewmat[:3, :3].double()
        torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-6, rtol=0)
        assert torch.equal(cam.viewmat[3], torch.tensor([0.0, 0, 0, 1]))


def test_fern_resolution2_uses_images_2_and_matches_training_cameras():
    root = shared_path("fern")
    s = load_colmap_scene(root, resolution=2)
    full = {c.name: c for c in load_colmap_scene(root).cameras}
    meta = {e["img_name"].rsplit(".", 1)[0]: e for e in json.loads((root / "pretrained" / "cameras.json").read_text())}
    for c in s.cameras:
        assert (c.width, c.height) == (497, 372)
        assert c.image_path == root / "images_2" / c.name
        f = full[c.name].K
        torch.testing.assert_close(c.K[0, 0], f[0, 0] * 0.5)
        torch.testing.assert_close(c.K[1, 1], f[1, 1] * 372 / 745)
        torch.testing.assert_close(c.K[0, 2], f[0, 2] * 0.5)
        assert torch.equal(c.viewmat, full[c.name].viewmat)
        # the pretrained checkpoint's cameras.json (official format: position, rotation = c2w)
        e = meta[c.name.rsplit(".", 1)[0]]
        assert (e["width"], e["height"]) == (497, 372)
        assert math.isclose(e["fx"], float(c.K[0, 0]), rel_tol=1e-5)
        assert math.isclose(e["fy"], float(c.K[1, 1]), rel_tol=1e-5)
        torch.testing.assert_close(c.center, torch.tensor(e["position"], dtype=torch.float32), atol=1e-4, rtol=0)
        torch.testing.assert_close(c.viewmat[:3, :3].T, torch.tensor(e["rotation"], dtype=torch.float32), atol=1e-5, rtol=0)
    img = s.load_image(s.test[0])
    assert img.shape == (372, 497, 3) and img.dtype == torch.float32
    assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0
    assert torch.equal(img, s.load_image(s.test[0]))  # cached copy
    expected = np.asarray(Image.open(root / "images_2" / "image000.jpg").convert("RGB"), dtype=np.float32) / 255
    assert np.array_equal(img.numpy(), expected)


def test_fern_resolution4_downsamples_images():
    root = shared_path("fern")
    s = load_colmap_scene(root, resolution=4, llffhold=0)
    assert s.test == [] and len(s.train) == 20
    c = s.train[0]
    assert (c.width, c.height) == (round(994 / 4), round(745 / 4)) and c.image_path.parent.name == "images"
    torch.testing.assert_close(c.K[0, 0], torch.tensor(828.83279954 * c.width / 994))
    assert s.load_image(c).shape == (c.height, c.width, 3)


def test_bonsai_tiny():
    root = shared_path("fixtures", "bonsai_tiny")
    s = load_colmap_scene(root)
    assert len(s.cameras) == 3 and len(s.test) == 1
    assert {(c.width, c.height) for c in s.cameras} == {(699, 461)}
    imgs = s.load_images(s.train)
    assert imgs.shape == (2, 461, 699, 3)


# --- errors -------------------------------------------------------------------------------------
def _tiny_model(root, model="PINHOLE", params=(50.0, 50.0, 16.0, 12.0), names=("a.png",), write_images=True):
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=32, height=24, params=list(params), camera_id=1))
    for i, n in enumerate(names):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=n, camera_id=1, image_id=i + 1), pycolmap.Rigid3d())
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(root / "sparse" / "0"))
    (root / "images").mkdir()
    if write_images:
        for n in names:
            Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(root / "images" / n)
    return root


def test_distorted_model_raises_with_undistort_hint(tmp_path):
    root = _tiny_model(tmp_path, model="SIMPLE_RADIAL", params=(50.0, 16.0, 12.0, 0.01))
    with pytest.raises(SceneError, match="SIMPLE_RADIAL.*undistort"):
        load_colmap_scene(root)


def test_simple_pinhole_and_model_in_sparse(tmp_path):
    root = _tiny_model(tmp_path, model="SIMPLE_PINHOLE", params=(50.0, 16.0, 12.0))
    for f in (root / "sparse" / "0").iterdir():
        os.replace(f, root / "sparse" / f.name)
    (root / "sparse" / "0").rmdir()
    c = load_colmap_scene(root, llffhold=0).train[0]
    assert torch.equal(c.K, torch.tensor([[50.0, 0, 16], [0, 50, 12], [0, 0, 1]]))
    torch.testing.assert_close(c.center, torch.zeros(3))


def test_missing_image_and_model_errors(tmp_path):
    root = _tiny_model(tmp_path / "s", names=("a.png", "b.png"), write_images=False)
    Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(root / "images" / "a.png")
    with pytest.raises(SceneError, match=r"images: image b\.png .*missing on disk"):
        load_colmap_scene(root)
    with pytest.raises(SceneError, match="no COLMAP model"):
        load_colmap_scene(tmp_path)
    with pytest.raises(SceneError, match="does not exist"):
        load_colmap_scene(tmp_path / "nothing")
    with pytest.raises(SceneError, match="resolution"):
        load_colmap_scene(root, resolution=3)
    (root / "sparse" / "0" / "images.bin").write_bytes(b"\x05\x00")
    with pytest.raises(SceneError, match=r"sparse/0: cannot read COLMAP model"):
        load_colmap_scene(root)


# --- image decoding -----------------------------------------------------------------------------
def test_load_image_modes(tmp_path):
    h, w = 6, 8
    cam = lambda name: Camera(name, tmp_path / name, torch.eye(4), torch.eye(3), w, h)  # noqa: E731
    scene = Scene(tmp_path, [], [])
    g = np.arange(h * w, dtype=np.uint8).reshape(h, w) * 5
    Image.fromarray(g).save(tmp_path / "gray.png")
    out = scene.load_image(cam("gray.png"))
    assert out.shape == (h, w, 3) and torch.equal(out[..., 0], out[..., 2])
    torch.testing.assert_close(out[..., 1], torch.from_numpy(g / 255.0).float())
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[..., 0] = 200
    rgba[..., 3] = 51  # alpha 0.2 -> 200/255*0.2 over black
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    out = scene.load_image(cam("rgba.png"))
    torch.testing.assert_close(out[..., 0], torch.full((h, w), 200 / 255 * 0.2))
    assert float(out[..., 1:].abs().max()) == 0.0
    g16 = (np.arange(h * w).reshape(h, w) * 1000).astype(np.uint16)
    Image.fromarray(g16).save(tmp_path / "g16.png")
    out = scene.load_image(cam("g16.png"))
    torch.testing.assert_close(out[..., 0], torch.from_numpy(g16 / 65535.0).float())
    Image.fromarray(np.full((2 * h, 2 * w, 3), 77, np.uint8)).save(tmp_path / "big.png")
    out = scene.load_image(cam("big.png"))  # resized with LANCZOS to the camera size
    assert out.shape == (h, w, 3)
    torch.testing.assert_close(out, torch.full((h, w, 3), 77 / 255))
    with pytest.raises(SceneError, match="missing.png: image file does not exist"):
        scene.load_image(cam("missing.png"))
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(SceneError, match="bad.png: cannot decode"):
        scene.load_image(cam("bad.png"))
    with pytest.raises(ValueError):
        scene.load_images([cam("gray.png"), Camera("x", tmp_path / "x", torch.eye(4), torch.eye(3), 3, 3)])


# --- writer round trip --------------------------------------------------------------------------
def test_write_read_round_trip(tmp_path):
    cams, imgs = _synthetic_cameras()
    root = tmp_path / "synthetic"
    pts = np.random.default_rng(1).normal(size=(20, 3))
    write_colmap_scene(root, cams, imgs, points3D=pts)
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= set(os.listdir(root / "sparse" / "0"))
    assert not [f for f in os.listdir(root / "sparse" / "0") if f.startswith(".")]
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    assert rec.num_points3D() == 20
    s = load_colmap_scene(root, llffhold=8)
    assert [c.name for c in s.test] == ["view000.png", "view008.png"]
    loaded = {c.name: c for c in s.cameras}
    for c, img in zip(cams, imgs):
        lc = loaded[c.name]
        assert (lc.width, lc.height) == (c.width, c.height)
        assert torch.equal(lc.K, c.K)
        torch.testing.assert_close(lc.viewmat, c.viewmat, atol=1e-5, rtol=0)
        assert np.array_equal((s.load_image(lc).numpy() * 255).round().astype(np.uint8), img)
    # rewriting into the same folder works (atomic replace of every file)
    write_colmap_scene(root, cams[:3], imgs[:3])
    assert len(load_colmap_scene(root, llffhold=0).train) == 3


def test_write_validates(tmp_path):
    cams, imgs = _synthetic_cameras(2)
    with pytest.raises(ValueError, match="2 cameras but 1 images"):
        write_colmap_scene(tmp_path, cams, imgs[:1])
    with pytest.raises(ValueError, match="uint8"):
        write_colmap_scene(tmp_path, cams, [i.astype(np.float32) for i in imgs])
