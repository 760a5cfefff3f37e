"""A learned hybrid deployed in SUMO networks: a ring and a multi-lane highway.

Every vehicle draws a particle of the run's hybrid (uniformly over its particles,
so each model drives its share ``beta_m`` of the fleet). A vehicle whose particle
is of a model SUMO has (IDM) drives as its exported vType, SUMO's own car
following (``python -m torchcf.sumo export``); every other vehicle is
co-simulated (:class:`torchcf.sumo.CoSimulation`, one sampler call per step for
all of them, torchcf's safety layer on). Lane changes are SUMO's (LC2013).

- **ring**: ``--ring-vehicles`` vehicles evenly spaced on a single-lane ring of
  ``--ring-length`` metres, from rest (Sugiyama et al. 2008's experiment);
- **highway**: a 3-lane road of ``--highway-length`` metres whose right lane ends
  at 70 % of it, fed by a demand rising linearly to ``--demand`` vehicles per
  hour (Poisson arrivals).

Measured per scene: the time-space diagram, the time headway distribution (bumper
gap / speed, moving vehicles) of native and co-simulated vehicles, flow and
density by Edie's definitions on 100 m x 30 s cells, and SUMO's counters:
collisions (``--collision.mingap-factor 0``: bumper contact only), emergency
braking, and the co-simulation's safety-layer interventions.

    python tools/sumo_network_demo.py runs/paper/carII --out reports/sumo

Writes ``OUT/network_demo.{md,json}`` and ``OUT/{ring,highway}_{time_space,
headways,flow_density}.png``. Needs ``pip install -e '.[sumo]'``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchcf.cli import run_main  # noqa: E402
from torchcf.rundir import RunDir  # noqa: E402
from torchcf.sumo import backend  # noqa: E402
from torchcf.sumo.cosim import CoSimulation  # noqa: E402
from torchcf.sumo.export import (  # noqa: E402
    MAPPINGS,
    VTYPES_FILE,
    export_hybrid,
    run_constants,
    write_export,
)
from torchcf.sumo.network import highway, ring  # noqa: E402
from torchcf.traffic import HybridSampler  # noqa: E402

COSIM_TYPE = "torchcf_cosim"
#: Edie's cells [m], [s].
CELL_LENGTH, CELL_TIME = 100.0, 30.0


class Fleet:
    """The drawn vehicles: which is native (its vType) and which co-simulated."""

    def __init__(self, sampler: HybridSampler, n: int, generator: torch.Generator):
        drawn = torch.randint(0, sampler.n_particles, (n,), generator=generator)
        self.model = [
            sampler.model_names[int(m)] for m in sampler.particle_model[drawn]
        ]
        rows = sampler.particle_row[drawn].tolist()
        self.native = [m in MAPPINGS for m in self.model]
        self.vtype = [
            f"{m}_{r}" if native else COSIM_TYPE
            for m, r, native in zip(self.model, rows, self.native, strict=True)
        ]
        self.cosim_index = [i for i, native in enumerate(self.native) if not native]
        self.particles = drawn[self.cosim_index]


def _routes(path: Path, length: float, vehicles: list[str]) -> None:
    path.write_text(
        "<routes>\n"
        f'    <vType id="{COSIM_TYPE}" length="{length!r}" minGap="0" '
        'maxSpeed="55.56" speedFactor="1" speedDev="0"/>\n'
        + "\n".join(vehicles)
        + "\n</routes>\n"
    )


def _arguments(net: Path, routes: Path, additional: Path, dt: float) -> list[str]:
    return [
        "--net-file", str(net), "--route-files", str(routes),
        "--additional-files", str(additional),
        "--step-length", repr(dt), "--step-method.ballistic", "true",
        "--collision.action", "warn", "--collision.mingap-factor", "0",
        "--time-to-teleport", "-1", "--no-step-log", "true", "--no-warnings", "true",
        "--seed", "0",
    ]  # fmt: skip


def _simulate(arguments, sampler, fleet, n_steps, position_of) -> dict:
    """Run SUMO with the fleet; record every vehicle at every step."""
    names = [f"v{i}" for i in range(len(fleet.vtype))]
    cosim_ids = [names[i] for i in fleet.cosim_index]
    native = dict(zip(names, fleet.native, strict=True))
    records = []  # (t, x, v, lane, headway, native)
    collided, emergency = set(), set()
    impact: dict[tuple[str, str], float] = {}  # (collider, victim) -> its top speed
    collision_steps = emergency_steps = 0
    with backend.running(arguments) as sumo:
        vehicle = sumo.vehicle
        cosim = None
        if cosim_ids:
            sampler.assign(fleet.particles)
            cosim = CoSimulation(sumo, sampler, cosim_ids)
        for step in range(n_steps):
            if cosim is not None:
                cosim.command()
            sumo.simulationStep()
            if cosim is not None:
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
            t = (step + 1) * sampler.dt
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
                    )
                )
        interventions = int(cosim.interventions.sum()) if cosim is not None else 0
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
    t, x, v, lane, headway, native = data.T
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

    fig, ax = plt.subplots(figsize=(6, 4))
    bins = np.linspace(0, 5, 51)
    stats = {}
    for flag, label in ((1.0, "native (SUMO IDM)"), (0.0, "co-simulated")):
        h = headway[(native == flag) & np.isfinite(headway)]
        if h.size:
            ax.hist(h, bins=bins, density=True, alpha=0.6, label=label)
            stats[label] = {
                "median_s": float(np.median(h)),
                "p05_s": float(np.quantile(h, 0.05)),
                "samples": int(h.size),
            }
    ax.set_xlabel("time headway [s]")
    ax.set_ylabel("density")
    ax.legend()
    ax.set_title(f"{name}: headway distribution")
    fig.savefig(out / f"{name}_headways.png", dpi=120, bbox_inches="tight")
    plt.close(fig)

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
        "max_flow_veh_h_lane": float(flow.max()) if flow.size else math.nan,
        "max_density_veh_km_lane": float(density.max()) if density.size else math.nan,
        "mean_speed_m_s": float(v.mean()),
    }


def _ring(args, sampler, fleet, export_file, length, work, out) -> dict:
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
    _routes(routes, length, vehicles)
    n_steps = int(round(args.duration / sampler.dt))

    def position_of(road: str, pos: float) -> float:
        return int(road[1:]) * edge_length + pos if road.startswith("e") else math.nan

    result = _simulate(
        _arguments(net, routes, export_file, sampler.dt), sampler, fleet, n_steps,
        position_of,
    )  # fmt: skip
    summary = _figures(
        "ring", result, out, sampler.dt, (0.0, args.ring_length), args.duration
    )
    return {**{k: v for k, v in result.items() if k != "data"}, **summary}


def _highway(args, sampler, fleet, export_file, length, work, out, generator) -> dict:
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
    fleet.vtype = fleet.vtype[:used]
    fleet.native = fleet.native[:used]
    keep = [k for k, i in enumerate(fleet.cosim_index) if i < used]
    fleet.cosim_index = [fleet.cosim_index[k] for k in keep]
    fleet.particles = fleet.particles[keep]
    routes = work / "highway.rou.xml"
    _routes(routes, length, vehicles)
    n_steps = int(round(args.duration / sampler.dt))

    def position_of(road: str, pos: float) -> float:
        return {"h0": 0.0, "h1": drop_at}.get(road, math.nan) + pos

    result = _simulate(
        _arguments(net, routes, export_file, sampler.dt), sampler, fleet, n_steps,
        position_of,
    )  # fmt: skip

    def left_lane(x: np.ndarray, lane: np.ndarray) -> np.ndarray:
        return np.where(x < drop_at, lane == 2, lane == 1)

    summary = _figures(
        "highway", result, out, sampler.dt, (0.0, drop_at), args.duration, left_lane
    )
    return {"vehicles": used, **{k: v for k, v in result.items() if k != "data"},
            **summary}  # fmt: skip


def _markdown(report: dict) -> str:
    lines = [
        "# The learned hybrid in SUMO networks",
        "",
        f"Run `{report['run']}` ({report['dataset']}); shares "
        + ", ".join(f"{k} {v:.1%}" for k, v in report["shares"].items() if v)
        + ". Natively in SUMO (exported vTypes): "
        + ", ".join(report["native_models"])
        + "; co-simulated (safety layer on): "
        + ", ".join(report["cosim_models"])
        + ".",
        "",
        f"Command: `{report['command']}`",
        "",
        "| scene | vehicles | native | co-simulated | mean speed [m/s] | max flow "
        "[veh/h/lane] | max density [veh/km/lane] | collisions (pairs; at "
        "standstill) | emergency braking (vehicles) | safety interventions (steps) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in ("ring", "highway"):
        s = report[name]
        lines.append(
            f"| {name} | {s['vehicles']} | {s['native']} | {s['cosimulated']} | "
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
    ]
    lines += ["", "Headways (median, 5th percentile) [s]:", ""]
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
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", nargs="?", default="runs/paper/carII")
    parser.add_argument("--out", default="reports/sumo")
    parser.add_argument("--ring-vehicles", type=int, default=30)
    parser.add_argument("--ring-length", type=float, default=900.0)
    parser.add_argument("--highway-length", type=float, default=2500.0)
    parser.add_argument("--demand", type=float, default=7000.0, help="veh/h")
    parser.add_argument("--duration", type=float, default=400.0, help="s")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    def body() -> int:
        cfg, posterior, _ = RunDir(args.run).load_run()
        dt, length = run_constants(cfg, posterior)
        sampler = HybridSampler.from_posterior(
            posterior, dt=dt, leader_length=length, dtype=torch.float64
        )
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        generator = torch.Generator().manual_seed(args.seed)
        report = {
            "run": args.run,
            "dataset": posterior.dataset,
            "shares": sampler.shares,
            "native_models": [m for m in sampler.model_names if m in MAPPINGS],
            "cosim_models": [
                m for m, share in sampler.shares.items() if share and m not in MAPPINGS
            ],
            "command": "python tools/sumo_network_demo.py " + " ".join(
                argv if argv is not None else sys.argv[1:]
            ),
        }  # fmt: skip
        with tempfile.TemporaryDirectory(prefix="torchcf-sumo-demo-") as name:
            work = Path(name)
            write_export(export_hybrid(posterior, dt=dt, length=length), work)
            export_file = work / VTYPES_FILE
            for scene in ("ring", "highway"):
                n = args.ring_vehicles if scene == "ring" else 100_000
                if scene == "highway":
                    n = int(args.demand * args.duration / 3600.0) + 10
                fleet = Fleet(sampler, n, generator)
                if scene == "ring":
                    summary = _ring(
                        args, sampler, fleet, export_file, length, work, out
                    )
                else:
                    summary = _highway(
                        args, sampler, fleet, export_file, length, work, out, generator
                    )
                counts = defaultdict(int)
                for m in fleet.model:
                    counts[m] += 1
                summary.setdefault("vehicles", len(fleet.vtype))
                summary["native"] = sum(fleet.native)
                summary["cosimulated"] = len(fleet.cosim_index)
                report[scene] = summary
                print(
                    f"{scene}: {summary['vehicles']} vehicles, collisions "
                    f"{summary['collisions']['vehicles']}, emergency braking "
                    f"{summary['emergency_braking']['vehicles']}, safety "
                    f"interventions {summary['safety_interventions']}"
                )
        (out / "network_demo.json").write_text(json.dumps(report, indent=2) + "\n")
        (out / "network_demo.md").write_text(_markdown(report))
        print(f"wrote {out}/network_demo.md")
        return 0

    return run_main(body)


if __name__ == "__main__":
    raise SystemExit(main())
