"""PlayCanvas splat-transform (npm ``@playcanvas/splat-transform``, pinned to 3.7.0 by the root
``package.json``, installed by ``npm ci``): finding it, running it on the CPU, and the two things
this project asks of it besides decimation (:func:`clod_adapter.lod.rankings.merge_decimate`):

* :func:`write_lod_set`: a streamed-SOG LoD set (``lod-meta.json`` plus one folder of SOG chunks
  per level, the format PlayCanvas, SuperSplat and Babylon.js stream), built as the tool's help
  says: ``lod0.ply -l 0 lod1.ply -l 1 ... out/lod-meta.json``;
* :func:`read_info`: ``--info json`` of any file it reads (format, per-level counts).

Every run adds ``-g cpu`` (without it the tool asks WebGPU for a device and fails on a machine
without one). A missing or failing tool raises :class:`PeerError` with one line saying why.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Optional, Sequence

__all__ = ["SPLAT_TRANSFORM_ENV", "SPLAT_TRANSFORM_VERSION", "NPM_INSTALL", "PeerError", "project_root",
           "find_splat_transform", "require_splat_transform", "run_splat_transform", "read_info", "write_lod_set", "LOD_META_NAME"]

#: environment variable naming the splat-transform executable (it wins over every other place).
SPLAT_TRANSFORM_ENV = "CLOD_SPLAT_TRANSFORM"
#: the pinned version (root ``package.json``; installed into ``node_modules/`` by :data:`NPM_INSTALL`).
SPLAT_TRANSFORM_VERSION = "3.7.0"
#: the one documented install command, run from the repository root (CI runs it too).
NPM_INSTALL = "npm ci"
#: the index file of a streamed-SOG LoD set.
LOD_META_NAME = "lod-meta.json"


class PeerError(RuntimeError):
    """A peer tool (splat-transform) is missing or failed: one line saying which and why."""


def project_root() -> Optional[Path]:
    """The folder holding ``pyproject.toml`` above this package's ``__file__`` (the checkout of
    an editable install), or None for an installed copy without one."""
    for d in Path(__file__).resolve().parents:
        if (d / "pyproject.toml").is_file():
            return d
    return None


def _local_bin(folder: Path) -> Optional[str]:
    """``folder/node_modules/.bin/splat-transform`` (``.cmd`` on Windows) when executable."""
    for name in ("splat-transform", "splat-transform.cmd") if os.name == "nt" else ("splat-transform",):
        exe = folder / "node_modules" / ".bin" / name
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    return None


def find_splat_transform() -> Optional[str]:
    """Path of the splat-transform executable, looked up in this order:

    1. ``$CLOD_SPLAT_TRANSFORM`` when set (an executable file, else None: no fallback);
    2. ``node_modules/.bin/splat-transform`` under the project root (:func:`project_root`, where
       ``npm ci`` installs it);
    3. ``node_modules/.bin/splat-transform`` under the current directory;
    4. ``splat-transform`` on PATH.

    Returns:
        the executable's path, or None when none is found.
    """
    env = os.environ.get(SPLAT_TRANSFORM_ENV)
    if env:
        return env if os.path.isfile(env) and os.access(env, os.X_OK) else None
    for folder in (project_root(), Path.cwd()):
        exe = _local_bin(folder) if folder is not None else None
        if exe is not None:
            return exe
    return shutil.which("splat-transform")


def require_splat_transform() -> str:
    """:func:`find_splat_transform`'s path.

    Raises:
        PeerError: none is found (one line naming ``npm ci``).
    """
    exe = find_splat_transform()
    if exe is None:
        env = os.environ.get(SPLAT_TRANSFORM_ENV)
        where = (f"${SPLAT_TRANSFORM_ENV}={env} is not an executable file" if env else
                 "not in node_modules/.bin nor on PATH")
        raise PeerError(f"splat-transform not found ({where}); install the pinned version with "
                        f"`{NPM_INSTALL}` in the repository root")
    return exe


def _failure_line(text: str) -> str:
    """The line of splat-transform's output that says what failed: the last ``✗ ...`` line that
    is not its closing ``✗ failed in ...`` summary, else the last non-empty line."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if ln.startswith("\u2717") and not ln[1:].strip().startswith("failed in"):
            return ln
    return lines[-1] if lines else "no output"


def run_splat_transform(args: Sequence[str], *, tool: Optional[str] = None, timeout: float = 600.0,
                        what: str = "") -> subprocess.CompletedProcess:
    """Run ``splat-transform -g cpu ARGS`` and return the finished process (text output).

    Args:
        args: the arguments after ``-g cpu`` (inputs, actions, the output).
        tool: the executable (default :func:`find_splat_transform`).
        timeout: seconds before the run is abandoned.
        what: what the run does, for the error line (e.g. ``"--decimate 500"``).

    Raises:
        PeerError: the tool is not found (the message names ``npm ci``), cannot be started,
            times out or exits non-zero (the message holds its error line).
    """
    exe = tool or require_splat_transform()
    label = f"splat-transform {what}".rstrip()
    try:
        res = subprocess.run([exe, "-g", "cpu", *map(str, args)], capture_output=True, text=True, errors="replace",
                             timeout=timeout)
    except subprocess.TimeoutExpired:
        raise PeerError(f"{label} timed out after {timeout:g} s") from None
    except OSError as e:
        raise PeerError(f"splat-transform could not be started ({exe}): {e}") from None
    if res.returncode != 0:
        raise PeerError(f"splat-transform exited {res.returncode}: {_failure_line(res.stderr or res.stdout)}")
    return res


def read_info(path: os.PathLike, *, tool: Optional[str] = None, timeout: float = 120.0) -> dict:
    """``splat-transform PATH --info json null``: what the tool reads in a file, e.g. for a LoD
    set ``{"format": "lod", "numLods": 3, "lodCounts": [n0, n1, n2], "shBands": ..., ...}``.

    Raises:
        PeerError: as :func:`run_splat_transform`, or no JSON object in its output.
    """
    out = run_splat_transform([str(path), "--info", "json", "null"], tool=tool, timeout=timeout,
                              what=f"--info {Path(path).name}").stdout
    start, end = out.find("\n{"), out.rfind("\n}")
    if out.startswith("{"):
        start = -1
    if end < 0 or end <= start:
        raise PeerError(f"splat-transform --info {Path(path).name} printed no JSON object")
    try:
        return json.loads(out[start + 1:end + 2])
    except ValueError as e:
        raise PeerError(f"splat-transform --info {Path(path).name}: unreadable JSON ({e})") from None


def write_lod_set(level_plys: Sequence[os.PathLike], out_dir: os.PathLike, *, tool: Optional[str] = None,
                  timeout: float = 7200.0, overwrite: bool = False,
                  sh_iterations: Optional[int] = None) -> tuple[dict, list[str]]:
    """Build a streamed-SOG LoD set from one standard .ply per level (level 0 = full detail) into
    ``out_dir``: ``splat-transform lod0.ply -l 0 lod1.ply -l 1 ... tmp/lod-meta.json`` in a
    staging folder beside it, checked with :func:`read_info` (the per-level counts must equal
    the inputs'), then each entry (the chunk folders ``LEVEL_CHUNK/``, then ``lod-meta.json``)
    renamed into ``out_dir``: a reader never finds an index whose chunks are missing.

    Args:
        level_plys: K >= 1 .ply files, finest first.
        out_dir: the folder to write into (created when missing).
        tool, timeout: as :func:`run_splat_transform`.
        overwrite: replace entries of the same name (else they are an error).
        sh_iterations: the tool's ``--sh-iterations`` (k-means iterations of the SOG SH palette;
            None: its default, 10). On the CPU that k-means dominates: a 60,000-Gaussian SH-3
            level clusters into 32,768 centroids, tens of minutes at 10 iterations.

    Returns:
        (:func:`read_info` of the written ``lod-meta.json``, the names written into ``out_dir``).

    Raises:
        PeerError: the tool failed or its set reads back with other counts.
        FileExistsError: an entry of the set exists in ``out_dir`` and not ``overwrite``.
    """
    import tempfile

    from plyfile import PlyData

    out_dir = Path(out_dir)
    counts = [PlyData.read(str(p))["vertex"].count for p in level_plys]
    args: list[str] = [] if sh_iterations is None else ["--sh-iterations", str(int(sh_iterations))]
    for k, p in enumerate(level_plys):
        args += [str(p), "-l", str(k)]
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out_dir, prefix=".lod-") as tmp:
        staged = Path(tmp) / "lod"
        run_splat_transform(args + [str(staged / LOD_META_NAME)], tool=tool, timeout=timeout,
                            what=f"LoD set of {len(counts)} levels")
        info = read_info(staged / LOD_META_NAME, tool=tool)
        if list(info.get("lodCounts", [])) != counts:
            raise PeerError(f"splat-transform LoD set reads back {info.get('lodCounts')} Gaussians per level, "
                            f"not {counts}")
        entries = sorted(staged.iterdir(), key=lambda e: (e.name == LOD_META_NAME, e.name))  # the index last
        clash = [e.name for e in entries if (out_dir / e.name).exists()]
        if clash and not overwrite:
            raise FileExistsError(f"{out_dir}: {', '.join(clash)} exist")
        for e in entries:
            for q in [e, *e.rglob("*")]:
                os.chmod(q, 0o755 if q.is_dir() else 0o644)
            target = out_dir / e.name
            if target.is_dir():
                shutil.rmtree(target)
            os.replace(e, target)
    return info, [e.name for e in entries]
