"""Merged tiers: a ladder of merged models that the coarser levels hand over to.

A selection keeps survivors; down the range survivors are few and, grown by the level gains,
large, and a merging decimator covers the same image with fewer, better-placed splats. So a model
may carry *parent tiers* (``Gaussians.parents``, whose own ``parents`` is the next tier, ...): the
input merged by PlayCanvas splat-transform's ``--decimate`` (mass-preserving moment matching of
nearest pairs, :func:`decimated`) to each of a few shares of it
(:data:`clod_adapter.train.config.DEFAULT_SHARES`, chosen on validation views:
docs/archive/studies_chain.md "A chain of merged tiers"; the first lowered by :func:`first_share`
where its merge would save little time), each adapted like any input (its own ``sigma_d`` and level
gains) and handing over from the tier above at that tier's
``LodSettings.tier_s_v`` (:func:`link`); ``clod-adapt`` then links the tiers into a merge tree
(:func:`clod_adapter.lod.tree.build`) that draws one cut of them per frame. They are stored in the
same .ply as more elements (``lod_parent``, ``lod_parent_2``, ...) that viewers reading only
``vertex`` leave out.

:func:`choose` picks where a tier takes over from the one above, on the views it is given
(training views, never validation or test views), by the fitted frame-time model
(:class:`clod_adapter.lod.cost.FrameTimeModel`: no wall clock, so the choice is reproducible): the
first level of the tier above at which some level of the tier is at least as good in PSNR and
predicted no slower. When there is none, the scene does not need the tier and it is left out.
"""
from __future__ import annotations

import statistics
from dataclasses import dataclass, replace
from typing import Optional, Sequence

import torch
from torch import Tensor

from .config import MERGES, TIER_TIME_CAP
from .finetune import global_cut
from ..lod.rankings import merge_decimate
from ..lod.view import view_lod
from ..lod.cost import DEFAULT_FRAME_TIME_MODEL, FrameTimeModel, splat_cost
from ..gaussians import Gaussians
from ..metrics import psnr

#: models with fewer Gaussians get no merged tiers (their coarsest frames already cost little)
PARENT_MIN_GAUSSIANS = 10_000
#: training views :func:`choose` scores on (evenly spaced)
CHOOSE_VIEWS = 8


def choice_views(cameras: Sequence) -> list:
    """The :data:`CHOOSE_VIEWS` evenly spaced cameras of ``cameras`` (training views) that a
    tier's share and hand-over are chosen on (all of them when there are fewer)."""
    cams = list(cameras)
    return cams[:: max(1, len(cams) // CHOOSE_VIEWS)][:CHOOSE_VIEWS]


#: the Gaussians' levels at which the switch may happen, and the parents' levels tried there
SWITCH_S_V = (1.1, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 10.0)
PARENT_S_V = (1.0, 1.1, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 10.0)


def decimated(gaussians: Gaussians, share: float, *, merge: str = "decimate", tool: Optional[str] = None,
              weights: Optional[Tensor] = None) -> Gaussians:
    """The parent tier's starting point: ``gaussians`` merged to ``share`` of its count by
    splat-transform 3.7.0's ``--decimate`` (``merge="decimate"``) or ``--decimate-adaptive``
    (``merge="adaptive"``) (:func:`clod_adapter.lod.rankings.merge_decimate`), or (``merge="prune"``)
    cut to the ``share`` of largest ``weights`` [N] (their blending weights), a plain 3DGS model
    (no ``sigma_d``).

    Raises:
        ValueError: ``share`` not in (0, 1), ``merge`` not one of
            :data:`clod_adapter.train.config.MERGES`, or ``"prune"``
            without ``weights`` of one per Gaussian.
        RuntimeError: splat-transform is missing or fails (the message says which).
    """
    if not 0.0 < share < 1.0:
        raise ValueError(f"parent share must be in (0, 1), got {share}")
    if merge not in MERGES:
        raise ValueError(f"merge must be one of {MERGES}, got {merge!r}")
    plain = replace(gaussians.with_sigma_d(None), extra={})
    k = max(1, int(round(share * len(gaussians))))
    if merge == "prune":
        if weights is None or weights.numel() != len(gaussians):
            raise ValueError("a pruned tier needs one blending weight per Gaussian")
        return plain.subset(global_cut(weights, k / max(len(gaussians), 1)).to(plain.means.device))
    return merge_decimate(plain, k, mode=merge, tool=tool)


#: :func:`prune_scores`' exponent of the cost: a Gaussian's blending weight over the square root of
#: its drawing cost. Chosen on fern's validation views, static cuts of the input (no fit): at 60 %
#: of the Gaussians the cut by weight alone draws 81 % of the predicted frame for 25.54 dB, by
#: weight over the square root of cost 75 % for 25.76 dB, by weight over cost 48 % for 18.31 dB
#: (``python -m benchmarks.studies.prune_cost``)
PRUNE_COST_EXPONENT = 0.5


@torch.no_grad()
def prune_scores(gaussians: Gaussians, cameras: Sequence, *, exponent: float = PRUNE_COST_EXPONENT) -> Tensor:
    """What a pruned first tier (``merge="prune"``) keeps first: each Gaussian's blending weight
    summed over ``cameras`` (:func:`clod_adapter.train.pruning.blend_weights`, pixels) over ``(1 +
    c)^exponent``, ``c`` its drawing cost summed over them (:func:`clod_adapter.lod.cost.splat_cost`,
    clipped ellipse pixels): a large splat that paints little is left out before a small one.

    Returns:
        [N] float64 scores (0 for a Gaussian no view draws).

    Raises:
        ValueError: no cameras.
    """
    from .pruning import blend_weights

    if not cameras:
        raise ValueError("prune_scores: no cameras")
    g = gaussians.with_sigma_d(None)
    cost = torch.zeros(len(g), dtype=torch.float64)
    for cam in cameras:
        view = view_lod(g, cam)
        idx = torch.nonzero(view.visible, as_tuple=False).squeeze(1)
        cost[idx.cpu()] += splat_cost(view, idx).cpu()
    return blend_weights(g, cameras).cpu() / (1.0 + cost) ** float(exponent)


#: :func:`first_share` lowers the share by this factor per try, at most this many times
TIER_SHARE_STEP = 0.7
TIER_SHARE_TRIES = 3


@torch.no_grad()
def predicted_ms(gaussians: Gaussians, cameras: Sequence, *,
                 time_model: FrameTimeModel = DEFAULT_FRAME_TIME_MODEL) -> float:
    """Mean predicted drawing time (ms) of ``gaussians`` at full detail over ``cameras``: every
    Gaussian in view at its base attributes (:func:`clod_adapter.lod.cost.splat_cost`, an upper bound
    of what the LoD rule draws at ``s_v = 1``) through ``time_model``. No wall clock: the same
    inputs give the same number. ``cameras``: objects with ``viewmat`` [4, 4], ``K`` [3, 3]
    (pixels), ``width``, ``height``.

    Raises:
        ValueError: no cameras.
    """
    if not cameras:
        raise ValueError("predicted_ms: no cameras")
    ms = []
    for cam in cameras:
        cost = splat_cost(view_lod(gaussians, cam))
        ms.append(float(time_model.ms(float(cost.sum()), int(cost.numel()))))
    return statistics.mean(ms)


def first_share(gaussians: Gaussians, share: float, cameras: Sequence, *, cap: float = TIER_TIME_CAP,
                floor: float = 0.0, merge: str = "decimate", tool: Optional[str] = None,
                weights: Optional[Tensor] = None,
                time_model: FrameTimeModel = DEFAULT_FRAME_TIME_MODEL, log=None) -> tuple[float, Gaussians, list]:
    """The first tier's share and its merge (:func:`decimated`): ``gaussians`` merged to ``share``
    and, while the merge's predicted full-detail frame (:func:`predicted_ms` on ``cameras``) is
    above ``cap`` times the input's, merged again to :data:`TIER_SHARE_STEP` times the share, as
    long as that stays above ``floor`` (the next tier's share), at most :data:`TIER_SHARE_TRIES`
    times (the last merge is kept). A pruned input (MaskGaussian) has
    large Gaussians whose merge at half the count still draws ~83 % of the input's frame; a
    vanilla 3DGS checkpoint's does not need lowering (docs/archive/studies_superseded.md "A first
    tier that saves time"). ``cap = 0``: ``share`` as given, nothing predicted.

    Args:
        gaussians: the input (N Gaussians).
        share: the first share tried, in (0, 1).
        cameras: the views predicted on (as :func:`predicted_ms`; the job's :func:`choice_views`).
        cap: the largest predicted share of the input's frame time kept (0: no prediction).
        floor: a share the lowered one must stay above (the next tier's share; 0: none).

    Returns:
        ``(share, merged Gaussians, [(share tried, predicted share of the input's frame)]``).

    Raises:
        ValueError: ``cap`` < 0, or as :func:`decimated`.
        RuntimeError: as :func:`decimated`.
    """
    if cap < 0:
        raise ValueError(f"tier_time_cap must be >= 0, got {cap}")
    merged = decimated(gaussians, share, merge=merge, tool=tool, weights=weights)
    if cap == 0:
        return share, merged, []
    base = predicted_ms(gaussians, cameras, time_model=time_model)
    tried = [(share, predicted_ms(merged, cameras, time_model=time_model) / base)]
    while tried[-1][1] > cap and share * TIER_SHARE_STEP > floor and len(tried) <= TIER_SHARE_TRIES:
        share = share * TIER_SHARE_STEP
        merged = decimated(gaussians, share, merge=merge, tool=tool, weights=weights)
        tried.append((share, predicted_ms(merged, cameras, time_model=time_model) / base))
    if log is not None and len(tried) > 1:
        log(f"parent tier: merges of {', '.join(f'{s:.3g}' for s, _ in tried[:-1])} of the input predicted at "
            f"{', '.join(f'{r:.0%}' for _, r in tried[:-1])} of its frame (over {cap:.0%}); the first tier is "
            f"{share:.3g} of it ({tried[-1][1]:.0%})")
    return share, merged, tried


def finetuned(merged: Gaussians, cameras: Sequence, images: Sequence, steps: int, *, background=None,
              seed: int = 0) -> Gaussians:
    """A merged tier fitted to the training views: every base attribute of ``merged`` (N
    Gaussians, no ``sigma_d``) fine-tuned at full detail for ``steps`` Adam steps, one view each,
    on ``0.8 L1 + 0.2 D-SSIM``, with LightGaussian's post-pruning recovery rates
    (:func:`clod_adapter.train.finetune.finetune_subset`, ``schedule="recovery"``). A merge by
    moment matching keeps each cluster's mass and covariance, not its look; a few hundred steps
    recover most of what it lost (docs/archive/studies_superseded.md "Fitting each merge").
    ``steps = 0`` returns ``merged``. Images are [H, W, 3] float32 in [0, 1]; the count and SH degree are unchanged."""
    from .finetune import FinetuneOptions, finetune_subset

    if steps <= 0:
        return merged
    bg = (0.0, 0.0, 0.0) if background is None else background
    return finetune_subset(merged, list(cameras), list(images),
                           FinetuneOptions(iterations=int(steps), background=bg, seed=seed, val_every=0))


def attach(gaussians: Gaussians, parents: Gaussians, tier_s_v: float, tier_start: float = 1.0,
           tier_fade: float = 1.25) -> Gaussians:
    """``gaussians`` (adapted) with the adapted ``parents`` as its parent tier, taking over from
    ``tier_s_v`` (the parents then at their own ``s_v = tier_start``). ``parents`` keep their own
    parent tiers (:func:`clod_adapter.lod.draw.tier_chain`). The tiers are data until
    :func:`clod_adapter.lod.tree.build` links them into a merge tree: until then the model draws
    as its own Gaussians.

    Raises:
        ValueError: a model without ``sigma_d`` or settings, SH degrees that differ, or
            settings out of range (:class:`clod_adapter.lod.rule.LodSettings`).
    """
    if gaussians.sigma_d is None or gaussians.lod is None or parents.sigma_d is None:
        raise ValueError("attach: both the model and its parents must be adapted (sigma_d and settings)")
    if parents.sh_degree != gaussians.sh_degree:
        raise ValueError(f"attach: parents of SH degree {parents.sh_degree}, model of {gaussians.sh_degree}")
    st = replace(gaussians.lod, tier_s_v=float(tier_s_v), tier_start=float(tier_start), tier_fade=float(tier_fade))
    return replace(gaussians, lod=st, parents=parents)


@dataclass(frozen=True)
class TierChoice:
    """What :func:`choose` found.

    Attributes:
        tier_s_v: the Gaussians' ``s_v`` where the parents take over (None: no tier pays).
        tier_start: the parents' ``s_v`` there.
        curves: ``{"gaussians": [(s_v, PSNR dB, predicted ms)], "parents": [...]}``, means over
            the views.
    """

    tier_s_v: Optional[float]
    tier_start: float
    curves: dict


@torch.no_grad()
def level_curve(model: Gaussians, cameras: Sequence, images: Sequence, s_vs: Sequence[float], *,
                background=None, time_model: FrameTimeModel = DEFAULT_FRAME_TIME_MODEL) -> list[tuple]:
    """[(s_v, mean PSNR dB, mean predicted drawing ms)] of ``model`` at each ``s_v`` over the
    views (``images``: [H, W, 3] float in [0, 1] per camera)."""
    out = []
    for s in s_vs:
        ps, ms = [], []
        for cam, gt in zip(cameras, images):
            v = view_lod(model, cam)
            sel = v.select(float(s))
            cost = float(splat_cost(v, sel.indices, level=sel.level, opacities=sel.opacities).sum())
            ms.append(float(time_model.ms(cost, int(sel.indices.numel()))))
            bg = None if background is None else torch.as_tensor(background, dtype=model.means.dtype)
            img = v.rasterize(sel, background=bg, sh_degree=model.sh_degree)[0]
            ps.append(psnr(img.clamp(0, 1), gt))
        out.append((float(s), statistics.mean(ps), statistics.mean(ms)))
    return out


#: how :func:`choose` places a hand-over (docs/archive/studies_chain.md "A chain of merged tiers"):
#: ``"time"`` where the tier above is first predicted no slower than the tier at full detail,
#: ``"psnr"`` where some level of the tier first scores at least the tier above's PSNR in no more
#: predicted time
CHOOSE_RULES = ("time", "psnr")
CHOOSE_RULE = "time"
#: ``"time"`` rule: the tier is left out when its full detail scores more than this below the
#: tier above at the hand-over on the views given (training views, where the input, fitted to them,
#: is favoured over any merge)
CHOOSE_MARGIN_DB = 1.5


def choose(gaussians: Gaussians, parents: Gaussians, cameras: Sequence, images: Sequence, *, background=None,
           time_model: FrameTimeModel = DEFAULT_FRAME_TIME_MODEL, rule: str = CHOOSE_RULE,
           margin_db: float = CHOOSE_MARGIN_DB, log=None) -> TierChoice:
    """Where the adapted ``parents`` should take over from the adapted ``gaussians``, on the views
    given (training cameras with their images [H, W, 3] in [0, 1]; a few suffice: the curves are
    means over them), by predicted frame time (``time_model``) and PSNR:

    * ``rule="time"`` (default, :data:`CHOOSE_RULE`): at the smallest ``s_v`` of :data:`SWITCH_S_V`
      at which the Gaussians are predicted no slower than the parents at full detail, the parents
      starting there (``tier_start = 1``), unless the parents' full detail scores more than
      ``margin_db`` below the Gaussians there (then, or when the Gaussians never get that cheap,
      None);
    * ``rule="psnr"``: at the smallest ``s_v`` of :data:`SWITCH_S_V` at which a level of the
      parents (:data:`PARENT_S_V`) is predicted no slower and scores at least the Gaussians' PSNR;
      that level is ``tier_start``.

    Parents with their own tier: only their levels up to its ``tier_s_v`` (drawn alone there).

    Raises:
        ValueError: an unknown ``rule``.
    """
    if rule not in CHOOSE_RULES:
        raise ValueError(f"choose: rule must be one of {CHOOSE_RULES}, got {rule!r}")
    kw = dict(background=background, time_model=time_model)
    gc = level_curve(gaussians, cameras, images, SWITCH_S_V, **kw)
    own = parents.lod.tier_s_v if parents.parents is not None and parents.lod is not None else 0.0
    pc = level_curve(parents, cameras, images, [s for s in PARENT_S_V if not own > 0 or s <= own], **kw)
    curves = {"gaussians": gc, "parents": pc}
    say = log if log is not None else (lambda m: None)
    if rule == "time":
        _, p1, ms1 = pc[0]  # PARENT_S_V[0] = 1: the parents at full detail
        for s, p_c, ms_c in gc:
            if ms_c <= ms1:
                if p1 >= p_c - margin_db:
                    say(f"parent tier: takes over at s_v = {s:g} ({p_c:.2f} dB, {ms_c:.1f} ms predicted) at its full "
                        f"detail ({p1:.2f} dB, {ms1:.1f} ms)")
                    return TierChoice(s, 1.0, curves)
                say(f"parent tier: {p1:.2f} dB at full detail against {p_c:.2f} dB where the model is as fast "
                    f"(s_v = {s:g}), more than {margin_db:g} dB below; not by time")
                return TierChoice(None, 1.0, curves)
        say("parent tier: the model is never predicted as fast as its parents' full detail; not by time")
        return TierChoice(None, 1.0, curves)
    for s, p_c, ms_c in gc:
        fits = [(sp, p, ms) for sp, p, ms in pc if ms <= ms_c]
        if fits:
            sp, p, _ = max(fits, key=lambda t: t[1])  # the parents' best level that fits
            if p >= p_c:
                say(f"parent tier: takes over at s_v = {s:g} ({p_c:.2f} dB, {ms_c:.1f} ms predicted) with its "
                    f"s_v = {sp:g} ({p:.2f} dB)")
                return TierChoice(s, sp, curves)
    say("parent tier: no level of the parents beats the Gaussians at equal predicted time; left out")
    return TierChoice(None, 1.0, curves)


def link(model: Gaussians, candidates: Sequence[Gaussians], cameras: Sequence, images: Sequence, *,
         background=None, margin_db: float = CHOOSE_MARGIN_DB, max_tier_s_v: float = 0.0,
         log=None) -> tuple[Gaussians, list[dict]]:
    """``model`` with the first of its adapted candidate tiers that pays attached (:func:`attach`):
    by the ``"time"`` rule (:func:`choose`) each candidate in order (the next tier down first, a
    tier that does not pay skipped), then by the ``"psnr"`` rule the last (coarsest) one alone,
    for the cheap end of a scene whose merges lose at equal time. ``candidates``: the tiers below,
    finest first, each with its own tiers attached. ``max_tier_s_v`` > 0: the hand-over is at
    most there (``clod-adapt`` passes ``AdaptConfig.tier_hand_over`` when ``model`` is itself a merged
    tier); 0: where the rule put it. Returns ``(model or the tiered model, one record per try:
    rule, count, curves, tier_s_v (applied), rule_s_v (the rule's), tier_start)``.

    Raises:
        ValueError: ``max_tier_s_v`` neither 0 nor > 1."""
    if max_tier_s_v != 0.0 and not max_tier_s_v > 1.0:
        raise ValueError(f"link: max_tier_s_v must be 0 (the rule's) or > 1, got {max_tier_s_v}")
    tried = []
    for i, (cand, rule) in enumerate([(c, "time") for c in candidates] + [(candidates[-1], "psnr")]):
        ch = choose(model, cand, cameras, images, background=background, rule=rule, margin_db=margin_db, log=log)
        s_v = ch.tier_s_v if ch.tier_s_v is None or max_tier_s_v == 0.0 else min(ch.tier_s_v, float(max_tier_s_v))
        tried.append({"candidate": i if rule == "time" else len(candidates) - 1, "rule": rule, "parents": len(cand),
                      "curves": ch.curves, "tier_s_v": s_v, "rule_s_v": ch.tier_s_v, "tier_start": ch.tier_start})
        if s_v is not None:
            if s_v != ch.tier_s_v and log is not None:
                log(f"parent tier: hands over at s_v = {s_v:g}, the latest a merged tier's may be (the rule's "
                    f"{ch.tier_s_v:g})")
            return attach(model, cand, s_v, ch.tier_start), tried
    return model, tried


__all__ = ["decimated", "choice_views", "predicted_ms", "first_share", "TIER_SHARE_STEP",
           "TIER_SHARE_TRIES", "attach", "choose", "link", "level_curve", "TierChoice", "SWITCH_S_V",
           "PARENT_S_V", "PARENT_MIN_GAUSSIANS", "CHOOSE_VIEWS", "CHOOSE_RULES", "CHOOSE_RULE", "CHOOSE_MARGIN_DB"]
