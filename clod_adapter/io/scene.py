"""Scenes: posed cameras (gsplat conventions), the train/test split and the images, whatever the
format (COLMAP: :mod:`clod_adapter.io.colmap`; NeRF-synthetic: :mod:`clod_adapter.io.blender`;
:func:`clod_adapter.io.load.load_scene` reads a folder in either).

Conventions:
    * ``Camera.viewmat`` is world-to-camera [4, 4] with OpenCV axes (x right, y down, z forward),
      i.e. COLMAP's ``cam_from_world`` and gsplat's ``viewmats`` (gsplat 1.5.3 ``rasterization``).
    * ``Camera.K`` is the pinhole intrinsic matrix in pixels at the camera's width/height, COLMAP's
      (fx, fy, cx, cy) scaled by width_ratio / height_ratio, as gsplat's COLMAP parser
      (examples/datasets/colmap.py) and the fern checkpoint's training (TRAINING.md) do.
    * COLMAP test split as the official 3DGS ``readColmapSceneInfo`` with ``eval``: images
      sorted by name, index % llffhold == 0 is a test view.
    * Validation views (:func:`validation_split`): settings and design choices are scored on
      training views held out of the fit, never on the test views.

``pycolmap`` is imported only for COLMAP scenes (NeRF-synthetic scenes never load it).
"""
from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from ..errors import InputError

__all__ = ["Camera", "Scene", "SceneError", "validation_split", "holdout_validation", "RESOLUTIONS", "image_size"]

PathLike = Union[str, "os.PathLike[str]"]

#: the downscale factors a scene folder may be read at (3DGS ``-r``: images_N folders).
RESOLUTIONS = (1, 2, 4, 8)


class SceneError(InputError):
    """A scene folder cannot be used; the message is one line ``"<path>: <problem>"``."""

    def __init__(self, path: PathLike, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


@dataclass
class Camera:
    """One posed pinhole view.

    Attributes:
        name: image file name as listed in the COLMAP model (e.g. ``image000.jpg``).
        image_path: the file this view's pixels are read from (None: a camera without an
            image, e.g. the viewer's, :meth:`pinhole`).
        viewmat: [4, 4] float32 world-to-camera, OpenCV axes (x right, y down, z forward);
            gsplat's ``viewmats`` entry.
        K: [3, 3] float32 intrinsics in pixels at ``width`` x ``height``.
        width, height: image size in pixels.
    """

    name: str
    image_path: Optional[Path]
    viewmat: Tensor
    K: Tensor
    width: int
    height: int

    @classmethod
    def pinhole(cls, viewmat: Tensor, K: Tensor, width: int, height: int, name: str = "view") -> "Camera":
        """A camera without an image: ``viewmat`` [4, 4] world-to-camera (OpenCV axes), ``K``
        [3, 3] intrinsics in pixels, ``width`` x ``height`` pixels (what the renderer reads)."""
        return cls(name, None, viewmat, K, int(width), int(height))

    @property
    def center(self) -> Tensor:
        """[3] float32 camera centre in world units, ``-R^T t``
        (:func:`clod_adapter.render.projection.camera_center`)."""
        from ..render.projection import camera_center

        return camera_center(self.viewmat)


@dataclass
class Scene:
    """A posed image set split into train and test views.

    Attributes:
        root: the scene folder.
        train: training cameras, sorted by name.
        test: held-out cameras (every ``llffhold``-th by sorted name), sorted by name.
        resolution: the downsampling factor the cameras were built for (1, 2, 4, 8).
        cache_size: how many decoded images ``load_image`` keeps (LRU).
        background: RGB in [0, 1] that images with an alpha channel are composited over
            (default black).
    """

    root: Path
    train: list[Camera]
    test: list[Camera]
    resolution: int = 1
    cache_size: int = 32
    background: tuple = (0.0, 0.0, 0.0)
    _cache: "OrderedDict[tuple, Tensor]" = field(default_factory=OrderedDict, init=False, repr=False, compare=False)

    @property
    def cameras(self) -> list[Camera]:
        """All cameras (train then test)."""
        return list(self.train) + list(self.test)

    def load_image(self, cam: Camera) -> Tensor:
        """The view's image as [H, W, 3] float32 in [0, 1], H = cam.height, W = cam.width.

        8-bit images are divided by 255, 16-bit (``I;16`` / ``I`` PNG) by 65535; grayscale is
        repeated to 3 channels, RGBA / LA / transparent palette images are composited over
        ``self.background`` (default black: ``rgb * alpha``), other modes converted by PIL to
        RGB. Note that Pillow decodes 48-bit RGB PNGs to 8 bits per channel. An image whose size differs from (cam.width, cam.height)
        is resized with PIL LANCZOS (in 8 bits for 8-bit RGB, as ``images_N`` folders are made;
        per channel in float otherwise). Results are cached (LRU, ``cache_size`` entries); a
        fresh copy is returned each call.

        Raises:
            SceneError: the file is missing or cannot be decoded.
        """
        key = (str(cam.image_path), int(cam.width), int(cam.height), tuple(self.background))
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit.clone()
        img = _read_image(Path(cam.image_path), int(cam.width), int(cam.height), self.background)
        if self.cache_size > 0:
            self._cache[key] = img
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return img.clone()

    def load_images(self, cams: Sequence[Camera]) -> Tensor:
        """[B, H, W, 3] float32 in [0, 1] for cameras of one size (see ``load_image``).

        Raises:
            SceneError: an image cannot be read.
            ValueError: the cameras do not all have the same width and height.
        """
        sizes = {(c.width, c.height) for c in cams}
        if len(sizes) > 1:
            raise ValueError(f"load_images needs cameras of one size, got {sorted(sizes)}; use load_image per view")
        if not cams:
            return torch.zeros((0, 0, 0, 3), dtype=torch.float32)
        return torch.stack([self.load_image(c) for c in cams])


#: :func:`validation_split` defaults: every 8th training view, starting at the 5th (offset 4,
#: half-way between the test views, which sit at index % 8 == 0 of all views).
VAL_EVERY = 8
VAL_OFFSET = 4


def validation_split(train_cameras: Sequence[Camera], every: int = VAL_EVERY,
                     offset: int = VAL_OFFSET) -> tuple[list[Camera], list[Camera]]:
    """Split the *training* cameras into (fit_cameras, val_cameras).

    What it is for: hyperparameters and design choices (a schedule, max_sv, lambda_reg, the start
    subset of a fine-tuned level, ...) are chosen by their score on the validation views, which
    the fit never sees; the test views are kept for the final report only, so a choice never
    looks at them. Pass ``scene.train`` only: no test view can then be a validation view.

    The rule: the cameras are sorted by name; the one at sorted index ``i`` is a validation view
    iff ``i >= offset`` and ``(i - offset) % every == 0`` (indices ``offset, offset + every,
    ...``). When that picks none but there are >= 2 training views (fewer than ``offset + 1``
    views), the view at index ``min(offset, n - 1)`` is the one validation view; a single training
    view is never held out. ``every >= 2``, so the fit set is never empty when ``n >= 1``.
    Deterministic (names only), disjoint, and fit + val is every training camera; both lists are
    sorted by name. E.g. 57 training views (skull), ``every=8``: 7 validation views (indices 4,
    12, ..., 52) and 50 fit views.

    Raises:
        ValueError: ``every < 2`` or ``offset < 0``.
    """
    every, offset = int(every), int(offset)
    if every < 2:
        raise ValueError(f"validation_split: every must be >= 2, got {every}")
    if offset < 0:
        raise ValueError(f"validation_split: offset must be >= 0, got {offset}")
    cams = sorted(train_cameras, key=lambda c: c.name)
    n = len(cams)
    val_idx = set(range(offset, n, every))
    if not val_idx and n >= 2:
        val_idx = {min(offset, n - 1)}
    fit = [c for i, c in enumerate(cams) if i not in val_idx]
    val = [c for i, c in enumerate(cams) if i in val_idx]
    return fit, val


def holdout_validation(scene: Scene, every: int = VAL_EVERY, offset: int = VAL_OFFSET) -> Scene:
    """A copy of ``scene`` whose ``train`` is the fit views and ``test`` the validation views of
    :func:`validation_split` (``scene.test`` left out entirely): a job run on it fits without
    the validation views and scores on them, and never sees a test view (``clod-adapt
    --holdout-val``). Same root, resolution and background; its own (empty) image cache."""
    fit, val = validation_split(scene.train, every, offset)
    return Scene(root=scene.root, train=fit, test=val, resolution=scene.resolution,
                 cache_size=scene.cache_size, background=scene.background)


def _read_image(path: Path, width: int, height: int, background: Sequence[float] = (0.0, 0.0, 0.0)) -> Tensor:
    """Decode ``path`` to [height, width, 3] float32 in [0, 1] (see ``Scene.load_image``)."""
    if not path.is_file():
        raise SceneError(path, "image file does not exist")
    try:
        with Image.open(path) as im:
            im.load()
            arr = _to_rgb_float(im, width, height, background)
    except SceneError:
        raise
    except (OSError, ValueError, SyntaxError) as e:
        raise SceneError(path, f"cannot decode image: {e}") from None
    return torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32))


def _to_rgb_float(im: Image.Image, width: int, height: int,
                  background: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    size = (width, height)
    mode = im.mode
    if mode == "P":
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
    elif mode == "PA":
        im = im.convert("RGBA")
    elif mode == "1":
        im = im.convert("L")
    elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
        im = im.convert("RGB")
    mode = im.mode

    if mode == "RGB":  # the common 8-bit case: resize like images_N were made, then scale
        if im.size != size:
            im = im.resize(size, Image.Resampling.LANCZOS)
        return np.asarray(im, dtype=np.float32) / 255.0

    if mode in ("RGBA", "LA", "La", "RGBa"):
        a = np.asarray(im, dtype=np.float32) / 255.0
        premultiplied = mode in ("La", "RGBa")
        color, alpha = a[..., :-1], a[..., -1:]
        rgb = color if premultiplied else color * alpha  # composite over black
        if rgb.shape[-1] == 1:
            rgb = np.repeat(rgb, 3, axis=-1)
        bg = np.asarray(background, dtype=np.float32).reshape(3)
        if bg.any():  # ... or over the scene's background
            rgb = rgb + bg * (1.0 - alpha)
    elif mode == "L":
        rgb = np.repeat((np.asarray(im, dtype=np.float32) / 255.0)[..., None], 3, axis=-1)
    elif mode.startswith("I;16") or mode == "I":
        v = np.asarray(im).astype(np.float32) / 65535.0
        rgb = np.repeat(v[..., None], 3, axis=-1)
    elif mode == "F":
        rgb = np.repeat(np.asarray(im, dtype=np.float32)[..., None], 3, axis=-1)
    else:
        rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0

    if (rgb.shape[1], rgb.shape[0]) != size:
        rgb = np.stack(
            [
                np.asarray(Image.fromarray(np.ascontiguousarray(rgb[..., c], dtype=np.float32)).resize(size, Image.Resampling.LANCZOS))
                for c in range(3)
            ],
            axis=-1,
        )
    return np.clip(rgb, 0.0, 1.0)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) in pixels of an image file, from its header only.

    Raises:
        SceneError: the file cannot be read as an image."""
    try:
        with Image.open(path) as im:  # lazy: reads the header only
            return im.size
    except (OSError, ValueError, SyntaxError) as e:
        raise SceneError(path, f"cannot read image header: {e}") from None
