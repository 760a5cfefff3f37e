"""The house's figures from the code alone: how the config travels, how run
records are read, how many examples run, how the packages import each other.

    python tools/house_counts.py            # this checkout
    python tools/house_counts.py --root DIR # another checkout (a worktree of a commit)

Prints one JSON object:

- ``packages``: the top-level packages and modules of ``torchcf`` (a room each);
- ``package_imports``: distinct imports between them (package A imports B);
- ``train_config_functions``: functions with a parameter annotated
  ``TrainConfig``, and per package;
- ``config_importers_below_train``: modules outside the edge (``config``,
  ``cli``, ``study``, ``train``, ``predict``) that import ``torchcf.config``;
- ``raw_record_reads``: subscripts or ``.get`` of a name ``summary`` or
  ``metrics`` outside the record modules (``runs/summary.py``,
  ``runs/metrics.py``), the raw JSON reads records replace;
- ``doctest_lines``: ``>>> `` lines in the package's docstrings;
- ``main_modules``: ``__main__.py`` files.
"""

from __future__ import annotations

import ast
import json
from collections import Counter
from pathlib import Path

from torchcf.system.console import OneLineParser, run_main

EDGE = {"config", "cli", "study", "train", "predict", "__main__"}
RECORD_MODULES = {"runs/summary.py", "runs/metrics.py"}


def _top(path: Path, package: Path) -> str:
    """The top-level package (or module) a file of ``package`` belongs to."""
    first = path.relative_to(package).parts[0]
    return first.removesuffix(".py")


def _imported(node: ast.ImportFrom, path: Path, package: Path) -> str | None:
    """The top-level package an ``from ... import`` names, or None (outside)."""
    if node.level == 0:
        parts = (node.module or "").split(".")
        return parts[1] if parts[0] == "torchcf" and len(parts) > 1 else None
    base = path.parent
    for _ in range(node.level - 1):
        base = base.parent
    target = base / (node.module or "").replace(".", "/")
    try:
        return _top(target, package) if target != package else None
    except ValueError:
        return None


def counts(root: Path) -> dict:
    """The figures of the checkout at ``root`` (module docstring)."""
    package = root / "torchcf"
    files = sorted(package.rglob("*.py"))
    packages = sorted({_top(p, package) for p in files} - {"__init__"})
    edges: set[tuple[str, str]] = set()
    functions: Counter[str] = Counter()
    importers, raw_reads, doctests, mains = [], [], 0, []
    for path in files:
        text = path.read_text()
        tree = ast.parse(text)
        top = _top(path, package)
        relative = str(path.relative_to(package))
        doctests += sum(line.lstrip().startswith(">>> ") for line in text.splitlines())
        if path.name == "__main__.py":
            mains.append(relative)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                target = _imported(node, path, package)
                if target and target != top and target != "__init__":
                    edges.add((top, target))
                if target == "config" and top not in EDGE:
                    importers.append(relative)
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                args = node.args.args + node.args.kwonlyargs
                if any(
                    a.annotation is not None
                    and "TrainConfig" in ast.unparse(a.annotation)
                    for a in args
                ):
                    functions[top] += 1
            if relative in RECORD_MODULES:
                continue
            if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name):
                if node.value.id in ("summary", "metrics") and isinstance(
                    node.slice, ast.Constant
                ):
                    raw_reads.append(f"{relative}:{node.lineno}")
    return {
        "packages": len(packages),
        "package_imports": len(edges),
        "train_config_functions": sum(functions.values()),
        "train_config_functions_by_package": dict(sorted(functions.items())),
        "config_importers_below_train": len(set(importers)),
        "raw_record_reads": len(raw_reads),
        "raw_record_read_places": raw_reads,
        "doctest_lines": doctests,
        "main_modules": mains,
    }


def main() -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path(__file__).parents[1])
    root = parser.parse_args().root
    if not (root / "torchcf").is_dir():
        raise FileNotFoundError(f"--root {root}: no torchcf package there")
    print(json.dumps(counts(root), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
