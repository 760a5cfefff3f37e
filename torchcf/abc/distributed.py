"""Sharding a training run over processes with torch.distributed (``torchrun``).

    torchrun --standalone --nproc-per-node 4 -m torchcf train configs/carII.json
    # on node 0 (HOST), then the same with --node-rank 1 on node 1
    torchrun --nnodes 2 --node-rank 0 --nproc-per-node 8 --master-addr HOST \\
        --master-port 29500 -m torchcf train configs/carII.json

:func:`init_from_env` reads the environment torchrun sets (``WORLD_SIZE``,
``RANK``, ``LOCAL_RANK``, ``MASTER_ADDR``, ``MASTER_PORT``) and joins the process
group: gloo for a CPU run, nccl for a CUDA run, where each process takes GPU
``LOCAL_RANK`` of its node. Without torchrun it returns :data:`SINGLE`, a group of
one process whose collective methods do nothing.

How the trainer shares a run (:func:`torchcf.train.train`):

* Each model's particle stream is processed in *rounds* of ``world_size`` chunks,
  rank ``r`` simulating the ``r``-th chunk of each round (:meth:`Group.shard`). The
  chunks are exactly those of a single process, so every particle gets the same
  score, bit for bit.
* After each round the ranks' replicas of the model's per-pair top-N buffer are
  merged (:meth:`Group.end_round`: an all-gather, then
  :meth:`torchcf.abc.topn.TopN.merge`, ties broken by particle index) and the invalid
  counts summed. Every rank then holds the buffer that one process holds after the
  same particles: the result is identical to a single-process run, and a checkpoint
  written at a round boundary is an ordinary checkpoint (a run may be resumed with
  another number of processes, or none).
* Rank 0 reads the checkpoint and the data and sends them to the others, and it
  alone writes: config, checkpoints, TensorBoard events, posterior, summary and the
  evaluation. An error of the user's making met by rank 0 in those steps is sent
  to every rank (:meth:`Group.on_main`), so all of them stop with the same one-line
  message and exit code 2 instead of waiting on each other.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any, TypeVar

import torch
import torch.distributed as dist
from torch import Tensor

from ..system.errors import TorchcfError
from .topn import TopN

__all__ = ["SINGLE", "Group", "GroupError", "init_from_env"]

T = TypeVar("T")

#: How long a rank waits on the others in one collective (rank 0 loading data or
#: writing a checkpoint, the slowest rank finishing its chunk).
TIMEOUT = timedelta(minutes=30)


class GroupError(TorchcfError, RuntimeError):
    """The process group cannot be joined, or rank 0 failed (one-line message)."""


@dataclass(frozen=True)
class Group:
    """The processes of one run and this process's place among them.

    Attributes:
        rank: this process, ``0 .. world_size - 1``; rank 0 writes the outputs.
        world_size: number of processes.
        local_rank: this process on its node (its GPU in a CUDA run).
        device: where collective tensors live (CPU for gloo, the GPU for nccl).

    Examples:
        >>> SINGLE.world_size, SINGLE.is_main
        (1, True)
        >>> group = Group(rank=1, world_size=4)  # the second of four processes
        >>> group.is_main, group.shard(first=0, stop=1000, chunk=100)
        (False, (100, 200))
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def is_main(self) -> bool:
        """True on rank 0, the process that reads checkpoints and writes outputs."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    def run_device(self, device: str) -> torch.device:
        """The device a run configured for ``device`` uses in this process.

        ``"cuda"`` without an index means this process's GPU (``LOCAL_RANK``) in a
        distributed run, so one config serves every process.
        """
        resolved = torch.device(device)
        if self.distributed and resolved.type == "cuda" and resolved.index is None:
            return torch.device("cuda", self.local_rank)
        return resolved

    def shard(self, first: int, stop: int, chunk: int) -> tuple[int, int]:
        """This rank's particles of the round that starts at particle ``first``.

        Args:
            first: first particle of the round.
            stop: particles in the stream (``abc.n_particles``).
            chunk: particles per chunk.

        Returns:
            ``(start, end)``: particles ``start .. end - 1``, empty when the stream
            ends before this rank's chunk.
        """
        start = min(first + self.rank * chunk, stop)
        return start, min(start + chunk, stop)

    def end_round(
        self, buffers: TopN | Sequence[TopN], invalid: int, due: bool
    ) -> tuple[int, bool]:
        """Synchronise the ranks at the end of a round.

        Merges the replicas of every buffer in place, so that every rank holds the
        best entries of every rank, and sums the invalid counts.

        Args:
            buffers: this rank's replica of the model's buffer (or buffers: the
                refinement's accepted set too).
            invalid: invalid rollouts in this rank's chunk of the round.
            due: whether a checkpoint is due (rank 0's clock decides).

        Returns:
            the invalid rollouts of the whole round, and rank 0's ``due``.
        """
        if not self.distributed:
            return invalid, due
        counts = self._all_gather(torch.tensor([invalid, int(due)], dtype=torch.int64))
        for buffer in [buffers] if isinstance(buffers, TopN) else buffers:
            score = self._all_gather(buffer.score)
            index = self._all_gather(buffer.index)
            theta = self._all_gather(buffer.theta)
            buffer.merge(score, index, theta)
        return int(counts[:, 0].sum()), bool(counts[0, 1])

    def sum(self, value: int) -> int:
        """``value`` summed over the ranks (itself in a single process)."""
        if not self.distributed:
            return value
        return int(self._all_gather(torch.tensor([value], dtype=torch.int64)).sum())

    def on_main(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` on rank 0 and hand its result to every rank.

        An exception raised by ``fn`` is raised on every rank: the same type with
        the same message where it can be rebuilt so (the errors of the user's
        making, which take one message), else a :class:`GroupError`. On the other
        ranks the exception carries ``from_main = True``, so that only rank 0
        reports it.
        """
        if not self.distributed:
            return fn(*args)
        payload: list[Any] = [None]
        error: BaseException | None = None
        if self.is_main:
            try:
                payload[0] = ("ok", fn(*args))
            except Exception as caught:  # noqa: BLE001 - sent to the others below
                error = caught
                payload[0] = ("error", type(caught), str(caught))
        dist.broadcast_object_list(payload, src=0, device=self._object_device())
        if error is not None:
            raise error
        status, *rest = payload[0]
        if status == "ok":
            return rest[0]
        kind, message = rest
        try:
            copy = kind(message)
        except Exception:  # noqa: BLE001 - an exception that takes other arguments
            copy = GroupError(f"rank 0 failed: {kind.__name__}: {message}")
        copy.from_main = True
        raise copy

    def close(self) -> None:
        """Leave the process group (nothing for a single process)."""
        if self.distributed and dist.is_initialized():
            dist.destroy_process_group()

    def _all_gather(self, tensor: Tensor) -> Tensor:
        """``(R, *tensor.shape)`` stack of every rank's ``tensor``, R = ``world_size``
        replicas (on ``tensor``'s device)."""
        local = tensor.to(self.device).contiguous()
        parts = [torch.empty_like(local) for _ in range(self.world_size)]
        dist.all_gather(parts, local)
        return torch.stack(parts).to(tensor.device)

    def _object_device(self) -> torch.device | None:
        return self.device if self.device.type == "cuda" else None


#: The group of a run without torchrun: one process, no collectives.
SINGLE = Group()


def init_from_env(device: str = "cpu") -> Group:
    """Join the process group that ``torchrun`` describes in the environment.

    Args:
        device: the run's configured device; a CUDA run uses nccl and the GPU
            ``LOCAL_RANK`` (unless the device names one), a CPU run gloo.

    Returns:
        :data:`SINGLE` when ``WORLD_SIZE`` is unset or 1, else this process's
        :class:`Group`.

    Raises:
        GroupError: a malformed environment, CUDA asked for but absent, or a
            process group that cannot be joined.

    Examples:
        >>> group = init_from_env("cpu")  # no torchrun: a single process
        >>> group is SINGLE, group.world_size
        (True, 1)
    """
    try:
        world_size = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", "0"))
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    except ValueError as error:
        raise GroupError(f"torchrun environment: {error}") from None
    if world_size <= 1:
        return SINGLE
    if not 0 <= rank < world_size:
        raise GroupError(f"RANK={rank} is outside WORLD_SIZE={world_size}")
    group = Group(rank, world_size, local_rank)
    run_device = group.run_device(device)
    if run_device.type == "cuda":
        if not torch.cuda.is_available():
            raise GroupError(f"device {device!r} asked for but CUDA is not available")
        torch.cuda.set_device(run_device)
        backend, collective = "nccl", run_device
    else:
        backend, collective = "gloo", torch.device("cpu")
    if not dist.is_initialized():
        try:
            dist.init_process_group(backend, timeout=TIMEOUT)
        except Exception as error:  # noqa: BLE001 - rendezvous errors vary
            message = " ".join(str(error).split())
            raise GroupError(
                f"cannot join the {backend} process group: {message}"
            ) from None
    return Group(rank, world_size, local_rank, collective)
