"""`textsearch.search` finds exactly what `pattern.search` finds, only faster."""

from __future__ import annotations

import importlib
import pkgutil
import re

import pytest

import kestimator.slicers
from kestimator.slicers import read_file_ends
from kestimator.textsearch import _literal, search

from .conftest import CORPUS

MODULES = ["kestimator.cli_output", "kestimator.rewrite", "kestimator.slicers.base"] + [
    "kestimator.slicers." + m.name for m in pkgutil.iter_modules(kestimator.slicers.__path__)]


def _patterns() -> list[re.Pattern[str] | re.Pattern[bytes]]:
    """Every compiled pattern the slicer adapters, the output and the rewriter hold."""
    found: dict[int, re.Pattern[str] | re.Pattern[bytes]] = {}
    for name in MODULES:
        for value in vars(importlib.import_module(name)).values():
            items = value if isinstance(value, (list, tuple)) else (value,)
            for item in items:
                item = item[1] if isinstance(item, tuple) and len(item) > 1 else item
                if isinstance(item, re.Pattern):
                    found[id(item)] = item
    return list(found.values())


def _same(pattern: re.Pattern[str] | re.Pattern[bytes], text: str | bytes) -> None:
    expected = pattern.search(text)  # type: ignore[arg-type]
    got = search(pattern, text)  # type: ignore[arg-type]
    assert (got is None) == (expected is None), (pattern.pattern, text[:80])
    if got is not None and expected is not None:
        assert got.span() == expected.span() and got.groups() == expected.groups()


def test_every_slicer_pattern_finds_the_same_match_in_every_corpus_file() -> None:
    patterns = _patterns()
    assert len(patterns) > 30
    assert sum(_literal(p) is not None for p in patterns) > 10  # the shortcut is used
    files = sorted(CORPUS.glob("gcode/*/*.gcode"))
    assert files
    for path in files:
        head, tail = read_file_ends(str(path))
        for data in (head, tail):
            text = data.decode("utf-8", "replace")
            for pattern in patterns:
                _same(pattern, data if isinstance(pattern.pattern, bytes) else text)


@pytest.mark.parametrize("source, flags, text", [
    (r"^;TIME:(\d+)", re.M, "x ;TIME:1\n;TIME:2\n"),           # literal mid-line first
    (r"^;TIME:(\d+)", re.M, ";TIME:x\n;TIME:7"),               # first line start fails
    (r"^;TIME:(\d+)", re.M, ";TIME:5"),                         # at the very start
    (r"^ab*c", re.M, "ac\nabbc"),                               # quantifier on the last char
    (r"^abc|x", re.M, "zzx\nabc"),                              # alternation: no shortcut
    (r"^abc", 0, "q\nabc"),                                     # not MULTILINE: no shortcut
    (r"^abc", re.M | re.I, "ABC"),                              # case-insensitive: none
    (rb"^; kes(\w+)", re.M, b";; kes\n; kestimator"),           # bytes
])
def test_search_equals_pattern_search_on_edge_cases(source: str, flags: int,
                                                     text: str) -> None:
    _same(re.compile(source, flags), text)
