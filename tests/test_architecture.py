"""The house as docs/architecture.md draws it, checked against the code: which stage imports
which, no import circle, library modules without a command line, commands thin.

Every import is counted, also one inside a function: an import deferred to break a circle is
still a circle, and one deferred for speed still ties the two stages together."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest
from conftest import REPO

# What each stage may import of the package (ARCHITECTURE.md, "may import"). The core is
# `tactile` itself: errors, the command-line conventions, the model contract, the kernels.
# Data flows device -> training -> export -> runtime; imports are layered core < device <
# {training, runtime} < export: training and the runtime never import each other, and the
# exporter may use the runtime's own loader to check a file as a board will load it.
STAGES = ("device", "training", "export", "runtime")
MAY_IMPORT = {
    "core": {"core"},
    "device": {"core", "device"},
    "training": {"core", "device", "training"},
    "export": {"core", "device", "training", "export", "runtime"},
    "runtime": {"core", "device", "runtime"},
}
# Third-party packages a stage must never reach, at any depth.
FORBIDDEN = {
    "core": {"torch", "onnx", "onnxscript", "sklearn", "PyEMD", "matplotlib"},
    "device": {"torch", "onnx", "onnxscript", "sklearn", "PyEMD", "onnxruntime"},
    "runtime": {"torch", "onnx", "onnxscript", "sklearn", "PyEMD", "matplotlib", "scipy"},
}


def _modules() -> dict[str, Path]:
    """Every module of the package, by dotted name, from pyproject's package-dir."""
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    found: dict[str, Path] = {}
    for package, folder in tool["package-dir"].items():
        for path in sorted((REPO / folder).glob("*.py")):
            name = package if path.stem == "__init__" else f"{package}.{path.stem}"
            found[name] = path
    return found


MODULES = _modules()


def _stage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in STAGES else "core"


def _resolve(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    package = module.split(".")
    is_package = MODULES[module].stem == "__init__"
    base = package[: len(package) - node.level + (1 if is_package else 0)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(module: str) -> tuple[set[str], set[str]]:
    """(modules of the package, top-level third-party names) that ``module`` imports."""
    ours, theirs = set(), set()
    for node in ast.walk(ast.parse(MODULES[module].read_text())):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(module, node)
            targets = [base]
            targets += [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in MODULES]
        for t in targets:
            if t.split(".")[0] != "tactile":
                theirs.add(t.split(".")[0])
                continue
            while t and t not in MODULES:  # a name inside a module: the module
                t = t.rpartition(".")[0]
            if t and t != module:
                ours.add(t)
    return ours, theirs


GRAPH = {m: _imports(m) for m in MODULES}


def test_every_stage_is_found():
    assert {_stage(m) for m in MODULES} == {"core", *STAGES}


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_stage_imports_a_later_one(module):
    stage = _stage(module)
    ours, theirs = GRAPH[module]
    bad = sorted(t for t in ours if _stage(t) not in MAY_IMPORT[stage])
    assert not bad, f"{module} ({stage}) imports {bad}"
    banned = sorted(theirs & FORBIDDEN.get(stage, set()))
    assert not banned, f"{module} ({stage}) imports {banned}"


def _cycle() -> list[str] | None:
    """One import circle among the package's modules, or None. A package's ``__init__`` that
    re-exports its submodules is an edge like any other, so a submodule that imports its own
    package's ``__init__`` closes a circle."""
    state: dict[str, int] = {}  # 1 on the path, 2 done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for t in sorted(GRAPH[m][0]):
            if state.get(t) == 1:
                return path[path.index(t):] + [t]
            if t not in state and (found := visit(t)):
                return found
        path.pop()
        state[m] = 2
        return None

    for m in sorted(MODULES):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_no_import_circle():
    circle = _cycle()
    assert circle is None, "import circle: " + " -> ".join(circle)


def test_commands_are_thin_modules_the_scripts_name():
    """Every console script is ``tactile.<stage>.commands.<name>:main``, and only modules under
    a ``commands`` package build an argument parser."""
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    for script, target in scripts.items():
        module, _, func = target.partition(":")
        parts = module.split(".")
        assert func == "main" and len(parts) == 4 and parts[2] == "commands", (script, target)
        assert module in MODULES, (script, module)
    parsers = sorted(m for m in MODULES if "argparse" in GRAPH[m][1]
                     and ".commands." not in m and m != "tactile.cli")
    assert parsers == [], f"library modules with a command line: {parsers}"
