"""`kestimator learn` against the real Moonraker (PyPI `moonraker`), its history planted.

How the history gets there without Klipper: Moonraker is started once on an empty data folder,
so it creates its own database (`database/moonraker-sql.db`, table `job_history`, see
moonraker/components/history.py) and stopped; the test then inserts rows into that table
with sqlite3, in the columns Moonraker writes for a finished job (metadata and
auxiliary_data as JSON, instance_id "default"), and starts Moonraker again. The printed files
are corpus files copied into `gcodes/` with a fixed modification time, which the jobs'
metadata records, as Moonraker does; `exists` in `/server/history/list` is Moonraker's own
check of that time. Klipper's limits come from the Moonraker settings cache kestimator keeps
for that URL (Moonraker answers 503 to the settings query without Klipper, so the cache
stands in, as it does for a printer whose Klipper is not running).

Each completed job's durations are those print_stats would record for a printer whose start
macro takes START_S and each timelapse frame FRAME_S, with a few seconds of scatter:
total_duration - print_duration = START_S + Klipper's motion before the first extrusion,
print_duration = motion after it + frames x FRAME_S. Planted outliers: a cancelled job, a
paused one (15 minutes more between start and end) and one of a file re-sliced since it was
printed (its metadata's modification time is not the file's).
"""

from __future__ import annotations

import datetime
import json
import os
import re
import shutil
import sqlite3
from pathlib import Path

import pytest

from kestimator import cli, learn
from kestimator.config.moonraker import _write_cache, cache_path
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.estimate import estimate_file
from kestimator.rewrite import PREP_PREFIX
from tests.conftest import CORPUS, CORPUS_CFG
from tests.fake_moonraker import CORPUS_SETTINGS
from tests.test_moonraker_e2e import (  # noqa: F401 (moonraker_python is a fixture)
    _free_port,
    _moonraker,
    _request,
    _wait_ready,
    moonraker_python,
)

START_S = 420.0
FRAME_S = 3.2
PAUSE_S = 900.0
FILE_MTIME = 1_763_000_000.0
GCODE = CORPUS / "gcode"
PYRAMID = GCODE / "superslicer" / "cancelobj_ss2.4_inverted_pyramid.gcode"
CUBE = GCODE / "orcaslicer" / "helixscreen_xyzcube_orca2.3.1_klipper.gcode"
ARCS = GCODE / "superslicer" / "cancelobj_ss2.3.56_arcwelder.gcode"
NUT = GCODE / "prusaslicer" / "ps25_nut_accelA_small.gcode"
CURA_NUT = GCODE / "cura" / "cura413_ender3_nut_small.gcode"
# Newest first: (file, status, scatter of the start in s, of each frame in s, kind).
JOBS = (
    (NUT, "cancelled", 0.0, 0.0, "cancelled"),
    (PYRAMID, "completed", -3.0, 0.02, ""),
    (CUBE, "completed", 2.0, -0.03, ""),
    (ARCS, "completed", 0.0, 0.01, "paused"),
    (NUT, "completed", 0.0, 0.0, ""),
    (CUBE, "completed", 5.0, 0.5, "resliced"),
    (ARCS, "completed", -1.0, -0.01, ""),
    (CURA_NUT, "completed", 1.0, 0.0, ""),
    (PYRAMID, "completed", 3.0, 0.0, ""),
)
PRUSA_TIME_RE = re.compile(rb"; estimated printing time \(normal mode\) = (?:(\d+)h )?"
                           rb"(?:(\d+)m )?(\d+)s")


def _history_rows(limits: object) -> list[tuple]:
    rows = []
    end = 1_763_500_000.0
    estimates = {path: estimate_file(path, limits) for path in {j[0] for j in JOBS}}
    for index, (path, status, start_d, frame_d, kind) in enumerate(reversed(JOBS)):
        est = estimates[path]
        first = est.first_extrusion_t
        assert first is not None
        frames = est.ignored_commands.get(learn.FRAME_MACRO, 0)
        print_s = est.total_s - first + frames * (FRAME_S + frame_d)
        total_s = print_s + START_S + start_d + first + (PAUSE_S if kind == "paused" else 0.0)
        if status != "completed":
            print_s, total_s = print_s / 3, total_s / 3
        modified = FILE_MTIME - (86400.0 if kind == "resliced" else 0.0)
        metadata = {"size": path.stat().st_size, "modified": modified, "slicer": "test",
                    "estimated_time": round(est.total_s)}
        end += 7200.0
        rows.append((index + 1, "No User", path.name, status, end - total_s, end, print_s,
                     total_s, 100.0, json.dumps(metadata), "[]", "default"))
    return rows


def _comment_seconds(data: bytes) -> int:
    match = PRUSA_TIME_RE.search(data)
    assert match is not None
    h, m, s = (int(g) if g else 0 for g in match.groups())
    return h * 3600 + m * 60 + s


def test_learn_reads_moonrakers_history_and_estimate_shows_the_parts(
        moonraker_python: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,  # noqa: F811
        capsys: pytest.CaptureFixture[str]) -> None:
    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home / "config"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(home / "cache"))
    monkeypatch.delenv("MOONRAKER_API_KEY", raising=False)
    data = tmp_path / "printer_data"
    for folder in ("config", "gcodes", "logs", "comms", "database"):
        (data / folder).mkdir(parents=True)
    for path in {j[0] for j in JOBS}:
        copy = data / "gcodes" / path.name
        shutil.copyfile(path, copy)
        os.utime(copy, (FILE_MTIME, FILE_MTIME))
    port = _free_port()
    (data / "config" / "moonraker.conf").write_text(
        "[server]\nhost: 127.0.0.1\nport: %d\nklippy_uds_address: %s\n\n"
        "[machine]\nprovider: none\nvalidate_service: False\n\n"
        "[authorization]\ntrusted_clients:\n  127.0.0.0/8\n\n"
        "[file_manager]\nenable_object_processing: False\n\n[history]\n"
        % (port, data / "comms" / "klippy.sock"))
    base = "http://127.0.0.1:%d" % port
    log = data / "logs" / "stdout.log"
    limits = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False)).limits
    # First start: Moonraker creates its database and history table.
    with _moonraker(moonraker_python, data, port) as process:
        _wait_ready(base, process, log)
    database = data / "database" / "moonraker-sql.db"
    with sqlite3.connect(database) as db:
        db.executemany("INSERT INTO job_history (job_id, user, filename, status, start_time, "
                       "end_time, print_duration, total_duration, filament_used, metadata, "
                       "auxiliary_data, instance_id) VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                       _history_rows(limits))
    db.close()
    # Klipper's settings as the kestimator cache holds them for this printer.
    _write_cache(cache_path(base, home / "cache" / "kestimator"), base,
                 {k: v for k, v in CORPUS_SETTINGS.items()},
                 datetime.datetime(2026, 11, 20, tzinfo=datetime.timezone.utc))
    with _moonraker(moonraker_python, data, port) as process:
        _wait_ready(base, process, log)
        listed = _request(base + "/server/history/list?limit=50")["result"]
        assert listed["count"] == len(JOBS)
        assert cli.main(["learn", "--moonraker", base, "--no-profile"]) == 0
        out = capsys.readouterr().out
    learned = learn.load(base)
    assert learned is not None and learned.jobs_read == len(JOBS)
    prep = learned.before_first_extrusion_s
    assert prep is not None and prep.value == pytest.approx(START_S, rel=0.02)
    # 7 completed jobs whose file is unchanged; the paused one is rejected.
    assert (prep.jobs, prep.rejected) == (6, 1)
    frame = learned.per_run_s[learn.FRAME_MACRO]
    assert frame.value == pytest.approx(FRAME_S, rel=0.02)
    assert frame.jobs == 5 and learned.motion_ratio is None
    assert "status cancelled" in out and "printed with another slicing or config" in out
    assert "is an outlier (a pause?)" in out
    assert "learned from 6 prints" in out

    # estimate with the printer's Moonraker as the limits source uses what was learned.
    assert cli.main(["estimate", str(PYRAMID), "--moonraker", base, "--no-profile",
                     "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    parts = doc["parts"]
    plain = estimate_file(PYRAMID, limits)
    sources = {s["name"]: s for s in parts["sources"]}
    assert sources["before the first extrusion"]["seconds"] == pytest.approx(prep.value)
    frames = sources[learn.FRAME_MACRO]
    assert frames["count"] == 50
    assert parts["total_s"] == pytest.approx(parts["motion_s"] + parts["added_s"], abs=1e-5)
    assert parts["added_s"] == pytest.approx(prep.value + frames["seconds"], abs=1e-5)
    # Each frame stops the toolhead, so motion is the planner's with those stops.
    assert parts["motion_s"] == pytest.approx(plain.total_s, rel=0.01)
    assert cli.main(["estimate", str(PYRAMID), "--moonraker", base, "--no-profile",
                     "--no-learned", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["total_s"] == pytest.approx(plain.total_s,
                                                                           abs=1e-6)
    assert cli.main(["limits", "--moonraker", base, "--no-profile"]) == 0
    shown = capsys.readouterr().out
    assert "learned from 6 prints" in shown and "per timelapse frame" in shown

    # inject: the time comments hold what print_duration measures; the start is one line.
    copy = tmp_path / NUT.name
    shutil.copyfile(NUT, copy)
    assert cli.main(["inject", str(copy), "--moonraker", base, "--no-profile"]) == 0
    written = copy.read_bytes()
    nut_plain = estimate_file(NUT, limits)
    assert _comment_seconds(written) == round(nut_plain.total_s)
    prep_lines = [line for line in written.splitlines()
                  if line.startswith(PREP_PREFIX.encode())]
    assert len(prep_lines) == 1 and b"(%.3f s)" % prep.value in prep_lines[0]
    assert "macros and prep 7m 0" in capsys.readouterr().out
