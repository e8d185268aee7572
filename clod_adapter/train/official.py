"""The official 3DGS training constants that the fine-tuning schedules reuse (graphdeco-inria
``gaussian-splatting``): its learning rates and its scene extent."""
from __future__ import annotations

import torch

from ..lod import rule as lod

__all__ = ["OFFICIAL_LR", "scene_extent"]

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


def scene_extent(cameras) -> float:
    """3DGS ``getNerfppNorm`` radius (world units): 1.1 x the largest distance of a camera
    centre from their mean (``cameras``: objects with a [4, 4] world-to-camera ``viewmat``)."""
    centers = torch.stack([lod.camera_center(c.viewmat.double()) for c in cameras])
    return float(1.1 * (centers - centers.mean(0)).norm(dim=1).max().clamp_min(1e-6))
