"""Shared paths (the corpus is read in place from ../shared beside the checkout), and how the
suite is spread over two processes (pytest-xdist, `-n 2 --dist loadfile` in pyproject.toml)."""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path
from typing import Any

import pytest

PROJECT = Path(__file__).resolve().parents[1]
SHARED = PROJECT.parent / "shared"
CORPUS = SHARED / "corpus"
CORPUS_CFG = CORPUS / "printer.cfg"
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


# Long test files start first, so neither process is left with a long file at the end
# (`--dist loadfile`: a file's tests run in one process, in order, so its module-scoped
# fixtures run once; `--no-loadscope-reorder` keeps this order); the rest follow in file
# order. The real-time prints mostly wait on the wall clock, so they start first and leave
# most of a core to the other process. Each file's time in a whole run: benchmarks/RESULTS.md.
LONGEST_FIRST = (
    "test_klipper_module_realtime.py",
    "test_arm_chroot.py",
    "test_compiled_build.py",
    "test_cura_gui.py",
    "test_pypy.py",
    "test_accuracy_corpus.py",
    "test_klipper_module_real.py",
    "test_moonraker_e2e.py",
    "test_hook_prusaslicer.py",
    "test_code_quality.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The longest files first (a stable sort: the rest keep their order)."""
    rank = {name: index for index, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


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


def load_cura_build_script() -> Any:
    """plugins/cura/build.py, under a name no installed module has."""
    spec = importlib.util.spec_from_file_location(
        "kestimator_cura_build", PROJECT / "plugins" / "cura" / "build.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
