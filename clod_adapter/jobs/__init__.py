"""Plumbing shared by the command-line jobs (``clod-adapt``, ``clod-eval``, ``clod-export``,
``clod-render``): thread defaults, the argument parser, one-line errors, budgets, the device, the
output folder and progress reporting. Nothing here imports torch at module level, so a CLI can
call :func:`thread_defaults` before torch loads its OpenMP runtime.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Callable, Iterable, Optional, Sequence

from ..errors import InputError  # noqa: F401  (the jobs' bad-input error, one import)
from ..progress import LineProgress, progress_bar  # noqa: F401  (the jobs' progress, one import)

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130

#: the OpenMP wait policy the CLIs use unless ``OMP_WAIT_POLICY`` is set (see :func:`thread_defaults`).
DEFAULT_WAIT_POLICY = "PASSIVE"


def thread_defaults(environ=os.environ) -> None:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` unless the environment already sets it.

    OpenMP threads that finish a parallel region spin for a while (GNU libgomp: about 300,000
    iterations, ~0.1-1 ms) waiting for the next one. The rasteriser runs many short parallel
    regions per image, so on a machine whose cores are busy with other work the spinning threads
    compete with the threads that have work: measured 5-15x slower (``benchmarks/studies/omp_wait.py``).
    ``PASSIVE`` makes idle threads sleep at once. libgomp reads the variable when it is loaded
    (when torch is first imported), so this must run before ``import torch``; the thread count
    stays torch's default (the number of cores) unless ``OMP_NUM_THREADS`` or ``--threads`` says
    otherwise.
    """
    environ.setdefault("OMP_WAIT_POLICY", DEFAULT_WAIT_POLICY)


def set_threads(n: Optional[int]) -> None:
    """``torch.set_num_threads(n)`` when ``n`` is given (``--threads``).

    Raises:
        InputError: ``n < 1``."""
    if n is not None:
        check_flag(n >= 1, "--threads", ">= 1", n)
        import torch

        torch.set_num_threads(int(n))


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line, ``prog: error: MESSAGE (see --help)``,
    exit status 2, instead of printing the whole usage first."""

    def error(self, message: str):  # noqa: D401 (argparse API)
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see --help)\n")


def make_parser(prog: str, description: str, example: str) -> ArgumentParser:
    """The parser of one CLI, with ``--version`` and an example in ``--help``."""
    from .. import __version__

    p = ArgumentParser(prog=prog, description=description, epilog=f"example:\n  {example}",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    return p


#: the scene folder flag's spellings: ours and the official 3DGS scripts' (``-s/--source_path``).
SCENE_FLAGS = ("--images", "-s", "--source_path", "--source-path")


def add_scene_flags(p: argparse.ArgumentParser, *, resolution_note: str = "") -> None:
    """``--images/-s/--source_path SCENE`` and ``-r/--resolution R``: the same in every CLI."""
    p.add_argument(*SCENE_FLAGS, dest="images", metavar="SCENE",
                   help="scene folder: COLMAP (images/, sparse/0) or NeRF-synthetic (transforms_*.json)")
    p.add_argument("-r", "--resolution", type=int, default=1, choices=(1, 2, 4, 8),
                   help="use images_R/ when present, else downsample by R (default 1)" + resolution_note)


def add_adapted_inputs(p: argparse.ArgumentParser) -> None:
    """The positional ADAPTED model and the scene flags (:func:`add_scene_flags`) of the CLIs
    that read an adapted model."""
    p.add_argument("ply", nargs="?", metavar="ADAPTED",
                   help="adapted model (with sigma_d): a clod-adapt output folder or its point_cloud.ply")
    add_scene_flags(p)


def add_level_flags(p: argparse.ArgumentParser, s_v_help: str, budget_help: str) -> None:
    """``--s-v X`` or ``--budget K`` (one of them): the level a CLI draws at."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--s-v", type=float, default=None, metavar="X", help=s_v_help)
    g.add_argument("--budget", default=None, metavar="K", help=budget_help)


def add_common_flags(p: argparse.ArgumentParser, *, device_default: str = "auto") -> None:
    """``--device``, ``--threads``, ``--quiet``, ``--force``: the same meaning in every CLI."""
    p.add_argument("--device", default=device_default, choices=("auto", "cpu", "cuda"),
                   help="where to render: auto = CUDA when available and gsplat imports, else CPU "
                        f"(default {device_default})")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="CPU threads (default: OMP_NUM_THREADS, else the number of cores). The CLIs set "
                        "OMP_WAIT_POLICY=PASSIVE unless it is set (idle threads sleep instead of spinning; "
                        "5-15x faster on a busy machine)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.add_argument("--force", action="store_true",
                   help="write into a non-empty output folder, replacing files of the same name")


def one_line(e: object) -> str:
    """The message of ``e`` on one line (bad-input errors promise exactly one stderr line)."""
    return " ".join(str(e).split("\n")).strip()


def run_cli(prog: str, body: Callable[[], int]) -> int:
    """Run ``body`` and turn bad input (:class:`clod_adapter.errors.InputError`, which a .ply or
    scene that cannot be read raises too, or an unreadable input / unwritable output, ``OSError``)
    into ``prog: error: ...`` on one stderr line (exit 2), Ctrl-C / SIGTERM into exit 130. Any
    other exception is a bug: it propagates (its traceback, exit status 1)."""
    try:
        return body()
    except InputError as e:
        print(f"{prog}: error: {one_line(e)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as e:  # an unreadable input or unwritable output the checks missed
        name = e.filename if e.filename is not None else prog
        print(f"{prog}: error: {name}: {e.strerror or e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


# --- flags ------------------------------------------------------------------------------------
def parse_budget(text: str, flag: str = "--budget"):
    """One budget from a flag: :func:`clod_adapter.lod.budget.normalize_budget` of the number, a
    fraction in [0, 1] (float) or a count > 1 (int). Raises InputError naming ``flag``."""
    from ..lod.budget import normalize_budget

    try:
        v = float(str(text).strip())
    except ValueError:
        raise InputError(f"{flag}: {str(text).strip()!r} is not a number") from None
    try:
        return normalize_budget(v)
    except ValueError as e:
        raise InputError(f"{flag}: {text!r}: {str(e).split(': ', 1)[-1]}") from None


def parse_budgets(text: str, flag: str = "--budgets") -> list:
    """Comma-separated budgets (:func:`parse_budget`); at least one. Raises InputError."""
    items = [x for x in str(text).split(",") if x.strip()]
    if not items:
        raise InputError(f"{flag}: give at least one budget")
    return [parse_budget(x, flag) for x in items]


def check_flag(ok: bool, flag: str, what: str, value) -> None:
    """Raise InputError ``"FLAG must be WHAT, got VALUE"`` unless ``ok``."""
    if not ok:
        raise InputError(f"{flag} must be {what}, got {value}")


def pick_device(device: str):
    """``auto``: CUDA when available and gsplat imports, else CPU. Raises InputError for cuda
    without CUDA."""
    import torch

    if device == "cpu":
        return torch.device("cpu")
    cuda_ok = torch.cuda.is_available()
    if device == "cuda":
        if not cuda_ok:
            raise InputError("--device cuda: no CUDA device is available (use --device cpu)")
        return torch.device("cuda")
    if device != "auto":
        raise InputError(f"--device must be auto, cpu or cuda, got {device!r}")
    if cuda_ok:
        try:
            import gsplat  # noqa: F401

            return torch.device("cuda")
        except Exception:
            pass
    return torch.device("cpu")


# --- the output folder ------------------------------------------------------------------------
PROBE_PREFIX = ".clod-probe-"


def probe_writable(directory: Path) -> Optional[str]:
    """None when a file can be created (and removed) in ``directory``, else the OS reason.

    ``os.access`` is not enough (as root it says yes whatever the mode bits), so a real hidden
    file is created and removed at once.
    """
    import tempfile

    try:
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=PROBE_PREFIX, suffix=".tmp")
    except OSError as e:
        return e.strerror or type(e).__name__
    os.close(fd)
    try:
        os.unlink(tmp)
    except OSError:
        pass
    return None


def check_output_dir(out_dir: Path, inputs: Sequence[Path], names: Iterable[str] = (), *,
                     create: bool = True, force: bool = False, resume: bool = False,
                     ignore: Iterable[str] = ()) -> None:
    """Refuse outputs that would overwrite an input, a non-empty folder, or cannot be written.

    Args:
        out_dir: the output folder.
        inputs: input files/folders; neither ``out_dir`` nor ``out_dir/NAME`` may be one.
        names: the file names the job writes into ``out_dir``.
        create: also create ``out_dir`` (with parents) and probe it; on failure the folders just
            created are removed. False: check only, nothing is created or left behind.
        force: accept a non-empty ``out_dir`` (files of the same name are replaced).
        resume: accept a non-empty ``out_dir`` (the job continues the run saved there).
        ignore: entries of ``out_dir`` that do not count as content (the job's own).

    Raises:
        InputError: naming ``out_dir`` and the problem (and the flag that would accept it).
    """
    out_dir = Path(out_dir)
    for inp in inputs:
        if out_dir.resolve() == Path(inp).resolve():
            raise InputError(f"{out_dir}: output path equals the input {inp}; -o takes a folder, choose another")
        for n in names:
            if (out_dir / n).resolve() == Path(inp).resolve():
                raise InputError(f"{out_dir / n}: output path equals the input {inp}; choose another -o")
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: output path exists and is not a directory")
    missing = [p for p in (out_dir, *out_dir.parents) if not p.exists()]
    anc = missing[-1].parent if missing else out_dir
    if not anc.is_dir():
        raise InputError(f"{out_dir}: cannot create output directory ({anc} is not a directory)")
    why = probe_writable(anc)
    if why is not None:
        what = "output directory is not writable" if anc == out_dir else f"cannot create output directory in {anc}"
        raise InputError(f"{out_dir}: {what} ({why})")
    if out_dir.is_dir() and not (force or resume):
        skip = set(ignore)
        content = sorted(p.name for p in out_dir.iterdir()
                         if not p.name.startswith(PROBE_PREFIX) and p.name not in skip)
        if content:
            shown = ", ".join(content[:3]) + (f" and {len(content) - 3} more" if len(content) > 3 else "")
            raise InputError(f"{out_dir}: output folder is not empty ({shown}); pass --force to replace "
                             "its files, --resume to continue a run saved there, or choose another -o")
    if not create:
        return
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{out_dir}: cannot create output directory ({e.strerror})") from None
    why = probe_writable(out_dir)
    if why is not None:
        for p in missing:  # deepest first: undo what mkdir made
            try:
                p.rmdir()
            except OSError:
                break
        raise InputError(f"{out_dir}: output directory is not writable ({why})")

