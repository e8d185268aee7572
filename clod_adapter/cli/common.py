"""What every command line shares (``clod-adapt``, ``clod-eval``, ``clod-export``, ``clod-render``,
``clod-view``): thread defaults, the argument parser and its common flags, budgets and checks on
flag values, and one-line errors (:func:`run_cli`). Nothing here imports torch at module level, so
a CLI can call :func:`thread_defaults` before torch loads its OpenMP runtime.
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Callable, Optional

from ..errors import InputError

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
