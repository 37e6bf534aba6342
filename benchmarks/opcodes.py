"""Bytecodes the pure build runs per G-code line, by function: a count that does not move
with the host's load.

The pure `estimate` of the 40 MB file is 23-24x a line copy, and issue 37 asks for 22x:
6-9 % less, about the size of the timings' scatter on a shared host. The bytecodes and
Python calls run per line are the same in every run, so a change on the per-line path can
be weighed by them before it is timed (`bench.py`). On the 2-CPU VM of benchmarks/RESULTS.md
(CPython 3.11) a line of the body costs about 950 bytecodes and 9 calls, 3.3-3.6 us: about
4 ns a bytecode with the C work it does, and a call costs more than its bytecodes show
(callgrind: each of three calls per line taken out of the path, the class call that makes a
Move and the calls of calc_junction and set_junction, saved 0.8-1.1 % of the instructions).

The file's first `--head` lines (its start: header, heating, first layers) are estimated
alone, then with `--lines` more lines from `--at` (a fraction of the file) after them, each
in the pure package of this checkout with every Python frame traced (`sys.settrace`,
`f_trace_opcodes`); the difference, divided by `--lines`, is what one line of the body of
the file costs, without the start-up and the end's fixed work. The estimate runs as
`kestimator estimate --json` does (the same limits), in this process.

    python benchmarks/opcodes.py [--file FILE] [--head N] [--lines N] [--at F] [--top N]

Under a compiled build the planner's frames are C and cannot be traced: the script refuses.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import os
import sys
import tempfile
from types import FrameType
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DEFAULT_FILE = os.path.join(ROOT, "..", "shared", "corpus", "gcode", "prusaslicer",
                            "ps25_bunny120_fast_fwretract_large.gcode")


def window(path: str, head: int, lines: int, at: float) -> tuple[list[bytes], list[bytes]]:
    """The file's first `head` lines, and `lines` lines from fraction `at` of it on (from
    the line after `head` when that is later)."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        first = [f.readline() for _ in range(head)]
        start = int(size * at)
        if start > f.tell():
            f.seek(start - 1)
            f.readline()  # to the start of the first line from `start` on
        body = [f.readline() for _ in range(lines)]
    return [line for line in first if line], [line for line in body if line]


def function_name(frame: FrameType) -> str:
    """The frame's function, as `Class.method` (its bare name before Python 3.11)."""
    code = frame.f_code
    return getattr(code, "co_qualname", code.co_name)


def count(path: str) -> tuple[collections.Counter[str], collections.Counter[str]]:
    """Bytecodes and calls per function (qualified name) of `kestimator estimate --json`
    of `path`, in this process."""
    from kestimator.cli import main

    ops: collections.Counter[str] = collections.Counter()
    calls: collections.Counter[str] = collections.Counter()

    def trace(frame: FrameType, event: str, _arg: Any) -> Any:
        if event == "opcode":
            ops[function_name(frame)] += 1
        elif event == "call":
            frame.f_trace_opcodes = True
            calls[function_name(frame)] += 1
        return trace

    argv = sys.argv
    sys.argv = ["kestimator", "estimate", path, "--json"]
    sys.settrace(trace)
    try:
        with contextlib.redirect_stdout(io.StringIO()), \
                contextlib.redirect_stderr(io.StringIO()):
            status = main()
    finally:
        sys.settrace(None)
        sys.argv = argv
    if status != 0:
        sys.exit("opcodes: kestimator estimate failed on %s" % path)
    return ops, calls


def per_line(head: list[bytes], body: list[bytes], tmpdir: str
             ) -> tuple[dict[str, float], dict[str, float]]:
    """Bytecodes and calls per body line, by function."""
    runs = []
    for file_name, lines in (("head.gcode", head), ("both.gcode", head + body)):
        path = os.path.join(tmpdir, file_name)
        with open(path, "wb") as f:
            f.writelines(lines)
        runs.append(count(path))
    (ops_a, calls_a), (ops_b, calls_b) = runs
    n = len(body)
    ops = {k: (ops_b[k] - ops_a[k]) / n for k in ops_b}
    calls = {k: (calls_b[k] - calls_a[k]) / n for k in calls_b}
    return ops, calls


def report(ops: dict[str, float], calls: dict[str, float], top: int) -> list[str]:
    """The table: total bytecodes per line, then the `top` functions by bytecodes."""
    total = sum(ops.values())
    out = ["%.1f bytecodes per line (%.2f Python calls per line)"
           % (total, sum(calls.values()))]
    out.append("  %8s %6s %7s  %s" % ("per line", "share", "calls", "function"))
    for function, value in sorted(ops.items(), key=lambda kv: -kv[1])[:top]:
        out.append("  %8.1f %5.1f%% %7.2f  %s" % (value, 100.0 * value / total,
                                                  calls.get(function, 0.0), function))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--file", default=DEFAULT_FILE)
    parser.add_argument("--head", type=int, default=30000)
    parser.add_argument("--lines", type=int, default=10000)
    parser.add_argument("--at", type=float, default=0.5)
    parser.add_argument("--top", type=int, default=15)
    args = parser.parse_args()
    sys.path.insert(0, ROOT)
    import kestimator.toolhead

    if not kestimator.toolhead.__file__.endswith(".py"):
        sys.exit("opcodes: %s is compiled; its frames cannot be traced"
                 % kestimator.toolhead.__file__)
    head, body = window(args.file, args.head, args.lines, args.at)
    with tempfile.TemporaryDirectory() as tmpdir:
        ops, calls = per_line(head, body, tmpdir)
    print("%s: %d lines from %.0f %% of the file, after its first %d"
          % (os.path.basename(args.file), len(body), 100 * args.at, len(head)))
    print("\n".join(report(ops, calls, args.top)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
