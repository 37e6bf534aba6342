"""The worker's answer after a change goes on from a saved planner state (kestimator.resume)
and is byte for byte the answer a whole pass gives: on every corpus file (the 40 MB one
marked slow), with events at several points of the file, added, moved and taken back."""

from __future__ import annotations

import json
import os
import pickle
import random
from array import array
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from kestimator import resume, worker

from .conftest import CORPUS_CFG, corpus_files, isolate_user_environment

BIG = "ps25_bunny120_fast_fwretract_large.gcode"
SMALL_FILES = [p for p in corpus_files() if p.name != BIG]
BIG_FILES = [p for p in corpus_files() if p.name == BIG]


@pytest.fixture(autouse=True)
def _fresh_worker(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    isolate_user_environment(tmp_path, monkeypatch)
    worker._resumable = None
    yield
    worker._resumable = None


def _answer(path: Path, events: list[list[Any]]) -> str:
    """The worker's answer as sent, without its elapsed time."""
    request = {"id": 1, "file": str(path), "config": str(CORPUS_CFG), "events": events,
               "use_table": False}
    doc = worker.handle(json.dumps(request).encode())
    doc.pop("elapsed_s", None)
    return json.dumps(doc, sort_keys=True)


def _whole_pass(path: Path, events: list[list[Any]]) -> str:
    """The answer of a worker that has no checkpoints and takes none (its planner is never
    pickled: the checkpoints are kept aside)."""
    kept, worker._resumable = worker._resumable, None
    limit = resume.MAX_CHECKPOINT_BYTES
    resume.MAX_CHECKPOINT_BYTES = 0
    try:
        return _answer(path, events)
    finally:
        resume.MAX_CHECKPOINT_BYTES = limit
        worker._resumable = kept


def _event_sets(path: Path, first: dict[str, Any]) -> list[list[list[Any]]]:
    """Events as the Klipper module sends them through a print: each request holds every
    change so far; then one taken back and one moved earlier."""
    size = path.stat().st_size
    names = first.get("object_names") or []
    exclusion = ("EXCLUDE_OBJECT NAME=%s" % names[0]) if names else "M220 S130"
    a = [int(size * 0.3), "SET_VELOCITY_LIMIT ACCEL=1500"]
    b = [int(size * 0.6), exclusion]
    c = [int(size * 0.9), "M220 S70"]
    return [[a], [a, b], [a, b, c], [a, c], [[int(size * 0.1), "M220 S150"], a]]


def _check_resumed_answers_match_whole_passes(path: Path) -> None:
    first = _answer(path, [])
    doc = json.loads(first)
    assert first == _whole_pass(path, [])
    resumed_any = False
    for events in _event_sets(path, doc):
        resumed = _answer(path, events)
        assert worker._resumable is not None or not doc["ok"]
        if worker._resumable is not None and worker._resumable.resumed_at:
            resumed_any = True
        assert resumed == _whole_pass(path, events), (path.name, events)
    if doc["ok"] and path.stat().st_size >= 8 * resume.MIN_GAP_BYTES:
        assert resumed_any, "no answer went on from a checkpoint"


@pytest.mark.parametrize("path", SMALL_FILES, ids=lambda p: p.name)
def test_resumed_answer_bytes_equal_whole_pass(corpus_root: Path, path: Path) -> None:
    _check_resumed_answers_match_whole_passes(path)


@pytest.mark.slow
@pytest.mark.parametrize("path", BIG_FILES, ids=lambda p: p.name)
def test_resumed_answer_bytes_equal_whole_pass_big_file(corpus_root: Path,
                                                        path: Path) -> None:
    first = _answer(path, [])
    size = path.stat().st_size
    resumable = worker._resumable
    assert resumable is not None
    assert len(resumable.checkpoints) <= resume.MAX_CHECKPOINTS
    assert resumable.nbytes <= resume.MAX_CHECKPOINT_BYTES + max(
        c.nbytes for c in resumable.checkpoints)
    events: list[list[Any]] = [[int(size * 0.5), "M220 S150"]]
    resumed = _answer(path, events)
    # It went on from a checkpoint within two spacings before the change.
    assert worker._resumable is resumable
    assert resumable.checkpoints[0].lineno <= resumable.resumed_at
    assert resumed == _whole_pass(path, events)
    assert first != resumed


def test_change_at_the_end_goes_on_from_the_last_checkpoint(corpus_root: Path) -> None:
    path = corpus_files("prusaslicer/gcodepreview_benchy_ps2.6.1.gcode")[0]
    _answer(path, [])
    resumable = worker._resumable
    assert resumable is not None
    before, last = resumable.checkpoints[-2:]
    size = path.stat().st_size
    _answer(path, [[(before.offset + last.offset) // 2, "M220 S150"]])
    assert resumable.resumed_at == before.lineno
    # Each gap GAP_RATIO of the rest (at least min_gap); the last within a gap of the end.
    offsets = [0] + [c.offset for c in resumable.checkpoints]
    for before, after in zip(offsets, offsets[1:]):
        assert resumable.gap(before) <= after - before <= resumable.gap(before) + (3 << 14)
    assert size - last.offset <= resumable.min_gap + (3 << 14)
    assert 30 <= len(resumable.checkpoints) <= resume.MAX_CHECKPOINTS


def test_checkpoints_are_dropped_when_the_file_changes(corpus_root: Path,
                                                       tmp_path: Path) -> None:
    source = corpus_files("prusaslicer/gcodepreview_benchy_ps2.6.1.gcode")[0]
    path = tmp_path / "x.gcode"
    path.write_bytes(source.read_bytes())
    _answer(path, [])
    before = worker._resumable
    data = path.read_bytes()
    cut = data.index(b"\nG1 ", len(data) // 2)
    path.write_bytes(data[:cut] + b"\nG4 P5000" + data[cut:])
    os.utime(path, ns=(1, 1))
    event = [[len(data) * 9 // 10, "M220 S150"]]
    changed = _answer(path, event)
    assert worker._resumable is not before
    assert changed == _whole_pass(path, event)


def test_a_planner_that_cannot_be_pickled_gives_whole_passes(
        corpus_root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = corpus_files("prusaslicer/gcodepreview_benchy_ps2.6.1.gcode")[0]

    def refuse(_blob: bytes) -> object:
        raise TypeError("__init__() missing 2 required positional arguments")
    monkeypatch.setattr(pickle, "loads", refuse)
    _answer(path, [])
    assert worker._resumable is not None and worker._resumable.disabled
    assert not worker._resumable.checkpoints
    event = [[path.stat().st_size // 2, "M220 S150"]]
    assert _answer(path, event) == _whole_pass(path, event)
    assert worker._resumable.resumed_at == 0


def test_event_lines_counted_from_each_events_checkpoint_are_those_counted_from_the_start(
        corpus_root: Path) -> None:
    path = corpus_files("prusaslicer/gcodepreview_benchy_ps2.6.1.gcode")[0]
    _answer(path, [])
    assert worker._resumable is not None and len(worker._resumable.checkpoints) > 10
    data = path.read_bytes()
    offsets = [0, 1, len(data) // 7, len(data) // 2, len(data) // 2 + 1, len(data) * 9 // 10,
               len(data) - 1, len(data)] + [c.offset for c in worker._resumable.checkpoints]
    offsets += [c.offset - 1 for c in worker._resumable.checkpoints]
    expected = [data.count(b"\n", 0, offset) + (0 if offset == 0 or data[offset - 1] == 10
                                                else 1) + 1 for offset in offsets]
    expected = [min(line, data.count(b"\n") + 1) for line in expected]
    assert worker.event_lines(str(path), offsets) == expected


def _assert_candidate_offsets_true(path: Path, resumable: resume.Resumable) -> None:
    """Each kept candidate's offset is that of the line after it (the file's size past
    its end)."""
    data = path.read_bytes()
    assert len(resumable.candidate_offsets) == len(resumable.candidates)
    starts = [0] + [i + 1 for i, byte in enumerate(data) if byte == 10]
    for line, offset in zip(resumable.candidates, resumable.candidate_offsets):
        assert offset == (starts[line] if line < len(starts) else len(data))


def test_candidate_offsets_are_kept_true_up_to_the_limit_and_answers_stay_a_whole_pass(
        corpus_root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = corpus_files("prusaslicer/gcodepreview_benchy_ps2.6.1.gcode")[0]
    _answer(path, [])
    resumable = worker._resumable
    assert resumable is not None and resumable.candidates
    _assert_candidate_offsets_true(path, resumable)
    n_candidates = len(resumable.candidates)
    size = path.stat().st_size
    # With room for fewer lines than the candidates, none are kept: each table counts
    # its own lines, and is still the whole pass's.
    monkeypatch.setattr(resume, "MAX_KNOWN_OFFSETS", n_candidates // 2)
    events: list[list[Any]] = []
    for fraction, command in ((0.3, "M220 S150"), (0.8, "M220 S60")):
        events.append([int(size * fraction), command])
        assert _answer(path, events) == _whole_pass(path, events)
        assert worker._resumable is resumable and resumable.resumed_at > 0
        assert resumable.candidates == [] and len(resumable.candidate_offsets) == 0
    # With room again, the next answer counts them all (no earlier ones to share) and
    # keeps them.
    monkeypatch.setattr(resume, "MAX_KNOWN_OFFSETS", 1 << 17)
    events.append([int(size * 0.9), "M220 S80"])
    assert _answer(path, events) == _whole_pass(path, events)
    assert worker._resumable is resumable and resumable.candidates
    _assert_candidate_offsets_true(path, resumable)


@pytest.mark.parametrize("name", ["prusaslicer/gcodepreview_benchy_ps2.6.1.gcode",
                                  "orcaslicer/helixscreen_calicat_orca2.3.1_klipper.gcode"])
def test_the_worker_tables_offsets_are_those_read_from_the_file(
        corpus_root: Path, name: str) -> None:
    """Read by candidate from the kept offsets, a table's offsets (its points' and its
    objects') are those `line_offsets` reads from the file, in the first answer and in
    those that go on from a checkpoint."""
    from kestimator.progress_table import ProgressTable, line_offsets, select

    path = corpus_files(name)[0]
    size = path.stat().st_size
    printer = worker.resolve_printer(str(path), str(CORPUS_CFG))
    events: list[tuple[int, str]] = []
    for fraction, command in ((0.0, ""), (0.4, "M220 S150"), (0.7, "M220 S60")):
        if command:
            events.append((int(size * fraction), command))
        lines = worker.event_lines(str(path), [offset for offset, _ in events])
        est, resumable = worker.estimate_resuming(
            str(path), printer, list(zip(lines, (text for _, text in events))))
        assert (resumable.resumed_at > 0) == bool(events)
        selection = select(est, precision=worker.WORKER_PRECISION)
        with open(path, "rb") as f:
            expected = ProgressTable.from_selection(
                selection, line_offsets(f.read, selection.wanted_lines()), size,
                printer.settings)
        offsets, object_offsets = resumable.line_offsets(str(path), selection,
                                                         size / est.n_lines)
        assert ProgressTable.from_offsets(selection, offsets, object_offsets, size,
                                          printer.settings) == expected
        assert len(offsets) == len(selection.lines) > 100
        assert len(object_offsets) == len(selection.object_lines)
        assert len(object_offsets) > 10


def test_shared_prefix_counts_the_items_two_lists_share() -> None:
    rng = random.Random(11)
    for _ in range(200):
        a = sorted(rng.sample(range(10_000), rng.randrange(0, 300)))
        b = list(a[:rng.randrange(0, len(a) + 1)])
        if rng.random() < 0.5:
            b.append(rng.randrange(-5, 0))
        b += sorted(rng.sample(range(10_000), rng.randrange(0, 30)))
        expected = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y),
                        min(len(a), len(b)))
        assert resume._shared_prefix(a, b) == expected
        assert resume._shared_prefix(b, a) == expected


def test_after_a_change_only_lines_past_the_checkpoint_are_counted_and_events_once(
        corpus_root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The first answer finds the offset of every line a later table may hold (the
    candidates), so an answer after a change counts only the candidates past the
    checkpoint it went on from, whichever points the new total keeps before it; and a
    change already answered is not looked for again."""
    path = corpus_files("prusaslicer/gcodepreview_benchy_ps2.6.1.gcode")[0]
    asked: list[tuple[list[int], list[int]]] = []
    real = resume.line_offsets_along

    def spy(read_at: Any, lines: Any, known_lines: Any, *args: Any, **kwargs: Any
            ) -> list[int]:
        asked.append((list(lines), list(known_lines)))
        return real(read_at, lines, known_lines, *args, **kwargs)

    monkeypatch.setattr(resume, "line_offsets_along", spy)
    counted: list[list[int]] = []
    real_lines_at = worker.lines_at_offsets

    def spy_lines(read: Any, offsets: Any, *args: Any) -> list[int]:
        counted.append(list(offsets))
        return real_lines_at(read, offsets, *args)

    monkeypatch.setattr(worker, "lines_at_offsets", spy_lines)
    from kestimator import progress_table
    went_on: list[object] = []
    real_go_on = progress_table._go_on_from

    def spy_go_on(*args: Any) -> Any:
        went_on.append(real_go_on(*args))
        return went_on[-1]

    monkeypatch.setattr(progress_table, "_go_on_from", spy_go_on)
    _answer(path, [])
    resumable = worker._resumable
    assert resumable is not None
    assert len(asked[0][0]) == len(resumable.candidates)  # all of them, once
    assert went_on == []  # nothing to go on from
    size = path.stat().st_size
    events: list[list[Any]] = []
    for fraction, command in ((0.3, "M220 S150"), (0.6, "SET_VELOCITY_LIMIT ACCEL=900"),
                              (0.9, "M220 S60")):
        events.append([int(size * fraction), command])
        counted.clear()
        asked.clear()
        went_on.clear()
        answer = _answer(path, events)
        assert worker._resumable is resumable and resumable.resumed_at > 0
        # The table's candidates went on from the last answer's (the whole pass's below
        # has none to go on from).
        assert len(went_on) == 1 and went_on[0] is not None
        # Only the new change's line is counted.
        assert sum(len(offsets) for offsets in counted) == 1
        # The candidates past the checkpoint, and no line before it that is not known.
        past = [line + 1 for line in resumable.candidates if line >= resumable.resumed_at]
        assert past and asked[0][0] == past
        for lines, known_lines in asked:
            known = set(known_lines)
            assert all(line in known or line > resumable.resumed_at for line in lines)
        assert answer == _whole_pass(path, events)
    _assert_candidate_offsets_true(path, resumable)


class _Elsewhere:
    """A plain class outside kestimator: pickled as pickle does."""

    def __init__(self, value: int) -> None:
        self.value = value


def test_pickling_sets_plain_kestimator_objects_attributes_and_leaves_the_rest_to_pickle(
        ) -> None:
    from kestimator.limits import Limits
    from kestimator.macros import MacroTimes

    limits = Limits()
    macros = MacroTimes()
    plain = [cls for cls in (Limits, MacroTimes) if resume._is_plain(cls)]
    assert plain  # the planner's configuration classes are plain in both builds
    state = {"limits": limits, "macros": macros, "class": Limits, "other": _Elsewhere(3),
             "error": ValueError("x"), "values": array("d", [1.5]), "complex": 1j}
    blob = resume._dumps(state)  # type: ignore[arg-type]
    for cls in plain:
        assert resume._REDUCTIONS[cls] is resume._plain_reduce
    assert resume._REDUCTIONS[_Elsewhere] is not resume._plain_reduce
    assert resume._REDUCTIONS[ValueError] is not resume._plain_reduce
    with pytest.raises(KeyError):  # classes themselves: pickled by name, as pickle does
        resume._REDUCTIONS[type]  # noqa: B018
    loaded = pickle.loads(blob)
    assert loaded["limits"] == limits and vars(loaded["limits"]) == vars(limits)
    assert loaded["macros"] == macros and loaded["class"] is Limits
    assert loaded["other"].value == 3 and loaded["error"].args == ("x",)
    assert loaded["values"] == array("d", [1.5]) and loaded["complex"] == 1j
    # Plain objects load through _set_attributes (attribute by attribute); others not.
    assert b"_set_attributes" in blob
    others = {"other": _Elsewhere(3), "error": ValueError("x")}
    assert b"_set_attributes" not in resume._dumps(others)  # type: ignore[arg-type]


def test_arrays_at_a_checkpoint_are_those_its_deltas_build_when_samples_thin_between(
        corpus_root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The growing arrays as at each checkpoint: a prefix of the last ones where nothing
    later kept fewer items, else built from the deltas; both are met when the samples
    thin out (every other one dropped) between checkpoints."""
    from kestimator import estimate

    monkeypatch.setattr(estimate, "MAX_SAMPLES", 64)
    path = corpus_files("cura/cura413_voron250_torus_relE_fwretract.gcode")[0]
    _answer(path, [])
    resumable = worker._resumable
    assert resumable is not None and len(resumable.checkpoints) > 10
    prefixes = 0
    for index in range(len(resumable.checkpoints)):
        expected: list[list[Any]] = [[] for _ in resumable._last]
        for earlier in resumable.checkpoints[:index + 1]:  # each delta applied in turn
            expected = [items[:kept] + tail.tolist()
                        for items, (kept, tail) in zip(expected, earlier.deltas)]
        got = resumable._arrays_at(index)
        assert [values.tolist() for values in got] == expected
        prefixes += sum(last[:len(items)].tolist() == items
                        for last, items in zip(resumable._last, expected))
    assert 0 < prefixes < len(resumable.checkpoints) * len(resumable._last)
    event = [[path.stat().st_size * 6 // 10, "M220 S70"]]
    assert _answer(path, event) == _whole_pass(path, event)
