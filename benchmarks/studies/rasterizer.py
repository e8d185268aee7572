"""Benchmark the CPU rasterizer (projection + SH + binning + compositor), 2 threads.

Usage: python -m benchmarks.studies.rasterizer [--quick] [--profile] [--sizes 10000,50000,200000]
       [--res 128,256,512] [--torch-limit 20]

Scenes: N Gaussians in front of a pinhole camera (depth 2..10, inside the frustum), SH
degree 3, opacities 0.05..0.95, anisotropic scales giving screen radii log-uniform in
~2..30 px. Timings: best of --reps runs after a warm-up (the 2 cores may be shared). Peak memory: ru_maxrss delta
(process high-water mark, so it only grows across rows; the first row that raises it is
the one that needs it).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")

import argparse  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from clod_adapter.render import rasterization  # noqa: E402
from clod_adapter.render.composite import use_impl  # noqa: E402

torch.set_num_threads(2)


def make_scene(n: int, res: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    W = H = res
    f = 0.9 * res
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    V = torch.eye(4)
    z = torch.empty(n).uniform_(2.0, 10.0, generator=g)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([W / f, H / f]) * 1.1 * z[:, None]
    means = torch.cat([xy, z[:, None]], 1)
    r_px = torch.exp(torch.empty(n).uniform_(math.log(2.0), math.log(30.0), generator=g))
    s = r_px * z / (3.0 * f)  # radius ~ 3 sigma f / z
    scales = s[:, None] * torch.empty(n, 3).uniform_(0.3, 1.0, generator=g)
    quats = torch.randn(n, 4, generator=g)
    opac = torch.empty(n).uniform_(0.05, 0.95, generator=g)
    sh = torch.randn(n, 16, 3, generator=g) * 0.2
    return means, quats, scales, opac, sh, V[None], K[None], W, H


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def time_it(fn, reps):
    fn()  # warm-up (and C++ extension build)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)  # best of reps: robust to other processes sharing the 2 cores


def run(n, res, impl, reps, backward):
    means, quats, scales, opac, sh, V, K, W, H = make_scene(n, res)
    params = [t.clone().requires_grad_(backward) for t in (means, quats, scales, opac, sh)]

    def fwd():
        with torch.set_grad_enabled(backward):
            with use_impl(impl):
                rc, ra, meta = rasterization(*params, V, K, W, H, sh_degree=3, backend="cpu")
        if backward:
            (rc.sum() + ra.sum()).backward()
            for p in params:
                p.grad = None
        return meta

    return time_it(fwd, reps)


def profile(n, res):
    from clod_adapter.render.projection import project_visible
    from clod_adapter.render.sh import spherical_harmonics
    from clod_adapter.render.tiles import isect_offset_encode, isect_tiles

    means, quats, scales, opac, sh, V, K, W, H = make_scene(n, res)
    params = [t.clone().requires_grad_() for t in (means, quats, scales, opac, sh)]
    ts = 16
    tw, th = math.ceil(W / ts), math.ceil(H / ts)
    out = {}
    p = project_visible(params[0], params[1], params[2], params[3], V[0], K[0], W, H)
    out["project"] = time_it(lambda: project_visible(params[0], params[1], params[2], params[3], V[0], K[0], W, H), 5)
    ids = p.ids
    campos = torch.linalg.inv(V[0])[:3, 3]
    out["sh"] = time_it(lambda: torch.clamp_min(spherical_harmonics(
        3, params[0].index_select(0, ids) - campos, params[4].index_select(0, ids)) + 0.5, 0), 5)
    out["isect_tiles"] = time_it(lambda: isect_tiles(p.means2d, p.radii, p.depths, ts, tw, th), 5)
    _, iid, fl = isect_tiles(p.means2d, p.radii, p.depths, ts, tw, th)
    out["offset_encode"] = time_it(lambda: isect_offset_encode(iid, tw, th), 5)

    def front_bwd():
        q = project_visible(params[0], params[1], params[2], params[3], V[0], K[0], W, H)
        col = spherical_harmonics(3, params[0].index_select(0, q.ids) - campos, params[4].index_select(0, q.ids))
        (q.means2d.sum() + q.conics.sum() + col.sum()).backward()
        for t in params:
            t.grad = None
    out["project+sh fwd+bwd"] = time_it(front_bwd, 5)
    print(f"profile N={n} {res}x{res}: visible={ids.numel()} intersections={iid.numel()}")
    for k, v in out.items():
        print(f"  {k:22s} {v * 1e3:8.1f} ms")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="10000,50000,200000")
    ap.add_argument("--res", default="128,256,512")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--torch-limit", type=float, default=20.0,
                    help="skip impl='torch' when its estimated fwd+bwd time exceeds this (s)")
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    ress = [int(r) for r in args.res.split(",")]
    print(f"torch {torch.__version__}, threads={torch.get_num_threads()}, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}")
    if args.profile:
        profile(max(sizes), max(ress))
    print("peak memory: ru_maxrss delta of the process (MiB), measured over the cpp rows then torch rows")
    hdr = f"{'N':>7} {'res':>5} | {'cpp fwd':>9} {'cpp f+b':>9} | {'torch fwd':>9} {'torch f+b':>9} | {'fwd x':>6} {'f+b x':>6} | {'dRSS MiB':>8}"
    print(hdr)
    print("-" * len(hdr))
    for n in sizes:
        for res in ress:
            r0 = rss_mb()
            cf = run(n, res, "cpp", args.reps, False)
            cb = run(n, res, "cpp", args.reps, True)
            # estimate the torch twin's cost from one forward before measuring it properly
            tf = tb = None
            est = run_once(n, res, "torch") * 3.5
            if est <= args.torch_limit:
                tf = run(n, res, "torch", 1, False)
                tb = run(n, res, "torch", 1, True)
            dr = rss_mb() - r0
            fmt = lambda x: f"{x * 1e3:8.0f}m" if x is not None else "  skipped"  # noqa: E731
            ratio = lambda a, b: f"{a / b:6.1f}" if a is not None else "     -"  # noqa: E731
            print(f"{n:>7} {res:>5} | {fmt(cf)} {fmt(cb)} | {fmt(tf)} {fmt(tb)} | {ratio(tf, cf)} {ratio(tb, cb)} | {dr:8.0f}",
                  flush=True)
    print("m = milliseconds; x = torch/cpp time ratio (same run); torch skipped when one forward x3.5 > "
          f"{args.torch_limit:.0f} s (estimated fwd+bwd).")


def run_once(n, res, impl):
    means, quats, scales, opac, sh, V, K, W, H = make_scene(n, res)
    t0 = time.perf_counter()
    with torch.no_grad():
        with use_impl(impl):
            rasterization(means, quats, scales, opac, sh, V, K, W, H, sh_degree=3, backend="cpu")
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()
