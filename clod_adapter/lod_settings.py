"""The settings an adapted model is drawn with (stored in its .ply header): :class:`LodSettings`
and the defaults of CLoD-GS's Eq. 2 (Cheng et al., ICLR 2026) that they start from. The rule
itself is :mod:`clod_adapter.lod.rule`."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal

#: default LoD threshold: 3DGS prunes opacities below 0.005, so at s_v = 1 every Gaussian of a
#: pretrained model passes (``alpha > tau``) when ``sigma_d`` is initialised large.
DEFAULT_TAU = 0.005
#: eps of Eq. 2 (denominator guard).
DEFAULT_EPS = 1e-8
#: smallest eps used: below it a dead Gaussian's exponent ``(d' s_v)^2 / eps`` and its
#: gradients overflow float32 (eps = 1e-45 gave NaN gradients at d' = 0, eps = 0 NaN values).
EPS_FLOOR = 1e-20
ETA_ESTIMATORS = ("ste", "sigmoid", "paper")
Estimator = Literal["ste", "sigmoid", "paper"]
#: how the Gaussians that pass the mask are drawn (module docstring).
FADES = ("window", "eq2")
Fade = Literal["window", "eq2"]
#: width ``w`` of the fade window in log-opacity units (``m`` of :func:`lod_margin`): a Gaussian
#: fades from full opacity to 0 as its ``alpha''`` falls from ``e^w tau s_v`` to ``tau s_v``
#: (0.75: docs/studies.md, "The knobs on the current checkpoints, with the merge tree").
DEFAULT_FADE_WIDTH = 0.75
#: the fade window opens from zero width at ``s_v = 1`` to its full width at this ``s_v``, so
#: full detail draws every Gaussian that passes the mask at its own opacity (and the image stays
#: continuous in ``s_v``: a Gaussian's weight ``m / width`` still reaches 0 where it leaves); the
#: blend from full detail to the rule (:func:`full_detail_share`) lasts at least this long, longer
#: in a view whose mask keeps less than all at ``s_v = 1`` (:func:`ramp_s_v`).
FADE_RAMP_S_V = 1.1


@dataclass(frozen=True)
class EtaGradient:
    """How the drawn share ``eta`` of an ``s_v`` frame carries a gradient (training only; CLoD-GS's
    ``L_reg``, :func:`clod_adapter.lod.rule.rendered_fraction`).

    Attributes:
        estimator: ``"ste"`` (straight-through), ``"sigmoid"`` or ``"paper"`` (no gradient).
        temperature: width of the sigmoid relaxation, log-opacity units.
        sigma_only: the gradient reaches ``sigma_d`` only (opacities and positions detached in the
            margin), so the count regulariser cuts Gaussians through their decay instead of eroding
            their opacity at every level.
    """

    estimator: Estimator = "ste"
    temperature: float = 1.0
    sigma_only: bool = True


@dataclass(frozen=True)
class LodSettings:
    """How an adapted model is drawn at a level of detail (stored in its .ply header).

    Attributes:
        max_sv: the largest virtual distance scale trained: the level of the gains is 1 where
            the drawn share is ``max_sv^-1.5`` (:func:`level_of_fraction`).
        level_max: the largest level of the gains (>= 1): below ``max_sv^-1.5`` of the
            Gaussians in view the level goes on growing with ``ln`` of the share up to this, in
            training and drawing alike (fewer survivors, grown further). Files written before it
            existed were trained with the level held at 1 and read as 1.
        tau: LoD threshold (mask ``alpha'' > tau s_v``).
        eps: Eq. 2's epsilon.
        fade: ``"window"`` or ``"eq2"`` (module docstring).
        fade_width: ``w`` of the window fade, log-opacity units (> 0).
        tier_s_v: the ``s_v`` (this model's own) at which its parent tier (``Gaussians.parents``:
            merged Gaussians, an adapted model of their own) takes over, as
            :func:`clod_adapter.train.tiers.link` chose it (0: no tier). With ``tier_start`` and
            ``tier_fade`` it places the hand-over of a merge tree: the parent tier's nodes enter
            around ``tier_fade * tier_s_v / tier_start`` times this tier's own scale
            (:func:`clod_adapter.lod.tree.tier_scales`).
        tier_start: the parent tier's own ``s_v`` at the hand-over (>= 1; 1: its full detail).
        tier_fade: the hand-over's width, a factor of ``s_v`` (> 1).
        tree: the tiers form a merge tree (each Gaussian of a tier names its parent in the next,
            ``Gaussians.extra["parent"]``) and an ``s_v`` or a budget draws one cut of it
            (:mod:`clod_adapter.lod.tree`; docs/lod_rule.md). Merged tiers not linked so are not
            drawn (a file holding them is refused, :func:`clod_adapter.io.ply.read_ply`).
    """

    max_sv: float = 5.0
    tau: float = DEFAULT_TAU
    eps: float = DEFAULT_EPS
    fade: Fade = "eq2"
    fade_width: float = DEFAULT_FADE_WIDTH
    level_max: float = 1.0
    tier_s_v: float = 0.0
    tier_start: float = 1.0
    tier_fade: float = 1.25
    tree: bool = False

    def __post_init__(self) -> None:
        if not self.max_sv >= 1.0:
            raise ValueError(f"max_sv must be >= 1, got {self.max_sv}")
        if not self.tau > 0:
            raise ValueError(f"tau must be > 0, got {self.tau}")
        if self.fade not in FADES:
            raise ValueError(f"fade must be one of {FADES}, got {self.fade!r}")
        if not self.fade_width > 0:
            raise ValueError(f"fade_width must be > 0, got {self.fade_width}")
        if not (self.level_max >= 1.0 and math.isfinite(self.level_max)):
            raise ValueError(f"level_max must be finite and >= 1, got {self.level_max}")
        if not (self.tier_s_v == 0.0 or (self.tier_s_v >= 1.0 and math.isfinite(self.tier_s_v))):
            raise ValueError(f"tier_s_v must be 0 (no tier) or finite and >= 1, got {self.tier_s_v}")
        if not (self.tier_start >= 1.0 and math.isfinite(self.tier_start)):
            raise ValueError(f"tier_start must be finite and >= 1, got {self.tier_start}")
        if not (self.tier_fade > 1.0 and math.isfinite(self.tier_fade)):
            raise ValueError(f"tier_fade must be finite and > 1, got {self.tier_fade}")
        if not isinstance(self.tree, bool):
            raise ValueError(f"tree must be a bool, got {self.tree!r}")

    def to_dict(self) -> dict:
        return asdict(self)
