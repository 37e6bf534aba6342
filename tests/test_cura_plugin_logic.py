"""The Cura plugin's Cura-free logic on real CuraEngine G-code: chunks, limits, rewrite.

G-code comes from Debian's CuraEngine 4.13 (a cube sliced here) and from the corpus' Cura
files (CuraEngine 4.13 CLI, the Cura 4.10 and 5.0 applications, CRLF). Each is cut into the
list Cura holds (``split_like_cura``) and rewritten as the plugin does at save time; the
reference is the core's own command line on the joined file.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.errors import KestimatorError
from kestimator.estimate import estimate_file
from kestimator.rewrite import MARKER_PREFIX

from .conftest import CORPUS, CORPUS_CFG, IN_CI, PROJECT, corpus_files, without_progress_table
from .cura_harness.curaengine import find_curaengine, slice_cube

sys.path.insert(0, str(PROJECT / "plugins" / "cura"))

from kestimator_cura import klipper_time  # noqa: E402
from kestimator_cura.chunks import (  # noqa: E402
    is_processed,
    plan_chunks,
    rewrite_chunks,
    split_like_cura,
)
from kestimator_cura.machine import (  # noqa: E402
    MACHINE_SOURCE_TEXT,
    SOURCE_PRINTER_CFG,
    LimitsChoice,
    limits_from_klipper,
    limits_from_klipper_directly,
    limits_from_machine,
)

OWNED_PREFIXES = ("M73", MARKER_PREFIX, ";TIME:", ";PRINT.TIME:", ";TIME_ELAPSED:",
                  "SET_PRINT_STATS_INFO")
# CuraEngine 4.13 CLI; the Cura 5.0 and 4.10 applications' files are CRLF.
CORPUS_CURA = ("cura/cura413_ender3_nut_small.gcode",
               "cura/cancelobj_cura5.0.0_inverted_pyramid.gcode",
               "cura/cancelobj_cura4.10.0.gcode")
_ELAPSED_RE = re.compile(r"^;TIME_ELAPSED:(\S+)$", re.MULTILINE)


@pytest.fixture(scope="session")
def cube_gcode(tmp_path_factory: pytest.TempPathFactory) -> Path:
    program = find_curaengine()
    if program is None:
        if IN_CI:
            pytest.fail("CuraEngine (Debian package cura-engine) and Debian's cura definitions "
                        "are required in CI")
        pytest.skip("CuraEngine or Debian's cura definitions are not installed")
    return slice_cube(program, tmp_path_factory.mktemp("curaengine"))


def _corpus_cura(name: str) -> Path:
    path = CORPUS / "gcode" / name
    if not path.is_file():
        if IN_CI:
            pytest.fail("corpus file missing: %s" % path)
        pytest.skip("the shared corpus is not beside this checkout")
    return path


@pytest.fixture(params=("cube",) + CORPUS_CURA)
def cura_gcode(request: pytest.FixtureRequest) -> Path:
    if request.param == "cube":
        return request.getfixturevalue("cube_gcode")
    return _corpus_cura(request.param)


def _text(path: Path) -> str:
    return path.read_bytes().decode("utf-8", "surrogateescape")


def _cfg_choice() -> LimitsChoice:
    return LimitsChoice(SOURCE_PRINTER_CFG, printer_cfg=str(CORPUS_CFG))


def _cli(*argv: str) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run([sys.executable, "-m", "kestimator", *argv], capture_output=True,
                          text=True, cwd=PROJECT)
    # 4: Klipper will stop this print (a Cura placeholder left in the file); the times are
    # written all the same.
    assert proc.returncode in (0, 4), proc.stderr
    return proc


def _cli_inject(text: str, tmp_path: Path) -> bytes:
    source = tmp_path / "cli_in.gcode"
    source.write_bytes(text.encode("utf-8", "surrogateescape"))
    _cli("inject", "--no-profile", "--printer-cfg", str(CORPUS_CFG), "-q", str(source))
    # The Cura plugin writes no progress table (Cura saves the file).
    return without_progress_table(source.read_bytes())


def _unowned(chunk: str) -> list[str]:
    return [line for line in chunk.split("\n") if not line.lstrip().startswith(OWNED_PREFIXES)]


def test_split_like_cura_gives_header_start_and_one_chunk_per_layer(cube_gcode: Path) -> None:
    text = _text(cube_gcode)
    chunks = split_like_cura(text)
    assert "".join(chunks) == text
    assert chunks[0].startswith(";FLAVOR:") and ";Generated with" not in chunks[0]
    assert chunks[1].startswith(";Generated with Cura_SteamEngine 4.13")
    layers = [chunk for chunk in chunks[2:] if chunk.startswith(";LAYER:")]
    assert len(layers) == len(chunks) - 2 == text.count("\n;LAYER:")


def test_rewrite_keeps_chunk_count_and_every_unowned_line_in_its_chunk(
        cura_gcode: Path) -> None:
    chunks = split_like_cura(_text(cura_gcode))
    outcome = klipper_time.compute(chunks, _cfg_choice(), {})
    assert len(outcome.rewritten) == len(chunks)
    for before, after in zip(chunks, outcome.rewritten, strict=True):
        assert _unowned(after) == _unowned(before)
    assert any(line.startswith("M73 P") for line in outcome.rewritten[-1].split("\n"))
    assert sum(chunk.count("\nM73 P") for chunk in outcome.rewritten) > len(chunks) - 2


def test_joined_rewrite_is_byte_identical_to_kestimator_inject(cura_gcode: Path,
                                                                tmp_path: Path) -> None:
    text = _text(cura_gcode)
    outcome = klipper_time.compute(split_like_cura(text), _cfg_choice(), {})
    joined = "".join(outcome.rewritten).encode("utf-8", "surrogateescape")
    assert joined == _cli_inject(text, tmp_path)


def test_times_written_equal_kestimator_estimate(cube_gcode: Path) -> None:
    proc = _cli("estimate", "--json", "--no-profile", "--printer-cfg", str(CORPUS_CFG),
                str(cube_gcode))
    expected_s = json.loads(proc.stdout)["total_s"]
    chunks = split_like_cura(_text(cube_gcode))
    outcome = klipper_time.compute(chunks, _cfg_choice(), {})
    assert round(outcome.total_s, 6) == expected_s
    assert ";TIME:%d\n" % round(expected_s) in outcome.rewritten[0]
    assert "klipper_s=%.3f " % expected_s in outcome.rewritten[1]
    # Each ;TIME_ELAPSED: gets the time every move before it has finished, as the core
    # computes it for the file.
    from kestimator.config.printer_cfg import limits_from_printer_cfg

    est = estimate_file(cube_gcode, limits_from_printer_cfg(CORPUS_CFG)[0],
                        mark_prefixes=(";TIME_ELAPSED:",))
    written = [float(value) for value in _ELAPSED_RE.findall("".join(outcome.rewritten))]
    assert written == [round(t, 6) for _, t in est.marks]
    assert len(written) == len(chunks) - 2


def test_second_run_changes_nothing(cura_gcode: Path) -> None:
    chunks = split_like_cura(_text(cura_gcode))
    first = klipper_time.compute(chunks, _cfg_choice(), {})
    assert is_processed(first.rewritten) and not is_processed(chunks)
    second = klipper_time.compute(first.rewritten, _cfg_choice(), {})
    assert second.rewritten == first.rewritten


def test_line_cut_between_two_chunks_keeps_its_pieces_in_their_chunks(
        cube_gcode: Path, tmp_path: Path) -> None:
    text = _text(cube_gcode)
    chunks = split_like_cura(text)
    # Move the cut into the middle of a layer marker and of a move line.
    cuts = (chunks[5].index(";LAYER:") + 3, chunks[8].index("\nG1 ") + 5)
    recut = list(chunks)
    for index, cut in zip((5, 8), cuts, strict=True):
        recut[index - 1] += recut[index][:cut]
        recut[index] = recut[index][cut:]
    assert "".join(recut) == text
    chosen = limits_from_klipper(_cfg_choice())
    plan = plan_chunks(recut, chosen.limits, chosen.marker_source)
    rewritten = rewrite_chunks(recut, plan.plan)
    assert len(rewritten) == len(recut)
    assert rewritten[4].endswith(";LA") and rewritten[5].startswith("YER:")
    assert rewritten[7].endswith("\nG1 F") and rewritten[8].startswith(chunks[8][cuts[1]:][:8])
    assert "".join(rewritten).encode() == _cli_inject(text, tmp_path)


def test_a_chunk_with_nothing_to_rewrite_comes_back_as_the_same_object(
        cube_gcode: Path) -> None:
    chunks = split_like_cura(_text(cube_gcode)) + [";a comment chunk after the end\n"]
    outcome = klipper_time.compute(chunks, _cfg_choice(), {})
    assert outcome.rewritten[-1] is chunks[-1]
    assert all(after is not before for before, after in zip(chunks[:-1], outcome.rewritten,
                                                            strict=False))


def test_outcome_applies_in_place_only_to_the_chunks_it_was_computed_from(
        cube_gcode: Path) -> None:
    chunks = split_like_cura(_text(cube_gcode))
    outcome = klipper_time.compute(chunks, _cfg_choice(), {})
    changed = list(chunks)
    changed[3] += "G4 P1000\n"
    assert not outcome.matches(changed)
    with pytest.raises(ValueError):
        outcome.apply_to(changed)
    target = list(chunks)
    same = target
    outcome.apply_to(target)
    assert target is same and target == list(outcome.rewritten)


def test_machine_settings_become_limits_through_the_core_cura_mapping() -> None:
    header = b";FLAVOR:RepRap\n;TIME:100\n;Generated with Cura_SteamEngine 5.0.0\n"
    settings = {
        "machine_max_feedrate_x": 299792458000, "machine_max_feedrate_y": 299792458000,
        "machine_max_feedrate_z": 5, "machine_max_feedrate_e": 25,
        "machine_max_acceleration_x": 800, "machine_max_acceleration_y": 500,
        "machine_max_acceleration_z": 100, "machine_max_acceleration_e": 5000,
        "machine_max_jerk_xy": 10.0, "machine_nozzle_size": 0.6, "material_diameter": 2.85,
        "acceleration_enabled": True, "relative_extrusion": False,
        "machine_firmware_retract": False, "retraction_amount": None,
    }
    chosen = limits_from_machine(settings, header, header)
    limits = chosen.limits
    assert chosen.source == MACHINE_SOURCE_TEXT
    assert limits.max_accel == 500.0 and limits.max_velocity == 300.0
    assert limits.max_z_velocity == 5.0 and limits.max_z_accel == 100.0
    assert limits.max_extrude_only_velocity == 25.0
    assert limits.square_corner_velocity == 10.0
    assert limits.nozzle_diameter == 0.6 and limits.filament_diameter == 2.85
    assert not limits.firmware_retraction_enabled
    assert any("M204" in note for note in chosen.notes)  # RepRap flavor: Klipper ignores them


def test_printer_cfg_choice_reads_the_same_limits_without_the_resolver() -> None:
    if not CORPUS_CFG.is_file():
        pytest.skip("the shared corpus is not beside this checkout")
    via_resolver = limits_from_klipper(_cfg_choice())
    direct = limits_from_klipper_directly(_cfg_choice())
    assert via_resolver.limits == direct.limits
    assert via_resolver.source == direct.source == str(CORPUS_CFG)


def test_unusable_limit_choices_raise_kestimator_errors(tmp_path: Path) -> None:
    with pytest.raises(KestimatorError, match="no printer.cfg"):
        limits_from_klipper(LimitsChoice(SOURCE_PRINTER_CFG))
    with pytest.raises(KestimatorError):
        limits_from_klipper(LimitsChoice(SOURCE_PRINTER_CFG,
                                         printer_cfg=os.fspath(tmp_path / "absent.cfg")))
    with pytest.raises(ValueError):
        LimitsChoice("octoprint")


def test_gcode_without_moves_is_refused(cube_gcode: Path) -> None:
    header = split_like_cura(_text(cube_gcode))[0]
    with pytest.raises(KestimatorError, match="no moves"):
        klipper_time.compute([header, ";LAYER:0\n"], _cfg_choice(), {})


def test_corpus_has_the_cura_files_these_tests_name() -> None:
    names = {path.relative_to(CORPUS / "gcode").as_posix() for path in corpus_files()}
    if not names:
        pytest.skip("the shared corpus is not beside this checkout")
    assert set(CORPUS_CURA) <= names


class _FakeQtCore:
    """A binding's QtCore module: ``QCoreApplication.instance()`` is the running app or None."""

    def __init__(self, running: bool) -> None:
        self.QCoreApplication = self  # noqa: N815 (Qt's name)
        self._running = running

    def instance(self) -> object | None:
        return self if self._running else None


def test_qt_binding_is_the_one_cura_runs_not_merely_an_importable_one() -> None:
    """Bug: PyQt6 was picked whenever importable, and Cura 4.13 (PyQt5) aborted on a dialog."""
    from kestimator_cura.qt import qt_binding_name

    cura4_with_pyqt6_loaded = {"PyQt6.QtCore": _FakeQtCore(False),
                               "PyQt5.QtCore": _FakeQtCore(True)}
    assert qt_binding_name(cura4_with_pyqt6_loaded) == "PyQt5"
    assert qt_binding_name({"PyQt5.QtCore": _FakeQtCore(True)}) == "PyQt5"
    assert qt_binding_name({"PyQt6.QtCore": _FakeQtCore(True),
                            "PyQt5.QtCore": _FakeQtCore(False)}) == "PyQt6"
    assert qt_binding_name({"PyQt5.QtCore": _FakeQtCore(False)}) == "PyQt5"


def test_panel_times_add_up_to_klippers_and_keep_curas_split() -> None:
    cura = {"inset_0": 300.0, "infill": 200.0, "travel": 100.0, "none": 0.0,
            "skin": float("nan")}
    times = klipper_time.klipper_feature_times(cura, 1234.567)
    assert sum(times.values()) == 1234.567
    assert set(times) == set(cura)
    assert times["inset_0"] / times["infill"] == pytest.approx(1.5)
    assert times["none"] == 0.0 and times["skin"] == 0.0
    assert klipper_time.klipper_feature_times({"none": 0.0}, 60.0) == {"none": 60.0}


def test_moonraker_choice_uses_the_times_learned_from_its_history(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from kestimator_cura.machine import SOURCE_MOONRAKER

    from kestimator import learn
    from tests.fake_moonraker import CORPUS_SETTINGS, FakeMoonraker

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("MOONRAKER_API_KEY", raising=False)
    nut = CORPUS / "gcode" / "cura" / "cura413_ender3_nut_small.gcode"
    chunks = split_like_cura(_text(nut))
    server = FakeMoonraker(CORPUS_SETTINGS).start()
    try:
        url = server.url
        learn.save(learn.LearnedTimes(
            learn.normalise_url(url), "2026-11-23T10:00:00Z",
            before_first_extrusion_s=learn.LearnedValue(300.0, 2.0, 4, 1)))
        outcome = klipper_time.compute(chunks, LimitsChoice(SOURCE_MOONRAKER,
                                                            moonraker_url=url), {})
    finally:
        server.stop()
    plain = estimate_file(nut, limits_from_klipper(_cfg_choice()).limits)
    est = outcome.plan.estimate
    assert est.total_s == pytest.approx(plain.total_s + 300.0, abs=1e-6)
    text = outcome.summary()
    assert "5m 00s of it before the first extrusion" in text
    assert "learned from 4 prints" in text
    joined = "".join(outcome.rewritten)
    # Cura's ;TIME: holds what print_duration measures: the learned start is not in it.
    assert re.search(r"^;TIME:(\d+)", joined, re.MULTILINE).group(1) == "%d" % round(
        plain.total_s)
