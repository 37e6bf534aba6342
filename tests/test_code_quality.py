"""The code base stays lint-clean and the core stays dependency-free."""

from __future__ import annotations

import ast
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import IN_CI, PROJECT

STDLIB = set(sys.stdlib_module_names)
# The only module that may import a package besides the standard library: the command's
# terminal rendering imports `rich`, lazily (inside its functions) and only if installed.
OPTIONAL_IMPORTS = {"kestimator/cli_render.py": frozenset(("rich",))}


def test_ruff_finds_nothing() -> None:
    if importlib.util.find_spec("ruff") is None:
        if IN_CI:
            pytest.fail("ruff is not installed (it is part of the test extras)")
        pytest.skip("ruff is not installed")
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "."], cwd=PROJECT,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def _mypy_finds_nothing(target: str) -> None:
    if importlib.util.find_spec("mypy") is None:
        if IN_CI:
            pytest.fail("mypy is not installed (it is part of the test extras)")
        pytest.skip("mypy is not installed")
    proc = subprocess.run([sys.executable, "-m", "mypy", target,
                           "--ignore-missing-imports", "--no-error-summary"],
                          cwd=PROJECT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_package_type_checks_with_mypy() -> None:
    _mypy_finds_nothing("kestimator")


def test_klipper_module_type_checks_with_mypy() -> None:
    """plugins/klipper/kestimator/ (its own run: it has the package's name)."""
    _mypy_finds_nothing("plugins/klipper/kestimator")


def test_benchmarks_type_check_with_mypy() -> None:
    """benchmarks/: the numbers the issues' targets are read from."""
    _mypy_finds_nothing("benchmarks")


def test_klipper_config_section_tool_type_checks_with_mypy() -> None:
    """plugins/klipper/config_section.py, which install.sh --uninstall runs."""
    _mypy_finds_nothing("plugins/klipper/config_section.py")


def test_core_imports_only_the_standard_library() -> None:
    offenders = []
    for path in sorted((PROJECT / "kestimator").rglob("*.py")):
        relative = path.relative_to(PROJECT).as_posix()
        optional = OPTIONAL_IMPORTS.get(relative, frozenset())
        tree = ast.parse(path.read_text(encoding="utf-8"))
        at_module_level = {id(node) for node in tree.body}
        # Imports under `if TYPE_CHECKING:` never run: only mypy (and mypyc, which takes
        # gcode.py's machine-integer types from mypy_extensions) reads them.
        typing_only = {id(inner) for node in ast.walk(tree)
                       if isinstance(node, ast.If) and isinstance(node.test, ast.Name)
                       and node.test.id == "TYPE_CHECKING"
                       for stmt in node.body for inner in ast.walk(stmt)}
        # mypy_extensions.mypyc_attr in a `try:` whose `except ImportError:` takes
        # kestimator.mypyc_attr's stand-in: it runs without mypy_extensions (mypyc reads
        # the decorator by its mypy_extensions name).
        with_fallback = {id(inner) for node in ast.walk(tree)
                         if isinstance(node, ast.Try) and any(
                             isinstance(h.type, ast.Name) and h.type.id == "ImportError"
                             and any(isinstance(x, ast.ImportFrom)
                                     and x.module == "kestimator.mypyc_attr" for x in h.body)
                             for h in node.handlers)
                         for stmt in node.body for inner in ast.walk(stmt)
                         if isinstance(inner, ast.ImportFrom)
                         and inner.module == "mypy_extensions"}
        for node in ast.walk(tree):
            if id(node) in typing_only or id(node) in with_fallback:
                continue
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for name in names:
                top = name.split(".")[0]
                if top in STDLIB or top in ("kestimator", "tomli"):
                    continue
                if top in optional and id(node) not in at_module_level:
                    continue  # imported when drawing, not when the module is
                offenders.append("%s: %s" % (relative, name))
    assert not offenders


def test_an_estimate_imports_nothing_that_only_moonraker_or_inject_needs(
        tmp_path: Path) -> None:
    """`kestimator estimate FILE --json` starts without the modules only a Moonraker
    request or a rewrite reads (each costs milliseconds of every estimate's start)."""
    gcode = tmp_path / "a.gcode"
    gcode.write_text("G28\nG1 X10 Y10 F3000\n")
    code = ("import sys, runpy; sys.argv = ['kestimator', 'estimate', %r, '--json']\n"
            "try:\n    runpy.run_module('kestimator', run_name='__main__')\n"
            "except SystemExit:\n    pass\n"
            "print(' '.join(sorted(sys.modules)), file=sys.stderr)" % str(gcode))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=PROJECT, env={**os.environ, "HOME": str(tmp_path)}, check=True)
    loaded = set(proc.stderr.split("\n")[-2].split())
    assert "kestimator.estimate" in loaded
    assert not loaded & {"urllib.request", "http.client", "datetime", "hashlib"}
