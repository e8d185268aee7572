"""LPIPS-alex v0.1: properties on real fern images, an independent float64 numpy reference, and
weights-file handling. Tests that need the weights skip when ../shared/data is absent."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from clod_adapter.evaluate import lpips as L
from conftest import shared_path


@pytest.fixture(scope="module")
def weights():
    return shared_path("lpips", L.WEIGHTS_NAME)


@pytest.fixture(scope="module")
def model(weights):
    m = L.load_lpips(weights)
    assert m is not None, L.lpips_unavailable_reason()
    return m


def _fern(i: int, crop: bool = False) -> torch.Tensor:
    """fern images_2/image{i} as [372, 497, 3] float32 in [0, 1]; crop: its central 192x256."""
    p = shared_path("fern", "images_2", f"image{i:03d}.jpg")
    img = torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), dtype=np.float32) / 255)
    return img[90:282, 120:376].contiguous() if crop else img


def _box2x(img: torch.Tensor) -> torch.Tensor:
    """2x2 box average then nearest upsample (a light blur); crops H, W to even."""
    h, w = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    x = img[:h, :w].permute(2, 0, 1)[None]
    return F.interpolate(F.avg_pool2d(x, 2), scale_factor=2, mode="nearest")[0].permute(1, 2, 0).contiguous()


# ---------------------------------------------------------------- independent reference (numpy)

def _np_conv(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int, pad: int) -> np.ndarray:
    """Cross-correlation of x [C, H, W] with w [O, C, k, k] (+ b), via strided windows + tensordot."""
    k = w.shape[-1]
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    win = np.lib.stride_tricks.sliding_window_view(xp, (k, k), axis=(1, 2))[:, ::stride, ::stride]
    out = np.tensordot(win, w, axes=([0, 3, 4], [1, 2, 3]))  # [Ho, Wo, O]
    return out.transpose(2, 0, 1) + b[:, None, None]


def _np_maxpool(x: np.ndarray) -> np.ndarray:
    return np.lib.stride_tricks.sliding_window_view(x, (3, 3), axis=(1, 2))[:, ::2, ::2].max(axis=(-1, -2))


def _np_lpips(weights_path, a: np.ndarray, b: np.ndarray) -> float:
    """LPIPS-alex v0.1 in float64 numpy from the raw safetensors arrays (no torch module)."""
    from safetensors.numpy import load_file

    W = {k: v.astype(np.float64) for k, v in load_file(str(weights_path)).items()}
    shift = np.array([-0.030, -0.088, -0.188])[:, None, None]
    scale = np.array([0.458, 0.448, 0.450])[:, None, None]

    def feats(img):
        x = ((img.astype(np.float64).transpose(2, 0, 1) * 2 - 1) - shift) / scale
        relu = lambda t: np.maximum(t, 0)  # noqa: E731
        t1 = relu(_np_conv(x, W["features.0.weight"], W["features.0.bias"], 4, 2))
        t2 = relu(_np_conv(_np_maxpool(t1), W["features.3.weight"], W["features.3.bias"], 1, 2))
        t3 = relu(_np_conv(_np_maxpool(t2), W["features.6.weight"], W["features.6.bias"], 1, 1))
        t4 = relu(_np_conv(t3, W["features.8.weight"], W["features.8.bias"], 1, 1))
        t5 = relu(_np_conv(t4, W["features.10.weight"], W["features.10.bias"], 1, 1))
        return [t1, t2, t3, t4, t5]

    total = 0.0
    for k, (f0, f1) in enumerate(zip(feats(a), feats(b))):
        n0 = f0 / (np.linalg.norm(f0, axis=0, keepdims=True) + 1e-10)
        n1 = f1 / (np.linalg.norm(f1, axis=0, keepdims=True) + 1e-10)
        lin = W[f"lin{k}.weight"].reshape(-1)
        total += float(np.einsum("c,chw->hw", lin, (n0 - n1) ** 2).mean())
    return total


# ---------------------------------------------------------------- properties

def test_identical_is_zero_and_symmetric(model):
    a, b = _fern(0, crop=True), _fern(1, crop=True)
    assert abs(L.lpips(a, a, model)) < 1e-7
    d_ab, d_ba = L.lpips(a, b, model), L.lpips(b, a, model)
    assert d_ab > 0.05
    assert d_ab == pytest.approx(d_ba, abs=1e-6)


def test_batch_matches_single(model):
    a, b = _fern(0, crop=True), _fern(8, crop=True)
    blur = _box2x(a)
    a_c, b_c = a[: blur.shape[0], : blur.shape[1]], b[: blur.shape[0], : blur.shape[1]]
    batch = model(torch.stack([a_c, b_c]), torch.stack([blur, a_c]))
    assert batch.shape == (2,)
    assert float(batch[0]) == pytest.approx(float(model(a_c, blur)), abs=1e-6)
    assert float(batch[1]) == pytest.approx(float(model(b_c, a_c)), abs=1e-6)
    assert not batch.requires_grad


@pytest.mark.slow
def test_increases_with_noise_and_blur(model):
    a = _fern(0, crop=True)
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(a.shape, generator=g)
    d_noise = [L.lpips(a + s * noise, a, model) for s in (0.01, 0.03, 0.1, 0.3)]
    assert all(x < y for x, y in zip(d_noise, d_noise[1:])), d_noise
    x = a.permute(2, 0, 1)[None]
    d_blur = []
    for k in (3, 7, 15):
        blurred = F.avg_pool2d(F.pad(x, (k // 2,) * 4, mode="replicate"), k, stride=1)[0].permute(1, 2, 0)
        d_blur.append(L.lpips(blurred, a, model))
    assert all(x < y for x, y in zip(d_blur, d_blur[1:])), d_blur


def test_known_pair_matches_independent_float64_reference(model, weights):
    a = _fern(0)
    blur = _box2x(a)
    a = a[: blur.shape[0], : blur.shape[1]]
    ours = L.lpips(blur, a, model)
    ref = _np_lpips(weights, blur.numpy(), a.numpy())
    assert ours == pytest.approx(ref, abs=1e-5)
    assert 0.05 < ref < 0.3  # a light blur, LPIPS-alex's usual range
    # two neighbouring fern views: a larger, still sub-1 distance
    b0, b1 = _fern(0), _fern(1)
    ref01 = _np_lpips(weights, b0.numpy(), b1.numpy())
    assert L.lpips(b0, b1, model) == pytest.approx(ref01, abs=1e-5)
    assert ref < ref01 < 0.6


def test_gradient_reaches_input_not_weights(model):
    a = _fern(0)[:64, :64]
    x = (a + 0.05).clamp(0, 1).requires_grad_(True)
    model(x, a).backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(p.grad is None for p in model.parameters())


def test_shape_errors(model):
    a = torch.rand(40, 40, 3)
    with pytest.raises(ValueError, match="one shape"):
        model(a, torch.rand(40, 41, 3))
    with pytest.raises(ValueError, match="at least 31"):
        model(torch.rand(30, 40, 3), torch.rand(30, 40, 3))


# ---------------------------------------------------------------- loading

def test_cached_and_env_precedence(weights, tmp_path, monkeypatch):
    assert L.load_lpips(weights) is L.load_lpips(weights)
    monkeypatch.setenv(L.WEIGHTS_ENV, str(weights))
    assert L.resolve_weights_path() == (weights, f"${L.WEIGHTS_ENV}")
    assert L.load_lpips() is L.load_lpips(weights)
    missing = tmp_path / "nope.safetensors"
    assert L.resolve_weights_path(missing)[0] == missing  # argument beats the env var
    monkeypatch.setenv(L.WEIGHTS_ENV, str(missing))
    try:
        import lpips as _official  # noqa: F401
    except ImportError:
        assert L.load_lpips() is None
        assert str(missing) in L.lpips_unavailable_reason()
        with pytest.raises(RuntimeError, match="not found"):
            L.lpips(torch.rand(32, 32, 3), torch.rand(32, 32, 3))


def test_corrupt_and_mismatched_files_raise_naming_them(tmp_path):
    from safetensors.torch import save_file

    bad = tmp_path / "garbage.safetensors"
    bad.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00not a header at all")
    with pytest.raises(ValueError, match="garbage.safetensors"):
        L.load_lpips(bad)

    sd = {k: torch.zeros(s) for k, s in L.expected_shapes().items()}
    sd["lin2.weight"] = torch.zeros(1, 256, 1, 1)
    del sd["features.10.bias"]
    wrong = tmp_path / "wrong.safetensors"
    save_file(sd, str(wrong))
    with pytest.raises(ValueError, match=r"wrong\.safetensors.*missing.*features\.10\.bias.*lin2\.weight"):
        L.load_lpips(wrong)


def test_convert_official_package_keys():
    sd = {k: torch.zeros(s) for k, s in L.expected_shapes().items()}
    slices = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
    official = {}
    for k, v in sd.items():
        head, idx, *rest = k.split(".")
        if head == "features":
            official[f"net.slice{slices[int(idx)]}.{idx}.{rest[0]}"] = v
        else:
            official[f"{head}.model.1.weight"] = v
    official["scaling_layer.shift"] = torch.zeros(1, 3, 1, 1)
    assert set(L.convert_lpips_package_state_dict(official)) == set(sd)
