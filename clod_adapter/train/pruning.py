"""Leaving out what a scene does not need before its level of detail is learned (opt-in:
``clod-adapt --keep-share``, :attr:`clod_adapter.train.config.AdaptConfig.keep_share`;
docs/method.md "Leaving Gaussians out first").

The input's Gaussians are ranked by their *blending weight*: ``sum alpha_i T_i`` over every
pixel of every training view, the share of the training images each one paints (the importance
Mini-Splatting prunes by, Fang & Wang, ECCV 2024; :func:`blend_weights`). The top ``keep_share``
are kept and every attribute of the survivors is fine-tuned with LightGaussian's recovery
schedule (:func:`clod_adapter.train.finetune.finetune_subset`) on the training views less a
held-out few (:func:`clod_adapter.io.scene.validation_split`). The recovery is kept whole when its
last step scores above the static cut on the held-out views, else the static cut is (skull:
33.10 dB for the cut, 30.43 after 1,000 steps, so the cut; fern: 26.97 -> 27.53, so the
recovery). Start and end only, not the best step between: the pretrained input was trained on
those views too, so the kept Gaussians still reproduce them from memory and a re-fit drifts away
from that, which biases their best step early. The full-detail level is then the kept model, no
longer the input: that is why it is not the default (docs/method.md "Leaving Gaussians out first": for
the same reason the validation views cannot choose it).
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional, Sequence

import torch
from torch import Tensor

from .config import FAINT_SHARE, RECOVERY_STEPS
from .finetune import FinetuneOptions, finetune_subset, global_cut
from ..gaussians import Gaussians



@torch.no_grad()
def blend_weights(gaussians: Gaussians, cameras: Sequence, *, backend: str = "auto") -> Tensor:
    """Each Gaussian's blending weight summed over the views: ``w_i = sum_views sum_pixels alpha_i
    T_i`` (alpha after gsplat 1.5.3's clamp to 0.999 and 1/255 skip, ``T_i`` the transmittance in
    front of it), the gradient of the rendered image's sum with respect to a constant per-Gaussian
    colour. For one view ``sum_i w_i`` is the sum of the rendered alpha (the identity
    ``tests/test_pruning.py`` holds it to).

    Args:
        gaussians: the model (N Gaussians); ``sigma_d`` and gains are not used (the plain model).
        cameras: views with ``viewmat`` [4, 4], ``K`` [3, 3] (pixels), ``width``, ``height``.
        backend: rasteriser backend (:func:`clod_adapter.render.rasterization`).

    Returns:
        [N] float64 weights (pixels; 0 for a Gaussian no view draws).
    """
    from ..render import rasterization

    g = gaussians.with_sigma_d(None)
    dev = g.means.device
    w = torch.zeros(len(g), dtype=torch.float64, device=dev)
    for c in cameras:
        feats = torch.ones(len(g), 1, dtype=g.means.dtype, device=dev, requires_grad=True)
        with torch.enable_grad():
            img, _, _ = rasterization(g.means, g.quats, g.scales, g.opacities, feats, c.viewmat[None].to(dev),
                                      c.K[None].to(dev), c.width, c.height, backend=backend)
            img.sum().backward()
        w += feats.grad[:, 0].double()
    return w


@dataclass
class LeaveOutInfo:
    """What :func:`leave_out` did (``metrics.json`` ``leave_out``).

    Attributes:
        keep_share: share of the input's Gaussians kept; input / kept: counts.
        recovery_steps: recovery steps run; fit_views / held_out_views: views they used / scored on.
        held_out_psnr: ``[[0, PSNR dB], [recovery_steps, PSNR dB]]`` on the held-out views: the
            static cut and the recovery's last step.
        chosen_step: what was kept: ``recovery_steps`` (the recovery) or 0 (the static cut).
        seconds: wall time of the ranking and the recovery.
    """

    keep_share: float
    input: int
    kept: int
    recovery_steps: int
    fit_views: int
    held_out_views: int
    held_out_psnr: list = field(default_factory=list)
    chosen_step: int = 0
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


@torch.no_grad()
def faint(gaussians: Gaussians, cameras: Sequence, share: float = FAINT_SHARE, *,
          backend: str = "auto") -> Tensor:
    """The Gaussians a scene does not need: those whose blending weight summed over every pixel of
    every view (:func:`blend_weights`) is under ``share`` of one view's pixels (``share x width x
    height`` of the first view; a share, so the rule does not change with the images' resolution).
    Together they change no view by more than that many pixels' worth of colour each.

    Args:
        gaussians: the model (N Gaussians; the plain model is scored).
        cameras: the views (the training views: what a user's checkpoint was trained on).
        share: the threshold, a share of one view's pixels (>= 0; 0 leaves nothing out).
        backend: rasteriser backend (:func:`clod_adapter.render.rasterization`).

    Returns:
        ([N] bool, True for a faint Gaussian; the threshold in pixels). When every Gaussian is
        faint, the one with the largest weight is not (a model keeps at least one).

    Raises:
        ValueError: ``share < 0`` or no camera.
    """
    if not share >= 0.0:
        raise ValueError(f"share must be >= 0, got {share}")
    if not cameras:
        raise ValueError("faint: no views")
    px = float(share) * cameras[0].width * cameras[0].height
    w = blend_weights(gaussians.with_sigma_d(None), cameras, backend=backend)
    out = w < px
    if bool(out.all()) and len(out):
        out[int(torch.argmax(w))] = False
    return out, px


def leave_out(gaussians: Gaussians, cameras: Sequence, images, *,
              keep_share: float, recovery_steps: int = RECOVERY_STEPS, background=(0.0, 0.0, 0.0),
              seed: int = 0, backend: str = "auto", progress: bool = False,
              log: Optional[Callable[[str], None]] = None) -> tuple[Gaussians, LeaveOutInfo]:
    """The input without what the training views need least, recovered (module docstring).

    Args:
        gaussians: the pretrained model (N Gaussians, plain: no ``sigma_d``).
        cameras: the training views; images: their [H, W, 3] float32 images in [0, 1],
            ``images[i]`` for ``cameras[i]`` (a list, or :class:`clod_adapter.io.view_images.ViewImages`).
        keep_share: share of the N kept, in (0, 1]; 1 returns the model unchanged.
        recovery_steps: steps of :func:`clod_adapter.train.finetune.finetune_subset` (recovery
            schedule) on the fit views of :func:`clod_adapter.io.scene.validation_split`, kept
            when the last step scores above the static cut on its validation views (a single
            training view: no held-out view, the recovery is kept). 0: the static cut.
        background, seed, backend, progress: as :func:`finetune_subset`.
        log: where a line per phase goes.

    Returns:
        ``(kept model (plain, ``round(keep_share N)`` Gaussians, at least 1), LeaveOutInfo)``.

    Raises:
        ValueError: ``keep_share`` outside (0, 1], ``recovery_steps < 0`` or no camera.
    """
    from ..io.scene import validation_split

    if not 0.0 < keep_share <= 1.0:
        raise ValueError(f"keep_share must be in (0, 1], got {keep_share}")
    if recovery_steps < 0:
        raise ValueError(f"recovery_steps must be >= 0, got {recovery_steps}")
    if not cameras:
        raise ValueError("leave_out: no training views")
    t0 = time.perf_counter()
    n = len(gaussians)
    plain = gaussians.with_sigma_d(None)
    if keep_share >= 1.0:
        return plain, LeaveOutInfo(1.0, n, n, 0, len(cameras), 0)
    w = blend_weights(plain, cameras, backend=backend)
    kept = plain.subset(global_cut(w, max(keep_share, 1.0 / max(n, 1))).to(plain.means.device))  # >= 1 kept
    if log is not None:
        log(f"leave out: kept {len(kept):,} of {n:,} Gaussians by blending weight over {len(cameras)} training "
            f"views ({time.perf_counter() - t0:.0f} s)")
    index = {id(c): i for i, c in enumerate(cameras)}
    fit, val = validation_split(list(cameras))
    info = LeaveOutInfo(float(keep_share), n, len(kept), int(recovery_steps), len(fit), len(val))
    if recovery_steps > 0:
        kept, ft = finetune_subset(kept, fit, [images[index[id(c)]] for c in fit],
                                   FinetuneOptions(iterations=recovery_steps, background=background, seed=seed,
                                                   backend=backend, val_every=0),
                                   val=(val, [images[index[id(c)]] for c in val]), return_info=True,
                                   progress="recovery" if progress else None)
        info.held_out_psnr = [[int(s), round(float(p), 3)] for s, p in ft.val_psnr]
        info.chosen_step = int(ft.best_step or 0)
        if log is not None:
            traj = ", ".join(f"{p:.2f}" for _, p in info.held_out_psnr)
            log(f"leave out: recovery {recovery_steps} steps on {len(fit)} views, held-out PSNR {traj} dB at steps "
                f"{', '.join(str(s) for s, _ in info.held_out_psnr)}; kept step {info.chosen_step}")
    info.seconds = round(time.perf_counter() - t0, 1)
    return kept, info


__all__ = ["blend_weights", "faint", "leave_out", "LeaveOutInfo"]
