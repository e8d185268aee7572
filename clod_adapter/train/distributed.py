"""Data-parallel fine-tuning over training views with ``torch.distributed`` (torchrun).

    torchrun --nproc_per_node=N -m clod_adapter.cli.adapt MODEL --images SCENE -o OUT
    clod-adapt --distributed ...        # the same, reading torchrun's environment

Every rank (process) holds the whole model and the same optimiser state. A step takes
``views_per_step`` views from the run's one seeded schedule (view order and ``s_v`` draws come
from the generator in the state, identical on every rank); view ``j`` of the step is rendered by
rank ``j mod world_size``, at its own ``s_v`` / budget. Each rank back-propagates its views, the
gradients are summed over the ranks (``all_reduce``), divided by ``views_per_step`` and every
rank takes the same Adam step, so the parameters stay identical everywhere. The step's records
(loss, PSNR, rendered fraction per view) and any rank's stop request (SIGINT/SIGTERM) travel in
the same reduction, so all ranks keep the same history and stop after the same step. Rank 0
alone writes the state and the outputs (atomically); the others wait for the final state on a
barrier and exit. Because the schedule is global, a run resumes from its state with any number
of processes, and one process with ``views_per_step = W`` does what ``W`` ranks do.

Backends: NCCL for CUDA (one GPU per rank, ``LOCAL_RANK``), gloo on the CPU; the process group
is joined with ``init_method="env://"`` (``MASTER_ADDR``, ``MASTER_PORT``, ``RANK``,
``WORLD_SIZE``, as torchrun sets them). Collectives time out after :data:`DEFAULT_TIMEOUT_S`
seconds (``CLOD_DIST_TIMEOUT`` overrides it); a rank that dies makes the others fail at their
next collective with :class:`PeerLost` (gloo sees the closed connection at once), never hang.
"""
from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Mapping, Optional

import torch
from torch import Tensor

#: the variables torchrun (or any ``env://`` launcher) sets for every rank.
ENV_VARS = ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")
#: True once this process has joined a process group (:func:`init`).
_JOINED = False
#: environment variable: seconds before a collective (or joining the group) gives up.
TIMEOUT_ENV = "CLOD_DIST_TIMEOUT"
DEFAULT_TIMEOUT_S = 1800.0


class PeerLost(RuntimeError):
    """Another rank stopped answering (died, was killed, or timed out); one-line message."""


def launched_by_torchrun(environ: Mapping[str, str] = os.environ) -> bool:
    """True when the torchrun / ``env://`` variables (:data:`ENV_VARS`) are all set."""
    return all(environ.get(k) for k in ENV_VARS)


def timeout_s(environ: Mapping[str, str] = os.environ) -> float:
    """The collective timeout in seconds (``CLOD_DIST_TIMEOUT``, default 1800).

    Raises:
        ValueError: the variable is not a positive number (message names it).
    """
    raw = environ.get(TIMEOUT_ENV)
    if not raw:
        return DEFAULT_TIMEOUT_S
    try:
        v = float(raw)
    except ValueError:
        v = -1.0
    if not v > 0:
        raise ValueError(f"{TIMEOUT_ENV}={raw!r}: must be a number of seconds > 0")
    return v


@dataclass
class Group:
    """This process's place in the data-parallel run.

    Attributes:
        rank, world_size, local_rank: from torchrun's environment.
        backend: ``"gloo"`` or ``"nccl"``.
        device: the torch device this rank trains on.
        timeout: seconds before a collective gives up.
    """

    rank: int
    world_size: int
    local_rank: int
    backend: str
    device: torch.device
    timeout: float

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that logs and writes."""
        return self.rank == 0

    def _fail(self, what: str, e: BaseException) -> PeerLost:
        why = " ".join(str(e).split())[:160] or type(e).__name__
        return PeerLost(f"rank {self.rank} of {self.world_size}: lost contact with the other processes during "
                        f"{what} (one died, was killed or did not answer within {self.timeout:g} s: {why})")

    def all_reduce(self, t: Tensor, what: str, op: str = "sum") -> Tensor:
        """In-place ``all_reduce`` (``op``: sum, max, min) of ``t``.

        Raises:
            PeerLost: another rank died or timed out.
        """
        import torch.distributed as dist

        ops = {"sum": dist.ReduceOp.SUM, "max": dist.ReduceOp.MAX, "min": dist.ReduceOp.MIN}
        try:
            dist.all_reduce(t, op=ops[op])
        except Exception as e:  # gloo/NCCL raise RuntimeError subclasses (DistBackendError, ...)
            raise self._fail(what, e) from None
        return t

    def broadcast(self, t: Tensor, what: str, src: int = 0) -> Tensor:
        """In-place broadcast of ``t`` from rank ``src``. Raises PeerLost."""
        import torch.distributed as dist

        try:
            dist.broadcast(t, src=src)
        except Exception as e:
            raise self._fail(what, e) from None
        return t

    def barrier(self, what: str) -> None:
        """Wait for every rank (an all-reduce of one number, so it works on gloo and NCCL and
        honours the timeout). Raises PeerLost."""
        self.all_reduce(torch.zeros(1, device=self.device), what)


def init(device: str | torch.device = "cpu", environ: Mapping[str, str] = os.environ) -> Group:
    """Join the process group described by torchrun's environment (``env://``).

    Args:
        device: ``cpu`` (gloo) or ``cuda`` (NCCL; this rank uses GPU ``LOCAL_RANK``).

    Returns:
        the :class:`Group`.

    Raises:
        ValueError: the environment lacks torchrun's variables, or holds bad values.
        PeerLost: the other ranks did not join within the timeout.
    """
    import torch.distributed as dist

    missing = [k for k in ENV_VARS if not environ.get(k)]
    if missing:
        raise ValueError(f"--distributed: {', '.join(missing)} not set; launch with "
                         "torchrun --nproc_per_node=N -m clod_adapter.cli.adapt ... (or set MASTER_ADDR, MASTER_PORT, "
                         "RANK, WORLD_SIZE for each process)")
    try:
        rank, world = int(environ["RANK"]), int(environ["WORLD_SIZE"])
        local = int(environ.get("LOCAL_RANK", environ["RANK"]))
    except ValueError:
        raise ValueError("--distributed: RANK, WORLD_SIZE and LOCAL_RANK must be integers") from None
    if not (world >= 1 and 0 <= rank < world):
        raise ValueError(f"--distributed: RANK={rank} must be in [0, WORLD_SIZE={world})")
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.set_device(local % max(torch.cuda.device_count(), 1))
        dev = torch.device("cuda", torch.cuda.current_device())
        backend = "nccl"
    else:
        backend = "gloo"
    t = timeout_s(environ)
    if not dist.is_initialized():
        try:
            dist.init_process_group(backend, init_method="env://", rank=rank, world_size=world,
                                    timeout=datetime.timedelta(seconds=t))
        except Exception as e:
            why = " ".join(str(e).split())[:200] or type(e).__name__
            raise PeerLost(f"rank {rank} of {world}: could not join the process group at "
                           f"{environ['MASTER_ADDR']}:{environ['MASTER_PORT']} ({backend}) within {t:g} s: {why}") from None
    global _JOINED
    _JOINED = True
    g = Group(rank=rank, world_size=world, local_rank=local, backend=backend, device=dev, timeout=t)
    g.barrier("start-up")
    return g


def shutdown() -> None:
    """Leave the process group (no-op when not in one)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        try:
            dist.destroy_process_group()
        except Exception:  # a broken group after a lost peer: nothing left to release
            pass


def exit_process(code: int) -> int:
    """End a process that joined a process group with ``os._exit(code)`` after flushing stdout
    and stderr; return ``code`` otherwise.

    Gloo's worker threads release the last collectives' tensors asynchronously; when that
    happens while Python is shutting down, the thread needs the GIL, is terminated by the
    interpreter and the process aborts (SIGABRT, "terminate called without an active
    exception"; pytorch/pytorch#190489, seen here about once in ten 2-rank runs, even after
    ``destroy_process_group``). Everything this job writes is complete and atomic before it
    returns, so skipping the interpreter's shutdown loses nothing."""
    if not _JOINED:
        return code
    import sys

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:
            pass
    os._exit(code)


def _trainable(optimizer: torch.optim.Optimizer) -> list[Tensor]:
    return [p for grp in optimizer.param_groups for p in grp["params"] if p.requires_grad]


def combine_step(optimizer: torch.optim.Optimizer, rows: dict, views: int, group: Optional[Group],
                 stop: bool = False) -> tuple[dict, bool]:
    """Turn the gradients of one step's views into their mean, over the ranks when ``group``.

    On entry each parameter's ``.grad`` holds the sum of the gradients of the views this process
    rendered (None where none reached it), and ``rows`` maps each of those views' index ``j`` in
    the step to ``(loss, psnr, eta)``. On return ``.grad`` is the mean over all ``views`` views of
    the step (None where no view of any rank reached the parameter, so Adam skips it as in one
    process), identical on every rank, and ``rows`` covers every view of the step.

    The sums are in the parameters' dtype (float32); with two ranks, or one process, the sum of
    two gradients is exact to the last bit in either order, so 2 ranks give bit-identical
    parameters to 1 process with ``views_per_step = 2`` in deterministic mode; with more ranks the
    summation order of the backend may change the last bits.

    Args:
        optimizer: the optimiser whose trainable parameters are combined.
        rows: ``{j: (loss, psnr, eta)}`` of this process's views.
        views: views in the step (``views_per_step``).
        group: the data-parallel group, or None (one process: only the division).
        stop: this rank was asked to stop (SIGINT/SIGTERM).

    Returns:
        (rows of all views, whether any rank asked to stop).

    Raises:
        PeerLost: another rank died or timed out.
    """
    params = _trainable(optimizer)
    if group is None:
        for p in params:
            if p.grad is not None:
                p.grad.div_(views)
        return rows, stop
    dev = params[0].device if params else group.device
    # the step's records, which parameters got a gradient, and the stop flag, in one reduction
    info = torch.zeros(3 * views + len(params) + 1, dtype=torch.float64, device=dev)
    for j, r in rows.items():
        info[3 * j: 3 * j + 3] = torch.tensor(r, dtype=torch.float64)
    for i, p in enumerate(params):
        info[3 * views + i] = float(p.grad is not None)
    info[-1] = float(stop)
    group.all_reduce(info, "the step's reduction")
    got = info[3 * views: 3 * views + len(params)].tolist()
    for p, n in zip(params, got):
        if n == 0:
            p.grad = None
            continue
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        group.all_reduce(p.grad, "the gradient reduction")
        p.grad.div_(views)
    vals = info[: 3 * views].view(views, 3).tolist()
    return {j: tuple(vals[j]) for j in range(views)}, bool(info[-1].item() > 0)


@torch.no_grad()
def broadcast_params(state, group: Group) -> None:
    """Give every rank rank 0's trainable parameters and Adam moments (after the
    initialisation or a resume), so the ranks start identical. Raises PeerLost."""
    for p in _trainable(state.optimizer):
        group.broadcast(p.data, "the start-up broadcast")
        st = state.optimizer.state.get(p, {})
        for key in ("exp_avg", "exp_avg_sq"):
            if key in st:
                group.broadcast(st[key], "the start-up broadcast")


@torch.no_grad()
def check_in_sync(state, group: Group) -> None:
    """Raise RuntimeError unless every rank holds the same trainable parameters (their sums and
    sums of squares compared with a min/max reduction; a guard against a silent divergence).
    Raises PeerLost when another rank is gone."""
    params = _trainable(state.optimizer)
    sig = torch.tensor([v for p in params for v in (float(p.double().sum()), float(p.double().square().sum()))]
                       + [float(state.iteration)], dtype=torch.float64, device=group.device)
    lo, hi = sig.clone(), sig.clone()
    group.all_reduce(lo, "the final check", "min")
    group.all_reduce(hi, "the final check", "max")
    if not torch.equal(lo, hi):
        raise RuntimeError(f"rank {group.rank}: the ranks' parameters differ after training (a bug; "
                           "please report it with the command line)")
