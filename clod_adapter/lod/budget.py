"""Exact Gaussian budgets: per-Gaussian critical s_v and a k-th-largest selection.

A Gaussian is rendered at ``s_v`` iff its margin (CLoD-GS Eq. 2 against the ``tau s_v`` mask)

    h(s) = log alpha - log tau - a s^2 - log s,    a = d'^2 / (2 ReLU(sigma_d)^2 + eps)

is positive. ``h`` is strictly decreasing in ``s > 0`` (from +inf to -inf), so each Gaussian has
exactly one *critical* scale ``s*`` with ``h(s*) = 0`` and is rendered iff ``s_v < s*``. The
rendered count is therefore non-increasing in ``s_v``, and rendering exactly ``k`` Gaussians
means keeping the ``k`` largest ``s*`` (ties broken by index) at any ``s_v`` in
``[s*_(k+1), s*_(k))``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Optional

import torch
from torch import Tensor

from . import rule as lod
from ..render.native import load as load_kernels, wanted as kernels_wanted

if TYPE_CHECKING:
    from .cost import FrameTimeModel

_NEWTON_STEPS = 80

#: the amounts a :class:`Budget` may name (exactly one of them)
BUDGET_KINDS = ("count", "share", "in_view", "cost", "ms")


@dataclass(frozen=True)
class Budget:
    """What one frame may draw, instead of a level ``s_v``: exactly one amount.

    Attributes:
        count: at most this many Gaussians (an int >= 0; on a merge tree, nodes whose centre is in
            the frustum).
        share: at most this share (in [0, 1]) of the model's Gaussians.
        in_view: at most this share (in [0, 1]) of the Gaussians in view (the frustum's; the knob
            web engines expose as a splat budget).
        cost: rasterisation cost (:func:`clod_adapter.lod.cost.splat_cost`, clipped ellipse
            pixels): a float in (0, 1] is that share of the cost of every Gaussian in view, > 1 an
            absolute cost.
        ms: predicted rasterisation milliseconds of ``time_model`` (default
            ``clod_adapter.lod.cost.DEFAULT_FRAME_TIME_MODEL``).
        time_model: the :class:`clod_adapter.lod.cost.FrameTimeModel` of an ``ms`` budget.
        min_s_v: the floor of the solved level (default 1, full detail: a budget that holds every
            Gaussian in view draws full detail); 0 draws exactly the budget whatever ``s_v``
            (single models; a merge tree's floor is 1).

    Raises:
        ValueError: not exactly one amount; a negative, non-finite or (for ``count``) non-integral
            amount; a share above 1; ``time_model`` without ``ms``.

    ``Budget(in_view=0.3)`` is 30 % of the Gaussians in view; ``Budget(count=5000)`` 5,000 of them.
    """

    count: Optional[int] = None
    share: Optional[float] = None
    in_view: Optional[float] = None
    cost: Optional[float] = None
    ms: Optional[float] = None
    time_model: Optional["FrameTimeModel"] = None
    min_s_v: float = 1.0

    def __post_init__(self) -> None:
        given = [k for k in BUDGET_KINDS if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"a Budget names exactly one of {', '.join(BUDGET_KINDS)}; got "
                             f"{' and '.join(given) or 'none'}")
        v = float(getattr(self, given[0]))
        if not math.isfinite(v) or v < 0:
            raise ValueError(f"Budget {given[0]}={v!r} must be finite and >= 0")
        if self.count is not None and v != int(v):
            raise ValueError(f"Budget count={self.count!r} must be an integer")
        if given[0] in ("share", "in_view") and v > 1.0:
            raise ValueError(f"Budget {given[0]}={v!r} must be in [0, 1]")
        if self.time_model is not None and self.ms is None:
            raise ValueError("Budget: time_model is only read by an ms budget")
        if not math.isfinite(float(self.min_s_v)):
            raise ValueError(f"Budget min_s_v={self.min_s_v!r} must be finite")

    @property
    def kind(self) -> str:
        """Which amount it names: one of :data:`BUDGET_KINDS`."""
        return next(k for k in BUDGET_KINDS if getattr(self, k) is not None)

    @property
    def counts(self) -> bool:
        """Whether it bounds a number of Gaussians (``count``, ``share`` or ``in_view``)."""
        return self.kind in ("count", "share", "in_view")

    @property
    def amount(self) -> float | int:
        """A count budget's amount as :func:`budget_count` reads it: an int count, or a float
        share; a cost or time budget's value."""
        v = getattr(self, self.kind)
        return int(v) if self.kind == "count" else float(v)

    def floored(self, min_s_v: float) -> "Budget":
        """This budget with the floor ``min_s_v``."""
        return Budget(**{f.name: getattr(self, f.name) for f in fields(self) if f.name != "min_s_v"},
                      min_s_v=float(min_s_v))

    def of(self, n: int, n_in_view: Optional[int] = None) -> int:
        """A count budget as a number of Gaussians of a model of ``n`` with ``n_in_view`` in view
        (``in_view`` needs it). Raises ValueError for a cost or time budget."""
        if not self.counts:
            raise ValueError(f"a {self.kind} budget is not a count")
        if self.kind == "in_view":
            if n_in_view is None:
                raise ValueError("an in_view budget needs the count in view")
            return int(round(self.in_view * n_in_view))
        return budget_count(self.amount, n)


def as_budget(budget, min_s_v: float = 1.0) -> Optional[Budget]:
    """``budget`` as a :class:`Budget`, for the edges that take plain numbers (the renderer
    hook's gsplat-style keyword, the command line's ``--budget`` after :func:`normalize_budget`):
    a Budget or None as it is; an int a ``count``, a float a ``share`` of the model (in [0, 1]),
    with the floor ``min_s_v``.

    Raises:
        TypeError: not a Budget, an int or a float.
        ValueError: as :class:`Budget` (negative; a float above 1)."""
    if budget is None or isinstance(budget, Budget):
        return budget
    if isinstance(budget, bool) or not isinstance(budget, (int, float)):
        raise TypeError(f"a budget is a clod_adapter.Budget, an int count or a float share, got {budget!r}")
    if isinstance(budget, int):
        return Budget(count=budget, min_s_v=min_s_v)
    return Budget(share=float(budget), min_s_v=min_s_v)


def critical_s_v(opacities: Tensor, d_norm: Tensor, sigma_d: Tensor, tau: float = lod.DEFAULT_TAU,
                 eps: float = lod.DEFAULT_EPS) -> Tensor:
    """Per-Gaussian critical scale ``s*`` (rendered iff ``s_v < s*``).

    Solves ``log alpha - log tau - a s^2 - log s = 0`` for ``u = log s`` by Newton's method in
    float64, started at ``u0 = min(log(alpha / tau), (log(|log(alpha / tau)| + 1) - log a) / 2)``
    (the second term is within a log factor of the root when ``a s^2`` dominates, e.g. a dead
    Gaussian with a tiny eps; from ``log(alpha / tau)`` alone Newton only moves -0.5 per step
    there). The function is concave and decreasing in u, so after at most one step the iterates
    decrease monotonically onto the root. ``eps`` is floored at :data:`lod.EPS_FLOOR`, as in
    :func:`lod.lod_log_attenuation`.

    Args:
        opacities: [N] activated opacities.
        d_norm: [N] frustum-normalised distances d'.
        sigma_d: [N] raw distance decays.
        tau, eps: the LoD threshold and Eq. 2's epsilon.

    On the CPU this is one pass of the C++ kernel ``csrc/lod_terms.cpp`` (each Gaussian stepped
    until its own step is below 1e-13), where it builds (:mod:`clod_adapter.render.native`); the
    torch form below, which steps every Gaussian until all of them are there, is its twin
    (``tests/test_lod_terms.py``: the same ``s*`` to 1e-12, relative). Neither carries a gradient.

    Returns:
        [N] float64 ``s*`` (> 0; 0 for alpha = 0; ``alpha / tau`` where d' = 0).
    """
    if d_norm.numel() and kernels_wanted(d_norm.device.type == "cpu"):
        dt = torch.promote_types(torch.promote_types(opacities.dtype, d_norm.dtype), sigma_d.dtype)
        args = (t.detach().to(dt).contiguous() for t in (opacities, d_norm, sigma_d))
        return load_kernels().lod_critical(*args, float(tau), float(eps))
    d = d_norm.double()
    a = d ** 2 / (2.0 * torch.relu(sigma_d.double()) ** 2 + max(float(eps), lod.EPS_FLOOR))
    a = torch.where(d == 0, torch.zeros_like(a), a)  # d' = 0: no attenuation
    A = torch.log(opacities.double()) - torch.log(torch.tensor(tau, dtype=torch.float64))
    finite = torch.isfinite(A) & torch.isfinite(a)  # a = inf: attenuated to 0, never rendered
    u = torch.where(finite, A, torch.zeros_like(A))
    a = torch.where(finite, a, torch.zeros_like(a))
    u = torch.minimum(u, 0.5 * (torch.log(u.abs() + 1.0) - torch.log(a)))  # log(0) = -inf: u
    A = A.where(finite, torch.zeros_like(A))
    for _ in range(_NEWTON_STEPS):
        e = a * torch.exp(2.0 * u)
        h = A - e - u
        step = h / (2.0 * e + 1.0)
        u = u + step  # concave, decreasing h: right of the root after one step, then leftwards
        if bool((step.abs() < 1e-13).all()):
            break
    s = torch.exp(u)
    return torch.where(finite, s, torch.zeros_like(s))


def normalize_budget(budget) -> float | int:
    """A budget as this project means it: a fraction in [0, 1] (float; so ``1`` is 100 %) or a
    count > 1 (int). Raises ValueError (negative, not finite, or a non-integral count)."""
    v = float(budget)
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"budget {budget!r} must be a fraction in [0, 1] or a count > 1")
    if v <= 1.0:
        return v
    if v != int(v):
        raise ValueError(f"budget {budget!r}: counts (> 1) must be integers; fractions are <= 1")
    return int(v)


def budget_count(budget: float | int, n: int) -> int:
    """A budget as a count: an int (or integral float > 1) is a count, a float in [0, 1] a
    fraction of ``n``. Raises ValueError for negative budgets."""
    if budget < 0:
        raise ValueError(f"budget must be >= 0, got {budget}")
    if isinstance(budget, float) and budget <= 1.0:
        return int(round(budget * n))
    return min(int(budget), n)


def select_budget(critical: Tensor, k: int, candidates: Optional[Tensor] = None) -> tuple[Tensor, float]:
    """The ``k`` Gaussians with the largest critical scale, and an ``s_v`` that renders them.

    Args:
        critical: [N] critical scales (:func:`critical_s_v`).
        k: number of Gaussians to render (clamped to the number of candidates).
        candidates: [N] bool, the Gaussians that may be chosen (e.g. those in view); None: all.

    Returns:
        (indices [k] int64 sorted ascending, s_v). ``s_v`` is the geometric mean of the k-th and
        (k+1)-th largest critical values, so the mask ``s_v < s*`` over the candidates selects
        exactly these k unless those two values tie (then the tie is broken by index and
        ``s_v`` equals the tied value). k = 0 gives the largest value; k = all gives half the
        smallest.
    """
    pool = torch.arange(critical.numel(), device=critical.device)
    if candidates is not None:
        pool = pool[candidates]
    vals = critical[pool]
    m = vals.numel()
    k = max(0, min(int(k), m))
    if m == 0:
        return pool, 1.0
    if bool(torch.isnan(vals).any()):
        return _select_budget_sorted(pool, vals, k)
    # O(m) selection instead of a full sort (at 1M candidates: 21-29 ms against 112 ms, with the
    # same result): the k-th and (k+1)-th largest values by quickselect, every value above the
    # k-th, and the values tied with it in index order (a stable descending sort's tie-break).
    if k == 0:
        return pool[:0], max(float(vals.max()), 1e-12)
    if k == m:
        return pool, max(float(vals.min()) * 0.5, 1e-12)
    hi = float(torch.kthvalue(vals, m - k + 1).values)  # k-th largest
    lo = float(torch.kthvalue(vals, m - k).values)  # (k+1)-th largest
    sel = vals > hi
    need = k - int(sel.sum())
    if need > 0:
        sel[torch.nonzero(vals == hi).squeeze(1)[:need]] = True
    s_v = hi if hi == lo else (hi * lo) ** 0.5 if lo > 0 else hi * 0.5
    return pool[sel], max(s_v, 1e-12)


def _select_budget_sorted(pool: Tensor, vals: Tensor, k: int) -> tuple[Tensor, float]:
    """:func:`select_budget` by a stable descending sort (used when a value is NaN: the sort
    places NaN as the original implementation did)."""
    m = vals.numel()
    order = torch.sort(-vals, stable=True).indices  # descending, ties by index
    chosen = torch.sort(pool[order[:k]]).values
    sv = vals[order]
    if k == 0:
        s_v = float(sv[0])
    elif k == m:
        s_v = float(sv[-1]) * 0.5
    else:
        hi, lo = float(sv[k - 1]), float(sv[k])
        s_v = hi if hi == lo else (hi * lo) ** 0.5 if lo > 0 else hi * 0.5
    return chosen, max(s_v, 1e-12)
