"""LPIPS v0.1 with the AlexNet trunk (Zhang et al., CVPR 2018), in plain ``torch.nn``.

The computation follows the official ``lpips`` package (github.com/richzhang/PerceptualSimilarity,
``lpips/lpips.py``, ``lpips/pretrained_networks.py``, ``lpips/__init__.py``) step for step:

1. images in [0, 1] are mapped to [-1, 1] (``2 x - 1``, the package's ``normalize=True``);
2. ``ScalingLayer``: ``(x - shift) / scale`` per RGB channel, shift [-.030, -.088, -.188],
   scale [.458, .448, .450] (v0.1 only; v0.0 skipped this);
3. torchvision's AlexNet ``features`` (conv1 3->64 k11 s4 p2, ReLU, max-pool 3/2,
   conv2 64->192 k5 p2, ReLU, max-pool 3/2, conv3 192->384 k3 p1, ReLU, conv4 384->256 k3 p1,
   ReLU, conv5 256->256 k3 p1, ReLU), tapped after each of the five ReLUs (the package's
   ``slice1..slice5`` = ``features[0:2], [2:5], [5:8], [8:10], [10:12]``; the final max-pool is
   unused);
4. each tap is unit-normalised over channels, ``f / (sqrt(sum_c f^2) + 1e-10)``
   (``normalize_tensor``);
5. squared difference of the two normalised taps, a 1x1 convolution ``lin{k}`` to one channel
   (no bias; the package's dropout in front of it is inactive in eval mode), mean over H and W
   (``spatial_average``), summed over the five layers.

Weights come from ``lpips_alex_v0.1.safetensors`` (torchvision key layout ``features.{0,3,6,8,10}
.{weight,bias}`` + ``lin{0..4}.weight`` [1, C, 1, 1]), looked up as: explicit path >
``$CLOD_LPIPS_WEIGHTS`` > :data:`DEFAULT_WEIGHTS` (the user cache,
``${XDG_CACHE_HOME:-~/.cache}/clod-adapter/lpips_alex_v0.1.safetensors``). If no file is
found and the official ``lpips`` package imports, its weights are converted instead (that
package downloads the torchvision AlexNet weights on first use).

Lower is more similar; identical images give 0. Inputs are [H, W, 3] or [B, H, W, 3] float
images in [0, 1] (the 3DGS image layout); H and W must be at least 31 for AlexNet's pools.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

import torch
from torch import Tensor, nn

WEIGHTS_ENV = "CLOD_LPIPS_WEIGHTS"
WEIGHTS_NAME = "lpips_alex_v0.1.safetensors"
#: where the weights are looked for when neither a path nor ``$CLOD_LPIPS_WEIGHTS`` is given
DEFAULT_WEIGHTS = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "clod-adapter" / WEIGHTS_NAME

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10
CHANNELS = (64, 192, 384, 256, 256)
# indices into torchvision's alexnet.features of the five ReLUs whose outputs are tapped
TAP_INDICES = (1, 4, 7, 9, 11)
MIN_SIZE = 31  # smallest H/W for which conv1 + two 3/2 max-pools leave at least one pixel

_CACHE: Dict[str, "LPIPSAlex"] = {}
_REASON: Optional[str] = None

PathLike = Union[str, "os.PathLike[str]"]


def _alexnet_features() -> nn.Sequential:
    """torchvision ``alexnet().features[:12]`` (same indices, so state-dict keys match)."""
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),  # 0
        nn.ReLU(),  # 1  -> tap relu1
        nn.MaxPool2d(kernel_size=3, stride=2),  # 2
        nn.Conv2d(64, 192, kernel_size=5, padding=2),  # 3
        nn.ReLU(),  # 4  -> tap relu2
        nn.MaxPool2d(kernel_size=3, stride=2),  # 5
        nn.Conv2d(192, 384, kernel_size=3, padding=1),  # 6
        nn.ReLU(),  # 7  -> tap relu3
        nn.Conv2d(384, 256, kernel_size=3, padding=1),  # 8
        nn.ReLU(),  # 9  -> tap relu4
        nn.Conv2d(256, 256, kernel_size=3, padding=1),  # 10
        nn.ReLU(),  # 11 -> tap relu5
    )


def expected_shapes() -> Dict[str, Tuple[int, ...]]:
    """Key -> shape of every tensor a complete LPIPS-alex v0.1 weights file must hold."""
    ref = LPIPSAlex()
    return {k: tuple(v.shape) for k, v in ref.state_dict().items()}


class LPIPSAlex(nn.Module):
    """LPIPS v0.1 (AlexNet) distance; construct via :func:`load_lpips` to get trained weights.

    ``LPIPSAlex()`` alone has random weights. The module starts in eval mode with every
    parameter frozen (``requires_grad=False``); gradients still flow to the inputs, so it can be
    used as a loss. Move it with ``.to(device)``; inputs are cast to its device and dtype.
    """

    def __init__(self) -> None:
        super().__init__()
        self.features = _alexnet_features()
        for k, c in enumerate(CHANNELS):
            self.add_module(f"lin{k}", nn.Conv2d(c, 1, kernel_size=1, stride=1, padding=0, bias=False))
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    @property
    def lins(self) -> List[nn.Conv2d]:
        return [getattr(self, f"lin{k}") for k in range(len(CHANNELS))]

    def taps(self, x: Tensor) -> List[Tensor]:
        """The five ReLU outputs [B, C_k, H_k, W_k] for a network input x [B, 3, H, W] (already scaled)."""
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in TAP_INDICES:
                out.append(x)
        return out

    def per_layer(self, img: Tensor, gt: Tensor) -> Tensor:
        """Per-layer LPIPS terms [B, 5] for two [B, H, W, 3] images in [0, 1]."""
        x0 = self._prep(img)
        x1 = self._prep(gt)
        terms = []
        for f0, f1, lin in zip(self.taps(x0), self.taps(x1), self.lins):
            n0 = f0 / (torch.sqrt(torch.sum(f0 ** 2, dim=1, keepdim=True)) + EPS)
            n1 = f1 / (torch.sqrt(torch.sum(f1 ** 2, dim=1, keepdim=True)) + EPS)
            terms.append(lin((n0 - n1) ** 2).mean(dim=(1, 2, 3)))
        return torch.stack(terms, dim=1)

    def forward(self, img: Tensor, gt: Tensor) -> Tensor:
        """LPIPS of ``img`` against ``gt``: both [H, W, 3] (-> scalar) or [B, H, W, 3] (-> [B]).

        Values are float images in [0, 1] (not clamped here: the official package does not clamp
        either). Result is float32 (or the module's dtype) on the module's device.
        """
        if img.shape != gt.shape or img.ndim not in (3, 4) or img.shape[-1] != 3:
            raise ValueError(
                f"lpips expects two [H, W, 3] or [B, H, W, 3] images of one shape, "
                f"got {tuple(img.shape)} and {tuple(gt.shape)}"
            )
        h, w = img.shape[-3], img.shape[-2]
        if min(h, w) < MIN_SIZE:
            raise ValueError(f"lpips (AlexNet) needs images of at least {MIN_SIZE}x{MIN_SIZE}, got {h}x{w}")
        single = img.ndim == 3
        if single:
            img, gt = img[None], gt[None]
        d = self.per_layer(img, gt).sum(dim=1)
        return d[0] if single else d

    def _prep(self, x: Tensor) -> Tensor:
        """[B, H, W, 3] in [0, 1] -> scaled network input [B, 3, H, W]."""
        w = self.features[0].weight
        x = x.to(device=w.device, dtype=w.dtype).permute(0, 3, 1, 2).contiguous()
        return ((2 * x - 1) - self.shift) / self.scale


def _load_safetensors(path: Path) -> LPIPSAlex:
    """Build an :class:`LPIPSAlex` from a safetensors file; ValueError naming the file if unusable."""
    from safetensors.torch import load_file

    try:
        sd = load_file(str(path), device="cpu")
    except Exception as e:  # safetensors raises its own error types for corrupt headers/data
        raise ValueError(f"LPIPS weights file {path} is not a readable safetensors file: {e}") from None
    model = LPIPSAlex()
    want = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    missing = sorted(set(want) - set(sd))
    extra = sorted(set(sd) - set(want))
    bad = sorted(k for k in set(want) & set(sd) if tuple(sd[k].shape) != want[k])
    if missing or extra or bad:
        parts = []
        if missing:
            parts.append(f"missing {missing}")
        if extra:
            parts.append(f"unexpected {extra}")
        if bad:
            parts.append("wrong shape " + ", ".join(f"{k} {tuple(sd[k].shape)} != {want[k]}" for k in bad))
        raise ValueError(f"LPIPS weights file {path} does not match LPIPS-alex v0.1: {'; '.join(parts)}")
    nonfinite = sorted(k for k, v in sd.items() if not torch.isfinite(v).all())
    if nonfinite:
        raise ValueError(f"LPIPS weights file {path} has non-finite values in {nonfinite}")
    model.load_state_dict({k: v.float() for k, v in sd.items()}, strict=True)
    return model


def convert_lpips_package_state_dict(sd: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """Map an official ``lpips.LPIPS(net='alex')`` state dict to :class:`LPIPSAlex` keys.

    ``net.sliceN.<i>.{weight,bias}`` -> ``features.<i>.{weight,bias}`` (the slices keep
    torchvision's indices) and ``linK.model.<j>.weight`` -> ``linK.weight`` (``<j>`` is 1 after a
    dropout, 0 without); scaling-layer buffers are dropped.
    """
    out: Dict[str, Tensor] = {}
    for k, v in sd.items():
        parts = k.split(".")
        if len(parts) == 4 and parts[0] == "net" and parts[1].startswith("slice"):
            out[f"features.{parts[2]}.{parts[3]}"] = v
        elif len(parts) == 4 and parts[0].startswith("lin") and parts[1] == "model" and parts[3] == "weight":
            out[f"{parts[0]}.weight"] = v
    return out


def _load_from_lpips_package() -> LPIPSAlex:
    import lpips as _lp  # the official package; absent in most environments

    ref = _lp.LPIPS(net="alex", version="0.1", verbose=False)
    model = LPIPSAlex()
    model.load_state_dict(convert_lpips_package_state_dict(ref.state_dict()), strict=True)
    return model


def resolve_weights_path(path: Optional[PathLike] = None) -> Tuple[Path, str]:
    """The weights path to use and where it came from ('argument', '$CLOD_LPIPS_WEIGHTS', 'default')."""
    if path is not None:
        return Path(path), "argument"
    env = os.environ.get(WEIGHTS_ENV)
    if env:
        return Path(env), f"${WEIGHTS_ENV}"
    return DEFAULT_WEIGHTS, "default"


def load_lpips(path: Optional[PathLike] = None) -> Optional[LPIPSAlex]:
    """The LPIPS-alex model (eval, frozen, CPU, cached per resolved source) or None if unavailable.

    ``path`` > ``$CLOD_LPIPS_WEIGHTS`` > :data:`DEFAULT_WEIGHTS`.
    When that file does not exist, the official ``lpips`` package is tried; if that fails too,
    returns None and :func:`lpips_unavailable_reason` says why. A file that exists but is corrupt
    or of the wrong layout raises ValueError naming it.
    """
    global _REASON
    p, source = resolve_weights_path(path)
    if p.is_file():
        key = str(p.resolve())
        if key not in _CACHE:
            _CACHE[key] = _load_safetensors(p)
        _REASON = None
        return _CACHE[key]
    reason = f"LPIPS weights not found: {p} (from {source}; set ${WEIGHTS_ENV} or pass a path)"
    if "lpips-package" in _CACHE:
        _REASON = None
        return _CACHE["lpips-package"]
    try:
        _CACHE["lpips-package"] = _load_from_lpips_package()
    except Exception as e:  # ImportError in the usual case; download/state-dict errors otherwise
        _REASON = f"{reason}; official lpips package unusable ({type(e).__name__}: {e})"
        return None
    _REASON = None
    return _CACHE["lpips-package"]


def lpips_unavailable_reason() -> Optional[str]:
    """Why the last :func:`load_lpips` call returned None (None if it returned a model)."""
    return _REASON


def lpips(img: Tensor, gt: Tensor, model: Optional[LPIPSAlex] = None) -> float:
    """LPIPS-alex v0.1 of one [H, W, 3] image in [0, 1] against ``gt`` (lower is better).

    ``img`` is clamped to [0, 1] first, as :func:`clod_adapter.metrics.psnr` does. Uses the cached
    :func:`load_lpips` model when ``model`` is None; raises RuntimeError with the reason if no
    weights are available. [B, H, W, 3] inputs give the batch mean.
    """
    if model is None:
        model = load_lpips()
        if model is None:
            raise RuntimeError(lpips_unavailable_reason() or "LPIPS unavailable")
    with torch.no_grad():
        return float(model(img.detach().clamp(0, 1), gt.detach()).mean().item())
