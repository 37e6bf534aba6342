"""The progress table (issue 27): its encoding, the interpolation bound on real estimates,
the reader that reads only the file's end, and the table `inject` writes at the end of its
output (offsets of the output, one table after re-runs, refused once the file is edited)."""

from __future__ import annotations

import dataclasses
import io
import os
import random
import shutil
import tracemalloc
from array import array
from pathlib import Path
from typing import Any

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file
from kestimator.progress_table import (
    COMPARE_BYTES,
    HEADER_PREFIX,
    MAX_NAME_BYTES,
    MAX_OBJECT_POINTS,
    MAX_OBJECTS,
    MAX_PAYLOAD_BYTES,
    MAX_TABLE_POINTS,
    MAX_TIME_POINTS,
    MAX_TRAILING_BYTES,
    TAIL_WINDOWS,
    ProgressTable,
    Selection,
    TableError,
    _candidates,
    _thin,
    common_prefix,
    decode_block,
    describe_differences,
    line_offsets,
    line_offsets_along,
    line_offsets_from,
    lines_at_offsets,
    read_table,
    read_table_file,
    select,
    setting_text,
    settings_differences,
    settings_digest,
    spacing_bound,
)
from kestimator.rewrite import inject_file

from .conftest import CORPUS_CFG
from .table_forgery import forge_payload, forged_block, huge_table_payload

FILES = ["prusaslicer/ps25_nut_accelA_small.gcode",
         "prusaslicer/cancelobj_ps2.4.0a1_arcwelder.gcode",
         "prusaslicer/libbgcode_mini_cube_ps2.8.1_arcs.gcode",
         "cura/gcodepreview_puzzle_cura2.3.1.gcode",
         "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode"]


@pytest.fixture(scope="module")
def limits():  # type: ignore[no-untyped-def]
    return limits_from_printer_cfg(CORPUS_CFG)[0]


def _table() -> ProgressTable:
    return ProgressTable(total_s=1234.567, content_bytes=10_000_000,
                         offsets=[0, 1, 200, 70_000, 9_999_999, 10_000_000],
                         times=[0.0, 0.0, 0.25, 600.125, 1234.0, 1234.567],
                         object_names=["cube", "näme with spaces; and = signs\t", ""],
                         object_offsets=[100, 5000, 9_000_000],
                         object_remaining=[[500.0, 400.5, 0.0], [20.0, 10.0, 0.001],
                                           [0.0, 0.0, 0.0]])


def test_encoding_round_trips_offsets_times_and_objects() -> None:
    table = _table()
    for eol in (b"\n", b"\r\n"):
        block = table.encode(eol)
        assert all(len(line) <= 5 + 200 for line in block.splitlines()[1:])
        back = decode_block(block, table.content_bytes)
        assert back == table  # times are whole milliseconds already


def test_time_at_interpolates_by_bytes_and_clamps() -> None:
    table = _table()
    assert table.time_at(0) == 0.0
    assert table.time_at(100) == pytest.approx(0.25 * 99 / 199)
    assert table.time_at(10_000_000) == 1234.567
    assert table.time_at(20_000_000) == 1234.567
    assert table.objects_remaining_at(0)["cube"] == 500.0
    assert table.objects_remaining_at(5000)["cube"] == 400.5
    assert table.objects_remaining_at(10_000_000)["cube"] == 0.0


@pytest.mark.parametrize("damage", ["crc", "version", "moved", "after", "cut"])
def test_a_damaged_or_moved_table_is_refused(damage: str) -> None:
    table = _table()
    block = table.encode()
    offset = table.content_bytes
    if damage == "crc":
        lines = block.split(b"\n")
        lines[1] = lines[1][:10] + (b"A" if lines[1][10:11] != b"A" else b"B") + lines[1][11:]
        block = b"\n".join(lines)
    elif damage == "version":
        block = block.replace(b"v1 ", b"v2 ", 1)
    elif damage == "moved":
        offset += 1
    elif damage == "after":
        block += b"G1 X10\n"
    else:
        block = block[:len(block) // 2]
    with pytest.raises(TableError):
        decode_block(block, offset)


# A small table as the writer writes it (issue 33): 1000 bytes, 100 s, two objects.
VALID: dict[str, Any] = {"content_bytes": 1000, "total_ms": 100_000,
         "points": [(0, 0), (500, 40_000), (1000, 100_000)],
         "names": [b"A", b"B"], "object_offsets": [100, 600],
         "remaining_ms": [[60_000, 20_000], [30_000, 0]]}


def test_the_forged_payload_is_the_writers_own_for_a_table_it_writes() -> None:
    table = ProgressTable(total_s=100.0, content_bytes=1000, offsets=[0, 500, 1000],
                          times=[0.0, 40.0, 100.0], object_names=["A", "B"],
                          object_offsets=[100, 600],
                          object_remaining=[[60.0, 20.0], [30.0, 0.0]])
    assert forge_payload(**VALID) == table.payload()
    assert decode_block(forged_block(table.payload(), 1000), 1000) == table


# Each a value the writer never writes (the negative time left once raised the Klipper
# module's time left from 100 s to 1,000,100 s when that object was excluded).
NEVER_WRITTEN: dict[str, dict[str, Any]] = {
    "negative object time left": {"remaining_ms": [[-1_000_000_000, 0], [30_000, 0]]},
    "object time left past the total": {"remaining_ms": [[200_000, 0], [30_000, 0]]},
    "object time left that grows": {"remaining_ms": [[20_000, 60_000], [30_000, 0]]},
    "time past the total": {"points": [(0, 0), (500, 40_000), (1000, 150_000)]},
    "offset past the file": {"points": [(0, 0), (500, 40_000), (2000, 100_000)]},
    "first offset not 0": {"points": [(10, 0), (500, 40_000), (1000, 100_000)]},
    "object offset past the file": {"object_offsets": [100, 2000]},
    "object named twice": {"names": [b"A", b"A"]},
    "objects without object points": {"names": [b"A"], "object_offsets": [],
                                      "remaining_ms": [[]]},
}


@pytest.mark.parametrize("damage", sorted(NEVER_WRITTEN))
def test_a_table_with_a_value_the_writer_never_writes_is_refused(damage: str) -> None:
    fields = dict(VALID, **NEVER_WRITTEN[damage])
    with pytest.raises(TableError):
        ProgressTable.from_payload(forge_payload(**fields))
    with pytest.raises(TableError):
        decode_block(forged_block(forge_payload(**fields), 1000), 1000)


def test_a_number_longer_than_64_bits_is_refused() -> None:
    with pytest.raises(TableError, match="too long"):
        ProgressTable.from_payload(b"\x01" + b"\xff" * 10 + b"\x01")


def _over(what: str) -> dict[str, Any]:
    """VALID's fields with one count a step past the writer's limit."""
    if what == "time points":
        n = MAX_TABLE_POINTS + 1
        return dict(VALID, content_bytes=n, total_ms=n, points=[(i, i) for i in range(n)],
                    object_offsets=[1, 2])
    if what == "objects":
        return dict(VALID, names=[b"O%d" % i for i in range(MAX_OBJECTS + 1)],
                    remaining_ms=[[2, 1]] * (MAX_OBJECTS + 1))
    if what == "object points":
        n = MAX_OBJECT_POINTS + 1
        return dict(VALID, names=[b"A"], object_offsets=list(range(1, n + 1)),
                    remaining_ms=[[0] * n])
    return dict(VALID, names=[b"A", b"\xc3\xa9" * (MAX_NAME_BYTES // 2) + b"x"])


@pytest.mark.parametrize("what", ["time points", "objects", "object points",
                                  "bytes in an object name"])
def test_a_table_past_the_writers_limits_is_refused(what: str) -> None:
    with pytest.raises(TableError, match="over the limit"):
        ProgressTable.from_payload(forge_payload(**_over(what)))


def test_a_table_at_the_writers_limits_is_read() -> None:
    n = MAX_TABLE_POINTS
    names = ["%04d" % i + "é" * ((MAX_NAME_BYTES - 4) // 2) for i in range(MAX_OBJECTS)]
    assert max(len(name.encode()) for name in names) == MAX_NAME_BYTES
    table = ProgressTable(
        total_s=float(n * 1000), content_bytes=n * 100_000,
        offsets=[i * 100_000 for i in range(n)], times=[float(i * 997 % 1000 + i * 1000)
                                                      / 1000 for i in range(n)],
        object_names=names, object_offsets=[i * 7777 for i in range(1, MAX_OBJECT_POINTS + 1)],
        object_remaining=[[(MAX_OBJECT_POINTS - j) * 13_001 / 1000 for j in
                           range(MAX_OBJECT_POINTS)] for _ in names])
    assert len(table.payload()) <= MAX_PAYLOAD_BYTES
    assert decode_block(table.encode(), table.content_bytes) == table


def test_a_table_declaring_millions_of_values_is_refused_before_they_are_read() -> None:
    payload = huge_table_payload(10_000, objects=1000, points=1000)
    tracemalloc.start()
    try:
        with pytest.raises(TableError, match="over the limit"):
            ProgressTable.from_payload(payload)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 256 << 10, peak  # the declared million values would take over 30 MB
    # Its lines: the payload is past what any table within the limits decodes to.
    with pytest.raises(TableError):
        decode_block(forged_block(huge_table_payload(10_000), 10_000), 10_000)


def test_select_leaves_out_objects_past_the_limits_and_counts_them() -> None:
    class Fake:
        total_s = 1000.0
        n_lines = 10
        sample_lines = [2, 5]
        sample_times = [100.0, 900.0]
        layers = [(3, 200.0)]
        tail_lines: list[int] = []
        tail_times: list[float] = []
        object_remaining = [(3, 200.0, {
            "A" * MAX_NAME_BYTES: 10.0,          # at the limit: kept
            "B" * (MAX_NAME_BYTES + 1): 500.0,   # over it: left out, not shortened
            "é" * (MAX_NAME_BYTES // 2 + 1): 400.0,  # over it in UTF-8 bytes
            "\udcff" * MAX_NAME_BYTES: 300.0,    # undecodable bytes count as bytes
            "\ud800": 200.0,                      # cannot be written at all
        })]

    selection = select(Fake())
    assert selection.object_names == ["\udcff" * MAX_NAME_BYTES, "A" * MAX_NAME_BYTES]
    assert selection.objects_left_out == 3

    class Many(Fake):
        object_remaining = [(3, 200.0, {"O%03d" % i: float(i) for i in range(MAX_OBJECTS + 5)})]

    selection = select(Many())
    assert len(selection.object_names) == MAX_OBJECTS
    assert selection.objects_left_out == 5
    assert "O000" not in selection.object_names  # the shortest go


def test_comment_lines_after_the_table_are_allowed() -> None:
    table = _table()
    block = table.encode() + b"; Processed by klipper_estimator 0.1.0\n\n"
    assert decode_block(block, table.content_bytes) == table


class CountingFile(io.BytesIO):
    def __init__(self, data: bytes) -> None:
        super().__init__(data)
        self.bytes_read = 0

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        self.bytes_read += len(data)
        return data


def test_the_reader_reads_only_the_end_of_the_file() -> None:
    table = _table()
    body = b"G1 X1 Y2 E0.1\n" * (table.content_bytes // 14)
    body += b";" * (table.content_bytes - len(body) - 1) + b"\n"
    f = CountingFile(body + table.encode())
    assert read_table(f) == table
    assert f.bytes_read <= TAIL_WINDOWS[0]
    # A file with no table: only the last window is read, then it is refused.
    f = CountingFile(body)
    with pytest.raises(TableError, match="no kestimator progress table"):
        read_table(f)
    assert f.bytes_read <= TAIL_WINDOWS[0]


def test_a_table_bigger_than_the_first_window_is_found() -> None:
    n = MAX_TIME_POINTS  # and the point at offset 0: within MAX_TABLE_POINTS
    state = 12345
    offsets, times = [0], [0.0]
    for _ in range(n):  # irregular steps, so that the table does not compress away
        state = (state * 1103515245 + 12345) % (1 << 31)
        offsets.append(offsets[-1] + 1 + state % 500)
        times.append(round(times[-1] + (state >> 12) % 3000 / 1000.0, 3))
    table = ProgressTable(total_s=times[-1], content_bytes=offsets[-1] + 5, offsets=offsets,
                          times=times)
    block = table.encode()
    assert len(block) > TAIL_WINDOWS[0]
    f = CountingFile(b"\n" * table.content_bytes + block)
    assert read_table(f) == table
    assert f.bytes_read <= TAIL_WINDOWS[0] + TAIL_WINDOWS[1]


def test_byte_offsets_and_line_numbers_agree() -> None:
    data = b"a\nbb\r\n\nccc\nd"
    starts = [0, 2, 6, 7, 11]
    reader = io.BytesIO(data)
    assert line_offsets(lambda n: reader.read(3), [1, 2, 3, 4, 5, 6]) == dict(
        zip([1, 2, 3, 4, 5], starts))
    reader = io.BytesIO(data)
    got = lines_at_offsets(lambda n: reader.read(4), [0, 1, 2, 3, 6, 7, 8, 11, 12, 99])
    assert got == [1, 2, 2, 3, 3, 4, 5, 5, 6, 6]


def test_select_keeps_at_most_the_point_limit_deterministically() -> None:
    class Fake:
        total_s = 100_000.0
        n_lines = 200_001
        sample_lines = list(range(1, 200_000, 2))
        sample_times = [i * 1.0 for i in range(100_000)]
        layers = [(i * 100 + 2, i * 50.0) for i in range(2000)]
        tail_lines: list[int] = []
        tail_times: list[float] = []
        object_remaining: list[tuple[int, float, dict[str, float]]] = []

    first = select(Fake(), max_points=5000)
    assert len(first.lines) <= 5000
    assert first == select(Fake(), max_points=5000)
    assert first.times == sorted(first.times)


@pytest.mark.parametrize("name", FILES)
def test_interpolation_stays_within_the_bound_at_every_progress_sample(
        name: str, limits, corpus_root: Path) -> None:  # type: ignore[no-untyped-def]
    path = corpus_root / "gcode" / name
    est = estimate_file(path, limits, sample=True)
    selection = select(est)
    with open(path, "rb") as f:
        offsets = line_offsets(f.read, sorted({line + 1 for line in est.sample_lines}
                                              | set(selection.wanted_lines())))
    table = ProgressTable.from_selection(selection, offsets, path.stat().st_size)
    # The time at the start of the line after a sample's move: when every move of that
    # line has finished (a line with many moves, an arc, has many samples: the last).
    at_line: dict[int, float] = {}
    for line, t in zip(est.sample_lines, est.sample_times):
        at_line[line + 1] = t
    checked = 0
    for line, t in at_line.items():
        if line > est.n_lines:
            continue
        got = table.time_at(offsets[line])
        assert abs(got - t) <= spacing_bound(est.total_s - t) + 1e-6, (line, got, t)
        checked += 1
    assert checked > 100
    assert len(table.offsets) <= 20_000


def _layer_offsets(path: Path, limits) -> list[int]:  # type: ignore[no-untyped-def]
    """The byte offsets of the layer markers of `path` (found by estimating it)."""
    lines = [line for line, _ in estimate_file(path, limits).layers]
    with open(path, "rb") as f:
        offsets = line_offsets(f.read, lines)
    return [offsets[line] for line in lines]


@pytest.mark.parametrize("name", FILES)
def test_injected_table_gives_estimate_times_at_every_layer_marker(
        name: str, limits, corpus_root: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    src = corpus_root / "gcode" / name
    est = estimate_file(src, limits)
    work = tmp_path / src.name
    shutil.copyfile(src, work)
    os.chmod(work, 0o644)
    result = inject_file(work, limits, limits_source="printer.cfg")
    table = read_table_file(work)
    assert result.table is not None
    assert table.offsets == result.table.offsets
    assert work.read_bytes()[table.content_bytes:].startswith(HEADER_PREFIX)
    layer_offsets = _layer_offsets(work, limits)
    assert len(layer_offsets) == len(est.layers) > 0
    points = dict(zip(table.offsets, table.times))
    exact = 0
    for offset, (_, t) in zip(layer_offsets, est.layers):
        got = table.time_at(offset)
        if offset in points:
            assert got == pytest.approx(t, abs=0.0006)
            exact += 1
        else:
            assert abs(got - t) <= spacing_bound(est.total_s - t) + 0.001
    assert exact >= len(layer_offsets) - 1  # the first may follow a TOTAL_LAYER line
    assert table.total_s == pytest.approx(est.total_s, abs=0.0006)

    # Again: the old table is replaced, not added to; the file is the same.
    first = work.read_bytes()
    inject_file(work, limits, limits_source="printer.cfg")
    assert work.read_bytes() == first
    assert first.count(b"\n" + HEADER_PREFIX) == 1

    # Edited afterwards (a line added near the start): the table no longer fits.
    work.write_bytes(first[:100] + b"; edited\n" + first[100:])
    with pytest.raises(TableError, match="changed after"):
        read_table_file(work)


def test_a_post_processors_line_after_the_table_stays_after_it(
        limits, corpus_root: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "nut.gcode"
    shutil.copyfile(corpus_root / "gcode" / FILES[0], work)
    os.chmod(work, 0o644)
    inject_file(work, limits)
    ident = b"; Processed by klipper_estimator 0.1.0\n"
    with open(work, "ab") as f:
        f.write(ident)
    once = work.read_bytes()
    read_table_file(work)
    inject_file(work, limits)
    assert work.read_bytes() == once


def test_a_selection_without_objects_has_none() -> None:
    selection = Selection(total_s=10.0, n_lines=3, lines=[1, 2], times=[0.0, 5.0],
                          object_names=[], object_lines=[], object_remaining=[])
    table = ProgressTable.from_selection(selection, {1: 0, 2: 10}, 20)
    assert table.offsets == [0, 10, 20] and table.times == [0.0, 5.0, 10.0]
    assert table.objects_remaining_at(5) == {}


SETTINGS = (("kinematics", "corexy"), ("max_accel", "3000"), ("max_velocity", "300"),
            ("square_corner_velocity", "5"), ("gcode_macros", "#0123456789abcdef"),
            ("shaper_type_x", "näme"))


def test_a_table_records_the_printer_settings_it_was_made_for() -> None:
    """Issue 38 item 2: version 2 carries the settings (and so the fingerprint); a table
    without settings is still written and read as version 1."""
    table = dataclasses.replace(_table(), settings=SETTINGS)
    block = table.encode()
    assert block.startswith(b"; kestimator_table v3 ")
    back = decode_block(block, table.content_bytes)
    assert back == table and back.settings == SETTINGS
    assert back.fingerprint == settings_digest(SETTINGS) and len(back.fingerprint) == 16
    old = _table()
    assert old.encode().startswith(b"; kestimator_table v1 ")
    assert decode_block(old.encode(), old.content_bytes).settings is None
    assert old.fingerprint is None


def test_setting_texts_are_exact_and_long_or_list_values_are_digests() -> None:
    assert [setting_text(v) for v in (3000.0, 3000, 0.1, 1e-7, True, None, "mzv")] == [
        "3000", "3000", "0.1", "1e-07", "true", "none", "mzv"]
    assert setting_text(0.1 + 0.2) != setting_text(0.3)
    digest = setting_text([["G28", "G28 X"]])
    assert digest.startswith("#") and len(digest) == 17
    assert setting_text("x" * 65).startswith("#") and setting_text("#1") != "#1"


def test_differences_name_the_first_few_settings_and_count_the_rest() -> None:
    here = (("kinematics", "corexy"), ("max_accel", "5000"), ("max_velocity", "250"),
            ("square_corner_velocity", "8"), ("gcode_macros", "#fedcba9876543210"),
            ("shaper_type_x", "näme"), ("new_setting", "1"))
    found = settings_differences(SETTINGS, here)
    assert found == ["max_accel 3000, this printer has 5000",
                     "max_velocity 300, this printer has 250",
                     "square_corner_velocity 5, this printer has 8",
                     "other gcode_macros than this printer's",
                     "a kestimator that did not record new_setting"]
    assert describe_differences(found) == (
        "max_accel 3000, this printer has 5000; max_velocity 300, this printer has 250; "
        "square_corner_velocity 5, this printer has 8 (and 2 more settings)")
    assert settings_differences(SETTINGS, SETTINGS) == []
    assert settings_differences(SETTINGS + (("old", "2"), ("older", "#0123456789abcdef")),
                                SETTINGS) == ["old 2, which this kestimator does not record",
                                              "older, which this kestimator does not record"]


@pytest.mark.parametrize("bad", ["over_count", "long_name", "long_value", "twice", "ascii"])
def test_forged_settings_are_refused(bad: str) -> None:
    table = dataclasses.replace(_table(), settings=(("a", "1"),))
    payload = table.payload()
    assert payload.endswith(b"\x01\x01a\x011\x00")  # the settings, then no stops
    head = payload[:-len(b"\x01\x01a\x011\x00")]
    tail = {"over_count": b"\xc9\x01",  # MAX_SETTINGS + 1 = 201
            "long_name": b"\x01\x41" + b"a" * 65 + b"\x011",
            "long_value": b"\x01\x01a\x41" + b"1" * 65,
            "twice": b"\x02\x01a\x011\x01a\x012",
            "ascii": b"\x01\x02\xc3\xa4\x011"}[bad]
    with pytest.raises(TableError):
        ProgressTable.from_payload(head + tail + b"\x00")


@pytest.mark.parametrize("appended", [b"M104 S0\nM84\n", b"; a note\n" * 500],
                         ids=["gcode", "over_4kb_of_comments"])
def test_reinject_after_something_was_appended_writes_a_table_the_reader_accepts(
        appended: bytes, limits, corpus_root: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """Issue 38 item 4: another post-processor's G-code, or more comments after the table
    than may follow it: the reader refuses the table, and a second inject writes its new
    one where the reader finds it (at the end), then stays byte-identical."""
    work = tmp_path / "nut.gcode"
    shutil.copyfile(corpus_root / "gcode" / FILES[0], work)
    os.chmod(work, 0o644)
    inject_file(work, limits)
    with open(work, "ab") as f:
        f.write(appended)
    with pytest.raises(TableError, match="goes on after"):
        read_table_file(work)
    inject_file(work, limits)
    once = work.read_bytes()
    table = read_table_file(work)
    assert once.count(b"\n" + HEADER_PREFIX) == 1
    assert appended in once[:table.content_bytes]
    inject_file(work, limits)
    assert work.read_bytes() == once


def test_a_slicers_settings_block_may_follow_the_table() -> None:
    """Issue 38 item 3: a settings block PrusaSlicer before 2.4 reads from the file's end
    (up to 64 KiB of "; key = value" lines) may follow the table; other comments only up to
    MAX_TRAILING_BYTES."""
    table = _table()
    block = b"".join(b"; setting_%d = %d\n" % (i, i) for i in range(2000))
    assert MAX_TRAILING_BYTES < len(block) < 65535
    assert decode_block(table.encode() + block, table.content_bytes) == table
    with pytest.raises(TableError, match="goes on after"):
        decode_block(table.encode() + b"; x\n" * 2000, table.content_bytes)


def _candidates_by_dict(est: Any, total_s: float) -> tuple[list[int], list[float], list[bool]]:
    """select's candidate points as it first found them: a dict by line, then sorted."""
    by_line: dict[int, float] = {1: 0.0}
    layer_lines = set()
    for line, t in est.layers:
        by_line[line] = max(t, by_line.get(line, 0.0))
        layer_lines.add(line)
    for line, t in list(zip(est.sample_lines, est.sample_times)) + list(
            zip(est.tail_lines, est.tail_times)):
        by_line[line + 1] = max(t, by_line.get(line + 1, 0.0))
    lines = sorted(line for line in by_line if line <= est.n_lines + 1)
    times, latest = [], 0.0
    for line in lines:
        latest = min(max(latest, by_line[line]), total_s)
        times.append(latest)
    return lines, times, [line in layer_lines for line in lines]


@pytest.mark.parametrize("seed", range(80))
def test_select_merges_its_candidates_as_a_dict_by_line_finds_them(seed: int) -> None:
    rng = random.Random(seed)

    def points(n: int, ordered: bool) -> tuple[list[int], list[float]]:
        lines = [rng.randrange(0, 400) for _ in range(n)]
        times = [rng.choice([0.0, -0.0, -1.0, rng.uniform(0, 900), rng.uniform(0, 1200)])
                 for _ in range(n)]
        if ordered:
            pairs = sorted(zip(lines, times), key=lambda p: p[0])
            lines, times = [p[0] for p in pairs], [p[1] for p in pairs]
            if seed % 2:  # an estimate's: times ascending too, mostly on distinct lines
                times = sorted(times)
        return lines, times

    class Fake:
        total_s = rng.choice([1000.0, 0.0, 5000.0])
        n_lines = rng.randrange(0, 420)
        sample_lines, sample_times = points(rng.randrange(0, 300), seed % 3 != 0)
        tail_lines, tail_times = points(rng.randrange(0, 100), seed % 4 != 0)
        layers = list(zip(*points(rng.randrange(0, 50), seed % 5 != 0)))
        object_remaining: list[tuple[int, float, dict[str, float]]] = []

    made = _candidates(Fake(), Fake.total_s)
    lines, times, keep = made.lines, made.times, made.keep
    assert ([line + 1 for line in lines], times, keep) == _candidates_by_dict(Fake(),
                                                                             Fake.total_s)


@pytest.mark.parametrize("seed", range(30))
def test_line_offsets_from_known_lines_are_those_counted_from_the_start(seed: int) -> None:
    rng = random.Random(seed)
    data = b"".join(b"x" * rng.choice([0, 0, 1, 5, 30, 300]) + rng.choice([b"\n", b"\r\n"])
                    for _ in range(rng.randrange(1, 3000)))
    if rng.random() < 0.5:
        data += b"tail without LF"
    n_lines = data.count(b"\n") + 1
    wanted = sorted(set(rng.sample(range(-1, n_lines + 4), min(n_lines + 5, 400))))
    expected = line_offsets(io.BytesIO(data).read, wanted)
    everything = line_offsets(io.BytesIO(data).read, list(range(1, n_lines + 2)))
    known = {line: everything[line]
             for line in rng.sample(sorted(everything), min(len(everything), 40))}
    known[1] = 0

    def read_at(size: int, offset: int) -> bytes:
        return data[offset:offset + size]

    for block_bytes in (1 << 16, 7, 100):
        got = line_offsets_from(read_at, wanted, known, sorted(known), len(data) / n_lines,
                                block_bytes)
        assert got == expected
    # Without anchors but line 1, and with a poor guess of the line length.
    assert line_offsets_from(read_at, wanted, {1: 0}, [1], 1.0) == expected
    # A line asked for more than once (the worker merges the table's lines with the
    # candidates') is found once, at the same offset.
    repeated = sorted(wanted + rng.sample(wanted, len(wanted) // 3))
    assert line_offsets_from(read_at, repeated, known, sorted(known),
                             len(data) / n_lines) == expected
    # Aligned, from a known line on (the worker's candidates past its checkpoint), a line
    # past the file's end given as `missing`.
    base_line = rng.choice(sorted(everything))
    after = [line for line in repeated if line > base_line]
    assert line_offsets_along(read_at, after, [], [], len(data) / n_lines,
                              base_line=base_line, base=everything[base_line],
                              missing=-7) == [expected.get(line, -7) for line in after]


def _select_lines_by_whole_walks(est: Any, max_points: int, precision: float) -> list[int]:
    """select's lines as it chose them before it stopped a walk past max_points: each
    walk to the end, its points counted after."""
    total_s = float(est.total_s)
    made = _candidates(est, total_s)
    lines, times, keep = made.lines, made.times, made.keep
    factor, forced = precision, True
    while True:
        kept = [0] if len(times) > 2 else list(range(len(times)))
        if len(times) > 2:
            for i in range(1, len(times) - 1):
                after = times[i + 1]
                if ((forced and keep[i]) or after - times[kept[-1]]
                        > factor * spacing_bound(total_s - after)):
                    kept.append(i)
            kept.append(len(times) - 1)
        if len(kept) <= max_points:
            return [lines[i] + 1 for i in kept]
        if forced:
            forced = False
        else:
            factor *= 2.0


def _samples_estimate(sample_times: list[float], total_s: float, n_layers: int,
                      rng: random.Random) -> Any:
    """An estimate with a sample on every odd line (at `sample_times`) and `n_layers` layer
    markers on sampled lines, no tail and no objects."""
    n = len(sample_times)

    class Fake:
        n_lines = 2 * n + 3
        sample_lines = list(range(1, 2 * n, 2))
        layers = [(line + 1, sample_times[(line - 1) // 2])
                  for line in sorted(rng.sample(range(1, 2 * n, 2), n_layers))]
        tail_lines: list[int] = []
        tail_times: list[float] = []
        object_remaining: list[tuple[int, float, dict[str, float]]] = []

    Fake.total_s = total_s  # type: ignore[attr-defined]
    Fake.sample_times = sample_times  # type: ignore[attr-defined]
    return Fake()


@pytest.mark.parametrize("seed", range(40))
def test_select_stopping_a_walk_past_the_limit_keeps_the_points_whole_walks_keep(
        seed: int) -> None:
    rng = random.Random(seed)
    n = rng.randrange(0, 3000)
    t = 0.0
    sample_times = []
    for _ in range(n):
        t += rng.choice([0.0, 0.01, 0.3, 2.0, 40.0])
        sample_times.append(t)

    est = _samples_estimate(sample_times, t + rng.choice([0.0, 5.0]),
                            min(n, rng.randrange(50)), rng)
    for max_points in (2, 3, 10, 100, 5000):
        for precision in (0.1, 1.0):
            got = select(est, max_points=max_points, precision=precision)
            assert got.lines == _select_lines_by_whole_walks(est, max_points, precision)
            assert len(got.lines) <= max(2, max_points)


def _walk_counts(est: Any, precision: float, walks: int) -> list[int]:
    """How many points select's first `walks` whole walks keep: forced, then unforced at
    precision, 2x, 4x, ... (the limits at which select stops at each of them)."""
    total_s = float(est.total_s)
    made = _candidates(est, total_s)
    times, keep = made.times, made.keep
    counts = [len(_thin(times, keep, total_s, precision, True, 10**9) or [])]
    factor = precision
    for _ in range(walks - 1):
        counts.append(len(_thin(times, keep, total_s, factor, False, 10**9) or []))
        factor *= 2.0
    return counts


@pytest.mark.parametrize("seed", range(20))
def test_select_lands_on_each_walk_as_whole_walks_do(seed: int) -> None:
    """With the limit at each walk's count (and one less), select keeps the points the
    whole walks keep, whichever walk it stops at."""
    rng = random.Random(seed)
    n = rng.randrange(50, 2000)
    sample_times = []
    t = 0.0
    for _ in range(n):
        t += rng.expovariate(1.0) * rng.choice([0.01, 1.0, 30.0])
        sample_times.append(t)

    est = _samples_estimate(sample_times, t + rng.choice([0.0, 50.0]), rng.randrange(1, 60),
                            rng)
    precision = rng.choice([0.01, 0.1, 1.0])
    limits: set[int] = set()
    for count in _walk_counts(est, precision, 6):
        limits.update((count, count - 1))
    for max_points in sorted(m for m in limits if m >= 2):
        got = select(est, max_points=max_points, precision=precision)
        assert got.lines == _select_lines_by_whole_walks(est, max_points, precision)


def test_common_prefix_counts_the_items_two_arrays_share_bit_for_bit() -> None:
    rng = random.Random(37)
    for typecode, size in (("q", 8), ("d", 8), ("b", 1)):
        for _ in range(100):
            n = rng.choice([0, 1, 5, COMPARE_BYTES // size, 3 * COMPARE_BYTES])
            a = array(typecode, rng.randbytes(n * size))
            b = array(typecode, a)
            b.extend(array(typecode, [1] * rng.randrange(0, 3)))
            expected = min(len(a), len(b))
            if n and rng.random() < 0.7:
                expected = rng.randrange(n)
                raw = bytearray(b.tobytes())
                raw[expected * size + rng.randrange(size)] ^= 1 << rng.randrange(8)
                b = array(typecode, bytes(raw))
            assert common_prefix(a, b) == expected
            assert common_prefix(b, a) == expected


def test_candidates_going_on_from_an_earlier_estimates_are_a_whole_walks() -> None:
    """`_candidates` with `previous` (the worker's, after a change) gives bit for bit what a
    whole walk gives, whether it goes on from the earlier points or cannot: estimates that
    share their first samples and layers, then part; tails; totals that hold times back;
    samples out of order; another file length."""
    from kestimator import progress_table
    from kestimator.timedlines import TimedLines

    went_on = []
    real = progress_table._go_on_from

    def spy(*args: Any) -> Any:
        start = real(*args)
        went_on.append(start is not None)
        return start

    def estimate(rng: random.Random, lines: list[int], times: list[float],
                 layers: list[tuple[int, float]], n_lines: int, total_s: float) -> Any:
        class Fake:
            pass
        est = Fake()
        est.sample_lines, est.sample_times = array("q", lines), array("d", times)  # type: ignore[attr-defined]
        tail_from = rng.choice([max(1, n_lines - 60), rng.randrange(1, n_lines + 2)])
        tail = sorted(rng.sample(range(tail_from, n_lines + 3),
                                 min(n_lines + 3 - tail_from, rng.choice([0, 5]))))
        est.tail_lines = array("q", tail)  # type: ignore[attr-defined]
        est.tail_times = array("d", [total_s - rng.uniform(0, 9) for _ in tail])  # type: ignore[attr-defined]
        est.layers = TimedLines(layers)  # type: ignore[attr-defined]
        est.n_lines, est.total_s = n_lines, total_s  # type: ignore[attr-defined]
        return est

    def points(rng: random.Random, first_line: int, first_t: float, n: int
               ) -> tuple[list[int], list[float]]:
        lines, times, line, t = [], [], first_line, first_t
        for _ in range(n):
            line += rng.choice([0, 1, 1, 3, 9])
            t += rng.choice([0.0, 0.5, rng.uniform(0, 4)])
            lines.append(line)
            times.append(t)
        return lines, times

    original = progress_table._go_on_from
    progress_table._go_on_from = spy
    try:
        for seed in range(300):
            rng = random.Random(seed)
            lines, times = points(rng, 1, 0.0, rng.randrange(1, 400))
            n_lines = lines[-1] + rng.randrange(0, 20)
            layers = sorted(rng.sample(list(zip(lines, times)), min(len(lines), 12)))
            total = times[-1] + rng.uniform(0, 5)
            first = _candidates(estimate(rng, lines, times, layers, n_lines, total), total)
            # A second estimate: the first `shared` samples, then others.
            shared = rng.randrange(0, len(lines) + 1)
            more_lines, more_times = points(rng, lines[shared - 1] if shared else 1,
                                            times[shared - 1] if shared else 0.0,
                                            rng.randrange(0, 300))
            lines2, times2 = lines[:shared] + more_lines, times[:shared] + more_times
            if rng.random() < 0.1 and len(lines2) > 3:
                lines2[-2], lines2[-1] = lines2[-1] + 1, lines2[-2]  # out of order
            if rng.random() < 0.1 and shared > 2:  # a later sample of an earlier line
                lines2.append(rng.randrange(1, lines[shared - 1]))
                times2.append(times2[-1])
            layers2 = [p for p in layers if p[0] <= (lines[shared - 1] if shared else 0)]
            if layers2 and rng.random() < 0.3:  # one of them differs
                k = rng.randrange(len(layers2))
                layers2[k] = (layers2[k][0], layers2[k][1] + rng.choice([0.0, 1.0]))
                if rng.random() < 0.5:
                    del layers2[k]
            layers2 += sorted(rng.sample(list(zip(more_lines, more_times)),
                                         min(len(more_lines), 5)))
            total2 = rng.choice([total, (times2 or [0.0])[-1] + 1.0,
                                 rng.uniform(0, total)])
            n_lines2 = rng.choice([n_lines, n_lines, n_lines, n_lines + 1])
            n_lines2 = max(n_lines2, (lines2 or [0])[-1])
            second = estimate(rng, lines2, times2, layers2, n_lines2, total2)
            got = _candidates(second, total2, first)
            whole = _candidates(second, total2)
            assert got.lines == whole.lines and got.keep == whole.keep
            assert array("d", got.times).tobytes() == array("d", whole.times).tobytes()
            assert got.ordered == whole.ordered
    finally:
        progress_table._go_on_from = original
    assert went_on.count(True) > 40 and went_on.count(False) > 30


def test_a_version_3_table_carries_its_stops_and_a_version_2_one_is_still_read() -> None:
    """Version 3 ends with the stops (offset, Klipper's time there, command); a version-2
    table (settings, no stops) reads with none, for the worker to refuse to follow."""
    table = dataclasses.replace(_table(), settings=SETTINGS, stop_offsets=[200, 9_000_000],
                                stop_times=[0.25, 1000.5], stop_commands=["M600", "PAUSE"])
    block = table.encode()
    assert block.startswith(b"; kestimator_table v3 ")
    back = decode_block(block, table.content_bytes)
    assert back == table
    assert (back.stop_offsets, back.stop_times, back.stop_commands) == (
        [200, 9_000_000], [0.25, 1000.5], ["M600", "PAUSE"])
    assert table.to_json("b64")["stop_commands"] == ["M600", "PAUSE"]


def test_a_forged_stop_past_the_file_or_the_total_is_refused() -> None:
    for change in ({"stop_offsets": [20_000_000]}, {"stop_times": [5000.0]}):
        forged = dataclasses.replace(_table(), settings=SETTINGS, stop_offsets=[200],
                                     stop_times=[0.25], stop_commands=["M600"])
        forged = dataclasses.replace(forged, **change)  # type: ignore[arg-type]
        with pytest.raises(TableError, match="stop"):
            decode_block(forged.encode(), forged.content_bytes)


def test_the_table_holds_as_many_stops_as_an_estimate_lists() -> None:
    from kestimator.progress_table import MAX_TABLE_STOPS
    from kestimator.stops import MAX_STOPS

    assert MAX_TABLE_STOPS == MAX_STOPS
