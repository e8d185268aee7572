"""The CLoD-GS mechanism (Cheng et al., "CLoD-GS: Continuous Level-of-Detail via 3D Gaussian
Splatting", ICLR 2026), in one place.

For a camera centred at ``c`` and a virtual distance scale ``s_v >= 1``:

* ``d_i = ||mu_i - c||`` and ``d'_i = d_i / max_{j in frustum} d_j``  (frustum-normalised distance)
* ``alpha''_i = alpha_i * exp(-(d'_i s_v)^2 / (2 ReLU(sigma_d_i)^2 + eps))``            (Eq. 2)
* only Gaussians with ``alpha''_i > tau * s_v`` are rasterised                        (the LoD mask)
* training draws ``s_v ~ U(1, max_sv)``, adds
  ``L_reg = (s_v - 1)^2 ReLU(eta - s_v^-1.5)^2`` (eta = rendered fraction) and weights the total
  ``L = w_s (L_render + lambda_reg L_reg)`` with ``w_s = (1 - 0.5 s_v / max_sv)^2``.

The hard 0/1 mask has no gradient, so ``L_reg`` as written never reaches ``sigma_d``. We work in
log space with the *margin* ``m_i = log alpha''_i - log(tau s_v)`` (``m_i > 0`` <=> rendered) and
offer three estimators of ``eta`` (:data:`ETA_ESTIMATORS`):

* ``"paper"``: the hard fraction, as written (zero gradient; kept for the ablation);
* ``"sigmoid"``: the relaxation ``mean(sigmoid(m_i / T))`` (value and gradient soft);
* ``"ste"`` (default): straight-through, value of the hard fraction, gradient of the relaxation.

How survivors are drawn (:data:`FADES`, :class:`LodSettings`):

* ``"eq2"`` (the paper): with Eq. 2's ``alpha''``. At large ``s_v`` this dims every survivor, not
  only the ones about to leave (fern, 25 % of the Gaussians: 8.9 dB against 16.9 dB for the same
  Gaussians drawn with their own opacity).
* ``"window"`` (default of the calibrated schedule): with their own opacity at the level
  (:func:`level_of_fraction` of the share drawn, learned per-Gaussian level gains,
  :class:`clod_adapter.gaussians.Gaussians`), times :func:`fade_weight` ``= clamp(m / w, 0, 1)``:
  only a Gaussian within ``w`` of its exit (``0 < m < w``) is faded, and it reaches 0 exactly
  where the mask drops it, so the image is continuous in ``s_v`` (no popping). The width opens
  from 0 at ``s_v = 1`` (:func:`fade_width_at`), so full detail is drawn unfaded.

The calibrated schedule sets ``sigma_d`` from a ranking (:func:`calibrate_sigma_d`) so that the
rendered fraction follows ``s_v^-1.5`` (the paper's count target) by construction.

All functions work on any float dtype; the exponent is evaluated in float32 at least, so
float16/bfloat16 inputs do not overflow.
"""
from __future__ import annotations

import math
import weakref
from typing import Optional

import torch
from torch import Tensor

from ..lod_settings import (DEFAULT_EPS, DEFAULT_FADE_WIDTH, DEFAULT_TAU, EPS_FLOOR, ETA_ESTIMATORS,  # noqa: F401
                            FADE_RAMP_S_V, FADES, Estimator, Fade, LodSettings)
from ..render.native import load as load_kernels, wanted as kernels_wanted
from ..render.projection import camera_center  # noqa: F401 (lod.camera_center: where the LoD terms use it)


def _work_dtype(*ts: Tensor) -> torch.dtype:
    dt = torch.promote_types(ts[0].dtype, torch.float32)
    for t in ts[1:]:
        dt = torch.promote_types(dt, t.dtype)
    return dt


#: per-tensor derived values (:func:`cached_value`): (id, name) -> (weakref, version, value)
_CACHE: dict = {}
_CACHE_MAX = 64


def cached_value(t: Tensor, name: str, make) -> Tensor:
    """``make(t)``, cached per tensor, in-place version (``Tensor._version``: an optimiser step
    makes a new value) and ``name``. Only for values without gradient. A write through
    ``tensor.data`` does not change the version: code that edits a model that way (none here)
    must pass a new tensor."""
    try:
        version = t._version
    except RuntimeError:  # an inference tensor (torch.inference_mode) has no version: no caching
        return make(t)
    key = (id(t), name)
    hit = _CACHE.get(key)
    if hit is not None and hit[0]() is t and hit[1] == version and hit[2].device == t.device:
        return hit[2]
    val = make(t)
    try:  # oldest first; another thread (the viewer's) may be evicting too
        while len(_CACHE) >= _CACHE_MAX:
            _CACHE.pop(next(iter(_CACHE)), None)
    except (RuntimeError, StopIteration):
        pass
    try:
        _CACHE[key] = (weakref.ref(t), version, val)
    except TypeError:  # not weak-referenceable: no caching
        pass
    return val


def centre_columns(means: Tensor, dtype: torch.dtype) -> Tensor:
    """[3, N] contiguous copy of ``means`` [N, 3] (detached, in ``dtype``), cached per tensor and
    in-place version (:func:`cached_value`). The per-frame terms (:func:`in_frustum`,
    :func:`normalized_distances`, :func:`frame_terms`) run on these rows: elementwise work on three
    contiguous [N] rows is 4-9x faster on the CPU than the same arithmetic on [N, 3] (a [N, 3] x
    [3, 3] product took 0.6 ms at 60,000 Gaussians, the rows 0.07 ms)."""
    return cached_value(means, f"columns:{dtype}", lambda m: m.detach().to(dtype).t().contiguous())


def activated(raw: Tensor, fn: str) -> Tensor:
    """``torch.exp(raw)`` (``fn="exp"``: scales of ``log_scales``) or ``torch.sigmoid(raw)``
    (``fn="sigmoid"``: opacities of ``opacity_logits``), same shape and dtype. Without
    autograd (``raw`` needs no gradient, or grad mode is off) the value is cached per tensor and
    version (:func:`cached_value`): a frame of a fixed model then does not re-activate all N rows
    (0.3 ms for [60,000, 3] scales on 2 threads, a tenth of a coarse level's selection)."""
    f = {"exp": torch.exp, "sigmoid": torch.sigmoid}[fn]
    if raw.requires_grad and torch.is_grad_enabled():
        return f(raw)
    return cached_value(raw, fn, lambda t: f(t.detach()))


def in_frustum(means: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int,
               near_plane: float = 0.01) -> Tensor:
    """Which Gaussian centres lie inside a pinhole camera's view frustum.

    Args:
        means: [N, 3] centres, world units.
        viewmat: [4, 4] world-to-camera (OpenCV axes, z forward; gsplat ``viewmats``).
        K: [3, 3] intrinsics in pixels.
        width, height: image size in pixels.
        near_plane: minimum camera-space depth (gsplat's default 0.01).

    Returns:
        [N] bool: ``z > near_plane`` and the projected centre ``(fx x / z + cx, fy y / z + cy)``
        inside ``[0, width) x [0, height)``, tested without the division (``0 <= fx x + cx z <
        width z`` for ``z > 0``); a non-finite centre is outside.
    """
    dt = _work_dtype(means, viewmat)
    cols = centre_columns(means, dt)
    R = viewmat[:3, :3].detach().to(dt).tolist()
    t = viewmat[:3, 3].detach().to(dt).tolist()

    def row(i: int) -> Tensor:  # camera-space coordinate i of every centre
        r = cols[0] * R[i][0]
        return r.add_(cols[1], alpha=R[i][1]).add_(cols[2], alpha=R[i][2]).add_(t[i])

    z = row(2)
    ok = z > near_plane
    for i, (f, c, size) in enumerate(((float(K[0, 0]), float(K[0, 2]), width), (float(K[1, 1]), float(K[1, 2]), height))):
        a = row(i).mul_(f).add_(z, alpha=c)  # = (pixel coordinate) * z
        ok &= a >= 0
        ok &= a < z * float(size)
    return ok


def normalized_distances(means: Tensor, center: Tensor, frustum: Tensor) -> Tensor:
    """Frustum-normalised distance ``d'_i = d_i / max_{j in frustum} d_j`` (CLoD-GS, Sec. 3).

    Args:
        means: [N, 3] centres, world units.
        center: [3] camera centre, world units.
        frustum: [N] bool, Gaussians inside the view frustum (see :func:`in_frustum`).

    Returns:
        [N] d' (dimensionless, >= 0; <= 1 inside the frustum). The normaliser is treated as a
        constant (detached). With an empty frustum the maximum over all Gaussians is used; with
        zero Gaussians an empty tensor is returned. The normaliser is clamped to >= 1e-12 so a
        camera sitting on every Gaussian gives d' = 0, never NaN.
    """
    if means.requires_grad and torch.is_grad_enabled():
        # |mu - c| with autograd: d = 0 gets gradient 0, not NaN
        diff = means - center.to(means.dtype)
        sq = diff.square() @ torch.ones(3, dtype=diff.dtype, device=diff.device)
        d = torch.where(sq > 0, sq.clamp_min(torch.finfo(sq.dtype).tiny).sqrt(), torch.zeros_like(sq))
    else:
        # no gradient: on the cached rows of the centres (this runs every frame)
        cols = centre_columns(means, means.dtype)
        c = center.detach().to(means.dtype).tolist()
        d = (cols[0] - c[0]).square_()
        d.add_((cols[1] - c[1]).square_()).add_((cols[2] - c[2]).square_()).sqrt_()
    if d.numel() == 0:
        return d
    dd = d.detach()
    # max over the frustum without a compacted copy (d >= 0, so 0 outside never wins)
    dmax = torch.where(frustum, dd, torch.zeros((), dtype=dd.dtype, device=dd.device)).max() \
        if bool(frustum.any()) else dd.max()
    dmax = torch.nan_to_num(dmax, nan=1.0, posinf=torch.finfo(dd.dtype).max)
    return d / dmax.clamp_min(1e-12)


def frame_terms(means: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int,
                near_plane: float = 0.01) -> tuple[Tensor, Tensor]:
    """The two per-frame terms every LoD frame starts from, in one call: ``(frustum [N] bool,
    d_norm [N])`` as :func:`in_frustum` and :func:`normalized_distances` give them (same
    arguments; ``d_norm`` in the centres' work dtype, no gradient).

    On the CPU this is one pass of the C++ kernel ``csrc/lod_terms.cpp`` (in double; one
    thread below 65,536 Gaussians, so a 60k-Gaussian frame does not pay OpenMP's wake-up of the
    second thread for each of the ~25 torch operations of the twin: ``python
    benchmarks/studies/frame_terms.py``); elsewhere, or without the extension, the two functions
    themselves (its twin, held to it by ``tests/test_lod_terms.py``). A centre within rounding
    of a frustum edge may fall on the other side in the two forms.

    Raises:
        ValueError: ``means`` requires grad with autograd on (use :func:`normalized_distances`).
    """
    if means.requires_grad and torch.is_grad_enabled():
        raise ValueError("frame_terms: no gradient; call normalized_distances for d' with autograd")
    dt = _work_dtype(means, viewmat)
    if means.shape[0] and kernels_wanted(means.device.type == "cpu"):
        cols = centre_columns(means, dt)
        vm = viewmat.detach().to(torch.float64)
        Kd = K.detach().to(torch.float64)
        c = camera_center(vm).tolist()
        fr, d = load_kernels().lod_frustum_distances(
            cols, vm[:3, :3].reshape(-1).tolist(), vm[:3, 3].tolist(), float(Kd[0, 0]), float(Kd[0, 2]),
            float(Kd[1, 1]), float(Kd[1, 2]), int(width), int(height), float(near_plane), c)
        return fr, d.to(means.dtype)
    fr = in_frustum(means, viewmat, K, width, height, near_plane)
    return fr, normalized_distances(means.detach(), camera_center(viewmat.detach()), fr)


def lod_log_attenuation(d_norm: Tensor, sigma_d: Tensor, s_v: float | Tensor,
                        eps: float = DEFAULT_EPS) -> Tensor:
    """Log of Eq. 2's factor: ``-(d' s_v)^2 / (2 ReLU(sigma_d)^2 + eps)``; [N], <= 0.

    Evaluated in at least float32. ``eps`` is floored at :data:`EPS_FLOOR` (a dead Gaussian,
    ``sigma_d <= 0``, then gets a large negative value rather than -inf/NaN, also for
    ``d' = 0``). Computed as ``-r^2`` with ``r = d' s_v / sqrt(den)``: the backward pass then
    only forms ``1 / sqrt(den)`` (<= 1e10), never ``x^2 / den^2``, so a stiff decay whose
    attenuation underflows to 0 gets a zero gradient instead of ``0 * inf = NaN``.
    """
    dt = _work_dtype(d_norm, sigma_d)
    x = d_norm.to(dt) * torch.as_tensor(s_v, dtype=dt, device=d_norm.device)
    sd = torch.relu(sigma_d.to(dt))
    r = x / torch.sqrt(2.0 * sd * sd + max(float(eps), EPS_FLOOR))
    return -(r * r)


def lod_opacities(opacities: Tensor, d_norm: Tensor, sigma_d: Tensor, s_v: float | Tensor,
                  eps: float = DEFAULT_EPS) -> Tensor:
    """Eq. 2: ``alpha''_i = alpha_i exp(-(d'_i s_v)^2 / (2 ReLU(sigma_d_i)^2 + eps))``.

    Args:
        opacities: [N] activated opacities alpha in [0, 1].
        d_norm: [N] frustum-normalised distances d' (:func:`normalized_distances`).
        sigma_d: [N] raw distance decay.
        s_v: virtual distance scale (>= 1), scalar.
        eps: Eq. 2's epsilon.

    Returns:
        [N] attenuated opacities in [0, alpha], dtype of ``opacities``.
    """
    att = torch.exp(lod_log_attenuation(d_norm, sigma_d, s_v, eps))
    return (opacities.to(att.dtype) * att).to(opacities.dtype)


def lod_margin(opacities: Tensor, d_norm: Tensor, sigma_d: Tensor, s_v: float | Tensor,
               tau: float = DEFAULT_TAU, eps: float = DEFAULT_EPS) -> Tensor:
    """Log-space margin ``m_i = log alpha''_i - log(tau s_v)``; rendered iff ``m_i > 0``. [N].

    Computed as ``log alpha + log-attenuation - log(tau s_v)`` so it stays finite where
    ``alpha''`` underflows (large s_v, tiny sigma_d). ``opacities`` of exactly 0 give -inf
    (never rendered, zero gradient: the log is taken through a double ``where``, so the
    backward pass never forms ``0 / 0``).
    """
    la = lod_log_attenuation(d_norm, sigma_d, s_v, eps)
    o = opacities.to(la.dtype)
    pos = o > 0
    log_alpha = torch.where(pos, torch.log(torch.where(pos, o, torch.ones_like(o))),
                            torch.full_like(o, -math.inf))
    s = torch.as_tensor(s_v, dtype=la.dtype, device=la.device)
    return log_alpha + la - torch.log(tau * s)


def lod_mask(opacities: Tensor, d_norm: Tensor, sigma_d: Tensor, s_v: float | Tensor,
             tau: float = DEFAULT_TAU, eps: float = DEFAULT_EPS,
             frustum: Optional[Tensor] = None) -> Tensor:
    """[N] bool: ``alpha''_i > tau * s_v`` (and inside ``frustum`` when given).

    The test of :func:`lod_margin` ``> 0`` without autograd, rearranged to
    ``log alpha > (d' s_v)^2 / (2 ReLU(sigma_d)^2 + eps) + log(tau s_v)`` and evaluated with
    in-place operations (about half the passes over [N]: it runs every frame). A Gaussian
    exactly at the boundary may differ from ``lod_margin > 0`` in the last bit of rounding.
    On the CPU with a float ``s_v`` this is one pass of the C++ kernel ``csrc/lod_terms.cpp``
    (in double), where it builds (:mod:`clod_adapter.render.native`); the torch form above is
    its twin (``tests/test_lod_terms.py``).
    """
    with torch.no_grad():
        dt = _work_dtype(d_norm, sigma_d)
        if isinstance(s_v, (int, float)) and kernels_wanted(d_norm.device.type == "cpu"):
            m = load_kernels().lod_mask(opacities.detach().to(dt).contiguous(), d_norm.detach().to(dt).contiguous(),
                                       sigma_d.detach().to(dt).contiguous(), float(s_v), float(tau), float(eps))
            return m & frustum if frustum is not None else m
        den = torch.relu(sigma_d.detach().to(dt)).square_().mul_(2.0).add_(max(float(eps), EPS_FLOOR))
        s = torch.as_tensor(s_v, dtype=dt, device=d_norm.device)
        thr = (d_norm.detach().to(dt) * s).square_().div_(den).add_(torch.log(tau * s))
        m = torch.log(opacities.detach().to(dt)) > thr  # log(0) = -inf: never drawn
    return m & frustum if frustum is not None else m


def lod_keep(opacities: Tensor, d_norm: Tensor, sigma_d: Tensor, s_v: float, frustum: Tensor,
             tau: float = DEFAULT_TAU, eps: float = DEFAULT_EPS, *,
             with_ids: bool = True) -> tuple[Optional[Tensor], int, int]:
    """What a frame at ``s_v`` keeps, as indices: ``(ids [k] int64 ascending where``
    :func:`lod_mask` ``is True, frustum.sum(), (mask & frustum).sum())``, no gradient
    (``with_ids=False``: ``ids`` is None, only the counts).

    ``opacities``, ``d_norm``, ``sigma_d`` [N] (one float dtype after promotion), ``frustum``
    [N] bool, ``s_v`` a float. The counts give the share of the frustum drawn (``eta``) and the
    level without a [N] mask: on the CPU one call of the C++ kernel ``csrc/lod_terms.cpp``
    (the mask in double, then per chunk the counts and the ids, in parallel), where the twin's
    ``nonzero`` and two sums are each a pass over [N] that wakes OpenMP's second thread (``python
    benchmarks/studies/frame_terms.py``: 0.47 against 0.97 ms at 60,000 Gaussians, 2 threads); the torch
    form here is its twin (``tests/test_lod_terms.py``). Source: CLoD-GS Eq. 2 (the mask).
    """
    with torch.no_grad():
        dt = _work_dtype(d_norm, sigma_d)
        if kernels_wanted(d_norm.device.type == "cpu"):
            ids, n_fr, n_kept = load_kernels().lod_keep(
                opacities.detach().to(dt).contiguous(), d_norm.detach().to(dt).contiguous(),
                sigma_d.detach().to(dt).contiguous(), frustum.contiguous(), float(s_v), float(tau), float(eps),
                bool(with_ids))
            return (ids if with_ids else None), int(n_fr), int(n_kept)
        m = lod_mask(opacities, d_norm, sigma_d, float(s_v), tau, eps)
        ids = torch.nonzero(m, as_tuple=False).squeeze(1) if with_ids else None
        return ids, int(frustum.sum()), int((m & frustum).sum())


def rendered_fraction(margin: Tensor, frustum: Optional[Tensor] = None, estimator: Estimator = "ste",
                      temperature: float = 1.0) -> Tensor:
    """Rendered fraction ``eta`` of the Gaussians in the frustum, with a chosen gradient.

    Args:
        margin: [N] log-space margins (:func:`lod_margin`).
        frustum: [N] bool or None (all Gaussians count).
        estimator: ``"paper"`` (hard count, no gradient), ``"sigmoid"`` (relaxation
            ``mean(sigmoid(m / temperature))``) or ``"ste"`` (hard value, relaxation gradient).
        temperature: relaxation width in log-opacity units (> 0).

    Returns:
        scalar tensor in [0, 1] (0 when the frustum is empty).

    Raises:
        ValueError: unknown estimator or temperature <= 0.
    """
    if estimator not in ETA_ESTIMATORS:
        raise ValueError(f"unknown eta estimator {estimator!r}; choose one of {ETA_ESTIMATORS}")
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    m = margin if frustum is None else margin[frustum]
    if m.numel() == 0:
        return margin.sum() * 0.0
    hard = (m > 0).to(m.dtype).mean()
    if estimator == "paper":
        return hard.detach()
    soft = torch.sigmoid(torch.nan_to_num(m, neginf=-1e4, posinf=1e4) / temperature).mean()
    if estimator == "sigmoid":
        return soft
    return hard.detach() + (soft - soft.detach())


def fade_weight(margin: Tensor, width: float = DEFAULT_FADE_WIDTH) -> Tensor:
    """Window fade ``clamp(m / width, 0, 1)`` of the margins ``m`` [N] (:func:`lod_margin`): 1 for
    a Gaussian well inside the level, falling linearly to 0 at its exit ``m = 0``. Its
    gradient reaches ``sigma_d`` (through ``m``) only inside the window, which is how training
    learns which Gaussians stay longest. ``-inf`` margins give 0; ``width = 0`` gives the hard
    mask ``m > 0``."""
    if width <= 0.0:
        return (margin > 0).to(margin.dtype)
    return torch.clamp(margin / float(width), 0.0, 1.0)


def fade_width_at(s_v: float, width: float = DEFAULT_FADE_WIDTH) -> float:
    """The window's width at ``s_v``: 0 at ``s_v = 1``, growing with ``ln s_v`` to ``width`` at
    :data:`FADE_RAMP_S_V` and constant beyond."""
    return float(width) * min(1.0, max(math.log(max(float(s_v), 1.0)) / math.log(FADE_RAMP_S_V), 0.0))


def full_detail_share(s_v: float, ramp: float = FADE_RAMP_S_V) -> float:
    """How much of full detail the window-fade drawing keeps at ``s_v``: 1 at ``s_v = 1``
    (every Gaussian in view, whatever its ``sigma_d``), falling with ``ln s_v`` to 0 at ``ramp``
    (the LoD rule alone; a view's :func:`ramp_s_v`, at least :data:`FADE_RAMP_S_V`), 0 beyond
    (:meth:`clod_adapter.lod.view.LodView.select`)."""
    return 1.0 - min(1.0, max(math.log(max(float(s_v), 1.0)) / math.log(max(float(ramp), FADE_RAMP_S_V)), 0.0))


def window_opacities(ids: Tensor, opacities: Tensor, opacity_logits: Tensor, d_norm: Tensor, sigma_d: Tensor,
                     s_v: float, level: float = 0.0, opacity_logit_gain: Optional[Tensor] = None,
                     tau: float = DEFAULT_TAU, eps: float = DEFAULT_EPS,
                     width: float = DEFAULT_FADE_WIDTH) -> Tensor:
    """The window fade's drawn opacities of the rows ``ids`` [k] int64:
    ``sigmoid(opacity_logits + level g) * fade_weight(lod_margin(...), width)`` (``g`` the
    opacity-logit gain, left out when None or at ``level <= 0``); returns [k] in [0, 1], float32
    (float64 when ``d_norm`` or ``sigma_d`` is float64).

    ``opacities`` (activated, the margin's alpha), ``opacity_logits``, ``d_norm``, ``sigma_d`` and
    the gain are [N]; ``width`` is the window's width at this ``s_v`` (:func:`fade_width_at`).
    With autograd on any input, or off the CPU, this is the torch form (the gradient reaches
    ``sigma_d`` through the margin, the gains through the logits); otherwise one pass of the C++
    kernel ``csrc/lod_terms.cpp`` over the k rows (in double), its twin
    (``tests/test_lod_terms.py``). Source: CLoD-GS Eq. 2 (the margin); the window fade is this
    project's (docs/method.md "The calibrated schedule").
    """
    dt = _work_dtype(d_norm, sigma_d)
    grad = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in
                                           (opacities, opacity_logits, d_norm, sigma_d, opacity_logit_gain))
    if not grad and kernels_wanted(d_norm.device.type == "cpu"):
        g = opacity_logit_gain if opacity_logit_gain is not None and level > 0 else None
        return load_kernels().lod_window_opacities(
            ids.contiguous(), opacities.detach().to(dt).contiguous(), opacity_logits.detach().to(dt).contiguous(),
            g.detach().to(dt).contiguous() if g is not None else torch.empty(0, dtype=dt),
            d_norm.detach().to(dt).contiguous(), sigma_d.detach().to(dt).contiguous(),
            float(s_v), float(level), float(tau), float(eps), float(width))
    margin = lod_margin(opacities.index_select(0, ids), d_norm.index_select(0, ids),
                        sigma_d.index_select(0, ids), s_v, tau, eps)
    logits = opacity_logits.index_select(0, ids)
    if opacity_logit_gain is not None and level > 0:
        logits = logits + level * opacity_logit_gain.index_select(0, ids)
    return torch.sigmoid(logits) * fade_weight(margin, width)


def ramp_cap(max_sv: float) -> float:
    """The longest ramp :func:`ramp_s_v` gives: ``sqrt(max_sv)`` (half the trained range in
    ``ln s_v``), at least :data:`FADE_RAMP_S_V`."""
    return max(FADE_RAMP_S_V, math.sqrt(max(float(max_sv), 1.0)))


def ramp_s_v(share_at_1: float, max_sv: float) -> float:
    """Where a view's ramp from full detail to the LoD rule ends (:func:`full_detail_share`):
    ``FADE_RAMP_S_V * share_at_1^(-2/3)``, within [:data:`FADE_RAMP_S_V`, :func:`ramp_cap`].

    ``share_at_1`` (in [0, 1]) is the share of the Gaussians in the frustum that Eq. 2's mask
    keeps at ``s_v = 1`` in this view. Where it is near 1 (the view's normaliser as in the
    training views) the ramp is the fixed 1.1; where a view's normaliser is shorter (a
    360-degree capture looking at a near wall: skull's first test view keeps 61 %) full detail
    draws Gaussians the rule has already left out, and the ramp lasts until the target share
    ``s_v^-1.5`` has fallen by the same factor, so they fade out over as many ``s_v`` steps as
    the rule's own exits instead of all at once (``benchmarks/studies/web_popping_steps.py``)."""
    sh = float(share_at_1)
    if not sh > 0.0:
        return ramp_cap(max_sv)
    return min(max(FADE_RAMP_S_V * min(sh, 1.0) ** (-2.0 / 3.0), FADE_RAMP_S_V), ramp_cap(max_sv))


def level(s_v: float | Tensor, max_sv: float, level_max: float = 1.0) -> float:
    """Level coordinate ``l = clamp(ln s_v / ln max_sv, 0, level_max)`` of the learned level
    gains: 0 at full detail (``s_v = 1``, the input's attributes), 1 at the trained maximum,
    ``level_max`` (:attr:`LodSettings.level_max`; default 1: held at 1 beyond ``max_sv``) at
    ``max_sv^level_max`` and beyond. ``max_sv = 1`` gives 0 everywhere."""
    if not max_sv > 1.0:
        return 0.0
    s = float(s_v)
    return min(max(math.log(max(s, 1.0)) / math.log(max_sv), 0.0), float(level_max))


def level_of_fraction(fraction: float, max_sv: float, level_max: float = 1.0) -> float:
    """The level of the gains when ``fraction`` of the Gaussians in view is drawn:
    :func:`level` of ``fraction^(-2/3)`` (the ``s_v`` whose target fraction it is). Taken from the
    drawn share, not from ``s_v``, so a model draws the same gains for the same share whatever the
    view and however exactly its ``sigma_d`` follows ``s_v^-1.5``. With cost levels a step's
    count share reaches ``max_sv^-1.5`` from ``s_v`` about 3.2 on (the weighted share is the
    target, not the count), so ``level_max = 1`` holds the gains of the coarsest trained levels
    at one value; above 1 they grow on (docs/studies.md)."""
    if not fraction > 0.0:
        return float(level_max) if max_sv > 1.0 else 0.0
    return level(min(float(fraction), 1.0) ** (-2.0 / 3.0), max_sv, level_max)


def s_v_for_fraction(fraction: float) -> float:
    """Inverse of :func:`target_fraction`: the ``s_v`` whose target fraction is ``fraction``
    (``fraction^(-2/3)``; ``fraction`` in (0, 1])."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    return float(fraction) ** (-2.0 / 3.0)


def calibrate_sigma_d(score: Tensor, opacities: Tensor, d_ref: Tensor, *, tau: float = DEFAULT_TAU,
                      eps: float = DEFAULT_EPS, fade_width: float = DEFAULT_FADE_WIDTH,
                      sigma_max: float = 1e3, cost: Optional[Tensor] = None) -> Tensor:
    """``sigma_d`` that turns a ranking into Eq. 2 levels: the Gaussian of rank quantile ``q``
    (0 = highest ``score``) keeps full opacity up to ``s_v = q^(-2/3)`` at its reference distance.

    With ``cost`` [N] (each Gaussian's mean frame cost, e.g. its footprint in pixels averaged
    over the training views, :func:`clod_adapter.lod.cost.splat_cost`) ``q`` is the *cost* quantile:
    the share of the total cost taken by the Gaussians ranked before it (plus half its own), so
    the drawn set at ``s_v`` costs ``s_v^-1.5`` of the full frame on average: levels in frame
    cost rather than in count. Without it ``q`` is the rank quantile (levels in count).

    With ``S = q^(-2/3)``, Eq. 2's margin at ``S`` is set to the fade width ``w``:
    ``log(alpha / tau) - a S^2 - log S = w`` with ``a = d_ref^2 / (2 sigma_d^2)``, so at ``s_v``
    the Gaussians drawn at full opacity are the top ``s_v^-1.5`` of the ranking (the paper's
    count target), none is faded at ``s_v = 1``, and each fades out just after its level.
    A Gaussian too faint to reach ``S`` (``alpha <= tau S e^w``) gets ``sigma_max`` (no distance
    decay: it leaves at ``s_v = alpha / tau`` at the latest). Ties are broken by index.

    Args:
        score: [N] ranking score (higher = kept longer), e.g. LightGaussian significance or the
            learned reference critical scale.
        opacities: [N] activated opacities.
        d_ref: [N] reference frustum-normalised distance of each Gaussian (e.g. its median d'
            over the training views); 0 gives ``sigma_max``.
        tau, eps, fade_width: as :class:`LodSettings`.
        sigma_max: the largest value returned.

    Returns:
        [N] float32 ``sigma_d`` in (0, sigma_max].
    """
    n = score.numel()
    out = torch.full((n,), float(sigma_max), dtype=torch.float32, device=score.device)
    if n == 0:
        return out
    order = torch.sort(-score.detach().double(), stable=True).indices
    q = torch.empty(n, dtype=torch.float64, device=score.device)
    if cost is None:
        q[order] = (torch.arange(n, dtype=torch.float64, device=score.device) + 0.5) / n
    else:
        c = cost.detach().double().clamp_min(0.0).index_select(0, order)
        total = float(c.sum())
        if not total > 0:
            c, total = torch.ones_like(c), float(n)
        q[order] = ((torch.cumsum(c, 0) - 0.5 * c) / total).clamp(1e-12, 1.0)
    S = q ** (-2.0 / 3.0)
    alpha = opacities.detach().double().clamp(1e-300, 1.0)
    rhs = torch.log(alpha / tau) - float(fade_width) - torch.log(S)  # = a S^2
    a = rhs / S ** 2
    d = d_ref.detach().double()
    ok = (rhs > 1e-6) & (d > 0) & torch.isfinite(a)
    sd2 = d ** 2 / (2.0 * a.clamp_min(1e-300)) - 0.5 * eps  # 2 sd^2 + eps = d^2 / a
    sd = torch.sqrt(sd2.clamp_min(0.0))
    sd = torch.where(ok & (sd2 > 0), sd, torch.full_like(sd, float(sigma_max)))
    return sd.clamp(max=float(sigma_max)).float()


#: how training draws ``s_v`` (:func:`sample_s_v`).
SAMPLINGS = ("uniform", "log")


def sample_s_v(max_sv: float, generator: Optional[torch.Generator] = None, sampling: str = "uniform") -> float:
    """Draw a training ``s_v`` in ``[1, max_sv]``: ``"uniform"``, ``s_v ~ U(1, max_sv)`` (CLoD-GS
    Sec. 3.2), or ``"log"``, ``ln s_v ~ U(0, ln max_sv)``: every factor of ``s_v`` (so of the
    drawn share ``s_v^-1.5``) gets the same number of steps, the levels near full detail as
    many as the coarse ones (under ``"uniform"`` the top half of the shares, ``s_v < 1.59``,
    gets 15 % of the steps at ``max_sv = 5``). One uniform draw from ``generator`` either way.

    Raises:
        ValueError: ``max_sv < 1`` or an unknown ``sampling``.
    """
    if max_sv < 1:
        raise ValueError(f"max_sv must be >= 1, got {max_sv}")
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    u = torch.rand((), generator=generator).item()
    if sampling == "log":
        return float(max_sv) ** u
    return 1.0 + u * (max_sv - 1.0)


def target_fraction(s_v: float) -> float:
    """The regulariser's target rendered fraction ``s_v^-1.5``."""
    return float(s_v) ** -1.5


def reg_loss(s_v: float, eta: Tensor) -> Tensor:
    """Rendered-count regulariser ``L_reg = (s_v - 1)^2 ReLU(eta - s_v^-1.5)^2`` (scalar)."""
    return (s_v - 1.0) ** 2 * torch.relu(eta - target_fraction(s_v)) ** 2


def scale_weight(s_v: float, max_sv: float) -> float:
    """Loss weight ``w_s = (1 - 0.5 s_v / max_sv)^2``: near views count more."""
    return (1.0 - 0.5 * s_v / max_sv) ** 2


def init_sigma_d(d_norm_max: Tensor, attenuation: float = 0.995) -> Tensor:
    """Initial ``sigma_d`` so that at ``s_v = 1`` every Gaussian keeps >= ``attenuation`` of its
    opacity in every training view: ``sigma_d_i = d'_max,i / sqrt(-2 ln attenuation)``.

    Args:
        d_norm_max: [N] largest d' of each Gaussian over the training views.
        attenuation: the smallest allowed factor of Eq. 2 at s_v = 1, in (0, 1).

    Returns:
        [N] float32 sigma_d (> 0; Gaussians with d'_max = 0 get the median value).
    """
    if not 0.0 < attenuation < 1.0:
        raise ValueError(f"attenuation must be in (0, 1), got {attenuation}")
    c = 1.0 / math.sqrt(-2.0 * math.log(attenuation))
    sd = d_norm_max.float() * c
    pos = sd > 0
    fill = sd[pos].median() if bool(pos.any()) else torch.tensor(c)
    return torch.where(pos, sd, fill)
