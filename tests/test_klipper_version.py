"""`klipper_version`: the Klipper a printer runs, as Moonraker's printer.info reports it, selects
that release's semantics (the klipper_generation: what max_accel_to_decel and ACCEL_TO_DECEL
mean, and which of the two [printer] options it accepts). Set by --set, the profile, a
printer.cfg comment, or read from Moonraker. It also selects the toolhead's junction and
print-time rules; held to real Klipper v0.12.0 and v0.13.0 by the references in
tests/oracle_refs_releases/klipper-<release> (made by make_refs.sh there)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from kestimator.config.moonraker import moonraker_values
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.errors import KestimatorError
from kestimator.estimate import Estimate, estimate_file
from kestimator.limits import Limits, klipper_release
from kestimator.toolhead import (
    ClampedJunctionMove,
    DelayedLookAheadQueue,
    ForceFlushToolHead,
    LookAheadQueue,
    MinRestartToolHead,
    Move,
    ToolHead,
    make_toolhead,
)

from .conftest import CORPUS
from .fake_moonraker import CORPUS_SETTINGS, TIMEOUT_S, V0_12_INFO, FakeMoonraker

V0_12 = Path(__file__).parent / "oracle_refs_releases" / "klipper-v0.12.0"
# What each release's own Klipper gave, against kestimator with that klipper_version (its
# generation, junction rule and print-time rule): the bar of every release, 0.01 s + 1e-6 x t
# on the total and every layer. Measured within 5e-7 s (the references' rounding) on all six
# files of v0.12.0 and of v0.13.0.
TOL_ABS_S = 0.01
TOL_REL = 1e-6
# flush_junctions.gcode is there for rules whose effect is small: its microsecond.
TOL_RULES_S = 2e-6
PRINTER = "[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n{extra}"


@pytest.fixture
def environ(tmp_path: Path) -> dict[str, str]:
    """No profile (until a test writes one), a private cache, no slicer environment."""
    return {"HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / "config"),
            "XDG_CACHE_HOME": str(tmp_path / "cache")}


@pytest.mark.parametrize(("version", "generation"), [
    ("v0.11.0-0-g9a7a2b4d", "absolute"),
    ("v0.12.0", "absolute"),
    ("v0.12.0-118-g18de421c4", "absolute"),
    ("v0.12.0-119-g0105aa330", "mcr"),
    ("v0.12.0-455-g5f2d7bc8", "mcr"),
    ("v0.13.0-0-g61c0c8d2", "mcr"),
    ("v0.13.0-191-gcfc58d3ce", "mcr"),
    ("v0.13.0-192-g3ef760c18", "mainline"),
    ("v0.13.0-730-g84104bbbd-dirty", "mainline"),
    ("Kalico v2026.07.00-0-g30c65e09", "mcr"),
    ("Kalico v2025.10.00-12-gabcdef12", "mcr"),
])
def test_a_version_as_printer_info_reports_it_selects_that_releases_generation(
        version: str, generation: str) -> None:
    release = klipper_release(version)
    assert (release.generation, release.note) == (generation, None)


@pytest.mark.parametrize(("version", "junction", "print_time", "waits"), [
    ("v0.11.0-0-g9a7a2b4d", "clamped", "force_flush", False),
    ("v0.12.0", "clamped", "force_flush", False),
    ("v0.12.0-22-g0e5b5e5c", "clamped", "force_flush", False),
    ("v0.12.0-23-gb7b13588c", "clamped", "mainline", False),
    ("v0.12.0-69-g3d3b87f97", "clamped", "min_restart", False),
    ("v0.12.0-262-gc84d78f3f", "clamped", "min_restart", True),
    ("v0.12.0-383-g8291788f4", "clamped_delta_v2", "min_restart", True),
    ("v0.12.0-384-g847331260", "mainline", "min_restart", True),
    ("v0.13.0-0-g61c0c8d2", "mainline", "min_restart", True),
    ("v0.13.0-238-g1e7c67919", "mainline", "mainline", True),
    ("v0.13.0-246-g542694350", "mainline", "mainline", False),
    ("v0.13.0-730-g84104bbbd-dirty", "mainline", "mainline", False),
    ("v0.14.0-2-g1234abcd", "mainline", "mainline", False),
    ("Kalico v2026.07.00-0-g30c65e09", "mainline", "min_restart", False),
])
def test_a_version_selects_its_releases_junction_and_print_time_rules(
        version: str, junction: str, print_time: str, waits: bool) -> None:
    """The commits that changed them (b7b13588c, 3d3b87f97, 1e7c67919: the restart after a
    flush of step generation; 8291788f4, 847331260: the junction; c84d78f3f, 542694350: a
    new pressure-advance window waiting for the toolhead); the generation does not decide."""
    release = klipper_release(version)
    assert (release.junction, release.print_time, release.pressure_advance_waits) == (
        junction, print_time, waits)


@pytest.mark.parametrize(("version", "always_flushes", "lookahead"), [
    ("v0.11.0-0-g9a7a2b4d", True, "delayed"),
    ("v0.12.0", True, "delayed"),
    ("v0.12.0-261-g0a2b3c4d5", True, "delayed"),
    ("v0.12.0-262-gc84d78f3f", False, "delayed"),
    ("v0.13.0-0-g61c0c8d2", False, "delayed"),
    ("v0.13.0-299-gff8c8eab5", False, "delayed"),
    ("v0.13.0-300-g41901ec38", False, "mainline"),
    ("v0.13.0-730-g84104bbbd-dirty", False, "mainline"),
    ("Kalico v2026.07.00-0-g30c65e09", True, "delayed"),
])
def test_a_version_selects_its_releases_pressure_advance_flush_and_look_ahead_rules(
        version: str, always_flushes: bool, lookahead: str) -> None:
    """c84d78f3f (v0.12.0-262) flushes step generation only for a new pressure-advance
    window (Kalico never took it); 41901ec38 (v0.13.0-300) took out the look-ahead's capped
    peak and its list of delayed moves (Kalico has them)."""
    release = klipper_release(version)
    assert (release.pressure_advance_always_flushes, release.lookahead) == (
        always_flushes, lookahead)
    toolhead = make_toolhead(Limits.from_values({"klipper_version": version}))
    assert type(toolhead.lookahead) is {"delayed": DelayedLookAheadQueue,
                                        "mainline": LookAheadQueue}[lookahead]


def test_only_the_releases_with_the_old_rules_get_the_old_toolhead() -> None:
    cases = {"": (ToolHead, Move), "v0.13.0-730": (ToolHead, Move),
             "Kalico v2026.07.00": (MinRestartToolHead, Move),
             "v0.13.0": (MinRestartToolHead, Move),
             "v0.12.0-118": (MinRestartToolHead, ClampedJunctionMove),
             "v0.12.0": (ForceFlushToolHead, ClampedJunctionMove)}
    for version, (toolhead_class, move_class) in cases.items():
        toolhead = make_toolhead(Limits.from_values({"klipper_version": version}))
        assert type(toolhead) is toolhead_class, version
        move = toolhead.move_to(10.0, 0.0, 0.0, 0.0, 100.0)
        assert type(move) is move_class, version


@pytest.mark.parametrize(("version", "newest"), [
    ("v0.14.0-2-g1234abcd", "Klipper 84104bbbd (v0.13.0-730, 2026-08)"),
    ("v0.13.0-731-gabcdef01", "Klipper 84104bbbd (v0.13.0-730, 2026-08)"),
    ("Kalico v2026.11.00-0-g0badc0de", "Kalico v2026.07.00"),
])
def test_a_version_newer_than_the_newest_known_is_taken_as_it_with_one_line(
        version: str, newest: str, tmp_path: Path, environ: dict[str, str]) -> None:
    release = klipper_release(version)
    assert release.note == (f"klipper_version {version} is newer than the newest "
                            f"{release.app} kestimator knows: taken as {newest}")
    resolved = resolve_limits(LimitRequest(environ=environ,
                                           overrides={"klipper_version": version}))
    assert resolved.limits.klipper_generation == klipper_release(
        "Kalico v2026.07.00" if version.startswith("Kalico") else "v0.13.0-730").generation
    assert [w for w in resolved.warnings if "newer than the newest" in w] == [release.note]


@pytest.mark.parametrize("version", ["banana", "Marlin 2.1.2", "v0.12.0 extra", "?", ""])
def test_text_that_is_no_klipper_version_is_refused_on_one_line(
        version: str, environ: dict[str, str]) -> None:
    with pytest.raises(KestimatorError, match="^--set klipper_version: ") as error:
        resolve_limits(LimitRequest(environ=environ, overrides={"klipper_version": version}))
    assert "\n" not in str(error.value)


def test_klipper_version_is_taken_from_set_the_profile_and_a_printer_cfg_comment(
        tmp_path: Path, environ: dict[str, str]) -> None:
    from_set = resolve_limits(LimitRequest(environ=environ,
                                           overrides={"klipper_version": "v0.12.0"}))
    assert from_set.limits.klipper_generation == "absolute"
    assert from_set.sources["klipper_generation"].startswith("klipper_version v0.12.0 (--set)")
    profile = Path(environ["XDG_CONFIG_HOME"]) / "kestimator" / "config.toml"
    profile.parent.mkdir(parents=True)
    profile.write_text('[limits]\nklipper_version = "Kalico v2026.07.00-0-g30c65e09"\n')
    from_profile = resolve_limits(LimitRequest(environ=environ))
    assert (from_profile.limits.klipper_version, from_profile.limits.klipper_generation) == (
        "Kalico v2026.07.00-0-g30c65e09", "mcr")
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("# kestimator: klipper_version = v0.12.0-455-g5f2d7bc8\n"
                   + PRINTER.format(extra="max_accel_to_decel: 1500\n"))
    from_cfg = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ))
    assert from_cfg.sources["klipper_version"] == f"{cfg}:1"
    assert from_cfg.limits.klipper_version == "v0.12.0-455-g5f2d7bc8"
    # A printer.cfg above the profile: its version wins, and v0.12.0-455 converts
    # max_accel_to_decel to minimum_cruise_ratio as it did.
    assert from_cfg.limits.klipper_generation == "mcr"
    assert from_cfg.limits.minimum_cruise_ratio == 0.5
    assert not [w for w in from_cfg.warnings if "max_accel_to_decel" in w]


def test_a_kalico_version_in_a_printer_cfg_comment_keeps_its_app_name(
        tmp_path: Path, environ: dict[str, str]) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(PRINTER.format(extra="# kestimator: klipper_version = "
                                        "Kalico v2026.07.00-0-g30c65e09\n"))
    resolved = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ))
    assert resolved.limits.klipper_version == "Kalico v2026.07.00-0-g30c65e09"
    assert resolved.limits.klipper_generation == "mcr"


def test_a_bad_version_in_a_printer_cfg_comment_names_the_file_and_line(
        tmp_path: Path, environ: dict[str, str]) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\n# kestimator: klipper_version = vx.y\nkinematics: cartesian\n")
    with pytest.raises(KestimatorError, match="is not a version") as error:
        resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ))
    assert str(error.value).startswith(f"{cfg}:2: ")


def test_klipper_generation_given_as_high_as_the_version_stays_the_low_level_knob(
        tmp_path: Path, environ: dict[str, str]) -> None:
    both = resolve_limits(LimitRequest(environ=environ, overrides={
        "klipper_version": "v0.12.0", "klipper_generation": "mcr"}))
    assert both.limits.klipper_generation == "mcr"
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("# kestimator: klipper_generation = mcr\n"
                   "# kestimator: klipper_version = v0.12.0\n" + PRINTER.format(extra=""))
    assert resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ)
                          ).limits.klipper_generation == "mcr"
    # A version on the command line is above a generation in the printer.cfg.
    above = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ,
                                        overrides={"klipper_version": "v0.13.0-730"}))
    assert above.limits.klipper_generation == "mainline"


@pytest.mark.parametrize(("version", "option", "line"), [
    ("v0.12.0", "minimum_cruise_ratio: 0.5", "minimum_cruise_ratio"),
    ("v0.13.0-730-g84104bbbd", "max_accel_to_decel: 1500", "max_accel_to_decel"),
])
def test_an_option_the_release_refuses_is_reported_as_that_klipper_would(
        version: str, option: str, line: str, tmp_path: Path, environ: dict[str, str]) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(PRINTER.format(extra=option + "\n"))
    with pytest.raises(KestimatorError) as error:
        resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ,
                                    overrides={"klipper_version": version}))
    assert str(error.value) == (
        f"{cfg}:5: [printer] has no option '{line}': Klipper {version} refuses to start "
        f"with it (Option '{line}' is not valid in section 'printer')")


def test_a_refusal_by_a_newer_klipper_says_which_known_one_it_was_taken_as(
        tmp_path: Path, environ: dict[str, str]) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(PRINTER.format(extra="max_accel_to_decel: 1500\n"))
    with pytest.raises(KestimatorError, match=(
            r":5: \[printer\] has no option 'max_accel_to_decel': Klipper v0\.14\.0-3-gabc, "
            r"taken as Klipper 84104bbbd \(v0\.13\.0-730, 2026-08\), refuses to start")):
        resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ,
                                    overrides={"klipper_version": "v0.14.0-3-gabc"}))


def _v0_12_settings() -> dict[str, dict[str, object]]:
    settings = copy.deepcopy(CORPUS_SETTINGS)
    printer = settings["printer"]
    del printer["minimum_cruise_ratio"]
    printer["max_accel_to_decel"] = 1500.0
    return settings


def test_moonraker_gives_the_version_from_printer_info_and_the_cache_keeps_it(
        tmp_path: Path) -> None:
    fake = FakeMoonraker(_v0_12_settings(), info=V0_12_INFO).start()
    try:
        found = moonraker_values(fake.url, None, TIMEOUT_S, tmp_path)
    finally:
        fake.stop()
    assert (found.values["klipper_version"], found.sources["klipper_version"]) == (
        "v0.12.0-0-g0d67d9c4", f"moonraker {fake.url}: printer.info software_version")
    assert "klipper_generation" not in found.values   # the version decides it
    offline = moonraker_values(fake.url, None, TIMEOUT_S, tmp_path)
    assert offline.values["klipper_version"] == "v0.12.0-0-g0d67d9c4"
    assert "printer offline" in offline.sources["klipper_version"]


def test_the_resolver_takes_the_version_from_moonraker_where_limits_come_from_it(
        environ: dict[str, str]) -> None:
    kalico = dict(V0_12_INFO, app="Kalico", software_version="v2026.07.00-0-g30c65e09")
    fake = FakeMoonraker(copy.deepcopy(CORPUS_SETTINGS), info=kalico).start()
    try:
        resolved = resolve_limits(LimitRequest(moonraker_url=fake.url, environ=environ))
    finally:
        fake.stop()
    assert resolved.limits.klipper_version == "Kalico v2026.07.00-0-g30c65e09"
    assert resolved.limits.klipper_generation == "mcr"
    assert resolved.sources["klipper_generation"].startswith(
        "klipper_version Kalico v2026.07.00-0-g30c65e09 (moonraker ")


def test_a_printer_info_that_is_no_version_is_said_sanitised_and_the_settings_decide(
        tmp_path: Path) -> None:
    odd = dict(V0_12_INFO, software_version="\x1b[31mhacked\x1b[0m")
    fake = FakeMoonraker(_v0_12_settings(), info=odd).start()
    try:
        found = moonraker_values(fake.url, None, TIMEOUT_S, tmp_path)
    finally:
        fake.stop()
    assert "klipper_version" not in found.values
    assert found.values["klipper_generation"] == "absolute"
    assert len(found.warnings) == 1 and "\x1b" not in found.warnings[0]


def test_a_klipper_that_does_not_know_its_version_leaves_the_settings_to_decide(
        tmp_path: Path) -> None:
    """Klipper reports "?" when its tree has neither git nor a .version file."""
    fake = FakeMoonraker(_v0_12_settings(), info=dict(V0_12_INFO, software_version="?")).start()
    try:
        found = moonraker_values(fake.url, None, TIMEOUT_S, tmp_path)
    finally:
        fake.stop()
    assert "klipper_version" not in found.values and found.warnings == ()
    assert found.values["klipper_generation"] == "absolute"


RELEASES = Path(__file__).parent / "oracle_refs_releases"
# Each release's references, and the klipper_version (as printer.info reports it) they run as.
RELEASE_VERSIONS = {"klipper-v0.12.0": "v0.12.0-0-g0d67d9c4",
                    "klipper-v0.13.0": "v0.13.0-0-g61c0c8d2",
                    "kalico-v2026.07.00": "Kalico v2026.07.00-0-g30c65e09"}


def _release_refs() -> list[object]:
    return [pytest.param(p, id=f"{p.parent.name}/{p.stem}")
            for folder in RELEASE_VERSIONS for p in sorted((RELEASES / folder).glob("*.json"))]


def _gcode(ref: dict[str, object]) -> Path:
    """The corpus's file, or kestimator's own beside the references."""
    own = RELEASES / str(ref["file"])
    return own if own.exists() else CORPUS / str(ref["file"])


def _estimate(ref_path: Path, environ: dict[str, str]) -> tuple[dict[str, object], Estimate]:
    ref = json.loads(ref_path.read_text())
    gcode = _gcode(ref)
    resolved = resolve_limits(LimitRequest(
        gcode=gcode, printer_cfg=ref_path.parent / "printer.cfg", environ=environ,
        use_profile=False, read_slicer_environment=False,
        overrides={"klipper_version": RELEASE_VERSIONS[
            ref_path.parent.name if ref_path.parent.name in RELEASE_VERSIONS
            else ref_path.parent.parent.name]}))
    return ref, estimate_file(gcode, resolved.limits)


def _assert_every_point(ref: dict[str, object], est: Estimate, points: int) -> None:
    """The total and every checkpoint of `ref` (`points` in all) within TOL_RULES_S."""
    mine = dict(est.layers)
    checkpoints: list[dict[str, float]] = ref["checkpoints"]  # type: ignore[assignment]
    got = [est.total_s] + [mine[int(cp["line"])] for cp in checkpoints]
    want = [float(ref["total_s"])] + [cp["t"] for cp in checkpoints]  # type: ignore[arg-type]
    assert len(got) == points and all(abs(a - b) <= TOL_RULES_S
                                      for a, b in zip(got, want)), (got, want)


@pytest.mark.parametrize("ref_path", _release_refs())
def test_klipper_version_gives_that_releases_own_times(ref_path: Path, corpus_root: Path,
                                                       environ: dict[str, str]) -> None:
    ref, est = _estimate(ref_path, environ)

    def within(mine: float, theirs: float) -> bool:
        return abs(mine - theirs) <= TOL_ABS_S + TOL_REL * theirs

    assert within(est.total_s, float(ref["total_s"])), (est.total_s, ref["total_s"])
    mine = dict(est.layers)
    layers = [cp for cp in ref["checkpoints"] if cp["kind"] == "layer"]  # type: ignore[attr-defined]
    assert {cp["line"] for cp in layers} == set(mine)
    off = [(cp["line"], mine[cp["line"]], cp["t"]) for cp in layers
           if not within(mine[cp["line"]], cp["t"])]
    assert not off, off[:5]


@pytest.mark.parametrize("folder", list(RELEASE_VERSIONS))
def test_each_releases_flush_and_junction_rules_agree_to_the_microsecond(
        folder: str, environ: dict[str, str]) -> None:
    """G4, M400 and new pressure-advance windows in and out of the flushed state (on v0.12.0
    0.15 s off with 84104bbbd's rules, on v0.13.0 0.03 s), near-straight and reversing
    junctions (on v0.12.0 1e-5 s off with 84104bbbd's)."""
    ref, est = _estimate(RELEASES / folder / "flush_junctions.json", environ)
    _assert_every_point(ref, est, 5)


@pytest.mark.parametrize("folder", list(RELEASE_VERSIONS))
@pytest.mark.parametrize(("name", "points"), [("pa_same_window", 5), ("lookahead_peak", 4)])
def test_each_releases_pressure_advance_and_look_ahead_rules_agree_to_the_microsecond(
        folder: str, name: str, points: int, environ: dict[str, str]) -> None:
    """pa_same_window: a SET_PRESSURE_ADVANCE that keeps the scan window flushes step
    generation in v0.12.0 and Kalico (v0.12.0 0.15 s off without it). lookahead_peak: the
    look-ahead before 41901ec38 (v0.12.0, v0.13.0, Kalico) caps the peak cruise at the
    accelerating move's max_cruise_v2 (with today's 3.3e-4 s off on v0.12.0, 5.5e-4 s on
    v0.13.0 and Kalico; on the held-out helixscreen_stand 5.1e-4 s and 7.9e-5 s)."""
    ref, est = _estimate(RELEASES / folder / (name + ".json"), environ)
    _assert_every_point(ref, est, points)


def test_without_the_version_a_v0_12_0_config_is_minutes_off_on_accel_changes(
        corpus_root: Path, environ: dict[str, str]) -> None:
    """What the setting is for: the same config and file without it (mainline semantics)."""
    ref = json.loads((V0_12 / "helixscreen_calicat_orca2.3.1_klipper.json").read_text())
    gcode = CORPUS / ref["file"]
    resolved = resolve_limits(LimitRequest(gcode=gcode, printer_cfg=V0_12 / "printer.cfg",
                                           environ=environ, use_profile=False,
                                           read_slicer_environment=False))
    assert resolved.limits.klipper_generation == "mainline"
    assert ref["total_s"] - estimate_file(gcode, resolved.limits).total_s > 60.0


def test_the_running_klippers_version_counts_unless_a_setting_names_one(
        tmp_path: Path, environ: dict[str, str]) -> None:
    """On the printer host the worker is told the version of the Klipper the module runs in
    (LimitRequest.running_klipper_version); --set, the profile or a printer.cfg comment win,
    and text that is no version is said on one line and left out."""
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(PRINTER.format(extra="max_accel_to_decel: 1500\n"))
    running = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ,
                                          running_klipper_version="v0.12.0-0-g0d67d9c4"))
    assert (running.limits.klipper_version, running.limits.klipper_generation) == (
        "v0.12.0-0-g0d67d9c4", "absolute")
    assert running.sources["klipper_version"] == (
        "the Klipper the module runs in: software_version")
    named = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ,
                                        overrides={"klipper_version": "v0.12.0-119"},
                                        running_klipper_version="v0.12.0-0-g0d67d9c4"))
    assert (named.limits.klipper_version, named.limits.klipper_generation) == (
        "v0.12.0-119", "mcr")
    junk = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ,
                                       running_klipper_version="Marlin 2.1\x1b[2J"))
    assert junk.limits.klipper_version == "" and junk.limits.klipper_generation == "mainline"
    (line,) = [w for w in junk.warnings if "module runs in" in w]
    assert "not used" in line and "\x1b" not in line


def test_kalicos_own_rules_agree_to_the_microsecond(environ: dict[str, str]) -> None:
    """What Kalico v2026.07.00 does that today's Klipper does not (kalico_rules.gcode): every
    SET_PRESSURE_ADVANCE flushes step generation (as Klipper did before v0.12.0-262),
    RESET_VELOCITY_LIMIT restores [printer]'s
    limits, SET_VELOCITY_LIMIT Z_VELOCITY / Z_ACCEL set the kinematics' (without the
    flushes 0.13 s off, without the two commands up to 3.8 s at a layer)."""
    ref, est = _estimate(RELEASES / "kalico-v2026.07.00" / "kalico_rules.json", environ)
    _assert_every_point(ref, est, 7)
    flushes = [klipper_release(v).pressure_advance_always_flushes
               for v in ("Kalico v2026.07.00-0-g30c65e09", "v0.13.0-0-g61c0c8d2", "v0.12.0",
                         "v0.13.0-730-g84104bbbd")]
    assert flushes == [True, False, True, False]


def test_reset_velocity_limit_is_kalicos_alone(tmp_path: Path, environ: dict[str, str]) -> None:
    """Klipper has no RESET_VELOCITY_LIMIT: there it is a command Klipper does not know."""
    gcode = RELEASES / "kalico_rules.gcode"
    cfg = RELEASES / "kalico-v2026.07.00" / "printer.cfg"
    for version, known in (("Kalico v2026.07.00-0-g30c65e09", True), ("v0.13.0-0", False)):
        resolved = resolve_limits(LimitRequest(
            gcode=gcode, printer_cfg=cfg, environ=environ, use_profile=False,
            read_slicer_environment=False, overrides={"klipper_version": version}))
        est = estimate_file(gcode, resolved.limits)
        unknown = [w for w in est.warnings if "'RESET_VELOCITY_LIMIT' is not a Klipper" in w]
        assert bool(unknown) is not known, (version, est.warnings)


@pytest.mark.parametrize("folder", list(RELEASE_VERSIONS))
@pytest.mark.parametrize(("name", "points"), [("motor_off", 6), ("heater_first", 6)])
def test_each_releases_motor_off_and_heater_barrier_agree_to_the_microsecond(
        folder: str, name: str, points: int, environ: dict[str, str]) -> None:
    """motor_off: M84 / M18 before set_motors_enable (v0.12.0, v0.13.0, Kalico: no flush
    first, both dwells whether or not a motor was on), 0.4 s (v0.12.0) and 0.28 s off with
    today's. heater_first (and fan_first): a heater (a fan) set with nothing queued is
    get_last_move_time, which with min_restart_time (v0.13.0, Kalico) restarts motion
    kin_flush_delay later (0.001 s off without it, as on the corpus's kisslicer and slic3r
    files)."""
    ref, est = _estimate(RELEASES / folder / (name + ".json"), environ)
    if name == "heater_first":
        # and a fan set so (fan/: the folder's printer.cfg with a [fan]), the same rule
        fan, fan_est = _estimate(RELEASES / folder / "fan" / "fan_first.json", environ)
        _assert_every_point(fan, fan_est, 4)
    _assert_every_point(ref, est, points)
