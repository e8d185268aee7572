"""Shared test fixtures: paths to ../shared/data, skipping with a reason when it is absent."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
#: ../shared/data beside the clone; CLOD_SHARED_DATA overrides it (e.g. for a git worktree elsewhere)
SHARED_DATA = Path(os.environ.get("CLOD_SHARED_DATA") or REPO.parent / "shared" / "data")
#: the shared LPIPS weights for every test and the CLIs they start (the package looks in the user cache)
if (SHARED_DATA / "lpips" / "lpips_alex_v0.1.safetensors").is_file():
    os.environ.setdefault("CLOD_LPIPS_WEIGHTS", str(SHARED_DATA / "lpips" / "lpips_alex_v0.1.safetensors"))

torch.set_num_threads(2)


@pytest.fixture(scope="session", autouse=True)
def _compositor_built():
    """Build (or load) the C++ compositor before any test, so its one-time build notice on stderr
    never lands in a test that counts stderr lines."""
    from clod_adapter.render.composite import cpp_extension_available

    cpp_extension_available()


def shared_path(*parts: str) -> Path:
    """Path under ../shared/data; skips the calling test when it does not exist."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p} (clone with ../shared beside the repo)")
    return p


def render_views(gaussians, cameras):
    """[H, W, 3] float images in [0, 1] of ``gaussians`` from each camera (CPU rasteriser)."""
    from clod_adapter.render import rasterization

    imgs = []
    with torch.no_grad():
        for c in cameras:
            col, _, _ = rasterization(gaussians.means, gaussians.quats, gaussians.scales,
                                      gaussians.opacities, gaussians.colors, c.viewmat[None],
                                      c.K[None], c.width, c.height,
                                      sh_degree=gaussians.sh_degree, backend="cpu")
            imgs.append(col[0].clamp(0, 1))
    return imgs


def uint8_views(gaussians, cameras):
    """:func:`render_views` as 8-bit images (H, W, 3), as written to a scene folder."""
    import numpy as np

    return [(im.numpy() * 255 + 0.5).astype(np.uint8) for im in render_views(gaussians, cameras)]


def write_tiny_scene(root: Path, n: int = 400, rows: int = 2, cols: int = 5, width: int = 64,
                     height: int = 48, seed: int = 4):
    """A tiny synthetic COLMAP scene under ``root``: returns (scene folder, pretrained .ply).

    Ground truth from :func:`clod_adapter.io.synthetic.make_ground_truth` rendered from a
    ``rows x cols`` camera grid; the .ply is a perturbed copy (the "pretrained" stand-in).
    """
    from clod_adapter.io.ply import write_ply
    from clod_adapter.io.colmap import write_colmap_scene
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb

    gt = make_ground_truth(n, seed=seed)
    cams = make_cameras(rows, cols, width=width, height=height)
    imgs = uint8_views(gt, cams)
    scene = Path(root) / "scene"
    write_colmap_scene(scene, cams, imgs)
    ply = Path(root) / "in.ply"
    write_ply(ply, perturb(gt, seed + 1))
    return scene, ply


@pytest.fixture(autouse=True)
def _compositor_impl(request):
    """A test parametrised over ``impl`` ("cpp" | "torch") runs with that CPU compositor
    (:func:`clod_adapter.render.composite.use_impl`); "cpp" skips where it cannot be built."""
    callspec = getattr(request.node, "callspec", None)
    impl = callspec.params.get("impl") if callspec is not None else None
    if impl not in ("cpp", "torch"):
        yield
        return
    from clod_adapter.render.composite import cpp_extension_available, use_impl

    if impl == "cpp" and not cpp_extension_available():
        pytest.skip("the C++ compositor cannot be built here")
    with use_impl(impl):
        yield


#: environment variable that runs the tests marked ``slow`` (CI sets it; the default run skips
#: them so it stays within a few minutes on 2 cores).
RUN_SLOW_ENV = "CLOD_RUN_SLOW"


def pytest_collection_modifyitems(config, items):
    import os

    if os.environ.get(RUN_SLOW_ENV, "").strip() not in ("", "0"):
        return
    skip = pytest.mark.skip(reason=f"slow; run with {RUN_SLOW_ENV}=1 (CI does)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


# --- a tiny pretrained model, its scene and one fast adaptation (CLI tests) ----------------------------
#: clod-adapt flags of the fast CLI runs
FAST = ["--iterations", "2", "--max-sv", "2", "--timing-repeats", "1", "--quiet"]


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> dict:
    """A 300-Gaussian model and its scene (:func:`write_tiny_scene`), also as an official 3DGS
    model folder: ``{"root", "scene", "ply", "model"}``."""
    import shutil

    root = tmp_path_factory.mktemp("jobs")
    scene, ply = write_tiny_scene(root, n=300)
    # the same model as an official 3DGS model folder (two iterations; the largest is taken)
    for it in (10, 30):
        d = root / "model" / "point_cloud" / f"iteration_{it}"
        d.mkdir(parents=True)
        shutil.copy(ply, d / "point_cloud.ply")
    return {"root": root, "scene": scene, "ply": ply, "model": root / "model"}


@pytest.fixture(scope="module")
def tiny_adapted(tiny_model, tmp_path_factory) -> Path:
    """One clod-adapt run from the model folder, with the official layout."""
    out = tmp_path_factory.mktemp("adapted") / "out"
    from clod_adapter.cli.adapt import main as adapt_main

    code = adapt_main(["-m", str(tiny_model["model"]), "-s", str(tiny_model["scene"]), "-o", str(out),
                       "--layout", "inria", *FAST])
    assert code == 0
    return out


def err_line(capfd) -> str:
    """The one stderr line a CLI wrote (asserts one line and no traceback)."""
    err = capfd.readouterr().err.strip()
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]

