"""Print every field of the estimate of each file given, floats as hex: one JSON line each.

Run as a script by the interpreter under test (the compiled build's venv, PyPy, pure
CPython), so that tests compare builds field by field and bit by bit in one process per
build: `python tests/estimate_digest.py PRINTER_CFG FILE...`. A file the planner refuses
prints its error message instead.
"""

from __future__ import annotations

import dataclasses
import json
import sys

from kestimator import build
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.errors import KestimatorError
from kestimator.estimate import estimate_file
from kestimator.timedlines import TimedLines

MARKS = (";TIME_ELAPSED:",)


def _plain(value: object) -> object:
    """JSON-able, with every float as its exact hex text (so -0.0 and 0.0 differ)."""
    if isinstance(value, float):
        return value.hex()
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {"__type__": type(value).__name__, **{
            f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}}
    if isinstance(value, (set, frozenset)):
        return sorted(_plain(v) for v in value)  # type: ignore[type-var]
    if isinstance(value, TimedLines):
        return [_plain(list(pair)) for pair in value]
    if hasattr(value, "tolist"):  # array.array
        return _plain(value.tolist())  # type: ignore[attr-defined]
    return value


def digest(path: str, printer_cfg: str) -> dict[str, object]:
    """The estimate of `path` (with samples, marks, homing and heat times) as plain data."""
    limits = limits_from_printer_cfg(printer_cfg)[0]
    try:
        est = estimate_file(path, limits, homing_time=1.5, heat_time=2.0, sample=True,
                            mark_prefixes=MARKS)
    except KestimatorError as exc:
        return {"error": str(exc)}
    fields = {f.name: getattr(est, f.name) for f in dataclasses.fields(est)}
    return {name: _plain(value) for name, value in fields.items()}


def main(argv: list[str]) -> int:
    printer_cfg, paths = argv[0], argv[1:]
    print(json.dumps({"build": build()}))
    for path in paths:
        print(json.dumps(digest(path, printer_cfg), sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
