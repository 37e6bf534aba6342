"""inject and check agree (issue 36): inject writes SET_PRINT_STATS_INFO only where the
printer knows it ([print_stats], which [virtual_sdcard] loads, or a printer whose config is
not known), so the pre-flight of an injected file finds nothing in inject's own lines."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file
from kestimator.limits import Limits
from kestimator.rewrite import LAYER_INFO_COMMAND, inject_file

from .conftest import CORPUS

HEATERS_CFG = Path(__file__).resolve().parent / "oracle_refs" / "configs" / "heaters.cfg"
NUT = CORPUS / "gcode" / "cura" / "cura413_ender3_nut_small.gcode"


def _limits(tmp_path: Path, extra: str) -> Limits:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(HEATERS_CFG.read_text() + extra)
    return limits_from_printer_cfg(cfg)[0]


def _skipped(path: Path, limits: Limits) -> dict[str, int]:
    est = estimate_file(path, limits)
    return {f.message.split('"')[1]: f.count for f in est.preflight if f.kind == "skipped"}


@pytest.mark.parametrize("extra, writes", [
    ("", False),
    ("\n[virtual_sdcard]\npath: /tmp\n", True),
    ("\n[print_stats]\n", True),
])
def test_inject_writes_layer_info_only_where_the_printer_knows_it(
        corpus_root: Path, tmp_path: Path, extra: str, writes: bool) -> None:
    limits = _limits(tmp_path, extra)
    out = tmp_path / "out.gcode"
    inject_file(NUT, limits, output=str(out))
    assert (LAYER_INFO_COMMAND in out.read_bytes()) is writes
    # The injected file's pre-flight finds what the original's does, nothing more.
    assert _skipped(out, limits) == _skipped(NUT, limits)


def test_inject_writes_layer_info_for_a_printer_not_known(corpus_root: Path,
                                                           tmp_path: Path) -> None:
    # The printer's limits, but not which sections its config has (a profile's limits).
    limits = dataclasses.replace(_limits(tmp_path, ""), configured_sections=())
    out = tmp_path / "out.gcode"
    inject_file(NUT, limits, output=str(out))
    assert LAYER_INFO_COMMAND in out.read_bytes()


def test_the_skipped_count_counts_commands_not_names(tmp_path: Path) -> None:
    from kestimator.estimate import estimate_text
    from kestimator.preflight import summary_lines

    est = estimate_text("G28\nG1 X10 Y10 F3000\nFOO\nFOO\nBAR\nG1 X20\n",
                        _limits(tmp_path, ""))
    head = summary_lines([f.to_json() for f in est.preflight])[0]
    assert head == "Pre-flight: 3 commands skipped"
