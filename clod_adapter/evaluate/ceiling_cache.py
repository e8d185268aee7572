"""The per-budget ceiling's fitted models kept on disk (:func:`clod_adapter.evaluate.comparison.ceiling_settings`'
``cache``): ``model=<share>.ply`` (the INRIA layout, :func:`clod_adapter.io.ply.write_ply`) with a
``model=<share>.json`` record beside it, read back only while the record matches what the model would
be fitted from."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

from ..gaussians import Gaussians
from ..io.atomic import atomic_write
from ..io.ply import read_ply, write_ply


def cached_ceiling(cache: Optional[Path], share: float, key: dict) -> Optional[tuple[Gaussians, dict]]:
    """The ceiling model at ``share`` kept in ``cache``, and its record.

    Args:
        cache: the folder (:func:`store_ceiling`'s), or None (nothing kept).
        share: the decimator share of the model (names the files).
        key: what the model would be fitted from (JSON values: the starts' counts, the input's
            count, the views' counts, the steps, the background); every key must equal the
            record's.

    Returns:
        ``(Gaussians, record dict)`` (float32 CPU tensors, as written), or None when nothing is
        kept for ``share``, its record differs from ``key`` or either file cannot be read.
    """
    if cache is None:
        return None
    ply, rec = Path(cache) / f"model={share:g}.ply", Path(cache) / f"model={share:g}.json"
    try:
        info = json.loads(rec.read_text())
        if {k: info.get(k) for k in key} != key:
            return None
        return read_ply(ply), info
    except (OSError, ValueError):
        return None


def store_ceiling(cache: Path, share: float, tuned: Gaussians, info: dict) -> None:
    """Write a fitted ceiling model and its record into ``cache``.

    Args:
        cache: the folder (made when missing).
        share: the decimator share (names the files ``model=<share>.ply`` / ``.json``).
        tuned: the fitted static model (N Gaussians, float32).
        info: its record (JSON values): :func:`cached_ceiling`'s key plus what to log on reuse.

    Both files are written atomically, the record last, so a model without its record is never
    read back.
    """
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    write_ply(cache / f"model={share:g}.ply", tuned)
    with atomic_write(cache / f"model={share:g}.json", "w") as f:
        f.write(json.dumps(info, indent=1) + "\n")
