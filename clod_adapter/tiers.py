"""The parent tier: merged Gaussians that the coarse levels cross-fade to.

A selection keeps survivors; at the cheap end of a frame budget survivors are few and, grown by
the level gains, large, and a merging decimator covers the same image with fewer, better-placed
splats (``python benchmarks/studies/merge_tier.py``: on skull's and fern's validation views the
adapted model plus an adapted ``--decimate`` to 4 % is 2.3-3.6 dB above the adapted model alone
within 25 / 15 / 10 % of the input's frame time, and level with it above 50 %). So a model may
carry a *parent tier* (``Gaussians.parents``): the input merged by PlayCanvas splat-transform's
``--decimate`` (mass-preserving moment matching of nearest pairs, :func:`decimated`), adapted
like any input (its own ``sigma_d`` and level gains), drawn instead of the Gaussians from
``LodSettings.tier_s_v`` on, after a cross-fade in ``s_v`` (:func:`clod_adapter.lod.tier_weight`,
:func:`clod_adapter.camera_lod.render_lod`). It is stored in the same .ply as a second element
(``lod_parent``) that viewers reading only ``vertex`` leave out.

:func:`choose` picks where it takes over, on the views it is given (training or validation
views, never test views), by the fitted frame-time model (:class:`clod_adapter.cost.FrameTimeModel`:
no wall clock, so the choice is reproducible): the first level of the Gaussians at which some
level of the parents is at least as good in PSNR and predicted no slower. When there is none,
the scene does not need the tier and the model is left without it.
"""
from __future__ import annotations

import statistics
from dataclasses import dataclass, replace
from typing import Optional, Sequence

import torch

from .baselines import merge_decimate
from .camera_lod import view_lod
from .cost import DEFAULT_FRAME_TIME_MODEL, FrameTimeModel, splat_cost
from .gaussians import Gaussians
from .metrics import psnr

#: models with fewer Gaussians get no parent tier (their coarsest frames already cost little)
PARENT_MIN_GAUSSIANS = 10_000
#: training views :func:`choose` scores on (evenly spaced)
CHOOSE_VIEWS = 8
#: the Gaussians' levels at which the switch may happen, and the parents' levels tried there
SWITCH_S_V = (2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 10.0)
PARENT_S_V = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 10.0)


def decimated(gaussians: Gaussians, share: float, *, tool: Optional[str] = None) -> Gaussians:
    """The parent tier's starting point: ``gaussians`` merged to ``share`` of its count by
    splat-transform 3.7.0's ``--decimate`` (:func:`clod_adapter.baselines.merge_decimate`), a
    plain 3DGS model (no ``sigma_d``).

    Raises:
        ValueError: ``share`` not in (0, 1).
        RuntimeError: splat-transform is missing or fails (the message says which).
    """
    if not 0.0 < share < 1.0:
        raise ValueError(f"parent share must be in (0, 1), got {share}")
    plain = replace(gaussians.with_sigma_d(None), extra={})
    return merge_decimate(plain, max(1, int(round(share * len(gaussians)))), mode="decimate", tool=tool)


def attach(gaussians: Gaussians, parents: Gaussians, tier_s_v: float, tier_start: float = 1.0,
           tier_fade: float = 1.25) -> Gaussians:
    """``gaussians`` (adapted) with the adapted ``parents`` as its parent tier, taking over from
    ``tier_s_v`` (the parents then drawn at their own ``s_v = tier_start``).

    Raises:
        ValueError: a model without ``sigma_d`` or settings, SH degrees that differ, or
            settings out of range (:class:`clod_adapter.lod.LodSettings`).
    """
    if gaussians.sigma_d is None or gaussians.lod is None or parents.sigma_d is None:
        raise ValueError("attach: both the model and its parents must be adapted (sigma_d and settings)")
    if parents.sh_degree != gaussians.sh_degree:
        raise ValueError(f"attach: parents of SH degree {parents.sh_degree}, model of {gaussians.sh_degree}")
    st = replace(gaussians.lod, tier_s_v=float(tier_s_v), tier_start=float(tier_start), tier_fade=float(tier_fade))
    return replace(gaussians, lod=st, parents=replace(parents, parents=None))


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


def choose(gaussians: Gaussians, parents: Gaussians, cameras: Sequence, images: Sequence, *, background=None,
           time_model: FrameTimeModel = DEFAULT_FRAME_TIME_MODEL, log=None) -> TierChoice:
    """Where the adapted ``parents`` should take over from the adapted ``gaussians``: the
    smallest ``s_v`` of :data:`SWITCH_S_V` at which a level of the parents (:data:`PARENT_S_V`)
    is predicted no slower and scores at least the Gaussians' PSNR on the views given; that
    level is ``tier_start``. Views: training or validation cameras with their images [H, W, 3]
    in [0, 1] (a few suffice: the curves are means over them)."""
    kw = dict(background=background, time_model=time_model)
    gc = level_curve(gaussians, cameras, images, SWITCH_S_V, **kw)
    pc = level_curve(parents, cameras, images, PARENT_S_V, **kw)
    curves = {"gaussians": gc, "parents": pc}
    for s, p_c, ms_c in gc:
        fits = [(sp, p, ms) for sp, p, ms in pc if ms <= ms_c]
        if fits:
            sp, p, _ = max(fits, key=lambda t: t[1])  # the parents' best level that fits
            if p >= p_c:
                if log is not None:
                    log(f"parent tier: takes over at s_v = {s:g} ({p_c:.2f} dB, {ms_c:.1f} ms predicted) with its "
                        f"s_v = {sp:g} ({p:.2f} dB)")
                return TierChoice(s, sp, curves)
    if log is not None:
        log("parent tier: no level of the parents beats the Gaussians at equal predicted time; left out")
    return TierChoice(None, 1.0, curves)


__all__ = ["decimated", "attach", "choose", "level_curve", "TierChoice", "SWITCH_S_V", "PARENT_S_V",
           "PARENT_MIN_GAUSSIANS", "CHOOSE_VIEWS"]
