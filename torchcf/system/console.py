"""One policy for every command line (``torchcf COMMAND``, ``python -m torchcf ...``).

The plumbing the commands share, low in the house so that any module may use it
(:mod:`torchcf.cli` holds the commands themselves, at the top, and re-exports
these names for older imports): the ``--help`` format, ``--set``, the
``error: <one line>`` of a failure, and the exit codes.

:func:`run_main` runs a command's body and maps its failures to exit codes:

- 0: done;
- 2: an error of the user's making or of the machine — a
  :class:`~torchcf.system.errors.TorchcfError` (bad config, data, arguments, run
  directory, a corrupted or unwritable file) or an ``OSError`` (a file system or
  device failing underneath) — printed as ``error: <one line>`` on stderr, never a
  traceback;
- 130: interrupted (Ctrl-C), 143: terminated (SIGTERM, treated as Ctrl-C:
  :mod:`torchcf.system.signals`), each with a hint on how to continue.

Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
from collections.abc import Callable
from typing import NoReturn

from .errors import TorchcfError
from .signals import Stopped, terminate_as_interrupt

#: Exit code of an error of the user's making or of the machine.
EXIT_USER_ERROR = 2
#: Exit code of an interrupted command (128 + SIGINT).
EXIT_INTERRUPTED = 130


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` that shows each option's default, where it has one worth
    saying (not for a required option, a flag, or a default of None, which the
    help text explains).

    Examples:
        >>> import argparse
        >>> from torchcf.system.console import DefaultsHelpFormatter
        >>> parser = argparse.ArgumentParser(formatter_class=DefaultsHelpFormatter)
        >>> _ = parser.add_argument("--draws", type=int, default=200, help="draws")
        >>> _ = parser.add_argument("--out", help="output folder")
        >>> text = parser.format_help()
        >>> "(default: 200)" in text, "(default: None)" in text
        (True, False)
    """

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.required or action.default in (None, False, argparse.SUPPRESS):
            return action.help or ""
        return super()._get_help_string(action) or ""


class OneLineParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose usage errors are one line: ``error:
    <what>`` and where the usage is (``PROG --help``), exit code 2, like every
    other error of the commands (the whole usage block is ``--help``'s).

    Examples:
        >>> import contextlib, io
        >>> from torchcf.system.console import OneLineParser
        >>> parser = OneLineParser(prog="torchcf predict")
        >>> _ = parser.add_argument("--draws", type=int)
        >>> err = io.StringIO()
        >>> with contextlib.redirect_stderr(err):
        ...     try:
        ...         parser.parse_args(["--draws", "many"])
        ...     except SystemExit as exit:
        ...         print(exit.code)
        2
        >>> text = err.getvalue()
        >>> text.count("\\n"), "(usage: torchcf predict --help)" in text
        (1, True)
    """

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USER_ERROR, f"error: {message} (usage: {self.prog} --help)\n")


#: The longest error line printed [characters]: a message that quotes a
#: user's input (a 100 000-character key, a header of 25 000 names) keeps its
#: head and its tail (the hint) and says how much was left out.
LONGEST_ERROR = 400


def one_line(error: BaseException) -> str:
    """The error's message on one line (its class name when it has none), at
    most :data:`LONGEST_ERROR` characters: a longer one keeps its first and last
    part around ``[... N characters ...]``.

    Examples:
        >>> from torchcf.system.console import one_line
        >>> one_line(ValueError("bad value\\n   in row 3"))
        'bad value in row 3'
        >>> one_line(KeyError())  # no message: the class name
        'KeyError'
    """
    text = " ".join(str(error).split()) or type(error).__name__
    if len(text) <= LONGEST_ERROR:
        return text
    head, tail = LONGEST_ERROR * 2 // 3, LONGEST_ERROR // 4
    cut = len(text) - head - tail
    return f"{text[:head]} [... {cut} characters ...] {text[-tail:]}"


def print_error(message: str) -> None:
    """``error: <message>`` on stderr.

    Examples:
        >>> import contextlib, io
        >>> from torchcf.system.console import print_error
        >>> err = io.StringIO()
        >>> with contextlib.redirect_stderr(err):
        ...     print_error("no such file: config.json")
        >>> err.getvalue()
        'error: no such file: config.json\\n'
    """
    print(f"error: {message}", file=sys.stderr)


def add_overrides(parser: argparse.ArgumentParser, metavar: str, example: str) -> None:
    """The ``--set KEY=VALUE`` option every command shares (repeatable; the value
    is JSON, or a plain string), collected in ``args.overrides``.

    Examples:
        >>> import argparse
        >>> from torchcf.system.console import add_overrides
        >>> parser = argparse.ArgumentParser()
        >>> add_overrides(parser, "KEY=VALUE", "abc.seed=1")
        >>> args = parser.parse_args(["--set", "abc.seed=1", "--set", "eval.beta=0.2"])
        >>> args.overrides
        ['abc.seed=1', 'eval.beta=0.2']
    """
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar=metavar,
        help=f"override a config field (repeatable), e.g. --set {example}",
    )


#: Seconds between a progress bar's lines where stderr is no terminal (a log
#: file, a pipe): progress moves at least every 10 s without flooding the log.
LOG_INTERVAL = 9.0


def bar_interval() -> float:
    """tqdm's ``mininterval`` for a bar on stderr: live on a terminal, a line
    every :data:`LOG_INTERVAL` seconds otherwise.

    Examples:
        >>> from torchcf.system.console import bar_interval
        >>> bar_interval() in (0.1, 9.0)  # [s]: 0.1 on a terminal, 9 in a log file
        True
    """
    return 0.1 if sys.stderr.isatty() else LOG_INTERVAL


def _whole(text: str) -> int:
    """``"200000"``, ``"2e5"`` -> 200000; anything else raises ValueError."""
    try:
        return int(text)
    except ValueError:
        value = float(text)  # "2e5"; raises ValueError on words
        if not value.is_integer():
            raise ValueError(text) from None
        return int(value)


def _checked(parse: Callable[[str], float], holds: Callable[[float], bool], what: str):
    """An argparse ``type=``: ``parse`` the text and keep it if ``holds``, else
    a one-line usage error naming ``what`` was expected."""

    def convert(text: str):
        try:
            value = parse(text)
        except (ValueError, OverflowError):
            value = None
        if value is None or not holds(value):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text[:40]!r}")
        return value

    convert.__name__ = what  # argparse names the type in some messages
    return convert


#: Checked argparse ``type=`` of every numeric option (tests/test_layout.py
#: refuses a bare ``type=int`` / ``type=float`` in the commands and tools: a
#: negative count or a NaN duration is refused at the command line, not found
#: as a traceback deep in the run). Counts accept ``2e5``.
count = _checked(_whole, lambda n: n >= 1, "a whole number >= 1")
natural = _checked(_whole, lambda n: n >= 0, "a whole number >= 0")
positive = _checked(float, lambda x: math.isfinite(x) and x > 0.0, "a number > 0")
nonnegative = _checked(float, lambda x: math.isfinite(x) and x >= 0.0, "a number >= 0")
finite = _checked(float, math.isfinite, "a finite number")
open_fraction = _checked(float, lambda x: 0.0 < x < 1.0, "a number between 0 and 1")
share = _checked(float, lambda x: 0.0 <= x < 1.0, "a number >= 0 and < 1")


def folder(text: str) -> str:
    """An argparse ``type=`` of an output folder: a non-empty name (``--out ''``
    would write into the working directory)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an output folder, got an empty name")
    return text


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

    Examples:
        >>> import contextlib, io
        >>> from torchcf.system.console import run_main
        >>> from torchcf.system.errors import TorchcfError
        >>> def body():
        ...     raise TorchcfError("data: no such folder")
        >>> err = io.StringIO()
        >>> with contextlib.redirect_stderr(err):
        ...     codes = run_main(lambda: 0), run_main(body)
        >>> codes, err.getvalue()
        ((0, 2), 'error: data: no such folder\\n')
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
    "LOG_INTERVAL",
    "add_overrides",
    "bar_interval",
    "count",
    "EXIT_USER_ERROR",
    "finite",
    "natural",
    "nonnegative",
    "open_fraction",
    "OneLineParser",
    "share",
    "positive",
    "one_line",
    "print_error",
    "run_main",
]
