"""Benchmark of the per-pixel compositor: C++/OpenMP (its vector rows, and its scalar rows alone)
vs the PyTorch twin.

Synthetic 2D splats approximating a real scene after projection: centres
spread over (and slightly beyond) the image, log-normal-ish screen radii of
a few to tens of pixels, random anisotropy/rotation, opacities skewed high,
tile lists from a 3-sigma bounding box sorted by a random depth.

Usage:  python -m benchmarks.studies.composite [--configs 10000:128,50000:256,200000:512]
        [--repeat 3] [--skip-torch-above 0]

Prints, per config: intersections, mean list length, forward and
forward+backward time of cpp (vector rows where the CPU has AVX2/FMA), cpp-scalar (the scalar
rows alone, ``composite.simd_rows(False)``) and torch, their ratios, and the peak RSS delta.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from clod_adapter.render.composite import use_impl  # noqa: E402
from clod_adapter.render.composite import (  # noqa: E402
    cpp_extension_available,
    rasterize_to_pixels,
    simd_rows,
)

torch.set_num_threads(2)


def bin_tiles(means2d, radii, width, height, tile_size, depths):
    N = means2d.shape[0]
    th = (height + tile_size - 1) // tile_size
    tw = (width + tile_size - 1) // tile_size
    mx, my, r = means2d[:, 0].double(), means2d[:, 1].double(), radii.double()
    vis = (mx + r >= 0) & (mx - r < width) & (my + r >= 0) & (my - r < height)
    tx0 = torch.floor((mx - r) / tile_size).clamp(0, tw - 1).long()
    tx1 = torch.floor((mx + r) / tile_size).clamp(0, tw - 1).long()
    ty0 = torch.floor((my - r) / tile_size).clamp(0, th - 1).long()
    ty1 = torch.floor((my + r) / tile_size).clamp(0, th - 1).long()
    nx, ny = tx1 - tx0 + 1, ty1 - ty0 + 1
    cnt = torch.where(vis, nx * ny, torch.zeros_like(nx))
    gid = torch.repeat_interleave(torch.arange(N), cnt)
    local = torch.arange(gid.numel()) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
    tile = (ty0[gid] + torch.div(local, nx[gid], rounding_mode="floor")) * tw + tx0[gid] + local % nx[gid]
    rank = torch.empty(N, dtype=torch.long)
    rank[torch.argsort(depths)] = torch.arange(N)
    order = torch.argsort(tile * N + rank[gid])
    ids = gid[order]
    offsets = torch.searchsorted(tile[order], torch.arange(th * tw)).to(torch.int32)
    return offsets.reshape(th, tw), ids


def make_scene(N, size, tile_size=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    W = H = size
    means2d = torch.rand(N, 2, generator=g, dtype=torch.float64) * (size * 1.1) - size * 0.05
    # screen-space std-dev: median ~1.5 px scaled with resolution (a scene
    # projected at 512 has ~the same splats as at 128 but 4x larger), tail to
    # tens of pixels (3-sigma radius)
    base = size / 512.0
    logs = torch.randn(N, 2, generator=g, dtype=torch.float64) * 0.6 + math.log(1.6 * max(base, 0.35))
    s = torch.exp(logs).clamp(0.3, 12.0)
    ang = torch.rand(N, generator=g, dtype=torch.float64) * math.pi
    c, sn = torch.cos(ang), torch.sin(ang)
    R = torch.stack([torch.stack([c, -sn], -1), torch.stack([sn, c], -1)], -2)
    cov = R @ torch.diag_embed(s * s) @ R.transpose(-1, -2)
    cov = cov + 0.3 * torch.eye(2, dtype=torch.float64)  # gsplat-style blur
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    # opacities: trained scenes are bimodal; mix of near-opaque and faint
    u = torch.rand(N, generator=g, dtype=torch.float64)
    opac = torch.where(u < 0.5, 0.6 + 0.39 * torch.rand(N, generator=g, dtype=torch.float64),
                       0.02 + 0.5 * torch.rand(N, generator=g, dtype=torch.float64))
    colors = torch.rand(N, 3, generator=g, dtype=torch.float64)
    depths = torch.rand(N, generator=g, dtype=torch.float64)
    eig = torch.linalg.eigvalsh(cov)
    radii = 3.0 * eig[:, -1].sqrt()
    offsets, ids = bin_tiles(means2d, radii, W, H, tile_size, depths)
    f = torch.float32
    return dict(means2d=means2d.to(f), conics=conics.to(f), colors=colors.to(f),
                opacities=opac.to(f), width=W, height=H, tile_size=tile_size,
                isect_offsets=offsets, flatten_ids=ids)


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run(scene, impl, backward):
    leaves = [scene[k].clone().requires_grad_(backward)
              for k in ("means2d", "conics", "colors", "opacities")]
    t0 = time.perf_counter()
    with use_impl("cpp" if impl.startswith("cpp") else impl), \
            simd_rows(impl != "cpp-scalar") if impl.startswith("cpp") else contextlib.nullcontext():
        img, alpha = rasterize_to_pixels(*leaves, scene["width"], scene["height"], scene["tile_size"],
                                         scene["isect_offsets"], scene["flatten_ids"])
    if backward:
        (img.sum() + alpha.sum()).backward()
    return time.perf_counter() - t0, img.detach()


def bench(scene, impl, repeat):
    run(scene, impl, False)  # warm-up
    rss0 = peak_rss_mb()
    fwd = min(run(scene, impl, False)[0] for _ in range(repeat))
    fb = min(run(scene, impl, True)[0] for _ in range(repeat))
    return fwd, fb, peak_rss_mb() - rss0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--configs", default="10000:128,50000:256,200000:512")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--skip-torch-above", type=int, default=0,
                    help="skip the torch twin for N above this (0: never skip)")
    args = ap.parse_args()
    print(f"threads={torch.get_num_threads()} OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')} "
          f"cpp={'yes' if cpp_extension_available() else 'NO'}")
    hdr = (f"{'N':>7} {'size':>5} {'isects':>9} {'len/tile':>8} | {'impl':>10} {'fwd s':>8} "
           f"{'fwd+bwd s':>9} {'bwd s':>8} {'dRSS MB':>8}")
    print(hdr)
    print("-" * len(hdr))
    for cfg in args.configs.split(","):
        n, size = (int(v) for v in cfg.split(":"))
        scene = make_scene(n, size)
        M = scene["flatten_ids"].numel()
        ntiles = scene["isect_offsets"].numel()
        res = {}
        impls = ["cpp", "cpp-scalar"] if cpp_extension_available() else []
        if not args.skip_torch_above or n <= args.skip_torch_above:
            impls.append("torch")
        for impl in impls:
            reps = args.repeat if impl.startswith("cpp") else 1
            fwd, fb, drss = bench(scene, impl, reps)
            res[impl] = (fwd, fb)
            print(f"{n:>7} {size:>5} {M:>9} {M / ntiles:>8.0f} | {impl:>10} {fwd:>8.4f} {fb:>9.4f} "
                  f"{fb - fwd:>8.4f} {drss:>8.1f}", flush=True)
        if "cpp" in res and "cpp-scalar" in res:
            print(f"{'':>33}   ratio cpp-scalar/cpp: fwd {res['cpp-scalar'][0] / res['cpp'][0]:.2f}x, "
                  f"fwd+bwd {res['cpp-scalar'][1] / res['cpp'][1]:.2f}x")
        if "cpp" in res and "torch" in res:
            print(f"{'':>33}   ratio torch/cpp: fwd {res['torch'][0] / res['cpp'][0]:.1f}x, "
                  f"fwd+bwd {res['torch'][1] / res['cpp'][1]:.1f}x")
        if "cpp" in res and "torch" in res:
            _, a = run(scene, "cpp", False)
            _, b = run(scene, "torch", False)
            print(f"{'':>33}   max |cpp - torch| image: {(a - b).abs().max().item():.2e}")


if __name__ == "__main__":
    main()
