"""Fitting a merge tree on its own cuts: the merged tiers trained where the tree draws them.

Each tier of a tree was fitted as a whole model of its own (``clod_adapter.train.tiers.finetuned``),
but a cut draws parts of several tiers side by side and their hand-overs in between. So, as
Hierarchical 3DGS optimises its hierarchy on cuts sampled at random (Kerbl et al. 2024,
``train_post.py``), :func:`finetune` draws a training view at a level ``s_v`` sampled
log-uniformly over the tree's range, renders that view's cut (:func:`clod_adapter.lod.tree.cut`,
:func:`clod_adapter.lod.tree.cut_attributes`: the hand-overs interpolated as they are drawn) and takes
an Adam step on ``0.8 L1 + 0.2 D-SSIM`` (``clod_adapter.train.losses.render_loss``) for the merged
tiers' attributes only. Tier 0, the model at full detail, is never changed, and neither is where
the cut falls (``sigma_d`` and the exits): the cut is chosen without gradient. Unbounded, the merged
nodes grow in the fit, filling what their tier's exits leave, so a count budget's frame costs more
than a merge of that count; by default ``grow`` holds them at their size but for the quarter of the
roots that leave last (docs/studies.md "Merged nodes held at their size in the fit").
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Optional, Sequence

import torch

from ..lod import tree
from ..gaussians import Gaussians
from .losses import render_loss
from .config import TREE_BUDGET_STEPS, TREE_FREE_ROOTS, TREE_GROW, TREE_STEPS
from .official import ADAM_EPS, BASE_FIELDS, OFFICIAL_LR, official_groups
from ..render.dispatch import rasterization

__all__ = ["finetune", "level_range"]

#: the attributes trained (``clod_adapter.train.official.BASE_FIELDS``) take the official 3DGS
#: rates, positions this factor of the official initial rate (a fine-tune of a finished model)
MEANS_LR_SCALE = 0.1
#: the smallest count budget a budget step of :func:`finetune` draws, a share of tier 0's centres
#: in view (issue 62's budget sweep: 100 % to 1 %)
BUDGET_LOWEST = 0.01
#: the coarsest level a level step of :func:`finetune` draws: :func:`level_range` capped here (a
#: study may lower it: docs/studies.md "The tree against its own first tier, and a fit held to the
#: middle of the range")
LEVEL_CAP = 1e4


def level_range(model: Gaussians, cameras: Sequence) -> float:
    """The largest ``s_v`` any of ``cameras`` draws something at: the largest end ``U`` of the
    last tier's nodes (:func:`clod_adapter.lod.tree.terms`), at least 1."""
    tiers = tree.tiers_of(model)
    top = 1.0
    for cam in cameras:
        u = tree.terms(tiers, cam).upper[-1]
        if u.numel():
            top = max(top, float(u.max()))
    return top


def _tiers_with(tiers: list, params: list) -> list:
    return [tiers[0]] + [replace(t, **p) for t, p in zip(tiers[1:], params)]


def finetune(model: Gaussians, cameras: Sequence, images: Sequence, steps: int = TREE_STEPS, *,
             background=None, seed: int = 0, log=None,
             budget_steps: float = TREE_BUDGET_STEPS, grow: Optional[float] = TREE_GROW,
             free_roots: float = TREE_FREE_ROOTS, tier0_rate: float = 0.0) -> Gaussians:
    """``model`` (a merge tree, :func:`clod_adapter.lod.tree.is_tree`) with its merged tiers fitted on
    its cuts (module docstring) for ``steps`` steps on ``cameras`` (training views) and their
    ``images`` ([H, W, 3] float32 in [0, 1]). ``s_v`` is sampled log-uniformly in ``[1, top]``,
    ``top`` the coarsest level the views draw (:func:`level_range`, capped at :data:`LEVEL_CAP`). A share
    ``budget_steps`` of the steps (default :data:`clod_adapter.train.config.TREE_BUDGET_STEPS`; 0:
    none, and no random number drawn for it) draws instead the cut of a count budget
    (:func:`clod_adapter.lod.tree.budget_cut`) of a share of tier 0's centres in view sampled
    log-uniformly in ``[BUDGET_LOWEST, 1]``. With ``grow`` (default
    :data:`clod_adapter.train.config.TREE_GROW`, 1; None: unbounded), after each step a merged
    node's log-scales are clamped to at most their value at the start plus ``ln grow`` (1: no node
    ends larger than it entered the fit), but for the share ``free_roots`` of the roots (the last
    tier's nodes) with the largest exits, the ones the coarsest levels draw alone (default
    :data:`clod_adapter.train.config.TREE_FREE_ROOTS`, 0.25). With ``tier0_rate`` > 0 tier 0 (the
    model at full detail) is fitted too, at its rates times ``tier0_rate``, its scales bounded by
    ``grow`` as the merged nodes' are (a study's knob: docs/studies.md "Where a cut loses, and four
    fits that do not win it back"; default 0, tier 0 unchanged). ``steps <= 0`` returns ``model``.
    Returns a new :class:`~clod_adapter.gaussians.Gaussians` (the same nodes, tree and dtype).

    Raises:
        ValueError: ``model`` is not a tree, ``cameras`` and ``images`` differ in number,
            ``budget_steps`` or ``free_roots`` is outside [0, 1], ``grow`` is below 1, or
            ``tier0_rate`` is negative.
    """
    if not tree.is_tree(model):
        raise ValueError("tree_fit.finetune: the model is not a merge tree")
    if len(cameras) != len(images):
        raise ValueError(f"tree_fit.finetune: {len(cameras)} cameras and {len(images)} images")
    if not 0.0 <= budget_steps <= 1.0:
        raise ValueError(f"tree_fit.finetune: budget_steps must be in [0, 1], got {budget_steps}")
    if grow is not None and not grow >= 1.0:
        raise ValueError(f"tree_fit.finetune: grow must be a factor >= 1 or None, got {grow}")
    if not 0.0 <= free_roots <= 1.0:
        raise ValueError(f"tree_fit.finetune: free_roots must be in [0, 1], got {free_roots}")
    if not tier0_rate >= 0.0:
        raise ValueError(f"tree_fit.finetune: tier0_rate must be >= 0, got {tier0_rate}")
    if steps <= 0 or not len(cameras):
        return model
    tiers = tree.tiers_of(model)
    params = [{k: torch.nn.Parameter(getattr(t, k).detach().clone()) for k in BASE_FIELDS} for t in tiers[1:]]
    means_lr = OFFICIAL_LR["means"][0] * MEANS_LR_SCALE
    groups = [grp for p in params for grp in official_groups(p, means_lr)]
    own = None
    if tier0_rate > 0.0:  # tier 0 fitted too, at a share of the rates
        own = {k: torch.nn.Parameter(getattr(tiers[0], k).detach().clone()) for k in BASE_FIELDS}
        groups += official_groups(own, means_lr * tier0_rate, tier0_rate)
    opt = torch.optim.Adam(groups, eps=ADAM_EPS)
    caps = None if grow is None else [p["log_scales"].detach() + math.log(grow) for p in params]
    own_cap = None if own is None or grow is None else own["log_scales"].detach() + math.log(grow)
    if caps is not None and free_roots > 0.0 and len(tiers[-1]):
        ex = tiers[-1].extra[tree.EXIT_KEY].double()
        last = ex >= torch.quantile(ex, 1.0 - free_roots, interpolation="lower")  # those that leave last
        caps[-1] = torch.where(last[:, None], torch.full_like(caps[-1], math.inf), caps[-1])
    ln_top = math.log(min(level_range(model, cameras), LEVEL_CAP))
    gen = torch.Generator().manual_seed(seed)
    bg = None if background is None else torch.as_tensor(background, dtype=model.means.dtype).reshape(1, -1)
    for it in range(int(steps)):
        i = int(torch.randint(len(cameras), (1,), generator=gen))
        s = math.exp(float(torch.rand(1, generator=gen)) * ln_top)
        budget = budget_steps > 0 and float(torch.rand(1, generator=gen)) < budget_steps
        share = math.exp(float(torch.rand(1, generator=gen)) * math.log(BUDGET_LOWEST)) if budget else 1.0
        cur = _tiers_with(tiers if own is None else [replace(tiers[0], **own)] + tiers[1:], params)
        with torch.no_grad():
            if budget:  # one frame of terms: its frustum gives the count the share is of
                at = tree.budget_frame(cur, cameras[i])
                c = tree.budget_cut(cur, cameras[i], share * int(at[1][0].sum()), at=at)
            else:
                c = tree.cut(cur, cameras[i], s)
        if own is None and all(ids.numel() == 0 for ids in c.ids[1:]):
            continue  # tier 0 alone: nothing trainable drawn
        with torch.enable_grad():
            m, q, sc, op, col = tree.cut_attributes(cur, c)
            cam = cameras[i]
            img = rasterization(m, q, sc, op, col, cam.viewmat[None], cam.K[None], int(cam.width), int(cam.height),
                                sh_degree=model.sh_degree, backgrounds=bg)[0][0]
            loss = render_loss(img.clamp(0.0, 1.0), images[i])
            opt.zero_grad(set_to_none=True)
            loss.backward()
        opt.step()
        if caps is not None:
            with torch.no_grad():
                for p, cap in zip(params, caps):
                    p["log_scales"].clamp_(max=cap)
                if own_cap is not None:
                    own["log_scales"].clamp_(max=own_cap)
        if log is not None and (it + 1) % 250 == 0:
            log(f"tree: fitted on its cuts, step {it + 1} of {steps} (loss {float(loss.detach()):.4f})")
    if own is not None:
        tiers = [replace(tiers[0], **{k: v.detach() for k, v in own.items()})] + tiers[1:]
    return tree.linked(_tiers_with(tiers, [{k: v.detach() for k, v in p.items()} for p in params]))
