"""The ranks of a distributed fit: torchrun's environment, the process group, the collectives.

`goi fit-field --distributed` runs under torchrun (one process per rank, rendezvous by c10d).
The fit's kernels are numba on the CPU, so the backend is gloo whatever the machine has. Every
collective waits at most the run's timeout, and a failure (another rank gone, a timeout)
becomes one GoiError line instead of a hang or a traceback. torch's C++ side logs its own
retries and errors, each with a C++ stack trace, straight to file descriptor 2 (a rank with no
rank 0 printed five of them under goi's line); what it writes during the rendezvous and the
collectives is kept out of the terminal (shown with --debug or GOI_DEBUG=1 when the collective
fails).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import numba
import torch
import torch.distributed as dist

from stages.core.errors import GoiError, debugging

#: What torchrun sets in each rank's environment; without it there is nothing to join.
TORCHRUN_ENV = (
    "RANK",
    "WORLD_SIZE",
    "LOCAL_RANK",
    "LOCAL_WORLD_SIZE",
    "MASTER_ADDR",
    "MASTER_PORT",
)

#: The version of what ranks exchange (shards, checkpoints, the step's sums): ranks that speak
#: different ones are refused at the rendezvous, like ranks of different goi versions.
PROTOCOL = 1


@dataclass
class Ranks:
    rank: int
    world: int
    local_world: int
    timeout_s: float

    @property
    def leader(self) -> bool:
        return self.rank == 0

    def all_reduce_(self, t: torch.Tensor, what: str) -> torch.Tensor:
        """Sum `t` over the ranks, in place."""
        with collective(what, self.timeout_s):
            dist.all_reduce(t)
        return t

    def barrier(self, what: str) -> None:
        with collective(what, self.timeout_s):
            dist.barrier()

    def gather_objects(self, obj: Any, what: str) -> list[Any]:
        """Every rank's `obj` (small, picklable), on every rank, in rank order."""
        out: list[Any] = [None] * self.world
        with collective(what, self.timeout_s):
            dist.all_gather_object(out, obj)
        return out

    def all_agree(self, flag: bool, what: str) -> bool:
        """True when `flag` holds on every rank."""
        t = torch.tensor([0 if flag else 1], dtype=torch.int64)
        return int(self.all_reduce_(t, what)) == 0


@contextlib.contextmanager
def collective(what: str, timeout_s: float) -> Iterator[None]:
    """Turn a failed collective into one line: gloo raises when a peer's connection closes
    (that rank stopped) or when the timeout passes. torch's C++ log of it goes elsewhere."""
    with _cpp_log() as log:
        try:
            yield
        except (RuntimeError, ValueError, OSError) as e:  # DistError is a RuntimeError
            first = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
            log.failed = True
            raise GoiError(
                f"--distributed: {what} failed (another rank stopped, or none answered within "
                f"--dist-timeout-s {timeout_s:g}): {first}"
            ) from None


class _CppLog:
    """Where file descriptor 2 goes while torch's C++ side may log: one temporary file per
    process, emptied after each use."""

    file: Any = None
    failed = False


@contextlib.contextmanager
def _cpp_log() -> Iterator[_CppLog]:
    """File descriptor 2 (where c10's logging writes, below Python's sys.stderr) sent to a
    temporary file while the block runs; written out after all only when it failed and
    --debug (or GOI_DEBUG=1) is given."""
    import sys
    import tempfile

    log = _CppLog()
    if _CppLog.file is None:
        _CppLog.file = tempfile.TemporaryFile()
    sys.stderr.flush()
    saved = os.dup(2)
    os.dup2(_CppLog.file.fileno(), 2)
    try:
        yield log
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        f = _CppLog.file
        if log.failed and debugging():
            f.seek(0)
            sys.stderr.write(f.read().decode("utf-8", "replace"))
        f.seek(0)
        f.truncate()


def rank_threads(threads: int, local_world: int) -> int:
    """CPU threads for one rank: `threads`, or this process's cores shared among the node's
    ranks (torchrun's LOCAL_WORLD_SIZE), at least one."""
    if threads > 0:
        return threads
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, (cores or 1) // max(local_world, 1))


def torchrun_env() -> tuple[int, int, int]:
    """(rank, world size, local world size) from torchrun's environment, checked."""
    missing = [k for k in TORCHRUN_ENV if not os.environ.get(k)]
    if missing:
        raise GoiError(
            f"--distributed: not started by torchrun ({', '.join(missing)} not set); run "
            "`torchrun --nproc-per-node N -m goi fit-field --distributed ...`, or drop "
            "--distributed"
        )
    try:
        rank, world, local_world = (
            int(os.environ[k]) for k in ("RANK", "WORLD_SIZE", "LOCAL_WORLD_SIZE")
        )
    except ValueError:
        raise GoiError(
            "--distributed: RANK, WORLD_SIZE or LOCAL_WORLD_SIZE is not an integer"
        ) from None
    if not (world >= 1 and 0 <= rank < world and 1 <= local_world <= world):
        raise GoiError(
            f"--distributed: RANK {rank}, WORLD_SIZE {world}, LOCAL_WORLD_SIZE {local_world} "
            "are inconsistent"
        )
    return rank, world, local_world


#: How much longer than --dist-timeout-s the rendezvous may take before it is given up: c10d
#: waits that long for the other ranks, then fails by itself; this margin is for the
#: connection, whose reply c10d waits for without a limit.
RENDEZVOUS_MARGIN_S = 10.0


def _rendezvous(timeout_s: float) -> None:
    """init_process_group, in a thread that is given up after the timeout (and a margin): a
    MASTER_PORT answered by a service that is not a torch rendezvous accepts the connection
    and never replies, and c10d would wait for it forever, deaf to SIGTERM."""
    import threading

    failed: list[BaseException] = []

    def join() -> None:
        try:
            dist.init_process_group("gloo", timeout=timedelta(seconds=timeout_s))
        except BaseException as e:  # handed to the caller's thread
            failed.append(e)

    t = threading.Thread(target=join, name="goi-rendezvous", daemon=True)
    t.start()
    t.join(timeout_s + RENDEZVOUS_MARGIN_S)
    if t.is_alive():
        where = f"{os.environ.get('MASTER_ADDR')}:{os.environ.get('MASTER_PORT')}"
        raise TimeoutError(
            f"{where} accepted the connection but never answered as a torch rendezvous "
            "(is MASTER_PORT another service's?)"
        )
    if failed:
        raise failed[0]


def start(timeout_s: float, threads: int) -> Ranks:
    """Join the process group torchrun prepared and check that every rank runs the same goi.
    Threads are set first: torch's and numba's pools, per rank."""
    import stages

    rank, world, local_world = torchrun_env()
    n = rank_threads(threads, local_world)
    torch.set_num_threads(n)
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    with collective("the rendezvous", timeout_s):
        if not dist.is_initialized():
            _rendezvous(timeout_s)
    ranks = Ranks(rank, world, local_world, timeout_s)
    mine = (stages.__version__, PROTOCOL)
    seen = ranks.gather_objects(mine, "the version check at the rendezvous")
    odd = [f"rank {r}: goi {v[0]} (protocol {v[1]})" for r, v in enumerate(seen) if v != mine]
    if odd:
        raise GoiError(
            f"--distributed: the ranks run different goi versions (rank {rank}: goi "
            f"{mine[0]} (protocol {mine[1]}); {', '.join(odd[:3])}); install the same goi on "
            "every node"
        )
    return ranks


def stop() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


class SumOverRanks(torch.autograd.Function):
    """The rendered features [B, S]: every rank's partial sum over its own Gaussians, summed
    over the ranks (one all_reduce). Every rank then computes the same loss from the same sum,
    so the loss's gradient with respect to a rank's partial sum is its gradient with respect
    to the sum: the backward passes it through, without communication."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx, partial: torch.Tensor, ranks: Ranks
    ) -> torch.Tensor:
        return ranks.all_reduce_(partial.detach().clone(), "the step's all_reduce")

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]  # noqa: ANN001, ANN205
        return grad, None
