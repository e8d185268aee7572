"""The ``clod-adapt`` job: read a checkpoint and a scene, fine-tune ``sigma_d``, evaluate, export.

Outputs (all written atomically) in ``out_dir``:

* ``point_cloud.ply``: the extended INRIA .ply (the input layout plus a float ``sigma_d``);
* ``adapt_state.safetensors``: parameters, Adam moments, RNG and view order (resumable);
* ``metrics.json``: test views at s_v = 1, 2, ..., max_sv and at the budgets 100 / 50 / 25 / 10 %
  and max_sv^-1.5 of the model (PSNR, SSIM, mean rendered Gaussians, ms per frame) and the input
  model's PSNR/SSIM;
* ``lod_strip.png``: one test view rendered at several s_v, side by side.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import torch

from . import __version__, lod
from .adapt import AdaptConfig, StopFlag, adapt, load_state, prepare, save_state
from .evaluate import evaluate_level, evaluate_levels
from .io.atomic import atomic_save, atomic_write
from .io.load import load_model
from .io.ply import write_ply
from .io.scenes import load_scene
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


def _probe_writable(directory: Path) -> Optional[str]:
    """None when a file can be created (and removed) in ``directory``, else the OS reason.

    ``os.access`` is not enough (as root it says yes whatever the mode bits), so a real hidden
    file is created and removed at once.
    """
    import tempfile

    try:
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=".clod-probe-", suffix=".tmp")
    except OSError as e:
        return e.strerror or type(e).__name__
    os.close(fd)
    try:
        os.unlink(tmp)
    except OSError:
        pass
    return None


def check_output_dir(out_dir: Path, inputs: list[Path], *, create: bool = True) -> None:
    """Refuse outputs that would overwrite an input or cannot be written; create ``out_dir``.

    With ``create=False`` only checks (nothing is created or left behind), so it can run before
    the inputs are fully validated; ``out_dir`` or, when it does not exist yet, its nearest
    existing ancestor must be a directory in which a file can be created. With ``create=True``
    (the default) ``out_dir`` is also created (with parents) and probed; on failure the folders
    just created are removed again.

    Raises:
        InputError: not creatable / not writable, not a directory, or an output path (or
            ``out_dir`` itself) equals an input path.
    """
    out_dir = Path(out_dir)
    targets = [out_dir / n for n in (PLY_NAME, STATE_NAME, METRICS_NAME, STRIP_NAME)]
    for inp in inputs:
        if out_dir.resolve() == Path(inp).resolve():
            raise InputError(f"{out_dir}: output path equals the input {inp}; -o takes a folder, choose another")
        for t in targets:
            if t.resolve() == Path(inp).resolve():
                raise InputError(f"{t}: output path equals the input {inp}; choose another -o")
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: output path exists and is not a directory")
    missing = [p for p in (out_dir, *out_dir.parents) if not p.exists()]
    if not create:
        anc = missing[-1].parent if missing else out_dir
        if not anc.is_dir():
            raise InputError(f"{out_dir}: cannot create output directory ({anc} is not a directory)")
        why = _probe_writable(anc)
        if why is not None:
            what = "output directory is not writable" if anc == out_dir else f"cannot create output directory in {anc}"
            raise InputError(f"{out_dir}: {what} ({why})")
        return
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{out_dir}: cannot create output directory ({e.strerror})") from None
    why = _probe_writable(out_dir)
    if why is not None:
        for p in missing:  # deepest first: undo what mkdir made
            try:
                p.rmdir()
            except OSError:
                break
        raise InputError(f"{out_dir}: output directory is not writable ({why})")


#: ``--sanitize`` maps +Inf opacity logits (opacity exactly 1, as some exporters write) to
#: logit(1 - 1e-7) ~ 16.12 instead of dropping those Gaussians: rendering is unchanged (alpha is
#: clamped to 0.999 anyway) and the value is finite, so optimisation stays well defined.
SANITIZE_OPACITY_LOGIT = float(math.log((1.0 - 1e-7) / 1e-7))


_PLY_FIELD = {"means": "x/y/z", "quats": "rot_*", "log_scales": "scale_*", "opacity_logits": "opacity",
              "sh0": "f_dc_*", "shN": "f_rest_*", "sigma_d": "sigma_d"}  # the .ply property names


def check_finite(gaussians, ply_path: Path, sanitize: bool = False, log=print):
    """Reject (default) or repair (``sanitize``) Gaussians with NaN/Inf values.

    Returns ``(gaussians, info)``: the (possibly reduced) model and ``{"dropped": n,
    "opacity_clamped": m}`` (zeros when everything was finite).

    Raises:
        InputError: non-finite values and not ``sanitize`` (the message names the file and
            counts the Gaussians), or nothing left after sanitising.
    """
    n = len(gaussians)
    info = {"dropped": 0, "opacity_clamped": 0}
    if n == 0:
        return gaussians, info
    pos_inf_op = torch.isposinf(gaussians.opacity_logits)
    bad_fields = []
    rows_bad = torch.zeros(n, dtype=torch.bool)   # any non-finite value but a +Inf opacity logit
    any_bad = torch.zeros(n, dtype=torch.bool)
    counts = {"NaN": 0, "+Inf": 0, "-Inf": 0}
    for name, t in gaussians.tensors().items():
        v = t.detach().reshape(n, -1)
        nonfin = ~torch.isfinite(v)
        if not bool(nonfin.any()):
            continue
        bad_fields.append(_PLY_FIELD.get(name, name))
        counts["NaN"] += int(torch.isnan(v).sum())
        counts["+Inf"] += int(torch.isposinf(v).sum())
        counts["-Inf"] += int(torch.isneginf(v).sum())
        any_bad |= nonfin.any(1)
        if name == "opacity_logits":
            nonfin = nonfin & ~pos_inf_op[:, None]
        rows_bad |= nonfin.any(1)
    if not bool(any_bad.any()):
        return gaussians, info
    if not sanitize:
        what = ", ".join(f"{c:,} {k}" for k, c in counts.items() if c)
        raise InputError(f"{ply_path}: {int(any_bad.sum()):,} of {n:,} Gaussians have non-finite values "
                         f"({what} in {', '.join(bad_fields)}); pass --sanitize to drop them "
                         "(+Inf opacity logits are clamped instead)")
    clamp = pos_inf_op & ~rows_bad
    info = {"dropped": int(rows_bad.sum()), "opacity_clamped": int(clamp.sum())}
    if info["opacity_clamped"]:
        from dataclasses import replace

        op = gaussians.opacity_logits
        gaussians = replace(gaussians, opacity_logits=torch.where(
            clamp, torch.full_like(op, SANITIZE_OPACITY_LOGIT), op))
    if info["dropped"]:
        gaussians = gaussians.subset(~rows_bad)
    if len(gaussians) == 0:
        raise InputError(f"{ply_path}: every Gaussian has non-finite values; nothing left after --sanitize")
    log(f"clod-adapt: --sanitize: dropped {info['dropped']:,} of {n:,} Gaussians with NaN/Inf values; "
        f"set {info['opacity_clamped']:,} +Inf opacity logits to {SANITIZE_OPACITY_LOGIT:.2f} (opacity 1 - 1e-7)")
    return gaussians, info


def budget_levels(max_sv: float) -> list[float]:
    """Fractions evaluated by the job: 1, 0.5, 0.25, 0.1 down to ``max_sv^-1.5`` (the coarsest
    trained level), plus ``max_sv^-1.5`` itself."""
    low = max_sv ** -1.5
    out = [b for b in (1.0, 0.5, 0.25, 0.1) if b >= low - 1e-12]
    if all(abs(b - low) > 1e-9 for b in out):
        out.append(float(low))
    return out


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
    sanitize: bool = False,
    deterministic: bool = False,
    iterations_from_state: bool = False,
) -> dict:
    """Run the whole job; returns the metrics dict (also written to ``metrics.json``).

    ``sanitize``: drop Gaussians with NaN/Inf values and clamp +Inf opacity logits (see
    :func:`check_finite`) instead of failing on them.

    ``resume``: continue from ``out_dir/adapt_state.safetensors``; refused (InputError) when it
    was saved for another input .ply, scene or resolution, or with other settings than ``cfg``
    (``cfg.iterations`` may differ, which changes the schedule; ``iterations_from_state`` takes
    it from the state instead). ``deterministic``: bit-reproducible CPU gradients
    (:func:`clod_adapter.render.composite.set_deterministic`, plus
    ``torch.use_deterministic_algorithms``), so that an interrupted and resumed run ends
    bit-identical to an uninterrupted one with the same seed and thread count.

    SIGINT/SIGTERM: while inputs are read and evaluated (nothing written yet) the run stops at
    once; from the initialisation on, the signal only sets a flag, checked between iterations
    and phases, and the state is saved atomically first (a second signal during the save changes
    nothing). The final state is saved before the final evaluation, so an interrupt there also
    resumes (at the last iteration). Outputs (.ply, metrics, strip) are written only at the end,
    each atomically; a signal that arrives while they are being written lets them complete.

    Raises:
        InputError, clod_adapter.io.ply.PlyFormatError, clod_adapter.io.scene.SceneError: bad
        input (one-line messages naming the file). Nothing is written before inputs are checked.
        KeyboardInterrupt: after SIGINT/SIGTERM, once the resumable state has been saved (or
        before anything was written).
    """
    kw = dict(resolution=resolution, device=device, resume=resume, progress=progress, log=log,
              sanitize=sanitize, iterations_from_state=iterations_from_state)
    with StopFlag(abortable=True) as stop, deterministic_mode(deterministic):
        try:
            return _run(ply_path, scene_root, out_dir, cfg, stop=stop, **kw)
        except KeyboardInterrupt:
            if not getattr(stop, "state_saved", False):
                log("\nclod-adapt: interrupted before training started; nothing written")
            raise


#: test hook (undocumented for users): write the iteration number to this file after each step.
PROGRESS_FILE_ENV = "CLOD_PROGRESS_FILE"


@contextlib.contextmanager
def deterministic_mode(on: bool = True):
    """Within the block: the C++ compositor's deterministic backward and
    ``torch.use_deterministic_algorithms(True, warn_only=True)``; restored afterwards."""
    if not on:
        yield
        return
    from .render import composite

    prev = composite._DETERMINISTIC
    prev_alg = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    composite.set_deterministic(True)
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        composite.set_deterministic(prev)
        torch.use_deterministic_algorithms(prev_alg, warn_only=prev_warn)


def file_sha256(path: os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes (read in 1 MiB blocks); stored in the state so --resume
    can refuse another input. Raises OSError when unreadable."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def scene_key(cameras) -> str:
    """Fingerprint of the training views (names, sizes, intrinsics, poses)."""
    h = hashlib.sha256()
    for c in cameras:
        h.update(f"{c.name}:{c.width}x{c.height};".encode())
        h.update(c.K.double().cpu().numpy().tobytes())
        h.update(c.viewmat.double().cpu().numpy().tobytes())
    return h.hexdigest()


def load_resume_state(state_path: Path, cfg: AdaptConfig, *, input_sha256: str, scene_fp: str,
                      resolution: int, num_gaussians: int, iterations_from_state: bool, device):
    """Load ``state_path`` for ``--resume`` and check it belongs to this input and these settings.

    Returns:
        (state, config, metadata); the config is ``cfg`` (with the state's iterations when
        ``iterations_from_state``).

    Raises:
        InputError: unreadable state, or saved for another input/scene/resolution/settings.
    """
    try:
        state, saved, meta = load_state(state_path, device)
    except (ValueError, KeyError, RuntimeError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(msg if str(state_path) in msg else f"{state_path}: {msg}") from None
    if iterations_from_state:
        cfg.iterations = saved.iterations
    want, have = asdict(cfg), asdict(saved)
    diffs = [f"{k}={have[k]!r} (now {want[k]!r})" for k in want if k != "iterations" and want[k] != have.get(k)]
    if diffs:
        raise InputError(f"{state_path}: saved with other settings: {', '.join(diffs)}; "
                         "resume with the same flags or use another -o")
    if meta.get("input_sha256", input_sha256) != input_sha256:
        raise InputError(f"{state_path}: saved for another input model ({meta.get('input_ply')}); "
                         "resume with the same PLY or use another -o")
    if meta.get("scene_key", scene_fp) != scene_fp:
        raise InputError(f"{state_path}: saved for another scene ({meta.get('scene')}); "
                         "resume with the same --images or use another -o")
    if str(meta.get("resolution", resolution)) != str(resolution):
        raise InputError(f"{state_path}: saved at --resolution {meta.get('resolution')}, now {resolution}")
    n = int(state.params["means"].shape[0])
    if n != num_gaussians:
        raise InputError(f"{state_path}: holds {n:,} Gaussians, the input has {num_gaussians:,}")
    if state.iteration > cfg.iterations:
        raise InputError(f"{state_path}: already at iteration {state.iteration} > --iterations {cfg.iterations}")
    return state, cfg, meta


def _run(ply_path, scene_root, out_dir, cfg: AdaptConfig, *, stop: StopFlag, resolution: int,
         device: str, resume: bool, progress: bool, log, sanitize: bool,
         iterations_from_state: bool) -> dict:
    t_start = time.perf_counter()
    ply_path, scene_root, out_dir = Path(ply_path), Path(scene_root), Path(out_dir)
    if not ply_path.is_file():
        raise InputError(f"{ply_path}: no such file")
    if not scene_root.is_dir():
        raise InputError(f"{scene_root}: no such scene folder")
    dev = pick_device(device)
    backend = "gsplat" if dev.type == "cuda" else "cpu"
    gaussians = load_model(ply_path, allow_nonfinite=True)
    if len(gaussians) == 0:
        raise InputError(f"{ply_path}: the model has no Gaussians")
    gaussians, sanitized = check_finite(gaussians, ply_path, sanitize, log=log)
    scene = load_scene(scene_root, resolution=resolution, background=cfg.background)
    stop.reinstall()  # importing pycolmap (COLMAP scenes only) replaces the SIGTERM handler
    if not scene.train:
        raise InputError(f"{scene_root}: no training views (every image is a test view)")
    state_path = out_dir / STATE_NAME
    if resume and not state_path.is_file():
        raise InputError(f"{state_path}: no state to resume from")
    check_output_dir(out_dir, [ply_path], create=False)  # checks only: nothing written yet
    input_sha256, scene_fp = file_sha256(ply_path), scene_key(scene.train)
    if resume:
        resumed = load_resume_state(state_path, cfg, input_sha256=input_sha256, scene_fp=scene_fp,
                                    resolution=resolution, num_gaussians=len(gaussians),
                                    iterations_from_state=iterations_from_state, device=dev)

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
    check_output_dir(out_dir, [ply_path])  # every input is valid: create the output folder
    log(f"clod-adapt: {len(gaussians):,} Gaussians (SH degree {gaussians.sh_degree}), "
        f"{len(scene.train)} train / {len(scene.test)} test views at "
        f"{scene.train[0].width}x{scene.train[0].height}, device {dev}")

    bg = cfg.background
    input_eval = evaluate_level(gaussians, test_cams, test_imgs, None, background=bg, backend=backend)
    # from here on a signal only sets the flag: the state is saved at the next safe point
    stop.set_abortable(False)
    if resume:
        state, cfg, saved_meta = resumed
        log(f"clod-adapt: resuming {state_path} at iteration {state.iteration}/{cfg.iterations}")
        init_s_v1 = json.loads(saved_meta.get("init_s_v1", "null"))
    else:
        state = prepare(gaussians, scene.train, cfg, train_imgs, backend=backend)
        log(f"clod-adapt: sigma_d initialised with attenuation {state.init.get('attenuation')} at s_v = 1")
        init_eval = evaluate_level(state.gaussians().detach(), test_cams, test_imgs, 1.0,
                                   tau=cfg.tau, background=bg, backend=backend)
        init_s_v1 = {"psnr": init_eval.psnr, "ssim": init_eval.ssim,
                     "psnr_drop_db": input_eval.psnr - init_eval.psnr, **state.init}

    from .render.composite import deterministic_enabled

    meta = {"input_ply": str(ply_path), "scene": str(scene_root), "resolution": resolution,
            "input_sha256": input_sha256, "scene_key": scene_fp, "init_s_v1": json.dumps(init_s_v1),
            "deterministic": int(deterministic_enabled()), "threads": torch.get_num_threads()}

    def on_interrupt(st):
        save_state(state_path, st, cfg, meta)
        stop.state_saved = True
        log(f"\nclod-adapt: interrupted at iteration {st.iteration}; state saved to {state_path} "
            f"(continue with --resume)")

    on_step = None
    if os.environ.get(PROGRESS_FILE_ENV):
        hook_path = Path(os.environ[PROGRESS_FILE_ENV])

        def on_step(st):
            hook_path.write_text(f"{st.iteration}\n")

    t_train = time.perf_counter()
    it0 = state.iteration
    finished = adapt(state, scene.train, train_imgs, cfg, backend=backend, progress=progress,
                     on_interrupt=on_interrupt, stop=stop, on_step=on_step)
    if not finished:
        raise KeyboardInterrupt
    train_s = time.perf_counter() - t_train
    model = state.gaussians().detach()
    # the final state first: an interrupt during the evaluation resumes at the last iteration
    save_state(state_path, state, cfg, meta)
    stop.state_saved = True

    levels = sv_levels(cfg.max_sv)
    stop.set_abortable(True)  # the evaluation writes nothing; raises if a signal came meanwhile
    evals = evaluate_levels(model, test_cams, test_imgs, levels, tau=cfg.tau, background=bg,
                            backend=backend)
    budget_evals = [evaluate_level(model, test_cams, test_imgs, None, tau=cfg.tau, background=bg,
                                   backend=backend, budget=float(b)) for b in budget_levels(cfg.max_sv)]
    stop.set_abortable(False)
    metrics = {
        "version": __version__,
        "input_ply": str(ply_path),
        "scene": str(scene_root),
        "resolution": resolution,
        "device": str(dev),
        "threads": torch.get_num_threads(),
        "num_gaussians": len(model),
        "input_sanitized": sanitized,
        "test_views": [c.name for c in test_cams],
        "config": asdict(cfg),
        "train_seconds": round(train_s, 2),
        "seconds_per_iteration": round(train_s / max(state.iteration - it0, 1), 4),
        "input_model": {"psnr": input_eval.psnr, "ssim": input_eval.ssim,
                        "gaussians": input_eval.gaussians, "ms_per_frame": input_eval.ms_per_frame},
        "init_s_v1": init_s_v1,
        "deterministic": bool(deterministic_enabled()),
        "levels": [m.to_dict() for m in evals],
        "budgets": [m.to_dict() for m in budget_evals],
        "dead_sigma_d": int((model.sigma_d <= 0).sum()),
    }
    if stop.stop:  # a signal just after the evaluation: nothing written yet, stop here
        log(f"\nclod-adapt: interrupted after training; state saved to {state_path} (continue with --resume)")
        raise KeyboardInterrupt
    # each output atomically; a signal from here on only lets them complete
    write_ply(out_dir / PLY_NAME, model.to("cpu"))
    with atomic_write(out_dir / METRICS_NAME, "w") as f:
        json.dump(metrics, f, indent=2)
    write_strip(out_dir / STRIP_NAME, model, test_cams[0], levels, bg, backend)
    if stop.stop:
        log("clod-adapt: signal received while writing the outputs; they were completed first")
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
    for lv in metrics.get("budgets", []):
        lines.append(f"{'b=' + format(100 * lv['budget'], '.3g') + '%':>10} {lv['psnr']:7.2f} {lv['ssim']:7.4f} "
                     f"{lv['gaussians']:10.0f} {100 * lv['fraction']:6.1f} {lv['ms_per_frame']:9.1f}")
    return "\n".join(lines)
