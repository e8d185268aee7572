"""Discrete level of detail, the per-budget ceiling: one fine-tuned model per level.

:func:`finetune_subset` takes a fixed subset of a pretrained model (the Gaussians a static ranking
keeps at one budget) and fine-tunes every attribute on the training views with the official 3DGS
learning rates (graphdeco-inria ``arguments/__init__.py``; positions scaled by the scene extent
and decayed log-linearly), as LightGaussian does after pruning. One such model per budget is what
a discrete-LoD pipeline ships: ``clod-eval`` reports it as ``dlod_finetuned`` beside the one
adapted model, with its storage (the sum of the levels).
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from .adapt import OFFICIAL_LR, scene_extent
from .gaussians import Gaussians
from .losses import render_loss
from .view import render_lod

_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")


def global_cut(scores: Tensor, fraction: float) -> Tensor:
    """[k] int64 ascending indices of the ``k = round(fraction N)`` highest ``scores`` [N] (ties
    by lower index): one discrete level cut from a global ranking."""
    n = scores.numel()
    k = max(0, min(n, int(round(float(fraction) * n))))
    order = torch.sort(-scores.double(), stable=True).indices[:k]
    return torch.sort(order).values


def finetune_subset(gaussians: Gaussians, train_cameras: Sequence, train_images: Sequence[Tensor], *,
                    iterations: int, lr_scale: float = 1.0, seed: int = 0, background=(0.0, 0.0, 0.0),
                    backend: str = "auto", progress: bool = False, desc: str = "dlod") -> Gaussians:
    """Fine-tune every attribute of ``gaussians`` (a fixed subset, no LoD, no densification).

    Each step renders one training view (shuffled, without replacement per epoch) with the whole
    model and takes an Adam step on ``0.8 L1 + 0.2 D-SSIM`` with the official 3DGS learning rates
    times ``lr_scale``.

    Args:
        gaussians: the level's model (N Gaussians; ``sigma_d`` and gains are dropped).
        train_cameras, train_images: training views and [H, W, 3] float32 images in [0, 1].
        iterations: optimisation steps.
        lr_scale: factor on the official learning rates.
        seed: seed of the view order.
        background: RGB behind the scene.
        backend: rasteriser backend.
        progress: show a tqdm bar.

    Returns:
        the fine-tuned model (detached copy).
    """
    from tqdm.auto import tqdm

    g = gaussians.with_sigma_d(None).clone()
    params = {k: torch.nn.Parameter(getattr(g, k).detach().clone().contiguous()) for k in _FIELDS}
    extent = scene_extent(train_cameras)
    groups = []
    for k in _FIELDS:
        if params[k].numel() == 0:
            continue
        lr = OFFICIAL_LR[k][0] * extent if k == "means" else OFFICIAL_LR[k]
        groups.append({"params": [params[k]], "lr": lr * lr_scale, "name": k})
    opt = torch.optim.Adam(groups, eps=1e-15)
    gen = torch.Generator().manual_seed(seed)
    init, final = OFFICIAL_LR["means"]
    order: list = []
    for it in tqdm(range(iterations), desc=desc, disable=not progress, leave=False):
        t = it / max(iterations, 1)
        for grp in opt.param_groups:
            if grp["name"] == "means":
                grp["lr"] = math.exp(math.log(init) * (1 - t) + math.log(final) * t) * extent * lr_scale
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
        opt.step()
    return Gaussians(**{k: v.detach() for k, v in params.items()})
