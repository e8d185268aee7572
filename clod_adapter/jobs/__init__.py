"""What the jobs behind the command lines share: the device (:func:`pick_device`), the output
folder's checks (:func:`check_output_dir`), the bad-input error and progress reporting (one import
each). The command lines' own plumbing (parsers, flags, one-line errors) is
:mod:`clod_adapter.cli.common`. Nothing here imports torch at module level.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Optional, Sequence

from ..errors import InputError  # noqa: F401  (the jobs' bad-input error, one import)
from ..progress import LineProgress, progress_bar  # noqa: F401  (the jobs' progress, one import)


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

