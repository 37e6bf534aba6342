"""Pass 2's shortcuts change no byte: the block copier equals full line-by-line processing.

`Rewriter.copy_stream` copies runs of quiet move lines as slices, and `process` skips
move lines before the next change of progress. The reference here is a Rewriter that
has no quiet lines at all (every line takes the full path); outputs must be identical on
every corpus file, with blocks so small that lines straddle them, and on files with CRLF,
no final newline, or M73 and layer lines in every place.
"""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from kestimator import rewrite
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.limits import Limits
from kestimator.rewrite import InjectPlan, Rewriter, plan_file

from .conftest import CORPUS_CFG, corpus_files

MAX_FILE_BYTES = 3_000_000


class FullRewriter(Rewriter):
    """The reference: no quiet lines, every line through `process`'s full path."""

    def _set_quiet_until(self) -> None:
        self._quiet_until = 0


def reference_output(plan: InjectPlan, data: bytes) -> bytes:
    rewriter = FullRewriter(plan)
    lines = list(io.BytesIO(data))
    open_last = bool(lines) and not lines[-1].endswith(b"\n")
    body = lines[:-1] if open_last else lines
    out = [piece for raw in body for piece in rewriter.process(raw)]
    # The tail time comment (SlicerAdapter.moonraker_time_comment) after the last whole line.
    out += rewriter.finish()
    if open_last:
        out += rewriter.process(lines[-1])
    return b"".join(out)


def fast_output(plan: InjectPlan, data: bytes) -> tuple[bytes, int]:
    rewriter = Rewriter(plan)
    out = io.BytesIO()
    rewriter.copy_stream(io.BytesIO(data), out.write)
    return out.getvalue(), rewriter.m73_written


@pytest.fixture(scope="module")
def limits() -> Limits:
    return limits_from_printer_cfg(CORPUS_CFG)[0]


SMALL_FILES = [p for p in corpus_files() if p.stat().st_size <= MAX_FILE_BYTES]


@pytest.mark.parametrize("path", SMALL_FILES, ids=lambda p: p.parent.name + "/" + p.name)
def test_block_copy_writes_the_same_bytes_as_full_processing(path: Path,
                                                             limits: Limits) -> None:
    plan = plan_file(str(path), limits, "printer.cfg")[0]
    data = path.read_bytes()
    want = reference_output(plan, data)
    got, m73_written = fast_output(plan, data)
    assert got == want
    assert m73_written == want.count(b"\nM73 P") + want.startswith(b"M73 P")


@pytest.mark.parametrize("block", [1, 7, 64, 4096])
def test_lines_straddling_blocks_come_out_the_same(block: int, limits: Limits,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    path = min(SMALL_FILES, key=lambda p: p.stat().st_size)
    plan = plan_file(str(path), limits, "printer.cfg")[0]
    data = path.read_bytes()
    want = reference_output(plan, data)
    monkeypatch.setattr(rewrite, "COPY_BLOCK_BYTES", block)
    assert fast_output(plan, data)[0] == want


@pytest.mark.parametrize("body", [
    b"G28\r\nM83\r\n;LAYER_CHANGE\r\nG1 X10 F3000\r\nG1 X20 E1\r\nM73 P5 R9\r\n"
    b";LAYER_CHANGE\r\n" + b"G1 X30 Y5 E1\r\nG1 X0 Y0 E1\r\n" * 400 + b"G1 X1",
    b";LAYER_CHANGE\nG1 X10 F600\n" + b"G1 X50 E1\nG1 X0 E1\n;WIDTH:0.4\nM106 S3\n" * 300
    + b";LAYER_CHANGE\nG1 Z5\nM73 P100 R0\n; end\n",
    b"G1 X1 F60\nG1 X2\nG1 X3\n",
    b";LAYER_CHANGE\nG1 X1 F60\n" + b"G1 X2 ; M73 in a comment; and ;\n  ;indented\n"
    b"G1 X3\n\tM73 P1\nM117 M73\nm73 P2\nG1 X4 E1\nM73\n" * 200,
    # Old Mac line endings: Klipper splits at LF only, so this is one long line.
    b";LAYER_CHANGE\r" + b"G1 X10 F600\rG1 X0\r" * 3000 + b"\nG1 X5\n",
])
def test_crlf_missing_final_newline_and_interleaved_lines_come_out_the_same(
        body: bytes, tmp_path: Path, limits: Limits, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "t.gcode"
    path.write_bytes(body)
    plan = plan_file(str(path), limits, "printer.cfg")[0]
    want = reference_output(plan, body)
    for block in (3, 1 << 20):
        monkeypatch.setattr(rewrite, "COPY_BLOCK_BYTES", block)
        assert fast_output(plan, body)[0] == want
