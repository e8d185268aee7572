"""What one frame draws, in one call: :func:`render_lod` (an image at ``s_v`` or within a
budget) and :func:`lod_subset` (the Gaussians and opacities it would draw), the entry points every
caller uses (training, evaluation, the renderer hook, export, the viewers).

A plain model is drawn from its :class:`clod_adapter.lod.view.LodView` (the per-camera terms of
CLoD-GS's Eq. 2); a model with merged tiers linked into a merge tree as one cut of the tree
(:mod:`clod_adapter.lod.cut`, :mod:`clod_adapter.lod.tree`). Merged tiers that are not linked into
a tree (``clod_adapter.train.tiers.attach``'s output before :func:`clod_adapter.lod.tree.build`)
are not drawn: such a model is drawn as its own Gaussians.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import torch
from torch import Tensor

from . import tree
from ..lod_settings import EtaGradient
from ..render.dispatch import Backend
from .budget import Budget
from .cut import tree_cut, tree_select
from ..gaussians import Gaussians
from ..render.projection import EPS2D, camera_center
from .view import LodSelection, LodView, view_lod

#: ``eta`` without a gradient (selections for drawing only)
PAPER = EtaGradient("paper")


# --- the one-call forms ---------------------------------------------------------------------------
@dataclass
class LodRender:
    """Result of :func:`render_lod`.

    Attributes:
        image: [H, W, 3] rendered colours (float32, not clamped).
        alpha: [H, W, 1] accumulated opacity.
        mask: [N] bool, Gaussians handed to the rasteriser: in view and passing the LoD mask (or
            the budget selection); built on first use from ``indices`` (a merge tree: tier 0's).
        indices: [n_rendered] int64, the same Gaussians as indices, ascending.
        n_rendered: Gaussians handed to the rasteriser, the render cost (``mask.sum()``; a merge
            tree: the cut's nodes in view, ``n_parents`` of them merged).
        n_frustum: number of Gaussian centres inside the view frustum.
        eta: scalar tensor, rendered fraction of the frustum (gradient per the estimator; 1.0
            without LoD).
        s_v: the virtual distance scale used (the solved one in budget mode; None: no LoD).
        level: level of the gains drawn, in [0, 1].
        project_ms, select_ms, raster_ms: wall time of the projection + in-view test, of the
            LoD selection (frustum, d', Eq. 2 mask or budget solve, drawn opacities), and of the
            rasterisation (finishing the projection of the drawn set, colours, compositing), ms.
        meta: the rasteriser's meta dict (per-Gaussian arrays index ``meta["visible_ids"]``).
        n_parents: a merge tree's merged nodes drawn, those of tiers 1 and above (in
            ``n_rendered``; ``mask`` and ``indices`` are tier 0's own Gaussians); 0 otherwise.
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
    def lead_ms(self) -> float:
        """Wall time before the rasteriser, ms: ``project_ms + select_ms`` (a plain frame projects
        the whole model before selecting; a merge-tree cut projects its nodes inside the
        rasterisation, its ``project_ms`` 0). ``lead_ms + raster_ms`` is the whole frame."""
        return self.project_ms + self.select_ms

    @property
    def indices(self) -> Tensor:
        return self.selection.indices


def render_lod(
    gaussians: Gaussians,
    camera,
    s_v: Optional[float] = None,
    *,
    budget: Optional[Budget] = None,
    tau: Optional[float] = None,
    eps: Optional[float] = None,
    eta_grad: EtaGradient = EtaGradient(),
    background: Optional[Sequence[float] | Tensor] = None,
    sh_degree: Optional[int] = None,
    backend: Backend = "auto",
    level: Optional[float] = None,
    view: Optional[LodView] = None,
) -> LodRender:
    """Render ``gaussians`` from ``camera`` at virtual distance scale ``s_v`` (or a budget).

    The Gaussians in view that pass the mask ``alpha'' > tau s_v`` (CLoD-GS Eq. 2) are handed to
    the rasteriser, drawn as the model's :class:`clod_adapter.lod.rule.LodSettings` say: ``"eq2"`` with
    Eq. 2's ``alpha''`` (the paper), ``"window"`` with the attributes at the level
    (:meth:`Gaussians.at_level`) and only the Gaussians about to leave faded
    (:func:`clod_adapter.lod.rule.fade_weight`). A model without settings is drawn as the paper does.
    A model whose merged tiers form a merge tree (:func:`clod_adapter.lod.tree.is_tree`) draws one
    cut of the tree at an ``s_v`` or within a budget (:func:`_render_tree`); a given ``level``, or
    neither ``s_v`` nor a budget, draws tier 0's own Gaussians. Merged tiers not linked into a
    tree are not drawn (the model's own Gaussians are).

    Args:
        gaussians: the model (N Gaussians). ``sigma_d`` is required when ``s_v`` or ``budget`` is given.
        camera: any object with ``viewmat`` [4, 4] (world-to-camera), ``K`` [3, 3] (pixels),
            ``width``, ``height`` (e.g. :class:`clod_adapter.io.scene.Camera`).
        s_v: virtual distance scale >= 1, or None for the plain model (no LoD, every Gaussian).
        budget: a :class:`clod_adapter.lod.budget.Budget` instead of a given ``s_v``: the ``s_v``
            solved exactly per view (:mod:`clod_adapter.lod.budget`), capped by the Gaussians in
            view, and raised to at least its ``min_s_v`` (default 1, the full-detail level, so a
            budget acts as a cap: a budget that holds every Gaussian in view renders full detail)
            where the level raised to draws no more than the budget (with the window fade, full
            detail draws every Gaussian in view, so a smaller budget draws its ``k`` at the solved
            ``s_v`` below 1); ``min_s_v = 0`` draws exactly the budget whatever ``s_v``. A count
            budget (``count``, ``share`` of the model, ``in_view`` share of the Gaussians in view)
            never draws more than its count. A ``cost`` budget (rasterisation cost instead of a
            count) draws the Gaussians in view with the largest critical ``s_v`` (the count
            budgets' order, so a prefix of it) while their summed
            :func:`clod_adapter.lod.cost.splat_cost` (clipped ellipse pixels) fits; a float in
            (0, 1] is that share of the cost of every Gaussian in view, > 1 an absolute cost
            (:meth:`LodView.cost_count`). An ``ms`` budget (predicted rasterisation ms,
            ``raster_ms``; the projection is not in it): the longest such prefix whose
            :class:`clod_adapter.lod.cost.FrameTimeModel` prediction (its ``time_model``, default
            the fitted one) fits. On a merge tree every budget is a cut of the tree
            (:func:`clod_adapter.lod.cut.tree_cut`).
        tau: LoD threshold (mask ``alpha'' > tau s_v``); default the model's (0.005).
        eps: Eq. 2's epsilon; default the model's (1e-8).
        eta_grad: how ``eta`` carries a gradient (training; :class:`clod_adapter.lod_settings.EtaGradient`).
        background: [3] colour behind the scene (default black, as 3DGS on LLFF).
        sh_degree: SH degree to evaluate (default: the model's).
        backend: rasteriser backend (``"auto"``, ``"cpu"``, ``"gsplat"``).
        level: window fade only: draw the level gains at this level in [0, 1] instead of
            :func:`clod_adapter.lod.rule.level_of_fraction` of the share of the Gaussians in view drawn.
        view: this model's :class:`LodView` for ``camera`` when the caller has built it (its
            projection and critical ``s_v`` are reused); default: built here.

    Returns:
        :class:`LodRender`.

    Raises:
        ValueError: ``s_v`` or a budget given but the model has no ``sigma_d``; ``s_v < 1``;
            both ``s_v`` and ``budget`` given.
        TypeError: a ``budget`` that is not a :class:`clod_adapter.lod.budget.Budget`.
    """
    _check_budget(budget)
    if _tree_frame(gaussians, s_v, budget, level):
        return _render_tree(gaussians, camera, s_v, budget=budget, background=background,
                            sh_degree=sh_degree, backend=backend)
    if view is None:
        view = view_lod(gaussians, camera, tau=tau, eps=eps)
    p0, t1 = view.project_ms, time.perf_counter()
    sel = view.select(s_v, budget=budget, level=level, eta_grad=eta_grad)
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


def _check_budget(budget) -> None:
    if budget is not None and not isinstance(budget, Budget):
        raise TypeError(f"render_lod: budget must be a clod_adapter.Budget (e.g. Budget(in_view=0.3), "
                        f"Budget(count=5000)), got {budget!r}")


def _tree_frame(gaussians: Gaussians, s_v, budget, level) -> bool:
    """Whether a frame of a merge-tree model (:func:`clod_adapter.lod.tree.is_tree`) is one cut of the
    tree: at an ``s_v`` or a budget, no ``level`` given."""
    return tree.is_tree(gaussians) and level is None and (s_v is not None or budget is not None)


def tier_chain(gaussians: Gaussians) -> list[Gaussians]:
    """The model's tiers, finest first: ``[gaussians, gaussians.parents, its parents, ...]``, each
    followed by the next while its ``lod.tier_s_v > 0`` (:func:`clod_adapter.lod.tree.tiers_of`:
    the tiers a merge tree is built from and drawn over; docs/lod_rule.md "The file")."""
    return tree.tiers_of(gaussians)


def tier_reach(gaussians: Gaussians) -> float:
    """How far the model's ``s_v`` reaches into its tiers: the last tier's ``G`` of
    :func:`clod_adapter.lod.tree.tier_scales` (the product over the tiers of :func:`tier_chain`
    but the last of ``tier_fade * tier_s_v / tier_start``; >= 1, 1 without tiers), the factor that
    turns the last tier's own ``s_v`` into the model's, around which a merge tree's last tier
    enters."""
    return max(tree.tier_scales(tier_chain(gaussians))[-1], 1.0)


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
        n_in_view: Gaussians in view (the population budgets and fractions refer to; a merge
            tree's cut: tier 0's centres in the frustum).
        parent_indices: a merge tree's cut: [p] int64 indices into ``Gaussians.parents`` of
            tier 1's drawn rows; None otherwise. The attribute rows are the model's ``indices``
            followed by these, then the next tiers' (:attr:`tier_indices`).
        tier_indices: one entry per parent tier of :func:`tier_chain` (``[0]`` is
            ``parent_indices``): [p_k] int64 indices into tier ``k + 1`` of the cut's drawn rows,
            or None (no cut: neither ``s_v`` nor a budget). Empty for a model without tiers.
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
def lod_subset(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget: Optional[Budget] = None,
               tau: Optional[float] = None, eps: Optional[float] = None) -> LodSubset:
    """The Gaussians :func:`render_lod` hands to the rasteriser for ``camera`` and their drawn
    attributes (same arguments; no gradient). For viewers and exporters that rasterise
    elsewhere. A merge tree at an ``s_v`` or a budget: the cut's nodes of every tier,
    concatenated (:class:`LodSubset` ``tier_indices``). No ``s_v`` and no budget: every Gaussian
    in view, unchanged.

    Raises:
        ValueError, TypeError: as :func:`render_lod`.
    """
    _check_budget(budget)
    if _tree_frame(gaussians, s_v, budget, None):
        c, (means, quats, scales, opacities, colors) = tree_select(gaussians, camera, s_v, budget=budget)
        return LodSubset(indices=c.ids[0], means=means, quats=quats, scales=scales, opacities=opacities,
                         colors=colors, s_v=c.s_v, n_in_view=c.n_frustum, parent_indices=c.ids[1],
                         tier_indices=list(c.ids[1:]))
    view = view_lod(gaussians, camera, tau=tau, eps=eps)
    n_tiers = len(tier_chain(gaussians)) - 1
    sel = view.select(s_v, budget=budget, eta_grad=PAPER)
    means, quats, scales, colors = view.drawn_attributes(sel)
    return LodSubset(indices=sel.indices, means=means, quats=quats, scales=scales, opacities=sel.opacities,
                     colors=colors, s_v=sel.s_v, n_in_view=view.n_in_view, tier_indices=[None] * n_tiers)


def _render_tree(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget: Optional[Budget] = None,
                 background=None, sh_degree: Optional[int] = None, backend: str = "auto"):
    """:func:`render_lod` of a tree model at ``s_v`` or a budget: one cut (:func:`tree_select`)
    rasterised as one set. Returns its ``LodRender`` (``selection``: tier 0's drawn rows;
    ``n_rendered``: the cut's nodes in view, as the rasteriser culls them; ``n_parents``: the merged
    ones among them; ``level`` 0). ``s_v = 1`` is tier 0 whole, drawn as a plain model (no per-node
    terms), and so is a count budget that holds tier 0's frustum (decided before any cut)."""
    from ..render.dispatch import rasterization, resolve_backend
    from ..render.projection import project_visible
    from .view import composite_projected

    def whole(select_ms: float = 0.0):
        out = render_lod(gaussians.with_sigma_d(None), camera, background=background, sh_degree=sh_degree,
                         backend=backend)
        out.s_v, out.select_ms = 1.0, (out.select_ms or 0.0) + select_ms
        return out

    if s_v is not None and float(s_v) <= 1.0:
        return whole()
    t0 = time.perf_counter()
    c = tree_cut(gaussians, camera, s_v, budget=budget, whole_as_none=True)
    if c is None or c.s_v <= 1.0:  # the budget holds tier 0: drawn whole, as s_v = 1 draws it
        return whole((time.perf_counter() - t0) * 1e3)
    sh = gaussians.sh_degree if sh_degree is None else sh_degree
    vm, K = (m.to(gaussians.means.device, gaussians.means.dtype)[None] for m in (camera.viewmat, camera.K))  # CUDA too
    # colours seen from the camera, evaluated in the cut's pass over its rows (the SH not copied)
    means, quats, scales, opacities, colors = tree.cut_attributes(tree.tiers_of(gaussians), c,
                                                                  campos=camera_center(vm[0]), sh_degree=sh)
    t1 = time.perf_counter()
    bg = None if background is None else torch.as_tensor(background, dtype=means.dtype, device=means.device)
    w, h = int(camera.width), int(camera.height)
    if resolve_backend(backend, means) == "gsplat":
        image, alpha, meta = rasterization(means, quats, scales, opacities, colors, vm, K, w, h, eps2d=EPS2D,
                                           backgrounds=None if bg is None else bg.reshape(1, -1), backend="gsplat")
        image, alpha = image[0], alpha[0]
    else:  # as a plain frame draws (LodView.rasterize): the visible rows only, no [N] meta arrays
        proj = project_visible(means, quats, scales, opacities, vm[0], K[0], w, h, EPS2D)
        image, alpha, meta = composite_projected(proj, colors.index_select(0, proj.ids),
                                                 opacities.index_select(0, proj.ids), w, h, bg)
    t2 = time.perf_counter()
    n0 = int(c.ids[0].numel())
    n_vis = int(torch.as_tensor(meta.get("n_visible", c.n_drawn)).sum())  # the cut's nodes in view
    vis_ids = meta.get("visible_ids")
    if isinstance(vis_ids, (list, tuple)):
        vis_ids = vis_ids[0]
    n_par = n_vis - int((vis_ids < n0).sum()) if isinstance(vis_ids, torch.Tensor) else c.n_drawn - n0
    eta = torch.tensor(n_vis / max(c.n_frustum, 1), dtype=means.dtype)
    sel = LodSelection(c.ids[0], opacities[:n0], None, c.s_v, 0.0, eta, n=len(gaussians))
    return LodRender(image=image, alpha=alpha, selection=sel, n_rendered=n_vis, n_frustum=c.n_frustum,
                     eta=eta, s_v=c.s_v, level=0.0, select_ms=(t1 - t0) * 1e3, raster_ms=(t2 - t1) * 1e3,
                     meta=meta, n_parents=n_par)
