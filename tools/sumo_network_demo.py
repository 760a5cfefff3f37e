"""Learned hybrids deployed in SUMO networks: a ring and a multi-lane highway.

A mixed fleet: ``--fleet RUN:FRACTION ...`` (default ``runs/paper/carII:0.3
runs/paper/ngsim:0.7``, an AV penetration rate of 30 %: CAR MODEL II's ACC
platoons as the AVs, NGSIM I-80's drivers as the humans). Each vehicle draws its
class (run) with the given probabilities, then a particle of that run's hybrid
(uniformly over its particles, so each model drives its share ``beta_m`` of the
class). A vehicle whose particle is of a model SUMO has (IDM) drives as its
exported vType, SUMO's own car following (``python -m torchcf sumo export``;
vType ids prefixed by the class's tag); every other vehicle is co-simulated
(:class:`torchcf.sumo.CoSimulation`, one per class, one sampler call per step for
all of its vehicles, torchcf's safety layer on). Lane changes are SUMO's (LC2013).

Units: every run is SI throughout. NGSIM's files are in feet, ft/s, ft/s^2;
torchcf converts them to SI on loading (``torchcf.data.formats.ngsim`` /
the registry's ``units="ft"``), so the NGSIM posterior was fitted on SI pairs and
its particles' lengths (IDM's ``s0``, spacings) are metres already; the leader
(vehicle) length is the registry's 5 m for both data sets. Nothing is converted
here; the script checks that the runs share ``dt`` and the vehicle length.

- **ring**: ``--ring-vehicles`` vehicles evenly spaced on a single-lane ring of
  ``--ring-length`` metres, from rest (Sugiyama et al. 2008's experiment);
- **highway**: a 3-lane road of ``--highway-length`` metres whose right lane ends
  at 70 % of it, fed by a demand rising linearly to ``--demand`` vehicles per
  hour (Poisson arrivals).

Measured per scene: the time-space diagram, the time headway distribution (bumper
gap / speed, vehicles above 1 m/s) per class beside the data's (the training
pairs of each class's run, same definition) with medians and the two-sample KS
distance, and of native against co-simulated vehicles, flow and
density by Edie's definitions on 100 m x 30 s cells, and SUMO's counters:
collisions (``--collision.mingap-factor 0``: bumper contact only), emergency
braking, and the co-simulation's safety-layer interventions.

    python tools/sumo_network_demo.py --out reports/sumo \
        --fleet runs/paper/carII:0.3 runs/paper/ngsim:0.7

Writes ``OUT/network_demo.{md,json}`` and ``OUT/{ring,highway}_{time_space,
headways,flow_density}.png``. Needs ``pip install -e '.[sumo]'``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch import Tensor  # noqa: E402

from torchcf.config import ConfigError, load_split  # noqa: E402
from torchcf.runs.directory import RunDir  # noqa: E402
from torchcf.sumo import backend  # noqa: E402
from torchcf.sumo.cosim import CoSimulation  # noqa: E402
from torchcf.sumo.export import (  # noqa: E402
    DISTRIBUTION_ID,
    MAPPINGS,
    export_hybrid,
    run_constants,
)
from torchcf.sumo.network import highway, ring  # noqa: E402
from torchcf.system.console import (
    OneLineParser,  # noqa: E402
    count,
    natural,
    nonnegative,
    positive,
    run_main,
)
from torchcf.system.files import no_empty_folder_left  # noqa: E402
from torchcf.traffic import HybridSampler  # noqa: E402

COSIM_TYPE = "torchcf_cosim"
#: Edie's cells [m], [s].
CELL_LENGTH, CELL_TIME = 100.0, 30.0


#: Vehicles below this speed [m/s] have no time headway (data and simulation).
MIN_SPEED = 1.0


def parse_fleet(items: list[str]) -> list[tuple[str, float]]:
    """``["RUN:FRACTION", ...]`` -> ``[(run, fraction), ...]``, fractions
    normalised to sum 1 (a bare ``RUN`` counts 1)."""
    fleet = []
    for item in items:
        run, sep, fraction = item.rpartition(":")
        if not sep:
            run, fraction = item, "1"
        try:
            value = nonnegative(fraction)
        except argparse.ArgumentTypeError:
            raise ConfigError(
                f"--fleet {item[:80]}: the fraction must be a number >= 0"
            ) from None
        fleet.append((run, value))
    total = sum(f for _, f in fleet)
    if not fleet or total <= 0.0:
        raise ConfigError("--fleet: needs a run with a fraction > 0")
    return [(run, f / total) for run, f in fleet]


def pair_headways(pairs, min_speed: float = MIN_SPEED) -> np.ndarray:
    """Time headways [s] of a PairSet's valid steps: the bumper gap
    ``x_lead - leader_length - x_follow`` over the follower's speed, where that
    speed exceeds ``min_speed`` and the gap is positive (NGSIM holds a few
    position errors with overlapping vehicles)."""
    gap = (pairs.x_lead - pairs.leader_length - pairs.x_follow).double()
    v = pairs.v_follow.double()
    keep = pairs.mask & (v > min_speed) & (gap > 0.0)
    return (gap[keep] / v[keep]).numpy()


def ks_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Kolmogorov-Smirnov distance: the largest gap between the two
    empirical CDFs."""
    a, b = np.sort(np.asarray(a, float)), np.sort(np.asarray(b, float))
    if a.size == 0 or b.size == 0:
        return math.nan
    grid = np.concatenate([a, b])
    cdf_a = np.searchsorted(a, grid, side="right") / a.size
    cdf_b = np.searchsorted(b, grid, side="right") / b.size
    return float(np.max(np.abs(cdf_a - cdf_b)))


class Component:
    """One class of the fleet: a run's hybrid, its fraction, its data."""

    def __init__(self, run: str, fraction: float, tag: str):
        cfg, posterior, _ = RunDir(run).load_run()
        self.run, self.fraction, self.tag = run, fraction, tag
        self.dataset = posterior.dataset
        self.label = (
            "AV" if self.dataset.startswith("car-model")
            else "human" if self.dataset.startswith("ngsim") else tag
        )  # fmt: skip
        self.posterior = posterior
        self.dt, self.length = run_constants(cfg, posterior)
        self.sampler = HybridSampler.from_posterior(
            posterior, dt=self.dt, leader_length=self.length, dtype=torch.float64
        )
        self.train = load_split(cfg.data)[0]
        self.data_headways = pair_headways(self.train)
        self.cosim_type = f"{COSIM_TYPE}_{tag}"

    def export_xml(self) -> str:
        """The exported vTypes with ids prefixed by the tag (two runs' ids and
        distributions would clash)."""
        xml = export_hybrid(self.posterior, dt=self.dt, length=self.length).xml
        return xml.replace('<vType id="', f'<vType id="{self.tag}_').replace(
            f'id="{DISTRIBUTION_ID}"', f'id="{DISTRIBUTION_ID}_{self.tag}"'
        )


class Fleet:
    """The drawn vehicles: class, model, native (its vType) or co-simulated."""

    def __init__(self, components: list[Component], n: int, generator):
        weights = torch.tensor([c.fraction for c in components], dtype=torch.float64)
        self.components = components
        self.cls = torch.multinomial(weights, n, True, generator=generator).tolist()
        self.model, self.native, self.vtype, drawn = [], [], [], []
        for c in self.cls:
            sampler = components[c].sampler
            particle = int(
                torch.randint(0, sampler.n_particles, (1,), generator=generator)
            )
            model = sampler.model_names[int(sampler.particle_model[particle])]
            row = int(sampler.particle_row[particle])
            native = model in MAPPINGS
            self.model.append(model)
            self.native.append(native)
            self.vtype.append(
                f"{components[c].tag}_{model}_{row}" if native
                else components[c].cosim_type
            )  # fmt: skip
            drawn.append(particle)
        self.drawn = drawn

    def truncate(self, used: int) -> None:
        for name in ("cls", "model", "native", "vtype", "drawn"):
            setattr(self, name, getattr(self, name)[:used])

    def cosim(self, c: int) -> tuple[list[int], Tensor]:
        """Class ``c``'s co-simulated vehicles: indices, particles."""
        index = [
            i for i, (k, native) in enumerate(zip(self.cls, self.native, strict=True))
            if k == c and not native
        ]  # fmt: skip
        return index, torch.tensor([self.drawn[i] for i in index], dtype=torch.long)


def _routes(path: Path, fleet: Fleet, length: float, vehicles: list[str]) -> None:
    path.write_text(
        "<routes>\n"
        + "".join(
            f'    <vType id="{c.cosim_type}" length="{length!r}" minGap="0" '
            'maxSpeed="55.56" speedFactor="1" speedDev="0"/>\n'
            for c in fleet.components
        )
        + "\n".join(vehicles)
        + "\n</routes>\n"
    )


def _arguments(net: Path, routes: Path, additional: str, dt: float) -> list[str]:
    return [
        "--net-file", str(net), "--route-files", str(routes),
        "--additional-files", additional,
        "--step-length", repr(dt), "--step-method.ballistic", "true",
        "--collision.action", "warn", "--collision.mingap-factor", "0",
        "--time-to-teleport", "-1", "--no-step-log", "true", "--no-warnings", "true",
        "--seed", "0",
    ]  # fmt: skip


def _simulate(arguments, dt, fleet, n_steps, position_of) -> dict:
    """Run SUMO with the fleet; record every vehicle at every step."""
    names = [f"v{i}" for i in range(len(fleet.vtype))]
    native = dict(zip(names, fleet.native, strict=True))
    cls = dict(zip(names, fleet.cls, strict=True))
    records = []  # (t, x, v, lane, headway, native, class)
    collided, emergency = set(), set()
    impact: dict[tuple[str, str], float] = {}  # (collider, victim) -> its top speed
    collision_steps = emergency_steps = 0
    with backend.running(arguments) as sumo:
        vehicle = sumo.vehicle
        cosims = []
        for c, component in enumerate(fleet.components):
            index, particles = fleet.cosim(c)
            if index:
                component.sampler.assign(particles)
                cosims.append(
                    CoSimulation(sumo, component.sampler, [names[i] for i in index])
                )
        for step in range(n_steps):
            for cosim in cosims:
                cosim.command()
            sumo.simulationStep()
            for cosim in cosims:
                cosim.settle()
            ids = sumo.simulation.getCollidingVehiclesIDList()
            collided.update(ids)
            collision_steps += len(ids)
            for event in sumo.simulation.getCollisions():
                key = (event.collider, event.victim)
                impact[key] = max(impact.get(key, 0.0), event.colliderSpeed)
            ids = sumo.simulation.getEmergencyStoppingVehiclesIDList()
            emergency.update(ids)
            emergency_steps += len(ids)
            t = (step + 1) * dt
            for vid in vehicle.getIDList():
                v = vehicle.getSpeed(vid)
                leader = vehicle.getLeader(vid, 300.0)
                headway = math.nan
                if leader and leader[0] and v > 1.0:
                    headway = (leader[1] + vehicle.getMinGap(vid)) / v
                records.append(
                    (
                        t,
                        position_of(
                            vehicle.getRoadID(vid), vehicle.getLanePosition(vid)
                        ),
                        v,
                        vehicle.getLaneIndex(vid),
                        headway,
                        native[vid],
                        cls[vid],
                    )
                )
        interventions = sum(int(cosim.interventions.sum()) for cosim in cosims)
    data = np.array(records, dtype=float)
    return {
        "data": data,
        "collisions": {
            "vehicles": len(collided),
            "vehicle_steps": collision_steps,
            "pairs": len(impact),
            "pairs_at_standstill": sum(v < 0.1 for v in impact.values()),
            "max_collider_speed_m_s": max(impact.values(), default=0.0),
        },
        "emergency_braking": {
            "vehicles": len(emergency),
            "vehicle_steps": emergency_steps,
        },
        "safety_interventions": interventions,
    }


def _edie(data: np.ndarray, dt: float, x_range: tuple[float, float], t_end: float):
    """Flow [veh/h] and density [veh/km] per lane of every 100 m x 30 s cell
    (Edie: distance travelled and time spent over the cell's area)."""
    t, x, v, lane = data[:, 0], data[:, 1], data[:, 2], data[:, 3]
    inside = (x >= x_range[0]) & (x < x_range[1])
    ix = ((x[inside] - x_range[0]) // CELL_LENGTH).astype(int)
    it = (t[inside] // CELL_TIME).astype(int)
    n_lanes = int(lane.max()) + 1
    shape = (int(t_end // CELL_TIME) + 1, int((x_range[1] - x_range[0]) // CELL_LENGTH))
    distance = np.zeros(shape)
    time = np.zeros(shape)
    keep = ix < shape[1]
    np.add.at(distance, (it[keep], ix[keep]), v[inside][keep] * dt)
    np.add.at(time, (it[keep], ix[keep]), dt)
    area = CELL_LENGTH * CELL_TIME * n_lanes
    flow = distance / area * 3600.0
    density = time / area * 1000.0
    full = (np.arange(shape[0]) + 1) * CELL_TIME <= t_end
    return flow[full].ravel(), density[full].ravel()


def _figures(
    name: str, result: dict, out: Path, dt: float, x_range, t_end, select=None
) -> dict:
    data = result["data"]
    t, x, v, lane, headway, native, cls = data.T
    fig, ax = plt.subplots(figsize=(8, 4.5))
    shown = np.ones_like(lane, dtype=bool) if select is None else select(x, lane)
    every = max(1, int(round(0.5 / dt)))
    sample = shown & (np.round(t / dt) % every == 0)
    points = ax.scatter(t[sample], x[sample], c=v[sample], s=0.3, cmap="viridis_r")
    fig.colorbar(points, ax=ax, label="speed [m/s]")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("ring position [m]" if name == "ring" else "position, left lane [m]")
    ax.set_title(f"{name}: time-space diagram")
    fig.savefig(out / f"{name}_time_space.png", dpi=120, bbox_inches="tight")
    plt.close(fig)

    components = result["components"]
    bins = np.linspace(0, 6, 61)
    fig, axes = plt.subplots(
        1, len(components), figsize=(5 * len(components), 4), squeeze=False
    )
    stats, classes = {}, {}
    for c, (component, ax) in enumerate(zip(components, axes[0], strict=True)):
        h = headway[(cls == c) & np.isfinite(headway)]
        d = component.data_headways
        name_c = f"{component.label} ({component.dataset})"
        ax.hist(d, bins=bins, density=True, alpha=0.5, label=f"data, train ({d.size})")
        if h.size:
            ax.hist(h, bins=bins, density=True, alpha=0.5, label=f"SUMO ({h.size})")
        classes[name_c] = {
            "run": component.run,
            "sim_median_s": float(np.median(h)) if h.size else math.nan,
            "sim_p05_s": float(np.quantile(h, 0.05)) if h.size else math.nan,
            "sim_samples": int(h.size),
            "data_median_s": float(np.median(d)),
            "data_p05_s": float(np.quantile(d, 0.05)),
            "data_samples": int(d.size),
            "ks_distance": ks_distance(h, d),
        }
        ax.set_xlabel("time headway [s] (gap / speed, v > 1 m/s)")
        ax.set_ylabel("density")
        ax.legend()
        ax.set_title(f"{name}: {name_c}")
    fig.savefig(out / f"{name}_headways.png", dpi=120, bbox_inches="tight")
    plt.close(fig)
    for flag, label in ((1.0, "native (SUMO IDM)"), (0.0, "co-simulated")):
        h = headway[(native == flag) & np.isfinite(headway)]
        if h.size:
            stats[label] = {
                "median_s": float(np.median(h)),
                "p05_s": float(np.quantile(h, 0.05)),
                "samples": int(h.size),
            }

    flow, density = _edie(data, dt, x_range, t_end)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.scatter(density, flow, s=6)
    ax.set_xlabel("density [veh/km/lane]")
    ax.set_ylabel("flow [veh/h/lane]")
    ax.set_title(f"{name}: flow-density (Edie, 100 m x 30 s)")
    fig.savefig(out / f"{name}_flow_density.png", dpi=120, bbox_inches="tight")
    plt.close(fig)
    return {
        "headways": stats,
        "headways_by_class": classes,
        "max_flow_veh_h_lane": float(flow.max()) if flow.size else math.nan,
        "max_density_veh_km_lane": float(density.max()) if density.size else math.nan,
        "mean_speed_m_s": float(v.mean()),
    }


def _ring(args, dt, fleet, export_files, length, work, out) -> dict:
    n_edges = 4
    edge_length = args.ring_length / n_edges
    net = ring(args.ring_length, work, n_edges=n_edges)
    vehicles = []
    for i, vtype in enumerate(fleet.vtype):
        at = i * args.ring_length / len(fleet.vtype)
        edge = int(at // edge_length)
        route = " ".join(f"e{(edge + k) % n_edges}" for k in range(n_edges))
        laps = int(args.duration * 40 / args.ring_length) + 2
        vehicles.append(
            f'    <vehicle id="v{i}" type="{vtype}" depart="0" '
            f'departPos="{at - edge * edge_length!r}" departSpeed="0" '
            f'insertionChecks="none"><route edges="{" ".join([route] * laps)}"/>'
            "</vehicle>"
        )
    routes = work / "ring.rou.xml"
    _routes(routes, fleet, length, vehicles)
    n_steps = int(round(args.duration / dt))

    def position_of(road: str, pos: float) -> float:
        return int(road[1:]) * edge_length + pos if road.startswith("e") else math.nan

    result = _simulate(
        _arguments(net, routes, export_files, dt), dt, fleet, n_steps, position_of
    )
    result["components"] = fleet.components
    summary = _figures("ring", result, out, dt, (0.0, args.ring_length), args.duration)
    return {**_counters(result), **summary}


def _highway(args, dt, fleet, export_files, length, work, out, generator) -> dict:
    drop_at = 0.7 * args.highway_length
    net = highway(args.highway_length, 3, work, drop_at=drop_at)
    # Poisson arrivals at a rate rising linearly to --demand over the run.
    rate_max = args.demand / 3600.0
    times, t = [], 0.0
    while True:
        t += float(torch.empty(1).exponential_(1.0, generator=generator)) / rate_max
        if t >= args.duration * 0.8 or len(times) == len(fleet.vtype):
            break
        if float(torch.rand(1, generator=generator)) < t / args.duration:
            times.append(t)
    vehicles = [
        f'    <vehicle id="v{i}" type="{fleet.vtype[i]}" depart="{depart:.1f}" '
        'departLane="best" departSpeed="max"><route edges="h0 h1"/></vehicle>'
        for i, depart in enumerate(times)
    ]
    used = len(times)
    fleet.truncate(used)
    routes = work / "highway.rou.xml"
    _routes(routes, fleet, length, vehicles)
    n_steps = int(round(args.duration / dt))

    def position_of(road: str, pos: float) -> float:
        return {"h0": 0.0, "h1": drop_at}.get(road, math.nan) + pos

    result = _simulate(
        _arguments(net, routes, export_files, dt), dt, fleet, n_steps, position_of
    )
    result["components"] = fleet.components

    def left_lane(x: np.ndarray, lane: np.ndarray) -> np.ndarray:
        return np.where(x < drop_at, lane == 2, lane == 1)

    summary = _figures(
        "highway", result, out, dt, (0.0, drop_at), args.duration, left_lane
    )
    return {"vehicles": used, **_counters(result), **summary}


def _counters(result: dict) -> dict:
    return {k: v for k, v in result.items() if k not in ("data", "components")}


def _markdown(report: dict) -> str:
    lines = [
        "# Learned hybrids in SUMO networks: a mixed fleet",
        "",
        "Fleet (class: run, data set, fraction of the vehicles; the hybrid's model "
        "shares):",
        "",
    ]
    for c in report["fleet"]:
        lines.append(
            f"- {c['label']}: `{c['run']}` ({c['dataset']}), {c['fraction']:.0%}; "
            + ", ".join(f"{k} {v:.1%}" for k, v in c["shares"].items() if v)
            + ". Native in SUMO (exported vTypes): "
            + (", ".join(c["native_models"]) or "none")
            + "; co-simulated (safety layer on): "
            + (", ".join(c["cosim_models"]) or "none")
            + "."
        )
    lines += [
        "",
        "Units: all SI. NGSIM I-80's files are in feet; torchcf converts them on "
        "loading (registry units `ft`), so the NGSIM run was fitted on SI pairs and "
        "its particles' lengths are metres; vehicle length 5 m for both classes "
        "(the registry's), step 0.1 s.",
        "",
        f"Command: `{report['command']}` (simulated time {report['duration_s']:g} s "
        "per scene).",
        "",
        "| scene | vehicles | AV / human | native | co-simulated | mean speed [m/s] "
        "| max flow [veh/h/lane] | max density [veh/km/lane] | collisions (pairs; at "
        "standstill) | emergency braking (vehicles) | safety interventions (steps) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in ("ring", "highway"):
        s = report[name]
        mix = " / ".join(str(n) for n in s["by_class"].values())
        lines.append(
            f"| {name} | {s['vehicles']} | {mix} | {s['native']} | "
            f"{s['cosimulated']} | "
            f"{s['mean_speed_m_s']:.2f} | {s['max_flow_veh_h_lane']:.0f} | "
            f"{s['max_density_veh_km_lane']:.1f} | {s['collisions']['pairs']}; "
            f"{s['collisions']['pairs_at_standstill']} | "
            f"{s['emergency_braking']['vehicles']} | {s['safety_interventions']} |"
        )
    lines += [
        "",
        "Collisions: SUMO's (`--collision.action warn`, `--collision.mingap-factor "
        "0`: bumper contact), counted once per (collider, victim) pair; 'at "
        "standstill': the collider's top speed in contact under 0.1 m/s (the safety "
        "layer stops at bumper contact, its stop spacing being the leader length). "
        "Emergency braking: SUMO's count (braking beyond a native vehicle's "
        "emergencyDecel; co-simulated vehicles run with speed mode 0).",
        "",
        "## Time headways against the data",
        "",
        "Time headway: bumper gap / follower speed, moving vehicles (v > 1 m/s); in "
        "SUMO every vehicle with a leader within 300 m at every 0.1 s step, in the "
        "data every valid step of the run's training pairs (gap > 0: NGSIM's few "
        "overlapping position errors left out). KS: the two-sample "
        "Kolmogorov-Smirnov distance (largest gap between the empirical CDFs; no "
        "p-value: the samples are strongly autocorrelated time series).",
        "",
        "**The comparison is qualitative.** The demo's traffic is not the data's: "
        "CAR MODEL II are ACC platoons driven by a scripted leader on a test track, "
        "NGSIM I-80 is congested, stop-and-go freeway traffic of 2005; the ring "
        "(from rest, one lane, one density) and the highway (a rising demand into a "
        "lane drop) impose their own densities and speeds, and each class here "
        "follows leaders of both classes. Headways depend on speed and density, so "
        "a difference mixes the scene with the models.",
        "",
        "| scene | class | median sim [s] | median data [s] | 5th pct sim / data [s] "
        "| KS distance | samples sim / data |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in ("ring", "highway"):
        for label, h in report[name]["headways_by_class"].items():
            lines.append(
                f"| {name} | {label} | {h['sim_median_s']:.2f} | "
                f"{h['data_median_s']:.2f} | {h['sim_p05_s']:.2f} / "
                f"{h['data_p05_s']:.2f} | {h['ks_distance']:.2f} | "
                f"{h['sim_samples']} / {h['data_samples']} |"
            )
    lines += ["", "Native against co-simulated (median, 5th percentile) [s]:", ""]
    for name in ("ring", "highway"):
        for label, h in report[name]["headways"].items():
            lines.append(
                f"- {name}, {label}: {h['median_s']:.2f}, {h['p05_s']:.2f} "
                f"({h['samples']} samples)"
            )
    lines += [
        "",
        "Figures: " + ", ".join(
            f"`{n}_{k}.png`" for n in ("ring", "highway")
            for k in ("time_space", "headways", "flow_density")
        ),
        "",
    ]  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "runs", nargs="*", metavar="RUN[:FRACTION]",
        help="classes of the fleet, as --fleet (given, they replace its default)",
    )  # fmt: skip
    parser.add_argument(
        "--fleet", nargs="+", default=["runs/paper/carII:0.3", "runs/paper/ngsim:0.7"],
        metavar="RUN:FRACTION",
        help="the classes of the fleet: a run directory and its fraction",
    )  # fmt: skip
    parser.add_argument("--out", default="reports/sumo")
    parser.add_argument("--ring-vehicles", type=count, default=30)
    parser.add_argument("--ring-length", type=positive, default=900.0)
    parser.add_argument("--highway-length", type=positive, default=2500.0)
    parser.add_argument("--demand", type=positive, default=7000.0, help="veh/h")
    parser.add_argument("--duration", type=positive, default=400.0, help="s")
    parser.add_argument("--seed", type=natural, default=0)
    args = parser.parse_args(argv)

    def body() -> int:
        components = []
        for k, (run, fraction) in enumerate(parse_fleet(args.runs or args.fleet)):
            tag = f"c{k}_{Path(run).name}"
            components.append(Component(run, fraction, tag))
        dt, length = components[0].dt, components[0].length
        for c in components[1:]:
            if c.dt != dt or c.length != length:
                raise ConfigError(
                    f"--fleet: {c.run} has dt {c.dt}, length {c.length}; "
                    f"{components[0].run} has {dt}, {length}"
                )
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        generator = torch.Generator().manual_seed(args.seed)
        report = {
            "fleet": [
                {
                    "label": c.label, "run": c.run, "dataset": c.dataset,
                    "fraction": c.fraction, "shares": c.sampler.shares,
                    "native_models": [
                        m for m in c.sampler.model_names if m in MAPPINGS
                    ],
                    "cosim_models": [
                        m for m, share in c.sampler.shares.items()
                        if share and m not in MAPPINGS
                    ],
                }
                for c in components
            ],
            "duration_s": args.duration,
            "command": "python tools/sumo_network_demo.py " + " ".join(
                argv if argv is not None else sys.argv[1:]
            ),
        }  # fmt: skip
        with tempfile.TemporaryDirectory(prefix="torchcf-sumo-demo-") as name:
            work = Path(name)
            files = []
            for c in components:
                path = work / f"{c.tag}.vtypes.add.xml"
                path.write_text(c.export_xml())
                files.append(str(path))
            export_files = ",".join(files)
            for scene in ("ring", "highway"):
                if scene == "ring":
                    fleet = Fleet(components, args.ring_vehicles, generator)
                    summary = _ring(args, dt, fleet, export_files, length, work, out)
                else:
                    n = int(args.demand * args.duration / 3600.0) + 10
                    fleet = Fleet(components, n, generator)
                    summary = _highway(
                        args, dt, fleet, export_files, length, work, out, generator
                    )
                summary.setdefault("vehicles", len(fleet.vtype))
                summary["by_class"] = {
                    c.label: sum(k == i for k in fleet.cls)
                    for i, c in enumerate(components)
                }
                summary["native"] = sum(fleet.native)
                summary["cosimulated"] = len(fleet.native) - sum(fleet.native)
                report[scene] = summary
                print(
                    f"{scene}: {summary['vehicles']} vehicles, collisions "
                    f"{summary['collisions']['vehicles']}, emergency braking "
                    f"{summary['emergency_braking']['vehicles']}, safety "
                    f"interventions {summary['safety_interventions']}",
                    flush=True,
                )
        (out / "network_demo.json").write_text(json.dumps(report, indent=2) + "\n")
        (out / "network_demo.md").write_text(_markdown(report))
        print(f"wrote {out}/network_demo.md")
        return 0

    return run_main(lambda: _leaving_no_empty_folder(body, Path(args.out)))


def _leaving_no_empty_folder(body, out: Path) -> int:
    with no_empty_folder_left(out):
        return body()


if __name__ == "__main__":
    raise SystemExit(main())
