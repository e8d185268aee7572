"""Read PlayCanvas / SuperSplat "compressed .ply" splats into ``Gaussians``.

Format (as written by splat-transform ``src/lib/writers/compressed-chunk.ts`` +
``write-compressed-ply.ts`` and SuperSplat; decoded as in splat-transform
``src/lib/readers/decompress-ply.ts`` and the PlayCanvas engine
``src/scene/gsplat/gsplat-compressed-data.js``), binary little endian:

* ``element chunk ceil(N/256)``: float ``min_x min_y min_z max_x max_y max_z``,
  ``min_scale_{x,y,z} max_scale_{x,y,z}`` (bounds of the *log* scales) and optionally
  ``min_{r,g,b} max_{r,g,b}`` (bounds of the DC colour); splat ``i`` belongs to chunk ``i // 256``.
* ``element vertex N``: uint32 ``packed_position`` and ``packed_scale`` (11-10-11 bits, x in the
  top 11 bits, unorm ``q / (2^bits - 1)`` lerped between the chunk's min and max),
  ``packed_rotation`` (bits 31-30: index of the largest quaternion component in
  ``rot_0..rot_3`` = w x y z order; then three 10-bit components, the other three in order, each
  ``(q/1023 - 0.5) * sqrt(2)``; the largest is ``sqrt(1 - a^2 - b^2 - c^2)``, the encoder flips
  the sign so that it is positive), ``packed_color`` (8-8-8-8: r g b in the top bytes, lerped
  between the chunk colour bounds when present, the colour ``0.5 + SH_C0 * f_dc``; alpha in the
  low byte, the activated opacity).
* optional ``element sh N``: uchar ``f_rest_0..f_rest_{M-1}``, M in {9, 24, 45} (gsplat's
  ``export_splats(format="ply_compressed")`` also writes it with M = 0 for degree 0), INRIA
  channel-major order; encoded ``trunc((v/8 + 0.5) * 256)`` clamped to 0..255, decoded at the
  bin centre ``((q + 0.5)/256 - 0.5) * 8`` with 0 -> -4 and 255 -> +4 (splat-transform's
  decoder; the engine's iterator uses ``q * 8/255 - 4``, which differs by < 0.016).

Conversions to the raw 3DGS parameters: ``f_dc = (c - 0.5) / SH_C0``; opacity logit
``-log(1/a - 1)`` with ``a`` clamped to ``[1e-6, 1 - 1e-6]`` (splat-transform writes +-inf for
alpha 0 / 255, the engine +-40; we keep the result finite, |logit| <= 13.8); log scales are
used as stored. Arithmetic is float64, the result float32.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Union

import numpy as np
import torch

from clod_adapter.gaussians import SH_C0, Gaussians
from clod_adapter.io.ply import PlyFormatError, open_ply

__all__ = ["read_compressed_ply", "is_compressed_ply", "CHUNK_SIZE"]

PathLike = Union[str, "os.PathLike[str]"]

CHUNK_SIZE = 256
_CHUNK_REQUIRED = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                   "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
_CHUNK_COLOR = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
_VERTEX_REQUIRED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
_SH_COUNTS = {9: 1, 24: 2, 45: 3}
_ALPHA_EPS = 1e-6


def _read_header(path: Path, limit: int = 1 << 20) -> list[bytes] | None:
    """The header lines (without ``end_header``) of a .ply, or None when it is not one."""
    with open(path, "rb") as f:
        head = f.read(limit)
    if not head.startswith(b"ply"):
        return None
    end = head.find(b"end_header")
    if end < 0:
        return None
    return head[:end].splitlines()


def is_compressed_ply(path: PathLike) -> bool:
    """Whether ``path`` is a PlayCanvas/SuperSplat compressed .ply: its header declares a
    ``chunk`` element and a ``packed_position`` property of the ``vertex`` element.

    Only the header is read. Files that are not .ply at all give False.

    Raises:
        FileNotFoundError / OSError: ``path`` cannot be opened.
    """
    lines = _read_header(Path(path))
    if lines is None:
        return False
    has_chunk = has_packed = False
    current = None
    for line in lines:
        tok = line.split()
        if len(tok) >= 2 and tok[0] == b"element":
            current = tok[1]
            has_chunk |= current == b"chunk"
        elif tok and tok[0] == b"property" and current == b"vertex" and tok[-1] == b"packed_position":
            has_packed = True
    return has_chunk and has_packed


def _unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    t = (1 << bits) - 1
    return ((v >> np.uint32(shift)) & np.uint32(t)).astype(np.float64) / t


def _lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray) -> np.ndarray:
    return lo * (1.0 - t) + hi * t


def _unpack_quats(rot: np.ndarray) -> np.ndarray:
    """[N, 4] float64 wxyz from the packed rotations: the smallest three components (10 bits
    each, scaled by sqrt 2) and a 2-bit index of the largest, in w x y z order."""
    norm = math.sqrt(2.0)
    abc = np.stack([(_unorm(rot, s, 10) - 0.5) * norm for s in (20, 10, 0)], axis=1)
    largest = np.sqrt(np.maximum(0.0, 1.0 - (abc * abc).sum(axis=1)))
    which = (rot >> np.uint32(30)).astype(np.int64)
    quats = np.empty((len(rot), 4), dtype=np.float64)
    for w in range(4):
        sel = which == w
        others = [i for i in range(4) if i != w]
        quats[np.ix_(sel, others)] = abc[sel]
        quats[sel, w] = largest[sel]
    return quats


def _read_sh(path: Path, elements: dict, n: int, require) -> np.ndarray:
    """[N, K-1, 3] float64 higher-order SH of the optional ``sh`` element (8-bit, in [-4, 4]);
    [N, 0, 3] without one (gsplat's exporter writes a property-less ``sh`` element for degree 0)."""
    sh_props = elements["sh"].properties if "sh" in elements else ()
    if not sh_props:
        return np.zeros((n, 0, 3), dtype=np.float64)
    sh = elements["sh"].data
    names = [f"f_rest_{i}" for i in range(len(sh_props))]
    m = len(names)
    if m not in _SH_COUNTS:
        raise PlyFormatError(path, f"sh element has {m} properties; expected 9, 24 or 45 (SH degree 1..3)")
    require(sh, "sh", names)
    if len(sh) != n:
        raise PlyFormatError(path, f"sh element has {len(sh)} rows, expected {n} (one per vertex)")
    q = np.stack([np.asarray(sh[name]).astype(np.float64) for name in names], axis=1)  # [N, M]
    t = np.where(q <= 0, 0.0, np.where(q >= 255, 1.0, (q + 0.5) / 256.0))
    return ((t - 0.5) * 8.0).reshape(n, 3, m // 3).transpose(0, 2, 1)


def read_compressed_ply(path: PathLike) -> Gaussians:
    """Decode a PlayCanvas/SuperSplat compressed .ply (see the module docstring) to ``Gaussians``.

    Returns:
        ``Gaussians`` with float32 CPU tensors: means [N,3], quats [N,4] (wxyz, unit length up to
        the 10-bit quantisation), log_scales [N,3], opacity_logits [N] (finite), sh0 [N,1,3],
        shN [N,K-1,3] (K-1 = 0 without an ``sh`` element), sigma_d None.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        PlyFormatError: not parseable, no ``chunk``/``vertex`` element, a required property
            missing, a chunk count other than ceil(N/256), an ``sh`` element with a row count
            other than N or an f_rest count that is no SH degree, or non-finite chunk bounds.
    """
    path = Path(path)
    ply = open_ply(path)

    elements = {el.name: el for el in ply.elements}
    for name in ("chunk", "vertex"):
        if name not in elements:
            raise PlyFormatError(path, f"not a compressed .ply: no {name!r} element "
                                       f"(elements: {', '.join(elements) or 'none'})")
    chunk, vertex = elements["chunk"].data, elements["vertex"].data

    def require(data: np.ndarray, element: str, names: list[str]) -> None:
        have = set(data.dtype.names or ())
        missing = [n for n in names if n not in have]
        if missing:
            raise PlyFormatError(path, f"{element} element lacks propert{'y' if len(missing) == 1 else 'ies'} "
                                       f"{', '.join(missing)}")

    require(chunk, "chunk", _CHUNK_REQUIRED)
    require(vertex, "vertex", _VERTEX_REQUIRED)
    n = len(vertex)
    n_chunks = -(-n // CHUNK_SIZE)
    if len(chunk) != n_chunks:
        raise PlyFormatError(path, f"chunk element has {len(chunk)} rows, expected ceil({n}/{CHUNK_SIZE}) = {n_chunks}")
    has_color = all(name in (chunk.dtype.names or ()) for name in _CHUNK_COLOR)

    def chunk_col(name: str) -> np.ndarray:  # per-splat float64 copy of a chunk column
        col = np.asarray(chunk[name], dtype=np.float64)
        if not np.isfinite(col).all():
            raise PlyFormatError(path, f"chunk property {name} has non-finite values")
        return np.repeat(col, CHUNK_SIZE)[:n]

    def packed(name: str) -> np.ndarray:
        col = np.asarray(vertex[name])
        if col.dtype.kind not in "iu" or col.dtype.itemsize > 8:
            raise PlyFormatError(path, f"vertex property {name} must be an integer type, got {col.dtype}")
        return col.astype(np.uint32)

    pos, rot, scl, col = (packed(k) for k in _VERTEX_REQUIRED)

    # positions and log scales: 11-10-11 unorm, lerped between the chunk bounds
    means = np.empty((n, 3), dtype=np.float64)
    log_scales = np.empty((n, 3), dtype=np.float64)
    for j, (shift, bits, axis) in enumerate(((21, 11, "x"), (11, 10, "y"), (0, 11, "z"))):
        means[:, j] = _lerp(chunk_col(f"min_{axis}"), chunk_col(f"max_{axis}"), _unorm(pos, shift, bits))
        log_scales[:, j] = _lerp(chunk_col(f"min_scale_{axis}"), chunk_col(f"max_scale_{axis}"),
                                 _unorm(scl, shift, bits))

    quats = _unpack_quats(rot)

    # colour (SH DC) and opacity
    rgb = np.stack([_unorm(col, s, 8) for s in (24, 16, 8)], axis=1)
    if has_color:
        for j, c in enumerate("rgb"):
            rgb[:, j] = _lerp(chunk_col(f"min_{c}"), chunk_col(f"max_{c}"), rgb[:, j])
    sh0 = ((rgb - 0.5) / SH_C0).reshape(n, 1, 3)
    alpha = np.clip(_unorm(col, 0, 8), _ALPHA_EPS, 1.0 - _ALPHA_EPS)
    opacity = -np.log(1.0 / alpha - 1.0)

    shN = _read_sh(path, elements, n, require)

    def t32(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return Gaussians(
        means=t32(means),
        quats=t32(quats),
        log_scales=t32(log_scales),
        opacity_logits=t32(opacity),
        sh0=t32(sh0),
        shN=t32(shN),
    )
