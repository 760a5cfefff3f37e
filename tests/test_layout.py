"""The house's layout: no import cycles, imports point down the pipeline, and
no public signature wider than a reader can hold.

Read from the source (every ``import`` statement, at any depth, so a
function-level import that dodges a cycle counts too), not by importing.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "torchcf"

#: The pipeline's stages, in the data's order: a module may import its own stage
#: and the stages before it, never a later one. (Checked per top-level name under
#: ``torchcf``; a name missing here is a new module that must be placed.)
STAGES = [
    {"typing", "system"},  # plumbing: errors, files, signals, the console
    {"data", "qp"},  # pairs in; the MPC's solver
    {"models"},
    {"sim"},  # the rollout; pairs made by it
    {"config", "posterior", "runs"},  # the run's config, learned set and folder
    {"abc", "amortised"},  # the ABC engine; the amortised estimator beside it
    {"calibration"},  # one calibration: samplers, buffers, the hybrid
    {"evaluation"},  # metrics and the test-split evaluation
    {"diagnose"},
    {"traffic"},
    {"sumo"},  # the learned hybrid in SUMO (export, co-simulation, verify)
    {"train"},
    {"predict"},  # a trained run predicting pairs it never saw
    {"study", "__init__"},  # the study and its variants
    {"cli"},  # the command lines: parse, call the library, print
]
#: The entry module (``python -m torchcf``, the only one: ``torchcf COMMAND``
#: and ``python -m torchcf COMMAND``): above the commands it runs, imported by
#: nothing.
CLI_MODULES = {"torchcf.__main__"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in ROOT.rglob("*.py")}


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The torchcf modules ``name`` imports (resolved relative imports; ``from
    package import submodule`` names the submodule)."""
    is_package = path.name == "__init__.py"
    package = name.split(".") if is_package else name.split(".")[:-1]
    found = set()
    tree = ast.parse(path.read_text(), str(path))
    for node in _runtime_nodes(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            submodules = [f"{module}.{a.name}" for a in node.names]
            # ``from package import submodule`` runs the package's __init__ only
            # where a name is not a submodule (the package itself is imported
            # then: a parent package is always, and not a cycle).
            targets = [m for m in submodules if m in known]
            if len(targets) < len(submodules):
                targets.append(module)
        else:
            continue
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target.startswith("torchcf") and target != name:
                found.add(target)
    return found


def _runtime_nodes(tree: ast.AST):
    """Every node except those under ``if TYPE_CHECKING:`` (never imported)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            yield from (n for child in node.orelse for n in ast.walk(child))
            continue
        yield node
        yield from _runtime_nodes(node)


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(name, path, known) for name, path in modules.items()}


def _stage(module: str) -> int:
    if module in CLI_MODULES:
        return len(STAGES)
    top = module.split(".")[1] if "." in module else "__init__"
    for rank, names in enumerate(STAGES):
        if top in names:
            return rank
    pytest.fail(f"{module}: place torchcf.{top} in a stage of tests/test_layout.py")


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """An import cycle of ``graph`` (module -> modules it imports), or None."""
    state: dict[str, int] = {}  # 1 on the stack, 2 done

    def visit(module: str, stack: list[str]) -> list[str] | None:
        state[module] = 1
        for target in sorted(graph.get(module, ())):
            if state.get(target) == 1:
                return stack[stack.index(target) :] + [target]
            if target not in state:
                found = visit(target, [*stack, target])
                if found:
                    return found
        state[module] = 2
        return None

    for module in sorted(graph):
        if module not in state:
            found = visit(module, [module])
            if found:
                return found
    return None


def test_no_import_cycle():
    cycle = _find_cycle(_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_the_cycle_finder_finds_one():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _find_cycle(graph) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set()}) is None


def test_imports_point_down_the_pipeline():
    wrong = []
    for module, targets in _graph().items():
        if module == "torchcf":  # the public API re-exports from every stage
            continue
        for target in targets:
            if target != "torchcf" and _stage(target) > _stage(module):
                wrong.append(f"{module} -> {target}")
    assert not wrong, "imports up the pipeline:\n" + "\n".join(sorted(wrong))


def test_nothing_imports_a_command_line():
    importers = [
        f"{module} -> {target}"
        for module, targets in _graph().items()
        for target in targets
        if target in CLI_MODULES
    ]
    assert not importers, importers


def test_training_is_reached_through_its_package():
    """The study and the commands call training by ``torchcf.train``'s names
    only: what the loop's re-calibration shares with training (the rollout, the
    plausibility screen) sits below both (``torchcf.calibration``,
    ``torchcf.traffic.configured``), not in training's own modules."""
    reaching = [
        f"{module} -> {target}"
        for module, targets in _graph().items()
        if not module.startswith("torchcf.train")
        for target in targets
        if target.startswith("torchcf.train.")
    ]
    assert not reaching, reaching


def test_the_graph_sees_relative_and_function_level_imports():
    """The checks above can fail: the parser finds what they look for."""
    graph = _graph()
    assert "torchcf.abc.rejection" in graph["torchcf.train.run"]
    assert "torchcf.sim.rollout" in graph["torchcf.abc.rejection"]
    assert "torchcf.study.pipeline" in graph["torchcf.cli.train"]
    assert "torchcf.cli.main" in graph["torchcf.__main__"]


def test_the_commands_sit_above_the_study():
    """The command package is its own stage, the last one, above the pipeline;
    the plumbing the lower modules share is a stage of its own, the first."""
    assert STAGES[-1] == {"cli"}
    assert _stage("torchcf.cli.train") > _stage("torchcf.study.pipeline")
    assert _stage("torchcf.system.console") == 0
    assert _stage("torchcf.cli") == len(STAGES) - 1


def test_only_the_command_lines_hold_main():
    """A command's ``main`` lives in :mod:`torchcf.cli` (and ``python -m
    torchcf``'s entry module, which calls it): a library module with its own
    ``main`` would hand over to a command above it, an import up the house."""
    holders = []
    for name, path in _modules().items():
        if name.startswith("torchcf.cli") or name in CLI_MODULES:
            continue
        tree = ast.parse(path.read_text(), str(path))
        if any(
            isinstance(node, ast.FunctionDef) and node.name == "main"
            for node in tree.body
        ):
            holders.append(name)
    assert not holders, f"main outside torchcf.cli: {holders}"


def test_every_numeric_option_is_checked():
    """The commands and the tools take numbers through the checked types of
    :mod:`torchcf.system.console` (``count``, ``positive``...): a bare ``type=int`` or
    ``type=float`` lets ``-3`` or ``nan`` through to a traceback deep in the
    run."""
    bare = re.compile(r"\btype=(int|float)\b")
    places = sorted(ROOT.parent.joinpath("tools").glob("*.py"))
    places += sorted(ROOT.joinpath("cli").glob("*.py"))
    found = [
        f"{path.relative_to(ROOT.parent)}:{number}"
        for path in places
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if bare.search(line)
    ]
    assert not found, f"unchecked numeric options: {found}"


def test_every_tool_runs_under_the_one_policy():
    """A tool's entry is ``run_main(main)``: a missing file or a corrupted run
    is one ``error:`` line and exit code 2, as in the commands."""
    entry = "raise SystemExit(run_main(main))"
    # a MkDocs hook, a module, a script for pyABC's own environment
    skipped = {"docs_reports.py", "peer_numpy.py", "pyabc_baseline.py"}
    missing = [
        path.name
        for path in sorted(ROOT.parent.joinpath("tools").glob("*.py"))
        if path.name not in skipped
        and entry not in path.read_text()
        and "return run_main(" not in path.read_text()
    ]
    assert not missing, f"tools not under run_main: {missing}"


#: The most parameters a public function or method may take (``self`` and
#: ``cls`` aside): beyond it, the ones that travel together belong in a
#: settings object (a frozen dataclass, or the config section they come from).
MAX_PARAMETERS = 8


def _parameter_count(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Positional-only, positional and keyword-only parameters, ``self`` or
    ``cls`` aside (``*args`` and ``**kwargs`` are not counted)."""
    args = node.args
    names = [a.arg for a in args.posonlyargs + args.args + args.kwonlyargs]
    return len(names) - (1 if names and names[0] in ("self", "cls") else 0)


def _wide_signatures(tree: ast.AST) -> list[tuple[int, str, int]]:
    """``(line, name, parameters)`` of every public function or method of
    ``tree`` (its name without a leading ``_``, or ``__init__``) that takes
    more than :data:`MAX_PARAMETERS`."""
    return [
        (node.lineno, node.name, _parameter_count(node))
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and (not node.name.startswith("_") or node.name == "__init__")
        and _parameter_count(node) > MAX_PARAMETERS
    ]


def test_no_public_signature_is_wider_than_eight_parameters():
    """A reader holds eight parameters; a public function or method with more
    groups those that travel together (units, bootstrap settings, what runs
    between rounds...) into one object."""
    wide = [
        f"{path.relative_to(ROOT.parent)}:{line} {name} ({count})"
        for path in sorted(ROOT.rglob("*.py"))
        for line, name, count in _wide_signatures(ast.parse(path.read_text()))
    ]
    assert not wide, f"more than {MAX_PARAMETERS} parameters:\n" + "\n".join(wide)


def test_the_signature_check_counts_what_it_should():
    """The check above can fail: nine parameters count, ``self`` and a private
    helper's do not, ``__init__``'s do."""
    source = (
        "def wide(a, b, /, c, d, e, f, g, *, h, i): ...\n"
        "def _private(a, b, c, d, e, f, g, h, i): ...\n"
        "class C:\n"
        "    def method(self, a, b, c, d, e, f, g, h): ...\n"
        "    def __init__(self, a, b, c, d, e, f, g, h, i, *args, **kw): ...\n"
    )
    found = [(name, count) for _, name, count in _wide_signatures(ast.parse(source))]
    assert found == [("wide", 9), ("__init__", 9)]
