"""Popping: how much the image jumps along a continuous ``s_v`` sweep, against one switch
between two static levels (``clod-eval``'s measure, issue 36's goal 5: >= 10x smaller steps).

:func:`popping_sweep` gives the sweep (through every tier's hand-over on a model with merged
tiers), :func:`popping_curve` the per-step image change of the model along it and the one jump of
a discrete switch, :func:`popping_ratio` ``clod-eval``'s ratio from one camera (the input cut by
LightGaussian significance as the discrete levels), :func:`popping_budget_ratio` the same along
count budgets.
"""
from __future__ import annotations

import statistics
from typing import Callable, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from ..lod.rankings import ranking_selection, render_subset
from ..lod.budget import Budget
from ..lod.draw import PAPER, render_lod, tier_reach
from ..gaussians import Gaussians

#: the sweep's end past the trained maximum (``clod-eval``'s ``s_v`` grid ends at 1.2 ``max_sv``)
SWEEP_OVERSHOOT = 1.2
#: issue 36's goal 5: the sweep's largest step at least this many times smaller than one switch
POPPING_GOAL = 10.0
#: the smallest count budget of :func:`popping_budget_ratio`'s sweep, a share of the Gaussians in
#: view (issue 62's budget sweep: 100 % to 1 %)
BUDGET_LOWEST = 0.01
#: frames of the sweep (``clod-eval``'s ``popping_steps``)
SWEEP_STEPS = 61


def popping_sweep(max_sv: float, reach: float = 1.0, steps: int = SWEEP_STEPS) -> list[float]:
    """The ``s_v`` values of ``clod-eval``'s popping sweep: ``steps`` of them from 1 to the end of
    ``clod-eval``'s ``s_v`` grid (:data:`SWEEP_OVERSHOOT` ``max_sv``), evenly spaced; for a model
    with merged tiers (``reach`` > 1, :func:`clod_adapter.lod.draw.tier_reach`) evenly in
    ``ln s_v`` to that end times ``reach``, through every tier's hand-over to the last tier's 1.2
    ``max_sv``.

    Raises:
        ValueError: ``steps`` < 2 or ``max_sv`` < 1.
    """
    if not max_sv >= 1:
        raise ValueError(f"max_sv must be >= 1, got {max_sv}")
    top = max(SWEEP_OVERSHOOT * max_sv, 1.0 + 1e-3)
    if steps < 2:
        raise ValueError(f"need at least 2 s_v steps, got {steps}")
    if reach > 1.0:
        return [float(x) for x in np.geomspace(1.0, top * reach, steps)]
    return [float(x) for x in np.linspace(1.0, top, steps)]


def image_change(a: Tensor, b: Tensor) -> float:
    """Mean absolute difference of two [H, W, 3] images clamped to [0, 1] (per pixel and
    channel, in [0, 1] units): the per-step image change used for popping."""
    return float((a.clamp(0, 1) - b.clamp(0, 1)).abs().mean())


@torch.no_grad()
def popping_curve(gaussians: Gaussians, camera, s_vs: Sequence[float], *,
                  discrete_model: Optional[Gaussians] = None, discrete_scores: Optional[Tensor] = None,
                  switch_s_v: Optional[float] = None, tau: Optional[float] = None, background=None,
                  backend: str = "auto", on_render: Optional[Callable[[], None]] = None,
                  budgets: bool = False) -> dict:
    """Popping of continuous LoD vs a discrete LoD switch, from one fixed camera.

    Continuous: render ``gaussians`` at each ``s_v`` in ``s_vs`` (increasing, small steps) and
    record the per-step image change (:func:`image_change`, mean |dI| in [0, 1] units) between
    consecutive frames. Discrete: the same range covered by two levels cut from
    ``discrete_model`` (default: ``gaussians`` without ``sigma_d``) by a global ranking
    ``discrete_scores`` [N] (default: opacity), at the Gaussian counts the continuous sweep
    renders at its first and last ``s_v``, switched once at ``switch_s_v`` (default: the middle
    of the range); its step change is 0 except at the switch. With ``budgets``, ``s_vs`` are count
    budgets instead, shares of the Gaussians in view (``Budget(in_view=...)``), in the
    order swept (e.g. 1 down to 0.01).

    Returns:
        dict with ``s_v`` [S], ``gaussians`` [S] (continuous), ``step_s_v`` [S-1] (step
        midpoints), ``continuous_step`` / ``discrete_step`` [S-1], ``switch_s_v``,
        ``discrete_counts`` [2], ``continuous_max`` / ``continuous_median`` /
        ``discrete_max`` / ``discrete_median`` (image change units) and ``ratio`` =
        discrete_max / continuous_max (inf when the continuous sweep never changes).
    """
    s_vs = [float(s) for s in s_vs]
    if len(s_vs) < 2:
        raise ValueError("popping_curve needs at least 2 values of s_v")
    frames, counts = [], []
    for s in s_vs:
        if budgets:  # a count-budget sweep: s is a share of the Gaussians in view
            out = render_lod(gaussians, camera, budget=Budget(in_view=s), tau=tau, background=background,
                             backend=backend, eta_grad=PAPER)
        else:
            out = render_lod(gaussians, camera, s, tau=tau, background=background, backend=backend,
                             eta_grad=PAPER)
        frames.append(out.image.clamp(0, 1))
        counts.append(out.n_rendered)
        if on_render:
            on_render()
    cont = [image_change(a, b) for a, b in zip(frames[:-1], frames[1:])]
    dm = gaussians.with_sigma_d(None) if discrete_model is None else discrete_model
    scores = dm.opacities if discrete_scores is None else discrete_scores
    switch = 0.5 * (s_vs[0] + s_vs[-1]) if switch_s_v is None else float(switch_s_v)
    levels = []
    for k in (counts[0], counts[-1]):
        sel = ranking_selection(dm, camera, scores, k)
        levels.append(render_subset(dm, camera, sel.indices, sel.opacities, background=background, view=sel.view,
                                    backend=backend).image.clamp(0, 1))
        if on_render:
            on_render()
    jump = image_change(levels[0], levels[1])
    disc = [jump if (a < switch <= b) else 0.0 for a, b in zip(s_vs[:-1], s_vs[1:])]
    if not any(disc):  # switch outside the range: put it at the middle step
        disc[len(disc) // 2] = jump
    cmax = max(cont)
    return {
        "s_v": s_vs, "gaussians": counts, "step_s_v": [0.5 * (a + b) for a, b in zip(s_vs[:-1], s_vs[1:])],
        "continuous_step": cont, "discrete_step": disc, "switch_s_v": switch,
        "discrete_counts": [counts[0], counts[-1]], "metric": "mean |dI| per pixel and channel, [0, 1] units",
        "continuous_max": cmax, "continuous_median": statistics.median(cont),
        "discrete_max": max(disc), "discrete_median": statistics.median(disc),
        "ratio": (max(disc) / cmax) if cmax > 0 else float("inf"),
    }


def popping_ratio(model: Gaussians, base: Gaussians, camera, scores: Optional[Tensor] = None, *,
                  steps: int = SWEEP_STEPS, background=None, on_render=None) -> dict:
    """``clod-eval``'s popping from ``camera``: :func:`popping_curve` of ``model`` along
    :func:`popping_sweep` (``steps`` frames through every tier's hand-over), the discrete levels
    cut from ``base`` (the input) by ``scores`` [N_base] (LightGaussian significance,
    :func:`clod_adapter.lod.rankings.lightgaussian_significance`; None: opacity). Returns
    :func:`popping_curve`'s dict (``ratio``: the switch's jump over the largest step).

    Raises:
        ValueError: as :func:`popping_sweep` (``max_sv`` < 1, ``steps`` < 2)."""
    svs = popping_sweep(model.lod.max_sv, tier_reach(model), steps)
    if background is not None and not isinstance(background, Tensor):
        background = torch.as_tensor(background, dtype=model.means.dtype)
    return popping_curve(model, camera, svs, discrete_model=base, discrete_scores=scores, background=background,
                         on_render=on_render)


def popping_budget_ratio(model: Gaussians, base: Gaussians, camera, scores: Optional[Tensor] = None, *,
                         steps: int = SWEEP_STEPS, lowest: float = BUDGET_LOWEST, background=None) -> dict:
    """Popping along a count budget from ``camera``: :func:`popping_curve` of ``model`` at
    ``steps`` budgets log-spaced from all the Gaussians in view down to ``lowest`` of them
    (``Budget(in_view=...)``), the discrete levels cut from ``base`` by
    ``scores`` as :func:`popping_ratio` does. Returns :func:`popping_curve`'s dict (``s_v``: the
    budgets).

    Raises:
        ValueError: ``steps`` < 2 or ``lowest`` not in (0, 1)."""
    if not 0.0 < lowest < 1.0:
        raise ValueError(f"lowest must be in (0, 1), got {lowest}")
    if steps < 2:
        raise ValueError(f"need at least 2 budget steps, got {steps}")
    shares = [float(x) for x in np.geomspace(1.0, lowest, steps)]
    if background is not None and not isinstance(background, Tensor):
        background = torch.as_tensor(background, dtype=model.means.dtype)
    return popping_curve(model, camera, shares, discrete_model=base, discrete_scores=scores, background=background,
                         budgets=True)
