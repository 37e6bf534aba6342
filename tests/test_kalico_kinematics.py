"""Kalico's limited_cartesian, limited_corexy and limited_corexz kinematics
(kestimator/kinematics/limited_*.py): per-axis [printer] max_x/y/z_velocity and
max_x/y/z_accel, scale_xy_accel, SET_KINEMATICS_LIMIT, range checks. Held to Kalico
v2026.07.00 itself by the references in tests/oracle_refs_releases/kalico-v2026.07.00/<name>/
(made by make_refs.sh there: two corpus files and kinematics_limit.gcode, each folder's
printer.cfg the corpus's with that kinematics)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.errors import KestimatorError
from kestimator.estimate import Estimate, estimate_file, estimate_text
from kestimator.kinematics import KALICO_KINEMATICS, load_kinematics
from kestimator.limits import Limits
from kestimator.preflight import KIND_STOP

from .conftest import CORPUS

RELEASES = Path(__file__).parent / "oracle_refs_releases"
KALICO = RELEASES / "kalico-v2026.07.00"
VERSION = "Kalico v2026.07.00-0-g30c65e09"
# The bar of every release: 0.01 s + 1e-6 x t on the total and every layer (measured within
# 5e-7 s, the references' rounding, on all nine).
TOL_ABS_S = 0.01
TOL_REL = 1e-6


@pytest.fixture
def environ(tmp_path: Path) -> dict[str, str]:
    return {"HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / "config"),
            "XDG_CACHE_HOME": str(tmp_path / "cache")}


def _limits(cfg: Path, environ: dict[str, str], gcode: Path | None = None,
            version: str | None = VERSION, **overrides: str) -> Limits:
    sets = dict(overrides)
    if version is not None:
        sets["klipper_version"] = version
    return resolve_limits(LimitRequest(gcode=gcode, printer_cfg=cfg, environ=environ,
                                       use_profile=False, read_slicer_environment=False,
                                       overrides=sets)).limits


def _gcode(ref: dict[str, object]) -> Path:
    own = RELEASES / str(ref["file"])
    return own if own.exists() else CORPUS / str(ref["file"])


def _refs() -> list[object]:
    return [pytest.param(p, id=f"{p.parent.name}/{p.stem}")
            for name in KALICO_KINEMATICS for p in sorted((KALICO / name).glob("*.json"))]


def _off(est: Estimate, ref: dict[str, object]) -> list[tuple[str, float, float]]:
    """Where the estimate misses the reference by more than the bar."""
    def within(mine: float, theirs: float) -> bool:
        return abs(mine - theirs) <= TOL_ABS_S + TOL_REL * theirs

    mine = dict(est.layers)
    layers = [cp for cp in ref["checkpoints"] if cp["kind"] == "layer"]  # type: ignore[attr-defined]
    assert {cp["line"] for cp in layers} == set(mine)
    off = [("total", est.total_s, float(ref["total_s"]))]  # type: ignore[arg-type]
    off += [(str(cp["line"]), mine[cp["line"]], cp["t"]) for cp in layers]
    return [o for o in off if not within(o[1], o[2])]


def test_all_three_kinematics_have_references() -> None:
    assert sorted(KALICO_KINEMATICS) == ["limited_cartesian", "limited_corexy", "limited_corexz"]
    assert len(_refs()) == 9


@pytest.mark.parametrize("ref_path", _refs())
def test_kalicos_limited_kinematics_give_kalicos_own_times(
        ref_path: Path, corpus_root: Path, environ: dict[str, str]) -> None:
    ref = json.loads(ref_path.read_text())
    gcode = _gcode(ref)
    est = estimate_file(gcode, _limits(ref_path.parent / "printer.cfg", environ, gcode))
    assert not _off(est, ref), _off(est, ref)[:5]


@pytest.mark.parametrize("name", KALICO_KINEMATICS)
def test_without_the_per_axis_limits_set_kinematics_limit_s_program_is_seconds_off(
        name: str, environ: dict[str, str]) -> None:
    """What the modules are for: the same config run as plain cartesian (the per-axis limits
    and SET_KINEMATICS_LIMIT ignored) misses Kalico's time by seconds."""
    ref = json.loads((KALICO / name / "kinematics_limit.json").read_text())
    gcode = _gcode(ref)
    cfg = (KALICO / name / "printer.cfg").read_text()
    plain = estimate_file(gcode, _limits(KALICO / "printer.cfg", environ, gcode))
    assert name in cfg
    assert float(ref["total_s"]) - plain.total_s > 5.0


def test_set_kinematics_limit_changes_the_limits_kalico_s_way(environ: dict[str, str]) -> None:
    limits = _limits(KALICO / "limited_cartesian" / "printer.cfg", environ)
    kin = load_kinematics(limits)
    assert kin.kinematics_limits() == ([250.0, 200.0, 15.0], [2500.0, 1500.0, 100.0], False)
    corexy = load_kinematics(_limits(KALICO / "limited_corexy" / "printer.cfg", environ))
    assert corexy.kinematics_limits() == (None, [2800.0, 1600.0, 100.0], True)
    # A pure X move at 3000 mm/s^2: limited by max_x_accel, until SET_KINEMATICS_LIMIT.
    move = "G1 X100 F30000\n"
    before = estimate_text(move, limits).total_s
    after = estimate_text("SET_KINEMATICS_LIMIT X_ACCEL=3000\n" + move, limits).total_s
    assert after < before - 0.01
    bad = estimate_text("SET_KINEMATICS_LIMIT SCALE=2\n" + move, limits)
    assert any("SCALE" in w and "maximum of 1" in w for w in bad.warnings), bad.warnings


def test_moves_out_of_range_stop_the_print_as_on_cartesian(
        tmp_path: Path, environ: dict[str, str]) -> None:
    """cartesian's range checks, on every move (limited_* check each move's end)."""
    for name in KALICO_KINEMATICS:
        cfg = tmp_path / (name + ".cfg")
        cfg.write_text((KALICO / name / "printer.cfg").read_text().replace(
            "position_max: 1000", "position_max: 200"))
        est = estimate_text("G1 X10 F6000\nG1 X250 Y5 F6000\n", _limits(cfg, environ))
        rejects = [w for w in est.warnings if "Klipper rejects" in w]
        assert rejects and ":2: " in rejects[0], (name, est.warnings)
        assert rejects[0].endswith("Move out of range: 250.000 5.000 0.000 [0.000]")
        assert any(f.kind == KIND_STOP for f in est.preflight), name


def test_a_per_axis_limit_kalico_refuses_is_an_error_with_file_and_line(
        tmp_path: Path, environ: dict[str, str]) -> None:
    """limited_cartesian bounds max_x_velocity by max_velocity (limited_corexz does not)."""
    cfg = tmp_path / "printer.cfg"
    cfg.write_text((KALICO / "limited_cartesian" / "printer.cfg").read_text().replace(
        "max_x_velocity: 250", "max_x_velocity: 350"))
    with pytest.raises(KestimatorError) as refused:
        _limits(cfg, environ)
    assert str(refused.value).startswith(str(cfg) + ":")
    assert "max_x_velocity' must have maximum of 300" in str(refused.value)
    cfg.write_text((KALICO / "limited_corexz" / "printer.cfg").read_text().replace(
        "max_x_velocity: 200", "max_x_velocity: 350"))
    assert load_kinematics(_limits(cfg, environ)).kinematics_limits() == (
        [350.0, 150.0, 15.0], [2000.0, 2500.0, 100.0], False)


def test_a_klipper_without_them_refuses_them_as_it_would(environ: dict[str, str]) -> None:
    cfg = KALICO / "limited_corexy" / "printer.cfg"
    with pytest.raises(KestimatorError) as refused:
        _limits(cfg, environ, version="v0.13.0-730-g84104bbbd")
    assert "limited_corexy is Kalico's" in str(refused.value)
    assert "\n" not in str(refused.value)
    # With no version known the name says Kalico: modelled.
    assert load_kinematics(_limits(cfg, environ, version=None)).kinematics_limits() is not None


def test_a_misspelt_per_axis_option_is_refused_as_kalico_would(
        tmp_path: Path, environ: dict[str, str]) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text((KALICO / "limited_corexy" / "printer.cfg").read_text().replace(
        "max_y_accel: 1600", "max_y_acel: 1600"))
    with pytest.raises(KestimatorError, match="has no option 'max_y_acel' .did you mean "
                                              "'max_y_accel'"):
        _limits(cfg, environ)
