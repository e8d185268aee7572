"""The model a viewer shows, and the level-of-detail range it was trained for."""
from __future__ import annotations

import os
from pathlib import Path

from clod_adapter.gaussians import Gaussians

__all__ = ["DEFAULT_MAX_SV", "model_max_sv", "load_view_model"]

#: ``max_sv`` assumed when the model carries none (``clod-adapt``'s default ``--max-sv``)
DEFAULT_MAX_SV = 5.0


def model_max_sv(ply_path: os.PathLike | str, model: Gaussians | None = None) -> float:
    """The largest virtual distance scale the model at ``ply_path`` was trained for.

    Read from the model's LoD settings (the ``clod_lod`` header comment of the extended .ply,
    ``model.lod`` when the model is given), else from ``adapt_state.safetensors`` beside the .ply
    (its ``config`` metadata; :func:`clod_adapter.jobs.eval.max_sv_from_state`); :data:`DEFAULT_MAX_SV`
    (5) when neither holds a positive finite value.
    """
    from clod_adapter.train.state import max_sv_from_state

    v = model.lod.max_sv if (model is not None and model.lod is not None) else None
    if v is None:
        v = max_sv_from_state(Path(ply_path))
    if v is None or not (v >= 1.0 and v < float("inf")):
        return DEFAULT_MAX_SV
    return float(v)


def load_view_model(path: os.PathLike | str) -> Gaussians:
    """Read a model for viewing: any format :func:`clod_adapter.io.load.load_model` takes (the
    CLoD-extended .ply with ``sigma_d``, or a plain 3DGS .ply / compressed .ply / gsplat .pt
    without it). float32 CPU tensors.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        PlyFormatError: not a readable model (message ``"<path>: <problem>"``), NaN/Inf values
            included, or a model with no Gaussian.
    """
    from clod_adapter.io.load import load_model
    from clod_adapter.io.ply import PlyFormatError

    g = load_model(path)
    if len(g) == 0:
        raise PlyFormatError(path, "the model has no Gaussian")
    return g.detach()
