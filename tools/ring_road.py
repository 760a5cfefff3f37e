"""Two learned hybrids on the same ring road: time-space diagrams and wave growth.

The NGSIM I-80 hybrid (human drivers) and the CAR MODEL II hybrid (ACC vehicles)
each drive ``--vehicles`` vehicles on a single-lane ring of ``--vehicles *
--spacing`` metres (Sugiyama et al. 2008's experiment), from the ring's
equilibrium (:func:`torchcf.traffic.ring_initial_state`) with vehicle 0 moved 1 m
back, for ``--duration`` seconds, in ``--scenarios`` rings with independently
drawn vehicles (:mod:`torchcf.traffic`, :class:`torchcf.HybridSampler`, float64).

To explain what the rings do, every particle of each hybrid also drives a
homogeneous platoon of ``--platoon`` identical vehicles behind a leader that
cruises at the ring's equilibrium speed (60 s to settle), then dips by 1 m/s over
4 s: a particle is *string-unstable* there when the last follower's peak speed
deviation exceeds the first follower's.

    python tools/ring_road.py                       # runs/paper/{ngsim,carII}
    python tools/ring_road.py --ngsim runs/ngsim/posterior.pt --carII runs/carII

Writes ``reports/traffic/ring_time_space.png``, ``ring_waves.png``,
``ring_road.json`` and ``README.md``. A missing posterior is a one-line error
(exit 2).
"""

from __future__ import annotations

import argparse
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
from torchcf.files import json_safe  # noqa: E402
from torchcf.traffic.scenarios import platoon, ring_road  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LABELS = {"ngsim": "NGSIM I-80 hybrid", "carII": "CAR MODEL II hybrid"}


def run_ring(sampler: HybridSampler, args) -> dict:
    """The rings of one hybrid and their summary numbers."""
    n_steps = round(args.duration / sampler.dt)
    sampler.sample(
        (args.scenarios, args.vehicles), torch.Generator().manual_seed(args.seed)
    )
    length = args.vehicles * args.spacing
    out = ring_road(sampler, length, n_steps, record_every=args.record_every)
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
        "vehicle_model": model,
    }


def string_stability(sampler: HybridSampler, speed: float, n_followers: int):
    """Per model: particles whose homogeneous platoon amplifies a speed dip."""
    dt = sampler.dt
    settle, dip, ramp, tail = 60.0, 1.0, 4.0, 60.0
    t = torch.arange(round((settle + 2 * ramp + tail) / dt), dtype=torch.float64) * dt
    down = torch.clamp((t - settle) / ramp, 0.0, 1.0)
    up = torch.clamp((t - settle - ramp) / ramp, 0.0, 1.0)
    v_leader = speed - dip * (down - up)  # (T,)
    x_leader = torch.cat((torch.zeros(1), torch.cumsum(v_leader[:-1] * dt, 0)))
    n_particles = sampler.n_particles
    sampler.assign(torch.arange(n_particles)[:, None].expand(-1, n_followers))
    out = platoon(
        sampler,
        x_leader[:, None].expand(-1, n_particles) + 100.0,
        v_leader[:, None].expand(-1, n_particles),
        initial_spacing=10.0 + 1.5 * speed,
    )
    after = t >= settle
    deviation = (out.v[after] - speed).abs().amax(dim=0)  # (P, n)
    ratio = deviation[:, -1] / deviation[:, 0].clamp_min(1e-12)  # (P,)
    collided = out.collided.any(dim=1)  # (P,)
    unstable = collided | ~(ratio <= 1.0)  # NaN counts as unstable
    rows = {}
    for m, name in enumerate(sampler.model_names):
        mine = sampler.particle_model == m
        if bool(mine.any()):
            rows[name] = {
                "particles": int(mine.sum()),
                "amplifying": int((unstable & mine).sum()),
                "collided": int((collided & mine).sum()),
                "median_ratio": float(ratio[mine & ~collided].median())
                if bool((mine & ~collided).any())
                else float("nan"),
            }
    return rows


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


def draw_waves(results: dict, path: Path) -> None:
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.2))
    for key, r in results.items():
        time = r["out"].time.numpy()
        spread = r["spread"].numpy()  # (T', S)
        median = np.nanmedian(spread, axis=1)
        low, high = np.nanpercentile(spread, [25, 75], axis=1)
        (line,) = left.plot(time, median, label=LABELS.get(key, key))
        left.fill_between(time, low, high, color=line.get_color(), alpha=0.2)
        first = np.sort(np.array(r["first_collision_s"]))
        share = np.searchsorted(first, time, side="right") / len(first)
        right.plot(time, share, color=line.get_color(), label=LABELS.get(key, key))
    left.set_yscale("log")
    left.set_xlabel("time [s]")
    left.set_ylabel("speed spread over a ring's vehicles [m/s]")
    left.set_title("wave growth (median and quartiles over rings)")
    right.set_xlabel("time [s]")
    right.set_ylabel("fraction of rings with a collision")
    right.set_ylim(0, 1.02)
    for ax in (left, right):
        ax.grid(alpha=0.3)
        ax.legend()
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


def write_readme(results, stability, args, command, path: Path) -> None:
    lines = [
        "# The learned hybrids on a ring road",
        "",
        f"`{command}`: each hybrid drives "
        f"{args.vehicles} vehicles on a single-lane ring of "
        f"{args.vehicles * args.spacing:g} m ({args.spacing:g} m per vehicle), "
        f"{args.scenarios} rings with independently drawn vehicles, "
        f"{args.duration:g} s at dt = 0.1 s, float64. Start: the ring's own "
        "equilibrium (`torchcf.traffic.ring_initial_state`: every vehicle at the "
        "common speed v* with its own steady spacing; a vehicle that cannot "
        "reach v* at any spacing is the bottleneck that sets v* and takes the "
        "rest of the ring; a vehicle with no steady spacing at v*, whose model "
        "still accelerates one vehicle length behind its leader, starts there), "
        "then vehicle 0 moved 1 m back. Each vehicle keeps its particle (no "
        "redraws). The models are simulated exactly as calibrated (SPEC section "
        "2): no acceleration limits but MPC's, no collision avoidance; a "
        "collision (spacing <= 0) is flagged and the dynamics are left as they "
        "are.",
        "",
        "![time-space diagrams](ring_time_space.png)",
        "",
        "Ring 0 of each hybrid, every vehicle's position against time, coloured "
        "by speed; x marks a vehicle's first collision.",
        "",
        "![wave growth](ring_waves.png)",
        "",
        "Left: the spread (standard deviation) of speed over each ring's "
        "vehicles, median and quartiles over all rings, collided ones included; "
        "right: the fraction of rings with a collision by then.",
        "",
        "| hybrid | v* [m/s] (median over rings) | speed spread at 30 s / 60 s "
        "[m/s] (intact rings) | rings with a collision | median first collision [s] |",
        "|---|---|---|---|---|",
    ]
    for key, r in results.items():
        first = torch.tensor(r["first_collision_s"])
        v_star = float(torch.tensor(r["v_init"]).median())
        lines.append(
            f"| {LABELS.get(key, key)} | {v_star:.1f}"
            f" | {spread_at(r, 30.0):.3g} / {spread_at(r, 60.0):.3g} | "
            f"{r['rings_collided']} / {args.scenarios} | "
            f"{float(first.median()):.0f} |"
        )
    lines += [
        "",
        "Per model (all rings): vehicles, vehicles that collided, and how often "
        "the model's vehicle was (one of) the first to collide in its ring.",
        "",
        "| hybrid | model | vehicles | collided | first to collide |",
        "|---|---|---|---|---|",
    ]
    for key, r in results.items():
        for name, row in r["per_model"].items():
            lines.append(
                f"| {LABELS.get(key, key)} | {name} | {row['vehicles']} | "
                f"{row['collided']} | {row['first_to_collide']} |"
            )
    lines += [
        "",
        f"String stability of each particle alone: a homogeneous platoon of "
        f"{args.platoon} vehicles behind a leader cruising at the ring's v* "
        "(median over rings) that dips by 1 m/s; *amplifying*: the last "
        "follower's peak speed deviation exceeds the first's (or the platoon "
        "collides); ratio: last / first, median over the particles that did not "
        "collide.",
        "",
        "| hybrid | model | particles | amplifying | collided | median ratio |",
        "|---|---|---|---|---|---|",
    ]
    for key, rows in stability.items():
        for name, row in rows.items():
            lines.append(
                f"| {LABELS.get(key, key)} | {name} | {row['particles']} | "
                f"{row['amplifying']} ({row['amplifying'] / row['particles']:.0%}) | "
                f"{row['collided']} | {row['median_ratio']:.3g} |"
            )
    lines += [
        "",
        "Reading it: a mixed ring is string stable only if the damping of some "
        "vehicles outweighs the amplification of others; each learned particle "
        "was fitted to 35-58 s of one follower behind one measured leader, which "
        "does not constrain how it amplifies disturbances along a string, nor "
        "how it behaves far from the speeds and spacings of its data. The "
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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--ngsim", type=Path, default=ROOT / "runs/paper/ngsim/posterior.pt"
    )
    parser.add_argument(
        "--carII", type=Path, default=ROOT / "runs/paper/carII/posterior.pt"
    )
    parser.add_argument("--vehicles", type=int, default=40)
    parser.add_argument("--spacing", type=float, default=25.0, help="[m]")
    parser.add_argument("--duration", type=float, default=300.0, help="[s]")
    parser.add_argument("--scenarios", type=int, default=16)
    parser.add_argument("--platoon", type=int, default=10)
    parser.add_argument("--record-every", type=int, default=5, help="steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
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
    samplers = {}
    for key, path in (("ngsim", args.ngsim), ("carII", args.carII)):
        posterior = path / "posterior.pt" if path.is_dir() else path
        if not posterior.is_file():
            print(f"error: no posterior file {posterior} (--{key})", file=sys.stderr)
            return 2
        try:
            samplers[key] = HybridSampler.from_file(posterior, dtype=torch.float64)
        except ValueError as error:
            print(f"error: {error}", file=sys.stderr)
            return 2

    results, stability = {}, {}
    for key, sampler in samplers.items():
        results[key] = run_ring(sampler, args)
        speed = float(torch.tensor(results[key]["v_init"]).median())
        stability[key] = string_stability(sampler, speed, args.platoon)
        print(
            f"{LABELS[key]}: {results[key]['rings_collided']}/{args.scenarios} rings "
            f"with a collision; particles amplifying a dip: "
            + ", ".join(
                f"{k} {v['amplifying']}/{v['particles']}"
                for k, v in stability[key].items()
            ),
            flush=True,
        )

    args.out.mkdir(parents=True, exist_ok=True)
    draw_time_space(results, args.out / "ring_time_space.png", args)
    draw_waves(results, args.out / "ring_waves.png")
    command = "python tools/ring_road.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])
    )
    summary = {
        "command": command.strip(),
        "settings": {
            k: _shown(v) if isinstance(v, Path) else v for k, v in vars(args).items()
        },
        "rings": {
            key: {
                "v_init": r["v_init"],
                "first_collision_s": r["first_collision_s"],
                "rings_collided": r["rings_collided"],
                "spread_30s": spread_at(r, 30.0),
                "spread_60s": spread_at(r, 60.0),
                "per_model": r["per_model"],
            }
            for key, r in results.items()
        },
        "string_stability": stability,
    }
    (args.out / "ring_road.json").write_text(
        json.dumps(json_safe(summary), indent=2) + "\n"
    )
    write_readme(results, stability, args, command.strip(), args.out / "README.md")
    print(f"wrote {_shown(args.out)}/: ring_time_space.png, ring_waves.png, README.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
