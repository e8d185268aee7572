"""Frame cost of a drawn set: per-Gaussian cost units and a frame-time model.

The CPU rasteriser's frame time follows splat-pixel work, not the number of Gaussians: the
compositor (``render/csrc/composite.cpp``) loops over the tiles' sorted Gaussian lists, i.e.
over every (Gaussian, 16x16 tile) intersection that tile binning
(:func:`clod_adapter.render.tiles.isect_tiles`) builds, and within each pair over the pixels of
the Gaussian's ``alpha >= 1/255`` ellipse in that tile (a tile stops early once every pixel's
transmittance is <= 1e-4). Per Gaussian, that work is
best predicted by the **clipped ellipse area** (unit ``"ellipse_px"``, :data:`COST_UNIT`): the
area in pixels of its ``alpha >= 1/255`` ellipse (``pi * 2 ln(255 opacity) * sqrt(det cov2d)``,
extent capped at 3.33 sigma as the radii are) times the share of its box ``mean2d +- radius``
inside the image. ``benchmarks/studies/cost_model.py`` fits the frame time against it, against the
tile-intersection count (``"tiles"``, what the binning emits) and against the clipped box
(``"bbox_px"``); the ellipse had the smallest relative errors (docs/method.md "Budgets:
count, cost, time").

* :func:`splat_cost`: [k] per-Gaussian cost of a :class:`clod_adapter.lod.view.LodView`'s rows,
  from the projection the view already has (no second projection);
* :func:`cost_prefix`: the top-scored Gaussians in view whose cumulative cost fits a budget
  (the static cut behind ``LodView.select(budget=Budget(cost=...))``, usable by baselines);
* :class:`FrameTimeModel`: ``ms = c0 + per_cost * cost_sum + per_gaussian * count``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from . import rule as lod
from ..render.projection import (ALPHA_THRESHOLD, EPS2D, FAR_PLANE, GAUSSIAN_EXTEND, MAX_RADIUS, NEAR_PLANE,
                                 VisibleProjection, finish_projection)
from ..render.tiles import TILE_SIZE, tile_rects

__all__ = ["splat_cost", "cost_units", "cost_prefix", "order_in_view", "prefix_count", "ordered_prefix_count",
           "native_splat_costs", "base_costs", "level_opacities",
           "FrameTimeModel", "DEFAULT_FRAME_TIME_MODEL", "COST_UNIT"]

#: the cost unit of :func:`splat_cost`
COST_UNIT = "ellipse_px"


@torch.no_grad()
def cost_units(proj: VisibleProjection, opacities: Optional[Tensor], width: int, height: int,
               tile_size: int = TILE_SIZE,
               units: tuple[str, ...] = ("tiles", "bbox_px", "ellipse_px")) -> dict[str, Tensor]:
    """Candidate per-Gaussian cost units of a finished projection (V rows, ``proj.ids``).

    Args:
        proj: :func:`clod_adapter.render.projection.finish_projection` output (V rows).
        opacities: [V] the opacities the projection was finished with (the ellipse's extent),
            or None (extent 3.33 sigma).
        width, height, tile_size: image and tile size, pixels.
        units: which of the units below to compute.

    Returns:
        dict of [V] float64: ``"tiles"`` (16x16 tiles the box ``mean2d +- radius`` touches, the
        tile-intersection count of the binning), ``"bbox_px"`` (that box clipped to the image,
        pixels), ``"ellipse_px"`` (the ``alpha >= 1/255`` ellipse's area, pixels, times the
        share of the box inside the image).
    """
    out = {}
    if "tiles" in units:
        tw, th = math.ceil(width / tile_size), math.ceil(height / tile_size)
        x0, y0, x1, y1 = tile_rects(proj.means2d, proj.radii, tile_size, tw, th)
        out["tiles"] = ((x1 - x0) * (y1 - y0)).double()
    if "bbox_px" in units or "ellipse_px" in units:
        m = proj.means2d.detach().double()
        r = proj.radii.double()
        bw = ((m[:, 0] + r[:, 0]).clamp(0, width) - (m[:, 0] - r[:, 0]).clamp(0, width)).clamp_min(0)
        bh = ((m[:, 1] + r[:, 1]).clamp(0, height) - (m[:, 1] - r[:, 1]).clamp(0, height)).clamp_min(0)
        bbox = bw * bh
        if "bbox_px" in units:
            out["bbox_px"] = bbox
    if "ellipse_px" in units:
        a, b, c = proj.conics.detach().double().unbind(-1)
        det_conic = (a * c - b * b).clamp_min(1e-30)
        if opacities is None:
            e2 = torch.full_like(a, GAUSSIAN_EXTEND ** 2)
        else:
            o = opacities.detach().double().clamp_min(ALPHA_THRESHOLD)
            e2 = (2.0 * torch.log(o / ALPHA_THRESHOLD)).clamp(0.0, GAUSSIAN_EXTEND ** 2)
        ell = math.pi * e2 / torch.sqrt(det_conic)
        full = (4.0 * r[:, 0] * r[:, 1]).clamp_min(1.0)
        out["ellipse_px"] = torch.minimum(ell, full) * (bbox / full)
    return out


def level_opacities(view, idx: Tensor, level: float) -> Tensor:
    """[k] activated opacities of the rows ``idx`` [k] (int64) of a LodView at ``level`` in
    [0, 1] (base logits + level x the opacity gain; no LoD fade)."""
    logits = view.opacity_logits.detach().index_select(0, idx)
    g = view.gains.get("opacity_logit_gain")
    if g is not None and level > 0:
        logits = logits + level * g.detach().index_select(0, idx)
    return torch.sigmoid(logits)


@torch.no_grad()
def splat_cost(view, indices: Optional[Tensor] = None, *, level: float = 0.0, opacities: Optional[Tensor] = None,
               unit: str = COST_UNIT) -> Tensor:
    """Per-Gaussian rasterisation cost of drawing ``indices`` from ``view``'s camera.

    Finishes the rows of the projection the :class:`clod_adapter.lod.view.LodView` already has (as
    :meth:`LodView.rasterize` does: the ``eps2d`` blur, the opacity-aware extent, culling), with
    the level's covariance scaling ``exp(2 level log_scale_gain)`` when ``level > 0``.

    Args:
        view: a :class:`clod_adapter.lod.view.LodView`.
        indices: [k] int64 model indices (any order; default: every Gaussian in view, ascending).
        level: level of the gains in [0, 1] (0: base attributes).
        opacities: [k] the opacities drawn (e.g. ``LodSelection.opacities``); default the
            opacities at ``level`` without the LoD fade (``sigmoid(logit + level *
            opacity_logit_gain)``). The fade and Eq. 2's attenuation only lower opacities, and a
            lower opacity never widens the footprint, so the default is an upper bound of the
            drawn cost (equal for Gaussians the fade leaves alone).
        unit: ``"ellipse_px"`` (default, :data:`COST_UNIT`), ``"tiles"`` or ``"bbox_px"``
            (:func:`cost_units`).

    Returns:
        [k] float64 cost in ``unit`` (0 for a Gaussian the projection culls). With
        ``opacities=sel.opacities`` and ``level=sel.level`` it is the cost of what
        :meth:`LodView.rasterize` draws: the ``"tiles"`` cost equals, Gaussian by Gaussian, the
        intersections the rasteriser bins for it (``meta["flatten_ids"]``).
    """
    dev = view.means.device
    idx = torch.nonzero(view.visible, as_tuple=False).squeeze(1) if indices is None else indices.to(dev).long()
    op = level_opacities(view, idx, level) if opacities is None else opacities.detach().to(dev)
    return Footprints(view, idx, level).cost(op, unit)


class Footprints:
    """The opacity-free part of the projection of rows ``idx`` [k] of ``view`` at ``level``
    (its covariance scaling applied), for costing them at many opacities
    (:meth:`cost`; :func:`splat_cost` is ``Footprints(view, idx, level).cost(opacities)``)."""

    @torch.no_grad()
    def __init__(self, view, idx: Tensor, level: float = 0.0):
        dev = view.means.device
        self.k, self.width, self.height = idx.numel(), view.width, view.height
        rows = view.geometry_rows.index_select(0, idx)
        self.pos = torch.nonzero(rows >= 0, as_tuple=False).squeeze(1)  # in front of the camera
        geom = view.geometry.subset(rows.index_select(0, self.pos))
        aa, ab, bb, axb2 = (t.detach() for t in (geom.aa, geom.ab, geom.bb, geom.axb2))
        g = view.gains.get("log_scale_gain")
        if g is not None and level > 0:  # as finish_projection's cov_scale, applied once
            cs = torch.exp(2.0 * level * g.detach().index_select(0, idx.index_select(0, self.pos)))
            aa, ab, bb, axb2 = aa * cs, ab * cs, bb * cs, axb2 * (cs * cs)
        # ids = positions in ``pos``, so the finished projection indexes this object directly
        self.geom = type(geom)(torch.arange(self.pos.numel(), device=dev), geom.means2d.detach(),
                               geom.depths.detach(), aa, ab, bb, axb2)
        # the opacity-free terms of finish_projection and cost_units (same operations, same
        # dtype), so "ellipse_px" costs at new opacities are a few elementwise operations
        c00, c01, c11 = aa + EPS2D, ab, bb + EPS2D
        det = axb2 + EPS2D * (aa + bb) + EPS2D * EPS2D
        self._det_ok = (det > 0) & torch.isfinite(det)
        self._sx, self._sy = torch.sqrt(c00), torch.sqrt(c11)
        inv_det = 1.0 / det
        a, b, c = (c11 * inv_det).double(), (-c01 * inv_det).double(), (c00 * inv_det).double()
        self._sqrt_det_conic = torch.sqrt((a * c - b * b).clamp_min(1e-30))

    @torch.no_grad()
    def cost(self, opacities: Tensor, unit: str = COST_UNIT, first: Optional[int] = None) -> Tensor:
        """[k] float64 cost in ``unit`` of the rows drawn with ``opacities`` [k] (0: culled);
        ``first``: only the first rows ([first] opacities in, [first] costs out)."""
        n = self.k if first is None else int(first)
        out = torch.zeros(n, dtype=torch.float64, device=opacities.device)
        npos = self.pos.numel() if first is None else int(torch.searchsorted(self.pos, torch.tensor([n]))[0])
        if npos == 0:
            return out
        pos = self.pos[:npos]
        if unit == "ellipse_px":
            return out.index_copy_(0, pos, self._ellipse(opacities.index_select(0, pos), npos))
        geom = type(self.geom)(*(t[:npos] for t in self.geom))
        op = opacities.index_select(0, pos).to(self.geom.means2d.dtype)
        proj = finish_projection(geom, op, self.width, self.height, EPS2D)
        u = cost_units(proj, op.index_select(0, proj.ids), self.width, self.height, TILE_SIZE, (unit,))[unit]
        return out.index_copy_(0, pos.index_select(0, proj.ids), u)

    def _ellipse(self, opacities: Tensor, n: int) -> Tensor:
        """[n] ``"ellipse_px"`` of the first ``n`` rows in front of the camera: finish_projection's
        extent, radii and culling, then :func:`cost_units`' formula, without compacting."""
        dt = self.geom.means2d.dtype
        op = opacities.detach().to(dt)
        w, h = self.width, self.height
        sx, sy = self._sx[:n], self._sy[:n]
        mx, my = self.geom.means2d[:n].unbind(-1)
        extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD)).clamp_max(GAUSSIAN_EXTEND)
        rad_x, rad_y = torch.ceil(extend * sx), torch.ceil(extend * sy)
        ok = self._det_ok[:n] & (op >= ALPHA_THRESHOLD) & ~((rad_x <= 0.0) & (rad_y <= 0.0))
        ok &= ~((mx + rad_x <= 0) | (mx - rad_x >= w) | (my + rad_y <= 0) | (my - rad_y >= h))
        rx = rad_x.clamp_max(MAX_RADIUS).to(torch.int32).double()
        ry = rad_y.clamp_max(MAX_RADIUS).to(torch.int32).double()
        mxd, myd = mx.double(), my.double()
        bw = ((mxd + rx).clamp(0, w) - (mxd - rx).clamp(0, w)).clamp_min(0)
        bh = ((myd + ry).clamp(0, h) - (myd - ry).clamp(0, h)).clamp_min(0)
        o = op.double().clamp_min(ALPHA_THRESHOLD)
        e2 = (2.0 * torch.log(o / ALPHA_THRESHOLD)).clamp(0.0, GAUSSIAN_EXTEND ** 2)
        ell = math.pi * e2 / self._sqrt_det_conic[:n]
        full = (4.0 * rx * ry).clamp_min(1.0)
        val = torch.minimum(ell, full) * (bw * bh / full)
        return torch.where(ok, val, torch.zeros_like(val))


def prefix_count(cost_sorted: Tensor, budget: float) -> int:
    """Largest k with ``cost_sorted[:k].sum() <= budget``: ``cost_sorted`` [m] non-negative costs
    in the order to keep them (any unit; float64 cumulative sum), ``budget`` in that unit; 0 for
    a negative budget."""
    if cost_sorted.numel() == 0 or budget < 0:
        return 0
    cum = torch.cumsum(cost_sorted.double(), 0)
    return int(torch.searchsorted(cum, torch.tensor([float(budget)], dtype=torch.float64, device=cum.device),
                                  right=True)[0])


def ordered_prefix_count(scores: Tensor, weights: Tensor, budget: float) -> int:
    """:func:`prefix_count` of ``weights`` [m] (non-negative) taken in the order of ``scores`` [m]
    descending, ties by position, NaN last (the order :func:`order_in_view` gives): the largest k
    whose first k weigh at most ``budget`` (0 for a negative budget). On the CPU, where the kernels
    run, without sorting them all (C++ ``ordered_prefix_count`` in ``render/csrc/splat_cost.cpp``:
    a weighted selection, O(m)); its twin, a stable sort of every score, otherwise. The two sum in
    different orders, so they agree up to rounding (tests/test_cost.py)."""
    from ..render.native import load, wanted

    m = scores.numel()
    if m == 0 or not budget >= 0:
        return 0
    s, w = scores.detach().double(), weights.detach().double()
    if wanted(s.device.type == "cpu"):
        return int(load().ordered_prefix_count(s.contiguous(), w.contiguous(), float(budget)))
    return prefix_count(w.index_select(0, torch.sort(-s, stable=True).indices), budget)


@torch.no_grad()
def native_splat_costs(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor,
                       width: int, height: int) -> Tensor:
    """[N] float64 ``"ellipse_px"`` cost of every Gaussian (``scales`` [N, 3] and ``opacities`` [N]
    activated, ``quats`` [N, 4] wxyz, ``means`` [N, 3] world units) from the camera ``viewmat``
    [4, 4] (world-to-camera) / ``K`` [3, 3] (pixels) / ``width`` x ``height`` pixels, by the C++
    kernel (``render/csrc/splat_cost.cpp``): what :func:`splat_cost` gives at level 0 with these
    opacities, to rounding (gsplat 1.5.3's projection in double, ``eps2d`` 0.3, near plane 0.01;
    ``tests/test_cost.py`` holds the two together).

    Raises:
        RuntimeError: the C++ kernels do not build here (:func:`clod_adapter.render.native.error`)."""
    from ..render.native import load

    if load() is None:
        raise RuntimeError("native_splat_costs: the C++ kernels do not build here")
    dt = means.dtype
    vm = viewmat.detach().to(torch.float64).cpu()
    K = K.detach().to(torch.float64).cpu()
    R, tr = vm[:3, :3].reshape(-1).tolist(), vm[:3, 3].tolist()
    return load().splat_cost(means.detach().contiguous(), quats.detach().to(dt).contiguous(),
                             scales.detach().to(dt).contiguous(), opacities.detach().to(dt).contiguous(), R, tr,
                             float(K[0, 0]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2]), int(width),
                             int(height), NEAR_PLANE, FAR_PLANE, EPS2D)


@torch.no_grad()
def base_costs(view, idx: Tensor) -> Tensor:
    """[k] float64 ``"ellipse_px"`` cost of rows ``idx`` [k] (int64) of ``view`` (a
    :class:`clod_adapter.lod.view.LodView`) at level 0 with the base opacities: one pass of the C++
    kernel over the model (:func:`native_splat_costs`) where the kernels run on the CPU, else
    :func:`splat_cost` (its twin, equal to rounding)."""
    from ..render.native import no_grad_cpu

    if not no_grad_cpu(view.means, view.quats, view.scales, view.opacity_logits):
        return splat_cost(view, idx)
    c = native_splat_costs(view.means, view.quats, view.scales, torch.sigmoid(view.opacity_logits.detach()),
                           view.viewmat, view.K, view.width, view.height)
    return c.index_select(0, idx.to(c.device))


def order_in_view(order_scores: Tensor, visible: Tensor) -> Tensor:
    """[V] int64 model indices of the ``visible`` [N] bool Gaussians by ``order_scores`` [N]
    descending, ties by lower index: the order every budget keeps a prefix of."""
    pool = torch.nonzero(visible, as_tuple=False).squeeze(1)
    order = torch.sort(-order_scores.index_select(0, pool).double(), stable=True).indices
    return pool.index_select(0, order)


def cost_prefix(order_scores: Tensor, cost: Tensor, visible: Tensor, budget_cost: float) -> Tensor:
    """The top-scored Gaussians in view whose cumulative cost fits ``budget_cost``: a static cut
    by cost (as :func:`clod_adapter.lod.rankings.topk_in_view` is by count).

    Args:
        order_scores: [N] scores, higher first (ties broken by lower index), e.g. the critical
            ``s_v`` (:attr:`LodView.critical`) or a baseline's significance.
        cost: [N] (or [V], aligned with ``visible.nonzero()``) non-negative per-Gaussian cost
            (:func:`splat_cost`; any unit, e.g. predicted ms per Gaussian).
        visible: [N] bool, the Gaussians that may be chosen.
        budget_cost: the budget in the unit of ``cost`` (absolute; >= 0).

    Returns:
        [k] int64 model indices, ascending: the longest prefix of the score order whose cost
        sum is <= ``budget_cost`` (so nested and non-decreasing in the budget).
    """
    order = order_in_view(order_scores, visible)
    c = cost if cost.numel() != visible.numel() else cost.index_select(0, order)
    if cost.numel() != visible.numel():  # [V] aligned with visible.nonzero()
        pool = torch.nonzero(visible, as_tuple=False).squeeze(1)
        where = torch.full((visible.numel(),), -1, dtype=torch.long, device=visible.device)
        where[pool] = torch.arange(pool.numel(), device=visible.device)
        c = cost.index_select(0, where.index_select(0, order))
    k = prefix_count(c, float(budget_cost))
    return torch.sort(order[:k]).values


@dataclass(frozen=True)
class FrameTimeModel:
    """Predicted drawing time of a frame: ``ms = c0_ms + per_cost_ms * cost_sum +
    per_gaussian_ms * count``, ``cost_sum`` in :data:`COST_UNIT` (clipped ellipse pixels,
    :func:`splat_cost`) of the drawn set and ``count`` its number of Gaussians.

    The time is that of :meth:`clod_adapter.lod.view.LodView.rasterize` (``LodRender.raster_ms``:
    finishing the projection of the drawn rows, SH colours, tile binning, compositing). The
    view's projection of the whole model (``LodRender.project_ms``) and the selection are paid
    before any budget applies and are not in it.

    Defaults: fitted by ``python -m benchmarks.studies.cost_model`` (fern images_2 and skull, 3 cameras
    each, full models and random / LightGaussian / opacity-ranked subsets of 1.5-100 % of the
    Gaussians in view; 2 threads, minimum of 5 interleaved rounds) on the 2-core development
    machine, shared with other jobs: ``c0_ms = 2.42``, ``per_cost_ms = 5.53e-6`` (per ellipse pixel),
    ``per_gaussian_ms = 9.31e-4``; R^2 0.95 over 96 draws, median relative error 13 % (fern) and
    11 % (skull). Runs while other jobs held one of the cores (wall = CPU time) gave
    ``per_cost_ms`` 7.9e-6 to 1.2e-5: the slope is the machine's and its load's.
    Refit on another machine (or thread count) with that command and pass the printed
    coefficients (``render_lod(..., budget=Budget(ms=..., time_model=FrameTimeModel(...)))``).
    """

    c0_ms: float = 0.0
    per_cost_ms: float = 0.0
    per_gaussian_ms: float = 0.0

    def ms(self, cost_sum: float | Tensor, count: int | Tensor) -> float | Tensor:
        """Predicted ms of drawing ``count`` Gaussians of total cost ``cost_sum``."""
        return self.c0_ms + self.per_cost_ms * cost_sum + self.per_gaussian_ms * count

    def cost_for_ms(self, ms: float, count: int = 0) -> float:
        """The cost (in :data:`COST_UNIT`, pixels) that ``count`` Gaussians may have to be drawn in ``ms``
        (may be negative: not even an empty set fits)."""
        if self.per_cost_ms <= 0:
            return math.inf if self.ms(0.0, count) <= ms else -math.inf
        return (ms - self.c0_ms - self.per_gaussian_ms * count) / self.per_cost_ms

    def per_splat_ms(self, cost: Tensor) -> Tensor:
        """[k] the marginal ms of each Gaussian of cost ``cost`` [k]
        (``per_cost_ms * cost + per_gaussian_ms``)."""
        return self.per_cost_ms * cost.double() + self.per_gaussian_ms


#: :class:`FrameTimeModel` fitted on the development machine (see its docstring)
DEFAULT_FRAME_TIME_MODEL = FrameTimeModel(c0_ms=2.42, per_cost_ms=5.53e-6, per_gaussian_ms=9.31e-4)


# --- a view's cost budgets (LodView.cost_count, full_cost) ----------------------------------------

def view_cost_count(view, budget, *, level: Optional[float] = None) -> int:
    """How many Gaussians a cost budget draws: the longest prefix of the count budgets' order
    (the Gaussians in view by :attr:`LodView.critical` descending, ties by index) whose cost fits.

    Per-Gaussian costs are :func:`clod_adapter.lod.cost.splat_cost` (clipped ellipse pixels) of
    the prefix as :meth:`LodView.select` would draw it with ``budget=k``:

    * Eq. 2 drawing: with the attenuated opacities ``alpha''`` at the ``s_v`` solved for the
      prefix (raised to ``min_s_v``): exact. The cost of a prefix grows with its length
      (longer prefix, smaller ``s_v``, larger ``alpha''``), so the count is searched (regula
      falsi, then bisection) between the prefix at the base opacities (fits) and the prefix
      at the first one's ``s_v`` (bounds it): 10-15 evaluations, 15-30 ms on fern and skull
      against 5 ms for a count budget (2 threads, shared machine);
    * window fade: at the base level (or ``level`` when given): the footprints the calibrated
      schedule measures its levels in (:func:`clod_adapter.train.loop.weighted_count`), one prefix
      search, monotone in the budget. The level gains change what is drawn (survivors grow
      to cover for those that left), so the drawn pixel work of a coarse level is larger
      than its base cost; ``benchmarks/quality_vs_time.py`` times what is drawn. (Costing
      each prefix at its own level has no monotone solution: a shorter prefix sits at a
      coarser level whose grown footprints cost more, and the search settled on a few
      hundred huge splats.)

    Args:
        budget: a :class:`clod_adapter.lod.budget.Budget` of ``cost`` (a float in (0, 1]: that
            share of the cost of drawing every Gaussian in view at full detail, base opacities,
            level 0; > 1: an absolute cost, pixels, :data:`clod_adapter.lod.cost.COST_UNIT`) or of
            ``ms`` (predicted rasterisation ms of its ``time_model`` or the defaults: the longest
            prefix whose predicted ms fits); its ``min_s_v`` is the budget rule of
            :meth:`LodView.select` (Eq. 2: the ``s_v`` floor of the drawing).
        level: the level of the gains to draw at (window fade; None: from the share).

    Returns:
        the count k (0 <= k <= :attr:`LodView.n_in_view`), non-decreasing in the budget.

    Raises:
        ValueError: a count budget.
    """
    if budget.kind not in ("cost", "ms"):
        raise ValueError(f"cost_count: a cost or ms budget, not {budget.kind}")
    budget_ms, min_s_v = budget.ms, budget.min_s_v
    b = float(budget.amount)
    tm = budget.time_model or DEFAULT_FRAME_TIME_MODEL
    order, fp, weights = _view_cost_weights(view, level)
    n_vis = order.numel()
    if n_vis == 0:
        return 0
    eq2 = view.settings.fade == "eq2"
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
        k = _view_eq2_cost_count(view, order, fp, k, limit, unit, min_s_v)
    return k


def _view_cost_weights(view, level: Optional[float] = None):
    """``(order, footprints, costs)`` of the Gaussians in view in the count budgets' order:
    window fade at the base level (or ``level`` given), the unit the calibrated levels are
    measured in; Eq. 2 at the base opacities (:func:`view_cost_count` then searches exactly)."""

    lv = float(level) if (level is not None and view.settings.fade != "eq2") else 0.0
    if view.cost_cache is not None and view.cost_cache[0] == lv:  # a cost budget, then the view's full cost
        return view.cost_cache[1:]
    order = order_in_view(view.critical, view.visible)
    if order.numel() == 0:
        return order, None, view.means.new_zeros(0)
    fp = Footprints(view, order, lv)
    view.cost_cache = (lv, order, fp, fp.cost(level_opacities(view, order, lv)))
    return view.cost_cache[1:]


def view_full_cost(view) -> float:
    """The cost (:func:`clod_adapter.lod.cost.splat_cost`, pixels) of every Gaussian in view at full
    detail: what a ``Budget(cost=...)`` share is a share of."""
    if not view.n_in_view:
        return 0.0
    if view.cost_cache is not None and view.cost_cache[0] == 0.0:  # a cost budget's weights: the same cost
        return float(torch.cumsum(view.cost_cache[3].double(), 0)[-1])
    # order-free: no critical s_v and no sort

    ids = torch.nonzero(view.visible, as_tuple=False).squeeze(1)
    return float(Footprints(view, ids, 0.0).cost(level_opacities(view, ids, 0.0)).double().sum())


def _view_eq2_cost_count(view, order: Tensor, fp, k_lo: int, limit: float, unit, min_s_v: float) -> int:
    """:func:`view_cost_count` for Eq. 2 drawing: the largest k whose prefix of ``order``, drawn with
    ``alpha''`` at its own ``s_v``, costs <= ``limit``; ``k_lo`` fits (base opacities); ``fp``:
    the :class:`clod_adapter.lod.cost.Footprints` of ``order`` at level 0."""

    crit = view.critical.index_select(0, order)  # descending
    m = order.numel()
    op = view.opacities.detach().index_select(0, order)
    d = view.d_norm.detach().index_select(0, order)
    sd = view.sigma_d.detach().index_select(0, order)
    eps = view.settings.eps

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
