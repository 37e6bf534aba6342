"""docs/ARCHITECTURE.md stays true: every module is on a storey, imports only its own storey
or below, with no circle; the mirrored Klipper files say so in their first line."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from .conftest import PROJECT

PACKAGE = PROJECT / "kestimator"
ARCHITECTURE = PROJECT / "docs" / "ARCHITECTURE.md"
FIDELITY = PROJECT / "docs" / "KLIPPER-FIDELITY.md"
KLIPPER_COMMIT = "84104bbbd"
# Kalico's own kinematics (limited_*) mirror the pinned Kalico release.
KALICO_RELEASE = "Kalico v2026.07.00"
MAX_CLASS_LINES = 400


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PROJECT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _exempt_block(node: ast.AST) -> bool:
    """`if TYPE_CHECKING:` (never runs) or `if __name__ == "__main__":` (runs only as a
    program, when nothing imports the module)."""
    if not isinstance(node, ast.If):
        return False
    test = node.test
    if isinstance(test, ast.Name):
        return test.id == "TYPE_CHECKING"
    return (isinstance(test, ast.Compare) and isinstance(test.left, ast.Name)
            and test.left.id == "__name__")


def runtime_imports(path: Path, known: set[str]) -> set[str]:
    """The package modules `path` imports when it is imported (not those under
    TYPE_CHECKING or a `__main__` guard)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    typing_only = {id(inner) for node in ast.walk(tree) if _exempt_block(node)
                   for stmt in node.body for inner in ast.walk(stmt)}
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module in known:
                found.add(node.module)
            found.update(node.module + "." + a.name for a in node.names
                         if node.module + "." + a.name in known)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name in known)
    found.discard(_module_name(path))
    return found


def storeys() -> dict[str, int]:
    """Module -> storey number, from the storey table of docs/ARCHITECTURE.md."""
    table: dict[str, int] = {}
    for line in ARCHITECTURE.read_text(encoding="utf-8").splitlines():
        row = re.match(r"\|\s*(\d+)\.[^|]*\|(.*)\|\s*$", line)
        if not row:
            continue
        for path in re.findall(r"`(kestimator/[\w/]+\.py)`", row.group(2)):
            name = _module_name(PROJECT / path)
            assert name not in table, "%s is on two storeys" % path
            table[name] = int(row.group(1))
    return table


def test_every_module_stands_on_one_storey_of_the_architecture_document() -> None:
    table = storeys()
    modules = _modules()
    assert sorted(set(modules) - set(table)) == [], "modules missing from ARCHITECTURE.md"
    assert sorted(set(table) - set(modules)) == [], "ARCHITECTURE.md names modules that are gone"


def test_no_module_imports_from_a_storey_above_its_own() -> None:
    table = storeys()
    modules = _modules()
    upward = ["%s (storey %d) imports %s (storey %d)" % (name, table[name], dep, table[dep])
              for name, path in modules.items() if name in table
              for dep in sorted(runtime_imports(path, set(modules)))
              if dep in table and table[dep] > table[name]]
    assert upward == []


def test_the_package_imports_form_no_circle() -> None:
    modules = _modules()
    graph = {name: runtime_imports(path, set(modules)) for name, path in modules.items()}
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(name: str, path: list[str]) -> None:
        state[name] = 1
        for dep in sorted(graph[name]):
            if state.get(dep) == 1:
                pytest.fail("import circle: " + " -> ".join(path[path.index(dep):] + [dep]))
            if dep not in state:
                visit(dep, path + [dep])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])


def _mirrored() -> dict[Path, str]:
    """Module -> the Klipper file its first docstring line says it mirrors."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
        first = doc.splitlines()[0] if doc else ""
        match = re.match(r"Mirrors (?:the [\w ]+ of )?(klippy/[\w/]+\.py) (?:at Klipper commit "
                         r"(\w+)|of (Kalico v[\d.]+))", first)
        if match:
            assert match.group(2) == KLIPPER_COMMIT or match.group(3) == KALICO_RELEASE, path
            found[path] = match.group(1)
    return found


def test_the_files_re_implementing_klipper_name_their_upstream_file_first() -> None:
    mirrored = {p.relative_to(PROJECT).as_posix(): upstream
                for p, upstream in _mirrored().items()}
    for module in ("toolhead", "gcode_move", "gcode_arcs", "firmware_retraction", "extruder",
                   "motion_queuing", "input_shaper", "gcode", "interpreter"):
        assert "kestimator/%s.py" % module in mirrored, module
    kinematics = [p.relative_to(PROJECT).as_posix()
                  for p in sorted((PACKAGE / "kinematics").glob("*.py"))
                  if p.stem not in ("__init__", "base", "standin")]
    assert kinematics and all(k in mirrored for k in kinematics)
    assert mirrored["kestimator/toolhead.py"] == "klippy/toolhead.py"
    assert mirrored["kestimator/kinematics/delta.py"] == "klippy/kinematics/delta.py"


def test_the_fidelity_map_names_every_mirrored_file_and_its_upstream() -> None:
    text = FIDELITY.read_text(encoding="utf-8")
    rows = {}
    for line in text.splitlines():
        row = re.match(r"\|\s*`(kestimator/[\w/<>]+\.py)`\s*\|(.*)\|\s*$", line)
        if row:
            rows[row.group(1)] = row.group(2)
    for path, upstream in _mirrored().items():
        module = path.relative_to(PROJECT).as_posix()
        if module.startswith("kestimator/kinematics/"):
            module, upstream = "kestimator/kinematics/<name>.py", "klippy/kinematics/<name>.py"
        assert module in rows, "%s is missing from KLIPPER-FIDELITY.md" % module
        assert upstream in rows[module], (module, upstream)


def test_no_class_in_the_package_is_longer_than_400_lines() -> None:
    long = ["%s: %s (%d lines)" % (path.relative_to(PROJECT), node.name,
                                   node.end_lineno - node.lineno + 1)
            for path in sorted(PACKAGE.rglob("*.py"))
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
            if isinstance(node, ast.ClassDef) and node.end_lineno is not None
            and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES]
    assert long == []
