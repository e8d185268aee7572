"""The per-frame LoD terms' C++ kernel (``csrc/lod_terms.cpp``) against its torch twin
(:func:`clod_adapter.lod.rule.in_frustum` + :func:`normalized_distances`, :func:`lod_mask`), and the
activation cache of a fixed model (:func:`clod_adapter.lod.rule.activated`)."""
import math

import pytest
import torch

from clod_adapter.lod import rule as lod
from clod_adapter.render import native

pytestmark = pytest.mark.skipif(not native.available(), reason="the C++ kernels do not build here")

W, H = 96, 64
K = torch.tensor([[80.0, 0.0, 47.5], [0.0, 80.0, 31.5], [0.0, 0.0, 1.0]])


def _viewmat(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.nn.functional.normalize(torch.randn(4, generator=g), dim=0)
    w, x, y, z = q.tolist()
    R = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    vm = torch.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = torch.randn(3, generator=g)
    return vm


def _both(fn, *args):
    with native.use_impl("cpp"):
        a = fn(*args)
    with native.use_impl("torch"):
        b = fn(*args)
    return a, b


def _edge_distance(means, vm):
    """Per centre, the pixel distance of its projection to the nearest image edge (inf behind)."""
    pc = means.double() @ vm[:3, :3].double().T + vm[:3, 3].double()
    z = pc[:, 2]
    u = K[0, 0].double() * pc[:, 0] / z + K[0, 2].double()
    v = K[1, 1].double() * pc[:, 1] / z + K[1, 2].double()
    e = torch.stack([u.abs(), (u - W).abs(), v.abs(), (v - H).abs()]).amin(0)
    return torch.where(torch.isfinite(e), e, torch.zeros_like(e))


@pytest.mark.parametrize("n", [0, 1, 1000, 200_000])  # 200,000: several parallel chunks
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_frame_terms_kernel_matches_its_twin(n, dtype):
    g = torch.Generator().manual_seed(n)
    means = (torch.randn(n, 3, generator=g) * 3).to(dtype)
    vm = _viewmat(n).to(dtype)
    (fa, da), (fb, db) = _both(lod.frame_terms, means, vm, K.to(dtype), W, H)
    assert fa.dtype == torch.bool and da.dtype == dtype and fa.shape == da.shape == (n,)
    if n == 0:
        return
    near_edge = _edge_distance(means, vm.double()) < 1e-3
    assert torch.equal(fa[~near_edge], fb[~near_edge])
    assert 0 < int(fa.sum()) < n or n == 1
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert torch.allclose(da, db, rtol=tol, atol=tol)
    if fa.any():
        assert float(da[fa].max()) == pytest.approx(1.0, abs=tol)


def test_frame_terms_extreme_centres():
    vm = torch.eye(4)
    vm[2, 3] = 2.0
    means = torch.tensor([[0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0], [0.0, float("inf"), 1.0],
                          [0.0, 0.0, float("inf")], [0.0, 0.0, -5.0], [1e30, 1e30, 1e30], [0.1, 0.1, 3.0]])
    (fa, da), (fb, db) = _both(lod.frame_terms, means, vm, K, W, H)
    assert fa.tolist() == fb.tolist() == [True, False, False, False, False, False, True]
    ok = torch.arange(7) != 5
    assert torch.allclose(da[ok], db[ok], equal_nan=True)
    # |mu - c| of a centre at 1e30: the twin's float32 square overflows to inf, the kernel's
    # double arithmetic keeps the distance
    assert math.isinf(float(db[5])) and float(da[5]) == pytest.approx(math.sqrt(3) * 1e30 / math.sqrt(0.02 + 25.0), rel=1e-5)
    assert float(da[6]) == 1.0 and torch.isfinite(da[[0, 4, 6]]).all()
    # an empty frustum normalises by the largest distance of all (the twin's rule)
    (fa, da), (fb, db) = _both(lod.frame_terms, means[[0, 4]] - torch.tensor([0.0, 0.0, 10.0]), vm, K, W, H)
    assert not fa.any() and not fb.any() and torch.allclose(da, db) and float(da.max()) == 1.0
    # every centre on the camera: d' = 0, never NaN
    (fa, da), _ = _both(lod.frame_terms, torch.tensor([[0.0, 0.0, -2.0]] * 3), vm, K, W, H)
    assert torch.equal(da, torch.zeros(3))


def test_frame_terms_refuses_autograd():
    means = torch.randn(5, 3, requires_grad=True)
    with pytest.raises(ValueError, match="no gradient"):
        lod.frame_terms(means, torch.eye(4), K, W, H)


@pytest.mark.parametrize("s_v", [1.0, 1.7, 5.0, 30.0, 1e6])
def test_lod_mask_kernel_matches_its_twin(s_v):
    n = 100_000
    g = torch.Generator().manual_seed(7)
    op = torch.rand(n, generator=g, dtype=torch.float64)
    op[:10] = 0.0
    d = torch.rand(n, generator=g, dtype=torch.float64)
    d[10:20] = 0.0
    sd = torch.randn(n, generator=g, dtype=torch.float64) * 0.5  # a quarter below 0: ReLU -> dead
    sd[20:30] = 0.0
    sd[30:40] = 1e-30
    sd[40:50] = 1e30
    (ma, mb) = _both(lod.lod_mask, op, d, sd, s_v, 0.005, 1e-8)
    margin = lod.lod_margin(op, d, sd, s_v, 0.005, 1e-8)
    tie = margin.abs() < 1e-9
    assert torch.equal(ma[~tie], mb[~tie]) and torch.equal(ma[~tie], (margin > 0)[~tie])
    assert not ma[:10].any()  # opacity 0 is never drawn
    # float32 inputs: the kernel computes in double, the twin in float32: they agree off the boundary
    (ma, mb) = _both(lod.lod_mask, op.float(), d.float(), sd.float(), s_v, 0.005, 1e-8)
    assert torch.equal(ma[margin.abs() > 1e-4], mb[margin.abs() > 1e-4])


@pytest.mark.parametrize("s_v", [1.0, 3.0, 30.0])
@pytest.mark.parametrize("n", [0, 5, 100_000])
def test_lod_keep_kernel_matches_its_twin_and_the_mask(s_v, n):
    g = torch.Generator().manual_seed(n + 3)
    op = torch.rand(n, generator=g, dtype=torch.float64)
    d = torch.rand(n, generator=g, dtype=torch.float64)
    sd = torch.randn(n, generator=g, dtype=torch.float64) * 0.5
    fr = torch.rand(n, generator=g) < 0.7
    margin = lod.lod_margin(op, d, sd, s_v, 0.005, 1e-8)
    assert margin.abs().min() > 1e-9 if n else True  # no ties: kernel and twin agree exactly
    (ia, fa, ka), (ib, fb, kb) = _both(lod.lod_keep, op, d, sd, s_v, fr, 0.005, 1e-8)
    want = torch.nonzero(margin > 0).squeeze(1)
    assert ia.dtype == ib.dtype == torch.long and torch.equal(ia, want) and torch.equal(ib, want)
    assert fa == fb == int(fr.sum()) and ka == kb == int(((margin > 0) & fr).sum())
    (na, fa2, ka2), (nb, fb2, kb2) = _both(lambda *a: lod.lod_keep(*a, with_ids=False), op, d, sd, s_v, fr, 0.005, 1e-8)
    assert na is None and nb is None and (fa2, ka2) == (fb2, kb2) == (fa, ka)
    if n == 100_000:
        assert 0 < ia.numel() < n and 0 < ka < fa < n


def test_lod_mask_tensor_s_v_and_frustum_use_the_twin_rule():
    op, d, sd = torch.tensor([0.9, 0.9]), torch.tensor([0.1, 0.9]), torch.tensor([0.5, 0.01])
    fr = torch.tensor([False, True])
    with native.use_impl("cpp"):
        assert lod.lod_mask(op, d, sd, torch.tensor(2.0)).tolist() == [True, False]
        assert lod.lod_mask(op, d, sd, 2.0, frustum=fr).tolist() == [False, False]


def test_activated_caches_per_version_and_keeps_autograd():
    raw = torch.randn(50, 3)
    a = lod.activated(raw, "exp")
    assert torch.equal(a, torch.exp(raw)) and lod.activated(raw, "exp") is a
    s = lod.activated(raw, "sigmoid")
    assert torch.equal(s, torch.sigmoid(raw)) and s is not a
    raw.add_(1.0)  # an optimiser step: a new version, a new value
    b = lod.activated(raw, "exp")
    assert b is not a and torch.allclose(b, torch.exp(raw))
    p = torch.randn(4, requires_grad=True)
    y = lod.activated(p, "sigmoid")
    assert y.requires_grad
    y.sum().backward()
    assert torch.allclose(p.grad, torch.sigmoid(p) * (1 - torch.sigmoid(p)))
    with torch.no_grad():
        assert not lod.activated(p, "sigmoid").requires_grad
    with pytest.raises(KeyError):
        lod.activated(raw, "relu")


def test_render_under_inference_mode_matches():
    """Tensors made under ``torch.inference_mode`` have no version counter: nothing is cached, the
    frame is the same."""
    from clod_adapter.lod.draw import render_lod
    from clod_adapter.io.synthetic import make_ground_truth

    g = make_ground_truth(200, seed=3).with_sigma_d(torch.full((200,), 0.5))

    class Cam:
        viewmat, K, width, height = torch.eye(4), K, W, H

    Cam.viewmat = Cam.viewmat.clone()
    Cam.viewmat[2, 3] = 4.0
    with torch.no_grad():
        ref = render_lod(g, Cam, 2.0).image
    with torch.inference_mode():
        gi = make_ground_truth(200, seed=3).with_sigma_d(torch.full((200,), 0.5))
        out = render_lod(gi, Cam, 2.0).image
    assert torch.allclose(ref, out) and float(ref.abs().sum()) > 0


@pytest.mark.parametrize("n", [0, 7, 100_000])  # 100,000 kept of 150,000: several parallel chunks
@pytest.mark.parametrize("width,level", [(0.5, 0.7), (0.0, 0.0), (0.2, 1.0)])
@pytest.mark.parametrize("with_gain", [True, False])
def test_window_opacities_kernel_matches_its_twin(n, width, level, with_gain):
    g = torch.Generator().manual_seed(n + 3)
    N = int(n * 1.5) + 1
    logits = torch.randn(N, generator=g) * 3
    logits[::11] = -200.0  # alpha underflows to 0: log alpha = -inf, drawn 0
    op = torch.sigmoid(logits)
    d = torch.rand(N, generator=g)
    sd = torch.randn(N, generator=g) * 0.5  # negative: ReLU -> 0, a dead Gaussian
    gain = torch.randn(N, generator=g) if with_gain else None
    ids = torch.randperm(N, generator=g)[:n].sort().values
    a, b = _both(lod.window_opacities, ids, op, logits, d, sd, 3.0, level, gain, 0.005, 1e-8, width)
    assert a.shape == b.shape == (n,) and a.dtype == b.dtype == torch.float32
    if n == 0:
        return
    assert torch.isfinite(a).all() and float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    assert 0 < int((a > 0).sum()) < n or n < 10
    m = lod.lod_margin(op[ids], d[ids], sd[ids], 3.0)
    exact = m.abs() > 1e-4  # off the hard mask's edge (width 0)
    # the twin's margin is float32 (terms of magnitude <= ~20 inside the window: ~2e-6 / width)
    assert torch.allclose(a[exact], b[exact], rtol=1e-5, atol=3e-5)
    assert torch.equal(a[exact] > 0, b[exact] > 0)


def test_window_opacities_with_autograd_is_the_torch_form():
    """With a gradient wanted the kernel is not used: sigma_d and the gain get gradients."""
    n = 50
    g = torch.Generator().manual_seed(1)
    logits = torch.randn(n, generator=g)
    d = torch.rand(n, generator=g)
    sd = (torch.rand(n, generator=g) * 0.5 + 0.2).requires_grad_(True)
    gain = torch.randn(n, generator=g).requires_grad_(True)
    ids = torch.arange(0, n, 2)
    with native.use_impl("cpp"):
        out = lod.window_opacities(ids, torch.sigmoid(logits), logits, d, sd, 2.0, 0.5, gain, width=0.5)
    out.sum().backward()
    assert out.requires_grad and sd.grad is not None and gain.grad is not None
    assert float(gain.grad[ids].abs().sum()) > 0 and float(gain.grad[1::2].abs().sum()) == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_critical_kernel_matches_its_twin(dtype):
    """The critical s_v (budget.critical_s_v): the kernel against the torch twin, to 1e-12
    relative, with dead decays (<= 0), alpha = 0, d' = 0, NaN, and a tiny and a large eps; and
    both the root of the margin."""
    from clod_adapter.lod.budget import critical_s_v

    g = torch.Generator().manual_seed(5)
    n = 5000
    opac = (torch.rand(n, generator=g, dtype=torch.float64) * 0.99 + 0.005).to(dtype)
    d = torch.rand(n, generator=g, dtype=torch.float64).to(dtype)
    sigma = (torch.rand(n, generator=g, dtype=torch.float64) * 1.5 - 0.1).to(dtype)
    opac[:20], d[20:40], sigma[40:45], opac[45:50], d[50:55] = 0.0, 0.0, float("nan"), float("nan"), 1e-30
    for eps in (1e-8, 1e-30, 0.5):
        a, b = _both(critical_s_v, opac, d, sigma, 0.005, eps)
        assert a.dtype == b.dtype == torch.float64 and a.shape == b.shape == (n,)
        assert torch.equal(a == 0, b == 0) and bool((a[:20] == 0).all()) and bool((a[40:50] == 0).all())
        torch.testing.assert_close(a, b, rtol=1e-12, atol=0)
        live = (a > 0) & (sigma > 0)
        below = lod.lod_margin(opac[live].double(), d[live].double(), sigma[live].double(), a[live] * (1 - 1e-9),
                               0.005, eps)
        above = lod.lod_margin(opac[live].double(), d[live].double(), sigma[live].double(), a[live] * (1 + 1e-9),
                               0.005, eps)
        assert bool((below > 0).all()) and bool((above < 0).all())


def test_a_stale_build_lock_is_removed_and_a_fresh_one_kept(tmp_path, capsys):
    """An interrupted build leaves ``lock`` behind and torch's loader waits on it without end:
    one older than STALE_LOCK_S goes (with a line on stderr), a build still running keeps its own."""
    import os
    import time

    from clod_adapter.render import native

    lock = tmp_path / "lock"
    lock.write_text("")
    assert not native.clear_stale_lock(tmp_path)  # just made: a build may hold it
    assert lock.exists()
    old = time.time() - native.STALE_LOCK_S - 60
    os.utime(lock, (old, old))
    assert native.clear_stale_lock(tmp_path)
    assert not lock.exists()
    assert "interrupted build" in capsys.readouterr().err
    assert not native.clear_stale_lock(tmp_path)  # nothing left to remove
