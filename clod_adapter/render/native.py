"""The project's C++ kernels, one extension built on first use (``csrc/*.cpp``):

* the per-pixel compositor (``csrc/composite.cpp``; :mod:`clod_adapter.render.composite`);
* the per-frame LoD terms (``csrc/lod_terms.cpp``; :func:`clod_adapter.lod.rule.frame_terms`,
  :func:`clod_adapter.lod.rule.lod_mask`, :func:`clod_adapter.lod.budget.critical_s_v`);
* the merge tree's cut and drawn attributes (``csrc/tree_cut.cpp``; :func:`clod_adapter.lod.tree.cut`,
  :func:`clod_adapter.lod.tree.cut_attributes`);
* the projection of a frame without gradients (``csrc/projection.cpp``;
  :func:`clod_adapter.render.projection.project_geometry`, :func:`clod_adapter.render.projection.finish_projection`);
* every Gaussian's rasterisation cost (``csrc/splat_cost.cpp``; :func:`clod_adapter.lod.cost.splat_cost`
  at level 0, behind :func:`clod_adapter.lod.cut.tree_node_costs` and
  :func:`clod_adapter.lod.cost.base_costs`) and the prefix of an order that fits a budget
  (:func:`clod_adapter.lod.cost.ordered_prefix_count`).

Built with ``torch.utils.cpp_extension.load`` and cached (honours ``TORCH_EXTENSIONS_DIR``).
Where it cannot be built every kernel falls back to its pure-PyTorch twin. :func:`use_impl`
switches all of them at once, for tests and benchmarks that hold the kernels to their twins (as
gsplat's ``cuda/_torch_impl.py``); it is not a user option.
"""
from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from pathlib import Path
from typing import Optional

__all__ = ["load", "available", "error", "impl", "use_impl", "wanted", "no_grad_cpu"]

_CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (_CSRC / "composite.cpp", _CSRC / "composite_simd.cpp", _CSRC / "lod_terms.cpp", _CSRC / "tree_cut.cpp",
           _CSRC / "splat_cost.cpp", _CSRC / "sh_colors.cpp", _CSRC / "projection.cpp")
_EXT = None
_EXT_ERROR: Optional[BaseException] = None
_LOCK = threading.Lock()
#: which implementation the kernels run: "auto" (C++ when it builds), "cpp", "torch"
_IMPL = "auto"


@contextlib.contextmanager
def use_impl(name: str):
    """Within the block every kernel runs ``name`` ("auto" | "cpp" | "torch")."""
    global _IMPL
    if name not in ("auto", "cpp", "torch"):
        raise ValueError(f"unknown implementation {name!r}")
    prev, _IMPL = _IMPL, name
    try:
        yield
    finally:
        _IMPL = prev


def impl() -> str:
    """The implementation :func:`use_impl` asks for ("auto" outside any block)."""
    return _IMPL


#: seconds after which a build lock is taken as left by an interrupted build (a build takes 1-3 min)
STALE_LOCK_S = 900.0


def clear_stale_lock(build_dir: Path, now: Optional[float] = None) -> bool:
    """Remove ``build_dir/lock`` when it is older than :data:`STALE_LOCK_S` seconds: torch's
    ``cpp_extension.load`` waits without end on a lock that an interrupted build (Ctrl-C, a killed
    process) left behind. Says so on stderr; returns whether it removed one."""
    lock = Path(build_dir) / "lock"
    try:
        age = (time.time() if now is None else now) - lock.stat().st_mtime
    except OSError:
        return False
    if age < STALE_LOCK_S:
        return False
    try:
        lock.unlink()
    except OSError:
        return False
    print(f"clod-adapter: removed {lock}, left {age / 60:.0f} min ago by an interrupted build of the C++ kernels",
          file=sys.stderr, flush=True)
    return True


def load():
    """The built extension module, building it on first use (or loading the cached build);
    None where it cannot be built (:func:`error` says why)."""
    global _EXT, _EXT_ERROR
    if _EXT is not None or _EXT_ERROR is not None:
        return _EXT
    with _LOCK:
        if _EXT is not None or _EXT_ERROR is not None:
            return _EXT
        try:
            from torch.utils.cpp_extension import load as cpp_load

            try:  # torch's own folder rule (a private helper): without it, no lock is cleared
                from torch.utils.cpp_extension import _get_build_directory

                clear_stale_lock(Path(_get_build_directory("clod_native", False)))
            except (ImportError, OSError, RuntimeError):
                pass

            # loading a cached build takes well under a second; anything longer is a (re)build,
            # which takes 1-3 min on 2 cores: say so instead of sitting silent
            t0 = time.perf_counter()
            folder = os.environ.get("TORCH_EXTENSIONS_DIR") or "torch's extension cache"
            notice = threading.Timer(2.0, lambda: print(
                f"clod-adapter: building the C++ kernels (first use or changed source; about 1-3 min on "
                f"2 cores; cached in {folder})...", file=sys.stderr, flush=True))
            notice.daemon = True
            notice.start()
            try:
                _EXT = cpp_load(
                    name="clod_native",
                    sources=[str(s) for s in SOURCES],
                    extra_cflags=["-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno"],
                    extra_ldflags=["-fopenmp"],
                    verbose=bool(os.environ.get("CLOD_VERBOSE_BUILD")),
                )
            finally:
                notice.cancel()
            if time.perf_counter() - t0 > 2.0:
                print(f"clod-adapter: C++ kernels ready after {time.perf_counter() - t0:.0f} s", file=sys.stderr,
                      flush=True)
        except Exception as e:  # no compiler, no headers, ...
            _EXT_ERROR = e
            _EXT = None
    return _EXT


def available() -> bool:
    """True when the extension builds/loads on this machine."""
    return load() is not None


def error() -> Optional[BaseException]:
    """Why the extension could not be built (None when it was, or was not tried yet)."""
    return _EXT_ERROR


def no_grad_cpu(*xs) -> bool:
    """Whether a frame's kernel runs its C++ form on the tensors ``xs`` (None entries skipped):
    CPU tensors of one dtype, float32 or float64, none recording autograd, and :func:`wanted`."""
    import torch

    ts = [x for x in xs if x is not None]
    dt = ts[0].dtype
    if dt not in (torch.float32, torch.float64) or any(x.device.type != "cpu" or x.dtype != dt for x in ts):
        return False
    return not (torch.is_grad_enabled() and any(x.requires_grad for x in ts)) and wanted(True)


def wanted(on_cpu: bool) -> bool:
    """Whether a kernel should run its C++ form now: "cpp" (raises RuntimeError where it cannot be
    built), "torch" (never), "auto" (on CPU tensors, where it builds)."""
    if _IMPL == "torch":
        return False
    if _IMPL == "cpp":
        if load() is None:
            raise RuntimeError(f"C++ kernels unavailable: {_EXT_ERROR!r}")
        return True
    return on_cpu and load() is not None
