"""What the web engines need from us: the vendored PlayCanvas engine (npm ``playcanvas``, pinned
to :data:`PLAYCANVAS_VERSION` by the root ``package.json``, installed by ``npm ci``; copied
into an export at build time, never fetched from a CDN) and our cameras in its axes.

Conventions (PlayCanvas 2.x): a camera looks down its -Z axis with +Y up (OpenGL); ours
(gsplat ``viewmats``, COLMAP) look down +Z with +Y down (OpenCV). The same world frame is kept
(the splat entity is not rotated), so a camera-to-world rotation ``R_cv`` becomes
``R_cv diag(1, -1, -1)``. PlayCanvas's ``fov`` is vertical, in degrees, for a centred
principal point (ours may be off-centre by a fraction of a pixel to a few pixels: not modelled).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

__all__ = ["PLAYCANVAS_VERSION", "find_playcanvas", "playcanvas_pose"]

#: the pinned engine (root ``package.json``).
PLAYCANVAS_VERSION = "2.23.3"
#: the engine build copied into exports (ES module, minified).
ENGINE_FILE = "playcanvas.min.mjs"


def find_playcanvas() -> Optional[Path]:
    """``node_modules/playcanvas/build/playcanvas.min.mjs`` under the project root or the current
    directory (where ``npm ci`` installs it), or None."""
    from ..splat_transform import project_root

    for folder in (project_root(), Path.cwd()):
        if folder is not None:
            p = folder / "node_modules" / "playcanvas" / "build" / ENGINE_FILE
            if p.is_file():
                return p
    return None


def playcanvas_pose(camera) -> dict:
    """One of our cameras (``viewmat``, ``K``, ``width``, ``height``) in PlayCanvas's terms: its
    OpenCV pose (:func:`clod_adapter.viewer.cameras.pose_from_camera`, ``q_cv`` wxyz) turned
    half a turn about its own x axis, ``q_cv (0, 1, 0, 0)``.

    Returns:
        ``{"position": [x, y, z] (world units), "rotation": [x, y, z, w] (unit quaternion,
        PlayCanvas ``Quat`` order), "fov": vertical field of view in degrees}``.
    """
    from .cameras import pose_from_camera

    p = pose_from_camera(camera)
    w, x, y, z = (float(v) for v in p.wxyz)
    return {"position": [float(v) for v in p.position], "rotation": [w, z, -y, -x],
            "fov": math.degrees(p.fov)}
