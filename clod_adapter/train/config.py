"""The options of one adaptation (:class:`AdaptConfig`), each with its default and its check, the
names they take (:data:`SCHEDULES`, :data:`RANKINGS`, :data:`MERGES`, the level gains' letters), and
the defaults that the stages running the job (:mod:`clod_adapter.train.tiers`,
:mod:`clod_adapter.train.tree_fit`, :mod:`clod_adapter.train.pruning`) read from here.
docs/method.md says what each default rests on."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Optional

from ..lod import rule as lod
# the merge tree's drawing rule: how a tier's hand-overs spread (R), where a child leaves (b) and
# where a parent enters (a) are constants of :func:`clod_adapter.lod.tree.build`, which places every
# node's interval with them; the job passes its choice of each (tree_spread, tree_exit_toward_parent,
# tree_entry_toward_children) and takes the rule's own as its default
from ..lod.tree import ENTRY_TOWARD_CHILDREN, EXIT_TOWARD_PARENT, SPREAD
from ..gaussians import GAIN_NAMES
from ..io.scene import RESOLUTIONS
from .official import OFFICIAL_LR

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
#: the merges a tier may start from (:attr:`AdaptConfig.tier_merge`): splat-transform 3.7.0's
#: ``--decimate`` and ``--decimate-adaptive`` (:func:`clod_adapter.lod.rankings.merge_decimate`'s
#: modes), and ``"prune"``: the first tier is the input's Gaussians of the largest
#: :func:`clod_adapter.train.tiers.prune_scores` (blending weight over the square root of cost) on the
#: training views, the later tiers ``--decimate``
MERGES = ("decimate", "adaptive", "prune")

# --- the job's defaults, each that of an AdaptConfig field (calibrated schedule) ----------------
#: the default tiers' shares of the input (:attr:`AdaptConfig.parent_share`), chosen on the
#: validation views (docs/archive/studies_chain.md "A chain of merged tiers")
DEFAULT_SHARES = (0.5, 0.15, 0.04)
#: the first tier's merge must be predicted to draw a frame in at most this share of the input's
#: (:func:`clod_adapter.train.tiers.first_share`, :attr:`AdaptConfig.tier_time_cap`): a first tier
#: that saves less leaves the upper middle of the range (75-90 % of the frame) to the input's faded
#: survivors. Chosen on the validation views (docs/archive/studies_superseded.md "A first tier that
#: saves time", measured before the merge tree)
TIER_TIME_CAP = 0.8
#: the latest ``s_v`` at which a merged tier hands over to the next (:attr:`AdaptConfig.tier_hand_over`):
#: past it a merged tier's survivors thin out and each leaves a visible step; the input's own
#: hand-over to the first tier stays the time rule's. Chosen on the validation views
#: (docs/archive/studies_superseded.md "Hand-overs out of the merged tiers", measured on the cross-fade chain that drew
#: the tiers then: popping up on every shared scene, no quality cell down by more than 0.01 dB)
TIER_HAND_OVER = 1.6
#: steps of the merge tree's fit on its cuts (:func:`clod_adapter.train.tree_fit.finetune`,
#: :attr:`AdaptConfig.tree_steps`)
TREE_STEPS = 1000
#: the share of those steps on count-budget cuts (:attr:`AdaptConfig.tree_budget_steps`)
TREE_BUDGET_STEPS = 0.5
#: the factor a merged node's scales may grow by in that fit (:attr:`AdaptConfig.tree_grow`): 1, none
#: ends larger than it entered (docs/studies.md "Merged nodes held at their size in the fit")
TREE_GROW = 1.0
#: the share of the roots (the last tier's nodes), those that leave last, that ``tree_grow`` does not
#: bound (:attr:`AdaptConfig.tree_free_roots`): a quarter
TREE_FREE_ROOTS = 0.25
#: :attr:`AdaptConfig.faint_share`: a Gaussian whose blending weight summed over every training view
#: is under this share of one view's pixels is left out (:func:`clod_adapter.train.pruning.faint`;
#: 1.7-1.8 px on the shared scenes' views). Chosen on the validation views (docs/studies.md "The faint
#: are left out by default"): the largest of 5e-6 / 1e-5 / 2e-5 that costs no shared scene 0.02 dB at full detail.
FAINT_SHARE = 1e-5
#: recovery steps of a leave-out (:attr:`AdaptConfig.recovery_steps`; LightGaussian recovers 5,000
#: on a GPU; 1,000 on fern's test views gave back all but 0.03 dB of a 40 % cut: docs/studies.md)
RECOVERY_STEPS = 1000


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
            eq2; :mod:`clod_adapter.lod.rule`).
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
            frame cost (footprint in pixels, :mod:`clod_adapter.lod.cost`). 0: the share of the
            *count* (the paper's target; coarse levels keep the largest splats, so they cost far
            more than their count); 1: the share of the frame *cost* (coarse levels reach
            ``max_sv^-1.5`` of the frame time, but mid levels lose what large splats cover
            cheaply); between: both. ``sigma_d`` is calibrated on these weighted quantiles and
            each step renders exactly that weighted share of the view.
        s_v_sampling: how each step draws its ``s_v`` (:func:`clod_adapter.lod.rule.sample_s_v`):
            ``"uniform"`` (the paper's ``U(1, max_sv)``; paper default) or ``"log"`` (``ln s_v``
            uniform: the levels near full detail trained as often as the coarse ones; calibrated
            default: on the validation views of skull and fern +0.1 to +0.6 dB at 11 of the 12
            decimator counts, docs/studies.md).
        level_max: the largest level of the gains (:attr:`clod_adapter.lod.rule.LodSettings.level_max`,
            >= 1): with cost levels a step's count share falls below ``max_sv^-1.5`` from ``s_v``
            about 3.2 on, where the default 1 holds the gains at one level. 2 lets them grow on
            (test views: +0.3 to +1.5 dB at ``s_v`` 15-30 on every scene, but -0.2 to -0.5 dB at
            ``s_v`` 2-5 on skull; docs/studies.md).
        trained_order_share: calibrated schedule: at the final recalibration (and every
            ``recalibrate_every`` steps), the learned order is kept for this share of the
            Gaussians, the top of it by count (the ones kept longest); the rest, the ones that
            leave first, are ordered by the starting ranking (``ranking``) again
            (:func:`merged_order`). 1 (default): the learned order throughout.
        parent_share: the parent tiers (:mod:`clod_adapter.train.tiers`): after the adaptation, the
            input merged by splat-transform's ``--decimate`` to each of these shares of its
            Gaussians (descending; a float is one share) is adapted too, each tier with the next
            as its own parents, and attached where it beats the tier above at equal predicted
            frame time (left out when it does not, for models under
            :data:`clod_adapter.train.tiers.PARENT_MIN_GAUSSIANS` Gaussians, and when splat-transform
            is not installed). Stored as a tuple; ``()`` or 0: no tier. Default
            :data:`DEFAULT_SHARES` (calibrated), none (paper). Chosen on the
            validation views: ``python -m benchmarks.quality_vs_time --split val --config
            parent_share=...`` (docs/studies.md).
        tier_finetune_steps: each merged tier's base attributes are fine-tuned at full detail
            for this many steps on the training views (:func:`clod_adapter.train.tiers.finetuned`,
            LightGaussian's recovery schedule) before its level of detail is learned: a merge is
            not a fitted model. 0: the merge as splat-transform wrote it. Default 400, chosen on
            the validation views (at 400 steps fern's 50 / 15 / 4 % merges +3.3 / +3.3 / +3.4 dB,
            0.17-0.34 dB more than at 200; skull's +0.09 / +0.25 / +0.51 dB, 0.03-0.08 dB less;
            ``benchmarks/archive/tier_finetune.py``, docs/archive/studies_superseded.md
            "Fitting each merge", measured before the merge tree).
        tier_merge: the merge each tier starts from, one of :data:`MERGES`:
            ``"prune"`` (default): the first tier is the input's Gaussians of the largest blending
            weight over the square root of their cost (:func:`clod_adapter.train.tiers.prune_scores`),
            the later ones splat-transform 3.7.0's ``--decimate``; ``"decimate"`` or ``"adaptive"``
            (``--decimate-adaptive``): every tier merged (docs/studies.md "The first tier pruned").
        tier_time_cap: the first tier's share is lowered (by 0.7x per try, not below the next
            share) while its merge is predicted to draw a frame in more than this share of the
            input's (:func:`clod_adapter.train.tiers.first_share`, the fitted frame-time model on the
            training views: no wall clock). Default :data:`TIER_TIME_CAP` (0.8):
            MaskGaussian fern's 50 % merge is predicted at 83 % and its first tier becomes 35 %;
            the vanilla checkpoints' 50 % merges (fern 77 %, skull 69 %) are kept. 0: the shares
            as given (docs/archive/studies_superseded.md "A first tier that saves time",
            measured before the merge tree).
        tier_hand_over: with merged tiers, the latest ``s_v`` (of the tier's own) at which each
            merged tier hands over to the next (:func:`clod_adapter.train.tiers.link`; the input's own
            hand-over to the first tier stays where the time rule puts it). Default
            :data:`TIER_HAND_OVER` (1.6) with the calibrated schedule; 0:
            where the time rule puts it (docs/archive/studies_superseded.md "Hand-overs out of the
            merged tiers", measured on the cross-fade chain that drew the tiers then: on the
            validation views popping median fern 15.6 -> 17.9, MaskGaussian fern 15.2 -> 16.6, skull 9.3 -> 11.9, no
            quality cell down by more than 0.01 dB). The linked tiers become a merge tree (each
            Gaussian names its parent in the next tier) drawn as one cut per frame
            (:mod:`clod_adapter.lod.tree`; docs/method.md "The merge tree").
        tree_steps: the merge tree's merged tiers are fitted on the tree's own cuts for this many
            steps, at most ``iterations`` (:func:`clod_adapter.train.tree_fit.finetune`; 0: not
            fitted; on fern's validation views popping and quality at equal count rise with the
            steps: docs/studies.md "Fitting the tree on its cuts").
        tree_budget_steps: the share of those steps that draws a count budget's cut (shares of the
            Gaussians in view from 100 % to 1 %, log-uniform) instead of a level's, in [0, 1]
            (:func:`clod_adapter.train.tree_fit.finetune`'s ``budget_steps``). Default
            :data:`TREE_BUDGET_STEPS` (0.5): the tree is trained on the
            cuts of both knobs (docs/studies.md "Fitting the tree on its cuts"); 0: levels only.
        tree_grow: in that fit a merged node's scales grow by at most this factor over what they
            were when the fit began (:func:`clod_adapter.train.tree_fit.finetune`'s ``grow``, >= 1;
            None: no bound). Default :data:`TREE_GROW`, 1. Unbounded,
            the fit grows the coarse nodes to fill what their exits leave, and a count budget's
            frame costs more than a merge of that count; held at 1 the frame costs less, and the
            coarsest levels would lose 2-4 dB but for ``tree_free_roots`` leaving their roots free
            (docs/studies.md "Merged nodes held at their size in the fit"); no command-line flag.
        tree_free_roots: with ``tree_grow``, the share of the roots (the last tier's nodes) that
            leave last, the ones the coarsest levels draw alone, left free to grow
            (:func:`clod_adapter.train.tree_fit.finetune`'s ``free_roots``, in [0, 1]; default
            :data:`TREE_FREE_ROOTS`, 0.25); no command-line flag.
        tree_spread: a tier's hand-overs spread over this factor of ``s_v`` by importance
            (:func:`clod_adapter.lod.tree.build`'s ``spread``, > 1; default
            :data:`clod_adapter.lod.tree.SPREAD`, 2). Set when the tree is built, so a model
            adapted with another spread is another model (docs/studies.md "How far a tier's
            hand-overs spread"); no command-line flag.
        tree_exit_toward_parent: a child that is not its parent's lead leaves this share of the way,
            in ``ln s_v``, from where its tier's own level of detail drops it toward where its
            parent takes over (:func:`clod_adapter.lod.tree.build`'s ``exit_toward_parent``, in
            [0, 1]; default :data:`clod_adapter.lod.tree.EXIT_TOWARD_PARENT`, 0.25), so a frame's
            count falls near the hand-overs that change its image. Set when the tree is built
            (docs/studies.md "Where a child leaves"); no command-line flag.
        tree_entry_toward_children: a merged node with children other than its lead enters this
            share of the way, in ``ln s_v``, from where its tier's spread puts it toward where the
            last of those children leaves (:func:`clod_adapter.lod.tree.build`'s
            ``entry_toward_children``, in [0, 1]; default
            :data:`clod_adapter.lod.tree.ENTRY_TOWARD_CHILDREN`, 0.5), so the lead turns into its
            parent nearer where its siblings leave. Set when the tree is built (docs/studies.md
            "When a parent takes over"); no command-line flag.
        tier_iteration_share: each merged tier learns its level of detail for this share of
            ``iterations`` (rounded, at least 1 when ``iterations`` > 0). Default 0.5: with the tree
            fitted on its cuts afterwards (``tree_steps``), half the steps score within 0.4 dB of
            every step at equal count on the validation views and take about a third off the job
            (docs/studies.md "Half the level-of-detail steps per tier"); 1: every step.
        tier_downscale: the second and later merged tiers are fine-tuned and learn their level of
            detail on the training views at 1/``tier_downscale`` of the model's resolution (at most
            1/8 of the images'); every hand-over is still chosen at a full-size view. The first
            tier, which draws the middle of the range, keeps the model's resolution
            (docs/studies.md "The later tiers trained at half resolution").
        faint_share: leave out, before anything else, the Gaussians whose blending weight summed
            over every pixel of every training view is under this share of one view's pixels
            (:func:`clod_adapter.train.pruning.faint`; no recovery: together they paint under that
            much of the training images each). Default :data:`FAINT_SHARE`
            (1e-5, calibrated), 0 (paper: every Gaussian). Chosen on the validation views
            (docs/studies.md "The faint are left out by default"): the largest that costs no
            shared scene 0.02 dB at full detail.
        keep_share: leave out what the scene does not need first (:mod:`clod_adapter.train.pruning`):
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
            (:mod:`clod_adapter.train.distributed`) view ``j`` of a step is rendered by rank
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
    tier_iteration_share: float = 0.5
    tier_downscale: int = 2
    tier_merge: str = "prune"
    tier_time_cap: Optional[float] = None
    tier_hand_over: Optional[float] = None
    tree_steps: int = TREE_STEPS
    tree_budget_steps: float = TREE_BUDGET_STEPS
    tree_grow: Optional[float] = TREE_GROW
    tree_free_roots: float = TREE_FREE_ROOTS
    tree_spread: float = SPREAD
    tree_exit_toward_parent: float = EXIT_TOWARD_PARENT
    tree_entry_toward_children: float = ENTRY_TOWARD_CHILDREN
    faint_share: Optional[float] = None
    keep_share: float = 1.0
    recovery_steps: int = RECOVERY_STEPS

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
            self.parent_share = DEFAULT_SHARES if cal else ()
        shares = self.parent_share if isinstance(self.parent_share, (tuple, list)) else (self.parent_share,)
        self.parent_share = tuple(float(x) for x in shares if float(x) != 0.0)
        if not all(0.0 < x < 1.0 for x in self.parent_share) or \
                any(b >= a for a, b in zip(self.parent_share, self.parent_share[1:])):
            raise ValueError(f"parent_share must be descending shares in (0, 1), got {shares}")
        if not (isinstance(self.tier_finetune_steps, int) and self.tier_finetune_steps >= 0):
            raise ValueError(f"tier_finetune_steps must be >= 0 (an integer), got {self.tier_finetune_steps!r}")
        if self.tier_merge not in MERGES:
            raise ValueError(f"tier_merge must be one of {MERGES}, got {self.tier_merge!r}")
        if self.tier_time_cap is None:
            self.tier_time_cap = TIER_TIME_CAP if cal else 0.0
        self.tier_time_cap = float(self.tier_time_cap)
        if not (math.isfinite(self.tier_time_cap) and 0.0 <= self.tier_time_cap <= 1.0):
            raise ValueError(f"tier_time_cap must be in [0, 1] (a share of the input's frame time), "
                             f"got {self.tier_time_cap}")
        if self.tier_hand_over is None:
            self.tier_hand_over = TIER_HAND_OVER if cal else 0.0
        self.tier_hand_over = float(self.tier_hand_over)
        if not (self.tier_hand_over == 0.0 or (math.isfinite(self.tier_hand_over) and self.tier_hand_over > 1.0)):
            raise ValueError(f"tier_hand_over must be 0 (the time rule's) or an s_v > 1, got {self.tier_hand_over}")
        if int(self.tree_steps) != self.tree_steps or self.tree_steps < 0:
            raise ValueError(f"tree_steps must be a count >= 0, got {self.tree_steps}")
        self.tree_steps = int(self.tree_steps)
        self.tree_budget_steps = float(self.tree_budget_steps)
        if not 0.0 <= self.tree_budget_steps <= 1.0:
            raise ValueError(f"tree_budget_steps must be in [0, 1], got {self.tree_budget_steps}")
        if self.tree_grow is not None:
            self.tree_grow = float(self.tree_grow)
            if not (math.isfinite(self.tree_grow) and self.tree_grow >= 1.0):
                raise ValueError(f"tree_grow must be a factor >= 1 or None, got {self.tree_grow}")
        self.tree_spread = float(self.tree_spread)
        if not (math.isfinite(self.tree_spread) and self.tree_spread > 1.0):
            raise ValueError(f"tree_spread must be a factor > 1, got {self.tree_spread}")
        for key in ("tree_exit_toward_parent", "tree_entry_toward_children", "tree_free_roots"):
            setattr(self, key, float(getattr(self, key)))
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ValueError(f"{key} must be in [0, 1], got {getattr(self, key)}")
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
        """The :class:`clod_adapter.lod.rule.LodSettings` the adapted model is drawn with."""
        return lod.LodSettings(max_sv=self.max_sv, tau=self.tau, eps=self.eps, fade=self.fade,
                               fade_width=self.fade_width, level_max=self.level_max)
