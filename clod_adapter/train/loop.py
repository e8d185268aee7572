"""Fine-tune a pretrained 3DGS model into a CLoD-GS model (the paper's robustness setting).

A per-Gaussian distance decay ``sigma_d`` is attached and trained with virtual distance scaling
(CLoD-GS, Cheng et al. ICLR 2026, Sec. 3). Two schedules (:data:`SCHEDULES`):

* ``"calibrated"`` (default): ``sigma_d`` starts from a static ranking (LightGaussian
  significance) mapped through Eq. 2 so that the top ``s_v^-1.5`` of the ranking is drawn at
  ``s_v`` (:func:`clod_adapter.lod.calibrate_sigma_d`); each step draws ``s_v`` log-uniform in [1, max_sv],
  renders exactly ``s_v^-1.5`` of the Gaussians in view (the Eq. 2 mask at the solved ``s_v``,
  :mod:`clod_adapter.budget`) with the window fade and the level gains of that share
  (:class:`clod_adapter.lod.LodSettings`), and takes a step on the rendering loss. After the
  last step ``sigma_d`` is re-mapped from the order it has learned, so the drawn share at
  ``s_v`` is ``s_v^-1.5`` again (training pushes every decay up). The base attributes are frozen by default
  (``other_lr_scale = 0``): full detail is the input model.
* ``"paper"``: the paper's recipe: ``sigma_d`` initialised large, ``s_v ~ U(1, max_sv)``, Eq. 2
  fading, ``L = w_s (L_render + lambda_reg L_reg)`` with a straight-through ``eta``; the other
  attributes at ``other_lr_scale`` (0.1) of the official 3DGS learning rates.

No densification.

Public entry points: :class:`AdaptConfig`, :func:`prepare`, :func:`adapt`, :func:`save_state`,
:func:`load_state`.
"""
from __future__ import annotations

import json
import math
import os
import signal
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Literal, Optional

import torch
from torch import Tensor

from . import __version__, lod
from .budget import critical_s_v
from .gaussians import GAIN_NAMES, Gaussians
from .io.atomic import atomic_save
from .io.scene import RESOLUTIONS
from .losses import clod_loss, render_loss
from .camera_lod import render_lod, view_lod
from .metrics import psnr
from .official import OFFICIAL_LR, scene_extent

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN", "sigma_d")
SCHEDULES = ("calibrated", "paper")
Schedule = Literal["calibrated", "paper"]
Ranking = Literal["lightgaussian", "opacity"]
LevelWeighting = Literal["paper", "uniform"]
#: level gains by letter of :attr:`AdaptConfig.gains`, and the official learning rate each uses
#: (that of the attribute it offsets).
GAIN_LETTERS = {"o": "opacity_logit_gain", "s": "log_scale_gain", "c": "sh0_gain"}
GAIN_LR = {"opacity_logit_gain": OFFICIAL_LR["opacity_logits"], "log_scale_gain": OFFICIAL_LR["log_scales"],
           "sh0_gain": OFFICIAL_LR["sh0"]}
RANKINGS = ("lightgaussian", "opacity")


#: AdaptConfig.tier_draw's values
TIER_DRAWS = ("tree", "chain")


@dataclass
class AdaptConfig:
    """Settings of one adaptation run (``None``: the schedule's default, resolved on creation).

    Attributes:
        max_sv: largest virtual distance scale trained (``s_v`` in [1, max_sv]); the coarsest
            trained level draws ``max_sv^-1.5`` of the Gaussians in view.
        iterations: optimisation steps (``views_per_step`` training views each).
        schedule: ``"calibrated"`` (default) or ``"paper"`` (module docstring).
        sigma_d_lr: Adam learning rate of sigma_d (paper: 1e-2).
        other_lr_scale: factor on the official 3DGS learning rates of the base attributes
            (calibrated: 0, frozen, so full detail stays the input; paper: 0.1).
        lambda_reg: weight of L_reg (paper schedule; default 0.05, docs/studies.md; the
            paper's 1 is for training from scratch). The calibrated schedule
            has no count regulariser (0): its count follows s_v^-1.5 by calibration.
        tau: LoD threshold (mask alpha'' > tau s_v).
        eps: Eq. 2's epsilon.
        eta_estimator: "ste" (default), "sigmoid" or "paper" (no gradient, ablation).
        temperature: width of the eta relaxation, log-opacity units.
        init_attenuation: paper schedule: Eq. 2's factor at s_v = 1 is at least this at
            initialisation; None: calibrated per scene (:func:`calibrate_init`).
        seed: seed of view order and s_v sampling.
        background: RGB behind the scene.
        fade: how survivors are drawn, ``"window"`` or ``"eq2"`` (calibrated: window, paper:
            eq2; :mod:`clod_adapter.lod`).
        fade_width: width of the window fade, log-opacity units.
        gains: which level gains to learn (calibrated schedule): letters of ``o`` (opacity),
            ``s`` (scale), ``c`` (colour, sh0); "" for none.
        gain_lr_scale: factor on the official learning rate of the attribute each gain offsets.
        ranking: the static ranking ``sigma_d`` starts from (calibrated): ``"lightgaussian"``
            or ``"opacity"``.
        recalibrate_every: calibrated: re-map ``sigma_d`` from its learned order every this
            many steps, and after the last; 0 (default): only after the last (on fern, every 100
            steps cost 0.2-1.4 dB at 50-5 % of the Gaussians: docs/studies.md).
        level_weighting: ``"paper"`` (w_s = (1 - 0.5 s_v / max_sv)^2) or ``"uniform"``
            (calibrated default: every level counts alike).
        cost_exponent: calibrated schedule: what a level's share ``s_v^-1.5`` measures: the
            share of ``sum cost_i^cost_exponent`` over the Gaussians in view, ``cost_i`` their
            frame cost (footprint in pixels, :mod:`clod_adapter.cost`). 0: the share of the
            *count* (the paper's target; coarse levels keep the largest splats, so they cost far
            more than their count); 1: the share of the frame *cost* (coarse levels reach
            ``max_sv^-1.5`` of the frame time, but mid levels lose what large splats cover
            cheaply); between: both. ``sigma_d`` is calibrated on these weighted quantiles and
            each step renders exactly that weighted share of the view.
        s_v_sampling: how each step draws its ``s_v`` (:func:`clod_adapter.lod.sample_s_v`):
            ``"uniform"`` (the paper's ``U(1, max_sv)``; paper default) or ``"log"`` (``ln s_v``
            uniform: the levels near full detail trained as often as the coarse ones; calibrated
            default: on the validation views of skull and fern +0.1 to +0.6 dB at 11 of the 12
            decimator counts, docs/studies.md).
        level_max: the largest level of the gains (:attr:`clod_adapter.lod.LodSettings.level_max`,
            >= 1): with cost levels a step's count share falls below ``max_sv^-1.5`` from ``s_v``
            about 3.2 on, where the default 1 holds the gains at one level. 2 lets them grow on
            (test views: +0.3 to +1.5 dB at ``s_v`` 15-30 on every scene, but -0.2 to -0.5 dB at
            ``s_v`` 2-5 on skull; docs/studies.md).
        trained_order_share: calibrated schedule: at the final recalibration (and every
            ``recalibrate_every`` steps), the learned order is kept for this share of the
            Gaussians, the top of it by count (the ones kept longest); the rest, the ones that
            leave first, are ordered by the starting ranking (``ranking``) again
            (:func:`merged_order`). 1 (default): the learned order throughout.
        parent_share: the parent tiers (:mod:`clod_adapter.tiers`): after the adaptation, the
            input merged by splat-transform's ``--decimate`` to each of these shares of its
            Gaussians (descending; a float is one share) is adapted too, each tier with the next
            as its own parents, and attached where it beats the tier above at equal predicted
            frame time (left out when it does not, for models under
            :data:`clod_adapter.tiers.PARENT_MIN_GAUSSIANS` Gaussians, and when splat-transform
            is not installed). Stored as a tuple; ``()`` or 0: no tier. Default
            :data:`clod_adapter.tiers.DEFAULT_SHARES` (calibrated), none (paper). Chosen on the
            validation views: ``python benchmarks/quality_vs_time.py --split val --config
            parent_share=...`` (docs/studies.md).
        tier_finetune_steps: each merged tier's base attributes are fine-tuned at full detail
            for this many steps on the training views (:func:`clod_adapter.tiers.finetuned`,
            LightGaussian's recovery schedule) before its level of detail is learned: a merge is
            not a fitted model. 0: the merge as splat-transform wrote it. Default 400, chosen on
            the validation views (at 400 steps fern's 50 / 15 / 4 % merges +3.3 / +3.3 / +3.4 dB,
            0.17-0.34 dB more than at 200; skull's +0.09 / +0.25 / +0.51 dB, 0.03-0.08 dB less;
            ``benchmarks/studies/tier_finetune.py``, docs/studies.md "Fitting each merge").
        tier_merge: the merge each tier starts from, one of :data:`clod_adapter.tiers.MERGES`:
            splat-transform 3.7.0's ``"decimate"`` (``--decimate``, default) or ``"adaptive"``
            (``--decimate-adaptive``) (docs/studies.md "Which merge a tier starts from").
        tier_time_cap: the first tier's share is lowered (by 0.7x per try, not below the next
            share) while its merge is predicted to draw a frame in more than this share of the
            input's (:func:`clod_adapter.tiers.first_share`, the fitted frame-time model on the
            training views: no wall clock). Default :data:`clod_adapter.tiers.TIER_TIME_CAP` (0.8):
            MaskGaussian fern's 50 % merge is predicted at 83 % and its first tier becomes 35 %;
            the vanilla checkpoints' 50 % merges (fern 77 %, skull 69 %) are kept. 0: the shares
            as given (docs/studies.md "A first tier that saves time").
        tier_hand_over: with merged tiers, the latest ``s_v`` (of the tier's own) at which each
            merged tier hands over to the next (:func:`clod_adapter.tiers.link`; the input's own
            hand-over to the first tier stays where the time rule puts it). Default
            :data:`clod_adapter.tiers.TIER_HAND_OVER` (1.6) with the calibrated schedule; 0:
            where the time rule puts it (docs/studies.md "The coarsest tier's window": on the
            validation views popping median fern 15.6 -> 17.9, MaskGaussian fern 15.2 -> 16.6,
            skull 9.3 -> 11.9, no quality cell down by more than 0.01 dB).
        tier_draw: how a model with merged tiers is drawn: ``"tree"`` (default), the tiers linked
            into a merge tree (each Gaussian names its parent in the next tier), fitted on its cuts
            and drawn as one cut per frame (:mod:`clod_adapter.tree`; docs/method.md "The merge
            tree"; docs/studies.md "The merge tree": on the validation views no frame along
            ``s_v`` or count budgets over 1.05x a more detailed one); ``"chain"``, whole tiers
            cross-faded at each hand-over (two sets drawn there).
        tree_steps: with ``tier_draw="tree"``, the merged tiers are fitted on the tree's own cuts
            for this many steps, at most ``iterations`` (:func:`clod_adapter.tree_train.finetune`;
            0: not fitted).
        tier_iteration_share: each merged tier learns its level of detail for this share of
            ``iterations`` (rounded, at least 1 when ``iterations`` > 0). Default 1: a finer ladder of
            five tiers at half the steps each was not better on the validation views
            (docs/studies.md "A finer ladder").
        tier_downscale: the second and later merged tiers are fine-tuned and learn their level of
            detail on the training views at 1/``tier_downscale`` of the model's resolution (at most
            1/8 of the images'); every hand-over is still chosen at a full-size view. The first
            tier, which draws the middle of the range, keeps the model's resolution
            (docs/studies.md "The later tiers trained at half resolution").
        faint_share: leave out, before anything else, the Gaussians whose blending weight summed
            over every pixel of every training view is under this share of one view's pixels
            (:func:`clod_adapter.pruning.faint`; no recovery: together they paint under that
            much of the training images each). Default :data:`clod_adapter.pruning.FAINT_SHARE`
            (1e-5, calibrated), 0 (paper: every Gaussian). Chosen on the validation views
            (docs/studies.md "Leaving out the faint"): the largest that costs no shared scene
            0.02 dB at full detail.
        keep_share: leave out what the scene does not need first (:mod:`clod_adapter.pruning`):
            keep this share of the input's Gaussians, the top by blending weight over the training
            views, recovered for ``recovery_steps`` before the level of detail is learned; full
            detail is then the kept model, not the input. 1 (default): every Gaussian that
            ``faint_share`` keeps (docs/method.md "Leaving Gaussians out first"; docs/studies.md: on
            the shared scenes' test views 0.6 gives full detail at -0.07 dB in 77 % of fern's
            frame and +0.01 dB in 76 % of skull's, -0.83 dB on MaskGaussian fern, and the
            validation views cannot choose it, since the input was trained on them).
        recovery_steps: with ``keep_share < 1``: recovery steps of the kept Gaussians (every
            attribute, LightGaussian's schedule), kept when the last step scores above the
            static cut on held-out training views (else the static cut). Default 1000.
        views_per_step: training views per optimisation step, each at its own ``s_v``; the
            step uses the mean of their gradients (default 1). In a data-parallel run
            (:mod:`clod_adapter.distributed`) view ``j`` of a step is rendered by rank
            ``j mod world_size``, so the result does not depend on the number of processes.
    """

    max_sv: float = 5.0
    iterations: int = 1000
    schedule: Schedule = "calibrated"
    sigma_d_lr: float = 1e-2
    other_lr_scale: Optional[float] = None
    lambda_reg: Optional[float] = None
    tau: float = lod.DEFAULT_TAU
    eps: float = lod.DEFAULT_EPS
    eta_estimator: lod.Estimator = "ste"
    temperature: float = 1.0
    init_attenuation: Optional[float] = None
    seed: int = 0
    background: tuple = (0.0, 0.0, 0.0)
    fade: Optional[lod.Fade] = None
    fade_width: float = lod.DEFAULT_FADE_WIDTH
    gains: Optional[str] = None
    gain_lr_scale: float = 1.0
    ranking: Ranking = "lightgaussian"
    recalibrate_every: int = 0
    level_weighting: Optional[LevelWeighting] = None
    views_per_step: int = 1
    cost_exponent: float = 0.5
    s_v_sampling: Optional[str] = None
    level_max: float = 1.0
    trained_order_share: float = 1.0
    parent_share: Optional[float | tuple] = None
    tier_finetune_steps: int = 400
    tier_iteration_share: float = 1.0
    tier_downscale: int = 2
    tier_merge: str = "decimate"
    tier_time_cap: Optional[float] = None
    tier_hand_over: Optional[float] = None
    tier_draw: str = "tree"
    tree_steps: int = 1000
    faint_share: Optional[float] = None
    keep_share: float = 1.0
    recovery_steps: int = 1000

    def __post_init__(self) -> None:
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {self.schedule!r}")
        cal = self.schedule == "calibrated"
        if self.other_lr_scale is None:
            self.other_lr_scale = 0.0 if cal else 0.1
        if self.lambda_reg is None:
            self.lambda_reg = 0.0 if cal else 0.05
        if self.fade is None:
            self.fade = "window" if cal else "eq2"
        if self.gains is None:
            self.gains = "osc" if cal else ""
        if self.level_weighting is None:
            self.level_weighting = "uniform" if cal else "paper"
        if self.s_v_sampling is None:
            self.s_v_sampling = "log" if cal else "uniform"
        self._settle_tiers(cal)
        if self.faint_share is None:
            from .pruning import FAINT_SHARE

            self.faint_share = FAINT_SHARE if cal else 0.0
        self.faint_share = float(self.faint_share)
        if not (math.isfinite(self.faint_share) and self.faint_share >= 0.0):
            raise ValueError(f"faint_share must be >= 0 (a share of one view's pixels), got {self.faint_share}")
        self.keep_share = float(self.keep_share)
        if not 0.0 < self.keep_share <= 1.0:
            raise ValueError(f"keep_share must be in (0, 1], got {self.keep_share}")
        if not (isinstance(self.recovery_steps, int) and self.recovery_steps >= 0):
            raise ValueError(f"recovery_steps must be >= 0 (an integer), got {self.recovery_steps!r}")
        self.lod_settings()  # max_sv, tau, fade, fade_width: LodSettings' rules, checked there
        if self.iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")
        if self.other_lr_scale < 0:
            raise ValueError(f"other_lr_scale must be >= 0, got {self.other_lr_scale}")
        if self.eta_estimator not in lod.ETA_ESTIMATORS:
            raise ValueError(f"eta_estimator must be one of {lod.ETA_ESTIMATORS}")
        bad = set(self.gains) - set(GAIN_LETTERS)
        if bad:
            raise ValueError(f"gains must be letters of 'osc' (opacity, scale, colour), got {self.gains!r}")
        if self.gains and not cal:
            raise ValueError(f"gains must be used with the calibrated schedule, got {self.gains!r}")
        if self.ranking not in RANKINGS:
            raise ValueError(f"ranking must be one of {RANKINGS}, got {self.ranking!r}")
        if self.recalibrate_every < 0:
            raise ValueError(f"recalibrate_every must be >= 0, got {self.recalibrate_every}")
        if self.level_weighting not in ("paper", "uniform"):
            raise ValueError(f"level_weighting must be 'paper' or 'uniform', got {self.level_weighting!r}")
        if self.s_v_sampling not in lod.SAMPLINGS:
            raise ValueError(f"s_v_sampling must be one of {lod.SAMPLINGS}, got {self.s_v_sampling!r}")
        if not 0.0 <= self.cost_exponent <= 1.0:
            raise ValueError(f"cost_exponent must be in [0, 1], got {self.cost_exponent}")
        if not (isinstance(self.views_per_step, int) and self.views_per_step >= 1):
            raise ValueError(f"views_per_step must be >= 1 (an integer), got {self.views_per_step!r}")
        self.background = tuple(float(x) for x in self.background)
        self.level_max = float(self.level_max)
        self.trained_order_share = float(self.trained_order_share)
        if not 0.0 <= self.trained_order_share <= 1.0:
            raise ValueError(f"trained_order_share must be in [0, 1], got {self.trained_order_share}")

    def _settle_tiers(self, cal: bool) -> None:
        """Defaults and checks of the merged tiers' settings (``parent_share``, ``tier_*``).

        Raises:
            ValueError: a setting out of range, naming the field.
        """
        if self.parent_share is None:
            from .tiers import DEFAULT_SHARES

            self.parent_share = DEFAULT_SHARES if cal else ()
        shares = self.parent_share if isinstance(self.parent_share, (tuple, list)) else (self.parent_share,)
        self.parent_share = tuple(float(x) for x in shares if float(x) != 0.0)
        if not all(0.0 < x < 1.0 for x in self.parent_share) or \
                any(b >= a for a, b in zip(self.parent_share, self.parent_share[1:])):
            raise ValueError(f"parent_share must be descending shares in (0, 1), got {shares}")
        if not (isinstance(self.tier_finetune_steps, int) and self.tier_finetune_steps >= 0):
            raise ValueError(f"tier_finetune_steps must be >= 0 (an integer), got {self.tier_finetune_steps!r}")
        from .tiers import MERGES

        if self.tier_merge not in MERGES:
            raise ValueError(f"tier_merge must be one of {MERGES}, got {self.tier_merge!r}")
        if self.tier_time_cap is None:
            from .tiers import TIER_TIME_CAP

            self.tier_time_cap = TIER_TIME_CAP if cal else 0.0
        self.tier_time_cap = float(self.tier_time_cap)
        if not (math.isfinite(self.tier_time_cap) and 0.0 <= self.tier_time_cap <= 1.0):
            raise ValueError(f"tier_time_cap must be in [0, 1] (a share of the input's frame time), "
                             f"got {self.tier_time_cap}")
        if self.tier_hand_over is None:
            from .tiers import TIER_HAND_OVER

            self.tier_hand_over = TIER_HAND_OVER if cal else 0.0
        self.tier_hand_over = float(self.tier_hand_over)
        if not (self.tier_hand_over == 0.0 or (math.isfinite(self.tier_hand_over) and self.tier_hand_over > 1.0)):
            raise ValueError(f"tier_hand_over must be 0 (the time rule's) or an s_v > 1, got {self.tier_hand_over}")
        if int(self.tree_steps) != self.tree_steps or self.tree_steps < 0:
            raise ValueError(f"tree_steps must be a count >= 0, got {self.tree_steps}")
        self.tree_steps = int(self.tree_steps)
        if self.tier_draw not in TIER_DRAWS:
            raise ValueError(f"tier_draw must be one of {', '.join(TIER_DRAWS)}, got {self.tier_draw!r}")
        self.tier_iteration_share = float(self.tier_iteration_share)
        if not 0.0 < self.tier_iteration_share <= 1.0:
            raise ValueError(f"tier_iteration_share must be in (0, 1], got {self.tier_iteration_share}")
        if self.tier_downscale not in RESOLUTIONS:
            raise ValueError(f"tier_downscale must be one of {RESOLUTIONS}, got {self.tier_downscale!r}")

    @property
    def gain_names(self) -> tuple:
        """The Gaussians fields of the learned level gains, in :data:`GAIN_NAMES` order."""
        return tuple(n for n in GAIN_NAMES if n in {GAIN_LETTERS[c] for c in self.gains})

    def tier_resolution(self, resolution: int) -> int:
        """The scene resolution factor (one of :data:`clod_adapter.io.scene.RESOLUTIONS`) the second
        and later merged tiers are trained at when the model is trained at ``resolution``:
        ``resolution * tier_downscale``, at most the largest factor."""
        return max(int(resolution), min(RESOLUTIONS[-1], int(resolution) * self.tier_downscale))

    def tier_iterations(self) -> int:
        """The LoD training steps of each merged tier: ``tier_iteration_share`` of
        ``iterations``, rounded, at least 1 when ``iterations`` > 0."""
        return 0 if self.iterations == 0 else max(1, int(round(self.tier_iteration_share * self.iterations)))

    def lod_settings(self) -> lod.LodSettings:
        """The :class:`clod_adapter.lod.LodSettings` the adapted model is drawn with."""
        return lod.LodSettings(max_sv=self.max_sv, tau=self.tau, eps=self.eps, fade=self.fade,
                               fade_width=self.fade_width, level_max=self.level_max)


@dataclass
class AdaptState:
    """Everything needed to continue a run: parameters, Adam moments, RNG, view order.

    ``history`` holds one record per rendered view (``s_v``, rendered fraction ``eta``,
    ``loss``, training-view ``psnr``), ``views_per_step`` of them per step, in schedule order.
    ``extra``: the input's other per-Gaussian properties (e.g. MaskGaussian's mask scores), carried
    along untrained so the model the state gives is written back with them (not saved in the
    state file: a resumed run takes them from its input again)."""

    params: dict
    optimizer: torch.optim.Optimizer
    generator: torch.Generator
    iteration: int = 0
    order: list = field(default_factory=list)
    extent: float = 1.0
    history: dict = field(default_factory=lambda: {"s_v": [], "eta": [], "loss": [], "psnr": []})
    init: dict = field(default_factory=dict)
    lod: Optional[lod.LodSettings] = None
    extra: dict = field(default_factory=dict)

    def gaussians(self) -> Gaussians:
        """The model as it stands (parameters, not copies; ``lod`` settings and ``extra`` attached)."""
        return Gaussians(**{k: v for k, v in self.params.items()}, lod=self.lod, extra=self.extra)


@torch.no_grad()
def max_normalized_distance(gaussians: Gaussians, cameras) -> Tensor:
    """[N] largest frustum-normalised distance d' of each Gaussian over ``cameras``."""
    dmax = torch.zeros(len(gaussians), dtype=torch.float32, device=gaussians.means.device)
    for cam in cameras:
        vm = cam.viewmat.to(gaussians.means)
        fr = lod.in_frustum(gaussians.means, vm, cam.K.to(gaussians.means), cam.width, cam.height)
        d = lod.normalized_distances(gaussians.means, lod.camera_center(vm), fr)
        dmax = torch.maximum(dmax, d.float())
    return dmax


@torch.no_grad()
def reference_distances(gaussians: Gaussians, cameras) -> Tensor:
    """[N] float32 reference d' of each Gaussian for :func:`lod.calibrate_sigma_d`: its mean
    frustum-normalised distance over the views whose frustum holds its centre (over all views
    when none does), so the drawn share at ``s_v`` is ``s_v^-1.5`` on average over the views.
    Streaming: O(N) memory whatever the number of views."""
    n = len(gaussians)
    dev = gaussians.means.device
    s_in = torch.zeros(n, dtype=torch.float64, device=dev)
    c_in = torch.zeros(n, dtype=torch.float64, device=dev)
    s_all = torch.zeros(n, dtype=torch.float64, device=dev)
    for cam in cameras:
        vm = cam.viewmat.to(gaussians.means)
        fr = lod.in_frustum(gaussians.means, vm, cam.K.to(gaussians.means), cam.width, cam.height)
        d = lod.normalized_distances(gaussians.means, lod.camera_center(vm), fr).double()
        s_all += d
        s_in += torch.where(fr, d, torch.zeros_like(d))
        c_in += fr.double()
    return torch.where(c_in > 0, s_in / c_in.clamp_min(1), s_all / max(len(cameras), 1)).float()


@torch.no_grad()
def view_statistics(gaussians: Gaussians, cameras) -> dict:
    """What calibration needs from the training views (O(N) memory).

    Returns:
        dict of [N] float32 tensors: ``d_ref`` (:func:`reference_distances`) and ``cost`` (mean
        frame cost over the views: :func:`clod_adapter.cost.splat_cost` at the base level,
        clipped ellipse pixels, 0 in views that do not draw it).
    """
    from .cost import splat_cost

    g = gaussians.detach().with_sigma_d(None)
    n = len(g)
    dev = g.means.device
    d_ref = reference_distances(g, cameras)
    cost = torch.zeros(n, dtype=torch.float64, device=dev)
    for cam in cameras:
        v = view_lod(g, cam)
        ids = torch.nonzero(v.visible, as_tuple=False).squeeze(1)
        cost.index_add_(0, ids, splat_cost(v, ids).double())
    return {"d_ref": d_ref, "cost": (cost / max(len(cameras), 1)).float()}


@torch.no_grad()
def ranking_scores(gaussians: Gaussians, cameras, ranking: str = "lightgaussian") -> Tensor:
    """[N] the static ranking the calibrated schedule starts from (higher = kept longer):
    LightGaussian global significance over ``cameras`` or the opacity."""
    if ranking == "opacity":
        return gaussians.opacities.detach().float()
    from .baselines import lightgaussian_significance

    return lightgaussian_significance(gaussians.detach(), cameras)


def calibrated_sigma_d(score: Tensor, opacities: Tensor, stats: dict, cfg: AdaptConfig) -> Tensor:
    """[N] ``sigma_d`` of the calibrated schedule: :func:`lod.calibrate_sigma_d` of ``score`` at
    the reference distances, on quantiles of ``cost^cfg.cost_exponent`` (``stats`` from
    :func:`view_statistics`; count quantiles for exponent 0)."""
    beta = cfg.cost_exponent
    return lod.calibrate_sigma_d(score, opacities, stats["d_ref"], tau=cfg.tau, eps=cfg.eps,
                                 fade_width=cfg.fade_width,
                                 cost=stats["cost"].double().clamp_min(1e-12) ** beta if beta > 0 else None)


def merged_order(learned: Tensor, start: Tensor, share: float) -> Tensor:
    """[N] float64 ranking score (higher = kept longer) that keeps the ``learned`` order for its
    top ``share`` of the Gaussians (by count; ``round(share N)`` of them) and ranks every other
    one by ``start`` below them. Ties are broken by index, as in :func:`lod.calibrate_sigma_d`.

    Args:
        learned: [N] learned ranking score (e.g. the reference critical ``s_v``).
        start: [N] starting ranking score (e.g. LightGaussian significance).
        share: in [0, 1]; 1 returns the learned order, 0 the starting one.
    """
    n = learned.numel()

    def ranks(score):  # 0 = kept longest
        r = torch.empty(n, dtype=torch.float64, device=score.device)
        r[torch.sort(-score.detach().double(), stable=True).indices] = torch.arange(
            n, dtype=torch.float64, device=score.device)
        return r
    r_learned = ranks(learned)
    keep = r_learned < round(share * n)
    # kept: scores in (n, 2n]; the others: (0, n], by the starting order
    return torch.where(keep, 2.0 * n - r_learned, n - ranks(start))


@torch.no_grad()
def recalibrate(state: "AdaptState", cameras, cfg: AdaptConfig) -> None:
    """Re-map ``sigma_d`` from the order it has learned (the reference critical s_v at each
    Gaussian's reference distance), in place: the learned order at the reference distance is
    kept and the drawn share at ``s_v`` is again ``s_v^-1.5`` (:func:`calibrated_sigma_d`)."""
    g = state.gaussians().detach()
    stats = view_statistics(g, cameras)
    s_ref = critical_s_v(g.opacities, stats["d_ref"], g.sigma_d, cfg.tau, cfg.eps)
    if cfg.trained_order_share < 1.0:
        s_ref = merged_order(s_ref, ranking_scores(g, cameras, cfg.ranking), cfg.trained_order_share)
    new = calibrated_sigma_d(s_ref, g.opacities, stats, cfg)
    state.params["sigma_d"].data.copy_(new.to(state.params["sigma_d"]))


def _lr_groups(params: dict, cfg: AdaptConfig, extent: float) -> list:
    groups = [{"params": [params["sigma_d"]], "lr": cfg.sigma_d_lr, "name": "sigma_d"}]
    for name in cfg.gain_names:
        groups.append({"params": [params[name]], "lr": GAIN_LR[name] * cfg.gain_lr_scale, "name": name})
    if cfg.other_lr_scale > 0:
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN"):
            if params[name].numel() == 0:
                continue
            lr = OFFICIAL_LR[name]
            lr = lr[0] * extent if name == "means" else lr
            groups.append({"params": [params[name]], "lr": lr * cfg.other_lr_scale, "name": name})
    return groups


def means_lr(cfg: AdaptConfig, extent: float, it: int) -> float:
    """Official 3DGS position schedule (log-linear init -> final) times ``other_lr_scale``."""
    init, final = OFFICIAL_LR["means"]
    t = min(max(it / max(cfg.iterations, 1), 0.0), 1.0)
    return math.exp(math.log(init) * (1 - t) + math.log(final) * t) * extent * cfg.other_lr_scale


#: candidate init attenuations, most aggressive first (:func:`calibrate_init`).
INIT_CANDIDATES = (0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 0.999)


@torch.no_grad()
def calibrate_init(gaussians: Gaussians, d_norm_max: Tensor, cameras, images, cfg: AdaptConfig,
                   max_drop_db: float = 0.02, views: int = 3, backend: str = "auto") -> tuple[float, float]:
    """Pick the smallest attenuation of :data:`INIT_CANDIDATES` whose s_v = 1 render loses at
    most ``max_drop_db`` PSNR against the input on up to ``views`` training views.

    A smaller attenuation starts ``sigma_d`` closer to where it cuts Gaussians at large s_v, so
    fewer steps are spent just getting there; the check keeps step 0 rendering like the input.

    Returns:
        (attenuation, measured PSNR drop in dB).
    """
    idx = torch.linspace(0, len(cameras) - 1, min(views, len(cameras))).round().long().tolist()
    base = [psnr(render_lod(gaussians, cameras[i], None, background=cfg.background,
                            backend=backend).image, images[i]) for i in idx]
    drop = 0.0
    for a in INIT_CANDIDATES:
        g = gaussians.with_sigma_d(lod.init_sigma_d(d_norm_max, a).to(gaussians.means))
        p = [psnr(render_lod(g, cameras[i], 1.0, tau=cfg.tau, eps=cfg.eps, background=cfg.background,
                             backend=backend).image, images[i]) for i in idx]
        drop = max(b - q for b, q in zip(base, p))
        if drop <= max_drop_db:
            return a, drop
    return INIT_CANDIDATES[-1], drop


def prepare(gaussians: Gaussians, train_cameras, cfg: AdaptConfig, train_images=None,
            backend: str = "auto") -> AdaptState:
    """Attach ``sigma_d`` (and zero level gains) and build the optimiser state for :func:`adapt`.

    Calibrated schedule: ``sigma_d`` from :func:`ranking_scores` through
    :func:`lod.calibrate_sigma_d` at :func:`reference_distances`. Paper schedule:
    :func:`clod_adapter.lod.init_sigma_d` over the training views; with
    ``cfg.init_attenuation`` None the attenuation is calibrated on ``train_images``
    (:func:`calibrate_init`; 0.995 when no images are given). A model that already has
    ``sigma_d`` (and gains) keeps them. What was done is stored in ``state.init``."""
    g = gaussians.clone()
    init = {}
    if g.sigma_d is None and cfg.schedule == "calibrated":
        scores = ranking_scores(g, train_cameras, cfg.ranking)
        stats = view_statistics(g, train_cameras)
        g = g.with_sigma_d(calibrated_sigma_d(scores, g.opacities, stats, cfg).to(g.means))
        init = {"ranking": cfg.ranking, "cost_exponent": cfg.cost_exponent}
    elif g.sigma_d is None:
        dmax = max_normalized_distance(g, train_cameras)
        att = cfg.init_attenuation
        if att is None and train_images is not None:
            att, drop = calibrate_init(g, dmax, train_cameras, train_images, cfg, backend=backend)
            init = {"attenuation": att, "train_psnr_drop_db": drop}
        elif att is None:
            att = 0.995
        init.setdefault("attenuation", att)
        g = g.with_sigma_d(lod.init_sigma_d(dmax, att).to(g.means))
    train_others = cfg.other_lr_scale > 0
    params = {}
    for name in PARAM_NAMES:
        t = getattr(g, name).detach().clone().contiguous()
        params[name] = torch.nn.Parameter(t, requires_grad=(name == "sigma_d") or train_others)
    for name in cfg.gain_names:
        have = getattr(g, name)
        shape = (len(g), 1, 3) if name == "sh0_gain" else (len(g),)
        t = have.detach().clone() if have is not None else torch.zeros(shape, dtype=g.means.dtype, device=g.means.device)
        params[name] = torch.nn.Parameter(t.contiguous())
    extent = scene_extent(train_cameras)
    opt = torch.optim.Adam(_lr_groups(params, cfg, extent), eps=1e-15)
    gen = torch.Generator().manual_seed(cfg.seed)
    return AdaptState(params=params, optimizer=opt, generator=gen, extent=extent, init=init,
                      lod=cfg.lod_settings(), extra=dict(g.extra))


class StopFlag:
    """Turns SIGINT/SIGTERM into a flag checked at safe points (between iterations; the
    pipeline also checks it between phases), so the state is saved, never half-written.

    The handler only sets ``stop`` while ``abortable`` is False (a second signal during a
    state save changes nothing). While ``abortable`` is True (phases that write nothing), it
    also raises KeyboardInterrupt at once. Outside the main thread no handler is installed.
    """

    def __init__(self, abortable: bool = False) -> None:
        self.stop = False
        self.signum: Optional[int] = None
        self.state_saved = False  # set by callers once a resumable state is on disk
        self._abortable = abortable
        self._old = {}

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not in the main thread
                pass
        return self

    def reinstall(self) -> None:
        """Put our handlers back after a library replaced them (pycolmap's glog installs a
        failure-signal handler for SIGTERM when it is first imported, which the lazy COLMAP
        import does in the middle of a run)."""
        for sig in list(self._old):
            signal.signal(sig, self._handle)

    def _handle(self, signum, frame) -> None:
        self.stop = True
        self.signum = signum
        if self._abortable:
            raise KeyboardInterrupt

    @property
    def abortable(self) -> bool:
        return self._abortable

    def set_abortable(self, value: bool) -> None:
        """Enter/leave an abortable phase; entering one after a signal raises KeyboardInterrupt."""
        self._abortable = bool(value)
        if self._abortable and self.stop:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        for sig, h in self._old.items():
            signal.signal(sig, h)
        self._old = {}


@torch.no_grad()
def weighted_count(view, share: float, cost_exponent: float) -> int:
    """How many Gaussians a level of ``share`` of the view's weighted cost draws: the longest
    prefix of the Gaussians in view by critical ``s_v`` (descending, ties by index: the order
    every budget uses) whose ``sum cost^cost_exponent`` is at most ``share`` of the total
    (``cost`` = :func:`clod_adapter.cost.splat_cost` at the base level, clipped ellipse pixels)."""
    from .cost import order_in_view, prefix_count, splat_cost

    order = order_in_view(view.critical, view.visible)
    if order.numel() == 0:
        return 0
    w = splat_cost(view, order).clamp_min(1e-12) ** float(cost_exponent)
    return prefix_count(w, float(share) * float(w.sum()))


def view_loss(g: Gaussians, camera, gt: Tensor, s_v: float, cfg: AdaptConfig, backend: str = "auto"):
    """One training view's render and loss at ``s_v`` (the body of a step of :func:`adapt`).

    Returns:
        (:class:`clod_adapter.camera_lod.LodRender`, scalar loss tensor).
    """
    if cfg.schedule == "calibrated" and cfg.cost_exponent > 0:
        # the level's exact share of the view's weighted cost, drawn with the level's gains
        view = view_lod(g, camera, tau=cfg.tau, eps=cfg.eps)
        k = weighted_count(view, lod.target_fraction(s_v), cfg.cost_exponent)
        out = render_lod(g, camera, budget=max(k, 1), min_s_v=0.0, tau=cfg.tau, eps=cfg.eps,
                         background=cfg.background, backend=backend, view=view)
    elif cfg.schedule == "calibrated":
        # the level's exact share of the Gaussians in view, drawn with the level's gains
        out = render_lod(g, camera, budget=lod.target_fraction(s_v), budget_in_view=True,
                         min_s_v=0.0, tau=cfg.tau, eps=cfg.eps, background=cfg.background,
                         backend=backend)
    else:
        out = render_lod(g, camera, s_v, tau=cfg.tau, eps=cfg.eps,
                         estimator=cfg.eta_estimator, temperature=cfg.temperature,
                         background=cfg.background, backend=backend)
    l_render = render_loss(out.image, gt)
    loss, _ = clod_loss(l_render, out.eta, s_v, cfg.max_sv, cfg.lambda_reg)
    if cfg.level_weighting == "uniform":
        # divided out rather than not applied: the same float rounding as every model adapted so
        # far (--deterministic runs reproduce to the last digit)
        loss = loss / lod.scale_weight(s_v, cfg.max_sv)
    return out, loss


def _draw_views(state: AdaptState, n_views: int, cfg: AdaptConfig) -> list:
    """One step's (view index, s_v) pairs: views shuffled without replacement per epoch, each
    with its own ``s_v``, drawn in that order from the state's generator (view, s_v, ...)."""
    picks = []
    for _ in range(cfg.views_per_step):
        if not state.order:
            state.order = torch.randperm(n_views, generator=state.generator).tolist()
        vi = state.order.pop()
        picks.append((vi, lod.sample_s_v(cfg.max_sv, state.generator, cfg.s_v_sampling)))
    return picks


def _record(h: dict, picks: list, rows: dict, ema: dict) -> None:
    """Append one step's records to the history ``h`` and update the progress averages ``ema``."""
    for j, (vi, s_v) in enumerate(picks):
        loss_j, p, eta = rows[j]
        h["s_v"].append(round(s_v, 4))
        h["eta"].append(round(eta, 5))
        h["loss"].append(round(loss_j, 6))
        h["psnr"].append(round(p, 3))
        for k, v in (("loss", h["loss"][-1]), ("psnr", p)):
            ema[k] = v if ema[k] is None else 0.9 * ema[k] + 0.1 * v


def adapt(
    state: AdaptState,
    train_cameras,
    train_images,
    cfg: AdaptConfig,
    *,
    backend: str = "auto",
    progress: bool = True,
    on_interrupt: Optional[Callable[[AdaptState], None]] = None,
    max_steps: Optional[int] = None,
    stop: Optional[StopFlag] = None,
    on_step: Optional[Callable[[AdaptState], None]] = None,
    group=None,
) -> bool:
    """Run (or continue) the fine-tuning from ``state.iteration`` to ``cfg.iterations``.

    Each step: ``cfg.views_per_step`` training views (shuffled, without replacement per
    epoch), each with its own ``s_v`` (:attr:`AdaptConfig.s_v_sampling`) (drawn in that order from the state's
    generator: view, s_v, view, s_v, ...), rendered at ``s_v``; ``L = w (L_render + lambda_reg
    L_reg)`` (``w``: the level weighting); one Adam step on the mean of the views' gradients;
    calibrated schedule: :func:`recalibrate` every ``cfg.recalibrate_every`` steps and after
    the last.

    Args:
        state: from :func:`prepare` or :func:`load_state`; updated in place.
        train_cameras, train_images: training views and their [H, W, 3] float images in [0, 1]
            (any sequence; only the views rendered here are indexed).
        cfg: the run's settings.
        backend: rasteriser backend.
        progress: show progress with loss, PSNR, s_v and rendered fraction (``frac``): a tqdm
            bar when stderr is a terminal, else a plain line every 10 %.
        on_interrupt: called with the state when SIGINT/SIGTERM stops the run early.
        max_steps: run at most this many steps in this call (the schedule still spans
            ``cfg.iterations``); None: run to the end.
        stop: an entered :class:`StopFlag` to use (the caller's signal handling, put in its
            non-abortable mode for the loop); None: install one for the duration of the call.
        on_step: called with the state after each completed step.
        group: a :class:`clod_adapter.distributed.Group` for data-parallel training (each rank
            renders views ``j`` with ``j mod world_size == rank`` of every step, gradients and
            the step's records are summed over the ranks, and a signal on any rank stops all of
            them after the same step); None: one process.

    Returns:
        True when all iterations ran, False when interrupted or stopped by ``max_steps``
        (state holds the progress).

    Raises:
        clod_adapter.distributed.PeerLost: (``group`` given) another rank stopped answering.
    """
    from .progress import progress_bar

    # a tqdm bar on a terminal; a plain line every 10 % in a log (stderr not a terminal)
    bar = progress_bar(cfg.iterations, "clod-adapt", unit="it", initial=state.iteration, disable=not progress)
    ema = {"loss": None, "psnr": None}
    stop_at = cfg.iterations if max_steps is None else min(cfg.iterations, state.iteration + max_steps)
    import contextlib

    if stop is None:
        ctx = StopFlag()
    else:
        stop.set_abortable(False)
        ctx = contextlib.nullcontext(stop)
    views = cfg.views_per_step
    rank, world = (group.rank, group.world_size) if group is not None else (0, 1)
    agreed_stop = False  # data-parallel: a signal on any rank, agreed in the step's reduction

    with ctx as flag:
        stopping = (lambda: agreed_stop) if group is not None else (lambda: flag.stop)
        while state.iteration < stop_at:
            if stopping():
                bar.close()
                if on_interrupt is not None:
                    on_interrupt(state)
                return False
            it = state.iteration
            picks = _draw_views(state, len(train_cameras), cfg)
            for grp in state.optimizer.param_groups:
                if grp["name"] == "means":
                    grp["lr"] = means_lr(cfg, state.extent, it)
            with torch.enable_grad():
                g = state.gaussians()
            state.optimizer.zero_grad(set_to_none=True)
            rows = {}
            for j, (vi, s_v) in enumerate(picks):
                if j % world != rank:
                    continue
                # grad on even when the caller is inside torch.no_grad() (an evaluation loop):
                # without it the step would silently train nothing
                with torch.enable_grad():
                    out, loss = view_loss(g, train_cameras[vi], train_images[vi], s_v, cfg, backend)
                    if loss.requires_grad:
                        loss.backward()
                rows[j] = (float(loss.detach()), psnr(out.image, train_images[vi]), float(out.eta.detach()))
                del out, loss
            if group is not None or views > 1:
                from .distributed import combine_step

                rows, agreed_stop = combine_step(state.optimizer, rows, views, group, stop=flag.stop)
            state.optimizer.step()
            state.iteration += 1
            if cfg.schedule == "calibrated" and (
                    state.iteration == cfg.iterations
                    or (cfg.recalibrate_every and state.iteration % cfg.recalibrate_every == 0)):
                recalibrate(state, train_cameras, cfg)
            _record(state.history, picks, rows, ema)
            # frac: the rendered fraction eta of the step (not tqdm's "time remaining")
            bar.set_postfix(loss=f"{ema['loss']:.4f}", psnr=f"{ema['psnr']:.2f}",
                            s_v=f"{picks[-1][1]:.2f}", frac=f"{rows[len(picks) - 1][2]:.3f}", refresh=False)
            bar.update(1)
            if on_step is not None:
                on_step(state)
        if stopping() and state.iteration >= stop_at:
            # a signal during the last step: the loop is done, report it all the same
            bar.close()
            if on_interrupt is not None:
                on_interrupt(state)
            return False
    bar.close()
    return state.iteration >= cfg.iterations


# --- resumable state -------------------------------------------------------------------------
#: the resumable state's file name in a clod-adapt output folder.
STATE_NAME = "adapt_state.safetensors"


def state_config(ply_path: os.PathLike) -> Optional[dict]:
    """The :class:`AdaptConfig` (as a dict) of the state beside an adapted .ply (its ``config``
    metadata, :func:`save_state`), or None when absent or unreadable."""
    p = Path(ply_path).parent / STATE_NAME
    if not p.is_file():
        return None
    try:
        from safetensors import safe_open

        with safe_open(str(p), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
        return json.loads(meta["config"])
    except Exception:
        return None


def max_sv_from_state(ply_path: os.PathLike) -> Optional[float]:
    """``max_sv`` of the adaptation state beside ``ply_path``, or None."""
    cfg = state_config(ply_path)
    try:
        return float(cfg["max_sv"]) if cfg else None
    except (KeyError, TypeError, ValueError):
        return None


def iterations_from_state(ply_path: os.PathLike) -> Optional[int]:
    """``iterations`` of the adaptation state beside ``ply_path``, or None."""
    cfg = state_config(ply_path)
    try:
        return int(cfg["iterations"]) if cfg else None
    except (KeyError, TypeError, ValueError):
        return None


def save_state(path: os.PathLike, state: AdaptState, cfg: AdaptConfig, extra_meta: Optional[dict] = None) -> None:
    """Write ``state`` to a safetensors file atomically.

    Tensors: ``param/<name>`` (raw parameters), ``adam/<name>/{exp_avg,exp_avg_sq,step}``,
    ``rng`` (torch generator state, uint8), ``order`` (remaining view order, int64).
    Metadata (strings): ``format`` = "clod-adapter-state/1", ``version``, ``iteration``,
    ``extent``, ``config`` (JSON of :class:`AdaptConfig`), ``history`` (JSON), plus
    ``extra_meta``.
    """
    from safetensors.torch import save_file

    tensors = {f"param/{k}": v.detach().cpu().contiguous() for k, v in state.params.items()}
    for grp in state.optimizer.param_groups:
        p = grp["params"][0]
        st = state.optimizer.state.get(p, {})
        for key in ("exp_avg", "exp_avg_sq", "step"):
            if key in st:
                tensors[f"adam/{grp['name']}/{key}"] = torch.as_tensor(st[key]).detach().cpu().reshape(-1).contiguous()
    tensors["rng"] = state.generator.get_state().contiguous()
    tensors["order"] = torch.tensor(state.order, dtype=torch.int64)
    meta = {
        "format": "clod-adapter-state/1",
        "version": __version__,
        "iteration": str(state.iteration),
        "extent": repr(state.extent),
        "config": json.dumps(asdict(cfg)),
        "history": json.dumps(state.history),
    }
    meta.update({k: str(v) for k, v in (extra_meta or {}).items()})
    atomic_save(path, lambda tmp: save_file(tensors, str(tmp), metadata=meta))


def load_state(path: os.PathLike, device: str | torch.device = "cpu") -> tuple[AdaptState, AdaptConfig, dict]:
    """Read a state written by :func:`save_state`.

    Returns:
        (state, config, metadata).

    Raises:
        ValueError: the file is not a clod-adapter state (message names the file).
    """
    from safetensors import safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:  # safetensors raises several types
        raise ValueError(f"{path}: not a readable safetensors state ({e})") from None
    if meta.get("format") != "clod-adapter-state/1":
        raise ValueError(f"{path}: not a clod-adapter state (format {meta.get('format')!r})")
    cfg_d = json.loads(meta["config"])
    cfg_d["background"] = tuple(cfg_d.get("background", (0, 0, 0)))
    cfg_d.setdefault("schedule", "paper")  # states written before the calibrated schedule
    cfg_d.setdefault("level_max", 1.0)  # states written before level_max: trained with the level held at 1

    try:
        cfg = AdaptConfig(**cfg_d)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: unusable config in state ({e})") from None
    train_others = cfg.other_lr_scale > 0
    params = {}
    for name in PARAM_NAMES + cfg.gain_names:
        key = f"param/{name}"
        if key not in tensors:
            raise ValueError(f"{path}: state lacks {key}")
        t = tensors[key].to(device)
        params[name] = torch.nn.Parameter(t, requires_grad=(name == "sigma_d") or (name in cfg.gain_names) or train_others)
    extent = float(meta["extent"])
    opt = torch.optim.Adam(_lr_groups(params, cfg, extent), eps=1e-15)
    for grp in opt.param_groups:
        p = grp["params"][0]
        key = f"adam/{grp['name']}/"
        if key + "exp_avg" in tensors:
            opt.state[p] = {
                "step": tensors[key + "step"].reshape(()).clone(),
                "exp_avg": tensors[key + "exp_avg"].reshape(p.shape).to(device),
                "exp_avg_sq": tensors[key + "exp_avg_sq"].reshape(p.shape).to(device),
            }
    gen = torch.Generator()
    gen.set_state(tensors["rng"])
    st = AdaptState(params=params, optimizer=opt, generator=gen, iteration=int(meta["iteration"]),
                    order=tensors["order"].tolist(), extent=extent, lod=cfg.lod_settings(),
                    history=json.loads(meta.get("history", "{}")) or {"s_v": [], "eta": [], "loss": [], "psnr": []})
    return st, cfg, meta
