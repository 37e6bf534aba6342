"""The core runs unchanged under Debian's PyPy and gives the very same bytes as CPython.

PyPy parses plain moves with its own scanner (`gcode.parse_plain_move_scan`), so this is
where that path meets real files in a real PyPy: on every corpus file `estimate --json`
must print exactly what CPython prints and `inject` must write exactly the same file, and
every field of the estimate must agree bit for bit (tests/builds.py). Debian's PyPy is a
Python 3.9, so this is also where the core and the zipapp are run on 3.9. Skipped without
`pypy3` outside CI; under CI a missing `pypy3` fails (.ci/run installs it).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .builds import (
    cli_outputs,
    compared_files,
    digests,
    extreme_programs,
    generated_programs,
    pure_cli_outputs,
    transform_runs,
)
from .conftest import PROJECT, require_program
from .test_hook_checks import build_zipapp

EXAMPLE = PROJECT / "examples" / "hex_nut_prusaslicer.gcode"
EXAMPLE_CFG = PROJECT / "examples" / "printer.cfg"


def _pypy() -> str:
    return require_program("pypy3")


def test_pypy_runs_the_core_unchanged() -> None:
    out = subprocess.run([_pypy(), "-c", "import platform, kestimator.estimate;"
                          "print(platform.python_implementation())"],
                         env=dict(os.environ, PYTHONPATH=str(PROJECT)), capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "PyPy"


@pytest.mark.parametrize("path", compared_files(), ids=lambda p: p.parent.name + "/" + p.name)
def test_pypy_estimate_json_and_inject_bytes_equal_cpython_on_corpus_file(path: Path) -> None:
    assert cli_outputs(_pypy(), path) == pure_cli_outputs(path)


def test_pypy_estimate_equals_cpython_field_by_field_on_corpus_and_programs(
        tmp_path: Path) -> None:
    paths = compared_files() + generated_programs(tmp_path)
    pypy = digests(_pypy(), paths)
    cpython = digests(sys.executable, paths)
    assert len(pypy) == len(cpython) == len(paths) + 1
    for path, a, b in zip(paths, pypy[1:], cpython[1:]):
        assert a == b, path.name


@pytest.mark.parametrize("kinematics", ["delta", "rotary_delta", "deltesian", "polar"])
def test_pypy_equals_cpython_on_extreme_values_with_every_kinematics_that_squares_positions(
        tmp_path: Path, kinematics: str) -> None:
    # These kinematics square the file's positions in check_move: PyPy's ** gave inf where
    # CPython raised OverflowError, so one build stopped the print and the other timed it.
    cfg = PROJECT / "tests" / "oracle_refs" / kinematics / "printer.cfg"
    paths = extreme_programs(tmp_path)
    pypy = digests(_pypy(), paths, printer_cfg=cfg)
    cpython = digests(sys.executable, paths, printer_cfg=cfg)
    assert len(pypy) == len(cpython) == len(paths) + 1
    for path, a, b in zip(paths, pypy[1:], cpython[1:]):
        assert a == b, path.name


def test_pypy_equals_cpython_with_a_bed_mesh_and_skew_correction(tmp_path: Path) -> None:
    for cfg, paths in transform_runs(tmp_path):
        pypy = digests(_pypy(), paths, printer_cfg=cfg)
        cpython = digests(sys.executable, paths, printer_cfg=cfg)
        assert len(pypy) == len(cpython) == len(paths) + 1
        for path, a, b in zip(paths, pypy[1:], cpython[1:]):
            assert a == b, (cfg.parent.name, path.name)


def test_the_zipapp_runs_under_pypy_a_python_3_9(tmp_path: Path) -> None:
    pyz = build_zipapp(tmp_path)
    version = subprocess.run([_pypy(), "-c", "import sys; print(sys.version_info[:2])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    assert version == "(3, 9)"
    out = tmp_path / "out.gcode"
    for python in (_pypy(), sys.executable):
        proc = subprocess.run([python, "-I", "-S", str(pyz), "inject", str(EXAMPLE), "-o",
                               str(out), "--printer-cfg", str(EXAMPLE_CFG), "-q"],
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr
        if python != sys.executable:
            by_pypy = out.read_bytes()
    assert by_pypy == out.read_bytes() != EXAMPLE.read_bytes()
