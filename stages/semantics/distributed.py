"""The ranks of a distributed fit: torchrun's environment, the process group, the collectives.

`goi fit-field --distributed` runs under torchrun (one process per rank, rendezvous by c10d).
The fit's kernels are numba on the CPU, so the backend is gloo whatever the machine has. Every
collective waits at most the run's timeout, and a failure (another rank gone, a timeout)
becomes one GoiError line instead of a hang or a traceback.
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

from stages.core.errors import GoiError

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
    (that rank stopped) or when the timeout passes."""
    try:
        yield
    except (RuntimeError, ValueError, OSError) as e:  # DistError is a RuntimeError
        first = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
        raise GoiError(
            f"--distributed: {what} failed (another rank stopped, or none answered within "
            f"--dist-timeout-s {timeout_s:g}): {first}"
        ) from None


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
            dist.init_process_group("gloo", timeout=timedelta(seconds=timeout_s))
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
