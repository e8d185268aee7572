"""COLMAP scenes: cameras from a COLMAP model (PINHOLE / SIMPLE_PINHOLE), the LLFF train/test
split, images; and a writer (:func:`write_colmap_scene`).

Conventions are :mod:`clod_adapter.io.scene`'s (OpenCV axes, K scaled to the image size, the
official 3DGS ``eval`` split: images sorted by name, index % llffhold == 0 is a test view).

pycolmap 4.x API (verified on 4.2.1): ``Image.cam_from_world()`` is a method returning a
``Rigid3d`` whose ``.matrix()`` is the 3x4 [R | t]; a Reconstruction needs a rig and a frame per
image (``add_camera_with_trivial_rig`` / ``add_image_with_trivial_frame``). pycolmap is imported
inside the functions, so importing this module does not load it.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np
import torch
from PIL import Image

from clod_adapter.io.atomic import atomic_save
from clod_adapter.io.scene import RESOLUTIONS, Camera, PathLike, Scene, SceneError, image_size

if TYPE_CHECKING:  # pragma: no cover
    import pycolmap

__all__ = ["load_colmap_scene", "write_colmap_scene"]

_UNDISTORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
_MODEL_FILES = ("cameras", "images")


def _find_model_dir(root: Path) -> Path:
    for cand in (root / "sparse" / "0", root / "sparse"):
        if cand.is_dir() and all(
            (cand / f"{f}.bin").is_file() or (cand / f"{f}.txt").is_file() for f in _MODEL_FILES
        ):
            return cand
    raise SceneError(root, "no COLMAP model found in sparse/0 or sparse (need cameras and images .bin or .txt)")


def _intrinsics(cam: "pycolmap.Camera", model_dir: Path, image_name: str) -> tuple[float, float, float, float]:
    name = cam.model.name
    p = [float(x) for x in cam.params]
    if name == "PINHOLE":
        return p[0], p[1], p[2], p[3]
    if name == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2]
    raise SceneError(
        model_dir,
        f"camera {cam.camera_id} (image {image_name}) uses the distorted model {name}; only PINHOLE and "
        "SIMPLE_PINHOLE are supported: undistort first with pycolmap.undistort_images(output_path, "
        "input_path, image_path) or `colmap image_undistorter`",
    )


def _check_binary_model(model_dir: Path) -> None:
    """Walk the records of ``cameras.bin`` / ``images.bin`` and check they end exactly at EOF.

    pycolmap (4.2.1) reads a truncated binary model without complaint, filling the missing
    values with garbage (a camera of 1x1 pixels with zero focal length, say), so a cut-short file
    must be caught here. Layout (COLMAP ``colmap/scene/reconstruction_io_binary.cc``):
    cameras.bin: u64 n, then n x (i32 id, i32 model, u64 width, u64 height, f64 params[k]);
    images.bin: u64 n, then n x (u32 id, f64 q[4], f64 t[3], u32 camera, name NUL-terminated,
    u64 m, m x (f64 x, f64 y, u64 point3D id)).

    Raises:
        SceneError: a file ends inside a record, has bytes after the last record, or names an
            unknown camera model.
    """
    import struct

    import pycolmap

    def walk(path: Path, record) -> None:
        if not path.is_file():
            return
        size = path.stat().st_size
        with open(path, "rb") as f:
            def read(fmt: str):
                n = struct.calcsize(fmt)
                b = f.read(n)
                if len(b) != n:
                    raise SceneError(model_dir, f"cannot read COLMAP model ({path.name} is truncated: it ends inside a record)")
                return struct.unpack(fmt, b)

            (num,) = read("<Q")
            for _ in range(num):
                record(f, read)
                if f.tell() > size:
                    break
            end = f.tell()
        if end > size:
            raise SceneError(model_dir, f"cannot read COLMAP model ({path.name} is truncated: it ends inside a record)")
        if end < size:
            raise SceneError(model_dir, f"cannot read COLMAP model ({path.name} is corrupt: {size - end} bytes after the last record)")

    n_params: dict[int, int] = {}

    def camera(f, read) -> None:
        _, model_id, _, _ = read("<iiQQ")
        if model_id not in n_params:
            try:
                n_params[model_id] = len(pycolmap.Camera.create_from_model_id(0, model_id, 1.0, 1, 1).params)
            except Exception:
                raise SceneError(model_dir, f"cannot read COLMAP model (cameras.bin is corrupt: unknown "
                                            f"camera model id {model_id})") from None
        f.seek(8 * n_params[model_id], os.SEEK_CUR)

    def image(f, read) -> None:
        read("<I7dI")
        while read("<c")[0] != b"\0":
            pass
        (m,) = read("<Q")
        f.seek(24 * m, os.SEEK_CUR)

    walk(model_dir / "cameras.bin", camera)
    walk(model_dir / "images.bin", image)


def _check_image_size(path: Path, w0: int, h0: int, camera_id: int, model_dir: Path) -> None:
    """An image in ``images/`` must have its camera's size, or an exact integer multiple of it
    (then ``Scene.load_image`` downscales it by that factor, the camera's K being for the smaller
    size); anything else means the images and the model do not belong together.

    Raises:
        SceneError: naming the image and both sizes.
    """
    iw, ih = image_size(path)
    if (iw, ih) == (w0, h0):
        return
    k = iw // w0 if w0 > 0 else 0
    if k >= 2 and (iw, ih) == (k * w0, k * h0):
        return
    raise SceneError(
        path,
        f"image is {iw}x{ih} but camera {camera_id} in {model_dir} is {w0}x{h0} (neither equal nor an "
        "exact integer multiple); the images do not match the COLMAP model",
    )


def _check_scaled_size(path: Path, w: int, h: int, w0: int, h0: int, resolution: int, camera_id: int,
                       model_dir: Path) -> None:
    """An image in ``images_R/`` must be its camera's size divided by R, up to rounding (within
    1 px: floor, round or ceil, as the tools that make ``images_R`` differ); anything else would
    be stretched onto the camera silently.

    Raises:
        SceneError: naming the image, its size and the expected one.
    """
    ew, eh = w0 / resolution, h0 / resolution
    if abs(w - ew) < 1.0 + 1e-9 and abs(h - eh) < 1.0 + 1e-9:
        return
    raise SceneError(
        path,
        f"image is {w}x{h} but camera {camera_id} in {model_dir} is {w0}x{h0}, so images_{resolution}/ should "
        f"hold {ew:g}x{eh:g} (up to rounding); the image does not match its camera",
    )


def load_colmap_scene(root: PathLike, resolution: int = 1, llffhold: int = 8) -> Scene:
    """Load a COLMAP scene folder (``images/``, optional ``images_R/``, ``sparse/0``) as a ``Scene``.

    The model is read from ``root/sparse/0`` (or ``root/sparse`` when it holds the model
    directly) with ``pycolmap.Reconstruction``; only registered images are used. With
    resolution R > 1, ``root/images_R/`` is used when it exists (its real image size is read from
    each file and K is scaled by actual_w / colmap_w and actual_h / colmap_h, e.g. fern 994x745 ->
    497x372); otherwise ``root/images/`` with size (round(w / R), round(h / R)) and
    ``Scene.load_image`` resizes on load.

    Args:
        root: the scene folder.
        resolution: downsampling factor, one of 1, 2, 4, 8.
        llffhold: every ``llffhold``-th image by sorted name (indices 0, llffhold, ...) is a test
            view; 0 puts every image in ``train``.

    Returns:
        ``Scene`` with ``train`` / ``test`` cameras sorted by image name.

    Raises:
        SceneError: missing folder or model, unreadable model, a distorted camera model
            (anything but PINHOLE / SIMPLE_PINHOLE: undistort first), an image listed in the
            model but absent from disk, an image in ``images/`` whose size is neither its
            camera's nor an exact integer multiple of it, an image in ``images_R/`` that is not its
            camera's size / R up to rounding, no registered images, or a bad ``resolution`` /
            ``llffhold``.
    """
    root = Path(root)
    if not root.is_dir():
        raise SceneError(root, "scene folder does not exist")
    if resolution not in RESOLUTIONS:
        raise SceneError(root, f"resolution must be one of {RESOLUTIONS}, got {resolution!r}")
    if not isinstance(llffhold, int) or llffhold < 0:
        raise SceneError(root, f"llffhold must be an integer >= 0, got {llffhold!r}")
    import pycolmap

    model_dir = _find_model_dir(root)
    _check_binary_model(model_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises ValueError / IndexError / RuntimeError on bad files
        raise SceneError(model_dir, f"cannot read COLMAP model ({type(e).__name__}: {e})") from None

    scaled_dir = root / f"images_{resolution}"
    use_scaled = resolution > 1 and scaled_dir.is_dir()
    image_dir = scaled_dir if use_scaled else root / "images"
    if not image_dir.is_dir():
        raise SceneError(image_dir, "image folder does not exist")

    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        raise SceneError(model_dir, "the COLMAP model has no registered images")
    missing = [im.name for im in images if not (image_dir / im.name).is_file()]
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise SceneError(image_dir, f"image {missing[0]}{more} listed in {model_dir} is missing on disk")

    cams: list[Camera] = []
    for im in images:
        ccam = rec.cameras[im.camera_id]
        fx, fy, cx, cy = _intrinsics(ccam, model_dir, im.name)
        w0, h0 = int(ccam.width), int(ccam.height)
        if not (w0 > 0 and h0 > 0 and fx > 0 and fy > 0 and np.isfinite([fx, fy, cx, cy]).all()):
            raise SceneError(model_dir, f"camera {ccam.camera_id} (image {im.name}) is invalid: {w0}x{h0}, "
                                        f"fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g}")
        path = image_dir / im.name
        if use_scaled:
            w, h = image_size(path)
            _check_scaled_size(path, w, h, w0, h0, resolution, ccam.camera_id, model_dir)
        else:
            _check_image_size(path, w0, h0, ccam.camera_id, model_dir)
            w, h = int(round(w0 / resolution)), int(round(h0 / resolution))
        sx, sy = w / w0, h / h0
        K = torch.tensor([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]], dtype=torch.float64)
        viewmat = np.eye(4)
        viewmat[:3, :4] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        cams.append(
            Camera(
                name=im.name,
                image_path=path,
                viewmat=torch.from_numpy(viewmat).to(torch.float32),
                K=K.to(torch.float32),
                width=w,
                height=h,
            )
        )
    if llffhold > 0:
        test = [c for i, c in enumerate(cams) if i % llffhold == 0]
        train = [c for i, c in enumerate(cams) if i % llffhold != 0]
    else:
        test, train = [], cams
    return Scene(root=root, train=train, test=test, resolution=resolution)


def write_colmap_scene(
    root: PathLike,
    cameras: Sequence[Camera],
    images: Sequence[np.ndarray],
    points3D: Optional[np.ndarray] = None,
    colors: Optional[np.ndarray] = None,
) -> Path:
    """Write a PINHOLE COLMAP scene that ``load_colmap_scene(root, llffhold=...)`` reads back.

    Writes ``root/images/<cam.name>`` (PNG pixels; the name is used as given) and
    ``root/sparse/0/{cameras,images,points3D,rigs,frames}.bin`` via ``pycolmap.Reconstruction``
    (one trivial rig / frame per camera). Cameras with identical (width, height, K) share one
    COLMAP camera. Every file is written atomically (temp file in its folder, then os.replace).

    Args:
        root: output scene folder (created if needed).
        cameras: views; ``viewmat`` world-to-camera [4,4] (OpenCV axes), ``K`` [3,3] pixels
            (skew must be 0), ``width`` / ``height``; ``image_path`` is ignored.
        images: one uint8 [height, width, 3] array per camera.
        points3D: optional [P, 3] float world points (SfM-like initialisation); default none.
        colors: optional [P, 3] uint8 colours for ``points3D``; default grey.

    Returns:
        ``Path(root)``.

    Raises:
        ValueError: mismatched lengths, duplicate names, bad image dtype/shape, bad points.
    """
    root = Path(root)
    if len(cameras) != len(images):
        raise ValueError(f"{root}: {len(cameras)} cameras but {len(images)} images")
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"{root}: duplicate image names among the cameras")
    for c, img in zip(cameras, images):
        img = np.asarray(img)
        if img.dtype != np.uint8 or img.shape != (c.height, c.width, 3):
            raise ValueError(
                f"{root}: image for {c.name} must be uint8 ({c.height}, {c.width}, 3), got {img.dtype} {img.shape}"
            )
        if Path(c.name).suffix.lower() != ".png":
            raise ValueError(f"{root}: image name {c.name} must end in .png (pixels are written as PNG)")
    if points3D is not None:
        points3D = np.asarray(points3D, dtype=np.float64).reshape(-1, 3)
        if colors is None:
            colors = np.full((len(points3D), 3), 128, dtype=np.uint8)
        colors = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        if len(colors) != len(points3D):
            raise ValueError(f"{root}: {len(points3D)} points3D but {len(colors)} colors")

    import pycolmap

    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple, int] = {}
    for i, c in enumerate(cameras):
        K = c.K.detach().to("cpu", torch.float64).numpy()
        if abs(K[0, 1]) > 0:
            raise ValueError(f"{root}: camera {c.name} has skew K[0,1]={K[0, 1]}; PINHOLE has none")
        key = (int(c.width), int(c.height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            rec.add_camera_with_trivial_rig(
                pycolmap.Camera(
                    model="PINHOLE", width=key[0], height=key[1], params=list(key[2:]), camera_id=cam_ids[key]
                )
            )
        pose = pycolmap.Rigid3d(c.viewmat.detach().to("cpu", torch.float64).numpy()[:3, :4])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=c.name, camera_id=cam_ids[key], image_id=i + 1), pose)
    if points3D is not None:
        for xyz, rgb in zip(points3D, colors):
            rec.add_point3D(xyz, pycolmap.Track(), rgb)

    image_dir = root / "images"
    model_dir = root / "sparse" / "0"
    model_dir.mkdir(parents=True, exist_ok=True)
    for c, img in zip(cameras, images):
        out = image_dir / c.name
        out.parent.mkdir(parents=True, exist_ok=True)
        pil = Image.fromarray(np.ascontiguousarray(img))
        atomic_save(out, lambda tmp, pil=pil: pil.save(tmp, format="PNG"))

    # pycolmap writes a whole folder: write into a temp folder beside sparse/0, then move each file.
    tmp_dir = Path(tempfile.mkdtemp(dir=model_dir, prefix=".write."))
    try:
        rec.write_binary(str(tmp_dir))
        for f in sorted(tmp_dir.iterdir()):
            os.replace(f, model_dir / f.name)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)
    return root
