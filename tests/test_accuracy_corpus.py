"""Every corpus file against the times Klipper itself computed (shared/corpus/reference).

Tolerance is the project's bar: 0.01 s + 1e-6 x t on the total and on every layer
checkpoint. Beyond that bar we also pin the move count and Klipper's unknown commands.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file

from .conftest import CORPUS, CORPUS_CFG, PROJECT

TOL_ABS_S = 0.01
TOL_REL = 1e-6
LARGE_FILE_BYTES = 10_000_000


def _references() -> list[Path]:
    return sorted((CORPUS / "reference").glob("*/*.json"))


def _ref_id(path: Path) -> str:
    return path.parent.name + "/" + path.stem


def _params() -> list[object]:
    params: list[object] = []
    for ref in _references():
        gcode = CORPUS / json.loads(ref.read_text())["file"]
        marks = [pytest.mark.slow] if gcode.stat().st_size > LARGE_FILE_BYTES else []
        params.append(pytest.param(ref, id=_ref_id(ref), marks=marks))
    return params


def _within(mine: float, ref: float) -> bool:
    return abs(mine - ref) <= TOL_ABS_S + TOL_REL * ref


@pytest.mark.parametrize("ref_path", _params())
def test_estimate_equals_klipper_at_every_layer(ref_path: Path, corpus_root: Path) -> None:
    ref = json.loads(ref_path.read_text())
    limits, _ = limits_from_printer_cfg(CORPUS_CFG)
    est = estimate_file(corpus_root / ref["file"], limits)
    assert _within(est.total_s, ref["total_s"]), (est.total_s, ref["total_s"])
    mine = dict(est.layers)
    ref_layers = [cp for cp in ref["checkpoints"] if cp["kind"] == "layer"]
    assert set(mine) == {cp["line"] for cp in ref_layers}
    off = [(cp["line"], mine[cp["line"]], cp["t"]) for cp in ref_layers
           if not _within(mine[cp["line"]], cp["t"])]
    assert not off, off[:5]
    assert est.n_moves == ref["n_moves"]
    assert est.ignored_commands == ref["klipper_ignored_commands"]


def test_reference_set_is_not_empty(corpus_root: Path) -> None:
    assert len(_references()) >= 30


def test_cli_json_matches_the_reference(corpus_root: Path) -> None:
    ref = json.loads((corpus_root / "reference/prusaslicer/ps25_nut_accelA_small.json")
                     .read_text())
    proc = subprocess.run(
        [sys.executable, "-m", "kestimator", "estimate", str(corpus_root / ref["file"]),
         "--printer-cfg", str(CORPUS_CFG), "--json"],
        capture_output=True, text=True, cwd=PROJECT, check=True)
    out = json.loads(proc.stdout)
    assert _within(out["total_s"], ref["total_s"])
    layers = {entry["line"]: entry["t"] for entry in out["layers"]}
    for cp in ref["checkpoints"]:
        if cp["kind"] == "layer":
            assert _within(layers[cp["line"]], cp["t"])
    assert out["slicer"]["name"] == "PrusaSlicer"
    assert out["ignored_commands"] == ref["klipper_ignored_commands"]
