"""The cut a merge-tree model draws for one camera at a level or within a budget
(:func:`tree_select`, :func:`tree_cut`): a level is :func:`clod_adapter.lod.tree.cut`; a count,
cost or time budget is the cut at the level :func:`clod_adapter.lod.tree.budget_s_v` solves for
it, so every budget is a cut of the same tree, coarser for a smaller budget."""
from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor

from . import tree
from ..gaussians import Gaussians
from .view import view_lod


def _tree_count(budget, n_model: int, n_frustum: int, in_view: bool) -> int:
    """A count budget as a number of Gaussians (``clod_adapter.lod.budget.budget_count``'s reading: an
    int is a count, a float in [0, 1] a share of the model, or of tier 0's frustum with ``in_view``)."""
    from .budget import budget_count, normalize_budget

    b = normalize_budget(budget)
    return budget_count(b, n_frustum if (in_view and isinstance(b, float)) else n_model)


def tree_node_costs(tiers: Sequence[Gaussians], camera, tt) -> list[Tensor]:
    """Per tier [N_k] float64: each node's clipped ellipse pixels at its own attributes
    (``clod_adapter.lod.cost.splat_cost``, the unit of cost budgets; 0 for a node never drawn at
    ``s_v >= 1`` or culled)."""
    from .cost import splat_cost

    out = []
    for t, n, u in zip(tiers, tt.entry, tt.upper):
        c = torch.zeros(len(t), dtype=torch.float64, device=t.means.device)
        idx = torch.nonzero(u > n.clamp_min(1.0)).flatten()
        if idx.numel():
            c[idx] = splat_cost(view_lod(t, camera), idx)
        out.append(c)
    return out


@torch.no_grad()
def tree_select(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget=None, budget_cost=None,
                budget_ms=None, time_model=None, budget_in_view: bool = False,
                hand_over: float = tree.HAND_OVER) -> tuple["tree.TreeCut", tuple]:
    """The cut a tree model draws for ``camera`` at ``s_v`` or within one budget, and its drawn
    attributes (:func:`clod_adapter.lod.tree.cut_attributes`): ``(cut, (means, quats, scales, opacities, colors))``.
    ``budget``: a count (int) or a share (float in [0, 1]) of the model's Gaussians (of tier 0's
    centres in the frustum with ``budget_in_view``), counted as centres in the frustum;
    ``budget_cost``: pixels of :func:`tree_node_costs` (a float in (0, 1]: that share of tier 0's
    whole cost); ``budget_ms``: predicted ms of ``time_model`` (default
    ``clod_adapter.lod.cost.DEFAULT_FRAME_TIME_MODEL``). Every budget is a cut of the same tree,
    coarser for a smaller budget (:func:`clod_adapter.lod.tree.budget_s_v`).

    Raises:
        ValueError: not exactly one of ``s_v`` and the budgets; ``s_v < 1``.
    """
    c = tree_cut(gaussians, camera, s_v, budget=budget, budget_cost=budget_cost, budget_ms=budget_ms,
                 time_model=time_model, budget_in_view=budget_in_view, hand_over=hand_over)
    return c, tree.cut_attributes(tree.tiers_of(gaussians), c)


@torch.no_grad()
def tree_cut(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget=None, budget_cost=None,
             budget_ms=None, time_model=None, budget_in_view: bool = False, hand_over: float = tree.HAND_OVER,
             whole_as_none: bool = False) -> Optional["tree.TreeCut"]:
    """The cut of :func:`tree_select` (same arguments and errors), without its attributes; with
    ``whole_as_none``, None for a count budget that holds every tier-0 node in the frustum (its
    level is 1: the caller draws tier 0 whole, no cut gathered)."""
    if sum(x is not None for x in (s_v, budget, budget_cost, budget_ms)) != 1:
        raise ValueError("tree_select: give exactly one of s_v, budget, budget_cost, budget_ms")
    if s_v is not None and not float(s_v) >= 1.0:
        raise ValueError(f"s_v must be >= 1, got {s_v}")
    tiers = tree.tiers_of(gaussians)
    if s_v is not None:  # a level: no per-node terms kept
        return tree.cut(tiers, camera, float(s_v), hand_over=hand_over)
    if budget is not None:
        at = tree.frame(tiers, camera)
        n0 = int(at[1][0].sum())
        k = _tree_count(budget, len(gaussians), n0, budget_in_view)
        if k >= n0:  # every tier-0 node in the frustum: the level is 1, no sweep
            return None if whole_as_none else tree.cut(tiers, camera, 1.0, hand_over=hand_over)
        tt = tree.terms(tiers, camera, hand_over=hand_over, at=at)
        s_v = tree.budget_s_v(tt, k)
        return tree.cut(tiers, camera, float(s_v), hand_over=hand_over, tt=tt)
    from .cost import DEFAULT_FRAME_TIME_MODEL

    tt = tree.terms(tiers, camera, hand_over=hand_over)
    costs = tree_node_costs(tiers, camera, tt)
    if budget_cost is not None:
        limit = float(budget_cost) * float(costs[0].sum()) if float(budget_cost) <= 1.0 else float(budget_cost)
        s_v = tree.budget_s_v(tt, limit, costs)
    else:
        tm = DEFAULT_FRAME_TIME_MODEL if time_model is None else time_model
        weights = [torch.where(c > 0, tm.per_splat_ms(c), c) for c in costs]
        s_v = tree.budget_s_v(tt, float(budget_ms) - tm.c0_ms, weights)
    return tree.cut(tiers, camera, float(s_v), hand_over=hand_over, tt=tt)
