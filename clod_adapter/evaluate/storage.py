"""Storage of a model, counted in the bytes of the file it is written as.

:func:`ply_bytes` is the size of the .ply :func:`clod_adapter.io.ply.write_ply` writes (what
"storage" means for a 3DGS checkpoint on disk), computed from the layout without writing the
file: the header that ``write_ply`` writes (built by plyfile from the same vertex dtype and
comments, :func:`clod_adapter.io.ply.ply_vertex_dtype` / :func:`~clod_adapter.io.ply.ply_comments`)
plus N rows of the packed vertex stride.
"""
from __future__ import annotations

import numpy as np
import plyfile

from ..gaussians import Gaussians
from ..io.ply import ply_comments, ply_vertex_dtype, tier_chain_of, tier_element

__all__ = ["ply_bytes", "ply_row_bytes"]


def ply_row_bytes(gaussians: Gaussians, *, with_normals: bool = True) -> int:
    """Bytes of one vertex row of the .ply :func:`~clod_adapter.io.ply.write_ply` writes for
    ``gaussians`` (packed, no padding): 4 per float32 property (``(62 + 3) x 4 = 248`` for an
    INRIA SH-degree-3 model with normals), plus ``sigma_d`` and gains when present, plus each
    ``extra`` property's own size.

    Raises:
        ValueError: an ``extra`` name is also a property of the layout (as ``write_ply``).
    """
    return int(ply_vertex_dtype(gaussians, with_normals=with_normals).itemsize)


def ply_bytes(gaussians: Gaussians, *, with_normals: bool = True) -> int:
    """The exact size in bytes of the .ply :func:`clod_adapter.io.ply.write_ply` writes for
    ``gaussians`` (same ``with_normals``): ``len(header) + 1`` (plyfile ends the header with a
    newline) ``+ N x`` :func:`ply_row_bytes`.

    Computed, not written: the header is the one plyfile builds for a ``vertex`` element of
    ``write_ply``'s dtype, count N and comments (the ``clod_lod`` line of an adapted model), so
    it is byte-for-byte the header ``write_ply`` writes; no data is allocated.

    Args:
        gaussians: the model (N Gaussians; ``sigma_d``, level gains, ``extra`` and the parent
            tier's element counted when present, as ``write_ply`` writes them).
        with_normals: count the (zero) ``nx ny nz`` properties, as ``write_ply``'s default.

    Returns:
        the file size in bytes.

    Raises:
        ValueError: an ``extra`` name is also a property of the layout (as ``write_ply``).
    """
    models = [(tier_element(k) if k else "vertex", g) for k, g in enumerate(tier_chain_of(gaussians))]
    elements, rows = [], 0
    for name, g in models:  # the parent tier is a second element of the vertex layout
        dtype = ply_vertex_dtype(g, with_normals=with_normals)
        props = plyfile.PlyElement.describe(np.empty(0, dtype=dtype), name).properties
        elements.append(plyfile.PlyElement(name, props, len(g)))
        rows += len(g) * int(dtype.itemsize)
    header = plyfile.PlyData(elements, text=False, byte_order="<", comments=ply_comments(gaussians)).header
    return len(header.encode("ascii")) + 1 + rows
