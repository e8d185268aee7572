"""Baselines for fixed Gaussian budgets: which ``k`` Gaussians of a pretrained model to render.

Every selection picks among the same population as :func:`clod_adapter.lod.draw.render_lod`
(:func:`clod_adapter.lod.view.in_view`: Gaussians whose footprint reaches the image), so a
budget of ``k`` means the same thing for every method, and returns the indices plus the
opacities to draw them with. :func:`render_subset` then hands exactly those Gaussians to the
rasteriser, the way ``render_lod`` does.

* :func:`constant_sigma_selection`: CLoD-GS Eq. 2 with one constant ``sigma_d = c`` for every
  Gaussian (the paper's "fair comparison" of opacity ranking without a learned decay). The
  ``k`` Gaussians with the largest critical ``s_v`` are kept (:mod:`clod_adapter.lod.budget`) and
  drawn with Eq. 2's attenuated opacities at the solved ``s_v``. Default ``c``: the median of
  the adapted model's ``ReLU(sigma_d)`` (:func:`default_sigma_c`).
* :func:`lightgaussian_significance`: LightGaussian's global significance (Fan et al., NeurIPS
  2024, Sec. 3.1; code ``VITA-Group/LightGaussian``, ``prune.py: calculate_v_imp_score`` and the
  ``count_render`` rasteriser): ``score_i = (sum over training views of opacity_i x pixels hit)
  x (V_i / V_ref)^0.1``, ranked once globally; per view the ``k`` best in view are drawn.
* :func:`random_scores`: a seeded random global ranking (same top-k-in-view rule).

All baselines except the constant-sigma one render the original opacities.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Literal, Optional, Sequence

import torch
from torch import Tensor

from . import rule as lod
from .budget import select_budget
from ..gaussians import Gaussians
from ..render.projection import ALPHA_THRESHOLD, GAUSSIAN_EXTEND, project_visible
from .view import LodView, view_lod
from ..io.splat_transform import PeerError, run_splat_transform

#: LightGaussian's volume exponent (``--v_pow 0.1`` in their prune scripts).
LIGHTGAUSSIAN_V_POW = 0.1


@dataclass
class Selection:
    """The Gaussians one baseline renders for one camera.

    Attributes:
        indices: [k] int64 indices into the model, sorted ascending.
        opacities: [k] float32 opacities to draw them with.
        s_v: the solved virtual distance scale (constant-sigma baseline), else None.
        select_ms: wall time of the selection for this camera (in-view test + ranking), ms.
        view: the camera's :class:`clod_adapter.lod.view.LodView` (its projection is reused to draw).
    """

    indices: Tensor
    opacities: Tensor
    s_v: Optional[float] = None
    select_ms: float = 0.0
    view: Optional[LodView] = None


@dataclass
class SubsetRender:
    """Result of :func:`render_subset`: ``image`` [H, W, 3] float32 (not clamped), ``alpha``
    [H, W, 1], ``n_rendered`` (Gaussians handed to the rasteriser), ``raster_ms`` (ms)."""

    image: Tensor
    alpha: Tensor
    n_rendered: int
    raster_ms: float


@torch.no_grad()
def render_subset(gaussians: Gaussians, camera, indices: Tensor, opacities: Optional[Tensor] = None,
                  *, background=None, sh_degree: Optional[int] = None, backend: str = "auto",
                  view: Optional[LodView] = None) -> SubsetRender:
    """Rasterise exactly the Gaussians ``indices`` of ``gaussians`` (as ``render_lod`` does).

    Args:
        gaussians: the model (N Gaussians; drawn at its base level, without LoD).
        camera: object with ``viewmat`` [4, 4], ``K`` [3, 3], ``width``, ``height``.
        indices: [k] int64 indices to render (ascending; Gaussians out of view are culled).
        opacities: [k] opacities for them (default: the model's activated opacities).
        background: [3] RGB behind the scene (default black).
        sh_degree, backend: as :func:`clod_adapter.render.rasterization`.
        view: the camera's :class:`clod_adapter.lod.view.LodView` of ``gaussians`` when the caller
            has it (its projection is reused).
    """
    v = view if view is not None else view_lod(gaussians.with_sigma_d(None), camera)
    idx = indices.to(gaussians.means.device)
    op = None if opacities is None else opacities.to(gaussians.means)
    keep = v.geometry_rows.index_select(0, idx) >= 0  # in front of the camera (the rest is culled anyway)
    if not bool(keep.all()):
        idx = idx[keep]
        op = None if op is None else op[keep]
    bg = None
    if background is not None:
        bg = torch.as_tensor(background, dtype=gaussians.means.dtype, device=gaussians.means.device)
    t0 = time.perf_counter()
    img, alpha, _ = v.rasterize(v.subset(idx, op), background=bg,
                                sh_degree=gaussians.sh_degree if sh_degree is None else sh_degree, backend=backend)
    t1 = time.perf_counter()
    return SubsetRender(img, alpha, int(indices.numel()), (t1 - t0) * 1e3)


def topk_in_view(scores: Tensor, visible: Tensor, k: int) -> Tensor:
    """[min(k, visible.sum())] int64 indices of the ``k`` highest ``scores`` among ``visible``
    Gaussians (ties broken by lower index), sorted ascending."""
    pool = torch.nonzero(visible, as_tuple=False).squeeze(1)
    k = max(0, min(int(k), pool.numel()))
    order = torch.sort(-scores[pool].double(), stable=True).indices[:k]
    return torch.sort(pool[order]).values


@torch.no_grad()
def ranking_selection(gaussians: Gaussians, camera, scores: Tensor, k: int) -> Selection:
    """Global-ranking baseline for one camera: the ``k`` best-scored Gaussians in view, drawn
    with their original opacities. ``scores`` [N] (higher = kept first), e.g. from
    :func:`lightgaussian_significance` or :func:`random_scores`."""
    t0 = time.perf_counter()
    view = view_lod(gaussians.with_sigma_d(None), camera)
    idx = topk_in_view(scores.to(view.visible.device), view.visible, k)
    return Selection(idx, view.opacities.index_select(0, idx), None, (time.perf_counter() - t0) * 1e3, view)


def default_sigma_c(adapted: Gaussians) -> float:
    """Default constant decay for :func:`constant_sigma_selection`: the median of the adapted
    model's ``ReLU(sigma_d)`` (the decay a "typical" adapted Gaussian has)."""
    if adapted.sigma_d is None:
        raise ValueError("default_sigma_c: the model has no sigma_d")
    return float(torch.relu(adapted.sigma_d.detach().float()).median())


@torch.no_grad()
def constant_sigma_selection(gaussians: Gaussians, camera, k: int, sigma_c: float, *,
                             tau: float = lod.DEFAULT_TAU, eps: float = lod.DEFAULT_EPS,
                             fade: bool = False) -> Selection:
    """Opacity ranking by CLoD-GS Eq. 2 with ``sigma_d = sigma_c`` for every Gaussian.

    For one constant decay the critical ``s*`` of each Gaussian (rendered iff ``s_v < s*``)
    grows with its opacity and shrinks with its frustum-normalised distance ``d'``; the ``k``
    largest among the Gaussians in view are kept (:func:`clod_adapter.lod.budget.select_budget`,
    ties by index). They are drawn with their original opacities (a pure selection baseline);
    ``fade=True`` draws them with Eq. 2's ``alpha''`` at the solved ``s_v`` instead, which with
    one shared small decay fades almost every kept Gaussian (on fern: ~5 dB at 50 %).

    Args:
        gaussians: the pretrained model (its own ``sigma_d``, if any, is ignored).
        camera: the view.
        k: number of Gaussians (clamped to those in view).
        sigma_c: the constant decay (> 0).
        tau, eps: the LoD threshold and Eq. 2's epsilon.
        fade: draw with Eq. 2's attenuated opacities instead of the original ones.
    """
    if not sigma_c > 0:
        raise ValueError(f"sigma_c must be > 0, got {sigma_c}")
    t0 = time.perf_counter()
    plain = gaussians.with_sigma_d(None)
    sig = torch.full((len(plain),), float(sigma_c), dtype=plain.means.dtype, device=plain.means.device)
    view = view_lod(plain.with_sigma_d(sig), camera, tau=tau, eps=eps)
    idx, s_v = select_budget(view.critical, k, view.visible)
    opac = view.opacities.index_select(0, idx)
    op = lod.lod_opacities(opac, view.d_norm[idx], sig[idx], s_v, eps) if fade else opac
    return Selection(idx, op, s_v, (time.perf_counter() - t0) * 1e3, view)


#: constant decays tried by :func:`tune_sigma_c` (from "distance dominates" to "opacity only").
SIGMA_C_CANDIDATES = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 100.0)


@torch.no_grad()
def tune_sigma_c(gaussians: Gaussians, cameras: Sequence, images: Sequence[Tensor],
                 fraction: float = 0.5, candidates: Sequence[float] = SIGMA_C_CANDIDATES,
                 views: int = 3, background=(0.0, 0.0, 0.0), backend: str = "auto") -> float:
    """The constant decay that serves :func:`constant_sigma_selection` best, chosen on
    *training* views: the candidate with the highest mean PSNR at ``fraction`` of the model.

    A small constant makes the critical ``s*`` rank by distance alone (only the nearest Gaussians
    survive: ~10 dB on fern at c = 0.2); a large one ranks by opacity. Tuning c on training views
    gives the baseline its best shot without looking at the test views.

    Returns:
        the chosen c (one of ``candidates``).
    """
    from ..metrics import psnr

    idx = torch.linspace(0, len(cameras) - 1, min(views, len(cameras))).round().long().tolist()
    k = int(round(fraction * len(gaussians)))
    best, best_c = -float("inf"), float(candidates[0])
    for c in candidates:
        ps = []
        for i in idx:
            sel = constant_sigma_selection(gaussians, cameras[i], k, float(c))
            img = render_subset(gaussians, cameras[i], sel.indices, sel.opacities, view=sel.view,
                                background=background, backend=backend).image
            ps.append(psnr(img, images[i]))
        score = sum(ps) / len(ps)
        if score > best:
            best, best_c = score, float(c)
    return best_c


@torch.no_grad()
def pixels_hit(gaussians: Gaussians, camera) -> Tensor:
    """[N] float32 estimate of the pixels each Gaussian touches in one view.

    The 3DGS/LightGaussian rasteriser counts a pixel when ``alpha = o exp(-q/2) >= 1/255``, with
    ``q`` the conic's quadratic form: the ellipse ``q <= 2 ln(255 o)``, whose area is
    ``pi 2 ln(255 o) sqrt(det Sigma_2D)``. We use that area with the extent capped at gsplat
    1.5.3's 3.33 sigma, times the fraction of the bounding box ``mean2d +- radius`` that lies
    inside the image (clipping). Transmittance early-out (pixels behind an opaque surface) is
    ignored, so occluded Gaussians are over-counted relative to ``count_render``.
    """
    dev, dt = gaussians.means.device, gaussians.means.dtype
    viewmat, K = camera.viewmat.to(dev, dt), camera.K.to(dev, dt)
    w, h = int(camera.width), int(camera.height)
    n = len(gaussians)
    out = torch.zeros(n, dtype=torch.float32, device=dev)
    if n == 0:
        return out
    op = gaussians.opacities
    pv = project_visible(gaussians.means, gaussians.quats, gaussians.scales, op, viewmat, K, w, h)
    a, b, c = pv.conics.unbind(-1)
    det_conic = (a * c - b * b).clamp_min(1e-30)
    o = op[pv.ids].clamp_min(ALPHA_THRESHOLD)
    e2 = (2.0 * torch.log(o / ALPHA_THRESHOLD)).clamp(0.0, GAUSSIAN_EXTEND ** 2)
    area = math.pi * e2 / torch.sqrt(det_conic)
    r = pv.radii.to(torch.float32)
    mx, my = pv.means2d.unbind(-1)
    fx = ((mx + r[:, 0]).clamp(0, w) - (mx - r[:, 0]).clamp(0, w)) / (2 * r[:, 0]).clamp_min(1)
    fy = ((my + r[:, 1]).clamp(0, h) - (my - r[:, 1]).clamp(0, h)) / (2 * r[:, 1]).clamp_min(1)
    out[pv.ids] = (area * fx.clamp(0, 1) * fy.clamp(0, 1)).float()
    return out


def volume_factor(gaussians: Gaussians, v_pow: float = LIGHTGAUSSIAN_V_POW) -> Tensor:
    """[N] LightGaussian's normalised volume term ``(V_i / V_ref)^v_pow``.

    As in ``calculate_v_imp_score``: ``V = prod(scales)``; ``V_ref`` is the element at position
    ``int(0.9 N)`` of the volumes sorted in *descending* order (the code calls it
    "kth_percent_largest"; it is the 10th percentile from below).
    """
    vol = torch.prod(gaussians.scales.detach().double(), dim=1)
    if vol.numel() == 0:
        return vol.float()
    ref = torch.sort(vol, descending=True).values[int(vol.numel() * 0.9)].clamp_min(1e-300)
    return torch.pow(vol / ref, v_pow).float()


@torch.no_grad()
def lightgaussian_significance(gaussians: Gaussians, train_cameras: Sequence,
                               v_pow: float = LIGHTGAUSSIAN_V_POW) -> Tensor:
    """[N] float32 LightGaussian global significance (higher = more important).

    ``score_i = (sum_views opacity_i x pixels_hit_i(view)) x (V_i / V_ref)^v_pow``, the
    ``important_score`` of LightGaussian's ``count_render`` (opacity accumulated once per pixel
    hit) times :func:`volume_factor`. Pixels hit are estimated from the projected footprint
    (:func:`pixels_hit`), not counted by a rasteriser pass.
    """
    imp = torch.zeros(len(gaussians), dtype=torch.float32, device=gaussians.means.device)
    op = gaussians.opacities.float()
    for cam in train_cameras:
        imp += op * pixels_hit(gaussians, cam)
    return imp * volume_factor(gaussians, v_pow).to(imp.device)


def random_scores(n: int, seed: int = 0, device="cpu") -> Tensor:
    """[N] float32 seeded uniform scores: a random global ranking (the random baseline)."""
    g = torch.Generator().manual_seed(int(seed))
    return torch.rand(n, generator=g).to(device)


# --- merging decimator (splat-transform) -------------------------------------------------------
#: ``merge_decimate`` modes and the splat-transform flag each one runs.
MERGE_MODES = {"decimate": "--decimate", "adaptive": "--decimate-adaptive"}


def merge_decimate(gaussians: Gaussians, count: int, *, mode: Literal["decimate", "adaptive"] = "decimate",
                   tool: Optional[str] = None, timeout: float = 600.0) -> Gaussians:
    """The model simplified to ``count`` Gaussians by the merging decimator viewers ship:
    PlayCanvas splat-transform 3.x (NanoGS progressive pairwise merging with mass-preserving
    moment matching), run on the CPU (``-g cpu``: without it the tool asks WebGPU for a device
    and fails on a machine without one). No training.

    ``mode="decimate"`` runs ``--decimate COUNT`` (``-d``: the same merge rate everywhere);
    ``mode="adaptive"`` runs ``--decimate-adaptive COUNT`` (removal allocated by local error).
    (In splat-transform 3.x ``-F`` is ``--filter-floaters``, not a decimator.) The model is
    written without ``sigma_d``, level gains and LoD settings (the plain 3DGS model); the tool
    returns exactly the count asked for (splat-transform 3.7.0; checked, not assumed).

    Args:
        gaussians: the model, N Gaussians (``sigma_d`` and gains are not written).
        count: target number of Gaussians, clamped to [1, N].
        mode: ``"decimate"`` or ``"adaptive"``.
        tool: the splat-transform executable (default
            :func:`clod_adapter.io.splat_transform.find_splat_transform`).
        timeout: seconds before the run is abandoned.

    Returns:
        the decimated model, ``count`` Gaussians (CPU float32 tensors, SH degree of the input,
        no ``sigma_d``).

    Raises:
        ValueError: ``mode`` is not one of :data:`MERGE_MODES`.
        RuntimeError: splat-transform is not found (the message names ``npm ci``), cannot be
            started, times out, exits non-zero (the message holds its error line), writes no
            file, or returns another number of Gaussians than asked; one line saying which.
    """
    import tempfile
    from pathlib import Path

    from ..io.load import load_model
    from ..io.ply import write_ply

    if mode not in MERGE_MODES:
        raise ValueError(f"merge_decimate: mode must be one of {', '.join(MERGE_MODES)}, got {mode!r}")
    count = max(1, min(int(count), len(gaussians)))
    with tempfile.TemporaryDirectory(prefix="clod-merge-") as tmp:
        src, dst = Path(tmp) / "in.ply", Path(tmp) / "out.ply"
        write_ply(src, gaussians.with_sigma_d(None).to("cpu"))
        run_splat_transform(["-w", str(src), MERGE_MODES[mode], str(count), str(dst)], tool=tool, timeout=timeout,
                            what=f"{MERGE_MODES[mode]} {count}")
        if not dst.is_file():
            raise PeerError("splat-transform exited 0 but wrote no file")
        try:
            out = load_model(dst)
        except (OSError, ValueError) as e:
            raise PeerError(f"splat-transform wrote an unreadable model: {e}") from None
    if len(out) != count:
        raise PeerError(f"splat-transform {MERGE_MODES[mode]} {count} returned {len(out)} Gaussians")
    return out
