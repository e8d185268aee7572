"""Discrete level of detail, the per-budget ceiling: one fine-tuned model per level.

:func:`finetune_subset` takes a fixed subset of a pretrained model (the Gaussians a static cut
keeps at one budget) and fine-tunes every attribute on the training views, as LightGaussian does
after pruning. One such model per budget is what a discrete-LoD pipeline ships: ``clod-eval``
reports it as ``dlod_finetuned`` beside the one adapted model, with its storage (the sum of the
levels).

Schedules (``schedule=``):

* ``"recovery"`` (default): LightGaussian's post-pruning recovery (``prune_finetune.py``: the
  pruned model resumes training at iteration 30,000 for 5,000 more, where the official position
  schedule has reached its *final* rate, 1.6e-6 x scene extent). Positions start at that final
  rate and decay log-linearly to ``decay`` (0.01) x it at the last step (LightGaussian holds the
  final rate constant; the decay lets the run settle, so the end of the run is converged, see
  :func:`convergence`); every other attribute at the official constant rates
  (:data:`clod_adapter.train.official.OFFICIAL_LR`); 5,000 steps by default.
* ``"official"``: the schedule of the first version: positions restart at the official
  *initial* rate 1.6e-4 x extent and decay to the final one over the run (a fresh 3DGS training
  schedule; too hot for a finished model: its ceiling ended below the adapted model).

With validation views (``val_cameras``), :func:`finetune_subset` keeps the checkpoint (the start,
every ``val_every`` steps, the end) with the best validation PSNR: on skull the recovery schedule,
converged on the training views, ended 0.95 dB below its start on the test views.

:func:`best_start` picks the subset a level starts from among candidates (static cuts, the
merging decimator's output, the adapted model's own selection) by PSNR on validation views
(:func:`clod_adapter.io.scene.validation_split`), never on test views.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Mapping, Optional, Sequence

import torch
from torch import Tensor

from . import official
from .official import ADAM_EPS, BASE_FIELDS, OFFICIAL_LR, official_groups, scene_extent
from ..gaussians import Gaussians
from .losses import render_loss
from ..lod.draw import render_lod

#: LightGaussian's recovery length after pruning (steps).
RECOVERY_ITERATIONS = 5000
#: the recovery position rate ends at this factor of where it starts (the official final rate).
RECOVERY_DECAY = 0.01
#: fine-tuning schedules (module docstring).
FINETUNE_SCHEDULES = ("recovery", "official")
#: :func:`convergence`: the window (share of the run) and the relative change that counts as converged.
CONVERGENCE_WINDOW = 0.1
CONVERGENCE_TOL = 0.01


def global_cut(scores: Tensor, fraction: float) -> Tensor:
    """[k] int64 ascending indices of the ``k = round(fraction N)`` highest ``scores`` [N] (ties
    by lower index): one discrete level cut from a global ranking."""
    n = scores.numel()
    k = max(0, min(n, int(round(float(fraction) * n))))
    order = torch.sort(-scores.double(), stable=True).indices[:k]
    return torch.sort(order).values


def means_lr(it: int, iterations: int, extent: float, *, schedule: str = "recovery",
             decay: float = RECOVERY_DECAY, lr_scale: float = 1.0) -> float:
    """Position learning rate at step ``it`` (0-based) of a run of ``iterations`` steps
    (:func:`clod_adapter.train.official.means_lr`'s log-linear schedule).

    With ``t = clamp(it / iterations, 0, 1)``: ``"recovery"``:
    ``1.6e-6 * extent * decay ** t`` (log-linear from the official final rate to ``decay`` times
    it, reached at ``it = iterations``); ``"official"``: ``exp((1 - t) log 1.6e-4 + t log 1.6e-6)
    * extent`` (the official 3DGS schedule over the run). Both times ``lr_scale``.
    """
    init, final = OFFICIAL_LR["means"]
    if schedule == "recovery":
        start, end = final, final * float(decay)
    elif schedule == "official":
        start, end = init, final
    else:
        raise ValueError(f"schedule must be one of {FINETUNE_SCHEDULES}, got {schedule!r}")
    return official.means_lr(it, iterations, extent, start=start, end=end, scale=lr_scale)


def convergence(losses: Sequence[float], window: float = CONVERGENCE_WINDOW,
                tol: float = CONVERGENCE_TOL) -> dict:
    """Has a run settled? Mean training loss of the last ``window`` share of the steps against
    the same number of steps before them.

    Returns ``{"window", "last", "previous", "relative_change", "converged"}``:
    ``relative_change = (last - previous) / previous`` (negative: still falling) and
    ``converged = |relative_change| <= tol``; ``previous``/``relative_change`` are None and
    ``converged`` False when the run has fewer than two windows of steps. The per-step loss is of
    one view at a time, so a window should span several epochs of the views.
    """
    n = len(losses)
    w = max(1, int(round(float(window) * n)))
    out = {"window": w, "last": None, "previous": None, "relative_change": None, "converged": False}
    if n == 0:
        return out
    out["last"] = float(sum(losses[-w:]) / len(losses[-w:]))
    if n < 2 * w:
        return out
    prev = float(sum(losses[-2 * w:-w]) / w)
    rel = (out["last"] - prev) / prev if prev > 0 else 0.0
    out.update(previous=prev, relative_change=rel, converged=bool(abs(rel) <= tol))
    return out


@dataclass
class FinetuneInfo:
    """What :func:`finetune_subset` did: the schedule, the per-step training loss (one view per
    step), the position rate at the first and last step, and :func:`convergence` of the loss;
    with validation views, ``val_psnr`` ([step, mean PSNR dB] pairs, step 0 = the start) and
    ``best_step``, the step of the model returned."""

    schedule: str
    iterations: int
    loss: list = field(default_factory=list)
    means_lr_first: Optional[float] = None
    means_lr_last: Optional[float] = None
    convergence: dict = field(default_factory=dict)
    val_psnr: list = field(default_factory=list)
    best_step: Optional[int] = None

    def to_dict(self) -> dict:
        return asdict(self)


def _plain(g: Gaussians) -> Gaussians:
    """The plain model a fine-tune starts from: the base attributes, no ``sigma_d``, no gains."""
    return Gaussians(**{k: getattr(g, k) for k in BASE_FIELDS})


@dataclass(frozen=True)
class FinetuneOptions:
    """How :func:`finetune_subset` trains.

    Attributes:
        iterations: optimisation steps (default 5000, LightGaussian's recovery).
        lr_scale: factor on every learning rate.
        seed: seed of the view order.
        background: RGB behind the scene.
        backend: rasteriser backend.
        schedule: ``"recovery"`` (default) or ``"official"`` (the first version's behaviour).
        decay: ``"recovery"``: the position rate at the end over the one at the start.
        val_every: with validation views, score them every this many steps (0: only at the start
            and after the last).
    """

    iterations: int = RECOVERY_ITERATIONS
    lr_scale: float = 1.0
    seed: int = 0
    background: Sequence[float] = (0.0, 0.0, 0.0)
    backend: str = "auto"
    schedule: str = "recovery"
    decay: float = RECOVERY_DECAY
    val_every: int = 500


def finetune_subset(gaussians: Gaussians, train_cameras: Sequence, train_images: Sequence[Tensor],
                    options: FinetuneOptions = FinetuneOptions(), *, val: Optional[tuple] = None,
                    progress: Optional[str] = None, return_info: bool = False):
    """Fine-tune every attribute of ``gaussians`` (a fixed subset, no LoD, no densification).

    Each step renders one training view (shuffled, without replacement per epoch) with the whole
    model and takes an Adam step on ``0.8 L1 + 0.2 D-SSIM``; learning rates by ``options.schedule``
    (module docstring, :func:`means_lr`), times ``options.lr_scale``.

    Args:
        gaussians: the level's model (N Gaussians; ``sigma_d`` and gains are dropped).
        train_cameras, train_images: training views and [H, W, 3] float32 images in [0, 1].
        options: :class:`FinetuneOptions` (steps, rates, seed, background, schedule).
        val: ``(cameras, images)``, validation views (not among the training views) and their
            [H, W, 3] images: the model is scored on them at the start, every ``val_every`` steps
            and after the last, and the best of those checkpoints is returned (the start when no
            step beats it: a fine-tune that fits the training views at the cost of held-out ones,
            as on skull, does not end below where it began).
        progress: the label of a progress display (:func:`clod_adapter.progress.progress_bar`: a
            tqdm bar on a terminal, a line every 10 % of the steps in a log); None: none.
        return_info: also return a :class:`FinetuneInfo` (loss per step, convergence).

    Returns:
        the fine-tuned model (detached copy), or ``(model, FinetuneInfo)`` with ``return_info``.

    Raises:
        ValueError: an unknown schedule.
    """
    from ..metrics import psnr
    from ..progress import progress_bar

    o = options
    iterations, lr_scale, schedule, decay = o.iterations, o.lr_scale, o.schedule, o.decay
    background, backend, val_every = o.background, o.backend, o.val_every
    val_cameras, val_images = val if val is not None else (None, None)
    if schedule not in FINETUNE_SCHEDULES:
        raise ValueError(f"schedule must be one of {FINETUNE_SCHEDULES}, got {schedule!r}")
    g = _plain(gaussians).clone()
    params = {k: torch.nn.Parameter(getattr(g, k).detach().clone().contiguous()) for k in BASE_FIELDS}
    extent = scene_extent(train_cameras)
    lr_of = lambda it: means_lr(it, iterations, extent, schedule=schedule, decay=decay, lr_scale=lr_scale)  # noqa: E731
    opt = torch.optim.Adam(official_groups(params, lr_of(0), lr_scale), eps=ADAM_EPS)
    gen = torch.Generator().manual_seed(o.seed)
    order: list = []
    losses: list = []
    val_history: list = []
    best = None  # (psnr, step, params)

    def validate(step: int) -> None:
        nonlocal best
        if not val_cameras:
            return
        with torch.no_grad():
            m = Gaussians(**{k: v.detach() for k, v in params.items()})
            p = sum(psnr(render_lod(m, c, None, background=background, backend=backend).image, gt, cap=True)
                    for c, gt in zip(val_cameras, val_images)) / len(val_cameras)
        val_history.append([step, p])
        if best is None or p > best[0]:
            best = (p, step, {k: v.detach().clone() for k, v in params.items()})

    validate(0)
    bar = progress_bar(iterations, progress or "", unit="step", disable=progress is None, leave=False)
    for it in range(iterations):
        for grp in opt.param_groups:
            if grp["name"] == "means":
                grp["lr"] = lr_of(it)
        if not order:
            order = torch.randperm(len(train_cameras), generator=gen).tolist()
        vi = order.pop()
        opt.zero_grad(set_to_none=True)
        with torch.enable_grad():  # also inside a caller's no_grad() (clod-eval's report is one)
            model = Gaussians(**params)
            out = render_lod(model, train_cameras[vi], None, background=background, backend=backend)
            loss = render_loss(out.image, train_images[vi])
            if loss.requires_grad:
                loss.backward()
        losses.append(float(loss.detach()))
        opt.step()
        bar.update(1)
        if val_every > 0 and (it + 1) % val_every == 0 and it + 1 < iterations:
            validate(it + 1)
    bar.close()
    if iterations:
        validate(iterations)
    result = Gaussians(**{k: v.detach() for k, v in (best[2] if best is not None else params).items()})
    if not return_info:
        return result
    info = FinetuneInfo(schedule=schedule, iterations=iterations, loss=losses,
                        means_lr_first=lr_of(0) if iterations else None,
                        means_lr_last=lr_of(iterations - 1) if iterations else None,
                        convergence=convergence(losses), val_psnr=val_history,
                        best_step=best[1] if best is not None else None)
    return result, info


@torch.no_grad()
def best_start(candidates: Mapping[str, Gaussians], val_cameras: Sequence, val_images: Sequence[Tensor], *,
               background=(0.0, 0.0, 0.0), backend: str = "auto", return_scores: bool = False):
    """The candidate start subset of one level with the highest mean PSNR on validation views.

    Each candidate is scored as :func:`finetune_subset` starts from it: its base attributes as
    stored, rendered without LoD (no ``sigma_d``, no level gains; apply
    :meth:`Gaussians.at_level` first to start from a level's attributes). Pass validation views
    (:func:`clod_adapter.io.scene.validation_split`), never test views: the choice is then made
    without them. Ties go to the first candidate in ``candidates``' order.

    Args:
        candidates: name -> Gaussians (e.g. ``{"lightgaussian": cut, "merge": decimated,
            "clod": the adapted model's selection}``); sizes may differ slightly.
        val_cameras, val_images: validation views and their [H, W, 3] images in [0, 1].
        return_scores: also return ``{name: mean PSNR (dB, capped)}``.

    Returns:
        ``(name, Gaussians)`` of the best candidate (the object passed in), or
        ``(name, Gaussians, scores)`` with ``return_scores``.

    Raises:
        ValueError: no candidates or no validation views.
    """
    from ..metrics import psnr

    if not candidates:
        raise ValueError("best_start: no candidates")
    if len(val_cameras) == 0 or len(val_cameras) != len(val_images):
        raise ValueError(f"best_start: need validation views with one image each, got {len(val_cameras)} "
                         f"cameras and {len(val_images)} images")
    scores = {}
    for name, g in candidates.items():
        m = _plain(g)
        ps = [psnr(render_lod(m, c, None, background=background, backend=backend).image, gt, cap=True)
              for c, gt in zip(val_cameras, val_images)]
        scores[name] = sum(ps) / len(ps)
    best = max(scores, key=lambda k: scores[k])  # first of equal maxima
    if return_scores:
        return best, candidates[best], scores
    return best, candidates[best]
