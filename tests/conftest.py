"""Shared paths (the corpus is read in place from ../shared beside the checkout); how the
suite is spread over processes (pytest-xdist, `-n 3 --dist loadfile` in pyproject.toml: the
files longest first by tests/file_times.json, which `--record-file-times` writes); what a run
makes once for all of them (once_per_run)."""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import json
import os
import resource
import shutil
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import pytest

PROJECT = Path(__file__).resolve().parents[1]
SHARED = PROJECT.parent / "shared"
CORPUS = SHARED / "corpus"
CORPUS_CFG = CORPUS / "printer.cfg"
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


# Each test file's seconds in a whole run (tests/file_times.json, written by
# `pytest --record-file-times tests/file_times.json`) order the files (`--dist loadfile`: a
# file's tests run in one process, in order, so its module-scoped fixtures run once;
# `--no-loadscope-reorder` keeps this order), so that no process is left with a long file at
# the end: first a file not in it yet (a new one: it may be long), then the files marked
# `wall_clock` (their time is the clock's, which their CPU seconds do not show: the real-time
# prints, a GUI's processes), then the rest by CPU seconds, the most first. CPU seconds, not
# wall: on a shared machine the wall time of a file that computes is mostly the others' load.
FILE_TIMES = PROJECT / "tests" / "file_times.json"
WALL_CLOCK = "wall_clock"


def recorded_file_times(path: Path | None = None) -> dict[str, dict[str, Any]]:
    """{test file name: {"wall_s", "cpu_s", "tests", "wall_clock"}} as recorded in `path`
    (FILE_TIMES); empty without the file."""
    try:
        with open(path or FILE_TIMES, encoding="utf-8") as f:
            data: dict[str, dict[str, Any]] = json.load(f)
    except FileNotFoundError:
        return {}
    return data


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files not timed yet first, then those marked wall_clock, then the rest by recorded CPU
    seconds, the most first; a file's tests keep their order (a stable sort)."""
    times = recorded_file_times()
    clock_bound = {item.path.name for item in items if item.get_closest_marker(WALL_CLOCK)}

    def rank(item: pytest.Item) -> tuple[int, float]:
        name = item.path.name
        if name not in times:
            return (0, 0.0)
        if name in clock_bound:
            return (1, -float(times[name]["wall_s"]))
        return (2, -float(times[name]["cpu_s"]))

    items.sort(key=rank)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--record-file-times", metavar="PATH", default=None,
        help="write each test file's seconds in this run (wall: its tests' setup, call and "
             "teardown; CPU: the process's and its waited-for children's) into PATH (JSON), "
             "keeping the files this run did not run")


_CPU_START = pytest.StashKey[float]()


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.config.getoption("record_file_times"):
        item.stash[_CPU_START] = _cpu_s()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    outcome = yield
    if call.when == "teardown" and _CPU_START in item.stash:
        # Carried to the controlling process with the report (pytest-xdist).
        report = outcome.get_result()
        report.user_properties.append(("cpu_s", _cpu_s() - item.stash[_CPU_START]))
        if item.get_closest_marker(WALL_CLOCK):
            report.user_properties.append((WALL_CLOCK, True))


_RUN_TIMES: dict[str, dict[str, float]] = {}
_RUN_CLOCK_BOUND: set[str] = set()
_CONTROLLER: list[bool] = []  # [True] in the process the reports end up in


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Sums each file's seconds where the reports end up (not in pytest-xdist's workers)."""
    if not _CONTROLLER:
        return
    name = report.nodeid.split("::")[0].rsplit("/", 1)[-1]
    entry = _RUN_TIMES.setdefault(name, {"wall_s": 0.0, "cpu_s": 0.0, "tests": 0})
    entry["wall_s"] += report.duration
    for key, value in report.user_properties:
        if key == "cpu_s" and isinstance(value, float):
            entry["cpu_s"] += value
        if key == WALL_CLOCK:
            _RUN_CLOCK_BOUND.add(name)
    if report.when == "teardown":
        entry["tests"] += 1


def pytest_sessionfinish(session: pytest.Session) -> None:
    target = session.config.getoption("record_file_times")
    if not target or not _CONTROLLER or not _RUN_TIMES:
        return
    times = recorded_file_times(Path(target))
    for name, entry in _RUN_TIMES.items():
        times[name] = {"wall_s": round(entry["wall_s"], 3), "cpu_s": round(entry["cpu_s"], 3),
                       "tests": int(entry["tests"]), WALL_CLOCK: name in _RUN_CLOCK_BOUND}
    ordered = dict(sorted(times.items(), key=lambda kv: (-kv[1]["cpu_s"], kv[0])))
    Path(target).write_text(json.dumps(ordered, indent=1) + "\n", encoding="utf-8")


# What a whole run makes once and every process reads (once_per_run): a folder the
# controlling process makes, named to pytest-xdist's workers by this variable.
RUN_FOLDER_ENV = "KESTIMATOR_TEST_RUN_FOLDER"
_RUN_FOLDER = pytest.StashKey[str]()
T = TypeVar("T")


def pytest_configure(config: pytest.Config) -> None:
    if not hasattr(config, "workerinput"):  # the controlling process (or the only one)
        folder = tempfile.mkdtemp(prefix="kestimator-tests-")
        config.stash[_RUN_FOLDER] = folder
        os.environ[RUN_FOLDER_ENV] = folder  # pytest-xdist's workers start after this
        _CONTROLLER.append(True)
        compile_checkout_bytecode()
        compile_klipper_bytecode()


# The checkout's package, as the tests' programs import it (`python -m kestimator`, PyPy,
# estimate_digest.py, pytest-xdist's workers): hundreds of processes in a run.
BYTECODE_DIRS = ("kestimator",)


def compile_checkout_bytecode() -> None:
    """Compile the checkout's package to bytecode beside its sources, for this Python and
    for PyPy when it is installed, as `pip install` does for an installed package: with
    PYTHONDONTWRITEBYTECODE set (as on this project's machines) every process of a run
    would otherwise compile it afresh (about 0.13 s of CPython's start-up and 0.16 s of
    PyPy's). Each interpreter still checks the source against its bytecode when it imports
    it; __pycache__ is ignored by git and left out of every package built from the
    checkout."""
    import compileall
    import subprocess

    for name in BYTECODE_DIRS:
        compileall.compile_dir(str(PROJECT / name), quiet=2)
    pypy = shutil.which("pypy3")
    if pypy is not None:
        subprocess.run([pypy, "-m", "compileall", "-q", *(str(PROJECT / name)
                                                           for name in BYTECODE_DIRS)],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600,
                       check=False)


def pytest_unconfigure(config: pytest.Config) -> None:
    folder = config.stash.get(_RUN_FOLDER, None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)


# Each Klipper tree the tests start (the oracle's 84104bbbd, the releases, Kalico; .ci/run's
# variables, else where tests/test_klipper_module_releases.py looks) with the variable naming
# its Python.
KLIPPER_TREES = (
    ("ORACLE_KLIPPER", str(Path.home() / "oracle" / "klipper"), "ORACLE_PYTHON"),
    ("ORACLE_KLIPPER_V0_12_0", "/var/tmp/oracle-v0.12.0/klipper", "ORACLE_PYTHON"),
    ("ORACLE_KLIPPER_V0_13_0", "/var/tmp/oracle-v0.13.0/klipper", "ORACLE_PYTHON"),
    ("ORACLE_KALICO", "/var/tmp/oracle-kalico/kalico", "ORACLE_KALICO_PYTHON"),
)
_KLIPPER_COMPILE = """
import compileall, os, sys
for top, dirs, files in os.walk(sys.argv[1]):
    for name in files:
        path = os.path.join(top, name)
        if name.endswith(".py") and not os.path.islink(path):
            compileall.compile_file(path, quiet=2)
"""


def compile_klipper_bytecode() -> None:
    """Compile each Klipper tree's own modules (klippy/, its regular files: not what a test
    links into extras/) to bytecode beside them, with the Python that runs it, as Klipper
    itself would on its first start on a host: with PYTHONDONTWRITEBYTECODE set, every
    Klipper a test starts would otherwise compile them afresh (about 0.15 s of each
    start). Up-to-date bytecode is left as it is."""
    import subprocess

    default_python = str(Path.home() / "oracle" / "venv" / "bin" / "python")
    for tree_env, tree_default, python_env in KLIPPER_TREES:
        klippy = Path(os.environ.get(tree_env, tree_default)) / "klippy"
        python = os.environ.get(python_env, default_python)
        if python_env == "ORACLE_KALICO_PYTHON" and python_env not in os.environ:
            python = "/var/tmp/oracle-kalico/venv/bin/python"
        if not (klippy / "klippy.py").is_file() or not os.access(python, os.X_OK):
            continue
        subprocess.run([python, "-c", _KLIPPER_COMPILE, str(klippy)],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600,
                       check=False)


def once_per_run(name: str, make: Callable[[Path], T]) -> T:
    """What `make(folder)` returns (JSON data), made once in a whole run, in the first
    process that asks; the others wait for it and read it (pytest-xdist's workers would each
    make it). A `make` that raises (a skip, a failure) leaves nothing: the next one asking
    tries again. `folder` is empty, kept to the end of the run."""
    given = os.environ.get(RUN_FOLDER_ENV)
    if not given or not os.path.isdir(given):  # not under this conftest's pytest
        return make(Path(tempfile.mkdtemp(prefix="kestimator-once-")))
    key = hashlib.sha256(name.encode()).hexdigest()[:24]
    root = Path(given)
    done = root / (key + ".json")
    with open(root / (key + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if done.exists():
            value: T = json.loads(done.read_text(encoding="utf-8"))
            return value
        folder = root / key
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
        value = make(folder)
        part = root / (key + ".part")
        part.write_text(json.dumps(value), encoding="utf-8")
        part.replace(done)
        return value


def corpus_files(pattern: str = "*/*.gcode") -> list[Path]:
    """Corpus G-code files, sorted; empty when the corpus is absent."""
    return sorted((CORPUS / "gcode").glob(pattern))


@pytest.fixture(scope="session")
def corpus_root() -> Path:
    if not CORPUS.is_dir():
        if IN_CI:
            pytest.fail("the shared corpus is missing at %s" % CORPUS)
        pytest.skip("the shared corpus is not beside this checkout")
    return CORPUS


def isolate_user_environment(home: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A run as a new user would make it: `home` as HOME with its own config and cache, no
    profile, no slicer hook environment (SLIC3R_*), no forced rich."""
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home / "config"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(home / "cache"))
    from kestimator.cli import RICH_ENV

    monkeypatch.delenv(RICH_ENV, raising=False)
    for name in [name for name in os.environ if name.startswith("SLIC3R_")]:
        monkeypatch.delenv(name)
    return home


def require_program(name: str) -> str:
    """The path of a program a test drives: skipped without it, but under CI it must be there
    (.ci/run installs it)."""
    found = shutil.which(name)
    if found is None:
        if IN_CI:
            pytest.fail("%s is not installed (.ci/run installs it)" % name)
        pytest.skip("%s is not installed" % name)
    return found


def require_klipper() -> tuple[str, str]:
    """(Klipper tree, its Python) of the oracle's Klipper 84104bbbd (ORACLE_KLIPPER /
    ORACLE_PYTHON, or ~/oracle): skipped without it, but under CI it must be there
    (.ci/run builds it with .ci/klipper-setup from ../shared/upstream)."""
    import sys

    sys.path.insert(0, str(PROJECT / "tests" / "klipper_module"))
    import run_print

    paths = run_print.oracle_paths()
    if paths is None:
        if IN_CI:
            pytest.fail("the oracle's Klipper is not set up (.ci/klipper-setup builds it)")
        pytest.skip("the oracle's Klipper is not set up here (.ci/klipper-setup)")
    return paths


# The Klipper releases the module runs on (tests/test_klipper_module_releases.py, and
# tests/test_klipper_module_realtime.py at wall-clock speed), and what each release's git
# checkout reports as its version (klippy's util.get_git_version): the tarballs the trees are
# built from have no .git, so klippy/.version says it, as Klipper's own release packaging
# does; the module hands it to its worker, which times the print with that release's rules
# (limits.klipper_release). 84104bbbd reports "?" (today's rules).
RELEASES = ["v0.12.0", "v0.13.0", "84104bbbd", "kalico-v2026.07.00"]
RELEASE_VERSIONS = {"v0.12.0": "v0.12.0-0-g0d67d9c4", "v0.13.0": "v0.13.0-0-g61c0c8d2",
                    "kalico-v2026.07.00": "v2026.07.00-0-g30c65e09"}


def require_release(release: str) -> tuple[tuple[str, str], str]:
    """((Klipper tree, its Python), printer.cfg) of `release` (one of RELEASES), built as
    .ci/klipper-setup builds 84104bbbd, its place taken from ORACLE_KLIPPER_V0_12_0,
    ORACLE_KLIPPER_V0_13_0, ORACLE_KALICO and ORACLE_KALICO_PYTHON (defaults:
    /var/tmp/oracle-<release>/); its printer.cfg the one tests/oracle_refs_releases/ made
    its references with. Skipped when the tree is not built here, but under CI it must be
    (.ci/run builds it)."""
    if release == "84104bbbd":
        return require_klipper(), str(CORPUS_CFG)
    oracle = require_klipper()
    refs = PROJECT / "tests" / "oracle_refs_releases"
    if release.startswith("kalico-"):
        tree = os.environ.get("ORACLE_KALICO", "/var/tmp/oracle-kalico/kalico")
        python = os.environ.get("ORACLE_KALICO_PYTHON", "/var/tmp/oracle-kalico/venv/bin/python")
        cfg = refs / release / "printer.cfg"
    else:
        tree = os.environ.get("ORACLE_KLIPPER_" + release.upper().replace(".", "_"),
                              "/var/tmp/oracle-%s/klipper" % release)
        python = oracle[1]
        cfg = refs / ("klipper-" + release) / "printer.cfg"
    if not (os.path.exists(os.path.join(tree, "out", "klipper.dict"))
            and os.path.exists(python)):
        if IN_CI:
            pytest.fail("the %s tree is not built at %s (.ci/run builds it)" % (release, tree))
        pytest.skip("the %s tree is not built here (%s)" % (release, tree))
    _report_version(tree, RELEASE_VERSIONS[release])
    return (tree, python), str(cfg)


def _report_version(tree: str, version: str) -> None:
    """`tree`'s klippy/.version says `version` (written once, atomically)."""
    path = os.path.join(tree, "klippy", ".version")
    try:
        with open(path) as f:
            if f.read().strip() == version:
                return
    except OSError:
        pass
    tmp = "%s.%d.tmp" % (path, os.getpid())
    with open(tmp, "w") as f:
        f.write(version + "\n")
    os.replace(tmp, path)


def load_script(name: str, path: Path) -> Any:
    """The script at `path` (a benchmark, a build script) imported as module `name`, a name
    no installed module has; registered in sys.modules, where its dataclasses look it up."""
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def load_cura_build_script() -> Any:
    """plugins/cura/build.py, under a name no installed module has."""
    return load_script("kestimator_cura_build", PROJECT / "plugins" / "cura" / "build.py")


def without_progress_table(data: bytes) -> bytes:
    """An injected file's bytes without the progress table that ends it (kestimator.
    progress_table), for tests that compare what inject does to the file's own lines."""
    import io

    from kestimator.progress_table import TableError, read_table

    try:
        table = read_table(io.BytesIO(data))
    except TableError:
        return data
    # What follows the table (a slicer's settings block, a post-processor's line) stays.
    start = table.content_bytes
    lines = int(data[start:data.index(b"\n", start)].split(b" lines=")[1].split()[0])
    end = start
    for _ in range(lines + 1):
        end = data.index(b"\n", end) + 1
    return data[:start] + data[end:]
