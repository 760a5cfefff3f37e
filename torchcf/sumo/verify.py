"""Verify the learned hybrid inside SUMO (``torchcf sumo verify RUN``).

The test split's pairs are replayed in SUMO and scored with torchcf's own metric
(SPEC sections 4 and 6), next to torchcf's own rollout of the same particles:

- **the road**: one straight single-lane edge per (particle, test pair) cell
  (:func:`torchcf.sumo.network.straight_edges`), so no cell sees another's
  vehicles; cell ``c = i n_test + j`` is particle ``i`` on test pair ``j``;
- **the leader**: a vehicle forced to the record: speed mode 0,
  ``vehicle.setSpeed(v_l(t+1))`` before SUMO's step and
  ``vehicle.moveTo(x_l(t+1))`` after it, so the follower perceives the recorded
  leader at every step (its FCD row is not read);
- **the follower** starts at the recorded ``x_f(0), v_f(0)`` (inserted at speed 0,
  then ``vehicle.setPreviousSpeed``: SUMO refuses a depart speed above the
  type's ``maxSpeed``) and is driven by
  (a) its particle's exported vType (:mod:`torchcf.sumo.export`; IDM), SUMO's
  own car following; the leader is placed one leader length ahead of its
  recorded front, so SUMO's bumper gap is SPEC's front-to-front spacing; or
  (b) the co-simulation (:class:`~torchcf.sumo.cosim.CoSimulation`, safety layer
  off: the calibration rollout's dynamics), the leader at its recorded front;
  the edges' 100 m/s limit keeps the free-road command above the leader's, so
  the command is the leader's, as in calibration;
- **the record**: SUMO's ``--fcd-output`` (9 decimals) read back. Row ``t`` is
  the state at step ``t`` (``pos`` shifted back to the data's frame, ``speed``);
  SPEC's acceleration series ``a(t)``, the acceleration of the step from t to
  t+1 (and the command at the final state), is SUMO's ``acceleration`` of row
  ``t + 1``: SUMO runs one step past the end for it. For a point mass that is
  SPEC's ``a(t) = u(t)`` except where the step stops the vehicle; for HL and
  ``+lag`` it is the step's mean acceleration, not the lag's state: the
  co-simulation's ``e_a`` differs from torchcf's there, its positions do not.

SUMO runs with ``--step-method.ballistic true`` at the data's ``dt``. Scores follow
SPEC section 4 (RMSE over the valid steps; a non-finite value or a spacing
``x_l - x <= 0`` makes the cell invalid), the set's metrics SPEC section 6
(:func:`torchcf.evaluation.metrics.evaluate_costs`). :func:`verify_run` returns a
:class:`VerifyReport` (its ``to_json`` is ``verify.json``).
"""

from __future__ import annotations

import math
import sys
import tempfile
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor
from tqdm import tqdm

from ..config import load_split
from ..data import PairSet
from ..evaluation.metrics import evaluate_costs
from ..models import get_model
from ..runs.directory import RunDir
from ..runs.metrics import SetMetrics
from ..sim.rollout import DEFAULT_WEIGHTS, SimOutput, simulate
from ..system.console import bar_interval
from ..system.files import (
    JSON,
    atomic_write_text,
    ensure_directory,
    read_json_object,
    write_json,
)
from ..system.records import Record
from ..traffic import HybridSampler, SafetyLayer
from . import backend
from .backend import SumoError
from .cosim import CoSimulation
from .export import MAPPINGS, VTYPES_FILE, export_hybrid, write_export
from .fcd import FCD_OPTIONS, read_fcd
from .network import lane_id, straight_edges

#: The follower's depart position on its edge [m].
START = 10.0
#: Road left beyond the furthest recorded leader position [m].
MARGIN = 300.0
#: The replayed leader's and the co-simulated follower's vType: SUMO's bounds
#: far away (their speed is set every step with speed mode 0).
_FREE = (
    'accel="1e4" decel="1e4" emergencyDecel="1e5" maxSpeed="300" '
    'speedFactor="1" speedDev="0" minGap="0"'
)
LEADER_TYPE = "torchcf_leader"
COSIM_TYPE = "torchcf_cosim"


class Replay(NamedTuple):
    """Followers' trajectories from SUMO in the data's frame, ``(T, C)`` each.

    Attributes:
        x: position [m]; v: speed [m/s]; a: SPEC's acceleration series [m/s^2]
            (module docstring); NaN where SUMO had no such vehicle.
        collisions: SUMO's count of colliding vehicles, summed over the steps.
        emergency_stops: SUMO's count of emergency-braking vehicles, summed.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> test = synthetic_pairs(get_model("idm"), idm, n_pairs=2, n_steps=50)
        >>> from torchcf.sumo import Replay, score_cells
        >>> own = Replay(test.x_follow, test.v_follow, test.a_follow, 0, 0)  # (T, C)
        >>> cells = score_cells(own.x, own.v, own.a, test, pair_index=[0, 1])
        >>> cells["valid"].tolist(), [round(e, 3) for e in cells["e_p"].tolist()]
        ([True, True], [0.0, 0.0])
    """

    x: Tensor
    v: Tensor
    a: Tensor
    collisions: int
    emergency_stops: int


def sumo_arguments(net: Path, routes: Path, fcd: Path, dt: float) -> list[str]:
    """SUMO's command line of a replay (without the program name)."""
    return [
        "--net-file", str(net),
        "--route-files", str(routes),
        "--step-length", repr(float(dt)),
        "--step-method.ballistic", "true",
        "--fcd-output", str(fcd),
        *FCD_OPTIONS,
        "--collision.action", "none",
        "--time-to-teleport", "-1",
        "--no-step-log", "true",
        "--no-warnings", "true",
        "--seed", "0",
    ]  # fmt: skip


def replay(
    test: PairSet,
    pair_index: Sequence[int],
    *,
    workdir: str | Path,
    vtypes: Sequence[str] | None = None,
    additional: str | Path | None = None,
    sampler: HybridSampler | None = None,
    safety: SafetyLayer | None = None,
    progress: str | None = None,
) -> Replay:
    """Replay test pairs in SUMO, followers driven by vTypes or co-simulated.

    Args:
        test: the pairs.
        pair_index: ``(C,)`` the test pair (column) of each cell.
        workdir: where the network, routes and FCD are written.
        vtypes: ``(C,)`` the vType id of each cell's follower (with
            ``additional``, the file defining them); or None with ``sampler``.
        additional: SUMO additional file of ``vtypes``.
        sampler: the co-simulation's sampler, ``vehicle_shape == (C,)``.
        safety: the co-simulation's safety layer (None: off).
        progress: the label of a progress bar over SUMO's steps (None: none).

    Returns:
        :class:`Replay`, ``(T, C)``.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> test = synthetic_pairs(get_model("idm"), idm, n_pairs=2, n_steps=50)
        >>> import tempfile
        >>> from torchcf.sumo import replay
        >>> with tempfile.TemporaryDirectory() as folder:  # doctest: +SKIP
        ...     found = replay(
        ...         test, [0, 1], workdir=folder, vtypes=["idm_0", "idm_0"],
        ...         additional="hybrid.vtypes.add.xml",  # write_export's file
        ...     )
        ...     print(found.x.shape)
        torch.Size([50, 2])
    """
    if (vtypes is None) == (sampler is None):
        raise SumoError("replay needs vtypes or a sampler, one of them")
    workdir = Path(workdir)
    columns = [int(p) for p in pair_index]
    n_cells, n_steps, dt = len(columns), test.n_steps, test.dt
    if vtypes is not None and len(vtypes) != n_cells:
        raise SumoError(f"{len(vtypes)} vtypes for {n_cells} cells")
    length = test.leader_length
    # vTypes: SUMO's IDM reads the bumper gap; one length ahead it is SPEC's s.
    shift = length if vtypes is not None else 0.0
    index = torch.tensor(columns, dtype=torch.long)
    mask = test.mask[:, index]  # (T, C)
    n_valid = mask.sum(0).tolist()
    x_lead = test.x_lead[:, index].double()  # (T, C)
    v_lead = test.v_lead[:, index].double()
    x0 = test.x_follow[0, index].double()  # (C,)
    offset = START - x0  # data frame -> lane position
    reach = torch.where(mask, x_lead, -math.inf).amax(0) + offset + shift  # (C,)
    edge_length = float(reach.max()) + MARGIN + 2 * float(v_lead.abs().amax()) * dt
    net = straight_edges(n_cells, edge_length, workdir, speed=100.0)

    follower_type = COSIM_TYPE if vtypes is None else None
    lines = [
        "<routes>",
        f'    <vType id="{LEADER_TYPE}" length="{length!r}" {_FREE}/>',
        f'    <vType id="{COSIM_TYPE}" length="{length!r}" {_FREE}/>',
    ]
    lead_pos = (x_lead[0] + offset + shift).tolist()
    for c in range(n_cells):
        kind = follower_type or vtypes[c]
        lines.append(
            f'    <route id="r{c}" edges="e{c}"/>\n'
            f'    <vehicle id="L{c}" type="{LEADER_TYPE}" route="r{c}" depart="0" '
            f'departPos="{lead_pos[c]!r}" departSpeed="0" insertionChecks="none"/>\n'
            f'    <vehicle id="F{c}" type="{kind}" route="r{c}" depart="0" '
            f'departPos="{START!r}" departSpeed="0" insertionChecks="none"/>'
        )
    lines.append("</routes>")
    routes = workdir / "replay.rou.xml"
    atomic_write_text(routes, "\n".join(lines) + "\n")
    fcd_path = workdir / "replay.fcd.xml"
    arguments = sumo_arguments(net, routes, fcd_path, dt)
    if additional is not None:
        arguments += ["--additional-files", str(additional)]

    leaders = [f"L{c}" for c in range(n_cells)]
    followers = [f"F{c}" for c in range(n_cells)]
    lanes = [lane_id(c) for c in range(n_cells)]
    lead_x = (x_lead + offset + shift).tolist()  # (T, C) lane positions
    lead_v = v_lead.tolist()
    v0 = test.v_follow[0, index].double().tolist()
    collisions = emergency = 0
    with backend.running(arguments) as sumo:
        sumo.simulationStep()  # inserts every vehicle at its depart position
        vehicle = sumo.vehicle
        missing = set(leaders + followers) - set(vehicle.getIDList())
        if missing:
            raise SumoError(f"SUMO did not insert {len(missing)} vehicles")
        for c in range(n_cells):
            vehicle.setSpeedMode(leaders[c], 0)
            vehicle.setPreviousSpeed(leaders[c], lead_v[0][c])
            vehicle.setPreviousSpeed(followers[c], v0[c])
        cosim = None
        if sampler is not None:
            cosim = CoSimulation(
                sumo,
                sampler,
                followers,
                safety=safety,
                position_offset=(-offset).to(sampler.dtype),
                initial_acceleration=test.a_follow[0, index].to(sampler.dtype),
            )
        steps = tqdm(
            range(n_steps), desc=progress, unit="step", disable=progress is None,
            mininterval=bar_interval(), postfix=f"{n_cells} followers",
        )  # fmt: skip
        for t in steps:  # SUMO rows 1 .. T: one past the end (module doc)
            if cosim is not None:
                cosim.command()
            forced = [c for c in range(n_cells) if t + 1 < n_valid[c]]
            for c in forced:
                vehicle.setSpeed(leaders[c], lead_v[t + 1][c])
            sumo.simulationStep()
            if cosim is not None:
                cosim.settle()
            for c in forced:
                vehicle.moveTo(leaders[c], lanes[c], lead_x[t + 1][c])
            collisions += sumo.simulation.getCollidingVehiclesNumber()
            emergency += sumo.simulation.getEmergencyStoppingVehiclesNumber()
    # FCD stamps the state after a step with the step's start time: 0 = insertion.
    fcd = read_fcd(
        fcd_path, followers, begin=0.0, dt=dt, n_steps=n_steps + 1,
        progress=None if progress is None else f"{progress}: reading SUMO's FCD",
    )  # fmt: skip
    x = fcd.pos[:n_steps] - offset[None, :]  # (T, C)
    v = fcd.speed[:n_steps].clone()
    # Row 0 is written at insertion, before setPreviousSpeed gave the speed.
    v[0] = test.v_follow[0, index].double()
    return Replay(x, v, fcd.acceleration[1:], collisions, emergency)


def score_cells(
    x: Tensor,
    v: Tensor,
    a: Tensor,
    test: PairSet,
    pair_index: Sequence[int],
    weights: Sequence[float] = DEFAULT_WEIGHTS,
) -> dict[str, Tensor]:
    """SPEC section 4 on trajectories: RMSE over each pair's valid steps of
    position, speed and acceleration against the record, their weighted score;
    ``+inf`` where a value is not finite or the spacing ``x_l - x <= 0``.

    Args:
        x: ``(T, C)`` simulated position [m].
        v: ``(T, C)`` simulated speed [m/s].
        a: ``(T, C)`` simulated acceleration [m/s^2].
        test: the pairs.
        pair_index: ``(C,)`` the pair of each column.
        weights: of (position, speed, acceleration).

    Returns:
        ``score, e_p, e_v, e_a``: ``(C,)`` float64 each, and ``valid`` bool.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> test = synthetic_pairs(get_model("idm"), idm, n_pairs=2, n_steps=50)
        >>> from torchcf.sumo import score_cells
        >>> x = test.x_follow - 1.0  # every follower 1 m behind its record [m]
        >>> cells = score_cells(x, test.v_follow, test.a_follow, test, [0, 1])
        >>> [round(e, 3) for e in cells["e_p"].tolist()]  # position RMSE [m]
        [1.0, 1.0]
        >>> [round(s, 3) for s in cells["score"].tolist()]  # 0.5 e_p + 0.3 e_v + ...
        [0.5, 0.5]
    """
    index = torch.as_tensor(list(pair_index), dtype=torch.long)
    mask = test.mask[:, index]  # (T, C)
    count = mask.sum(0).double()  # (C,)
    spacing = test.x_lead[:, index].double() - x
    finite = torch.isfinite(x) & torch.isfinite(v) & torch.isfinite(a)
    valid = ((finite & (spacing > 0)) | ~mask).all(0)  # (C,)
    out: dict[str, Tensor] = {}
    for key, sim, obs in (
        ("e_p", x, test.x_follow),
        ("e_v", v, test.v_follow),
        ("e_a", a, test.a_follow),
    ):
        err = torch.where(mask, sim - obs[:, index].double(), 0.0)
        out[key] = torch.where(valid, torch.sqrt((err * err).sum(0) / count), math.inf)
    out["score"] = sum(
        w * out[k] for w, k in zip(weights, ("e_p", "e_v", "e_a"), strict=True)
    )
    out["valid"] = valid
    return out


@dataclass(frozen=True)
class CosimCheck(Record):
    """(b) Every model co-simulated in SUMO against torchcf's rollout of the same
    particles (``verify.json``'s ``cosim``).

    Attributes:
        models: the models co-simulated.
        max_position_difference_m: the largest |x - torchcf| over the valid
            steps [m].
        max_speed_difference_m_s: the same of the speeds [m/s].
        sumo: SUMO's trajectories' metrics; torchcf: torchcf's.
        collisions: SUMO's colliding vehicles, summed over the steps.
        emergency_stops: SUMO's emergency-braking vehicles, summed.
    """

    models: tuple[str, ...]
    max_position_difference_m: float
    max_speed_difference_m_s: float
    sumo: SetMetrics
    torchcf: SetMetrics
    collisions: int
    emergency_stops: int


#: The JSON key of :attr:`VTypesCheck.cells_within_tolerance`.
_WITHIN = "cells_within_1e-6_m"


@dataclass(frozen=True)
class VTypesCheck(Record):
    """(a) The exported vTypes replayed in SUMO against torchcf's rollout
    (``verify.json``'s ``vtypes``).

    Attributes:
        models: the models exported (those SUMO has).
        max_position_difference_m: the largest |x - torchcf| [m].
        cells: the (particle, test pair) cells replayed.
        cells_within_tolerance: cells within 1e-6 m of torchcf's rollout
            (``cells_within_1e-6_m`` in the file).
        cells_above_v0: cells whose follower drives above its ``v0``, where
            SUMO brakes at ``decel`` towards it.
        max_position_difference_at_or_below_v0_m: the largest difference over
            the other cells [m] (NaN: none).
        sumo: SUMO's trajectories' metrics; torchcf: torchcf's.
        collisions: SUMO's colliding vehicles, summed over the steps.
        emergency_stops: SUMO's emergency-braking vehicles, summed.
    """

    models: tuple[str, ...]
    max_position_difference_m: float
    cells: int
    cells_within_tolerance: int
    cells_above_v0: int
    max_position_difference_at_or_below_v0_m: float
    sumo: SetMetrics
    torchcf: SetMetrics
    collisions: int
    emergency_stops: int

    def to_json(self) -> JSON:
        """The ``vtypes`` object, in the file's order and keys."""
        return {
            (_WITHIN if key == "cells_within_tolerance" else key): value
            for key, value in super().to_json().items()
        }


@dataclass(frozen=True)
class VerifyReport(Record):
    """A SUMO verification of a run: the content of ``verify.json``.

    Attributes:
        run: the run directory.
        dataset: its data set.
        n_test: test pairs replayed; dt: their step [s].
        particles: model -> its hybrid particles replayed.
        torchcf_metrics_json: the hybrid's ``ws, min, e_p, e_v, e_a`` of the
            run's own evaluation (its ``metrics.json`` as read; None: not
            evaluated).
        vtypes: the exported vTypes' check (None: no model SUMO has; absent
            from the file then).
        cosim: the co-simulation's check.
    """

    run: str
    dataset: str
    n_test: int
    dt: float
    particles: dict[str, int]
    torchcf_metrics_json: JSON | None
    vtypes: VTypesCheck | None
    cosim: CosimCheck

    def to_json(self) -> JSON:
        """The content of ``verify.json``, key order included."""
        out = super().to_json()
        if self.vtypes is None:
            del out["vtypes"]
        return out


def _metrics(costs: dict[str, Tensor], n_test: int, beta: float) -> SetMetrics:
    shaped = [
        costs[k].reshape(-1, n_test).numpy() for k in ("score", "e_p", "e_v", "e_a")
    ]
    return evaluate_costs(*shaped, beta=beta)


def _max_difference(x: Tensor, reference: Tensor, mask: Tensor) -> float:
    """Largest |x - reference| [m] over valid steps where both are finite."""
    both = mask & torch.isfinite(x) & torch.isfinite(reference)
    if not bool(both.any()):
        return math.nan
    return float((x - reference).abs()[both].max())


def verify_run(
    run_dir: str | Path,
    out_dir: str | Path | None = None,
    *,
    max_particles: int | None = None,
    test: PairSet | None = None,
    workdir: str | Path | None = None,
    progress: bool = False,
) -> VerifyReport:
    """Replay a trained run's test split in SUMO and score it beside torchcf.

    Args:
        run_dir: a trained run.
        out_dir: where ``verify.json`` and ``verify.md`` go (default
            ``RUN_DIR/sumo``).
        max_particles: keep each model's first this many hybrid particles (None:
            all); torchcf's figures are computed on the same particles.
        test: the test pairs (default: the run's test split).
        workdir: where SUMO's files go (default: a temporary folder, removed).
        progress: say each stage on stderr and show a bar over SUMO's steps.

    Returns:
        the report (its ``to_json`` is ``verify.json``).

    Raises:
        RunFileError, ConfigError, DataError: the run or its data.
        SumoError, SumoMissingError: SUMO.

    Examples:
        >>> from torchcf.sumo import verify_run
        >>> report = verify_run("runs/demo", max_particles=10)  # doctest: +SKIP
    """
    if max_particles is not None and max_particles < 1:
        raise SumoError(f"max particles must be >= 1, got {max_particles}")
    run = RunDir(run_dir)
    # No training or evaluation rewrites the run meanwhile.
    with run.locked() if run.path.is_dir() else nullcontext():
        return _verify_held(run, out_dir, max_particles, test, workdir, progress)


def _verify_held(
    run: RunDir,
    out_dir: str | Path | None,
    max_particles: int | None,
    test: PairSet | None,
    workdir: str | Path | None,
    progress: bool,
) -> VerifyReport:
    """:func:`verify_run` with the run directory held."""

    def say(text: str) -> None:
        if progress:
            print(f"sumo verify: {text}", file=sys.stderr, flush=True)

    say("loading the run and its test split")
    cfg, posterior, _ = run.load_run()
    if test is None:
        test = load_split(cfg.data)[1]
    weights = tuple(cfg.abc.weights)
    beta = cfg.eval.beta
    out = Path(out_dir) if out_dir is not None else run.path / "sumo"
    ensure_directory(out, "verify output directory")
    backend.require_libsumo()
    backend.binary("netconvert")
    n_test = test.n_pairs
    names = [n for n in posterior.models if len(posterior.hybrid[n])]
    models = {n: get_model(n) for n in names}  # the posterior's names enter here
    theta = {
        n: posterior.hybrid[n].theta[: max_particles or None].double() for n in names
    }
    mask_all = test.mask

    # torchcf's own rollout of the same particles, float64.
    say(
        f"torchcf's rollout of {sum(len(t) for t in theta.values())} particles on "
        f"{n_test} test pairs"
    )
    own = {
        n: simulate(
            models[n],
            theta[n],
            test,
            dtype=torch.float64,
            return_traj=True,
            weights=weights,
        )
        for n in names
    }
    recorded = _recorded_ws(run)
    vtypes = None
    scratch = (
        tempfile.TemporaryDirectory(prefix="torchcf-sumo-") if workdir is None else None
    )
    base = Path(scratch.name) if scratch is not None else Path(workdir)
    try:
        # (a) exported vTypes, the models SUMO has.
        exported = [n for n in names if n in MAPPINGS]
        if exported:
            folder = base / "vtypes"
            folder.mkdir(parents=True, exist_ok=True)
            export = export_hybrid(posterior, dt=test.dt, length=test.leader_length)
            write_export(export, folder)
            pairs_a, types_a = [], []
            for n in exported:
                for i in range(theta[n].shape[0]):
                    for j in range(n_test):
                        pairs_a.append(j)
                        types_a.append(f"{n}_{i}")
            run_a = replay(
                test,
                pairs_a,
                workdir=folder,
                vtypes=types_a,
                additional=folder / VTYPES_FILE,
                progress="sumo verify: exported vTypes" if progress else None,
            )
            scored = score_cells(run_a.x, run_a.v, run_a.a, test, pairs_a, weights)
            reference = torch.cat(
                [own[n].x.reshape(test.n_steps, -1) for n in exported], dim=1
            )  # (T, P_a n_test), cell i n_test + j
            ref_costs = _own_costs(own, exported)
            mask = mask_all[:, torch.tensor(pairs_a)]
            # SUMO brakes at decel above the desired speed (export's docstring):
            # the cells where torchcf's follower exceeds v0 are reported apart.
            above = torch.cat(
                [_above_desired(own[n], theta[n], mask_all) for n in exported]
            )  # (C,)
            differences = _cell_differences(run_a.x, reference, mask)  # (C,)
            vtypes = VTypesCheck(
                models=tuple(exported),
                max_position_difference_m=_max_difference(run_a.x, reference, mask),
                cells=len(pairs_a),
                cells_within_tolerance=int((differences <= 1e-6).sum()),
                cells_above_v0=int(above.sum()),
                max_position_difference_at_or_below_v0_m=float(
                    differences[~above].max()
                )
                if bool((~above).any())
                else math.nan,
                sumo=_metrics(scored, n_test, beta),
                torchcf=_metrics(ref_costs, n_test, beta),
                collisions=run_a.collisions,
                emergency_stops=run_a.emergency_stops,
            )
        # (b) co-simulation of every model.
        folder = base / "cosim"
        folder.mkdir(parents=True, exist_ok=True)
        sampler = HybridSampler(
            [models[n] for n in names],
            [theta[n] for n in names],
            dt=test.dt,
            leader_length=test.leader_length,
            dtype=torch.float64,
        )
        pairs_b, particles_b = [], []
        for n in names:
            ids = sampler.particle_ids(n).tolist()
            for i in ids:
                for j in range(n_test):
                    pairs_b.append(j)
                    particles_b.append(i)
        sampler.assign(torch.tensor(particles_b))
        run_b = replay(
            test, pairs_b, workdir=folder, sampler=sampler,
            progress="sumo verify: co-simulation" if progress else None,
        )  # fmt: skip
        scored = score_cells(run_b.x, run_b.v, run_b.a, test, pairs_b, weights)
        reference = torch.cat([own[n].x.reshape(test.n_steps, -1) for n in names], 1)
        mask = mask_all[:, torch.tensor(pairs_b)]
        cosim = CosimCheck(
            models=tuple(names),
            max_position_difference_m=_max_difference(run_b.x, reference, mask),
            max_speed_difference_m_s=_max_difference(
                run_b.v,
                torch.cat([own[n].v.reshape(test.n_steps, -1) for n in names], 1),
                mask,
            ),
            sumo=_metrics(scored, n_test, beta),
            torchcf=_metrics(_own_costs(own, names), n_test, beta),
            collisions=run_b.collisions,
            emergency_stops=run_b.emergency_stops,
        )
    finally:
        if scratch is not None:
            scratch.cleanup()
    report = VerifyReport(
        run=str(run.path),
        dataset=posterior.dataset,
        n_test=n_test,
        dt=test.dt,
        particles={n: int(theta[n].shape[0]) for n in names},
        torchcf_metrics_json=recorded,
        vtypes=vtypes,
        cosim=cosim,
    )
    write_json(out / "verify.json", report.to_json())
    atomic_write_text(out / "verify.md", report_markdown(report))
    return report


def _cell_differences(x: Tensor, reference: Tensor, mask: Tensor) -> Tensor:
    """``(C,)`` largest |x - reference| [m] of each cell over its valid steps
    (``inf`` where one side is not finite)."""
    gap = torch.where(mask, (x - reference).abs(), 0.0)
    return torch.where(torch.isnan(gap), math.inf, gap).amax(0)


def _above_desired(sim: SimOutput, theta: Tensor, mask: Tensor) -> Tensor:
    """``(P n_test,)`` cells whose rollout (``(T, P, N)``) drives above the
    IDM particle's desired speed ``v0`` at a valid step."""
    v0 = theta[:, get_model("idm").param_names.index("v0")]  # (P,)
    above = (sim.v > v0[None, :, None]) & mask[:, None, :]  # (T, P, N)
    return above.any(0).reshape(-1)


def _own_costs(own: dict[str, SimOutput], names: Sequence[str]) -> dict[str, Tensor]:
    """torchcf's (P, n_test) costs of these models, stacked, flattened like the
    cells (particle-major)."""
    return {
        key: torch.cat([getattr(own[n], key).reshape(-1) for n in names]).double()
        for key in ("score", "e_p", "e_v", "e_a")
    }


def _recorded_ws(run: RunDir) -> JSON | None:
    """The hybrid's WS of the run's own evaluation (``metrics.json``, read as
    JSON: any release's), if any."""
    path = run.path / "metrics.json"
    if not path.is_file():
        return None
    hybrid = read_json_object(path).get("hybrid", {})
    return {k: hybrid.get(k) for k in ("ws", "min", "e_p", "e_v", "e_a")}


def _fmt(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:.6g}"
    return str(value)


def report_markdown(report: VerifyReport) -> str:
    """``verify.md``: SUMO's figures beside torchcf's on the same particles."""
    lines = [
        f"# SUMO verification: {report.dataset}",
        "",
        f"Run `{report.run}`; {report.n_test} test pairs, dt {report.dt} s; "
        "particles per model: "
        + ", ".join(f"{k} {v}" for k, v in report.particles.items())
        + ".",
        "",
        "| particles | simulator | WS | min | e_p [m] | e_v [m/s] | e_a [m/s^2] "
        "| invalid cells | max \\|x - torchcf\\| [m] | collisions | emergency stops |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    checks: tuple[tuple[VTypesCheck | CosimCheck | None, str], ...] = (
        (report.vtypes, "exported vTypes"),
        (report.cosim, "co-simulation"),
    )
    for part, label in checks:
        if part is None:
            continue
        who = "+".join(part.models)
        for side, name in (("torchcf", "torchcf rollout"), ("sumo", f"SUMO {label}")):
            m = part.sumo if side == "sumo" else part.torchcf
            diff = part.max_position_difference_m if side == "sumo" else None
            counters = (
                (part.collisions, part.emergency_stops) if side == "sumo" else ("", "")
            )
            lines.append(
                f"| {who} | {name} | {_fmt(m.ws)} | {_fmt(m.min)} | "
                f"{_fmt(m.e_p)} | {_fmt(m.e_v)} | {_fmt(m.e_a)} | "
                f"{m.invalid_cells} | {_fmt(diff)} | {counters[0]} | {counters[1]} |"
            )
    vtypes = report.vtypes
    if vtypes is not None:
        lines += [
            "",
            f"Exported vTypes: {vtypes.cells_within_tolerance} of {vtypes.cells} "
            "cells within 1e-6 m of torchcf's rollout; the largest difference over "
            "the cells whose follower stays at or below its v0 is "
            f"{_fmt(vtypes.max_position_difference_at_or_below_v0_m)} m; "
            f"{vtypes.cells_above_v0} cells drive above v0, where SUMO brakes at "
            "decel towards it (`torchcf/sumo/export.py`).",
        ]
    recorded = report.torchcf_metrics_json
    if recorded:
        lines += [
            "",
            f"The run's own evaluation (`metrics.json`, its dtype, all particles): "
            f"hybrid WS {_fmt(recorded.get('ws'))}, min {_fmt(recorded.get('min'))}.",
        ]
    lines += [
        "",
        "SUMO: straight single-lane edge per cell, leader forced to the record, "
        "--step-method.ballistic, FCD at 9 decimals; co-simulation without the "
        "safety layer (the calibration rollout). The acceleration SUMO reports is "
        "the step's mean: for HL it is not the lag's state (see "
        "`torchcf/sumo/verify.py`).",
        "",
    ]
    return "\n".join(lines)


__all__ = [
    "COSIM_TYPE",
    "LEADER_TYPE",
    "CosimCheck",
    "Replay",
    "VTypesCheck",
    "VerifyReport",
    "replay",
    "report_markdown",
    "score_cells",
    "sumo_arguments",
    "verify_run",
]
