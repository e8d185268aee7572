"""What ``clod-eval`` compares: the registry of methods (:data:`METHOD_REGISTRY`: the adapted
model, the static rankings, splat-transform's decimators), each with its plot style and how it
selects or builds its Gaussians."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional

from torch import Tensor

from ..lod.rankings import constant_sigma_selection, ranking_selection


@dataclass(frozen=True)
class RankingContext:
    """What the ranking baselines select from, computed once per report: the pretrained model's
    LightGaussian significance on the training views and a seeded random ranking (both [N]
    float32), and the constant-sigma baseline's ``sigma_c`` and ``tau``."""

    lightgaussian: Tensor
    random: Tensor
    sigma_c: float
    tau: float


@dataclass(frozen=True)
class Method:
    """One method of the report: its plot style (matplotlib colour, line style, marker) and, for
    a ranking baseline, how it selects ``k`` Gaussians of the pretrained model in one view
    (``select(base, camera, k, ctx: RankingContext) -> Selection``); ``decimate``: the
    ``merge_decimate`` mode of a splat-transform decimator. Adding a baseline is one entry of
    :data:`METHOD_REGISTRY`."""

    style: tuple
    select: Optional[Callable] = None
    decimate: Optional[str] = None


#: every method of the report, in table and legend order.
METHOD_REGISTRY: dict[str, Method] = {
    "clod": Method(("C0", "-", ".")),
    "clod_budget": Method(("C0", "", "o")),
    "constant_sigma": Method(("C1", "--", "s"), select=lambda base, cam, k, ctx: constant_sigma_selection(
        base, cam, k, ctx.sigma_c, tau=ctx.tau)),
    "lightgaussian": Method(("C2", "--", "^"), select=lambda base, cam, k, ctx: ranking_selection(
        base, cam, ctx.lightgaussian, k)),
    "random": Method(("C3", ":", "x"), select=lambda base, cam, k, ctx: ranking_selection(base, cam, ctx.random, k)),
    # splat-transform 3.7.0's untrained decimators
    "decimate": Method(("C4", "--", "D"), decimate="decimate"),
    "decimate_adaptive": Method(("C6", "--", "v"), decimate="adaptive"),
    "dlod_finetuned": Method(("C5", "-.", "P")),
    "pretrained": Method(("k", "", "*")),
}


#: the ranking baselines (drawn at the adapted budgets' per-view counts).
BASELINES = tuple(k for k, m in METHOD_REGISTRY.items() if m.select is not None)
#: the decimators (method name -> ``merge_decimate`` mode).
DECIMATORS = {k: m.decimate for k, m in METHOD_REGISTRY.items() if m.decimate is not None}
METHODS = tuple(METHOD_REGISTRY)


def finite(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
