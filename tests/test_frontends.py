"""What Mainsail and Fluidd show during a print, by their own code (issue 34).

tests/frontends/ runs Mainsail's and Fluidd's store getters (pinned, unmodified sources from
../shared/upstream) in node. These checks hold the harness to the front ends' formulas on
synthetic status cycles, and show that it runs their code: a setting changes the answer as
their source says it must.
"""

from __future__ import annotations

import sys
from typing import Any

import pytest

from .conftest import IN_CI, PROJECT, require_program

sys.path.insert(0, str(PROJECT / "tests" / "frontends"))
import frontends  # noqa: E402

FILE = "nut.gcode"
# Moonraker's metadata for the file: G-code from byte 1000 to 11000, 2000 mm of filament,
# the slicer's 900 s.
METADATA = {"filename": FILE, "gcode_start_byte": 1000, "gcode_end_byte": 11000,
            "filament_total": 2000., "estimated_time": 900., "size": 12000}


@pytest.fixture(scope="module", autouse=True)
def node_side() -> None:
    require_program("node")
    require_program("npm")
    if not all((frontends.UPSTREAM / tarball).is_file()
               for tarball, _ in frontends.SOURCES.values()):
        message = "the pinned front-end sources are not in %s" % frontends.UPSTREAM
        if IN_CI:
            pytest.fail(message)
        pytest.skip(message)
    frontends.prepare()


def cycle(eventtime: float, printed: float, left: float, file_fraction: float,
          filament: float) -> dict[str, Any]:
    """A printing cycle: `printed` s done, `left` s to go (display_status.progress =
    D/(D+R)), the file read to `file_fraction` of its G-code, `filament` mm used."""
    position = 1000 + int(10000 * file_fraction)
    return {"eventtime": eventtime, "status": {
        "print_stats": {"filename": FILE, "state": "printing", "print_duration": printed,
                        "total_duration": printed + 5., "filament_used": filament},
        "display_status": {"progress": printed / (printed + left), "message": None},
        "virtual_sdcard": {"file_path": "/sd/" + FILE, "file_position": position,
                           "progress": position / 12000., "is_active": True},
        "kestimator": {"remaining_s": left},
        "toolhead": {"print_time": eventtime}, "gcode_move": {"gcode_position": [0, 0, 1, 0]},
        "pause_resume": {"is_paused": False}, "exclude_object": {"objects": []}}}


CYCLES = [cycle(100. + d, d, r, f, fil) for d, r, f, fil in (
    (60., 540., 0.2, 150.), (300., 310., 0.45, 900.), (599., 1.5, 0.97, 1990.))]


def test_mainsail_with_kestimator_settings_shows_the_remaining_time() -> None:
    """Progress from M73 and the estimate and ETA from "file": D/p - D with p = D/(D+R) is R
    (Mainsail rounds it to whole seconds)."""
    shown = frontends.show(CYCLES, frontends.KESTIMATOR_SETTINGS, METADATA)
    for c, row in zip(CYCLES, shown):
        m = row["mainsail"]
        left = c["status"]["kestimator"]["remaining_s"]
        assert m["progress"] == c["status"]["display_status"]["progress"]
        assert m["displayedPercent"] == int(100 * m["progress"])
        assert abs(m["file_s"] - left) <= 1.
        assert m["estimate_s"] == m["file_s"]  # the "Estimate" shown: file alone
        assert abs(m["eta_left_s"] - left) <= 1.  # the ETA: now + file


def test_mainsail_defaults_use_file_position_and_average() -> None:
    """Mainsail's defaults: progress from the file position (relative to the G-code's bytes),
    "Estimate" the average of file and filament, ETA the average of file, filament, slicer."""
    row = frontends.show(CYCLES[:1], {}, METADATA)[0]
    m = row["mainsail"]
    printed = 60.
    assert m["progress"] == pytest.approx(0.2)
    file_s = printed / 0.2 - printed
    filament_s = printed / (150. / 2000.) - printed
    slicer_s = 900. - printed
    assert m["file_s"] == round(file_s) and m["filament_s"] == round(filament_s)
    assert m["slicer_s"] == slicer_s
    assert m["estimate_s"] == (round(file_s) + round(filament_s)) / 2
    assert m["eta_left_s"] == pytest.approx((round(file_s) + round(filament_s) + slicer_s) / 3,
                                            abs=1e-3)


def test_a_mainsail_setting_changes_what_it_shows() -> None:
    """The harness runs Mainsail's own getters: each setting changes the answer as its code
    says (file-absolute reads virtual_sdcard.progress; filament progress; ETA from slicer)."""
    base = frontends.show(CYCLES[:1], frontends.KESTIMATOR_SETTINGS, METADATA)[0]["mainsail"]
    for setting, expect_progress in (("file-relative", 0.2), ("file-absolute", 3000 / 12000),
                                     ("filament", 150. / 2000.)):
        settings = {"mainsail": dict(frontends.KESTIMATOR_SETTINGS["mainsail"],
                                     **{"general.calcPrintProgress": setting})}
        m = frontends.show(CYCLES[:1], settings, METADATA)[0]["mainsail"]
        assert m["progress"] == pytest.approx(expect_progress)
        assert m["file_s"] == round(60. / expect_progress - 60.) != base["file_s"]
    settings = {"mainsail": dict(frontends.KESTIMATOR_SETTINGS["mainsail"],
                                 **{"general.calcEtaTime": ["slicer"]})}
    m = frontends.show(CYCLES[:1], settings, METADATA)[0]["mainsail"]
    assert m["eta_left_s"] == pytest.approx(900. - 60., abs=1e-3)
    assert m["file_s"] == base["file_s"]


def test_fluidd_progress_follows_m73_but_its_time_left_the_file_position() -> None:
    """Fluidd's progress can be display_status.progress; its "File" time left and its ETA
    (default "file") use the file position whatever the progress setting."""
    shown = frontends.show(CYCLES, frontends.KESTIMATOR_SETTINGS, METADATA)
    defaults = frontends.show(CYCLES, {}, METADATA)
    for c, row, default in zip(CYCLES, shown, defaults):
        f, fd = row["fluidd"], default["fluidd"]
        status = c["status"]
        position = (status["virtual_sdcard"]["file_position"] - 1000) / 10000
        assert f["progress"] == pytest.approx(status["display_status"]["progress"])
        assert f["getTimeEstimates"]["progress"] == int(100 * f["progress"])
        assert fd["progress"] == pytest.approx(position)
        printed = status["print_stats"]["print_duration"]
        assert f["file_s"] == fd["file_s"] == pytest.approx(printed / position - printed)
        assert f["eta_left_s"] == pytest.approx(f["file_s"], abs=1e-3)
        assert f["slicer_s"] == 900. - printed
    slicer = frontends.show(CYCLES[:1], {"fluidd": {
        "uiSettings.general.printEtaCalculation": ["slicer"]}}, METADATA)[0]["fluidd"]
    assert slicer["eta_left_s"] == pytest.approx(900. - 60., abs=1e-3)


def test_fluidd_shows_the_actual_time_of_a_completed_earlier_print() -> None:
    """Fluidd's "file" ETA takes a completed earlier job's duration when the file's job_id
    names it in Moonraker's history (the "Actual" line), before the file position."""
    metadata = dict(METADATA, job_id="00000A")
    jobs = [{"job_id": "00000A", "filename": FILE, "status": "completed", "start_time": 1.,
             "end_time": 700., "print_duration": 650., "total_duration": 700.,
             "filament_used": 2000., "exists": True, "metadata": None}]
    f = frontends.show(CYCLES[:1], {}, metadata, jobs)[0]["fluidd"]
    assert f["actual_s"] == 700. - 60.
    assert f["eta_left_s"] == pytest.approx(640., abs=1e-3)


def test_realtime_view_compares_with_the_truth() -> None:
    """realtime_view on a run_realtime-shaped result: per sample what each front end shows
    and its difference from truth_s."""
    samples = [dict(c, truth_s=c["status"]["kestimator"]["remaining_s"] + 0.2,
                    remaining_s=c["status"]["kestimator"]["remaining_s"]) for c in CYCLES]
    rows = frontends.realtime_view({"samples": samples}, metadata=METADATA)
    assert len(rows) == len(samples)
    for sample, row in zip(samples, rows):
        assert row["truth_s"] == sample["truth_s"]
        assert abs(row["mainsail_estimate_error_s"] + 0.2) <= 1.
        assert abs(row["mainsail_eta_left_error_s"] + 0.2) <= 1.
        assert row["fluidd_file_error_s"] == pytest.approx(row["fluidd_file_s"]
                                                           - sample["truth_s"])
