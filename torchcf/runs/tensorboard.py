"""TensorBoard logging of one training run: ABC progress, posteriors and the hybrid.

:class:`RunLogger` wraps one :class:`~torch.utils.tensorboard.SummaryWriter`. The tags:

========================================  ============  =============================
tag                                       kind          step
========================================  ============  =============================
``abc/particles/<model>``                 scalar        particles processed so far
``abc/threshold/<model>``                 scalar        particles processed so far
``abc/particles_per_s/<model>``           scalar        particles processed so far
``abc/invalid_rate/<model>``              scalar        particles processed so far
``posterior/<model>/<param>``             histogram     0
``hybrid/shares``, ``hybrid/pairwise``    image (HWC)   0
``hybrid/share/<model>``                  scalar        0
``hybrid/sensitivity/N=<n>/<model>``      scalar        0
``eval/<figure>``                         image (HWC)   0
``eval/<metric>/<model or hybrid>``       scalar        0
``<tag>/text_summary``                    text          0
``_hparams_/...``                         hparams       0
========================================  ============  =============================

A disabled logger is a no-op throughout and imports neither TensorBoard nor
matplotlib. On resume, ``purge_step`` makes TensorBoard discard the events a killed
run wrote at or past the checkpoint's step.

**Write failures.** TensorBoard writes its events from a background thread; a
failure there (a full disk) would print that thread's traceback and surface later
as a bare ``OSError`` in whatever call came next. The logger keeps the thread
quiet (:func:`_quiet_writer_threads`) and reports the failure from its own
methods as one :class:`~torchcf.system.files.RunFileError` naming the event directory.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
from torch import Tensor

from ..system.files import RunFileError, writing
from .summary import PlausibilitySummary, RunSummary

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

__all__ = ["RunLogger", "markdown_summary"]

HParamValue = float | int | str | bool


def _quiet_writer_threads() -> None:
    """Keep TensorBoard's writer thread from printing the traceback of an
    ``OSError`` (idempotent). The thread stores the error and TensorBoard raises it
    again in the next call of the writing thread, where :class:`RunLogger`
    reports it."""
    previous = threading.excepthook
    if getattr(previous, "torchcf_quiet", False):
        return

    def hook(args: threading.ExceptHookArgs) -> None:
        writer_thread = type(args.thread).__name__ == "_AsyncWriterThread"
        if writer_thread and isinstance(args.exc_value, OSError):
            return
        previous(args)

    hook.torchcf_quiet = True  # type: ignore[attr-defined]
    threading.excepthook = hook


def _reports_write_errors(method: Callable[..., Any]) -> Callable[..., Any]:
    """A RunLogger method whose ``OSError`` (the event file cannot be written)
    becomes a RunFileError naming the event directory."""

    @functools.wraps(method)
    def wrapped(self: RunLogger, *args: Any, **kwargs: Any) -> Any:
        with writing(self.logdir):
            return method(self, *args, **kwargs)

    return wrapped


class RunLogger:
    """TensorBoard writer for one training run.

    Args:
        logdir: the run's folder (created when enabled); all events, hparams included,
            go into this one folder.
        enabled: when False every method does nothing and no file is written.
        purge_step: passed to ``SummaryWriter``: events of an earlier, killed run with
            a step at or past it are discarded (use the checkpoint's step on resume).
        stream: a stage written whole each time it runs (``"evaluation"``): its
            event file ends in ``.<stream>``, and once it is closed the stream's
            earlier files are removed, so evaluating a run again replaces its
            evaluation in TensorBoard instead of adding a second copy of every
            scalar. None: the training's stream (a resumed run appends to it,
            ``purge_step`` dropping what a killed run wrote past its checkpoint).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.runs.tensorboard import RunLogger
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     with RunLogger(Path(folder) / "tb") as logger:
        ...         logger.progress("idm", particles=600, threshold=1.2,
        ...                         particles_per_s=4e4, invalid_rate=0.0)
        ...     print([p.name[:20] for p in (Path(folder) / "tb").iterdir()])
        ['events.out.tfevents.']
        >>> RunLogger("unused", enabled=False).enabled  # a no-op; writes nothing
        False
    """

    def __init__(
        self,
        logdir: str | Path,
        *,
        enabled: bool = True,
        purge_step: int | None = None,
        stream: str | None = None,
    ) -> None:
        self.logdir = Path(logdir)
        self._writer: SummaryWriter | None = None
        self._replaces: list[Path] = []
        if enabled:
            # Imported here so that a disabled logger does not pay for TensorBoard.
            from torch.utils.tensorboard import SummaryWriter

            _quiet_writer_threads()
            suffix = ""
            if stream is not None:
                suffix = f".{stream}"
                self._replaces = sorted(
                    self.logdir.glob(f"events.out.tfevents.*{suffix}")
                )
            with writing(self.logdir):
                self._writer = SummaryWriter(
                    str(self.logdir), purge_step=purge_step, filename_suffix=suffix
                )

    @property
    def enabled(self) -> bool:
        """False when disabled or closed."""
        return self._writer is not None

    @_reports_write_errors
    def progress(
        self,
        model: str,
        *,
        particles: int,
        threshold: float,
        particles_per_s: float,
        invalid_rate: float,
    ) -> None:
        """ABC progress of one model, at step ``particles``.

        Args:
            model: model name.
            particles: number of this model's particles processed so far (the step).
            threshold: current acceptance distance; inf until a particle is accepted.
            particles_per_s: throughput [1/s].
            invalid_rate: fraction of particles rejected as invalid, in [0, 1].

        Non-finite values (the threshold before the first acceptance, a rate over zero
        seconds) are skipped: an inf point would flatten the whole curve.
        """
        if self._writer is None:
            return
        values = {
            "particles": particles,
            "threshold": threshold,
            "particles_per_s": particles_per_s,
            "invalid_rate": invalid_rate,
        }
        step = int(particles)
        for name, value in values.items():
            value = float(value)
            if math.isfinite(value):
                self._writer.add_scalar(f"abc/{name}/{model}", value, global_step=step)

    @_reports_write_errors
    def posterior(self, model: str, param_names: Sequence[str], theta: Tensor) -> None:
        """One histogram per parameter of the accepted particles.

        Args:
            model: model name.
            param_names: the K parameter names, in the column order of ``theta``.
            theta: (P, K) accepted parameters; nothing is logged when P == 0.
        """
        if self._writer is None:
            return
        if theta.ndim != 2 or theta.shape[1] != len(param_names):
            raise ValueError(
                f"theta has shape {tuple(theta.shape)}, expected "
                f"(P, {len(param_names)}) for parameters {list(param_names)}"
            )
        if theta.shape[0] == 0:
            return
        values = theta.detach().cpu().numpy()  # (P, K)
        for k, name in enumerate(param_names):
            column = values[:, k]
            # np.histogram rejects NaN/inf (its range would not be finite).
            column = column[np.isfinite(column)]
            if column.size:
                self._writer.add_histogram(f"posterior/{model}/{name}", column)

    @_reports_write_errors
    def hybrid(
        self,
        shares: Mapping[str, float],
        images: Mapping[str, np.ndarray],
        sensitivity: Mapping[int, Mapping[str, float]] | None = None,
    ) -> None:
        """The hybrid model: share figures and share scalars.

        Args:
            shares: model name -> share in [0, 1].
            images: the figures ``shares`` and ``pairwise``, rendered
                (:func:`torchcf.evaluation.plots.hybrid_images`).
            sensitivity: optional top-N size ``n`` (accepted particles per pair)
                -> shares; logged under the tag ``hybrid/sensitivity/N=<n>``.
        """
        if self._writer is None:
            return
        self._writer.add_image("hybrid/shares", images["shares"], dataformats="HWC")
        self._writer.add_image("hybrid/pairwise", images["pairwise"], dataformats="HWC")
        for model, share in shares.items():
            self._writer.add_scalar(f"hybrid/share/{model}", float(share))
        for n, by_model in (sensitivity or {}).items():
            for model, share in by_model.items():
                self._writer.add_scalar(
                    f"hybrid/sensitivity/N={n}/{model}", float(share)
                )

    @_reports_write_errors
    def evaluation(
        self,
        images: Mapping[str, np.ndarray],
        metrics: Mapping[str, Mapping[str, float]],
    ) -> None:
        """Test-split evaluation: figures as images ``eval/<name>`` and the finite
        metrics as scalars ``eval/<metric>/<entry>`` (entry: a model or "hybrid").

        Args:
            images: name -> ``(H, W, 3)`` uint8 rendered figure
                (:func:`torchcf.evaluation.plots.figure_to_array`).
            metrics: entry -> {metric name: value}.
        """
        if self._writer is None:
            return
        for name, image in images.items():
            self._writer.add_image(f"eval/{name}", image, dataformats="HWC")
        for entry, values in metrics.items():
            for key, value in values.items():
                if isinstance(value, int | float) and math.isfinite(value):
                    self._writer.add_scalar(f"eval/{key}/{entry}", float(value))

    @_reports_write_errors
    def plausibility(self, per_model: Mapping[str, PlausibilitySummary]) -> None:
        """The hybrid's plausibility battery: per model, the shares of particles
        that collided, are string-unstable and have no equilibrium, as scalars
        ``plausibility/<share>/<model>``."""
        if self._writer is None:
            return
        for model, row in per_model.items():
            for key in ("collided", "string_unstable", "no_equilibrium", "not_started"):
                value = float(getattr(row, key))
                self._writer.add_scalar(f"plausibility/{key}/{model}", value)

    @_reports_write_errors
    def text(self, tag: str, markdown: str) -> None:
        """Markdown text (TensorBoard stores it under ``<tag>/text_summary``)."""
        if self._writer is None:
            return
        self._writer.add_text(tag, markdown)

    @_reports_write_errors
    def hparams(
        self,
        hparams: Mapping[str, HParamValue | Any],
        metrics: Mapping[str, float],
    ) -> None:
        """Hyper-parameters and final metrics for TensorBoard's HPARAMS tab.

        Unlike ``SummaryWriter.add_hparams``, which opens a second writer (in a
        timestamped sub-folder unless given a ``run_name``), the summaries go through
        this run's own writer: one event file, one run, and ``purge_step`` applies.
        The metrics are also written as scalars, which the HPARAMS tab reads.

        Args:
            hparams: name -> value. Values other than int/float/str/bool are written
                with ``str()`` (NumPy scalars as their Python value), None as "none".
                TensorBoard's encoder stores bools as 1.0/0.0.
            metrics: metric tag -> value; use tags not logged elsewhere.
        """
        if self._writer is None:
            return
        from torch.utils.tensorboard.summary import hparams as hparams_summary

        hparam_dict = {str(k): _hparam_value(v) for k, v in hparams.items()}
        metric_dict = {str(k): float(v) for k, v in metrics.items()}
        file_writer = self._writer.file_writer
        assert file_writer is not None  # set in SummaryWriter.__init__
        for summary in hparams_summary(hparam_dict, metric_dict):
            file_writer.add_summary(summary)
        for tag, value in metric_dict.items():
            self._writer.add_scalar(tag, value)

    @_reports_write_errors
    def flush(self) -> None:
        if self._writer is not None:
            self._writer.flush()

    @_reports_write_errors
    def close(self) -> None:
        """Flush and close; later calls do nothing. Idempotent. A stream's
        earlier files go once this one is complete (module docstring)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
        replaced, self._replaces = self._replaces, []
        for path in replaced:
            path.unlink(missing_ok=True)

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc is None:
            self.close()
            return
        try:  # the error under way is the one to report, not a second one here
            self.close()
        except RunFileError:
            pass


def _hparam_value(value: Any) -> HParamValue:
    if value is None:
        return "none"
    if isinstance(value, np.generic):
        value = value.item()
    elif isinstance(value, Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool | int | float | str):
        return value
    return str(value)


def _fmt(value: Any) -> str:
    if value is None:
        return "–"
    if isinstance(value, Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:.4g}"
    return str(value).replace("|", "\\|")


def _fmt_share(value: Any) -> str:
    if value is None:
        return "–"
    return f"{100.0 * float(value):.1f} %"


_PER_MODEL_COLUMNS = (
    ("best_score", "best score"),
    ("threshold", "threshold"),
    ("invalid", "invalid"),
    ("particles", "particles"),
    ("seconds", "seconds"),
    ("particles_per_s", "particles/s"),
)


def markdown_summary(summary: RunSummary) -> str:
    """Render a run summary as Markdown for TensorBoard's TEXT tab.

    Args:
        summary: the run's summary (its dataset, training pairs, shares, each
            model's record and the shares' sensitivity to N).

    Returns:
        Markdown: a header line, one table with a row per model and, with
        ``sensitivity``, a second table with a column per top-N size ``n``.

    Examples:
        >>> from types import SimpleNamespace
        >>> from torchcf.runs.tensorboard import markdown_summary
        >>> summary = SimpleNamespace(dataset="demo", n_train=3, shares={"idm": 0.75},
        ...                           per_model={}, sensitivity={})  # what it reads
        >>> print(markdown_summary(summary).splitlines()[0])
        **dataset:** demo · **training pairs:** 3
    """
    shares, per_model = summary.shares, summary.per_model
    sensitivity = summary.sensitivity

    lines = [
        f"**dataset:** {_fmt(summary.dataset)} · "
        f"**training pairs:** {_fmt(summary.n_train)}",
        "",
    ]
    # Models in first-seen order: the shares first, then any model only in per_model.
    models = list(dict.fromkeys([*shares, *per_model]))
    if models:
        header = ["model", "share", *(label for _, label in _PER_MODEL_COLUMNS)]
        lines += [_row(header), _row(["---"] + ["---:"] * (len(header) - 1))]
        for model in models:
            stats = per_model.get(model)
            cells = [
                _fmt(None if stats is None else getattr(stats, key))
                for key, _ in _PER_MODEL_COLUMNS
            ]
            lines.append(_row([_fmt(model), _fmt_share(shares.get(model)), *cells]))
    else:
        lines.append("_no model results_")

    if sensitivity:
        ns = sorted(sensitivity)
        sens_models = list(
            dict.fromkeys([*models, *(m for n in ns for m in sensitivity[n])])
        )
        lines += [
            "",
            "**share sensitivity to N (accepted particles):**",
            "",
            _row(["model", *(f"N={n}" for n in ns)]),
            _row(["---"] + ["---:"] * len(ns)),
        ]
        for model in sens_models:
            cells = [_fmt_share(sensitivity[n].get(model)) for n in ns]
            lines.append(_row([_fmt(model), *cells]))
    return "\n".join(lines) + "\n"


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"
