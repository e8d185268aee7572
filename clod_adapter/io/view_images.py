"""The images of a list of views, decoded when first used and kept while they fit in a memory
budget: what the fine-tuning loop indexes instead of a list of every decoded image, so memory
does not grow with the number of views (hundreds of views at 1-2 Mpixel are 1-3 GB as float32).
"""
from __future__ import annotations

import os
from collections import OrderedDict
from typing import Sequence

import torch
from torch import Tensor

from ..errors import InputError

#: environment variable: the decoded-image budget in MB of :class:`ViewImages` (default 1024).
CACHE_MB_ENV = "CLOD_IMAGE_CACHE_MB"
DEFAULT_CACHE_MB = 1024.0


def cache_bytes(environ=os.environ) -> int:
    """The decoded-image budget in bytes (``CLOD_IMAGE_CACHE_MB``, default 1024 MB).

    Raises:
        InputError: the variable is not a number >= 0 (message names it).
    """
    raw = environ.get(CACHE_MB_ENV)
    if not raw:
        return int(DEFAULT_CACHE_MB * 2**20)
    try:
        v = float(raw)
    except ValueError:
        v = -1.0
    if not v >= 0:
        raise InputError(f"{CACHE_MB_ENV}={raw!r}: must be a number of MB >= 0")
    return int(v * 2**20)


class ViewImages(Sequence):
    """``images[i]``: the [H, W, 3] float32 image of ``cameras[i]`` in [0, 1] on ``device``,
    read with ``scene.load_image`` on first use and cached, least recently used first out, while
    the cached images total at most ``max_bytes`` (0: nothing is kept). The same
    tensor is returned while it is cached: callers must not modify it.

    Args:
        scene: a :class:`clod_adapter.io.scene.Scene` (or anything with ``load_image(camera)``).
        cameras: the views.
        device: where the images live.
        max_bytes: the budget (None: :func:`cache_bytes`).
    """

    def __init__(self, scene, cameras: Sequence, device="cpu", max_bytes=None) -> None:
        self.scene = scene
        self.cameras = list(cameras)
        self.device = torch.device(device)
        self.max_bytes = cache_bytes() if max_bytes is None else int(max_bytes)
        self._cache: "OrderedDict[int, Tensor]" = OrderedDict()
        self._bytes = 0
        self.loads = 0  # decodes so far (a test and benchmark hook)

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        i = range(len(self))[i]  # negative indices, IndexError
        hit = self._cache.get(i)
        if hit is not None:
            self._cache.move_to_end(i)
            return hit
        img = self.scene.load_image(self.cameras[i]).to(self.device)
        self.loads += 1
        size = img.numel() * img.element_size()
        while self._cache and self._bytes + size > self.max_bytes:
            _, old = self._cache.popitem(last=False)
            self._bytes -= old.numel() * old.element_size()
        if size <= self.max_bytes:
            self._cache[i] = img
            self._bytes += size
        return img

    @property
    def cached_bytes(self) -> int:
        """Bytes of decoded images held now."""
        return self._bytes
