"""The nearest centres of a point set: a merge tree's parent candidates (:func:`clod_adapter.lod.tree.assign_parents`).

:func:`nearest` queries a k-d tree (``scipy.spatial.cKDTree``: ``O((N + M) log M)``, so a tree of
millions of Gaussians is built in seconds); :func:`nearest_torch` is its twin, every distance in
chunks (``O(N M)``), which the tests hold it to.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["nearest", "nearest_torch"]


def _check(points: Tensor, queries: Tensor, k: int) -> None:
    if points.ndim != 2 or points.shape[-1] != 3 or queries.ndim != 2 or queries.shape[-1] != 3:
        raise ValueError(f"nearest: points [M, 3] and queries [N, 3] expected, got {tuple(points.shape)} and "
                         f"{tuple(queries.shape)}")
    if not 1 <= k <= len(points):
        raise ValueError(f"nearest: k must be in [1, {len(points)}] (the points), got {k}")


def nearest(points: Tensor, queries: Tensor, k: int) -> Tensor:
    """The ``k`` points nearest (Euclidean) to each query, nearest first.

    Args:
        points: [M, 3] float (world units). queries: [N, 3] float. k: 1 <= k <= M.

    Returns:
        [N, k] int64 indices into ``points`` on the CPU, by increasing distance (ties in any order).

    Raises:
        ValueError: shapes other than [M, 3] / [N, 3], or ``k`` outside [1, M].
    """
    from scipy.spatial import cKDTree

    _check(points, queries, k)
    p = points.detach().double().cpu().numpy()
    q = queries.detach().double().cpu().numpy()
    _, idx = cKDTree(p).query(q, k=k, workers=max(1, torch.get_num_threads()))
    return torch.from_numpy(idx.reshape(len(q), k)).long()


def nearest_torch(points: Tensor, queries: Tensor, k: int, chunk: int = 2048) -> Tensor:
    """:func:`nearest`'s twin: every query's distance to every point (``torch.cdist`` without the
    matrix-product form, in float64), ``chunk`` queries at a time, the ``k`` smallest by
    ``topk``. Same arguments, result and errors."""
    _check(points, queries, k)
    p = points.detach().double().cpu()
    q = queries.detach().double().cpu()
    out = torch.empty(len(q), k, dtype=torch.long)
    for a in range(0, len(q), chunk):
        d = torch.cdist(q[a:a + chunk], p, compute_mode="donot_use_mm_for_euclid_dist")
        out[a:a + chunk] = d.topk(k, dim=1, largest=False).indices
    return out
