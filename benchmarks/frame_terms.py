"""The per-frame LoD terms on the centres' cached rows against the same arithmetic on [N, 3].

Every ``s_v`` frame tests all N centres against the frustum and takes their distances to the
camera (:func:`clod_adapter.lod.in_frustum`, :func:`clod_adapter.lod.normalized_distances`)
before it knows what it draws: O(N) work that a coarse level pays in full. Both run on the
centres' cached [3, N] rows (:func:`clod_adapter.lod.centre_columns`); this times them against
the [N, 3] form they replaced (a [N, 3] x [3, 3] product and a division per coordinate; the
distances as ``(mu - c)^2 @ 1``), interleaved in one run, random centres in front of a 960x540
camera, 2 threads. Goal: the rows at least 2x faster at 1,000,000 centres; exit 1 when missed.
At 60,000 centres both forms are dominated by OpenMP's wake-up of the second thread for every
elementwise operation over more than 32,768 elements under ``OMP_WAIT_POLICY=PASSIVE`` (the CLIs'
default, set here too: about 0.1 ms per operation, against 8 us with ``ACTIVE``), and the rows
form has more, cheaper operations (about 40): it is printed, not held to the goal::

    python benchmarks/frame_terms.py                 # 60,000 and 1,000,000 centres
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clod_adapter import lod  # noqa: E402

GOAL = 2.0
#: the size the goal applies to (module docstring)
GOAL_SIZE = 1_000_000


def rows_form(means, vm, K, w, h):
    fr = lod.in_frustum(means, vm, K, w, h)
    return fr, lod.normalized_distances(means, lod.camera_center(vm), fr)


def n3_form(means, vm, K, w, h):
    pc = means @ vm[:3, :3].T + vm[:3, 3]
    z = pc[:, 2]
    front = z > 0.01
    zs = torch.where(front, z, torch.ones_like(z))
    u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    fr = front & (u >= 0) & (u < w) & (v >= 0) & (v < h) & torch.isfinite(u) & torch.isfinite(v)
    d = ((means - lod.camera_center(vm)).square() @ torch.ones(3)).sqrt()
    return fr, d / torch.where(fr, d, torch.zeros(())).max().clamp_min(1e-12)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[60_000, 1_000_000])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    vm = torch.eye(4)
    vm[2, 3] = 4.0
    K = torch.tensor([[800.0, 0, 480], [0, 800.0, 270], [0, 0, 1]])
    ok = True
    with torch.no_grad():
        for n in a.sizes:
            means = torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
            fa, da = rows_form(means, vm, K, 960, 540)
            fb, db = n3_form(means, vm, K, 960, 540)
            assert torch.equal(fa, fb) and torch.allclose(da, db, rtol=1e-5, atol=1e-6)
            times = {"rows": [], "n3": []}
            for _ in range(a.repeats):  # interleaved rounds
                for name, f in (("rows", rows_form), ("n3", n3_form)):
                    t0 = time.perf_counter()
                    f(means, vm, K, 960, 540)
                    times[name].append((time.perf_counter() - t0) * 1e3)
            r, q = statistics.median(times["rows"]), statistics.median(times["n3"])
            verdict = "printed only"
            if n >= GOAL_SIZE:
                ok &= q / r >= GOAL
                verdict = f"{'ok' if q / r >= GOAL else 'MISS'}, goal {GOAL:g}x"
            print(f"{n:>9,} centres: rows {r:.2f} ms, [N, 3] {q:.2f} ms per frame: {q / r:.1f}x ({verdict})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
