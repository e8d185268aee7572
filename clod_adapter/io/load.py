"""Load a pretrained 3DGS model from any supported checkpoint format, chosen by content.

Dispatch (:func:`load_model`):

* a .ply whose header has a ``chunk`` element and a ``packed_position`` vertex property
  (PlayCanvas / SuperSplat compressed) -> :func:`~clod_adapter.io.compressed_ply.read_compressed_ply`;
* any other .ply (content starts with ``ply``, or the name ends in ``.ply``) ->
  :func:`~clod_adapter.io.ply.read_ply`: the INRIA layout, which also covers MaskGaussian
  checkpoints (its ``save_ply_default`` writes the vanilla layout; its ``save_ply`` adds the
  ``masks_0``/``masks_1`` properties, which ``read_ply`` ignores -- see *Masks* below), the
  no-normals exporter variant and the CLoD extension with ``sigma_d``;
* a torch checkpoint (name ``*.pt`` / ``*.pth`` / ``*.ckpt`` or a zip-format torch file) ->
  :func:`~clod_adapter.io.gsplat_ckpt.read_gsplat_ckpt` (gsplat simple_trainer ``ckpt_*.pt``);
* anything else -> :class:`~clod_adapter.io.ply.PlyFormatError` naming the file.

Masks (INRIA-layout .ply only). MaskGaussian (Liu et al., CVPR 2025; kaikai23/MaskGaussian
``scene/gaussian_model.py``) learns two mask scores per Gaussian, saved as ``masks_0``,
``masks_1``; it renders with ``mask = gumbel_softmax(log_softmax([masks_0, masks_1]),
hard=True)[:, 0]`` (class 0 = "keep"), i.e. a stochastic hard mask. With ``masks="auto"`` (the
default):

* a ``masks_0``/``masks_1`` pair that is already hard one-hot (every value 0 or 1 and
  ``masks_0 + masks_1 == 1``) keeps the Gaussians with ``masks_0 == 1``;
* a single ``mask`` (or lone ``masks_0``) property with only 0/1 values keeps those equal to 1;
* soft scores (learned logits, anything else) are ignored: every Gaussian is kept and a
  ``UserWarning`` says so.

``masks="argmax"`` also applies soft scores deterministically, keeping the mode of
MaskGaussian's sampled mask (``masks_0 > masks_1``; for a single ``mask`` logit, ``mask > 0``);
``masks="ignore"`` never filters. Filtering never empties the model silently: a mask that would
keep no Gaussian raises ``PlyFormatError``.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Literal, Optional, Union

import numpy as np
import plyfile
import torch

from clod_adapter.gaussians import Gaussians
from clod_adapter.io.compressed_ply import is_compressed_ply, read_compressed_ply
from clod_adapter.io.gsplat_ckpt import read_gsplat_ckpt
from clod_adapter.io.ply import PlyFormatError, read_ply

__all__ = ["load_model", "resolve_model_path", "model_folder", "training_size", "MASK_PROPERTIES"]

PathLike = Union[str, "os.PathLike[str]"]
MaskMode = Literal["auto", "argmax", "ignore"]

MASK_PROPERTIES = ("masks_0", "masks_1", "mask")
_TORCH_SUFFIXES = {".pt", ".pth", ".ckpt"}


MODEL_SUFFIXES = (".ply", ".pt", ".pth", ".ckpt")


def _iteration_dirs(folder: Path) -> dict[int, Path]:
    out = {}
    pc = folder / "point_cloud"
    if pc.is_dir():
        for d in pc.iterdir():
            if d.is_dir() and d.name.startswith("iteration_") and (d / "point_cloud.ply").is_file():
                try:
                    out[int(d.name[len("iteration_"):])] = d / "point_cloud.ply"
                except ValueError:
                    pass
    return out


def resolve_model_path(path: PathLike, iteration: Optional[int] = None, flag: str = "",
                       prefer: Optional[str] = None) -> Path:
    """The model file a user means by ``path``, as 3DGS users pass it.

    * a file: itself;
    * an official 3DGS model folder (``-m`` layout, graphdeco-inria/gaussian-splatting
      ``scene/__init__.py``): ``point_cloud/iteration_N/point_cloud.ply``, the largest ``N``
      unless ``iteration`` is given;
    * a folder holding exactly one model file (.ply, or a gsplat .pt/.pth/.ckpt when there is no
      .ply), e.g. ``point_cloud/iteration_7000`` or a ``clod-adapt`` output folder.

    ``flag`` (e.g. ``"--pretrained"``) is named in errors. ``prefer``: a file name taken first
    when the folder holds it (``"point_cloud.ply"`` for a ``clod-adapt`` output folder, whose
    ``--layout inria`` copy under ``point_cloud/`` has no ``sigma_d``).

    Raises:
        PlyFormatError: ``path`` does not exist ("no such file or folder"), a folder that is none of the above ("is a folder, expected ..."), or no
            ``iteration_<iteration>``.
    """
    path = Path(path)
    via = f" ({flag})" if flag else ""
    if path.is_file():
        if iteration is not None:
            raise PlyFormatError(path, f"--iteration {iteration} needs a model folder, not a file{via}")
        return path
    if not path.exists():
        raise PlyFormatError(path, f"no such file or folder{via}")
    if prefer is not None and iteration is None and (path / prefer).is_file():
        return path / prefer
    its = _iteration_dirs(path)
    if its:
        if iteration is None:
            return its[max(its)]
        if iteration not in its:
            have = ", ".join(str(i) for i in sorted(its))
            raise PlyFormatError(path, f"no point_cloud/iteration_{iteration}/point_cloud.ply (iterations: {have}){via}")
        return its[iteration]
    if iteration is not None:
        raise PlyFormatError(path, f"--iteration {iteration}: no point_cloud/iteration_*/point_cloud.ply in this folder{via}")
    files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in MODEL_SUFFIXES)
    plys = [p for p in files if p.suffix.lower() == ".ply"]
    pick = plys if plys else files
    if len(pick) == 1:
        return pick[0]
    what = (f"it holds {len(pick)} model files ({', '.join(p.name for p in pick[:4])}); name one"
            if pick else "it holds no .ply")
    raise PlyFormatError(path, f"is a folder, expected a .ply file, a 3DGS model folder "
                               f"(point_cloud/iteration_N/point_cloud.ply) or a folder holding one .ply; "
                               f"{what}{via}")


def model_folder(model_path: PathLike) -> Optional[Path]:
    """The official model folder a ``.../point_cloud/iteration_N/point_cloud.ply`` lies in, or the
    folder of any other model file (where ``cameras.json`` / ``cfg_args`` may be); None if none."""
    p = Path(model_path)
    if p.parent.name.startswith("iteration_") and p.parent.parent.name == "point_cloud":
        return p.parent.parent.parent
    return p.parent


def training_size(model_path: PathLike) -> Optional[tuple[int, int]]:
    """(width, height) the checkpoint was trained at, from ``cameras.json`` of its model folder
    (the official trainer's format: one entry per camera with ``width``/``height`` at the
    training resolution), or None when unknown or not one size."""
    import json

    folder = model_folder(model_path)
    f = folder / "cameras.json" if folder is not None else None
    if f is None or not f.is_file():
        return None
    try:
        cams = json.loads(f.read_text())
        sizes = {(int(c["width"]), int(c["height"])) for c in cams}
    except (ValueError, KeyError, TypeError, OSError):
        return None
    return sizes.pop() if len(sizes) == 1 else None


def load_model(path: PathLike, *, masks: MaskMode = "auto", allow_nonfinite: bool = False,
               allow_appearance: bool = False) -> Gaussians:
    """Read a 3DGS model from ``path``, whatever its supported format (see the module docstring).

    Args:
        path: a .ply (INRIA / MaskGaussian / CLoD-extended / compressed) or a gsplat ``.pt``.
        masks: how MaskGaussian-style mask properties of an INRIA-layout .ply are treated:
            ``"auto"``, ``"argmax"`` or ``"ignore"`` (module docstring).
        allow_nonfinite: passed to ``read_ply`` / ``read_gsplat_ckpt``.
        allow_appearance: passed to ``read_gsplat_ckpt`` (gsplat ``--app_opt`` checkpoints).

    Returns:
        ``Gaussians`` (float32, CPU).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        PlyFormatError: the content is no supported format, or the reader rejects it.
        ValueError: ``masks`` is not one of the modes.
    """
    if masks not in ("auto", "argmax", "ignore"):
        raise ValueError(f"masks must be 'auto', 'argmax' or 'ignore', got {masks!r}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    with open(path, "rb") as f:
        magic = f.read(4)
    suffix = path.suffix.lower()

    if magic[:3] == b"ply" or suffix == ".ply":
        if magic[:3] == b"ply" and is_compressed_ply(path):
            return read_compressed_ply(path)
        g = read_ply(path, allow_nonfinite=allow_nonfinite)
        if masks != "ignore":
            keep = _mask_selection(path, len(g), masks)
            if keep is not None:
                g = g.subset(torch.from_numpy(keep))
        return g
    if suffix in _TORCH_SUFFIXES or magic == b"PK\x03\x04":
        return read_gsplat_ckpt(path, allow_appearance=allow_appearance, allow_nonfinite=allow_nonfinite)
    if not magic:
        raise PlyFormatError(path, "file is empty")
    raise PlyFormatError(path, "unrecognised model file: expected a .ply (INRIA, MaskGaussian or "
                               "PlayCanvas compressed) or a gsplat checkpoint .pt")


def _mask_selection(path: Path, n: int, mode: MaskMode) -> Optional[np.ndarray]:
    """Boolean keep-mask [n] from the vertex mask properties of ``path``, or None to keep all."""
    ply = plyfile.PlyData.read(str(path))  # read_ply succeeded, so this parses; binary data is mmapped
    vertex = ply["vertex"]
    have = {p.name for p in vertex.properties if not isinstance(p, plyfile.PlyListProperty)}
    present = [m for m in MASK_PROPERTIES if m in have]
    if not present:
        return None

    def col(name: str) -> np.ndarray:
        return np.asarray(vertex.data[name], dtype=np.float64)

    def hard(a: np.ndarray) -> bool:
        return bool(np.isin(a, (0.0, 1.0)).all())

    if "masks_0" in have and "masks_1" in have:
        m0, m1 = col("masks_0"), col("masks_1")
        if hard(m0) and hard(m1) and bool((m0 + m1 == 1.0).all()):
            keep, how = m0 == 1.0, "hard one-hot masks_0/masks_1"
        elif mode == "argmax":
            keep, how = m0 > m1, "masks_0 > masks_1 (argmax of MaskGaussian's mask scores)"
        else:
            warnings.warn(f"{path}: masks_0/masks_1 hold soft MaskGaussian mask scores; ignored, all {n} "
                          f"Gaussians kept (load_model(..., masks='argmax') keeps masks_0 > masks_1)",
                          UserWarning, stacklevel=3)
            return None
    else:
        name = "mask" if "mask" in have else present[0]
        m = col(name)
        if hard(m):
            keep, how = m == 1.0, f"hard 0/1 {name}"
        elif mode == "argmax":
            keep, how = m > 0.0, f"{name} > 0 (mask logit)"
        else:
            warnings.warn(f"{path}: {name} holds soft values (not 0/1); ignored, all {n} Gaussians kept "
                          f"(load_model(..., masks='argmax') keeps {name} > 0)", UserWarning, stacklevel=3)
            return None
    if len(keep) != n:  # cannot happen for a file read_ply accepted; guard anyway
        raise PlyFormatError(path, f"mask has {len(keep)} rows, model has {n}")
    if n and not keep.any():
        raise PlyFormatError(path, f"the mask ({how}) keeps no Gaussian; load with masks='ignore' to keep all")
    return keep
