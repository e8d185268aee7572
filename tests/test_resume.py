"""Interrupting ``clod-adapt`` (SIGINT / SIGTERM) and resuming it.

* a signal during training: exit 130, OUT holds only a valid ``adapt_state.safetensors`` (no
  .ply, metrics, strip or temp files); ``--resume`` ends bit-identical (the .ply bytes and every
  state tensor) to an uninterrupted run with the same seed, in deterministic mode;
* a signal during the final evaluation leaves a resumable state too (same final result);
* a second signal while the state is being saved does not corrupt it;
* ``--resume`` refuses a state saved for another input .ply or other settings (exit 2, one line).

The CLI runs in a subprocess (real signals, real exit codes); the test waits for iteration >= 5
through the ``CLOD_PROGRESS_FILE`` hook instead of sleeping. The uninterrupted reference runs
in-process (faster; the subprocesses use the same thread count, and their results must equal it
bit for bit, which also shows the CLI and ``pipeline.run`` agree).
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from clod_adapter.train.state import load_state
from clod_adapter.io.ply import write_ply
from clod_adapter.io.colmap import write_colmap_scene
from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb
from conftest import REPO, uint8_views

ITERATIONS = 24
MAX_SV = 3.0
SEED = 5
THREADS = 2
STATE = "adapt_state.safetensors"
OUTPUTS = ("point_cloud.ply", "metrics.json", "lod_strip.png")


def _env(**extra) -> dict:
    env = dict(os.environ)
    env.update({"OMP_NUM_THREADS": str(THREADS), "PYTHONPATH": str(REPO)}, **extra)
    env.pop("CLOD_DETERMINISTIC", None)
    return env


def _cli(ply, scene, out, *extra) -> list[str]:
    return [sys.executable, "-m", "clod_adapter.cli.adapt", str(ply), "--images", str(scene), "-o", str(out),
            "--max-sv", str(MAX_SV), "--seed", str(SEED), "--deterministic", "--quiet", *extra]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from clod_adapter.render.composite import cpp_extension_available

    cpp_extension_available()  # build/load the compositor once, before the subprocesses use it
    root = tmp_path_factory.mktemp("resume")
    gt = make_ground_truth(400)
    cams = make_cameras(2, 5, 64, 48)
    imgs = uint8_views(gt, cams)
    write_colmap_scene(root / "scene", cams, imgs)
    write_ply(root / "in.ply", perturb(gt, 2))
    write_ply(root / "other.ply", perturb(gt, 3))
    # the uninterrupted reference, in-process (same code, seed, thread count and deterministic
    # mode as the CLI subprocesses below; their results must match it bit for bit)
    assert torch.get_num_threads() == THREADS
    _inprocess_run(root, root / "ref")
    return root


def _assert_same_result(out: Path, ref: Path) -> None:
    assert (out / "point_cloud.ply").read_bytes() == (ref / "point_cloud.ply").read_bytes()
    a, _, ma = load_state(out / STATE)
    b, _, mb = load_state(ref / STATE)
    assert a.iteration == b.iteration == ITERATIONS
    for k in b.params:
        assert torch.equal(a.params[k], b.params[k]), k
    assert a.generator.get_state().equal(b.generator.get_state())
    assert a.order == b.order
    assert ma["history"] == mb["history"]


def _only_state(out: Path) -> None:
    names = sorted(p.name for p in out.iterdir())
    assert names == [STATE], names  # no outputs, no temp files


def _wait_for_iteration(proc, progress: Path, at_least: int, timeout: float = 60.0) -> int:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if proc.poll() is not None:
            raise AssertionError(f"clod-adapt ended (exit {proc.returncode}) before iteration {at_least}: "
                                 f"{proc.stderr.read()[-2000:]}")
        try:
            it = int(progress.read_text().strip() or 0)
        except (OSError, ValueError):
            it = 0
        if it >= at_least:
            return it
        time.sleep(0.005)
    proc.kill()
    raise AssertionError(f"no iteration {at_least} within {timeout} s")


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_then_resume_is_bit_exact(scene, tmp_path, sig):
    out, progress = tmp_path / "out", tmp_path / "progress"
    cmd = _cli(scene / "in.ply", scene / "scene", out, "--iterations", str(ITERATIONS))
    proc = subprocess.Popen(cmd, cwd=REPO, env=_env(CLOD_PROGRESS_FILE=str(progress)),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for_iteration(proc, progress, 5)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err
    _only_state(out)
    st, cfg, meta = load_state(out / STATE)
    assert 5 <= st.iteration < ITERATIONS
    assert cfg.seed == SEED and cfg.iterations == ITERATIONS and meta["deterministic"] == "1"

    # resume: --iterations comes from the state
    r = subprocess.run(_cli(scene / "in.ply", scene / "scene", out, "--resume"), cwd=REPO, env=_env(),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    _assert_same_result(out, scene / "ref")


def _inprocess_run(scene: Path, out: Path, **kw):
    from clod_adapter.train.config import AdaptConfig
    from clod_adapter.jobs.adapt import AdaptOptions, run

    cfg = AdaptConfig(max_sv=MAX_SV, iterations=ITERATIONS, seed=SEED)
    return run(scene / "in.ply", scene / "scene", out, cfg, AdaptOptions(
        device="cpu", progress=False, log=lambda *a: None, deterministic=True, **kw))


@pytest.mark.slow
def test_interrupt_during_final_evaluation_resumes(scene, tmp_path, monkeypatch):
    import clod_adapter.jobs.adapt_levels as lv

    real = lv.evaluate_levels

    def interrupted(*a, **k):
        os.kill(os.getpid(), signal.SIGINT)  # arrives while evaluating
        return real(*a, **k)

    out = tmp_path / "out"
    with monkeypatch.context() as m:
        m.setattr(lv, "evaluate_levels", interrupted)
        with pytest.raises(KeyboardInterrupt):
            _inprocess_run(scene, out)
    _only_state(out)
    assert load_state(out / STATE)[0].iteration == ITERATIONS
    _inprocess_run(scene, out, resume=True)
    _assert_same_result(out, scene / "ref")


@pytest.mark.slow
def test_second_signal_during_state_save(scene, tmp_path, monkeypatch):
    import safetensors.torch

    import clod_adapter.jobs.adapt as pl

    real_fit, real_save = pl.fit, safetensors.torch.save_file
    saves = []

    def fit_with_signal(*a, **k):
        def on_step(st):
            if st.iteration == 3:
                os.kill(os.getpid(), signal.SIGINT)
        k["on_step"] = on_step
        return real_fit(*a, **k)

    def save_with_signals(*a, **k):
        os.kill(os.getpid(), signal.SIGTERM)  # a second (and third) signal while saving
        real_save(*a, **k)
        os.kill(os.getpid(), signal.SIGINT)
        saves.append(a[1])

    out = tmp_path / "out"
    with monkeypatch.context() as m:
        m.setattr(pl, "fit", fit_with_signal)
        m.setattr(safetensors.torch, "save_file", save_with_signals)
        with pytest.raises(KeyboardInterrupt):
            _inprocess_run(scene, out)
    assert len(saves) == 1
    _only_state(out)
    assert load_state(out / STATE)[0].iteration == 3
    _inprocess_run(scene, out, resume=True)
    _assert_same_result(out, scene / "ref")


def test_resume_refuses_other_input_or_settings(scene, tmp_path, capsys):
    from clod_adapter.cli.adapt import main

    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(scene / "ref" / STATE, out / STATE)
    before = (out / STATE).read_bytes()
    base = [str(scene / "scene"), "-o", str(out), "--resume", "--quiet", "--seed", str(SEED)]
    cases = [
        ([str(scene / "other.ply"), "--images", *base, "--max-sv", str(MAX_SV)], "another input model"),
        ([str(scene / "in.ply"), "--images", *base, "--max-sv", "4"], "max_sv"),
        ([str(scene / "in.ply"), "--images", *base[:-2], "--max-sv", str(MAX_SV)], "seed"),
        ([str(scene / "in.ply"), "--images", *base, "--max-sv", str(MAX_SV), "--gains", "o"],
         "gains"),
    ]
    for argv, must in cases:
        code = main(argv)
        err = capsys.readouterr().err.strip()
        assert code == 2, (argv, err)
        assert len(err.splitlines()) == 1 and must in err and STATE in err, err
        assert sorted(p.name for p in out.iterdir()) == [STATE]
        assert (out / STATE).read_bytes() == before


@pytest.mark.parametrize("threads", [2, 4])
def test_deterministic_backward_is_bit_reproducible(threads):
    """The C++ backward in deterministic mode gives bit-identical gradients call after call (the
    dynamic schedule may not), and the same gradients as the dynamic mode up to rounding."""
    from test_composite import grads_of, make_scene

    from clod_adapter.render import composite

    if not composite.cpp_extension_available():
        pytest.skip("C++ compositor did not build")
    scene = make_scene(3000, 96, 80, seed=3)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        composite.set_deterministic(True)
        runs = [grads_of(scene, "cpp")[2] for _ in range(4)]
        composite.set_deterministic(False)
        dyn = grads_of(scene, "cpp")[2]
    finally:
        composite.set_deterministic(None)
        torch.set_num_threads(old)
    for r in runs[1:]:
        for k in r:
            assert torch.equal(r[k], runs[0][k]), k
    for k in dyn:
        torch.testing.assert_close(runs[0][k], dyn[k], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("drawn", ["tree", "chain"])
def test_a_state_saved_with_tier_draw_still_loads(scene, tmp_path, drawn):
    """States written while merged tiers could also be drawn as a chain carry ``tier_draw`` in their
    config: they load (the model's own training does not depend on it) with the same settings."""
    import json

    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(scene / "ref" / STATE), framework="pt", device="cpu") as f:
        meta, tensors = dict(f.metadata()), {k: f.get_tensor(k) for k in f.keys()}
    cfg = json.loads(meta["config"])
    assert "tier_draw" not in cfg
    save_file(tensors, str(tmp_path / STATE), metadata={**meta, "config": json.dumps({**cfg, "tier_draw": drawn})})
    old, old_cfg, _ = load_state(tmp_path / STATE)
    new, new_cfg, _ = load_state(scene / "ref" / STATE)
    assert old_cfg == new_cfg and old.iteration == new.iteration > 0
