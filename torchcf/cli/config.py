"""``torchcf config``: validate a run configuration, or print the schema.

    torchcf config configs/carII.json --set abc.seed=3   # resolved + hash
    torchcf config --schema                              # every field
    python -m torchcf config --schema                    # the same

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 a bad configuration (one line on
stderr) or bad arguments.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

from ..config.loading import config_hash, load_config, resolved_json
from ..config.schema import TrainConfig
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    add_overrides,
    run_main,
)


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf config``: print the schema, or a resolved config.

    Returns:
        0 on success, 2 on a bad configuration (``error: <one line>`` on stderr).
    """
    parser = OneLineParser(
        formatter_class=DefaultsHelpFormatter,
        prog="torchcf config",
        description=(
            "Validate a torchcf run configuration and print it resolved (every "
            "default filled in) with its hash, or print the JSON schema."
        ),
    )
    parser.add_argument("config", nargs="?", help="JSON run configuration")
    add_overrides(parser, "KEY=VALUE", "abc.seed=3")
    parser.add_argument(
        "--schema", action="store_true", help="print the JSON schema and exit"
    )
    args = parser.parse_args(argv)
    if args.schema:
        print(json.dumps(TrainConfig.model_json_schema(), indent=2))
        return 0
    if args.config is None:
        parser.error("give a CONFIG file or --schema")

    def body() -> int:
        cfg = load_config(args.config, args.overrides)
        resolved = {"config": resolved_json(cfg), "hash": config_hash(cfg)}
        print(json.dumps(resolved, indent=2))
        return 0

    return run_main(body)
