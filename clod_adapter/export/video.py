"""Camera paths and MP4 output for ``clod-render``.

Paths (cameras in :class:`clod_adapter.io.scene.Camera` form: world-to-camera ``viewmat`` with
OpenCV axes, pixel ``K``):

* :func:`camera_path`: through the scene's cameras sorted by name, positions interpolated
  linearly and rotations by spherical linear interpolation (``scipy.spatial.transform.Slerp``);
* :func:`orbit_path`: a circle around the cameras' centroid in the plane of their mean image
  axes, radius the RMS spread of the camera centres in that plane, every frame looking at the
  focus point (the cameras' mean viewing axis at the median depth of the model's centres in
  front of them), as the spiral paths of forward-facing (LLFF-style) scenes.

:func:`write_mp4` encodes frames with ``imageio`` through the ``imageio-ffmpeg`` binary wheel
(optional extra ``[video]``).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..io.scene import Camera


def _c2w(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    vm = cam.viewmat.detach().double().cpu().numpy()
    R = vm[:3, :3].T
    return R, -R @ vm[:3, 3]


def _camera(name: str, R: np.ndarray, c: np.ndarray, like: Camera) -> Camera:
    vm = np.eye(4)
    vm[:3, :3] = R.T
    vm[:3, 3] = -R.T @ c
    return Camera(name=name, image_path=Path(name), viewmat=torch.from_numpy(vm).float(), K=like.K.clone(),
                  width=like.width, height=like.height)


def camera_path(cameras: Sequence[Camera], frames: int) -> list[Camera]:
    """``frames`` cameras through ``cameras`` (sorted by name), evenly spaced in path parameter;
    intrinsics and size of the first camera. One camera: it, repeated."""
    from scipy.spatial.transform import Rotation, Slerp

    cams = sorted(cameras, key=lambda c: c.name)
    if len(cams) == 1:
        return [cams[0]] * frames
    Rs, cs = zip(*(_c2w(c) for c in cams))
    key_t = np.arange(len(cams), dtype=float)
    slerp = Slerp(key_t, Rotation.from_matrix(np.stack(Rs)))
    ts = np.linspace(0.0, len(cams) - 1.0, frames)
    rots = slerp(ts).as_matrix()
    cs = np.stack(cs)
    out = []
    for i, t in enumerate(ts):
        j = min(int(math.floor(t)), len(cams) - 2)
        a = t - j
        out.append(_camera(f"path{i:04d}", rots[i], (1 - a) * cs[j] + a * cs[j + 1], cams[0]))
    return out


def orbit_path(cameras: Sequence[Camera], means: torch.Tensor, frames: int, radius_scale: float = 1.0) -> list[Camera]:
    """``frames`` cameras on a circle around the cameras' centroid (module docstring).

    Args:
        cameras: the scene's cameras (their mean orientation, centroid and spread).
        means: [N, 3] model centres (the focus depth).
        frames: number of cameras.
        radius_scale: factor on the circle's radius.
    """
    from scipy.spatial.transform import Rotation

    Rs, cs = zip(*(_c2w(c) for c in cameras))
    Rm = Rotation.from_matrix(np.stack(Rs)).mean().as_matrix()
    cs = np.stack(cs)
    c0 = cs.mean(0)
    right, down, fwd = Rm[:, 0], Rm[:, 1], Rm[:, 2]
    off = cs - c0
    r = float(np.sqrt(np.mean((off @ right) ** 2 + (off @ down) ** 2))) * radius_scale
    m = means.detach().double().cpu().numpy()
    z = (m - c0) @ fwd
    depth = float(np.median(z[z > 0])) if (z > 0).any() else 1.0
    if r <= 0:
        r = 0.05 * depth
    target = c0 + depth * fwd
    out = []
    for i in range(frames):
        t = 2 * math.pi * i / frames
        c = c0 + r * (math.cos(t) * right + math.sin(t) * down)
        zz = target - c
        zz /= np.linalg.norm(zz)
        xx = np.cross(down, zz)
        xx /= np.linalg.norm(xx)
        yy = np.cross(zz, xx)
        out.append(_camera(f"orbit{i:04d}", np.stack([xx, yy, zz], axis=1), c, cameras[0]))
    return out


def video_available() -> str | None:
    """None when MP4s can be written, else why not (the pip command that fixes it)."""
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg  # noqa: F401
    except ImportError as e:
        return f"needs imageio and imageio-ffmpeg ({e.name} is missing): pip install -e \".[video]\""
    return None


def write_mp4(path: Path, frames: Sequence[np.ndarray], fps: int = 30) -> Path:
    """Encode uint8 [H, W, 3] frames as H.264 MP4 (yuv420p, so any player opens it); odd sizes
    are cropped by one pixel (H.264 4:2:0 needs even sizes). Written to a temporary file beside
    ``path``, then renamed."""
    import os
    import tempfile

    import imageio.v2 as iio

    h, w = frames[0].shape[:2]
    h2, w2 = h - h % 2, w - w % 2
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".mp4")
    os.close(fd)
    try:
        with iio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=8,
                            pixelformat="yuv420p", macro_block_size=1) as wr:
            for f in frames:
                wr.append_data(np.ascontiguousarray(f[:h2, :w2]))
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path
