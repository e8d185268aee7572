"""The cut a merge-tree model draws for one camera at a level or within a budget
(:func:`tree_select`, :func:`tree_cut`): a level is :func:`clod_adapter.lod.tree.cut`; a count,
cost or time budget is the cut at the level :func:`clod_adapter.lod.tree.budget_s_v` solves for
it, every node at its reference distance (:func:`clod_adapter.lod.tree.budget_frame`), so every
budget is a cut of the same tree, coarser for a smaller budget."""
from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor

from . import tree
from .budget import Budget
from ..gaussians import Gaussians
from . import rule as lod
from .view import view_lod


def tree_node_costs(tiers: Sequence[Gaussians], camera, tt) -> list[Tensor]:
    """Per tier [N_k] float64: each node's clipped ellipse pixels at its own attributes
    (``clod_adapter.lod.cost.splat_cost``, the unit of cost budgets; 0 for a node never drawn at
    ``s_v >= 1`` or culled): one C++ pass per tier (``render/csrc/splat_cost.cpp``) where the
    kernels run, else :func:`splat_cost` (its twin; ``tests/test_cost.py`` holds them together)."""
    from .cost import splat_cost
    from ..render.native import wanted

    out = []
    for t, n, u in zip(tiers, tt.entry, tt.upper):
        drawn = u > n.clamp_min(1.0)
        if wanted(t.means.device.type == "cpu"):
            c = node_costs_native(t, camera)
            out.append(torch.where(drawn, c, torch.zeros_like(c)))
            continue
        c = torch.zeros(len(t), dtype=torch.float64, device=t.means.device)
        idx = torch.nonzero(drawn).flatten()
        if idx.numel():
            c[idx] = splat_cost(view_lod(t, camera), idx)
        out.append(c)
    return out


def node_costs_native(t: Gaussians, camera) -> Tensor:
    """[N] float64 ``"ellipse_px"`` cost of every Gaussian of ``t`` (activated scales, opacities
    ``sigmoid(opacity_logits)``, no gains) from ``camera``, by the C++ kernel
    (:func:`clod_adapter.lod.cost.native_splat_costs`): what :func:`clod_adapter.lod.cost.splat_cost`
    gives at level 0 (to rounding). ``camera``: ``viewmat`` [4, 4] world-to-camera, ``K`` [3, 3]
    pixels, ``width``, ``height`` (pixels).

    Raises:
        RuntimeError: the C++ kernels do not build here (:func:`clod_adapter.render.native.error`)."""
    from .cost import native_splat_costs

    with torch.no_grad():
        scales, opacities = lod.activated(t.log_scales, "exp"), lod.activated(t.opacity_logits, "sigmoid")
    return native_splat_costs(t.means, t.quats, scales, opacities, camera.viewmat, camera.K, int(camera.width),
                              int(camera.height))


def tree_select(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget: Optional[Budget] = None,
                hand_over: Optional[float] = None) -> tuple["tree.TreeCut", tuple]:
    """The cut a tree model draws for ``camera`` at ``s_v`` or within one ``budget``, and its drawn
    attributes (:func:`clod_adapter.lod.tree.cut_attributes`): ``(cut, (means, quats, scales, opacities, colors))``.
    A count budget counts nodes whose centre is in the frustum (``count``; ``share`` of the
    model's Gaussians, of tier 0's; ``in_view``: of tier 0's centres in the frustum); ``cost``:
    pixels of :func:`tree_node_costs` (a float in (0, 1]: that share of tier 0's whole cost);
    ``ms``: predicted ms of its ``time_model`` (default
    ``clod_adapter.lod.cost.DEFAULT_FRAME_TIME_MODEL``). Every budget is a cut of the same tree,
    every node at its reference distance (:func:`clod_adapter.lod.tree.budget_frame`), coarser
    for a smaller budget (:func:`clod_adapter.lod.tree.budget_s_v`); a tree's floor is
    ``s_v = 1`` (the budget's ``min_s_v`` is not read).

    Raises:
        ValueError: not exactly one of ``s_v`` and ``budget``; ``s_v < 1``.
    """
    c = tree_cut(gaussians, camera, s_v, budget=budget, hand_over=hand_over)
    return c, tree.cut_attributes(tree.tiers_of(gaussians), c)


@torch.no_grad()
def tree_cut(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget: Optional[Budget] = None,
             hand_over: Optional[float] = None, whole_as_none: bool = False) -> Optional["tree.TreeCut"]:
    """The cut of :func:`tree_select` (same arguments and errors), without its attributes; with
    ``whole_as_none``, None for a count budget that holds every tier-0 node in the frustum (its
    level is 1: the caller draws tier 0 whole, no cut gathered)."""
    if (s_v is None) == (budget is None):
        raise ValueError("tree_select: give exactly one of s_v and budget")
    if s_v is not None and not float(s_v) >= 1.0:
        raise ValueError(f"s_v must be >= 1, got {s_v}")
    tiers = tree.tiers_of(gaussians)
    if s_v is not None:  # a level: no per-node terms kept
        return tree.cut(tiers, camera, float(s_v), hand_over=hand_over)
    if budget.counts:
        def whole():  # every tier-0 node in the frustum: the level is 1, no sweep
            return None if whole_as_none else tree.cut(tiers, camera, 1.0, hand_over=hand_over)

        n = len(tiers[0])
        if (budget.in_view >= 1.0) if budget.kind == "in_view" else budget.of(n) >= n:
            return whole()  # holds every tier-0 node whatever the view: no per-node pass
        at = tree.budget_frame(tiers, camera)
        n0 = int(at[1][0].sum())
        k = budget.of(n, n0)
        return whole() if k >= n0 else tree.budget_cut(tiers, camera, k, hand_over=hand_over, at=at, n_frustum=n0)
    from .cost import DEFAULT_FRAME_TIME_MODEL

    tt = tree.terms(tiers, camera, hand_over=hand_over, at=tree.budget_frame(tiers, camera))
    costs = tree_node_costs(tiers, camera, tt)
    if budget.cost is not None:
        limit = float(budget.cost) * float(costs[0].sum()) if float(budget.cost) <= 1.0 else float(budget.cost)
        s_v = tree.budget_s_v(tt, limit, costs)
    else:
        tm = budget.time_model or DEFAULT_FRAME_TIME_MODEL
        weights = [torch.where(c > 0, tm.per_splat_ms(c), c) for c in costs]
        s_v = tree.budget_s_v(tt, float(budget.ms) - tm.c0_ms, weights)
    return tree.cut(tiers, camera, float(s_v), hand_over=hand_over, tt=tt)
