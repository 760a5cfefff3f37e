"""The one base class of every error that a command line reports as one line.

An error of the user's making (config, data, arguments, a run directory) or of the
machine (a full disk, an unreachable process group) is a :class:`TorchcfError`;
every ``python -m torchcf.<x>`` prints it as ``error: <one line>`` and exits with
code 2 (:mod:`torchcf.cli`). Anything else is a bug and keeps its traceback.

Each module's own error derives from it (and, where callers catch a builtin,
from that builtin too: :class:`torchcf.config.ConfigError` is also a
``ValueError``), so a new error class needs no list to be kept up to date.
"""


class TorchcfError(Exception):
    """An error reported as one line on stderr with exit code 2."""


__all__ = ["TorchcfError"]
