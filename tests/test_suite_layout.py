"""How the suite is spread over processes (pyproject.toml's addopts, tests/conftest.py): two
pytest-xdist processes, each test file in one of them, the longest files first."""

from __future__ import annotations

import sys
from types import SimpleNamespace

from .conftest import LONGEST_FIRST, PROJECT, pytest_collection_modifyitems

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib


def test_the_suite_runs_in_two_processes_a_file_in_one_of_them() -> None:
    options = tomllib.loads((PROJECT / "pyproject.toml").read_text())["tool"]["pytest"][
        "ini_options"]["addopts"]
    assert options == ["-n", "2", "--dist", "loadfile", "--no-loadscope-reorder"]
    extras = tomllib.loads((PROJECT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]["test"]
    assert any(extra.startswith("pytest-xdist") for extra in extras)


def test_every_file_started_first_is_a_test_file_of_the_suite() -> None:
    assert len(set(LONGEST_FIRST)) == len(LONGEST_FIRST)
    for name in LONGEST_FIRST:
        assert (PROJECT / "tests" / name).is_file(), name


def test_the_longest_files_are_collected_first_and_the_rest_keep_their_order() -> None:
    collected = [SimpleNamespace(path=PROJECT / "tests" / name, n=n) for n, name in enumerate(
        ["test_a.py", LONGEST_FIRST[1], "test_b.py", LONGEST_FIRST[0], "test_a.py",
         LONGEST_FIRST[1]])]
    items = list(collected)
    pytest_collection_modifyitems(items)  # type: ignore[arg-type]
    assert [item.n for item in items] == [3, 1, 5, 0, 2, 4]
