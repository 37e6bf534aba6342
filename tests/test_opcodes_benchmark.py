"""benchmarks/opcodes.py: the bytecodes and calls per line it reports are the body's alone."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from .conftest import PROJECT, isolate_user_environment


def _opcodes() -> ModuleType:
    spec = importlib.util.spec_from_file_location("opcodes_benchmark",
                                                  PROJECT / "benchmarks" / "opcodes.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_each_body_line_counts_one_move_and_the_start_is_left_out(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import kestimator.toolhead

    if not kestimator.toolhead.__file__.endswith(".py"):
        pytest.skip("a compiled build's frames cannot be traced")
    isolate_user_environment(tmp_path / "home", monkeypatch)
    opcodes = _opcodes()
    source = tmp_path / "source.gcode"
    head = [b"G90\n", b"M83\n", b"G1 Z0.2 F600\n"] + [
        b"G1 X%d Y%d E0.05 F3000 ; start %d\n" % (i, i % 7, i) for i in range(40)]
    body = [b"G1 X%d.5 Y%d E0.0%d\n" % (100 - i % 90, (i * 3) % 11, 1 + i % 9)
            for i in range(300)]
    source.write_bytes(b"".join(head + body))
    read_head, read_body = opcodes.window(str(source), len(head), len(body), 0.0)
    assert (read_head, read_body) == (head, body)

    ops, calls = opcodes.per_line(head, body, str(tmp_path))
    # Every body line is a plain move: parsed once, one Move, one junction.
    assert calls["parse_plain_move_regex"] == pytest.approx(1.0)
    assert calls["Move.__init__"] == pytest.approx(1.0)
    assert calls["Move.calc_junction"] == pytest.approx(1.0)
    # The start-up and the end of the estimate run in both passes and cancel out.
    assert "main" not in ops or ops["main"] == 0.0
    assert 300.0 < sum(ops.values()) < 3000.0
    assert ops["Move.calc_junction"] > 50.0
    table = opcodes.report(ops, calls, 3)
    assert table[0].endswith("Python calls per line)") and len(table) == 5
