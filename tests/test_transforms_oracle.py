"""Bed mesh and skew correction against real Klipper (84104bbbd): corpus files with a mesh or
skew profile loaded after G28, and snippets of their commands (tests/oracle_refs/transforms,
made by runs.py there).

The bar is exactness: the total and every layer time within the oracle's rounding to 1 µs
(plus 1e-9 relative), and the same number of toolhead moves (the mesh splits moves).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file, estimate_text
from kestimator.limits import Limits

from .conftest import CORPUS
from .oracle_refs.transforms.runs import HERE as REFS
from .oracle_refs.transforms.runs import RUNS, derive

TOL_ABS_S = 5e-7 + 1e-9
TOL_REL = 1e-9


def _within(mine: float, ref: float) -> bool:
    return abs(mine - ref) <= TOL_ABS_S + TOL_REL * ref


def _params() -> list[object]:
    return [pytest.param(cfg, gcode, commands, id=cfg + "/" + Path(gcode).stem)
            for cfg, gcode, commands in RUNS]


@pytest.mark.parametrize(("cfg", "gcode", "commands"), _params())
def test_estimate_equals_klipper_with_a_move_transform(cfg: str, gcode: str,
                                                      commands: tuple[str, ...],
                                                      tmp_path: Path) -> None:
    if not gcode.startswith("snippets/") and not CORPUS.is_dir():
        pytest.skip("the shared corpus is not beside this checkout")
    ref = json.loads((REFS / cfg / (Path(gcode).stem + ".json")).read_text())
    limits, _ = limits_from_printer_cfg(REFS / cfg / "printer.cfg")
    est = estimate_file(derive(gcode, commands, tmp_path, CORPUS / "gcode"), limits)
    assert _within(est.total_s, ref["total_s"]), (est.total_s, ref["total_s"])
    mine = dict(est.layers)
    ref_layers = [cp for cp in ref["checkpoints"] if cp["kind"] == "layer"]
    assert ref_layers
    assert set(mine) == {cp["line"] for cp in ref_layers}
    off = [(cp["line"], mine[cp["line"]], cp["t"]) for cp in ref_layers
           if not _within(mine[cp["line"]], cp["t"])]
    assert not off, off[:5]
    assert est.n_moves == ref["n_moves"]
    assert not [w for w in est.warnings if "not a Klipper command" in w
                and ("MESH" in w or "SKEW" in w)]


def _saved_config(cfg: Path, out: Path) -> Path:
    """The config with its [bed_mesh default] / [skew_correction my_skew] profile moved into a
    SAVE_CONFIG block, as Klipper writes it."""
    text = cfg.read_text()
    regular, profiles = [], []
    section = ""
    for line in text.split("\n"):
        if line.startswith("["):
            section = line
        (profiles if " " in section.strip("[]") else regular).append(line)
    block = ["#*# <---------------------- SAVE_CONFIG ---------------------->",
             "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.", "#*#"]
    block += ["#*# " + line if line else "#*#" for line in profiles]
    out.write_text("\n".join(regular + block) + "\n")
    return out


@pytest.mark.parametrize("cfg", ["bed_mesh", "bed_mesh_bicubic", "mesh_skew"])
def test_a_profile_in_the_save_config_block_is_the_same_profile(cfg: str,
                                                                tmp_path: Path) -> None:
    saved = _saved_config(REFS / cfg / "printer.cfg", tmp_path / "printer.cfg")
    assert "#*# [bed_mesh default]" in saved.read_text()
    snippet = "snippets/mesh_commands.gcode"
    if cfg == "mesh_skew":
        snippet = "snippets/mesh_skew_commands.gcode"
    gcode = derive(snippet, (), tmp_path)
    ref = json.loads((REFS / cfg / (Path(snippet).stem + ".json")).read_text())
    est = estimate_file(gcode, limits_from_printer_cfg(saved)[0])
    assert _within(est.total_s, ref["total_s"])
    assert est.n_moves == ref["n_moves"]


def _mesh_limits(tmp_path: Path, extra: str = "") -> Limits:
    cfg = tmp_path / "printer.cfg"
    shutil.copy(REFS / "bed_mesh" / "printer.cfg", cfg)
    with cfg.open("a") as f:
        f.write(extra)
    return limits_from_printer_cfg(cfg)[0]


def test_without_a_loaded_profile_the_mesh_changes_nothing(tmp_path: Path) -> None:
    text = "G28\nG1 Z0.3 F600\nG1 X200 Y30 F12000\nG1 X30 Y200 E5 F6000\n"
    with_section = estimate_text(text, _mesh_limits(tmp_path))
    plain = estimate_text(text, limits_from_printer_cfg(CORPUS / "printer.cfg")[0]) \
        if CORPUS.is_dir() else None
    loaded = estimate_text(text.replace("G28\n", "G28\nBED_MESH_PROFILE LOAD=default\n"),
                           _mesh_limits(tmp_path))
    assert with_section.n_moves == 3
    assert loaded.n_moves > with_section.n_moves
    if plain is not None:
        assert with_section.total_s == plain.total_s


def test_an_unknown_profile_is_klippers_error(tmp_path: Path) -> None:
    est = estimate_text("G28\nBED_MESH_PROFILE LOAD=nope\nG1 X100 Y100 F6000\n",
                        _mesh_limits(tmp_path))
    assert any("bed_mesh: Unknown profile [nope]" in w for w in est.warnings), est.warnings
    assert est.n_moves == 1


def test_a_mesh_beyond_the_fade_range_is_refused(tmp_path: Path) -> None:
    limits = _mesh_limits(tmp_path, "\n[bed_mesh steep]\nversion = 1\npoints =\n"
                          "  0, 0, 0\n  0, 12, 0\n  0, 0, 0\nx_count = 3\ny_count = 3\n"
                          "mesh_x_pps = 0\nmesh_y_pps = 0\nalgo = direct\ntension = 0.2\n"
                          "min_x = 10\nmax_x = 220\nmin_y = 10\nmax_y = 220\n")
    est = estimate_text("G28\nBED_MESH_PROFILE LOAD=steep\nG1 X100 Y100 F6000\n", limits)
    assert any("Mesh extends outside of the fade range" in w for w in est.warnings)
    assert est.n_moves == 1
    assert math.isfinite(est.total_s)


def test_bed_mesh_calibrate_clears_the_mesh_and_says_its_probing_is_unknown(
        tmp_path: Path) -> None:
    text = ("G28\nBED_MESH_PROFILE LOAD=default\nBED_MESH_CALIBRATE\nG1 Z0.3 F600\n"
            "G1 X200 Y30 F12000\n")
    est = estimate_text(text, _mesh_limits(tmp_path))
    assert est.n_moves == 2
    assert any("BED_MESH_CALIBRATE probes the bed" in w for w in est.warnings)


def test_profiles_from_moonrakers_settings_are_the_same_profiles() -> None:
    from kestimator.config.machine import MachineConfig
    from kestimator.config.moonraker import machine_from_settings
    from kestimator.config.printer_cfg import read_printer_cfg

    cfg = REFS / "mesh_skew" / "printer.cfg"
    limits, _ = limits_from_printer_cfg(cfg)
    # configfile.settings as Klipper reports them: parsed values, points as rows of floats
    settings: dict[str, dict[str, object]] = {}
    for name, options in read_printer_cfg(cfg).items():
        settings[name] = {option: raw.value for option, raw in options.items()}
    profile = settings["bed_mesh default"]
    profile["points"] = [[float(v) for v in row.split(",")]
                         for row in str(profile["points"]).strip().split("\n")]
    machine = machine_from_settings(settings, "moonraker http://printer")
    assert isinstance(machine, MachineConfig) and machine.has_section("bed_mesh default")
    gcode = REFS.parent / "snippets" / "mesh_skew_commands.gcode"
    from_cfg = estimate_file(gcode, limits)
    from_moonraker = estimate_file(gcode, limits.replace(machine=machine))
    assert from_moonraker.total_s == from_cfg.total_s
    assert from_moonraker.n_moves == from_cfg.n_moves


MESH_MACROS = """
[gcode_macro PRINT_START]
gcode:
    G28
    {% if params.MESH|default(1)|int %}
    BED_MESH_PROFILE LOAD=default
    {% endif %}

[gcode_macro PURGE]
gcode:
    {% for i in range(3) %}
    G1 X{i} Y0
    {% endfor %}
"""
MOVES = "G1 Z0.3 F600\nG1 X200 Y30 F12000\nG1 X30 Y200 E5 F6000\n"


def _mesh_warnings(tmp_path: Path, text: str) -> list[str]:
    est = estimate_text(text, _mesh_limits(tmp_path, MESH_MACROS))
    return [w for w in est.warnings if "bed mesh" in w]


def test_a_start_macro_that_loads_a_mesh_is_said_not_silently_left_out(
        tmp_path: Path) -> None:
    (warning,) = _mesh_warnings(tmp_path, "PRINT_START\n" + MOVES)
    assert "macro PRINT_START loads a bed mesh" in warning
    assert "BED_MESH_PROFILE LOAD=<name>" in warning


def test_a_file_explicit_about_the_mesh_gets_no_mesh_warning(tmp_path: Path) -> None:
    # It loads the mesh itself, or runs no macro that could, or a macro that does not.
    assert _mesh_warnings(tmp_path, "PRINT_START\nBED_MESH_PROFILE LOAD=default\n" + MOVES) == []
    assert _mesh_warnings(tmp_path, "G28\n" + MOVES) == []
    assert _mesh_warnings(tmp_path, "G28\nPURGE\n" + MOVES) == []


def test_a_macro_of_unknown_text_may_load_a_mesh_and_is_said(tmp_path: Path) -> None:
    # Moonraker gives macros by name only: such a start macro may load a mesh.
    limits = _mesh_limits(tmp_path)
    limits = limits.replace(gcode_macros=limits.gcode_macros + (("START", ""),))
    est = estimate_text("START\n" + MOVES, limits)
    (warning,) = [w for w in est.warnings if "bed mesh" in w]
    assert "saved bed mesh profiles (default) and this file loads none" in warning
