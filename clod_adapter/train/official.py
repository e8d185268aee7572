"""The official 3DGS training setup that the fine-tuning schedules reuse (graphdeco-inria
``gaussian-splatting``): its learning rates (:data:`OFFICIAL_LR`), its log-linear position schedule
(:func:`means_lr`), Adam's parameter groups of the base attributes at those rates
(:func:`official_groups`) and Adam's epsilon (:data:`ADAM_EPS`), and its scene extent."""
from __future__ import annotations

import math
from typing import Mapping

import torch
from torch import Tensor

from ..lod import rule as lod

__all__ = ["OFFICIAL_LR", "BASE_FIELDS", "ADAM_EPS", "means_lr", "official_groups", "scene_extent"]

#: official 3DGS learning rates (arguments/__init__.py, OptimizationParams); means are scaled by
#: the scene extent and decay log-linearly from init to final over the run.
OFFICIAL_LR = {
    "means": (1.6e-4, 1.6e-6),
    "sh0": 2.5e-3,
    "shN": 2.5e-3 / 20.0,
    "opacity_logits": 5e-2,
    "log_scales": 5e-3,
    "quats": 1e-3,
}
#: the base attributes of a 3DGS model (``Gaussians`` fields), in the order their Adam groups take
BASE_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")
#: Adam's epsilon in official 3DGS (scene/gaussian_model.py, ``torch.optim.Adam(l, lr=0.0,
#: eps=1e-15)``); betas are torch's defaults, as there
ADAM_EPS = 1e-15


def means_lr(it: float, iterations: int, extent: float, *, start: float = OFFICIAL_LR["means"][0],
             end: float = OFFICIAL_LR["means"][1], scale: float = 1.0) -> float:
    """The position learning rate at step ``it`` (0-based) of a run of ``iterations`` steps: with
    ``t = clamp(it / iterations, 0, 1)``, ``exp((1 - t) ln start + t ln end) * extent * scale``
    (log-linear from ``start`` to ``end``, reached at ``it = iterations``; the defaults are the
    official 3DGS schedule, initial to final rate; ``extent``: the scene extent, world units,
    :func:`scene_extent`)."""
    t = min(max(it / max(iterations, 1), 0.0), 1.0)
    return math.exp(math.log(start) * (1 - t) + math.log(end) * t) * extent * scale


def official_groups(params: Mapping[str, Tensor], means: float, scale: float = 1.0) -> list:
    """Adam's parameter groups of the base attributes (:data:`BASE_FIELDS` of ``params``, name ->
    tensor; other keys ignored), one per attribute that is not empty, in that order, each named
    (``"name"``): ``means`` at the rate ``means`` (the caller's position schedule, e.g.
    :func:`means_lr`), every other attribute at its :data:`OFFICIAL_LR` times ``scale``.

    Raises:
        KeyError: ``params`` lacks one of :data:`BASE_FIELDS`.
    """
    return [{"params": [params[k]], "lr": means if k == "means" else OFFICIAL_LR[k] * scale, "name": k}
            for k in BASE_FIELDS if params[k].numel()]


def scene_extent(cameras) -> float:
    """3DGS ``getNerfppNorm`` radius (world units): 1.1 x the largest distance of a camera
    centre from their mean (``cameras``: objects with a [4, 4] world-to-camera ``viewmat``)."""
    centers = torch.stack([lod.camera_center(c.viewmat.double()) for c in cameras])
    return float(1.1 * (centers - centers.mean(0)).norm(dim=1).max().clamp_min(1e-6))
