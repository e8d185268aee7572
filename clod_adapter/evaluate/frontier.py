"""Quality against frame time: each method's PSNR-vs-ms frontier and the margins between them.

A level of detail exists to make a frame cheaper, so methods are compared at equal *frame time*
(same renderer, interleaved timing rounds, one run: :mod:`clod_adapter.evaluate.timing`), not only at
equal counts. Every method contributes *points* (one per setting: a level, a budget, a cut):
mean quality over the views and the median frame time. A method's frontier at time ``t`` is the
best quality among its points that take at most ``t`` ms (a step function: a method offers
exactly the settings it was measured at; nothing is interpolated). Times are given as a share of
the input's frame time measured in the same run, so ratios, not absolute ms, are compared.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Optional, Sequence


@dataclass(frozen=True)
class Point:
    """One measured setting of one method.

    Attributes:
        method: method name (e.g. ``clod``, ``lightgaussian``, ``decimate``).
        setting: the setting (e.g. ``s_v=2``, ``budget=0.25``, ``count=0.3``).
        ms: median frame time, ms (render of the setting, selection included).
        psnr: mean PSNR over the views, dB.
        drawn: mean Gaussians drawn per view.
    """

    method: str
    setting: str
    ms: float
    psnr: float
    drawn: float = float("nan")


def frontier(points: Iterable[Point]) -> list[Point]:
    """The points no other point beats on both axes (faster or equal *and* better), sorted by ms:
    the upper-left staircase of PSNR against time."""
    pts = sorted((p for p in points if math.isfinite(p.ms) and math.isfinite(p.psnr)),
                 key=lambda p: (p.ms, -p.psnr))
    out: list[Point] = []
    for p in pts:
        if not out or p.psnr > out[-1].psnr:
            out.append(p)
    return out


def best_within(points: Iterable[Point], ms: float) -> Optional[Point]:
    """The best-PSNR point taking at most ``ms`` ms, or None when every point is slower."""
    cand = [p for p in points if math.isfinite(p.psnr) and p.ms <= ms]
    return max(cand, key=lambda p: p.psnr) if cand else None


@dataclass(frozen=True)
class TimeMargin:
    """The comparison at one frame-time share (:func:`time_margins`).

    Attributes:
        share: the frame-time share of the input (e.g. 0.5).
        ms: ``share`` x the input's ms.
        ours: our best point within ``ms`` (None: no setting that fast).
        peer: the peers' best point within ``ms`` (None: no peer that fast).
        margin_db: ``ours.psnr - peer.psnr``; +inf when only ours reaches that time, -inf when
            only a peer does, nan when neither does.
    """

    share: float
    ms: float
    ours: Optional[Point]
    peer: Optional[Point]
    margin_db: float


def time_margins(ours: Sequence[Point], peers: Sequence[Point], input_ms: float,
                 shares: Sequence[float]) -> list[TimeMargin]:
    """Our frontier against the best of the peers' frontiers at each frame-time ``share`` of the
    input's ``input_ms``.

    Args:
        ours: points of the method under test.
        peers: points of every static method (all of them: the best one at each time counts).
        input_ms: the input's full frame time in the same run, ms (> 0).
        shares: frame-time shares to compare at, e.g. (0.75, 0.5, 0.25, 0.1).

    Raises:
        ValueError: ``input_ms`` not positive.
    """
    if not input_ms > 0:
        raise ValueError(f"input_ms must be > 0, got {input_ms}")
    out = []
    for s in shares:
        t = float(s) * input_ms
        a, b = best_within(ours, t), best_within(peers, t)
        if a is not None and b is not None:
            m = a.psnr - b.psnr
        elif a is not None:
            m = math.inf
        elif b is not None:
            m = -math.inf
        else:
            m = math.nan
        out.append(TimeMargin(float(s), t, a, b, m))
    return out
