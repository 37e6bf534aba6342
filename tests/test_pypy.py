"""The core runs unchanged under Debian's PyPy and gives the very same bytes as CPython.

PyPy parses plain moves with its own scanner (`gcode.parse_plain_move_scan`), so this is
where that path meets real files in a real PyPy: `estimate --json` must print exactly
what CPython prints, and `inject` must write exactly the same file. Skipped without
`pypy3` outside CI; under CI a missing `pypy3` fails (.ci/run installs it).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import CORPUS_CFG, PROJECT, corpus_files, require_program

# Files from every slicer family, small enough to keep this test to seconds.
MAX_FILE_BYTES = 1_500_000


def _pypy() -> str:
    return require_program("pypy3")


def _run(python: str, *args: str) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ, PYTHONPATH=str(PROJECT), PYPY_GC_NURSERY="16M")
    return subprocess.run([python, "-m", "kestimator", *args], env=env, cwd=PROJECT,
                          capture_output=True, timeout=600, check=False)


def _one_per_family() -> list[Path]:
    chosen: dict[str, Path] = {}
    for path in corpus_files():
        if path.stat().st_size <= MAX_FILE_BYTES:
            chosen.setdefault(path.parent.name, path)
    return list(chosen.values())


def test_pypy_runs_the_core_unchanged() -> None:
    out = subprocess.run([_pypy(), "-c", "import platform, kestimator.estimate;"
                          "print(platform.python_implementation())"],
                         env=dict(os.environ, PYTHONPATH=str(PROJECT)), capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "PyPy"


@pytest.mark.parametrize("path", _one_per_family(), ids=lambda p: p.parent.name)
def test_pypy_estimate_prints_the_same_json_as_cpython(path: Path) -> None:
    args = ("estimate", str(path), "--json", "--printer-cfg", str(CORPUS_CFG))
    pypy = _run(_pypy(), *args)
    assert pypy.returncode == 0, pypy.stderr.decode()
    cpython = _run(sys.executable, *args)
    assert cpython.returncode == 0, cpython.stderr.decode()
    assert pypy.stdout == cpython.stdout


def test_pypy_inject_writes_the_same_bytes_as_cpython(tmp_path: Path) -> None:
    pypy_python = _pypy()
    for path in _one_per_family():
        outputs = []
        for python in (pypy_python, sys.executable):
            out = tmp_path / ("%s-%s.gcode" % (path.stem, Path(python).name))
            result = _run(python, "inject", str(path), "-o", str(out), "-q",
                          "--printer-cfg", str(CORPUS_CFG))
            # 4: Klipper will stop this print; the times are written all the same.
            assert result.returncode in (0, 4), result.stderr.decode()
            outputs.append(out.read_bytes())
        assert outputs[0] == outputs[1], path.name
