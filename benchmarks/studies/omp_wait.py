"""OpenMP wait policy and thread count against machine load: seconds per adaptation step.

    python -m benchmarks.studies.omp_wait [--iterations 30] [--loads 0,1,2] [--configs default,passive,passive1]

Each configuration runs in a fresh Python process (OpenMP reads ``OMP_WAIT_POLICY`` when torch
loads it): the demo scene (6,000 Gaussians, 160x120, as ``clod-adapt --demo``) is built in memory,
``sigma_d`` attached (fixed attenuation 0.99, no calibration), 5 untimed steps, then
``--iterations`` timed steps of :func:`clod_adapter.train.loop.fit`. ``--loads``: how many competing
busy processes (pure-Python spin loops, one core each) run meanwhile. Configurations:

* ``default``: ``OMP_WAIT_POLICY`` unset (libgomp's default: idle threads spin before sleeping),
  ``OMP_NUM_THREADS=2``;
* ``active``: ``OMP_WAIT_POLICY=ACTIVE`` (always spin), 2 threads;
* ``passive``: ``OMP_WAIT_POLICY=PASSIVE`` (what the CLIs set by default), 2 threads;
* ``passive1``: ``PASSIVE`` and ``OMP_NUM_THREADS=1``.

Prints s/it per configuration and load, and the ratio to ``passive`` measured in the same run.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

CONFIGS = {
    "default": {"OMP_NUM_THREADS": "2"},
    "active": {"OMP_NUM_THREADS": "2", "OMP_WAIT_POLICY": "ACTIVE"},
    "passive": {"OMP_NUM_THREADS": "2", "OMP_WAIT_POLICY": "PASSIVE"},
    "passive1": {"OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"},
}

CHILD = r"""
import json, sys, time
import torch
from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.loop import fit, prepare
from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb
from clod_adapter.render import rasterization
iters = int(sys.argv[1])
gt = make_ground_truth(6000, seed=0)
cams = make_cameras()
imgs = []
with torch.no_grad():
    for c in cams:
        col, _, _ = rasterization(gt.means, gt.quats, gt.scales, gt.opacities, gt.colors, c.viewmat[None],
                                  c.K[None], c.width, c.height, sh_degree=gt.sh_degree, backend="cpu")
        imgs.append(col[0].clamp(0, 1))
cfg = AdaptConfig(max_sv=5.0, iterations=iters + 5, init_attenuation=0.99)
state = prepare(perturb(gt, 1), cams, cfg, backend="cpu")
fit(state, cams, imgs, cfg, backend="cpu", progress=False, max_steps=5)
t0 = time.perf_counter()
fit(state, cams, imgs, cfg, backend="cpu", progress=False, max_steps=iters)
dt = time.perf_counter() - t0
print(json.dumps({"s_per_it": dt / iters, "threads": torch.get_num_threads()}))
"""


def _spin(stop_at: float) -> None:
    x = 0
    while time.time() < stop_at:
        x += 1


def run_config(name: str, iters: int, load: int) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS", "GOMP_SPINCOUNT")}
    env.update(CONFIGS[name])
    env.setdefault("TORCH_EXTENSIONS_DIR", str(REPO / ".torch_extensions"))
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    procs = [mp.Process(target=_spin, args=(time.time() + 3600,), daemon=True) for _ in range(load)]
    for p in procs:
        p.start()
    try:
        r = subprocess.run([sys.executable, "-c", CHILD, str(iters)], env=env, capture_output=True,
                           text=True, timeout=3600)
    finally:
        for p in procs:
            p.terminate()
            p.join()
    if r.returncode != 0:
        raise SystemExit(f"{name}: child failed:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--loads", default="0,1,2", help="competing busy processes, comma-separated")
    ap.add_argument("--configs", default="default,active,passive,passive1")
    args = ap.parse_args(argv)
    loads = [int(x) for x in args.loads.split(",")]
    names = [x for x in args.configs.split(",") if x]
    print(f"cores: {os.cpu_count()}, load average at start: {os.getloadavg()[0]:.2f} "
          f"(other users of the machine count too)")
    run_config("passive", 2, 0)  # make sure the extension is built before timing
    res = {}
    for load in loads:
        for n in names:
            res[(n, load)] = run_config(n, args.iterations, load)["s_per_it"]
            print(f"  load {load}, {n:9s}: {res[(n, load)]:.3f} s/it", flush=True)
    print()
    print("| config | " + " | ".join(f"{ld} busy: s/it | x passive" for ld in loads) + " |")
    print("|---|" + "---:|---:|" * len(loads))
    for n in names:
        cells = []
        for ld in loads:
            base = res.get(("passive", ld))
            cells.append(f"{res[(n, ld)]:.3f} | {res[(n, ld)] / base:.2f}" if base else f"{res[(n, ld)]:.3f} | -")
        print(f"| {n} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
