"""What a ``clod-adapt`` job measures and prints of its model: the levels and budgets on the test
views (PSNR, SSIM, Gaussians drawn), timed in interleaved rounds against the input, and the
summary table (:func:`format_summary`)."""
from __future__ import annotations

import os

import torch

from ..evaluate.level_metrics import budget_levels, evaluate_level, evaluate_levels, sv_levels
from ..lod.budget import Budget
from ..lod.draw import PAPER, render_lod

__all__ = ["retime_levels", "level_metrics", "format_summary"]


@torch.no_grad()
def retime_levels(input_model, model, cameras, levels, *, tau, background, repeats: int) -> dict:
    """Interleaved render timings (:func:`clod_adapter.evaluate.timing.time_interleaved`, ``repeats``
    rounds after one warm-up) of the input model and of ``model`` at each s_v in ``levels``, on
    ``cameras``: keys ``"input"`` and each level, each ``time_interleaved``'s record (``ms_total``,
    ``ms_total_min``, ``ms_total_max``, ``ms_select``, ``ms_raster``: wall milliseconds per frame)."""
    from ..evaluate.timing import time_interleaved

    jobs_ = {"input": [lambda c=c: render_lod(input_model, c, None, tau=tau, background=background,
                                              eta_grad=PAPER) for c in cameras]}
    for s in levels:
        jobs_[s] = [lambda c=c, s=s: render_lod(model, c, s, tau=tau, background=background, eta_grad=PAPER)
                    for c in cameras]
    return time_interleaved(jobs_, repeats=repeats, warmup=1)


def level_metrics(inp, model, cfg, o, metrics: dict) -> dict:
    """``metrics`` with ``levels``, ``budgets`` and ``timing`` of ``model`` on the test views of ``inp``
    (:class:`clod_adapter.jobs.adapt_inputs.Inputs`): every ``s_v`` of
    :func:`clod_adapter.evaluate.level_metrics.sv_levels` up to ``cfg.max_sv`` and every budget of
    :func:`~clod_adapter.evaluate.level_metrics.budget_levels`, the levels and the input timed in
    ``o.timing_repeats`` interleaved rounds (:func:`retime_levels`; 0: a single pass, the input's
    ``ms_per_frame`` as ``metrics`` has it). Returns a new dict."""
    bg = cfg.background
    levels = sv_levels(cfg.max_sv)
    evals = evaluate_levels(model, inp.test_cams, inp.test_imgs, levels, tau=cfg.tau, background=bg)
    budget_evals = [evaluate_level(model, inp.test_cams, inp.test_imgs, None, tau=cfg.tau, background=bg,
                                   budget=Budget(in_view=float(b))) for b in budget_levels(cfg.max_sv)]
    timing = None
    if o.timing_repeats > 0:  # ms/frame of the input and every level, interleaved (load hits all alike)
        timing = retime_levels(inp.input_model, model, inp.test_cams, levels, tau=cfg.tau, background=bg,
                               repeats=o.timing_repeats)
    level_dicts = [m.to_dict() for m in evals]
    input_model = dict(metrics["input_model"])
    if timing is not None:
        for d, t in [(input_model, timing["input"])] + [(d, timing[d["s_v"]]) for d in level_dicts]:
            d["ms_per_frame"] = t["ms_total"]
            d["ms_per_frame_min"], d["ms_per_frame_max"] = t["ms_total_min"], t["ms_total_max"]
            if "select_ms" in d:
                d["select_ms"], d["raster_ms"] = t["ms_select"], t["ms_raster"]
    return {**metrics, "input_model": input_model,
            "timing": {"method": "interleaved" if timing is not None else "single pass",
                       "repeats": o.timing_repeats, "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
                       "what": "median over rounds of the median over test views of LoD selection + "
                               "rasterisation wall time (ms); *_min/*_max: smallest/largest round; "
                               "budgets: single pass"},
            "levels": level_dicts, "budgets": [m.to_dict() for m in budget_evals]}


def format_summary(metrics: dict) -> str:
    """A short text table of ``metrics`` (input model, then each s_v); ms/frame is the median of
    interleaved rounds, with the smallest-largest round when measured."""
    n = metrics["num_gaussians"]
    im = metrics["input_model"]

    def ms(d):
        if "ms_per_frame_min" in d:
            return f"{d['ms_per_frame']:9.1f} ({d['ms_per_frame_min']:.1f}-{d['ms_per_frame_max']:.1f})"
        return f"{d['ms_per_frame']:9.1f}"

    lines = [f"{'model':>10} {'PSNR':>7} {'SSIM':>7} {'Gaussians':>10} {'%':>6} {'ms/frame (range)':>16}",
             f"{'input':>10} {im['psnr']:7.2f} {im['ssim']:7.4f} {im['gaussians']:10.0f} "
             f"{100 * im['gaussians'] / n:6.1f} {ms(im)}"]
    for lv in metrics["levels"]:
        lines.append(f"{'s_v=' + format(lv['s_v'], 'g'):>10} {lv['psnr']:7.2f} {lv['ssim']:7.4f} "
                     f"{lv['gaussians']:10.0f} {100 * lv['fraction']:6.1f} {ms(lv)}")
    for lv in metrics.get("budgets", []):
        lines.append(f"{'b=' + format(100 * lv['budget'], '.3g') + '%':>10} {lv['psnr']:7.2f} {lv['ssim']:7.4f} "
                     f"{lv['gaussians']:10.0f} {100 * lv['fraction']:6.1f} {ms(lv)}")
    for note in metrics.get("notes", []):
        lines.append(f"note: {note}")
    return "\n".join(lines)
