"""clod_adapter.io.load and the readers behind it: PlayCanvas/SuperSplat
compressed .ply, gsplat simple_trainer checkpoints, MaskGaussian .ply masks and the
``load_model`` dispatcher."""
from __future__ import annotations

import fractions
import math
import warnings

import numpy as np
import plyfile
import pytest
import torch

from clod_adapter.gaussians import SH_C0, Gaussians
from clod_adapter.io.compressed_ply import CHUNK_SIZE, is_compressed_ply, read_compressed_ply
from clod_adapter.io.gsplat_ckpt import read_gsplat_ckpt
from clod_adapter.io.load import load_model
from clod_adapter.io.ply import PlyFormatError, ply_property_names, read_ply, write_ply
from conftest import shared_path

COMPRESSED = ("fixtures", "plys", "guitar.compressed.ply")
DECOMPRESSED = ("fixtures", "plys", "guitar_sh0_nonormals.ply")


def _random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(r(n, 3), r(n, 4), r(n, 3) - 3, r(n) * 2, r(n, 1, 3), r(n, k - 1, 3) * 0.5)


def _quat_err(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[N] max-abs difference of normalised quaternions, up to sign."""
    a = a / a.norm(dim=1, keepdim=True)
    b = b / b.norm(dim=1, keepdim=True)
    return torch.minimum((a - b).abs().amax(1), (a + b).abs().amax(1))


# --- a test-only encoder, following splat-transform src/lib/writers/compressed-chunk.ts ----------
def _write_compressed(path, g: Gaussians, *, chunk_colors: bool = True) -> None:
    n = len(g)
    nc = -(-n // CHUNK_SIZE)
    means = g.means.double().numpy()
    logs = g.log_scales.double().numpy()
    rgb = g.sh0.reshape(n, 3).double().numpy() * SH_C0 + 0.5
    alpha = g.opacities.double().numpy()
    q = torch.nn.functional.normalize(g.quats.double(), dim=1).numpy()

    def unorm(v, bits):
        t = (1 << bits) - 1
        return np.clip(np.floor(v * t + 0.5), 0, t).astype(np.uint32)

    def norm01(x, lo, hi):
        d = hi - lo
        return np.where(d < 1e-5, 0.0, np.clip((x - lo) / np.where(d < 1e-5, 1, d), 0, 1))

    chunk_names = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y",
                   "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
    if chunk_colors:
        chunk_names += ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
    chunk = np.zeros(nc, dtype=[(c, "<f4") for c in chunk_names])
    vert = np.zeros(n, dtype=[(c, "<u4") for c in ("packed_position", "packed_rotation", "packed_scale",
                                                     "packed_color")])
    for c in range(nc):
        s = slice(c * CHUNK_SIZE, min(n, (c + 1) * CHUNK_SIZE))
        pm, pM = means[s].min(0).astype(np.float32), means[s].max(0).astype(np.float32)
        sm, sM = logs[s].min(0).astype(np.float32), logs[s].max(0).astype(np.float32)
        cm, cM = rgb[s].min(0).astype(np.float32), rgb[s].max(0).astype(np.float32)
        for j, a in enumerate("xyz"):
            chunk[f"min_{a}"][c], chunk[f"max_{a}"][c] = pm[j], pM[j]
            chunk[f"min_scale_{a}"][c], chunk[f"max_scale_{a}"][c] = sm[j], sM[j]
        p = norm01(means[s], pm, pM)
        sc = norm01(logs[s], sm, sM)
        vert["packed_position"][s] = (unorm(p[:, 0], 11) << 21) | (unorm(p[:, 1], 10) << 11) | unorm(p[:, 2], 11)
        vert["packed_scale"][s] = (unorm(sc[:, 0], 11) << 21) | (unorm(sc[:, 1], 10) << 11) | unorm(sc[:, 2], 11)
        if chunk_colors:
            for j, a in enumerate("rgb"):
                chunk[f"min_{a}"][c], chunk[f"max_{a}"][c] = cm[j], cM[j]
            col = norm01(rgb[s], cm, cM)
        else:
            col = np.clip(rgb[s], 0, 1)
        vert["packed_color"][s] = ((unorm(col[:, 0], 8) << 24) | (unorm(col[:, 1], 8) << 16)
                                   | (unorm(col[:, 2], 8) << 8) | unorm(alpha[s], 8))
    # rotation: wxyz, largest |component| made positive, the other three at 10 bits
    largest = np.abs(q).argmax(1)
    q = q * np.where(q[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    packed = largest.astype(np.uint32)
    rest = np.stack([np.delete(q[k], largest[k]) for k in range(n)])
    for j in range(3):
        packed = (packed << np.uint32(10)) | unorm(rest[:, j] * (math.sqrt(2) * 0.5) + 0.5, 10)
    vert["packed_rotation"] = packed
    elements = [plyfile.PlyElement.describe(chunk, "chunk"), plyfile.PlyElement.describe(vert, "vertex")]
    km1 = g.shN.shape[1]
    if km1:
        rest_cm = g.shN.double().numpy().transpose(0, 2, 1).reshape(n, 3 * km1)  # INRIA channel-major
        sh = np.zeros(n, dtype=[(f"f_rest_{i}", "u1") for i in range(3 * km1)])
        qv = np.clip(np.trunc((rest_cm / 8 + 0.5) * 256), 0, 255).astype(np.uint8)
        for i in range(3 * km1):
            sh[f"f_rest_{i}"] = qv[:, i]
        elements.append(plyfile.PlyElement.describe(sh, "sh"))
    plyfile.PlyData(elements, text=False, byte_order="<").write(str(path))


# --- compressed .ply: the real fixture ----------------------------------------------------------
def test_compressed_guitar_matches_splat_transform_decompression():
    comp, ref_path = shared_path(*COMPRESSED), shared_path(*DECOMPRESSED)
    assert is_compressed_ply(comp) and not is_compressed_ply(ref_path)
    g = read_compressed_ply(comp)
    ref = read_ply(ref_path, allow_nonfinite=True)  # splat-transform writes +inf logits for alpha 255
    assert len(g) == len(ref) == 90_854
    assert g.sh_degree == 0 and g.sigma_d is None
    for t in g.tensors().values():
        assert t.dtype == torch.float32 and torch.isfinite(t).all()

    chunk = plyfile.PlyData.read(str(comp))["chunk"].data
    per = lambda name: np.repeat(np.asarray(chunk[name], np.float64), CHUNK_SIZE)[: len(g)]  # noqa: E731
    errs = {}
    # means: within one quantisation step (chunk extent / 2047 for x, z; / 1023 for y)
    for j, (a, bits) in enumerate(zip("xyz", (11, 10, 11))):
        step = (per(f"max_{a}") - per(f"min_{a}")) / ((1 << bits) - 1)
        e = (g.means[:, j].double() - ref.means[:, j].double()).abs().numpy()
        assert (e <= step + 1e-6).all(), a
        errs[f"mean_{a}"] = e.max()
    for j, a in enumerate("xyz"):
        step = (per(f"max_scale_{a}") - per(f"min_scale_{a}")) / 1023
        e = (g.log_scales[:, j].double() - ref.log_scales[:, j].double()).abs().numpy()
        assert (e <= step + 1e-5).all(), a
        errs[f"log_scale_{a}"] = e.max()
    for j, a in enumerate("rgb"):
        step = (per(f"max_{a}") - per(f"min_{a}")) / 255
        e = ((g.sh0[:, 0, j].double() - ref.sh0[:, 0, j].double()) * SH_C0).abs().numpy()
        assert (e <= step + 1e-6).all(), a
        errs[f"color_{a}"] = e.max()
    e_op = (g.opacities.double() - ref.opacities.double()).abs()
    assert e_op.max() <= 1 / 255
    errs["opacity"] = e_op.max().item()
    e_q = _quat_err(g.quats, ref.quats)
    assert e_q.max() <= 1e-2
    errs["quat"] = e_q.max().item()
    finite = torch.isfinite(ref.opacity_logits)
    assert (g.opacity_logits[~finite] > 13).all()  # alpha 255: clamped, finite
    print("max errors vs splat-transform:", {k: float(v) for k, v in errs.items()})


# --- compressed .ply: synthetic, through an independent encoder ------------------------------------
@pytest.mark.parametrize("degree,chunk_colors", [(1, True), (3, False), (0, True)])
def test_compressed_synthetic_round_trip(tmp_path, degree, chunk_colors):
    n = 2 * CHUNK_SIZE + 37  # last chunk partial
    g = _random_gaussians(n, degree, seed=degree)
    g.sh0.clamp_(-1.7, 1.7)  # colour within [0, 1] for the no-chunk-colour variant
    g.shN.clamp_(-3.9, 3.9)
    p = tmp_path / "c.ply"
    _write_compressed(p, g, chunk_colors=chunk_colors)
    assert is_compressed_ply(p)
    d = read_compressed_ply(p)
    assert len(d) == n and d.sh_degree == degree
    for c in range(-(-n // CHUNK_SIZE)):
        s = slice(c * CHUNK_SIZE, min(n, (c + 1) * CHUNK_SIZE))
        ext = g.means[s].amax(0) - g.means[s].amin(0)
        half = ext / torch.tensor([2047.0, 1023.0, 2047.0]) / 2
        assert ((d.means[s] - g.means[s]).abs() <= half + 1e-5).all()
        sext = g.log_scales[s].amax(0) - g.log_scales[s].amin(0)
        assert ((d.log_scales[s] - g.log_scales[s]).abs() <= sext / 1023 / 2 + 1e-5).all()
    col_err = ((d.sh0 - g.sh0) * SH_C0).abs().max()
    assert col_err <= (1 / 255 if chunk_colors else 0.5 / 255) + 1e-6
    assert (d.opacities - g.opacities).abs().max() <= 0.5 / 255 + 1e-6
    assert _quat_err(d.quats, g.quats).max() <= 2e-3
    if degree:
        assert (d.shN - g.shN).abs().max() <= 4 / 256 + 1e-6  # half a bin of 8/256


def test_compressed_empty_sh_element_is_degree_0(tmp_path):
    # gsplat's export_splats(format="ply_compressed") always writes "element sh N", with no
    # properties for degree 0
    g = _random_gaussians(300, 0)
    p = tmp_path / "gsplat.ply"
    _write_compressed(p, g)
    raw = p.read_bytes()
    p.write_bytes(raw.replace(b"end_header\n", f"element sh {len(g)}\nend_header\n".encode(), 1))
    assert is_compressed_ply(p)
    d = read_compressed_ply(p)
    assert len(d) == len(g) and d.sh_degree == 0
    assert _quat_err(d.quats, g.quats).max() <= 2e-3


def test_compressed_bad_files(tmp_path):
    g = _random_gaussians(300, 0)
    good = tmp_path / "good.ply"
    _write_compressed(good, g)
    ply = plyfile.PlyData.read(str(good))
    chunk, vert = ply["chunk"].data, ply["vertex"].data

    bad = tmp_path / "chunks.ply"  # one chunk too few
    plyfile.PlyData([plyfile.PlyElement.describe(chunk[:1], "chunk"),
                     plyfile.PlyElement.describe(vert, "vertex")]).write(str(bad))
    with pytest.raises(PlyFormatError, match="chunks.ply.*chunk element has 1 rows"):
        read_compressed_ply(bad)

    from numpy.lib import recfunctions as rfn
    bad = tmp_path / "norot.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(chunk, "chunk"),
                     plyfile.PlyElement.describe(rfn.drop_fields(vert, "packed_rotation"), "vertex")]).write(str(bad))
    with pytest.raises(PlyFormatError, match="norot.ply.*packed_rotation"):
        read_compressed_ply(bad)

    raw = good.read_bytes()
    bad = tmp_path / "negative.ply"
    bad.write_bytes(raw.replace(b"element vertex 300", b"element vertex -300", 1))
    with pytest.raises(PlyFormatError, match="negative.ply.*negative count"):
        read_compressed_ply(bad)
    bad = tmp_path / "shrows.ply"  # an sh element with the wrong row count
    bad.write_bytes(raw.replace(b"end_header\n", b"element sh 7\n" + b"".join(
        b"property uchar f_rest_%d\n" % i for i in range(9)) + b"end_header\n", 1) + bytes(63))
    with pytest.raises(PlyFormatError, match="shrows.ply.*sh element has 7 rows"):
        read_compressed_ply(bad)
    bad = tmp_path / "trunc.ply"
    bad.write_bytes(raw[: len(raw) - 100])
    with pytest.raises(PlyFormatError, match="trunc.ply"):
        read_compressed_ply(bad)
    bad = tmp_path / "vanilla.ply"
    write_ply(bad, g)
    assert not is_compressed_ply(bad)
    with pytest.raises(PlyFormatError, match="vanilla.ply.*no 'chunk' element"):
        read_compressed_ply(bad)
    (tmp_path / "junk.ply").write_bytes(b"\x00garbage")
    assert not is_compressed_ply(tmp_path / "junk.ply")


# --- gsplat checkpoints -------------------------------------------------------------------------
def _gsplat_ckpt(g: Gaussians) -> dict:
    return {"step": 6999, "splats": {"means": g.means, "quats": g.quats, "scales": g.log_scales,
                                     "opacities": g.opacity_logits, "sh0": g.sh0, "shN": g.shN},
            "pose_adjust": {"embeds.weight": torch.zeros(4, 9)}}


@pytest.mark.parametrize("degree", [0, 3])
def test_gsplat_ckpt_round_trip(tmp_path, degree):
    g = _random_gaussians(257, degree, seed=3)
    p = tmp_path / "ckpt_6999_rank0.pt"
    torch.save(_gsplat_ckpt(g), p)
    r = read_gsplat_ckpt(p)
    assert r.sigma_d is None and r.sh_degree == degree
    for k, t in g.tensors().items():
        assert torch.equal(r.tensors()[k], t), k
    # the "means3d" spelling of early gsplat examples, and [N, 1] opacities
    ck = _gsplat_ckpt(g)
    ck["splats"]["means3d"] = ck["splats"].pop("means")
    ck["splats"]["opacities"] = g.opacity_logits[:, None]
    torch.save(ck, p)
    r = read_gsplat_ckpt(p)
    assert torch.equal(r.means, g.means) and torch.equal(r.opacity_logits, g.opacity_logits)
    assert torch.equal(load_model(p).shN, g.shN)  # dispatch by suffix


def test_gsplat_ckpt_appearance_variant(tmp_path):
    g = _random_gaussians(50, 0)
    ck = _gsplat_ckpt(g)
    del ck["splats"]["sh0"], ck["splats"]["shN"]
    ck["splats"]["features"] = torch.randn(50, 32)
    ck["splats"]["colors"] = torch.randn(50, 3)
    p = tmp_path / "ckpt_app.pt"
    torch.save(ck, p)
    with pytest.raises(PlyFormatError, match="ckpt_app.pt.*appearance"):
        read_gsplat_ckpt(p)
    r = read_gsplat_ckpt(p, allow_appearance=True)
    assert r.sh_degree == 0
    assert torch.allclose(r.sh0[:, 0] * SH_C0 + 0.5, torch.sigmoid(ck["splats"]["colors"]), atol=1e-6)


def test_gsplat_ckpt_bad_files(tmp_path):
    g = _random_gaussians(20, 1)
    cases = {}
    p = tmp_path / "noise.pt"
    p.write_bytes(np.random.default_rng(0).bytes(4096))
    cases[p] = "not a loadable torch checkpoint"
    p = tmp_path / "nosplats.pt"
    torch.save({"step": 1, "model": {}}, p)
    cases[p] = "no 'splats'"
    p = tmp_path / "noquats.pt"
    ck = _gsplat_ckpt(g)
    del ck["splats"]["quats"]
    torch.save(ck, p)
    cases[p] = "lacks 'quats'"
    p = tmp_path / "shape.pt"
    ck = _gsplat_ckpt(g)
    ck["splats"]["scales"] = torch.zeros(19, 3)
    torch.save(ck, p)
    cases[p] = "inconsistent splats"
    p = tmp_path / "nan.pt"
    ck = _gsplat_ckpt(g)
    ck["splats"]["means"] = g.means.clone()
    ck["splats"]["means"][3, 1] = float("nan")
    torch.save(ck, p)
    cases[p] = "non-finite"
    p = tmp_path / "object.pt"  # arbitrary pickled objects are refused (weights_only=True)
    torch.save({"splats": {"means": g.means}, "obj": fractions.Fraction(1, 3)}, p)
    cases[p] = "not a loadable torch checkpoint"
    p = tmp_path / "empty.pt"
    p.write_bytes(b"")
    cases[p] = "empty"
    for path, msg in cases.items():
        with pytest.raises(PlyFormatError, match=f"{path.name}.*{msg}"):
            read_gsplat_ckpt(path)
        with pytest.raises(PlyFormatError, match=path.name):
            load_model(path)
    with pytest.raises(FileNotFoundError):
        read_gsplat_ckpt(tmp_path / "missing.pt")


# --- load_model and MaskGaussian masks ----------------------------------------------------------
def _write_ply_with(path, g: Gaussians, extra: dict[str, np.ndarray]) -> None:
    """An INRIA-layout .ply (MaskGaussian ``save_ply`` order: masks after opacity)."""
    names = ply_property_names(g.sh_degree)
    cols = dict(zip(names, _columns(g)))
    order = names[: names.index("opacity") + 1] + list(extra) + names[names.index("opacity") + 1:]
    cols.update(extra)
    data = np.empty(len(g), dtype=[(k, "<f4") for k in order])
    for k in order:
        data[k] = cols[k]
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")]).write(str(path))


def _columns(g: Gaussians) -> list[np.ndarray]:
    n = len(g)
    flat = np.concatenate([g.means.numpy(), np.zeros((n, 3), np.float32), g.sh0.reshape(n, 3).numpy(),
                           g.shN.numpy().transpose(0, 2, 1).reshape(n, -1), g.opacity_logits.numpy()[:, None],
                           g.log_scales.numpy(), g.quats.numpy()], axis=1)
    return list(flat.T)


def test_load_model_dispatch(tmp_path):
    g = _random_gaussians(100, 2)
    p = write_ply(tmp_path / "point_cloud.ply", g)
    r = load_model(p)
    assert torch.equal(r.means, g.means) and torch.equal(r.shN, g.shN)
    c = tmp_path / "c.bin"  # compressed content, dispatched by header, not by name
    _write_compressed(c, g)
    assert torch.allclose(load_model(c).means, g.means, atol=1e-2)
    for name, data in {"model.npz": b"PK\x03\x04zzzz", "notes.txt": b"hello", "x.splat": b"\x00" * 64}.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(PlyFormatError, match=name):
            load_model(tmp_path / name)
    (tmp_path / "empty").write_bytes(b"")
    with pytest.raises(PlyFormatError, match="empty.*empty"):
        load_model(tmp_path / "empty")
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / "nope.ply")
    with pytest.raises(ValueError):
        load_model(p, masks="sometimes")


def test_load_model_compressed_fixture():
    g = load_model(shared_path(*COMPRESSED))
    assert len(g) == 90_854 and g.sh_degree == 0


def test_load_model_maskgaussian_masks(tmp_path):
    n = 64
    g = _random_gaussians(n, 1, seed=7)
    on = np.arange(n) % 3 != 0
    # hard one-hot masks_0/masks_1: keep masks_0 == 1
    p = tmp_path / "hard.ply"
    _write_ply_with(p, g, {"masks_0": on.astype(np.float32), "masks_1": (~on).astype(np.float32)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = load_model(p)
    assert len(r) == on.sum() and torch.equal(r.means, g.means[torch.from_numpy(on)])
    assert len(read_ply(p)) == n  # read_ply itself keeps every Gaussian (the masks go to extra)
    # soft scores (MaskGaussian's learned logits): argmax by default (tests/test_masks.py: the rest)
    s0 = np.where(on, 2.0, -1.0).astype(np.float32) + 0.25
    p = tmp_path / "soft.ply"
    _write_ply_with(p, g, {"masks_0": s0, "masks_1": np.full(n, 0.5, np.float32)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = load_model(p)
    assert torch.equal(r.quats, g.quats[torch.from_numpy(on)])
    assert torch.equal(load_model(p, masks="argmax").quats, r.quats)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(load_model(p, masks="ignore")) == n
    # a single hard "mask" property
    p = tmp_path / "single.ply"
    _write_ply_with(p, g, {"mask": on.astype(np.float32)})
    assert len(load_model(p)) == on.sum()
    # a mask that keeps nothing is an error, not an empty model
    p = tmp_path / "none.ply"
    _write_ply_with(p, g, {"mask": np.zeros(n, np.float32)})
    with pytest.raises(PlyFormatError, match="none.ply.*keeps no Gaussian"):
        load_model(p)
    assert len(load_model(p, masks="ignore")) == n
