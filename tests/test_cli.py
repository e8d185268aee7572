"""The clod-adapt command line: bad input exits 2 with one line and writes nothing; --demo runs."""
import json
import subprocess
import sys
from pathlib import Path

import pytest


from clod_adapter.cli.adapt import main
from conftest import REPO, shared_path

FERN_PLY = ("fern", "pretrained", "point_cloud", "iteration_7000", "point_cloud.ply")


def _run(args, capsys):
    code = main([str(a) for a in args] + ["--quiet"])
    err = capsys.readouterr().err.strip()
    return code, err


def _assert_bad(code, err, must_contain, out_dir: Path):
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err
    assert must_contain in err
    assert not out_dir.exists() or not any(out_dir.iterdir())


def test_missing_ply(tmp_path, capsys):
    out = tmp_path / "out"
    code, err = _run([tmp_path / "nope.ply", "--images", tmp_path, "-o", out], capsys)
    _assert_bad(code, err, "nope.ply", out)


def test_missing_arguments(tmp_path, capsys):
    code, err = _run([], capsys)
    assert code == 2 and "--images" in err


def test_bad_ply(tmp_path, capsys):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n\x00")
    out = tmp_path / "out"
    code, err = _run([bad, "--images", tmp_path, "-o", out], capsys)
    _assert_bad(code, err, "bad.ply", out)


def test_distorted_scene(tmp_path, capsys):
    bonsai = shared_path("fixtures", "bonsai_tiny")
    ply = shared_path("fixtures", "plys", "inria_sh3_9080.ply")
    # a scene whose camera is SIMPLE_RADIAL: fern's source model is, but shipped undistorted;
    # build one from bonsai's images with a distorted camera
    import pycolmap

    rec = pycolmap.Reconstruction(str(bonsai / "sparse" / "0"))
    cam = next(iter(rec.cameras.values()))
    cam.model = pycolmap.CameraModelId.SIMPLE_RADIAL
    cam.params = [cam.params[0], cam.params[2], cam.params[3], 0.01]
    scene = tmp_path / "scene"
    (scene / "sparse" / "0").mkdir(parents=True)
    rec.write(str(scene / "sparse" / "0"))
    (scene / "images").symlink_to(bonsai / "images")
    out = tmp_path / "out"
    code, err = _run([ply, "--images", scene, "-o", out], capsys)
    _assert_bad(code, err, "undistort", out)


def test_output_equal_to_input(tmp_path, capsys):
    fern = shared_path("fern")
    src = shared_path(*FERN_PLY)
    d = tmp_path / "m"
    d.mkdir()
    ply = d / "point_cloud.ply"
    ply.write_bytes(src.read_bytes())
    code, err = _run([ply, "--images", fern, "--resolution", "2", "-o", d, "--iterations", "1"], capsys)
    assert code == 2 and "equals the input" in err and len(err.splitlines()) == 1
    assert ply.read_bytes() == src.read_bytes()
    assert sorted(p.name for p in d.iterdir()) == ["point_cloud.ply"]


def test_model_from_another_scene(tmp_path, capsys):
    from clod_adapter.io.ply import read_ply, write_ply

    fern = shared_path("fern")
    g = read_ply(shared_path("fixtures", "plys", "inria_sh3_9080.ply"))
    g.means += 1e5  # a model whose Gaussians lie nowhere near fern's cameras
    ply = tmp_path / "other.ply"
    write_ply(ply, g)
    out = tmp_path / "out"
    code, err = _run([ply, "--images", fern, "--resolution", "2", "-o", out, "--iterations", "1"], capsys)
    _assert_bad(code, err, "another scene", out)


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    r = subprocess.run([sys.executable, "-m", "clod_adapter.cli.adapt", "--demo", "-o", str(out), "--iterations", "40",
                        "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["levels"]) == 5 and m["num_gaussians"] == 6000
    assert "s_v=5" in r.stdout  # summary table printed
    assert (out / "point_cloud.ply").stat().st_size > 0


@pytest.mark.slow
def test_adapt_from_gsplat_checkpoint(tmp_path, capsys):
    """clod-adapt takes a gsplat ckpt_*.pt (its `splats` dict) as the pretrained model."""
    import torch

    from clod_adapter.io.ply import read_ply
    from conftest import write_tiny_scene

    scene, ply = write_tiny_scene(tmp_path, n=300)
    g = read_ply(ply)
    ckpt = tmp_path / "ckpt_6999.pt"
    torch.save({"step": 6999, "splats": {"means": g.means, "quats": g.quats, "scales": g.log_scales,
                                         "opacities": g.opacity_logits, "sh0": g.sh0, "shN": g.shN}}, ckpt)
    out = tmp_path / "out"
    code, err = _run([ckpt, "--images", scene, "-o", out, "--iterations", "2", "--max-sv", "2"], capsys)
    assert code == 0, err
    adapted = read_ply(out / "point_cloud.ply")
    assert len(adapted) == 300 and adapted.sigma_d is not None
