"""A trained run as a predictor: its hybrid, its priors, its data's constants.

:meth:`TrainedRun.load` reads what prediction needs from a run directory (the
posterior, the resolved config's prior boxes, the training pairs and with them
the data's time step and leader length, the estimator of an amortised run), and
:meth:`TrainedRun.check` refuses pairs recorded otherwise: a model discretised
at one ``dt`` predicts nothing at another, and a gap computed with another
leader length is another gap.

Shapes: K parameters of a model (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..calibration.estimator_samples import trained_estimator
from ..calibration.of_config import method_of
from ..config import DataConfig, TrainConfig
from ..config.pairs import load_split
from ..data import PairSet, load_pairs
from ..data.registry import DATASETS, read_meta
from ..models import CFModel, get_model
from ..posterior import Posterior
from ..runs.directory import RunDir
from ..system.errors import TorchcfError

#: Relative tolerance of a time step or leader length that counts as the run's.
SAME_CONSTANT = 1e-6


class PredictError(TorchcfError, ValueError):
    """Pairs or a run that cannot be predicted (one-line message)."""


@dataclass(frozen=True, eq=False)
class TrainedRun:
    """What prediction reads from a trained run.

    Attributes:
        path: the run directory.
        config: its resolved config.
        posterior: its hybrid (``posterior.pt``).
        train: its training pairs (the population model is searched on them).
        priors: model name -> ``(K, 2)`` float64 prior box ``[low, high]``.
        estimator: the amortised estimator of an ``abc.method = "amortised"``
            run, else None.

    Examples:
        >>> from pathlib import Path
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.config import TrainConfig
        >>> from torchcf.posterior import ModelParticles, Posterior
        >>> from torchcf.predict import PredictSettings, TrainedRun, predict
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm, truth = get_model("idm"), [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> pairs = synthetic_pairs(idm, truth, n_pairs=6, n_steps=200)  # 20 s each
        >>> train, test = pairs.subset([0, 1, 2, 3]), pairs.subset([4, 5])
        >>> low, high = idm.prior_bounds().unbind(1)
        >>> g = torch.Generator().manual_seed(0)
        >>> theta = low + (high - low) * torch.rand(8, 6, generator=g).double()
        >>> theta[0] = torch.tensor(truth)  # the hybrid holds the true driver
        >>> hybrid = {"idm": ModelParticles(
        ...     idm.param_names, theta, torch.zeros(8).double(),
        ...     pair_ids=torch.arange(8) % 4, particle_index=torch.arange(8),
        ... )}
        >>> posterior = Posterior(
        ...     "demo", "per_pair", 2, ("idm",), {"idm": 1.0}, torch.arange(4),
        ...     hybrid, buffers={},
        ... )
        >>> config = TrainConfig(data={"path": "demo"}, models=["idm"])
        >>> priors = {"idm": idm.prior_bounds()}
        >>> run = TrainedRun(Path("demo"), config, posterior, train, priors)
        >>> run.dt, run.leader_length, [model.name for model in run.models]  # [s], [m]
        (0.1, 5.0, ['idm'])
        >>> run.particles(idm).shape  # the hybrid's IDM particles
        torch.Size([8, 6])
        >>> coarse = synthetic_pairs(idm, truth, n_pairs=1, n_steps=50, dt=0.2)
        >>> run.check(coarse)
        Traceback (most recent call last):
            ...
        torchcf.predict.trained.PredictError: the pairs' time step is 0.2 s, ...
        >>> run = TrainedRun.load("runs/demo")  # doctest: +SKIP
    """

    path: Path
    config: TrainConfig
    posterior: Posterior
    train: PairSet
    priors: dict[str, Tensor]
    estimator: torch.nn.Module | None = None

    @property
    def dt(self) -> float:
        """The run's time step [s] (its training pairs')."""
        return self.train.dt

    @property
    def leader_length(self) -> float:
        """The run's leader length [m] (its training pairs')."""
        return self.train.leader_length

    @property
    def models(self) -> list[CFModel]:
        """The run's models, in its order."""
        return [get_model(name) for name in self.posterior.models]

    @property
    def hybrid_models(self) -> list[CFModel]:
        """The models the hybrid holds particles of, in the run's order."""
        return [m for m in self.models if len(self.posterior.hybrid[m.name].theta)]

    def particles(self, model: CFModel) -> Tensor:
        """``(Q, K)`` float64 the hybrid's particles of ``model``."""
        return self.posterior.hybrid[model.name].theta.double()

    def kept(self, model: CFModel) -> Tensor:
        """``(Q, K)`` float64 the particles the run kept of ``model``: its
        buffer's best ``top_n`` per training pair (finite scores only) and its
        hybrid particles, each once."""
        buffer = self.posterior.buffers.get(model.name)
        sets = [self.particles(model)]
        if buffer is not None:
            n = self.posterior.top_n
            finite = torch.isfinite(buffer["score"][:, :n])  # (N, n)
            sets.append(buffer["theta"][:, :n][finite].double())
        return torch.unique(torch.cat(sets), dim=0)

    @classmethod
    def load(
        cls, path: str | os.PathLike[str], train: PairSet | None = None
    ) -> TrainedRun:
        """The trained run at ``path``; ``train``: its training pairs where the
        run's config cannot load them (a run trained on pairs passed in code).

        Raises:
            RunFileError: the run is not trained or a file is unreadable.
            PredictError: the training pairs cannot be loaded, or are not the
                run's.
        """
        run = RunDir(path)
        cfg, posterior, _ = run.load_run()
        if train is None:
            train = _training_pairs(cfg.data, run)
        ids = tuple(int(i) for i in posterior.train_pair_ids.tolist())
        if tuple(train.pair_ids) != ids:
            raise PredictError(
                f"{run.path}: the training pairs given are not the run's "
                f"({train.n_pairs} pairs, the run has {len(ids)})"
            )
        priors = {spec.name: spec.bounds(torch.float64) for spec in cfg.models}
        estimator = None
        if cfg.abc.method == "amortised" and run.amortised_checkpoint.is_file():
            estimator = trained_estimator(  # the run's own network
                method_of(cfg),
                {spec.model: spec.bounds(torch.float64) for spec in cfg.models},
                run.amortised_checkpoint,
            )
        return cls(run.path, cfg, posterior, train, priors, estimator)

    def check(self, pairs: PairSet) -> None:
        """Refuse ``pairs`` whose time step or leader length is not the run's.

        Raises:
            PredictError: naming the constant, both values and what to do.
        """
        for what, unit, theirs, ours in (
            ("time step", "s", pairs.dt, self.dt),
            ("leader length", "m", pairs.leader_length, self.leader_length),
        ):
            if not math.isclose(theirs, ours, rel_tol=SAME_CONSTANT):
                raise PredictError(
                    f"the pairs' {what} is {theirs:g} {unit}, the run's "
                    f"{ours:g} {unit}: resample or re-extract the pairs at the "
                    "run's (their meta.json's dt / leader_length)"
                )


def pairs_to_predict(
    run: TrainedRun, source: str | os.PathLike[str] | None, split: str | None
) -> PairSet:
    """The pairs to predict: ``source`` (a named data set or a six-CSV folder,
    its ``split``: None the whole set, "train" or "test"), read at the run's
    time step and leader length where the data do not state theirs (a folder
    without them in its ``meta.json``); None: the run's own test split.

    Raises:
        PredictError: the pairs cannot be loaded, or state another time step or
            leader length than the run's.
    """
    try:
        if source is None:
            _, test = load_split(run.config.data, download=False)
            pairs = test
        else:
            stated = _stated_constants(source)
            pairs = load_pairs(
                source,
                split=split,
                dt=None if "dt" in stated else run.dt,
                leader_length=None if "leader_length" in stated else run.leader_length,
            )
    except TorchcfError as error:
        raise PredictError(f"the pairs to predict: {error}") from None
    if pairs is None or pairs.n_pairs == 0:
        raise PredictError("no pairs to predict (the run has no test split: give DATA)")
    run.check(pairs)
    return pairs


def _stated_constants(source: str | os.PathLike[str]) -> set[str]:
    """The constants a folder's ``meta.json`` states (a named set: all)."""
    if isinstance(source, str) and source in DATASETS:
        return {"dt", "leader_length"}
    return set(read_meta(Path(source)))


def _training_pairs(data: DataConfig, run: RunDir) -> PairSet:
    try:
        train, _ = load_split(data, download=False, require_test=False)
    except TorchcfError as error:
        raise PredictError(
            f"{run.path}: the run's training pairs cannot be loaded ({error})"
        ) from None
    return train


__all__ = ["PredictError", "TrainedRun", "pairs_to_predict"]
