"""One camera's level of detail: the per-camera terms of CLoD-GS, computed once per frame.

:func:`view_lod` (or :func:`view_lod_tensors` for raw gsplat-style tensors) builds a
:class:`LodView` for one camera:

* ``frustum`` [N]: Gaussian centres inside the image (``z > near``): the population of d''s
  normaliser and of ``eta`` (CLoD-GS Sec. 3);
* the projection of the Gaussians in front of the camera (stage 1,
  :func:`clod_adapter.render.projection.project_geometry`), computed once and only when needed:
  it gives ``visible`` [N] (the footprint reaches the image, gsplat 1.5.3 culling with the
  opacity-free 3.33-sigma extent: the population budgets and in-view shares refer to) and,
  later, the rasteriser's own projection of the drawn subset (:meth:`LodView.rasterize` finishes
  the same rows with the drawn opacities and level scales instead of projecting again). A frame
  at a given ``s_v`` needs no population: its LoD mask is evaluated first (it needs only the
  centres) and only what the mask keeps is projected, so a coarse level does not pay for
  projecting the whole model; a count budget projects a prefix of its order that holds enough
  Gaussians in view (:meth:`LodView._visible_prefix`); a cost or time budget, and full detail,
  project everything in front;
* ``d_norm`` [N]: ``d' = |mu - c| / max_frustum |mu - c|``;
* ``critical`` [N] (on first use): each Gaussian's critical ``s_v`` (:mod:`clod_adapter.lod.budget`).

:meth:`LodView.select` picks what is drawn at a virtual distance scale ``s_v`` (the mask
``alpha'' > tau s_v``, Eq. 2) or within a budget (``s_v`` solved exactly), with the drawn
opacities of the model's :class:`clod_adapter.lod.rule.LodSettings` (Eq. 2's ``alpha''``, or the
window fade with the level gains); :meth:`LodView.rasterize` draws a selection.
:func:`render_lod` and :func:`lod_subset` are the one-call forms every caller uses (training,
evaluation, the renderer hook, export, baselines, the viewer).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Optional

import torch
from torch import Tensor

from . import rule as lod
from ..lod_settings import EtaGradient
from ..render.dispatch import Backend
from .budget import Budget, critical_s_v, select_budget
from .cost import view_cost_count, view_full_cost
from ..gaussians import Gaussians
# gsplat 1.5.3's near and far planes, eps2d and tile size, used by every LoD render
from ..render.projection import (EPS2D, FAR_PLANE, NEAR_PLANE, ProjectedGeometry, VisibleProjection,
                                 finish_projection, project_geometry)
from ..render.tiles import TILE_SIZE

#: how often a budget's prefix is cut further on before the whole model is projected
#: (:meth:`LodView._visible_prefix`)
PREFIX_TRIES = 3


def _settings(st: Optional[lod.LodSettings], tau: Optional[float], eps: Optional[float]) -> lod.LodSettings:
    """``st`` (defaults when None) with ``tau``/``eps`` overrides."""
    st = st if st is not None else lod.LodSettings()
    if tau is not None or eps is not None:
        st = replace(st, tau=st.tau if tau is None else float(tau), eps=st.eps if eps is None else float(eps))
    return st


class ShParts:
    """A model's SH coefficients as its two stored parts, ``sh0`` [N, 1, 3] and ``shN`` [N, K-1, 3],
    read as the [N, K, 3] ``colors`` layout without concatenating all N rows: a frame gathers
    only the rows it draws (:meth:`index_select`), so no per-frame copy of the whole model's SH
    (at 60k Gaussians of degree 3: 11.5 MB, 3-4 ms of a frame whose drawing may take 5)."""

    def __init__(self, sh0: Tensor, shN: Tensor) -> None:
        self.sh0, self.shN = sh0, shN
        self.ndim = 3
        self.shape = (sh0.shape[0], sh0.shape[1] + shN.shape[1], sh0.shape[2])

    def index_select(self, dim: int, idx: Tensor) -> Tensor:
        """[k, K, 3] the rows ``idx`` (``dim`` must be 0)."""
        if dim != 0:
            raise ValueError("ShParts.index_select: rows only (dim 0)")
        return torch.cat([self.sh0.index_select(0, idx), self.shN.index_select(0, idx)], dim=1)


class LodSelection:
    """What one camera draws (:meth:`LodView.select`).

    Attributes:
        indices: [k] int64 indices into the model, ascending.
        opacities: [k] the opacities the rasteriser is given (after the LoD rule; autograd).
        mask: [N] bool, ``indices`` as a mask (built on first use when the selection was made
            without one: an ``s_v`` frame does not need it).
        s_v: the virtual distance scale used (solved in budget mode; None without LoD).
        level: level of the gains in [0, 1] (0: the base attributes).
        eta: scalar tensor, rendered fraction of the frustum (gradient per the estimator).
    """

    __slots__ = ("indices", "opacities", "_mask", "_n", "s_v", "level", "eta")

    def __init__(self, indices: Tensor, opacities: Tensor, mask: Optional[Tensor], s_v: Optional[float],
                 level: float, eta: Tensor, n: Optional[int] = None) -> None:
        if mask is None and n is None:
            raise ValueError("LodSelection: give the mask or the model's size n")
        self.indices, self.opacities, self._mask = indices, opacities, mask
        self._n = int(mask.numel()) if mask is not None else int(n)
        self.s_v, self.level, self.eta = s_v, level, eta

    def rows(self, keep: Tensor) -> "LodSelection":
        """The rows ``keep`` ([k] bool over ``indices``) holds, with their drawn opacities, this
        selection's ``s_v`` and level (no gradient through the choice)."""
        return LodSelection(self.indices[keep], self.opacities[keep], None, self.s_v, self.level, self.eta, n=self._n)

    @property
    def mask(self) -> Tensor:
        if self._mask is None:
            self._mask = torch.zeros(self._n, dtype=torch.bool, device=self.indices.device)
            self._mask[self.indices] = True
        return self._mask


@dataclass
class LodView:
    """The per-camera LoD terms of one model (see the module docstring). Build with
    :func:`view_lod` / :func:`view_lod_tensors`.

    Attributes:
        means [N, 3], quats [N, 4], scales [N, 3] (activated, base), opacity_logits [N]
        (raw, base), colors [N, K, 3] SH coefficients (or [N, D] features with ``sh_degree``
        None), sigma_d [N] or None, gains: dict of the level gains present (Gaussians field
        names), settings: :class:`clod_adapter.lod.rule.LodSettings`.
        viewmat [4, 4], K [3, 3], width, height: the camera.
        frustum [N] bool, visible [N] bool, n_in_view: see the module docstring.
        project_ms: wall time of the projection and the in-view test, ms.
        cost_cache: the costs of the Gaussians in view that :mod:`clod_adapter.lod.cost` last
        computed for a cost budget, kept for the next one: ``(level, order [m] int64,
        footprints, costs [m] float64)`` (a :class:`clod_adapter.lod.cost.Footprints`), or None.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacity_logits: Tensor
    colors: Tensor
    sigma_d: Optional[Tensor]
    gains: dict
    settings: lod.LodSettings
    viewmat: Tensor
    K: Tensor
    width: int
    height: int
    frustum: Tensor
    project_ms: float = 0.0
    _proj: Optional[tuple] = field(default=None, repr=False)  # (geom, visible ids, candidate ids or None, their rows)
    _visible: Optional[Tensor] = field(default=None, repr=False)  # [N] bool of the full projection
    _rows: Optional[Tensor] = field(default=None, repr=False)  # [N] row of the full projection
    _d_norm: Optional[Tensor] = field(default=None, repr=False)
    _critical: Optional[Tensor] = field(default=None, repr=False)
    _ramp: Optional[float] = field(default=None, repr=False)
    _opacities: Optional[Tensor] = field(default=None, repr=False)
    _n_frustum: Optional[int] = field(default=None, repr=False)
    cost_cache: Optional[tuple] = field(default=None, repr=False)
    _prefix: Optional[tuple] = field(default=None, repr=False)  # (k, pool): _visible_prefix's last answer

    # --- per-camera terms ----------------------------------------------------------------------
    @property
    def n(self) -> int:
        return self.means.shape[0]

    @property
    def n_in_view(self) -> int:
        return int(self.visible.sum())

    @property
    def n_frustum(self) -> int:
        """Gaussian centres inside the view frustum: the population of the level's share (no
        projection needed, so an ``s_v`` frame projects only what its LoD mask keeps)."""
        if self._n_frustum is None:
            self._n_frustum = int(self.frustum.sum())
        return self._n_frustum

    def _projection(self, candidates: Optional[Tensor] = None) -> tuple:
        """(geometry, ids [m] int64 ascending of the rows whose footprint reaches the image) of
        the Gaussians in front of the camera: all of them, or only ``candidates`` ([k] int64
        indices, ascending: the geometry's rows and ``ids`` cover just those, and nothing of
        size N is built). Computed once and reused; a full projection serves any later
        request."""
        have = self._proj
        if have is not None and (have[2] is None or have[2] is candidates):
            return have[:2]
        t0 = time.perf_counter()
        w, h = self.width, self.height
        geom = project_geometry(self.means, self.quats, self.scales, self.viewmat, self.K, w, h, NEAR_PLANE,
                                FAR_PLANE, candidates)
        with torch.no_grad():
            vis = finish_projection(geom, None, w, h, EPS2D)
        self._proj = (geom, vis.ids, candidates, vis.rows)
        self._visible = self._rows = None
        self.project_ms += (time.perf_counter() - t0) * 1e3
        return self._proj[:2]

    @property
    def visible(self) -> Tensor:
        """[N] bool: the footprint reaches the image (gsplat 1.5.3 culling, opacity-free 3.33-sigma
        extent): the population budgets and in-view shares refer to. Projects the whole model."""
        vis_ids = self._projection()[1]
        if self._visible is None:
            self._visible = torch.zeros(self.n, dtype=torch.bool, device=self.means.device)
            self._visible[vis_ids] = True
        return self._visible

    @property
    def geometry(self) -> ProjectedGeometry:
        """The whole model's :class:`clod_adapter.render.projection.ProjectedGeometry` (stage 1 of
        the projection, opacity-free): one row per Gaussian between the near and far planes,
        ``geometry.ids`` [m] int64 ascending. Projects the whole model (once)."""
        return self._projection()[0]

    @property
    def geometry_rows(self) -> Tensor:
        """[N] int64: the row of each Gaussian in :attr:`geometry` (-1: culled by the near or far
        plane). Projects the whole model (once)."""
        geom = self._projection()[0]
        if self._rows is None:
            self._rows = torch.full((self.n,), -1, dtype=torch.long, device=self.means.device)
            self._rows[geom.ids] = torch.arange(geom.ids.numel(), device=self.means.device)
        return self._rows

    @property
    def opacities(self) -> Tensor:
        """[N] activated base opacities."""
        if self._opacities is None:
            self._opacities = lod.activated(self.opacity_logits, "sigmoid")
        return self._opacities

    @property
    def d_norm(self) -> Tensor:
        """[N] frustum-normalised distances d' (:func:`clod_adapter.lod.rule.normalized_distances`)."""
        if self._d_norm is None:
            self._d_norm = lod.normalized_distances(self.means, lod.camera_center(self.viewmat), self.frustum)
        return self._d_norm

    @property
    def critical(self) -> Tensor:
        """[N] float64 critical ``s_v`` of each Gaussian in this view (rendered iff ``s_v < s*``)."""
        if self._critical is None:
            self._require_sigma()
            self._critical = critical_s_v(self.opacities.detach(), self.d_norm.detach(), self.sigma_d.detach(),
                                          self.settings.tau, self.settings.eps)
        return self._critical

    @property
    def ramp_s_v(self) -> float:
        """Where this view's ramp from full detail to the LoD rule ends (window fade; world-free
        scalar >= 1.1): :func:`clod_adapter.lod.rule.ramp_s_v` of the share of the Gaussians in the
        frustum that Eq. 2's mask keeps at ``s_v = 1``."""
        if self._ramp is None:
            self._require_sigma()
            st = self.settings
            _, self._n_frustum, n_keep = lod.lod_keep(self.opacities, self.d_norm, self.sigma_d, 1.0, self.frustum,
                                                      st.tau, st.eps, with_ids=False)
            n_fr = self._n_frustum
            self._ramp = lod.ramp_s_v(n_keep / n_fr if n_fr else 1.0, st.max_sv)
        return self._ramp

    def _require_sigma(self) -> None:
        if self.sigma_d is None:
            raise ValueError("render_lod: s_v/budget given but the model has no sigma_d")

    def _visible_prefix(self, k: int) -> Optional[Tensor]:
        """[N] bool: the Gaussians in view among a prefix of the count budgets' order (critical
        ``s_v`` descending) that holds at least ``k`` of them, found by projecting only that
        prefix; None where the whole model is (or must be) projected instead (:attr:`visible`).

        A budget of ``k`` draws the ``k`` Gaussians in view with the largest critical ``s_v``
        and reads the ``(k + 1)``-th: both lie in any set that is closed upwards in critical
        ``s_v`` and holds ``k + 1`` Gaussians in view, so the budget is solved on the prefix
        exactly as on the whole model, without projecting the rest
        (``benchmarks/studies/budget_frames.py`` holds the two to the same image). The prefix is cut
        where it holds ``k`` centres in the frustum (a centre in the image is in view unless its
        footprint overflows, or it lies within rounding of the image's edge); where the
        projection finds fewer in view, the cut moves on by twice the shortfall, up to
        :data:`PREFIX_TRIES` times; where the frustum holds fewer than ``k``, the whole model is
        projected."""
        if (self._proj is not None and self._proj[2] is None) or k <= 0:
            return None
        if self._prefix is not None and self._prefix[0] == k:  # the prefix found last
            return self._prefix[1]
        crit = self.critical
        if bool(torch.isnan(crit).any()):
            return None
        inside = crit[self.frustum]
        cut = k
        for _ in range(PREFIX_TRIES):
            if inside.numel() < cut:
                return None
            t = torch.kthvalue(inside, inside.numel() - cut + 1).values  # the cut-th largest in the frustum
            ids = self._projection(torch.nonzero(crit >= t, as_tuple=False).squeeze(1))[1]
            if ids.numel() >= k:
                pool = torch.zeros(crit.numel(), dtype=torch.bool, device=crit.device)
                pool[ids] = True
                self._prefix = (k, pool)
                return pool
            cut += 2 * (k - ids.numel())  # centres in the frustum but out of view: cut further on
        return None

    def count_of(self, budget: Budget) -> int:
        """A count ``budget`` as a number of this model's Gaussians (:meth:`Budget.of`; an
        ``in_view`` share of :attr:`n_in_view`)."""
        return budget.of(self.n, self.n_in_view if budget.kind == "in_view" else None)

    # --- selection -----------------------------------------------------------------------------
    def select(self, s_v: Optional[float] = None, *, budget: Optional[Budget] = None,
               level: Optional[float] = None, eta_grad: EtaGradient = EtaGradient()) -> LodSelection:
        """What this camera draws at ``s_v`` or within ``budget`` (arguments as :func:`render_lod`).
        A cost or time budget draws the count :meth:`cost_count` gives, as a count budget of that
        size would (same Gaussians, same ``s_v``, the ``min_s_v`` rule).

        Raises:
            ValueError: both ``s_v`` and ``budget``; ``s_v < 1``; LoD without ``sigma_d``.
        """
        if s_v is not None and budget is not None:
            raise ValueError("render_lod: give one of s_v and budget, not both")
        min_s_v = 1.0 if budget is None else budget.min_s_v
        k = None
        if budget is not None and not budget.counts:
            k = self.cost_count(budget, level=level)
        elif budget is not None:
            k = self.count_of(budget)
        dev = self.means.device
        if s_v is None and k is None:
            idx = self._projection()[1]
            return LodSelection(idx, self.opacities.index_select(0, idx), self.visible, None, 0.0,
                                torch.ones((), dtype=self.means.dtype, device=dev))
        self._require_sigma()
        if s_v is not None and not s_v >= 1.0:
            raise ValueError(f"render_lod: s_v must be >= 1, got {s_v}")
        st = self.settings
        opac, sd = self.opacities, self.sigma_d
        if k is not None:
            crit = self.critical
            prefix = self._visible_prefix(k + 1)  # the visible among a prefix of the order, or None
            pool = self.visible if prefix is None else prefix
            idx, s_used = select_budget(crit, k, pool)
            full_floor = min_s_v <= 1.0 and st.fade == "window"  # the floor is full detail: every Gaussian in view
            if s_used < min_s_v and full_floor and prefix is None and k >= self.n_in_view:
                return self.select(1.0, level=level)  # the budget holds full detail: as s_v = 1 draws it
            if s_used < min_s_v and not full_floor:
                s_used = float(min_s_v)
                # above the solved s_v: only the chosen k, all in ``pool``
                mask = (crit > s_used) & pool
                idx = torch.nonzero(mask, as_tuple=False).squeeze(1)
            else:
                mask = torch.zeros(self.n, dtype=torch.bool, device=dev)
                mask[idx] = True
            eta = self._share_in_frustum(mask)
        else:
            s_used = float(s_v)
            if s_used <= 1.0 and st.fade == "window" and level is None:  # full detail: the input as it is
                idx = self._projection()[1]
                return LodSelection(idx, opac.index_select(0, idx), self.visible, 1.0, 0.0,
                                    self._share_in_frustum(self.visible))
            d = self.d_norm.detach()
            if st.fade == "window" and s_used < lod.ramp_cap(st.max_sv) and \
                    lod.full_detail_share(s_used, self.ramp_s_v) > 0.0:
                mask = lod.lod_mask(opac, d, sd, s_used, st.tau, st.eps) & self.visible
                return self._near_full_detail(mask, torch.nonzero(mask, as_tuple=False).squeeze(1), s_used, level)
            # what the LoD mask keeps, as indices (only those are projected) and the frustum counts
            keep, self._n_frustum, _ = lod.lod_keep(opac, d, sd, s_used, self.frustum, st.tau, st.eps)
            idx = self._projection(keep)[1]
            if self._proj[2] is None:  # a projection of the whole model served: the kept among its visible
                idx = keep[self.visible.index_select(0, keep)]
            mask = None  # built on use (LodSelection.mask): an s_v frame does not need the [N] mask
            if eta_grad.estimator != "paper" and torch.is_grad_enabled() and sd.requires_grad:
                m_eta = (lod.lod_margin(opac.detach(), d, sd, s_used, st.tau, st.eps) if eta_grad.sigma_only
                         else lod.lod_margin(opac, self.d_norm, sd, s_used, st.tau, st.eps))
                eta = lod.rendered_fraction(m_eta, self.frustum, eta_grad.estimator, eta_grad.temperature)
            else:
                eta = (self.frustum.index_select(0, idx).sum() / max(self.n_frustum, 1)).to(self.means.dtype)
        if st.fade == "eq2":
            drawn = lod.lod_opacities(opac.index_select(0, idx), self.d_norm.index_select(0, idx),
                                      sd.index_select(0, idx), s_used, st.eps)
            return LodSelection(idx, drawn, mask, s_used, 0.0, eta, self.n)
        if level is None:
            n_fr = self.n_frustum
            level = lod.level_of_fraction(idx.numel() / n_fr if n_fr else 1.0, st.max_sv, st.level_max)
        drawn = lod.window_opacities(idx, opac, self.opacity_logits, self.d_norm.detach(), sd, s_used, level,
                                     self.gains.get("opacity_logit_gain"), st.tau, st.eps,
                                     lod.fade_width_at(s_used, st.fade_width))
        return LodSelection(idx, drawn, mask, s_used, float(level), eta, self.n)

    def _near_full_detail(self, mask: Tensor, idx: Tensor, s_v: float, level: Optional[float]) -> LodSelection:
        """Window fade, ``1 <= s_v <`` :attr:`ramp_s_v`: every Gaussian in view is drawn, those the
        mask keeps with weight ``(1 - t) + t fade`` and the others with ``1 - t``, ``t`` = 1 -
        :func:`clod_adapter.lod.rule.full_detail_share` of ``s_v`` (0 at ``s_v = 1``: exactly the
        input; 1 at the ramp's end: the LoD rule). So full detail is the whole model in every
        view (a Gaussian whose critical ``s_v`` is below 1 in this view, e.g. a view whose
        frustum is shallower than the training views', fades out over the ramp instead of
        being missing), and the image stays continuous in ``s_v``."""
        st = self.settings
        t = 1.0 - lod.full_detail_share(s_v, self.ramp_s_v)
        n_fr = self.n_frustum
        if level is None:
            level = t * lod.level_of_fraction(idx.numel() / n_fr if n_fr else 1.0, st.max_sv, st.level_max)
        all_idx = torch.nonzero(self.visible, as_tuple=False).squeeze(1)
        margin = lod.lod_margin(self.opacities.index_select(0, all_idx),
                                self.d_norm.detach().index_select(0, all_idx),
                                self.sigma_d.index_select(0, all_idx), s_v, st.tau, st.eps)
        logits = self.opacity_logits.index_select(0, all_idx)
        g = self.gains.get("opacity_logit_gain")
        if g is not None and level > 0:
            logits = logits + level * g.index_select(0, all_idx)
        w = (1.0 - t) + t * lod.fade_weight(margin, lod.fade_width_at(s_v, st.fade_width))
        eta = self._share_in_frustum(mask)
        return LodSelection(all_idx, torch.sigmoid(logits) * w, self.visible, s_v, float(level), eta)

    def cost_count(self, budget: Budget, *, level: Optional[float] = None) -> int:
        """:func:`clod_adapter.lod.cost.view_cost_count` of this view (a cost or time ``budget``)."""
        return view_cost_count(self, budget, level=level)

    def full_cost(self) -> float:
        """:func:`clod_adapter.lod.cost.view_full_cost` of this view."""
        return view_full_cost(self)

    def subset(self, indices: Tensor, opacities: Optional[Tensor] = None) -> LodSelection:
        """A selection of given ``indices`` [k] (ascending, in view) drawn with ``opacities``
        [k] (default: the base opacities) at the base level: for static cuts (baselines)."""
        idx = indices.to(self.means.device)
        op = self.opacities.index_select(0, idx) if opacities is None else opacities.to(self.means)
        mask = torch.zeros_like(self.visible)
        mask[idx] = True
        return LodSelection(idx, op, mask, None, 0.0, self._share_in_frustum(mask))

    def _share_in_frustum(self, mask: Tensor) -> Tensor:
        """[] float: the share of the frustum's Gaussians that ``mask`` [N] bool holds, 0 for an
        empty frustum (counts, not a compacted copy: this runs every frame)."""
        return ((mask & self.frustum).sum() / max(self.n_frustum, 1)).to(self.means.dtype)

    # --- drawing -------------------------------------------------------------------------------
    def drawn_attributes(self, sel: LodSelection) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(means [k, 3], quats [k, 4], scales [k, 3], colors [k, ...]) of ``sel`` at its level
        (autograd), for rasterisers that project themselves (gsplat, viewers)."""
        idx = sel.indices
        scales = self.scales.index_select(0, idx)
        g = self.gains.get("log_scale_gain")
        if g is not None and sel.level > 0:
            scales = scales * torch.exp(sel.level * g.index_select(0, idx))[:, None]
        return (self.means.index_select(0, idx), self.quats.index_select(0, idx), scales,
                self._colors_at(idx, sel.level))

    def _colors_at(self, idx: Tensor, level: float) -> Tensor:
        g = self.gains.get("sh0_gain")
        if g is None or level <= 0 or self.colors.ndim != 3:
            return self.colors.index_select(0, idx)
        gain = level * g.index_select(0, idx)
        if isinstance(self.colors, ShParts):  # the gain on sh0 before the one concatenation
            c = self.colors
            return torch.cat([c.sh0.index_select(0, idx) + gain, c.shN.index_select(0, idx)], dim=1)
        col = self.colors.index_select(0, idx)
        return torch.cat([col[:, :1] + gain, col[:, 1:]], dim=1)

    def rasterize(self, sel: LodSelection, *, background: Optional[Tensor] = None,
                  sh_degree: Optional[int] = None, backend: Backend = "auto", colors: Optional[Tensor] = None):
        """Draw ``sel``: ``(image [H, W, D], alpha [H, W, 1], meta)``.

        CPU backend: the rows of this view's projection are finished with the drawn opacities
        and the level's scales (:func:`clod_adapter.render.projection.finish_projection`; no
        second projection), coloured (SH at the camera centre) and composited. CUDA: gsplat
        rasterises the drawn attributes (it projects them itself).

        Args:
            background: [D] colour behind the scene (default black).
            sh_degree: SH degree to evaluate (default: from ``colors``' K); None with [N, D]
                features.
            colors: [N, D] features to draw instead of the model's colours (the renderer hook).
        """
        from ..render.dispatch import rasterization, resolve_backend

        idx = sel.indices
        w, h = self.width, self.height
        feats = self.colors if colors is None else colors
        sh = sh_degree
        if sh is None and colors is None and feats.ndim == 3:
            sh = int(math.isqrt(feats.shape[1]) - 1)
        if resolve_backend(backend, self.means) == "gsplat":
            means, quats, scales, col = self.drawn_attributes(sel)
            if colors is not None:
                col = colors.index_select(0, idx)
            bg = None if background is None else background.reshape(1, -1)
            rc, ra, meta = rasterization(means, quats, scales, sel.opacities, col, self.viewmat[None],
                                         self.K[None], w, h, sh_degree=sh, backgrounds=bg, backend="gsplat")
            return rc[0], ra[0], meta
        return composite_parts([(self, sel)], background, sh, colors)

    def _finished(self, sel: LodSelection, sh: Optional[int], colors: Optional[Tensor] = None):
        """CPU drawing of ``sel`` up to compositing: (VisibleProjection of the drawn rows, their
        colours [V, D], opacities [V]); the projection's rows are finished with the drawn
        opacities and the level's scales (no second projection)."""
        from ..render.cpu import sh_colors, sh_colors_rows

        idx = sel.indices
        w, h = self.width, self.height
        feats = self.colors if colors is None else colors
        have = self._proj
        geom_all = self._projection(have[2] if have is not None else None)[0]
        if idx is self._proj[1]:  # the projection's visible rows themselves (full detail, an ``s_v`` frame)
            rows = self._proj[3]
        elif self._proj[2] is None:  # the whole model's projection: its row map
            rows = self.geometry_rows.index_select(0, idx)
        else:  # a candidate projection (a few rows): ``idx`` lies in its ascending ids
            rows = torch.searchsorted(geom_all.ids, idx)
            m = geom_all.ids.numel()
            if idx.numel() and (m == 0 or not torch.equal(geom_all.ids.index_select(0, rows.clamp_max(m - 1)), idx)):
                geom_all = self._projection()[0]  # another selection's candidates: project the whole model
                rows = self.geometry_rows.index_select(0, idx)
        geom = geom_all.subset(rows)
        cov_scale = None
        g = self.gains.get("log_scale_gain")
        if g is not None and sel.level > 0:
            cov_scale = torch.exp(2.0 * sel.level * g.index_select(0, idx))
        proj = finish_projection(geom, sel.opacities, w, h, EPS2D, 0.0, cov_scale)
        local = proj.rows  # positions of the drawn rows in ``sel`` (``geom`` has one row per index)
        op = sel.opacities.index_select(0, local)
        if colors is not None:
            col = colors.index_select(0, proj.ids)
        elif sh is None:
            col = feats.index_select(0, proj.ids)
        elif isinstance(feats, ShParts) and not (self.gains.get("sh0_gain") is not None and sel.level > 0):
            col = sh_colors_rows(sh, self.means, feats.sh0, feats.shN, proj.ids, lod.camera_center(self.viewmat))
        else:
            coeffs = self._colors_at(proj.ids, sel.level)
            col = sh_colors(sh, self.means.index_select(0, proj.ids), coeffs, lod.camera_center(self.viewmat))
        return proj, col, op


def view_lod_tensors(means: Tensor, quats: Tensor, scales: Tensor, opacity_logits: Tensor, colors: Tensor,
                     camera, *, sigma_d: Optional[Tensor] = None, gains: Optional[dict] = None,
                     settings: Optional[lod.LodSettings] = None, tau: Optional[float] = None,
                     eps: Optional[float] = None) -> LodView:
    """:class:`LodView` of raw tensors: ``means`` [N, 3], ``quats`` [N, 4] (wxyz), ``scales``
    [N, 3] (activated), ``opacity_logits`` [N] (raw), ``colors`` [N, K, 3] SH (a tensor, or
    :class:`ShParts` to gather only the drawn rows) or [N, D] features, seen by ``camera`` (as
    :func:`view_lod`'s: ``viewmat`` [4, 4] world-to-camera, ``K`` [3, 3] pixels, ``width`` /
    ``height`` pixels); ``sigma_d`` [N], ``gains`` {Gaussians gain field: tensor}, ``settings``
    (default: the paper's Eq. 2 drawing), ``tau``/``eps`` overrides."""
    t0 = time.perf_counter()
    dt = means.dtype
    viewmat = camera.viewmat.to(means.device, dt)
    K = camera.K.to(means.device, dt)
    w, h = int(camera.width), int(camera.height)
    d_norm = None
    if means.requires_grad and torch.is_grad_enabled():  # d' keeps its gradient (on first use)
        frustum = lod.in_frustum(means, viewmat, K, w, h, NEAR_PLANE)
    else:  # both terms in one pass (the C++ kernel where it builds)
        frustum, d_norm = lod.frame_terms(means, viewmat, K, w, h, NEAR_PLANE)
    return LodView(means=means, quats=quats, scales=scales, opacity_logits=opacity_logits, colors=colors,
                   sigma_d=sigma_d, gains={k: v for k, v in (gains or {}).items() if v is not None},
                   settings=_settings(settings, tau, eps), viewmat=viewmat, K=K, width=w, height=h,
                   frustum=frustum, project_ms=(time.perf_counter() - t0) * 1e3, _d_norm=d_norm)


def view_lod(gaussians: Gaussians, camera, *, tau: Optional[float] = None,
             eps: Optional[float] = None) -> LodView:
    """:class:`LodView` of ``gaussians`` (its ``sigma_d``, level gains and LoD settings) for
    ``camera``: any object with ``viewmat`` [4, 4] (world-to-camera, OpenCV axes), ``K`` [3, 3]
    (pixels), ``width``, ``height`` (e.g. :class:`clod_adapter.io.scene.Camera`)."""
    g = gaussians
    return view_lod_tensors(g.means, g.quats, lod.activated(g.log_scales, "exp"), g.opacity_logits,
                            ShParts(g.sh0, g.shN), camera, sigma_d=g.sigma_d,
                            gains={k: getattr(g, k) for k in ("opacity_logit_gain", "log_scale_gain", "sh0_gain")},
                            settings=g.lod, tau=tau, eps=eps)


@torch.no_grad()
def in_view(gaussians: Gaussians, viewmat: Tensor, K: Tensor, width: int, height: int) -> Tensor:
    """[N] bool: Gaussians whose footprint reaches the image (gsplat 1.5.3 culling with the
    opacity-free 3.33-sigma extent, near plane 0.01): :attr:`LodView.visible`."""
    return in_view_tensors(gaussians.means, gaussians.quats, gaussians.scales, viewmat, K, width, height)


@torch.no_grad()
def in_view_tensors(means: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor, K: Tensor,
                    width: int, height: int) -> Tensor:
    """:func:`in_view` on raw tensors (means [N, 3], quats [N, 4], activated scales [N, 3])."""
    n = means.shape[0]
    vis = torch.zeros(n, dtype=torch.bool, device=means.device)
    if n == 0:
        return vis
    dt = means.dtype
    vm, Kd = viewmat.to(means.device, dt), K.to(means.device, dt)
    geom = project_geometry(means.detach(), quats.detach(), scales.detach(), vm, Kd, int(width), int(height),
                            NEAR_PLANE, FAR_PLANE)
    vis[finish_projection(geom, None, int(width), int(height), EPS2D).ids] = True
    return vis


def composite_parts(parts, background, sh, colors=None):
    """CPU: each (view, selection)'s finished rows (:meth:`LodView._finished`), concatenated (a
    later view's ids offset by the earlier views' N) and composited as one image."""
    projs, cols, ops, off = [], [], [], 0
    for v, sel in parts:
        p, c, o = v._finished(sel, sh, colors)
        projs.append(p._replace(ids=p.ids + off) if off else p)
        cols.append(c)
        ops.append(o)
        off += v.n
    proj = projs[0] if len(projs) == 1 else VisibleProjection(
        *(torch.cat([getattr(p, f) for p in projs]) for f in ("ids", "radii", "means2d", "depths", "conics")))
    col, op = (cols[0], ops[0]) if len(parts) == 1 else (torch.cat(cols), torch.cat(ops))
    return composite_projected(proj, col, op, parts[0][0].width, parts[0][0].height, background)


def composite_projected(proj: VisibleProjection, colors: Tensor, opacities: Tensor, width: int, height: int,
                        background: Optional[Tensor] = None):
    """CPU: the visible rows of one projection (:func:`clod_adapter.render.projection.project_visible`,
    V rows), their colours [V, D] and opacities [V], composited (tile size :data:`TILE_SIZE`) over
    ``background`` ([D] or None: black): ``(image [H, W, D], alpha [H, W, 1], meta)``, meta's
    per-Gaussian arrays indexing ``meta["visible_ids"]`` (the plain frame's and a tree cut's)."""
    from ..render.cpu import rasterize_projected

    bg = None if background is None else background.reshape(-1)
    rc, ra, offsets, flat = rasterize_projected(proj, colors, opacities, width, height, TILE_SIZE, bg)
    meta = {"visible_ids": proj.ids, "radii": proj.radii, "means2d": proj.means2d, "depths": proj.depths,
            "conics": proj.conics, "isect_offsets": offsets, "flatten_ids": flat,
            "n_visible": int(proj.ids.numel()), "width": width, "height": height, "tile_size": TILE_SIZE}
    return rc, ra, meta
