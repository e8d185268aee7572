"""Estimated CPU raster time for a drawn count: our rasteriser, timed on the model at startup.

The viewer's read-out gives, next to the count, what rasterising that many Gaussians costs with
*our* CPU rasteriser (:func:`clod_adapter.render.rasterization`, backend ``"cpu"``) at one image
size: a least-squares line ``ms = a + b n`` (a, b >= 0) through three timings on the model itself
(the Gaussians in view of the start camera: all of them, a half and a quarter, each the median
of ``repeats`` runs after a warm-up). It is an estimate of our renderer's cost, not the browser's frame time.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from clod_adapter.gaussians import Gaussians
from clod_adapter.lod.view import in_view
from clod_adapter.render import rasterization

__all__ = ["RasterTimeModel", "calibrate_raster_time"]


@dataclass
class RasterTimeModel:
    """``ms = intercept_ms + per_gaussian_ms * n`` (both >= 0), fitted at ``width`` x ``height``
    with ``threads`` torch threads from ``(counts[i], times_ms[i])``."""

    intercept_ms: float
    per_gaussian_ms: float
    width: int
    height: int
    threads: int
    counts: tuple
    times_ms: tuple

    def estimate_ms(self, n: int) -> float:
        """Estimated CPU raster milliseconds for ``n`` Gaussians at the fitted image size."""
        return self.intercept_ms + self.per_gaussian_ms * max(int(n), 0)

    def label(self) -> str:
        """How the estimate was made, for the read-out."""
        return (f"our CPU rasteriser, {self.threads} threads, {self.width}x{self.height}, "
                f"line fitted at startup to {' / '.join(f'{c:,}' for c in self.counts)} Gaussians of this model")


def _time_ms(fn, repeats: int) -> float:
    fn()  # warm-up (first use may also build the C++ compositor)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts)


@torch.no_grad()
def calibrate_raster_time(gaussians: Gaussians, camera, *, max_count: int = 200_000,
                          repeats: int = 3, seed: int = 0) -> Optional[RasterTimeModel]:
    """Fit :class:`RasterTimeModel` on ``gaussians`` seen from ``camera``.

    Args:
        gaussians: the model (any; ``sigma_d`` unused: Gaussians drawn with their opacities).
        camera: ``viewmat``, ``K``, ``width``, ``height``; the image size of the estimate.
        max_count: at most this many in-view Gaussians are timed (a random subset, so a large
            model costs a bounded startup); larger counts are extrapolated by the line.
        repeats: timed runs per count (median).

    Returns:
        the model, or None when fewer than 8 Gaussians are in view (nothing to fit).
    """
    g = gaussians
    viewmat = camera.viewmat.to(g.means)
    K = camera.K.to(g.means)
    w, h = int(camera.width), int(camera.height)
    pool = torch.nonzero(in_view(g, viewmat, K, w, h), as_tuple=False).squeeze(1)
    if pool.numel() < 8:
        return None
    gen = torch.Generator().manual_seed(seed)
    pool = pool[torch.randperm(pool.numel(), generator=gen)[:max_count]]
    counts = (int(pool.numel()), int(pool.numel()) // 2, int(pool.numel()) // 4)
    times = []
    for n in counts:
        idx = pool[:n]
        args = (g.means[idx], g.quats[idx], g.scales[idx], g.opacities[idx], g.colors[idx],
                viewmat[None], K[None], w, h)
        times.append(_time_ms(lambda: rasterization(*args, sh_degree=g.sh_degree, backend="cpu"), repeats))
    x, y = np.asarray(counts, dtype=np.float64), np.asarray(times)
    slope = max(float(np.polyfit(x, y, 1)[0]), 0.0)
    intercept = max(float(np.mean(y - slope * x)), 0.0)
    return RasterTimeModel(intercept, slope, w, h, torch.get_num_threads(), counts, tuple(times))
