"""A count budget between two merged tiers, drawn as one mixed frame (a model whose
``LodSettings.count_mix`` is set: chosen per scene by ``clod-adapt``'s default ``--count-mix auto``,
or ``--count-mix on``).

A count budget of ``k`` Gaussians on a model with merged tiers (docs/lod_rule_chain.md "The tiers")
that ends in a tier whose full detail (its start, where the ``s_v`` rule first draws it alone)
holds more than ``k`` in view, the next tier holding fewer, draws the **nearer** Gaussians of the
finer tier and the **farther** of the coarser one, split at the camera distance ``D`` (world
units) where the two together hold ``k``. As ``k`` falls from one tier's count to the next's the
split moves from behind the scene to the camera, so the frame goes over from one tier's full
detail to the next's a Gaussian at a time, with no frame of a tier's survivors grown by its gains.
Without it such a budget is cut from the finer tier's survivors
(:func:`clod_adapter.camera_lod.budget_walk`). On the validation views of the shared scenes the
mix scores better on the 360-degree skull and worse on both forward-facing ferns, where the
farthest Gaussians are the large background splats, and the training views give each scene the
same verdict (:func:`clod_adapter.tiers.choose_count_mix`; docs/studies.md "A count budget
between two tiers, mixed by distance").

:func:`mix` draws it; :func:`split_distance` solves ``D``; :func:`clod_adapter.camera_lod.budget_walk`
decides where.
"""
from __future__ import annotations

import torch
from torch import Tensor

from . import lod


def split_distance(r_near: Tensor, r_far: Tensor, k: int) -> float:
    """The split of two tiers for a count ``k``: the largest distance ``D`` (world units) at
    which ``#(r_near < D) + #(r_far >= D) <= k``; ``r_near`` [A] are the finer tier's distances to
    the camera, ``r_far`` [B] the coarser tier's (any order). ``-inf`` where even ``D = -inf``
    (the coarser tier whole, ``B`` Gaussians) exceeds ``k``; ``+inf`` where ``A <= k``.

    The count is not monotone in ``D`` (each finer Gaussian passed adds one, each coarser one
    takes one away), so every candidate is evaluated: O((A + B) log(A + B))."""
    a, _ = r_near.reshape(-1).sort()
    b, _ = r_far.reshape(-1).sort()
    if a.numel() <= k:
        return float("inf")
    cand = torch.cat([a, b]).sort().values
    counts = torch.searchsorted(a, cand) + (b.numel() - torch.searchsorted(b, cand))
    ok = torch.nonzero(counts <= k, as_tuple=False)  # the smallest candidate counts the coarser tier whole
    return float(cand[ok[-1, 0]]) if ok.numel() else float("-inf")


def mix(view_a, view_b, start_a, start_b, k: int, s_a: float, s_b: float):
    """A count budget of ``k`` drawn by two neighbouring tiers, the finer ``a`` and the coarser
    ``b``: ``start_a`` / ``start_b`` are each tier's start selection (its full detail,
    :class:`clod_adapter.camera_lod.LodSelection`) in its :class:`clod_adapter.camera_lod.LodView`
    ``view_a`` / ``view_b`` of one camera, ``start_b`` drawing fewer than ``k``; ``s_a`` / ``s_b``
    the model's ``s_v`` each start stands for.

    Returns:
        ``(near, far, s_v)``: ``start_a``'s rows nearer the camera than :func:`split_distance`
        and ``start_b``'s at or beyond it (selections with their drawn opacities and level;
        exactly ``k`` together where the split allows, never more), and the model's ``s_v`` the
        frame stands for, interpolated in ``ln s_v`` between ``s_a`` and ``s_b`` by the count.
    """
    c = lod.camera_center(view_a.viewmat)
    ra = (view_a.means.index_select(0, start_a.indices) - c).norm(dim=1)
    rb = (view_b.means.index_select(0, start_b.indices) - c).norm(dim=1)
    d = split_distance(ra, rb, k)
    near, far = start_a.rows(ra < d), start_b.rows(rb >= d)
    n_a, n_b = int(start_a.indices.numel()), int(start_b.indices.numel())
    x = (near.indices.numel() + far.indices.numel() - n_b) / max(n_a - n_b, 1)  # 0: the coarser whole
    return near, far, float(s_a ** x * s_b ** (1.0 - x))
