"""The examples in the public API's docstrings run, and say what they show."""

from __future__ import annotations

import doctest
import importlib
import inspect
from types import ModuleType

import pytest

#: Modules whose docstrings hold runnable examples: every module that defines
#: an entry of :data:`DOCUMENTED` (checked below), and a few more.
MODULES = [
    "torchcf.models",
    "torchcf.models.augmented",
    "torchcf.models.base",
    "torchcf.models.effects",
    "torchcf.data.extract",
    "torchcf.data.formats",
    "torchcf.data.pairset",
    "torchcf.data.reader",
    "torchcf.data.registry",
    "torchcf.data.splits",
    "torchcf.sim.rollout",
    "torchcf.sim.synthetic",
    "torchcf.posterior.learned_set",
    "torchcf.traffic.battery",
    "torchcf.traffic.safety",
    "torchcf.traffic.sampler",
    "torchcf.traffic.scenarios",
    "torchcf.evaluation.bootstrap",
    "torchcf.evaluation.coverage",
    "torchcf.evaluation.entropic",
    "torchcf.evaluation.metrics",
    "torchcf.evaluation.plots",
    "torchcf.evaluation.sbc",
    "torchcf.evaluation.uncertainty",
    "torchcf.sumo.cosim",
    "torchcf.sumo.export",
    "torchcf.sumo.fcd",
    "torchcf.sumo.network",
    "torchcf.sumo.verify",
    "torchcf.qp.boxqp",
    "torchcf.qp.general",
    "torchcf.qp.problem",
    "torchcf.predict",
    "torchcf.predict.predict",
    "torchcf.predict.trained",
    "torchcf.system.console",
    "torchcf.system.errors",
    "torchcf.system.files",
    "torchcf.system.process",
    "torchcf.system.records",
    "torchcf.system.signals",
    "torchcf.calibration.budget",
    "torchcf.calibration.calibrate",
    "torchcf.calibration.methods",
    "torchcf.calibration.of_config",
    "torchcf.calibration.priors",
    "torchcf.calibration.results",
    "torchcf.calibration.state",
    "torchcf.evaluation.evaluate",
    "torchcf.train.run",
    "torchcf.config.diagnose",
    "torchcf.config.loading",
    "torchcf.config.methods",
    "torchcf.config.overrides",
    "torchcf.config.pairs",
    "torchcf.config.schema",
    "torchcf.runs.directory",
    "torchcf.runs.metrics",
    "torchcf.runs.summary",
    "torchcf.runs.tensorboard",
    "torchcf.study.crossval",
    "torchcf.study.demo",
    "torchcf.study.pipeline",
    "torchcf.abc.distributed",
    "torchcf.abc.hybrid",
    "torchcf.abc.particles",
    "torchcf.abc.rejection",
    "torchcf.abc.rounds",
    "torchcf.abc.smc",
    "torchcf.abc.streams",
    "torchcf.abc.topn",
    "torchcf.amortised.encoder",
    "torchcf.amortised.estimator",
    "torchcf.amortised.features",
    "torchcf.amortised.inference",
    "torchcf.amortised.proposals",
    "torchcf.amortised.simulations",
    "torchcf.amortised.space",
    "torchcf.amortised.training",
    "torchcf.amortised.training_state",
]

#: Packages and modules whose public entries carry an example: the names of
#: their ``__all__`` (a module without one: the public classes and functions
#: it defines) that are classes or functions of the package itself (the names
#: of ``torchcf.__all__`` are checked in the packages they come from). Left out:
#: constants and type aliases, exceptions, names re-exported from elsewhere
#: (``torchcf.runs``...), and callables made under another name (the checked
#: argparse types of ``torchcf.system.console``).
DOCUMENTED = [
    "torchcf.calibration",
    "torchcf.models",
    "torchcf.data",
    "torchcf.data.extract",
    "torchcf.data.formats",
    "torchcf.data.reader",
    "torchcf.data.splits",
    "torchcf.sim.rollout",
    "torchcf.sim.synthetic",
    "torchcf.posterior",
    "torchcf.traffic",
    "torchcf.evaluation.bootstrap",
    "torchcf.evaluation.coverage",
    "torchcf.evaluation.entropic",
    "torchcf.evaluation.metrics",
    "torchcf.evaluation.plots",
    "torchcf.evaluation.sbc",
    "torchcf.evaluation.uncertainty",
    "torchcf.sumo",
    "torchcf.qp",
    "torchcf.predict",
    "torchcf.system.console",
    "torchcf.system.errors",
    "torchcf.system.files",
    "torchcf.system.process",
    "torchcf.system.records",
    "torchcf.system.signals",
    "torchcf.config",
    "torchcf.runs.directory",
    "torchcf.runs.metrics",
    "torchcf.runs.summary",
    "torchcf.runs.tensorboard",
    "torchcf.study.crossval",
    "torchcf.study.demo",
    "torchcf.study.pipeline",
    "torchcf.abc",
    "torchcf.amortised",
]


def _package(module: ModuleType) -> str:
    """The package a module belongs to (a package: itself)."""
    if hasattr(module, "__path__"):
        return module.__name__
    return module.__name__.rpartition(".")[0]


def public_entries(name: str) -> dict[str, object]:
    """The classes and functions of ``name`` that must carry an example
    (:data:`DOCUMENTED`), by their public name."""
    module = importlib.import_module(name)
    names = getattr(module, "__all__", None)
    if names is None:
        names = [
            key
            for key, value in vars(module).items()
            if not key.startswith("_")
            and getattr(value, "__module__", None) == module.__name__
        ]
    package = _package(module)
    found = {}
    for key in names:
        entry = getattr(module, key)
        if not (inspect.isclass(entry) or inspect.isfunction(entry)):
            continue  # a constant, a type alias, a module
        if inspect.isclass(entry) and issubclass(entry, BaseException):
            continue
        if not entry.__module__.startswith(package):
            continue  # re-exported from another package
        if entry.__name__ != key:
            continue  # made under another name (an argparse type)
        found[key] = entry
    return found


ENTRIES = [
    pytest.param(package, key, id=f"{package}.{key}")
    for package in DOCUMENTED
    for key in public_entries(package)
]


@pytest.mark.parametrize("name", MODULES)
def test_the_examples_run(name):
    module = importlib.import_module(name)
    flags = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE
    failed, attempted = doctest.testmod(module, optionflags=flags, verbose=False)
    assert failed == 0
    assert attempted > 0, f"{name}: no example"


@pytest.mark.parametrize(("package", "key"), ENTRIES)
def test_the_entry_points_carry_an_example(package, key):
    entry = public_entries(package)[key]
    assert ">>> " in (entry.__doc__ or ""), f"{package}.{key}: no example"
    # ... and it runs: doctest finds an entry's examples in its own module only
    assert entry.__module__ in MODULES, f"{entry.__module__} is not in MODULES"


def test_every_package_has_entries_to_check():
    """A package whose ``__all__`` moved away would pass the check vacuously."""
    empty = [package for package in DOCUMENTED if not public_entries(package)]
    assert not empty, empty
