"""NeRF-synthetic (Blender) scenes: ``transforms_train.json`` / ``transforms_test.json`` + RGBA PNGs.

Conventions (as the official 3DGS ``readNerfSyntheticInfo``):
    * ``frames[i].transform_matrix`` is camera-to-world with Blender/OpenGL camera axes (x right,
      y up, z backward); flipping the y and z camera axes gives OpenCV axes, and its inverse is
      ``Camera.viewmat`` (world-to-camera, gsplat's ``viewmats``).
    * ``fx = fy = 0.5 W / tan(0.5 camera_angle_x)``, principal point at the image centre.
    * ``frames[i].file_path`` is given without extension; the image is ``root / file_path + ".png"``.
    * RGBA images are composited over the chosen background (``Scene.background``) on load.
    * train views from ``transforms_train.json``, test views from ``transforms_test.json``
      (``transforms_val.json`` is ignored), in file order.

No pycolmap import here.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from clod_adapter.io.scene import RESOLUTIONS, Camera, PathLike, Scene, SceneError, image_size

__all__ = ["load_blender_scene", "is_blender_scene"]

#: OpenGL (Blender) camera axes -> OpenCV camera axes: flip y and z.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def is_blender_scene(root: PathLike) -> bool:
    """True when ``root`` holds a ``transforms_train.json`` (a NeRF-synthetic scene)."""
    return (Path(root) / "transforms_train.json").is_file()


def _check_background(root: Path, background: Sequence[float]) -> tuple:
    try:
        bg = tuple(float(x) for x in background)
    except (TypeError, ValueError):
        raise SceneError(root, f"background must be 3 numbers in [0, 1], got {background!r}") from None
    if len(bg) != 3 or not all(0.0 <= x <= 1.0 for x in bg):
        raise SceneError(root, f"background must be 3 numbers in [0, 1], got {background!r}")
    return bg


def _image_path(root: Path, file_path: str) -> Path:
    p = root / file_path
    if p.suffix.lower() == ".png" and p.is_file():
        return p
    return p.with_name(p.name + ".png")


def _read_split(root: Path, name: str, resolution: int) -> list[Camera]:
    path = root / name
    try:
        meta = json.loads(path.read_text())
    except OSError as e:
        raise SceneError(path, f"cannot read: {e.strerror or e}") from None
    except ValueError as e:
        raise SceneError(path, f"not valid JSON: {e}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise SceneError(path, "expected an object with a 'frames' list")
    try:
        fovx = float(meta["camera_angle_x"])
    except (KeyError, TypeError, ValueError):
        raise SceneError(path, "missing or invalid 'camera_angle_x'") from None
    if not 0.0 < fovx < math.pi:
        raise SceneError(path, f"camera_angle_x must be in (0, pi), got {fovx}")
    cams: list[Camera] = []
    for i, fr in enumerate(meta["frames"]):
        try:
            fp = str(fr["file_path"])
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise SceneError(path, f"frame {i}: missing or invalid 'file_path' / 'transform_matrix'") from None
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise SceneError(path, f"frame {i}: transform_matrix must be a finite 4x4 matrix")
        img = _image_path(root, fp)
        if not img.is_file():
            raise SceneError(img, f"image of frame {i} in {name} does not exist")
        W, H = image_size(img)
        w, h = int(round(W / resolution)), int(round(H / resolution))
        f0 = 0.5 * W / math.tan(0.5 * fovx)  # fx = fy at the file's size, scaled to (w, h)
        K = torch.tensor([[f0 * w / W, 0.0, w / 2.0], [0.0, f0 * h / H, h / 2.0], [0.0, 0.0, 1.0]],
                         dtype=torch.float64)
        try:
            viewmat = np.linalg.inv(c2w @ _GL_TO_CV)
        except np.linalg.LinAlgError:
            raise SceneError(path, f"frame {i}: transform_matrix is singular") from None
        cams.append(Camera(name=img.relative_to(root).as_posix(), image_path=img,
                           viewmat=torch.from_numpy(viewmat).to(torch.float32),
                           K=K.to(torch.float32), width=w, height=h))
    return cams


def load_blender_scene(root: PathLike, resolution: int = 1,
                       background: Sequence[float] = (0.0, 0.0, 0.0)) -> Scene:
    """Load a NeRF-synthetic scene folder as a :class:`~clod_adapter.io.scene.Scene`.

    Args:
        root: folder with ``transforms_train.json`` (required), ``transforms_test.json``
            (optional; no test views without it) and the PNGs they name.
        resolution: downsampling factor (1, 2, 4, 8); images are resized on load.
        background: RGB in [0, 1] the RGBA images are composited over, usually black (0, 0, 0)
            or white (1, 1, 1) (3DGS ``--white_background``).

    Returns:
        ``Scene`` with ``background`` set (``Scene.load_image`` composites over it).

    Raises:
        SceneError: missing folder or ``transforms_train.json``, unreadable / malformed JSON, a
            missing image, a bad ``resolution`` or ``background``.
    """
    root = Path(root)
    if not root.is_dir():
        raise SceneError(root, "scene folder does not exist")
    if resolution not in RESOLUTIONS:
        raise SceneError(root, f"resolution must be one of {RESOLUTIONS}, got {resolution!r}")
    bg = _check_background(root, background)
    if not is_blender_scene(root):
        raise SceneError(root, "no transforms_train.json (not a NeRF-synthetic scene)")
    train = _read_split(root, "transforms_train.json", resolution)
    test = _read_split(root, "transforms_test.json", resolution) if (root / "transforms_test.json").is_file() else []
    return Scene(root=root, train=train, test=test, resolution=resolution, background=bg)
