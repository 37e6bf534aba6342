"""The progress table (issue 27): its encoding, the interpolation bound on real estimates,
the reader that reads only the file's end, and the table `inject` writes at the end of its
output (offsets of the output, one table after re-runs, refused once the file is edited)."""

from __future__ import annotations

import io
import os
import shutil
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file
from kestimator.progress_table import (
    HEADER_PREFIX,
    TAIL_WINDOWS,
    ProgressTable,
    Selection,
    TableError,
    decode_block,
    line_offsets,
    lines_at_offsets,
    read_table,
    read_table_file,
    select,
    spacing_bound,
)
from kestimator.rewrite import inject_file

from .conftest import CORPUS_CFG

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
                         object_remaining=[[500.0, 400.5, 0.0], [10.0, 20.0, 0.001],
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
    n = 30_000
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
    table = ProgressTable.from_selection(selection, offsets.get, path.stat().st_size)
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
    table = ProgressTable.from_selection(selection, {1: 0, 2: 10}.get, 20)
    assert table.offsets == [0, 10, 20] and table.times == [0.0, 5.0, 10.0]
    assert table.objects_remaining_at(5) == {}
