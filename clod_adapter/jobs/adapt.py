"""The ``clod-adapt`` job: read a checkpoint and a scene, fine-tune ``sigma_d``, evaluate, export.

Outputs (all written atomically) in ``out_dir``:

* ``point_cloud.ply``: the extended INRIA .ply (the input layout plus a float ``sigma_d``);
* ``adapt_state.safetensors``: parameters, Adam moments, RNG and view order (resumable);
* ``metrics.json``: test views at s_v = 1, 2, ..., max_sv and at the budgets 100 / 50 / 25 / 10 %
  and max_sv^-1.5 of the Gaussians in view (PSNR, SSIM, mean rendered Gaussians, ms per frame) and the input
  model's PSNR/SSIM;
* ``lod_strip.png``: one test view rendered at several s_v, side by side.
* with ``keep_share < 1`` (:mod:`clod_adapter.train.pruning`), first: ``kept_input.ply`` (the input less what
  the training views need least, recovered: what the LoD is learned on) and ``leave_out.json``.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from .. import __version__
from ..train.state import STATE_NAME, save_state
from ..train.config import AdaptConfig
from ..train.loop import StopFlag, fit, prepare
from ..export.figures import write_strip, write_training_plot
from ..evaluate.level_metrics import evaluate_level, sv_levels
from ..io.atomic import atomic_write
from ..io.load import resolve_model_path
from . import InputError, pick_device  # noqa: F401 (public here since the first release)
from ..io.ply import read_ply, write_ply
from ..io.scene import Scene
from ..render.composite import deterministic_enabled
from ..gaussians import Gaussians
from .adapt_levels import format_summary, level_metrics, retime_levels  # noqa: F401 (public here)
from .adapt_inputs import (METRICS_NAME, PLY_NAME, STRIP_NAME, TENSORBOARD_DIR, TRAINING_PLOT_NAME, Inputs,
                           fresh_scene, input_iteration, job_scene, read_inputs, read_model)


def write_inria_layout(out_dir: Path, model, scene, *, iteration: int, resolution: int, background,
                       scene_root: Path) -> list[str]:
    """The official 3DGS model folder inside ``out_dir`` (graphdeco-inria/gaussian-splatting
    ``scene/__init__.py`` and ``utils/camera_utils.camera_to_JSON``), so SIBR-style viewers and
    the official scripts open it: ``point_cloud/iteration_N/point_cloud.ply`` in the exact INRIA
    layout (no ``sigma_d``: SIBR reads a fixed struct per vertex), ``cameras.json`` (id,
    img_name, width, height, position = camera centre, rotation = camera-to-world, fx, fy in
    pixels; train views then test views) and ``cfg_args`` (``Namespace(...)`` as the trainer
    writes it). Returns the paths written, relative to ``out_dir``."""
    import numpy as np

    rel_ply = Path("point_cloud") / f"iteration_{iteration}" / "point_cloud.ply"
    (out_dir / rel_ply.parent).mkdir(parents=True, exist_ok=True)
    write_ply(out_dir / rel_ply, replace(model.with_sigma_d(None), extra={}).to("cpu"))
    cams = []
    for i, c in enumerate(list(scene.train) + list(scene.test)):
        c2w = np.linalg.inv(c.viewmat.detach().double().cpu().numpy())
        K = c.K.detach().double().cpu().numpy()
        cams.append({"id": i, "img_name": Path(c.name).stem, "width": int(c.width), "height": int(c.height),
                     "position": c2w[:3, 3].tolist(), "rotation": [r.tolist() for r in c2w[:3, :3]],
                     "fy": float(K[1, 1]), "fx": float(K[0, 0])})
    with atomic_write(out_dir / "cameras.json", "w") as f:
        json.dump(cams, f)
    images = f"images_{resolution}" if resolution > 1 and (Path(scene_root) / f"images_{resolution}").is_dir() else "images"
    res = 1 if images != "images" else (resolution if resolution > 1 else -1)
    cfg = (f"Namespace(data_device='cuda', eval=True, images='{images}', model_path='{Path(out_dir).resolve()}', "
           f"resolution={res}, sh_degree={model.sh_degree}, source_path='{Path(scene_root).resolve()}', "
           f"white_background={bool(tuple(background) == (1.0, 1.0, 1.0))})")
    with atomic_write(out_dir / "cfg_args", "w") as f:
        f.write(cfg)
    return [str(rel_ply), "cameras.json", "cfg_args"]


@dataclass
class AdaptOptions:
    """How one ``clod-adapt`` run goes, besides its model, scene, output folder and
    :class:`clod_adapter.train.config.AdaptConfig` (what the fine-tuning is). Checked once, on creation.

    Attributes:
        resolution: scene images at 1/R (``images_R/`` when present).
        device: ``"auto"`` (CUDA when available and gsplat imports), ``"cpu"`` or ``"cuda"``.
        resume: continue from ``out_dir/adapt_state.safetensors`` (same input, scene, resolution
            and settings; ``cfg.iterations`` may differ, which changes the schedule).
        iterations_from_state, views_from_state: with ``resume``, take ``iterations`` /
            ``views_per_step`` from the state instead of ``cfg``.
        progress: a progress display; log: where the job's lines go.
        sanitize: drop Gaussians with NaN/Inf values and clamp +Inf opacity logits
            (:func:`check_finite`) instead of failing on them.
        deterministic: bit-reproducible CPU gradients (a resumed run then ends bit-identical to
            an uninterrupted one with the same seed and thread count).
        force: write into a non-empty output folder. allow_mismatch: go on with a model that
            renders the training views no better than a flat colour (:func:`scene_match`).
        iteration: with an official model folder, ``point_cloud/iteration_N`` (default the largest).
        layout: ``"clod"`` or ``"inria"`` (also the official model folder, :func:`write_inria_layout`).
        tensorboard: log loss, PSNR, s_v, rendered fraction per step to ``out_dir/tensorboard``.
        timing_repeats: interleaved timing rounds of the final ms/frame (:mod:`clod_adapter.evaluate.timing`).
        masks: a MaskGaussian .ply's mask policy (:func:`clod_adapter.io.load.apply_masks`).
        distributed: data-parallel over the processes torchrun started (:mod:`clod_adapter.train.distributed`).
        save_every: also write the resumable state every this many steps (0: only on a signal
            and at the end; None: every 10 % of the run when distributed, else 0).
        holdout_val: fit on the fit views, score on the validation views
            (:func:`clod_adapter.io.scene.holdout_validation`; the test views unused).

    Raises:
        InputError: an unknown ``layout`` or a negative ``save_every``.
    """

    resolution: int = 1
    device: str = "auto"
    resume: bool = False
    progress: bool = True
    log: Callable = print
    sanitize: bool = False
    deterministic: bool = False
    iterations_from_state: bool = False
    force: bool = False
    allow_mismatch: bool = False
    iteration: Optional[int] = None
    layout: str = "clod"
    tensorboard: bool = False
    timing_repeats: int = 3
    masks: str = "auto"
    distributed: bool = False
    save_every: Optional[int] = 0
    views_from_state: bool = False
    holdout_val: bool = False

    def __post_init__(self) -> None:
        if self.save_every is not None and self.save_every < 0:
            raise InputError(f"--save-every must be >= 0, got {self.save_every}")
        if self.layout not in ("clod", "inria"):
            raise InputError(f"--layout must be clod or inria, got {self.layout!r}")


def run(ply_path: os.PathLike, scene_root: os.PathLike, out_dir: os.PathLike, cfg: AdaptConfig,
        options: Optional[AdaptOptions] = None) -> dict:
    """Run the whole job; returns the metrics dict (also written to ``metrics.json``).

    ``ply_path`` is a model file, an official 3DGS model folder (``point_cloud/iteration_N/``,
    the largest N unless ``iteration``) or a folder holding one .ply
    (:func:`clod_adapter.io.load.resolve_model_path`). ``out_dir`` must be empty or new unless
    ``force`` (replace files of the same name) or ``resume``. ``options``: :class:`AdaptOptions`
    (default: its defaults).

    The job runs as named phases, in order: :func:`read_inputs` (load and check every input;
    nothing is written before all of them pass), :func:`_start_state` (the input's quality, the
    initial or resumed state), :func:`_train` (with resumable saves on a signal, at checkpoints
    and at the end), :func:`_evaluate` (the levels and budgets on the test views, timed) and
    :func:`_write_outputs` (each file atomically); with merged tiers (``cfg.parent_share``) then
    :func:`_add_parent_tier` (the tiers, linked into a merge tree) and :func:`_final_levels` (the
    levels and budgets measured on the model as written, tree included, instead of in
    :func:`_evaluate`).

    ``masks``: unknown per-Gaussian .ply properties of the kept Gaussians (e.g. MaskGaussian's
    mask scores) are written back to ``point_cloud.ply`` (not to the exact INRIA copy). With
    ``distributed`` every process calls ``run`` with the same arguments: rank 0 logs, writes
    the state and the outputs and returns the metrics; the other ranks return ``{"rank",
    "world_size", "iteration", "train_seconds"}`` once the final state is written.
    ``metrics.json`` ends with ``job_seconds``: this call's wall time in seconds, every phase and
    merged tier included (a resumed run: from its resumption).

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
        clod_adapter.train.distributed.PeerLost: (``distributed``) another process died or stopped
            answering; the message says which state is on disk.
    """
    o = options if options is not None else AdaptOptions()
    t_job = time.perf_counter()
    with StopFlag(abortable=True) as stop, deterministic_mode(o.deterministic):
        group = None
        try:
            if o.distributed:
                from ..train import distributed as dd

                group = dd.init(pick_device(o.device))
                if not group.is_main:  # rank 0 speaks for the run
                    o = replace(o, log=lambda *a, **k: None, progress=False)
            src, left, first = Path(ply_path), None, None
            if cfg.keep_share < 1.0:  # phase 0: leave out what the scene does not need
                src, left, first = _leave_out(src, Path(scene_root), Path(out_dir), cfg, o, stop, group)
            ro = o if left is None else replace(o, force=True, iteration=None,  # the folder was checked
                                                resume=o.resume and (Path(out_dir) / STATE_NAME).is_file())
            metrics, adapted = _run(src, Path(scene_root), Path(out_dir), cfg, ro, stop, group,
                                    scene=first.scene if first is not None else None, levels="untiered")
            if left is not None and "rank" not in metrics:
                metrics = _record_leave_out(Path(out_dir), metrics, left)
                # the tiers are merged from the input itself, not the kept part (None: phase 0 resumed)
                adapted = replace(adapted, input_model=first.input_model if first is not None else None)
            if cfg.parent_share and "rank" not in metrics:
                metrics, linked = _add_parent_tier(Path(ply_path), Path(scene_root), Path(out_dir), cfg, o, stop,
                                                   group, metrics, adapted=adapted)
                if not metrics["levels"]:  # deferred to the model as written, its tiers attached
                    metrics = _final_levels(Path(out_dir), metrics, linked if linked is not None else adapted.model,
                                            adapted.inputs, cfg, o, stop)
            if "rank" not in metrics:
                metrics = _record_job_seconds(Path(out_dir), metrics, time.perf_counter() - t_job)
            return metrics
        except KeyboardInterrupt:
            if not getattr(stop, "state_saved", False):
                o.log("\nclod-adapt: interrupted before training started; nothing written")
            raise
        finally:
            if group is not None:
                dd.shutdown()


#: the keys of ``metrics.json``, in file order (``wall_seconds`` is added to the returned dict).
METRICS_KEYS = ("version", "input_ply", "scene", "resolution", "image_size", "device", "threads", "num_gaussians",
                "input_sanitized", "input_masks", "faint", "test_views", "holdout_val", "config", "train_seconds",
                "seconds_per_iteration", "world_size", "input_model", "scene_match", "init_s_v1", "deterministic",
                "timing", "levels", "budgets", "dead_sigma_d", "notes")


@dataclass
class _Adapted:
    """What an adaptation (:func:`_run`) or phase 0 (:func:`_leave_out`) hands to the phases after
    it, not to be read again (None: nothing to hand on): ``input_model``, the input as read and
    checked (masks applied, faint Gaussians not left out); ``model``, the adapted model as written
    to ``point_cloud.ply`` (CPU); ``scene``, the job's scene at its resolution (:func:`job_scene`);
    ``inputs``, the adaptation's checked inputs (its test views: :func:`_final_levels`)."""

    input_model: Optional[Gaussians]
    model: Optional[Gaussians]
    scene: Optional[Scene]
    inputs: Optional[Inputs] = None


def _run(ply_path: Path, scene_root: Path, out_dir: Path, cfg: AdaptConfig, o: AdaptOptions, stop: StopFlag,
         group, scene: Optional[Scene] = None, levels: str = "yes") -> tuple[dict, Optional[_Adapted]]:
    """One adaptation of ``ply_path``: ``(its metrics, what it hands to the merged tiers)`` (None on
    a data-parallel rank other than 0). ``scene``: the job's scene at ``o.resolution`` when an
    earlier phase read it. ``levels``: whether :func:`_evaluate` measures the levels and budgets,
    ``"yes"``, ``"no"`` (a merged tier's own run) or ``"untiered"`` (unless the job will build merged
    tiers for the model, :func:`_builds_tiers`: then :func:`_final_levels` measures them)."""
    t_start = time.perf_counter()
    inp = read_inputs(ply_path, scene_root, out_dir, cfg, o, stop, group, scene=scene)
    measure = levels == "yes" or (levels == "untiered" and not _builds_tiers(cfg, len(inp.gaussians), group))
    state, cfg, input_eval, init_s_v1 = _start_state(inp, cfg, o, stop, group)
    meta = {"input_ply": str(inp.ply_path), "scene": str(inp.scene_root), "resolution": o.resolution,
            "input_sha256": inp.input_sha256, "scene_key": inp.scene_fp, "init_s_v1": json.dumps(init_s_v1),
            "deterministic": int(deterministic_enabled()), "threads": torch.get_num_threads(),
            "world_size": 1 if group is None else group.world_size}
    it0 = state.iteration
    train_s = _train(inp, state, cfg, o, stop, group, meta)
    model = state.gaussians().detach()  # the input's unknown .ply properties ride along (state.extra)
    # the final state first: an interrupt during the evaluation resumes at the last iteration
    if inp.main:
        save_state(inp.state_path, state, cfg, meta)
    stop.state_saved = True
    if group is not None:
        group.barrier("the final save")  # the others may leave once the final state is on disk
        if not inp.main:
            return {"rank": group.rank, "world_size": group.world_size, "iteration": state.iteration,
                    "train_seconds": round(train_s, 2)}, None
    stop.set_abortable(True)  # the evaluation writes nothing; raises if a signal came meanwhile
    metrics = _evaluate(inp, model, cfg, o, input_eval, levels=measure)
    stop.set_abortable(False)
    metrics.update({
        "config": asdict(cfg), "train_seconds": round(train_s, 2),
        "seconds_per_iteration": round(train_s / max(state.iteration - it0, 1), 4),
        "world_size": 1 if group is None else group.world_size, "init_s_v1": init_s_v1,
        "dead_sigma_d": int((model.sigma_d <= 0).sum()),
    })
    metrics = {k: metrics[k] for k in METRICS_KEYS}
    if stop.stop:  # a signal just after the evaluation: nothing written yet, stop here
        o.log(f"\nclod-adapt: interrupted after training; state saved to {inp.state_path} (continue with --resume)")
        raise KeyboardInterrupt
    written = _write_outputs(inp, model, state, cfg, o, metrics)
    if stop.stop:
        o.log("clod-adapt: signal received while writing the outputs; they were completed first")
    metrics["wall_seconds"] = round(time.perf_counter() - t_start, 1)
    if measure:
        o.log(format_summary(metrics))
    o.log(f"clod-adapt: wrote {', '.join(written)} to {inp.out_dir} in {metrics['wall_seconds']:.0f} s "
          f"({metrics['seconds_per_iteration']:.3f} s per iteration)")
    return metrics, _Adapted(inp.input_model, model.to("cpu"), inp.scene, inp)


#: phase 0's files (``keep_share < 1``): the kept, recovered input the LoD is learned on, and
#: what :func:`clod_adapter.train.pruning.leave_out` did (read back by ``--resume``)
KEPT_INPUT_NAME = "kept_input.ply"
LEAVE_OUT_NAME = "leave_out.json"


def _leave_out(ply_path: Path, scene_root: Path, out_dir: Path, cfg: AdaptConfig, o: AdaptOptions,
               stop: StopFlag, group) -> tuple[Path, dict, Optional[_Adapted]]:
    """Phase 0 (``cfg.keep_share < 1``, :mod:`clod_adapter.train.pruning`): every input checked as
    :func:`read_inputs` checks it (nothing written before), then the input less what the
    training views need least, recovered, written to ``out_dir/kept_input.ply`` (the input the
    following phases adapt) with ``leave_out.json``. With ``resume`` and both files there, they
    are reused. Returns (the kept input's path, the ``metrics.json`` ``leave_out`` record, the
    input as read and the scene for the phases after it; None when reused).

    Raises:
        InputError: a data-parallel run, or any input :func:`read_inputs` refuses.
    """
    from ..train import pruning

    kept_path, info_path = out_dir / KEPT_INPUT_NAME, out_dir / LEAVE_OUT_NAME
    if group is not None:
        raise InputError("--keep-share is not available in a data-parallel run: leave out in a single-process "
                         f"run first (its {KEPT_INPUT_NAME} is a plain input)")
    if o.resume and kept_path.is_file() and info_path.is_file():
        o.log(f"clod-adapt: resuming with the kept input {kept_path}")
        return kept_path, json.loads(info_path.read_text()), None
    inp = read_inputs(ply_path, scene_root, out_dir, cfg, replace(o, resume=False), stop, group)
    input_eval = evaluate_level(inp.gaussians, inp.test_cams, inp.test_imgs, None, background=cfg.background)
    kept, info = pruning.leave_out(inp.gaussians, inp.scene.train, inp.train_imgs, keep_share=cfg.keep_share,
                                   recovery_steps=cfg.recovery_steps, background=cfg.background, seed=cfg.seed,
                                   progress=o.progress, log=lambda m: o.log("clod-adapt: " + m))
    record = {**info.as_dict(), "input_ply": str(inp.ply_path), "kept_ply": str(kept_path),
              "input_test": {"psnr": input_eval.psnr, "ssim": input_eval.ssim}}
    o.log(f"clod-adapt: leave out: {len(kept):,} of {len(inp.gaussians):,} Gaussians kept in {info.seconds:.0f} s "
          f"(the input's test PSNR {input_eval.psnr:.2f} dB; the kept model's is the adaptation's input_model)")
    # the adaptation reads the kept input back from its file, as a resumed run does: both adapt
    # what the file holds (float32, no sigma_d), and the state's input hash is the file's
    write_ply(kept_path, kept.to("cpu"))
    with atomic_write(info_path, "w") as f:
        json.dump(record, f, indent=2)
    return kept_path, record, _Adapted(inp.input_model.to("cpu"), None, inp.scene)


def _rewrite_metrics(out_dir: Path, metrics: dict) -> None:
    """``out_dir/metrics.json`` rewritten atomically from ``metrics`` (all but ``wall_seconds``,
    which the returned dict alone carries)."""
    with atomic_write(out_dir / METRICS_NAME, "w") as f:
        json.dump({k: v for k, v in metrics.items() if k != "wall_seconds"}, f, indent=2)


def _record_leave_out(out_dir: Path, metrics: dict, record: dict) -> dict:
    """``metrics.json`` with phase 0's record (``leave_out``, plus ``kept_test``: the kept model's
    test quality, the adaptation's ``input_model``) and ``input_ply`` the input given, not the
    kept one the phases after it read."""
    kept = {k: metrics["input_model"][k] for k in ("psnr", "ssim")}
    metrics = {**metrics, "input_ply": record["input_ply"], "leave_out": {**record, "kept_test": kept}}
    _rewrite_metrics(out_dir, metrics)
    return metrics


def _record_job_seconds(out_dir: Path, metrics: dict, seconds: float) -> dict:
    """``metrics.json`` with ``job_seconds``: the whole job's wall time (every phase and tier)."""
    metrics = {**metrics, "job_seconds": round(seconds, 1)}
    _rewrite_metrics(out_dir, metrics)
    return metrics


PARENT_DIR = "parents"
PARENT_INPUT_NAME = "parents_input.ply"


def _builds_tiers(cfg: AdaptConfig, n: int, group) -> bool:
    """Whether the job goes on to build merged tiers (:func:`_add_parent_tier`) for a model of ``n``
    Gaussians: ``cfg.parent_share`` set, ``n`` at least
    :data:`clod_adapter.train.tiers.PARENT_MIN_GAUSSIANS`, no data-parallel group."""
    from ..train.tiers import PARENT_MIN_GAUSSIANS

    return bool(cfg.parent_share) and n >= PARENT_MIN_GAUSSIANS and group is None


def _add_parent_tier(ply_path: Path, scene_root: Path, out_dir: Path, cfg: AdaptConfig, o: AdaptOptions,
                     stop: StopFlag, group, metrics: dict, nested: bool = False,
                     adapted: Optional[_Adapted] = None) -> tuple[dict, Optional[Gaussians]]:
    """Phase 6 (``cfg.parent_share``, :mod:`clod_adapter.train.tiers`): the input merged by
    splat-transform to the first of ``parent_share`` of its Gaussians (lowered while the merge is
    predicted to draw over ``tier_time_cap`` of the input's frame: :func:`clod_adapter.train.tiers.first_share`;
    ``out_dir/parents_input.ply``),
    fine-tuned and adapted (the second and later tiers at 1/``cfg.tier_downscale`` of the
    resolution, :meth:`AdaptConfig.tier_resolution`) by the same job into ``out_dir/parents/`` (its
    own state, metrics (untimed) and strip, and the
    next shares as its own parent tiers, ``out_dir/parents/parents/``, ...), and attached to
    ``point_cloud.ply`` where it beats the model at equal predicted frame time on the training
    views (:func:`clod_adapter.train.tiers.choose`; a merged tier's own hand-over at its
    ``cfg.tier_hand_over`` at the latest, :func:`clod_adapter.train.tiers.link`). Left out, with a note
    in ``metrics["tier"]``, for an input under :data:`clod_adapter.train.tiers.PARENT_MIN_GAUSSIANS`
    Gaussians, a data-parallel run, or without splat-transform. ``adapted``: what the adaptation of
    ``ply_path`` into ``out_dir`` handed on (its input, model and scene; each read from disk where
    missing). Returns ``(metrics, the model as written with its tier attached, or None when none was)``."""
    from ..train import tiers

    t0 = time.perf_counter()
    n = int(metrics["num_gaussians"])
    share, rest = cfg.parent_share[0], cfg.parent_share[1:]
    tres = cfg.tier_resolution(o.resolution) if nested else o.resolution  # trained at it, linked at o's
    info = {"parent_share": share, "used": False, "resolution": tres}

    def done(why: Optional[str] = None, linked=None) -> tuple[dict, Optional[Gaussians]]:
        if why:
            info["why"] = why
            o.log(f"clod-adapt: no merged tier: {why}")
        info["seconds"] = round(time.perf_counter() - t0, 1)
        metrics["tier"] = info
        _rewrite_metrics(out_dir, metrics)
        return metrics, linked

    if n < tiers.PARENT_MIN_GAUSSIANS and not nested:  # a tier's own tiers: the input's size decided
        return done(f"{n:,} Gaussians, under {tiers.PARENT_MIN_GAUSSIANS:,}")
    if group is not None:
        return done("not built in a data-parallel run")
    quiet = replace(o, log=lambda *a, **k: None)
    adapted = adapted if adapted is not None else _Adapted(None, None, None)
    scene = fresh_scene(adapted.scene) if adapted.scene is not None else job_scene(scene_root, cfg, o)
    cams = tiers.choice_views(scene.train)
    try:
        source = adapted.input_model
        if source is None:  # the input was not handed on (a resumed leave-out adapted another file)
            source = read_model(resolve_model_path(ply_path, o.iteration), cfg, quiet)[0]
        share, parents_in = _tier_start(source.to("cpu"), share, rest, scene.train, cams, cfg, o, nested, info)
        del source
    except RuntimeError as e:
        return done(f"splat-transform: {e}")
    tscene = scene if tres == o.resolution else job_scene(scene_root, cfg, replace(o, resolution=tres))
    parents_in = _finetuned_tier(parents_in, tscene, cfg, info)
    # the tier adapts its input read back from the file, as a resumed tier does: both adapt what
    # the file holds, and the tier's state names the file's hash
    write_ply(out_dir / PARENT_INPUT_NAME, parents_in)
    pdir = out_dir / PARENT_DIR
    o.log(f"clod-adapt: parent tier: {len(parents_in):,} Gaussians ({_MERGE_NAMES[_merge(cfg, nested)]}"
          f"{f', fine-tuned {cfg.tier_finetune_steps} steps' if cfg.tier_finetune_steps else ''}), "
          f"adapting them into {pdir} ...")
    # the merged input derives from the checked one: no second scene check (a coarse merge may
    # not clear its margin on a tiny model)
    # untimed: nothing reads a tier's own ms/frame (the top job times the linked model)
    po = replace(o, resume=o.resume and (pdir / STATE_NAME).is_file(), force=True, allow_mismatch=True,
                 log=lambda *a, **k: o.log("  [parents]", *a, **k), iteration=None, timing_repeats=0, resolution=tres)
    pcfg = replace(cfg, parent_share=tuple(x / share for x in rest), keep_share=1.0, faint_share=0.0,
                   iterations=cfg.tier_iterations(), tier_iteration_share=1.0,
                   tier_downscale=1 if nested else cfg.tier_downscale)  # the nested call downscales once
    pm, p_adapted = _run(out_dir / PARENT_INPUT_NAME, scene_root, pdir, pcfg, po, stop, None, scene=tscene,
                         levels="no")
    if pcfg.parent_share:  # the tier's own parent tiers, shares relative to it
        _add_parent_tier(out_dir / PARENT_INPUT_NAME, scene_root, pdir, pcfg, po, stop, None, pm, nested=True,
                         adapted=p_adapted)
    # the tiers below are read from their files: each with its own tiers attached and their settings
    # as a file stores them (written after their own linking), found in the folders as a resume finds them
    model = adapted.model if adapted.model is not None else _read_own(out_dir / PLY_NAME)
    parents = _read_own(pdir / PLY_NAME)
    imgs = [scene.load_image(c) for c in cams]
    dirs = _tier_dirs(pdir)
    cands = [parents] + [_read_own(d / PLY_NAME) for d in dirs[1:]]
    linked, tried = tiers.link(model, cands, cams, imgs, background=cfg.background,
                               max_tier_s_v=cfg.tier_hand_over if nested else 0.0,
                               log=lambda m: o.log("clod-adapt: " + m))
    for t in tried:
        t["dir"] = str(dirs[t["candidate"]].relative_to(out_dir))
    info.update({"parents": len(parents), "curves": tried[0]["curves"], "views": len(cams), "tried": tried})
    if linked.parents is None:
        return done("no merged tier beats the model at equal predicted time on the training views")
    if not nested:
        linked = _drawing_rule(linked, out_dir, scene, cfg, o, info)
    write_ply(out_dir / PLY_NAME, linked)
    st = linked.lod
    info.update({"used": True, "tier_s_v": st.tier_s_v, "tier_start": st.tier_start, "attached": len(linked.parents),
                 "attached_dir": tried[-1]["dir"]})
    o.log(f"clod-adapt: merged tier of {len(linked.parents):,} attached to {out_dir / PLY_NAME} (from s_v = "
          f"{st.tier_s_v:g}) in {time.perf_counter() - t0:.0f} s")
    return done(linked=linked)


#: how each merge is named in the log
_MERGE_NAMES = {"decimate": "splat-transform --decimate", "adaptive": "splat-transform --decimate-adaptive",
                "prune": "the input less its least blending weight per cost"}


def _merge(cfg: AdaptConfig, nested: bool) -> str:
    """The merge a tier starts from: ``cfg.tier_merge``, but ``"decimate"`` below a pruned first tier."""
    return "decimate" if nested and cfg.tier_merge == "prune" else cfg.tier_merge


def _tier_start(source, share: float, rest: tuple, train: Sequence, cams: Sequence, cfg: AdaptConfig,
                o: AdaptOptions, nested: bool, info: dict):
    """``(share, the tier's starting Gaussians)``: a tier's own tiers merged at ``share`` of it; the
    first tier cut or merged by ``cfg.tier_merge`` at the share :func:`clod_adapter.train.tiers.first_share`
    settles on (``info`` records the tries), the cut scored on ``train`` (the training views).
    With later tiers (``rest``) splat-transform must be found first, whatever the first tier is.

    Raises:
        RuntimeError: splat-transform is missing or fails."""
    from ..io.splat_transform import require_splat_transform
    from ..train import tiers

    if nested:  # a tier's own tiers: shares relative to it, as the first tier's share left them
        return share, tiers.decimated(source, share, merge=_merge(cfg, nested))
    if rest:  # the later tiers are merges: without splat-transform no tier is built, as with a merged first one
        require_splat_transform()
    weights = tiers.prune_scores(source, train) if cfg.tier_merge == "prune" else None
    share, parents_in, tried = tiers.first_share(
        source, share, cams, cap=cfg.tier_time_cap, floor=rest[0] if rest else 0.0, merge=cfg.tier_merge,
        weights=weights, log=lambda m: o.log("clod-adapt: " + m))
    info.update({"parent_share": share, "time_cap": {"cap": cfg.tier_time_cap, "tried": tried}})
    return share, parents_in


def _read_own(path: Path):
    """A model ``clod-adapt`` wrote in this run's folders, as written: a merged tier's own file holds
    the tiers below it attached, not linked into a merge tree (only the top model's are,
    :func:`_drawing_rule`), so it is read with ``read_ply(unlinked_tiers=True)``."""
    return read_ply(path, unlinked_tiers=True)


def _drawing_rule(linked, out_dir: Path, scene, cfg: AdaptConfig, o: AdaptOptions, info: dict):
    """The linked model's tiers as a merge tree (:func:`clod_adapter.lod.tree.build`;
    ``info["tree"]`` its tiers' sizes), its merged tiers fitted on its cuts
    (:func:`clod_adapter.train.tree_fit.finetune`, ``cfg.tree_steps`` at most ``cfg.iterations``,
    ``cfg.tree_budget_steps`` of them on budget cuts, the merged nodes' scales grown by at most
    ``cfg.tree_grow`` but for ``cfg.tree_free_roots`` of the roots; ``info["tree_fit"]``) and
    ``lod_strip.png`` redrawn through it."""
    from ..lod import tree
    from ..train.tree_fit import finetune

    linked = tree.build(linked, scene.train, log=lambda m: o.log("clod-adapt: " + m), spread=cfg.tree_spread,
                        exit_toward_parent=cfg.tree_exit_toward_parent,
                        entry_toward_children=cfg.tree_entry_toward_children)
    info["tree"] = [len(t) for t in tree.tiers_of(linked)]
    steps, t0 = min(cfg.tree_steps, cfg.iterations), time.perf_counter()
    linked = finetune(linked, scene.train, [scene.load_image(c) for c in scene.train], steps,
                      background=cfg.background, seed=cfg.seed, budget_steps=cfg.tree_budget_steps,
                      grow=cfg.tree_grow, free_roots=cfg.tree_free_roots,
                      log=lambda m: o.log("clod-adapt: " + m))
    info["tree_fit"] = {"steps": steps, "budget_steps": cfg.tree_budget_steps, "grow": cfg.tree_grow,
                        "free_roots": cfg.tree_free_roots, "seconds": round(time.perf_counter() - t0, 1)}
    _final_strip(out_dir, linked, scene, cfg)
    return linked


def _final_strip(out_dir: Path, model, scene, cfg: AdaptConfig) -> None:
    """``lod_strip.png`` of the model with its tree attached: the first test view of the job's
    ``scene`` (a validation view with ``holdout_val``) from ``s_v = 1`` to past the coarsest tier's
    reach, doubling."""
    from ..lod.draw import tier_reach
    from ..export.figures import write_strip

    cam = (scene.test or scene.train[:1])[0]
    top = cfg.max_sv * tier_reach(model)
    levels = [2.0 ** i for i in range(int(math.log2(top)) + 1)][:7]
    write_strip(out_dir / STRIP_NAME, model, cam, levels, cfg.background, gt=scene.load_image(cam))


def _finetuned_tier(parents_in, scene, cfg: AdaptConfig, info: dict):
    """A merge fine-tuned for ``cfg.tier_finetune_steps`` on ``scene``'s training views, at most
    ``cfg.iterations`` (:func:`clod_adapter.train.tiers.finetuned`; ``info["finetune"]`` notes steps and
    seconds)."""
    from ..train import tiers

    steps = min(cfg.tier_finetune_steps, cfg.iterations)  # --iterations bounds every stage of the job
    if steps <= 0:
        return parents_in
    t1 = time.perf_counter()
    out = tiers.finetuned(parents_in, scene.train, [scene.load_image(c) for c in scene.train],
                          steps, background=cfg.background, seed=cfg.seed)
    info["finetune"] = {"steps": steps, "seconds": round(time.perf_counter() - t1, 1)}
    return out


def _tier_dirs(pdir: Path) -> list[Path]:
    """The adapted tiers below a model: ``pdir`` (its first tier), ``pdir/parents``, ... while
    they hold an adapted model."""
    out = []
    while (pdir / PLY_NAME).is_file():
        out.append(pdir)
        pdir = pdir / PARENT_DIR
    return out


def _start_state(inp: Inputs, cfg: AdaptConfig, o: AdaptOptions, stop: StopFlag, group):
    """Phase 2: the input's quality on the test views, then the initial state (:func:`prepare`)
    or the resumed one. Returns (state, cfg (the state's, when resumed), input evaluation, the
    initial model's s_v = 1 quality)."""
    bg = cfg.background
    input_eval = (evaluate_level(inp.input_model, inp.test_cams, inp.test_imgs, None, background=bg)
                  if inp.main else None)
    # from here on a signal only sets the flag: the state is saved at the next safe point
    stop.set_abortable(False)
    if inp.resumed is not None:
        state, cfg, saved_meta = inp.resumed
        state.extra = dict(inp.gaussians.extra)  # not in the state file: the input's, as at the start
        o.log(f"clod-adapt: resuming {inp.state_path} at iteration {state.iteration}/{cfg.iterations}")
        init_s_v1 = json.loads(saved_meta.get("init_s_v1", "null"))
    else:
        state = prepare(inp.gaussians, inp.scene.train, cfg, inp.train_imgs)
        if "attenuation" in state.init:
            o.log(f"clod-adapt: sigma_d initialised with attenuation {state.init['attenuation']} at s_v = 1")
        elif not state.init:
            o.log("clod-adapt: the input already has sigma_d: fine-tuning it as it is")
        else:
            o.log(f"clod-adapt: sigma_d calibrated from the {state.init.get('ranking')} ranking on quantiles of "
                  f"cost^{state.init.get('cost_exponent')} (levels in frame cost and count)")
        init_s_v1 = None
        if inp.main:
            init_eval = evaluate_level(state.gaussians().detach(), inp.test_cams, inp.test_imgs, 1.0,
                                       tau=cfg.tau, background=bg)
            init_s_v1 = {"psnr": init_eval.psnr, "ssim": init_eval.ssim,
                         "psnr_drop_db": input_eval.psnr - init_eval.psnr, **state.init}
    if group is not None:
        from ..train.distributed import broadcast_params

        broadcast_params(state, group)  # every rank starts from rank 0's parameters
    return state, cfg, input_eval, init_s_v1


def _step_hooks(inp: Inputs, cfg: AdaptConfig, o: AdaptOptions, stop: StopFlag, group, meta: dict,
                saved: dict):
    """(called after each step or None, the tensorboard writer or None): periodic saves
    (``save_every``), the test hook's progress file, tensorboard scalars."""
    save_every = o.save_every
    if save_every is None:
        save_every = max(1, cfg.iterations // 10) if group is not None else 0
    hooks = []
    if save_every and inp.main:
        def checkpoint(st):
            if st.iteration % save_every == 0 and st.iteration < cfg.iterations:
                save_state(inp.state_path, st, cfg, meta)
                saved["iteration"] = st.iteration
                stop.state_saved = True
        hooks.append(checkpoint)
    if os.environ.get(PROGRESS_FILE_ENV) and inp.main:
        hook_path = Path(os.environ[PROGRESS_FILE_ENV])
        hooks.append(lambda st: hook_path.write_text(f"{st.iteration}\n"))
    writer = None
    if o.tensorboard and inp.main:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(log_dir=str(inp.out_dir / TENSORBOARD_DIR))

        def tb_step(st):
            h = st.history
            for key in ("loss", "psnr", "eta", "s_v"):
                if h.get(key):
                    writer.add_scalar(f"train/{'rendered_fraction' if key == 'eta' else key}", h[key][-1], st.iteration)
        hooks.append(tb_step)
    if not hooks:
        return None, writer

    def on_step(st):
        for f in hooks:
            f(st)
    return on_step, writer


def _train(inp: Inputs, state, cfg: AdaptConfig, o: AdaptOptions, stop: StopFlag, group, meta: dict) -> float:
    """Phase 3: the fine-tuning (:func:`clod_adapter.train.loop.fit`) with its saves; returns its
    seconds. Raises KeyboardInterrupt when a signal stopped it (the state saved first)."""
    saved = {"iteration": state.iteration if o.resume else None}  # the state on disk

    def on_interrupt(st):
        if inp.main:
            save_state(inp.state_path, st, cfg, meta)
            saved["iteration"] = st.iteration
        stop.state_saved = True
        o.log(f"\nclod-adapt: interrupted at iteration {st.iteration}; state saved to {inp.state_path} "
              f"(continue with --resume)")

    on_step, writer = _step_hooks(inp, cfg, o, stop, group, meta, saved)
    t_train = time.perf_counter()
    try:
        finished = fit(state, inp.scene.train, inp.train_imgs, cfg, progress=o.progress,
                         on_interrupt=on_interrupt, stop=stop, on_step=on_step, group=group)
        if group is not None and finished:
            from ..train.distributed import check_in_sync

            check_in_sync(state, group)
    except Exception as e:
        from ..train.distributed import PeerLost

        if isinstance(e, PeerLost):
            how = "continue with --resume, with any number of processes"
            if not inp.main:
                what = f"{inp.state_path} holds the last state rank 0 saved ({how})"
            elif saved["iteration"] is not None:
                what = f"{inp.state_path} holds iteration {saved['iteration']} ({how})"
            else:
                what = "no state was saved"
            raise PeerLost(f"{e}; {what}") from None
        raise
    finally:
        if writer is not None:
            writer.close()
    if not finished:
        raise KeyboardInterrupt
    return time.perf_counter() - t_train


def _evaluate(inp: Inputs, model, cfg: AdaptConfig, o: AdaptOptions, input_eval, levels: bool = True) -> dict:
    """Phase 4: the metrics dict (without the run's training facts, which :func:`_run` adds): the
    input's quality and, with ``levels``, the adapted model at every level and budget on the test
    views, the input and the levels timed in interleaved rounds
    (:func:`clod_adapter.jobs.adapt_levels.level_metrics`); without, empty ``levels`` and ``budgets`` (a merged tier's own run; the top job's when its tiers are
    built, which :func:`_final_levels` measures once they are attached)."""
    input_model = {"psnr": input_eval.psnr, "ssim": input_eval.ssim,
                   "gaussians": input_eval.gaussians, "ms_per_frame": input_eval.ms_per_frame}
    metrics = {
        "version": __version__, "input_ply": str(inp.ply_path), "scene": str(inp.scene_root),
        "resolution": o.resolution, "image_size": list(inp.size), "device": str(inp.dev),
        "threads": torch.get_num_threads(), "num_gaussians": len(model), "input_sanitized": inp.sanitized,
        "input_masks": asdict(inp.mask_info) if inp.mask_info is not None else None, "faint": inp.faint,
        "test_views": [c.name for c in inp.test_cams], "holdout_val": bool(o.holdout_val),
        "input_model": input_model, "scene_match": inp.match,
        "deterministic": bool(deterministic_enabled()),
        "timing": {"method": "none", "repeats": 0, "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
                   "what": "levels not measured"},
        "levels": [], "budgets": [], "notes": inp.notes,
    }
    return level_metrics(inp, model, cfg, o, metrics) if levels else metrics


def _final_levels(out_dir: Path, metrics: dict, model, inp: Inputs, cfg: AdaptConfig, o: AdaptOptions,
                  stop: StopFlag) -> dict:
    """Phase 7 (a job that may build merged tiers): the levels and budgets of ``model``, as written
    to ``point_cloud.ply`` (the merge tree when a tier was attached, else the model alone), on the
    test views of ``inp``, timed (:func:`clod_adapter.jobs.adapt_levels.level_metrics`);
    ``metrics.json`` rewritten and the summary logged. A signal meanwhile stops it at once (the outputs are written; ``metrics.json`` then
    has no levels)."""
    stop.set_abortable(True)
    metrics = level_metrics(inp, model.to(inp.dev), cfg, o, metrics)
    stop.set_abortable(False)
    _rewrite_metrics(out_dir, metrics)
    o.log(format_summary(metrics))
    return metrics


def _write_outputs(inp: Inputs, model, state, cfg: AdaptConfig, o: AdaptOptions, metrics: dict) -> list:
    """Phase 5: every output, each atomically (a signal from here on only lets them complete);
    returns the names written."""
    bg = cfg.background
    written = [PLY_NAME, STATE_NAME, METRICS_NAME, STRIP_NAME, TRAINING_PLOT_NAME]
    write_ply(inp.out_dir / PLY_NAME, model.to("cpu"))
    with atomic_write(inp.out_dir / METRICS_NAME, "w") as f:
        json.dump(metrics, f, indent=2)
    write_strip(inp.out_dir / STRIP_NAME, model, inp.test_cams[0], sv_levels(cfg.max_sv), bg,
                gt=inp.test_imgs[0])
    write_training_plot(inp.out_dir / TRAINING_PLOT_NAME, state.history, cfg.max_sv, cfg.views_per_step)
    if o.layout == "inria":
        it_n = (input_iteration(inp.ply_path) or 0) + state.iteration
        written += write_inria_layout(inp.out_dir, model, inp.scene, iteration=it_n, resolution=o.resolution,
                                      background=bg, scene_root=inp.scene_root)
    if o.tensorboard:
        written.append(TENSORBOARD_DIR + "/")
    return written


#: test hook (undocumented for users): write the iteration number to this file after each step.
PROGRESS_FILE_ENV = "CLOD_PROGRESS_FILE"


@contextlib.contextmanager
def deterministic_mode(on: bool = True):
    """Within the block: the C++ compositor's deterministic backward and
    ``torch.use_deterministic_algorithms(True, warn_only=True)``; restored afterwards."""
    if not on:
        yield
        return
    from ..render import composite

    prev = composite.deterministic_override()
    prev_alg = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    composite.set_deterministic(True)
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        composite.set_deterministic(prev)
        torch.use_deterministic_algorithms(prev_alg, warn_only=prev_warn)
