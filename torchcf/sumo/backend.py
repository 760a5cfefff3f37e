"""SUMO itself: the optional packages, their binaries and one simulation at a time.

torchcf drives Eclipse SUMO (https://eclipse.dev/sumo) through two PyPI packages,
the extra ``torchcf[sumo]``:

- ``eclipse-sumo``: the binaries (``sumo``, ``netconvert``) under
  ``sumo.SUMO_HOME/bin``;
- ``libsumo``: SUMO linked into the Python process (TraCI's API without a socket).

Neither is imported by ``import torchcf``; :func:`require_libsumo` and
:func:`binary` import them on first use and, where they are missing, raise
:class:`SumoMissingError` naming the extra to install.

libsumo runs one simulation per process: :func:`running` starts one and always
closes it, and refuses to start a second while the first runs.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

from ..system.console import one_line
from ..system.errors import TorchcfError

#: What a user runs to get SUMO.
INSTALL_HINT = "pip install 'torchcf[sumo]' (eclipse-sumo and libsumo 1.28)"


class SumoError(TorchcfError, RuntimeError):
    """SUMO cannot do what was asked (one-line message, exit code 2)."""


class SumoMissingError(SumoError, ImportError):
    """SUMO's Python packages are not installed."""


_RUNNING = False


def require_libsumo() -> ModuleType:
    """The ``libsumo`` module.

    Raises:
        SumoMissingError: it is not installed (the message names the extra).
    """
    try:
        return importlib.import_module("libsumo")
    except ImportError as error:
        raise SumoMissingError(
            f"SUMO is not installed ({error.msg}): {INSTALL_HINT}"
        ) from None


def sumo_home() -> Path:
    """``SUMO_HOME`` of the ``eclipse-sumo`` package.

    Raises:
        SumoMissingError: the package is not installed.
    """
    try:
        sumo = importlib.import_module("sumo")
    except ImportError:
        raise SumoMissingError(
            f"SUMO's binaries are not installed: {INSTALL_HINT}"
        ) from None
    home = getattr(sumo, "SUMO_HOME", None)
    if home is None:
        raise SumoMissingError(
            f"the 'sumo' module found is not eclipse-sumo's: {INSTALL_HINT}"
        )
    return Path(home)


def binary(name: str) -> Path:
    """The path of a SUMO binary (``"netconvert"``, ``"sumo"``).

    Raises:
        SumoMissingError: the package or the binary is missing.
    """
    path = sumo_home() / "bin" / name
    if not path.is_file() or not os.access(path, os.X_OK):
        raise SumoMissingError(f"{path}: no executable SUMO {name}: {INSTALL_HINT}")
    return path


@contextmanager
def running(arguments: Sequence[str]) -> Iterator[ModuleType]:
    """Start a libsumo simulation with these command-line ``arguments`` (without
    the program name), yield ``libsumo``, close it on the way out.

    Raises:
        SumoMissingError: libsumo is not installed.
        SumoError: a simulation already runs in this process, or SUMO refused
            the arguments or its input files, or failed while it ran (SUMO's
            message, on one line).
    """
    global _RUNNING
    libsumo = require_libsumo()
    if _RUNNING:
        raise SumoError("a SUMO simulation already runs in this process")
    failures = (libsumo.TraCIException, libsumo.FatalTraCIError)
    try:
        libsumo.start(["sumo", *arguments])
    except failures as error:
        raise SumoError(f"SUMO did not start: {one_line(error)}") from None
    _RUNNING = True
    try:
        yield libsumo
    except failures as error:
        raise SumoError(f"SUMO: {one_line(error)}") from None
    finally:
        _RUNNING = False
        libsumo.close()


__all__ = [
    "INSTALL_HINT",
    "SumoError",
    "SumoMissingError",
    "binary",
    "require_libsumo",
    "running",
    "sumo_home",
]
