"""The ``clod-adapt`` job: read a checkpoint and a scene, fine-tune ``sigma_d``, evaluate, export.

Outputs (all written atomically) in ``out_dir``:

* ``point_cloud.ply``: the extended INRIA .ply (the input layout plus a float ``sigma_d``);
* ``adapt_state.safetensors``: parameters, Adam moments, RNG and view order (resumable);
* ``metrics.json``: test views at s_v = 1, 2, ..., max_sv (PSNR, SSIM, mean rendered Gaussians,
  ms per frame) and the input model's PSNR/SSIM;
* ``lod_strip.png``: one test view rendered at several s_v, side by side.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import torch

from . import __version__, lod
from .adapt import AdaptConfig, adapt, load_state, prepare, save_state
from .evaluate import evaluate_level, evaluate_levels
from .io.atomic import atomic_save, atomic_write
from .io.ply import read_ply, write_ply
from .io.scene import load_colmap_scene
from .lod_render import render_lod

PLY_NAME = "point_cloud.ply"
STATE_NAME = "adapt_state.safetensors"
METRICS_NAME = "metrics.json"
STRIP_NAME = "lod_strip.png"


class InputError(ValueError):
    """Bad user input (a file, a folder or a flag); the message is one line naming it."""


def pick_device(device: str) -> torch.device:
    """``auto``: CUDA when available and gsplat imports, else CPU. Raises InputError for cuda
    without CUDA."""
    if device == "cpu":
        return torch.device("cpu")
    cuda_ok = torch.cuda.is_available()
    if device == "cuda":
        if not cuda_ok:
            raise InputError("--device cuda: no CUDA device is available (use --device cpu)")
        return torch.device("cuda")
    if device != "auto":
        raise InputError(f"--device must be auto, cpu or cuda, got {device!r}")
    if cuda_ok:
        try:
            import gsplat  # noqa: F401

            return torch.device("cuda")
        except Exception:
            pass
    return torch.device("cpu")


def check_output_dir(out_dir: Path, inputs: list[Path]) -> None:
    """Create ``out_dir`` if needed and refuse outputs that would overwrite an input.

    Raises:
        InputError: not creatable / not writable, or an output path equals an input path.
    """
    targets = [out_dir / n for n in (PLY_NAME, STATE_NAME, METRICS_NAME, STRIP_NAME)]
    for inp in inputs:
        for t in targets:
            if t.resolve() == inp.resolve():
                raise InputError(f"{t}: output path equals the input {inp}; choose another -o")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{out_dir}: cannot create output directory ({e.strerror})") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise InputError(f"{out_dir}: output directory is not writable")


def sv_levels(max_sv: float) -> list[float]:
    """s_v = 1, 2, ..., floor(max_sv), plus max_sv itself when it is not an integer."""
    levels = [float(s) for s in range(1, int(math.floor(max_sv)) + 1)]
    if max_sv > levels[-1] + 1e-9:
        levels.append(float(max_sv))
    return levels


def write_strip(path: Path, gaussians, camera, s_vs, background, backend: str) -> None:
    """Render ``camera`` at each ``s_v`` and write the images side by side as a PNG."""
    import numpy as np
    from PIL import Image, ImageDraw

    tiles = []
    with torch.no_grad():
        for s in s_vs:
            out = render_lod(gaussians, camera, s, background=background, backend=backend)
            arr = (out.image.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
            im = Image.fromarray(arr)
            ImageDraw.Draw(im).text((4, 4), f"s_v={s:g}  {out.n_rendered} G", fill=(255, 255, 0))
            tiles.append(im)
    w, h = tiles[0].size
    strip = Image.new("RGB", (w * len(tiles), h))
    for i, t in enumerate(tiles):
        strip.paste(t, (i * w, 0))
    atomic_save(path, lambda tmp: strip.save(tmp, format="PNG"))


def run(
    ply_path: os.PathLike,
    scene_root: os.PathLike,
    out_dir: os.PathLike,
    cfg: AdaptConfig,
    *,
    resolution: int = 1,
    device: str = "auto",
    resume: bool = False,
    progress: bool = True,
    log=print,
) -> dict:
    """Run the whole job; returns the metrics dict (also written to ``metrics.json``).

    Raises:
        InputError, clod_adapter.io.ply.PlyFormatError, clod_adapter.io.scene.SceneError: bad
        input (one-line messages naming the file). Nothing is written before inputs are checked.
        KeyboardInterrupt: after SIGINT/SIGTERM, once the resumable state has been saved.
    """
    t_start = time.perf_counter()
    ply_path, scene_root, out_dir = Path(ply_path), Path(scene_root), Path(out_dir)
    if not ply_path.is_file():
        raise InputError(f"{ply_path}: no such file")
    if not scene_root.is_dir():
        raise InputError(f"{scene_root}: no such scene folder")
    dev = pick_device(device)
    backend = "gsplat" if dev.type == "cuda" else "cpu"
    gaussians = read_ply(ply_path)
    if len(gaussians) == 0:
        raise InputError(f"{ply_path}: the model has no Gaussians")
    scene = load_colmap_scene(scene_root, resolution=resolution)
    if not scene.train:
        raise InputError(f"{scene_root}: no training views (every image is a test view)")
    state_path = out_dir / STATE_NAME
    if resume and not state_path.is_file():
        raise InputError(f"{state_path}: no state to resume from")
    check_output_dir(out_dir, [ply_path])

    gaussians = gaussians.to(dev)
    train_imgs = [scene.load_image(c).to(dev) for c in scene.train]
    test_cams = scene.test or scene.train[:1]
    test_imgs = [scene.load_image(c).to(dev) for c in test_cams]
    fr_any = torch.zeros(len(gaussians), dtype=torch.bool, device=dev)
    for c in scene.train:
        fr_any |= lod.in_frustum(gaussians.means, c.viewmat.to(dev), c.K.to(dev), c.width, c.height)
    if not bool(fr_any.any()):
        raise InputError(f"{ply_path}: no Gaussian lies inside any training view of {scene_root}; "
                         "is the model from another scene?")
    log(f"clod-adapt: {len(gaussians):,} Gaussians (SH degree {gaussians.sh_degree}), "
        f"{len(scene.train)} train / {len(scene.test)} test views at "
        f"{scene.train[0].width}x{scene.train[0].height}, device {dev}")

    bg = cfg.background
    input_eval = evaluate_level(gaussians, test_cams, test_imgs, None, background=bg, backend=backend)
    if resume:
        state, cfg_saved, _ = load_state(state_path, dev)
        cfg_saved.iterations = cfg.iterations
        cfg = cfg_saved
        log(f"clod-adapt: resuming {state_path} at iteration {state.iteration}/{cfg.iterations}")
        init_eval = None
    else:
        state = prepare(gaussians, scene.train, cfg, train_imgs, backend=backend)
        log(f"clod-adapt: sigma_d initialised with attenuation {state.init.get('attenuation')} at s_v = 1")
        init_eval = evaluate_level(state.gaussians().detach(), test_cams, test_imgs, 1.0,
                                   tau=cfg.tau, background=bg, backend=backend)

    meta = {"input_ply": str(ply_path), "scene": str(scene_root), "resolution": resolution}

    def on_interrupt(st):
        save_state(state_path, st, cfg, meta)
        log(f"\nclod-adapt: interrupted at iteration {st.iteration}; state saved to {state_path} "
            f"(continue with --resume)")

    t_train = time.perf_counter()
    it0 = state.iteration
    finished = adapt(state, scene.train, train_imgs, cfg, backend=backend, progress=progress,
                     on_interrupt=on_interrupt)
    if not finished:
        raise KeyboardInterrupt
    train_s = time.perf_counter() - t_train
    model = state.gaussians().detach()

    levels = sv_levels(cfg.max_sv)
    evals = evaluate_levels(model, test_cams, test_imgs, levels, tau=cfg.tau, background=bg,
                            backend=backend)
    metrics = {
        "version": __version__,
        "input_ply": str(ply_path),
        "scene": str(scene_root),
        "resolution": resolution,
        "device": str(dev),
        "threads": torch.get_num_threads(),
        "num_gaussians": len(model),
        "test_views": [c.name for c in test_cams],
        "config": asdict(cfg),
        "train_seconds": round(train_s, 2),
        "seconds_per_iteration": round(train_s / max(state.iteration - it0, 1), 4),
        "input_model": {"psnr": input_eval.psnr, "ssim": input_eval.ssim,
                        "gaussians": input_eval.gaussians, "ms_per_frame": input_eval.ms_per_frame},
        "init_s_v1": None if init_eval is None else {"psnr": init_eval.psnr, "ssim": init_eval.ssim,
                                                     "psnr_drop_db": input_eval.psnr - init_eval.psnr,
                                                     **state.init},
        "levels": [m.to_dict() for m in evals],
        "dead_sigma_d": int((model.sigma_d <= 0).sum()),
    }
    write_ply(out_dir / PLY_NAME, model.to("cpu"))
    save_state(state_path, state, cfg, meta)
    with atomic_write(out_dir / METRICS_NAME, "w") as f:
        json.dump(metrics, f, indent=2)
    write_strip(out_dir / STRIP_NAME, model, test_cams[0], levels, bg, backend)
    metrics["wall_seconds"] = round(time.perf_counter() - t_start, 1)
    log(format_summary(metrics))
    log(f"clod-adapt: wrote {out_dir / PLY_NAME}, {state_path.name}, {METRICS_NAME}, {STRIP_NAME} "
        f"in {metrics['wall_seconds']:.0f} s")
    return metrics


def format_summary(metrics: dict) -> str:
    """A short text table of ``metrics`` (input model, then each s_v)."""
    n = metrics["num_gaussians"]
    im = metrics["input_model"]
    lines = [f"{'model':>10} {'PSNR':>7} {'SSIM':>7} {'Gaussians':>10} {'%':>6} {'ms/frame':>9}",
             f"{'input':>10} {im['psnr']:7.2f} {im['ssim']:7.4f} {im['gaussians']:10.0f} "
             f"{100 * im['gaussians'] / n:6.1f} {im['ms_per_frame']:9.1f}"]
    for lv in metrics["levels"]:
        lines.append(f"{'s_v=' + format(lv['s_v'], 'g'):>10} {lv['psnr']:7.2f} {lv['ssim']:7.4f} "
                     f"{lv['gaussians']:10.0f} {100 * lv['fraction']:6.1f} {lv['ms_per_frame']:9.1f}")
    return "\n".join(lines)
