"""Read gsplat ``simple_trainer`` checkpoints (``ckpt_<step>[_rank<r>].pt``) into ``Gaussians``.

gsplat's ``examples/simple_trainer.py`` saves ``torch.save({"step": step, "splats":
self.splats.state_dict(), ...optional "pose_adjust", "app_module", ...}, ...)`` where ``splats``
is the ``torch.nn.ParameterDict`` built by ``create_splats_with_optimizers``:

* ``means`` [N,3] (``means3d`` in gsplat <= 0.1 examples), ``quats`` [N,4] (wxyz, unnormalised),
  ``scales`` [N,3] (log), ``opacities`` [N] (logits),
* SH colours (the default): ``sh0`` [N,1,3], ``shN`` [N,K-1,3], K = (degree+1)^2 -- the same
  layout as :class:`~clod_adapter.gaussians.Gaussians`;
* or, with ``--app_opt``: ``features`` [N,D] (appearance embedding inputs) and ``colors`` [N,3]
  (logit of the base RGB). That variant is not an SH model (its colour is
  ``sigmoid(colors + app_module(features, camera, dirs))``); it is rejected unless
  ``allow_appearance=True``, which keeps the base colour only: ``sh0 = (sigmoid(colors) - 0.5) /
  SH_C0``, degree 0 (the appearance network's view-/camera-dependent part is dropped).

A distributed run writes one shard per rank (``ckpt_<step>_rank<r>.pt``); this reads one file.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Union

import torch

from clod_adapter.gaussians import SH_C0, Gaussians
from clod_adapter.io.ply import PlyFormatError

__all__ = ["read_gsplat_ckpt"]

PathLike = Union[str, "os.PathLike[str]"]


def read_gsplat_ckpt(path: PathLike, *, allow_appearance: bool = False,
                     allow_nonfinite: bool = False) -> Gaussians:
    """Load a gsplat simple_trainer checkpoint's ``splats`` as ``Gaussians``.

    The file is loaded with ``torch.load(path, map_location="cpu", weights_only=True)`` (no
    arbitrary code runs). Tensors are converted to contiguous float32 CPU copies.

    Args:
        path: the ``.pt`` file.
        allow_appearance: accept the ``features``/``colors`` (``--app_opt``) variant, keeping only
            the base colour (see the module docstring).
        allow_nonfinite: keep NaN/Inf values instead of raising.

    Returns:
        ``Gaussians`` (sigma_d None).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        PlyFormatError: not a loadable torch file, no ``splats`` dict, a required key missing,
            inconsistent shapes, an SH count that is no degree 0..3, the appearance variant
            without ``allow_appearance``, or NaN/Inf values.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise PlyFormatError(path, "file is empty")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 -- any failure to unpickle an untrusted file is a format error
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise PlyFormatError(path, f"not a loadable torch checkpoint: {msg}") from None

    if not isinstance(ckpt, dict) or "splats" not in ckpt:
        what = f"keys: {', '.join(map(str, list(ckpt)[:10]))}" if isinstance(ckpt, dict) else type(ckpt).__name__
        raise PlyFormatError(path, f"not a gsplat checkpoint: no 'splats' dict ({what})")
    splats = ckpt["splats"]
    if not isinstance(splats, dict):
        raise PlyFormatError(path, f"'splats' is a {type(splats).__name__}, expected a dict of tensors")

    def get(*names: str, required: bool = True):
        for name in names:
            if name in splats:
                t = splats[name]
                if not isinstance(t, torch.Tensor):
                    raise PlyFormatError(path, f"splats[{name!r}] is a {type(t).__name__}, expected a tensor")
                return t.detach().to(device="cpu", dtype=torch.float32).contiguous().clone()
        if required:
            raise PlyFormatError(path, f"splats lacks {' / '.join(repr(n) for n in names)} "
                                       f"(keys: {', '.join(map(str, splats))})")
        return None

    means = get("means", "means3d")
    quats = get("quats")
    log_scales = get("scales")
    opacities = get("opacities")
    n = means.shape[0] if means.ndim >= 1 else -1
    if opacities.ndim == 2 and opacities.shape[1:] == (1,):  # tolerate [N, 1]
        opacities = opacities.reshape(-1)

    if "sh0" in splats or "shN" in splats:
        sh0 = get("sh0")
        shN = get("shN", required=False)
        if sh0.ndim == 2 and sh0.shape[1:] == (3,):
            sh0 = sh0.reshape(-1, 1, 3)
        if shN is None or shN.numel() == 0:
            shN = torch.zeros((sh0.shape[0], 0, 3), dtype=torch.float32)
    elif "colors" in splats and "features" in splats:
        if not allow_appearance:
            raise PlyFormatError(path, "checkpoint uses gsplat's appearance model (splats 'features' + "
                                       "'colors', --app_opt), not SH colours; pass allow_appearance=True "
                                       "to keep only the base colour")
        colors = get("colors")
        if colors.ndim != 2 or colors.shape[1] != 3:
            raise PlyFormatError(path, f"splats['colors'] has shape {tuple(colors.shape)}, expected ({n}, 3)")
        sh0 = ((torch.sigmoid(colors) - 0.5) / SH_C0).reshape(-1, 1, 3)
        shN = torch.zeros((colors.shape[0], 0, 3), dtype=torch.float32)
    else:
        raise PlyFormatError(path, f"splats has no colour parameters ('sh0'/'shN' or 'features'/'colors'; "
                                   f"keys: {', '.join(map(str, splats))})")

    try:
        g = Gaussians(means=means, quats=quats, log_scales=log_scales, opacity_logits=opacities,
                      sh0=sh0, shN=shN)
    except ValueError as e:
        raise PlyFormatError(path, f"inconsistent splats: {e}") from None

    if not allow_nonfinite:
        bad = [k for k, t in g.tensors().items() if not torch.isfinite(t).all()]
        if bad:
            raise PlyFormatError(path, f"non-finite values in {', '.join(bad)}; pass allow_nonfinite=True to keep them")
    return g
