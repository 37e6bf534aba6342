"""Klipper's timing behaviour, pinned on small G-code snippets.

The analytic cases are worked out by hand from Klipper's trapezoid; the traps are the
ones listed in shared/docs/KLIPPER.md, each shown against the naive reading it refutes.
"""

from __future__ import annotations

import math

import pytest

from kestimator.estimate import estimate_text
from kestimator.limits import Limits

# The corpus printer: 300 mm/s, 3000 mm/s^2, scv 5, mcr 0.5, Z 15 mm/s / 100 mm/s^2,
# extruder 120 mm/s / 1500 mm/s^2, icv 1, arcs at 1 mm, firmware retraction 0.8 mm @ 35.
CORPUS_LIMITS = Limits.from_values(dict(
    max_velocity=300.0, max_accel=3000.0, square_corner_velocity=5.0,
    minimum_cruise_ratio=0.5, max_z_velocity=15.0, max_z_accel=100.0,
    max_extrude_only_velocity=120.0, max_extrude_only_accel=1500.0,
    max_extrude_only_distance=10000.0, max_extrude_cross_section=1000.0,
    instantaneous_corner_velocity=1.0, arcs_enabled=True, arc_resolution=1.0,
    firmware_retraction_enabled=True, retract_length=0.8, retract_speed=35.0,
    unretract_extra_length=0.0, unretract_speed=35.0))


def t(gcode: str, limits: Limits = CORPUS_LIMITS, **options: float) -> float:
    return estimate_text(gcode, limits, **options).total_s


def trapezoid_t(distance: float, speed: float, accel: float) -> float:
    """Rest-to-rest time of one move (no cruise-ratio limit)."""
    accel_d = speed * speed / (2 * accel)
    if 2 * accel_d >= distance:
        return 2 * math.sqrt(distance / accel)
    return 2 * speed / accel + (distance - 2 * accel_d) / speed


# Analytic cases
def test_single_line_takes_the_trapezoid_time() -> None:
    # 100 mm at 100 mm/s, 3000 mm/s^2: 1/30 s up, 1/30 s down, 93.33 mm cruise.
    assert t("G1 X100 F6000\n") == pytest.approx(1.033333, abs=1e-6)
    assert t("G1 X100 F6000\n") == pytest.approx(trapezoid_t(100, 100, 3000), abs=1e-9)


def test_square_with_5mm_s_corners() -> None:
    square = "G1 X100 F6000\nG1 Y100\nG1 X0\nG1 Y0\n"
    assert t(square) == pytest.approx(4.123583, abs=1e-6)


def test_g4_p_dwells_milliseconds() -> None:
    assert t("G4 P500\n") == pytest.approx(0.5, abs=1e-12)


def test_g4_s_is_ignored_by_klipper() -> None:
    assert t("G4 S3\n") == 0.0
    assert t("G4\n") == 0.0


def test_m204_p_alone_changes_nothing() -> None:
    est = estimate_text("M204 P1000\nG1 X100 F6000\n", CORPUS_LIMITS)
    assert est.total_s == pytest.approx(t("G1 X100 F6000\n"), abs=1e-12)
    assert any("M204" in w for w in est.warnings)


def test_m204_s_sets_accel_and_p_with_t_takes_the_minimum() -> None:
    assert t("M204 S1000\nG1 X100 F6000\n") == pytest.approx(
        trapezoid_t(100, 100, 1000), abs=1e-9)
    assert t("M204 P800 T1200\nG1 X100 F6000\n") == pytest.approx(
        trapezoid_t(100, 100, 800), abs=1e-9)


def test_marlin_limit_codes_do_not_exist_in_klipper() -> None:
    est = estimate_text("M201 X100 Y100\nM203 X10\nM205 X1\nG1 X100 F6000\n", CORPUS_LIMITS)
    assert est.total_s == pytest.approx(1.033333, abs=1e-6)
    assert est.ignored_commands == {"M201": 1, "M203": 1, "M205": 1}


def test_speed_is_capped_by_max_velocity() -> None:
    assert t("G1 X300 F60000\n") == pytest.approx(trapezoid_t(300, 300, 3000), abs=1e-9)


# Dwells and full stops
def test_g4_flushes_the_lookahead_so_the_head_stops() -> None:
    straight = t("G1 X50 F6000\nG1 X100\n")
    stopped = t("G1 X50 F6000\nG4 P0\nG1 X100\n")
    assert straight == pytest.approx(trapezoid_t(100, 100, 3000), abs=1e-9)
    assert stopped == pytest.approx(2 * trapezoid_t(50, 100, 3000), abs=1e-9)


def test_m400_stops_the_head_like_a_dwell() -> None:
    assert t("G1 X50 F6000\nM400\nG1 X100\n") == pytest.approx(
        2 * trapezoid_t(50, 100, 3000), abs=1e-9)


def test_heater_wait_stops_the_head_but_m109_r_does_not_wait() -> None:
    stop = 2 * trapezoid_t(50, 100, 3000)
    assert t("G1 X50 F6000\nM109 S200\nG1 X100\n") == pytest.approx(stop, abs=1e-9)
    assert t("G1 X50 F6000\nM190 S60\nG1 X100\n") == pytest.approx(stop, abs=1e-9)
    assert t("G1 X50 F6000\nTEMPERATURE_WAIT SENSOR=extruder MINIMUM=200\nG1 X100\n") == (
        pytest.approx(stop, abs=1e-9))
    assert t("G1 X50 F6000\nM109 R200\nG1 X100\n") == pytest.approx(
        trapezoid_t(100, 100, 3000), abs=1e-9)
    assert t("G1 X50 F6000\nM104 S200\nG1 X100\n") == pytest.approx(
        trapezoid_t(100, 100, 3000), abs=1e-9)


def test_heat_and_homing_time_are_settings() -> None:
    base = t("G28\nM109 S200\nG1 X10 F6000\n")
    assert t("G28\nM109 S200\nG1 X10 F6000\n", heat_time=30.0) == pytest.approx(base + 30.0)
    assert t("G28\nM109 S200\nG1 X10 F6000\n", homing_time=12.0) == pytest.approx(base + 12.0)


def test_m84_dwells_twice_and_homing_adds_the_restart_gap() -> None:
    move = trapezoid_t(50, 100, 3000)
    # M84 after motion: 2 x 0.1 s dwell plus the 2 ms step-generation restart.
    assert t("G1 X50 F6000\nM84\n") == pytest.approx(move + 0.202, abs=1e-9)
    # Motors already off: nothing to wait for.
    assert t("M84\nG1 X50 F6000\n") == pytest.approx(move, abs=1e-9)
    # G28 after motion: the next move starts 2 ms after the last one ended.
    assert t("G1 X50 F6000\nG28 X\nG1 X50\n") == pytest.approx(2 * move + 0.002, abs=1e-9)
    # G28 before any motion costs nothing.
    assert t("G28\nG1 X50 F6000\n") == pytest.approx(move, abs=1e-9)


def test_estimator_add_time_comment_adds_seconds() -> None:
    assert t("G1 X50 F6000\n; ESTIMATOR_ADD_TIME 20 filament change\n") == pytest.approx(
        trapezoid_t(50, 100, 3000) + 20.0, abs=1e-9)


# Extruder limits
def test_extrude_only_move_uses_extruder_limits_not_max_velocity() -> None:
    # 100 mm of E at 200 mm/s: capped by max_extrude_only_velocity 120, accel 1500,
    # and shaped by the cruise ratio pseudo-accel 1500: peak v2 = 1500*100 > 120^2.
    assert t("M83\nG1 E100 F12000\n") == pytest.approx(trapezoid_t(100, 120, 1500), abs=1e-9)


def test_retract_speed_follows_minimum_cruise_ratio_after_low_accel() -> None:
    # 1 mm retract at 35 mm/s: with accel 3000 the mcr pseudo-accel (1500) allows 35 mm/s.
    fast = t("M83\nG1 E-1 F2100\n")
    assert fast == pytest.approx(0.051905, abs=1e-6)
    # After M204 S1250 the pseudo-accel is 625: the retract peaks at 25 mm/s.
    slow = t("M83\nM204 S1250\nG1 E-1 F2100\n")
    assert slow == pytest.approx(0.056667, abs=1e-6)


def test_retract_while_travelling_is_limited_like_an_extrude_only_move() -> None:
    # Wipe: 10 mm of XY with 8 mm of retract, E/mm = 0.8: the extruder caps the move at
    # 120/0.8 = 150 mm/s and 1500/0.8 = 1875 mm/s^2; the cruise ratio (pseudo-accel 1500
    # over 10 mm) then caps the peak at v2 = 15000, reached after 4 mm at 1875 mm/s^2.
    wipe = t("M83\nG1 X10 E-8 F18000\n")
    plain = t("M83\nG1 X10 F18000\n")
    peak_v = math.sqrt(15000.0)
    assert wipe == pytest.approx(2 * 4 / (peak_v / 2) + 2 / peak_v, rel=1e-12)
    assert wipe > plain


def test_extruder_junction_limit_slows_corners_where_flow_changes() -> None:
    # Same direction, different E per mm: Klipper limits the junction to
    # (icv / |delta E/mm|)^2 = (1 / 0.05)^2 → 20 mm/s instead of full speed.
    same_flow = t("M83\nG1 X50 E2.5 F6000\nG1 X100 E2.5\n")
    new_flow = t("M83\nG1 X50 E2.5 F6000\nG1 X100 E5\n")
    assert same_flow == pytest.approx(trapezoid_t(100, 100, 3000), abs=1e-9)
    assert new_flow > same_flow + 0.01


def test_overextrusion_beyond_cross_section_is_rejected_with_a_warning() -> None:
    limits = CORPUS_LIMITS.replace(max_extrude_cross_section=0.64)
    est = estimate_text("M83\nG1 X10 E50 F6000\nG1 X20 F6000\n", limits)
    assert any(":2:" in w and "extrusion" in w for w in est.warnings)
    # The rejected move does not happen; the next one travels the full 20 mm.
    assert est.total_s == pytest.approx(trapezoid_t(20, 100, 3000), abs=1e-9)


# Z limits
def test_z_moves_use_max_z_velocity_and_accel() -> None:
    assert t("G1 Z10 F6000\n") == pytest.approx(trapezoid_t(10, 15, 100), abs=1e-9)


def test_diagonal_z_move_is_scaled_by_distance_over_dz() -> None:
    # 3-4-0 in XZ: distance 5, dz 4, so 15*5/4 mm/s and 100*5/4 mm/s^2.
    assert t("G1 X3 Z4 F6000\n") == pytest.approx(trapezoid_t(5, 18.75, 125), abs=1e-9)


# Coordinate modes
def test_g91_makes_e_relative_even_after_m82() -> None:
    # Cura's end G-code: read with absolute E, "G1 E-2" would retract the whole filament.
    cura_end = "M82\nG1 X10 E500 F3000\nG91\nG1 E-2 F2700\nG1 Z0.5 E-5 X-5 Y-5\n"
    explicit = "M83\nG1 X10 E500 F3000\nG1 E-2 F2700\nG1 X5 Y-5 Z0.5 E-5 F2700\n"
    assert t(cura_end) == pytest.approx(t(explicit), abs=1e-12)


def test_m83_with_g90_keeps_e_relative() -> None:
    assert t("M83\nG90\nG1 E5 F600\nG1 E5\n") == pytest.approx(
        t("M83\nG1 E10 F600\n") + 0.0, rel=0.5)
    assert t("M83\nG90\nG1 E5 F600\nG1 E5\n") > t("M82\nG90\nG1 E5 F600\nG1 E5\n")


def test_g92_moves_nothing() -> None:
    assert t("G1 X10 F6000\nG92 X0\nG1 X10\n") == pytest.approx(
        t("G1 X20 F6000\n"), abs=1e-12)


def test_m220_scales_feedrates() -> None:
    assert t("M220 S50\nG1 X100 F6000\n") == pytest.approx(
        trapezoid_t(100, 50, 3000), abs=1e-9)


def test_m221_scales_every_e_move_including_retracts() -> None:
    assert t("M83\nM221 S50\nG1 E-4 F600\n") == pytest.approx(t("M83\nG1 E-2 F600\n"), abs=1e-12)
    assert t("M83\nM221 T0 S95\nG1 E-10 F600\n") == pytest.approx(
        t("M83\nG1 E-9.5 F600\n"), abs=1e-12)


def test_moves_before_any_extrusion_mode_are_warned_about() -> None:
    est = estimate_text("G1 X10 E1 F600\n", CORPUS_LIMITS)
    assert any("M82/M83" in w for w in est.warnings)


# SET_VELOCITY_LIMIT and Klipper generations
def test_set_velocity_limit_changes_accel_and_velocity() -> None:
    assert t("SET_VELOCITY_LIMIT ACCEL=1000 VELOCITY=50\nG1 X100 F6000\n") == pytest.approx(
        trapezoid_t(100, 50, 1000), abs=1e-9)


def test_accel_to_decel_is_ignored_by_mainline_but_not_by_the_2024_generation() -> None:
    gcode = ("SET_VELOCITY_LIMIT ACCEL=3000 ACCEL_TO_DECEL=300\n"
             "G1 X100 F18000\n")
    mainline = t(gcode)
    assert mainline == pytest.approx(t("G1 X100 F18000\n"), abs=1e-12)
    mcr = t(gcode, CORPUS_LIMITS.replace(klipper_generation="mcr"))
    assert mcr > mainline + 0.1


def test_minimum_cruise_ratio_limits_short_moves() -> None:
    # A 10 mm move at 300 mm/s: mcr 0 reaches sqrt(accel*d); mcr 0.5 only half the v2.
    no_mcr = t("G1 X10 F18000\n", CORPUS_LIMITS.replace(minimum_cruise_ratio=0.0))
    assert no_mcr == pytest.approx(trapezoid_t(10, 300, 3000), abs=1e-9)
    assert t("G1 X10 F18000\n") > no_mcr


# Arcs
def test_arc_segment_count_follows_resolution() -> None:
    # Half circle of radius 10 (31.4 mm) at 1 mm resolution: 31 segments.
    est = estimate_text("G1 X10 Y0 F3000\nG2 X-10 Y0 I-10 J0\n", CORPUS_LIMITS)
    assert est.n_moves == 1 + 31


def test_arc_with_unchanged_xy_is_a_full_circle_helix() -> None:
    est = estimate_text("G1 X10 Y0 F3000\nG3 Z1 I-10 J0 P1\n", CORPUS_LIMITS)
    assert est.n_moves == 1 + math.floor(math.hypot(2 * math.pi * 10, 1))


def test_relative_arcs_and_r_arcs_are_rejected_like_klipper() -> None:
    est = estimate_text("G91\nG2 X10 Y0 I5 J0\nG90\nG2 X10 R5\n", CORPUS_LIMITS)
    assert est.n_moves == 0
    g2_warnings = [w for w in est.warnings if "G2" in w]
    assert len(g2_warnings) == 1 and g2_warnings[0].endswith("(1 more like it)")


def test_absurdly_long_arcs_are_refused_instead_of_hanging() -> None:
    est = estimate_text("G1 X0 Y0 F3000\nG2 X0 Y0 I5000000 J0\nG1 X10\n", CORPUS_LIMITS)
    assert est.n_moves == 1
    assert any("segments" in w and "<text>:2:" in w for w in est.warnings)


def test_arcs_without_gcode_arcs_are_unknown_commands() -> None:
    est = estimate_text("G2 X10 Y0 I5 J0\n", CORPUS_LIMITS.replace(arcs_enabled=False))
    assert est.n_moves == 0
    assert est.ignored_commands == {"G2": 1}


# Firmware retraction
def test_g10_g11_retract_once_at_the_configured_speed() -> None:
    one = t("M83\nG10\n")
    assert t("M83\nG10\nG10\n") == pytest.approx(one, abs=1e-12)
    assert one == pytest.approx(t("M83\nG1 E-0.8 F2100\n"), abs=1e-12)
    assert t("M83\nG10\nG11\n") == pytest.approx(2 * one, abs=1e-12)


def test_set_retraction_changes_length_and_speed() -> None:
    assert t("M83\nSET_RETRACTION RETRACT_LENGTH=2 RETRACT_SPEED=20\nG10\n") == (
        pytest.approx(t("M83\nG1 E-2 F1200\n"), abs=1e-12))


# Robustness of the G-code layer
def test_unparsable_line_gives_a_warning_with_its_line_not_a_crash() -> None:
    est = estimate_text("G1 X10 F6000\nG1 X1.2.3\nG1 X20\n", CORPUS_LIMITS)
    assert any("<text>:2:" in w for w in est.warnings)
    assert est.total_s == pytest.approx(trapezoid_t(20, 100, 3000), abs=1e-9)


def test_unknown_move_parameters_are_warned_about_and_ignored_like_klipper() -> None:
    # Klipper reads "XABC" as a parameter named XABC: the move goes nowhere.
    est = estimate_text("G1 X10 F6000\nG1 Xabc\nG1 X20\n", CORPUS_LIMITS)
    assert any("<text>:2:" in w and "XABC" in w for w in est.warnings)
    assert est.total_s == pytest.approx(trapezoid_t(20, 100, 3000), abs=1e-9)


def test_macros_are_counted_and_warned_as_unknown() -> None:
    est = estimate_text("PRINT_START BED=60\nT0\nG1 X10 F6000\n", CORPUS_LIMITS)
    assert est.ignored_commands == {"PRINT_START": 1, "T0": 1}
    assert any("PRINT_START" in w for w in est.warnings)


def test_layers_record_the_time_every_earlier_move_has_finished() -> None:
    est = estimate_text(";LAYER_CHANGE\nG1 X50 F6000\n;LAYER_CHANGE\nG1 X100\n",
                        CORPUS_LIMITS)
    assert [line for line, _ in est.layers] == [1, 3]
    assert est.layers[0][1] == 0.0
    # The first move does not stop at the layer change: it ends at cruise speed.
    # 1/30 s to reach 100 mm/s over 5/3 mm, then the rest of the 50 mm at 100 mm/s.
    assert est.layers[1][1] == pytest.approx(1 / 30 + (50 - 5 / 3) / 100, abs=1e-9)


def test_features_add_up_to_the_motion_time() -> None:
    est = estimate_text(";TYPE:Perimeter\nG1 X50 F6000\n;TYPE:Infill\nG1 X100\n",
                        CORPUS_LIMITS)
    assert set(est.features) == {"Perimeter", "Infill"}
    assert sum(est.features.values()) == pytest.approx(est.total_s, abs=1e-9)


def test_a_time_mark_after_a_dwell_gets_klipper_print_time_like_a_layer_marker() -> None:
    # A slicer's time comment (Cura's ;TIME_ELAPSED:) right after a dwell on an empty
    # look-ahead queue is reached after the dwell: Klipper's print_time there, the time the
    # oracle records for a layer marker at the same place (tests/oracle_refs/snippets/
    # dwell_then_layer.gcode), not the end of the last move.
    import io

    from kestimator.estimate import estimate_lines
    gcode = ("G90\nG1 X10 Y10 Z1 F6000\nG4 P500\n;LAYER_CHANGE\n;TIME_ELAPSED:1\n"
             "G1 X20 F6000\nG4 P250\nM400\n;LAYER_CHANGE\n;TIME_ELAPSED:2\nG1 X30 F6000\n")
    result = estimate_lines(io.BytesIO(gcode.encode()), CORPUS_LIMITS,
                            mark_prefixes=(";TIME_ELAPSED:",))
    layers = dict(result.layers)
    marks = result.marks.by_line()
    assert sorted(marks) == [5, 10]
    assert marks[5] == layers[4]
    assert marks[10] == layers[9]
    # The first mark is 0.5 s (the G4 P500) after the first move's end.
    assert marks[5] == pytest.approx(t("G90\nG1 X10 Y10 Z1 F6000\n") + 0.5, abs=1e-9)
