"""The compiled build: `pip wheel .` compiles the core with mypyc, and it gives the same bytes.

A wheel is built from a copy of the package's sources (setup.py, as `pip install .` runs
it), installed into a fresh venv without mypy, and then run side by side with the pure
package of this checkout: `estimate --json` prints the same bytes and `inject` writes the
same file for every corpus file, and every field of the estimate (floats bit for bit) is
the same on the corpus and on generated programs. The fallback is pinned too: with no
working C compiler the same command builds the pure wheel and says so in one line.

Building needs a C compiler with Python's headers, and pip fetches setuptools and mypy for
the build as `pip install .` does: outside CI the test is skipped without a compiler; under
CI it must be there (.ci/run installs gcc).
"""

from __future__ import annotations

import concurrent.futures
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from kestimator import build, worker

from .builds import (
    cli_outputs,
    compared_files,
    digests,
    generated_programs,
    pure_cli_outputs,
    setup_py_module,
    transform_runs,
)
from .conftest import CORPUS, CORPUS_CFG, IN_CI, PROJECT, isolate_user_environment

BUILD_TIMEOUT_S = 1200
# What a wheel is built from: the package's sources and the build files (as in an sdist).
SOURCES = ("kestimator", "setup.py", "pyproject.toml", "README.md")
COMPILED_LINE = "kestimator build: compiled with mypyc:"
PURE_LINE = "kestimator build: pure Python ("


def _require_build_tools() -> None:
    problems = []
    if shutil.which(sysconfig.get_config_var("CC").split()[0] if sysconfig.get_config_var(
            "CC") else "cc") is None:
        problems.append("no C compiler")
    if not (Path(sysconfig.get_paths()["include"]) / "Python.h").exists():
        problems.append("no Python.h")
    if problems:
        if IN_CI:
            pytest.fail("cannot build the compiled wheel: %s (.ci/run installs gcc)"
                        % ", ".join(problems))
        pytest.skip("cannot build the compiled wheel: %s" % ", ".join(problems))


def _copy_sources(target: Path) -> Path:
    target.mkdir()
    for name in SOURCES:
        source = PROJECT / name
        if source.is_dir():
            shutil.copytree(source, target / name, ignore=shutil.ignore_patterns(
                "__pycache__", "*.so", "*.pyd", "*.c"))
        else:
            shutil.copyfile(source, target / name)
    return target


def _pip_wheel(src: Path, out: Path, env_extra: dict[str, str],
               python: str = sys.executable) -> tuple[Path, str]:
    # As `pip install .` does: build isolation, setuptools and mypy from the package index.
    env = dict(os.environ, **env_extra)
    env.pop("PYTHONPATH", None)
    proc = subprocess.run(
        [python, "-m", "pip", "wheel", "-v", "--no-deps", "-w", str(out), str(src)],
        env=env, cwd=src, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    wheels = sorted(out.glob("kestimator-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0], proc.stdout + proc.stderr


def _compiled_venv(root: Path, python: str, version: tuple[int, int],
                   env_extra: dict[str, str] | None = None) -> str:
    """Build the compiled wheel with `python` (CPython `version`), install it into a fresh
    venv of that python without mypy; that venv's python. `env_extra`: the build's own
    environment (CC, CFLAGS)."""
    wheel, log = _pip_wheel(_copy_sources(root / "src"), root / "wheels",
                            {"KESTIMATOR_BUILD": "compiled", **(env_extra or {})}, python)
    # setup.py's float flags come after the user's on every compile of a C file.
    compiles = [line for line in log.splitlines() if " -c " in line and ".c -o " in line]
    assert compiles and all(
        line.rfind("-ffp-contract=off") > line.rfind("-ffp-contract=fast") for line in compiles)
    # Each group's C file at its level (gcc takes the last -O): the per-line path at -O3,
    # the commands and the kinematics at -O1; the comparisons below hold for both levels.
    levels = setup_py_module().GROUP_OPT_LEVELS
    assert levels["kestimator_core"] == "3"
    for group, level in levels.items():
        line = next(line for line in compiles if "__native_%s.c" % group in line)
        assert re.findall(r"(?<!\S)-O(\w)(?!\S)", line)[-1] == level, line
    assert [line.strip() for line in log.splitlines() if "kestimator build:" in line] == [
        line.strip() for line in log.splitlines() if COMPILED_LINE in line][:1]
    assert "-cp%d%d-" % version in wheel.name
    env_dir = root / "venv"
    subprocess.run([python, "-m", "venv", str(env_dir)], check=True, capture_output=True,
                   timeout=BUILD_TIMEOUT_S)
    venv_python = str(env_dir / "bin" / "python")
    subprocess.run([venv_python, "-m", "pip", "install", "-q", "--no-deps", str(wheel)],
                   check=True, capture_output=True, timeout=BUILD_TIMEOUT_S)
    return venv_python


@pytest.fixture(scope="module")
def compiled_python(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The python of a fresh venv holding the compiled wheel (and not mypy)."""
    _require_build_tools()
    return _compiled_venv(tmp_path_factory.mktemp("compiled"), sys.executable,
                          (sys.version_info[0], sys.version_info[1]))


# Builds with fused multiply-add allowed, as a user's CFLAGS (or aarch64's GCC, or clang on
# Apple Silicon) would have them: unguarded, GCC's gave 1471.918 s for OrcaSlicer's calicat
# where Klipper (and the pure build) give 1473.045 s. setup.py's flags must undo it.
FMA_BUILDS = {
    "gcc": {"CC": "gcc", "CFLAGS": "-march=haswell -ffp-contract=fast"},
    "clang": {"CC": "clang", "CFLAGS": "-mfma -ffp-contract=fast -ffast-math"},
}


@pytest.fixture(scope="module")
def compiled_fma_pythons(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Each FMA-allowed build's venv python, by compiler; the builds run side by side."""
    _require_build_tools()
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("the FMA-allowed builds use x86's -march=haswell / -mfma")
    with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
        if " fma" not in f.read():
            pytest.skip("this CPU has no FMA instructions")
    missing = [name for name in FMA_BUILDS if shutil.which(name) is None]
    if missing and IN_CI:
        pytest.fail("no %s for the FMA-allowed build (.ci/run installs it)" % missing)
    wanted = {name: env for name, env in FMA_BUILDS.items() if name not in missing}
    version = (sys.version_info[0], sys.version_info[1])
    with concurrent.futures.ThreadPoolExecutor(len(wanted)) as pool:
        futures = {name: pool.submit(_compiled_venv, tmp_path_factory.mktemp("fma_" + name),
                                     sys.executable, version, env)
                   for name, env in wanted.items()}
        return {name: future.result() for name, future in futures.items()}


def oldest_python() -> str | None:
    """A CPython 3.9 (the oldest we support, Raspberry Pi OS Bullseye's): $KESTIMATOR_PYTHON39,
    `python3.9` on PATH, or pyenv's, as this project's machines have it."""
    candidates = [os.environ.get("KESTIMATOR_PYTHON39", ""), shutil.which("python3.9") or ""]
    candidates += sorted(str(p) for p in Path.home().glob(".pyenv/versions/3.9*/bin/python3.9"))
    for candidate in candidates:
        if not candidate or not os.access(candidate, os.X_OK):
            continue
        probe = subprocess.run(
            [candidate, "-c", "import sys, sysconfig, os; sys.exit(not ("
             "sys.implementation.name == 'cpython' and sys.version_info[:2] == (3, 9) and "
             "os.path.exists(os.path.join(sysconfig.get_paths()['include'], 'Python.h'))))"],
            capture_output=True)
        if probe.returncode == 0:
            return candidate
    return None


@pytest.fixture(scope="module")
def compiled_python39(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A venv of CPython 3.9 holding the wheel compiled there."""
    _require_build_tools()
    python = oldest_python()
    if python is None:
        if IN_CI:
            pytest.fail("no CPython 3.9 with its headers to build the compiled wheel on "
                        "(set KESTIMATOR_PYTHON39)")
        pytest.skip("no CPython 3.9 with its headers")
    return _compiled_venv(tmp_path_factory.mktemp("compiled39"), python, (3, 9))


def test_the_wheel_holds_compiled_modules_and_says_compiled(compiled_python: str) -> None:
    proc = subprocess.run([compiled_python, "-m", "kestimator", "--version"],
                          capture_output=True, text=True, cwd="/", check=True)
    assert proc.stdout.strip().endswith("(compiled)")
    where = subprocess.run(
        [compiled_python, "-c", "import kestimator.toolhead as p, kestimator.gcode as g;"
         "print(p.__file__); print(g.SCAN_PLAIN_MOVES)"],
        capture_output=True, text=True, cwd="/", check=True).stdout.split()
    assert where[0].endswith(sysconfig.get_config_var("EXT_SUFFIX"))
    assert where[1] == "True"  # the compiled build parses moves with the byte scanner
    # ...while this checkout (the editable install the tests run) is the pure package.
    assert build() == "pure Python"


# Run by the compiled build: the worker's answers after changes at 50 % and 90 % of a file
# go on from checkpoints (the compiled planner pickles and loads again) and are the bytes
# of a whole pass (and of the pure build's answer, printed for the test to compare).
RESUME_SRC = """
import json, os, sys
from kestimator import worker
path, config = sys.argv[1], sys.argv[2]
size = os.path.getsize(path)
def ask(events):
    doc = worker.answer(worker._checked({"id": 1, "file": path, "config": config,
                                         "events": events, "use_table": False}))
    doc.pop("elapsed_s")
    return json.dumps(doc, sort_keys=True)
ask([])
resumable = worker._resumable
assert not resumable.disabled and len(resumable.checkpoints) > 10, resumable.checkpoints
events = [[size // 2, "M220 S150"], [size * 9 // 10, "SET_VELOCITY_LIMIT ACCEL=1500"]]
resumed = ask(events)
assert worker._resumable is resumable and resumable.resumed_at > 0
worker._resumable = None
assert resumed == ask(events)
print(resumed)
"""


def test_compiled_worker_resumes_from_checkpoints_with_whole_pass_bytes(
        compiled_python: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = CORPUS / "gcode" / "prusaslicer" / "gcodepreview_benchy_ps2.6.1.gcode"
    if not path.exists():
        pytest.skip("the shared corpus is not beside this checkout")
    isolate_user_environment(tmp_path, monkeypatch)
    compiled = subprocess.run([compiled_python, "-c", RESUME_SRC, str(path), str(CORPUS_CFG)],
                              capture_output=True, text=True, cwd="/", env=dict(os.environ),
                              timeout=BUILD_TIMEOUT_S)
    assert compiled.returncode == 0, compiled.stderr[-2000:]
    worker._resumable = None
    try:
        pure = worker.answer(worker._checked({
            "id": 1, "file": str(path), "config": str(CORPUS_CFG), "use_table": False,
            "events": [[path.stat().st_size // 2, "M220 S150"],
                       [path.stat().st_size * 9 // 10, "SET_VELOCITY_LIMIT ACCEL=1500"]]}))
    finally:
        worker._resumable = None
    pure.pop("elapsed_s")
    assert compiled.stdout.strip() == json.dumps(pure, sort_keys=True)


@pytest.mark.parametrize("path", compared_files(), ids=lambda p: p.parent.name + "/" + p.name)
def test_compiled_estimate_json_and_inject_bytes_equal_pure_on_corpus_file(
        compiled_python: str, path: Path) -> None:
    assert cli_outputs(compiled_python, path, on_path=False) == pure_cli_outputs(path)


def test_compiled_estimate_equals_pure_field_by_field_on_corpus_and_programs(
        compiled_python: str, tmp_path: Path) -> None:
    paths = compared_files() + generated_programs(tmp_path)
    compiled = digests(compiled_python, paths, on_path=False)
    pure = digests(sys.executable, paths)
    assert compiled[0] == '{"build": "compiled"}' and pure[0] == '{"build": "pure Python"}'
    assert len(compiled) == len(pure) == len(paths) + 1
    for path, a, b in zip(paths, compiled[1:], pure[1:]):
        assert a == b, path.name


@pytest.mark.parametrize("compiler", list(FMA_BUILDS))
def test_compiled_with_fused_multiply_add_allowed_equals_pure_on_the_whole_corpus(
        compiled_fma_pythons: dict[str, str], compiler: str, tmp_path: Path) -> None:
    # Totals, every layer, samples and marks bit for bit (tests/estimate_digest.py), the
    # `estimate --json` bytes and `inject`'s bytes, progress table included: every file.
    if compiler not in compiled_fma_pythons:
        pytest.skip("%s is not installed" % compiler)
    python = compiled_fma_pythons[compiler]
    paths = compared_files() + generated_programs(tmp_path)
    compiled = digests(python, paths, on_path=False)
    pure = digests(sys.executable, paths)
    assert compiled[0] == '{"build": "compiled"}' and len(compiled) == len(paths) + 1
    assert [path.name for path, a, b in zip(paths, compiled[1:], pure[1:]) if a != b] == []
    assert [path.name for path in compared_files()
            if cli_outputs(python, path, on_path=False) != pure_cli_outputs(path)] == []


def test_compiled_equals_pure_with_a_bed_mesh_and_skew_correction(
        compiled_python: str, tmp_path: Path) -> None:
    for cfg, paths in transform_runs(tmp_path):
        compiled = digests(compiled_python, paths, on_path=False, printer_cfg=cfg)
        pure = digests(sys.executable, paths, printer_cfg=cfg)
        assert compiled[0] == '{"build": "compiled"}'
        assert len(compiled) == len(pure) == len(paths) + 1
        for path, a, b in zip(paths, compiled[1:], pure[1:]):
            assert a == b, (cfg.parent.name, path.name)


def test_compiled_equals_pure_on_files_with_stops(compiled_python: str) -> None:
    """Each stop runs the look-ahead out (kestimator.stops): the same bits in both builds,
    on the real multi-colour files of tests/stop_refs with their printer.cfg."""
    from .test_stops import FILES, STOPS, STOPS_CFG

    paths = [STOPS / name for name in FILES]
    compiled = digests(compiled_python, paths, on_path=False, printer_cfg=STOPS_CFG)
    pure = digests(sys.executable, paths, printer_cfg=STOPS_CFG)
    assert compiled[0] == '{"build": "compiled"}'
    assert compiled[1:] == pure[1:]
    assert '"command": "PAUSE"' in pure[1] and '"command": "M25"' in pure[2]


def test_the_wheel_compiles_on_python_3_9_and_gives_the_same_fields(
        compiled_python39: str, tmp_path: Path) -> None:
    # mypy for 3.9 refused code 3.10+ accepted, and the build fell back to pure Python with
    # no word but under `pip -v` (issue 29 item 15): the 3.9 build must compile and agree.
    version = subprocess.run([compiled_python39, "-m", "kestimator", "--version"],
                             capture_output=True, text=True, cwd="/", check=True).stdout
    assert version.strip().endswith("(compiled)")
    paths = compared_files()[:6] + generated_programs(tmp_path)
    compiled = digests(compiled_python39, paths, on_path=False)
    pure = digests(sys.executable, paths)
    assert compiled[0] == '{"build": "compiled"}'
    for path, a, b in zip(paths, compiled[1:], pure[1:]):
        assert a == b, path.name


def test_without_a_c_compiler_the_same_build_installs_the_pure_package(
        tmp_path: Path) -> None:
    _require_build_tools()
    wheel, log = _pip_wheel(_copy_sources(tmp_path / "src"), tmp_path / "wheels",
                            {"CC": str(tmp_path / "no-such-compiler")})
    lines = [line.strip() for line in log.splitlines() if "kestimator build:" in line]
    assert len(lines) == 1 and lines[0].startswith(PURE_LINE), lines
    assert "C compiler" in lines[0]
    assert wheel.name.endswith("-py3-none-any.whl")


def test_with_too_little_memory_free_the_build_installs_the_pure_package_and_says_why(
        tmp_path: Path) -> None:
    _require_build_tools()
    wheel, log = _pip_wheel(_copy_sources(tmp_path / "src"), tmp_path / "wheels",
                            {"KESTIMATOR_BUILD_MEMORY_MIB": str(1 << 40)})
    lines = [line.strip() for line in log.splitlines() if "kestimator build:" in line]
    assert len(lines) == 1 and lines[0].startswith(PURE_LINE), lines
    assert "MiB of memory free (RAM and swap); compiling needs %d MiB" % (1 << 40) in lines[0]
    assert wheel.name.endswith("-py3-none-any.whl")


def test_every_compiled_module_is_in_exactly_one_mypyc_group() -> None:
    # A module left out of setup.py's GROUPS would be compiled apart (mypyc's runtime once
    # more) or not as planned; one in two groups would be two extensions of one name.
    setup_py = setup_py_module()
    grouped = [module for modules, _ in setup_py.GROUPS for module in modules]
    assert sorted(grouped) == sorted(setup_py.COMPILED_MODULES)
    assert len(set(grouped)) == len(grouped)
    assert len({name for _, name in setup_py.GROUPS}) == len(setup_py.GROUPS)


@pytest.mark.parametrize(("available_mib", "cpus", "jobs"), [
    (280, 4, 1),     # a small board: one compiler at a time, as the 300 MiB bar was measured
    (540, 4, 1),     # not yet room for a second cc1 (COMPILE_JOB_MIB) beside the install
    (560, 1, 1),     # one CPU: nothing to gain
    (560, 2, 2),     # the README's 2-CPU host with memory: both CPUs compile
    (24000, 2, 2),
    (24000, 8, 8),
])
def test_c_files_compile_side_by_side_only_where_cpus_and_ram_allow(
        available_mib: int, cpus: int, jobs: int, monkeypatch: pytest.MonkeyPatch) -> None:
    setup_py = setup_py_module()
    monkeypatch.delenv("KESTIMATOR_BUILD_JOBS", raising=False)
    monkeypatch.delenv("KESTIMATOR_BUILD_MEMORY_MIB", raising=False)
    # Swap does not count: a compile that swaps is slower than one after the other.
    monkeypatch.setattr(setup_py, "_meminfo_mib",
                        lambda: {"MemAvailable": available_mib, "SwapFree": 4096})
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cpus)))
    assert setup_py.compile_jobs() == jobs
    monkeypatch.setenv("KESTIMATOR_BUILD_JOBS", "3")
    assert setup_py.compile_jobs() == 3
