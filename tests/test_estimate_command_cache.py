"""The cache of parsed non-move lines (`Timeline._commands`) changes no result and stays
within its bound."""

from __future__ import annotations

import dataclasses

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import Estimate, Timeline
from kestimator.limits import Limits

from .conftest import CORPUS_CFG


def assert_identical(a: Estimate, b: Estimate) -> None:
    da, db = dataclasses.asdict(a), dataclasses.asdict(b)
    for key in da:
        assert da[key] == db[key], key
    # == treats 0.0 and -0.0 alike and arrays compare by value: compare the bits too.
    assert a.total_s.hex() == b.total_s.hex()
    assert a.sample_times.tobytes() == b.sample_times.tobytes()


@pytest.fixture(scope="module")
def limits() -> Limits:
    return limits_from_printer_cfg(CORPUS_CFG)[0]


def test_command_cache_changes_nothing_and_stays_bounded(limits: Limits,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from kestimator import estimate

    program = []
    for i in range(3000):
        program += ["M204 S%d" % (500 + i % 2500), "G1 X%d Y%d F6000" % (i % 50, i % 7), "G10",
                    "G1 X%d" % (i % 13), "G11", "SET_VELOCITY_LIMIT ACCEL=%d" % (1000 + i)]
    lines = [(line + "\n").encode() for line in program]
    timeline = Timeline(limits, "x.gcode", sample=True)
    timeline.feed_lines(lines)
    cached = timeline.finish()
    assert 0 < len(timeline._commands) <= estimate.MAX_CACHED_COMMANDS
    monkeypatch.setattr(estimate, "MAX_CACHED_COMMAND_CHARS", -1)  # no line is cached
    timeline = Timeline(limits, "x.gcode", sample=True)
    timeline.feed_lines(lines)
    assert not timeline._commands
    assert_identical(timeline.finish(), cached)
