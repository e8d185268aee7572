"""Speed of data-parallel fine-tuning on this machine: 2 gloo ranks against 1 process, the same
total views.

Usage: python -m benchmarks.studies.distributed_speedup [--inputs demo|fern|...] [--input NAME=PLY:SCENE[:RES]]
       [--iterations 60] [--rounds 3]

Every configuration runs ``clod-adapt`` with ``--views-per-step 2`` (two views per step, so the
same views at the same s_v whatever the number of processes) for ``--iterations`` steps, and
its training time is read from ``metrics.json`` (``train_seconds``: the loop only, not reading
the inputs or the evaluation):

* ``1 process x 2 threads``: the single-process run with both cores;
* ``2 ranks x 1 thread``: ``torchrun --nproc_per_node=2`` (gloo on loopback, OMP_NUM_THREADS=1);
* ``1 process x 1 thread``: what one rank does alone, for reference.

The configurations are interleaved over ``--rounds`` rounds (a burst of load from another
process hits all of them alike); the table gives the median s/step with the fastest and slowest
round, and the speed-up against ``1 process x 2 threads``. The machine's 1-minute load average
is printed: on a shared 2-core machine this is not an idle measurement unless it is near 0.
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, add_inputs_args, resolve_input, selected_inputs, table  # noqa: E402

CONFIGS = {
    "1 process x 2 threads": {"procs": 1, "threads": 2},
    "2 ranks x 1 thread (gloo)": {"procs": 2, "threads": 1},
    "1 process x 1 thread": {"procs": 1, "threads": 1},
}


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_once(cfg: dict, ply: Path, scene: Path, res: int, iterations: int, out: Path) -> float:
    """Seconds per step of one configuration (``train_seconds / iterations``)."""
    args = ["-m", "clod_adapter.cli.adapt", str(ply), "--images", str(scene), "--resolution", str(res), "-o", str(out),
            "--iterations", str(iterations), "--views-per-step", "2", "--timing-repeats", "0", "--quiet",
            "--force"]
    env = dict(os.environ, OMP_NUM_THREADS=str(cfg["threads"]), OMP_WAIT_POLICY="PASSIVE", PYTHONPATH=str(REPO))
    for k in ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT", "LOCAL_RANK"):
        env.pop(k, None)
    if cfg["procs"] > 1:
        cmd = [sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={cfg['procs']}",
               "--master_addr=127.0.0.1", f"--master_port={_port()}", *args]
    else:
        cmd = [sys.executable, *args]
    r = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"distributed_speedup: {' '.join(cmd)} failed:\n{r.stderr[-3000:]}")
    m = json.loads((out / "metrics.json").read_text())
    return m["train_seconds"] / iterations


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_inputs_args(p, ["demo"])
    p.add_argument("--iterations", type=int, default=60)
    p.add_argument("--rounds", type=int, default=3)
    args = p.parse_args(argv)
    for name in selected_inputs(args):
        run_input(name, args)
    return 0


def run_input(name: str, args) -> None:
    """Time every configuration on one input and print its table."""
    ply, scene, res = resolve_input(name)
    load0 = os.getloadavg()[0]
    times = {k: [] for k in CONFIGS}
    with tempfile.TemporaryDirectory() as tmp:
        for rnd in range(args.rounds):
            for label, cfg in CONFIGS.items():
                t0 = time.perf_counter()
                s = run_once(cfg, ply, scene, res, args.iterations, Path(tmp) / f"o{rnd}_{cfg['procs']}_{cfg['threads']}")
                times[label].append(s)
                print(f"[{name}] round {rnd + 1}/{args.rounds}: {label}: {s:.3f} s/step ({time.perf_counter() - t0:.0f} s wall)",
                      file=sys.stderr, flush=True)
    load1 = os.getloadavg()[0]
    base = sorted(times["1 process x 2 threads"])[len(times["1 process x 2 threads"]) // 2]
    rows = []
    for label, ts in times.items():
        med = sorted(ts)[len(ts) // 2]
        rows.append([label, f"{med:.3f}", f"{min(ts):.3f}-{max(ts):.3f}", f"{base / med:.2f}"])
    print(f"input {name} ({ply.name}), {args.iterations} steps of 2 views, {args.rounds} interleaved rounds; "
          f"1-min load average {load0:.1f} at the start, {load1:.1f} at the end\n")
    print(table(["configuration", "s/step (median)", "range over rounds", "speed-up vs 1 x 2 threads"], rows,
                "---|---:|---:|---:|"))


if __name__ == "__main__":
    sys.exit(main())
