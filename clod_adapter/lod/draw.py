"""What one frame draws, in one call: :func:`render_lod` (an image at ``s_v`` or within a
budget) and :func:`lod_subset` (the Gaussians and opacities it would draw), the entry points every
caller uses (training, evaluation, the renderer hook, export, the viewers).

A plain model is drawn from its :class:`clod_adapter.lod.view.LodView` (the per-camera terms of
CLoD-GS's Eq. 2); a model with a merge tree as one cut of the tree
(:mod:`clod_adapter.lod.cut`, :mod:`clod_adapter.lod.tree`); a model whose merged tiers are drawn
as a chain (``--tier-draw chain``) by cross-fading whole tiers (:func:`chain_parts`,
:func:`budget_walk`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Optional, Sequence

import torch
from torch import Tensor

from . import rule as lod
from . import tree
from ..lod_settings import EtaGradient
from ..render.dispatch import Backend
from .budget import Budget
from .cut import tree_cut, tree_select
from ..gaussians import Gaussians
from .view import EPS2D, LodSelection, LodView, composite_parts, view_lod

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
            the fitted one) fits. On a model with a parent tier, a cost budget whose prefix lands
            where the ``s_v`` rule draws the parents alone draws the parents alone within it
            (:func:`cost_budget_parents`); on a merge tree every budget is a cut of the tree
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
    if tiered(gaussians, s_v, level):
        return _render_tiered(gaussians, camera, float(s_v), tau, eps, background,
                              gaussians.sh_degree if sh_degree is None else sh_degree, backend, view)
    if view is None:
        view = view_lod(gaussians, camera, tau=tau, eps=eps)
    p0, t1 = view.project_ms, time.perf_counter()
    walked, par = _budget_parents_first(gaussians, camera, view, level=level, budget=budget, tau=tau, eps=eps)
    if par is None:
        sel = view.select(s_v, budget=budget, level=level, eta_grad=eta_grad)
        if not walked and level is None:
            par = cost_budget_parents(gaussians, camera, view, sel, budget=budget, tau=tau, eps=eps)
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


def _check_budget(budget) -> None:
    if budget is not None and not isinstance(budget, Budget):
        raise TypeError(f"render_lod: budget must be a clod_adapter.Budget (e.g. Budget(in_view=0.3), "
                        f"Budget(count=5000)), got {budget!r}")


def _tree_frame(gaussians: Gaussians, s_v, budget, level) -> bool:
    """Whether a frame of a merge-tree model (:func:`clod_adapter.lod.tree.is_tree`) is one cut of the
    tree: at an ``s_v`` or a budget, no ``level`` given."""
    return tree.is_tree(gaussians) and level is None and (s_v is not None or budget is not None)


def tiered(gaussians: Gaussians, s_v: Optional[float], level: Optional[float] = None) -> bool:
    """Whether ``render_lod(gaussians, ..., s_v)`` draws the model's parent tier: an ``s_v``
    given (no budget, no ``level``) past the model's ``tier_s_v`` (:func:`clod_adapter.lod.rule.tier_weight`)."""
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
    hand-over; :func:`clod_adapter.lod.rule.tier_weight`)."""
    r = 1.0
    for m in tier_chain(gaussians)[:-1]:
        r *= m.lod.tier_fade * m.lod.tier_s_v / m.lod.tier_start
    return max(r, 1.0)


def chain_parts(s_v: float, settings: Sequence[lod.LodSettings], view_of: Callable[[int], LodView]):
    """What a model with a chain of tiers draws at ``s_v`` (docs/lod_rule.md "The tiers"):
    ``(parts, sels)``, ``parts`` the ``(view, selection)`` pairs for :func:`rasterize_views`
    (finest tier first), ``sels[k]`` tier ``k``'s selection or None where it is not drawn.

    ``settings[k]`` are tier ``k``'s :class:`clod_adapter.lod.rule.LodSettings` (its ``tier_s_v`` hands
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


def cost_budget_parents(gaussians: Gaussians, camera, view: LodView, sel: Optional[LodSelection], *,
                        budget: Optional[Budget] = None, tau=None, eps=None, count: Optional[int] = None):
    """A budget on a model with tiers (:func:`budget_walk` with the model's :func:`tier_chain`):
    a :class:`TierBudget` (the tier drawn, its selection, the model's ``s_v`` it stands for, its
    depth >= 1), else None (the model's own
    selection ``sel`` of ``view`` stands; ``sel`` may be None as :func:`budget_walk` allows,
    ``count`` the count budget's count in ``view``)."""
    models = tier_chain(gaussians)
    if len(models) < 2:
        return None
    return budget_walk([m.lod for m in models], lambda k: view_lod(models[k], camera, tau=tau, eps=eps), view, sel,
                       budget=budget, count=count)


def _budget_parents_first(gaussians: Gaussians, camera, view: LodView, *, level, budget: Optional[Budget], tau,
                          eps) -> tuple[bool, Optional[tuple]]:
    """A budget on a tiered model walked before the model's own selection is solved (which it
    then never needs where a tier takes the budget over): ``(walked, cost_budget_parents' answer)``;
    ``walked`` False where the walk needs that selection first (a count budget whose count the
    rule does not give, :meth:`LodView.budget_drawn`; a share of the Gaussians in view)."""
    models = tier_chain(gaussians)
    if level is not None or budget is None or len(models) < 2:
        return False, None
    count = None
    if budget.counts:
        if budget.kind == "in_view":
            return False, None
        # tier 1 cannot take a count over its size: the budget is then solved in this view
        count = view.budget_drawn(budget, solving=_taken_at(view.count_of(budget)) > len(models[1]))
        if count is None:
            return False, None
    return True, cost_budget_parents(gaussians, camera, view, None, budget=budget, tau=tau, eps=eps, count=count)


def budget_walk(settings: Sequence[lod.LodSettings], view_of: Callable[[int], LodView], view: LodView,
                sel: Optional[LodSelection] = None, *, budget: Optional[Budget] = None, depth: int = 0,
                count: Optional[int] = None):
    """A budget down a chain of tiers (docs/lod_rule.md "The tiers"; ``settings[k]`` tier ``k``'s,
    ``view_of(k)`` its :class:`LodView` of the camera, ``sel`` tier ``depth``'s own solution of the
    budget in ``view``). The next tier takes the budget when it can fill it from where the
    ``s_v`` rule first draws it alone (its ``tier_start`` level, selection ``start``): a count
    budget of ``k`` (the count ``sel`` drew) when ``start`` draws at least :data:`COUNT_TAKE_SHARE`
    of ``k`` (it is then asked for ``k`` and may draw fewer), a cost budget
    when ``start`` costs at least the budget (a ``cost`` share is taken of the first view's
    full cost), an ``ms`` budget when ``start`` is predicted to take at least that
    long (``time_model``, default the fitted one). A ``start`` at the tier's full detail
    (``tier_start <= 1``, as ``clod-adapt`` links tiers) and the first view's full cost are
    estimated from a sample, the widest Gaussians and every :data:`clod_adapter.lod.cost.COST_SAMPLE_STEP`-th of the rest
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

    if budget is None:
        return None
    if sel is not None and sel.s_v is None:
        return None
    view_of = _memo(view_of)
    budget_cost, budget_ms, time_model = budget.cost, budget.ms, budget.time_model
    k = None
    if budget.counts:
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
                drawn = vn.budget_drawn(Budget(count=k0, min_s_v=st.tier_start), solving=solving)
                if drawn is None:  # not given by the rule: solve it
                    sel_n = vn.select(budget=Budget(count=k0, min_s_v=st.tier_start))
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
            sel_p = vp.select(budget=budget.floored(start))
        elif b is not None:
            sel_p = vp.select(budget=Budget(cost=b, min_s_v=start))
        else:
            sel_p = vp.select(budget=Budget(count=k, min_s_v=start))
    s_equiv = sel_p.s_v
    for f in reversed(scales):  # from the deepest tier up, as each hand-over maps it
        s_equiv = s_equiv * f
    return TierBudget(vp, sel_p, s_equiv, d)


def count_budget_walk(settings: Sequence[lod.LodSettings], view_of: Callable[[int], LodView], view: LodView,
                      budget: Budget) -> tuple[Optional[LodSelection], Optional[TierBudget]]:
    """A count ``budget`` (``count`` or ``share``) on tier 0's ``view`` of a chain of tiers:
    ``(tier 0's own selection or None, budget_walk's answer or None)``, exactly one of them set.
    The walk goes first where the rule gives tier 0's count (:meth:`LodView.budget_drawn`), so
    tier 0's selection is solved only where the budget stays in it (the renderer hook's and
    bake's path; :func:`render_lod` does the same).

    Raises:
        ValueError: as :meth:`LodView.select` (a negative budget; no ``sigma_d``).
    """
    view_of = _memo(view_of)
    solving = len(settings) < 2 or not _may_take(settings, view_of, 0, view.count_of(budget))
    count = view.budget_drawn(budget, solving=solving) if len(settings) > 1 else None
    sel = None if count is not None else view.select(budget=budget, eta_grad=PAPER)
    par = budget_walk(settings, view_of, view, sel, budget=budget, count=count) if len(settings) > 1 else None
    if par is None and sel is None:
        sel = view.select(budget=budget, eta_grad=PAPER)
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
#: budget); chosen on the validation views, docs/archive/studies_chain.md "Count budgets across tiers"
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
    from ..render.dispatch import rasterization, resolve_backend

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
    return composite_parts(parts, background, sh)


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
def lod_subset(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget: Optional[Budget] = None,
               tau: Optional[float] = None, eps: Optional[float] = None) -> LodSubset:
    """The Gaussians :func:`render_lod` hands to the rasteriser for ``camera`` and their drawn
    attributes (same arguments; no gradient). For viewers and exporters that rasterise
    elsewhere. A model with a parent tier, at an ``s_v`` past its ``tier_s_v``: the Gaussians
    and the parents it draws there, concatenated (:class:`LodSubset` ``parent_indices``); at a
    budget past it, the tier it ends in alone (:func:`cost_budget_parents`). No ``s_v`` and no
    budget: every Gaussian in view, unchanged.

    Raises:
        ValueError, TypeError: as :func:`render_lod`.
    """
    _check_budget(budget)
    if _tree_frame(gaussians, s_v, budget, None):
        c, (means, quats, scales, opacities, colors) = tree_select(gaussians, camera, s_v, budget=budget)
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
    walked, par = _budget_parents_first(gaussians, camera, view, level=None, budget=budget, tau=tau, eps=eps)
    n_tiers = len(tier_chain(gaussians)) - 1
    if par is not None:  # past a hand-over: a tier alone, or two mixed (count budgets)
        return _tier_subset(par, n_tiers)
    sel = view.select(s_v, budget=budget, eta_grad=PAPER)
    if not walked:
        par = cost_budget_parents(gaussians, camera, view, sel, budget=budget, tau=tau, eps=eps)
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


def _render_tree(gaussians: Gaussians, camera, s_v: Optional[float] = None, *, budget: Optional[Budget] = None,
                 background=None, sh_degree: Optional[int] = None, backend: str = "auto"):
    """:func:`render_lod` of a tree model at ``s_v`` or a budget: one cut (:func:`tree_select`)
    rasterised as one set. Returns its ``LodRender`` (``selection``: tier 0's drawn rows;
    ``n_rendered``: the cut's nodes in view, as the rasteriser culls them; ``n_parents``: the merged
    ones among them; ``level`` 0). ``s_v = 1`` is tier 0 whole, drawn as a plain model (no per-node
    terms), and so is a count budget that holds tier 0's frustum (decided before any cut)."""
    from ..render.dispatch import rasterization

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
