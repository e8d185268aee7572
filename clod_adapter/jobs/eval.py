"""The ``clod-eval`` report: what each level of detail costs and what it loses, against baselines.

:func:`evaluate_report` renders the test views of a scene with

* ``clod``: the adapted model over a grid of ``s_v`` (1 to past the trained maximum);
* ``clod_budget``: the adapted model at hard budgets, ``s_v`` solved exactly per view
  (:mod:`clod_adapter.lod.budget`);
* ``constant_sigma``, ``lightgaussian``, ``random``: baselines from the pretrained model at the
  *same per-view Gaussian counts* as ``clod_budget`` (:mod:`clod_adapter.lod.rankings`);
* ``merge`` (when splat-transform is available): the pretrained model simplified to the budget's
  share of the model by the merging decimator viewers ship (:func:`clod_adapter.lod.rankings.merge_decimate`),
  every Gaussian in view drawn;
* ``dlod_finetuned`` (``dlod_iterations > 0``): the per-budget ceiling, one model per level: the
  pretrained model cut to the budget by the best static ranking of this report, fine-tuned on the
  training views (:mod:`clod_adapter.train.finetune`); its storage is the sum of the levels;
* ``pretrained``: the pretrained model in full (reference);

then runs the quality-against-frame-time comparison with the peers a user already has
(:func:`clod_adapter.evaluate.comparison.compare`, the same code as ``benchmarks/quality_vs_time.py``:
the adapted model along ``s_v`` and at cost budgets, LightGaussian and opacity cuts, the
decimators, the equal-count points; its one-paragraph verdict opens ``report.md``);
scores each render (PSNR, SSIM in the 3DGS form, LPIPS-alex when weights exist), times it
(:mod:`clod_adapter.evaluate.timing`: after the quality pass, which warms up, ``timing_repeats`` rounds
render every method x setting x view once in a shuffled order, so load from other processes hits
all methods alike; ms = median over rounds of the median over views, split into LoD selection
and rasterisation, with the smallest and largest round as the spread) and measures popping
(:func:`popping_curve`). Outputs in ``out_dir`` (each written atomically):

* ``report.csv``: one row per method x setting, aggregated over views (:data:`CSV_COLUMNS`);
* ``report_per_view.csv``: one row per method x setting x view (:data:`PER_VIEW_COLUMNS`);
* ``report.json``: the rows, the popping measurement, the settings and notes;
* ``quality_vs_time.png`` (PSNR against the share of the input's frame time, the comparison's
  every method and frontier), ``quality_vs_time.csv`` (its every point);
* ``report.md``: the verdict and the comparison's cells, then the tables per budget and level;
* ``quality_vs_gaussians.png``, ``levels_vs_time.png`` (the levels and budgets above against
  ms), ``popping.png``, ``lod_strip.png``.

CSV columns (fixed order; empty cell = not applicable / unavailable):

=========== ====================================================================================
method      ``clod`` | ``clod_budget`` | ``constant_sigma`` | ``lightgaussian`` | ``random`` |
            ``merge`` | ``dlod_finetuned`` | ``pretrained``
setting     ``s_v=<x>``, ``budget=<b>`` (b <= 1: fraction of the model; integer > 1: count) or
            ``full``
s_v         virtual distance scale (mean over views of the solved one in budget modes)
budget      the requested budget (fraction or count), empty for s_v sweeps
gaussians   mean number of Gaussians handed to the rasteriser per view
fraction    ``gaussians`` / size of the rendered model
psnr, ssim  mean over views (dB; 3DGS SSIM)
lpips       mean LPIPS-alex v0.1 over views (empty without weights)
ms_total    ms_select + ms_raster per frame: median over timing rounds of the median over views (ms)
ms_select   LoD selection / baseline selection time, the same medians (ms)
ms_raster   rasterisation time, the same medians (ms)
bytes       mean bytes of the rendered subset: gaussians x 4 x properties of the .ply layout
            (float32; 62 properties for SH degree 3 with normals, +1 for ``sigma_d`` for the
            adapted model)
views       number of views aggregated (per-view CSV: ``view``, the image name, instead)
ms_min      smallest per-round ms_total (the spread of the timing; = ms_total with one round)
ms_max      largest per-round ms_total
=========== ====================================================================================
"""
from __future__ import annotations

import json
import math
import os
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from .. import __version__
from ..errors import InputError
from ..lod import rule as lod
from ..evaluate import comparison as qvt
from ..train.state import max_sv_from_state
from ..lod.rankings import (SIGMA_C_CANDIDATES, Selection, lightgaussian_significance, random_scores, render_subset,
                            tune_sigma_c)
from ..lod.budget import Budget, normalize_budget
from ..gaussians import Gaussians
from ..io.atomic import atomic_write
from ..io.ply import read_ply
from ..evaluate.storage import ply_bytes, ply_row_bytes
from ..lod.draw import PAPER, render_lod, tier_reach
from ..evaluate.popping import SWEEP_OVERSHOOT, SWEEP_STEPS, image_change, popping_curve, popping_sweep  # noqa: F401 (clod-eval's popping)
from ..metrics import psnr, ssim
from .eval_methods import BASELINES, DECIMATORS, METHOD_REGISTRY, RankingContext
from .eval_report import csv_text, format_markdown, format_table, jsonable, plot_popping, plot_quality, \
    plot_time_curve


CSV_COLUMNS = ("method", "setting", "s_v", "budget", "gaussians", "fraction", "psnr", "ssim", "lpips",
               "ms_total", "ms_select", "ms_raster", "bytes", "views", "ms_min", "ms_max")


PER_VIEW_COLUMNS = ("method", "setting", "view", "s_v", "budget", "gaussians", "fraction", "psnr", "ssim",
                    "lpips", "ms_total", "ms_select", "ms_raster", "bytes")


OUTPUT_NAMES = ("report.csv", "report_per_view.csv", "report.json", "report.md", "quality_vs_gaussians.png",
                "levels_vs_time.png", "quality_vs_time.png", "quality_vs_time.csv", "popping.png", "lod_strip.png")


DEFAULT_BUDGETS = (1.0, 0.5, 0.25, 0.1)
LpipsSpec = Union[str, os.PathLike, Callable, None]


# --- small helpers ----------------------------------------------------------------------------
def sv_grid(max_sv: float, steps: int = 25, overshoot: float = SWEEP_OVERSHOOT, lod_settings=None,
            tier_steps: int = 6, reach: Optional[float] = None) -> list[float]:
    """``steps`` values of ``s_v`` evenly spaced from 1 to ``overshoot * max_sv`` (past the
    trained maximum); for a model with merged tiers (``lod_settings.tier_s_v > 0``, docs/method.md
    "Merged tiers") then ``tier_steps`` values spaced evenly in ``ln s_v`` from the middle of its
    first hand-over (``tier_s_v sqrt(tier_fade)``) to where the last tier is at ``overshoot`` times
    its own ``max_sv`` (``overshoot max_sv reach``, ``reach`` :func:`clod_adapter.lod.draw.tier_reach`;
    default ``tier_fade tier_s_v / tier_start``, one tier), those beyond the even part."""
    if steps < 2:
        raise ValueError(f"need at least 2 s_v steps, got {steps}")
    if not max_sv >= 1:
        raise ValueError(f"max_sv must be >= 1, got {max_sv}")
    top = max(overshoot * max_sv, 1.0 + 1e-3)
    grid = [float(x) for x in np.linspace(1.0, top, steps)]
    st = lod_settings
    if st is not None and st.tier_s_v > 0:
        lo = st.tier_s_v * math.sqrt(st.tier_fade)
        hi = overshoot * max_sv * (reach if reach else st.tier_fade * st.tier_s_v / st.tier_start)
        grid += [float(x) for x in np.geomspace(lo, max(hi, lo), tier_steps) if x > top * (1 + 1e-9)]
    return grid


def budget_label(b: float | int) -> str:
    """The CSV ``setting`` of a budget: ``budget=0.5`` (fraction) or ``budget=5000`` (count)."""
    return f"budget={b:g}" if isinstance(b, float) else f"budget={int(b)}"


def normalize_budgets(budgets: Sequence) -> list:
    """Budgets as floats in [0, 1] (fractions) or ints > 1 (counts)
    (:func:`clod_adapter.lod.budget.normalize_budget` each). Raises ValueError."""
    return [normalize_budget(b) for b in budgets]


def resolve_lpips(spec: LpipsSpec) -> tuple[Optional[Callable], str]:
    """LPIPS scorer and a note. ``spec``: ``"auto"`` (argument-less
    :func:`clod_adapter.evaluate.lpips.load_lpips`: ``$CLOD_LPIPS_WEIGHTS``, then the user cache),
    a weights path, a callable ``f(img [H,W,3], gt [H,W,3]) -> scalar``, or None (skip)."""
    if spec is None:
        return None, "LPIPS skipped (disabled)"
    if callable(spec):
        return spec, "LPIPS from a caller-supplied model"
    try:
        from ..evaluate import lpips as lp
    except ImportError as e:
        return None, f"LPIPS skipped: clod_adapter.evaluate.lpips unavailable ({e})"
    path = None if spec == "auto" else spec
    model = lp.load_lpips(path)
    if model is None:
        return None, f"LPIPS skipped: {lp.lpips_unavailable_reason()}"
    src = lp.resolve_weights_path(path)
    return model, f"LPIPS-alex v0.1 from {src[0]} ({src[1]})"


# --- one render, one score ------------------------------------------------------------------
@dataclass
class Sample:
    """One rendered view: image [H, W, 3], Gaussians rendered, solved/used s_v, times (ms:
    ``select_ms`` everything before the rasteriser, the projection of a plain frame included)."""

    image: Tensor
    n: int
    s_v: Optional[float]
    select_ms: float
    raster_ms: float
    again: Optional[Callable[[], "Sample"]] = None  # the same render again (for the timing rounds)


def _sample(fn: Callable[[], Sample]) -> Sample:
    """Run a render once and remember how to repeat it (:mod:`clod_adapter.evaluate.timing`)."""
    s = fn()
    s.again = fn
    return s


def _render_selection(g: Gaussians, cam, sel: Selection, bg) -> Sample:
    r = render_subset(g, cam, sel.indices, sel.opacities, background=bg, view=sel.view)
    return Sample(r.image, r.n_rendered, sel.s_v, sel.select_ms, r.raster_ms)


def _render_lod(g: Gaussians, cam, bg, tau, s_v=None, budget=None) -> Sample:
    # clod-eval's --budgets: fractions are shares of the Gaussians in view, integers counts
    if budget is not None:
        budget = Budget(in_view=budget) if isinstance(budget, float) else Budget(count=int(budget))
    out = render_lod(g, cam, s_v, budget=budget, tau=tau, background=bg, eta_grad=PAPER)
    return Sample(out.image, out.n_rendered, out.s_v, out.lead_ms, out.raster_ms)  # the projection too


@dataclass
class _Rows:
    per_view: list = field(default_factory=list)
    rows: list = field(default_factory=list)
    redo: dict = field(default_factory=dict)  # row index -> per-view render callables (timing)


def _score(rows: _Rows, method: str, setting: str, budget, samples: list[Sample], cams, gts,
           n_model: int, bpg: int, lpips_fn) -> dict:
    pv = []
    for s, cam, gt in zip(samples, cams, gts):
        img = s.image.clamp(0, 1)
        lp = None
        if lpips_fn is not None:
            with torch.no_grad():
                lp = float(lpips_fn(img, gt))
        pv.append({"method": method, "setting": setting, "view": cam.name, "s_v": s.s_v, "budget": budget,
                   "gaussians": s.n, "fraction": s.n / max(n_model, 1), "psnr": psnr(img, gt),
                   "ssim": float(ssim(img, gt)), "lpips": lp, "ms_total": s.select_ms + s.raster_ms,
                   "ms_select": s.select_ms, "ms_raster": s.raster_ms, "bytes": s.n * bpg})
    mean = lambda k: (sum(r[k] for r in pv) / len(pv)) if all(r[k] is not None for r in pv) else None  # noqa: E731
    med = lambda k: statistics.median(r[k] for r in pv)  # noqa: E731
    agg = {"method": method, "setting": setting, "s_v": mean("s_v"), "budget": budget,
           "gaussians": mean("gaussians"), "fraction": mean("fraction"), "psnr": mean("psnr"),
           "ssim": mean("ssim"), "lpips": mean("lpips"), "ms_total": med("ms_total"),
           "ms_select": med("ms_select"), "ms_raster": med("ms_raster"), "bytes": mean("bytes"),
           "views": len(pv), "ms_min": med("ms_total"), "ms_max": med("ms_total")}
    if all(s.again is not None for s in samples):
        rows.redo[len(rows.rows)] = ([s.again for s in samples], len(rows.per_view))
    rows.per_view.extend(pv)
    rows.rows.append(agg)
    return agg


def _retime(rows: _Rows, repeats: int, seed: int, on_render=None) -> None:
    """Replace the quality pass's times of every row with interleaved timing rounds."""
    from ..evaluate.timing import time_interleaved

    if repeats <= 0 or not rows.redo:
        return
    res = time_interleaved({i: fns for i, (fns, _) in rows.redo.items()}, repeats=repeats, warmup=0,
                           seed=seed, on_render=on_render)
    for i, t in res.items():
        r = rows.rows[i]
        r.update(ms_total=t["ms_total"], ms_select=t["ms_select"], ms_raster=t["ms_raster"],
                 ms_min=t["ms_total_min"], ms_max=t["ms_total_max"])
        start = rows.redo[i][1]
        for j, pv in enumerate(t["per_view"]):
            rows.per_view[start + j].update(pv)


def _adapted_cut(adapted: Gaussians, k: int, cameras) -> Gaussians:
    """The adapted model's own ``k``-Gaussian level as a static model (a start for
    ``dlod_finetuned``): the first ``k`` of its importance order over ``cameras``
    (:func:`clod_adapter.export.bake.importance_order`), base attributes, no ``sigma_d``."""
    from ..export.bake import importance_order

    keep = torch.sort(importance_order(adapted, cameras)[:k]).values
    return adapted.subset(keep).with_sigma_d(None)


# --- the report -----------------------------------------------------------------------------
@dataclass
class EvalOptions:
    """How ``clod-eval`` (:func:`evaluate_report`) evaluates an adapted model.

    Attributes:
        pretrained: the pretrained model the baselines cut (.ply or Gaussians). None: the adapted
            model's own attributes without ``sigma_d`` (noted in the report).
        pretrained_label: the report's name for a ``pretrained`` given as Gaussians.
        budgets: fractions (<= 1) and/or counts (integers > 1), see :func:`normalize_budgets`.
        s_vs: the s_v sweep; default :func:`sv_grid` ``(max_sv, sv_steps)``, a parent tier's
            levels added.
        max_sv: the trained maximum (default: from the model's header or
            ``adapt_state.safetensors`` beside the .ply, else 5).
        popping_steps: frames of the popping sweep, s_v from 1 to the sweep's end (a model with
            merged tiers: evenly in ln s_v, through every hand-over to where the last tier is at
            1.2 times its max_sv, :func:`clod_adapter.lod.draw.tier_reach`).
        lpips: see :func:`resolve_lpips`.
        sigma_c: the constant decay of the constant-sigma baseline (default: the best on training
            views, :func:`clod_adapter.lod.rankings.tune_sigma_c`).
        seed: seed of the random baseline. tau: the LoD threshold (default: the adapted model's).
        background: [3] RGB behind the scene. device: where to render (CUDA renders with gsplat).
        progress: show progress (a tqdm bar on a terminal, else a plain line every 10 %).
        log: where the final text table goes (None: nowhere).
        timing_repeats: interleaved timing rounds after the quality pass
            (:mod:`clod_adapter.evaluate.timing`); 0 keeps the quality pass's own (single) times.
        notes: extra notes for the report (e.g. a resolution warning).
        dlod_iterations: > 0 adds ``dlod_finetuned``: for each budget below 1, the best start on
            validation views (:func:`clod_adapter.train.finetune.best_start`) fine-tuned for this many steps
            (:func:`clod_adapter.train.finetune.finetune_subset`).
        merge_tool: a splat-transform executable: adds splat-transform's decimators at each
            budget's share of the model and to the quality-against-time comparison; a failing run
            raises RuntimeError (a peer never silently drops out of the report). None: they are not
            run, and the report says so.
        full_rounds: paired rounds of the comparison's full-detail time ratio
            (:func:`clod_adapter.evaluate.comparison.full_detail_ratio`; 0: not measured).
    """

    pretrained: Union[os.PathLike, str, Gaussians, None] = None
    budgets: Sequence = DEFAULT_BUDGETS
    s_vs: Optional[Sequence[float]] = None
    max_sv: Optional[float] = None
    sv_steps: int = 25
    popping_steps: int = SWEEP_STEPS
    lpips: LpipsSpec = "auto"
    sigma_c: Optional[float] = None
    pretrained_label: Optional[str] = None
    seed: int = 0
    tau: Optional[float] = None
    background: tuple = (0.0, 0.0, 0.0)
    device: Union[str, torch.device] = "cpu"
    progress: bool = True
    log: Optional[Callable[[str], None]] = print
    timing_repeats: int = 3
    notes: Sequence[str] = ()
    dlod_iterations: int = 0
    merge_tool: Optional[str] = None
    full_rounds: int = qvt.FULL_ROUNDS


@dataclass
class _Eval:
    """One report in the making: the models, views and settings every phase reads, and the rows."""

    o: EvalOptions
    adapted: Gaussians
    base: Gaussians
    ply_path: Optional[Path]
    max_sv: float
    budgets: list
    s_vs: list
    dev: torch.device
    cams: list
    train_cams: list
    gts: list
    train_gts: list
    sigma_c: float
    sigma_c_rule: str
    lpips_fn: Optional[Callable]
    notes: list
    bar: object = None
    rows: _Rows = field(default_factory=_Rows)
    dlod: dict = field(default_factory=lambda: {"levels": {}, "choice": {}, "info": {}})
    merge_sizes: dict = field(default_factory=dict)
    decimated: dict = field(default_factory=dict)
    comparison: Optional[qvt.Comparison] = None

    @property
    def bg(self) -> list:
        return list(self.o.background)

    def tick(self) -> None:
        self.bar.update(1)

    def run(self, fn) -> list:
        """One sample per view of ``fn(cam)`` (``fn`` binds its loop variables: it is called
        again for timing)."""
        out = []
        for cam in self.cams:
            out.append(_sample(lambda cam=cam: fn(cam)))
            self.tick()
        return out

    def render(self, g: Gaussians, cam, s_v: Optional[float] = None, budget=None) -> Sample:
        return _render_lod(g, cam, self.bg, self.o.tau, s_v=s_v, budget=budget)

    def score(self, method: str, setting: str, budget, samples: list, adapted: bool) -> None:
        g = self.adapted if adapted else self.base
        _score(self.rows, method, setting, budget, samples, self.cams, self.gts, len(g), ply_row_bytes(g),
               self.lpips_fn)


@torch.no_grad()
def evaluate_report(adapted: Union[os.PathLike, Gaussians], scene, out_dir: os.PathLike,
                    options: Optional[EvalOptions] = None) -> dict:
    """Evaluate an adapted CLoD model against baselines and write the report to ``out_dir``.

    Phases, in order: :func:`_eval_inputs` (models, views, settings), :func:`_score_sweep` (the
    pretrained model and the adapted one along ``s_v``), :func:`_score_budget` per budget (the
    adapted model's budget, every ranking baseline of :data:`METHOD_REGISTRY` at the same per-view
    counts, the decimators, the dlod ceiling), the interleaved timing rounds, the popping sweep,
    :func:`_write_report`.

    Args:
        adapted: the adapted model (.ply path or :class:`Gaussians` with ``sigma_d``).
        scene: a :class:`clod_adapter.io.scene.Scene` (test views: ``scene.test``, or the first
            training view when there are none; LightGaussian scores use ``scene.train``).
        out_dir: output folder (must exist or be creatable; the CLI checks it first).
        options: :class:`EvalOptions` (default: its defaults).

    Returns:
        the report dict (also ``report.json``): ``rows`` (aggregated, :data:`CSV_COLUMNS`),
        ``per_view``, ``popping`` (:func:`popping_curve`), ``settings`` and ``notes``.

    Raises:
        ValueError: the adapted model has no ``sigma_d``. RuntimeError: a decimator failed.
    """
    from . import progress_bar

    o = options if options is not None else EvalOptions()
    t_start = time.perf_counter()
    ev = _eval_inputs(adapted, scene, o)
    extra = len(BASELINES) + (len(DECIMATORS) if o.merge_tool else 0) + (1 if o.dlod_iterations > 0 else 0)
    n_renders = len(ev.cams) * (len(ev.s_vs) + 1 + len(ev.budgets) * (1 + extra)) * (1 + max(o.timing_repeats, 0))
    n_renders += qvt.n_renders(len(ev.cams), max(o.timing_repeats, 1), o.full_rounds, o.merge_tool is not None,
                               n_levels=len(qvt.clod_s_vs(ev.adapted)))
    ev.bar = progress_bar(n_renders + o.popping_steps + 2, "clod-eval", unit="render", disable=not o.progress,
                          leave=False)
    t0 = time.perf_counter()
    _score_sweep(ev)
    t_sig = time.perf_counter()
    ctx = RankingContext(lightgaussian=lightgaussian_significance(ev.base, ev.train_cams),
                         random=random_scores(len(ev.base), o.seed, ev.dev), sigma_c=float(ev.sigma_c),
                         tau=lod.DEFAULT_TAU if o.tau is None else o.tau)
    t_sig = time.perf_counter() - t_sig
    if o.merge_tool is None:
        ev.notes.append("splat-transform's decimators (decimate, decimate_adaptive) NOT RUN: splat-transform not "
                        "found (`npm ci` in the repository root installs the pinned 3.7.0)")
    global_scores = _dlod_rankings(ev, ctx) if o.dlod_iterations > 0 else {}
    for b in ev.budgets:
        _score_budget(ev, b, ctx, global_scores)
    ev.bar.set_postfix_str(f"timing x{o.timing_repeats}")
    _retime(ev.rows, o.timing_repeats, o.seed, on_render=ev.tick)
    _compare_time(ev, ctx.lightgaussian)
    ev.bar.set_postfix_str("popping")
    if o.s_vs is None:
        pop_svs = popping_sweep(ev.max_sv, tier_reach(ev.adapted), o.popping_steps)
    else:
        pop_svs = [float(x) for x in np.linspace(1.0, ev.s_vs[-1], o.popping_steps)]
    pop = popping_curve(ev.adapted, ev.cams[0], pop_svs, discrete_model=ev.base, discrete_scores=ctx.lightgaussian,
                        tau=o.tau, background=ev.bg, on_render=ev.tick)
    pop["camera"] = ev.cams[0].name
    pop["discrete"] = "pretrained model cut by LightGaussian significance at the continuous sweep's end counts"
    ev.bar.close()
    report = _report_dict(ev, scene, pop, t_sig, time.perf_counter() - t0)
    _write_report(ev, Path(out_dir), report, pop, t_start)
    if o.log is not None:
        o.log(format_table(ev.rows.rows))
        o.log(f"popping (camera {pop['camera']}): continuous max {pop['continuous_max']:.4g} / median "
              f"{pop['continuous_median']:.4g}; discrete max {pop['discrete_max']:.4g}; ratio {pop['ratio']:.1f}")
        for n in ev.notes:
            o.log(f"note: {n}")
        o.log(report["quality_vs_time"]["verdict"])
    return report


def _compare_time(ev: _Eval, significance: Tensor) -> None:
    """Phase 3b: the quality-against-frame-time comparison with the peers
    (:func:`clod_adapter.evaluate.comparison.compare`, the one ``benchmarks/quality_vs_time.py`` runs),
    with the LightGaussian significance the ranking baselines already computed on the same views."""
    ev.bar.set_postfix_str("quality against time")
    opts = qvt.CompareOptions(merge_tool=ev.o.merge_tool, lpips_fn=ev.lpips_fn, repeats=max(ev.o.timing_repeats, 1),
                              full_rounds=ev.o.full_rounds, background=ev.bg)
    ev.comparison = qvt.compare(ev.adapted, ev.base, ev.train_cams, ev.cams, ev.gts, max_sv=ev.max_sv, options=opts,
                                significance=significance, tick=ev.tick)


def _eval_inputs(adapted, scene, o: EvalOptions) -> _Eval:
    """Phase 1: the adapted and pretrained models on the device, the sweep and budgets, the
    views and their images, LPIPS and the constant-sigma baseline's ``sigma_c``."""
    dev = torch.device(o.device)
    notes = list(o.notes)
    ply_path = None
    if not isinstance(adapted, Gaussians):
        ply_path = Path(adapted)
        adapted = read_ply(ply_path)
    if adapted.sigma_d is None:
        raise InputError(f"{ply_path or 'the model'}: no sigma_d: not an adapted model (run clod-adapt first)")
    max_sv = o.max_sv
    if max_sv is None:
        max_sv = (adapted.lod.max_sv if adapted.lod is not None else None) \
            or (max_sv_from_state(ply_path) if ply_path is not None else None) or 5.0
    if o.pretrained is None:
        base = adapted.with_sigma_d(None)
        notes.append("no pretrained model given: baselines cut the adapted model's own attributes")
    else:
        base = o.pretrained if isinstance(o.pretrained, Gaussians) else read_ply(o.pretrained)
        base = base.with_sigma_d(None)
    budgets = normalize_budgets(o.budgets)
    tier = adapted.lod if adapted.parents is not None else None
    s_vs = sv_grid(max_sv, o.sv_steps, lod_settings=tier, reach=tier_reach(adapted)) if o.s_vs is None \
        else [float(s) for s in o.s_vs]
    lpips_fn, lpips_note = resolve_lpips(o.lpips)
    if lpips_fn is not None and hasattr(lpips_fn, "to"):
        lpips_fn = lpips_fn.to(dev)
    notes.append(lpips_note)
    adapted, base = adapted.to(dev), base.to(dev)
    cams = list(scene.test) or list(scene.train[:1])
    train_cams = list(scene.train) or cams
    gts = [scene.load_image(c).to(dev) for c in cams]
    need_train = o.sigma_c is None or o.dlod_iterations > 0
    train_gts = [scene.load_image(c).to(dev) for c in train_cams] if need_train else []
    sigma_c, sigma_c_rule = o.sigma_c, "given"
    if sigma_c is None:
        sigma_c = tune_sigma_c(base, train_cams, train_gts, background=list(o.background))
        sigma_c_rule = "best training-view PSNR at 50 % over " + ", ".join(f"{c:g}" for c in SIGMA_C_CANDIDATES)
    return _Eval(o, adapted, base, ply_path, max_sv, budgets, s_vs, dev, cams, train_cams, gts, train_gts,
                 sigma_c, sigma_c_rule, lpips_fn, notes)


def _score_sweep(ev: _Eval) -> None:
    """Phase 2: the pretrained model, then the adapted one at every ``s_v`` of the sweep."""
    # one untimed render first: the first call pays one-off costs (extension load, allocator);
    # the quality pass below is the warm-up of the interleaved timing rounds
    ev.render(ev.base, ev.cams[0])
    ev.score("pretrained", "full", None, ev.run(lambda c: ev.render(ev.base, c)), adapted=False)
    for s in ev.s_vs:
        ev.bar.set_postfix_str(f"clod s_v={s:.2f}")
        ev.score("clod", f"s_v={s:g}", None, ev.run(lambda c, s=s: ev.render(ev.adapted, c, s_v=s)), adapted=True)


def _dlod_rankings(ev: _Eval, ctx: RankingContext) -> dict:
    """The global rankings the dlod ceiling may start from (name -> [N] scores)."""
    from ..train.loop import reference_distances
    from ..lod.budget import critical_s_v

    d_ref = reference_distances(ev.base, ev.train_cams)
    return {"lightgaussian": ctx.lightgaussian, "random": ctx.random,
            "constant_sigma": critical_s_v(ev.base.opacities, d_ref, torch.full_like(d_ref, ev.sigma_c),
                                           ctx.tau).float()}


def _score_budget(ev: _Eval, b, ctx: RankingContext, global_scores: dict) -> None:
    """Phase 3, one budget: the adapted model's budget render, each ranking baseline at the same
    per-view counts, the decimators at the budget's share of the model, the dlod ceiling."""
    lab = budget_label(b)
    ev.bar.set_postfix_str(lab)
    clod_s = ev.run(lambda c, b=b: ev.render(ev.adapted, c, budget=b))
    ev.score("clod_budget", lab, b, clod_s, adapted=True)
    ks = [s.n for s in clod_s]  # the baselines render the same per-view counts
    for name in BASELINES:
        samples = []
        for cam, k in zip(ev.cams, ks):
            samples.append(_sample(lambda cam=cam, k=k, sel=METHOD_REGISTRY[name].select:
                                   _render_selection(ev.base, cam, sel(ev.base, cam, k, ctx), ev.bg)))
            ev.tick()
        ev.score(name, lab, b, samples, adapted=False)
    nb = len(ev.base)
    share = (b if isinstance(b, float) else b / max(nb, 1))
    if ev.o.merge_tool and share < 1.0:
        from ..lod.rankings import merge_decimate

        for method, mode in DECIMATORS.items():
            ev.bar.set_postfix_str(f"{lab} {method}")
            m = merge_decimate(ev.base, max(1, int(round(share * nb))), mode=mode, tool=ev.o.merge_tool).to(ev.dev)
            ev.merge_sizes[f"{method} {lab}"] = len(m)
            ev.decimated[(method, lab)] = m
            ev.score(method, lab, b, ev.run(lambda c, m=m: ev.render(m, c)), adapted=False)
    if ev.o.dlod_iterations > 0 and share < 1.0:
        _score_dlod(ev, b, lab, share, global_scores)


def _score_dlod(ev: _Eval, b, lab: str, share: float, global_scores: dict) -> None:
    """The dlod ceiling at one budget: the best start by PSNR on validation views (training
    views; the test views only score the result), fine-tuned with the recovery schedule on the
    other training views, keeping the checkpoint (every 500 steps, the start included) with the
    best validation PSNR."""
    from ..train.finetune import FinetuneOptions, best_start, finetune_subset, global_cut
    from ..io.scene import validation_split

    fit_cams, val_cams = validation_split(ev.train_cams)
    gt_of = {id(c): gt for c, gt in zip(ev.train_cams, ev.train_gts)}  # the split returns these objects
    val_gts, fit_gts = [gt_of[id(c)] for c in val_cams], [gt_of[id(c)] for c in fit_cams]
    k = max(1, int(round(share * len(ev.base))))
    cands = {m: ev.base.subset(global_cut(global_scores[m].to(ev.dev), share)) for m in global_scores}
    cands.update({m: d for (m, lb), d in ev.decimated.items() if lb == lab})
    cands["clod"] = _adapted_cut(ev.adapted, k, fit_cams)
    best, start, val_scores = best_start(cands, val_cams, val_gts, background=ev.bg,
                                         return_scores=True)
    ev.bar.set_postfix_str(f"{lab} dlod ({best}, {ev.o.dlod_iterations} steps)")
    level, info = finetune_subset(start, fit_cams, fit_gts,
                                  FinetuneOptions(iterations=ev.o.dlod_iterations, seed=ev.o.seed, background=ev.bg),
                                  val=(val_cams, val_gts), return_info=True,
                                  progress=f"clod-eval dlod_finetuned {lab} (from {best})" if ev.o.progress else None)
    ev.dlod["levels"][lab], ev.dlod["choice"][lab] = len(level), best
    ev.dlod["info"][lab] = {"start": best, "val_psnr": val_scores, "convergence": info.convergence,
                            "loss_every_100": info.loss[::100], "val_psnr_during": info.val_psnr,
                            "best_step": info.best_step}
    ev.score("dlod_finetuned", lab, b, ev.run(lambda c, m=level: ev.render(m, c)), adapted=False)


def _report_dict(ev: _Eval, scene, pop: dict, t_sig: float, t_eval: float) -> dict:
    o, base, cams = ev.o, ev.base, ev.cams
    dl = ev.dlod["levels"]
    return {
        "version": __version__,
        "adapted": str(ev.ply_path) if ev.ply_path is not None else None,
        "pretrained": None if o.pretrained is None else (str(o.pretrained) if not isinstance(o.pretrained, Gaussians)
                                                         else (o.pretrained_label or "<Gaussians>")),
        "scene": str(getattr(scene, "root", "")),
        "device": str(ev.dev), "threads": torch.get_num_threads(),
        "views": [c.name for c in cams], "image_size": [cams[0].width, cams[0].height],
        "num_gaussians": {"adapted": len(ev.adapted), "pretrained": len(base)},
        "bytes_per_gaussian": {"adapted": ply_row_bytes(ev.adapted), "pretrained": ply_row_bytes(base)},
        "storage": {"adapted_bytes": ply_bytes(ev.adapted), "pretrained_bytes": ply_bytes(base),
                    **({"dlod_bytes": ply_bytes(base) + sum(ply_bytes(base.subset(torch.arange(v)))
                                                           for v in dl.values()),
                        "dlod_levels": dl, "dlod_ranking": ev.dlod["choice"], "dlod": ev.dlod["info"],
                        "dlod_iterations": o.dlod_iterations} if dl else {}),
                    **({"decimated_sizes": ev.merge_sizes} if ev.merge_sizes else {}),
                    "what": "bytes of the .ply write_ply writes for the model (= the file size)"},
        "timing": {"repeats": o.timing_repeats,
                   "order": "shuffled per round (seed)" if o.timing_repeats else "single pass",
                   "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
                   "what": "ms = median over rounds of the median over views; ms_min/ms_max = smallest/largest round"},
        "settings": {"max_sv": ev.max_sv, "s_vs": ev.s_vs, "budgets": ev.budgets, "sigma_c": ev.sigma_c,
                     "sigma_c_rule": ev.sigma_c_rule, "seed": o.seed, "tau": o.tau,
                     "background": ev.bg, "popping_steps": o.popping_steps,
                     "lightgaussian": {"v_pow": 0.1, "volume_ref": "sorted-descending volume at int(0.9 N)",
                                       "pixels_hit": "projected ellipse area (alpha >= 1/255, <= 3.33 sigma), "
                                                     "clipped by the bbox fraction inside the image",
                                       "train_views": len(ev.train_cams), "seconds": round(t_sig, 2)}},
        "columns": list(CSV_COLUMNS),
        "rows": ev.rows.rows,
        "per_view": ev.rows.per_view,
        "popping": pop,
        "quality_vs_time": _comparison_dict(ev.comparison),
        "notes": ev.notes,
        "eval_seconds": round(t_eval, 1),
    }


def _comparison_dict(comp: qvt.Comparison) -> dict:
    """``report.json``'s ``quality_vs_time``: the verdict, the cells, every point."""
    cs = qvt.cells(comp)
    return {"verdict": qvt.verdict(comp, cs), "cells": qvt.cells_json(cs), "cells_markdown": qvt.cells_markdown(cs),
            "full_ratio": comp.full_ratio, "decimators_run": comp.merge_run,
            "points": [{"method": s.method, "setting": s.setting, "psnr": s.psnr, "ssim": s.ssim, "lpips": s.lpips,
                        "ms": s.ms, "time_share": s.ms / comp.input.ms, "drawn_per_view": statistics.mean(s.drawn),
                        "in_view_share": comp.in_view_share(s), "storage_bytes": s.storage} for s in comp.settings],
            "what": "clod_adapter.evaluate.comparison.compare: every point timed in interleaved rounds in one run; "
                    "time_share = ms / the input's ms"}


def _write_report(ev: _Eval, out_dir: Path, report: dict, pop: dict, t_start: float) -> None:
    """Phase 4: the CSVs, the figures, the strip, ``report.json`` and ``report.md``, each atomically."""
    from ..export.figures import write_strip
    from ..evaluate.level_metrics import sv_levels

    rows = ev.rows
    with atomic_write(out_dir / "report.csv", "w", newline="") as f:
        f.write(csv_text(rows.rows, CSV_COLUMNS))
    with atomic_write(out_dir / "report_per_view.csv", "w", newline="") as f:
        f.write(csv_text(rows.per_view, PER_VIEW_COLUMNS))
    mark = ev.max_sv ** -1.5
    plot_quality(rows.rows, "gaussians", "mean Gaussians rendered per view", out_dir / "quality_vs_gaussians.png",
                  mark=(len(ev.adapted) * mark, f"max_sv^-1.5 = {100 * mark:.1f} %"))
    plot_quality(rows.rows, "ms_total", "median ms per frame (bars: fastest-slowest round)",
                  out_dir / "levels_vs_time.png", extra=plot_time_curve(rows.rows), time_axis=True)
    title = f"{Path(str(report.get('scene') or 'scene')).name}: adapted model against the peers (clod-eval)"
    qvt.plot(out_dir / "quality_vs_time.png", {title: ev.comparison})
    with atomic_write(out_dir / "quality_vs_time.csv", "w", newline="") as f:
        f.write(qvt.csv_text(ev.comparison))
    plot_popping(pop, out_dir / "popping.png")
    write_strip(out_dir / "lod_strip.png", ev.adapted, ev.cams[0], sv_levels(ev.max_sv), ev.bg, gt=ev.gts[0])
    report["wall_seconds"] = round(time.perf_counter() - t_start, 1)
    with atomic_write(out_dir / "report.json", "w") as f:
        json.dump(jsonable(report), f, indent=1)
    with atomic_write(out_dir / "report.md", "w") as f:
        f.write(format_markdown(report))
