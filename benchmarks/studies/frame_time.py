"""Where a frame's time goes: projection (+ in-view test), LoD selection, rasterisation.

One :func:`clod_adapter.lod.draw.render_lod` frame is split into the projection of the Gaussians in
front of the camera (done once per frame and reused by the rasteriser), the LoD selection
(frustum, d', the Eq. 2 mask and the drawn opacities) and the rasterisation (finishing the
projection of the drawn set, colours, tiles, compositing). Inputs: the fern checkpoint with a
calibrated ``sigma_d`` (its adapted model when given) at ``images_2``, and a synthetic model of
1M Gaussians at 960x540; s_v = 1 and 5. Settings are interleaved and each median is over
``--repeats`` rounds after a warm-up, so machine load hits all alike; the spread (min-max over
rounds) is printed beside it:

    python -m benchmarks.studies.frame_time                      # fern + 1M synthetic
    python -m benchmarks.studies.frame_time --sizes 200000 --no-fern

Goal: selection <= 3 % of the frame.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

from clod_adapter.lod import rule as lod  # noqa: E402
from clod_adapter.train.loop import reference_distances  # noqa: E402
from clod_adapter.lod.draw import render_lod  # noqa: E402


def fern_model(adapted: str | None):
    from clod_adapter.io.load import load_model
    from clod_adapter.io.load import load_scene

    root = REPO.parent / "shared" / "data" / "fern"
    scene = load_scene(root, resolution=2)
    if adapted:
        return load_model(adapted), scene.test[0], "fern (adapted)"
    g = load_model(root / "pretrained/point_cloud/iteration_7000/point_cloud.ply")
    return calibrated(g, scene.train), scene.test[0], "fern (calibrated sigma_d)"


def calibrated(g, cams):
    from dataclasses import replace

    sd = lod.calibrate_sigma_d(g.opacities, g.opacities, reference_distances(g, cams))
    return replace(g.with_sigma_d(sd), lod=lod.LodSettings(fade="window"))


def synthetic(n: int):
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth

    g = make_ground_truth(n, seed=0)
    cams = make_cameras(1, 3, width=960, height=540)
    return calibrated(g, cams), cams[1], f"synthetic {n:,}"


@torch.no_grad()
def measure(model, cam, s_vs, repeats: int) -> dict:
    for s in s_vs:  # warm-up (extension load, allocator)
        render_lod(model, cam, s)
    rec = {s: [] for s in s_vs}
    for r in range(repeats):
        order = list(s_vs) if r % 2 == 0 else list(reversed(s_vs))
        for s in order:
            out = render_lod(model, cam, s)
            rec[s].append((out.project_ms, out.select_ms, out.raster_ms, out.n_rendered))
    res = {}
    for s, rows in rec.items():
        tot = [p + q + w for p, q, w, _ in rows]
        res[s] = {"project": statistics.median(r[0] for r in rows), "select": statistics.median(r[1] for r in rows),
                  "raster": statistics.median(r[2] for r in rows), "total": statistics.median(tot),
                  "total_min": min(tot), "total_max": max(tot), "drawn": rows[0][3],
                  "select_share": statistics.median(r[1] / t for r, t in zip(rows, tot))}
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="*", type=int, default=[1_000_000])
    ap.add_argument("--no-fern", action="store_true")
    ap.add_argument("--adapted", default=None, help="an adapted fern .ply (default: calibrated sigma_d)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cases = []
    if not args.no_fern and (REPO.parent / "shared" / "data" / "fern").is_dir():
        cases.append(fern_model(args.adapted))
    cases += [synthetic(n) for n in args.sizes]
    print(f"{torch.get_num_threads()} threads, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}; "
          f"median of {args.repeats} interleaved rounds (ms)")
    print(f"{'model':<28}{'s_v':>5}{'drawn':>11}{'project':>9}{'select':>8}{'raster':>9}{'total':>9}"
          f"{'(min-max)':>16}{'select %':>9}")
    for model, cam, name in cases:
        t = time.perf_counter()
        res = measure(model, cam, (1.0, 5.0), args.repeats)
        for s, r in res.items():
            print(f"{name:<28}{s:5.0f}{r['drawn']:11,}{r['project']:9.1f}{r['select']:8.1f}{r['raster']:9.1f}"
                  f"{r['total']:9.1f}{'(' + format(r['total_min'], '.0f') + '-' + format(r['total_max'], '.0f') + ')':>16}"
                  f"{100 * r['select_share']:8.1f}%", flush=True)
        print(f"  ({len(model):,} Gaussians, {cam.width}x{cam.height}; {time.perf_counter() - t:.0f} s)")


if __name__ == "__main__":
    main()
