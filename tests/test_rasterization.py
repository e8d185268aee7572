"""Tests for the CPU rasterizer front end (projection, SH, tile binning, pipeline)."""
from __future__ import annotations

import math

import pytest
import torch

from clod_adapter.render import fully_fused_projection, rasterization, spherical_harmonics
from clod_adapter.render.composite import cpp_extension_available
from clod_adapter.render.projection import project_visible
from clod_adapter.render.tiles import isect_offset_encode, isect_tiles

W, H = 24, 16
ALPHA_T = 1.0 / 255.0


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------
IMPLS = ["torch", "cpp"]


def _composite_pixels(px, py, means2d, conics, colors, opacities, bg):
    """gsplat per-pixel front-to-back compositing of an ordered list (vectorised over pixels):
    the brute-force reference's compositor."""
    P = px.numel()
    D = colors.shape[-1]
    if means2d.shape[0] == 0:
        T = torch.ones(P, dtype=colors.dtype)
        col = torch.zeros(P, D, dtype=colors.dtype)
    else:
        dx = means2d[None, :, 0] - px[:, None]
        dy = means2d[None, :, 1] - py[:, None]
        sigma = 0.5 * (conics[None, :, 0] * dx * dx + conics[None, :, 2] * dy * dy) + conics[None, :, 1] * dx * dy
        alpha = torch.clamp_max(opacities[None] * torch.exp(-sigma), 0.999)
        valid = (sigma >= 0) & (alpha >= ALPHA_T)
        a = torch.where(valid, alpha, torch.zeros_like(alpha))
        cp = torch.cumprod(1 - a, dim=1)
        include = valid & (cp > 1e-4)
        a = torch.where(include, a, torch.zeros_like(a))
        cp = torch.cumprod(1 - a, dim=1)
        T_before = torch.cat([torch.ones(P, 1, dtype=a.dtype), cp[:, :-1]], dim=1)
        w = a * T_before
        col = w @ colors
        T = cp[:, -1]
    if bg is not None:
        col = col + T[:, None] * bg
    return col, (1 - T)[:, None]


def camera(dtype=torch.float64, fx=22.0, fy=21.0, cx=W / 2 + 0.3, cy=H / 2 - 0.2, theta=0.1):
    """A camera at (0.2, -0.1, -0.3) slightly rotated about y, looking down +z."""
    c, s = math.cos(theta), math.sin(theta)
    R = torch.tensor([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=dtype)
    cam_pos = torch.tensor([0.2, -0.1, -0.3], dtype=dtype)
    V = torch.eye(4, dtype=dtype)
    V[:3, :3] = R
    V[:3, 3] = -R @ cam_pos
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=dtype)
    return V, K


def scene(n=6, seed=0, dtype=torch.float64, sh_degree=3, spread=0.45, depth=(2.0, 4.0)):
    g = torch.Generator().manual_seed(seed)
    z = torch.empty(n, dtype=dtype).uniform_(*depth, generator=g)
    xy = (torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * 2 * spread * z[:, None]
    means = torch.cat([xy, z[:, None]], dim=1)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.empty(n, 3, dtype=dtype).uniform_(0.05, 0.25, generator=g)
    opac = torch.empty(n, dtype=dtype).uniform_(0.3, 0.8, generator=g)
    K = (sh_degree + 1) ** 2
    sh = torch.randn(n, K, 3, generator=g, dtype=dtype) * 0.3
    return means, quats, scales, opac, sh


# textbook EWA (per Gaussian, float64) --------------------------------------------------------
def ref_project_one(m, q, s, o, V, K, width, height, eps2d=0.3, near=0.01, far=1e10, screen_cull=True):
    q = q / q.norm()
    w, x, y, z = q.tolist()
    Rq = torch.tensor([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ], dtype=torch.float64)
    Sigma = Rq @ torch.diag(s.double() ** 2) @ Rq.T
    Rv, tv = V[:3, :3].double(), V[:3, 3].double()
    t = Rv @ m.double() + tv
    if t[2] < near or t[2] > far:
        return None
    fx, fy, cx, cy = K[0, 0].item(), K[1, 1].item(), K[0, 2].item(), K[1, 2].item()
    tanx, tany = 0.5 * width / fx, 0.5 * height / fy
    u = min(max(t[0].item() / t[2].item(), -(cx / fx + 0.3 * tanx)), (width - cx) / fx + 0.3 * tanx)
    v = min(max(t[1].item() / t[2].item(), -(cy / fy + 0.3 * tany)), (height - cy) / fy + 0.3 * tany)
    tz = t[2].item()
    J = torch.tensor([[fx / tz, 0, -fx * u / tz], [0, fy / tz, -fy * v / tz]], dtype=torch.float64)
    cov = J @ Rv @ Sigma @ Rv.T @ J.T + eps2d * torch.eye(2, dtype=torch.float64)
    mean2d = torch.tensor([fx * t[0] / tz + cx, fy * t[1] / tz + cy], dtype=torch.float64)
    conic_m = torch.linalg.inv(cov)
    if o is not None and o < ALPHA_T:
        return None
    ext = 3.33 if o is None else min(3.33, math.sqrt(2 * math.log(float(o) * 255.0)))
    rx, ry = math.ceil(ext * math.sqrt(cov[0, 0])), math.ceil(ext * math.sqrt(cov[1, 1]))
    if not screen_cull:
        return dict(radii=(rx, ry), mean2d=mean2d, depth=tz,
                    conic=torch.stack([conic_m[0, 0], conic_m[0, 1], conic_m[1, 1]]))
    if rx <= 0 and ry <= 0:
        return None
    if mean2d[0] + rx <= 0 or mean2d[0] - rx >= width or mean2d[1] + ry <= 0 or mean2d[1] - ry >= height:
        return None
    return dict(radii=(rx, ry), mean2d=mean2d, depth=tz,
                conic=torch.stack([conic_m[0, 0], conic_m[0, 1], conic_m[1, 1]]))


def brute_force_render(means, quats, scales, opac, colors_fn, V, K, width, height, bg=None):
    """Per-pixel compositing over ALL Gaussians in front of the camera sorted by depth, no tiles,
    no radii (uses the textbook projection without its radius-based culling)."""
    m2d, con, dep, ids = [], [], [], []
    for i in range(means.shape[0]):
        r = ref_project_one(means[i], quats[i], scales[i], None, V, K, width, height, screen_cull=False)
        if r is None or opac[i] < ALPHA_T:
            continue
        m2d.append(r["mean2d"]); con.append(r["conic"]); dep.append(r["depth"]); ids.append(i)
    if not ids:
        n = 0
        m2d = torch.zeros(0, 2, dtype=torch.float64); con = torch.zeros(0, 3, dtype=torch.float64)
        ids_t = torch.zeros(0, dtype=torch.long)
    else:
        m2d, con = torch.stack(m2d), torch.stack(con)
        order = torch.argsort(torch.tensor(dep))
        ids_t = torch.tensor(ids)[order]
        m2d, con = m2d[order], con[order]
    cols = colors_fn(ids_t)
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                            torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    c, a = _composite_pixels(xs.reshape(-1), ys.reshape(-1), m2d, con, cols, opac[ids_t], bg)
    return c.reshape(height, width, -1), a.reshape(height, width, 1)


# ------------------------------------------------------------------------------------------
# projection
# ------------------------------------------------------------------------------------------
def test_projection_matches_textbook_ewa():
    means, quats, scales, opac, _ = scene(n=40, seed=1, spread=0.9)
    # a few special ones: behind the camera, far off-screen, tiny opacity, near the FOV clamp
    means[0] = torch.tensor([0.0, 0.0, -2.0])
    means[1] = torch.tensor([50.0, 0.0, 3.0])
    opac[2] = 0.002
    means[3] = torch.tensor([2.5, 0.2, 2.0])
    V, K = camera()
    radii, m2d, dep, con = fully_fused_projection(means, quats, scales, opac, V, K, W, H)
    assert radii.dtype == torch.int32 and radii.shape == (40, 2)
    n_vis = 0
    for i in range(40):
        r = ref_project_one(means[i], quats[i], scales[i], opac[i], V, K, W, H)
        if r is None:
            assert radii[i].tolist() == [0, 0], i
            continue
        n_vis += 1
        assert tuple(radii[i].tolist()) == r["radii"], i
        torch.testing.assert_close(m2d[i], r["mean2d"], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(con[i], r["conic"], rtol=1e-9, atol=1e-10)
        assert abs(dep[i].item() - r["depth"]) < 1e-12
    assert n_vis >= 10
    assert radii[0].tolist() == [0, 0] and radii[1].tolist() == [0, 0] and radii[2].tolist() == [0, 0]
    # opacities=None -> extend 3.33
    radii2, *_ = fully_fused_projection(means, quats, scales, None, V, K, W, H)
    for i in range(4, 40):
        r = ref_project_one(means[i], quats[i], scales[i], None, V, K, W, H)
        assert (tuple(radii2[i].tolist()) == r["radii"]) if r is not None else radii2[i].tolist() == [0, 0]


def test_projection_gradients_finite_for_culled():
    means, quats, scales, opac, _ = scene(n=5, seed=2)
    means[0] = torch.tensor([0.0, 0.0, -1.0])  # behind
    means[1] = torch.tensor([0.0, 0.0, 0.0])  # at the camera plane region (z < near after view)
    params = [t.clone().requires_grad_() for t in (means, quats, scales)]
    V, K = camera()
    radii, m2d, dep, con = fully_fused_projection(*params, opac, V, K, W, H)
    (m2d.sum() + dep.sum() + con.sum()).backward()
    for p in params:
        assert torch.isfinite(p.grad).all()
    assert (params[0].grad[0] == 0).all()


def test_projection_float32_matches_float64():
    means, quats, scales, opac, _ = scene(n=200, seed=3, spread=0.7)
    V, K = camera()
    r64, m64, d64, c64 = fully_fused_projection(means, quats, scales, opac, V, K, W, H)
    r32, m32, d32, c32 = fully_fused_projection(means.float(), quats.float(), scales.float(), opac.float(),
                                                V.float(), K.float(), W, H)
    same = (r64 == r32).all(-1)
    assert same.float().mean() > 0.97  # ceil() may flip at exact integers
    torch.testing.assert_close(m32.double()[same], m64[same], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(c32.double()[same], c64[same], rtol=1e-4, atol=1e-6)


def _stiff_scene(n, dtype, seed=5):
    """Random Gaussians with the cases the projection culls or must keep well-conditioned: some
    behind or at the camera, off-screen, under the 1/255 opacity, needles (scale ratio 1e6), huge."""
    means, quats, scales, opac, _ = scene(n=n, seed=seed, spread=1.2, dtype=dtype, sh_degree=0)
    g = torch.Generator().manual_seed(seed + 1)
    kind = torch.randint(0, 6, (n,), generator=g)
    means[kind == 0, 2] = -means[kind == 0, 2]  # behind the camera
    scales[kind == 1] = scales[kind == 1] * torch.tensor([1e3, 1e-3, 1e-3], dtype=dtype)  # needles
    scales[kind == 2] = scales[kind == 2] * 40.0  # larger than the image
    opac[kind == 3] = opac[kind == 3] * 0.01  # some under 1/255
    means[kind == 4, 0] = means[kind == 4, 0] * 8.0  # off-screen
    return means, quats, scales, opac


@pytest.mark.skipif(not cpp_extension_available(), reason="the C++ kernels do not build here")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_cpp_projection_equals_its_torch_twin(dtype):
    """project_geometry / finish_projection without gradients (csrc/projection.cpp, arithmetic in
    double) against their torch form: in float64 the same rows, radii and values; in float32 the
    same rows but where a ceil lands on the other side of an integer, and every value at least as
    close to the float64 projection as the torch form's."""
    from clod_adapter.render import native
    from clod_adapter.render.projection import finish_projection, project_geometry

    means, quats, scales, opac = _stiff_scene(3000, dtype)
    V, K = camera(dtype)
    n = means.shape[0]
    cov_scale = torch.empty(n, dtype=dtype).uniform_(0.5, 2.0, generator=torch.Generator().manual_seed(2))

    def project(impl, dt, keep, op, cs):
        with native.use_impl(impl), torch.no_grad():
            geom = project_geometry(means.to(dt), quats.to(dt), scales.to(dt), V.to(dtype).to(dt), K.to(dtype).to(dt),
                                    W, H, 0.01, 1e10, keep)
            r = geom.ids
            return geom, finish_projection(geom, None if op is None else op.to(dt)[r], W, H, 0.3, 0.0,
                                           None if cs is None else cs.to(dt)[r])

    def close(x, y, ref):  # x (the kernel's) no further from ref than y (the twin's), or both at rounding
        ex, ey = (x.double() - ref).abs(), (y.double() - ref).abs()
        return bool((ex <= torch.maximum(ey, 1e-12 + 1e-12 * ref.abs())).all()) if dtype == torch.float64 else \
            bool((ex <= ey + 1e-6 * ref.abs() + 1e-6).all())

    for keep in (None, opac >= 0.2, torch.arange(0, n, 3)):
        for op, cs in ((opac, None), (None, None), (opac, cov_scale)):
            (ga, pa), (gb, pb) = project("cpp", dtype, keep, op, cs), project("torch", dtype, keep, op, cs)
            gr, pr = project("torch", torch.float64, keep, op, cs)
            assert torch.equal(ga.ids, gb.ids) and torch.equal(ga.ids, gr.ids) and ga.ids.numel() > 100
            for x, y, ref in zip(ga[1:], gb[1:], gr[1:]):
                assert x.dtype == dtype and close(x, y, ref)
            kept = torch.isin(pa.ids, pb.ids)
            assert kept.float().mean() >= (0.995 if dtype == torch.float32 else 1.0) and int(kept.sum()) > 50
            assert torch.equal(pa.ids, pr.ids) or dtype == torch.float32
            ia, ib, ir = kept, torch.isin(pb.ids, pa.ids), torch.isin(pr.ids, pa.ids)
            assert torch.equal(pa.ids[ia], pb.ids[ib]) and torch.equal(pa.ids[ia], pr.ids[ir])
            d = (pa.radii[ia] - pb.radii[ib]).abs()
            assert int(d.max()) <= 1 and (d == 0).all(-1).float().mean() >= (0.99 if dtype == torch.float32 else 1.0)
            for f in ("means2d", "depths", "conics"):
                assert close(getattr(pa, f)[ia], getattr(pb, f)[ib], getattr(pr, f)[ir].double())
    with native.use_impl("cpp"), torch.no_grad(), pytest.raises(RuntimeError, match="outside"):
        project_geometry(means, quats, scales, V, K, W, H, 0.01, 1e10, torch.tensor([0, n]))


# ------------------------------------------------------------------------------------------
# SH
# ------------------------------------------------------------------------------------------
def _sh_3dgs_reference(deg, d, sh):
    """The official 3DGS ``eval_sh`` (utils/sh_utils.py), with its constants."""
    C0 = 0.28209479177387814
    C1 = 0.4886025119029199
    C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
    C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
          -0.4570457994644658, 1.445305721320277, -0.5900435899266435]
    x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    r = C0 * sh[:, 0]
    if deg > 0:
        r = r - C1 * y * sh[:, 1] + C1 * z * sh[:, 2] - C1 * x * sh[:, 3]
    if deg > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        r = (r + C2[0] * xy * sh[:, 4] + C2[1] * yz * sh[:, 5] + C2[2] * (2 * zz - xx - yy) * sh[:, 6]
             + C2[3] * xz * sh[:, 7] + C2[4] * (xx - yy) * sh[:, 8])
    if deg > 2:
        r = (r + C3[0] * y * (3 * xx - yy) * sh[:, 9] + C3[1] * xy * z * sh[:, 10]
             + C3[2] * y * (4 * zz - xx - yy) * sh[:, 11] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
             + C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + C3[5] * z * (xx - yy) * sh[:, 14]
             + C3[6] * x * (xx - 3 * yy) * sh[:, 15])
    return r


@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_sh_matches_3dgs_eval_sh(deg):
    g = torch.Generator().manual_seed(deg)
    dirs = torch.randn(64, 3, generator=g, dtype=torch.float64)
    coeffs = torch.randn(64, 16, 3, generator=g, dtype=torch.float64)
    out = spherical_harmonics(deg, dirs * 3.7, coeffs)  # unnormalised dirs on purpose
    ref = _sh_3dgs_reference(deg, dirs / dirs.norm(dim=-1, keepdim=True), coeffs)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)


def test_sh_known_values():
    # direction +z: Y00 = 0.28209, Y1 = (0, C1, 0), Y20 index 6 = 0.63078, Y30 index 12 = 0.74635
    dirs = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    expected = {0: 0.2820947917738781, 2: 0.48860251190292, 6: 0.9461746957575601 - 0.3153915652525201,
                12: 1.865881662950577 - 1.119528997770346}
    for k in range(16):
        coeffs = torch.zeros(1, 16, 3, dtype=torch.float64)
        coeffs[0, k] = torch.tensor([1.0, 2.0, -1.0])
        v = spherical_harmonics(3, dirs, coeffs)[0]
        e = expected.get(k, 0.0)
        torch.testing.assert_close(v, torch.tensor([e, 2 * e, -e], dtype=torch.float64), atol=1e-14, rtol=0)
    # direction +x: index 3 = -C1, index 8 = 0.54627 (x^2 - y^2), index 15 = -0.59004 (x^3)
    dirs = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    for k, e in {3: -0.48860251190292, 8: 0.5462742152960395, 15: -0.5900435899266435,
                 6: -0.3153915652525201, 13: 0.4570457994644658}.items():
        coeffs = torch.zeros(1, 16, 3, dtype=torch.float64)
        coeffs[0, k] = 1.0
        torch.testing.assert_close(spherical_harmonics(3, dirs, coeffs)[0, 0],
                                   torch.tensor(e, dtype=torch.float64), atol=1e-14, rtol=0)
    with pytest.raises(ValueError):
        spherical_harmonics(3, dirs, torch.zeros(1, 9, 3))


# ------------------------------------------------------------------------------------------
# tiles
# ------------------------------------------------------------------------------------------
def test_isect_tiles_complete_and_offsets_consistent():
    g = torch.Generator().manual_seed(5)
    n, ts, width, height = 300, 16, 200, 120
    tw, th = math.ceil(width / ts), math.ceil(height / ts)
    means2d = torch.rand(n, 2, generator=g) * torch.tensor([width + 60.0, height + 60.0]) - 30
    radii = torch.randint(0, 40, (n, 2), generator=g, dtype=torch.int32)
    radii[::7, 0] = 0
    depths = torch.rand(n, generator=g) * 10 + 0.1
    depths[10] = depths[11]  # tie
    tpg, isect_ids, flat = isect_tiles(means2d, radii, depths, ts, tw, th)
    assert isect_ids.dtype == torch.int64 and flat.dtype == torch.int64
    got = {}
    for k, (iid, f) in enumerate(zip(isect_ids.tolist(), flat.tolist())):
        got.setdefault((iid >> 32, f), 0)
        got[(iid >> 32, f)] += 1
        assert iid & 0xFFFFFFFF == (depths[f:f + 1].view(torch.int32).item() & 0xFFFFFFFF)
    expected = set()
    for i in range(n):
        rx, ry = radii[i].tolist()
        if rx <= 0 or ry <= 0:
            assert tpg[i] == 0
            continue
        mx, my = (means2d[i] / ts).tolist()
        x0 = min(max(0, math.floor(mx - rx / ts)), tw); x1 = min(max(0, math.ceil(mx + rx / ts)), tw)
        y0 = min(max(0, math.floor(my - ry / ts)), th); y1 = min(max(0, math.ceil(my + ry / ts)), th)
        assert tpg[i] == (x1 - x0) * (y1 - y0)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                expected.add((ty * tw + tx, i))
    # every pair whose rect overlaps a tile is present, exactly once, and nothing else
    assert set(got) == expected and all(v == 1 for v in got.values())
    # rects vs pixel footprint: every pixel within the radius box lies in a listed tile
    offsets = isect_offset_encode(isect_ids, tw, th)
    assert offsets.shape == (th, tw) and offsets.dtype == torch.int32
    offs = torch.cat([offsets.flatten().long(), torch.tensor([isect_ids.numel()])])
    assert (offs[1:] >= offs[:-1]).all() and offs[0] == 0
    for t in range(tw * th):
        seg = isect_ids[offs[t]:offs[t + 1]]
        assert ((seg >> 32) == t).all()
        d = depths[flat[offs[t]:offs[t + 1]]]
        assert (d[1:] >= d[:-1]).all()


def test_isect_empty():
    tpg, ii, fl = isect_tiles(torch.zeros(0, 2), torch.zeros(0, 2, dtype=torch.int32), torch.zeros(0), 16, 2, 1)
    assert ii.numel() == 0 and fl.numel() == 0 and tpg.numel() == 0
    off = isect_offset_encode(ii, 2, 1)
    assert off.tolist() == [[0, 0]]


# ------------------------------------------------------------------------------------------
# whole pipeline
# ------------------------------------------------------------------------------------------
def _sh_colors_fn(means, sh, V, deg):
    campos = torch.linalg.inv(V)[:3, 3]

    def fn(ids):
        return torch.clamp_min(spherical_harmonics(deg, means[ids] - campos, sh[ids]) + 0.5, 0.0)
    return fn


@pytest.mark.parametrize("impl", IMPLS)
def test_matches_brute_force_renderer(impl):
    means, quats, scales, opac, sh = scene(n=60, seed=7, spread=0.8)
    means[0] = torch.tensor([0.0, 0.0, -1.0])  # behind
    means[1] = torch.tensor([30.0, 0.0, 3.0])  # off-screen
    opac[5] = 0.95
    V, K = camera()
    bg = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64)
    rc, ra, meta = rasterization(means, quats, scales, opac, sh, V[None], K[None], W, H,
                                 sh_degree=3, backgrounds=bg, backend="cpu")
    bc, ba = brute_force_render(means, quats, scales, opac, _sh_colors_fn(means, sh, V, 3), V, K, W, H, bg[0])
    torch.testing.assert_close(rc[0], bc, atol=1e-5, rtol=0)
    torch.testing.assert_close(ra[0], ba, atol=1e-5, rtol=0)
    assert meta["n_visible"].tolist() == [int((meta["radii"][0] > 0).all(-1).sum())]
    assert meta["radii"].shape == (1, 60, 2) and meta["means2d"].shape == (1, 60, 2)
    assert meta["radii"][0, 0].tolist() == [0, 0] and meta["radii"][0, 1].tolist() == [0, 0]


@pytest.mark.parametrize("impl", IMPLS)
def test_precomputed_colors_multi_camera(impl):
    means, quats, scales, opac, _ = scene(n=30, seed=8)
    V0, K0 = camera()
    V1, K1 = camera(theta=-0.15, fx=18.0)
    g = torch.Generator().manual_seed(0)
    cols = torch.rand(30, 4, generator=g, dtype=torch.float64)
    rc, ra, meta = rasterization(means, quats, scales, opac, cols, torch.stack([V0, V1]),
                                 torch.stack([K0, K1]), W, H, backend="cpu")
    assert rc.shape == (2, H, W, 4) and ra.shape == (2, H, W, 1)
    for c, (V, K) in enumerate([(V0, K0), (V1, K1)]):
        bc, ba = brute_force_render(means, quats, scales, opac, lambda ids: cols[ids], V, K, W, H)
        torch.testing.assert_close(rc[c], bc, atol=1e-5, rtol=0)
        torch.testing.assert_close(ra[c], ba, atol=1e-5, rtol=0)


@pytest.mark.parametrize("impl", IMPLS)
def test_empty_and_all_culled_return_background(impl):
    V, K = camera()
    bg = torch.tensor([[0.25, 0.5, 0.75]], dtype=torch.float64)
    z = torch.zeros(0, dtype=torch.float64)
    rc, ra, meta = rasterization(z.view(0, 3), z.view(0, 4), z.view(0, 3), z, z.view(0, 16, 3), V[None], K[None],
                                 W, H, sh_degree=3, backgrounds=bg, backend="cpu")
    assert torch.allclose(rc, bg.view(1, 1, 1, 3).expand(1, H, W, 3)) and (ra == 0).all()
    assert meta["n_visible"].tolist() == [0]
    means, quats, scales, opac, sh = scene(n=8, seed=9)
    means[:, 2] = -means[:, 2]  # all behind the camera
    means[:4] = torch.tensor([100.0, 100.0, 3.0])  # and some far off-screen
    rc, ra, meta = rasterization(means, quats, scales, opac, sh, V[None], K[None], W, H, sh_degree=3,
                                 backgrounds=bg, backend="cpu")
    assert torch.allclose(rc, bg.view(1, 1, 1, 3).expand(1, H, W, 3)) and (ra == 0).all()
    assert (meta["radii"] == 0).all()
    rc, ra, _ = rasterization(means, quats, scales, opac, sh, V[None], K[None], W, H, sh_degree=3,
                              backend="cpu")
    assert (rc == 0).all() and (ra == 0).all()


@pytest.mark.parametrize("impl", IMPLS)
def test_gradients_finite_differences(impl):
    """Central differences (float64) through the whole pipeline for every input."""
    means, quats, scales, opac, sh = scene(n=4, seed=11, spread=0.35, depth=(2.0, 3.0))
    scales = scales * 2.0
    V, K = camera()
    g = torch.Generator().manual_seed(1)
    wc = torch.randn(H, W, 3, generator=g, dtype=torch.float64)
    wa = torch.randn(H, W, 1, generator=g, dtype=torch.float64)
    bg = torch.tensor([[0.3, 0.1, 0.2]], dtype=torch.float64)
    names = ["means", "quats", "scales", "opacities", "sh"]
    base = [means, quats, scales, opac, sh]

    def loss(ts):
        rc, ra, _ = rasterization(ts[0], ts[1], ts[2], ts[3], ts[4], V[None], K[None], W, H, sh_degree=3,
                                  backgrounds=bg, backend="cpu")
        return (rc[0] * wc).sum() + (ra[0] * wa).sum()

    params = [t.clone().requires_grad_() for t in base]
    loss(params).backward()
    eps = 1e-6
    for k, name in enumerate(names):
        ana = params[k].grad
        flat = base[k].reshape(-1)
        idx = range(flat.numel()) if flat.numel() <= 48 else torch.randperm(
            flat.numel(), generator=torch.Generator().manual_seed(k))[:48].tolist()
        for j in idx:
            plus = [t.clone() for t in base]
            minus = [t.clone() for t in base]
            plus[k].view(-1)[j] += eps
            minus[k].view(-1)[j] -= eps
            with torch.no_grad():
                num = (loss(plus) - loss(minus)) / (2 * eps)
            a = ana.reshape(-1)[j].item()
            assert abs(a - num.item()) <= 1e-5 + 1e-4 * abs(num.item()), (name, j, a, num.item())
    assert ana.abs().sum() > 0


@pytest.mark.parametrize("impl", IMPLS)
def test_means2d_retain_grad(impl):
    means, quats, scales, opac, sh = scene(n=10, seed=12)
    V, K = camera()
    means.requires_grad_()
    rc, ra, meta = rasterization(means, quats, scales, opac, sh, V[None], K[None], W, H, sh_degree=3,
                                 backend="cpu")
    meta["means2d"].retain_grad()
    rc.sum().backward()
    g2 = meta["means2d"].grad
    assert g2.shape == (1, 10, 2)
    vis = (meta["radii"][0] > 0).all(-1)
    assert (g2[0][~vis] == 0).all() and g2[0][vis].abs().sum() > 0


def test_dispatch_errors():
    means, quats, scales, opac, sh = scene(n=3, seed=13)
    V, K = camera()
    with pytest.raises(ValueError):
        rasterization(means, quats, scales, opac, sh, V[None], K[None], W, H, sh_degree=3, backend="vulkan")
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            rasterization(means, quats, scales, opac, sh, V[None], K[None], W, H, sh_degree=3, backend="gsplat")
