"""Tests for clod_adapter.io.ply and clod_adapter.io.atomic."""
from __future__ import annotations

import os

import numpy as np
import plyfile
import pytest
import torch

from clod_adapter.gaussians import Gaussians
from clod_adapter.io.atomic import atomic_save, atomic_write
from clod_adapter.io.ply import PlyFormatError, ply_property_names, read_ply, write_ply
from conftest import shared_path

INRIA = ("fixtures", "plys", "inria_sh3_9080.ply")
GUITAR = ("fixtures", "plys", "guitar_sh0_nonormals.ply")
FERN = ("fern", "pretrained", "point_cloud", "iteration_7000", "point_cloud.ply")


def _random_gaussians(n: int, degree: int, sigma_d: bool, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(r(n, 3), r(n, 4), r(n, 3), r(n), r(n, 1, 3), r(n, k - 1, 3), r(n) if sigma_d else None)


def _assert_bit_equal(a: Gaussians, b: Gaussians) -> None:
    ta, tb = a.tensors(), b.tensors()
    assert ta.keys() == tb.keys()
    for k in ta:
        assert ta[k].dtype == tb[k].dtype == torch.float32, k
        assert ta[k].shape == tb[k].shape, k
        assert ta[k].numpy().tobytes() == tb[k].numpy().tobytes(), k


def _vertex_bytes(path) -> bytes:
    raw = open(path, "rb").read()
    return raw[raw.index(b"end_header\n") + len(b"end_header\n"):]


def _header(path) -> bytes:
    raw = open(path, "rb").read(20000)
    return raw[: raw.index(b"end_header\n")]


# --- atomic -------------------------------------------------------------------------------------
def test_atomic_write_replaces_and_cleans(tmp_path):
    p = tmp_path / "out.bin"
    with atomic_write(p) as f:
        f.write(b"abc")
    assert p.read_bytes() == b"abc"
    with pytest.raises(RuntimeError):
        with atomic_write(p) as f:
            f.write(b"partial")
            raise RuntimeError("boom")
    assert p.read_bytes() == b"abc"  # old content kept
    assert sorted(os.listdir(tmp_path)) == ["out.bin"]  # no temp left behind
    with atomic_write(tmp_path / "t.txt", "w") as f:
        f.write("hi")
    assert (tmp_path / "t.txt").read_text() == "hi"


def test_atomic_save(tmp_path):
    p = tmp_path / "x.npy"
    atomic_save(p, lambda tmp: np.save(tmp, np.arange(3)))
    assert np.array_equal(np.load(p), np.arange(3))

    def bad(tmp):
        open(tmp, "wb").write(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError):
        atomic_save(tmp_path / "y.npy", bad)
    assert sorted(os.listdir(tmp_path)) == ["x.npy"]
    with pytest.raises(FileNotFoundError):
        atomic_save(tmp_path / "nodir" / "z", lambda t: None)


def test_write_ply_failure_leaves_no_temp(tmp_path, monkeypatch):
    g = _random_gaussians(10, 1, False)
    out = tmp_path / "m.ply"
    write_ply(out, g)
    before = out.read_bytes()

    def fail(self, stream):
        stream.write(b"ply\n")
        raise RuntimeError("writer died")

    monkeypatch.setattr(plyfile.PlyData, "write", fail)
    with pytest.raises(RuntimeError):
        write_ply(out, _random_gaussians(5, 0, False))
    assert out.read_bytes() == before
    assert os.listdir(tmp_path) == ["m.ply"]


# --- real checkpoints ---------------------------------------------------------------------------
def test_read_inria_fixture_matches_plyfile():
    path = shared_path(*INRIA)
    g = read_ply(path)
    assert len(g) == 9080 and g.sh_degree == 3 and g.sigma_d is None
    assert g.shN.shape == (9080, 15, 3)
    v = plyfile.PlyData.read(str(path))["vertex"].data
    assert np.array_equal(g.means.numpy(), np.stack([v["x"], v["y"], v["z"]], 1))
    assert np.array_equal(g.quats.numpy(), np.stack([v[f"rot_{i}"] for i in range(4)], 1))
    assert np.array_equal(g.log_scales.numpy(), np.stack([v[f"scale_{i}"] for i in range(3)], 1))
    assert np.array_equal(g.opacity_logits.numpy(), v["opacity"])
    assert np.array_equal(g.sh0[:, 0].numpy(), np.stack([v[f"f_dc_{i}"] for i in range(3)], 1))
    # channel-major f_rest: f_rest_{c*15+k} == shN[:, k, c]
    for c in range(3):
        for k in (0, 7, 14):
            assert np.array_equal(g.shN[:, k, c].numpy(), v[f"f_rest_{c * 15 + k}"])
    for t in g.tensors().values():
        assert t.is_contiguous() and t.device.type == "cpu"


def test_inria_fixture_rewrites_byte_identical(tmp_path):
    path = shared_path(*INRIA)
    v = plyfile.PlyData.read(str(path))["vertex"].data
    assert all(np.all(v[k] == 0) for k in ("nx", "ny", "nz"))  # the fixture's normals are zeros
    out = write_ply(tmp_path / "o.ply", read_ply(path))
    assert _vertex_bytes(out) == _vertex_bytes(path)
    assert out.read_bytes() == path.read_bytes()  # header identical too (both written by plyfile)


def test_fern_checkpoint_round_trip(tmp_path):
    path = shared_path(*FERN)
    g = read_ply(path)
    assert len(g) == 39977 and g.sh_degree == 3
    out = write_ply(tmp_path / "fern.ply", g)
    assert _vertex_bytes(out) == _vertex_bytes(path)
    _assert_bit_equal(g, read_ply(out))


def test_guitar_degree0_no_normals(tmp_path):
    path = shared_path(*GUITAR)
    # The fixture stores 667 opacities of exactly 1.0 as logit +Inf.
    with pytest.raises(PlyFormatError, match=r"guitar_sh0_nonormals\.ply: non-finite values \(667 \+Inf\) in opacity"):
        read_ply(path)
    g = read_ply(path, allow_nonfinite=True)
    assert len(g) == 90854 and g.sh_degree == 0 and g.shN.shape == (90854, 0, 3)
    assert int(torch.isinf(g.opacity_logits).sum()) == 667
    v = plyfile.PlyData.read(str(path))["vertex"].data  # file order: ... opacity rot_* scale_*
    assert np.array_equal(g.quats.numpy(), np.stack([v[f"rot_{i}"] for i in range(4)], 1))
    assert np.array_equal(g.log_scales.numpy(), np.stack([v[f"scale_{i}"] for i in range(3)], 1))
    out = write_ply(tmp_path / "g.ply", g, with_normals=False)
    assert b"nx" not in _header(out)
    _assert_bit_equal(g, read_ply(out, allow_nonfinite=True))


# --- synthetic round trips ----------------------------------------------------------------------
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("sigma_d", [False, True])
def test_round_trip_bit_exact(tmp_path, degree, sigma_d):
    g = _random_gaussians(257, degree, sigma_d, seed=degree)
    out = write_ply(tmp_path / "m.ply", g)
    names = plyfile.PlyData.read(str(out))["vertex"].data.dtype.names
    assert list(names) == ply_property_names(degree, with_sigma_d=sigma_d)
    assert (names[-1] == "sigma_d") == sigma_d
    g2 = read_ply(out)
    _assert_bit_equal(g, g2)
    # write(read(write(g))) is byte-identical
    out2 = write_ply(tmp_path / "m2.ply", g2)
    assert out2.read_bytes() == out.read_bytes()


def test_round_trip_special_values_and_empty(tmp_path):
    g = _random_gaussians(4, 1, True)
    g.means[0, 0] = float("nan")
    g.sigma_d[1] = float("-inf")
    g.sh0[2, 0, 1] = -0.0
    out = write_ply(tmp_path / "m.ply", g)
    with pytest.raises(PlyFormatError, match="NaN.*-Inf|non-finite"):
        read_ply(out)
    _assert_bit_equal(g, read_ply(out, allow_nonfinite=True))
    e = _random_gaussians(0, 3, True)
    _assert_bit_equal(e, read_ply(write_ply(tmp_path / "e.ply", e)))


def test_write_converts_dtype_and_ignores_grad(tmp_path):
    g = _random_gaussians(8, 2, True)
    g64 = Gaussians(**{k: v.double().requires_grad_(True) for k, v in g.tensors().items()})
    _assert_bit_equal(g, read_ply(write_ply(tmp_path / "d.ply", g64)))


def test_ascii_and_big_endian(tmp_path):
    g = _random_gaussians(20, 1, True)
    src = write_ply(tmp_path / "le.ply", g)
    el = plyfile.PlyData.read(str(src))["vertex"]
    data = np.array(el.data)
    plyfile.PlyData([plyfile.PlyElement.describe(data.astype(data.dtype.newbyteorder(">")), "vertex")],
                    byte_order=">").write(str(tmp_path / "be.ply"))
    _assert_bit_equal(g, read_ply(tmp_path / "be.ply"))
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")], text=True).write(str(tmp_path / "a.ply"))
    ga = read_ply(tmp_path / "a.ply")
    for k, t in g.tensors().items():  # ASCII goes through decimal text: equal to float32 rounding
        torch.testing.assert_close(ga.tensors()[k], t, rtol=1e-6, atol=1e-6)
    # extra properties, reordered columns and a double-typed property are fine
    names = list(data.dtype.names)
    dt = [(n, "<f8" if n == "opacity" else "<f4") for n in names[::-1]] + [("red", "u1")]
    arr = np.zeros(len(data), dtype=dt)
    for n in names:
        arr[n] = data[n]
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "mix.ply"))
    _assert_bit_equal(g, read_ply(tmp_path / "mix.ply"))


# --- extra (unknown) per-Gaussian properties --------------------------------------------------------
def test_extra_properties_round_trip(tmp_path):
    g = _random_gaussians(50, 2, False, seed=3)
    src = write_ply(tmp_path / "plain.ply", g)
    data = np.array(plyfile.PlyData.read(str(src))["vertex"].data)
    names = list(data.dtype.names)
    i = names.index("opacity") + 1  # MaskGaussian's save_ply puts masks_0/1 right after opacity
    rng = np.random.default_rng(0)
    extra = {"masks_0": ("<f4", rng.normal(size=50)), "masks_1": ("<f4", rng.normal(size=50)),
             "red": ("u1", rng.integers(0, 256, 50)), "weight": ("<f8", rng.normal(size=50)),
             "label": ("<u2", rng.integers(0, 65536, 50))}
    order = names[:i] + ["masks_0", "masks_1"] + names[i:] + ["red", "weight", "label"]
    arr = np.empty(50, dtype=[(k, extra[k][0] if k in extra else "<f4") for k in order])
    for k in order:
        arr[k] = extra[k][1] if k in extra else data[k]
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "mg.ply"))

    r = read_ply(tmp_path / "mg.ply")
    _assert_bit_equal(g, r)  # the model itself is untouched by the extras
    assert list(r.extra) == ["masks_0", "masks_1", "red", "weight", "label"]  # file order
    assert [r.extra[k].dtype for k in r.extra] == [torch.float32, torch.float32, torch.uint8, torch.float64,
                                                   torch.uint16]
    assert "masks_0" not in r.tensors()  # not parameters
    out = write_ply(tmp_path / "out.ply", r)
    v = plyfile.PlyData.read(str(out))["vertex"]
    assert [p.name for p in v.properties] == ply_property_names(2) + list(r.extra)  # known layout, then extras
    for k in extra:
        assert v.data[k].dtype == arr[k].dtype.newbyteorder("<") and np.array_equal(v.data[k], arr[k]), k
    rr = read_ply(out)
    _assert_bit_equal(g, rr)
    assert all(rr.extra[k].numpy().tobytes() == r.extra[k].numpy().tobytes() for k in extra)
    # big endian and ASCII files give the same extras
    plyfile.PlyData([plyfile.PlyElement.describe(arr.astype(arr.dtype.newbyteorder(">")), "vertex")],
                    byte_order=">").write(str(tmp_path / "be.ply"))
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], text=True).write(str(tmp_path / "a.ply"))
    for f in ("be.ply", "a.ply"):
        e = read_ply(tmp_path / f).extra
        assert list(e) == list(r.extra) and all(torch.equal(e[k], r.extra[k]) for k in e), f
    # a CLoD extended file (sigma_d, gains) keeps them as known properties, the extras after
    ext = Gaussians(**r.tensors(), sigma_d=torch.ones(50), opacity_logit_gain=torch.zeros(50), extra=r.extra)
    names = [p.name for p in plyfile.PlyData.read(str(write_ply(tmp_path / "ext.ply", ext)))["vertex"].properties]
    assert names == ply_property_names(2, with_sigma_d=True) + ["opacity_gain"] + list(r.extra)
    assert list(read_ply(tmp_path / "ext.ply").extra) == list(r.extra)
    with pytest.raises(ValueError, match="opacity"):
        write_ply(tmp_path / "clash.ply", Gaussians(**g.tensors(), extra={"opacity": torch.zeros(50)}))


def test_gaussians_carry_extra():
    g = _random_gaussians(6, 1, True, seed=4)
    m = torch.arange(6, dtype=torch.float32)
    g = Gaussians(**g.tensors(), extra={"masks_0": m, "id": torch.arange(6, dtype=torch.int16)})
    assert set(g.tensors()) == {"means", "quats", "log_scales", "opacity_logits", "sh0", "shN", "sigma_d"}
    keep = torch.tensor([True, False, True, True, False, False])
    for s in (g.subset(keep), g.subset(torch.tensor([0, 2, 3]))):
        assert torch.equal(s.extra["masks_0"], torch.tensor([0.0, 2.0, 3.0]))
        assert s.extra["id"].dtype == torch.int16 and torch.equal(s.means, g.means[keep])
    c = g.clone()
    c.extra["masks_0"][0] = 99.0
    assert m[0] == 0.0  # a copy
    for other in (g.detach(), g.to("cpu"), g.with_sigma_d(None), g.at_level(0.5)):
        assert torch.equal(other.extra["masks_0"], m)
    with pytest.raises(ValueError, match=r"extra\['masks_0'\] has shape \(5,\)"):
        Gaussians(**g.tensors(), extra={"masks_0": torch.zeros(5)})


# --- errors -------------------------------------------------------------------------------------
def _write_fields(path, names, n=5, element="vertex"):
    arr = np.zeros(n, dtype=[(k, "<f4") for k in names])
    plyfile.PlyData([plyfile.PlyElement.describe(arr, element)]).write(str(path))
    return path


def test_f_rest_count_mismatch(tmp_path):
    names = [n for n in ply_property_names(1) if n != "f_rest_8"]  # 8 f_rest
    p = _write_fields(tmp_path / "bad.ply", names)
    with pytest.raises(PlyFormatError, match=r"bad\.ply: 8 f_rest_\* properties match no SH degree"):
        read_ply(p)


def test_missing_property(tmp_path):
    p = _write_fields(tmp_path / "noscale.ply", [n for n in ply_property_names(0) if n != "scale_1"])
    with pytest.raises(PlyFormatError, match=r"noscale\.ply: .*lacks required property scale_1"):
        read_ply(p)


def test_missing_vertex_element(tmp_path):
    p = _write_fields(tmp_path / "face.ply", ply_property_names(0), element="splat")
    with pytest.raises(PlyFormatError, match=r"face\.ply: no 'vertex' element"):
        read_ply(p)


def test_truncated_empty_and_garbage(tmp_path):
    g = _random_gaussians(100, 3, False)
    full = write_ply(tmp_path / "full.ply", g).read_bytes()
    (tmp_path / "trunc.ply").write_bytes(full[: len(full) - 1000])
    with pytest.raises(PlyFormatError, match=r"trunc\.ply: .*truncated"):
        read_ply(tmp_path / "trunc.ply")
    (tmp_path / "hdr.ply").write_bytes(full[:300])
    with pytest.raises(PlyFormatError, match=r"hdr\.ply"):
        read_ply(tmp_path / "hdr.ply")
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(PlyFormatError, match=r"empty\.ply: file is empty"):
        read_ply(tmp_path / "empty.ply")
    (tmp_path / "junk.ply").write_bytes(b"\x00\x01garbage" * 10)
    with pytest.raises(PlyFormatError, match=r"junk\.ply: not a valid PLY"):
        read_ply(tmp_path / "junk.ply")
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        read_ply(tmp_path / "nope.ply")


def test_lod_comment_round_trip_and_legacy():
    from clod_adapter.io.ply import lod_comment, parse_lod_comment
    from clod_adapter.lod_settings import LodSettings

    st = LodSettings(max_sv=7.5, fade="window", level_max=2.5)
    assert parse_lod_comment([lod_comment(st)]) == st
    # a file written before level_max existed was trained with the level held at 1: drawn so
    legacy = "clod_lod max_sv=5.0 tau=0.005 eps=1e-08 fade=window fade_width=0.5"
    assert parse_lod_comment([legacy]).level_max == 1.0
    with pytest.raises(PlyFormatError, match="level_max"):
        parse_lod_comment([legacy + " level_max=0.5"], "m.ply")
