"""kestimator/fused.py is generated from the readable methods, and gives what they give.

Pure CPython feeds lines through `fused.feed_lines` (kestimator/fusegen.py inlines
`Interpreter.plain_move`, `ToolHead.move_to`, `Move.__init__`, `LookAheadQueue.add_move`
and `Move.calc_junction` into `Timeline.feed_lines`). These tests pin it two ways: the
checked-in module must be exactly what the generator makes from today's sources (so an
edit to one of those methods that is not regenerated fails here), and both loops must give
the same estimate, field by field, on corpus files and on programs that take the rare
branches (rejected moves, extrude-only moves, relative and absolute modes, G92, M221).
"""

from __future__ import annotations

import ast
import dataclasses
import subprocess
import sys
from array import array
from pathlib import Path
from typing import Any

import pytest

from kestimator import estimate, fusegen
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import Estimate, estimate_file, estimate_text
from kestimator.limits import Limits
from kestimator.timedlines import TimedLines

from .conftest import CORPUS_CFG, PROJECT, corpus_files

MAX_FILE_BYTES = 2_000_000

PROGRAMS = {
    "rejected moves and recovery": """G28
G90
M83
G1 X10 Y10 F6000
G1 X9999 Y10 E1
G1 X20 Y20 E0.5
G1 E50000
G1 X30 Y20 E0.2
""",
    "extrude-only, relative and absolute": """G28
G1 Z0.3 F600
G1 X5 Y5 F3000
G1 E2 F1800
G1 E-1
G91
G1 X1 Y1 E0.1
G1 Z1
G90
M82
G92 E0
G1 X10 Y10 E5 F1200
G1 X10 Y10 E5
G1 X10 Y10 E6
M221 S90
G1 X20 Y10 E7
G0 X0 Y0
G1 F0
G1 X3 Y3 F-5
""",
    "corners and short moves": "G28\nG90\nM83\n" + "".join(
        "G1 X%.3f Y%.3f E0.01 F%d\n" % (50 + 10 * ((i * 7) % 13) / 13.0,
                                        50 + 0.001 * i, 1200 + 60 * (i % 50))
        for i in range(400)),
}


def _comparable(est: Estimate) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for field in dataclasses.fields(est):
        value = getattr(est, field.name)
        if isinstance(value, TimedLines):
            value = (value.lines.tolist(), value.times.tolist())
        elif isinstance(value, array):
            value = value.tolist()
        out[field.name] = value
    return out


@pytest.fixture(scope="module")
def limits() -> Limits:
    return limits_from_printer_cfg(CORPUS_CFG)[0]


def both_loops(monkeypatch: pytest.MonkeyPatch, run: Any) -> tuple[dict[str, Any], ...]:
    results = []
    for fused in (False, True):
        monkeypatch.setattr(estimate, "FUSED_FEED", fused)
        results.append(_comparable(run()))
    return tuple(results)


def test_fused_module_is_what_the_generator_makes_from_the_current_methods() -> None:
    generated = fusegen.generate()
    current = (PROJECT / "kestimator" / "fused.py").read_text(encoding="utf-8")
    # The syntax trees: ast.unparse's spelling may differ between Python versions.
    assert ast.dump(ast.parse(generated)) == ast.dump(ast.parse(current)), (
        "kestimator/fused.py is out of date: run python -m kestimator.fusegen")


def test_fusegen_check_fails_on_a_stale_module(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    stale = tmp_path / "fused.py"
    stale.write_text(fusegen.generate().replace("mt_move.end_x = mt_x", "mt_move.end_x = 0.0"),
                     encoding="utf-8")
    monkeypatch.setattr(fusegen, "OUTPUT", str(stale))
    assert fusegen.main(["--check"]) == 1
    stale.write_text(fusegen.generate(), encoding="utf-8")
    assert fusegen.main(["--check"]) == 0


def test_fused_module_inlines_every_call_on_the_move_path() -> None:
    tree = ast.parse((PROJECT / "kestimator" / "fused.py").read_text(encoding="utf-8"))
    called = {node.func.attr for node in ast.walk(tree)
              if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)}
    assert not called & set(fusegen.INLINED_METHODS)
    constructed = {node.func.id for node in ast.walk(tree)
                   if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
    assert not constructed & set(fusegen.INLINED_CONSTRUCTORS)


def test_pure_cpython_uses_the_fused_loop_and_the_other_builds_do_not() -> None:
    assert estimate.FUSED_FEED == (not estimate.SCAN_PLAIN_MOVES)


@pytest.mark.parametrize("name", sorted(PROGRAMS))
def test_fused_and_readable_loops_agree_on_programs(name: str, limits: Limits,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    readable, fused = both_loops(monkeypatch, lambda: estimate_text(PROGRAMS[name], limits))
    assert fused == readable
    assert readable["n_moves"] > 0


SMALL_FILES = [p for p in corpus_files() if p.stat().st_size <= MAX_FILE_BYTES]


@pytest.mark.parametrize("path", SMALL_FILES, ids=lambda p: p.parent.name + "/" + p.name)
def test_fused_and_readable_loops_agree_on_corpus_file(path: Path, limits: Limits,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    readable, fused = both_loops(
        monkeypatch, lambda: estimate_file(str(path), limits, sample=True))
    assert fused == readable


def test_fusegen_runs_as_a_module_and_says_up_to_date() -> None:
    proc = subprocess.run([sys.executable, "-m", "kestimator.fusegen", "--check"],
                          cwd=PROJECT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
