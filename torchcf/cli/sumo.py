"""``torchcf sumo export RUN --out DIR`` and ``torchcf sumo verify RUN [--out
DIR]``: the learned hybrid in Eclipse SUMO.

- ``export``: the hybrid's particles of the models SUMO has (IDM) as a SUMO
  additional file ``DIR/hybrid.vtypes.add.xml`` (a ``vTypeDistribution``, one
  ``vType`` per particle) and ``DIR/export.json`` (what it carries, what it does
  not and why, the share of the hybrid); :mod:`torchcf.sumo.export`.
- ``verify``: the run's test split replayed in SUMO, followers driven by the
  exported vTypes and by co-simulation, scored with torchcf's metrics beside
  torchcf's own rollout: ``DIR/verify.json`` and ``verify.md`` (default
  ``DIR = RUN/sumo``); :mod:`torchcf.sumo.verify`.

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 a run that is not trained, a
corrupted file, bad arguments, SUMO not installed (the message names the extra
``torchcf[sumo]``) or refusing its input (one line on stderr, no traceback);
130 interrupted.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from ..runs.directory import RunDir
from ..sumo.export import EMERGENCY_DECEL, export_hybrid, run_constants, write_export
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    count,
    folder,
    positive,
    run_main,
)


def _parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        formatter_class=DefaultsHelpFormatter,
        prog="torchcf sumo",
        description="The learned hybrid in Eclipse SUMO.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    export = commands.add_parser(
        "export",
        formatter_class=DefaultsHelpFormatter,
        help="write the hybrid's SUMO vTypes",
        description="Write the hybrid's particles of the models SUMO has (IDM) as "
        "a vTypeDistribution: OUT/hybrid.vtypes.add.xml and OUT/export.json.",
    )
    export.add_argument("run_dir", help="a trained run directory")
    export.add_argument("--out", type=folder, required=True, help="output folder")
    export.add_argument(
        "--length",
        type=positive,
        default=None,
        help="vehicle length [m] (default: the data's leader length)",
    )
    export.add_argument(
        "--emergency-decel",
        type=positive,
        default=EMERGENCY_DECEL,
        help="SUMO's emergencyDecel [m/s^2] (at least each particle's b)",
    )
    verify = commands.add_parser(
        "verify",
        formatter_class=DefaultsHelpFormatter,
        help="replay the test split in SUMO and score it",
        description="Replay the run's test split in SUMO (exported vTypes and "
        "co-simulation) and score it beside torchcf's own rollout: "
        "OUT/verify.json and verify.md.",
    )
    verify.add_argument("run_dir", help="a trained run directory")
    verify.add_argument(
        "--out", type=folder, default=None, help="output folder (default RUN/sumo)"
    )
    verify.add_argument(
        "--max-particles",
        type=count,
        default=None,
        help="each model's first N hybrid particles only (default: all)",
    )
    verify.add_argument(
        "--keep",
        default=None,
        metavar="DIR",
        help="keep SUMO's network, routes and FCD files in DIR",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf sumo``.

    Returns:
        0 done; 2 an error of the user's making or of the machine; 130
        interrupted.
    """
    args = _parser().parse_args(argv)  # numbers checked by their types
    if args.command == "export":
        return run_main(lambda: _export(args))
    return run_main(lambda: _verify(args), interrupted="interrupted: run it again")


def _export(args: argparse.Namespace) -> int:
    cfg, posterior, _ = RunDir(args.run_dir).load_run()
    dt, leader_length = run_constants(cfg, posterior)
    length = args.length if args.length is not None else leader_length
    export = export_hybrid(
        posterior, dt=dt, length=length, emergency_decel=args.emergency_decel
    )
    xml_path, manifest_path = write_export(export, args.out)
    manifest = export.manifest
    print(
        f"exported {sum(manifest.exported.values())} of {manifest.particles} "
        f"particles (share {manifest.share:.4f}): "
        + ", ".join(f"{k} {v}" for k, v in manifest.exported.items())
    )
    for name, skipped in manifest.not_exported.items():
        print(f"  not exported: {name} {skipped.particles} ({skipped.reason})")
    print(f"wrote {xml_path} and {manifest_path.name}")
    print(
        f"run SUMO with --step-length {dt!r} --step-method.ballistic true "
        f"--additional-files {xml_path}"
    )
    return 0


def _verify(args: argparse.Namespace) -> int:
    from ..sumo.verify import verify_run

    if args.keep is not None:
        from ..system.files import ensure_directory

        ensure_directory(args.keep, "--keep directory")
    report = verify_run(
        args.run_dir,
        args.out,
        max_particles=args.max_particles,
        workdir=args.keep,
        progress=True,
    )
    for part, label in (
        (report.vtypes, "exported vTypes"),
        (report.cosim, "co-simulation"),
    ):
        if part is None:
            continue
        print(
            f"{label} ({'+'.join(part.models)}): WS SUMO {part.sumo.ws:.6g}"
            f", torchcf {part.torchcf.ws:.6g}; max |x - torchcf| "
            f"{part.max_position_difference_m:.3g} m"
        )
    out = args.out if args.out is not None else f"{args.run_dir}/sumo"
    print(f"wrote {out}/verify.json and verify.md")
    return 0
