"""The merging-decimator peer (clod_adapter.lod.rankings.merge_decimate): the pinned splat-transform
(root package.json, installed by ``npm ci``) run for real when it is found, and the failure modes
with stand-in scripts (absent tool, a tool that fails, one that returns another count)."""
from __future__ import annotations

import os
import stat
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from clod_adapter.lod import rankings as baselines
from clod_adapter.io import splat_transform
from clod_adapter.lod.rankings import merge_decimate
from clod_adapter.io.splat_transform import SPLAT_TRANSFORM_ENV, find_splat_transform
from clod_adapter.io.synthetic import make_ground_truth

TOOL = find_splat_transform()
needs_tool = pytest.mark.skipif(
    TOOL is None, reason="splat-transform not found: run `npm ci` in the repository root (pinned "
                         "@playcanvas/splat-transform 3.7.0), or set $CLOD_SPLAT_TRANSFORM")
posix_only = pytest.mark.skipif(os.name == "nt", reason="stand-in tools are POSIX shell scripts")


def _adapted(n: int) -> "baselines.Gaussians":
    """A synthetic model with sigma_d and level gains (none of which may reach the tool)."""
    g = make_ground_truth(n, seed=2)
    gen = torch.Generator().manual_seed(7)
    return replace(g.with_sigma_d(torch.rand(n, generator=gen)), opacity_logit_gain=torch.randn(n, generator=gen),
                   log_scale_gain=torch.randn(n, generator=gen), sh0_gain=torch.randn(n, 1, 3, generator=gen))


def _script(path: Path, body: str) -> str:
    path.write_text("#!/bin/sh\n" + body)
    path.chmod(path.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return str(path)


# --- the real tool -------------------------------------------------------------------------------
@needs_tool
@pytest.mark.parametrize("mode", ["decimate", "adaptive"])
def test_merge_decimate_real_tool_returns_count(mode):
    g = _adapted(3000)
    for count in (1, 750, 2999):
        out = merge_decimate(g, count, mode=mode, tool=TOOL)
        assert len(out) == count  # exact (splat-transform 3.7.0)
        assert out.sh_degree == g.sh_degree
        assert out.sigma_d is None and not out.has_gains and out.lod is None
        assert not out.extra  # sigma_d / gains were not written, so none come back as extra columns
        for name, t in out.tensors().items():
            assert t.device.type == "cpu" and t.dtype == torch.float32 and torch.isfinite(t).all(), name
        # merged Gaussians stay inside the input's bounding box (moment matching averages means)
        lo, hi = g.means.min(0).values, g.means.max(0).values
        assert bool(((out.means >= lo - 1e-4) & (out.means <= hi + 1e-4)).all())


@needs_tool
def test_merge_decimate_real_tool_clamps_count():
    g = make_ground_truth(500, seed=1)
    assert len(merge_decimate(g, 10_000, tool=TOOL)) == 500
    assert len(merge_decimate(g, 0, mode="adaptive", tool=TOOL)) == 1


# --- finding the tool ----------------------------------------------------------------------------
def test_find_splat_transform_order(tmp_path, monkeypatch):
    """$CLOD_SPLAT_TRANSFORM, then node_modules/.bin under the project root, then under the current
    directory, then PATH."""
    def fake(folder: Path) -> str:
        folder.mkdir(parents=True)
        return _script(folder / "splat-transform", "exit 0\n")

    env_exe = fake(tmp_path / "env")
    root_exe = fake(tmp_path / "root" / "node_modules" / ".bin")
    cwd_exe = fake(tmp_path / "cwd" / "node_modules" / ".bin")
    path_exe = fake(tmp_path / "path")
    monkeypatch.setenv(SPLAT_TRANSFORM_ENV, env_exe)
    monkeypatch.setattr(splat_transform, "project_root", lambda: tmp_path / "root")
    monkeypatch.chdir(tmp_path / "cwd")
    monkeypatch.setenv("PATH", str(tmp_path / "path"))
    assert find_splat_transform() == env_exe
    monkeypatch.delenv(SPLAT_TRANSFORM_ENV)
    assert find_splat_transform() == root_exe
    monkeypatch.setattr(splat_transform, "project_root", lambda: None)
    assert find_splat_transform() == cwd_exe
    monkeypatch.chdir(tmp_path)
    assert find_splat_transform() == path_exe
    monkeypatch.setenv("PATH", str(tmp_path / "nowhere"))
    assert find_splat_transform() is None


def test_project_root_holds_pyproject():
    root = splat_transform.project_root()
    assert root is not None and (root / "pyproject.toml").is_file()
    assert Path(splat_transform.__file__).resolve().is_relative_to(root)


# --- failures ------------------------------------------------------------------------------------
def test_absent_tool_names_npm_ci(tmp_path, monkeypatch):
    monkeypatch.setenv(SPLAT_TRANSFORM_ENV, str(tmp_path / "no-such-splat-transform"))
    assert find_splat_transform() is None
    with pytest.raises(RuntimeError, match="npm ci") as e:
        merge_decimate(make_ground_truth(50), 10)
    assert "no-such-splat-transform" in str(e.value) and "\n" not in str(e.value)


@posix_only
def test_failing_tool_reports_last_stderr_line(tmp_path):
    exe = _script(tmp_path / "fails", "echo 'progress...' >&2\necho 'first problem' >&2\n"
                                      "echo 'the last line' >&2\nexit 1\n")
    with pytest.raises(RuntimeError, match="exited 1: the last line$"):
        merge_decimate(make_ground_truth(50), 10, tool=exe)


@posix_only
def test_failing_tool_reports_splat_transform_error_line(tmp_path):
    """splat-transform's own layout: the error is the last '✗' line, before its '✗ failed in' summary."""
    exe = _script(tmp_path / "fails", "printf '  \\342\\234\\227 --decimate target resolves to 0 gaussians\\n"
                                      "    at main (cli.mjs:1:1)\\n  failed in 0.002s\\n"
                                      "\\342\\234\\227 failed in 0.005s  [peak cpu=85.0MB]\\n' >&2\nexit 1\n")
    with pytest.raises(RuntimeError, match="exited 1: \u2717 --decimate target resolves to 0 gaussians$"):
        merge_decimate(make_ground_truth(50), 10, tool=exe)


@posix_only
@pytest.mark.parametrize("mode,flag", [("decimate", "--decimate"), ("adaptive", "--decimate-adaptive")])
def test_command_line_and_plain_input(tmp_path, mode, flag):
    """The tool is called as ``-g cpu -w IN FLAG COUNT OUT`` on a file without sigma_d or gains; a
    tool that returns another count than asked (here: the input unchanged) is an error."""
    spy = tmp_path / "spy"
    exe = _script(tmp_path / "copy", f'echo "$@" > "{spy}.args"\ncp "$4" "{spy}.ply"\ncp "$4" "$7"\n')
    with pytest.raises(RuntimeError, match=f"{flag} 10 returned 40 Gaussians"):
        merge_decimate(_adapted(40), 10, mode=mode, tool=exe)
    args = (tmp_path / "spy.args").read_text().split()
    assert args[:3] == ["-g", "cpu", "-w"] and args[4:6] == [flag, "10"] and args[6].endswith("out.ply")
    from clod_adapter.io.ply import read_ply

    written = read_ply(tmp_path / "spy.ply")
    assert written.sigma_d is None and not written.has_gains and not written.extra
    assert b"sigma_d" not in (tmp_path / "spy.ply").read_bytes()[:4096]


@posix_only
def test_tool_without_output_file(tmp_path):
    exe = _script(tmp_path / "quiet", "exit 0\n")
    with pytest.raises(RuntimeError, match="wrote no file"):
        merge_decimate(make_ground_truth(50), 10, tool=exe)


@posix_only
def test_tool_timeout(tmp_path):
    exe = _script(tmp_path / "slow", "exec sleep 30\n")
    with pytest.raises(RuntimeError, match="timed out"):
        merge_decimate(make_ground_truth(50), 10, tool=exe, timeout=0.3)


def test_bad_mode():
    with pytest.raises(ValueError, match="mode"):
        merge_decimate(make_ground_truth(50), 10, mode="uniform")  # type: ignore[arg-type]
