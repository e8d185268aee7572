"""Quality against frame time: the adapted model against the peers a user already has.

One implementation for ``clod-eval`` (its verdict, ``quality_vs_time.csv`` and
``quality_vs_time.png``) and ``benchmarks/quality_vs_time.py`` (the README's results table).
:func:`compare` renders the evaluation views with

* ``input``: the pretrained model, every Gaussian in view;
* ``clod``: the adapted model along ``s_v`` (:func:`clod_s_vs`) and at cost budgets
  (:data:`COST_SHARES`: shares of the view's frame cost, ``render_lod(budget=Budget(cost=...))``);
* static cuts of the input over several counts (:data:`STATIC_SHARES` of the Gaussians *in
  view*): ``lightgaussian`` (LightGaussian significance on the fit views) and ``opacity``;
* when splat-transform is given: its untrained merging decimators ``decimate`` and
  ``decimate_adaptive`` (:data:`DECIMATE_SHARES` of the model;
  :func:`clod_adapter.lod.rankings.merge_decimate`);
* at each decimator point whose drawn share per view lies in ``[max_sv^-1.5, 0.5]``: the adapted
  model, LightGaussian and opacity at exactly the decimator's drawn count in every view
  (setting ``match:<decimator>:<its setting>``);
* with ``ceiling_views``: the honest ceiling at each of those decimator shares (``ceiling``,
  setting ``model=<share>``; :func:`ceiling_settings`): one static model per budget, fine-tuned
  from the best start on the fit views, its step chosen on the validation views; not a peer, it
  caps what a goal may ask;

scores every setting (PSNR, SSIM, LPIPS when a scorer is given), then times every setting with
the same renderer in interleaved shuffled rounds (:func:`clod_adapter.evaluate.timing.time_interleaved`:
each render's whole wall time: projection, selection, rasterisation), and the input against
``s_v = 1`` alone in :data:`FULL_ROUNDS` paired rounds. A static cut is timed as the smaller model
it is (only its Gaussians are projected). Times are read as shares of the input's frame in the same
run (:mod:`clod_adapter.evaluate.frontier`).

The *cells* (:func:`cells`) are what both callers report: full detail; our best PSNR and the
peers' best within each share of :data:`TIME_SHARES` of the input's frame time; ours against the
best peer at each equal-count point. :func:`verdict` says them in one paragraph.
"""
from __future__ import annotations

import csv
import io
import math
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from ..lod.rankings import lightgaussian_significance, merge_decimate, topk_in_view
from ..lod.budget import Budget
from ..lod.draw import render_lod, tier_reach
from ..lod.view import view_lod
from .ceiling_cache import cached_ceiling, store_ceiling
from .frontier import Point, frontier, time_margins
from ..gaussians import Gaussians
from ..metrics import psnr, ssim
from .storage import ply_bytes
from .timing import time_interleaved
from ..lod.tree import is_tree

#: ``s_v`` levels and cost budgets of the adapted model.
S_VS = (1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 10.0, 12.5, 15.0, 17.5, 20.0, 25.0,
        30.0)
COST_SHARES = (0.6, 0.4, 0.25, 0.15, 0.1, 0.06, 0.04)
#: static cuts: shares of the Gaussians in view (rankings) or of the model (decimators).
STATIC_SHARES = (0.75, 0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01)
DECIMATE_SHARES = (0.75, 0.5, 0.3, 0.15, 0.08, 0.04)
#: frame-time shares of the input at which the best points are compared.
TIME_SHARES = (0.75, 0.5, 0.25, 0.1)
#: paired rounds of the full-detail time ratio (input and ``s_v = 1`` alone).
FULL_ROUNDS = 9
#: interleaved rounds of the adapted model's two sweeps timed with the input alone (issue 62's
#: cost goals, :func:`sweep_times`): a step of 5 % between two frames of a few ms is within the
#: spread of the comparison's 5 rounds
SWEEP_ROUNDS = 15
#: margins smaller than this (dB) are said to be level.
LEVEL_DB = 0.05
OURS = ("clod",)
PEERS = ("lightgaussian", "opacity", "decimate", "decimate_adaptive")
#: the per-budget ceiling (:func:`ceiling_settings`): at most this many fine-tuning steps, the
#: validation views scoring the model every :data:`CEILING_VAL_EVERY` of them.
CEILING_STEPS = 600
CEILING_VAL_EVERY = 100
DECIMATORS = {"decimate": "decimate", "decimate_adaptive": "adaptive"}
CSV_COLUMNS = ("method", "setting", "psnr", "ssim", "lpips", "ms", "ms_min", "ms_max", "time_share",
               "drawn_per_view", "in_view_share", "storage_bytes")


def timed_call(fn: Callable):
    """``(fn(), wall ms of the call)``: how every render of the comparison is timed
    (``time.perf_counter``)."""
    t0 = time.perf_counter()
    out = fn()
    return out, (time.perf_counter() - t0) * 1e3


@dataclass
class Setting:
    """One method x setting: its per-view renders and what they scored.

    Attributes:
        method: ``input``, ``clod`` or a peer of :data:`PEERS`.
        setting: e.g. ``s_v=2``, ``cost=0.25``, ``in_view=0.3``, ``model=0.15``,
            ``match:decimate:model=0.15``.
        renders: zero-argument callables, one per view, returning (image [H, W, 3], drawn, ms).
        storage: bytes of the .ply of what the setting draws from (the model or the cut).
        psnr, ssim, lpips: means over the views (dB; 3DGS SSIM; LPIPS-alex, nan without a scorer).
        drawn: Gaussians drawn in each view.
        ms, ms_min, ms_max: median over rounds of the median over views, and the smallest and
            largest round (ms).
    """

    method: str
    setting: str
    renders: list
    storage: int
    psnr: float = float("nan")
    ssim: float = float("nan")
    lpips: float = float("nan")
    drawn: list = field(default_factory=list)
    ms: float = float("nan")
    ms_min: float = float("nan")
    ms_max: float = float("nan")


@dataclass
class Comparison:
    """The outcome of :func:`compare`: every setting scored and timed, and the views' context.

    Attributes:
        settings: every :class:`Setting` (the input first).
        n_in_view: [V] Gaussians of the input in each evaluation view.
        max_sv: the adapted model's trained maximum ``s_v``.
        full_ratio: the full-detail time ratio (``s_v = 1`` / input), the median of
            :data:`FULL_ROUNDS` paired rounds (nan when not measured).
        merge_run: whether splat-transform's decimators were run.
        sweep_rounds: the input, the adapted model's sweep settings and each equal-count pair
            timed alone (:func:`sweep_times`): key (``"input"``, the adapted model's setting,
            ``<method>:<setting>`` for a decimator) -> [R] per-round ms, or empty when not measured.
    """

    settings: list
    n_in_view: list
    max_sv: float
    full_ratio: float = float("nan")
    merge_run: bool = False
    sweep_rounds: dict = field(default_factory=dict)

    @property
    def input(self) -> Setting:
        return next(s for s in self.settings if s.method == "input")

    def get(self, method: str, setting: str) -> Setting:
        return next(s for s in self.settings if s.method == method and s.setting == setting)

    def in_view_share(self, s: Setting) -> float:
        """Mean over views of the drawn share of the input's Gaussians in view."""
        return statistics.mean(d / max(n, 1) for d, n in zip(s.drawn, self.n_in_view))


def lod_render(g: Gaussians, cam, **kw) -> Callable:
    """One view's render as a zero-argument callable returning (image, drawn, wall ms of the
    whole :func:`clod_adapter.lod.draw.render_lod` call, via :func:`timed_call`)."""
    def f():
        out, ms = timed_call(lambda: render_lod(g, cam, **kw))
        return out.image, out.n_rendered, ms
    return f


@dataclass
class _Context:
    """What the settings are built from (:func:`build_settings`)."""

    adapted: Gaussians
    base: Gaussians
    cams: list
    views: list
    scores: dict
    render_kw: dict
    merged: dict = field(default_factory=dict)  # (decimator, model share) -> its output

    def ranking_cut(self, method: str, ks: Sequence[int]) -> tuple[list, int]:
        """Each view's cut is a model of its own (what a static cut ships): only it is projected."""
        idx = [topk_in_view(self.scores[method], v.visible, k) for v, k in zip(self.views, ks)]
        size = ply_bytes(self.base.subset(torch.unique(torch.cat(idx)))) if idx else 0
        return [lod_render(self.base.subset(i), c, **self.render_kw) for c, i in zip(self.cams, idx)], size


#: the count budgets of the adapted model's budget sweep: shares of the Gaussians in view
COUNT_SHARES = (1.0, 0.75, 0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01)
#: levels of a merge tree's sweep (log-spaced from 1 to past its coarsest tier)
TREE_LEVELS = 40


def clod_s_vs(adapted: Gaussians) -> list[float]:
    """The adapted model's levels compared: :data:`S_VS`; for a merge tree
    (:func:`clod_adapter.lod.tree.is_tree`), :data:`TREE_LEVELS` log-spaced levels from 1 to
    ``S_VS[-1] x`` its reach (:func:`clod_adapter.lod.draw.tier_reach`) instead."""
    if is_tree(adapted):  # one sweep through the whole tree, log-spaced (its cost must fall along it)
        top = S_VS[-1] * tier_reach(adapted)
        return [round(math.exp(math.log(top) * i / (TREE_LEVELS - 1)), 4) for i in range(TREE_LEVELS)]
    return sorted(set(S_VS))


def build_settings(adapted: Gaussians, base: Gaussians, fit_cams: Sequence, cams: Sequence, *,
                   merge_tool: Optional[str] = None, background=None, significance: Optional[torch.Tensor] = None,
                   log: Callable[[str], None] = lambda s: None) -> tuple[list, _Context]:
    """Every method x setting (renders not yet run; see the module docstring).

    Args:
        adapted, base, fit_cams, cams, merge_tool, background, log: as :func:`compare`.
        significance: [N] float32 LightGaussian significance of ``base`` on ``fit_cams`` when the
            caller has it (default: computed here,
            :func:`clod_adapter.lod.rankings.lightgaussian_significance`).

    Returns:
        (settings, the context :func:`matched_settings` reads).

    Raises:
        RuntimeError: a decimator failed (:func:`clod_adapter.lod.rankings.merge_decimate`).
    """
    kw = {} if background is None else {"background": background}
    n0 = len(base)
    settings = [Setting("input", "full", [lod_render(base, c, **kw) for c in cams], ply_bytes(base))]
    sa = ply_bytes(adapted)
    for s in clod_s_vs(adapted):
        settings.append(Setting("clod", f"s_v={s:g}", [lod_render(adapted, c, s_v=s, **kw) for c in cams], sa))
    for b in COST_SHARES:
        settings.append(Setting("clod", f"cost={b:g}", [lod_render(adapted, c, budget=Budget(cost=b), **kw)
                                                        for c in cams], sa))
    for b in COUNT_SHARES:
        settings.append(Setting("clod", f"in_view={b:g}", [lod_render(adapted, c, budget=Budget(in_view=b), **kw)
                                                           for c in cams], sa))
    if significance is None:
        t = time.perf_counter()
        significance = lightgaussian_significance(base, list(fit_cams))
        log(f"LightGaussian significance on {len(fit_cams)} fit views in {time.perf_counter() - t:.0f} s")
    scores = {"lightgaussian": significance, "opacity": base.opacities.detach()}
    ctx = _Context(adapted, base, list(cams), [view_lod(base, c) for c in cams], scores, kw)
    for method in scores:
        for share in STATIC_SHARES:
            fns, size = ctx.ranking_cut(method, [int(round(share * v.n_in_view)) for v in ctx.views])
            settings.append(Setting(method, f"in_view={share:g}", fns, size))
    if merge_tool is not None:
        for method, mode in DECIMATORS.items():
            for share in DECIMATE_SHARES:
                t = time.perf_counter()
                m = merge_decimate(base, max(1, int(round(share * n0))), mode=mode, tool=merge_tool)
                log(f"splat-transform --{'decimate' if mode == 'decimate' else 'decimate-adaptive'} "
                    f"{len(m):,} in {time.perf_counter() - t:.1f} s")
                ctx.merged[(method, share)] = m
                settings.append(Setting(method, f"model={share:g}", [lod_render(m, c, **kw) for c in cams],
                                        ply_bytes(m)))
    return settings, ctx


def score(settings: Sequence[Setting], gts: Sequence, lpips_fn=None, tick=lambda: None) -> None:
    """Render every setting once per view and store its mean PSNR / SSIM / LPIPS and counts."""
    for st in settings:
        ps, ss, ls, drawn = [], [], [], []
        for fn, gt in zip(st.renders, gts):
            img, n, _ = fn()
            img = img.clamp(0, 1)
            ps.append(psnr(img, gt))
            ss.append(float(ssim(img, gt)))
            if lpips_fn is not None:
                with torch.no_grad():
                    ls.append(float(lpips_fn(img, gt)))
            drawn.append(n)
            tick()
        st.psnr, st.ssim, st.drawn = statistics.mean(ps), statistics.mean(ss), drawn
        st.lpips = statistics.mean(ls) if ls else float("nan")


def matched_settings(settings: Sequence[Setting], ctx: _Context, max_sv: float) -> list[Setting]:
    """The adapted model and the rankings at each in-range decimator point's per-view counts."""
    out = []
    for st in settings:
        if st.method not in DECIMATORS or not _in_range(st, ctx, max_sv):
            continue
        key = f"match:{st.method}:{st.setting}"
        ks = list(st.drawn)
        out.append(Setting("clod", key, [lod_render(ctx.adapted, c, budget=Budget(count=k, min_s_v=0.0),
                                                    **ctx.render_kw) for c, k in zip(ctx.cams, ks)],
                           ply_bytes(ctx.adapted)))
        for method in ("lightgaussian", "opacity"):
            fns, size = ctx.ranking_cut(method, ks)
            out.append(Setting(method, key, fns, size))
    return out


def _in_range(st: Setting, ctx: _Context, max_sv: float) -> bool:
    """Whether a decimator point's mean drawn share per view lies in ``[max_sv^-1.5, 0.5]``."""
    shares = [d / max(v.n_in_view, 1) for d, v in zip(st.drawn, ctx.views)]
    return max_sv ** -1.5 * 0.9 <= statistics.mean(shares) <= 0.5


def ceiling_settings(settings: Sequence[Setting], ctx: _Context, max_sv: float, ceiling_views: tuple, *,
                     steps: int = CEILING_STEPS, cache: Optional[Path] = None,
                     log: Callable[[str], None] = lambda s: None) -> list[Setting]:
    """The honest ceiling at each in-range decimator share (issue 36's goal 4): per model share,
    the best start among both decimators' outputs and the LightGaussian cut of the input to the
    same count (:func:`clod_adapter.train.finetune.best_start` on the validation views), every
    attribute fine-tuned on the fit views for up to ``steps`` steps with LightGaussian's recovery
    schedule, keeping the checkpoint (start, every :data:`CEILING_VAL_EVERY` steps, end) that
    scores best on the validation views (:func:`clod_adapter.train.finetune.finetune_subset`). One
    static model per budget, as a discrete-LoD pipeline ships; scored and timed as every setting.

    Args:
        settings: the scored settings of :func:`build_settings` (the decimators' drawn counts).
        ctx: their context (the decimators' outputs in ``ctx.merged``).
        max_sv: the adapted model's trained maximum (the range's low end ``max_sv^-1.5``).
        ceiling_views: ``(fit_cams, fit_imgs, val_cams, val_imgs)``: views the fine-tune fits
            and views that choose its step (images [H, W, 3] float32 in [0, 1]); neither may be
            an evaluation view.
        steps: the fine-tune's length (its step is chosen among its checkpoints).
        cache: a folder for the fitted models (made when missing): each is written there as
            ``model=<share>.ply`` with a ``.json`` beside it (the start chosen, the step kept and
            what they were fitted from: the starts' counts, the input's count, the views' counts,
            ``steps``), and read back instead of fitted again while those match. Delete the
            folder to fit them again (after a change to the fine-tune). None: fitted every call.

    Returns:
        one :class:`Setting` per model share, method ``ceiling``, setting ``model=<share>``.
    """
    from ..train.finetune import FinetuneOptions, best_start, finetune_subset, global_cut

    fit_cams, fit_imgs, val_cams, val_imgs = ceiling_views
    bg = ctx.render_kw.get("background", (0.0, 0.0, 0.0))
    out = []
    for share in DECIMATE_SHARES:
        dec = [st for st in settings if st.method in DECIMATORS and st.setting == f"model={share:g}"]
        if not dec or not any(_in_range(st, ctx, max_sv) for st in dec):
            continue
        cands = {m: ctx.merged[(m, share)] for m in DECIMATORS if (m, share) in ctx.merged}
        n = len(next(iter(cands.values())))
        cands["lightgaussian"] = ctx.base.subset(global_cut(ctx.scores["lightgaussian"], n / len(ctx.base)))
        key = {"steps": steps, "starts": {m: len(g) for m, g in cands.items()}, "input": len(ctx.base),
               "fit_views": len(fit_cams), "val_views": len(val_cams), "background": [float(v) for v in bg]}
        t = time.perf_counter()
        kept = cached_ceiling(cache, share, key)
        if kept is not None:
            tuned, record = kept
            log(f"ceiling at model={share:g}: reusing {cache / f'model={share:g}.ply'} ({record['start']} "
                f"fine-tuned, step {record['best_step']} of {steps})")
        else:
            name, start = best_start(cands, val_cams, val_imgs, background=bg)
            tuned, info = finetune_subset(start, fit_cams, fit_imgs,
                                          FinetuneOptions(iterations=steps, background=bg, val_every=CEILING_VAL_EVERY),
                                          val=(val_cams, val_imgs), return_info=True)
            log(f"ceiling at model={share:g}: {name} fine-tuned, step {info.best_step} of {steps} chosen on "
                f"{len(val_cams)} validation views, in {time.perf_counter() - t:.0f} s")
            if cache is not None:
                store_ceiling(cache, share, tuned, {**key, "start": name, "best_step": info.best_step})
        out.append(Setting("ceiling", f"model={share:g}", [lod_render(tuned, c, **ctx.render_kw) for c in ctx.cams],
                           ply_bytes(tuned)))
    return out


def _time(settings: Sequence[Setting], repeats: int, tick, seed: int = 0) -> dict:
    class _Timed:  # what time_interleaved reads from a render
        def __init__(self, ms: float) -> None:
            self.select_ms, self.raster_ms = 0.0, ms

    def timed(fn):
        return lambda: _Timed(fn()[2])

    return time_interleaved({i: [timed(fn) for fn in st.renders] for i, st in enumerate(settings)},
                            repeats=repeats, warmup=1, seed=seed, on_render=tick)


def retime(settings: Sequence[Setting], repeats: int, tick=lambda: None) -> None:
    """Time every setting in ``repeats`` interleaved shuffled rounds after one warm-up round."""
    res = _time(settings, repeats, tick)
    for i, st in enumerate(settings):
        st.ms, st.ms_min, st.ms_max = res[i]["ms_total"], res[i]["ms_total_min"], res[i]["ms_total_max"]


def full_detail_ratio(comp: Comparison, repeats: int = FULL_ROUNDS, tick=lambda: None) -> float:
    """The full-detail time ratio, paired: the input and the adapted model at ``s_v = 1`` alone,
    ``repeats`` interleaved rounds, the median over rounds of (s_v = 1 round / input round). A
    ratio of two settings measured side by side in each round is far less noisy than two medians
    read from the whole run."""
    pair = [comp.input, comp.get("clod", "s_v=1")]
    res = _time(pair, repeats, tick, seed=1)
    return statistics.median(b / a for a, b in zip(res[0]["per_round"], res[1]["per_round"]))


@dataclass(frozen=True)
class Cell:
    """One comparison of :func:`cells`.

    Attributes:
        kind: ``"full"`` (``s_v = 1`` against the input), ``"time"`` (best within ``share`` of the
            input's frame time) or ``"count"`` (at a decimator point's per-view counts).
        share: the frame-time share (``time``), the decimator point's drawn share of the
            Gaussians in view (``count``: the count budget; the adapted model draws at most
            that), 1 (``full``).
        ours, peer: (method, setting, PSNR dB, time share of the input's frame) of our point and
            the best peer's (the input for ``full``, where our time share is the paired ratio
            :attr:`Comparison.full_ratio` when measured); None where no setting is that fast.
        margin_db: ours - peer (+inf: only ours that fast; -inf: only a peer; nan: neither).
        ceiling: the per-budget ceiling's point (:func:`ceiling_settings`): at the decimator's
            model share (``count``), the best one within the time (``time``); None without one.
    """

    kind: str
    share: float
    ours: Optional[tuple]
    peer: Optional[tuple]
    margin_db: float
    ceiling: Optional[tuple] = None


def _pt(comp: Comparison, p) -> Optional[tuple]:
    if p is None:
        return None
    s = comp.get(p.method, p.setting) if isinstance(p, Point) else p
    return (s.method, s.setting, round(s.psnr, 6), round(s.ms / comp.input.ms, 6))


def cells(comp: Comparison, shares: Sequence[float] = TIME_SHARES) -> list[Cell]:
    """The comparison's cells: full detail, each time share, each equal-count point."""
    inp = comp.input
    pts = lambda methods: [Point(s.method, s.setting, s.ms, s.psnr) for s in comp.settings  # noqa: E731
                           if s.method in methods and not s.setting.startswith("match:")]
    full = comp.get("clod", "s_v=1")
    ours = _pt(comp, full)
    if math.isfinite(comp.full_ratio):  # the paired rounds' ratio, far less noisy than two medians
        ours = ours[:3] + (round(comp.full_ratio, 6),)
    out = [Cell("full", 1.0, ours, _pt(comp, inp), full.psnr - inp.psnr)]
    ceil = [s for s in comp.settings if s.method == "ceiling"]
    for m in time_margins(pts(OURS), pts(PEERS), inp.ms, shares):
        fast = [s for s in ceil if s.ms <= m.share * inp.ms]
        out.append(Cell("time", m.share, _pt(comp, m.ours), _pt(comp, m.peer), m.margin_db,
                        _pt(comp, max(fast, key=lambda s: s.psnr)) if fast else None))
    for st in comp.settings:
        if st.method != "clod" or not st.setting.startswith("match:"):
            continue
        _, dmethod, dsetting = st.setting.split(":")
        point = comp.get(dmethod, dsetting)  # the decimator point: its count per view is the budget
        group = [point] + [s for s in comp.settings if s.setting == st.setting and s.method != "clod"]
        best = max(group, key=lambda s: s.psnr)
        at = next((s for s in ceil if s.setting == dsetting), None)
        out.append(Cell("count", round(comp.in_view_share(point), 6), _pt(comp, st), _pt(comp, best),
                        st.psnr - best.psnr, _pt(comp, at)))
    return out


@dataclass(frozen=True)
class CompareOptions:
    """How :func:`compare` runs.

    Attributes:
        merge_tool: a splat-transform executable (None: the decimators are not run).
        lpips_fn: ``f(img, gt) -> scalar`` or None.
        repeats: interleaved timing rounds.
        full_rounds: paired rounds of :func:`full_detail_ratio` (0: not measured).
        background: [3] colour behind the scene (default black).
        ceiling_views: ``(fit_cams, fit_imgs, val_cams, val_imgs)`` for the per-budget ceiling
            (:func:`ceiling_settings`; needs the decimators), or None (not built).
        ceiling_steps: its fine-tune's length.
        ceiling_cache: a folder where the ceiling's models are kept and read back
            (:func:`ceiling_settings`' ``cache``), or None.
        sweep_rounds: rounds of :func:`sweep_times` (0: not measured; the cost goals read the
            comparison's own timing then).
    """

    merge_tool: Optional[str] = None
    lpips_fn: Optional[Callable] = None
    repeats: int = 5
    full_rounds: int = FULL_ROUNDS
    background: Optional[Sequence[float]] = None
    ceiling_views: Optional[tuple] = None
    ceiling_steps: int = CEILING_STEPS
    ceiling_cache: Optional[Path] = None
    sweep_rounds: int = 0


def compare(adapted: Gaussians, base: Gaussians, fit_cams: Sequence, cams: Sequence, gts: Sequence, *,
            max_sv: float, options: CompareOptions = CompareOptions(), significance: Optional[torch.Tensor] = None,
            log: Callable[[str], None] = lambda s: None, tick=lambda: None) -> Comparison:
    """The whole comparison of an adapted model with the input it was adapted from.

    Args:
        adapted: the adapted model (with ``sigma_d``). base: the input (pretrained) model.
        fit_cams: the views LightGaussian's significance is accumulated on (training views).
        cams, gts: the evaluation views and their images ([H, W, 3] float in [0, 1]).
        max_sv: the adapted model's trained maximum (the equal-count range's low end is
            ``max_sv^-1.5``).
        options: :class:`CompareOptions` (decimators, LPIPS, timing rounds, background, ceiling).
        significance: [N] LightGaussian significance of ``base`` on ``fit_cams``, when the caller
            has it (default: computed).
        log: progress lines. tick: called after each render.

    Raises:
        RuntimeError: a decimator failed.
    """
    o = options
    settings, ctx = build_settings(adapted, base, fit_cams, cams, merge_tool=o.merge_tool, background=o.background,
                                   significance=significance, log=log)
    score(settings, gts, o.lpips_fn, tick)
    extra = matched_settings(settings, ctx, max_sv)
    if o.ceiling_views is not None and o.merge_tool is not None and o.ceiling_steps > 0:
        extra += ceiling_settings(settings, ctx, max_sv, o.ceiling_views, steps=o.ceiling_steps,
                                  cache=o.ceiling_cache, log=log)
    score(extra, gts, o.lpips_fn, tick)
    settings += extra
    log(f"{len(settings)} settings x {len(cams)} views scored; timing x{o.repeats} ...")
    retime(settings, o.repeats, tick)
    comp = Comparison(settings, [v.n_in_view for v in ctx.views], max_sv, merge_run=o.merge_tool is not None)
    if o.full_rounds > 0:
        comp.full_ratio = full_detail_ratio(comp, o.full_rounds, tick)
    if o.sweep_rounds > 0:
        log(f"the sweeps timed alone x{o.sweep_rounds} ...")
        comp.sweep_rounds = sweep_times(comp, o.sweep_rounds, tick)
    return comp


def n_renders(n_views: int, repeats: int, full_rounds: int = FULL_ROUNDS, merge: bool = True,
              n_levels: int = len(S_VS)) -> int:
    """About how many renders :func:`compare` makes (for a progress bar); ``n_levels``: the
    adapted model's levels, ``len(clod_s_vs(adapted))``."""
    n = 1 + n_levels + len(COST_SHARES) + len(COUNT_SHARES) + 2 * len(STATIC_SHARES)
    n += 2 * len(DECIMATE_SHARES) if merge else 0
    # the equal-count points: about three in range per decimator, three methods each
    n += 3 * len(DECIMATORS) * 3 if merge else 0
    return n_views * (n * (2 + repeats) + 2 * (1 + full_rounds))


def _sweep(comp: Comparison) -> tuple[list, list]:
    """The adapted model's ``s_v`` sweep (by ``s_v``) and count-budget sweep (100 % down), as
    ``[(key, setting)]``."""
    lev = sorted(((float(s.setting[4:]), s) for s in comp.settings
                  if s.method == "clod" and s.setting.startswith("s_v=")), key=lambda p: p[0])
    bud = sorted(((-float(s.setting[8:]), s) for s in comp.settings
                  if s.method == "clod" and s.setting.startswith("in_view=")), key=lambda p: p[0])
    return lev, bud


def _matched_pairs(comp: Comparison) -> list[tuple[Setting, Setting]]:
    """Each equal-count point as ``(adapted at the decimator's counts, that decimator's setting)``."""
    out = []
    for s in comp.settings:
        if s.method == "clod" and s.setting.startswith("match:"):
            _, method, setting = s.setting.split(":", 2)
            out.append((s, comp.get(method, setting)))
    return out


def _round_key(st: Setting) -> str:
    """A setting's key in :attr:`Comparison.sweep_rounds`: ``"input"``, the adapted model's setting
    (``s_v=2``, ``match:decimate:model=0.08``) or ``<method>:<setting>`` for a peer."""
    return "input" if st.method == "input" else st.setting if st.method == "clod" else f"{st.method}:{st.setting}"


def sweep_times(comp: Comparison, repeats: int = SWEEP_ROUNDS, tick=lambda: None) -> dict:
    """The input, the adapted model's two sweeps (``s_v=...``, ``in_view=...``) and each
    equal-count pair (the adapted model at a decimator's counts and that decimator) timed alone in
    ``repeats`` interleaved shuffled rounds: key (:func:`_round_key`) -> [repeats] per-round ms
    (median over views), for the paired ratios of :func:`cost_follows`."""
    lev, bud = _sweep(comp)
    sel = [comp.input] + [s for _, s in lev + bud] + [s for pair in _matched_pairs(comp) for s in pair]
    res = _time(sel, repeats, tick, seed=2)
    return {_round_key(st): res[i]["per_round"] for i, st in enumerate(sel)}


def paired_worst_step(rounds: Sequence[Sequence[float]]) -> float:
    """:func:`worst_step` of a sweep timed in paired rounds (``rounds[i][r]``: frame ``i``'s ms in
    round ``r``): the largest median over rounds of ``rounds[j][r] / rounds[i][r]`` over ``i < j``
    (1 or below: the cost never rises along it)."""
    worst = 0.0
    for j in range(1, len(rounds)):
        for i in range(j):
            worst = max(worst, statistics.median(b / a for a, b in zip(rounds[i], rounds[j])))
    return worst


def worst_step(ms: Sequence[float]) -> float:
    """The largest ``ms[j] / ms[i]`` over ``i < j``: a frame of a sweep from detailed to coarse
    against the cheapest more detailed frame (1 or below: the cost never rises along it)."""
    worst, best = 0.0, math.inf
    for m in ms:
        if best < math.inf:
            worst = max(worst, m / best)
        best = min(best, m)
    return worst


def cost_follows(comp: Comparison) -> dict:
    """How the adapted model's frame time follows its level (issue 62's goals 1 and 2):
    ``level_step`` / ``budget_step``, :func:`worst_step` along the ``s_v`` sweep and along the count
    budgets from 100 % to 1 % of the Gaussians in view; ``over_input``, the largest frame of both
    over the input's; ``count_ratio``, the largest time ratio of the adapted model at a decimator's
    count per view to that decimator's own frame (nan without the equal-count points). With
    :attr:`Comparison.sweep_rounds` all three are paired: the sweeps' steps by
    :func:`paired_worst_step`, ``over_input`` and ``count_ratio`` as the median over rounds of a
    frame over the input's / over the decimator's in the same round."""
    lev, bud = _sweep(comp)
    rr = comp.sweep_rounds
    ratios = [statistics.median(b / a for a, b in zip(rr[_round_key(d)], rr[_round_key(o)]))
              if _round_key(o) in rr and _round_key(d) in rr else o.ms / d.ms for o, d in _matched_pairs(comp)]
    out = {"count_ratio": max(ratios) if ratios else float("nan")}
    if rr:
        inp = rr["input"]
        over = [statistics.median(b / a for a, b in zip(inp, rr[s.setting])) for _, s in lev + bud]
        return {**out, "level_step": paired_worst_step([rr[s.setting] for _, s in lev]),
                "budget_step": paired_worst_step([rr[s.setting] for _, s in bud]),
                "over_input": max(over) if over else float("nan")}
    frames = [s.ms for _, s in lev + bud]
    return {**out, "level_step": worst_step([s.ms for _, s in lev]), "budget_step": worst_step([s.ms for _, s in bud]),
            "over_input": max(frames) / comp.input.ms if frames else float("nan")}


# --- what is said ------------------------------------------------------------------------------
def _where(p: tuple) -> str:
    return f"{p[0]} {p[1]}, {p[2]:.2f} dB in {100 * p[3]:.0f} %"


def verdict(comp: Comparison, cs: Optional[Sequence[Cell]] = None) -> str:
    """One paragraph: where the adapted model is ahead of the best peer and by how much, at
    equal frame time and within equal count budgets, and what full detail costs."""
    cs = list(cells(comp) if cs is None else cs)
    inp, full = comp.input, cs[0]
    ratio = comp.full_ratio if math.isfinite(comp.full_ratio) else full.ours[3]
    peers = "LightGaussian and opacity cuts" + (" and splat-transform's decimators" if comp.merge_run else
                                               " (splat-transform's decimators not run)")
    out = [f"Against {peers}: at full detail the adapted model scores {full.ours[2]:.2f} dB against the "
           f"input's {inp.psnr:.2f} dB ({full.margin_db:+.2f} dB) in {100 * ratio:.0f} % of its frame time."]
    ahead, level, behind = [], [], []
    for c in cs:
        if c.kind != "time":
            continue
        lab = f"within {100 * c.share:.0f} %"
        if c.ours is None:
            behind.append(f"{lab} (no level that fast; best peer {_where(c.peer)})" if c.peer
                          else f"{lab} (no setting of any method that fast)")
        elif c.peer is None:
            ahead.append(f"{lab} (only ours: {_where(c.ours)})")
        else:
            line = f"{lab} ({c.margin_db:+.2f} dB: {_where(c.ours)} against {_where(c.peer)})"
            (level if abs(c.margin_db) < LEVEL_DB else ahead if c.margin_db > 0 else behind).append(line)
    parts = [f"ahead {'; '.join(ahead)}" if ahead else "ahead nowhere"]
    if level:
        parts.append(f"level (within {LEVEL_DB} dB) {'; '.join(level)}")
    if behind:
        parts.append(f"behind {'; '.join(behind)}")
    out.append("At equal frame time it is " + ", ".join(parts) + ".")
    counts = [c for c in cs if c.kind == "count"]
    if counts:
        up = [c for c in counts if c.margin_db > 0]
        desc = lambda c: f"{100 * c.share:.0f} % in view {c.margin_db:+.2f} dB against {c.peer[0]}"  # noqa: E731
        out.append(f"Within each decimator point's count per view (in range; the adapted model draws at most that) "
                   f"it is ahead at {len(up)} of "
                   f"{len(counts)}: " + "; ".join(desc(c) for c in counts) + ".")
    elif comp.merge_run:
        out.append("No decimator point lies in the adapted range, so there is no equal-count cell.")
    return " ".join(out)


def csv_text(comp: Comparison) -> str:
    """Every point as CSV (:data:`CSV_COLUMNS`; time share of the input's frame in the same run)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    inp_ms = comp.input.ms
    for s in comp.settings:
        w.writerow([s.method, s.setting, f"{s.psnr:.3f}", f"{s.ssim:.4f}", f"{s.lpips:.4f}", f"{s.ms:.2f}",
                    f"{s.ms_min:.2f}", f"{s.ms_max:.2f}", f"{s.ms / inp_ms:.4f}", f"{statistics.mean(s.drawn):.0f}",
                    f"{comp.in_view_share(s):.4f}", s.storage])
    return buf.getvalue()


STYLE = {"clod": ("C0", "o", "adapted (one model)"), "lightgaussian": ("C1", "s", "LightGaussian cut"),
         "opacity": ("C7", "v", "opacity cut"), "decimate": ("C2", "^", "splat-transform --decimate"),
         "decimate_adaptive": ("C3", "D", "splat-transform --decimate-adaptive"),
         "ceiling": ("k", "*", "ceiling (one fine-tuned model per budget)")}


def plot(path, results: dict) -> None:
    """PSNR against the share of the input's frame time, one panel per ``{title: Comparison}``:
    each method's points and its frontier (best PSNR within each time), written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.atomic import atomic_save

    fig, axes = plt.subplots(1, len(results), figsize=(5.2 * len(results), 4.2), squeeze=False)
    for ax, (title, comp) in zip(axes[0], results.items()):
        inp = comp.input
        for method, (col, mk, lab) in STYLE.items():
            pts = [s for s in comp.settings if s.method == method and not s.setting.startswith("match:")]
            if not pts:
                continue
            x = [100 * s.ms / inp.ms for s in pts]
            ax.scatter(x, [s.psnr for s in pts], color=col, marker=mk, s=18, alpha=0.55)
            fr = frontier(Point(s.method, s.setting, 100 * s.ms / inp.ms, s.psnr) for s in pts)
            ax.step([p.ms for p in fr], [p.psnr for p in fr], where="post", color=col, label=lab)
        ax.axhline(inp.psnr, color="k", lw=0.8, ls=":", label=f"input {inp.psnr:.2f} dB")
        for sh in TIME_SHARES:
            ax.axvline(100 * sh, color="0.8", lw=0.6)
        ax.set_xscale("log")
        ax.set_xlabel("frame time, % of the input's (same run)")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    atomic_save(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    plt.close(fig)


def plot_cost(path, results: dict) -> None:
    """Frame time against the level, one row per ``{title: Comparison}``: the adapted model's
    ms along ``s_v`` (left) and along the count budgets (right, share of the Gaussians in view), as
    shares of the input's frame (paired, :attr:`Comparison.sweep_rounds`, when measured), the
    decimators' points beside the budgets; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.atomic import atomic_save

    fig, axes = plt.subplots(len(results), 2, figsize=(10.4, 3.4 * len(results)), squeeze=False)
    for (ax_l, ax_b), (title, comp) in zip(axes, results.items()):
        t0, rr = comp.input.ms, comp.sweep_rounds

        def share(s: Setting) -> float:
            if rr and _round_key(s) in rr:
                return 100 * statistics.median(b / a for a, b in zip(rr["input"], rr[_round_key(s)]))
            return 100 * s.ms / t0

        lev, bud = _sweep(comp)
        ax_l.plot([k for k, _ in lev], [share(s) for _, s in lev], "o-", ms=3, color=STYLE["clod"][0])
        ax_l.set_xscale("log")
        ax_l.set_xlabel("s_v")
        bud = [(-100 * k, share(s)) for k, s in bud]
        ax_b.plot(*zip(*bud), "o-", ms=3, color=STYLE["clod"][0], label="adapted, count budget")
        for m in DECIMATORS:
            pts = [(100 * comp.in_view_share(s), share(s)) for s in comp.settings if s.method == m]
            if pts:
                ax_b.scatter(*zip(*pts), color=STYLE[m][0], marker=STYLE[m][1], s=18, label=STYLE[m][2])
        ax_b.set_xscale("log")
        ax_b.invert_xaxis()
        ax_b.set_xlabel("Gaussians drawn, % of those in view")
        for ax in (ax_l, ax_b):
            ax.axhline(100, color="k", lw=0.8, ls=":")
            ax.set_ylabel("frame time, % of the input's")
            ax.set_title(title, fontsize=9)
            ax.grid(alpha=0.3)
        ax_b.legend(fontsize=7)
    fig.tight_layout()
    atomic_save(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    plt.close(fig)


def _cell_label(c: Cell) -> str:
    if c.kind == "full":
        return "full detail (s_v = 1 against the input)"
    if c.kind == "time":
        return f"best within {100 * c.share:.0f} % of the input's frame time"
    return f"equal count budget, {100 * c.share:.1f} % of the Gaussians in view"


def cells_markdown(cs: Sequence[Cell]) -> str:
    """The cells as a Markdown table: comparison, ours, the best peer, the margin (dB)."""
    with_ceiling = any(c.ceiling is not None for c in cs)
    out = ["| comparison | adapted: setting, PSNR, time share | best peer: setting, PSNR, time share | margin (dB) |"
           + (" ceiling: setting, PSNR, time share |" if with_ceiling else ""),
           "|---|---|---|---:|" + ("---|" if with_ceiling else "")]
    for c in cs:
        o = "none that fast" if c.ours is None else _where(c.ours)
        p = "none that fast" if c.peer is None else _where(c.peer)
        m = f"{c.margin_db:+.2f}" if math.isfinite(c.margin_db) else ("only ours" if c.margin_db > 0 else
                                                                        "only peers" if c.margin_db < 0 else "-")
        extra = (" - |" if c.ceiling is None else f" {_where(c.ceiling)} |") if with_ceiling else ""
        out.append(f"| {_cell_label(c)} | {o} | {p} | {m} |" + extra)
    return "\n".join(out)


def cells_json(cs: Sequence[Cell]) -> list[dict]:
    """The cells as JSON-able dicts (non-finite margins as None)."""
    def pt(p):
        return None if p is None else {"method": p[0], "setting": p[1], "psnr": p[2], "time_share": p[3]}
    return [{"kind": c.kind, "share": c.share, "ours": pt(c.ours), "peer": pt(c.peer),
             "margin_db": c.margin_db if math.isfinite(c.margin_db) else None, "ceiling": pt(c.ceiling)}
            for c in cs]
