"""How the suite is spread over processes (pyproject.toml's addopts, tests/conftest.py): three
pytest-xdist processes on the test machine's two cores (the real-time prints mostly wait on
the wall clock, and the other two keep both cores busy meanwhile), each test file in one of
them, the files longest first by tests/file_times.json, a file it does not know yet before
them all; what a run makes once for every process (conftest.once_per_run)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from . import conftest
from .conftest import (
    PROJECT,
    load_script,
    once_per_run,
    pytest_collection_modifyitems,
    recorded_file_times,
)

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib


def test_the_suite_runs_in_three_processes_a_file_in_one_of_them() -> None:
    options = tomllib.loads((PROJECT / "pyproject.toml").read_text())["tool"]["pytest"][
        "ini_options"]["addopts"]
    assert options == ["-n", "3", "--dist", "loadfile", "--no-loadscope-reorder"]
    extras = tomllib.loads((PROJECT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]["test"]
    assert any(extra.startswith("pytest-xdist") for extra in extras)


def test_every_timed_file_is_a_test_file_of_the_suite() -> None:
    times = recorded_file_times()
    assert "test_klipper_module_realtime.py" in times and "test_compiled_build.py" in times
    for name, entry in times.items():
        assert (PROJECT / "tests" / name).is_file(), name
        assert set(entry) == {"wall_s", "cpu_s", "tests", "wall_clock"}, name


def test_a_new_file_starts_first_then_wall_clock_files_then_the_most_cpu_and_tests_keep_order(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    times = tmp_path / "file_times.json"
    times.write_text(json.dumps({
        "test_print.py": {"wall_s": 300.0, "cpu_s": 20.0, "tests": 2, "wall_clock": True},
        "test_short.py": {"wall_s": 1.5, "cpu_s": 1.4, "tests": 2, "wall_clock": False},
        "test_mid.py": {"wall_s": 90.0, "cpu_s": 39.0, "tests": 1, "wall_clock": False}}))
    monkeypatch.setattr(conftest, "FILE_TIMES", times)
    marked = pytest.mark.wall_clock.mark
    collected = [SimpleNamespace(path=PROJECT / "tests" / name, n=n,
                                 get_closest_marker=lambda _, m=mark: m)
                 for n, (name, mark) in enumerate([
                     ("test_short.py", None), ("test_mid.py", None), ("test_print.py", marked),
                     ("test_new.py", None), ("test_short.py", None), ("test_print.py", marked),
                     ("test_new.py", None)])]
    items = list(collected)
    pytest_collection_modifyitems(items)  # type: ignore[arg-type]
    assert [item.n for item in items] == [3, 6, 2, 5, 1, 0, 4]


def test_the_real_time_prints_and_the_cura_guis_are_marked_as_waiting_on_the_clock() -> None:
    for name in ("test_klipper_module_realtime.py", "test_cura_gui.py"):
        assert "pytestmark = pytest.mark.wall_clock" in (PROJECT / "tests" / name).read_text()
    assert recorded_file_times()["test_klipper_module_realtime.py"]["wall_clock"] is True


def test_a_run_records_each_files_wall_and_cpu_seconds_and_keeps_the_other_files(
        tmp_path: Path) -> None:
    """Two processes (pytest-xdist), this conftest as a plugin, two files: one computing, one
    marked wall_clock that sleeps."""
    (tmp_path / "test_computes.py").write_text(
        "import pytest\n"
        "@pytest.mark.parametrize('n', [1, 2])\n"
        "def test_computes(n):\n"
        "    assert sum(i * i for i in range(2_000_000)) > n\n")
    (tmp_path / "test_sleeps.py").write_text(
        "import time, pytest\n"
        "pytestmark = pytest.mark.wall_clock\n"
        "def test_sleeps():\n"
        "    time.sleep(1.0)\n")
    out = tmp_path / "times.json"
    out.write_text(json.dumps({"test_other.py": {"wall_s": 9.0, "cpu_s": 8.0, "tests": 3,
                                                 "wall_clock": False}}))
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PYTEST_", "KESTIMATOR_TEST_"))}
    env["PYTHONPATH"] = str(PROJECT)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-c", os.devnull, "--rootdir", str(tmp_path),
         "-p", "tests.conftest", "-p", "no:cacheprovider", "-n", "2", "--dist", "loadfile",
         "-q", "-W", "ignore::pytest.PytestUnknownMarkWarning", "test_computes.py",
         "test_sleeps.py", "--record-file-times", str(out)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "3 passed" in proc.stdout
    recorded = json.loads(out.read_text())
    assert list(recorded) == ["test_other.py", "test_computes.py", "test_sleeps.py"]
    assert recorded["test_other.py"] == {"wall_s": 9.0, "cpu_s": 8.0, "tests": 3,
                                         "wall_clock": False}
    computes, sleeps = recorded["test_computes.py"], recorded["test_sleeps.py"]
    assert computes["tests"] == 2 and not computes["wall_clock"]
    assert computes["cpu_s"] > 0.1 and computes["wall_s"] >= computes["cpu_s"] * 0.9
    assert sleeps["tests"] == 1 and sleeps["wall_clock"]
    assert sleeps["wall_s"] >= 1.0 and sleeps["cpu_s"] < 0.5


def test_what_a_run_makes_once_is_made_by_one_process_and_read_by_the_others() -> None:
    made = []
    name = "test_suite_layout %s" % threading.get_ident()

    def make(folder: Path) -> dict[str, str]:
        assert folder.is_dir() and not any(folder.iterdir())
        made.append(folder)
        (folder / "built").write_text("yes")
        return {"folder": str(folder)}

    first = once_per_run(name, make)
    assert once_per_run(name, make) == first and len(made) == 1
    assert Path(first["folder"], "built").read_text() == "yes"
    # Another process of the run (a pytest-xdist worker) reads it.
    other = subprocess.run(
        [sys.executable, "-c", "import json, sys; from tests.conftest import once_per_run; "
         "print(json.dumps(once_per_run(sys.argv[1], lambda folder: 'made again')))", name],
        cwd=PROJECT, capture_output=True, text=True, timeout=120)
    assert other.returncode == 0, other.stderr
    assert json.loads(other.stdout) == first


def test_what_failed_to_be_made_once_is_tried_again_by_the_next_that_asks() -> None:
    name = "test_suite_layout failing %s" % threading.get_ident()

    def fail(folder: Path) -> int:
        raise RuntimeError("no network")

    with pytest.raises(RuntimeError):
        once_per_run(name, fail)
    assert once_per_run(name, lambda folder: 7) == 7


def _suite_time() -> Any:
    return load_script("suite_time_benchmark", PROJECT / "benchmarks" / "suite_time.py")


def test_the_idle_estimate_runs_a_file_waiting_on_the_clock_beside_cpu_bound_ones() -> None:
    """benchmarks/suite_time.py: a 300 s print using 30 s of CPU and three CPU-bound files.
    Two processes: the print holds one while the other runs 200 + 200 s, the 100 s file
    starts when the print ends (300 s) and shares the cores to 400 s. Three: the two 200 s
    files share what the print leaves (1.9 cores) to 210.5 s, then the last runs 100 s."""
    suite_time = _suite_time()
    files = suite_time.files_from({
        "d.py": {"wall_s": 150.0, "cpu_s": 100.0, "tests": 1, "wall_clock": False},
        "b.py": {"wall_s": 200.0, "cpu_s": 200.0, "tests": 5, "wall_clock": False},
        "print.py": {"wall_s": 300.0, "cpu_s": 30.0, "tests": 5, "wall_clock": True},
        "c.py": {"wall_s": 900.0, "cpu_s": 200.0, "tests": 5, "wall_clock": False}})
    assert [(f.name, f.wall_s, f.waiting) for f in files] == [
        ("print.py", 300.0, True), ("b.py", 200.0, False), ("c.py", 200.0, False),
        ("d.py", 100.0, False)]
    assert suite_time.simulate(files, 2, 2.0, 0.0) == pytest.approx(400.0, abs=0.5)
    assert suite_time.simulate(files, 3, 2.0, 0.0) == pytest.approx(310.5, abs=0.5)
    assert suite_time.share([0.1, 1.0, 1.0], 2.0) == pytest.approx([0.1, 0.95, 0.95])
