"""One policy for every command line (``torchcf COMMAND``, ``python -m torchcf.<x>``).

The plumbing the commands share, low in the house so that any module may use it
(:mod:`torchcf.cli` holds the commands themselves, at the top, and re-exports
these names for older imports): the ``--help`` format, ``--set``, the
``error: <one line>`` of a failure, and the exit codes.

:func:`run_main` runs a command's body and maps its failures to exit codes:

- 0: done;
- 2: an error of the user's making or of the machine — a
  :class:`~torchcf.errors.TorchcfError` (bad config, data, arguments, run
  directory, a corrupted or unwritable file) or an ``OSError`` (a file system or
  device failing underneath) — printed as ``error: <one line>`` on stderr, never a
  traceback;
- 130: interrupted (Ctrl-C), 143: terminated (SIGTERM, treated as Ctrl-C:
  :mod:`torchcf.signals`), each with a hint on how to continue.

Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Callable

from .errors import TorchcfError
from .signals import Stopped, terminate_as_interrupt

#: Exit code of an error of the user's making or of the machine.
EXIT_USER_ERROR = 2
#: Exit code of an interrupted command (128 + SIGINT).
EXIT_INTERRUPTED = 130


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` that shows each option's default, where it has one worth
    saying (not for a required option, a flag, or a default of None, which the
    help text explains)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.required or action.default in (None, False, argparse.SUPPRESS):
            return action.help or ""
        return super()._get_help_string(action) or ""


def one_line(error: BaseException) -> str:
    """The error's message on one line (its class name when it has none)."""
    return " ".join(str(error).split()) or type(error).__name__


def print_error(message: str) -> None:
    """``error: <message>`` on stderr."""
    print(f"error: {message}", file=sys.stderr)


def add_overrides(parser: argparse.ArgumentParser, metavar: str, example: str) -> None:
    """The ``--set KEY=VALUE`` option every command shares (repeatable; the value
    is JSON, or a plain string), collected in ``args.overrides``."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar=metavar,
        help=f"override a config field (repeatable), e.g. --set {example}",
    )


def run_main(
    body: Callable[[], int],
    *,
    report: Callable[[BaseException], None] | None = None,
    interrupted: str = "interrupted",
) -> int:
    """Run a command's ``body`` under the one policy (module docstring).

    Args:
        body: the command; returns its exit code (0 on success).
        report: prints a user or machine error (default ``error: <one line>``);
            a distributed command names the rank or stays silent on ranks whose
            error rank 0 reports.
        interrupted: the line printed on Ctrl-C (say how to continue); on
            SIGTERM its word "interrupted" reads "terminated".

    Returns:
        the exit code.
    """
    try:
        with terminate_as_interrupt():
            return body()
    except (TorchcfError, OSError) as error:
        (report or _print)(error)
        return EXIT_USER_ERROR
    except Stopped as stopped:
        word = "interrupted" if stopped.signum == signal.SIGINT else "terminated"
        if stopped.checkpointed:
            word += " (checkpoint written)"
        if interrupted:  # the line says how to continue
            print(interrupted.replace("interrupted", word, 1), file=sys.stderr)
        return 128 + stopped.signum
    except KeyboardInterrupt:
        print(interrupted, file=sys.stderr)
        return EXIT_INTERRUPTED


def _print(error: BaseException) -> None:
    print_error(one_line(error))


__all__ = [
    "DefaultsHelpFormatter",
    "EXIT_INTERRUPTED",
    "add_overrides",
    "EXIT_USER_ERROR",
    "one_line",
    "print_error",
    "run_main",
]
