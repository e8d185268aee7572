"""Tests of the per-pixel compositor (clod_adapter.render.composite).

Scenes are built directly here: random means/SPD conics/colors/opacities and
tile lists from a simple 3-sigma bounding-box rule, sorted by a random depth.
"""
from __future__ import annotations

import math

import pytest
import torch

from clod_adapter.render import _torch_impl, composite
from clod_adapter.render._torch_impl import rasterize_to_pixels_torch
from clod_adapter.render.composite import cpp_extension_available, rasterize_to_pixels, use_impl

needs_cpp = pytest.mark.skipif(not cpp_extension_available(), reason="C++ compositor did not build")


# ----------------------------------------------------------------------------
# scene helpers
# ----------------------------------------------------------------------------
def bin_tiles(means2d, radii, width, height, tile_size, depths):
    """Tile lists from an axis-aligned bounding box of radius ``radii``, sorted by depth."""
    N = means2d.shape[0]
    th = (height + tile_size - 1) // tile_size
    tw = (width + tile_size - 1) // tile_size
    mx, my = means2d[:, 0].double(), means2d[:, 1].double()
    r = radii.double()
    vis = (mx + r >= 0) & (mx - r < width) & (my + r >= 0) & (my - r < height)
    tx0 = torch.floor((mx - r) / tile_size).clamp(0, tw - 1).long()
    tx1 = torch.floor((mx + r) / tile_size).clamp(0, tw - 1).long()
    ty0 = torch.floor((my - r) / tile_size).clamp(0, th - 1).long()
    ty1 = torch.floor((my + r) / tile_size).clamp(0, th - 1).long()
    nx = tx1 - tx0 + 1
    ny = ty1 - ty0 + 1
    cnt = torch.where(vis, nx * ny, torch.zeros_like(nx))
    gid = torch.repeat_interleave(torch.arange(N), cnt)
    first = torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
    local = torch.arange(gid.numel()) - first
    tx = tx0[gid] + local % nx[gid]
    ty = ty0[gid] + torch.div(local, nx[gid], rounding_mode="floor")
    tile = ty * tw + tx
    rank = torch.empty(N, dtype=torch.long)
    rank[torch.argsort(depths)] = torch.arange(N)
    key = tile * N + rank[gid]
    order = torch.argsort(key)
    flatten_ids = gid[order]
    tiles_sorted = tile[order]
    offsets = torch.searchsorted(tiles_sorted, torch.arange(th * tw)).to(torch.int32)
    return offsets.reshape(th, tw), flatten_ids.to(torch.int64)


def make_scene(N, width, height, tile_size=16, seed=0, dtype=torch.float32,
               scale=(0.7, 5.0), opacity=(0.05, 0.99), D=3):
    g = torch.Generator().manual_seed(seed)
    means2d = torch.rand(N, 2, generator=g, dtype=torch.float64) * torch.tensor(
        [width + 8.0, height + 8.0], dtype=torch.float64) - 4.0
    lo, hi = math.log(scale[0]), math.log(scale[1])
    s = torch.exp(torch.rand(N, 2, generator=g, dtype=torch.float64) * (hi - lo) + lo)
    th_ = torch.rand(N, generator=g, dtype=torch.float64) * math.pi
    c, sn = torch.cos(th_), torch.sin(th_)
    R = torch.stack([torch.stack([c, -sn], -1), torch.stack([sn, c], -1)], -2)
    cov = R @ torch.diag_embed(s * s) @ R.transpose(-1, -2)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    colors = torch.rand(N, D, generator=g, dtype=torch.float64)
    opac = torch.rand(N, generator=g, dtype=torch.float64) * (opacity[1] - opacity[0]) + opacity[0]
    depths = torch.rand(N, generator=g, dtype=torch.float64)
    radii = 3.0 * s.max(dim=-1).values
    offsets, ids = bin_tiles(means2d, radii, width, height, tile_size, depths)
    return dict(
        means2d=means2d.to(dtype), conics=conics.to(dtype), colors=colors.to(dtype),
        opacities=opac.to(dtype), width=width, height=height, tile_size=tile_size,
        isect_offsets=offsets, flatten_ids=ids,
    )


def render(scene, impl, backgrounds=None, grad=False):
    leaves = {k: scene[k].clone().requires_grad_(grad)
              for k in ("means2d", "conics", "colors", "opacities")}
    bg = None
    if backgrounds is not None:
        bg = backgrounds.clone().requires_grad_(grad)
    fn = rasterize_to_pixels_torch if impl == "torch" else rasterize_to_pixels
    with use_impl(impl):
        img, alpha = fn(leaves["means2d"], leaves["conics"], leaves["colors"], leaves["opacities"],
                        scene["width"], scene["height"], scene["tile_size"],
                        scene["isect_offsets"], scene["flatten_ids"], backgrounds=bg)
    return img, alpha, leaves, bg


def grads_of(scene, impl, backgrounds=None, seed=1):
    img, alpha, leaves, bg = render(scene, impl, backgrounds, grad=True)
    g = torch.Generator().manual_seed(seed)
    w1 = torch.randn(img.shape, generator=g, dtype=img.dtype)
    w2 = torch.randn(alpha.shape, generator=g, dtype=img.dtype)
    loss = (img * w1).sum() + (alpha * w2).sum()
    loss.backward()
    out = {k: v.grad for k, v in leaves.items()}
    if bg is not None:
        out["backgrounds"] = bg.grad
    return img.detach(), alpha.detach(), out


def brute_force(scene, backgrounds=None):
    """Plain per-pixel loops, float64, straight from the gsplat rules."""
    W, H, ts = scene["width"], scene["height"], scene["tile_size"]
    m = scene["means2d"].double().tolist()
    cn = scene["conics"].double().tolist()
    col = scene["colors"].double().tolist()
    op = scene["opacities"].double().tolist()
    offs = scene["isect_offsets"].reshape(-1).tolist()
    ids = scene["flatten_ids"].tolist()
    tw = scene["isect_offsets"].shape[1]
    D = len(col[0])
    img = torch.zeros(H, W, D, dtype=torch.float64)
    alp = torch.zeros(H, W, 1, dtype=torch.float64)
    stopped = 0
    for y in range(H):
        for x in range(W):
            t = (y // ts) * tw + (x // ts)
            start = offs[t]
            end = offs[t + 1] if t + 1 < len(offs) else len(ids)
            T = 1.0
            acc = [0.0] * D
            for i in range(start, end):
                gi = ids[i]
                dx = m[gi][0] - (x + 0.5)
                dy = m[gi][1] - (y + 0.5)
                a, b, c = cn[gi]
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                alpha = min(0.999, op[gi] * math.exp(-sigma))
                if sigma < 0 or alpha < 1.0 / 255.0:
                    continue
                nT = T * (1.0 - alpha)
                if nT <= 1e-4:
                    stopped += 1
                    break
                for k in range(D):
                    acc[k] += alpha * T * col[gi][k]
                T = nT
            for k in range(D):
                img[y, x, k] = acc[k] + (T * float(backgrounds[k]) if backgrounds is not None else 0.0)
            alp[y, x, 0] = 1.0 - T
    return img, alp, stopped


def assert_close(a, b, tol=1e-5, name=""):
    torch.testing.assert_close(a, b, rtol=tol, atol=tol, msg=lambda m: f"{name}: {m}")


# ----------------------------------------------------------------------------
# (a) C++ vs twin, float32
# ----------------------------------------------------------------------------
@needs_cpp
@pytest.mark.parametrize("seed,N,W,H,ts", [(0, 1200, 70, 50, 16), (3, 1500, 64, 64, 16), (7, 600, 45, 37, 8)])
def test_cpp_matches_torch_float32(seed, N, W, H, ts, monkeypatch):
    scene = make_scene(N, W, H, tile_size=ts, seed=seed, opacity=(0.3, 0.995))
    # several tiles, non-trivial lists
    assert scene["isect_offsets"].numel() > 4
    img_c, a_c, g_c = grads_of(scene, "cpp")
    img_t, a_t, g_t = grads_of(scene, "torch")
    assert_close(img_c, img_t, name="image")
    assert_close(a_c, a_t, name="alpha")
    for k in ("means2d", "conics", "colors", "opacities"):
        assert torch.isfinite(g_c[k]).all()
        assert g_c[k].abs().sum() > 0, k
        assert_close(g_c[k], g_t[k], name=k)

    # the T <= 1e-4 early stop did trigger: without it the image changes
    monkeypatch.setattr(_torch_impl, "TRANSMITTANCE_THRESHOLD", 0.0)
    img_ns, a_ns, *_ = render(scene, "torch")
    assert (a_ns.detach() - a_t).abs().max() > 1e-4
    assert (img_ns.detach() - img_t).abs().max() > 1e-4
    # the 1/255 skip and the 0.999 clamp matter too
    monkeypatch.setattr(_torch_impl, "TRANSMITTANCE_THRESHOLD", 1e-4)
    monkeypatch.setattr(_torch_impl, "ALPHA_THRESHOLD", 0.0)
    img_na, *_ = render(scene, "torch")
    assert (img_na.detach() - img_t).abs().max() > 1e-5


# ----------------------------------------------------------------------------
# (b) float64 gradcheck, both implementations
# ----------------------------------------------------------------------------
def _tiny_scene():
    # 4 broad Gaussians on a 16x16 single tile: alpha stays well inside
    # (1/255, 0.999) everywhere relevant and T never reaches 1e-4.
    means = torch.tensor([[5.3, 6.1], [9.7, 8.2], [7.4, 11.6], [11.9, 4.4]], dtype=torch.float64)
    s = torch.tensor([[5.0, 3.5], [4.2, 6.0], [6.5, 4.5], [3.8, 5.5]], dtype=torch.float64)
    ang = torch.tensor([0.3, 1.1, -0.6, 2.0], dtype=torch.float64)
    c, sn = torch.cos(ang), torch.sin(ang)
    R = torch.stack([torch.stack([c, -sn], -1), torch.stack([sn, c], -1)], -2)
    inv = torch.linalg.inv(R @ torch.diag_embed(s * s) @ R.transpose(-1, -2))
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    colors = torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9], [0.6, 0.6, 0.2]],
                          dtype=torch.float64)
    opac = torch.tensor([0.55, 0.7, 0.45, 0.6], dtype=torch.float64)
    offsets = torch.zeros(1, 1, dtype=torch.int32)
    ids = torch.tensor([2, 0, 3, 1], dtype=torch.int64)
    return means, conics, colors, opac, offsets, ids


@pytest.mark.parametrize("impl", ["cpp", "torch"])
def test_gradcheck_float64(impl):
    if impl == "cpp" and not cpp_extension_available():
        pytest.skip("C++ compositor did not build")
    means, conics, colors, opac, offsets, ids = _tiny_scene()
    bg = torch.tensor([0.3, 0.5, 0.7], dtype=torch.float64)
    # all Gaussian/pixel pairs must be away from the 1/255 discontinuity
    px = torch.arange(16, dtype=torch.float64) + 0.5
    dx = means[:, 0, None, None] - px[None, None, :]
    dy = means[:, 1, None, None] - px[None, :, None]
    sig = 0.5 * (conics[:, 0, None, None] * dx * dx + conics[:, 2, None, None] * dy * dy) \
        + conics[:, 1, None, None] * dx * dy
    alpha = opac[:, None, None] * torch.exp(-sig)
    # an eps=1e-6 perturbation moves alpha by << 1e-5
    assert ((alpha - 1 / 255).abs() > 1e-5).all() and (alpha < 0.99).all()

    def fn(m, cn, cl, op, b):
        return rasterize_to_pixels(m, cn, cl, op, 16, 16, 16, offsets, ids, backgrounds=b)

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, conics, colors, opac, bg))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4,
                                    fast_mode=True)


# ----------------------------------------------------------------------------
# (c) brute-force per-pixel loop
# ----------------------------------------------------------------------------
def test_brute_force_agrees():
    scene = make_scene(200, 21, 18, tile_size=8, seed=5, dtype=torch.float64,
                       scale=(0.8, 4.0), opacity=(0.5, 0.999))
    bg = torch.tensor([0.2, 0.4, 0.9], dtype=torch.float64)
    ref_img, ref_a, stopped = brute_force(scene, bg)
    assert stopped > 0, "scene should saturate some pixels"
    impls = ["torch"] + (["cpp"] if cpp_extension_available() else [])
    for impl in impls:
        img, a, *_ = render(scene, impl, backgrounds=bg)
        assert_close(img.detach(), ref_img, tol=1e-10, name=f"{impl} image")
        assert_close(a.detach(), ref_a, tol=1e-10, name=f"{impl} alpha")


# ----------------------------------------------------------------------------
# (d) backgrounds
# ----------------------------------------------------------------------------
@needs_cpp
def test_backgrounds_cpp_vs_torch():
    scene = make_scene(300, 48, 40, tile_size=16, seed=11, opacity=(0.2, 0.99))
    bg = torch.tensor([0.25, 0.5, 0.75])
    img_c, a_c, g_c = grads_of(scene, "cpp", backgrounds=bg)
    img_t, a_t, g_t = grads_of(scene, "torch", backgrounds=bg)
    assert_close(img_c, img_t, name="image")
    assert_close(a_c, a_t, name="alpha")
    for k in ("means2d", "conics", "colors", "opacities", "backgrounds"):
        assert_close(g_c[k], g_t[k], name=k)
    # image with background = image without + (1 - alpha) * bg
    img0, a0, *_ = render(scene, "cpp")
    assert_close(img_c, img0.detach() + (1 - a0.detach()) * bg, name="bg identity")


@pytest.mark.parametrize("impl", ["cpp", "torch"])
def test_empty_and_misc(impl):
    if impl == "cpp" and not cpp_extension_available():
        pytest.skip("C++ compositor did not build")
    N = 5
    means = torch.rand(N, 2) * 20
    conics = torch.tensor([[0.5, 0.0, 0.5]]).repeat(N, 1)
    colors = torch.rand(N, 2)
    opac = torch.full((N,), 0.5)
    offsets = torch.zeros(2, 2, dtype=torch.int32)  # all tiles empty
    ids = torch.zeros(0, dtype=torch.int64)
    bg = torch.tensor([0.1, 0.2])
    img, a = rasterize_to_pixels(means, conics, colors, opac, 20, 18, 16, offsets, ids, backgrounds=bg)
    assert img.shape == (18, 20, 2) and a.shape == (18, 20, 1)
    assert torch.equal(a, torch.zeros_like(a))
    assert torch.allclose(img, bg.expand(18, 20, 2))


@needs_cpp
def test_int32_ids_and_channels():
    scene = make_scene(200, 40, 33, tile_size=16, seed=2, D=5)
    scene["flatten_ids"] = scene["flatten_ids"].to(torch.int32)
    img_c, a_c, g_c = grads_of(scene, "cpp")
    img_t, a_t, g_t = grads_of(scene, "torch")
    assert img_c.shape == (33, 40, 5)
    assert_close(img_c, img_t, name="image")
    for k in g_c:
        assert_close(g_c[k], g_t[k], name=k)


# ----------------------------------------------------------------------------
# (e) the vector rows and their scalar twin (csrc/composite_simd.cpp)
# ----------------------------------------------------------------------------
@needs_cpp
@pytest.mark.parametrize("case", [
    dict(N=400, width=61, height=47, tile_size=16, D=3, opacity=(0.05, 0.999)),  # saturates pixels
    dict(N=300, width=70, height=33, tile_size=8, D=1, scale=(0.3, 9.0)),
    dict(N=250, width=90, height=40, tile_size=64, D=5, opacity=(0.6, 0.999)),  # full 64-pixel rows
    dict(N=120, width=150, height=20, tile_size=128, D=3),  # rows of two words: scalar rows only
    dict(N=150, width=40, height=40, tile_size=16, D=17),  # over 16 channels: scalar rows only
])
def test_vector_rows_give_the_scalar_rows_bits(case):
    """Image, alpha and every gradient (deterministic backward, with a background and an alpha
    loss) are bit-identical with the vector rows on and off; where the CPU has no AVX2/FMA the
    test says so and skips."""
    scene = make_scene(seed=7, **case)
    # a few needle-shaped (ill-conditioned) and near-opaque ones ride the scalar path in between
    scene["conics"][::17] = torch.tensor([40.0, 19.99, 10.0])
    bg = torch.linspace(0.1, 0.9, case["D"])
    out = {}
    prev = composite.deterministic_override()
    composite.set_deterministic(True)
    try:
        for on in (True, False):
            with composite.simd_rows(on) as running:
                if on and not running:
                    pytest.skip("this CPU has no AVX2/FMA vector rows (or its expf is not glibc's FMA form)")
                assert running == on
                out[on] = grads_of(scene, "cpp", backgrounds=bg)
    finally:
        composite.set_deterministic(prev)
    (img1, a1, g1), (img0, a0, g0) = out[True], out[False]
    assert torch.equal(img1, img0) and torch.equal(a1, a0)
    assert a0.max() > 0.9  # the rows drew something opaque
    for k in g0:
        assert torch.equal(g1[k], g0[k]), k
    assert g0["means2d"].abs().sum() > 0
