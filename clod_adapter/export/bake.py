"""Export an adapted CLoD-GS model for renderers that know nothing of ``sigma_d``.

* :func:`persistence` / :func:`importance_order`: one global order in which every prefix is a
  level of detail (for prefix / budget renderers).
* :func:`bake`: the Gaussians one setting (``s_v`` or a budget) renders from a camera set, as a
  standard INRIA model (no decay).
* :func:`lod_set_s_vs` / :func:`lod_level`: the levels of a discrete LoD set (the web engines'
  streamed LoD files), each a view-independent cut of the model.
* :func:`prune_never_rendered`: drop Gaussians no training view renders at any ``s_v >= 1``.
* :func:`reduce_sh`: drop SH bands whose removal costs less than a set PSNR on training views.

Persistence (the choice made here). A Gaussian is rendered from a view iff it is in view
(:func:`clod_adapter.lod.view.in_view`) and ``s_v < s*`` (:func:`clod_adapter.lod.budget.critical_s_v`,
which folds opacity, ``sigma_d`` and the view's normalised distance into one number). Its
persistence is the largest ``s*`` over the views that see it, i.e. the coarsest level at which
*some* view still draws it; 0 for a Gaussian no view sees. The maximum (not the mean) is used so
that a Gaussian that matters from one view is not ranked below one that is weak everywhere.
Ties (e.g. the zeros) are broken by opacity, then index.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional, Sequence

import torch
from torch import Tensor

from ..lod import rule as lod
from ..gaussians import Gaussians, concat
from ..metrics import psnr
from ..lod.budget import Budget
from ..lod.draw import PAPER, render_lod, tier_chain
from ..lod.view import view_lod
from ..lod.cut import tree_select
from ..lod.tree import EXIT_KEY, in_frustum, is_tree, leads, tiers_of

__all__ = ["persistence", "importance_order", "bake", "lod_set_s_vs", "lod_level", "prune_never_rendered",
           "reduce_sh", "truncate_sh", "BakeInfo"]


def _require_sigma(g: Gaussians, what: str) -> None:
    if g.sigma_d is None:
        raise ValueError(f"{what}: the model has no sigma_d (not an adapted model)")


@torch.no_grad()
def persistence(gaussians: Gaussians, cameras: Sequence, *, tau: Optional[float] = None,
                eps: Optional[float] = None) -> Tensor:
    """[N] float64 persistence: max over ``cameras`` that see a Gaussian of its critical scale
    ``s*`` (rendered from that view iff ``s_v < s*``); 0 when no camera sees it.

    Raises:
        ValueError: the model has no ``sigma_d``.
    """
    _require_sigma(gaussians, "persistence")
    p = torch.zeros(len(gaussians), dtype=torch.float64, device=gaussians.means.device)
    for cam in cameras:
        v = view_lod(gaussians, cam, tau=tau, eps=eps)
        p = torch.maximum(p, torch.where(v.visible, v.critical, torch.zeros_like(v.critical)))
    return p


@torch.no_grad()
def importance_order(gaussians: Gaussians, cameras: Sequence, *, tau: Optional[float] = None,
                     eps: Optional[float] = None, persist: Optional[Tensor] = None) -> Tensor:
    """[N] int64 permutation: descending :func:`persistence`, ties by descending opacity, then
    ascending index. ``gaussians.subset(perm)[:k]`` is the k-Gaussian level of detail."""
    p = persistence(gaussians, cameras, tau=tau, eps=eps) if persist is None else persist
    n = len(gaussians)
    idx = torch.arange(n, device=p.device)
    # lexicographic sort by stable sorts, least significant key first
    order = idx
    op = gaussians.opacities.detach().to(p.device).double()
    order = order[torch.sort(-op[order], stable=True).indices]
    order = order[torch.sort(-p[order], stable=True).indices]
    return order


@dataclass
class BakeInfo:
    """How :func:`bake` chose the opacities: PSNR (dB) of each candidate against ``render_lod``
    at the setting, mean over the cameras; ``chosen`` is ``"original"`` or ``"mean"``."""

    chosen: str
    psnr_vs_lod: dict = field(default_factory=dict)
    n_kept: int = 0
    per_view_rendered: float = 0.0
    n_parents: int = 0


def _logit(a: Tensor) -> Tensor:
    a = a.clamp(1e-7, 1 - 1e-7)
    return torch.log(a) - torch.log1p(-a)


@torch.no_grad()
def bake(gaussians: Gaussians, cameras: Sequence, s_v: Optional[float] = None, budget: Optional[Budget] = None, *,
         opacity: str = "auto", tau: Optional[float] = None, eps: Optional[float] = None,
         background=None, backend: str = "auto", return_info: bool = False):
    """A standard model (``sigma_d = None``) of the Gaussians one setting renders.

    The kept set is the union over ``cameras`` of what :func:`render_lod` draws at ``s_v`` (or,
    with ``budget``, a count :class:`clod_adapter.lod.budget.Budget`, at each view's solved ``s_v``,
    never below 1): a superset of each view's
    selection, so its count can exceed a budget. Scales and colours are the model's at the mean
    level the views draw (level gains, :meth:`Gaussians.at_level`). A standard file has no decay,
    so opacities are:

    * ``"original"``: each kept Gaussian's opacity at that level, unfaded;
    * ``"mean"``: the mean over the views that keep it of the opacity :func:`render_lod` draws it
      with (Eq. 2's ``alpha''``, or the window-faded opacity at the level);
    * ``"auto"`` (default): both are rendered from ``cameras`` and the one closer (PSNR) to
      ``render_lod`` at the setting is kept (:class:`BakeInfo` records the choice and both PSNRs).

    A merge tree: each tier's nodes of the cut a view draws, finest tier first, at their own
    attributes ("original") or their mean drawn opacity ("mean"; a node in a hand-over is baked as
    itself, not on its way to its parent; ``BakeInfo.n_parents`` counts the merged tiers' rows).
    Merged tiers not linked into a tree are not drawn, so not baked.

    Returns:
        The baked ``Gaussians``, or ``(Gaussians, BakeInfo)`` with ``return_info``.
    """
    _require_sigma(gaussians, "bake")
    if opacity not in ("auto", "original", "mean"):
        raise ValueError(f"bake: opacity must be auto, original or mean, got {opacity!r}")
    if (s_v is None) == (budget is None):
        raise ValueError("bake: give exactly one of s_v and budget")
    tree = is_tree(gaussians)
    members = tiers_of(gaussians) if tree else [gaussians]
    acc = [_Drawn.of(m) for m in members]
    settings, rendered = [], []
    for cam in cameras:
        if tree:  # one cut of the merge tree: each tier's drawn rows
            sels, s_used = _tree_sels(gaussians, cam, s_v, budget)
        else:
            sel = view_lod(gaussians, cam, tau=tau, eps=eps).select(s_v, budget=budget, eta_grad=PAPER)
            sels, s_used = [sel], sel.s_v
        settings.append(s_used)
        for a, sel in zip(acc, sels):
            a.add(sel)
        rendered.append(sum(int(sel.indices.numel()) for sel in sels))
    cands = {"original": [], "mean": []}
    for m, a in zip(members, acc):
        at = m.at_level(sum(a.levels) / max(len(a.levels), 1))
        orig = at.opacity_logits.detach().clone()
        mean_drawn = (a.drawn_sum / a.cnt.clamp_min(1)).to(at.opacity_logits.dtype)
        for name, logits in (("original", orig), ("mean", _logit(mean_drawn))):
            cands[name].append(replace(at, opacity_logits=logits).with_sigma_d(None).subset(a.indices))
    cands = {k: concat(v) for k, v in cands.items()}
    names = list(cands) if opacity == "auto" else [opacity]
    scores = {}
    if opacity == "auto" or return_info:
        refs = [render_lod(gaussians, cam, s, tau=tau, eps=eps, background=background, backend=backend,
                           eta_grad=PAPER).image for cam, s in zip(cameras, settings)]
        for name, g in cands.items():
            if opacity != "auto" and name != opacity:
                continue
            ps = [psnr(render_lod(g, cam, background=background, backend=backend).image,
                       ref.clamp(0, 1), cap=True) for cam, ref in zip(cameras, refs)]
            scores[name] = sum(ps) / max(len(ps), 1)
        if opacity == "auto":
            names = [max(scores, key=lambda k: (scores[k], k == "original"))]
    chosen = names[0]
    out = cands[chosen].clone()
    if return_info:
        return out, BakeInfo(chosen=chosen, psnr_vs_lod=scores, n_kept=len(out),
                             per_view_rendered=sum(rendered) / max(len(rendered), 1),
                             n_parents=sum(int(a.indices.numel()) for a in acc[1:]))
    return out


def _tree_sels(gaussians: Gaussians, cam, s_v, budget) -> tuple[list, float]:
    """What one camera draws of a merge tree (:func:`clod_adapter.lod.cut.tree_select`) as one
    selection-like record per tier (``indices``, drawn ``opacities``, ``level`` 0), and the level."""
    from types import SimpleNamespace

    c, attrs = tree_select(gaussians, cam, s_v, budget=budget)
    ops, sels, at = attrs[3], [], 0
    for ids in c.ids:
        sels.append(SimpleNamespace(indices=ids, opacities=ops[at:at + ids.numel()], level=0.0))
        at += ids.numel()
    return sels, c.s_v


@dataclass
class _Drawn:
    """What :func:`bake`'s cameras draw of one model: which rows, their summed drawn opacities,
    how many views draw each, and each view's level."""

    keep: Tensor
    drawn_sum: Tensor
    cnt: Tensor
    levels: list

    @classmethod
    def of(cls, g: Gaussians) -> "_Drawn":
        n, dev = len(g), g.means.device
        return cls(torch.zeros(n, dtype=torch.bool, device=dev), torch.zeros(n, dtype=torch.float64, device=dev),
                   torch.zeros(n, dtype=torch.float64, device=dev), [])

    def add(self, sel) -> None:
        self.keep[sel.indices] = True
        self.drawn_sum[sel.indices] += sel.opacities.double()
        self.cnt[sel.indices] += 1.0
        self.levels.append(sel.level)

    @property
    def indices(self) -> Tensor:
        return torch.nonzero(self.keep, as_tuple=False).squeeze(1)


@torch.no_grad()
def lod_set_s_vs(max_sv: float) -> list[float]:
    """The ``s_v`` of a discrete LoD set's levels, finest first: 1, then each ``s_v`` whose target
    share of the Gaussians in view, ``s_v^-1.5`` (:func:`clod_adapter.lod.rule.target_fraction`),
    is half the previous level's: ``2^(2k/3)`` = 1, 1.59, 2.52, 4, 6.35, ... up to ``max_sv``
    (the trained range; 4 levels for the default 5). ``max_sv < 1.59`` gives ``[1.0]``."""
    out, k = [], 0
    while 2.0 ** (2.0 * k / 3.0) <= float(max_sv) * (1.0 + 1e-9):
        out.append(round(2.0 ** (2.0 * k / 3.0), 4))
        k += 1
    return out or [1.0]


#: how a merge tree's LoD set is cut (:func:`lod_set_levels`)
TREE_LEVELS = ("tiers", "cut")


@torch.no_grad()
def lod_set_levels(gaussians: Gaussians, cameras: Sequence, *,
                   tree_levels: str = "cut") -> list[tuple[Gaussians, Optional[float]]]:
    """The levels of ``clod-export --lod-meta``'s streamed LoD set, finest first: ``[(level, s_v)]``,
    each level a plain model (``sigma_d`` dropped). A merge tree
    (:func:`clod_adapter.lod.tree.is_tree`), ``tree_levels``:

    * ``"cut"`` (default): tier 0 whole, then per merged tier the tree's view-independent cut with
      as many nodes: every node at its reference ``d'`` (``extra["d_ref"]``, as a count budget
      draws it: :func:`clod_adapter.lod.tree.budget_frame`), the level :func:`clod_adapter.lod.tree.budget_s_v` solves for that
      count, each drawn node at its own attributes (``s_v`` that level). An engine that streams
      the set picks a level per chunk by distance itself; each level is the tree's own stand-in
      for the scene at its usual distances (``benchmarks/studies/lod_set.py``, validation views:
      ahead of its tiers whole at 5 of 6 levels of fern and skull);
    * ``"tiers"``: its tiers (:func:`clod_adapter.lod.draw.tier_chain`), each whole (``s_v`` None).

    Otherwise the model's own Gaussians cut at each of :func:`lod_set_s_vs` of its ``max_sv`` by
    :func:`lod_level` (reference distances over ``cameras``, the training views).

    Raises:
        ValueError: a model without a tree and without ``sigma_d``; ``tree_levels`` not one of
        :data:`TREE_LEVELS`."""
    from ..lod import tree as tr
    from ..train.loop import reference_distances

    if tree_levels not in TREE_LEVELS:
        raise ValueError(f"lod_set_levels: tree_levels must be one of {', '.join(TREE_LEVELS)}, got {tree_levels!r}")
    if is_tree(gaussians):
        ts = tier_chain(gaussians)
        if tree_levels == "tiers":
            return [(t.with_sigma_d(None), None) for t in ts]
        ds = [t.extra[tr.REFERENCE_KEY].to(t.means.dtype) for t in ts]
        tt = tr.terms(ts, None, at=(ds, [torch.ones(len(t), dtype=torch.bool, device=t.means.device) for t in ts]))
        out = [(ts[0].with_sigma_d(None), 1.0)]
        for t in ts[1:]:
            c = tr.cut(ts, None, tr.budget_s_v(tt, float(len(t))), tt=tt)
            out.append((concat([m.with_sigma_d(None).subset(i) for m, i in zip(ts, c.ids) if i.numel()]), c.s_v))
        return out
    own = replace(gaussians, parents=None)
    _require_sigma(own, "lod_set_levels")
    d_ref = reference_distances(own, cameras)
    s_vs = lod_set_s_vs(own.lod.max_sv if own.lod is not None else 5.0)
    return [(lod_level(own, cameras, s, d_ref=d_ref), s) for s in s_vs]


@torch.no_grad()
def lod_level(gaussians: Gaussians, cameras: Sequence, s_v: float, *, d_ref: Optional[Tensor] = None) -> Gaussians:
    """One level of a discrete LoD set: a standard model (``sigma_d = None``) of the Gaussians
    whose critical ``s_v`` (:func:`clod_adapter.lod.budget.critical_s_v`) at their reference distance
    (:func:`clod_adapter.train.loop.reference_distances` over ``cameras``: the mean ``d'`` over the
    views that see them) exceeds ``s_v``, with the attributes at ``s_v``'s level coordinate
    (:func:`clod_adapter.lod.rule.level`: the level gains) and their own opacity. ``s_v <= 1``: the
    whole model at its base attributes (full detail).

    View-independent, unlike :func:`bake` (the union of what each view draws): an engine that
    streams a LoD set picks a level per chunk by distance itself, and on a 360-degree capture the
    union over the training views keeps nearly everything (``benchmarks/studies/lod_set_cuts.py``, skull's
    validation views: more rows than tier 0 at ``s_v`` = 1.59 / 2.52 / 4, 2.9-5.1 dB below the
    decimator at equal count; this cut: 47 / 18 / 6 %, +0.07 / -0.28 / -0.11 dB; fern: the union
    +0.8 to +2.8 dB, this cut +2.9 to +3.4).

    Args:
        gaussians: adapted model (``sigma_d`` required).
        cameras: the views the reference distances come from (the training views).
        s_v: the level's virtual distance scale (>= 1).
        d_ref: [N] reference distances when already computed (default: from ``cameras``).

    Returns:
        the level: ``Gaussians`` with ``sigma_d``, gains and settings dropped (a plain model of
        the kept rows, in the model's order; float32 like the input).

    Raises:
        ValueError: the model has no ``sigma_d``.
    """
    from ..lod.budget import critical_s_v
    from ..train.loop import reference_distances

    _require_sigma(gaussians, "lod_level")
    if s_v <= 1.0:
        return gaussians.with_sigma_d(None).clone()
    st = gaussians.lod or lod.LodSettings()
    d = reference_distances(gaussians, cameras) if d_ref is None else d_ref
    keep = torch.nonzero(critical_s_v(gaussians.opacities, d, gaussians.sigma_d, st.tau, st.eps) > s_v,
                         as_tuple=False).squeeze(1)
    return gaussians.at_level(lod.level(s_v, st.max_sv, st.level_max)).with_sigma_d(None).subset(keep).clone()


def prune_never_rendered(gaussians: Gaussians, cameras: Sequence, *,
                         anchor_cameras: Optional[Sequence] = None, tau: Optional[float] = None,
                         eps: Optional[float] = None) -> tuple[Gaussians, int]:
    """Drop the Gaussians that no camera in ``cameras`` renders at any ``s_v >= 1``.

    A merge tree (:func:`clod_adapter.lod.tree.is_tree`) loses only tier-0 rows that are outside
    every camera's frustum (their centre) and not visible from any (gsplat 1.5.3 culling), and are
    not their parent's lead child (:func:`clod_adapter.lod.tree.leads`, the one that grows into
    the parent; written with its mark, an exit of +inf): every cut, count and hand-over on
    ``cameras`` is then the same; the merged tiers and the parent links are kept.

    The rendered set shrinks as ``s_v`` grows, so "rendered at some s_v >= 1" is "rendered at
    s_v = 1": in view and ``s* > 1``. One exception keeps LoD unchanged: ``d'`` is normalised by
    the farthest Gaussian inside each view's frustum, so for every camera of ``anchor_cameras``
    (default ``cameras``) that farthest Gaussian is kept too (at most one per camera); every
    other Gaussian's ``d'``, hence every LoD decision on those cameras, is then exactly the same.

    Returns:
        (pruned model, number dropped).
    """
    _require_sigma(gaussians, "prune_never_rendered")
    if is_tree(gaussians):
        return _prune_tree_leaves(gaussians, cameras, tau=tau, eps=eps)
    keep = torch.zeros(len(gaussians), dtype=torch.bool, device=gaussians.means.device)
    for cam in cameras:
        v = view_lod(gaussians, cam, tau=tau, eps=eps)
        keep |= v.visible & (v.critical > 1.0)
    for cam in (cameras if anchor_cameras is None else anchor_cameras):
        viewmat = cam.viewmat.to(gaussians.means.device, gaussians.means.dtype)
        fr = lod.in_frustum(gaussians.means, viewmat, cam.K.to(viewmat), int(cam.width), int(cam.height))
        if bool(fr.any()):
            d = torch.linalg.vector_norm(gaussians.means - lod.camera_center(viewmat), dim=-1)
            d = torch.where(fr, d, torch.full_like(d, -1.0))
            keep[int(torch.argmax(d))] = True
    n_drop = int((~keep).sum())
    return gaussians.subset(keep).clone(), n_drop


def _prune_tree_leaves(gaussians: Gaussians, cameras: Sequence, *, tau, eps) -> tuple[Gaussians, int]:
    """:func:`prune_never_rendered` of a merge tree: its tier 0's rows out of every view dropped
    but each parent's lead (its parent grows out of it); the tiers above kept with their links."""
    seen = torch.zeros(len(gaussians), dtype=torch.bool, device=gaussians.means.device)
    for cam in cameras:
        seen |= view_lod(gaussians, cam, tau=tau, eps=eps).visible | in_frustum(gaussians, cam)
    lead = leads(gaussians)
    keep = lead | seen
    marked = torch.where(lead, torch.full_like(gaussians.extra[EXIT_KEY], float("inf")), gaussians.extra[EXIT_KEY])
    gaussians = replace(gaussians, extra={**gaussians.extra, EXIT_KEY: marked})
    return replace(gaussians.subset(keep).clone(), parents=gaussians.parents), int((~keep).sum())


def truncate_sh(gaussians: Gaussians, degree: int) -> Gaussians:
    """The model with SH bands above ``degree`` removed (``degree`` <= the model's)."""
    if not 0 <= degree <= gaussians.sh_degree:
        raise ValueError(f"truncate_sh: degree must be 0..{gaussians.sh_degree}, got {degree}")
    return replace(gaussians, shN=gaussians.shN[:, : (degree + 1) ** 2 - 1].contiguous())


@torch.no_grad()
def reduce_sh(gaussians: Gaussians, cameras: Sequence, images: Sequence[Tensor],
              max_drop_db: float = 0.05, *, s_v: Optional[float] = 1.0, background=None,
              backend: str = "auto") -> tuple[Gaussians, dict]:
    """Lower the SH degree as far as the PSNR on ``cameras`` allows.

    Every degree below the model's is tried (3, 2, 1, 0); the lowest whose PSNR drop against the
    full model (rendered at ``s_v``, None: no LoD; PSNR against ``images``, capped at 100 dB) is
    ``<= max_drop_db`` is kept (the model's own degree when none passes).

    Returns:
        (model, info): info = {"degree_in", "degree_out", "max_drop_db", "psnr_full",
        "per_degree": [{"degree", "psnr", "drop_db", "bytes_saved"}], "bytes_saved"}; bytes are
        those of the .ply (4 bytes x 3 channels x coefficients removed x N).
    """
    if s_v is not None:
        _require_sigma(gaussians, "reduce_sh")

    def score(g: Gaussians) -> float:
        ps = [psnr(render_lod(g, cam, s_v, background=background, backend=backend,
                              eta_grad=PAPER).image, gt, cap=True) for cam, gt in zip(cameras, images)]
        return sum(ps) / max(len(ps), 1)

    d0 = gaussians.sh_degree
    n = len(gaussians)
    full = score(gaussians)
    per, best = [], d0
    for d in range(d0 - 1, -1, -1):
        p = score(truncate_sh(gaussians, d))
        saved = 4 * 3 * ((d0 + 1) ** 2 - (d + 1) ** 2) * n
        per.append({"degree": d, "psnr": p, "drop_db": full - p, "bytes_saved": saved})
        if full - p <= max_drop_db:
            best = d
    info = {"degree_in": d0, "degree_out": best, "max_drop_db": max_drop_db, "psnr_full": full,
            "per_degree": per, "bytes_saved": 4 * 3 * ((d0 + 1) ** 2 - (best + 1) ** 2) * n,
            "psnr_cost_db": next((r["drop_db"] for r in per if r["degree"] == best), 0.0)}
    return truncate_sh(gaussians, best).clone(), info


@torch.no_grad()
def prefix_vs_selection(gaussians: Gaussians, perm: Tensor, cameras: Sequence, images: Sequence[Tensor],
                        fractions: Sequence[float] = (1.0, 0.5, 0.25, 0.1), *, background=None,
                        backend: str = "auto") -> list[dict]:
    """PSNR of prefixes of the importance order against the per-view ``s_v`` selection.

    For each fraction f the prefix is the first ``round(f N)`` Gaussians of ``perm`` rendered
    as a standard model (original opacities, no decay); the selection renders, per view, the
    same number of Gaussians the prefix has in view, chosen by :func:`render_lod`'s exact budget
    (``min_s_v = 0``, Eq. 2 opacities). Rows: fraction, count, mean in-view count per view,
    psnr_prefix, psnr_selection (means over views).
    """
    rows = []
    n = len(gaussians)
    plain = gaussians.with_sigma_d(None)
    for f in fractions:
        k = int(round(f * n))
        sub = plain.subset(perm[:k])
        pp, ps, cnt = [], [], []
        for cam, gt in zip(cameras, images):
            r = render_lod(sub, cam, background=background, backend=backend)
            pp.append(psnr(r.image, gt, cap=True))
            cnt.append(r.n_rendered)
            s = render_lod(gaussians, cam, budget=Budget(count=int(r.n_rendered), min_s_v=0.0),
                           background=background, backend=backend, eta_grad=PAPER)
            ps.append(psnr(s.image, gt, cap=True))
        m = max(len(pp), 1)
        rows.append({"fraction": f, "count": k, "rendered_per_view": sum(cnt) / m,
                     "psnr_prefix": sum(pp) / m, "psnr_selection": sum(ps) / m})
    return rows
