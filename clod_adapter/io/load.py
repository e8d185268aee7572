"""Load a pretrained 3DGS model from any supported checkpoint format, chosen by content.

Dispatch (:func:`load_model`):

* a .ply whose header has a ``chunk`` element and a ``packed_position`` vertex property
  (PlayCanvas / SuperSplat compressed) -> :func:`~clod_adapter.io.compressed_ply.read_compressed_ply`;
* any other .ply (content starts with ``ply``, or the name ends in ``.ply``) ->
  :func:`~clod_adapter.io.ply.read_ply`: the INRIA layout, which also covers MaskGaussian
  checkpoints (its ``save_ply_default`` writes the vanilla layout; its ``save_ply`` adds the
  ``masks_0``/``masks_1`` properties, applied by :func:`apply_masks` -- see *Masks* below), the
  no-normals exporter variant and the CLoD extension with ``sigma_d``;
* a torch checkpoint (name ``*.pt`` / ``*.pth`` / ``*.ckpt`` or a zip-format torch file) ->
  :func:`~clod_adapter.io.gsplat_ckpt.read_gsplat_ckpt` (gsplat simple_trainer ``ckpt_*.pt``);
* anything else -> :class:`~clod_adapter.io.ply.PlyFormatError` naming the file.

Masks (INRIA-layout .ply only). MaskGaussian (Liu et al., CVPR 2025; kaikai23/MaskGaussian
``scene/gaussian_model.py``) learns two mask scores per Gaussian. Its official save
(``save_ply_default``) draws the mask once and writes the kept Gaussians in the plain layout
(nothing to do here); its unused ``save_ply`` writes every Gaussian with the scores as
``masks_0``, ``masks_1``. It renders with ``mask = gumbel_softmax(log_softmax([masks_0, masks_1]),
hard=True)[:, 0]`` (class 0 = "keep"), a stochastic hard mask with ``p(keep) =
sigmoid(masks_0 - masks_1)``. ``read_ply`` keeps the scores in ``Gaussians.extra``;
:func:`apply_masks` (called by :func:`load_model`) selects Gaussians by one of the policies
(:data:`MASK_POLICIES`):

* ``"argmax"`` (the default, ``"auto"``; chosen by measurement, see
  ``benchmarks/studies/maskgaussian_masks.py``): keep ``p(keep) > 0.5``, i.e. ``masks_0 > masks_1``, the
  mode of the sampled mask; deterministic;
* ``"gumbel"``: one hard Gumbel-softmax draw as the official save does, from a
  ``torch.Generator`` seeded with ``mask_seed`` (deterministic for a seed);
* ``"all"`` (alias ``"ignore"``): keep every Gaussian.

``"auto"`` keeps every Gaussian of a CLoD-adapted model (one with ``sigma_d``: ``clod-adapt``
applied the masks before adapting and wrote the kept Gaussians' scores back), so re-reading an
output never drops Gaussians again.

A single ``mask`` property (or a lone ``masks_0``) is read as the logit of ``p(keep)``
(``argmax``: ``mask > 0``; ``gumbel``: keep with probability ``sigmoid(mask)``). Masks that are
already hard (``masks_0``/``masks_1`` one-hot, or a 0/1 ``mask``) are a drawn mask: ``argmax`` and
``gumbel`` both keep exactly the Gaussians marked 1. The mask properties of the kept Gaussians stay
in ``extra`` (and so in a ``.ply`` written from the model). Filtering never empties the model
silently: a policy that would keep no Gaussian raises ``PlyFormatError``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Sequence, Union

import torch

from clod_adapter.gaussians import Gaussians
from clod_adapter.io.compressed_ply import is_compressed_ply, read_compressed_ply
from clod_adapter.io.gsplat_ckpt import read_gsplat_ckpt
from clod_adapter.io.ply import PlyFormatError, read_ply
from clod_adapter.io.scene import Scene, SceneError

__all__ = ["load_model", "apply_masks", "MaskInfo", "resolve_model_path", "model_folder", "training_size",
           "MASK_PROPERTIES", "MASK_POLICIES", "DEFAULT_MASK_POLICY"]

PathLike = Union[str, "os.PathLike[str]"]
MaskMode = Literal["auto", "argmax", "gumbel", "all", "ignore"]

MASK_PROPERTIES = ("masks_0", "masks_1", "mask")
#: the mask policies (module docstring); ``"auto"`` means :data:`DEFAULT_MASK_POLICY`, ``"ignore"`` is ``"all"``.
MASK_POLICIES = ("argmax", "gumbel", "all")
#: the policy for learned (soft) mask scores, by ``benchmarks/studies/maskgaussian_masks.py`` (docs/studies.md).
DEFAULT_MASK_POLICY = "argmax"
_MASK_WHAT = {"argmax": "keep p(keep) > 0.5", "gumbel": "one Gumbel draw, seed {seed}", "all": "keep all"}
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


def load_model(path: PathLike, *, masks: MaskMode = "auto", mask_seed: int = 0, allow_nonfinite: bool = False,
               allow_appearance: bool = False) -> Gaussians:
    """Read a 3DGS model from ``path``, whatever its supported format (see the module docstring).

    Args:
        path: a .ply (INRIA / MaskGaussian / CLoD-extended / compressed) or a gsplat ``.pt``.
        masks: how MaskGaussian-style mask properties of an INRIA-layout .ply are applied:
            ``"auto"`` (= :data:`DEFAULT_MASK_POLICY`), ``"argmax"``, ``"gumbel"``, ``"all"`` /
            ``"ignore"`` (module docstring; :func:`apply_masks`).
        mask_seed: seed of the ``"gumbel"`` draw.
        allow_nonfinite: passed to ``read_ply`` / ``read_gsplat_ckpt``.
        allow_appearance: passed to ``read_gsplat_ckpt`` (gsplat ``--app_opt`` checkpoints).

    Returns:
        ``Gaussians`` (float32, CPU); unknown .ply properties (e.g. the mask scores of the kept
        Gaussians) in ``extra``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        PlyFormatError: the content is no supported format, the reader rejects it, or the mask
            keeps no Gaussian.
        ValueError: ``masks`` is not one of the policies.
    """
    _policy(masks)
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
        return apply_masks(g, masks, seed=mask_seed, path=path)[0]
    if suffix in _TORCH_SUFFIXES or magic == b"PK\x03\x04":
        return read_gsplat_ckpt(path, allow_appearance=allow_appearance, allow_nonfinite=allow_nonfinite)
    if not magic:
        raise PlyFormatError(path, "file is empty")
    raise PlyFormatError(path, "unrecognised model file: expected a .ply (INRIA, MaskGaussian or "
                               "PlayCanvas compressed) or a gsplat checkpoint .pt")


def _policy(masks: str) -> str:
    """The policy ``masks`` names (``"auto"`` -> the default, ``"ignore"`` -> ``"all"``).

    Raises:
        ValueError: not a policy.
    """
    if masks == "auto":
        return DEFAULT_MASK_POLICY
    if masks == "ignore":
        return "all"
    if masks not in MASK_POLICIES:
        raise ValueError(f"masks must be one of auto, {', '.join(MASK_POLICIES)} or ignore, got {masks!r}")
    return masks


@dataclass
class MaskInfo:
    """What :func:`apply_masks` did: the ``policy`` asked for, the mask ``source`` (which
    properties), whether the mask was ``hard`` (already drawn: applied as is unless ``"all"``),
    Gaussians ``kept`` of ``total``, the ``seed`` of a Gumbel draw (None when there was none)."""

    policy: str
    source: str
    hard: bool
    kept: int
    total: int
    seed: Optional[int] = None
    note: str = ""

    def describe(self) -> str:
        """One line, e.g. ``masks_0/masks_1 (soft scores): argmax (keep p(keep) > 0.5), kept
        19,458 of 39,977 Gaussians (48.7 %)``."""
        what = _MASK_WHAT[self.policy].format(seed=self.seed)
        if self.hard and self.policy != "all":
            what = "a drawn 0/1 mask, applied as is"
        kind = "hard mask" if self.hard else "soft scores"
        note = f"; {self.note}" if self.note else ""
        return (f"{self.source} ({kind}): {self.policy} ({what}{note}), kept {self.kept:,} of {self.total:,} "
                f"Gaussians ({100 * self.kept / max(self.total, 1):.1f} %)")


def apply_masks(gaussians: Gaussians, masks: MaskMode = "auto", *, seed: int = 0,
                path: PathLike = "<model>") -> tuple[Gaussians, Optional[MaskInfo]]:
    """Select Gaussians by the MaskGaussian mask properties in ``gaussians.extra``.

    Args:
        gaussians: a model read by ``read_ply`` (mask properties, if any, in ``extra``).
        masks: the policy (module docstring): ``"auto"`` (= :data:`DEFAULT_MASK_POLICY`, or
            ``"all"`` for a model with ``sigma_d``), ``"argmax"``, ``"gumbel"``, ``"all"`` /
            ``"ignore"``.
        seed: seed of the ``"gumbel"`` draw (a ``torch.Generator`` on the CPU: the same seed
            keeps the same Gaussians on every machine).
        path: named in errors.

    Returns:
        (the kept Gaussians, their ``extra`` subset alike, or ``gaussians`` itself; a
        :class:`MaskInfo`, or None when the model has no mask property).

    Raises:
        PlyFormatError: the policy keeps no Gaussian.
        ValueError: unknown policy.
    """
    policy = _policy(masks)
    note = ""
    if masks == "auto" and gaussians.sigma_d is not None:
        policy, note = "all", "a CLoD-adapted model: its masks were applied before adaptation"
    ex = gaussians.extra
    n = len(gaussians)
    if "masks_0" in ex and "masks_1" in ex:
        m0, m1 = ex["masks_0"].double().cpu(), ex["masks_1"].double().cpu()
        hard = _is_hard(m0) and _is_hard(m1) and bool((m0 + m1 == 1.0).all())
        source, logit = "masks_0/masks_1", m0 - m1
    elif "mask" in ex or "masks_0" in ex:
        name = "mask" if "mask" in ex else "masks_0"
        logit = ex[name].double().cpu()
        hard = _is_hard(logit)
        source = name
        if hard:  # a drawn 0/1 mask: 1 = keep
            logit = logit - 0.5
    else:
        return gaussians, None
    if policy == "all":
        return gaussians, MaskInfo(policy, source, hard, n, n, note=note)
    if policy == "argmax" or hard:
        keep, used_seed = logit > 0, None
    else:  # one hard Gumbel-softmax draw of log_softmax([s0, s1]): keep iff s0 + g0 > s1 + g1
        gen = torch.Generator().manual_seed(int(seed))
        u = torch.rand((n, 2), generator=gen, dtype=torch.float64).clamp_min(1e-300)
        g = -torch.log(-torch.log(u))
        keep, used_seed = logit + g[:, 0] > g[:, 1], int(seed)
    info = MaskInfo(policy, source, hard, int(keep.sum()), n, used_seed)
    if n and not bool(keep.any()):
        raise PlyFormatError(path, f"the mask ({info.describe()}) keeps no Gaussian; load with masks='all' to keep all")
    if info.kept == n:
        return gaussians, info
    return gaussians.subset(keep.to(gaussians.means.device)), info


def _is_hard(a: torch.Tensor) -> bool:
    return bool(((a == 0.0) | (a == 1.0)).all())


def scene_format(root: PathLike) -> str:
    """``"blender"`` when ``root/transforms_train.json`` exists, else ``"colmap"``."""
    from clod_adapter.io.blender import is_blender_scene

    return "blender" if is_blender_scene(root) else "colmap"


def load_scene(root: PathLike, resolution: int = 1, background: Sequence[float] = (0.0, 0.0, 0.0),
               llffhold: int = 8) -> Scene:
    """Load a scene folder, NeRF-synthetic or COLMAP.

    ``transforms_train.json`` present: :func:`clod_adapter.io.blender.load_blender_scene` (RGBA
    images composited over ``background``; ``llffhold`` unused). Otherwise
    :func:`clod_adapter.io.colmap.load_colmap_scene` (``llffhold`` split; ``background`` is
    recorded on the Scene and applies to images with an alpha channel). pycolmap is imported only
    for COLMAP scenes.

    Raises:
        SceneError: as the loader chosen.
    """
    if scene_format(root) == "blender":
        from clod_adapter.io.blender import load_blender_scene

        return load_blender_scene(root, resolution=resolution, background=background)
    from clod_adapter.io.colmap import load_colmap_scene

    scene = load_colmap_scene(root, resolution=resolution, llffhold=llffhold)
    try:
        scene.background = tuple(float(x) for x in background)
    except (TypeError, ValueError):
        raise SceneError(Path(root), f"background must be 3 numbers in [0, 1], got {background!r}") from None
    return scene
