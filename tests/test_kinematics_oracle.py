"""Each kinematics against real Klipper (84104bbbd): corpus files and snippets on delta, polar,
corexz and a corexy homing to X/Y max (tests/oracle_refs, made by make_refs.sh there).

Same bar as the corpus: 0.01 s + 1e-6 x t on the total and on every layer checkpoint; for a
file Klipper stops, the line it stops at and its exact error text.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file

from .conftest import CORPUS

REFS = Path(__file__).parent / "oracle_refs"
TOL_ABS_S = 0.01
TOL_REL = 1e-6


def _gcode_for(ref: Path, name: str) -> Path:
    snippet = REFS / "snippets" / name
    if snippet.exists():
        return snippet
    found = sorted((CORPUS / "gcode").glob("*/" + name))
    assert found, name
    return found[0]


def _within(mine: float, ref: float) -> bool:
    return abs(mine - ref) <= TOL_ABS_S + TOL_REL * ref


def _refs(errors: bool) -> list[object]:
    return [pytest.param(p, id=p.parent.name + "/" + p.name.split(".json")[0])
            for p in sorted(REFS.glob("*/*.json"))
            if p.name.endswith(".errors.json") == errors]


@pytest.mark.parametrize("ref_path", _refs(errors=False))
def test_estimate_equals_klipper_on_other_kinematics(ref_path: Path,
                                                     corpus_root: Path) -> None:
    ref = json.loads(ref_path.read_text())
    limits, _ = limits_from_printer_cfg(ref_path.parent / "printer.cfg")
    assert limits.machine is not None
    est = estimate_file(_gcode_for(ref_path, ref["file"]), limits)
    assert _within(est.total_s, ref["total_s"]), (est.total_s, ref["total_s"])
    mine = dict(est.layers)
    ref_layers = [cp for cp in ref["checkpoints"] if cp["kind"] == "layer"]
    assert set(mine) == {cp["line"] for cp in ref_layers}
    off = [(cp["line"], mine[cp["line"]], cp["t"]) for cp in ref_layers
           if not _within(mine[cp["line"]], cp["t"])]
    assert not off, off[:5]
    assert est.n_moves == ref["n_moves"]
    assert not [w for w in est.warnings if "kinematics" in w or "rejects" in w]


@pytest.mark.parametrize("ref_path", _refs(errors=True))
def test_move_out_of_range_is_klippers_error_on_klippers_line(ref_path: Path,
                                                              corpus_root: Path) -> None:
    ref = json.loads(ref_path.read_text())
    # The error that stopped the print is the one naming its command (an internal error
    # also reports 'Internal error on command:"G1"' first).
    error = [e for e in ref["errors"] if "cmd" in e][0]
    name = ref_path.name[:-len(".errors.json")] + ".gcode"
    limits, _ = limits_from_printer_cfg(ref_path.parent / "printer.cfg")
    est = estimate_file(_gcode_for(ref_path, name), limits)
    rejects = [w for w in est.warnings if "Klipper rejects" in w]
    assert rejects, est.warnings
    first = rejects[0]
    assert (":%d: " % error["src_line"]) in first, (first, error)
    assert first.endswith(": " + error["msg"]) or (error["msg"] + " (") in first, (first, error)


def test_every_config_has_references() -> None:
    configs = sorted(p.parent.name for p in REFS.glob("*/printer.cfg"))
    assert configs == ["cartesian_idex", "corexy_eddy", "corexy_maxend", "corexy_probe", "corexz",
                       "corexz_force_move", "delta", "delta_mini", "delta_tight", "deltesian",
                       "generic_cartesian", "none", "polar", "rotary_delta", "safe_z_home",
                       "safe_z_home_previous", "winch"]
    for config in configs:
        assert list((REFS / config).glob("*.json")), config
