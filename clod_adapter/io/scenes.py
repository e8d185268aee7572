"""One entry point for every scene format: NeRF-synthetic (Blender) or COLMAP."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

from clod_adapter.io.blender import is_blender_scene, load_blender_scene
from clod_adapter.io.scene import PathLike, Scene, SceneError, load_colmap_scene

__all__ = ["load_scene", "scene_format"]


def scene_format(root: PathLike) -> str:
    """``"blender"`` when ``root/transforms_train.json`` exists, else ``"colmap"``."""
    return "blender" if is_blender_scene(root) else "colmap"


def load_scene(root: PathLike, resolution: int = 1, background: Sequence[float] = (0.0, 0.0, 0.0),
               llffhold: int = 8) -> Scene:
    """Load a scene folder, NeRF-synthetic or COLMAP.

    ``transforms_train.json`` present: :func:`clod_adapter.io.blender.load_blender_scene` (RGBA
    images composited over ``background``; ``llffhold`` unused). Otherwise
    :func:`clod_adapter.io.scene.load_colmap_scene` (``llffhold`` split; ``background`` is
    recorded on the Scene and applies to images with an alpha channel). pycolmap is imported only
    for COLMAP scenes.

    Raises:
        SceneError: as the loader chosen.
    """
    if scene_format(root) == "blender":
        return load_blender_scene(root, resolution=resolution, background=background)
    scene = load_colmap_scene(root, resolution=resolution, llffhold=llffhold)
    try:
        scene.background = tuple(float(x) for x in background)
    except (TypeError, ValueError):
        raise SceneError(Path(root), f"background must be 3 numbers in [0, 1], got {background!r}") from None
    return scene
