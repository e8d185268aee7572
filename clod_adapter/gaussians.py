"""The Gaussian model: raw (optimised) parameters and their activated views.

Conventions follow the official 3DGS code and gsplat 1.5.3:
``means`` world units, ``quats`` wxyz (unnormalised, normalised on use), ``log_scales`` (raw,
``scales = exp(log_scales)``), ``opacity_logits`` (raw, ``opacities = sigmoid(opacity_logits)``),
SH coefficients split as ``sh0`` [N, 1, 3] and ``shN`` [N, K-1, 3] with K = (degree + 1)^2
(gsplat's ``colors`` layout [N, K, 3]), and the CLoD-GS distance decay ``sigma_d`` [N]
(Cheng et al., ICLR 2026, Eq. 2; ``None`` for a model that has not been adapted).

An adapted model may also carry *level gains* (this project's extension, docs/method.md "The
calibrated schedule"): raw offsets added at level ``l`` in [0, 1] (:func:`clod_adapter.lod.rule.level`)
as ``opacity_logits + l * opacity_logit_gain``, ``log_scales + l * log_scale_gain`` (one scalar
for the three axes) and ``sh0 + l * sh0_gain``. At full detail (``l = 0``) the model is exactly
its base attributes. ``lod`` holds the settings it is drawn with (:class:`clod_adapter.lod.rule.LodSettings`).

``extra`` carries per-Gaussian values the model does not use but a checkpoint had (e.g.
MaskGaussian's ``masks_0``/``masks_1``), so that they survive a read, an adaptation and a write
(:func:`clod_adapter.io.ply.read_ply` / ``write_ply``); they are never parameters
(:meth:`Gaussians.tensors` leaves them out), but every per-Gaussian operation carries them.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Optional, Sequence

import torch
from torch import Tensor

from .lod_settings import LodSettings

SH_C0 = 0.28209479177387814  # Y_0^0, as in the official 3DGS utils/sh_utils.py


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    """SH degree for K = (degree + 1)^2 coefficients per channel.

    Raises:
        ValueError: K is not 1, 4, 9 or 16.
    """
    for deg in range(4):
        if (deg + 1) ** 2 == num_coeffs:
            return deg
    raise ValueError(f"{num_coeffs} SH coefficients per channel match no SH degree 0..3")


@dataclass
class Gaussians:
    """A 3DGS model with N Gaussians (all tensors on one device, float32 unless noted).

    Attributes:
        means: [N, 3] centres, world units.
        quats: [N, 4] rotations, wxyz, unnormalised.
        log_scales: [N, 3] log of the per-axis standard deviations (world units).
        opacity_logits: [N] logit of the opacity.
        sh0: [N, 1, 3] degree-0 SH coefficient (the INRIA ``f_dc``).
        shN: [N, K-1, 3] higher-order SH coefficients (the INRIA ``f_rest``, reordered from
            channel-major); K-1 = 0 for degree 0.
        sigma_d: [N] CLoD-GS distance decay (raw; Eq. 2 uses ReLU(sigma_d)), or None.
        opacity_logit_gain: [N] level gain of the opacity logit, or None (zero).
        log_scale_gain: [N] level gain of the log-scales (all three axes), or None (zero).
        sh0_gain: [N, 1, 3] level gain of the degree-0 SH coefficient, or None (zero).
        lod: how the model is drawn at a level of detail, or None (defaults; the paper's Eq. 2).
        extra: [N] tensors by .ply property name (any dtype), carried along but not trained or
            rendered (e.g. ``masks_0``, ``masks_1``); empty by default.
        parents: the parent tier, or None: an adapted model of merged Gaussians (M of them, its
            own ``sigma_d`` and gains) that the coarse levels hand over to from ``lod.tier_s_v``
            on (docs/method.md "Merged tiers"), with its own ``parents`` for the next tier
            (:func:`clod_adapter.lod.draw.tier_chain`); drawn where the tiers are linked into a
            merge tree (``lod.tree``, :mod:`clod_adapter.lod.tree`). Moved and copied with the
            model; a :meth:`subset` drops it.
    """

    means: Tensor
    quats: Tensor
    log_scales: Tensor
    opacity_logits: Tensor
    sh0: Tensor
    shN: Tensor
    sigma_d: Optional[Tensor] = None
    opacity_logit_gain: Optional[Tensor] = None
    log_scale_gain: Optional[Tensor] = None
    sh0_gain: Optional[Tensor] = None
    lod: Optional[LodSettings] = None
    extra: dict[str, Tensor] = field(default_factory=dict)
    parents: Optional["Gaussians"] = None

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        checks = {
            "means": (self.means, (n, 3)),
            "quats": (self.quats, (n, 4)),
            "log_scales": (self.log_scales, (n, 3)),
            "opacity_logits": (self.opacity_logits, (n,)),
            "sh0": (self.sh0, (n, 1, 3)),
        }
        for name, (t, shape) in checks.items():
            if tuple(t.shape) != shape:
                raise ValueError(f"Gaussians.{name} has shape {tuple(t.shape)}, expected {shape}")
        if self.shN.ndim != 3 or self.shN.shape[0] != n or self.shN.shape[2] != 3:
            raise ValueError(f"Gaussians.shN has shape {tuple(self.shN.shape)}, expected ({n}, K-1, 3)")
        sh_degree_from_coeffs(self.shN.shape[1] + 1)
        for name, shape in (("sigma_d", (n,)), ("opacity_logit_gain", (n,)), ("log_scale_gain", (n,)),
                            ("sh0_gain", (n, 1, 3))):
            t = getattr(self, name)
            if t is not None and tuple(t.shape) != shape:
                raise ValueError(f"Gaussians.{name} has shape {tuple(t.shape)}, expected {shape}")
        for name, t in self.extra.items():
            if tuple(t.shape) != (n,):
                raise ValueError(f"Gaussians.extra[{name!r}] has shape {tuple(t.shape)}, expected ({n},)")

    # --- activated views -------------------------------------------------------------------
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.shN.shape[1] + 1)

    @property
    def scales(self) -> Tensor:
        """[N, 3] activated scales, exp(log_scales)."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        """[N] activated opacities, sigmoid(opacity_logits)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def colors(self) -> Tensor:
        """[N, K, 3] SH coefficients in gsplat's ``colors`` layout (sh0 then shN)."""
        return torch.cat([self.sh0, self.shN], dim=1)

    # --- utilities --------------------------------------------------------------------------
    @property
    def has_gains(self) -> bool:
        """True when any level gain is present."""
        return any(getattr(self, k) is not None for k in GAIN_NAMES)

    def at_level(self, ell: float) -> "Gaussians":
        """The model's attributes at level ``ell`` (>= 0; 1 at ``max_sv``, up to
        ``LodSettings.level_max``: :func:`clod_adapter.lod.rule.level`): base attributes plus ``ell``
        times the level gains (differentiable in both). ``ell = 0`` or no gains: ``self``."""
        if ell == 0.0 or not self.has_gains:
            return self
        upd = {}
        if self.opacity_logit_gain is not None:
            upd["opacity_logits"] = self.opacity_logits + ell * self.opacity_logit_gain
        if self.log_scale_gain is not None:
            upd["log_scales"] = self.log_scales + ell * self.log_scale_gain[:, None]
        if self.sh0_gain is not None:
            upd["sh0"] = self.sh0 + ell * self.sh0_gain
        return replace(self, **upd)

    def tensors(self) -> dict[str, Tensor]:
        """The non-None parameter tensors by field name (not :attr:`extra`)."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if isinstance(getattr(self, f.name), Tensor)}

    def _map(self, fn) -> "Gaussians":
        """``fn`` applied to every tensor, parameters and :attr:`extra` alike."""
        return replace(self, **{k: fn(v) for k, v in self.tensors().items()},
                       extra={k: fn(v) for k, v in self.extra.items()})

    def to(self, device: torch.device | str) -> "Gaussians":
        return self._map_all(lambda v: v.to(device))

    def detach(self) -> "Gaussians":
        return self._map_all(lambda v: v.detach())

    def clone(self) -> "Gaussians":
        return self._map_all(lambda v: v.detach().clone())

    def _map_all(self, fn) -> "Gaussians":
        """:meth:`_map`, the parent tier included."""
        out = self._map(fn)
        return out if self.parents is None else replace(out, parents=self.parents._map_all(fn))

    def subset(self, index: Tensor) -> "Gaussians":
        """Gaussians selected by a boolean mask [N] or an index tensor [M] (int64), without a
        parent tier (its Gaussians merge the whole model's)."""
        return replace(self._map(lambda v: v[index]), parents=None)

    def with_sigma_d(self, sigma_d: Optional[Tensor]) -> "Gaussians":
        """The model with ``sigma_d`` replaced; ``None`` also drops the level gains, settings,
        tiers and a merge tree's node data (``extra["parent"]``, ``extra["exit"]``, ``extra["d_ref"]``): the plain 3DGS
        model."""
        if sigma_d is None:
            return replace(self, sigma_d=None, opacity_logit_gain=None, log_scale_gain=None,
                           sh0_gain=None, lod=None, parents=None,
                           extra={k: v for k, v in self.extra.items() if k not in TREE_NODE_KEYS})
        return replace(self, sigma_d=sigma_d)


def concat(models: Sequence[Gaussians]) -> Gaussians:
    """Plain models (no ``sigma_d``, gains or tier; the same SH degree and :attr:`Gaussians.extra`
    keys) one after the other: [N_1 + N_2 + ...] rows, in order.

    Raises:
        ValueError: no model, a model with LoD data, or differing SH degrees / extra keys.
    """
    if not models:
        raise ValueError("concat: no models")
    for m in models:
        if m.sigma_d is not None or m.has_gains or m.parents is not None:
            raise ValueError("concat: plain models only (sigma_d, gains and tier dropped: with_sigma_d(None))")
    if len({m.sh_degree for m in models}) > 1 or len({tuple(sorted(m.extra)) for m in models}) > 1:
        raise ValueError("concat: the models differ in SH degree or extra properties")
    if len(models) == 1:
        return models[0]
    names = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")
    return Gaussians(**{k: torch.cat([getattr(m, k) for m in models]) for k in names},
                     extra={k: torch.cat([m.extra[k] for m in models]) for k in models[0].extra})


#: the level-gain fields of :class:`Gaussians`.
GAIN_NAMES = ("opacity_logit_gain", "log_scale_gain", "sh0_gain")
#: a merge tree's node data (``extra`` keys and .ply properties; :mod:`clod_adapter.lod.tree`): the
#: parent index in the next tier, the exit constant, the reference distance
TREE_NODE_KEYS = ("parent", "exit", "d_ref")
