"""A training run's ``summary.json`` record
(:class:`~torchcf.runs.summary.RunSummary`) of its calibration.

The calibration (:class:`~torchcf.calibration.Calibration`) holds the hybrid
and its records; the summary adds what the run knows besides: the data set's
label, the config's hash and settings, the test split's size and ids, the
wall time of this process and the processes of the run.

Units: seconds (s) for times, rounded to the millisecond where stored; scores
and thresholds are the run's score (dimensionless); shares in [0, 1].
"""

from __future__ import annotations

from ..calibration import Calibration
from ..config import TrainConfig, config_hash
from ..config.schema import DataConfig
from ..data import PairSet
from ..runs.summary import Pairwise, RunSummary, Versions


def dataset_label(data: DataConfig) -> str:
    """The data set's name, folder, or raw source ("SOURCE (FORMAT)")."""
    if data.raw is not None:
        return f"{data.raw.source} ({data.raw.format})"
    return data.name if data.name is not None else str(data.path)


def run_summary(
    cfg: TrainConfig,
    calibration: Calibration,
    train: PairSet,
    test: PairSet | None,
    wall: float,
    processes: int = 1,
) -> RunSummary:
    """The run's summary.

    Args:
        cfg: the run's config.
        calibration: the run's calibration.
        train: its training pairs.
        test: the test pairs (None: the data have no test split, ``n_test``
            is 0).
        wall: this process's wall time so far (s).
        processes: the run's processes.
    """
    posterior = calibration.posterior
    names = list(posterior.models)
    table = calibration.pairwise
    train_ids = tuple(int(i) for i in train.pair_ids)
    per_model = calibration.per_model
    summary = RunSummary(
        dataset=dataset_label(cfg.data),
        layout=cfg.abc.layout,
        selection=cfg.abc.selection,
        top_n=cfg.abc.top_n,
        n_particles=cfg.abc.n_particles,
        n_train=train.n_pairs,
        n_test=0 if test is None else test.n_pairs,
        train_pair_ids=train_ids,
        test_pair_ids=() if test is None else tuple(int(i) for i in test.pair_ids),
        models=tuple(names),
        shares=dict(posterior.shares),
        hybrid_size=sum(len(p) for p in posterior.hybrid.values()),
        pairwise=Pairwise(
            models=tuple(names),
            table=tuple(tuple(round(float(v), 6) for v in row) for row in table),
        ),
        sensitivity=dict(calibration.sensitivity),
        per_model=per_model,
        seconds_total=round(calibration.stream_seconds, 3),
        seconds_wall_this_process=round(wall, 3),
        processes=processes,
        config_hash=config_hash(cfg),
        versions=Versions.current(),
        method=cfg.abc.method,
        smc=calibration.smc,
        dt=train.dt,
        leader_length=train.leader_length,
    )
    if calibration.amortised is not None:
        summary = summary.with_amortised(calibration.amortised)
    return summary


__all__ = ["dataset_label", "run_summary"]
