"""Render a :class:`~clod_adapter.gaussians.Gaussians` model from one camera at a level of detail.

This joins the CLoD mechanism (:mod:`clod_adapter.lod`: Eq. 2 and the ``tau * s_v`` mask) to the
rasteriser (:func:`clod_adapter.render.rasterization`): only the Gaussians that pass the mask are
handed to the rasteriser, with their attenuated opacities ``alpha''``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import torch
from torch import Tensor

from . import lod
from .gaussians import Gaussians
from .render import rasterization


@dataclass
class LodRender:
    """Result of :func:`render_lod`.

    Attributes:
        image: [H, W, 3] rendered colours (float32, not clamped).
        alpha: [H, W, 1] accumulated opacity.
        mask: [N] bool, Gaussians handed to the rasteriser (those passing the LoD mask).
        n_rendered: number of Gaussians the rasteriser actually drew (passed the mask and
            projected onto the image, gsplat's ``radii > 0``): the render cost.
        n_frustum: number of Gaussian centres inside the view frustum.
        eta: scalar tensor, rendered fraction of the frustum (gradient per the estimator;
            1.0 without LoD).
        select_ms: wall time of the LoD selection (Eq. 2 + mask), milliseconds.
        raster_ms: wall time of the rasterisation, milliseconds.
        meta: the rasteriser's meta dict.
    """

    image: Tensor
    alpha: Tensor
    mask: Tensor
    n_rendered: int
    n_frustum: int
    eta: Tensor
    select_ms: float = 0.0
    raster_ms: float = 0.0
    meta: dict = field(default_factory=dict)


def render_lod(
    gaussians: Gaussians,
    camera,
    s_v: Optional[float] = None,
    *,
    tau: float = lod.DEFAULT_TAU,
    eps: float = lod.DEFAULT_EPS,
    estimator: str = "ste",
    temperature: float = 1.0,
    background: Optional[Sequence[float] | Tensor] = None,
    sh_degree: Optional[int] = None,
    backend: str = "auto",
    impl: str = "auto",
) -> LodRender:
    """Render ``gaussians`` from ``camera`` at virtual distance scale ``s_v``.

    Args:
        gaussians: the model (N Gaussians). ``sigma_d`` is required when ``s_v`` is given.
        camera: any object with ``viewmat`` [4, 4] (world-to-camera), ``K`` [3, 3] (pixels),
            ``width``, ``height`` (e.g. :class:`clod_adapter.io.scene.Camera`).
        s_v: virtual distance scale >= 1, or None for the plain model (no LoD, every Gaussian).
        tau: LoD threshold (mask ``alpha'' > tau s_v``).
        eps: Eq. 2's epsilon.
        estimator, temperature: gradient of ``eta`` (see :func:`clod_adapter.lod.rendered_fraction`).
        background: [3] colour behind the scene (default black, as 3DGS on LLFF).
        sh_degree: SH degree to evaluate (default: the model's).
        backend, impl: rasteriser backend (``"auto"``, ``"cpu"``, ``"gsplat"``) and CPU compositor.

    Returns:
        :class:`LodRender`.

    Raises:
        ValueError: ``s_v`` given but the model has no ``sigma_d``, or ``s_v < 1``.
    """
    means = gaussians.means
    dev = means.device
    viewmat = camera.viewmat.to(dev, means.dtype)
    K = camera.K.to(dev, means.dtype)
    w, h = int(camera.width), int(camera.height)
    t0 = time.perf_counter()
    frustum = lod.in_frustum(means, viewmat, K, w, h)
    opac = gaussians.opacities
    if s_v is None:
        mask = torch.ones_like(frustum)
        eta = torch.ones((), dtype=means.dtype, device=dev)
        opac_used = opac
    else:
        if gaussians.sigma_d is None:
            raise ValueError("render_lod: s_v given but the model has no sigma_d")
        if not s_v >= 1.0:
            raise ValueError(f"render_lod: s_v must be >= 1, got {s_v}")
        center = lod.camera_center(viewmat)
        d_norm = lod.normalized_distances(means, center, frustum)
        margin = lod.lod_margin(opac, d_norm, gaussians.sigma_d, s_v, tau, eps)
        # The mask covers every Gaussian: one whose centre lies just outside the image can
        # still cover pixels (the rasteriser culls by footprint). The frustum only defines
        # the normaliser of d' and the population of eta.
        mask = margin > 0
        eta = lod.rendered_fraction(margin, frustum, estimator, temperature)
        opac_used = lod.lod_opacities(opac, d_norm, gaussians.sigma_d, s_v, eps)
    idx = torch.nonzero(mask, as_tuple=False).squeeze(1)
    t1 = time.perf_counter()
    bg = None
    if background is not None:
        bg = torch.as_tensor(background, dtype=means.dtype, device=dev).reshape(1, 3)
    colors, alphas, meta = rasterization(
        means[idx], gaussians.quats[idx], gaussians.scales[idx], opac_used[idx],
        gaussians.colors[idx], viewmat[None], K[None], w, h,
        sh_degree=gaussians.sh_degree if sh_degree is None else sh_degree,
        backgrounds=bg, backend=backend, impl=impl,
    )
    t2 = time.perf_counter()
    n_vis = meta.get("n_visible")
    n_rendered = int(n_vis.reshape(-1)[0]) if n_vis is not None else int(idx.numel())
    return LodRender(
        image=colors[0], alpha=alphas[0], mask=mask, n_rendered=n_rendered,
        n_frustum=int(frustum.sum()), eta=eta, select_ms=(t1 - t0) * 1e3,
        raster_ms=(t2 - t1) * 1e3, meta=meta,
    )
