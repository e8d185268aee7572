"""A drop-in for ``gsplat.rasterization`` with CLoD-GS level of detail.

:func:`clod_rasterization` takes ``gsplat.rasterization``'s arguments (activated scales and
opacities, ``viewmats`` [C, 4, 4], ``Ks`` [C, 3, 3], ...) plus the per-Gaussian distance decay
``sigma_d`` and either a virtual distance scale ``s_v`` or a Gaussian ``budget``. Per camera it
applies Eq. 2 (``alpha'' = alpha exp(-(d' s_v)^2 / (2 ReLU(sigma_d)^2 + eps))``) and the
``alpha'' > tau s_v`` mask (or the exact budget selection of :mod:`clod_adapter.lod.budget`), and hands
the selected Gaussians to :func:`clod_adapter.render.rasterization` (gsplat on CUDA, CPU
otherwise). The selection is the one :func:`clod_adapter.lod.draw.render_lod` makes, so both
give the same image.

A model with merged tiers linked into a merge tree (docs/method.md "The merge tree") passes them
too (``parents=``, each tier's own ``parents`` nested in it, and ``lod_nodes=``), and an
``s_v`` or a budget draws one cut of the tree as ``render_lod`` draws it
(:func:`clod_adapter.lod.cut.tree_select`). :func:`clod_kwargs` gives every LoD keyword of an
adapted model.

Without ``sigma_d``, or with neither ``s_v`` nor ``budget``, it is exactly ``rasterization``.
"""
from __future__ import annotations

from types import SimpleNamespace
from typing import Any, Dict, Optional, Tuple

import torch
from torch import Tensor

from . import rule as lod
from . import tree
from ..render.dispatch import rasterization
from .budget import Budget, as_budget
from .draw import PAPER
from .view import view_lod_tensors
from .cut import tree_select

__all__ = ["clod_rasterization", "clod_kwargs"]

_GAINS = ("opacity_logit_gain", "log_scale_gain", "sh0_gain")
#: the tensors a ``parents=`` mapping must hold (activated ``scales`` / ``opacities``, as the model's)
PARENT_KEYS = ("means", "quats", "scales", "opacities", "colors", "sigma_d")


def clod_kwargs(model) -> Dict[str, Any]:
    """Every LoD keyword argument of :func:`clod_rasterization` for an adapted model
    (:class:`clod_adapter.gaussians.Gaussians`, e.g. ``load_model(".../point_cloud.ply")``):
    ``sigma_d`` [N], ``lod_settings``, ``opacity_logits`` [N], the level gains (``opacity_logit_gain`` [N],
    ``log_scale_gain`` [N], ``sh0_gain`` [N, 1, 3]; None where the model has none) and, for a
    model with merged tiers, ``parents`` (a dict of the first parent tier's :data:`PARENT_KEYS`
    tensors, its gains, its own ``lod_settings`` and ``parent``/``exit``/``d_ref``, and the next tier nested
    in it as its own ``parents``) and, for a merge tree, ``lod_nodes``. Add ``s_v=``
    or ``budget=``.

    Raises:
        ValueError: the model has no ``sigma_d`` (not adapted by ``clod-adapt``).
    """
    if model.sigma_d is None:
        raise ValueError("clod_kwargs: the model has no sigma_d (run clod-adapt first)")
    kw: Dict[str, Any] = {"sigma_d": model.sigma_d, "lod_settings": model.lod, "opacity_logits": model.opacity_logits,
                          **{k: getattr(model, k) for k in _GAINS}}
    p = model.parents
    if p is not None:
        kw["parents"] = _parent_dict(p)
    if "parent" in model.extra:  # a merge tree: its own rows' node data
        kw["lod_nodes"] = {k: model.extra[k] for k in tree.NODE_KEYS if k in model.extra}
    return kw


def _parent_dict(p) -> Dict[str, Any]:
    """A parent tier as ``parents=`` takes it; its own parent tier nested under ``"parents"`` (and,
    in a merge tree, its rows' parents in that tier under ``"parent"``)."""
    d = {**{k: getattr(p, k) for k in PARENT_KEYS}, **{k: getattr(p, k) for k in _GAINS},
         "opacity_logits": p.opacity_logits, "lod_settings": p.lod}
    if p.parents is not None:
        d["parents"] = _parent_dict(p.parents)
    for key in tree.NODE_KEYS:  # a merge tree's node data
        if key in p.extra:
            d[key] = p.extra[key]
    return d


def _tree_tier(means, quats, scales, logits, colors, sigma_d, settings, parent, above, exit_=None, d_ref=None):
    """One tier of a merge tree as :class:`clod_adapter.gaussians.Gaussians` (``colors`` [N, K, 3]
    SH, or [N, D] stored as a degree-0 block and drawn as given), its parents ``above``."""
    from dataclasses import replace as _replace

    from ..gaussians import Gaussians

    col = colors if colors.ndim == 3 else colors[:, None, :]
    g = Gaussians(means=means, quats=quats, log_scales=torch.log(scales), opacity_logits=logits,
                  sh0=col[:, :1], shN=col[:, 1:],
                  sigma_d=sigma_d, lod=settings,
                  extra={k: v for k, v in (("parent", parent), ("exit", exit_), ("d_ref", d_ref)) if v is not None})
    return _replace(g, parents=above)


def _tree_model(means, quats, scales, logits, colors, sigma_d, settings, node, parents, per_cam: Optional[int]):
    """The model and its nested ``parents=`` tiers as one tree (:mod:`clod_adapter.lod.tree`);
    ``per_cam``: the camera whose colours to take from [C, N, D] colours.

    Raises:
        ValueError: a tier's dict misses one of :data:`PARENT_KEYS` or has a ``sigma_d`` of the
            wrong shape."""
    def build(d, settings_above):
        _check_parents(d)
        st = d.get("lod_settings") or settings_above
        col = d["colors"][per_cam] if per_cam is not None else d["colors"]
        above = build(d["parents"], st) if (d.get("parents") is not None and st.tier_s_v > 0) else None
        return _tree_tier(d["means"], d["quats"], d["scales"], _logits(d["opacities"], d.get("opacity_logits")),
                          col, d["sigma_d"], st, d.get("parent"), above, d.get("exit"), d.get("d_ref"))

    col = colors[per_cam] if per_cam is not None else colors
    return _tree_tier(means, quats, scales, logits, col, sigma_d, settings, node[0], build(parents, settings), *node[1:])


def _logits(opacities: Tensor, logits: Optional[Tensor] = None) -> Tensor:
    if logits is not None:
        if logits.shape != opacities.shape:
            raise ValueError(f"clod_rasterization: opacity_logits must be {list(opacities.shape)}, got {list(logits.shape)}")
        return logits
    a = opacities.clamp(1e-30, 1.0)
    return torch.log(a) - torch.log1p(-a.clamp_max(1.0 - 1e-7))  # the view works on raw logits


def _check_parents(parents: Dict[str, Any]) -> None:
    missing = [k for k in PARENT_KEYS if parents.get(k) is None]
    if missing:
        raise ValueError(f"clod_rasterization: parents needs {', '.join(missing)}")
    m = parents["means"].shape[0]
    if tuple(parents["sigma_d"].shape) != (m,):
        raise ValueError(f"clod_rasterization: parents' sigma_d must be [{m}], got {tuple(parents['sigma_d'].shape)}")

# gsplat.rasterization keyword arguments accepted when they hold gsplat's default (no effect here).
_NOOP_DEFAULTS = {
    "absgrad": False, "sparse_grad": False, "distributed": False, "camera_model": "pinhole",
    "covars": None, "segmented": False, "channel_chunk": 32, "with_ut": False, "with_eval3d": False,
    "rolling_shutter": None, "radial_coeffs": None, "tangential_coeffs": None,
    "thin_prism_coeffs": None, "ortho": False,
}


def _check_lod_args(means, sigma_d, s_v, viewmats, Ks, gsplat_args) -> None:
    """:func:`clod_rasterization`'s checks of a LoD call (the errors it documents)."""
    N = means.shape[0]
    if tuple(sigma_d.shape) != (N,):
        raise ValueError(f"clod_rasterization: sigma_d must be [{N}], got {tuple(sigma_d.shape)}")
    if s_v is not None and not s_v >= 1.0:
        raise ValueError(f"clod_rasterization: s_v must be >= 1, got {s_v}")
    if viewmats.ndim != 3 or Ks.ndim != 3 or viewmats.shape[0] != Ks.shape[0]:
        raise ValueError(f"clod_rasterization: viewmats [C, 4, 4] and Ks [C, 3, 3] expected, got "
                         f"{tuple(viewmats.shape)} and {tuple(Ks.shape)}")
    if tuple(gsplat_args) != (0.01, 1e10, 0.0, 0.3, 16):
        raise ValueError("clod_rasterization: with LoD only gsplat's defaults near_plane=0.01, far_plane=1e10, "
                         "radius_clip=0, eps2d=0.3, tile_size=16 are supported")


def _refuse_unsupported(packed: bool, render_mode: str, rasterize_mode: str, kwargs: dict) -> None:
    """Raise on a gsplat mode or keyword this hook does not implement (gsplat's defaults pass)."""
    if render_mode != "RGB":
        raise ValueError(f"clod_rasterization: only render_mode='RGB' is supported, got {render_mode!r}")
    if rasterize_mode != "classic":
        raise ValueError(f"clod_rasterization: only rasterize_mode='classic' is supported, got {rasterize_mode!r}")
    del packed  # packed / unpacked give the same image; the backends render unpacked
    for k, v in kwargs.items():
        if k in _NOOP_DEFAULTS:
            if v != _NOOP_DEFAULTS[k]:
                raise ValueError(f"clod_rasterization: {k}={v!r} is not supported "
                                 f"(only gsplat's default {_NOOP_DEFAULTS[k]!r})")
        else:
            raise TypeError(f"clod_rasterization: unexpected keyword argument {k!r}")


def clod_rasterization(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Optional[Tensor] = None,
    render_mode: str = "RGB",
    rasterize_mode: str = "classic",
    *,
    sigma_d: Optional[Tensor] = None,
    s_v: Optional[float] = None,
    budget: Optional[float | int | Budget] = None,
    lod_settings: Optional[lod.LodSettings] = None,
    opacity_logit_gain: Optional[Tensor] = None,
    log_scale_gain: Optional[Tensor] = None,
    sh0_gain: Optional[Tensor] = None,
    parents: Optional[Dict[str, Any]] = None,
    lod_nodes: Optional[Dict[str, Tensor]] = None,
    opacity_logits: Optional[Tensor] = None,
    tau: Optional[float] = None,
    eps: Optional[float] = None,
    min_s_v: float = 1.0,
    backend: str = "auto",
    **kwargs: Any,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """``gsplat.rasterization`` with CLoD-GS level of detail (Eq. 2 and the ``tau s_v`` mask).

    Args:
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
        far_plane, radius_clip, eps2d, sh_degree, tile_size, backgrounds: as
            ``gsplat.rasterization`` (activated ``scales`` [N, 3] and ``opacities`` [N];
            ``colors`` [N, D], [C, N, D] or SH [N, K, 3]; ``backgrounds`` [C, D]).
        packed: accepted for compatibility (the image does not depend on it).
        render_mode, rasterize_mode: only ``"RGB"`` and ``"classic"``.
        sigma_d: [N] raw per-Gaussian distance decay (the adapted model's ``sigma_d``).
        s_v: virtual distance scale (>= 1); render the Gaussians with ``alpha'' > tau s_v``.
        budget: instead of ``s_v``: render exactly this many Gaussians (int) or this fraction
            of N (float in [0, 1]) per camera, ``s_v`` solved per camera (capped by the
            Gaussians in view; never more; raised to at least ``min_s_v``, see ``render_lod``),
            or a :class:`clod_adapter.lod.budget.Budget` (its own ``min_s_v``; a merge tree takes
            every kind, other models count budgets: ``count``, ``share``, ``in_view``).
        lod_settings: how the model is drawn (:class:`clod_adapter.lod.rule.LodSettings`; the
            adapted .ply's ``Gaussians.lod``); None: the paper's Eq. 2 drawing.
        opacity_logit_gain, log_scale_gain: [N] level gains, sh0_gain: [N, 1, 3] (SH colours
            only): the adapted model's (None: none).
        parents: a merge tree's first parent tier (:func:`clod_kwargs`): ``means`` [M, 3],
            ``quats`` [M, 4], ``scales`` [M, 3], ``opacities`` [M] (activated), ``colors`` (as
            ``colors``, M rows), ``sigma_d`` [M], optional gains, ``opacity_logits`` and
            ``lod_settings`` (the tier's own), its ``parent``/``exit``/``d_ref`` and the next tier as its
            own ``parents``. Drawn only with ``lod_settings.tree`` (below); otherwise not read.
        lod_nodes: a merge tree's node data of the N Gaussians, as each tier's dict in ``parents``
            holds its own (:func:`clod_kwargs`; docs/lod_rule.md "The file"): ``"parent"`` [N] int,
            each one's parent in ``parents``; ``"exit"`` [N] float, the exit constants (+inf:
            the parent's lead); ``"d_ref"`` [N] float, the reference distances a budget's cut uses (needed for a
            budget). With ``lod_settings.tree`` an ``s_v`` or a budget draws one cut of the tree
            (:func:`clod_adapter.lod.cut.tree_select`).
        opacity_logits: [N] the raw opacities ``opacities`` came from: the rule works on logits
            (the gains shift them), and a float32 opacity near 1 keeps few digits of ``1 - o``
            (exactly 1 above a logit of ~16.6), so ``log(o / (1 - o))`` returns logits above ~14
            off by up to ~2 (None: recovered so). ``parents`` may hold its own.
        tau, eps: LoD threshold and Eq. 2's epsilon (default: ``lod_settings``', else 0.005 / 1e-8).
        min_s_v: budget mode: lowest ``s_v`` used (1 = full detail; 0: exactly ``budget``).
        backend: ``"auto"`` | ``"cpu"`` | ``"gsplat"`` (see ``clod_adapter.render.rasterization``).
        **kwargs: other gsplat keywords, only at their defaults.

    Returns:
        (render_colors [C, H, W, D], render_alphas [C, H, W, 1], meta). Without LoD, meta is
        the rasteriser's. With LoD, each camera is rasterised with its own subset: for C = 1
        meta is that call's meta (its per-Gaussian arrays index ``lod_indices[0]``), for C > 1
        ``meta["cameras"]`` lists the per-camera metas; in both cases meta also has
        ``lod_s_v`` (list of C floats), ``lod_n_rendered`` (list of C ints: parents included),
        ``lod_indices`` (list of C [k_c] int64 tensors into the N input Gaussians),
        ``lod_n_parents`` (list of C ints: every parent tier's), ``lod_parent_indices`` (list of
        C [p_c] int64 tensors into the M parents; empty without a tree) and
        ``lod_tier_indices`` (per camera, a list with one such tensor per parent tier of the
        tree; empty without a tree). A tree's cut is rasterised as one set: the camera's meta
        numbers its rows after the N Gaussians and the tiers before it (``visible_ids``).

    Raises:
        ValueError: ``s_v`` and ``budget`` both given, ``s_v < 1``, ``sigma_d`` of the wrong
            shape, ``parents`` missing a tensor, an unsupported mode or keyword value, a cost or
            time budget on a model that is not a merge tree.
        TypeError: a ``budget`` that is not a number or a ``Budget``.
    """
    _refuse_unsupported(packed, render_mode, rasterize_mode, kwargs)
    common = dict(near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d,
                  sh_degree=sh_degree, tile_size=tile_size, backend=backend)
    if s_v is not None and budget is not None:
        raise ValueError("clod_rasterization: give s_v or budget, not both")
    budget = as_budget(budget, min_s_v)  # gsplat-style numbers become one Budget here
    if sigma_d is None or (s_v is None and budget is None):
        return rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                             backgrounds=backgrounds, **common)
    _check_lod_args(means, sigma_d, s_v, viewmats, Ks, (near_plane, far_plane, radius_clip, eps2d, tile_size))
    C = viewmats.shape[0]
    per_cam_colors = sh_degree is None and colors.ndim == 3
    w, h = int(width), int(height)
    gains = {"opacity_logit_gain": opacity_logit_gain, "log_scale_gain": log_scale_gain, "sh0_gain": sh0_gain}
    logits = _logits(opacities, opacity_logits)
    if parents is not None and lod_settings is not None and lod_settings.tree and lod_settings.tier_s_v > 0:
        nodes = lod_nodes or {}
        if "parent" not in nodes or "exit" not in nodes:
            raise ValueError("clod_rasterization: lod_settings.tree needs lod_nodes= with 'parent' and 'exit' "
                             "(clod_kwargs gives them)")
        return _tree_frames(lambda c: _tree_model(means, quats, scales, logits, colors, sigma_d, lod_settings,
                                                  (nodes.get("parent"), nodes.get("exit"), nodes.get("d_ref")), parents, c),
                            per_cam_colors, colors.ndim == 3 and not per_cam_colors, viewmats, Ks, w, h, s_v, budget,
                            backgrounds, sh_degree, backend)
    if budget is not None and not budget.counts:
        raise ValueError(f"clod_rasterization: a {budget.kind} budget needs a merge tree (count budgets otherwise)")
    imgs, alphas, metas, svs, counts, indices, n_par, par_idx, tier_idx = [], [], [], [], [], [], [], [], []
    for c in range(C):
        col = colors[c] if per_cam_colors else colors
        cam = SimpleNamespace(viewmat=viewmats[c], K=Ks[c], width=w, height=h)
        view = view_lod_tensors(means, quats, scales, logits, col, cam, sigma_d=sigma_d, gains=gains,
                                settings=lod_settings, tau=tau, eps=eps)
        sel = view.select(s_v, budget=budget, eta_grad=PAPER)
        bg = None if backgrounds is None else backgrounds[c]
        rc, ra, meta = view.rasterize(sel, background=bg, sh_degree=sh_degree, backend=backend,
                                      colors=None if sh_degree is not None else col)
        idx = sel.indices
        imgs.append(rc[None])
        alphas.append(ra[None])
        metas.append(meta)
        svs.append(sel.s_v)
        n_par.append(0)
        counts.append(int(idx.numel()))
        indices.append(idx)
        par_idx.append(idx.new_zeros(0))
        tier_idx.append([])
    out_meta: Dict[str, Any] = dict(metas[0]) if C == 1 else {"cameras": metas, "n_cameras": C}
    out_meta.update(lod_s_v=svs, lod_n_rendered=counts, lod_indices=indices, lod_n_parents=n_par,
                    lod_parent_indices=par_idx, lod_tier_indices=tier_idx)
    return torch.cat(imgs, 0), torch.cat(alphas, 0), out_meta


def _tree_frames(model_of, per_cam_colors: bool, sh_colors: bool, viewmats, Ks, w, h, s_v,
                 budget: Optional[Budget], backgrounds, sh_degree, backend):
    """:func:`clod_rasterization` of a merge tree: per camera the cut of :func:`clod_adapter.lod.cut.tree_select`
    rasterised as one set (meta as documented there; ``lod_tier_indices`` the cut's rows per tier).
    ``model_of(c)``: the tree as :class:`Gaussians` with camera ``c``'s colours (None: shared
    colours, built once); ``sh_colors``: the colours are SH [N, K, 3] (else [N, D])."""
    imgs, alphas, metas, svs, counts, indices, n_par, par_idx, tier_idx = [], [], [], [], [], [], [], [], []
    g = None
    for c in range(viewmats.shape[0]):
        if g is None or per_cam_colors:
            g = model_of(c if per_cam_colors else None)
        cam = SimpleNamespace(viewmat=viewmats[c], K=Ks[c], width=w, height=h)
        cut, (m, q, sc, op, col) = tree_select(g, cam, s_v, budget=budget)
        col = col if sh_colors else col[:, 0]  # [k, 1, D] back to [k, D]
        bg = None if backgrounds is None else backgrounds[c][None]
        rc, ra, meta = rasterization(m, q, sc, op, col, viewmats[c][None], Ks[c][None], w, h, sh_degree=sh_degree,
                                     backgrounds=bg, backend=backend)
        imgs.append(rc)
        alphas.append(ra)
        metas.append(meta)
        svs.append(cut.s_v)
        counts.append(cut.n_drawn)
        indices.append(cut.ids[0])
        n_par.append(cut.n_drawn - int(cut.ids[0].numel()))
        par_idx.append(cut.ids[1])
        tier_idx.append(list(cut.ids[1:]))
    out_meta: Dict[str, Any] = dict(metas[0]) if len(metas) == 1 else {"cameras": metas, "n_cameras": len(metas)}
    out_meta.update(lod_s_v=svs, lod_n_rendered=counts, lod_indices=indices, lod_n_parents=n_par,
                    lod_parent_indices=par_idx, lod_tier_indices=tier_idx)
    return torch.cat(imgs, 0), torch.cat(alphas, 0), out_meta
