"""One calibration: every model's particles through its per-pair buffer, then
the hybrid read from the buffers (:func:`calibrate`).

For each model, in order, its particles come from its sampler
(:data:`~torchcf.calibration.Method`): rejection's prior stream
(:func:`torchcf.abc.run_rejection`), SMC's rounds (:func:`torchcf.abc.run_smc`)
or an estimator's samples (:func:`torchcf.amortised.run_amortised`, refined per
pair once every model's samples are in: :mod:`torchcf.calibration.refinement`).
Each is simulated (:class:`~torchcf.abc.Rollout`), screened (an optional
plausibility filter) and pushed into the model's buffer of the best per pair.

What a caller keeps and shows while it runs is a :class:`Tracker`'s: the state
(resumable: a model finished is not run again, one stopped part-way continues
where it stopped), a progress display per model, and a checkpoint when one is
due. The default tracker keeps the state in memory and shows nothing; a
training run's (:mod:`torchcf.train.run`) draws progress bars, logs to
TensorBoard and saves checkpoints. The buffers, hence the result, do not depend
on the tracker, the chunk size, the processes or where a run was cut and
resumed.

Units: SI throughout (m, s, m/s). Shapes: N training pairs, K parameters.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

from torch import Tensor

from ..abc.distributed import SINGLE, Group
from ..abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from ..abc.rounds import RoundHooks
from ..abc.screen import PlausibilityScreen
from ..abc.smc import refine_population, run_smc
from ..amortised import run_amortised
from ..data import PairSet
from ..models import CFModel
from ..system.signals import StopRequest
from .budget import check_budget
from .estimator_samples import AmortisedSamples, amortised_samples
from .methods import SMC, Amortised, Method, Rejection, SelectionRule, weighted
from .priors import drawn_and_held, held_values, prior_boxes
from .refinement import refinement_result, scores_before
from .results import Calibration, read_calibration
from .state import CalibrationState, build_buffers


class Tracker:
    """Where a calibration keeps its state and what it shows while it runs.

    This default keeps the state in memory and shows nothing; a subclass
    overrides :meth:`model` (a progress display per model), :meth:`round`
    (after every round), :meth:`due` and :meth:`save` (checkpoints).

    Attributes:
        state: the calibration's state: pass a loaded one to resume.
        estimator_checkpoint: where an amortised calibration keeps its
            estimator's training checkpoint (None: nowhere).
        resume: continue that checkpoint where it is there.
        stop: a stop request checked between an estimator's batches.

    Examples:
        >>> Tracker().state.buffers
        {}
    """

    def __init__(
        self,
        state: CalibrationState | None = None,
        *,
        estimator_checkpoint: Path | None = None,
        resume: bool = False,
        stop: StopRequest | None = None,
    ) -> None:
        self.state = state if state is not None else CalibrationState()
        self.estimator_checkpoint = estimator_checkpoint
        self.resume = resume
        self.stop = stop

    @contextmanager
    def model(self, name: str, total: int, done: int) -> Iterator[None]:
        """Around one model's stream of ``total`` particles, ``done`` of them
        already offered (a resumed state)."""
        yield

    def round(self, name: str, progress: ModelProgress, rollout: Rollout) -> None:
        """After every round of model ``name``'s stream."""

    def due(self) -> bool:
        """A checkpoint is due (asked between rounds)."""
        return False

    def save(self) -> None:
        """Keep the state (called when :meth:`due`, and after each model)."""


def calibrate(
    pairs: PairSet | Rollout,
    models: Sequence[CFModel] | Mapping[CFModel, Tensor],
    method: Method | None = None,
    *,
    selection: SelectionRule | None = None,
    seed: int = 0,
    screen: PlausibilityScreen | None = None,
    group: Group = SINGLE,
    tracker: Tracker | None = None,
) -> Calibration:
    """Calibrate ``models`` on ``pairs`` and select the hybrid.

    Args:
        pairs: the training pairs, or a :class:`~torchcf.abc.Rollout` of them
            (how particles are simulated: layout, precision, device, score
            weights, chunks, compilation, early rejection); a plain
            :class:`~torchcf.data.PairSet` is simulated with the rollout's
            defaults (paired, float32, CPU).
        models: the candidate models, each over its default prior box
            (:meth:`CFModel.prior_bounds <torchcf.models.CFModel.prior_bounds>`),
            or a mapping of each model to its box ``(K, 2)`` [SI units]; a
            box's last rows of zero width hold those parameters at that value
            (rejection and SMC; a shared effect's one value).
        method: the sampler and its budget; default :class:`Rejection`.
        selection: how the hybrid is read (N, the other N reported, the mode);
            default :class:`SelectionRule`.
        seed: the particle streams', the estimator's and the samples' seed.
        screen: a plausibility filter on the candidates (None: none).
        group: the processes sharing the calibration
            (:func:`torchcf.abc.distributed.init_from_env`); every process calls
            ``calibrate`` with the same arguments and holds the same result.
        tracker: where the state is kept and progress shown (default: in
            memory, silent).

    Returns:
        The hybrid and its records (:class:`Calibration`).

    Raises:
        CalibrationError: the budget cannot fill every pair's buffer, a reused
            estimator does not fit, or a resumed state does not fit.

    Examples:
        >>> import torch
        >>> from torchcf import PairSet, get_model
        >>> from torchcf.calibration import Rejection, calibrate
        >>> t = torch.arange(100, dtype=torch.float64)[:, None] * 0.1  # (T, 1) [s]
        >>> v_lead = 15.0 + torch.sin(t)  # [m/s]
        >>> x_lead = 40.0 + 15.0 * t - torch.cos(t)  # [m]
        >>> a_lead = torch.cos(t)  # [m/s^2]
        >>> pairs = PairSet.from_arrays(
        ...     [x_lead, v_lead, a_lead, x_lead - 30.0, v_lead, a_lead], dt=0.1
        ... )
        >>> result = calibrate(
        ...     pairs, [get_model("idm"), get_model("ovm")], Rejection(2_000)
        ... )
        >>> sorted(result.shares), round(sum(result.shares.values()), 6)
        (['idm', 'ovm'], 1.0)
    """
    began = time.perf_counter()
    method = method if method is not None else Rejection()
    selection = selection if selection is not None else SelectionRule()
    rollout = pairs if isinstance(pairs, Rollout) else Rollout(pairs)
    priors = prior_boxes(models)
    tracker = tracker if tracker is not None else Tracker()
    check_budget(method, selection, rollout.pairs, rollout.paired)
    state = tracker.state
    held = {model.name: len(held_values(box)) for model, box in priors.items()}
    if isinstance(method, Amortised) and any(held.values()):
        raise ValueError("calibrate: the amortised sampler holds no parameter")
    build_buffers(
        list(priors), rollout.pairs.n_pairs, selection.buffer_size,
        weighted(method), state, held,
    )  # fmt: skip
    amortised = None
    if isinstance(method, Amortised):
        # the state kept first: a calibration stopped while its estimator
        # trains is one to resume
        tracker.save()
        amortised = group.on_main(
            amortised_samples,
            method,
            priors,
            rollout.pairs,
            seed,
            tracker.estimator_checkpoint,
            tracker.resume,
            tracker.stop,
        )
    run = _Streams(priors, method, seed, rollout, screen, group, tracker)
    for model in priors:
        run.stream(model, amortised)
    if amortised is not None and method.refine is not None:
        names = [model.name for model in priors]
        if state.refinement_before is None:  # kept, so a resumed run says the same
            state.refinement_before = scores_before(names, state.buffers, selection)
            tracker.save()
        for model in priors:
            run.stream(model, amortised, refining=True)
    result = read_calibration(
        priors,
        method,
        selection,
        seed,
        rollout.pairs,
        state,
        rollout.cells_per_particle,
        time.perf_counter() - began,
    )
    if amortised is not None:
        record = amortised.record
        if state.refinement_before is not None and method.refine is not None:
            record = record.with_refinement(
                refinement_result(
                    method.refine,
                    state.refinement_before,
                    state.buffers,
                    selection,
                    rollout.pairs.n_pairs,
                )
            )
        result = replace(result, amortised=record)
    return result


@dataclass(frozen=True)
class CalibrationSetup:
    """Everything :func:`calibrate` takes but the processes and the tracker:
    a calibration ready to run (:meth:`run`), as a run config sets it
    (:func:`torchcf.calibration.of_config.setup_of`).

    Attributes:
        rollout: the training pairs and how particles are simulated.
        priors: the models, in order, and their prior boxes ``(K, 2)``.
        method: the sampler and its budget.
        selection: how the hybrid is read.
        seed: the streams', the estimator's and the samples' seed.
        screen: the plausibility filter (None: none).

    Examples:
        >>> import torch
        >>> from torchcf import PairSet, get_model
        >>> t = torch.arange(100, dtype=torch.float64)[:, None] * 0.1  # (T, 1) [s]
        >>> x_lead, v = 40.0 + 15.0 * t, torch.full_like(t, 15.0)  # [m], [m/s]
        >>> a = torch.zeros_like(t)
        >>> pairs = PairSet.from_arrays([x_lead, v, a, x_lead - 30.0, v, a], dt=0.1)
        >>> from torchcf.abc import Rollout
        >>> from torchcf.calibration import Rejection, SelectionRule
        >>> setup = CalibrationSetup(
        ...     Rollout(pairs), prior_boxes([get_model("idm")]), Rejection(500),
        ...     SelectionRule(), seed=0,
        ... )
        >>> setup.run().models
        ['idm']
    """

    rollout: Rollout
    priors: dict[CFModel, Tensor]
    method: Method
    selection: SelectionRule
    seed: int = 0
    screen: PlausibilityScreen | None = None

    def run(
        self, *, group: Group = SINGLE, tracker: Tracker | None = None
    ) -> Calibration:
        """:func:`calibrate` with this setup."""
        return calibrate(
            self.rollout,
            self.priors,
            self.method,
            selection=self.selection,
            seed=self.seed,
            screen=self.screen,
            group=group,
            tracker=tracker,
        )

    def check(self, prefix: str = "") -> None:
        """The budget checked against the pairs (:func:`check_budget`), with
        the settings named ``prefix + name``."""
        check_budget(
            self.method, self.selection, self.rollout.pairs, self.rollout.paired,
            prefix,
        )  # fmt: skip


class _Streams:
    """The models' streams of one calibration, each through its buffer."""

    def __init__(
        self,
        priors: Mapping[CFModel, Tensor],
        method: Method,
        seed: int,
        rollout: Rollout,
        screen: PlausibilityScreen | None,
        group: Group,
        tracker: Tracker,
    ) -> None:
        self.priors, self.method, self.seed = priors, method, seed
        self.rollout, self.screen, self.group = rollout, screen, group
        self.tracker = tracker
        self.order = [model.name for model in priors]

    def stream(
        self,
        model: CFModel,
        amortised: AmortisedSamples | None,
        refining: bool = False,
    ) -> None:
        """Run ``model``'s particles through its buffer (rejection, SMC, the
        amortised samples, or, ``refining``, their refinement). Under a
        refinement a model is streamed twice: its samples (the model left
        unfinished: the shares before the refinement need every model's),
        then its refinement."""
        method, rollout, tracker = self.method, self.rollout, self.tracker
        state = tracker.state
        name = model.name
        buffer, progress = state.buffers[name], state.progress[name]
        if progress.done:
            return
        own: tuple[Tensor, Tensor] | None = None
        refine = None
        n_total = getattr(method, "n_particles", 0)
        if amortised is not None:  # the model's samples are its stream
            own = amortised.samples.of_model(self.order.index(name))
            n_total = own[0].shape[0]
            if isinstance(method, Amortised) and method.refine is not None:
                refine = method.refine.budget(n_total, rollout.pairs.n_pairs)
                n_total = refine.total

        def after_round(progress: ModelProgress, due: bool) -> None:
            tracker.round(name, progress, rollout)
            if due:
                tracker.save()

        drawn, fixed = drawn_and_held(self.priors[model])
        stream = prior_stream(model, drawn, self.seed, rollout, fixed)
        hooks = RoundHooks(self.group, self.screen, tracker.due, after_round)
        with tracker.model(name, n_total, progress.next):
            if refine is not None and refining:
                refine_population(
                    stream,
                    buffer,
                    rollout,
                    refine,
                    method.refine.settings,
                    progress,
                    state.smc[name],
                    hooks=hooks,
                )
            elif own is not None:
                if progress.next < own[0].shape[0]:
                    run_amortised(
                        model,
                        own,
                        buffer,
                        rollout,
                        progress,
                        hooks=hooks,
                        weight_column=refine is not None,
                    )
                if refine is not None:  # refined once every model's samples are in
                    tracker.save()
                    return
            elif isinstance(method, SMC):
                run_smc(
                    stream,
                    buffer,
                    rollout,
                    n_total,
                    method.settings,
                    progress,
                    state.smc[name],
                    hooks=hooks,
                )
            else:
                run_rejection(stream, buffer, rollout, n_total, progress, hooks=hooks)
        progress.done = True
        tracker.save()


__all__ = ["CalibrationSetup", "Tracker", "calibrate"]
