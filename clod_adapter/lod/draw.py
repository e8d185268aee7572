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
  Gaussians in view (:meth:`LodView._visible_prefix`), and a tier it only passes through on a
  model with tiers projects just that many of its centres in the frustum
  (:meth:`LodView._frustum_holds`), and a cost or time budget tests the tiers it passes through
  on a sample of each (:meth:`LodView.full_detail_estimate`); the tier a cost or time budget ends
  in, and full detail, project everything in front;
* ``d_norm`` [N]: ``d' = |mu - c| / max_frustum |mu - c|``;
* ``critical`` [N] (on first use): each Gaussian's critical ``s_v`` (:mod:`clod_adapter.budget`).

:meth:`LodView.select` picks what is drawn at a virtual distance scale ``s_v`` (the mask
``alpha'' > tau s_v``, Eq. 2) or within a budget (``s_v`` solved exactly), with the drawn
opacities of the model's :class:`clod_adapter.lod.LodSettings` (Eq. 2's ``alpha''``, or the
window fade with the level gains); :meth:`LodView.rasterize` draws a selection.
:func:`render_lod` and :func:`lod_subset` are the one-call forms every caller uses (training,
evaluation, the renderer hook, export, baselines, the viewer).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, NamedTuple, Optional, Sequence

import torch
from torch import Tensor

from . import lod, tree
from .lod import Estimator
from .render.dispatch import Backend
from .budget import budget_count, critical_s_v, select_budget
from .cost import FrameTimeModel
from .gaussians import Gaussians
from .render.projection import VisibleProjection, finish_projection, project_geometry

#: gsplat 1.5.3 defaults used by every LoD render.
EPS2D, NEAR_PLANE, FAR_PLANE, TILE_SIZE = 0.3, 0.01, 1e10, 16
#: how often a budget's prefix is cut further on before the whole model is projected
#: (:meth:`LodView._visible_prefix`)
PREFIX_TRIES = 3
#: a budget walking down a chain of tiers compares each tier's full detail estimated from the
#: widest :data:`COST_SAMPLE_TOP` share and every this many-th of the rest
#: (:meth:`LodView.full_detail_estimate`; ``benchmarks/studies/cost_sample.py``, docs/studies.md
#: "Costing the tiers from a sample")
COST_SAMPLE_STEP = 8
#: the share of a model's Gaussians, the widest on screen, that the estimate costs exactly
COST_SAMPLE_TOP = 0.03
#: models with fewer Gaussians than this are costed whole (:meth:`LodView.full_detail_estimate`)
COST_SAMPLE_MIN = 4096


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
        names), settings: :class:`clod_adapter.lod.LodSettings`.
        viewmat [4, 4], K [3, 3], width, height: the camera.
        frustum [N] bool, visible [N] bool, n_in_view: see the module docstring.
        project_ms: wall time of the projection and the in-view test, ms.
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
    _costs: Optional[tuple] = field(default=None, repr=False)  # (level, order, footprints, costs): _cost_weights
    _prefix: Optional[tuple] = field(default=None, repr=False)  # (k, pool): _visible_prefix's last answer
    _held: int = field(default=0, repr=False)  # a count of Gaussians in view _frustum_holds has shown

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
    def _geom(self):
        return self._projection()[0]

    @property
    def _row_of(self) -> Tensor:
        """[N] int64: the row of each Gaussian in the whole model's projection (-1: behind)."""
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
        """[N] frustum-normalised distances d' (:func:`clod_adapter.lod.normalized_distances`)."""
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
        scalar >= 1.1): :func:`clod_adapter.lod.ramp_s_v` of the share of the Gaussians in the
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

    def draws_at_least(self, s_v: float, k: int, *, solving: bool = False) -> bool:
        """Whether :meth:`select` at ``s_v`` (>= 1) draws at least ``k`` (a count) Gaussians:
        ``select(s_v)``'s count ``>= k``, without projecting the whole model where the window
        fade's full detail draws every Gaussian in view: ``k`` centres in the frustum shown in
        view (:meth:`_frustum_holds`), or, with ``solving`` (a budget of ``k`` is solved in this
        view next) or where that does not show it, the prefix of the budget's order holding
        ``k`` in view that the budget then reads. The hand-over test of count budgets
        (:func:`budget_walk`).

        Raises:
            ValueError: as :meth:`select` (``s_v < 1``; no ``sigma_d``).
        """
        if s_v <= 1.0 and self.settings.fade == "window":
            if k <= 0:
                return True
            if k > self.n:
                return False
            if not solving and self._frustum_holds(k):
                return True
            # k + 1: the prefix a budget of k solved next in this view reads (projected once)
            return self._visible_prefix(k + 1) is not None or self.n_in_view >= k
        return int(self.select(s_v).indices.numel()) >= k

    def _frustum_holds(self, k: int) -> bool:
        """Whether ``k`` Gaussians whose centres lie in the frustum are in view, found by projecting
        only ``k`` (plus a sixteenth) of them: a sufficient test of ``n_in_view >= k`` that needs
        neither the critical ``s_v`` nor the whole projection (a tier a count budget passes on
        through is never solved, :func:`budget_walk`). False where it is not shown so."""
        if self._proj is not None and self._proj[2] is None:
            return self.n_in_view >= k
        if k <= self._held:
            return True
        ids = torch.nonzero(self.frustum, as_tuple=False).squeeze(1)
        if ids.numel() < k:
            return False
        t0 = time.perf_counter()
        geom = project_geometry(self.means, self.quats, self.scales, self.viewmat, self.K, self.width, self.height,
                                NEAR_PLANE, FAR_PLANE, ids[:k + k // 16])
        with torch.no_grad():
            n_vis = int(finish_projection(geom, None, self.width, self.height, EPS2D).ids.numel())
        self.project_ms += (time.perf_counter() - t0) * 1e3
        self._held = max(self._held, n_vis)
        return n_vis >= k

    def budget_drawn(self, budget: float | int, min_s_v: float = 1.0, *, solving: bool = False) -> Optional[int]:
        """How many Gaussians ``select(budget=budget, min_s_v=min_s_v)`` draws, without solving it,
        where the rule gives the count: window fade and ``min_s_v <= 1`` (full detail is the
        floor), ``min(k, n_in_view)`` for ``k`` = :func:`clod_adapter.budget.budget_count` of the
        budget, found by :meth:`draws_at_least` (``solving`` as there); None otherwise (solve it).

        Raises:
            ValueError: a negative budget.
        """
        if self.settings.fade != "window" or min_s_v > 1.0:
            return None
        k = budget_count(budget, self.n)
        return k if self.draws_at_least(1.0, k, solving=solving) else self.n_in_view

    # --- selection -----------------------------------------------------------------------------
    def select(self, s_v: Optional[float] = None, *, budget: Optional[float | int] = None,
               min_s_v: float = 1.0, budget_in_view: bool = False, level: Optional[float] = None,
               estimator: Estimator = "ste", temperature: float = 1.0,
               eta_grad_sigma_only: bool = True, budget_cost: Optional[float] = None,
               budget_ms: Optional[float] = None, time_model: Optional[FrameTimeModel] = None) -> LodSelection:
        """What this camera draws at ``s_v`` or within ``budget``, ``budget_cost`` or
        ``budget_ms`` (arguments as :func:`render_lod`). A cost budget draws the count
        :meth:`cost_count` gives, as a count budget of that size would (same Gaussians, same
        ``s_v``, the ``min_s_v`` rule).

        Raises:
            ValueError: more than one of ``s_v``, ``budget``, ``budget_cost``, ``budget_ms``;
                ``s_v < 1``; a negative cost budget; LoD without ``sigma_d``.
        """
        given = [k for k, v in (("s_v", s_v), ("budget", budget), ("budget_cost", budget_cost),
                                ("budget_ms", budget_ms)) if v is not None]
        if len(given) > 1:
            raise ValueError(f"render_lod: give one of s_v, budget, budget_cost, budget_ms, not {' and '.join(given)}")
        if budget_cost is not None or budget_ms is not None:
            budget = self.cost_count(budget_cost, budget_ms, level=level, time_model=time_model, min_s_v=min_s_v)
            budget_in_view = False
        dev = self.means.device
        if s_v is None and budget is None:
            idx = self._projection()[1]
            return LodSelection(idx, self.opacities.index_select(0, idx), self.visible, None, 0.0,
                                torch.ones((), dtype=self.means.dtype, device=dev))
        self._require_sigma()
        if s_v is not None and not s_v >= 1.0:
            raise ValueError(f"render_lod: s_v must be >= 1, got {s_v}")
        st = self.settings
        opac, sd = self.opacities, self.sigma_d
        if budget is not None:
            if budget_in_view and isinstance(budget, float) and budget <= 1.0:
                budget = int(round(budget * self.n_in_view))
            crit = self.critical
            k = budget_count(budget, self.n)
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
            if estimator != "paper" and torch.is_grad_enabled() and sd.requires_grad:
                m_eta = (lod.lod_margin(opac.detach(), d, sd, s_used, st.tau, st.eps) if eta_grad_sigma_only
                         else lod.lod_margin(opac, self.d_norm, sd, s_used, st.tau, st.eps))
                eta = lod.rendered_fraction(m_eta, self.frustum, estimator, temperature)
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
        :func:`clod_adapter.lod.full_detail_share` of ``s_v`` (0 at ``s_v = 1``: exactly the
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

    def cost_count(self, budget_cost: Optional[float] = None, budget_ms: Optional[float] = None, *,
                   level: Optional[float] = None, time_model: Optional[FrameTimeModel] = None,
                   min_s_v: float = 1.0) -> int:
        """How many Gaussians a cost budget draws: the longest prefix of the count budgets' order
        (the Gaussians in view by :attr:`critical` descending, ties by index) whose cost fits.

        Per-Gaussian costs are :func:`clod_adapter.cost.splat_cost` (clipped ellipse pixels) of
        the prefix as :meth:`select` would draw it with ``budget=k``:

        * Eq. 2 drawing: with the attenuated opacities ``alpha''`` at the ``s_v`` solved for the
          prefix (raised to ``min_s_v``): exact. The cost of a prefix grows with its length
          (longer prefix, smaller ``s_v``, larger ``alpha''``), so the count is searched (regula
          falsi, then bisection) between the prefix at the base opacities (fits) and the prefix
          at the first one's ``s_v`` (bounds it): 10-15 evaluations, 15-30 ms on fern and skull
          against 5 ms for a count budget (2 threads, shared machine);
        * window fade: at the base level (or ``level`` when given): the footprints the calibrated
          schedule measures its levels in (:func:`clod_adapter.training.weighted_count`), one prefix
          search, monotone in the budget. The level gains change what is drawn (survivors grow
          to cover for those that left), so the drawn pixel work of a coarse level is larger
          than its base cost; ``benchmarks/quality_vs_time.py`` times what is drawn. (Costing
          each prefix at its own level has no monotone solution: a shorter prefix sits at a
          coarser level whose grown footprints cost more, and the search settled on a few
          hundred huge splats.)

        Args:
            budget_cost: a float in (0, 1]: that share of the cost of drawing every Gaussian in
                view at full detail (base opacities, level 0); > 1: an absolute cost (pixels,
                :data:`clod_adapter.cost.COST_UNIT`).
            budget_ms: predicted rasterisation ms (:class:`clod_adapter.cost.FrameTimeModel`,
                ``time_model`` or the defaults): the longest prefix whose predicted ms fits.
            level: the level of the gains to draw at (window fade; None: from the share).
            min_s_v: the budget rule of :meth:`select` (Eq. 2: the ``s_v`` floor of the drawing).

        Returns:
            the count k (0 <= k <= :attr:`n_in_view`), non-decreasing in the budget.
        """
        from .cost import DEFAULT_FRAME_TIME_MODEL, prefix_count

        if (budget_cost is None) == (budget_ms is None):
            raise ValueError("cost_count: give budget_cost or budget_ms")
        b = float(budget_cost if budget_cost is not None else budget_ms)
        if not b >= 0:
            raise ValueError(f"render_lod: cost budgets must be >= 0, got {b}")
        tm = time_model or DEFAULT_FRAME_TIME_MODEL
        order, fp, weights = self._cost_weights(level)
        n_vis = order.numel()
        if n_vis == 0:
            return 0
        eq2 = self.settings.fade == "eq2"
        if budget_ms is not None:
            weights = tm.per_splat_ms(weights)
            limit = b - tm.c0_ms
        elif b <= 1.0:
            # the same float64 cumulative sum as the prefix search: 1.0 draws every Gaussian
            limit = b * float(torch.cumsum(weights.double(), 0)[-1])
        else:
            limit = b
        k = prefix_count(weights, limit)
        if eq2 and k < n_vis:
            unit = (lambda c: c) if budget_ms is None else tm.per_splat_ms
            k = self._eq2_cost_count(order, fp, k, limit, unit, min_s_v)
        return k

    def _cost_weights(self, level: Optional[float] = None):
        """``(order, footprints, costs)`` of the Gaussians in view in the count budgets' order:
        window fade at the base level (or ``level`` given), the unit the calibrated levels are
        measured in; Eq. 2 at the base opacities (:meth:`cost_count` then searches exactly)."""
        from .cost import Footprints, level_opacities, order_in_view

        lv = float(level) if (level is not None and self.settings.fade != "eq2") else 0.0
        if self._costs is not None and self._costs[0] == lv:  # a cost budget, then the tier's full cost
            return self._costs[1:]
        order = order_in_view(self.critical, self.visible)
        if order.numel() == 0:
            return order, None, self.means.new_zeros(0)
        fp = Footprints(self, order, lv)
        self._costs = (lv, order, fp, fp.cost(level_opacities(self, order, lv)))
        return self._costs[1:]

    def full_cost(self) -> float:
        """The cost (:func:`clod_adapter.cost.splat_cost`, pixels) of every Gaussian in view at full
        detail: what a ``budget_cost`` share is a share of."""
        if not self.n_in_view:
            return 0.0
        if self._costs is not None and self._costs[0] == 0.0:  # a cost budget's weights: the same cost
            return float(torch.cumsum(self._costs[3].double(), 0)[-1])
        # order-free: no critical s_v and no sort (a tier's budget walk reads only this of the model)
        from .cost import Footprints, level_opacities

        ids = torch.nonzero(self.visible, as_tuple=False).squeeze(1)
        return float(Footprints(self, ids, 0.0).cost(level_opacities(self, ids, 0.0)).double().sum())

    def full_detail_estimate(self, step: Optional[int] = None) -> tuple[float, float]:
        """``(cost, count)`` of every Gaussian in view at full detail (:meth:`full_cost`,
        :attr:`n_in_view`) estimated without projecting the model whole: the
        :data:`COST_SAMPLE_TOP` share of the Gaussians with the largest ``max(scales) / d'`` (the
        widest on screen, which carry most of the cost) costed exactly, and every ``step``-th of
        the rest by index (default :data:`COST_SAMPLE_STEP`) weighted by the rest over the rows
        taken. What a budget walking down a chain of tiers compares (:func:`budget_walk`). Exact
        (the whole model) below :data:`COST_SAMPLE_MIN` Gaussians or with ``step`` 1.

        Returns:
            (cost in :data:`clod_adapter.cost.COST_UNIT`, clipped ellipse pixels; the count of
            Gaussians in view), both float; within 5.1 % of the exact cost on the validation views
            of the shared checkpoints (docs/studies.md "Costing the tiers from a sample")."""
        from .cost import Footprints, level_opacities

        step = COST_SAMPLE_STEP if step is None else int(step)
        n = self.n
        if step <= 1 or n < COST_SAMPLE_MIN:
            return self.full_cost(), float(self.n_in_view)
        size = self.scales.detach().amax(-1) / self.d_norm.detach().clamp_min(1e-12)
        dev = self.means.device
        top = torch.topk(size, int(COST_SAMPLE_TOP * n)).indices
        rest = torch.ones(n, dtype=torch.bool, device=dev)
        rest[top] = False
        rest_ids = torch.nonzero(rest, as_tuple=False).squeeze(1)
        taken = rest_ids[::step]
        ids, _ = torch.sort(torch.cat([top, taken]))
        weight = torch.zeros(n, dtype=torch.float64, device=dev)
        weight[top] = 1.0
        weight[taken] = rest_ids.numel() / max(taken.numel(), 1)
        sub = LodView(means=self.means[ids], quats=self.quats[ids], scales=self.scales[ids],
                      opacity_logits=self.opacity_logits[ids], colors=None, sigma_d=None, gains={},
                      settings=self.settings, viewmat=self.viewmat, K=self.K, width=self.width,
                      height=self.height, frustum=self.frustum[ids])
        vis = torch.nonzero(sub.visible, as_tuple=False).squeeze(1)
        w = weight[ids].index_select(0, vis)
        cost = Footprints(sub, vis, 0.0).cost(level_opacities(sub, vis, 0.0)).double()
        return float((cost * w).sum()), float(w.sum())

    def _eq2_cost_count(self, order: Tensor, fp, k_lo: int, limit: float, unit, min_s_v: float) -> int:
        """:meth:`cost_count` for Eq. 2 drawing: the largest k whose prefix of ``order``, drawn with
        ``alpha''`` at its own ``s_v``, costs <= ``limit``; ``k_lo`` fits (base opacities); ``fp``:
        the :class:`clod_adapter.cost.Footprints` of ``order`` at level 0."""
        from .cost import prefix_count

        crit = self.critical.index_select(0, order)  # descending
        m = order.numel()
        op = self.opacities.detach().index_select(0, order)
        d = self.d_norm.detach().index_select(0, order)
        sd = self.sigma_d.detach().index_select(0, order)
        eps = self.settings.eps

        def s_of(k: int) -> float:  # select_budget's s_v for the top k, with the min_s_v rule
            if k <= 0:
                s = float(crit[0])
            elif k >= m:
                s = float(crit[-1]) * 0.5
            else:
                hi, lo = float(crit[k - 1]), float(crit[k])
                s = hi if hi == lo else (hi * lo) ** 0.5 if lo > 0 else hi * 0.5
            return max(s, 1e-12, float(min_s_v))

        def drawn(k: int) -> float:  # the cost of the first k drawn at s_v(k)
            if k == 0:
                return 0.0
            s = s_of(k)
            c = unit(fp.cost(lod.lod_opacities(op[:k], d[:k], sd[:k], s, eps), first=k))
            return float(torch.cumsum(c.double(), 0)[-1])

        # A prefix's drawn cost grows with k (smaller s_v, larger alpha''), and for k >= lo the
        # costs at s_v(lo) are <= the drawn ones: their prefix bounds the answer from above.
        lo, c_lo = k_lo, drawn(k_lo)
        full = unit(fp.cost(lod.lod_opacities(op, d, sd, s_of(lo), eps)))
        hi = max(lo, prefix_count(full, limit))
        if hi > lo:
            c_hi = drawn(hi)
            if c_hi <= limit:
                return hi
            side, steps = 0, 0
            while hi - lo > 1:  # lo fits, hi does not: regula falsi (Illinois), then bisection
                steps += 1
                if c_hi > c_lo and steps <= 8:
                    t = (limit - c_lo) / (c_hi - c_lo)
                    mid = lo + int(t * (hi - lo))
                else:
                    mid = (lo + hi) // 2
                mid = min(max(mid, lo + 1), hi - 1)
                c_mid = drawn(mid)
                if c_mid <= limit:
                    lo, c_lo = mid, c_mid
                    if side == -1:
                        c_hi = limit + 0.5 * (c_hi - limit)
                    side = -1
                else:
                    hi, c_hi = mid, c_mid
                    if side == 1:
                        c_lo = limit - 0.5 * (limit - c_lo)
                    side = 1
        return lo

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
        from .render.dispatch import rasterization, resolve_backend

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
        return _composite([(self, sel)], background, sh, colors)

    def _finished(self, sel: LodSelection, sh: Optional[int], colors: Optional[Tensor] = None):
        """CPU drawing of ``sel`` up to compositing: (VisibleProjection of the drawn rows, their
        colours [V, D], opacities [V]); the projection's rows are finished with the drawn
        opacities and the level's scales (no second projection)."""
        from .render.cpu import sh_colors

        idx = sel.indices
        w, h = self.width, self.height
        feats = self.colors if colors is None else colors
        have = self._proj
        geom_all = self._projection(have[2] if have is not None else None)[0]
        if idx is self._proj[1]:  # the projection's visible rows themselves (full detail, an ``s_v`` frame)
            rows = self._proj[3]
        elif self._proj[2] is None:  # the whole model's projection: its row map
            rows = self._row_of.index_select(0, idx)
        else:  # a candidate projection (a few rows): ``idx`` lies in its ascending ids
            rows = torch.searchsorted(geom_all.ids, idx)
            m = geom_all.ids.numel()
            if idx.numel() and (m == 0 or not torch.equal(geom_all.ids.index_select(0, rows.clamp_max(m - 1)), idx)):
                geom_all = self._projection()[0]  # another selection's candidates: project the whole model
                rows = self._row_of.index_select(0, idx)
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
        else:
            coeffs = self._colors_at(proj.ids, sel.level)
            col = sh_colors(sh, self.means.index_select(0, proj.ids), coeffs, lod.camera_center(self.viewmat))
        return proj, col, op


def view_lod_tensors(means: Tensor, quats: Tensor, scales: Tensor, opacity_logits: Tensor, colors: Tensor,
                     viewmat: Tensor, K: Tensor, width: int, height: int, *, sigma_d: Optional[Tensor] = None,
                     gains: Optional[dict] = None, settings: Optional[lod.LodSettings] = None,
                     tau: Optional[float] = None, eps: Optional[float] = None) -> LodView:
    """:class:`LodView` of raw tensors: ``means`` [N, 3], ``quats`` [N, 4] (wxyz), ``scales``
    [N, 3] (activated), ``opacity_logits`` [N] (raw), ``colors`` [N, K, 3] SH (a tensor, or
    :class:`ShParts` to gather only the drawn rows) or [N, D] features,
    ``viewmat`` [4, 4] world-to-camera, ``K`` [3, 3] (pixels), ``width``/``height`` (pixels),
    ``sigma_d`` [N], ``gains`` {Gaussians gain field: tensor}, ``settings`` (default: the paper's
    Eq. 2 drawing), ``tau``/``eps`` overrides."""
    t0 = time.perf_counter()
    dt = means.dtype
    viewmat = viewmat.to(means.device, dt)
    K = K.to(means.device, dt)
    w, h = int(width), int(height)
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
    return view_lod_tensors(g.means, g.quats, lod.activated(g.log_scales, "exp"), g.opacity_logits, ShParts(g.sh0, g.shN), camera.viewmat, camera.K,
                            camera.width, camera.height, sigma_d=g.sigma_d,
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


# --- the one-call forms ---------------------------------------------------------------------------
@dataclass
class LodRender:
    """Result of :func:`render_lod`.

    Attributes:
        image: [H, W, 3] rendered colours (float32, not clamped).
        alpha: [H, W, 1] accumulated opacity.
        mask: [N] bool, Gaussians handed to the rasteriser: in view and passing the LoD mask (or
            the budget selection); built on first use from ``indices``.
        indices: [n_rendered] int64, the same Gaussians as indices, ascending.
        n_rendered: Gaussians handed to the rasteriser, the render cost (``mask.sum()``, plus
            ``n_parents``).
        n_frustum: number of Gaussian centres inside the view frustum (the parent tier's when
            only it is drawn).
        eta: scalar tensor, rendered fraction of the frustum (gradient per the estimator; 1.0
            without LoD).
        s_v: the virtual distance scale used (the solved one in budget mode; None: no LoD).
        level: level of the gains drawn, in [0, 1].
        project_ms, select_ms, raster_ms: wall time of the projection + in-view test, of the
            LoD selection (frustum, d', Eq. 2 mask or budget solve, drawn opacities), and of the
            rasterisation (finishing the projection of the drawn set, colours, compositing), ms.
        meta: the rasteriser's meta dict (per-Gaussian arrays index ``meta["visible_ids"]``).
        n_parents: parents of the model's parent tier drawn (in ``n_rendered``; ``mask`` and
            ``indices`` are the model's own Gaussians).
    """

    image: Tensor
    alpha: Tensor
    selection: LodSelection = field(repr=False)
    n_rendered: int
    n_frustum: int
    eta: Tensor
    s_v: Optional[float] = None
    level: float = 0.0
    project_ms: float = 0.0
    select_ms: float = 0.0
    raster_ms: float = 0.0
    meta: dict = field(default_factory=dict)
    n_parents: int = 0

    @property
    def mask(self) -> Tensor:
        return self.selection.mask

    @property
    def indices(self) -> Tensor:
        return self.selection.indices


def render_lod(
    gaussians: Gaussians,
    camera,
    s_v: Optional[float] = None,
    *,
    budget: Optional[float | int] = None,
    tau: Optional[float] = None,
    eps: Optional[float] = None,
    estimator: Estimator = "ste",
    temperature: float = 1.0,
    background: Optional[Sequence[float] | Tensor] = None,
    sh_degree: Optional[int] = None,
    backend: Backend = "auto",
    eta_grad_sigma_only: bool = True,
    min_s_v: float = 1.0,
    budget_in_view: bool = False,
    level: Optional[float] = None,
    budget_cost: Optional[float] = None,
    budget_ms: Optional[float] = None,
    time_model: Optional[FrameTimeModel] = None,
    view: Optional[LodView] = None,
) -> LodRender:
    """Render ``gaussians`` from ``camera`` at virtual distance scale ``s_v`` (or a budget).

    The Gaussians in view that pass the mask ``alpha'' > tau s_v`` (CLoD-GS Eq. 2) are handed to
    the rasteriser, drawn as the model's :class:`clod_adapter.lod.LodSettings` say: ``"eq2"`` with
    Eq. 2's ``alpha''`` (the paper), ``"window"`` with the attributes at the level
    (:meth:`Gaussians.at_level`) and only the Gaussians about to leave faded
    (:func:`clod_adapter.lod.fade_weight`). A model without settings is drawn as the paper does.
    A model with parent tiers (``gaussians.parents``, ``lod.tier_s_v > 0``; a chain,
    :func:`tier_chain`) cross-fades to its parents beyond ``tier_s_v`` at a given ``s_v``
    (:func:`chain_parts`: both drawn in one image, the Gaussians' opacities times ``1 - u``, the
    parents' times ``u``, the parents at their own ``s_v``, and so on down the chain); a budget
    whose solution passes a hand-over draws the next tier alone within it (:func:`budget_walk`); a given
    ``level`` draws the Gaussians alone.

    Args:
        gaussians: the model (N Gaussians). ``sigma_d`` is required when ``s_v`` or ``budget`` is given.
        camera: any object with ``viewmat`` [4, 4] (world-to-camera), ``K`` [3, 3] (pixels),
            ``width``, ``height`` (e.g. :class:`clod_adapter.io.scene.Camera`).
        s_v: virtual distance scale >= 1, or None for the plain model (no LoD, every Gaussian).
        budget: render exactly this many Gaussians (int) or this fraction of the model (float
            in [0, 1]) instead of a given ``s_v``: the ``s_v`` is solved exactly per view
            (:mod:`clod_adapter.budget`), capped by the Gaussians in view.
        tau: LoD threshold (mask ``alpha'' > tau s_v``); default the model's (0.005).
        eps: Eq. 2's epsilon; default the model's (1e-8).
        estimator, temperature: gradient of ``eta`` (see :func:`clod_adapter.lod.rendered_fraction`).
        background: [3] colour behind the scene (default black, as 3DGS on LLFF).
        sh_degree: SH degree to evaluate (default: the model's).
        backend: rasteriser backend (``"auto"``, ``"cpu"``, ``"gsplat"``).
        eta_grad_sigma_only: ``eta``'s gradient reaches ``sigma_d`` only (opacities and positions
            detached in its margin), so the count regulariser cuts Gaussians through their decay
            instead of eroding their opacity at every level of detail.
        min_s_v: budget mode only: the solved ``s_v`` is raised to at least this (default 1,
            the full-detail level, so a budget acts as a cap: a budget that holds every
            Gaussian in view renders full detail), where the level raised to draws no more than
            the budget: with the window fade, full detail (``min_s_v <= 1``) draws every Gaussian
            in view, so a smaller budget draws its ``k`` at the solved ``s_v`` below 1. A budget
            never draws more than ``budget`` Gaussians. 0 renders exactly ``budget`` Gaussians
            whatever ``s_v``.
        budget_in_view: a fractional ``budget`` is a share of the Gaussians in view, not of the
            model (the calibrated schedule's training).
        level: window fade only: draw the level gains at this level in [0, 1] instead of
            :func:`clod_adapter.lod.level_of_fraction` of the share of the Gaussians in view drawn.
        budget_cost: a budget in rasterisation cost instead of a count: the Gaussians in view
            with the largest critical ``s_v`` (the count budgets' order, so a prefix of it)
            while their summed :func:`clod_adapter.cost.splat_cost` (clipped ellipse pixels)
            fits; a float in (0, 1] is that share of the cost of every Gaussian in view, > 1 an
            absolute cost (:meth:`LodView.cost_count`). ``min_s_v`` applies as to ``budget``.
        budget_ms: a budget in predicted rasterisation ms (``raster_ms``; the projection is not
            in it): the longest such prefix whose :class:`clod_adapter.cost.FrameTimeModel`
            prediction (``time_model``, default the fitted one) fits. On a model with a parent
            tier, a cost budget whose prefix lands where the ``s_v`` rule draws the parents alone
            draws the parents alone within it (:func:`cost_budget_parents`).
        view: this model's :class:`LodView` for ``camera`` when the caller has built it (its
            projection and critical ``s_v`` are reused); default: built here.

    Returns:
        :class:`LodRender`.

    Raises:
        ValueError: ``s_v`` or a budget given but the model has no ``sigma_d``; ``s_v < 1``;
            more than one of ``s_v``, ``budget``, ``budget_cost``, ``budget_ms`` given.
    """
    if _tree_frame(gaussians, s_v, budget, level, budget_cost, budget_ms):
        return _render_tree(gaussians, camera, s_v, budget=budget, budget_cost=budget_cost, budget_ms=budget_ms,
                           time_model=time_model, budget_in_view=budget_in_view, background=background,
                           sh_degree=sh_degree, backend=backend)
    if tiered(gaussians, s_v, level):
        return _render_tiered(gaussians, camera, float(s_v), tau, eps, background,
                              gaussians.sh_degree if sh_degree is None else sh_degree, backend, view)
    if view is None:
        view = view_lod(gaussians, camera, tau=tau, eps=eps)
    p0, t1 = view.project_ms, time.perf_counter()
    walked, par = _budget_parents_first(gaussians, camera, view, level=level, budget=budget, min_s_v=min_s_v,
                                        budget_in_view=budget_in_view, budget_cost=budget_cost, budget_ms=budget_ms,
                                        time_model=time_model, tau=tau, eps=eps)
    if par is None:
        sel = view.select(s_v, budget=budget, min_s_v=min_s_v, budget_in_view=budget_in_view, level=level,
                          estimator=estimator, temperature=temperature, eta_grad_sigma_only=eta_grad_sigma_only,
                          budget_cost=budget_cost, budget_ms=budget_ms, time_model=time_model)
        if not walked and level is None:
            par = cost_budget_parents(gaussians, camera, view, sel, budget=budget, budget_cost=budget_cost,
                                      budget_ms=budget_ms, time_model=time_model, tau=tau, eps=eps)
    if par is not None:  # past a hand-over: a tier alone, or two mixed (count budgets), within the budget
        return _render_budget_parts(gaussians, par, t1, background,
                                    gaussians.sh_degree if sh_degree is None else sh_degree, backend)
    t2 = time.perf_counter()
    bg = None
    if background is not None:
        bg = torch.as_tensor(background, dtype=gaussians.means.dtype, device=gaussians.means.device)
    image, alpha, meta = view.rasterize(sel, background=bg,
                                        sh_degree=gaussians.sh_degree if sh_degree is None else sh_degree,
                                        backend=backend)
    t3 = time.perf_counter()
    return LodRender(image=image, alpha=alpha, selection=sel, n_rendered=int(sel.indices.numel()),
                     n_frustum=view.n_frustum, eta=sel.eta, s_v=sel.s_v, level=sel.level,
                     project_ms=view.project_ms, select_ms=(t2 - t1) * 1e3 - (view.project_ms - p0),
                     raster_ms=(t3 - t2) * 1e3, meta=meta)


def _tree_frame(gaussians: Gaussians, s_v, budget, level, budget_cost, budget_ms) -> bool:
    """Whether a frame of a merge-tree model (:func:`clod_adapter.tree.is_tree`) is one cut of the
    tree: at an ``s_v`` or any budget, no ``level`` given."""
    return (tree.is_tree(gaussians) and level is None
            and any(x is not None for x in (s_v, budget, budget_cost, budget_ms)))


def tiered(gaussians: Gaussians, s_v: Optional[float], level: Optional[float] = None) -> bool:
    """Whether ``render_lod(gaussians, ..., s_v)`` draws the model's parent tier: an ``s_v``
    given (no budget, no ``level``) past the model's ``tier_s_v`` (:func:`clod_adapter.lod.tier_weight`)."""
    st = gaussians.lod
    return (s_v is not None and level is None and gaussians.parents is not None and st is not None
            and st.tier_s_v > 0 and lod.tier_weight(float(s_v), st)[0] > 0)


def tier_chain(gaussians: Gaussians) -> list[Gaussians]:
    """The model's tiers, finest first: ``[gaussians, gaussians.parents, its parents, ...]``, each
    followed by the next while its ``lod.tier_s_v > 0`` (docs/lod_rule.md "The tiers")."""
    return tree.tiers_of(gaussians)


def tier_reach(gaussians: Gaussians) -> float:
    """How far the model's ``s_v`` reaches into its tiers: the product over the chain
    (:func:`tier_chain`) of ``tier_fade * tier_s_v / tier_start`` (>= 1; 1 without tiers), so the
    coarsest tier is at its own ``s_v = s`` where the model is at ``s * tier_reach`` (past every
    hand-over; :func:`clod_adapter.lod.tier_weight`)."""
    r = 1.0
    for m in tier_chain(gaussians)[:-1]:
        r *= m.lod.tier_fade * m.lod.tier_s_v / m.lod.tier_start
    return max(r, 1.0)


def chain_parts(s_v: float, settings: Sequence[lod.LodSettings], view_of: Callable[[int], LodView]):
    """What a model with a chain of tiers draws at ``s_v`` (docs/lod_rule.md "The tiers"):
    ``(parts, sels)``, ``parts`` the ``(view, selection)`` pairs for :func:`rasterize_views`
    (finest tier first), ``sels[k]`` tier ``k``'s selection or None where it is not drawn.

    ``settings[k]`` are tier ``k``'s :class:`clod_adapter.lod.LodSettings` (its ``tier_s_v`` hands
    over to tier ``k + 1``; the last tier's is not read). Tier 0 is drawn at ``s_v``; with
    ``(u, s_next) = lod.tier_weight(s, settings[k])`` tier ``k`` keeps ``1 - u`` of its weight and
    passes ``u`` to tier ``k + 1`` at its own ``s_next``: each tier's drawn opacities are times its
    weight, so at most two neighbouring tiers are drawn at once and the image is continuous in
    ``s_v``. ``view_of(k)`` builds tier ``k``'s :class:`LodView` of the camera (called only for
    the tiers drawn)."""
    parts, sels = [], [None] * len(settings)
    for k, (w, s) in enumerate(chain_weights(s_v, settings)):
        if w > 0.0:
            v = view_of(k)
            sel = v.select(s)
            if w != 1.0:
                sel.opacities = sel.opacities * w
            parts.append((v, sel))
            sels[k] = sel
    return parts, sels


def chain_weights(s_v: float, settings: Sequence[lod.LodSettings]) -> list[tuple[float, float]]:
    """``[(weight, s_v)]`` of each tier of a chain at the model's ``s_v`` (:func:`chain_parts`):
    tier ``k``'s share of the image (0: not drawn) and its own ``s_v``. The weights sum to 1 and at
    most two neighbouring ones are > 0."""
    out, w, s = [], 1.0, float(s_v)
    for k, st in enumerate(settings):
        u, s_next = lod.tier_weight(s, st) if k + 1 < len(settings) else (0.0, s)
        out.append((w * (1.0 - u), s))
        w, s = w * u, s_next
    return out


class TierBudget(NamedTuple):
    """A budget drawn past a hand-over of a chain of tiers (:func:`budget_walk`): ``sel`` of tier
    ``depth`` (>= 1) in its ``view``, ``s_v`` the model's ``s_v`` it stands for."""

    view: "LodView"
    sel: LodSelection
    s_v: float
    depth: int

    def parts(self) -> list:
        """``[(depth, view, selection)]``: what the frame draws (one tier)."""
        return [(self.depth, self.view, self.sel)]

    def views(self) -> list:
        """``[(view, selection)]``, finest first: :func:`rasterize_views`' parts."""
        return [(v, sel) for _, v, sel in self.parts()]

    def tier_indices(self, n_tiers: int, empty=None) -> tuple:
        """``(the model's own drawn rows, [tier k's drawn rows for k = 1..n_tiers])``, [m] int64
        each, ``empty`` where a tier draws nothing."""
        by_depth = {d: sel.indices for d, _, sel in self.parts()}
        return by_depth.get(0, empty), [by_depth.get(k + 1, empty) for k in range(n_tiers)]


def cost_budget_parents(gaussians: Gaussians, camera, view: LodView, sel: Optional[LodSelection], *, budget=None,
                        budget_cost=None, budget_ms=None, time_model=None, tau=None, eps=None,
                        count: Optional[int] = None):
    """A budget on a model with tiers (:func:`budget_walk` with the model's :func:`tier_chain`):
    a :class:`TierBudget` (the tier drawn, its selection, the model's ``s_v`` it stands for, its
    depth >= 1), else None (the model's own
    selection ``sel`` of ``view`` stands; ``sel`` may be None as :func:`budget_walk` allows,
    ``count`` the count budget's count in ``view``)."""
    models = tier_chain(gaussians)
    if len(models) < 2:
        return None
    return budget_walk([m.lod for m in models], lambda k: view_lod(models[k], camera, tau=tau, eps=eps), view, sel,
                       budget=budget, budget_cost=budget_cost, budget_ms=budget_ms, time_model=time_model,
                       count=count)


def _budget_parents_first(gaussians: Gaussians, camera, view: LodView, *, level, budget, min_s_v, budget_in_view,
                          budget_cost, budget_ms, time_model, tau, eps) -> tuple[bool, Optional[tuple]]:
    """A budget on a tiered model walked before the model's own selection is solved (which it
    then never needs where a tier takes the budget over): ``(walked, cost_budget_parents' answer)``;
    ``walked`` False where the walk needs that selection first (a count budget whose count the
    rule does not give, :meth:`LodView.budget_drawn`; a share of the Gaussians in view)."""
    models = tier_chain(gaussians)
    if level is not None or (budget is None and budget_cost is None and budget_ms is None) or len(models) < 2:
        return False, None
    count = None
    if budget is not None:
        if budget_in_view:
            return False, None
        # tier 1 cannot take a count over its size: the budget is then solved in this view
        count = view.budget_drawn(budget, min_s_v, solving=_taken_at(budget_count(budget, view.n)) > len(models[1]))
        if count is None:
            return False, None
    return True, cost_budget_parents(gaussians, camera, view, None, budget=budget, budget_cost=budget_cost,
                                     budget_ms=budget_ms, time_model=time_model, tau=tau, eps=eps, count=count)


def budget_walk(settings: Sequence[lod.LodSettings], view_of: Callable[[int], LodView], view: LodView,
                sel: Optional[LodSelection] = None, *, budget=None, budget_cost=None, budget_ms=None, time_model=None,
                depth: int = 0, count: Optional[int] = None):
    """A budget down a chain of tiers (docs/lod_rule.md "The tiers"; ``settings[k]`` tier ``k``'s,
    ``view_of(k)`` its :class:`LodView` of the camera, ``sel`` tier ``depth``'s own solution of the
    budget in ``view``). The next tier takes the budget when it can fill it from where the
    ``s_v`` rule first draws it alone (its ``tier_start`` level, selection ``start``): a count
    budget of ``k`` (the count ``sel`` drew) when ``start`` draws at least :data:`COUNT_TAKE_SHARE`
    of ``k`` (it is then asked for ``k`` and may draw fewer), a cost budget
    when ``start`` costs at least the budget (a ``budget_cost`` share is taken of the first view's
    full cost), a ``budget_ms`` when ``start`` is predicted to take at least that
    long (``time_model``, default the fitted one). A ``start`` at the tier's full detail
    (``tier_start <= 1``, as ``clod-adapt`` links tiers) and the first view's full cost are
    estimated from a sample, the widest Gaussians and every :data:`COST_SAMPLE_STEP`-th of the rest
    (:meth:`LodView.full_detail_estimate`).
    It is then solved in that tier (from its
    ``tier_start`` level on), and so on down the chain; so a smaller budget never draws a finer
    tier.
    Returns a :class:`TierBudget` (``depth >= 1``), or None (``sel`` stands).

    Only the tier the walk ends in is solved: a cost or time budget is tested against each tier's
    ``start``, and a count budget's count in a tier it passed on is known without solving it where
    the rule gives it (window fade from ``tier_start <= 1``: exactly ``k``,
    :meth:`LodView.budget_drawn`). ``sel`` may be None where ``count`` (a count budget) gives the
    count tier ``depth`` draws, or for a cost or time budget (:func:`render_lod` then solves tier
    ``depth`` only when no tier takes the budget over).

    Raises:
        ValueError: a count budget with neither ``sel`` nor ``count``."""
    from .cost import DEFAULT_FRAME_TIME_MODEL, splat_cost

    if budget is None and budget_cost is None and budget_ms is None:
        return None
    if sel is not None and sel.s_v is None:
        return None
    view_of = _memo(view_of)
    k = None
    if budget_ms is None and budget_cost is None:
        if sel is None and count is None:
            raise ValueError("budget_walk: a count budget needs the tier's selection or its count")
        k = int(sel.indices.numel()) if count is None else int(count)
    k0 = k  # the count tier ``depth`` draws: what each tier below is asked for
    b = None if budget_cost is None else float(budget_cost)
    d, vp, sel_p, scales = depth, None, None, []
    while d + 1 < len(settings):
        st = settings[d]
        if st is None or st.tier_s_v <= 0:
            break
        vn, sel_n = view_of(d + 1), None
        if k is None:
            if st.tier_start <= 1.0:  # first drawn alone at its full detail: estimated, not projected whole
                cost, drawn_n = vn.full_detail_estimate()
            else:
                start = vn.select(st.tier_start)
                cost = float(splat_cost(vn, start.indices, level=start.level, opacities=start.opacities).sum())
                drawn_n = float(start.indices.numel())
            if budget_ms is not None:
                fits = budget_ms <= float((time_model or DEFAULT_FRAME_TIME_MODEL).ms(cost, drawn_n))
            else:
                if b <= 1.0:  # a share of the first view's (estimated) full cost, absolute from here on
                    b = float(budget_cost) * view.full_detail_estimate()[0]
                b = max(b, 1.0 + 1e-6)
                fits = b <= cost
        else:
            solving = not _may_take(settings, view_of, d + 1, k0)  # the budget ends here if it fits
            fits = vn.draws_at_least(st.tier_start, _taken_at(k0), solving=solving)
            if fits:
                drawn = vn.budget_drawn(k0, st.tier_start, solving=solving)
                if drawn is None:  # not given by the rule: solve it
                    sel_n = vn.select(budget=k0, min_s_v=st.tier_start)
                    drawn = int(sel_n.indices.numel())
                k = drawn
        if not fits:
            break
        d, vp, sel_p = d + 1, vn, sel_n
        scales.append(st.tier_fade * st.tier_s_v / st.tier_start)  # the tier's s -> the model's (lod.tier_weight)
    if vp is None:
        return None
    start = settings[d - 1].tier_start
    if sel_p is None:
        if budget_ms is not None:
            sel_p = vp.select(budget_ms=budget_ms, time_model=time_model, min_s_v=start)
        elif b is not None:
            sel_p = vp.select(budget_cost=b, min_s_v=start)
        else:
            sel_p = vp.select(budget=k, min_s_v=start)
    s_equiv = sel_p.s_v
    for f in reversed(scales):  # from the deepest tier up, as each hand-over maps it
        s_equiv = s_equiv * f
    return TierBudget(vp, sel_p, s_equiv, d)


def count_budget_walk(settings: Sequence[lod.LodSettings], view_of: Callable[[int], LodView], view: LodView,
                      budget: float | int, min_s_v: float = 1.0) -> tuple[Optional[LodSelection], Optional[TierBudget]]:
    """A count ``budget`` (as :meth:`LodView.select`'s) on tier 0's ``view`` of a chain of tiers:
    ``(tier 0's own selection or None, budget_walk's answer or None)``, exactly one of them set.
    The walk goes first where the rule gives tier 0's count (:meth:`LodView.budget_drawn`), so
    tier 0's selection is solved only where the budget stays in it (the renderer hook's and
    bake's path; :func:`render_lod` does the same).

    Raises:
        ValueError: as :meth:`LodView.select` (a negative budget; no ``sigma_d``).
    """
    view_of = _memo(view_of)
    solving = len(settings) < 2 or not _may_take(settings, view_of, 0, budget_count(budget, view.n))
    count = view.budget_drawn(budget, min_s_v, solving=solving) if len(settings) > 1 else None
    sel = None if count is not None else view.select(budget=budget, min_s_v=min_s_v, estimator="paper")
    par = budget_walk(settings, view_of, view, sel, budget=budget, count=count) if len(settings) > 1 else None
    if par is None and sel is None:
        sel = view.select(budget=budget, min_s_v=min_s_v, estimator="paper")
    return sel, par


def _memo(view_of: Callable[[int], LodView]) -> Callable[[int], LodView]:
    """``view_of`` building each tier's view once."""
    if getattr(view_of, "memo", False):
        return view_of
    views: dict = {}

    def get(k: int) -> LodView:
        if k not in views:
            views[k] = view_of(k)
        return views[k]
    get.memo = True
    return get


#: a count budget of ``k`` passes to the next tier where that tier, as the ``s_v`` rule first draws
#: it alone, draws at least this share of ``k`` (:func:`budget_walk`; 1: only where it fills the
#: budget)
COUNT_TAKE_SHARE = 0.6


def _taken_at(k: int) -> int:
    """The count a tier must draw from its start to take a count budget of ``k`` over
    (:data:`COUNT_TAKE_SHARE` of it, at least 1 for ``k`` >= 1)."""
    return min(k, max(1, math.ceil(COUNT_TAKE_SHARE * k - 1e-9))) if k > 0 else 0


def _may_take(settings: Sequence[lod.LodSettings], view_of: Callable[[int], LodView], d: int, k: int) -> bool:
    """Whether tier ``d + 1`` of a chain could take a count budget of ``k`` over from tier ``d``
    (it exists and holds :func:`_taken_at` ``(k)`` Gaussians): where not, a budget that tier ``d`` takes is
    solved there (:meth:`LodView.draws_at_least`'s ``solving``)."""
    st = settings[d]
    return d + 1 < len(settings) and st is not None and st.tier_s_v > 0 and view_of(d + 1).n >= _taken_at(k)


def _chain_views(gaussians: Gaussians, camera, tau, eps, view: Optional[LodView] = None):
    """``(settings, view_of)`` of :func:`chain_parts` for ``gaussians``' tiers seen from ``camera``
    (tier 0's view is ``view`` when given)."""
    models = tier_chain(gaussians)
    return [m.lod for m in models], lambda k: view if (k == 0 and view is not None) else \
        view_lod(models[k], camera, tau=tau, eps=eps)


def _render_tiered(gaussians: Gaussians, camera, s_v: float, tau, eps, background, sh_degree, backend,
                   view: Optional[LodView]) -> LodRender:
    """:func:`render_lod` at an ``s_v`` where a parent tier is drawn (cross-fade or alone)."""
    t1 = time.perf_counter()
    parts, sels = chain_parts(s_v, *_chain_views(gaussians, camera, tau, eps, view))
    return _render_parts(gaussians, parts, sels[0], sum(int(x.indices.numel()) for x in sels[1:] if x is not None),
                         s_v, t1, background, sh_degree, backend)


def _render_parts(gaussians: Gaussians, parts, sel_c: Optional[LodSelection], n_p: int, s_v: float,
                  t1: float, background, sh_degree, backend) -> LodRender:
    """:class:`LodRender` of a frame that draws a parent tier: ``parts`` for
    :func:`rasterize_views`, the model's selection (None: none), the tiers' drawn count ``n_p``;
    ``s_v`` the model's ``s_v`` it stands for; ``t1`` when the selection began."""
    if sel_c is None:
        sel_c = LodSelection(torch.zeros(0, dtype=torch.long, device=gaussians.means.device),
                             gaussians.opacity_logits.new_zeros(0), None, s_v, 0.0, parts[0][1].eta.new_zeros(()),
                             len(gaussians))
    t2 = time.perf_counter()
    bg = None
    if background is not None:
        bg = torch.as_tensor(background, dtype=gaussians.means.dtype, device=gaussians.means.device)
    image, alpha, meta = rasterize_views(parts, background=bg, sh_degree=sh_degree, backend=backend)
    t3 = time.perf_counter()
    proj_ms = sum(v.project_ms for v, _ in parts)
    main = parts[0][1]
    return LodRender(image=image, alpha=alpha, selection=sel_c, n_rendered=int(sel_c.indices.numel()) + n_p,
                     n_frustum=parts[0][0].n_frustum, eta=main.eta, s_v=s_v, level=main.level,
                     project_ms=proj_ms, select_ms=(t2 - t1) * 1e3 - proj_ms, raster_ms=(t3 - t2) * 1e3,
                     meta=meta, n_parents=n_p)


def _render_budget_parts(gaussians: Gaussians, par: TierBudget, t1: float, background, sh_degree, backend):
    """:func:`_render_parts` of a budget past a hand-over (:class:`TierBudget`)."""
    parts = par.parts()
    own = next((sel for d, _, sel in parts if d == 0), None)
    n_p = sum(int(sel.indices.numel()) for d, _, sel in parts if d > 0)
    return _render_parts(gaussians, par.views(), own, n_p, par.s_v, t1, background, sh_degree, backend)


def rasterize_views(parts: Sequence[tuple[LodView, LodSelection]], *, background: Optional[Tensor] = None,
                    sh_degree: Optional[int] = None, backend: Backend = "auto"):
    """Draw the selections of several models seen from one camera (one :class:`LodView` each,
    same camera) as one image, composited together in depth order: ``(image [H, W, D], alpha
    [H, W, 1], meta)``. ``meta["visible_ids"]`` numbers the models' Gaussians one after the other
    (the second model's ids offset by the first's N, ...). Used for a model and its parent tier
    during their cross-fade (:func:`render_lod`). CPU: each view's projection is finished as in
    :meth:`LodView.rasterize` and the rows concatenated; CUDA: gsplat rasterises the
    concatenated drawn attributes."""
    from .render.dispatch import rasterization, resolve_backend

    v0 = parts[0][0]
    w, h = v0.width, v0.height
    sh = sh_degree
    if sh is None and v0.colors.ndim == 3:
        sh = int(math.isqrt(v0.colors.shape[1]) - 1)
    if resolve_backend(backend, v0.means) == "gsplat":
        attrs = [v.drawn_attributes(sel) for v, sel in parts]
        cat = [torch.cat([a[i] for a in attrs]) for i in range(4)]
        op = torch.cat([sel.opacities for _, sel in parts])
        bg = None if background is None else background.reshape(1, -1)
        rc, ra, meta = rasterization(*cat[:3], op, cat[3], v0.viewmat[None], v0.K[None], w, h, sh_degree=sh,
                                     backgrounds=bg, backend="gsplat")
        return rc[0], ra[0], meta
    return _composite(parts, background, sh)


def _composite(parts, background, sh, colors=None):
    """CPU: each (view, selection)'s finished rows (:meth:`LodView._finished`), concatenated (a
    later view's ids offset by the earlier views' N) and composited as one image."""
    from .render.cpu import rasterize_projected

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
    w, h = parts[0][0].width, parts[0][0].height
    bg = None if background is None else background.reshape(-1)
    rc, ra, offsets, flat = rasterize_projected(proj, col, op, w, h, TILE_SIZE, bg)
    meta = {"visible_ids": proj.ids, "radii": proj.radii, "means2d": proj.means2d, "depths": proj.depths,
            "conics": proj.conics, "isect_offsets": offsets, "flatten_ids": flat,
            "n_visible": int(proj.ids.numel()), "width": w, "height": h, "tile_size": TILE_SIZE}
    return rc, ra, meta


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
        n_in_view: Gaussians in view (the population budgets and fractions refer to; on a
            parents-only frame, the parents in view).
        parent_indices: [p] int64 indices into ``Gaussians.parents`` of the parent tier's
            drawn rows, or None (no tier drawn). Where the tier is drawn (:func:`chain_parts`)
            the attribute rows are the model's ``indices`` (opacities times ``1 - u``) followed
            by these parents (opacities times ``u``).
        tier_indices: one entry per parent tier of :func:`tier_chain` (``[0]`` is
            ``parent_indices``): [p_k] int64 indices into tier ``k + 1`` of its drawn rows, or
            None; the attribute rows are the model's, then each drawn tier's, in this order
            (:func:`chain_parts`). Empty for a model without tiers.
    """

    indices: Tensor
    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    s_v: Optional[float]
    n_in_view: int
    parent_indices: Optional[Tensor] = None
    tier_indices: list = field(default_factory=list)


@torch.no_grad()
def lod_subset(gaussians: Gaussians, camera, s_v: Optional[float] = None, *,
               budget: Optional[float | int] = None, tau: Optional[float] = None,
               eps: Optional[float] = None, min_s_v: float = 1.0, budget_cost: Optional[float] = None,
               budget_ms: Optional[float] = None, time_model: Optional[FrameTimeModel] = None) -> LodSubset:
    """The Gaussians :func:`render_lod` hands to the rasteriser for ``camera`` and their drawn
    attributes (same arguments; no gradient). For viewers and exporters that rasterise
    elsewhere. A model with a parent tier, at an ``s_v`` past its ``tier_s_v``: the Gaussians
    and the parents it draws there, concatenated (:class:`LodSubset` ``parent_indices``); at a
    budget past it, the tier it ends in alone (:func:`cost_budget_parents`). No ``s_v`` and no
    budget (``budget``, ``budget_cost``, ``budget_ms``): every Gaussian in view, unchanged.

    Raises:
        ValueError: as :func:`render_lod`.
    """
    if _tree_frame(gaussians, s_v, budget, None, budget_cost, budget_ms):
        c, (means, quats, scales, opacities, colors) = tree_select(gaussians, camera, s_v, budget=budget,
                                                                   budget_cost=budget_cost, budget_ms=budget_ms,
                                                                   time_model=time_model)
        return LodSubset(indices=c.ids[0], means=means, quats=quats, scales=scales, opacities=opacities,
                         colors=colors, s_v=c.s_v, n_in_view=c.n_frustum, parent_indices=c.ids[1],
                         tier_indices=list(c.ids[1:]))
    if tiered(gaussians, s_v):
        parts, sels = chain_parts(float(s_v), *_chain_views(gaussians, camera, tau, eps))
        attrs = [v.drawn_attributes(sel) for v, sel in parts]
        cat = [torch.cat([a[i] for a in attrs]) for i in range(4)]
        idx = sels[0].indices if sels[0] is not None else parts[0][1].indices.new_zeros(0)
        ti = [x.indices if x is not None else None for x in sels[1:]]
        return LodSubset(indices=idx, means=cat[0], quats=cat[1], scales=cat[2],
                         opacities=torch.cat([sel.opacities for _, sel in parts]), colors=cat[3],
                         s_v=float(s_v), n_in_view=parts[0][0].n_in_view, parent_indices=ti[0], tier_indices=ti)
    view = view_lod(gaussians, camera, tau=tau, eps=eps)
    walked, par = _budget_parents_first(gaussians, camera, view, level=None, budget=budget, min_s_v=min_s_v,
                                        budget_in_view=False, budget_cost=budget_cost, budget_ms=budget_ms,
                                        time_model=time_model, tau=tau, eps=eps)
    n_tiers = len(tier_chain(gaussians)) - 1
    if par is not None:  # past a hand-over: a tier alone, or two mixed (count budgets)
        return _tier_subset(par, n_tiers)
    sel = view.select(s_v, budget=budget, min_s_v=min_s_v, estimator="paper", budget_cost=budget_cost,
                      budget_ms=budget_ms, time_model=time_model)
    if not walked:
        par = cost_budget_parents(gaussians, camera, view, sel, budget=budget, budget_cost=budget_cost,
                                  budget_ms=budget_ms, time_model=time_model, tau=tau, eps=eps)
        if par is not None:
            return _tier_subset(par, n_tiers)
    means, quats, scales, colors = view.drawn_attributes(sel)
    return LodSubset(indices=sel.indices, means=means, quats=quats, scales=scales, opacities=sel.opacities,
                     colors=colors, s_v=sel.s_v, n_in_view=view.n_in_view, tier_indices=[None] * n_tiers)


def _tier_subset(par: TierBudget, n_tiers: int) -> LodSubset:
    """:class:`LodSubset` of a budget past a hand-over (:func:`cost_budget_parents`' answer: one
    tier alone, or two mixed), the rows finest first."""
    parts = par.views()
    attrs = [v.drawn_attributes(sel) for v, sel in parts]
    cat = [torch.cat([a[i] for a in attrs]) for i in range(4)]
    own, ti = par.tier_indices(n_tiers)
    return LodSubset(indices=par.sel.indices.new_zeros(0) if own is None else own, means=cat[0], quats=cat[1],
                     scales=cat[2], opacities=torch.cat([sel.opacities for _, sel in parts]), colors=cat[3],
                     s_v=par.s_v, n_in_view=parts[0][0].n_in_view, parent_indices=ti[0], tier_indices=ti)

def _tree_count(budget, n_model: int, n_frustum: int, in_view: bool) -> int:
    """A count budget as a number of Gaussians (``clod_adapter.budget.budget_count``'s reading: an
    int is a count, a float in [0, 1] a share of the model, or of tier 0's frustum with ``in_view``)."""
    from .budget import budget_count, normalize_budget

    b = normalize_budget(budget)
    return budget_count(b, n_frustum if (in_view and isinstance(b, float)) else n_model)


def tree_node_costs(tiers: Sequence[Gaussians], camera, tt) -> list[Tensor]:
    """Per tier [N_k] float64: each node's clipped ellipse pixels at its own attributes
    (``clod_adapter.cost.splat_cost``, the unit of cost budgets; 0 for a node never drawn at
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
    attributes (:func:`clod_adapter.tree.cut_attributes`): ``(cut, (means, quats, scales, opacities, colors))``.
    ``budget``: a count (int) or a share (float in [0, 1]) of the model's Gaussians (of tier 0's
    centres in the frustum with ``budget_in_view``), counted as centres in the frustum;
    ``budget_cost``: pixels of :func:`tree_node_costs` (a float in (0, 1]: that share of tier 0's
    whole cost); ``budget_ms``: predicted ms of ``time_model`` (default
    ``clod_adapter.cost.DEFAULT_FRAME_TIME_MODEL``). Every budget is a cut of the same tree,
    coarser for a smaller budget (:func:`clod_adapter.tree.budget_s_v`).

    Raises:
        ValueError: not exactly one of ``s_v`` and the budgets; ``s_v < 1``.
    """
    c = tree_cut(gaussians, camera, s_v, budget=budget, budget_cost=budget_cost, budget_ms=budget_ms,
                 time_model=time_model, budget_in_view=budget_in_view, hand_over=hand_over)
    return c, tree.cut_attributes(tree.tiers_of(gaussians), c)


@torch.no_grad()
def tree_cut(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget=None, budget_cost=None,
             budget_ms=None, time_model=None, budget_in_view: bool = False,
             hand_over: float = tree.HAND_OVER) -> "tree.TreeCut":
    """The cut of :func:`tree_select` (same arguments and errors), without its attributes."""
    return _tree_cut(gaussians, camera, s_v, budget=budget, budget_cost=budget_cost, budget_ms=budget_ms,
                     time_model=time_model, budget_in_view=budget_in_view, hand_over=hand_over)


def _tree_cut(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget=None, budget_cost=None,
              budget_ms=None, time_model=None, budget_in_view: bool = False, hand_over: float = tree.HAND_OVER,
              whole_as_none: bool = False) -> Optional["tree.TreeCut"]:
    """:func:`tree_cut`; with ``whole_as_none``, None for a count budget that holds every tier-0
    node in the frustum (its level is 1: the caller draws tier 0 whole, no cut gathered)."""
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


def _render_tree(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget=None, budget_cost=None,
                 budget_ms=None, time_model=None, budget_in_view: bool = False, background=None,
                 sh_degree: Optional[int] = None, backend: str = "auto"):
    """:func:`render_lod` of a tree model at ``s_v`` or a budget: one cut (:func:`tree_select`)
    rasterised as one set. Returns its ``LodRender`` (``selection``: tier 0's drawn rows;
    ``n_rendered``: the cut's nodes in view, as the rasteriser culls them; ``n_parents``: the merged
    ones among them; ``level`` 0). ``s_v = 1`` is tier 0 whole, drawn as a plain model (no per-node
    terms), and so is a count budget that holds tier 0's frustum (decided before any cut)."""
    from .render.dispatch import rasterization

    def whole(select_ms: float = 0.0):
        out = render_lod(gaussians.with_sigma_d(None), camera, background=background, sh_degree=sh_degree,
                         backend=backend)
        out.s_v, out.select_ms = 1.0, (out.select_ms or 0.0) + select_ms
        return out

    if s_v is not None and float(s_v) <= 1.0:
        return whole()
    t0 = time.perf_counter()
    c = _tree_cut(gaussians, camera, s_v, budget=budget, budget_cost=budget_cost, budget_ms=budget_ms,
                  time_model=time_model, budget_in_view=budget_in_view, whole_as_none=True)
    if c is None or c.s_v <= 1.0:  # the budget holds tier 0: drawn whole, as s_v = 1 draws it
        return whole((time.perf_counter() - t0) * 1e3)
    means, quats, scales, opacities, colors = tree.cut_attributes(tree.tiers_of(gaussians), c)
    t1 = time.perf_counter()
    bg = None
    if background is not None:
        bg = torch.as_tensor(background, dtype=means.dtype, device=means.device).reshape(1, -1)
    sh = gaussians.sh_degree if sh_degree is None else sh_degree
    vm, K = (m.to(means.device, means.dtype)[None] for m in (camera.viewmat, camera.K))  # CUDA models too
    image, alpha, meta = rasterization(means, quats, scales, opacities, colors, vm, K, int(camera.width),
                                       int(camera.height), eps2d=EPS2D, sh_degree=sh, backgrounds=bg, backend=backend)
    t2 = time.perf_counter()
    n0 = int(c.ids[0].numel())
    n_vis = int(torch.as_tensor(meta.get("n_visible", c.n_drawn)).sum())  # the cut's nodes in view
    vis_ids = meta.get("visible_ids")
    if isinstance(vis_ids, (list, tuple)):
        vis_ids = vis_ids[0]
    n_par = n_vis - int((vis_ids < n0).sum()) if isinstance(vis_ids, torch.Tensor) else c.n_drawn - n0
    eta = torch.tensor(n_vis / max(c.n_frustum, 1), dtype=means.dtype)
    sel = LodSelection(c.ids[0], opacities[:n0], None, c.s_v, 0.0, eta, n=len(gaussians))
    return LodRender(image=image[0], alpha=alpha[0], selection=sel, n_rendered=n_vis, n_frustum=c.n_frustum,
                     eta=eta, s_v=c.s_v, level=0.0, select_ms=(t1 - t0) * 1e3, raster_ms=(t2 - t1) * 1e3,
                     meta=meta, n_parents=n_par)
