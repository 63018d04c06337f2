"""The import rules of the package (docs/architecture.md), read from the source with `ast`:
every `import` a module runs, at its top or inside a function (only `if TYPE_CHECKING:`
blocks are left out), between the modules of `mocap`.

1. Only the entry point (`mocap.__main__`) imports `mocap.cli`; only `mocap.cli` (and the
   command modules' shared helpers) import `mocap.commands`.
2. No import cycle among the modules.
3. No import runs up the layers: core < io < stages < orchestration < commands < entry;
   the core imports only the core, a format only the core and the formats. What breaks a
   rule today and needs a file moved to mend is listed in KNOWN, to shrink.
4. No module sits loose at the top of the package but the entry points and two leaves
   (`TOP_LEVEL`).
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mocap"

# the layers, lowest first; a module's layer is that of its longest matching prefix
LAYERS = {
    # core types and geometry, beside each other, below everything; the errors and the
    # progress line, leaves every layer uses
    "mocap.core": 0, "mocap.errors": 0, "mocap.progress": 0,
    # formats: read and write the core types (and the session folder)
    "mocap.io": 1,
    # the stages: compute from core types, read and write through io
    "mocap.calibration": 2, "mocap.tracking": 2, "mocap.clocks": 2, "mocap.reconstruct": 2, "mocap.analysis": 2,
    "mocap.report": 2, "mocap.interchange": 2, "mocap.viewer": 2, "mocap.synthetic": 2,
    # orchestration: the chain of stages, the batch, the live run, the API
    "mocap.orchestration": 3, "mocap.batch": 3, "mocap.live": 3, "mocap.api": 3,
    # the command line
    "mocap.commands": 4, "mocap.cli": 5, "mocap.__main__": 6,
}
# the only modules at the top of the package: the entry points (the package, `python -m
# mocap`, the command line, the API) and the two leaves every layer imports
TOP_LEVEL = {"mocap", "mocap.__main__", "mocap.cli", "mocap.api", "mocap.errors", "mocap.progress"}
NAMES = ("core", "io", "stages", "orchestration", "commands", "cli", "entry")

# rules broken today that moving a file would mend (issue: the layered house); shrink, never grow
KNOWN: set[tuple[str, str]] = set()
KNOWN_CROSSING: set[tuple[str, str]] = set()


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}


def _type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _resolve(name: str) -> str | None:
    """The mocap module an imported name is, or lives in."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def imports(name: str) -> set[str]:
    """The mocap modules that module `name` imports when it runs (not under TYPE_CHECKING)."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("mocap"):
                    found.add(_resolve(alias.name))
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            if base.startswith("mocap"):
                for alias in node.names:
                    found.add(_resolve(f"{base}.{alias.name}"))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(encoding="utf-8")))
    found.discard(None)
    found.discard(name)
    found.discard("mocap")  # the package's own __init__ (its version, the API's lazy names)
    return found


@functools.cache
def graph() -> dict[str, set[str]]:
    """Each mocap module's imports (parsed once, when a test first asks: not at collection)."""
    return {name: imports(name) for name in MODULES}


def layer(name: str) -> int:
    best = max((prefix for prefix in LAYERS if name == prefix or name.startswith(prefix + ".")), key=len,
               default=None)
    assert best is not None, f"{name} is in no layer: add it to LAYERS (and docs/architecture.md)"
    return LAYERS[best]


def test_only_the_entry_point_imports_the_command_line():
    importers = sorted(m for m, targets in graph().items() if "mocap.cli" in targets)
    assert importers == ["mocap.__main__"]
    commands = sorted(m for m, targets in graph().items()
                      if any(t.startswith("mocap.commands") for t in targets) and not m.startswith("mocap.commands"))
    assert commands == ["mocap.cli"]


def cycles_of(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of more than one node."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return cycles


def test_no_import_cycle():
    assert cycles_of(graph()) == []


# packages that import each other though no module does in a loop: the calibration's start
# uses the reconstruction's marker tolerance (offsets.tape_sd), the refinement the
# calibration's problem; one shared module below both would end it
KNOWN_PACKAGE_CYCLES: list[list[str]] = []


def test_no_import_cycle_between_packages():
    def package(name: str) -> str:
        return ".".join(name.split(".")[:2])

    packages: dict[str, set[str]] = {}
    for m, targets in graph().items():
        packages.setdefault(package(m), set()).update(package(t) for t in targets if package(t) != package(m))
    assert cycles_of(packages) == KNOWN_PACKAGE_CYCLES


def test_no_import_runs_up_the_layers():
    upward = {(m, t) for m, targets in graph().items() for t in targets if layer(t) > layer(m)}
    described = sorted(f"{m} ({NAMES[layer(m)]}) imports {t} ({NAMES[layer(t)]})" for m, t in upward - KNOWN)
    assert described == []
    mended = KNOWN - upward
    assert not mended, f"mended, take them off KNOWN: {sorted(mended)}"


def test_stages_do_not_import_each_others_stage_modules():
    """A stage uses another's computing modules at most, never its `stage` (load/save) module."""
    crossing = {(m, t) for m, targets in graph().items() for t in targets
                if layer(m) == 2 and t.endswith(".stage") and t.split(".")[1] != m.split(".")[1]}
    assert sorted(crossing - KNOWN_CROSSING) == []
    assert not KNOWN_CROSSING - crossing, "mended: take them off KNOWN_CROSSING"


def test_no_module_sits_loose_at_the_top():
    """Every module but the entry points and the two leaves lives in its layer's package."""
    assert sorted(m for m, path in MODULES.items() if path.parent == PACKAGE and m not in TOP_LEVEL) == []


def test_core_imports_only_core_and_io_only_core_and_io():
    """The core types know no format and no stage; a format knows the core types only."""
    def outside(prefix: str, allowed: tuple[str, ...]) -> list[str]:
        return sorted(f"{m} imports {t}" for m, targets in graph().items() if m.startswith(prefix)
                      for t in targets if not t.startswith(allowed))

    assert outside("mocap.core", ("mocap.core", "mocap.errors", "mocap.progress")) == []
    assert outside("mocap.io", ("mocap.core", "mocap.io", "mocap.errors", "mocap.progress")) == []


def test_the_rules_see_the_imports():
    """The reader finds imports at the top, in functions, relative ones, and leaves out TYPE_CHECKING."""
    assert "mocap.commands" in graph()["mocap.cli"] and "mocap.cli" in graph()["mocap.__main__"]
    assert "mocap.orchestration.pipeline" in graph()["mocap.orchestration.demo"]  # imported inside run_demo
    assert "mocap.reconstruct.kinfit" in graph()["mocap.reconstruct.stage"]  # inside fit_motion
    assert "mocap.batch.stage" in graph()["mocap.commands.batch"]  # relative to nothing, inside run()
