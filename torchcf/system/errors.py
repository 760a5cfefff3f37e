"""The one base class of every error that a command line reports as one line.

An error of the user's making (config, data, arguments, a run directory) or of the
machine (a full disk, an unreachable process group) is a :class:`TorchcfError`;
every ``torchcf COMMAND`` prints it as ``error: <one line>`` and exits with
code 2 (:mod:`torchcf.system.console`). Anything else is a bug and keeps its traceback.

Each module's own error derives from it (and, where callers catch a builtin,
from that builtin too: :class:`torchcf.config.ConfigError` is also a
``ValueError``), so a new error class needs no list to be kept up to date.
"""

import difflib
from collections.abc import Iterable, Sequence


class TorchcfError(Exception):
    """An error reported as one line on stderr with exit code 2."""


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``" (did you mean 'idm'?)"`` for a mistyped name close to one of
    ``choices`` (difflib's ratio >= 0.6), else ``""``: the tail of a one-line
    message.

    Examples:
        >>> from torchcf.system.errors import did_you_mean
        >>> "unknown model 'imd'" + did_you_mean("imd", ["idm", "ovm", "gfm"])
        "unknown model 'imd' (did you mean 'idm'?)"
        >>> did_you_mean("xyz", ["idm", "ovm"])
        ''
    """
    close = difflib.get_close_matches(str(word).lower(), list(choices), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def first_names(names: Sequence[str], shown: int = 3) -> str:
    """``"a, b, c, ... 4 more"``: the first ``shown`` of ``names`` for a one-line
    message, and how many more.

    Examples:
        >>> from torchcf.system.errors import first_names
        >>> first_names(["idm", "ovm", "gfm", "fvdm", "hl"])
        'idm, ovm, gfm, ... 2 more'
    """
    more = f", ... {len(names) - shown} more" if len(names) > shown else ""
    return ", ".join(names[:shown]) + more


__all__ = ["TorchcfError", "did_you_mean", "first_names"]
