"""Evaluation of a model on a set of views at several levels of detail.

Metrics follow 3DGS evaluation: renders clamped to [0, 1], PSNR and SSIM (11x11 Gaussian window)
per view, averaged over views. Time is the median per-frame wall time (LoD selection plus
rasterisation) in milliseconds on the current device and thread count.
"""
from __future__ import annotations

import math
import statistics
from dataclasses import asdict, dataclass
from typing import Callable, Optional, Sequence

import torch
from torch import Tensor


from ..gaussians import Gaussians
from ..lod.budget import Budget
from ..lod.draw import PAPER, render_lod
from ..metrics import psnr, ssim


@dataclass
class LevelMetrics:
    """Metrics of one level of detail averaged over views.

    ``s_v`` is None for the plain (non-LoD) model (in budget mode: the mean solved ``s_v``).
    ``budget`` is the requested budget's amount (:attr:`Budget.amount`; None in s_v mode). ``gaussians`` is the mean number of
    Gaussians rendered per view, ``fraction`` that over the model size; times are medians in ms
    (``select_ms``: everything before the rasteriser, :attr:`clod_adapter.lod.draw.LodRender.lead_ms`;
    ``ms_per_frame``: the whole frame).
    """

    s_v: Optional[float]
    psnr: float
    ssim: float
    gaussians: float
    fraction: float
    ms_per_frame: float
    select_ms: float
    raster_ms: float
    per_view_psnr: list
    budget: Optional[float] = None

    def to_dict(self) -> dict:
        return asdict(self)


@torch.no_grad()
def evaluate_level(
    gaussians: Gaussians,
    cameras: Sequence,
    images: Sequence[Tensor],
    s_v: Optional[float],
    *,
    tau: Optional[float] = None,
    background=None,
    backend: str = "auto",
    budget: Optional[Budget] = None,
) -> LevelMetrics:
    """Render every camera at ``s_v`` (None: no LoD) or within ``budget`` (a
    :class:`clod_adapter.lod.budget.Budget`; ``s_v`` solved per view, at least its ``min_s_v``)
    and score against ``images`` ([H, W, 3] float in [0, 1], one per camera): mean PSNR (dB) and
    SSIM, the mean count drawn, and the median select / raster / total ms per frame.

    Raises:
        ValueError, TypeError: as :func:`clod_adapter.lod.draw.render_lod` (``s_v < 1``, both
            ``s_v`` and ``budget``, a model without ``sigma_d``)."""
    ps, ss, counts, tms, sel, ras, svs = [], [], [], [], [], [], []
    for cam, gt in zip(cameras, images):
        out = render_lod(gaussians, cam, s_v, tau=tau, background=background, backend=backend,
                         eta_grad=PAPER, budget=budget)
        svs.append(out.s_v)
        img = out.image.clamp(0, 1)
        gt = gt.to(img.device)
        ps.append(psnr(img, gt))
        ss.append(float(ssim(img, gt)))
        counts.append(out.n_rendered)
        sel.append(out.lead_ms)  # a plain frame's projection included, as a tree cut's is in its raster_ms
        ras.append(out.raster_ms)
        tms.append(out.lead_ms + out.raster_ms)
    n = max(len(gaussians), 1)
    mean_count = sum(counts) / max(len(counts), 1)
    if budget is not None and svs and all(v is not None for v in svs):
        s_v = sum(svs) / len(svs)
    return LevelMetrics(
        budget=None if budget is None else budget.amount, s_v=s_v, psnr=sum(ps) / len(ps),
        ssim=sum(ss) / len(ss), gaussians=mean_count,
        fraction=mean_count / n, ms_per_frame=statistics.median(tms),
        select_ms=statistics.median(sel), raster_ms=statistics.median(ras), per_view_psnr=ps,
    )


def evaluate_levels(
    gaussians: Gaussians,
    cameras: Sequence,
    images: Sequence[Tensor],
    s_vs: Sequence[float],
    *,
    tau: Optional[float] = None,
    background=None,
    backend: str = "auto",
    progress: Optional[Callable[[LevelMetrics], None]] = None,
) -> list[LevelMetrics]:
    """:func:`evaluate_level` for each ``s_v`` in ``s_vs``."""
    out = []
    for s in s_vs:
        m = evaluate_level(gaussians, cameras, images, s, tau=tau, background=background,
                           backend=backend)
        out.append(m)
        if progress is not None:
            progress(m)
    return out


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
