"""Resumable training state: :class:`AdaptState` (the parameters, the optimiser and the step) and
its file beside the output (:data:`STATE_NAME`, :func:`save_state`, :func:`load_state`, and what a
finished run recorded: :func:`state_config`, :func:`max_sv_from_state`, :func:`iterations_from_state`)."""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import torch

from .. import __version__
from ..gaussians import Gaussians
from ..io.atomic import atomic_save
from .config import GAIN_LR, PARAM_NAMES, AdaptConfig
from .official import ADAM_EPS, OFFICIAL_LR, official_groups


@dataclass
class AdaptState:
    """Everything needed to continue a run: parameters, Adam moments, RNG, view order.

    ``history`` holds one record per rendered view (``s_v``, rendered fraction ``eta``,
    ``loss``, training-view ``psnr``), ``views_per_step`` of them per step, in schedule order.
    ``extra``: the input's other per-Gaussian properties (e.g. MaskGaussian's mask scores), carried
    along untrained so the model the state gives is written back with them (not saved in the
    state file: a resumed run takes them from its input again)."""

    params: dict
    optimizer: torch.optim.Optimizer
    generator: torch.Generator
    iteration: int = 0
    order: list = field(default_factory=list)
    extent: float = 1.0
    history: dict = field(default_factory=lambda: {"s_v": [], "eta": [], "loss": [], "psnr": []})
    init: dict = field(default_factory=dict)
    lod: Optional[lod.LodSettings] = None
    extra: dict = field(default_factory=dict)

    def gaussians(self) -> Gaussians:
        """The model as it stands (parameters, not copies; ``lod`` settings and ``extra`` attached)."""
        return Gaussians(**{k: v for k, v in self.params.items()}, lod=self.lod, extra=self.extra)


# --- resumable state -------------------------------------------------------------------------
#: the resumable state's file name in a clod-adapt output folder.
STATE_NAME = "adapt_state.safetensors"


def state_config(ply_path: os.PathLike) -> Optional[dict]:
    """The :class:`AdaptConfig` (as a dict) of the state beside an adapted .ply (its ``config``
    metadata, :func:`save_state`), or None when absent or unreadable."""
    p = Path(ply_path).parent / STATE_NAME
    if not p.is_file():
        return None
    try:
        from safetensors import safe_open

        with safe_open(str(p), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
        return json.loads(meta["config"])
    except Exception:
        return None


def _config_value(ply_path: os.PathLike, key: str, cast):
    """``cast(config[key])`` of the adaptation state beside ``ply_path``, or None."""
    cfg = state_config(ply_path)
    try:
        return cast(cfg[key]) if cfg else None
    except (KeyError, TypeError, ValueError):
        return None


def max_sv_from_state(ply_path: os.PathLike) -> Optional[float]:
    """``max_sv`` of the adaptation state beside ``ply_path``, or None."""
    return _config_value(ply_path, "max_sv", float)


def iterations_from_state(ply_path: os.PathLike) -> Optional[int]:
    """``iterations`` of the adaptation state beside ``ply_path``, or None."""
    return _config_value(ply_path, "iterations", int)


def save_state(path: os.PathLike, state: AdaptState, cfg: AdaptConfig, extra_meta: Optional[dict] = None) -> None:
    """Write ``state`` to a safetensors file atomically.

    Tensors: ``param/<name>`` (raw parameters), ``adam/<name>/{exp_avg,exp_avg_sq,step}``,
    ``rng`` (torch generator state, uint8), ``order`` (remaining view order, int64).
    Metadata (strings): ``format`` = "clod-adapter-state/1", ``version``, ``iteration``,
    ``extent``, ``config`` (JSON of :class:`AdaptConfig`), ``history`` (JSON), plus
    ``extra_meta``.
    """
    from safetensors.torch import save_file

    tensors = {f"param/{k}": v.detach().cpu().contiguous() for k, v in state.params.items()}
    for grp in state.optimizer.param_groups:
        p = grp["params"][0]
        st = state.optimizer.state.get(p, {})
        for key in ("exp_avg", "exp_avg_sq", "step"):
            if key in st:
                tensors[f"adam/{grp['name']}/{key}"] = torch.as_tensor(st[key]).detach().cpu().reshape(-1).contiguous()
    tensors["rng"] = state.generator.get_state().contiguous()
    tensors["order"] = torch.tensor(state.order, dtype=torch.int64)
    meta = {
        "format": "clod-adapter-state/1",
        "version": __version__,
        "iteration": str(state.iteration),
        "extent": repr(state.extent),
        "config": json.dumps(asdict(cfg)),
        "history": json.dumps(state.history),
    }
    meta.update({k: str(v) for k, v in (extra_meta or {}).items()})
    atomic_save(path, lambda tmp: save_file(tensors, str(tmp), metadata=meta))


def load_state(path: os.PathLike, device: str | torch.device = "cpu") -> tuple[AdaptState, AdaptConfig, dict]:
    """Read a state written by :func:`save_state`.

    Returns:
        (state, config, metadata).

    Raises:
        ValueError: the file is not a clod-adapter state (message names the file).
    """
    from safetensors import safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:  # safetensors raises several types
        raise ValueError(f"{path}: not a readable safetensors state ({e})") from None
    if meta.get("format") != "clod-adapter-state/1":
        raise ValueError(f"{path}: not a clod-adapter state (format {meta.get('format')!r})")
    cfg_d = json.loads(meta["config"])
    cfg_d["background"] = tuple(cfg_d.get("background", (0, 0, 0)))
    cfg_d.setdefault("schedule", "paper")  # states written before the calibrated schedule
    cfg_d.setdefault("level_max", 1.0)  # states written before level_max: trained with the level held at 1
    # states written while tiers could also be drawn as a chain (tier_draw): the model's own training
    # does not depend on it, and its tiers are now always linked into a merge tree
    cfg_d.pop("tier_draw", None)

    try:
        cfg = AdaptConfig(**cfg_d)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: unusable config in state ({e})") from None
    train_others = cfg.other_lr_scale > 0
    params = {}
    for name in PARAM_NAMES + cfg.gain_names:
        key = f"param/{name}"
        if key not in tensors:
            raise ValueError(f"{path}: state lacks {key}")
        t = tensors[key].to(device)
        params[name] = torch.nn.Parameter(t, requires_grad=(name == "sigma_d") or (name in cfg.gain_names) or train_others)
    extent = float(meta["extent"])
    opt = torch.optim.Adam(lr_groups(params, cfg, extent), eps=ADAM_EPS)
    for grp in opt.param_groups:
        p = grp["params"][0]
        key = f"adam/{grp['name']}/"
        if key + "exp_avg" in tensors:
            opt.state[p] = {
                "step": tensors[key + "step"].reshape(()).clone(),
                "exp_avg": tensors[key + "exp_avg"].reshape(p.shape).to(device),
                "exp_avg_sq": tensors[key + "exp_avg_sq"].reshape(p.shape).to(device),
            }
    gen = torch.Generator()
    gen.set_state(tensors["rng"])
    st = AdaptState(params=params, optimizer=opt, generator=gen, iteration=int(meta["iteration"]),
                    order=tensors["order"].tolist(), extent=extent, lod=cfg.lod_settings(),
                    history=json.loads(meta.get("history", "{}")) or {"s_v": [], "eta": [], "loss": [], "psnr": []})
    return st, cfg, meta


def lr_groups(params: dict, cfg: AdaptConfig, extent: float) -> list:
    """Adam's parameter groups of an adaptation: ``sigma_d`` at ``cfg.sigma_d_lr``, the level gains
    at the official learning rate of the attribute each offsets times ``cfg.gain_lr_scale``, and,
    with ``cfg.other_lr_scale > 0``, the base attributes at the official 3DGS rates times it
    (:func:`clod_adapter.train.official.official_groups`; ``means`` at the official initial rate
    times the scene extent)."""
    groups = [{"params": [params["sigma_d"]], "lr": cfg.sigma_d_lr, "name": "sigma_d"}]
    for name in cfg.gain_names:
        groups.append({"params": [params[name]], "lr": GAIN_LR[name] * cfg.gain_lr_scale, "name": name})
    if cfg.other_lr_scale > 0:
        groups += official_groups(params, OFFICIAL_LR["means"][0] * extent * cfg.other_lr_scale, cfg.other_lr_scale)
    return groups
