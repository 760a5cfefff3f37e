"""Two learned hybrids in traffic: rings, braking platoons and the plausibility battery.

The NGSIM I-80 hybrid (human drivers) and the CAR MODEL II hybrid (ACC vehicles)
each drive ``--vehicles`` vehicles on a single-lane ring of ``--vehicles *
--spacing`` metres (Sugiyama et al. 2008's experiment), from the ring's
equilibrium (:func:`torchcf.traffic.ring_initial_state`) with vehicle 0 moved 1 m
back, for ``--duration`` seconds (default one hour), in ``--scenarios`` rings
with independently drawn vehicles (:mod:`torchcf.traffic`,
:class:`torchcf.HybridSampler`, float64); and ``--scenarios`` platoons of
``--platoon`` drawn vehicles behind a leader that cruises at ``--brake-speed``
and brakes at ``--brake-decel`` to a stop. Each scene runs twice: the learned
models alone (``safety=None``) and with torchcf.traffic's default safety layer
(:class:`torchcf.traffic.SafetyLayer`), whose interventions are counted per
model.

To explain what the scenes do, every particle of each hybrid also goes through
the plausibility battery (:func:`torchcf.traffic.check_plausibility`: emergency
braking at 4, 6 and 8 m/s^2, stop-and-go, a cut-in, a standstill start, a
homogeneous platoon's string-stability ratio, an equilibrium) at the data's
95th-percentile leader speed (needs ``TORCHCF_DATA``, or ``--battery-speed``).

    python tools/ring_road.py                       # runs/paper/{ngsim,carII}
    python tools/ring_road.py --ngsim runs/ngsim/posterior.pt --carII runs/carII

Writes ``reports/traffic/ring_time_space.png``, ``ring_waves.png``,
``ring_road.json`` and ``README.md``. A missing posterior is a one-line error
(exit 2).
"""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from torchcf import HybridSampler  # noqa: E402
from torchcf.data import DataError, load_pairs  # noqa: E402
from torchcf.posterior import Posterior  # noqa: E402
from torchcf.system.console import OneLineParser, count, natural, positive, run_main  # noqa: E402
from torchcf.system.files import json_safe  # noqa: E402
from torchcf.traffic import (  # noqa: E402
    DEFAULT_SAFETY,
    Battery,
    battery_speed,
    interventions_per_model,
)
from torchcf.traffic.battery import (  # noqa: E402
    braking_leader,
    leader_positions,
    plausibility_by_model,
)
from torchcf.traffic.scenarios import platoon, ring_road  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LABELS = {"ngsim": "NGSIM I-80 hybrid", "carII": "CAR MODEL II hybrid"}


def run_ring(sampler: HybridSampler, args, safety) -> dict:
    """The rings of one hybrid and their summary numbers."""
    n_steps = round(args.duration / sampler.dt)
    sampler.sample(
        (args.scenarios, args.vehicles), torch.Generator().manual_seed(args.seed)
    )
    length = args.vehicles * args.spacing
    out = ring_road(
        sampler, length, n_steps, record_every=args.record_every, safety=safety
    )
    collided_at = out.collision_step.double() * sampler.dt  # (S, n) [s]
    first = torch.where(out.collided, collided_at, torch.inf).amin(dim=1)  # (S,)
    spread = out.v.std(dim=2)  # (T', S): speed spread over each ring's vehicles
    model = sampler.vehicle_model
    per_model = {}
    for m, name in enumerate(sampler.model_names):
        mine = model == m
        if bool(mine.any()):
            per_model[name] = {
                "vehicles": int(mine.sum()),
                "collided": int((out.collided & mine).sum()),
                "first_to_collide": int(
                    (out.collided & mine & (collided_at == first[:, None])).sum()
                ),
            }
    return {
        "out": out,
        "length": length,
        "v_init": out.v[0, :, 0].tolist(),
        "first_collision_s": first.tolist(),
        "rings_collided": int((~out.valid).sum()),
        "spread": spread,
        "per_model": per_model,
        "interventions": interventions_per_model(
            model, out.interventions, sampler.model_names, out.interventions_moving
        ),
        "vehicle_model": model,
    }


def braking_platoons(sampler: HybridSampler, args, safety) -> dict:
    """``--scenarios`` platoons of ``--platoon`` drawn vehicles behind a leader
    that brakes to a stop; each follower starts 10 m + 1.5 s behind the one
    ahead at the leader's speed and has 30 s to settle."""
    sampler.sample(
        (args.scenarios, args.platoon), torch.Generator().manual_seed(args.seed + 1)
    )
    v_leader = braking_leader(
        args.brake_speed, args.brake_decel, sampler.dt, cruise=30.0, stand=20.0
    )
    x_leader = leader_positions(v_leader, sampler.dt)
    expand = (-1, args.scenarios)
    out = platoon(
        sampler,
        x_leader[:, None].expand(*expand),
        v_leader[:, None].expand(*expand),
        record_every=None,
        safety=safety,
    )
    model = sampler.vehicle_model
    return {
        "platoons_collided": int((~out.valid).sum()),
        "vehicles_collided": {
            name: int((out.collided & (model == m)).sum())
            for m, name in enumerate(sampler.model_names)
            if bool((model == m).any())
        },
        "interventions": interventions_per_model(
            model, out.interventions, sampler.model_names, out.interventions_moving
        ),
    }


def plausibility(sampler: HybridSampler, speed: float) -> dict:
    """Per model: the battery's shares over the hybrid's particles (as JSON)."""
    battery = Battery(speed=speed, dt=sampler.dt, leader_length=sampler.leader_length)
    particles = {model: sampler.particles(model.name) for model in sampler.models}
    return {
        name: summary.to_json()
        for name, summary in plausibility_by_model(particles, battery).items()
    }


def draw_time_space(results: dict, path: Path, args) -> None:
    fig, axes = plt.subplots(1, len(results), figsize=(6.5 * len(results), 5.2))
    axes = np.atleast_1d(axes)
    v_max = max(float(r["out"].v[:, 0].max()) for r in results.values())
    norm = plt.Normalize(0.0, max(v_max, 1.0))
    for ax, (key, r) in zip(axes, results.items(), strict=True):
        out = r["out"]
        time = out.time.numpy()
        for i in range(args.vehicles):
            x = out.x[:, 0, i].numpy()
            v = out.v[:, 0, i].numpy()
            points = np.stack((time, x), axis=1)
            segments = np.stack((points[:-1], points[1:]), axis=1)
            # No segment across the wrap (x jumps from L back to 0).
            keep = np.diff(x) > -0.5 * r["length"]
            lines = LineCollection(
                segments[keep], cmap="RdYlGn", norm=norm, linewidths=0.8
            )
            lines.set_array(v[:-1][keep])
            ax.add_collection(lines)
        hit = out.collided[0]
        if bool(hit.any()):
            step = out.collision_step[0, hit]
            record = torch.clamp(step // args.record_every, max=len(time) - 1)
            ax.plot(
                time[record.numpy()],
                out.x[record, 0, hit.nonzero().squeeze(1)].numpy(),
                "kx",
                markersize=7,
                label="collision",
            )
            ax.legend(loc="upper right")
        ax.set_xlim(0, time[-1])
        ax.set_ylim(0, r["length"])
        ax.set_xlabel("time [s]")
        ax.set_ylabel("position on the ring [m]")
        ax.set_title(
            f"{LABELS.get(key, key)}: {args.vehicles} vehicles, {r['length']:g} m"
        )
    fig.colorbar(
        plt.cm.ScalarMappable(norm=norm, cmap="RdYlGn"), ax=axes, label="speed [m/s]"
    )
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def draw_waves(results: dict, alone: dict, path: Path) -> None:
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.2))
    for key, r in results.items():
        time = r["out"].time.numpy()
        spread = r["spread"].numpy()  # (T', S)
        median = np.nanmedian(spread, axis=1)
        low, high = np.nanpercentile(spread, [25, 75], axis=1)
        label = LABELS.get(key, key)
        (line,) = left.plot(time, median, label=f"{label}, with the layer")
        left.fill_between(time, low, high, color=line.get_color(), alpha=0.2)
        raw = np.nanmedian(alone[key]["spread"].numpy(), axis=1)
        left.plot(time, raw, "--", color=line.get_color(), label=f"{label}, alone")
        for rings, style, what in (
            (r, "-", "with the layer"),
            (alone[key], "--", "alone"),
        ):
            first = np.sort(np.array(rings["first_collision_s"]))
            share = np.searchsorted(first, time, side="right") / len(first)
            right.plot(
                time, share, style, color=line.get_color(), label=f"{label}, {what}"
            )
    left.set_yscale("log")
    left.set_xlabel("time [s]")
    left.set_ylabel("speed spread over a ring's vehicles [m/s]")
    left.set_title("wave growth (median and quartiles over rings)")
    right.set_xlabel("time [s]")
    right.set_ylabel("fraction of rings with a collision")
    right.set_ylim(0, 1.02)
    for ax in (left, right):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)


def spread_at(r: dict, seconds: float) -> float:
    """Median over rings of the speed spread at ``seconds`` (rings intact then)."""
    time = r["out"].time
    k = int(torch.searchsorted(time, torch.tensor(seconds, dtype=time.dtype)))
    k = min(k, len(time) - 1)
    intact = torch.tensor(r["first_collision_s"]) > float(time[k])
    if not bool(intact.any()):
        return float("nan")
    return float(r["spread"][k, intact].median())


def write_readme(report: dict, args, command: str, path: Path) -> None:
    rings, alone = report["rings"], report["rings_alone"]
    lines = [
        "# The learned hybrids in traffic",
        "",
        f"`{command}`; torch {torch.__version__}, {args.threads} threads. The "
        "hybrids: `--ngsim` and `--carII` posteriors "
        f"({', '.join(f'{k}: {v}' for k, v in report['posteriors'].items())}).",
        "",
        "## Rings",
        "",
        f"Each hybrid drives {args.vehicles} vehicles on a single-lane ring of "
        f"{args.vehicles * args.spacing:g} m ({args.spacing:g} m per vehicle), "
        f"{args.scenarios} rings with independently drawn vehicles, "
        f"{args.duration:g} s at dt = 0.1 s, float64. Start: the ring's own "
        "equilibrium (`torchcf.traffic.ring_initial_state`: every vehicle at the "
        "common speed v* with its own steady spacing; a vehicle that cannot "
        "reach v* at any spacing is the bottleneck that sets v* and takes the "
        "rest of the ring; a vehicle with no steady spacing at v*, whose model "
        "still accelerates one vehicle length behind its leader, starts there), "
        "then vehicle 0 moved 1 m back. Each vehicle keeps its particle (no "
        "redraws). Every ring runs twice with the same vehicles: the learned "
        "models alone, exactly as calibrated (SPEC section 2: no acceleration "
        "limits but MPC's; a collision, spacing <= 0, is flagged and the "
        "dynamics are left as they are), and with torchcf.traffic's default "
        "safety layer (`torchcf.traffic.SafetyLayer`: Gipps' safe speed, "
        f"braking up to {DEFAULT_SAFETY.max_decel:g} m/s^2, assuming the leader "
        f"brakes up to {DEFAULT_SAFETY.leader_decel:g} m/s^2, keeping one "
        "leader length front to front at a stop).",
        "",
        "![time-space diagrams](ring_time_space.png)",
        "",
        "Ring 0 of each hybrid with the safety layer, every vehicle's position "
        "against time, coloured by speed; x marks a vehicle's first collision.",
        "",
        "![wave growth](ring_waves.png)",
        "",
        "Left: the spread (standard deviation) of speed over each ring's "
        "vehicles, median and quartiles over all rings (solid: with the layer; "
        "dashed: the models alone); right: the fraction of rings with a "
        "collision by then.",
        "",
        "| hybrid | v* [m/s] (median over rings) | rings with a collision: "
        "models alone / with the layer | median first collision, alone [s] | "
        "layer's interventions per vehicle: all / while moving |",
        "|---|---|---|---|---|",
    ]
    for key, r in rings.items():
        a = alone[key]
        first = torch.tensor(a["first_collision_s"])
        v_star = float(torch.tensor(r["v_init"]).median())
        vehicles = sum(row["vehicles"] for row in r["interventions"].values())
        total, moving = (
            sum(row[k] * row["vehicles"] for row in r["interventions"].values())
            for k in ("per_vehicle", "per_vehicle_moving")
        )
        lines.append(
            f"| {LABELS.get(key, key)} | {v_star:.1f} | "
            f"{a['rings_collided']} / {r['rings_collided']} of {args.scenarios} | "
            f"{float(first.median()):.0f} | {total / max(vehicles, 1):.1f} / "
            f"{moving / max(vehicles, 1):.1f} |"
        )
    lines += [
        "",
        "Per model: vehicles, vehicles that collided with the models alone, and "
        "with the layer the share of the model's vehicles it overrode at least "
        "once and its interventions (steps of 0.1 s) per vehicle; 'while moving' "
        "counts only the steps a vehicle drove faster than 0.1 m/s (the others "
        "hold a stopped vehicle that creeps forward at its leader's bumper, as "
        "SPEC's IDM, whose s0 is front to front, does).",
        "",
        "| hybrid | model | vehicles | collided alone | overridden vehicles: all "
        "/ while moving | interventions per vehicle: all / while moving |",
        "|---|---|---|---|---|---|",
    ]
    for key, r in rings.items():
        for name, row in r["interventions"].items():
            lines.append(
                f"| {LABELS.get(key, key)} | {name} | {row['vehicles']} | "
                f"{alone[key]['per_model'][name]['collided']} | "
                f"{row['vehicles_overridden']:.1%} / "
                f"{row['vehicles_overridden_moving']:.1%} | "
                f"{row['per_vehicle']:.1f} / {row['per_vehicle_moving']:.1f} |"
            )
    lines += [
        "",
        "## Emergency braking",
        "",
        f"{args.scenarios} platoons of {args.platoon} vehicles drawn from each "
        f"hybrid follow a leader that cruises at {args.brake_speed:g} m/s for 30 s "
        f"and brakes at {args.brake_decel:g} m/s^2 to a stop; the followers start "
        "10 m + 1.5 s x speed apart at the leader's speed.",
        "",
        "| hybrid | platoons with a collision: alone / with the layer | "
        "vehicles collided alone, per model | interventions per vehicle, per "
        "model: all / while moving |",
        "|---|---|---|---|",
    ]
    for key, b in report["braking"].items():
        a = report["braking_alone"][key]
        collided = ", ".join(f"{k} {v}" for k, v in a["vehicles_collided"].items())
        overrides = ", ".join(
            f"{k} {v['per_vehicle']:.1f} / {v['per_vehicle_moving']:.1f}"
            for k, v in b["interventions"].items()
        )
        lines.append(
            f"| {LABELS.get(key, key)} | {a['platoons_collided']} / "
            f"{b['platoons_collided']} of {args.scenarios} | {collided} | "
            f"{overrides} |"
        )
    speeds = ", ".join(
        f"{LABELS.get(k, k)} {v:.1f} m/s" for k, v in report["battery_speed"].items()
    )
    lines += [
        "",
        "## The plausibility battery",
        "",
        "Every particle of each hybrid alone, the learned model without a "
        "safety layer (`torchcf.traffic.check_plausibility`), at the data's "
        "95th-percentile leader speed "
        f"({speeds}): "
        "the share of particles that collide with a leader braking to a stop "
        "at 4 / 6 / 8 m/s^2, in stop-and-go, after a cut-in at 0.5 s net time "
        "gap 3 m/s slower, or when the leader pulls away from standstill; that "
        "amplify a speed dip in a homogeneous platoon of 10 (ratio per vehicle "
        "> 1); that have no equilibrium at some speed up to the battery's; and "
        "the median least time to collision.",
        "",
        "| hybrid | model | particles | collided | brake 4 / 6 / 8 | stop-and-go | "
        "cut-in | standstill | string-unstable (untested) | no equilibrium | "
        "median min TTC [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, rows in report["battery"].items():
        for name, row in rows.items():
            per = row["per_scenario"]
            brakes = " / ".join(f"{per[k]:.0%}" for k in per if k.startswith("brake_"))
            ttc = row["min_ttc_median"]
            lines.append(
                f"| {LABELS.get(key, key)} | {name} | {row['n_particles']} | "
                f"{row['collided']:.0%} | {brakes} | {per['stop_and_go']:.0%} | "
                f"{per['cut_in']:.0%} | {per['standstill']:.0%} | "
                f"{row['string_unstable']:.0%} ({row['string_untested']:.0%}) | "
                f"{row['no_equilibrium']:.0%} | "
                f"{'-' if ttc is None else f'{ttc:.2f}'} |"
            )
    lines += [
        "",
        "Reading it: each learned particle was fitted to 35-58 s of one follower "
        "behind one measured leader, which does not constrain how it amplifies "
        "disturbances along a string, nor how it behaves far from the speeds "
        "and spacings of its data; the battery shows where it is implausible "
        "and the layer bounds it in simulation. An intervention is a step of "
        "0.1 s the layer overrode; most of IDM's are standing in a jam: SPEC's "
        "IDM measures its standstill gap s0 (0.5-3 m) front to front, without "
        "the leader length, so a stopped IDM vehicle creeps up to 0.5-3 m behind "
        "its leader's front bumper, and the layer holds it one leader length "
        "back at every such step (on CAR MODEL II's rings, 92 % of IDM's "
        "overrides over the first 1200 s came at speeds under 1 m/s). The "
        "numbers above are measured, not assumed; rerun the tool to regenerate "
        "them.",
        "",
    ]
    path.write_text("\n".join(lines))


def _shown(path: Path) -> str:
    """A path relative to the checkout where it lies inside it."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--ngsim", type=Path, default=ROOT / "runs/paper/ngsim/posterior.pt"
    )
    parser.add_argument(
        "--carII", type=Path, default=ROOT / "runs/paper/carII/posterior.pt"
    )
    parser.add_argument("--vehicles", type=count, default=40)
    parser.add_argument("--spacing", type=positive, default=25.0, help="[m]")
    parser.add_argument("--duration", type=positive, default=3600.0, help="[s]")
    parser.add_argument("--scenarios", type=count, default=16)
    parser.add_argument("--platoon", type=count, default=10)
    parser.add_argument("--brake-speed", type=positive, default=20.0, help="[m/s]")
    parser.add_argument("--brake-decel", type=positive, default=6.0, help="[m/s^2]")
    parser.add_argument(
        "--battery-speed",
        type=positive,
        default=None,
        help="[m/s]; default: the data's 95th-percentile leader speed",
    )
    parser.add_argument("--record-every", type=count, default=5, help="steps")
    parser.add_argument("--seed", type=natural, default=0)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--out", type=Path, default=ROOT / "reports/traffic")
    args = parser.parse_args(argv)
    if args.vehicles < 2 or args.scenarios < 1 or args.platoon < 2:
        print(
            "error: need --vehicles >= 2, --scenarios >= 1, --platoon >= 2",
            file=sys.stderr,
        )
        return 2
    if not (args.spacing > 1.0 and args.duration > 0 and args.record_every >= 1):
        print(
            "error: need --spacing > 1 m, --duration > 0, --record-every >= 1",
            file=sys.stderr,
        )
        return 2
    torch.set_num_threads(args.threads)
    samplers, speeds, posteriors = {}, {}, {}
    for key, path in (("ngsim", args.ngsim), ("carII", args.carII)):
        posterior = path / "posterior.pt" if path.is_dir() else path
        if not posterior.is_file():
            print(f"error: no posterior file {posterior} (--{key})", file=sys.stderr)
            return 2
        try:
            samplers[key] = HybridSampler.from_file(posterior, dtype=torch.float64)
            speeds[key] = args.battery_speed or data_speed(posterior)
        except (ValueError, DataError) as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
        posteriors[key] = _provenance(posterior)

    report = {"posteriors": posteriors, "battery_speed": speeds}
    for part in ("rings", "rings_alone", "braking", "braking_alone", "battery"):
        report[part] = {}
    for key, sampler in samplers.items():
        for suffix, safety in (("", DEFAULT_SAFETY), ("_alone", None)):
            report["rings" + suffix][key] = run_ring(sampler, args, safety)
            report["braking" + suffix][key] = braking_platoons(sampler, args, safety)
        report["battery"][key] = plausibility(sampler, speeds[key])
        print(
            f"{LABELS[key]}: rings with a collision "
            f"{report['rings_alone'][key]['rings_collided']} alone, "
            f"{report['rings'][key]['rings_collided']} with the layer; braking "
            f"platoons {report['braking_alone'][key]['platoons_collided']} / "
            f"{report['braking'][key]['platoons_collided']}",
            flush=True,
        )

    args.out.mkdir(parents=True, exist_ok=True)
    draw_time_space(report["rings"], args.out / "ring_time_space.png", args)
    draw_waves(report["rings"], report["rings_alone"], args.out / "ring_waves.png")
    command = "python tools/ring_road.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])
    )
    summary = {
        "command": command.strip(),
        "settings": {
            k: _shown(v) if isinstance(v, Path) else v for k, v in vars(args).items()
        },
        **{
            part: {key: _ring_json(r) for key, r in report[part].items()}
            for part in ("rings", "rings_alone")
        },
        **{part: report[part] for part in ("braking", "braking_alone", "battery")},
        "battery_speed": speeds,
    }
    (args.out / "ring_road.json").write_text(
        json.dumps(json_safe(summary), indent=2) + "\n"
    )
    write_readme(report, args, command.strip(), args.out / "README.md")
    print(f"wrote {_shown(args.out)}/: ring_time_space.png, ring_waves.png, README.md")
    return 0


def _provenance(posterior: Path) -> str:
    """The posterior's path and, from the run's config.json, how it was trained."""
    config = posterior.parent / "config.json"
    if not config.is_file():
        return _shown(posterior)
    abc = json.loads(config.read_text()).get("abc", {})
    return (
        f"{_shown(posterior)}, {abc.get('n_particles', '?'):,} particles per model, "
        f"{abc.get('method', 'rejection')}"
    )


def data_speed(posterior: Path) -> float:
    """The battery's speed from the posterior's training data (named data sets
    through ``TORCHCF_DATA``)."""
    name = Posterior.load(posterior).dataset
    pairs = load_pairs(name, split="train", download=False)
    return battery_speed(pairs.v_lead, pairs.mask)


def _ring_json(r: dict) -> dict:
    return {
        "v_init": r["v_init"],
        "first_collision_s": r["first_collision_s"],
        "rings_collided": r["rings_collided"],
        "spread_30s": spread_at(r, 30.0),
        "spread_60s": spread_at(r, 60.0),
        "per_model": r["per_model"],
        "interventions": r["interventions"],
    }


if __name__ == "__main__":
    raise SystemExit(run_main(main))
