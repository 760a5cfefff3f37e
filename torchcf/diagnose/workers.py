"""Effect arms side by side: a pool of worker processes for the attribution.

The effect arms of a step are independent of one another (each a pure function
of the step's start, its base and placebo arms and its own seeded random
numbers: :mod:`torchcf.diagnose.arms.arena`), so they can run in several processes at
once. On a CPU the rollouts of an arm simulate a few thousand particles per
call, where most of a call's time is the fixed cost of every operation, not the
arithmetic: one thread per process does nearly as much as two, and two
processes of one thread each do nearly twice what one process of two threads
does (``tools/bench_loop.py`` times the loop with them).

:class:`ArmPool` starts ``workers`` processes, each with one torch thread;
the rounds the workers search are counted in the parent's progress bar through
a queue. Where the system can ``fork`` (Linux), a worker is a copy of the
parent: no interpreter to start, and no re-import of the caller's script (which
``spawn`` would run again without a ``if __name__ == "__main__"`` guard); like
PyTorch's data-loader workers, it runs one thread, so the parent's thread pool
is never used across the fork. Elsewhere workers are spawned. Results are the
same as in one process: every arm is seeded by its place and its rollouts are
elementwise in the particles (tested).

Workers ``1`` (or a budget too small to pay for starting them,
:func:`worker_count`) runs everything in the calling process.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any

import torch

#: Simulated steps per search round (fit pairs x slots x copies x steps) from
#: which ``diagnose.workers = 0`` (auto) starts workers: starting one costs a
#: few seconds, an effect arm's dozens of rounds of this size several.
PARALLEL_MIN_STEPS = 2e6

_TICKS: Any = None  # a worker's queue to the parent's progress bar


def worker_count(asked: int, arms: int, round_steps: float) -> int:
    """How many worker processes run a step's ``arms`` effect arms.

    Args:
        asked: ``diagnose.workers``: 0 (auto) or a number (1: none, in process).
        arms: effect arms left to compute.
        round_steps: simulated steps of one search round (its cost).

    Auto starts one worker per core (at most one per arm) where a round is worth
    it (:data:`PARALLEL_MIN_STEPS`), and none on a single core.
    """
    if asked > 0:
        return max(1, min(asked, arms))
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
    if cores < 2 or arms < 2 or round_steps < PARALLEL_MIN_STEPS:
        return 1
    return min(cores, arms)


def _start_worker(ticks: Any, threads: int) -> None:
    global _TICKS
    _TICKS = ticks
    torch.set_num_threads(threads)


def tick(amount: float = 1.0) -> None:
    """A worker's progress: ``amount`` search rounds done (sent to the parent)."""
    if _TICKS is not None:
        _TICKS.put(amount)


class ArmPool:
    """Worker processes for effect arms (module docstring); a context manager.

    Args:
        workers: processes (>= 2).
        progress: called in the parent with the rounds the workers report.
    """

    def __init__(self, workers: int, progress: Callable[[float], None]) -> None:
        methods = multiprocessing.get_all_start_methods()
        context = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
        threads = 1
        self.ticks = context.Queue()
        self.progress = progress
        self.executor = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=context,
            initializer=_start_worker,
            initargs=(self.ticks, threads),
        )
        self.listening = True
        self.listener = threading.Thread(target=self._listen, daemon=True)
        self.listener.start()

    def _listen(self) -> None:
        while self.listening:
            try:
                amount = self.ticks.get(timeout=0.2)
            except queue.Empty:
                continue
            except (EOFError, OSError):  # the queue closed under us
                return
            self.progress(amount)

    def results(
        self, function: Callable[..., Any], tasks: Iterable[tuple[Any, tuple]]
    ) -> Iterator[tuple[Any, Any]]:
        """``(label, function(*args))`` for every ``(label, args)``, as each
        finishes (a worker's exception is raised here)."""
        pending: dict[Future, Any] = {
            self.executor.submit(function, *args): label for label, args in tasks
        }
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                label = pending.pop(future)
                yield label, future.result()

    def close(self) -> None:
        self.executor.shutdown(wait=True, cancel_futures=True)
        self.listening = False
        self.listener.join()
        self.ticks.close()

    def __enter__(self) -> ArmPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["PARALLEL_MIN_STEPS", "ArmPool", "tick", "worker_count"]
