"""The merge tree: a model's tiers drawn as one cut, one set of Gaussians per frame.

A model with merged tiers (``Gaussians.parents``, each tier's own ``parents`` the next: tier 0 the
model, tier ``k + 1`` merged Gaussians standing in for tier ``k``) becomes a tree (:func:`build`) when each Gaussian of
tier ``k < T`` names one parent in tier ``k + 1`` (``Gaussians.extra["parent"]``, the ``parent``
property of each element of the .ply) and its settings say ``tree=True``. It is then drawn as
Hierarchical 3DGS draws its hierarchy (Kerbl et al. 2024, ``runtime_switching.cu``): every frame
draws one *cut* of the tree, each root-to-leaf path crossing it once, and a hand-over
interpolates the children toward their parent so that the image is continuous at the switch
(docs/lod_rule.md). CLoD-GS's distance term decides where (Cheng et al., ICLR 2026, Eq. 2): a
merged node replaces its children once ``d' s_v`` reaches its ``sigma_d``, the level at which Eq.
2's exponent ``(d' s_v)^2 / (2 sigma_d^2)`` reaches 1/2, so far things hand over first.

Per camera (:func:`terms`, :func:`cut`; docs/lod_rule.md steps 1-5, ``F`` = :data:`HAND_OVER`,
``M`` = :data:`MORPH`): every node's ``d'_i = |mu_i - c| / D`` (``D`` the largest distance of the
last tier's centres in the frustum); a merged node's *entry* ``E_i = max(min(sigma_d_i / d'_i, E_p /
F), F^k)`` from the last tier down (tier 0 enters at 0), its end ``U_i = min(E_p, X_i)`` with its
own exit ``X_i = max(x_i / d'_i, F max(E_i, 1))`` (``extra["exit"]``, +inf for each parent's *lead*
child, :func:`leads`); it is drawn iff ``E_i <= s_v < U_i`` (no path crosses the cut twice), over
the last factor ``min(M, U_i / max(E_i, 1))`` of its interval at ``t`` falling from 1 to 0 in ``ln
s_v``. A node whose end is its own exit fades out (opacity times ``t``); a lead that hands over is
drawn with position, log-scales, rotation and SH interpolated toward its parent's and opacity ``t
a_i + (1 - t) a_p``; its siblings shrink (log-scales plus ``ln t``) and fade where they are. At ``t
= 0`` the lead is the parent and its siblings are gone: the image is continuous and the frame's cost
falls to the parent's (Hierarchical 3DGS gives each of ``K`` children ``1 - (1 - a_p)^(1/K)``,
which composites to the parent at its centre only and draws the parent's size ``K`` times).

The node constants are set by :func:`build` from the tiers the job linked: at their mean ``d'``
over the training views a tier's nodes enter around ``s_v = G_k`` (:func:`tier_scales`, where the
tiers' hand-overs put the tier), spread over a factor :data:`SPREAD` by the order the tier below
learned and moved toward where the last sibling of their lead leaves (:data:`ENTRY_TOWARD_CHILDREN`),
and every node leaves where its tier's own level of detail (its trained Eq. 2
``sigma_d``) drops it at its usual distance, a child moved part of the way toward its parent's
entry (:data:`EXIT_TOWARD_PARENT`); ``clod_adapter.train.tree_fit`` then fits the merged
tiers on the cuts. Between hand-overs nothing is dimmed or grown: every
drawn node is a Gaussian of one tier as trained; ``s_v = 1`` is the model at full detail. A
budget draws, with every node's ``d'`` its reference distance (its mean over the training views,
``extra["d_ref"]``: one cut of the tree per share, whatever the view's distances; :func:`budget_frame`),
the cut at the smallest ``s_v >= 1`` from which no cut holds more (:func:`budget_s_v`), so a larger
budget never draws a coarser cut.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, replace
from typing import Optional, Sequence

import torch
from torch import Tensor

from . import rule as lod
from ..render import native
from .budget import critical_s_v
from .neighbours import nearest
from ..gaussians import GAIN_NAMES, TREE_NODE_KEYS, Gaussians

__all__ = ["CPP_KERNELS", "HAND_OVER", "MORPH", "PARENT_KEY", "EXIT_KEY", "REFERENCE_KEY", "NODE_KEYS", "budget_frame",
           "is_tree", "tiers_of", "linked", "own_model", "tier_scales", "assign_parents", "build", "cut", "walk",
           "budget_s_v", "budget_cut", "TreeCut", "TreeTerms", "terms", "cut_attributes", "leads", "choose_leads",
           "in_frustum"]

#: whether the rule's C++ kernels (``render/csrc/tree_cut.cpp``) draw where they can run (CPU, the
#: kernels wanted by :mod:`clod_adapter.render.native`); False: its Python twin draws every cut
#: (a study may set it; the package's other kernels are unaffected)
CPP_KERNELS = True
#: ``F``: a node is drawn over at least this factor of ``s_v`` (and a hand-over or an exit lasts at
#: least from ``U / F`` to ``U``: :data:`MORPH`)
HAND_OVER = 1.25
#: ``M``: a hand-over or an exit lasts over the last ``min(M, U / max(E, 1))`` of a node's
#: interval ``[E, U)`` in ``s_v`` (at least ``F``): a node drawn over a wider interval turns into
#: its parent, or fades, more slowly
MORPH = 1.6
#: the ``Gaussians.extra`` key (and .ply property) of a node's parent index in the next tier
PARENT_KEY = "parent"
#: the ``Gaussians.extra`` key (and .ply property) of every node's exit constant
EXIT_KEY = "exit"
#: the ``Gaussians.extra`` key (and .ply property) of every node's reference distance: its mean
#: ``d'`` over the training views (:func:`reference_distances`), the ``d'`` of a budget's cut
REFERENCE_KEY = "d_ref"
#: the node data of a merge tree (``Gaussians.extra`` keys, .ply properties): :data:`PARENT_KEY`,
#: :data:`EXIT_KEY`, :data:`REFERENCE_KEY` (``clod_adapter.gaussians.TREE_NODE_KEYS``)
NODE_KEYS = TREE_NODE_KEYS
#: a shrinking sibling's scale factor ``w`` is floored here (its opacity reaches 0 with ``w``)
SHRINK_FLOOR = 1e-4
#: ``R``: a tier's hand-overs spread over this factor of ``s_v`` by importance (:func:`build`)
SPREAD = 2.0
#: ``b``: a child that is not its parent's lead leaves this share of the way, in ``ln s_v``, from
#: where its tier's own level of detail drops it toward where its parent takes over (:func:`build`)
EXIT_TOWARD_PARENT = 0.25
#: ``a``: a merged node with children other than its lead enters this share of the way, in ``ln
#: s_v``, from where its tier's spread puts it toward where the last of those children leaves
#: (:func:`build`)
ENTRY_TOWARD_CHILDREN = 0.5
#: candidate parents scored per child (:func:`assign_parents`)
CANDIDATES = 16


def is_tree(gaussians: Gaussians) -> bool:
    """Whether ``gaussians`` is drawn as a merge tree: its settings say ``tree`` and it has tiers."""
    return (gaussians.lod is not None and getattr(gaussians.lod, "tree", False) and gaussians.parents is not None
            and gaussians.lod.tier_s_v > 0)


def tiers_of(gaussians: Gaussians) -> list[Gaussians]:
    """The tree's tiers, finest first: the model, then each ``parents`` while the tier above has a
    hand-over (``lod.tier_s_v > 0``; ``clod_adapter.lod.draw.tier_chain``)."""
    out = [gaussians]
    while out[-1].parents is not None and out[-1].lod is not None and out[-1].lod.tier_s_v > 0:
        out.append(out[-1].parents)
    return out


def linked(tiers: Sequence[Gaussians]) -> Gaussians:
    """The model whose tiers (finest first) are ``tiers``: each tier's ``parents`` the next, the
    inverse of :func:`tiers_of` (each tier's own settings and node data kept)."""
    out = tiers[-1]
    for t in reversed(tiers[:-1]):
        out = replace(t, parents=out)
    return out


def own_model(gaussians: Gaussians) -> Gaussians:
    """Tier 0 of a tree as a model of its own, drawn by the rule of a model without merged tiers
    (docs/lod_rule_plain.md): no parents, no node data (``extra["parent"]``, ``extra["exit"]``),
    settings without ``tree``. Any other model is returned as it is."""
    if not is_tree(gaussians):
        return gaussians
    return replace(gaussians, parents=None, lod=replace(gaussians.lod, tree=False),
                   extra={k: v for k, v in gaussians.extra.items() if k not in NODE_KEYS})


def tier_scales(tiers: Sequence[Gaussians]) -> list[float]:
    """``G_k`` per tier: 1 for tier 0, then the product over the tiers above of ``tier_fade *
    tier_s_v / tier_start`` (their hand-over settings), the factor that turns a tier's own ``s_v``
    into the model's (``clod_adapter.lod.draw.tier_reach``)."""
    out, g = [], 1.0
    for k, t in enumerate(tiers):
        out.append(g)
        if k + 1 < len(tiers):
            st = t.lod
            g *= st.tier_fade * st.tier_s_v / st.tier_start
    return out


def _covariance_factors(g: Gaussians) -> tuple[Tensor, Tensor]:
    """``(R [M, 3, 3], inverse scales [M, 3])`` of the Gaussians' covariances, the scales floored
    at 1e-3 of their median (a flat Gaussian still accepts children beside its plane)."""
    from ..render.projection import quat_to_rotmat_rows

    R = torch.stack(quat_to_rotmat_rows(g.quats.detach().double()), dim=-1).reshape(-1, 3, 3)
    s = torch.exp(g.log_scales.detach().double())
    s = s.clamp_min(1e-3 * float(s.median()) if s.numel() else 1e-12)
    return R, 1.0 / s


@torch.no_grad()
def assign_parents(children: Gaussians, parents: Gaussians, *, candidates: int = CANDIDATES,
                   chunk: int = 2048) -> Tensor:
    """Each child's parent: among the ``candidates`` parent centres nearest to it (Euclidean, a k-d
    tree: :func:`clod_adapter.lod.neighbours.nearest`), the one under whose Gaussian it is most
    likely (the smallest squared Mahalanobis distance plus the log-determinant of the parent's
    covariance).

    Args:
        children: [N] Gaussians (tier ``k``). parents: [M] Gaussians (tier ``k + 1``), M >= 1.

    Returns:
        [N] int64 indices into ``parents``.

    Raises:
        ValueError: no parents.
    """
    if len(parents) == 0:
        raise ValueError("assign_parents: the parent tier is empty")
    R, inv_s = _covariance_factors(parents)
    logdet = 2.0 * torch.log(1.0 / inv_s).sum(-1)
    pm = parents.means.detach().double()
    cm = children.means.detach().double()
    nears = nearest(pm, cm, min(int(candidates), len(parents))).to(pm.device)  # [N, k]
    out = torch.empty(len(children), dtype=torch.long)
    for a in range(0, len(children), chunk):
        c, near = cm[a:a + chunk], nears[a:a + chunk]
        delta = c[:, None, :] - pm[near]  # [c, k, 3]
        local = torch.einsum("ckj,ckji->cki", delta, R[near])  # coordinates in the parent's axes
        score = ((local * inv_s[near]) ** 2).sum(-1) + logdet[near]
        out[a:a + chunk] = near.gather(1, score.argmin(1, keepdim=True))[:, 0]
    return out.to(children.means.device)


def in_frustum(t: Gaussians, camera) -> Tensor:
    """[N] bool: the centres in front of ``camera`` (z > 0.01) projecting inside its image (one pass
    of the C++ kernel of :func:`clod_adapter.lod.rule.frame_terms` on the CPU)."""
    with torch.no_grad():  # the model's own tensor: its cached rows (lod.centre_columns) are reused
        return lod.frame_terms(t.means, camera.viewmat.to(t.means), camera.K.to(t.means), int(camera.width),
                               int(camera.height))[0]


def _centre(camera) -> list:
    """The camera centre in world units, as three Python floats (double)."""
    return lod.camera_center(camera.viewmat.detach().double()).tolist()


def _node_distances(means: Tensor, c: Sequence[float]) -> Tensor:
    """[N] ``|mu - c|`` in double, rounded to the centres' dtype (as ``tree_frame`` computes it)."""
    m = means.detach().double()
    return ((m[:, 0] - c[0]).square() + (m[:, 1] - c[1]).square() + (m[:, 2] - c[2]).square()).sqrt().to(means.dtype)


def _normaliser(d_last: Tensor, fr_last: Tensor) -> float:
    """``D``: the largest distance of the last tier's centres in the frustum (of all of them when
    none is), at least 1e-12; 1 for an empty tier."""
    inside = d_last[fr_last] if bool(fr_last.any()) else d_last
    return max(float(inside.max()), 1e-12) if inside.numel() else 1.0


@torch.no_grad()
def frame(tiers: Sequence[Gaussians], camera) -> tuple[list, list]:
    """Step 1 for ``camera``, per tier: ``(d' [N_k] in the centres' dtype, frustum [N_k] bool)``
    (:func:`in_frustum`). One pass of the C++ kernel over every node on the CPU; its twin
    elsewhere (the same rounding: distances in double rounded to the dtype, divided by ``D``)."""
    if _native(tiers):
        out = native.load().tree_frame(*_camera_args(tiers, camera), _centre(camera))
        return out[1::2], out[0::2]
    c, frs = _centre(camera), [in_frustum(t, camera) for t in tiers]
    ds = [_node_distances(t.means, c) for t in tiers]
    D = _normaliser(ds[-1], frs[-1])
    return [d / D for d in ds], frs


def _camera_args(tiers: Sequence[Gaussians], camera) -> tuple:
    """The tiers' centre columns and the camera as ``render/csrc/tree_cut.cpp`` takes them (``tree_frame``:
    then the centre, per tier [frustum, d']; ``[]``, the frustum alone)."""
    vm, K = camera.viewmat.detach().to(torch.float64), camera.K.detach().to(torch.float64)
    return ([lod.centre_columns(t.means, tiers[0].means.dtype) for t in tiers], vm[:3, :3].reshape(-1).tolist(),
            vm[:3, 3].tolist(), float(K[0, 0]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2]), int(camera.width),
            int(camera.height), 0.01)


def _camera(tiers: Sequence[Gaussians], camera) -> tuple[list, float, Tensor]:
    """Step 1's camera terms for :func:`walk`: ``(c, D, the last tier's d' [N_T])`` (``c`` three
    floats), ``D`` the largest distance of the last tier's centres in the frustum."""
    c = _centre(camera)
    d = _node_distances(tiers[-1].means, c)
    D = _normaliser(d, in_frustum(tiers[-1], camera))
    return c, D, d / D


@torch.no_grad()
def reference_distances(tiers: Sequence[Gaussians], cameras) -> list[Tensor]:
    """Per tier [N_k] float64: each node's mean ``d'`` (step 1) over the views whose frustum holds
    its centre (over all views where none does)."""
    s_in, c_in, s_all = ([torch.zeros(len(t), dtype=torch.float64) for t in tiers] for _ in range(3))
    for cam in cameras:
        ds, frs = frame(tiers, cam)
        for k, (fr, d) in enumerate(zip(frs, ds)):
            d = d.double()
            s_all[k] += d.cpu()
            s_in[k] += torch.where(fr, d, torch.zeros_like(d)).cpu()
            c_in[k] += fr.double().cpu()
    n = max(len(cameras), 1)
    return [torch.where(c > 0, a / c.clamp_min(1), b / n) for a, b, c in zip(s_in, s_all, c_in)]


def budget_frame(tiers: Sequence[Gaussians], camera) -> tuple[list, list]:
    """Step 6's terms for ``camera``: per tier ``(d' [N_k], frustum [N_k] bool)`` as :func:`frame`
    gives them, but every node's ``d'`` its stored reference distance (``extra["d_ref"]``, in the
    centres' dtype), so a budget draws one cut of the tree for every view at that share, only the
    frustum the view's. Raises KeyError where a tier lacks ``extra["d_ref"]``."""
    refs = [t.extra[REFERENCE_KEY].detach().to(t.means.dtype) for t in tiers]
    if _native(tiers):
        return refs, native.load().tree_frame(*_camera_args(tiers, camera), [])
    return refs, [in_frustum(t, camera) for t in tiers]


def _group_rank(child_level: Tensor, parent: Tensor, n_parents: int) -> Tensor:
    """[n_parents] float64 in (0, 1): each parent's rank quantile by the largest ``child_level``
    among its children (ties by index)."""
    top = torch.full((n_parents,), -math.inf, dtype=torch.float64).scatter_reduce(
        0, parent, child_level.double(), reduce="amax", include_self=True)
    order = torch.argsort(top, stable=True)
    rank = torch.empty(n_parents, dtype=torch.float64)
    rank[order] = (torch.arange(n_parents, dtype=torch.float64) + 0.5) / max(n_parents, 1)
    return rank


def _toward(x: Tensor, y: Tensor, w: float) -> Tensor:
    """``x^(1 - w) y^w`` in float64 (both clamped at 0): the share ``w`` of the way from ``x`` to
    ``y`` in log space, how :func:`build` moves an entry or an exit constant."""
    return x.double().clamp_min(0.0) ** (1.0 - w) * y.double().clamp_min(0.0) ** w


def build(gaussians: Gaussians, cameras, log=None, *, spread: float = None,
          exit_toward_parent: float = None, entry_toward_children: float = None) -> Gaussians:
    """``gaussians`` (a model with merged tiers, linked by ``clod-adapt``) as a merge
    tree, the node constants set on ``cameras`` (training views):

    * each tier's Gaussians get their parent in the next tier (:func:`assign_parents`,
      ``extra["parent"]``, int32); a merged Gaussian no Gaussian of the tier below chose is left
      out of its tier;
    * a merged node's ``sigma_d`` becomes ``G_k R^(q - 1/2) d_ref`` (:func:`tier_scales`,
      :func:`reference_distances`; ``R`` = ``spread``, default :data:`SPREAD`): at its usual
      distance it enters around where the tiers' hand-overs put its tier, earlier or later by its
      rank ``q`` among the tier's nodes by their most important child (the largest of the
      children's own Eq. 2 levels at their ``d_ref``: the order the tier below learned), so the
      hand-overs of a tier spread over a factor ``R`` of ``s_v``; a node with children other
      than its lead then moves the share ``a`` = ``entry_toward_children`` (default
      :data:`ENTRY_TOWARD_CHILDREN`, in [0, 1]) of the way, in ``ln s_v``, toward the last of
      those children's own exits (``sigma^(1 - a) x_last^a``, below), so the lead turns into its
      parent nearer where its siblings leave and the count falls nearer where the image changes;
    * every node's own exit is ``G_k s* d_ref``, ``s*`` its Eq. 2 critical scale at ``d_ref``
      with its own (trained) ``sigma_d``: where its tier's own level of detail would drop it. A
      root's exit (``extra["exit"]``) is its own; a child that is not its parent's lead leaves the
      share ``b`` = ``exit_toward_parent`` (default :data:`EXIT_TOWARD_PARENT`, in [0, 1]) of the
      way from its own exit toward its parent's ``sigma_d``, in ``ln s_v`` (``own^(1 - b)
      sigma_p^b``), so the count of a frame falls near the hand-overs that change its image; each
      family's lead (:func:`choose_leads`, the child nearest the family's centre) gets an exit of
      +inf instead, the mark :func:`leads` reads (it is drawn until its parent takes over);
    * every node keeps its ``d_ref`` (``extra["d_ref"]``, float32), the ``d'`` its budgets' cuts
      use (:func:`budget_frame`);
    * no tier keeps level gains (the tree does not draw them: docs/lod_rule.md "The file"), and
      the settings say ``tree=True``. Tier 0's Gaussians are otherwise unchanged.

    Raises:
        ValueError: a model without tiers, no cameras, or ``exit_toward_parent`` or
            ``entry_toward_children`` outside [0, 1].
    """
    spread = SPREAD if spread is None else float(spread)
    b = EXIT_TOWARD_PARENT if exit_toward_parent is None else float(exit_toward_parent)
    a = ENTRY_TOWARD_CHILDREN if entry_toward_children is None else float(entry_toward_children)
    for name, v in (("exit_toward_parent", b), ("entry_toward_children", a)):
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"tree.build: {name} must be in [0, 1], got {v}")
    tiers = tiers_of(gaussians)
    if len(tiers) < 2:
        raise ValueError("tree.build: the model has no merged tiers")
    if not len(cameras):
        raise ValueError("tree.build: no cameras to set the node constants on")
    tiers = [replace(t, extra={k: v for k, v in t.extra.items() if k not in NODE_KEYS},
                     **dict.fromkeys(GAIN_NAMES)) for t in tiers]
    for k in range(len(tiers) - 1):
        parent = assign_parents(tiers[k], tiers[k + 1])
        keep = torch.bincount(parent, minlength=len(tiers[k + 1])) > 0
        if not bool(keep.all()):
            parent = (torch.cumsum(keep.long(), 0) - 1)[parent]
            if log is not None:
                log(f"tree: tier {k + 1}: {int((~keep).sum()):,} of {len(keep):,} merged Gaussians are no "
                    f"Gaussian's parent; left out")
            tiers[k + 1] = replace(tiers[k + 1].subset(keep), parents=tiers[k + 1].parents)
        tiers[k] = replace(tiers[k], extra={**tiers[k].extra, PARENT_KEY: parent.to(torch.int32)})
    scales, d_ref = tier_scales(tiers), reference_distances(tiers, cameras)
    own = [critical_s_v(torch.sigmoid(t.opacity_logits.detach()), d.to(t.means), t.sigma_d.detach(), t.lod.tau,
                        t.lod.eps).cpu() for t, d in zip(tiers, d_ref)]  # each tier's own Eq. 2 level at d_ref
    exits = [scales[k] * own[k] * d_ref[k] for k in range(len(tiers))]  # where its tier's own LoD drops it
    for k in range(1, len(tiers)):
        t = tiers[k]
        p = tiers[k - 1].extra[PARENT_KEY].long().cpu()
        rank = _group_rank(own[k - 1], p, len(t))
        s = (scales[k] * spread ** (rank - 0.5) * d_ref[k]).double()
        if a > 0.0:  # toward the last exit of its children that are not its lead
            nl = ~choose_leads(tiers[k - 1]).cpu()
            last = torch.zeros(len(t), dtype=torch.float64).scatter_reduce(
                0, p[nl], exits[k - 1].double()[nl].clamp_min(0.0), reduce="amax", include_self=True)
            s = torch.where(last > 0, _toward(s, last, a), s)
        tiers[k] = replace(t, sigma_d=s.to(t.means))
    for k, t in enumerate(tiers):  # where its tier's own level of detail drops it, moved toward the parent
        x = exits[k]
        if k + 1 < len(tiers):  # each family's lead marked by an exit of +inf
            lead = choose_leads(t).cpu()
            if b > 0.0:
                s_p = tiers[k + 1].sigma_d.detach().double().cpu()[t.extra[PARENT_KEY].long().cpu()]
                x = _toward(x, s_p, b).to(x.dtype)
            x = torch.where(lead, torch.full_like(x, math.inf), x)
        tiers[k] = replace(t, extra={**t.extra, EXIT_KEY: x.float().to(t.means.device),
                                     REFERENCE_KEY: d_ref[k].float().to(t.means.device)})
    out = linked(tiers)
    return replace(out, lod=replace(out.lod, tree=True))


@dataclass
class TreeCut:
    """What one camera draws of a tree at one ``s_v`` (:func:`cut`).

    Attributes:
        ids: per tier, [n_k] int64 indices of the drawn nodes, ascending.
        t: per tier, [n_k] float64 hand-over position (1: the node's own attributes; 0: its
            parent's); for the last tier, the fade toward the root's exit (opacity times ``t``).
        s_v: the level drawn.
        n_frustum: tier 0's centres in the frustum (the population of shares of the view).
    """

    ids: list
    t: list
    s_v: float
    _n_frustum: object  # int, or a zero-argument callable that counts it on first use
    fade: Optional[list] = None  # per tier [n_k] bool: the row fades out (else it hands over to its parent)

    @property
    def n_frustum(self) -> int:
        if callable(self._n_frustum):
            self._n_frustum = self._n_frustum()
        return self._n_frustum

    @property
    def n_drawn(self) -> int:
        return sum(int(i.numel()) for i in self.ids)


@dataclass
class TreeTerms:
    """The per-camera terms of a tree (:func:`terms`): per tier the entry ``E`` and the end ``U``
    of each node's interval [N_k], whether it ends by fading out ([N_k] bool), and (on first use,
    or as given in ``frustum_masks``) the frustum [N_k] bool (:func:`in_frustum`)."""

    entry: list
    upper: list
    fade: list
    tiers: list
    camera: object
    frustum_masks: Optional[list] = None

    @property
    def frustum(self) -> list:
        if self.frustum_masks is None:
            self.frustum_masks = [in_frustum(t, self.camera) for t in self.tiers]
        return self.frustum_masks


@torch.no_grad()
def terms(tiers: Sequence[Gaussians], camera, *, hand_over: Optional[float] = None,
          at: Optional[tuple] = None) -> TreeTerms:
    """Steps 1-3 of the module docstring for ``camera`` (``viewmat`` [4, 4] world-to-camera, ``K``
    [3, 3] pixels, ``width``, ``height`` pixels): every node's entry and end, in ``s_v`` (the
    centres' dtype), and whether it fades. Every node is visited; :func:`walk` visits only what a
    level needs. ``at``: :func:`frame` of this camera, when the caller has it. Raises KeyError where
    a tier lacks ``extra["parent"]`` or ``extra["exit"]``."""
    F = _width(hand_over)
    ds, frs = frame(tiers, camera) if at is None else at
    if _native(tiers):
        out = _native_call("tree_terms", tiers, ds, F)
        return TreeTerms(out[0::3], out[1::3], out[2::3], list(tiers), camera, frs)
    T = len(tiers) - 1
    entry = [None] * (T + 1)
    entry[0] = torch.zeros_like(ds[0])
    for k in range(T, 0, -1):
        e = tiers[k].sigma_d.detach() / ds[k].clamp_min(1e-12)
        if k < T:
            e = torch.minimum(e, entry[k + 1][tiers[k].extra[PARENT_KEY].long()] / F)
        entry[k] = e.clamp_min(F ** k)
    ends = [_end(tiers, k, None, entry[k], entry[k + 1][tiers[k].extra[PARENT_KEY].long()] if k < T else None,
                 ds[k], F) for k in range(T + 1)]
    return TreeTerms(entry, [e for e, _ in ends], [f for _, f in ends], list(tiers), camera, frs)


def _end(tiers: Sequence[Gaussians], k: int, rows: Optional[Tensor], E: Tensor, U: Optional[Tensor], d: Tensor,
         F: float) -> tuple[Tensor, Tensor]:
    """Steps 3's end of the nodes ``rows`` of tier ``k`` (all when None) with entries ``E``, their
    parents' entries ``U`` (None in the last tier) and ``d'``: ``(end, fades)``."""
    x = tiers[k].extra[EXIT_KEY].detach()
    x = x if rows is None else x[rows]
    X = torch.maximum(x.to(d) / d.clamp_min(1e-12), F * E.clamp_min(1.0))
    if U is None:
        return X, torch.ones_like(X, dtype=torch.bool)
    lead = leads(tiers[k])
    lead = lead if rows is None else lead[rows]
    fades = ~lead & (X < U)
    return torch.where(fades, X, U), fades


@torch.no_grad()
def cut(tiers: Sequence[Gaussians], camera, s_v: float, *, hand_over: Optional[float] = None,
        tt: Optional[TreeTerms] = None) -> TreeCut:
    """The cut drawn at ``s_v`` (>= 1; below, 1) for ``camera`` (module docstring, steps 3-4): from
    every node's terms ``tt`` when given, else by :func:`walk`."""
    s, F = max(float(s_v), 1.0), _width(hand_over)
    if tt is None:
        if _native(tiers):
            return _native_cut(tiers, camera, s, F)
        return walk(tiers, camera, s, hand_over=F)
    M = _morph(hand_over)
    ids, ts, fades = [], [], []
    for n, u, f in zip(tt.entry, tt.upper, tt.fade):
        i = torch.nonzero((n <= s) & (s < u)).flatten()
        ids.append(i)
        ts.append(_weight(n[i], u[i], s, M))
        fades.append(f[i])
    return TreeCut(ids, ts, s, int(tt.frustum[0].sum()), fades)


@torch.no_grad()
def budget_cut(tiers: Sequence[Gaussians], camera, k: float, *, hand_over: Optional[float] = None,
               at: Optional[tuple] = None, n_frustum: Optional[int] = None) -> TreeCut:
    """The cut a count budget of ``k`` nodes with their centre in the frustum draws (docs/lod_rule.md
    step 6): :func:`terms` at the reference distances (:func:`budget_frame`), :func:`budget_s_v`
    and :func:`cut` at that level. Where the kernels run, the terms and their sorted ends are kept
    per model (:func:`_budget_terms`) and ``tree_budget_walk`` (``render/csrc/tree_cut.cpp``) finds
    the level from the coarsest end down and emits the cut (the three functions are its twin,
    ``tests/test_tree.py``). ``camera``: ``viewmat`` [4, 4], ``K`` [3, 3] pixels, ``width``,
    ``height``; ``k`` >= 0 nodes; ``at``: :func:`budget_frame` of this camera and ``n_frustum`` its
    tier-0 count, when the caller has them. Returns the :class:`TreeCut` (its ``s_v`` the level,
    >= 1). Raises KeyError where a tier lacks ``extra["parent"]``, ``extra["exit"]`` or ``extra["d_ref"]``."""
    ds, frs = budget_frame(tiers, camera) if at is None else at
    if _native(tiers):
        F = _width(hand_over)
        E, U, fade, pos, node, hi = _budget_terms(tiers, ds, F)
        out = native.load().tree_budget_walk(E, U, fade, pos, node, hi, [f.contiguous() for f in frs], float(k),
                                             _morph(F))
        level = max(float(out[-1]), 1.0)
        n0 = (lambda: int(frs[0].sum())) if n_frustum is None else n_frustum
        return TreeCut(out[0:-1:3], out[1:-1:3], level, n0, out[2:-1:3])
    tt = terms(tiers, camera, hand_over=hand_over, at=(ds, frs))
    return cut(tiers, camera, budget_s_v(tt, k), hand_over=hand_over, tt=tt)


_BUDGET_TERMS: dict = {}


def _budget_terms(tiers: Sequence[Gaussians], ds: Sequence[Tensor], F: float) -> tuple:
    """Every node's terms at its reference distance (:func:`terms` at ``ds``: the same for every
    camera) and their intervals' ends sorted coarsest first (``tree_budget_events``): ``(E, U,
    fade, positions, nodes, is_end)``, kept while every tensor they come from is the same object
    at the same in-place version."""
    deps = [x for t in tiers for x in (t.sigma_d, t.extra[EXIT_KEY], t.extra[REFERENCE_KEY])]
    deps += [t.extra[PARENT_KEY] for t in tiers[:-1]]
    key, stamp = (id(deps[0]), F, tiers[0].means.dtype), [(id(x), x._version) for x in deps]
    hit = _BUDGET_TERMS.get(key)
    if hit is None or hit[0] != stamp or any(r() is not x for r, x in zip(hit[1], deps)):
        out = _native_call("tree_terms", tiers, ds, F)
        terms_ = (out[0::3], out[1::3], out[2::3])
        hit = (stamp, [weakref.ref(x) for x in deps], (*terms_, *native.load().tree_budget_events(*terms_[:2])))
        while len(_BUDGET_TERMS) >= 8:
            _BUDGET_TERMS.pop(next(iter(_BUDGET_TERMS)))
        _BUDGET_TERMS[key] = hit
    return hit[2]


def _weight(E: Tensor, U: Tensor, s: float, M: float) -> Tensor:
    """Step 5's ``w`` of drawn nodes with entries ``E`` and ends ``U`` at ``s``: 1 until the last
    ``min(M, U / max(E, 1))`` of their interval, falling to 0 at ``U`` linearly in ``ln s_v``."""
    width = torch.clamp(U / E.clamp_min(1.0), max=M)
    return torch.clamp(torch.log(U / s) / torch.log(width), 0.0, 1.0)


def _morph(hand_over: Optional[float]) -> float:
    """``M``: :data:`MORPH` as it is at the call, at least ``F`` (a study may set either)."""
    return max(float(MORPH), _width(hand_over))


def _width(hand_over: Optional[float]) -> float:
    """``F``: ``hand_over`` where given, else :data:`HAND_OVER` as it is at the call (a study may
    set the module's value; every function of the rule reads it here)."""
    return float(HAND_OVER if hand_over is None else hand_over)


def _native(tiers: Sequence[Gaussians]) -> bool:
    """Whether the C++ kernels (``render/csrc/tree_cut.cpp``) draw these tiers: :data:`CPP_KERNELS`,
    CPU, one dtype, one SH size, no autograd recording, and the kernels wanted
    (``clod_adapter.render.native``)."""
    if not CPP_KERNELS:
        return False
    t0 = tiers[0]
    records = torch.is_grad_enabled() and any(x.requires_grad for t in tiers for x in (
        t.means, t.quats, t.log_scales, t.opacity_logits, t.sh0, t.shN))
    return (not records and all(t.means.device.type == "cpu" and t.means.dtype == t0.means.dtype
                                                 and t.shN.shape[1] == t0.shN.shape[1] for t in tiers)
            and native.wanted(t0.means.device.type == "cpu"))


def _int_parents(tier: Gaussians) -> Tensor:
    return lod.cached_value(tier.extra[PARENT_KEY], "tree_parent64", lambda p: p.long().contiguous())


def _node_constants(tiers: Sequence[Gaussians]) -> list:
    """The nodes' constants as ``render/csrc/tree_cut.cpp`` takes them: per tier ``sigma_d`` and
    ``exit`` [N_k] in the centres' dtype, and for all but the last int64 parents and bool leads."""
    dt = tiers[0].means.dtype
    return [[t.sigma_d.detach().to(dt).contiguous() for t in tiers],
            [t.extra[EXIT_KEY].detach().to(dt).contiguous() for t in tiers],
            [_int_parents(t) for t in tiers[:-1]], [leads(t).contiguous() for t in tiers[:-1]]]


def _native_call(name: str, tiers: Sequence[Gaussians], ds: Sequence[Tensor], *args) -> list:
    """A kernel of ``render/csrc/tree_cut.cpp`` over the tiers' node constants at the nodes' ``d'``
    ``ds`` (:func:`frame`)."""
    return getattr(native.load(), name)([d.contiguous() for d in ds], *_node_constants(tiers), *args)


def _native_cut(tiers: Sequence[Gaussians], camera, s: float, F: float) -> TreeCut:
    """:func:`cut` by :func:`walk`'s C++ twin (``tree_cut``): from the roots down, the terms of the
    children of nodes not yet entered only (every other node is one look at its parent's entry),
    and tier 0's frustum counted in the same pass (:attr:`TreeCut.n_frustum`)."""
    out = native.load().tree_cut(*_camera_args(tiers, camera), _centre(camera), *_node_constants(tiers), s, F,
                                 _morph(F))
    return TreeCut(out[0:-1:3], out[1:-1:3], s, int(out[-1]), out[2:-1:3])


def _children(tier: Gaussians) -> tuple[Tensor, Tensor, Tensor]:
    """``(order, start, count)``: the tier's rows ordered by parent (stable), and per parent of the
    next tier where its children start in that order and how many there are. Cached."""
    p = tier.extra[PARENT_KEY]
    order = lod.cached_value(p, "tree_order", lambda x: torch.argsort(x.long(), stable=True))
    count = lod.cached_value(p, "tree_count", lambda x: torch.bincount(x.long(), minlength=int(x.max()) + 1 if x.numel()
                                                                  else 0))
    return order, torch.cumsum(count, 0) - count, count


@torch.no_grad()
def walk(tiers: Sequence[Gaussians], camera, s_v: float, *, hand_over: Optional[float] = None) -> TreeCut:
    """:func:`cut` computed from the roots down: only the children of nodes not yet entered at
    ``s_v`` (>= 1; below, 1) are visited, so a coarse frame touches few nodes. Returns the same
    :class:`TreeCut` as :func:`cut` from :func:`terms` (``tests/test_tree.py``)."""
    F = _width(hand_over)
    s, M = max(float(s_v), 1.0), _morph(hand_over)
    T = len(tiers) - 1
    c, D, d_last = _camera(tiers, camera)
    last = tiers[T]
    E = (last.sigma_d.detach() / d_last.clamp_min(1e-12)).clamp_min(F ** T)
    U, f = _end(tiers, T, None, E, None, d_last, F)
    i = torch.nonzero((E <= s) & (s < U)).flatten()
    ids, ts, fades = [i], [_weight(E[i], U[i], s, M)], [f[i]]
    open_rows = torch.nonzero(s < E).flatten()  # roots not yet entered: their subtrees are drawn
    E_open = E[open_rows]
    for k in range(T - 1, -1, -1):
        order, start, count = _children(tiers[k])
        n = count[open_rows]
        first = torch.repeat_interleave(start[open_rows], n)
        offset = torch.arange(int(n.sum()), device=n.device) - torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
        rows = order[first + offset]
        U_c = torch.repeat_interleave(E_open, n)
        d = _node_distances(tiers[k].means[rows], c) / D
        if k == 0:
            E_c = torch.zeros_like(U_c)
        else:
            E_c = torch.minimum(tiers[k].sigma_d.detach()[rows] / d.clamp_min(1e-12), U_c / F).clamp_min(F ** k)
        end, f = _end(tiers, k, rows, E_c, U_c, d, F)
        drawn = (E_c <= s) & (s < end)  # s < U_c holds for every child of an open node
        sel, srt = torch.sort(rows[drawn])
        ids.append(sel)
        ts.append(_weight(E_c[drawn][srt], end[drawn][srt], s, M))
        fades.append(f[drawn][srt])
        opened = s < E_c  # not entered yet: its subtree is drawn
        open_rows, E_open = rows[opened], E_c[opened]
    ids.reverse()
    ts.reverse()
    fades.reverse()
    return TreeCut(ids, ts, s, lambda: int(in_frustum(tiers[0], camera).sum()), fades)  # counted on first use


@torch.no_grad()
def budget_s_v(tt: TreeTerms, k: float, weights: Optional[Sequence[Tensor]] = None) -> float:
    """The level a budget draws (module docstring): the smallest ``s_v >= 1`` from which no cut
    holds more than ``k`` nodes whose centre is in the frustum (``weights``: per tier [N_k] float64,
    no cut whose summed weight exceeds ``k``), or the coarsest end (nothing drawn) where none is.
    Non-increasing in ``k``."""
    if weights is None:
        weights = [f.double() for f in tt.frustum]
    if _native(tt.tiers):
        return native.load().tree_budget([e.contiguous() for e in tt.entry], [u.contiguous() for u in tt.upper],
                                  [w.double().contiguous() for w in weights], float(k))
    sel = [(w > 0) & (u > n.clamp_min(1.0)) for w, n, u in zip(weights, tt.entry, tt.upper)]
    lo = torch.cat([n[m] for n, m in zip(tt.entry, sel)]).clamp_min(1.0)
    hi = torch.cat([u[m] for u, m in zip(tt.upper, sel)])
    w = torch.cat([x[m].double() for x, m in zip(weights, sel)])
    pos = torch.cat([lo, hi, lo.new_ones(1)])
    delta = torch.cat([w, -w, lo.new_zeros(1)])
    order = torch.argsort(pos, stable=True)
    pos, delta = pos[order], delta[order]
    uniq, inv = torch.unique_consecutive(pos, return_inverse=True)
    step = torch.zeros(len(uniq), dtype=torch.float64, device=pos.device).index_add_(0, inv, delta)
    count = torch.cumsum(step, 0)  # drawn on [uniq[j], uniq[j + 1])
    suffix_max = torch.flip(torch.cummax(torch.flip(count, [0]), 0).values, [0])
    ok = torch.nonzero(suffix_max <= k + 1e-9 * abs(k)).flatten()  # summed in another order than k was
    return float(uniq[ok[0]]) if ok.numel() else float(uniq[-1])


def _quat_lerp(q: Tensor, qp: Tensor, t: Tensor) -> Tensor:
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    qp = qp / qp.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    qp = torch.where(((q * qp).sum(-1, keepdim=True) < 0), -qp, qp)
    return t[:, None] * q + (1.0 - t[:, None]) * qp


def choose_leads(tier: Gaussians) -> Tensor:
    """[N] bool: the lead :func:`build` marks in each family, the child nearest (Euclidean) the
    centre of its parent's children weighted by their mass ``sigmoid(opacity) s0 s1 s2`` (the
    moment-matched centre of the family; ties: the first row), the one with the least far to go
    (docs/studies.md "Which child turns into its parent"). Cached per parent-index tensor. Raises
    KeyError where the tier has no ``extra["parent"]``."""
    def make(p: Tensor) -> Tensor:
        p = p.long()
        n = int(p.max()) + 1 if p.numel() else 0
        mass = torch.sigmoid(tier.opacity_logits.detach().double()) * torch.exp(
            tier.log_scales.detach().double().sum(-1))
        mu = tier.means.detach().double()
        centre = torch.zeros(n, 3, dtype=torch.float64, device=p.device).index_add_(0, p, mu * mass[:, None])
        weight = torch.zeros(n, dtype=torch.float64, device=p.device).index_add_(0, p, mass)
        d = torch.linalg.vector_norm(mu - (centre / weight[:, None].clamp_min(1e-300))[p], dim=-1)
        top = torch.full((n,), math.inf, dtype=torch.float64, device=p.device)
        top = top.scatter_reduce(0, p, d, reduce="amin", include_self=True)
        cand = d == top[p]
        rows = torch.arange(len(p), device=p.device)
        first = torch.full_like(top, float(len(p))).scatter_reduce(0, p[cand], rows[cand].double(), reduce="amin",
                                                                    include_self=True)
        return rows == first[p].long()

    return lod.cached_value(tier.extra[PARENT_KEY], "tree_choose_leads", make)


def leads(tier: Gaussians) -> Tensor:
    """[N] bool: the child that becomes its parent at the switch, one per parent: the row whose
    ``extra["exit"]`` is +inf, the mark :func:`build` writes (its choice, :func:`choose_leads`),
    so the fit, the file and every consumer draw the leads the fit trained whatever it moves. A
    tier with parents but no mark (a tree file written before the marks) gets
    :func:`choose_leads` of its attributes as they are, and so does a tier without exits. Cached
    per exit tensor. Raises KeyError where it falls back and the tier has no ``extra["parent"]``."""
    def make(x: Tensor) -> Tensor:
        marked = torch.isposinf(x)
        return marked if bool(marked.any()) or not x.numel() else choose_leads(tier)

    if EXIT_KEY not in tier.extra:
        return choose_leads(tier)
    return lod.cached_value(tier.extra[EXIT_KEY], "tree_leads", make)


def _handed_over(t: Gaussians, par: Gaussians, rows: Tensor, w: Tensor, mu: Tensor, ls: Tensor, q: Tensor,
                 col: Tensor, a: Tensor) -> tuple:
    """Tier rows ``rows`` [h] in a hand-over at positions ``w`` [h] (module docstring, step 4), from
    their own attributes gathered for this frame (``mu`` [h, 3], ``ls`` [h, 3] log-scales, ``q``
    [h, 4], ``col`` [h, K, 3] SH, ``a`` [h] opacities; written in place where autograd does not
    record): ``(mu, ls, q, col, a)`` as drawn."""
    wh = w.to(mu.dtype)
    li = torch.nonzero(leads(t)[rows]).flatten()  # the leads grow into their parents
    p, wl = t.extra[PARENT_KEY].long()[rows[li]], wh[li]
    grown = [wl[:, None] * mu[li] + (1.0 - wl[:, None]) * par.means[p],
             wl[:, None] * ls[li] + (1.0 - wl[:, None]) * par.log_scales[p],
             _quat_lerp(q[li], par.quats[p], wl),
             wl[:, None, None] * col[li] + (1.0 - wl[:, None, None]) * torch.cat([par.sh0[p], par.shN[p]], 1),
             wl * a[li] + (1.0 - wl) * torch.sigmoid(par.opacity_logits[p])]
    ls = ls + torch.log(wh.clamp_min(SHRINK_FLOOR))[:, None]  # the siblings shrink and fade where they are
    a = wh * a
    in_place = not torch.is_grad_enabled()
    return tuple(x.index_put_((li,), v) if in_place or not v.requires_grad else x.index_put((li,), v)
                 for x, v in zip((mu, ls, q, col, a), grown))


def cut_attributes(tiers: Sequence[Gaussians], c: TreeCut, *, campos: Optional[Tensor] = None,
                   sh_degree: Optional[int] = None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The drawn attributes of a cut, tier 0's rows first: ``(means [k, 3], quats [k, 4] wxyz,
    scales [k, 3] activated (world units), opacities [k], colors)``, each node interpolated toward
    its parent by its ``t`` (module docstring, step 4; only the rows in a hand-over are
    interpolated). ``colors``: [k, K, 3] SH in gsplat's layout; with a camera centre ``campos``
    [3] (world units) and ``sh_degree`` (default the tiers'), [k, 3] the colours seen from it at
    the drawn positions (:func:`clod_adapter.render.cpu.sh_colors`; the C++ kernel evaluates them
    in its pass over the rows). Raises ValueError: ``sh_degree`` outside 0..the tiers' degree."""
    rgb = campos is not None
    deg = (tiers[0].sh_degree if sh_degree is None else int(sh_degree)) if rgb else -1
    if rgb and not 0 <= deg <= tiers[0].sh_degree:
        raise ValueError(f"sh_degree must be in 0..{tiers[0].sh_degree}, got {sh_degree}")
    if c.fade is not None and _native(tiers):
        attrs = [x.detach().contiguous() for t in tiers
                 for x in (t.means, t.quats, t.log_scales, t.opacity_logits, t.sh0, t.shN)]
        centre = [float(v) for v in campos.detach().to(tiers[0].means.dtype).tolist()] if rgb else []
        return tuple(native.load().tree_attributes(attrs, [i.contiguous() for i in c.ids],
                                            [w.to(tiers[0].means.dtype).contiguous() for w in c.t],
                                            [f.contiguous() for f in c.fade], [_int_parents(t) for t in tiers[:-1]],
                                            [leads(t).contiguous() for t in tiers[:-1]], SHRINK_FLOOR, centre, deg))
    out = _cut_attributes(tiers, c)
    if not rgb:
        return out
    from ..render.cpu import sh_colors

    return (*out[:4], sh_colors(deg, out[0], out[4], campos.to(out[0])))


def _cut_attributes(tiers: Sequence[Gaussians], c: TreeCut) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`cut_attributes` in torch, the SH as coefficients (the C++ kernel's twin)."""
    out = [[] for _ in range(5)]
    for k, (t, ids, w) in enumerate(zip(tiers, c.ids, c.t)):
        whole = ids.numel() == len(t) and bool((w >= 1.0).all())
        if whole:  # a whole tier as it is (full detail): no gather
            mu, q, ls, col, a = t.means, t.quats, t.log_scales, t.colors, torch.sigmoid(t.opacity_logits)
        else:
            mu, q, ls = t.means[ids], t.quats[ids], t.log_scales[ids]
            col = torch.cat([t.sh0[ids], t.shN[ids]], dim=1)  # only the drawn rows of the SH
            a = torch.sigmoid(t.opacity_logits[ids])
        fade = c.fade[k] if c.fade is not None else torch.full_like(w, k + 1 == len(tiers), dtype=torch.bool)
        if bool(fade.any()):  # rows leaving without a parent taking over: faded out
            a = a * torch.where(fade, w.to(a.dtype), torch.ones_like(a))
        if k + 1 < len(tiers) and not whole:
            h = torch.nonzero((w < 1.0) & ~fade).flatten()  # rows in a hand-over
            if h.numel():
                new = _handed_over(t, tiers[k + 1], ids[h], w[h], mu[h], ls[h], q[h], col[h], a[h])
                # rows gathered for this frame: written in place (out of place where autograd records)
                mu, ls, q, col, a = (x.index_put_((h,), v) if not torch.is_grad_enabled() or not v.requires_grad
                                     else x.index_put((h,), v) for x, v in zip((mu, ls, q, col, a), new))
        for lst, v in zip(out, (mu, q, torch.exp(ls), a, col)):
            lst.append(v)
    return tuple(v[0] if len(v) == 1 or all(x.numel() == 0 for x in v[1:]) else torch.cat(v) for v in out)
