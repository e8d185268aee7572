"""EWA projection of 3D Gaussians (pinhole), matching gsplat 1.5.3's
``fully_fused_projection`` (``ProjectionEWA3DGSFused.cu``, classic mode, no compensation).

Per Gaussian (gsplat order of operations):
  1. camera-space mean ``t = R m + T``; cull if ``t.z < near_plane or t.z > far_plane``;
  2. cull if ``opacity < 1/255`` (only when ``opacities`` is given);
  3. ``cov2d = J R Sigma R^T J^T`` with the Jacobian evaluated at x/z, y/z clamped to
     ``[-(cx/fx + 0.3 tan_fovx), (W - cx)/fx + 0.3 tan_fovx]`` (same for y), tan_fovx = 0.5 W / fx;
     ``means2d = (fx x/z + cx, fy y/z + cy)`` from the unclamped mean;
  4. ``cov2d += eps2d I``; cull if ``det <= 0``; ``conics = inverse(cov2d)`` upper triangle;
  5. ``extend = 3.33``, or ``min(3.33, sqrt(2 log(opacity * 255)))`` with opacities
     (gsplat 1.5.3 uses 3.33, not 3); ``radius_{x,y} = ceil(extend sqrt(cov2d_{xx,yy}))``;
  6. cull if both radii ``<= radius_clip``, or the box ``mean2d +- radius`` misses the image.

Everything is plain torch (autograd). The heavy math runs only on the Gaussians that survive
the cheap depth/opacity tests. A frame without gradients (nothing recording autograd, CPU,
float32/64, the C++ kernels built) runs :func:`project_geometry` and :func:`finish_projection` as
one C++ pass each (``csrc/projection.cpp``, arithmetic in double), these functions being its twin
(``tests/test_rasterization.py``); ``python -m benchmarks.studies.cpu_frame`` times both.
"""
from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from ._torch_impl import ALPHA_THRESHOLD  # gsplat 1.5.3's 1/255, one definition for both stages
from .native import no_grad_cpu as _kernel  # whether a stage runs csrc/projection.cpp

__all__ = ["fully_fused_projection", "project_visible", "project_geometry", "finish_projection",
           "ProjectedGeometry", "VisibleProjection", "ALPHA_THRESHOLD", "EPS2D", "NEAR_PLANE", "FAR_PLANE",
           "quat_to_rotmat_rows"]

#: gsplat 1.5.3's default ``eps2d`` (pixels squared, added to every 2D covariance's diagonal: step 4):
#: what every level-of-detail render and cost projects with
EPS2D = 0.3
#: gsplat 1.5.3's near and far planes (world units of camera depth), used by every LoD render
NEAR_PLANE, FAR_PLANE = 0.01, 1e10
GAUSSIAN_EXTEND = 3.33
#: cap of the int32 radii (pixels); larger footprints cover any image anyway
MAX_RADIUS = float(2 ** 30)


class VisibleProjection(NamedTuple):
    """Projection restricted to the Gaussians with radii > 0 (``ids`` into the inputs; ``rows``:
    their positions in the :class:`ProjectedGeometry` it was finished from, or None)."""

    ids: Tensor  # [V] int64
    radii: Tensor  # [V, 2] int32
    means2d: Tensor  # [V, 2]
    depths: Tensor  # [V]
    conics: Tensor  # [V, 3]
    rows: Optional[Tensor] = None  # [V] int64


def camera_center(viewmat: Tensor) -> Tensor:
    """[3] camera centre in world units from a [4, 4] world-to-camera matrix (OpenCV axes, gsplat
    ``viewmats``): ``c = -R^T t``, in ``viewmat``'s dtype and device."""
    R = viewmat[:3, :3]
    t = viewmat[:3, 3]
    return -(R.T @ t)


def quat_to_rotmat_rows(quats: Tensor) -> Tuple[Tensor, ...]:
    """Nine [n] entries (row-major) of the rotation of the normalised wxyz quaternions."""
    q = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return (
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    )


def _check(means: Tensor, quats: Tensor, scales: Tensor, opacities: Optional[Tensor],
           viewmat: Tensor, K: Tensor) -> None:
    n = means.shape[0]
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    if tuple(quats.shape) != (n, 4):
        raise ValueError(f"quats must be [{n}, 4], got {tuple(quats.shape)}")
    if tuple(scales.shape) != (n, 3):
        raise ValueError(f"scales must be [{n}, 3], got {tuple(scales.shape)}")
    if opacities is not None and tuple(opacities.shape) != (n,):
        raise ValueError(f"opacities must be [{n}], got {tuple(opacities.shape)}")
    if tuple(viewmat.shape) != (4, 4):
        raise ValueError(f"viewmat must be [4, 4], got {tuple(viewmat.shape)}")
    if tuple(K.shape) != (3, 3):
        raise ValueError(f"K must be [3, 3], got {tuple(K.shape)}")


class ProjectedGeometry(NamedTuple):
    """Stage 1 of the projection (:func:`project_geometry`): the Gaussians in front of the camera
    (``ids`` into the inputs) with their 2D means, depths and the raw 2D covariance terms
    ``cov2d = [[aa, ab], [ab, bb]]`` *before* the ``eps2d`` blur, plus ``axb2 = |A x B|^2``
    (for the cancellation-free determinant). All [M] tensors (autograd)."""

    ids: Tensor  # [M] int64
    means2d: Tensor  # [M, 2]
    depths: Tensor  # [M]
    aa: Tensor
    ab: Tensor
    bb: Tensor
    axb2: Tensor

    def subset(self, idx: Tensor) -> "ProjectedGeometry":
        """The rows ``idx`` [k] (int64 positions into this geometry)."""
        return ProjectedGeometry(*(t.index_select(0, idx) for t in self))


def project_geometry(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    keep: Optional[Tensor] = None,
) -> ProjectedGeometry:
    """Stage 1 of :func:`project_visible`: depth culling and the EWA terms (steps 1 and 3 of
    the module docstring) for the Gaussians with ``near_plane <= z <= far_plane`` (and in
    ``keep``, when given: [N] bool, or [k] int64 indices, ascending). ``means`` [N, 3],
    ``quats`` [N, 4] wxyz, ``scales`` [N, 3] activated, ``viewmat`` [4, 4], ``K`` [3, 3]."""
    _check(means, quats, scales, None, viewmat, K)
    if _kernel(means, quats, scales) and not (torch.is_grad_enabled() and (viewmat.requires_grad or K.requires_grad)):
        from .native import load

        vm, Kd = viewmat.detach().to(means.dtype).double(), K.detach().to(means.dtype).double()
        rows = torch.zeros((), dtype=torch.int64) if keep is None else (
            keep if keep.dtype == torch.long else keep.nonzero().squeeze(1)).contiguous()
        out = load().project_geometry(means.contiguous(), quats.contiguous(), scales.contiguous(), rows,
                                      vm[:3, :3].reshape(-1).tolist(), vm[:3, 3].tolist(), float(Kd[0, 0]),
                                      float(Kd[0, 2]), float(Kd[1, 1]), float(Kd[1, 2]), int(width), int(height),
                                      float(near_plane), float(far_plane))
        return ProjectedGeometry(*out)
    dt = means.dtype
    viewmat = viewmat.to(dt)
    K = K.to(dt)
    R = viewmat[:3, :3]
    T = viewmat[:3, 3]

    # --- cheap culling on depth (and ``keep``) without autograd -----------------------------
    with torch.no_grad():
        if keep is not None:  # depth of the kept rows only (an LoD level keeps few of N)
            ids = keep if keep.dtype == torch.long else keep.nonzero().squeeze(1)
            z = means.detach().index_select(0, ids) @ R[2].detach() + T[2].detach()
            ids = ids[(z >= near_plane) & (z <= far_plane)]
        else:
            z_all = means.detach() @ R[2].detach() + T[2].detach()
            ids = ((z_all >= near_plane) & (z_all <= far_plane)).nonzero().squeeze(1)

    m = means.index_select(0, ids)
    q = quats.index_select(0, ids)
    s = scales.index_select(0, ids)

    # camera-space mean
    mc = m @ R.T + T
    tx, ty, tz = mc.unbind(-1)

    # intrinsics as python floats when possible (fast scalar broadcast); keep tensors when
    # K requires grad (never in practice)
    if K.requires_grad:
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    else:
        fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))

    rz = 1.0 / tz
    means2d = torch.stack([fx * tx * rz + cx, fy * ty * rz + cy], dim=-1)

    # Jacobian with gsplat's FOV clamping (x/z, y/z clamped to 1.3x the FOV limits)
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    if isinstance(fx, float):
        u = torch.clamp(tx * rz, min=-lim_x_neg, max=lim_x_pos)  # = clamped tx / tz
        v = torch.clamp(ty * rz, min=-lim_y_neg, max=lim_y_pos)
    else:
        u = torch.minimum(torch.maximum(tx * rz, -lim_x_neg), lim_x_pos)
        v = torch.minimum(torch.maximum(ty * rz, -lim_y_neg), lim_y_pos)
    # J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]] ; JR = J @ R_view  ([n,3] per row)
    a0 = fx * rz
    a2 = -fx * u * rz
    b1 = fy * rz
    b2 = -fy * v * rz
    JR0 = a0[:, None] * R[0] + a2[:, None] * R[2]  # [n, 3]
    JR1 = b1[:, None] * R[1] + b2[:, None] * R[2]  # [n, 3]

    # (J R_view R_q) S  -> rows A, B; cov2d = [A.A, A.B; A.B, B.B]
    r = quat_to_rotmat_rows(q)
    rq = torch.stack(r, dim=-1).view(-1, 3, 3)  # [n, 3, 3]
    JRQ = torch.bmm(torch.stack([JR0, JR1], dim=1), rq)  # [n, 2, 3]
    Ms = JRQ * s[:, None, :]
    A, B = Ms.unbind(1)
    # |A x B|^2 for det = c00 c11 - c01^2 without cancellation: for M = [A; B],
    # det(M M^T + e I) = |A x B|^2 + e (|A|^2 + |B|^2) + e^2 (Lagrange's identity). The naive
    # product loses every digit in float32 for long needle/flat Gaussians (scale ratio 1e6) and
    # culls them or yields a non-positive-definite conic.
    AxB = torch.linalg.cross(A, B, dim=-1)
    return ProjectedGeometry(ids, means2d, tz, (A * A).sum(-1), (A * B).sum(-1), (B * B).sum(-1),
                             (AxB * AxB).sum(-1))


def finish_projection(
    geom: ProjectedGeometry,
    opacities: Optional[Tensor],
    width: int,
    height: int,
    eps2d: float = 0.3,
    radius_clip: float = 0.0,
    cov_scale: Optional[Tensor] = None,
) -> VisibleProjection:
    """Stage 2 of :func:`project_visible` (steps 2, 4-6 of the module docstring): the ``eps2d``
    blur, conics, radii and culling of the rows of ``geom``.

    Args:
        geom: stage 1 (:func:`project_geometry`).
        opacities: [M] opacities of those rows (opacity cull and opacity-aware extent), or None
            (extent 3.33, no opacity cull: the footprint test of "in view").
        cov_scale: [M] factor on each 3D covariance (``exp(2 l g)`` of an isotropic level gain
            ``g`` on the log-scales), applied to the raw 2D terms exactly as re-projecting with
            scaled ``scales`` would (up to rounding); None = 1.

    Returns:
        :class:`VisibleProjection` with ``ids`` into the original inputs and ``rows`` [V] int64,
        the kept rows' positions in ``geom`` (ascending).
    """
    aa, ab, bb, axb2 = geom.aa, geom.ab, geom.bb, geom.axb2
    if _kernel(geom.means2d, aa, ab, bb, axb2, opacities, cov_scale):
        from .native import load

        none = aa.new_zeros(0)
        rows, radii, conics = load().finish_projection(
            geom.means2d.contiguous(), aa.contiguous(), ab.contiguous(), bb.contiguous(), axb2.contiguous(),
            none if opacities is None else opacities.to(aa.dtype).contiguous(),
            none if cov_scale is None else cov_scale.to(aa.dtype).contiguous(), int(width), int(height),
            float(eps2d), float(radius_clip))
        return VisibleProjection(geom.ids.index_select(0, rows), radii, geom.means2d.index_select(0, rows),
                                 geom.depths.index_select(0, rows), conics, rows)
    if cov_scale is not None:
        aa, ab, bb, axb2 = aa * cov_scale, ab * cov_scale, bb * cov_scale, axb2 * (cov_scale * cov_scale)
    c00 = aa + eps2d
    c01 = ab
    c11 = bb + eps2d
    det = axb2 + eps2d * (aa + bb) + eps2d * eps2d
    with torch.no_grad():
        det_ok = (det > 0) & torch.isfinite(det)  # an overflowing footprint is culled
        if opacities is not None:
            op = opacities.detach()
            det_ok &= op >= ALPHA_THRESHOLD
            extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD)).clamp_max(GAUSSIAN_EXTEND)
        else:
            extend = GAUSSIAN_EXTEND
        rad_x = torch.ceil(extend * torch.sqrt(c00.detach()))
        rad_y = torch.ceil(extend * torch.sqrt(c11.detach()))
        mx, my = geom.means2d.detach().unbind(-1)
        ok = det_ok & ~((rad_x <= radius_clip) & (rad_y <= radius_clip))
        ok &= ~((mx + rad_x <= 0) | (mx - rad_x >= width) | (my + rad_y <= 0) | (my - rad_y >= height))
        sel = ok.nonzero().squeeze(1)
        # culling above uses the float radii; the stored int32 ones are capped so a huge
        # footprint (huge focal length, huge scale) cannot wrap to a negative radius
        radii = torch.stack([rad_x, rad_y], dim=-1).index_select(0, sel)
        radii = radii.clamp_max(MAX_RADIUS).to(torch.int32)

    means2d = geom.means2d.index_select(0, sel)
    depths = geom.depths.index_select(0, sel)
    c00 = c00.index_select(0, sel)
    c01 = c01.index_select(0, sel)
    c11 = c11.index_select(0, sel)
    inv_det = 1.0 / det.index_select(0, sel)
    conics = torch.stack([c11 * inv_det, -c01 * inv_det, c00 * inv_det], dim=-1)
    return VisibleProjection(geom.ids.index_select(0, sel), radii, means2d, depths, conics, sel)


def project_visible(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Optional[Tensor],
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
) -> VisibleProjection:
    """Project and keep only the Gaussians gsplat would not cull (radii > 0):
    :func:`project_geometry` (Gaussians under the 1/255 opacity cull skipped before the heavy
    math) then :func:`finish_projection`."""
    _check(means, quats, scales, opacities, viewmat, K)
    keep = None if opacities is None else opacities.detach() >= ALPHA_THRESHOLD
    geom = project_geometry(means, quats, scales, viewmat, K, width, height, near_plane, far_plane, keep)
    op = None if opacities is None else opacities.index_select(0, geom.ids)
    return finish_projection(geom, op, width, height, eps2d, radius_clip)


def fully_fused_projection(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Optional[Tensor],
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project N 3D Gaussians into one pinhole camera (gsplat 1.5.3 semantics, CPU autograd).

    Args:
        means: [N, 3] world-space centres.
        quats: [N, 4] wxyz rotations (normalised inside).
        scales: [N, 3] activated scales (standard deviations).
        opacities: [N] activated opacities for the opacity-aware extent, or None (extent 3.33).
        viewmat: [4, 4] world-to-camera.
        K: [3, 3] intrinsics.
        width, height: image size in pixels.

    Returns:
        radii [N, 2] int32 (0 = culled), means2d [N, 2], depths [N], conics [N, 3]
        (upper triangle of the inverse 2D covariance). Culled Gaussians get zeros (finite
        gradients: nothing flows into them).
    """
    n = means.shape[0]
    vis = project_visible(means, quats, scales, opacities, viewmat, K, width, height,
                          eps2d, near_plane, far_plane, radius_clip)
    dt = means.dtype
    dev = means.device
    radii = torch.zeros(n, 2, dtype=torch.int32, device=dev)
    radii[vis.ids] = vis.radii
    means2d = torch.zeros(n, 2, dtype=dt, device=dev).index_copy(0, vis.ids, vis.means2d)
    depths = torch.zeros(n, dtype=dt, device=dev).index_copy(0, vis.ids, vis.depths)
    conics = torch.zeros(n, 3, dtype=dt, device=dev).index_copy(0, vis.ids, vis.conics)
    return radii, means2d, depths, conics
