"""Stopping a long command cleanly: SIGTERM like Ctrl-C, a checkpoint at the signal.

A batch system ends a job with SIGTERM, a user with Ctrl-C (SIGINT). Python
turns Ctrl-C into :class:`KeyboardInterrupt` wherever the program happens to
be, and ends on SIGTERM at once with exit code 143 and no word. Two pieces:

- :func:`terminate_as_interrupt` (every command line, :func:`torchcf.system.console.
  run_main`): SIGTERM raises :class:`Stopped`, a ``KeyboardInterrupt``, so a
  terminated command unwinds like an interrupted one (files being written stay
  whole: every write is atomic) and says so; its exit code stays 143.
- :class:`StopRequest` (around the training's stream of particles): the first
  SIGINT or SIGTERM only *asks* to stop; the training writes its checkpoint at
  the end of the round under way (a round is one chunk of particles: seconds)
  and then raises :class:`Stopped`, so ``--resume`` redoes at most that round.
  A second signal stops at once, as before.

Signal handlers can only be installed from the main thread; elsewhere both
pieces leave the handlers alone.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

#: The signals a user or a batch system stops a command with.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stopped(KeyboardInterrupt):
    """The command was stopped by ``signum`` (SIGINT: Ctrl-C, SIGTERM: kill).

    Attributes:
        signum: the signal's number; the command's exit code is ``128 + signum``.
        checkpointed: whether the work so far was saved before stopping.
    """

    def __init__(self, signum: int, checkpointed: bool = False) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.checkpointed = checkpointed


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises :class:`Stopped` (a ``KeyboardInterrupt``) while the
    block runs, so a terminated command unwinds as an interrupted one does.

    Examples:
        >>> import signal
        >>> from torchcf.system.signals import terminate_as_interrupt
        >>> before = signal.getsignal(signal.SIGTERM)
        >>> with terminate_as_interrupt():  # SIGTERM here raises Stopped
        ...     pass
        >>> signal.getsignal(signal.SIGTERM) is before  # restored
        True
    """
    if not _in_main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        raise Stopped(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class StopRequest:
    """A context in which SIGINT and SIGTERM ask to stop at the next safe point.

    The first signal is recorded in :attr:`signum` (and announced on stderr); the
    work checks :attr:`requested` at its safe points (the training: after each
    round, where it writes a checkpoint when a stop is requested) and calls
    :meth:`stop`. A second signal raises :class:`Stopped` at once.

    Examples:
        >>> import signal
        >>> from torchcf.system.signals import StopRequest, Stopped
        >>> with StopRequest() as stop:
        ...     stop.stop()  # no signal yet: goes on
        ...     stop.signum = signal.SIGTERM  # as the first SIGTERM records it
        ...     try:
        ...         stop.stop()  # the next safe point
        ...     except Stopped as stopped:
        ...         print(stopped.signum == signal.SIGTERM, stopped.checkpointed)
        True True
    """

    def __init__(self, what: str = "writing a checkpoint at the end of this round"):
        self.what = what
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def stop(self, checkpointed: bool = True) -> None:
        """Raise :class:`Stopped` if a stop was requested."""
        if self.signum is not None:
            raise Stopped(self.signum, checkpointed)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is not None:
            raise Stopped(signum)
        self.signum = signum
        name = signal.Signals(signum).name
        print(
            f"\n{name}: stopping, {self.what} (send it again to stop at once)",
            file=sys.stderr,
            flush=True,
        )

    def __enter__(self) -> StopRequest:
        if _in_main_thread():
            for signum in STOP_SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()


__all__ = ["STOP_SIGNALS", "StopRequest", "Stopped", "terminate_as_interrupt"]
