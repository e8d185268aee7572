"""A pinhole camera's pose in the world: the camera-to-world rotation and its quaternion, the
centre and the vertical field of view.

Our cameras (:class:`clod_adapter.io.scene.Camera`) hold ``viewmat`` = world-to-camera [4, 4]
with OpenCV axes (x right, y down, z forward) and ``K`` in pixels; the pose is its inverse.
Quaternions are ``wxyz`` (scalar first).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["quat_to_matrix", "matrix_to_quat", "camera_to_world"]


def quat_to_matrix(wxyz: Sequence[float]) -> np.ndarray:
    """[3, 3] float64 rotation of a ``wxyz`` quaternion [4] (normalised; need not be unit), by
    ``scipy.spatial.transform.Rotation``."""
    return Rotation.from_quat(np.asarray(wxyz, dtype=np.float64), scalar_first=True).as_matrix()


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """[4] float64 unit ``wxyz`` quaternion (w >= 0) of a [3, 3] rotation matrix, by
    ``scipy.spatial.transform.Rotation``."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat(canonical=True, scalar_first=True)


def camera_to_world(camera) -> tuple[np.ndarray, np.ndarray, float]:
    """The pose of one of our cameras (``viewmat``, ``K``, ``height``).

    Returns:
        ``(R_wc, position, fov)``: the camera-to-world rotation [3, 3] (its columns the camera's
        x right, y down, z forward axes in the world), the camera centre [3] (world units), both
        float64 numpy, and the vertical field of view ``2 atan(H / (2 fy))`` (radians).
    """
    vm = camera.viewmat.detach().double().cpu().numpy()
    R_wc = vm[:3, :3].T
    pos = -R_wc @ vm[:3, 3]
    fov = 2.0 * math.atan(0.5 * int(camera.height) / float(camera.K[1, 1]))
    return R_wc, pos, fov
