"""Atomic file output: write to a temporary file in the destination directory, then rename.

``os.replace`` within one directory (hence one file system) is atomic on POSIX and Windows, so
readers see either the old file or the complete new one, never a partial write.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Callable, Iterator, Union

PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["atomic_write", "atomic_save"]


def _tmp_path(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    return Path(tmp)


def _fsync_dir(directory: Path) -> None:
    # Persist the rename itself; not possible (nor needed) on every platform.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _finish(tmp: Path, path: Path) -> None:
    # mkstemp creates the file 0600; give the output the usual permissions (0666 & ~umask).
    umask = os.umask(0)
    os.umask(umask)
    with contextlib.suppress(OSError):
        os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)
    _fsync_dir(path.parent)


@contextlib.contextmanager
def atomic_write(path: PathLike, mode: str = "wb", **open_kwargs) -> Iterator[IO]:
    """Open a temporary file next to ``path`` for writing; move it onto ``path`` on success.

    Usage::

        with atomic_write("out.bin") as f:
            f.write(data)

    The temporary file lives in ``path``'s directory (same file system, so ``os.replace`` is
    atomic), is flushed and fsync'ed before the rename, and is removed if the block raises;
    ``path`` is then left untouched (an existing file keeps its old content).

    Args:
        path: destination file; its parent directory must exist.
        mode: an ``open`` write mode ("wb", "w", "xb" is not supported); text modes accept
            ``encoding`` / ``newline`` via ``open_kwargs``.

    Raises:
        ValueError: ``mode`` is not a write mode.
        FileNotFoundError: the parent directory does not exist.
    """
    if mode not in ("w", "wb", "wt", "w+", "wb+", "w+b"):
        raise ValueError(f"{path}: atomic_write mode must be a write mode like 'w' or 'wb', got {mode!r}")
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: parent directory does not exist")
    tmp = _tmp_path(path)
    try:
        with open(tmp, mode, **open_kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        _finish(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def atomic_save(path: PathLike, write_fn: Callable[[Path], object]) -> Path:
    """Atomically produce ``path`` with a writer that takes a file name.

    ``write_fn(tmp_path)`` must write the complete file at ``tmp_path`` (a fresh empty file in
    ``path``'s directory, with the same suffix as ``path`` so format-sniffing writers such as
    PIL's ``Image.save`` or ``torch.save`` behave as for ``path``). On success the file is
    fsync'ed and renamed onto ``path``; if ``write_fn`` raises, the temporary file is removed
    and the exception propagates.

    Returns:
        ``Path(path)``.

    Raises:
        FileNotFoundError: the parent directory does not exist (or ``write_fn`` wrote nothing).
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: parent directory does not exist")
    fd, tmp_s = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}")
    os.close(fd)
    tmp = Path(tmp_s)
    try:
        write_fn(tmp)
        if not tmp.exists():
            raise FileNotFoundError(f"{path}: writer produced no file at {tmp}")
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        _finish(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    return path
