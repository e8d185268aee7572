"""clod_adapter.evaluate.storage.ply_bytes: the exact size of the .ply write_ply writes, computed without
writing it (plain model, adapted model with sigma_d, level gains and LoD settings, extra
properties of several types, no normals, an empty model)."""
from __future__ import annotations

import os

import pytest
import torch

from clod_adapter.gaussians import GAIN_NAMES
from clod_adapter.io.ply import write_ply
from clod_adapter.lod_settings import LodSettings
from clod_adapter.evaluate.storage import ply_bytes, ply_row_bytes
from clod_adapter.io.synthetic import make_ground_truth


def _plain(n=300):
    return make_ground_truth(n, seed=3)


def _adapted(n=300):
    g = _plain(n)
    gen = torch.Generator().manual_seed(5)
    gains = {"opacity_logit_gain": torch.randn(n, generator=gen), "log_scale_gain": torch.randn(n, generator=gen),
             "sh0_gain": torch.randn(n, 1, 3, generator=gen)}
    assert set(gains) == set(GAIN_NAMES)
    from dataclasses import replace

    return replace(g.with_sigma_d(torch.rand(n, generator=gen)), lod=LodSettings(max_sv=7.5, fade="window"),
                   **gains)


def _with_extra(n=300):
    from dataclasses import replace

    g = _plain(n)
    return replace(g, extra={"masks_0": torch.rand(n), "masks_1": torch.arange(n, dtype=torch.uint8),
                             "label": torch.arange(n, dtype=torch.int32), "w": torch.rand(n, dtype=torch.float64)})


@pytest.mark.parametrize("make", [_plain, _adapted, _with_extra], ids=["plain", "adapted", "extra"])
@pytest.mark.parametrize("with_normals", [True, False])
def test_ply_bytes_equals_written_size(tmp_path, make, with_normals):
    g = make()
    path = write_ply(tmp_path / "m.ply", g, with_normals=with_normals)
    assert ply_bytes(g, with_normals=with_normals) == os.path.getsize(path)


def test_ply_bytes_adapted_counts_sigma_d_gains_and_comment(tmp_path):
    plain, adapted = _plain(), _adapted()
    # sigma_d + opacity_gain + scale_gain + f_dc_gain_0..2: 6 float32 per row
    assert ply_row_bytes(adapted) - ply_row_bytes(plain) == 6 * 4
    # ... and the header grows by those 6 property lines and the clod_lod comment
    assert ply_bytes(adapted) - ply_bytes(plain) > 6 * 4 * len(plain)
    assert ply_row_bytes(plain) == (3 + 3 + 3 + 9 + 1 + 3 + 4) * 4  # SH degree 1, with normals


def test_ply_bytes_extra_row_stride():
    g = _with_extra()
    assert ply_row_bytes(g) == ply_row_bytes(_plain()) + 4 + 1 + 4 + 8  # packed, no padding


@pytest.mark.parametrize("n", [0, 1, 9, 10, 100000])
def test_ply_bytes_count_digits(tmp_path, n):
    """The header holds N in decimal: sizes stay exact across digit counts (and for N = 0)."""
    g = make_ground_truth(max(n, 1), seed=1).subset(torch.arange(n))
    path = write_ply(tmp_path / "m.ply", g)
    assert ply_bytes(g) == os.path.getsize(path)


def test_ply_bytes_extra_clash_raises():
    from dataclasses import replace

    g = _plain(10)
    with pytest.raises(ValueError, match="opacity"):
        ply_bytes(replace(g, extra={"opacity": torch.zeros(10)}))
