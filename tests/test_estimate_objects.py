"""Per-object times: EXCLUDE_OBJECT, M486 and `; printing object` labels split the print."""

from __future__ import annotations

from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file, estimate_text
from kestimator.limits import Limits
from kestimator.segments import NO_OBJECT

from .conftest import CORPUS_CFG


@pytest.fixture(scope="module")
def limits() -> Limits:
    return limits_from_printer_cfg(CORPUS_CFG)[0]


def test_four_labelled_tori_each_get_their_time_and_all_sum_to_the_total(
        corpus_root: Path, limits: Limits) -> None:
    est = estimate_file(corpus_root / "gcode/prusaslicer/ps25_torus_x4_labels_marlin.gcode",
                        limits)
    names = ["torus.stl id:0 copy %d" % i for i in (1, 0, 2, 3)]
    assert list(est.objects) == [NO_OBJECT] + names
    assert sum(est.objects.values()) == pytest.approx(est.total_s, abs=1e-6)
    for name in names:  # four copies of one torus take about the same time
        assert est.objects[name] == pytest.approx(est.total_s / 4, rel=0.05)


def test_exclude_object_commands_win_over_the_comments_beside_them(
        corpus_root: Path, limits: Limits) -> None:
    est = estimate_file(
        corpus_root / "gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode", limits)
    assert [n for n in est.objects if n != NO_OBJECT] == [
        "xyz-10mm-calibration-cube.stl_id_0_copy_0"]
    assert sum(est.objects.values()) == pytest.approx(est.total_s, abs=1e-6)


def test_m486_objects_take_their_a_name(corpus_root: Path, limits: Limits) -> None:
    est = estimate_file(
        corpus_root / "gcode/prusaslicer/libbgcode_mini_cube_ps2.8.1_arcs.gcode", limits)
    assert set(est.objects) == {NO_OBJECT, "Shape-Box"}
    assert sum(est.objects.values()) == pytest.approx(est.total_s, abs=1e-6)


def test_object_time_is_the_moves_inside_it_and_a_dwell_inside_counts_for_it(
        limits: Limits) -> None:
    text = "\n".join([
        "G28", "G90", "M83", "G1 X10 Y10 F6000",
        "EXCLUDE_OBJECT_START NAME=a", "G1 X60 F3000", "G4 P2000", "EXCLUDE_OBJECT_END NAME=a",
        "G1 X10 Y60 F6000",
        "EXCLUDE_OBJECT_START NAME=b", "G1 X60 F3000", "EXCLUDE_OBJECT_END NAME=b",
        "G1 X10 Y10 F6000", ""])
    est = estimate_text(text, limits)
    assert set(est.objects) == {NO_OBJECT, "a", "b"}
    assert sum(est.objects.values()) == pytest.approx(est.total_s, abs=1e-9)
    assert est.objects["a"] == pytest.approx(est.objects["b"] + 2.0, abs=0.02)


def test_a_file_without_labels_has_no_objects(limits: Limits) -> None:
    assert estimate_text("G28\nG1 X10 F3000\n", limits).objects == {}
