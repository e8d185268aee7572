"""Viewer cameras: viser's camera pose <-> our pinhole camera, and where a viewer starts.

viser reports each browser camera as ``T_world_camera`` (``wxyz`` quaternion, ``position``) in
the OpenCV convention (x right, y down, z forward), a vertical field of view ``fov`` (radians)
and the canvas size in pixels; its renderer centres the principal point. Our cameras
(:class:`clod_adapter.io.scene.Camera`) hold the inverse, ``viewmat`` = world-to-camera, and
``K`` in pixels, in the same axes, so the conversion is an inverse and ``fy = (H / 2) /
tan(fov / 2)``, ``fx = fy``, ``(cx, cy) = (W / 2, H / 2)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from clod_adapter.gaussians import Gaussians
from clod_adapter.io.camera_pose import camera_to_world, matrix_to_quat, quat_to_matrix
from clod_adapter.io.scene import Camera

__all__ = ["ViewPose", "camera_from_pose", "pose_from_camera", "default_start_view",
           "scene_start_view", "robust_bounds"]

#: vertical field of view of the start view without a scene (radians)
DEFAULT_FOV = math.radians(50.0)


@dataclass
class ViewPose:
    """A viser camera pose: ``wxyz`` [4] and ``position`` [3] of ``T_world_camera`` (OpenCV
    axes), ``fov`` vertical field of view (radians), the orbit centre ``look_at`` [3] and the
    ``up`` direction [3] (world units / unit vectors, float64 numpy)."""

    wxyz: np.ndarray
    position: np.ndarray
    fov: float
    look_at: np.ndarray
    up: np.ndarray


def camera_from_pose(wxyz: Sequence[float], position: Sequence[float], fov: float, width: int,
                     height: int) -> Camera:
    """Our camera for a viser pose.

    Args:
        wxyz: [4] rotation of ``T_world_camera`` (OpenCV axes; need not be normalised).
        position: [3] camera centre, world units.
        fov: vertical field of view, radians, in (0, pi).
        width, height: image size, pixels (>= 1).

    Returns:
        :class:`clod_adapter.io.scene.Camera` (no image) with ``viewmat = T_world_camera^-1`` and a centred ``K``.

    Raises:
        ValueError: ``fov`` outside (0, pi) or a size < 1.
    """
    if not 0.0 < fov < math.pi:
        raise ValueError(f"fov must be in (0, pi) radians, got {fov}")
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"image size must be >= 1 pixel, got {width}x{height}")
    R = quat_to_matrix(wxyz)
    t = np.asarray(position, dtype=np.float64)
    vm = np.eye(4)
    vm[:3, :3] = R.T
    vm[:3, 3] = -R.T @ t
    f = 0.5 * int(height) / math.tan(0.5 * fov)
    K = np.array([[f, 0.0, 0.5 * int(width)], [0.0, f, 0.5 * int(height)], [0.0, 0.0, 1.0]])
    return Camera.pinhole(torch.from_numpy(vm).float(), torch.from_numpy(K).float(), width, height, name="viewer")


def pose_from_camera(camera, look_at: Optional[Sequence[float]] = None) -> ViewPose:
    """The viser pose of one of our cameras (``viewmat``, ``K``, ``width``, ``height``).

    viser has no principal-point offset and one focal length: the pose keeps the vertical field
    of view ``2 atan(H / (2 fy))``. ``look_at`` defaults to one unit ahead of the camera.
    """
    R_wc, pos, fov = camera_to_world(camera)
    fwd = R_wc[:, 2]
    la = pos + fwd if look_at is None else np.asarray(look_at, dtype=np.float64)
    return ViewPose(matrix_to_quat(R_wc), pos, fov, la, -R_wc[:, 1])


def robust_bounds(means: Tensor, q: float = 0.02, max_points: int = 1_000_000) -> tuple[np.ndarray, np.ndarray]:
    """([3], [3]) the ``q`` and ``1 - q`` quantiles of the centres per axis (float64 numpy): a
    bounding box that stray floaters do not inflate. At most ``max_points`` centres are used (an
    evenly spaced subsample)."""
    m = means.detach().double()
    if m.shape[0] > max_points:
        m = m[torch.linspace(0, m.shape[0] - 1, max_points).long()]
    lo = torch.quantile(m, q, dim=0).numpy()
    hi = torch.quantile(m, 1.0 - q, dim=0).numpy()
    return lo, hi


def default_start_view(gaussians: Gaussians, fov: float = DEFAULT_FOV) -> ViewPose:
    """Start view without a scene: outside the model's bounding box looking at its centre.

    The box is :func:`robust_bounds` (2 % / 98 % quantiles of the centres). The camera looks
    along +z (the COLMAP / OpenCV forward axis) with up = -y, from ``r / tan(fov / 2)`` in front
    of the box centre, ``r`` = half the box diagonal: outside the sphere around the box (so
    outside the box) with the sphere inside the vertical field of view.
    """
    lo, hi = robust_bounds(gaussians.means)
    centre = 0.5 * (lo + hi)
    r = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    dist = 1.05 * r / math.tan(0.5 * fov)
    pos = centre - np.array([0.0, 0.0, dist])
    # OpenCV camera axes in world: x right = +x, y down = +y, z forward = +z: the identity
    return ViewPose(np.array([1.0, 0.0, 0.0, 0.0]), pos, fov, centre, np.array([0.0, -1.0, 0.0]))


def scene_start_view(camera, gaussians: Gaussians) -> ViewPose:
    """Start view at a scene camera: its position, orientation and vertical field of view;
    the orbit centre on its optical axis at the depth of the model's (robust) centre, or one
    unit ahead when that centre is behind the camera."""
    lo, hi = robust_bounds(gaussians.means)
    centre = 0.5 * (lo + hi)
    p = pose_from_camera(camera)
    fwd = quat_to_matrix(p.wxyz)[:, 2]
    depth = float((centre - p.position) @ fwd)
    p.look_at = p.position + fwd * (depth if depth > 1e-6 else 1.0)
    return p
