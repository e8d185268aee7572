"""``clod-adapt``'s first phase: read the checkpoint and the scene once and check them (finite
values, a model of this scene, the output folder, a resumable state), into :class:`Inputs`, which
the later phases take. Bad input raises :class:`clod_adapter.errors.InputError`, naming the file.
``o`` is always the job's :class:`clod_adapter.jobs.adapt.AdaptOptions`."""
from __future__ import annotations

import hashlib
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Optional

import torch

from .. import jobs
from ..lod import rule as lod
from ..train.state import STATE_NAME, load_state
from ..train.config import AdaptConfig
from ..train.loop import StopFlag
from ..gaussians import Gaussians
from ..io.load import apply_masks, load_model, resolve_model_path, training_size
from . import InputError, pick_device  # noqa: F401 (public here since the first release)
from ..io.ply import PlyFormatError
from ..io.view_images import ViewImages
from ..io.load import load_scene
from ..io.scene import Scene
from ..lod.draw import render_lod


PLY_NAME = "point_cloud.ply"
METRICS_NAME = "metrics.json"
STRIP_NAME = "lod_strip.png"
#: the training curve (loss, PSNR, rendered fraction against the step).
TRAINING_PLOT_NAME = "training.png"
#: written with ``layout="inria"`` (besides the files above): the official 3DGS model folder.
INRIA_FILES = ("point_cloud", "cameras.json", "cfg_args")
TENSORBOARD_DIR = "tensorboard"
OUTPUT_NAMES = (PLY_NAME, STATE_NAME, METRICS_NAME, STRIP_NAME, TRAINING_PLOT_NAME)


def check_output_dir(out_dir: Path, inputs: list[Path], *, create: bool = True, force: bool = False,
                     resume: bool = False, ignore=()) -> None:
    """:func:`clod_adapter.jobs.check_output_dir` for this job's outputs: refuse an output that
    would overwrite an input, a non-empty folder (unless ``force`` or ``resume``) or one that
    cannot be written; with ``create`` make the folder.

    Raises:
        InputError: naming the folder and the problem.
    """
    jobs.check_output_dir(out_dir, inputs, OUTPUT_NAMES, create=create, force=force, resume=resume,
                          ignore=ignore)
_PLY_FIELD = {"means": "x/y/z", "quats": "rot_*", "log_scales": "scale_*", "opacity_logits": "opacity",
              "sh0": "f_dc_*", "shN": "f_rest_*", "sigma_d": "sigma_d"}  # the .ply property names


#: ``--sanitize`` maps +Inf opacity logits (opacity exactly 1, as some exporters write) to
#: logit(1 - 1e-7) ~ 16.12 instead of dropping those Gaussians: rendering is unchanged (alpha is
#: clamped to 0.999 anyway) and the value is finite, so optimisation stays well defined.
SANITIZE_OPACITY_LOGIT = float(math.log((1.0 - 1e-7) / 1e-7))


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


#: a model whose training-view PSNR is not at least this far above that of a flat image of the
#: views' mean colour does not belong to the scene (every real pair measured is >= 6.2 dB above
#: it, fern even at --resolution 8; models from other scenes were 0.8-7.4 dB below it).
MISMATCH_MARGIN_DB = 1.0


@torch.no_grad()
def scene_match(gaussians, cameras, images, *, background, views: int = 3) -> dict:
    """Evidence that ``gaussians`` was trained on this scene, from up to ``views`` training views.

    Returns ``{"psnr", "flat_psnr", "margin_db", "in_view_fraction", "views", "view_psnr",
    "view_flat_psnr"}``: the model's mean PSNR on those views, the mean PSNR of a flat image of each
    view's mean colour, their difference, the fraction of Gaussians whose centre lies in any
    training view (over all ``cameras``), the views' names and both PSNRs per view.
    ``margin_db < MISMATCH_MARGIN_DB`` means a model from another scene: any model
    trained on these views renders them far better than a constant colour.
    """
    from ..metrics import psnr

    idx = torch.linspace(0, len(cameras) - 1, min(views, len(cameras))).round().long().tolist()
    pm, pf = [], []
    for i in idx:
        gt = images[i]
        img = render_lod(gaussians, cameras[i], None, background=background).image.clamp(0, 1)
        pm.append(psnr(img, gt))
        pf.append(psnr(gt.mean(dim=(0, 1), keepdim=True).expand_as(gt), gt))
    dev = gaussians.means.device
    fr = torch.zeros(len(gaussians), dtype=torch.bool, device=dev)
    for c in cameras:
        fr |= lod.in_frustum(gaussians.means, c.viewmat.to(dev), c.K.to(dev), c.width, c.height)
    m, f = sum(pm) / len(pm), sum(pf) / len(pf)
    return {"psnr": m, "flat_psnr": f, "margin_db": m - f, "in_view_fraction": float(fr.float().mean()),
            "views": [cameras[i].name for i in idx], "view_psnr": pm, "view_flat_psnr": pf}


def resolution_note(train_size, eval_size, source: str) -> Optional[str]:
    """A note when the images are evaluated at another size than the checkpoint was trained at
    (more than rounding apart), else None: the renders then alias (smaller) or blur (larger), and
    coarser levels can score *higher* than full detail."""
    if not train_size:
        return None
    tw, th = train_size
    w, h = eval_size
    if abs(tw - w) <= 1 and abs(th - h) <= 1:
        return None
    ratio = tw / max(w, 1)
    return (f"the checkpoint was trained at {tw}x{th} ({source}) but is evaluated at {w}x{h} "
            f"({ratio:.2g}x {'smaller' if ratio > 1 else 'larger'}): 3DGS renders alias at other "
            "resolutions, so PSNR can rise with s_v; use the training resolution (--resolution) to compare levels")


def input_iteration(ply_path: Path) -> Optional[int]:
    """N of a ``.../iteration_N/point_cloud.ply`` input, else None."""
    name = Path(ply_path).parent.name
    if name.startswith("iteration_"):
        try:
            return int(name[len("iteration_"):])
        except ValueError:
            return None
    return None


@dataclass
class Inputs:
    """What :func:`read_inputs` loaded and checked (phase 1 of a run)."""

    ply_path: Path
    scene_root: Path
    out_dir: Path
    gaussians: Gaussians
    mask_info: object
    sanitized: object
    scene: object
    dev: torch.device
    train_imgs: ViewImages
    test_cams: list
    test_imgs: ViewImages
    input_sha256: str
    scene_fp: str
    resumed: Optional[tuple]
    match: dict
    notes: list
    size: tuple
    main: bool
    given: Optional[Gaussians] = None  # the input as read, when faint Gaussians were left out
    faint: Optional[dict] = None  # what leave_out_faint did (metrics.json "faint")

    @property
    def input_model(self) -> Gaussians:
        """The input as given (what every level is compared with and timed against)."""
        return self.gaussians if self.given is None else self.given

    @property
    def state_path(self) -> Path:
        return self.out_dir / STATE_NAME


def read_model(ply_path: Path, cfg: AdaptConfig, o):
    """The input model with its masks applied and non-finite values checked: (model, mask info,
    sanitize info)."""
    try:
        gaussians = load_model(ply_path, masks="all", allow_nonfinite=True)
        gaussians, mask_info = apply_masks(gaussians, o.masks, seed=cfg.seed, path=ply_path)
    except ValueError as e:  # an unknown policy (a PlyFormatError names the file already)
        if isinstance(e, PlyFormatError):
            raise
        raise InputError(f"--masks: {e}") from None
    if len(gaussians) == 0:
        raise InputError(f"{ply_path}: the model has no Gaussians")
    if mask_info is not None:
        o.log(f"clod-adapt: MaskGaussian masks {mask_info.describe()} (--masks argmax|gumbel|all)")
    gaussians, sanitized = check_finite(gaussians, ply_path, o.sanitize, log=o.log)
    return gaussians, mask_info, sanitized


def job_scene(scene_root: Path, cfg: AdaptConfig, o) -> Scene:
    """The scene a job reads: ``scene_root`` at ``o.resolution`` over ``cfg.background``; with
    ``o.holdout_val`` its fit views as the training views and its validation views as the test
    views (:func:`clod_adapter.io.scene.holdout_validation`).

    Raises:
        clod_adapter.io.scene.SceneError: as :func:`clod_adapter.io.load.load_scene`.
    """
    scene = load_scene(scene_root, resolution=o.resolution, background=cfg.background)
    if o.holdout_val:
        from ..io.scene import holdout_validation

        scene = holdout_validation(scene)
    return scene


def fresh_scene(scene: Scene) -> Scene:
    """``scene`` (its cameras and split) with its own empty image cache of the default size: one
    :func:`job_scene` read serves every phase and merged tier at its resolution as a new read would."""
    return replace(scene, cache_size=Scene.cache_size)


def read_inputs(ply_path: Path, scene_root: Path, out_dir: Path, cfg: AdaptConfig, o,
                stop: StopFlag, group, scene: Optional[Scene] = None) -> Inputs:
    """Phase 1: load and check the model, the scene, the output folder and (``resume``) the state;
    the folder is created only once every input has passed. ``scene``: the job's scene
    (:func:`job_scene` at ``o.resolution``) when an earlier phase has read it, else read here."""
    if not ply_path.exists():
        raise InputError(f"{ply_path}: no such file")
    ply_path = resolve_model_path(ply_path, o.iteration)
    if not scene_root.is_dir():
        raise InputError(f"{scene_root}: no such scene folder")
    if o.tensorboard:
        try:
            from torch.utils.tensorboard import SummaryWriter  # noqa: F401
        except Exception:
            raise InputError("--tensorboard: the tensorboard package is not installed "
                             "(pip install -e \".[tensorboard]\")") from None
    dev = pick_device(o.device) if group is None else group.device
    gaussians, mask_info, sanitized = read_model(ply_path, cfg, o)
    scene = job_scene(scene_root, cfg, o) if scene is None else fresh_scene(scene)
    stop.reinstall()  # importing pycolmap (COLMAP scenes only) replaces the SIGTERM handler
    if not scene.train:
        raise InputError(f"{scene_root}: no training views (every image is a test view)")
    given = gaussians
    gaussians, faint = leave_out_faint(gaussians, scene, cfg, o, group, ply_path)
    state_path = out_dir / STATE_NAME
    if o.resume and not state_path.is_file():
        raise InputError(f"{state_path}: no state to resume from")
    check_output_dir(out_dir, [ply_path], create=False, force=o.force, resume=o.resume)  # checks only
    # the file's bytes hashed in a pass of their own (a resumed state must name this input): the
    # model's readers parse several formats (load_model); the pass finds the file just read in the cache
    input_sha256, scene_fp = file_sha256(ply_path), scene_key(scene.train)
    resumed = None
    if o.resume:
        resumed = load_resume_state(state_path, cfg, input_sha256=input_sha256, scene_fp=scene_fp,
                                    resolution=o.resolution, num_gaussians=len(gaussians),
                                    iterations_from_state=o.iterations_from_state, device=dev,
                                    views_from_state=o.views_from_state)
    gaussians = gaussians.to(dev)
    # decoded on first use, kept within a memory budget (CLOD_IMAGE_CACHE_MB): a data-parallel
    # rank decodes only its own views, and hundreds of large views do not fill the memory
    scene.cache_size = 0
    train_imgs = ViewImages(scene, scene.train, dev)
    test_cams = scene.test or scene.train[:1]
    inp = Inputs(ply_path, scene_root, out_dir, gaussians, mask_info, sanitized, scene, dev, train_imgs,
                  test_cams, ViewImages(scene, test_cams, dev), input_sha256, scene_fp, resumed, {}, [],
                  (scene.train[0].width, scene.train[0].height), group is None or group.is_main,
                  given.to(dev) if len(given) != len(gaussians) else None, faint)
    check_scene_match(inp, cfg, o)
    if inp.main:
        check_output_dir(out_dir, [ply_path], force=True)  # every input is valid: create the output folder
    log_inputs(inp, cfg, o, group)
    return inp


def leave_out_faint(gaussians: Gaussians, scene, cfg: AdaptConfig, o, group,
                     ply_path: Path) -> tuple[Gaussians, Optional[dict]]:
    """Leave out the Gaussians the scene does not need (``cfg.faint_share``,
    :func:`clod_adapter.train.pruning.faint` on the training views; in a data-parallel run rank 0's
    choice is broadcast). Returns (the kept model, the ``metrics.json`` ``faint`` record, None when
    the rule is off)."""
    if cfg.faint_share <= 0.0:
        return gaussians, None
    from ..train.pruning import faint

    t0 = time.perf_counter()
    out, px = faint(gaussians, scene.train, cfg.faint_share)
    if group is not None:
        out = group.broadcast(out.to(torch.uint8).to(group.device), "the faint Gaussians").to(out.device).bool()
    n, k = len(gaussians), int(out.sum())
    info = {"faint_share": cfg.faint_share, "px": round(px, 3), "input": n, "left_out": k,
            "views": len(scene.train), "seconds": round(time.perf_counter() - t0, 1)}
    o.log(f"clod-adapt: {ply_path.name}: left out {k:,} of {n:,} Gaussians ({100 * k / max(n, 1):.1f} %) painting "
          f"under {px:.2g} px of the {len(scene.train)} training views together (--faint-share "
          f"{cfg.faint_share:g}; {info['seconds']:.0f} s)")
    return (gaussians.subset(~out) if k else gaussians), info


def check_scene_match(inp: Inputs, cfg: AdaptConfig, o) -> None:
    """Refuse a model from another scene (no Gaussian in any training view, or renders no better
    than a flat colour, unless ``allow_mismatch``); notes a resolution that differs from the
    model's training one."""
    g, dev = inp.input_model, inp.dev  # the model given, before the faint ones are left out
    fr_any = torch.zeros(len(g), dtype=torch.bool, device=dev)
    for c in inp.scene.train:
        fr_any |= lod.in_frustum(g.means, c.viewmat.to(dev), c.K.to(dev), c.width, c.height)
    if not bool(fr_any.any()):
        raise InputError(f"{inp.ply_path}: no Gaussian lies inside any training view of {inp.scene_root}; "
                         "is the model from another scene?")
    match = scene_match(g, inp.scene.train, inp.train_imgs, background=cfg.background)
    margins = [a - b for a, b in zip(match["view_psnr"], match["view_flat_psnr"])]
    bad = [i for i, v in enumerate(margins) if v < MISMATCH_MARGIN_DB]
    if bad and len(bad) < len(margins):  # the model renders the others: the images are suspect
        views = ", ".join(f"{match['views'][i]} ({match['view_psnr'][i]:.2f} dB, a flat image "
                          f"{match['view_flat_psnr'][i]:.2f} dB)" for i in bad)
        what = (f"{inp.scene_root}: the model {inp.ply_path} renders {len(margins) - len(bad)} of {len(margins)} "
                f"checked training views but not {views}: is that image damaged, or from another capture?")
        if match["margin_db"] < MISMATCH_MARGIN_DB and not o.allow_mismatch:
            raise InputError(what + " (--allow-mismatch goes on anyway)")
        o.log(f"clod-adapt: warning: {what}; going on")
    elif match["margin_db"] < MISMATCH_MARGIN_DB:
        what = (f"{inp.ply_path}: the model does not render {inp.scene_root}: {match['psnr']:.2f} dB PSNR on "
                f"{len(match['views'])} training views, not above a flat image of their mean colour "
                f"({match['flat_psnr']:.2f} dB); {100 * match['in_view_fraction']:.0f} % of its Gaussians "
                "lie in any training view")
        if not o.allow_mismatch:
            raise InputError(what + "; is the model from another scene? (--allow-mismatch goes on anyway)")
        o.log(f"clod-adapt: warning: {what}; going on (--allow-mismatch)")
    inp.match = match
    note = resolution_note(training_size(inp.ply_path), inp.size, "cameras.json of the model folder")
    if note:
        inp.notes.append(note)
        o.log(f"clod-adapt: note: {note}")


def log_inputs(inp: Inputs, cfg: AdaptConfig, o, group) -> None:
    g, size = inp.gaussians, inp.size
    o.log(f"clod-adapt: {inp.ply_path}: {len(g):,} Gaussians (SH degree {g.sh_degree}); "
          f"{len(inp.scene.train)} train / {len(inp.scene.test)} test views at {size[0]}x{size[1]}; device "
          f"{inp.dev}, {torch.get_num_threads()} threads; training-view PSNR {inp.match['psnr']:.2f} dB")
    if group is not None:
        o.log(f"clod-adapt: data-parallel over {group.world_size} processes ({group.backend}), "
              f"{cfg.views_per_step} views per step; rank 0 writes")
        if cfg.views_per_step < group.world_size:
            o.log(f"clod-adapt: note: {cfg.views_per_step} views per step for {group.world_size} processes: "
                  f"{group.world_size - cfg.views_per_step} of them render nothing (--views-per-step)")


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
                      resolution: int, num_gaussians: int, iterations_from_state: bool, device,
                      views_from_state: bool = False):
    """Load ``state_path`` for ``--resume`` and check it belongs to this input and these settings.

    Returns:
        (state, config, metadata); the config is ``cfg`` (with the state's iterations when
        ``iterations_from_state``, and its views per step when ``views_from_state``).

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
    if views_from_state:
        cfg.views_per_step = saved.views_per_step
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
