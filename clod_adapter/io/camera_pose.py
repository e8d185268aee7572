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

__all__ = ["quat_to_matrix", "matrix_to_quat", "camera_to_world"]


def quat_to_matrix(wxyz: Sequence[float]) -> np.ndarray:
    """[3, 3] float64 rotation of a ``wxyz`` quaternion [4] (normalised here; need not be unit)."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / max(float(np.linalg.norm(wxyz)), 1e-300)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """[4] float64 unit ``wxyz`` quaternion (w >= 0) of a [3, 3] rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


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
