"""The package's layers hold: data flows cli -> pipeline -> vision / cad / tolerances -> reports.

Every import in the package's source is read (module level and inside
functions alike, since the heavy ones are deferred), so a new upward
import fails here, naming the module and the line.
"""

import ast
from collections import defaultdict
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "partinspect"

# Which packages or modules each may not import. Production code never
# depends on the simulator (only the command line, which runs `inspect
# render` and hands the planner's check its renderer, and the simulator
# itself); vision knows nothing of the CAD model or the tolerances; the
# reports only format what they are given; the production layer (batches,
# results database, SPC) sits beside the pipeline, above it only the command line.
UPPER = ["partinspect.cli", "partinspect.pipeline", "partinspect.multiview", "partinspect.diagnosis",
         "partinspect.results", "partinspect.production"]
FORBIDDEN = {
    "partinspect.vision": ["partinspect.cad", "partinspect.tolerances", "partinspect.planning", "partinspect.reports",
                           "partinspect.simulate", "partinspect.adaptive", *UPPER],
    "partinspect.cad": ["partinspect.tolerances", "partinspect.planning", "partinspect.reports",
                        "partinspect.simulate", "partinspect.adaptive", *UPPER],
    "partinspect.tolerances": ["partinspect.cad.registration", "partinspect.vision", "partinspect.planning",
                               "partinspect.reports", "partinspect.simulate", "partinspect.adaptive", *UPPER],
    "partinspect.reports": ["partinspect.vision", "partinspect.cad", "partinspect.tolerances", "partinspect.planning",
                            "partinspect.simulate", "partinspect.adaptive", *UPPER],
    "partinspect.planning": ["partinspect.simulate", *UPPER],
    "partinspect.adaptive": ["partinspect.simulate", *UPPER],
    "partinspect.frames": ["partinspect."],
    "partinspect.poses": ["partinspect.simulate", "partinspect.vision", "partinspect.cad", *UPPER],
    "partinspect.diagnosis": ["partinspect.simulate", "partinspect.cli", "partinspect.pipeline", "partinspect.multiview",
                              "partinspect.production"],
    "partinspect.results": ["partinspect.simulate", "partinspect.cli", "partinspect.pipeline", "partinspect.multiview",
                            "partinspect.production"],
    "partinspect.pipeline": ["partinspect.simulate", "partinspect.cli", "partinspect.planning", "partinspect.production"],
    # Several views: orchestration beside the pipeline, whose stages it calls per view.
    "partinspect.multiview": ["partinspect.simulate", "partinspect.cli", "partinspect.planning",
                              "partinspect.production"],
    # Batches orchestrate like the pipeline (which they call once per part);
    # the SPC maths is plain functions on arrays: no I/O, no other layer.
    "partinspect.production": ["partinspect.simulate", "partinspect.cli", "partinspect.planning"],
    "partinspect.production.spc": ["partinspect."],
}


def _modules():
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _imports(path):
    """(line, imported module, imported name or None) of every import of partinspect in a file."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and node.module.startswith("partinspect"):
            for alias in node.names:
                yield node.lineno, node.module, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("partinspect"):
                    yield node.lineno, alias.name, None


def _targets(module, name):
    """The modules an import reaches: the module, and a submodule imported by name."""
    out = [module]
    if name is not None and f"{module}.{name}" in MODULES:
        out.append(f"{module}.{name}")
    return out


def _within(module, prefix):
    return module == prefix or module.startswith(prefix if prefix.endswith(".") else prefix + ".")


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_no_upward_imports(layer):
    bad = []
    for module, path in MODULES.items():
        if not _within(module, layer):
            continue
        for line, target, name in _imports(path):
            for t in _targets(target, name):
                if any(_within(t, f) for f in FORBIDDEN[layer]) and not _within(t, layer):
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} imports {t}")
    assert not bad, "\n".join(bad)


def test_only_the_command_line_and_the_simulator_import_the_simulator():
    bad = [f"{path.relative_to(PACKAGE.parent)}:{line} imports {target}"
           for module, path in MODULES.items()
           if not (_within(module, "partinspect.simulate") or module == "partinspect.cli")
           for line, target, _ in _imports(path) if _within(target, "partinspect.simulate")]
    assert not bad, "\n".join(bad)


def test_no_private_names_imported_across_modules():
    bad = [f"{path.relative_to(PACKAGE.parent)}:{line} imports {name} from {target}"
           for module, path in MODULES.items()
           for line, target, name in _imports(path)
           if name and name.startswith("_") and not name.startswith("__") and target != module]
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    graph = defaultdict(set)
    for module, path in MODULES.items():
        for _, target, name in _imports(path):
            graph[module].update(t for t in _targets(target, name) if t in MODULES and t != module)
    # Tarjan's strongly connected components: any of more than one module is a cycle.
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in MODULES:
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_the_checks_see_an_upward_import(tmp_path):
    """The reader finds imports inside functions too (where the heavy ones are)."""
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from partinspect.cad.features import inventory\n")
    assert list(_imports(src)) == [(2, "partinspect.cad.features", "inventory")]
