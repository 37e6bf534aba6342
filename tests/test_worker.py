"""`python3 -m kestimator.worker` over real pipes: JSON lines in, one answer line out per
request, from the file's table or by estimating; a bad request is answered and the worker
lives on; end of input ends it with status 0. Hostile files (issue 33): a forged table or a
huge object name gets a bounded answer from a worker of bounded memory, and nothing but
answers ever reaches its standard output."""

from __future__ import annotations

import base64
import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file
from kestimator.progress_table import (
    MAX_NAME_BYTES,
    MAX_OBJECT_POINTS,
    MAX_OBJECTS,
    MAX_TABLE_POINTS,
)
from kestimator.rewrite import inject_file
from kestimator.worker import MAX_ANSWER_BYTES

from .conftest import CORPUS_CFG, PROJECT
from .table_forgery import forge_payload, forged_block, huge_table_payload

NUT = "gcode/prusaslicer/ps25_nut_accelA_small.gcode"
# The worker's peak RSS on hostile files (it takes about 40 MiB estimating the nut; the
# forged table once took 1.1 GB).
PEAK_LIMIT_MIB = 300


def _start(tmp_path: Path, *args: str) -> subprocess.Popen[bytes]:
    """The worker (or `python3 -c args[1]` ...) with a private home."""
    env = dict(os.environ, PYTHONPATH=str(PROJECT), HOME=str(tmp_path),
               XDG_CONFIG_HOME=str(tmp_path / "config"), XDG_CACHE_HOME=str(tmp_path / "cache"))
    return subprocess.Popen([sys.executable, *(args or ("-m", "kestimator.worker"))], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)


def _peak_mib(pid: int) -> int:
    """The process's peak resident memory (VmHWM), MiB."""
    with open("/proc/%d/status" % pid) as status:
        kib = [int(line.split()[1]) for line in status if line.startswith("VmHWM:")]
    return kib[0] // 1024


def _ask(proc: subprocess.Popen[bytes], request: object) -> dict[str, Any]:
    assert proc.stdin is not None and proc.stdout is not None
    line = request if isinstance(request, bytes) else json.dumps(request).encode()
    proc.stdin.write(line + b"\n")
    proc.stdin.flush()
    answer = proc.stdout.readline()
    assert answer.endswith(b"\n")
    return json.loads(answer)  # type: ignore[no-any-return]


def test_worker_answers_from_the_table_and_by_estimating_and_survives_bad_requests(
        corpus_root: Path, tmp_path: Path) -> None:
    src = corpus_root / NUT
    injected = tmp_path / "nut.gcode"
    shutil.copyfile(src, injected)
    os.chmod(injected, 0o644)
    limits = limits_from_printer_cfg(CORPUS_CFG)[0]
    inject_file(injected, limits)
    total = estimate_file(src, limits).total_s
    env = dict(os.environ, PYTHONPATH=str(PROJECT), HOME=str(tmp_path),
               XDG_CONFIG_HOME=str(tmp_path / "config"), XDG_CACHE_HOME=str(tmp_path / "cache"))
    proc = subprocess.Popen([sys.executable, "-m", "kestimator.worker"], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        table = _ask(proc, {"id": 1, "file": str(injected), "config": str(CORPUS_CFG),
                            "events": [], "use_table": True})
        assert table["ok"] and table["id"] == 1 and table["source"] == "table"
        assert abs(table["total_s"] - total) < 0.001
        assert table["offsets"][0] == 0 and table["offsets"] == sorted(table["offsets"])
        assert len(table["offsets"]) == len(table["times"]) > 100

        bad = _ask(proc, b"{not json")
        assert bad["ok"] is False and "JSON" in bad["error"]
        missing = _ask(proc, {"id": 3, "file": str(tmp_path / "missing.gcode")})
        assert missing == {"id": 3, "ok": False, "error": missing["error"]}
        assert "missing.gcode" in missing["error"]

        estimated = _ask(proc, {"id": 4, "file": str(src), "config": str(CORPUS_CFG),
                                "events": [], "use_table": True})
        assert estimated["ok"] and estimated["source"] == "estimate", estimated
        assert abs(estimated["total_s"] - total) < 1e-6
        assert estimated["offsets"][-1] == src.stat().st_size
        # The same times as the table of the injected file, at the same lines (the offsets
        # differ by what inject inserted).
        assert abs(estimated["times"][len(estimated["times"]) // 2]
                   - table["times"][len(table["times"]) // 2]) < 5.0

        with_events = _ask(proc, {"id": 5, "file": str(src), "config": str(CORPUS_CFG),
                                  "events": [[5000, "M220 S150"]]})
        assert with_events["id"] == 5
        assert with_events["ok"]
        assert with_events["source"] == "estimate"
        assert with_events["total_s"] < total
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        assert proc.wait(timeout=60) == 0
        assert proc.stderr is not None
        assert proc.stderr.read() == b""


def _ask_bounded(proc: subprocess.Popen[bytes], request: dict[str, Any]) -> dict[str, Any]:
    """The answer, read no further than MAX_ANSWER_BYTES (a longer one fails the test)."""
    assert proc.stdin is not None and proc.stdout is not None
    proc.stdin.write(json.dumps(request).encode() + b"\n")
    proc.stdin.flush()
    line = proc.stdout.readline(MAX_ANSWER_BYTES + 1)
    assert line.endswith(b"\n") and len(line) <= MAX_ANSWER_BYTES, len(line)
    return json.loads(line)  # type: ignore[no-any-return]


def _hostile_files(nut: bytes, tmp_path: Path) -> dict[str, Path]:
    size = len(nut)
    negative = forge_payload(size, 100_000, [(0, 0), (size, 100_000)], names=[b"A"],
                             object_offsets=[1000], remaining_ms=[[-1_000_000_000]])
    contents = {
        # 4000 objects x 4000 points: 16 KB compressed, 16 M values declared.
        "huge_table": nut + forged_block(huge_table_payload(size), size),
        # Past the object limit but within the payload limit: reaches the count check.
        "many_objects": nut + forged_block(huge_table_payload(size, 4000, 1000), size),
        # An object's time left of -1,000,000 s.
        "negative_time": nut + forged_block(negative, size),
    }
    name = b"\xff" * 700_000  # six characters a byte once escaped in JSON
    lines = [b"G28", b"G90", b"M83", b"M486 T1", b"M486 S0 A" + name]
    for _ in range(3):
        lines += [b";LAYER_CHANGE", b"M486 S0", b"G1 X10 Y10 F3000",
                  b"G1 X60 Y10 E2 F1800", b"G1 X60 Y60 E2", b"M486 S-1"]
    contents["huge_name"] = b"\n".join(lines) + b"\n"
    paths = {}
    for key, data in contents.items():
        paths[key] = tmp_path / (key + ".gcode")
        paths[key].write_bytes(data)
    return paths


def _check_bounded(doc: dict[str, Any]) -> None:
    """A valid table within the writer's limits, or ok: false with a one-line error."""
    if not doc["ok"]:
        assert isinstance(doc["error"], str) and "\n" not in doc["error"]
        return
    names = doc["object_names"]
    assert len(names) <= MAX_OBJECTS
    assert all(len(name.encode("utf-8", "surrogateescape")) <= MAX_NAME_BYTES
               for name in names)
    if "offsets_b64" in doc:
        offsets = len(base64.b64decode(doc["offsets_b64"])) // 8
        points = len(base64.b64decode(doc["object_offsets_b64"])) // 8
        values = len(base64.b64decode(doc["object_remaining_b64"])) // 8
    else:
        offsets, points = len(doc["offsets"]), len(doc["object_offsets"])
        values = sum(len(column) for column in doc["object_remaining"])
    assert 0 < offsets <= MAX_TABLE_POINTS
    assert points <= MAX_OBJECT_POINTS and values == points * len(names)


def test_worker_answers_hostile_files_within_bounds_of_size_and_memory(
        corpus_root: Path, tmp_path: Path) -> None:
    paths = _hostile_files((corpus_root / NUT).read_bytes(), tmp_path)
    proc = _start(tmp_path)
    try:
        for i, key in enumerate(["huge_table", "many_objects", "negative_time"]):
            doc = _ask_bounded(proc, {"id": i, "file": str(paths[key]),
                                      "config": str(CORPUS_CFG), "encoding": "b64"})
            _check_bounded(doc)
            # The forged table is refused: the file is estimated, with a warning.
            assert doc["ok"] and doc["source"] == "estimate", (key, doc)
            assert any(w.startswith("no usable progress table") for w in doc["warnings"])
            assert 200.0 < doc["total_s"] < 250.0, (key, doc)
            assert doc["object_names"] == ["M3_hex_nut.stl id:0 copy 0"], (key, doc)
        for encoding in ("b64", None):
            doc = _ask_bounded(proc, {"id": 9, "file": str(paths["huge_name"]),
                                      "config": str(CORPUS_CFG), "encoding": encoding})
            _check_bounded(doc)
            assert doc["ok"] and doc["object_names"] == []
            assert any("1 objects left out" in w for w in doc["warnings"]), doc["warnings"]
        peak = _peak_mib(proc.pid)
        assert peak < PEAK_LIMIT_MIB, peak
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        assert proc.wait(timeout=60) == 0


# The worker with library code that prints to standard output (and, asked for id 3, calls
# sys.exit) before each answer.
NOISY = """
import os, sys
import kestimator.worker as worker
answer = worker.answer
def noisy(request):
    print("stray print from library code")
    sys.stdout.flush()
    os.write(1, b"stray write to descriptor 1\\n")
    if request.get("id") == 3:
        sys.exit(3)
    return answer(request)
worker.answer = noisy
sys.exit(worker.main())
"""


def test_worker_writes_only_answers_on_stdout_and_survives_any_request(
        corpus_root: Path, tmp_path: Path) -> None:
    nut = str(corpus_root / NUT)
    requests: list[bytes] = [
        json.dumps({"id": 1, "file": nut, "config": str(CORPUS_CFG)}).encode(),
        json.dumps({"id": 2, "file": str(tmp_path / "missing.gcode")}).encode(),
        json.dumps({"id": 3, "file": nut}).encode(),
        b"\xff\xfe not JSON",
        b"[" * 100_000 + b"]" * 100_000,
        json.dumps({"id": "x" * 100_000, "file": nut}).encode(),
        json.dumps({"id": 10 ** 40, "file": nut}).encode(),
        json.dumps({"id": 7, "file": 7}).encode(),
        json.dumps({"id": 8, "file": "/dev/null"}).encode(),
        json.dumps({"id": 9, "file": nut, "events": [[10 ** 30, "M220 S50"]]}).encode(),
        b'{"id": NaN, "file": "x"}',
        b"[]",
    ]
    proc = _start(tmp_path, "-c", NOISY)
    out, err = proc.communicate(b"\n".join(requests) + b"\n", timeout=120)
    assert proc.returncode == 0
    answers = [json.loads(line) for line in out.splitlines()]  # every line an answer
    assert len(answers) == len(requests)
    assert [a["id"] for a in answers] == [1, 2, 3, None, None, None, None, 7, 8, 9, None,
                                          None]
    assert answers[0]["ok"] and answers[0]["source"] == "estimate"
    assert answers[9]["ok"]  # an event past the end runs after the last line
    assert all(not a["ok"] and "\n" not in a["error"] for i, a in enumerate(answers)
               if i not in (0, 9))
    assert "SystemExit(3)" in answers[2]["error"]
    assert b"stray print from library code" in err and b"stray write to descriptor 1" in err


def _printer_cfg_with(tmp_path: Path, name: str, old: str, new: str) -> Path:
    """The corpus printer.cfg with one line changed (printer B)."""
    text = CORPUS_CFG.read_text(encoding="utf-8")
    assert old in text
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    return path


def _finish(proc: subprocess.Popen[bytes]) -> None:
    assert proc.stdin is not None
    proc.stdin.close()
    assert proc.wait(timeout=60) == 0


def test_a_table_made_for_another_printer_is_estimated_afresh_naming_the_difference(
        corpus_root: Path, tmp_path: Path) -> None:
    """Issue 38 item 2: a file injected for printer A and printed on B (max_accel changed)
    is followed by an estimate for B, with a warning naming max_accel; on A, the table."""
    src = corpus_root / NUT
    injected = tmp_path / "nut.gcode"
    shutil.copyfile(src, injected)
    os.chmod(injected, 0o644)
    inject_file(injected, limits_from_printer_cfg(CORPUS_CFG)[0])
    other = _printer_cfg_with(tmp_path, "b.cfg", "max_accel: 3000", "max_accel: 5000")
    other_total = estimate_file(src, limits_from_printer_cfg(other)[0]).total_s
    proc = _start(tmp_path)
    try:
        same = _ask(proc, {"id": 1, "file": str(injected), "config": str(CORPUS_CFG),
                           "events": [], "use_table": True})
        assert same["ok"] and same["source"] == "table", same
        assert same["warnings"] == []
        changed = _ask(proc, {"id": 2, "file": str(injected), "config": str(other),
                              "events": [], "use_table": True})
        assert changed["ok"] and changed["source"] == "estimate", changed
        assert abs(changed["total_s"] - other_total) < 0.001
        assert abs(changed["total_s"] - same["total_s"]) > 1.0
        (why,) = [w for w in changed["warnings"] if "the file's table" in w]
        assert why == ("the file's table was made for max_accel 3000, this printer has 5000: "
                       "estimated afresh")
        assert why.endswith("estimated afresh")
    finally:
        _finish(proc)


def test_an_old_table_without_printer_settings_is_not_trusted_for_a_printer_cfg(
        corpus_root: Path, tmp_path: Path) -> None:
    """A version-1 table records no settings: given a printer.cfg the worker estimates
    afresh and says why; without one it has nothing to check and uses the table."""
    from kestimator.progress_table import read_table_file

    injected = tmp_path / "nut.gcode"
    shutil.copyfile(corpus_root / NUT, injected)
    os.chmod(injected, 0o644)
    inject_file(injected, limits_from_printer_cfg(CORPUS_CFG)[0])
    table = read_table_file(injected)
    assert table.settings is not None
    old = dataclasses.replace(table, settings=None)
    data = injected.read_bytes()[:table.content_bytes] + old.encode()
    assert b"; kestimator_table v1 " in data
    injected.write_bytes(data)
    proc = _start(tmp_path)
    try:
        checked = _ask(proc, {"id": 1, "file": str(injected), "config": str(CORPUS_CFG),
                              "events": [], "use_table": True})
        assert checked["ok"] and checked["source"] == "estimate", checked
        assert any("records no printer settings" in w for w in checked["warnings"])
        unchecked = _ask(proc, {"id": 2, "file": str(injected), "config": None,
                                "events": [], "use_table": True})
        assert unchecked["ok"] and unchecked["source"] == "table", unchecked
    finally:
        _finish(proc)


def test_cli_inject_then_worker_uses_the_table_only_for_the_printer_it_was_made_for(
        corpus_root: Path, tmp_path: Path) -> None:
    """Through the real command: `kestimator inject --printer-cfg A`, then the worker."""
    injected = tmp_path / "nut.gcode"
    shutil.copyfile(corpus_root / NUT, injected)
    os.chmod(injected, 0o644)
    env = dict(os.environ, PYTHONPATH=str(PROJECT), HOME=str(tmp_path),
               XDG_CONFIG_HOME=str(tmp_path / "config"), XDG_CACHE_HOME=str(tmp_path / "cache"))
    done = subprocess.run([sys.executable, "-m", "kestimator", "inject", str(injected),
                           "--printer-cfg", str(CORPUS_CFG), "-q"], env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    other = _printer_cfg_with(tmp_path, "b.cfg", "max_velocity: 300", "max_velocity: 250")
    proc = _start(tmp_path)
    try:
        same = _ask(proc, {"id": 1, "file": str(injected), "config": str(CORPUS_CFG),
                           "events": [], "use_table": True})
        assert same["ok"] and same["source"] == "table" and same["warnings"] == [], same
        changed = _ask(proc, {"id": 2, "file": str(injected), "config": str(other),
                              "events": [], "use_table": True})
        assert changed["ok"] and changed["source"] == "estimate", changed
        assert any("max_velocity 300, this printer has 250" in w
                   for w in changed["warnings"]), changed["warnings"]
    finally:
        _finish(proc)


def test_a_same_length_edit_after_inject_is_noticed(corpus_root: Path, tmp_path: Path) -> None:
    """Issue 38 item 6: feed rates changed in place (the file's length unchanged) make the
    table stale; its content checksum no longer matches, so the worker estimates afresh."""
    injected = tmp_path / "nut.gcode"
    shutil.copyfile(corpus_root / NUT, injected)
    os.chmod(injected, 0o644)
    inject_file(injected, limits_from_printer_cfg(CORPUS_CFG)[0])
    data = injected.read_bytes()
    edited = data.replace(b" F1800\n", b" F9000\n")
    assert edited != data and len(edited) == len(data)
    injected.write_bytes(edited)
    proc = _start(tmp_path)
    try:
        got = _ask(proc, {"id": 1, "file": str(injected), "config": str(CORPUS_CFG),
                          "events": [], "use_table": True})
        assert got["ok"] and got["source"] == "estimate", got
        assert any("checksum differs" in w for w in got["warnings"]), got["warnings"]
        injected.write_bytes(data)
        got = _ask(proc, {"id": 2, "file": str(injected), "config": str(CORPUS_CFG),
                          "events": [], "use_table": True})
        assert got["ok"] and got["source"] == "table", got
    finally:
        _finish(proc)


def test_a_table_injected_without_a_version_holds_on_a_host_running_todays_klipper(
        corpus_root: Path, tmp_path: Path) -> None:
    """The Klipper module sends the version of the Klipper it runs in: one with today's rules
    (84104bbbd, or newer) gets the file's table; one with other rules (v0.13.0) an estimate
    naming the difference."""
    src = corpus_root / NUT
    injected = tmp_path / "nut.gcode"
    shutil.copyfile(src, injected)
    os.chmod(injected, 0o644)
    inject_file(injected, limits_from_printer_cfg(CORPUS_CFG)[0])
    proc = _start(tmp_path)
    try:
        asked = {"file": str(injected), "config": str(CORPUS_CFG), "events": [],
                 "use_table": True}
        for request_id, version in enumerate(("v0.13.0-730-g84104bbbd",
                                              "v0.13.0-800-gabcdef12")):
            today = _ask(proc, dict(asked, id=request_id, klipper_version=version))
            assert today["ok"] and today["source"] == "table", today
        older = _ask(proc, dict(asked, id=9, klipper_version="v0.13.0-0-g61c0c8d2"))
        assert older["ok"] and older["source"] == "estimate", older
        (why,) = [w for w in older["warnings"] if "the file's table" in w]
        assert "klipper_version , this printer has v0.13.0-0-g61c0c8d2" in why
        bad = _ask(proc, dict(asked, id=10, klipper_version=["v0.13.0"]))
        assert bad["ok"] is False and "klipper_version" in bad["error"]
    finally:
        _finish(proc)


STOPS = Path(__file__).parent / "stop_refs"


def _as_version_2(table: Any) -> bytes:
    """`table`'s lines as a kestimator before the stops wrote them: version 2, its
    settings and no stops."""
    return dataclasses.replace(table, stop_offsets=[], stop_times=[], stop_commands=[],
                               read_version=2).encode()


def test_the_answer_gives_each_stop_its_line_command_and_klippers_time(
        tmp_path: Path) -> None:
    """From an estimate and from the table inject wrote: each stop's time is the oracle's
    (tests/stop_refs), its offset the start of the stop's own line, and its line that
    line's number in the file being printed (inject's lines before it counted)."""
    ref = json.loads((STOPS / "ps25_box_color_pause.json").read_text())
    src = STOPS / "ps25_box_color_pause.gcode"
    injected = tmp_path / "box.gcode"
    shutil.copyfile(src, injected)
    inject_file(injected, limits_from_printer_cfg(STOPS / "printer.cfg")[0])
    proc = _start(tmp_path)
    try:
        for request_id, path, source, tolerance in ((1, src, "estimate", 2e-6),
                                                    (2, injected, "table", 5e-4)):
            answer = _ask(proc, {"id": request_id, "file": str(path),
                                 "config": str(STOPS / "printer.cfg"), "use_table": True,
                                 "encoding": "b64"})
            assert answer["ok"] and answer["source"] == source, answer
            assert answer["stop_commands"] == [s["command"] for s in ref["stops"]]
            assert len(answer["stop_times"]) == len(ref["stops"])
            for t, stop in zip(answer["stop_times"], ref["stops"]):
                assert abs(t - stop["t"]) <= tolerance
            lines = path.read_bytes().split(b"\n")
            starts = [0]
            for line in lines:
                starts.append(starts[-1] + len(line) + 1)
            assert [lines[n - 1] for n in answer["stop_lines"]] == [b"M600", b"PAUSE"]
            assert answer["stop_offsets"] == [starts[n - 1] for n in answer["stop_lines"]]
        assert answer["stop_lines"] != [s["line"] for s in ref["stops"]]  # inject's lines
    finally:
        _finish(proc)


def test_a_table_written_before_stops_were_recorded_is_estimated_afresh(
        tmp_path: Path) -> None:
    """A version-2 table (settings, no stops) was made without the look-ahead running out
    at the file's M600 and PAUSE: for the very printer it was made for, the worker
    estimates the file again (the stops' times Klipper's), saying why."""
    ref = json.loads((STOPS / "ps25_box_color_pause.json").read_text())
    injected = tmp_path / "box.gcode"
    shutil.copyfile(STOPS / "ps25_box_color_pause.gcode", injected)
    inject_file(injected, limits_from_printer_cfg(STOPS / "printer.cfg")[0])
    from kestimator.progress_table import read_table_file

    table = read_table_file(injected)
    assert table.version == 3 and len(table.stop_offsets) == 2
    data = injected.read_bytes()[:table.content_bytes]
    injected.write_bytes(data + _as_version_2(table))
    old = read_table_file(injected)
    assert old.version == 2 and old.settings == table.settings and not old.stop_offsets
    proc = _start(tmp_path)
    try:
        answer = _ask(proc, {"id": 1, "file": str(injected),
                             "config": str(STOPS / "printer.cfg"), "use_table": True})
        assert answer["ok"] and answer["source"] == "estimate", answer
        assert any("records no stops (a version-2 table" in w for w in answer["warnings"])
        assert [round(t, 6) for t in answer["stop_times"]] == [s["t"] for s in ref["stops"]]
    finally:
        _finish(proc)
