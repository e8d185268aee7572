"""Data-parallel fine-tuning (``torchrun ... -m clod_adapter.cli.adapt``, gloo, 2 ranks on loopback).

* 2 ranks x ITERATIONS steps (one view each per step) give the same parameters, Adam moments,
  history and .ply as 1 process with ``--views-per-step 2`` doing the same views at the same
  per-view s_v, in deterministic mode with 1 thread per process. Tolerance: 1e-6 absolute on
  every tensor (float32); with two ranks the sum of two gradients is exact in either order, so
  the runs are in fact bit-identical, which the test also reports through the .ply bytes;
* a rank killed mid-run makes the other exit 1 with one line naming the state on disk, which
  is intact (the last periodic save); ``--resume`` with 1 process continues it to the end, and
  the result equals the uninterrupted run;
* the flag checks: ``--distributed`` outside torchrun, ``--demo`` with it.

Every subprocess has a timeout, and the collectives one of 60 s (``CLOD_DIST_TIMEOUT``).
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.state import load_state
from conftest import REPO, write_tiny_scene

ITERATIONS = 24
MAX_SV = 3.0
SEED = 3
STATE = "adapt_state.safetensors"
ATOL = 1e-6


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(**extra) -> dict:
    env = dict(os.environ)
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT", "TORCHELASTIC_RUN_ID",
              "CLOD_DETERMINISTIC", "CLOD_PROGRESS_FILE"):
        env.pop(k, None)
    # gloo on the loopback interface whatever the host name resolves to
    env.update({"OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO), "CLOD_DIST_TIMEOUT": "60",
                "GLOO_SOCKET_IFNAME": "lo"}, **extra)
    return env


def _args(scene: Path, out: Path, *extra) -> list[str]:
    return ["-m", "clod_adapter.cli.adapt", str(scene / "in.ply"), "--images", str(scene / "scene"), "-o", str(out),
            "--max-sv", str(MAX_SV), "--seed", str(SEED), "--deterministic", "--quiet", "--timing-repeats", "0",
            *extra]


def _inprocess(scene: Path, out: Path, **kw) -> dict:
    """``clod-adapt`` in this process with 1 thread (as each rank), deterministic: the same
    results bit for bit as a subprocess with OMP_NUM_THREADS=1 (tests/test_resume.py)."""
    from clod_adapter.jobs.adapt import AdaptOptions, run

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cfg = AdaptConfig(max_sv=MAX_SV, iterations=ITERATIONS, seed=SEED, views_per_step=2)
        return run(scene / "in.ply", scene / "scene", out, cfg, AdaptOptions(
            device="cpu", progress=False, log=lambda *a: None, deterministic=True, timing_repeats=0, **kw))
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("dist")
    write_tiny_scene(root, n=300, rows=2, cols=4, width=48, height=36, seed=6)
    _inprocess(root, root / "ref")  # the reference: one process, the same two views per step
    return root


def _assert_close_runs(out: Path, ref: Path) -> None:
    a, ca, _ = load_state(out / STATE)
    b, cb, _ = load_state(ref / STATE)
    assert a.iteration == b.iteration == ITERATIONS
    assert ca.views_per_step == cb.views_per_step == 2
    assert len(a.history["loss"]) == 2 * ITERATIONS  # one record per view
    assert a.order == b.order and torch.equal(a.generator.get_state(), b.generator.get_state())
    assert a.history["s_v"] == b.history["s_v"]  # the same schedule
    for k in ("loss", "psnr", "eta"):
        torch.testing.assert_close(torch.tensor(a.history[k]), torch.tensor(b.history[k]), rtol=0, atol=2e-3)
    for k in b.params:
        torch.testing.assert_close(a.params[k].detach(), b.params[k].detach(), rtol=0, atol=ATOL, msg=k)
    for ga, gb in zip(a.optimizer.param_groups, b.optimizer.param_groups):
        sa, sb = a.optimizer.state[ga["params"][0]], b.optimizer.state[gb["params"][0]]
        for key in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(sa[key], sb[key], rtol=0, atol=ATOL, msg=f"{ga['name']} {key}")
    # not required by the tolerance above, but what two gloo ranks give in deterministic mode
    assert (out / "point_cloud.ply").read_bytes() == (ref / "point_cloud.ply").read_bytes()


def test_two_ranks_equal_one_process_with_two_views_per_step(scene, tmp_path):
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_addr=127.0.0.1",
           f"--master_port={_free_port()}", *_args(scene, out, "--iterations", str(ITERATIONS))]
    r = subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    import json

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["world_size"] == 2 and metrics["config"]["views_per_step"] == 2
    _, _, meta = load_state(out / STATE)
    assert meta["world_size"] == "2" and meta["threads"] == "1"
    _assert_close_runs(out, scene / "ref")


def _wait_for(progress: Path, procs, at_least: int, timeout: float = 120.0) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        for p in procs:
            if p.poll() is not None:
                raise AssertionError(f"a rank ended (exit {p.returncode}) early: {p.stderr.read()[-2000:]}")
        try:
            if int(progress.read_text().strip() or 0) >= at_least:
                return
        except (OSError, ValueError):
            pass
        time.sleep(0.005)
    raise AssertionError(f"no iteration {at_least} within {timeout} s")


def test_killed_rank_exits_nonzero_state_intact_resume_with_one_process(scene, tmp_path):
    out, progress = tmp_path / "out", tmp_path / "progress"
    port = _free_port()
    args = _args(scene, out, "--iterations", str(ITERATIONS), "--distributed", "--save-every", "3")
    procs = []
    try:
        for rank in (0, 1):
            extra = {"CLOD_PROGRESS_FILE": str(progress)} if rank == 0 else {}
            env = _env(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), WORLD_SIZE="2", RANK=str(rank),
                       LOCAL_RANK=str(rank), **extra)
            procs.append(subprocess.Popen([sys.executable, *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                                          stderr=subprocess.PIPE, text=True))
        _wait_for(progress, procs, 7)
        procs[1].send_signal(signal.SIGSTOP)  # rank 0 can now do at most one more step
        time.sleep(0.2)
        procs[1].kill()
        _, err = procs[0].communicate(timeout=120)
        procs[1].wait(timeout=30)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert procs[0].returncode == 1, err[-2000:]
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert "Traceback" not in err
    assert lines[-1].startswith("clod-adapt: error: rank 0 of 2: lost contact with the other processes"), lines[-1]
    st, cfg, meta = load_state(out / STATE)  # intact: it loads, at a periodic save
    assert st.iteration % 3 == 0 and 6 <= st.iteration < ITERATIONS
    assert f"holds iteration {st.iteration} " in lines[-1]
    assert cfg.views_per_step == 2 and meta["world_size"] == "2"
    assert sorted(p.name for p in out.iterdir()) == [STATE]  # no outputs, no temp files

    # resume with another world size (1 process)
    _inprocess(scene, out, resume=True)
    _assert_close_runs(out, scene / "ref")


def test_flag_errors(tmp_path, capsys, monkeypatch):
    from clod_adapter.cli.adapt import main

    for k in ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    assert main(["x.ply", "--images", "s", "--distributed", "-o", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--distributed: RANK, WORLD_SIZE, MASTER_ADDR, MASTER_PORT are not set" in err
    assert main(["--demo", "--views-per-step", "0", "-o", str(tmp_path / "b")]) == 2
    assert "--views-per-step must be >= 1" in capsys.readouterr().err
    monkeypatch.setenv("MASTER_ADDR", "127.0.0.1")
    monkeypatch.setenv("MASTER_PORT", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    assert main(["--demo", "-o", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--demo runs in one process" in err
    assert not any(tmp_path.iterdir())  # nothing written


def test_views_per_step_is_the_mean_of_the_views():
    """In one process, ``views_per_step = 2`` takes one Adam step on the mean of two views'
    gradients, drawn (view, s_v, view, s_v) from the seeded schedule (bit-exact: the compositor's
    threaded gradient sums in their deterministic order)."""
    from clod_adapter.render.composite import deterministic_enabled, set_deterministic

    was = deterministic_enabled()
    set_deterministic(True)
    try:
        _check_views_per_step()
    finally:
        set_deterministic(was)


def _check_views_per_step():
    from clod_adapter.train.loop import fit, prepare, view_loss
    from clod_adapter.lod import rule as lod
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb
    from conftest import render_views

    gt = make_ground_truth(300, seed=2)
    cams = make_cameras(2, 3, width=40, height=30)
    imgs = render_views(gt, cams)
    cfg = AdaptConfig(max_sv=3.0, iterations=3, seed=1, views_per_step=2)
    st = prepare(perturb(gt, 3), cams, cfg)
    ref = prepare(perturb(gt, 3), cams, cfg)
    assert fit(st, cams, imgs, cfg, progress=False, max_steps=1) is False
    # by hand: the same draws, the mean gradient, one step
    gen = torch.Generator().manual_seed(1)
    order = torch.randperm(len(cams), generator=gen).tolist()
    picks = []
    for _ in range(2):
        vi = order.pop()
        picks.append((vi, lod.sample_s_v(3.0, gen, cfg.s_v_sampling)))
    g = ref.gaussians()
    ref.optimizer.zero_grad(set_to_none=True)
    for vi, s_v in picks:
        _, loss = view_loss(g, cams[vi], imgs[vi], s_v, cfg, "cpu")
        loss.backward()
    for p in ref.params.values():
        if p.grad is not None:
            p.grad /= 2
    ref.optimizer.step()
    assert st.history["s_v"] == [round(s, 4) for _, s in picks]
    assert st.order == order
    for k in ref.params:
        torch.testing.assert_close(st.params[k].detach(), ref.params[k].detach(), rtol=0, atol=0, msg=k)


def test_view_images_keep_within_budget():
    from clod_adapter.io.view_images import ViewImages

    class FakeScene:
        def __init__(self):
            self.calls = 0

        def load_image(self, cam):
            self.calls += 1
            return torch.full((4, 5, 3), float(cam))

    sc = FakeScene()
    one = 4 * 5 * 3 * 4
    imgs = ViewImages(sc, [0, 1, 2], max_bytes=2 * one)
    assert len(imgs) == 3 and float(imgs[2][0, 0, 0]) == 2.0 and float(imgs[-3][0, 0, 0]) == 0.0
    assert imgs[0] is imgs[0] and sc.calls == 2  # cached
    imgs[1]  # evicts 2 (least recently used), keeps 0
    assert imgs.cached_bytes == 2 * one and sc.calls == 3
    imgs[0]
    assert sc.calls == 3
    imgs[2]
    assert sc.calls == 4
    none = ViewImages(sc, [0, 1], max_bytes=0)
    none[0], none[0]
    assert none.cached_bytes == 0 and none.loads == 2
    with pytest.raises(IndexError):
        imgs[3]


def test_a_stop_request_from_another_rank_stops_after_the_same_step():
    """The stop flag travels in the step's reduction: when another rank reports a signal in
    step 3, this rank finishes step 3 and stops before step 4 (saving through on_interrupt),
    although it never saw a signal itself. The other rank is simulated: it adds nothing to the
    gradients and the records of its views, and its stop flag at the third reduction."""
    from clod_adapter.train.loop import fit, prepare
    from clod_adapter.train.distributed import Group
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb
    from conftest import render_views

    class OtherRankSignals(Group):
        calls = 0

        def all_reduce(self, t, what, op="sum"):
            if t.dtype == torch.float64 and what == "the step's reduction":
                OtherRankSignals.calls += 1
                if OtherRankSignals.calls == 3:
                    t[-1] += 1.0
            return t

    gt = make_ground_truth(200, seed=4)
    cams = make_cameras(2, 2, width=32, height=24)
    imgs = render_views(gt, cams)
    cfg = AdaptConfig(max_sv=3.0, iterations=10, seed=2, views_per_step=2)
    st = prepare(perturb(gt, 5), cams, cfg)
    group = OtherRankSignals(rank=0, world_size=2, local_rank=0, backend="gloo", device=torch.device("cpu"),
                             timeout=60.0)
    saved = []
    assert fit(st, cams, imgs, cfg, progress=False, group=group, on_interrupt=lambda s: saved.append(s.iteration)) is False
    assert saved == [3] and st.iteration == 3
    assert len(st.history["loss"]) == 6  # two records per step, the other rank's included
