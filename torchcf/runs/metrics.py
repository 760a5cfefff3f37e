"""The records of a run's ``metrics.json``: the evaluation of its test split, or a
cross-validation's mean over its folds.

:func:`torchcf.evaluation.evaluate.evaluate_run` returns an :class:`Evaluation`,
the content of ``RUN_DIR/metrics.json``; :meth:`Evaluation.to_json` gives the
file's object (key order included) and :meth:`Evaluation.from_json` reads it
back (``from_json(e.to_json()) == e``, the strings ``"inf"`` and ``"nan"`` the
file holds for non-finite numbers read as floats again);
:class:`~torchcf.runs.directory.RunDir` writes and reads it
(``run.read_metrics()``). Its parts:

- :class:`SetEvaluation`: one learned set (a model or ``"hybrid"``), the
  set's :class:`SetMetrics` (SPEC section 6, computed by
  :mod:`torchcf.evaluation.metrics`) and its :class:`SetUncertainty`, one flat
  object in the file;
- :class:`SetUncertainty`: the set's bootstrap intervals (:class:`Interval`,
  of the :data:`METRICS`) and predictive coverage
  (:mod:`torchcf.evaluation.uncertainty` lists the keys), with its
  :class:`CoverageCurve`;
- :class:`Difference`: the hybrid minus a model in one metric, paired bootstrap;
- :class:`ShareInterval`: the hybrid's share of a model with its interval
  over training pairs;
- :class:`BootstrapSettings`: how the intervals were made.

A cross-validation's ``OUT/metrics.json`` is a :class:`CrossvalResult`
(:func:`torchcf.study.crossval.crossval`): a :class:`FoldMeans` per learned set.

Units: the metrics are the run's score (dimensionless) or RMSEs [m, m/s,
m/s^2]; coverage, shares and levels are fractions in [0, 1]; ``seconds`` is
the evaluation's wall time (s, rounded to the millisecond).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, NamedTuple

from ..system.files import JSON, from_json_safe
from ..system.records import Record, to_json_value

#: The metrics with a bootstrap interval, in report order (keys of metrics.json).
METRICS = ("min", "beta_ws", "ws")


class Interval(NamedTuple):
    """A point estimate and its percentile bootstrap interval (NaN: none).

    Examples:
        >>> from torchcf.runs.metrics import Interval
        >>> Interval(0.8, 0.5, 1.1).excludes_zero()  # value, low, high
        True
        >>> Interval(0.1, -0.2, 0.4).excludes_zero()
        False
    """

    value: float
    low: float
    high: float

    def excludes_zero(self) -> bool:
        """Whether the interval lies strictly on one side of 0."""
        return bool(self.low > 0 or self.high < 0)


@dataclass(frozen=True)
class SetMetrics(Record):
    """Every SPEC section 6 metric of one learned set on one test split
    (:func:`torchcf.evaluation.metrics.evaluate_costs`); its JSON object is the
    set's first keys in ``metrics.json``, in this order.

    Attributes:
        e_p: mean position RMSE over the valid cells [m] (NaN: none valid).
        e_v: mean speed RMSE [m/s]; e_a: mean acceleration RMSE [m/s^2].
        valid_cells: (particle, test pair) cells whose rollout is valid.
        invalid_cells: the others (excluded from the means, forbidden in the
            transport metrics).
        min: the minimum distance.
        beta_ws: the beta-WS (``inf``: infeasible).
        ws: the exact WS (``inf``: infeasible).
        sinkhorn: the entropic plan's transport cost.
        sinkhorn_gap: ``sinkhorn - ws`` (NaN when infeasible).
        sinkhorn_iterations: iterations of the Sinkhorn solve (0: WS infeasible).
        sinkhorn_converged: whether its pair marginals met the tolerance.
        sinkhorn_marginal_error: the L2 error of its pair marginals.
        n_particles: particles P; n_test: test pairs N.
        ws_valid: WS over the particles valid on some test pair.
        beta_ws_valid: beta-WS over them.
        particles_never_valid: particles invalid on every test pair (dropped
            from ``ws_valid`` and ``beta_ws_valid``).

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.runs.metrics import SetMetrics
        >>> [f.name for f in fields(SetMetrics)][:8]
        ['e_p', 'e_v', 'e_a', 'valid_cells', 'invalid_cells', 'min', 'beta_ws', 'ws']
    """

    e_p: float
    e_v: float
    e_a: float
    valid_cells: int
    invalid_cells: int
    min: float
    beta_ws: float
    ws: float
    sinkhorn: float
    sinkhorn_gap: float
    sinkhorn_iterations: int
    sinkhorn_converged: bool
    sinkhorn_marginal_error: float
    n_particles: int
    n_test: int
    ws_valid: float
    beta_ws_valid: float
    particles_never_valid: int


#: The keys of a set's coverage that are no headline band.
_COVERAGE_COUNTS = ("coverage_points", "coverage_pairs_without_draws")
_COVERAGE_CURVE = "coverage_curve"


@dataclass(frozen=True)
class CoverageCurve(Record):
    """The calibration curve of a set's predictive bands (``coverage_curve``):
    at each nominal level, the fraction of observed points inside the central
    band, per variable.

    Examples:
        >>> from torchcf.runs.metrics import CoverageCurve
        >>> curve = CoverageCurve((0.5, 0.9), (0.48, 0.87), (0.52, 0.91))
        >>> curve.to_json()["speed"], CoverageCurve.from_json(curve.to_json()) == curve
        ([0.52, 0.91], True)
    """

    levels: tuple[float, ...]
    spacing: tuple[float, ...]
    speed: tuple[float, ...]


@dataclass(frozen=True)
class SetUncertainty:
    """One set's intervals and coverage: the keys
    :mod:`torchcf.evaluation.uncertainty` adds to its metrics, flat in the file.

    Attributes:
        intervals: metric (``min``, ``beta_ws``, ``ws``) -> its value and
            percentile bootstrap interval over test pairs (the file holds
            ``<metric>_low`` and ``<metric>_high``; the value is the metric's).
        coverage: ``coverage_<variable>_<pct>`` -> the fraction of observed
            points inside that band and its interval (the file holds the key,
            ``<key>_low`` and ``<key>_high``); empty without coverage.
        coverage_points: the observed points scored (None: no coverage).
        coverage_pairs_without_draws: test pairs no particle drew a band on.
        coverage_curve: the calibration curve (None: no coverage).

    Examples:
        >>> from torchcf.runs.metrics import Interval, SetUncertainty
        >>> SetUncertainty({"min": Interval(1.2, 1.0, 1.5)}).to_json()
        {'min_low': 1.0, 'min_high': 1.5}
    """

    intervals: dict[str, Interval]
    coverage: dict[str, Interval] = field(default_factory=dict)
    coverage_points: int | None = None
    coverage_pairs_without_draws: int | None = None
    coverage_curve: CoverageCurve | None = None

    def to_json(self) -> JSON:
        """The set's keys, in the file's order."""
        out: JSON = {}
        for key, interval in self.intervals.items():
            out[f"{key}_low"], out[f"{key}_high"] = interval.low, interval.high
        if self.coverage_curve is None:
            return out
        for key, band in self.coverage.items():
            out[key] = band.value
            out[f"{key}_low"], out[f"{key}_high"] = band.low, band.high
        out["coverage_points"] = self.coverage_points
        out["coverage_pairs_without_draws"] = self.coverage_pairs_without_draws
        out[_COVERAGE_CURVE] = self.coverage_curve.to_json()
        return out

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> SetUncertainty:
        """The uncertainty keys of a set's object (its metrics beside them give
        the intervals' values).

        Raises:
            KeyError: a metric of an interval, or a band's bound, is missing.
        """
        intervals = {
            key: Interval(raw[key], raw[f"{key}_low"], raw[f"{key}_high"])
            for key in METRICS
            if f"{key}_low" in raw
        }
        curve = raw.get(_COVERAGE_CURVE)
        if curve is None:
            return cls(intervals)
        bands = [
            key
            for key in raw
            if key.startswith("coverage_")
            and key not in (*_COVERAGE_COUNTS, _COVERAGE_CURVE)
            and not key.endswith(("_low", "_high"))
        ]
        return cls(
            intervals,
            {
                key: Interval(raw[key], raw[f"{key}_low"], raw[f"{key}_high"])
                for key in bands
            },
            raw["coverage_points"],
            raw["coverage_pairs_without_draws"],
            CoverageCurve.from_json(curve),
        )


@dataclass(frozen=True)
class SetEvaluation:
    """One learned set's entry of ``metrics.json``: its metrics, then their
    uncertainty, one flat object in the file.

    Attributes:
        metrics: the set's SPEC section 6 metrics.
        uncertainty: its intervals and coverage (None: not computed).

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.runs.metrics import SetEvaluation, SetMetrics
        >>> metrics = SetMetrics(**{f.name: 0 for f in fields(SetMetrics)})  # all 0
        >>> entry = SetEvaluation(metrics)
        >>> len(entry.to_json()), SetEvaluation.from_json(entry.to_json()) == entry
        (18, True)
    """

    metrics: SetMetrics
    uncertainty: SetUncertainty | None = None

    def to_json(self) -> JSON:
        """The set's object: the metrics' keys, then the uncertainty's."""
        out = self.metrics.to_json()
        if self.uncertainty is not None:
            out.update(self.uncertainty.to_json())
        return out

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> SetEvaluation:
        """The record of a set's object.

        Raises:
            KeyError: a metric is missing.
            ValueError: a key neither the metrics nor the uncertainty write.
        """
        names = [f.name for f in fields(SetMetrics)]
        metrics = SetMetrics.from_json({key: raw[key] for key in names})
        rest = [key for key in raw if key not in names]
        if not rest:
            return cls(metrics)
        uncertainty = SetUncertainty.from_json(raw)
        written = uncertainty.to_json()
        unknown = [key for key in rest if key not in written]
        if unknown:
            raise ValueError(f"SetEvaluation: unknown key(s) {unknown}")
        return cls(metrics, uncertainty)


@dataclass(frozen=True)
class Difference(Record):
    """The hybrid minus a model in one metric, on the same resampled test pairs
    (``hybrid_minus[model][metric]``; negative: the hybrid is closer).

    Attributes:
        value: the difference on the test pairs.
        low, high: its percentile bootstrap interval.
        excludes_zero: the interval lies strictly on one side of 0.

    Examples:
        >>> from torchcf.runs.metrics import Difference, Interval
        >>> Difference.of(Interval(-0.3, -0.5, -0.1))
        Difference(value=-0.3, low=-0.5, high=-0.1, excludes_zero=True)
    """

    value: float
    low: float
    high: float
    excludes_zero: bool

    @classmethod
    def of(cls, interval: Interval) -> Difference:
        """The record of a paired bootstrap interval."""
        return cls(
            interval.value, interval.low, interval.high, interval.excludes_zero()
        )


@dataclass(frozen=True)
class ShareInterval(Record):
    """The hybrid's share of a model with its percentile bootstrap interval over
    training pairs (``shares[model]``).

    Examples:
        >>> from torchcf.runs.metrics import ShareInterval
        >>> ShareInterval(0.6, 0.45, 0.75).to_json()
        {'share': 0.6, 'low': 0.45, 'high': 0.75}
    """

    share: float
    low: float
    high: float


@dataclass(frozen=True)
class BootstrapSettings(Record):
    """How the intervals were made (``bootstrap``).

    Attributes:
        unit: what a resample draws (``"test pair"``).
        resamples: resamples of every metric (``eval.bootstrap``).
        resamples_transport: those of WS and beta-WS
            (``eval.bootstrap_transport``, at most ``resamples``).
        transport_metrics: the metrics with the fewer resamples.
        level: the intervals' nominal coverage (``eval.level``).
        seed: the resamples' seed.
        method: ``"percentile"``.

    Examples:
        >>> from torchcf.runs.metrics import BootstrapSettings
        >>> settings = BootstrapSettings("test pair", 1000, 100, ("ws", "beta_ws"),
        ...                              0.95, 0, "percentile")
        >>> settings.to_json()["transport_metrics"]
        ['ws', 'beta_ws']
        >>> BootstrapSettings.from_json(settings.to_json()) == settings
        True
    """

    unit: str
    resamples: int
    resamples_transport: int
    transport_metrics: tuple[str, ...]
    level: float
    seed: int
    method: str


@dataclass(frozen=True)
class Evaluation:
    """A run's test-split evaluation: the content of ``metrics.json``.

    Attributes (in the file's order):
        dataset: the run's data set label (``summary.json``'s).
        n_test: test pairs.
        test_pair_ids: ``(n_test,)`` their ids.
        beta: the beta of beta-WS (``eval.beta``).
        sinkhorn_reg: the Sinkhorn regularisation (``eval.sinkhorn_reg``).
        sinkhorn_max_iter: its iteration cap (``eval.sinkhorn_max_iter``).
        bootstrap: how the intervals were made.
        coverage_levels: the headline levels of the coverage.
        sets: learned set -> its entry, the models in the run's order, then
            ``"hybrid"`` (each a top-level key of the file).
        hybrid_minus: model -> metric -> the hybrid minus the model.
        shares: model -> the hybrid's share with its interval.
        hybrid_min_by_pair: ``(n_test,)`` the hybrid's best score per test pair
            (None where no particle is valid).
        seconds: the evaluation's wall time (s, ms).

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.runs.metrics import Evaluation
        >>> [f.name for f in fields(Evaluation)][:6]
        ['dataset', 'n_test', 'test_pair_ids', 'beta', 'sinkhorn_reg',
         'sinkhorn_max_iter']
    """

    dataset: str
    n_test: int
    test_pair_ids: tuple[int, ...]
    beta: float
    sinkhorn_reg: float
    sinkhorn_max_iter: int
    bootstrap: BootstrapSettings
    coverage_levels: tuple[float, ...]
    sets: dict[str, SetEvaluation]
    hybrid_minus: dict[str, dict[str, Difference]]
    shares: dict[str, ShareInterval]
    hybrid_min_by_pair: tuple[float | None, ...]
    seconds: float

    @property
    def hybrid(self) -> SetEvaluation:
        """The hybrid's entry."""
        return self.sets["hybrid"]

    def to_json(self) -> JSON:
        """The content of ``metrics.json``, key order included (a fresh copy;
        non-finite numbers as floats: :func:`~torchcf.system.files.write_json`
        writes them as strings)."""
        out: JSON = {}
        for f in fields(self):
            if f.name == "sets":
                out.update({name: s.to_json() for name, s in self.sets.items()})
            else:
                out[f.name] = to_json_value(getattr(self, f.name))
        return out

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> Evaluation:
        """The evaluation of ``metrics.json``'s content (as read: ``"inf"`` and
        ``"nan"`` strings are numbers again).

        Raises:
            ValueError: a key is missing or malformed.
        """
        raw = from_json_safe(dict(raw))
        names = {f.name for f in fields(cls)} - {"sets"}
        try:
            return cls(
                dataset=raw["dataset"],
                n_test=raw["n_test"],
                test_pair_ids=tuple(raw["test_pair_ids"]),
                beta=raw["beta"],
                sinkhorn_reg=raw["sinkhorn_reg"],
                sinkhorn_max_iter=raw["sinkhorn_max_iter"],
                bootstrap=BootstrapSettings.from_json(raw["bootstrap"]),
                coverage_levels=tuple(raw["coverage_levels"]),
                sets={
                    key: SetEvaluation.from_json(value)
                    for key, value in raw.items()
                    if key not in names
                },
                hybrid_minus={
                    model: {k: Difference.from_json(d) for k, d in row.items()}
                    for model, row in raw["hybrid_minus"].items()
                },
                shares={
                    m: ShareInterval.from_json(s) for m, s in raw["shares"].items()
                },
                hybrid_min_by_pair=tuple(raw["hybrid_min_by_pair"]),
                seconds=raw["seconds"],
            )
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise ValueError(
                f"not an evaluation ({type(error).__name__}: {error})"
            ) from None


@dataclass(frozen=True)
class FoldMeans(Record):
    """One learned set's metrics averaged over the folds (an entry of the
    cross-validation's ``metrics.json``): per metric of
    :data:`torchcf.study.crossval.METRIC_KEYS` its mean (non-finite if any
    fold's is, or the entry is missing from a fold) and
    ``<metric>_folds_finite``, the folds whose value was finite.

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.runs.metrics import FoldMeans
        >>> [f.name for f in fields(FoldMeans)][:4]
        ['e_p', 'e_p_folds_finite', 'e_v', 'e_v_folds_finite']
    """

    e_p: float
    e_p_folds_finite: int
    e_v: float
    e_v_folds_finite: int
    e_a: float
    e_a_folds_finite: int
    min: float
    min_folds_finite: int
    beta_ws: float
    beta_ws_folds_finite: int
    ws: float
    ws_folds_finite: int
    sinkhorn: float
    sinkhorn_folds_finite: int


@dataclass(frozen=True)
class CrossvalResult:
    """A cross-validation's result: the content of ``OUT/metrics.json``.

    Attributes:
        folds: the folds averaged.
        entries: learned set (the models, then ``"hybrid"``) -> its means
            (each a top-level key of the file, after ``folds``).

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.runs.metrics import CrossvalResult, FoldMeans
        >>> means = FoldMeans(**{f.name: 0 for f in fields(FoldMeans)})  # all 0
        >>> result = CrossvalResult(folds=3, entries={"hybrid": means})
        >>> list(result.to_json()), CrossvalResult.from_json(result.to_json()) == result
        (['folds', 'hybrid'], True)
    """

    folds: int
    entries: dict[str, FoldMeans]

    def to_json(self) -> JSON:
        """The content of ``OUT/metrics.json``, key order included."""
        return {
            "folds": self.folds,
            **{name: means.to_json() for name, means in self.entries.items()},
        }

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> CrossvalResult:
        """The result of ``OUT/metrics.json``'s content (as read: the strings
        ``"inf"`` and ``"nan"`` the file holds are numbers again).

        Raises:
            KeyError, ValueError: a key is missing or unknown.
        """
        raw = from_json_safe(dict(raw))
        return cls(
            folds=raw["folds"],
            entries={
                name: FoldMeans.from_json(value)
                for name, value in raw.items()
                if name != "folds"
            },
        )


__all__ = [
    "METRICS",
    "BootstrapSettings",
    "CoverageCurve",
    "CrossvalResult",
    "Difference",
    "Evaluation",
    "FoldMeans",
    "Interval",
    "SetEvaluation",
    "SetMetrics",
    "SetUncertainty",
    "ShareInterval",
]
