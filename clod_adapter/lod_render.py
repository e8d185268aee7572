"""Render a :class:`~clod_adapter.gaussians.Gaussians` model from one camera at a level of detail.

This joins the CLoD mechanism (:mod:`clod_adapter.lod`: Eq. 2 and the ``tau * s_v`` mask) to the
rasteriser (:func:`clod_adapter.render.rasterization`): only the Gaussians that pass the mask are
handed to the rasteriser, with their attenuated opacities ``alpha''``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Optional, Sequence

import torch
from torch import Tensor

from . import lod
from .budget import budget_count, critical_s_v, select_budget
from .gaussians import Gaussians
from .render import rasterization
from .render.projection import project_visible


@torch.no_grad()
def in_view(gaussians: Gaussians, viewmat: Tensor, K: Tensor, width: int, height: int) -> Tensor:
    """[N] bool: Gaussians whose footprint reaches the image (gsplat 1.5.3 culling with the
    opacity-free 3.33-sigma extent, near plane 0.01). A superset of what the rasteriser draws for
    any opacity <= alpha; the population LoD counts and budgets refer to."""
    return in_view_tensors(gaussians.means, gaussians.quats, gaussians.scales, viewmat, K,
                           width, height)


@torch.no_grad()
def in_view_tensors(means: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor, K: Tensor,
                    width: int, height: int, near_plane: float = 0.01) -> Tensor:
    """:func:`in_view` on raw tensors (means [N, 3], quats [N, 4], activated scales [N, 3])."""
    vis = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    if means.shape[0] == 0:
        return vis
    pv = project_visible(means.detach(), quats.detach(), scales.detach(), None, viewmat, K,
                         width, height, near_plane=near_plane)
    vis[pv.ids] = True
    return vis


@torch.no_grad()
def select_lod(opacities: Tensor, d_norm: Tensor, sigma_d: Tensor, visible: Tensor, *,
               s_v: Optional[float] = None, budget: Optional[float | int] = None,
               tau: float = lod.DEFAULT_TAU, eps: float = lod.DEFAULT_EPS,
               min_s_v: float = 1.0) -> tuple[Tensor, float]:
    """Which Gaussians one camera renders at ``s_v``, or within ``budget`` (no gradient).

    Args:
        opacities: [N] activated opacities.
        d_norm: [N] frustum-normalised distances d' for this camera.
        sigma_d: [N] raw distance decays.
        visible: [N] bool, Gaussians in view (:func:`in_view`).
        s_v: virtual distance scale: the mask ``alpha'' > tau s_v`` (CLoD-GS Eq. 2).
        budget: instead of ``s_v``: at most this many Gaussians (int) or this fraction of N
            (float in [0, 1]); ``s_v`` solved exactly (:mod:`clod_adapter.budget`) and raised to
            at least ``min_s_v`` (1: a budget is a cap at full detail; 0: exactly ``budget``).
        tau, eps: LoD threshold and Eq. 2's epsilon.

    Returns:
        (mask [N] bool, the s_v used).
    """
    if budget is not None:
        crit = critical_s_v(opacities, d_norm, sigma_d, tau, eps)
        idx, sv = select_budget(crit, budget_count(budget, opacities.shape[0]), visible)
        if sv < min_s_v:
            return (crit > min_s_v) & visible, float(min_s_v)
        mask = torch.zeros_like(visible)
        mask[idx] = True
        return mask, sv
    return (lod.lod_margin(opacities, d_norm, sigma_d, s_v, tau, eps) > 0) & visible, float(s_v)


def _settings(gaussians: Gaussians, tau: Optional[float], eps: Optional[float]) -> lod.LodSettings:
    """The model's LoD settings (defaults when it has none) with ``tau``/``eps`` overrides."""
    st = gaussians.lod if gaussians.lod is not None else lod.LodSettings()
    if tau is not None or eps is not None:
        st = replace(st, tau=st.tau if tau is None else float(tau), eps=st.eps if eps is None else float(eps))
    return st


@dataclass
class _Draw:
    """Selection and drawn attributes of one camera at one level (internal)."""

    mask: Tensor            # [N] bool, handed to the rasteriser
    model: Gaussians        # attributes at the level (gains applied), [N]
    opacities: Tensor       # [N] drawn opacities
    visible: Tensor         # [N] bool, in view
    frustum: Tensor         # [N] bool, centre in the frustum
    s_v: Optional[float]
    eta: Tensor             # scalar, rendered fraction of the frustum


def _draw(gaussians: Gaussians, viewmat: Tensor, K: Tensor, w: int, h: int, s_v: Optional[float],
          budget, st: lod.LodSettings, min_s_v: float, estimator: str, temperature: float,
          eta_grad_sigma_only: bool, budget_in_view: bool = False, ell: Optional[float] = None) -> _Draw:
    means = gaussians.means
    frustum = lod.in_frustum(means, viewmat, K, w, h)
    visible = in_view(gaussians, viewmat, K, w, h)
    if budget is not None and budget_in_view and isinstance(budget, float) and budget <= 1.0:
        budget = int(round(budget * int(visible.sum())))
    opac = gaussians.opacities
    if budget is not None and s_v is not None:
        raise ValueError("render_lod: give s_v or budget, not both")
    if (s_v is not None or budget is not None) and gaussians.sigma_d is None:
        raise ValueError("render_lod: s_v/budget given but the model has no sigma_d")
    if s_v is None and budget is None:
        return _Draw(visible, gaussians, opac, visible, frustum, None,
                     torch.ones((), dtype=means.dtype, device=means.device))
    if s_v is not None and not s_v >= 1.0:
        raise ValueError(f"render_lod: s_v must be >= 1, got {s_v}")
    d_norm = lod.normalized_distances(means, lod.camera_center(viewmat), frustum)
    sd = gaussians.sigma_d
    # The mask covers every Gaussian in view: one whose centre lies just outside the image
    # can still cover pixels. The frustum only defines d''s normaliser and eta's population.
    mask, s_used = select_lod(opac.detach(), d_norm.detach(), sd.detach(), visible, s_v=s_v,
                              budget=budget, tau=st.tau, eps=st.eps, min_s_v=min_s_v)
    if budget is not None:
        eta = mask[frustum].float().mean() if bool(frustum.any()) else torch.zeros((), device=means.device)
    else:
        m_eta = (lod.lod_margin(opac.detach(), d_norm.detach(), sd, s_used, st.tau, st.eps) if eta_grad_sigma_only
                 else lod.lod_margin(opac, d_norm, sd, s_used, st.tau, st.eps))
        eta = lod.rendered_fraction(m_eta, frustum, estimator, temperature)
    if st.fade == "eq2":
        return _Draw(mask, gaussians, lod.lod_opacities(opac, d_norm, sd, s_used, st.eps), visible,
                     frustum, s_used, eta)
    margin = lod.lod_margin(opac, d_norm.detach(), sd, s_used, st.tau, st.eps)
    if ell is None:
        n_vis = int(visible.sum())
        ell = lod.level_of_fraction(int(mask.sum()) / n_vis if n_vis else 1.0, st.max_sv)
    model = gaussians.at_level(float(ell))
    drawn = model.opacities * lod.fade_weight(margin, lod.fade_width_at(s_used, st.fade_width))
    return _Draw(mask, model, drawn, visible, frustum, s_used, eta)


def _colors_at(m: Gaussians, idx: Tensor) -> Tensor:
    """``m.colors[idx]`` without concatenating the whole model's SH first ([k, K, 3]; at 1M
    Gaussians of degree 3 that copy was 192 MB and ~0.2 s per render)."""
    return torch.cat([m.sh0[idx], m.shN[idx]], dim=1)


@dataclass
class LodSubset:
    """What one camera draws at one level of detail (:func:`lod_subset`), without rasterising.

    Attributes:
        indices: [k] int64 indices into the model, ascending.
        means: [k, 3], quats: [k, 4] (wxyz), scales: [k, 3] (activated, world units, at the
        level), opacities: [k] (the opacities the rasteriser is given, after the LoD rule),
        colors: [k, K, 3] SH coefficients (gsplat ``colors`` layout, at the level): the drawn
            attributes.
        s_v: the virtual distance scale used (solved in budget mode; None without LoD).
        n_in_view: Gaussians in view (the population budgets and fractions refer to).
    """

    indices: Tensor
    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    s_v: Optional[float]
    n_in_view: int


@torch.no_grad()
def lod_subset(gaussians: Gaussians, camera, s_v: Optional[float] = None, *,
               budget: Optional[float | int] = None, tau: Optional[float] = None,
               eps: Optional[float] = None, min_s_v: float = 1.0) -> LodSubset:
    """The Gaussians :func:`render_lod` hands to the rasteriser for ``camera`` and their drawn
    attributes (same arguments; no gradient). For viewers and exporters that rasterise
    elsewhere. Neither ``s_v`` nor ``budget``: every Gaussian in view, unchanged.

    Raises:
        ValueError: as :func:`render_lod`.
    """
    means = gaussians.means
    dev = means.device
    viewmat = camera.viewmat.to(dev, means.dtype)
    K = camera.K.to(dev, means.dtype)
    w, h = int(camera.width), int(camera.height)
    dr = _draw(gaussians, viewmat, K, w, h, s_v, budget, _settings(gaussians, tau, eps), min_s_v,
               "paper", 1.0, True)
    idx = torch.nonzero(dr.mask, as_tuple=False).squeeze(1)
    m = dr.model
    return LodSubset(indices=idx, means=m.means[idx], quats=m.quats[idx], scales=m.scales[idx],
                     opacities=dr.opacities[idx], colors=_colors_at(m, idx), s_v=dr.s_v,
                     n_in_view=int(dr.visible.sum()))


@dataclass
class LodRender:
    """Result of :func:`render_lod`.

    Attributes:
        image: [H, W, 3] rendered colours (float32, not clamped).
        alpha: [H, W, 1] accumulated opacity.
        mask: [N] bool, Gaussians handed to the rasteriser: in view (:func:`in_view`) and
            passing the LoD mask (or the budget selection).
        n_rendered: ``mask.sum()``, the render cost. With tau * s_v >= 1/255 every one of them
            is drawn (none falls under gsplat's alpha threshold).
        s_v: the virtual distance scale used (the solved one in budget mode; None: no LoD).
        n_frustum: number of Gaussian centres inside the view frustum.
        eta: scalar tensor, rendered fraction of the frustum (gradient per the estimator;
            1.0 without LoD).
        select_ms: wall time of the LoD selection (Eq. 2 + mask), milliseconds.
        raster_ms: wall time of the rasterisation, milliseconds.
        meta: the rasteriser's meta dict.
    """

    image: Tensor
    alpha: Tensor
    mask: Tensor
    n_rendered: int
    n_frustum: int
    eta: Tensor
    s_v: Optional[float] = None
    select_ms: float = 0.0
    raster_ms: float = 0.0
    meta: dict = field(default_factory=dict)


def render_lod(
    gaussians: Gaussians,
    camera,
    s_v: Optional[float] = None,
    *,
    tau: Optional[float] = None,
    eps: Optional[float] = None,
    estimator: str = "ste",
    temperature: float = 1.0,
    background: Optional[Sequence[float] | Tensor] = None,
    sh_degree: Optional[int] = None,
    backend: str = "auto",
    impl: str = "auto",
    eta_grad_sigma_only: bool = True,
    budget: Optional[float | int] = None,
    min_s_v: float = 1.0,
    budget_in_view: bool = False,
    level: Optional[float] = None,
) -> LodRender:
    """Render ``gaussians`` from ``camera`` at virtual distance scale ``s_v``.

    The Gaussians in view that pass the mask ``alpha'' > tau s_v`` (CLoD-GS Eq. 2) are handed to
    the rasteriser, drawn as the model's :class:`clod_adapter.lod.LodSettings` say: ``"eq2"``
    with Eq. 2's ``alpha''`` (the paper), ``"window"`` with the attributes at the level
    (:meth:`Gaussians.at_level`) and only the Gaussians about to leave faded
    (:func:`clod_adapter.lod.fade_weight`). A model without settings is drawn as the paper does.

    Args:
        gaussians: the model (N Gaussians). ``sigma_d`` is required when ``s_v`` is given.
        camera: any object with ``viewmat`` [4, 4] (world-to-camera), ``K`` [3, 3] (pixels),
            ``width``, ``height`` (e.g. :class:`clod_adapter.io.scene.Camera`).
        s_v: virtual distance scale >= 1, or None for the plain model (no LoD, every Gaussian).
        tau: LoD threshold (mask ``alpha'' > tau s_v``); default the model's (0.005).
        eps: Eq. 2's epsilon; default the model's (1e-8).
        estimator, temperature: gradient of ``eta`` (see :func:`clod_adapter.lod.rendered_fraction`).
        background: [3] colour behind the scene (default black, as 3DGS on LLFF).
        sh_degree: SH degree to evaluate (default: the model's).
        backend, impl: rasteriser backend (``"auto"``, ``"cpu"``, ``"gsplat"``) and CPU compositor.
        budget: render exactly this many Gaussians (int) or this fraction of the model (float
            in [0, 1]) instead of a given ``s_v``: the ``s_v`` is solved exactly per view
            (:mod:`clod_adapter.budget`), capped by the Gaussians in view.
        min_s_v: budget mode only: the solved ``s_v`` is raised to at least this (default 1,
            the full-detail level, so a budget acts as a cap: larger budgets than the s_v = 1
            count render that level). 0 renders exactly ``budget`` Gaussians whatever ``s_v``.
        eta_grad_sigma_only: ``eta``'s gradient reaches ``sigma_d`` only (opacities and positions
            detached in its margin), so the count regulariser cuts Gaussians through their decay
            instead of eroding their opacity at every level of detail.
        budget_in_view: a fractional ``budget`` is a share of the Gaussians in view (the
            calibrated schedule's training), not of the model.
        level: window fade only: draw the level gains at this level in [0, 1] instead of
            :func:`clod_adapter.lod.level_of_fraction` of the share of the Gaussians in view
            drawn.

    Returns:
        :class:`LodRender`.

    Raises:
        ValueError: ``s_v`` or ``budget`` given but the model has no ``sigma_d``; ``s_v < 1``;
            both ``s_v`` and ``budget`` given.
    """
    means = gaussians.means
    dev = means.device
    viewmat = camera.viewmat.to(dev, means.dtype)
    K = camera.K.to(dev, means.dtype)
    w, h = int(camera.width), int(camera.height)
    t0 = time.perf_counter()
    dr = _draw(gaussians, viewmat, K, w, h, s_v, budget, _settings(gaussians, tau, eps), min_s_v,
               estimator, temperature, eta_grad_sigma_only, budget_in_view, level)
    idx = torch.nonzero(dr.mask, as_tuple=False).squeeze(1)
    t1 = time.perf_counter()
    bg = None
    if background is not None:
        bg = torch.as_tensor(background, dtype=means.dtype, device=dev).reshape(1, 3)
    m = dr.model
    colors, alphas, meta = rasterization(
        m.means[idx], m.quats[idx], m.scales[idx], dr.opacities[idx], _colors_at(m, idx),
        viewmat[None], K[None], w, h,
        sh_degree=gaussians.sh_degree if sh_degree is None else sh_degree,
        backgrounds=bg, backend=backend, impl=impl,
    )
    t2 = time.perf_counter()
    return LodRender(
        image=colors[0], alpha=alphas[0], mask=dr.mask, n_rendered=int(idx.numel()),
        n_frustum=int(dr.frustum.sum()), eta=dr.eta, s_v=dr.s_v, select_ms=(t1 - t0) * 1e3,
        raster_ms=(t2 - t1) * 1e3, meta=meta,
    )
