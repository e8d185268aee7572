"""Bad input through the command line (issue "Stiff and extreme cases: bad input", part 2).

Every listed bad input either stops ``clod-adapt`` with exit status 2, exactly one stderr line
naming the file and the problem, no traceback and nothing written (inputs unchanged, no output
folder), or, for the inputs that are merely unusual (ASCII / big-endian .ply, grayscale / RGBA /
16-bit images, ``--sanitize``), is handled: the run succeeds. The table of cases is
docs/robustness_input.md. A tiny COLMAP scene (300 Gaussians, 10 views of 64x48) is built once
per module and copied per test; stderr is captured at the file-descriptor level (``capfd``) so
C++ logging (pycolmap) would count too.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import plyfile
import pycolmap
import pytest
import torch
from PIL import Image

from clod_adapter.cli.adapt import main as adapt_main
from clod_adapter.cli.eval import main as eval_main
from clod_adapter.io.ply import read_ply, write_ply
from clod_adapter.cli.export import main as export_main
from conftest import FAST, err_line, shared_path, uint8_views

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
RUN_FAST = ["--iterations", "2", "--max-sv", "2"]


# --- the tiny scene -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_src(tmp_path_factory) -> Path:
    from clod_adapter.io.colmap import write_colmap_scene
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb

    root = tmp_path_factory.mktemp("tiny")
    gt = make_ground_truth(300, seed=4)
    cams = make_cameras(2, 5, width=64, height=48)
    imgs = uint8_views(gt, cams)
    write_colmap_scene(root / "scene", cams, imgs)
    write_ply(root / "in.ply", perturb(gt, 2))
    return root


@pytest.fixture
def tiny(tiny_src, tmp_path) -> Path:
    """A private copy: ``tiny/in.ply`` (300 Gaussians, SH degree 1) and ``tiny/scene``."""
    work = tmp_path / "w"
    shutil.copytree(tiny_src, work)
    return work


def _snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _adapt(args, capfd):
    code = adapt_main([str(a) for a in args] + ["--quiet"])
    out, err = capfd.readouterr()
    return code, out, err


def _assert_bad(work: Path, args, capfd, *needles, out: Path | None = None, prog: str = "clod-adapt") -> str:
    """Run ``args -o out``: exit 2, one stderr line with ``needles``, no traceback, nothing
    written under ``work`` (every file byte-identical, no new file) and no output folder created
    (an ``out`` that existed before is covered by the snapshot when it lies under ``work``)."""
    out = work / "out" if out is None else out
    before = _snapshot(work)
    existed = out.exists()
    main = adapt_main if prog == "clod-adapt" else eval_main
    code = main([str(a) for a in args] + ["-o", str(out), "--quiet"])
    _, err = capfd.readouterr()
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    line = lines[0]
    assert line.startswith(f"{prog}: error: "), line
    for n in needles:
        assert str(n) in line, (n, line)
    assert _snapshot(work) == before, "an input changed or a file was written"
    if not existed:
        assert not out.exists(), f"{out} was created"
    return line


def _assert_ok(work: Path, args, capfd, out: Path | None = None) -> tuple[str, dict]:
    out = work / "out" if out is None else out
    code, stdout, err = _adapt([*args, *RUN_FAST, "-o", out], capfd)
    assert code == 0, err
    assert "Traceback" not in err
    m = json.loads((out / "metrics.json").read_text())
    assert (out / "point_cloud.ply").is_file()
    return stdout, m


def _vertex(ply: Path) -> np.ndarray:
    return np.array(plyfile.PlyData.read(str(ply))["vertex"].data)


def _write_vertex(path: Path, arr: np.ndarray, element: str = "vertex", **kw) -> Path:
    plyfile.PlyData([plyfile.PlyElement.describe(arr, element)], **kw).write(str(path))
    return path


def _rename(arr: np.ndarray, old: str, new: str) -> np.ndarray:
    dt = arr.dtype
    renamed = np.dtype({"names": [new if n == old else n for n in dt.names],
                        "formats": [dt.fields[n][0] for n in dt.names],
                        "offsets": [dt.fields[n][1] for n in dt.names], "itemsize": dt.itemsize})
    return arr.view(renamed).copy()


def _drop(arr: np.ndarray, *names: str) -> np.ndarray:
    keep = [n for n in arr.dtype.names if n not in names]
    res = np.zeros(len(arr), dtype=[(n, arr.dtype[n]) for n in keep])
    for n in keep:
        res[n] = arr[n]
    return res


# --- the .ply -----------------------------------------------------------------------------------
def test_empty_ply(tiny, capfd):
    (tiny / "empty.ply").write_bytes(b"")
    _assert_bad(tiny, [tiny / "empty.ply", "--images", tiny / "scene"], capfd, "empty.ply", "file is empty")


def test_truncated_ply(tiny, capfd):
    raw = (tiny / "in.ply").read_bytes()
    (tiny / "trunc.ply").write_bytes(raw[: len(raw) - 1000])
    _assert_bad(tiny, [tiny / "trunc.ply", "--images", tiny / "scene"], capfd, "trunc.ply", "truncated")


def test_header_only_and_garbage_ply(tiny, capfd):
    raw = (tiny / "in.ply").read_bytes()
    (tiny / "hdr.ply").write_bytes(raw[:200])  # cut inside the header
    _assert_bad(tiny, [tiny / "hdr.ply", "--images", tiny / "scene"], capfd, "hdr.ply", "not a valid PLY")
    (tiny / "junk.ply").write_bytes(b"\x00\x01garbage" * 10)
    _assert_bad(tiny, [tiny / "junk.ply", "--images", tiny / "scene"], capfd, "junk.ply", "not a valid PLY")


def test_missing_ply(tiny, capfd):
    _assert_bad(tiny, [tiny / "nope.ply", "--images", tiny / "scene"], capfd, "nope.ply", "no such file")


def test_ply_without_vertex_element(tiny, capfd):
    _write_vertex(tiny / "splat.ply", _vertex(tiny / "in.ply"), element="splat")
    _assert_bad(tiny, [tiny / "splat.ply", "--images", tiny / "scene"], capfd,
                "splat.ply", "no 'vertex' element (elements: splat)")


def test_ply_missing_property(tiny, capfd):
    _write_vertex(tiny / "noscale.ply", _drop(_vertex(tiny / "in.ply"), "scale_1"))
    _assert_bad(tiny, [tiny / "noscale.ply", "--images", tiny / "scene"], capfd,
                "noscale.ply", "lacks required property scale_1")


@pytest.mark.parametrize("old,new", [("opacity", "opacities"), ("rot_0", "rotation_0")])
def test_ply_misnamed_property(tiny, capfd, old, new):
    _write_vertex(tiny / "renamed.ply", _rename(_vertex(tiny / "in.ply"), old, new))
    _assert_bad(tiny, [tiny / "renamed.ply", "--images", tiny / "scene"], capfd,
                "renamed.ply", f"lacks required property {old}")


def test_ply_f_rest_count_matches_no_sh_degree(tiny, capfd):
    _write_vertex(tiny / "rest8.ply", _drop(_vertex(tiny / "in.ply"), "f_rest_8"))  # degree 1 has 9
    _assert_bad(tiny, [tiny / "rest8.ply", "--images", tiny / "scene"], capfd,
                "rest8.ply", "8 f_rest_* properties match no SH degree")


def _with_nonfinite(tiny: Path) -> Path:
    v = _vertex(tiny / "in.ply")
    v["x"][[3, 7]] = np.nan       # 2 Gaussians dropped
    v["scale_2"][11] = -np.inf     # 1 dropped
    v["f_dc_0"][12] = np.inf       # 1 dropped
    v["opacity"][[20, 21, 22]] = np.inf  # opacity exactly 1: clamped, kept
    v["opacity"][3] = np.inf       # also NaN in x: dropped, not clamped
    return _write_vertex(tiny / "nonfinite.ply", v)


def test_nan_inf_is_an_error_by_default(tiny, capfd):
    ply = _with_nonfinite(tiny)
    _assert_bad(tiny, [ply, "--images", tiny / "scene"], capfd, "nonfinite.ply",
                "7 of 300 Gaussians have non-finite values (2 NaN, 5 +Inf, 1 -Inf in x/y/z, scale_*, opacity, f_dc_*)",
                "--sanitize")


def test_sanitize_drops_nonfinite_and_clamps_inf_opacity(tiny, capfd):
    from clod_adapter.jobs.adapt_inputs import SANITIZE_OPACITY_LOGIT

    ply = _with_nonfinite(tiny)
    before = ply.read_bytes()
    stdout, m = _assert_ok(tiny, [ply, "--images", tiny / "scene", "--sanitize"], capfd)
    assert "--sanitize: dropped 4 of 300 Gaussians with NaN/Inf values; set 3 +Inf opacity logits" in stdout
    assert m["input_sanitized"] == {"dropped": 4, "opacity_clamped": 3}
    assert m["faint"]["input"] == 296 and m["num_gaussians"] == 296 - m["faint"]["left_out"]
    g = read_ply(tiny / "out" / "point_cloud.ply")  # finite (read_ply raises otherwise)
    assert len(g) == m["num_gaussians"]
    assert ply.read_bytes() == before
    assert 16.0 < SANITIZE_OPACITY_LOGIT < 16.2


def test_real_inf_opacity_fixture(tiny, capfd):
    """guitar_sh0_nonormals.ply stores 667 opacities of exactly 1 as logit +Inf."""
    from clod_adapter.jobs.adapt_inputs import SANITIZE_OPACITY_LOGIT, check_finite

    guitar = shared_path("fixtures", "plys", "guitar_sh0_nonormals.ply")
    _assert_bad(tiny, [guitar, "--images", tiny / "scene"], capfd, "guitar_sh0_nonormals.ply",
                "667 of 90,854 Gaussians have non-finite values (667 +Inf in opacity)")
    g, info = check_finite(read_ply(guitar, allow_nonfinite=True), guitar, sanitize=True, log=lambda *a: None)
    assert info == {"dropped": 0, "opacity_clamped": 667} and len(g) == 90854
    assert bool(torch.isfinite(g.opacity_logits).all())
    assert int((g.opacity_logits == SANITIZE_OPACITY_LOGIT).sum()) >= 667
    assert float(torch.sigmoid(g.opacity_logits).max()) > 0.9999


def test_ascii_ply_is_read(tiny, capfd):
    _write_vertex(tiny / "ascii.ply", _vertex(tiny / "in.ply"), text=True)
    assert b"format ascii" in (tiny / "ascii.ply").read_bytes()[:40]
    _, m = _assert_ok(tiny, [tiny / "ascii.ply", "--images", tiny / "scene"], capfd)
    assert m["faint"]["input"] == 300 and m["num_gaussians"] == 300 - m["faint"]["left_out"]


def test_big_endian_ply_is_read(tiny, capfd):
    v = _vertex(tiny / "in.ply")
    _write_vertex(tiny / "be.ply", v.astype(v.dtype.newbyteorder(">")), byte_order=">")
    assert b"binary_big_endian" in (tiny / "be.ply").read_bytes()[:60]
    _, m = _assert_ok(tiny, [tiny / "be.ply", "--images", tiny / "scene"], capfd)
    assert m["faint"]["input"] == 300 and m["num_gaussians"] == 300 - m["faint"]["left_out"]


def test_ply_from_another_scene(tiny, capfd):
    g = read_ply(tiny / "in.ply")
    g.means += 1e5  # nowhere near the cameras
    write_ply(tiny / "other.ply", g)
    _assert_bad(tiny, [tiny / "other.ply", "--images", tiny / "scene"], capfd,
                "other.ply", "no Gaussian lies inside any training view", "another scene")


# --- the COLMAP scene ---------------------------------------------------------------------------
def test_missing_colmap_model(tiny, capfd):
    shutil.rmtree(tiny / "scene" / "sparse")
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd, "scene", "no COLMAP model found")


def test_missing_scene_folder(tiny, capfd):
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "nowhere"], capfd, "nowhere", "no such scene folder")


@pytest.mark.parametrize("which", ["cameras.bin", "images.bin"])
def test_corrupt_colmap_model(tiny, capfd, which):
    f = tiny / "scene" / "sparse" / "0" / which
    f.write_bytes(f.read_bytes()[:13])  # truncated
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                os.path.join("sparse", "0"), "cannot read COLMAP model")


def test_image_listed_but_absent(tiny, capfd):
    (tiny / "scene" / "images" / "view003.png").unlink()
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                "images", "image view003.png", "missing on disk")


def test_corrupt_image(tiny, capfd):
    (tiny / "scene" / "images" / "view003.png").write_bytes(b"not a png at all")
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd, "view003.png", "cannot read image")


def test_image_size_not_matching_camera(tiny, capfd):
    p = tiny / "scene" / "images" / "view003.png"
    Image.open(p).resize((50, 40)).save(p)
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                "view003.png", "image is 50x40 but camera", "is 64x48")


def test_image_exact_integer_multiple_is_downscaled(tiny):
    """Library level (no run needed): a 2x image is accepted and downscaled to the camera size."""
    from clod_adapter.io.colmap import load_colmap_scene

    p = tiny / "scene" / "images" / "view003.png"
    small = np.asarray(Image.open(p).convert("RGB"))
    Image.fromarray(small).resize((128, 96), Image.Resampling.NEAREST).save(p)
    s = load_colmap_scene(tiny / "scene")
    cam = next(c for c in s.cameras if c.name == "view003.png")
    img = s.load_image(cam)
    assert img.shape == (48, 64, 3)
    assert float((img - torch.from_numpy(small / 255.0).float()).abs().mean()) < 0.03


@pytest.mark.parametrize("model,params", [("SIMPLE_RADIAL", 4), ("OPENCV", 8)])
def test_distorted_camera_model(tiny, capfd, model, params):
    d = tiny / "scene" / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(d))
    for cam in rec.cameras.values():
        fx, fy, cx, cy = list(cam.params)
        cam.model = getattr(pycolmap.CameraModelId, model)
        cam.params = [fx, cx, cy, 0.01] if params == 4 else [fx, fy, cx, cy, 0.01, 0.0, 0.0, 0.0]
    rec.write(str(d))
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                os.path.join("sparse", "0"), f"distorted model {model}", "undistort")


def _convert_images(scene: Path, fn) -> None:
    for p in sorted((scene / "images").iterdir()):
        Image.fromarray(fn(np.asarray(Image.open(p).convert("RGB")))).save(p)


@pytest.mark.parametrize("kind", ["grayscale", "rgba", "gray16"])
def test_image_modes_are_handled(tiny, capfd, kind):
    conv = {
        "grayscale": lambda a: a.mean(-1).round().astype(np.uint8),                      # mode L
        "rgba": lambda a: np.concatenate([a, np.full(a.shape[:2] + (1,), 255, np.uint8)], -1),
        "gray16": lambda a: (a.mean(-1) * 257).round().astype(np.uint16),               # mode I;16
    }[kind]
    _convert_images(tiny / "scene", conv)
    mode = Image.open(tiny / "scene" / "images" / "view000.png").mode
    assert mode == {"grayscale": "L", "rgba": "RGBA", "gray16": "I;16"}[kind]
    _, m = _assert_ok(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd)
    assert np.isfinite(m["input_model"]["psnr"])


# --- the output ---------------------------------------------------------------------------------
def test_output_parent_is_a_file(tiny, capfd):
    (tiny / "afile").write_text("x")
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                "afile", "cannot create output directory", "not a directory", out=tiny / "afile" / "out")


def test_output_is_an_existing_file(tiny, capfd):
    (tiny / "afile").write_text("x")
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                "afile", "exists and is not a directory", out=tiny / "afile")


@pytest.mark.skipif(IS_ROOT, reason="root writes into a 0o500 folder; see the /proc test")
def test_output_dir_read_only(tiny, capfd):
    ro = tiny / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd, "ro", "not writable", out=ro)
        _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd, "ro", "cannot create output",
                    out=ro / "sub")
    finally:
        ro.chmod(0o700)


@pytest.mark.skipif(not sys.platform.startswith("linux") or not os.path.isdir("/proc/self"),
                    reason="needs Linux /proc")
def test_output_dir_unwritable_even_for_root(tiny, capfd):
    """/proc/self is a directory no one (root included) can create files in; os.access says yes
    for root, so only the probe file catches it."""
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                "/proc/self", "not writable", out=Path("/proc/self"))
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                "/proc/self/clod_out", "cannot create output directory", out=Path("/proc/self/clod_out"))


def test_output_equal_to_input(tiny, capfd):
    os.replace(tiny / "in.ply", tiny / "point_cloud.ply")
    _assert_bad(tiny, [tiny / "point_cloud.ply", "--images", tiny / "scene"], capfd,
                "point_cloud.ply", "output path equals the input", out=tiny)


def test_output_is_the_input_file(tiny, capfd):
    _assert_bad(tiny, [tiny / "in.ply", "--images", tiny / "scene"], capfd,
                "in.ply", "output path equals the input", out=tiny / "in.ply")


# --- clod-eval ----------------------------------------------------------------------------------
def _adapted(tiny: Path) -> Path:
    g = read_ply(tiny / "in.ply")
    return write_ply(tiny / "adapted.ply", g.with_sigma_d(torch.ones(len(g))))


def test_eval_missing_and_corrupt_ply(tiny, capfd):
    args = ["--images", tiny / "scene", "--no-lpips"]
    _assert_bad(tiny, [tiny / "nope.ply", *args], capfd, "nope.ply", "no such file", prog="clod-eval")
    raw = _adapted(tiny).read_bytes()
    (tiny / "trunc.ply").write_bytes(raw[: len(raw) - 1000])
    _assert_bad(tiny, [tiny / "trunc.ply", *args], capfd, "trunc.ply", "truncated", prog="clod-eval")


def test_eval_missing_and_corrupt_scene(tiny, capfd):
    ply = _adapted(tiny)
    _assert_bad(tiny, [ply, "--images", tiny / "nowhere", "--no-lpips"], capfd,
                "nowhere", "no such scene folder", prog="clod-eval")
    f = tiny / "scene" / "sparse" / "0" / "cameras.bin"
    f.write_bytes(f.read_bytes()[:13])
    _assert_bad(tiny, [ply, "--images", tiny / "scene", "--no-lpips"], capfd,
                os.path.join("sparse", "0"), "cannot read COLMAP model", prog="clod-eval")


# --- the CLIs' usage and the output folder (the tiny model of conftest) -------------------------
def test_missing_arguments(tmp_path, capsys):
    code = adapt_main(["--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--images" in err


def test_folder_without_model_is_a_one_line_error(tiny_model, tmp_path, capfd):
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "out"
    code = adapt_main([str(empty), "--images", str(tiny_model["scene"]), "-o", str(out), *FAST])
    line = err_line(capfd)
    assert code == 2 and "is a folder, expected" in line and str(empty) in line
    assert not out.exists()


@pytest.mark.slow
def test_non_empty_output_is_refused(tiny_model, tmp_path, capfd):
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text('{"earlier": true}\n')
    args = [str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), "-o", str(out), *FAST]
    code = adapt_main(args)
    line = err_line(capfd)
    assert code == 2 and "output folder is not empty (metrics.json)" in line and "--force" in line
    assert (out / "metrics.json").read_text() == '{"earlier": true}\n'
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]
    assert adapt_main(args + ["--force"]) == 0
    assert "earlier" not in (out / "metrics.json").read_text()


def test_eval_and_export_refuse_non_empty_output(tiny_adapted, tiny_model, tmp_path, capfd):
    out = tmp_path / "rep"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code = eval_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "-o", str(out), "--no-lpips", "--quiet"])
    assert code == 2 and "not empty (notes.txt)" in err_line(capfd)
    code = export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "-o", str(out), "--quiet"])
    assert code == 2 and "not empty (notes.txt)" in err_line(capfd)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_demo_rerun_is_refused(tmp_path, capfd):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    code = adapt_main(["--demo", "-o", str(out), "--quiet"])
    assert code == 2 and "not empty" in err_line(capfd)
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]  # no demo scene written


def test_model_from_another_scene_is_refused(tmp_path, capfd):
    ply = shared_path("fixtures", "plys", "inria_sh3_9080.ply")
    bonsai = shared_path("fixtures", "bonsai_tiny")
    out = tmp_path / "out"
    code = adapt_main([str(ply), "--images", str(bonsai), "-o", str(out), *FAST])
    line = err_line(capfd)
    assert code == 2
    assert "does not render" in line and "flat image" in line and "another scene" in line
    assert "--allow-mismatch" in line
    assert not out.exists()


@pytest.mark.parametrize("damaged", [1, 2])
def test_a_damaged_training_image_is_named(tiny_model, tmp_path, capfd, damaged):
    """Checked training images decoded as a cut-short JPEG often is (grey below the break): the
    message names those images, not the checkpoint. One of three: a warning and the job goes on;
    two of three (the model's mean PSNR below a flat image's): refused, nothing written."""
    from clod_adapter.io.load import load_scene

    scene = tmp_path / "scene"
    shutil.copytree(tiny_model["scene"], scene)
    train = load_scene(scene).train
    hit = [Path(train[0].image_path), Path(train[-1].image_path)][:damaged]  # among the checked views
    for p in hit:
        with Image.open(p) as im:
            arr = np.asarray(im.convert("RGB")).copy()
        arr[arr.shape[0] // 20:] = 128
        Image.fromarray(arr).save(p)
    out = tmp_path / "out"
    code = adapt_main([str(tiny_model["ply"]), "--images", str(scene), "-o", str(out), *FAST])
    o, e = capfd.readouterr()
    text = e if damaged == 2 else o
    assert all(p.stem in text for p in hit) and "damaged" in text and f"renders {3 - damaged} of 3" in text, text
    if damaged == 2:
        assert code == 2 and len(e.strip().splitlines()) == 1 and "Traceback" not in e and not out.exists()
    else:
        assert code == 0 and "warning:" in o, e


def test_an_internal_error_is_not_reported_as_bad_input(tiny_model, tmp_path, monkeypatch, capfd):
    """A ValueError from inside a job is a bug, not bad input: it propagates with its traceback
    (exit status 1 from the console script) instead of one 'error:' line and exit 2; an
    InputError (and the .ply / scene errors, which are InputErrors) is the one-line exit 2."""
    from clod_adapter.errors import InputError
    from clod_adapter.io.ply import PlyFormatError
    from clod_adapter.io.scene import SceneError
    from clod_adapter.cli.common import run_cli
    from clod_adapter.jobs import adapt_inputs

    def broken(*a, **k):
        raise ValueError("internal: an index went wrong")

    monkeypatch.setattr(adapt_inputs, "scene_match", broken)
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="internal: an index went wrong"):
        adapt_main([str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), "-o", str(out), *FAST])
    assert issubclass(PlyFormatError, InputError) and issubclass(SceneError, InputError)
    capfd.readouterr()

    def bad_scene():
        raise SceneError("here", "no images")

    assert run_cli("prog", bad_scene) == 2
    assert err_line(capfd) == "prog: error: here: no images"


@pytest.mark.slow
def test_allow_mismatch_goes_on(tmp_path, capfd):
    ply = shared_path("fixtures", "plys", "inria_sh3_9080.ply")
    bonsai = shared_path("fixtures", "bonsai_tiny")
    out = tmp_path / "out"
    code = adapt_main([str(ply), "--images", str(bonsai), "--resolution", "4", "-o", str(out),
                       "--allow-mismatch", *FAST])
    o, e = capfd.readouterr()
    assert code == 0, e
    assert "warning:" in o and "--allow-mismatch" in o
    m = json.loads((out / "metrics.json").read_text())
    assert m["scene_match"]["margin_db"] < 1.0


def test_flag_names_in_errors(tiny_model, tmp_path, capfd, tiny_adapted):
    code = adapt_main([str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), "-o", str(tmp_path / "o"),
                       "--max-sv", "0.5", "--quiet"])
    assert code == 2 and "--max-sv must be >= 1, got 0.5" in err_line(capfd)
    code = adapt_main([str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), "-o", str(tmp_path / "o"),
                       "--level-max", "0.5", "--quiet"])
    assert code == 2 and "--level-max must be finite and >= 1, got 0.5" in err_line(capfd)
    assert not (tmp_path / "o").exists()
    code = eval_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "-o", str(tmp_path / "r"), "--budgets", "0,-1,abc"])
    line = err_line(capfd)
    assert code == 2 and "--budgets" in line and "'-1'" in line
    code = eval_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "-o", str(tmp_path / "r"), "--budgets", "0.5,abc"])
    line = err_line(capfd)
    assert code == 2 and "--budgets: 'abc' is not a number" in line
    code = export_main([str(tiny_adapted), "-s", str(tiny_model["scene"]), "-o", str(tmp_path / "x"), "--budget", "abc"])
    assert code == 2 and "--budget: 'abc' is not a number" in err_line(capfd)


@pytest.mark.parametrize("main", [adapt_main, eval_main, export_main])
def test_usage_error_is_one_line(main, capfd):
    with pytest.raises(SystemExit) as e:
        main(["x.ply", "--resolution", "3"])
    assert e.value.code == 2
    line = err_line(capfd)
    assert "--resolution" in line and "invalid choice" in line and line.endswith("(see --help)")


def test_mis_sized_image_in_images_r_is_refused(tiny_model, tmp_path, capfd):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_model["scene"], scene)
    (scene / "images_2").mkdir()
    for p in sorted((scene / "images").iterdir()):
        Image.open(p).resize((32, 24)).save(scene / "images_2" / p.name)
    bad = scene / "images_2" / "view003.png"
    Image.open(bad).resize((21, 12)).save(bad)  # a third of the width, half the height of 64x48
    out = tmp_path / "out"
    code = adapt_main([str(tiny_model["ply"]), "--images", str(scene), "--resolution", "2", "-o", str(out), *FAST])
    line = err_line(capfd)
    assert code == 2 and "view003.png" in line and "21x12" in line and "32x24" in line
    assert not out.exists()


def _bad_eval(args, capsys, out, must):
    code = eval_main([str(a) for a in args] + ["--quiet", "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert must in err, err
    assert not out.exists()


def test_eval_bad_inputs(tiny_model, tiny_adapted, tmp_path, capsys):
    ad, scene, pre = tiny_adapted, tiny_model["scene"], tiny_model["ply"]
    out = tmp_path / "rep"
    _bad_eval([tmp_path / "missing.ply", "--images", scene], capsys, out, "missing.ply")
    _bad_eval([ad, "--images", tmp_path / "noscene"], capsys, out, "noscene")
    _bad_eval([pre, "--images", scene], capsys, out, "sigma_d")  # not an tiny_adapted model
    _bad_eval([ad, "--images", scene, "--pretrained", tmp_path / "nopre.ply"], capsys, out, "nopre.ply")
    _bad_eval([ad, "--images", scene, "--budgets", "0.5,2.5"], capsys, out, "--budgets")
    _bad_eval([ad, "--images", scene, "--lpips-weights", tmp_path / "w.safetensors"], capsys, out, "w.safetensors")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"not a ply")
    _bad_eval([junk, "--images", scene], capsys, out, "junk.ply")
    _bad_eval([ad], capsys, out, "--images")
