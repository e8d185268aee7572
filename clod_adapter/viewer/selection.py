"""What a viewer sends for one camera at one level of detail.

The selection and the drawn attributes (positions, rotations, scales, opacities after the LoD
rule, SH coefficients) come from :func:`clod_adapter.lod.draw.lod_subset` only, so the viewer
draws what our renderer rasterises for that camera, whatever rule ``lod_subset`` implements.
The viewer then turns them into what viser's splat renderer takes: world-space covariances
``R diag(s)^2 R^T`` and RGB colours evaluated from the SH at the camera centre
(:func:`clod_adapter.render.sh.spherical_harmonics`, then ``+ 0.5``, clamped at 0, as 3DGS).

The static comparison is :func:`clod_adapter.lod.rankings.ranking_selection` on the model without
``sigma_d``, scored by opacity (the pretrained-style cut: the ``k`` most opaque Gaussians in
view, original opacities) at the count the LoD level draws.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from clod_adapter.lod.rankings import ranking_selection
from clod_adapter.gaussians import Gaussians
from clod_adapter.lod.budget import Budget
from clod_adapter.lod.draw import lod_subset
from clod_adapter.render.projection import quat_to_rotmat_rows
from clod_adapter.render.sh import spherical_harmonics

__all__ = ["DEFAULT_MAX_DRAWN", "BYTES_PER_GAUSSIAN", "ViewPayload", "view_payload", "covariances",
           "view_colors"]

#: above this many drawn Gaussians the viewer sends a budget-solved subset of this size
DEFAULT_MAX_DRAWN = 2_000_000
#: bytes per Gaussian in viser's splat buffer (centre 3 x f32, 4 reserved, covariance 6 x f16, RGBA 4 x u8)
BYTES_PER_GAUSSIAN = 32

METHOD_LOD = "clod"
METHOD_STATIC = "static_opacity_cut"
METHOD_ALL = "all_in_view"


@dataclass
class ViewPayload:
    """The Gaussians sent to one client camera (k of them) and how they were chosen.

    Attributes:
        indices: [k] int64 indices into the model, ascending (a merge tree's cut,
            :func:`clod_adapter.lod.draw.lod_subset`: only tier 0's rows; the arrays below hold
            them followed by the merged nodes drawn).
        means: [k, 3] float32 centres; covariances: [k, 3, 3] float32 world-space covariances;
        rgbs: [k, 3] float32 colours at the camera (>= 0, not clipped above);
        opacities: [k, 1] float32 drawn opacities (after the LoD rule for ``method="clod"``).
        method: ``"clod"`` (the LoD level), ``"static_opacity_cut"`` (the comparison) or
            ``"all_in_view"`` (a model without ``sigma_d``).
        n_total: Gaussians in the model; n_in_view: in view of the camera.
        n_level: what the requested level selects before the cap (the LoD count, parents included; for
            ``"all_in_view"`` the in-view count).
        s_v: the virtual distance scale drawn (solved in budget mode or under the cap; None
            without LoD).
        capped: the level selected more than ``max_drawn``; ``max_drawn`` were sent instead,
            chosen by the budget solver (by opacity for a model without ``sigma_d``).
        max_drawn: the cap in force.
    """

    indices: Tensor
    means: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray
    method: str
    n_total: int
    n_in_view: int
    n_level: int
    s_v: Optional[float]
    capped: bool
    max_drawn: int

    @property
    def n_drawn(self) -> int:
        """Gaussians sent (and drawn; a parent tier's included)."""
        return int(self.means.shape[0])

    @property
    def message_bytes(self) -> int:
        """Size of viser's per-update splat buffer for them: ``n_drawn * 32`` bytes."""
        return self.n_drawn * BYTES_PER_GAUSSIAN


def covariances(quats: Tensor, scales: Tensor) -> Tensor:
    """[N, 3, 3] world-space covariances ``R diag(scales)^2 R^T``.

    Args:
        quats: [N, 4] wxyz (unnormalised; normalised here, as the rasteriser does).
        scales: [N, 3] activated standard deviations, world units.
    """
    R = torch.stack(quat_to_rotmat_rows(quats), dim=-1).reshape(-1, 3, 3)
    RS = R * scales[:, None, :]
    return RS @ RS.transpose(1, 2)


def view_colors(means: Tensor, sh: Tensor, sh_degree: int, campos: Tensor) -> Tensor:
    """[N, 3] RGB of each Gaussian seen from ``campos`` [3]: SH (``sh`` [N, K, 3], gsplat layout)
    evaluated along ``means - campos``, ``+ 0.5``, clamped at 0 (3DGS / gsplat; the same path as
    :func:`clod_adapter.render.cpu.rasterization_cpu`)."""
    dirs = means - campos.to(means)
    return torch.clamp_min(spherical_harmonics(sh_degree, dirs, sh) + 0.5, 0.0)


@torch.no_grad()
def view_payload(gaussians: Gaussians, camera, *, s_v: Optional[float] = None,
                 budget: Optional[Budget] = None, compare: bool = False,
                 max_drawn: int = DEFAULT_MAX_DRAWN) -> ViewPayload:
    """The Gaussians a viewer sends for ``camera`` at one level, ready for viser.

    Args:
        gaussians: the model. Without ``sigma_d`` every Gaussian in view is sent (``s_v``,
            ``budget`` and ``compare`` are ignored).
        camera: ``viewmat`` [4, 4] world-to-camera, ``K`` [3, 3], ``width``, ``height``
            (e.g. :func:`clod_adapter.viewer.cameras.camera_from_pose`).
        s_v: virtual distance scale >= 1, or
        budget: a :class:`clod_adapter.lod.budget.Budget`, as :func:`clod_adapter.lod.draw.lod_subset`
            (a budget is a cap at the s_v = 1 level).
            Neither: s_v = 1.
        compare: send the static opacity cut at the count the level draws instead.
        max_drawn: cap on what is sent (>= 1): a larger level is replaced by
            ``lod_subset(..., budget=Budget(count=max_drawn))``.

    Raises:
        ValueError: ``s_v < 1``, both ``s_v`` and ``budget``, ``max_drawn < 1``.
    """
    if max_drawn < 1:
        raise ValueError(f"max_drawn must be >= 1, got {max_drawn}")
    g = gaussians
    n_total = len(g)
    if g.sigma_d is None:
        sub = lod_subset(g, camera)
        n_level, capped, method = int(sub.indices.numel()), False, METHOD_ALL
        idx, means, quats, scales, opac, sh = (sub.indices, sub.means, sub.quats, sub.scales,
                                               sub.opacities, sub.colors)
        if n_level > max_drawn:
            sel = ranking_selection(g, camera, g.opacities, max_drawn)
            capped, idx, opac = True, sel.indices, sel.opacities
            means, quats, scales, sh = g.means[idx], g.quats[idx], g.scales[idx], g.colors[idx]
        used_sv = None
    else:
        if s_v is None and budget is None:
            s_v = 1.0
        sub = lod_subset(g, camera, s_v=s_v, budget=budget)
        n_level, capped = int(sub.means.shape[0]), False  # a parent tier's rows included
        if n_level > max_drawn:
            sub, capped = lod_subset(g, camera, budget=Budget(count=int(max_drawn))), True
        used_sv = sub.s_v
        if compare:
            sel = ranking_selection(g.with_sigma_d(None), camera, g.opacities, int(sub.means.shape[0]))
            idx, opac, method = sel.indices, sel.opacities, METHOD_STATIC
            means, quats, scales, sh = g.means[idx], g.quats[idx], g.scales[idx], g.colors[idx]
        else:
            idx, means, quats, scales, opac, sh, method = (sub.indices, sub.means, sub.quats, sub.scales,
                                                           sub.opacities, sub.colors, METHOD_LOD)
    campos = camera.viewmat.detach().double().inverse()[:3, 3].float()
    rgb = view_colors(means, sh, g.sh_degree, campos)
    return ViewPayload(
        indices=idx, means=means.float().numpy(), covariances=covariances(quats, scales).float().numpy(),
        rgbs=rgb.float().numpy(), opacities=opac.float().reshape(-1, 1).numpy(), method=method,
        n_total=n_total, n_in_view=int(sub.n_in_view), n_level=n_level, s_v=used_sv, capped=capped,
        max_drawn=int(max_drawn))
