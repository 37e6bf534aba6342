"""After `inject`, Moonraker's own metadata parser reads Klipper's time for every slicer family
it reads a time for, including files whose slicer wrote no line it reads (issue 17).

Runs Moonraker's real `file_manager.metadata.extract_metadata` (PyPI `moonraker`, the same
pinned version the end-to-end test installs) on injected corpus files.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.progress_table import HEADER_PREFIX, read_table_file
from kestimator.rewrite import inject_file

from .conftest import CORPUS, CORPUS_CFG
from .test_moonraker_e2e import moonraker_python  # noqa: F401  (the session fixture)

GCODE = CORPUS / "gcode"

METADATA_SCRIPT = (
    "import json, sys\n"
    "from moonraker.components.file_manager import metadata\n"
    "print(json.dumps({p: metadata.extract_metadata(p, []) for p in sys.argv[1:]}))\n")
# (corpus file, what Moonraker calls the slicer, whether the slicer wrote a line it reads)
FAMILIES = (
    ("prusaslicer/ps25_nut_accelA_small.gcode", "PrusaSlicer", True),
    ("superslicer/cancelobj_ss2.4_inverted_pyramid.gcode", "SuperSlicer", False),
    ("superslicer/cancelobj_ss2.3.56_arcwelder.gcode", "SuperSlicer", True),
    ("orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode", "OrcaSlicer", True),
    ("bambustudio/gcodeparsersharp_bs1.6.2.gcode", "BambuStudio", False),
    ("icesl/cancelobj_icesl_2021-09.gcode", "IceSL", False),
    ("cura/cura413_ender3_nut_small.gcode", "Cura", True),
    ("ideamaker/cancelobj_ideamaker4.2.0.gcode", "IdeaMaker", True),
    ("kirimoto/cancelobj_kirimoto3.0.gcode", "Kiri:Moto", True),
    ("kisslicer/cancelobj_kisslicer2.0.6.gcode", "KISSlicer", True),
)
# Moonraker reads no time for these (its Slic3r parser returns None): nothing is added.
NO_MOONRAKER_TIME = ("slic3r/slic3r130_torus_x3_accel.gcode",)


def _metadata(python: str, paths: list[Path]) -> dict[str, dict]:
    out = subprocess.run([python, "-c", METADATA_SCRIPT, *map(str, paths)], check=True,
                         capture_output=True, timeout=300).stdout
    return json.loads(out)


def test_moonraker_reads_klippers_time_from_every_injected_family(
        moonraker_python: str, corpus_root: Path, tmp_path: Path) -> None:  # noqa: F811
    limits, _ = limits_from_printer_cfg(CORPUS_CFG)
    outputs, totals = [], []
    for name, _, _ in FAMILIES:
        out = tmp_path / Path(name).name
        result = inject_file(GCODE / name, limits, output=str(out))
        outputs.append(out)
        totals.append(result.estimate.total_s)
    # Moonraker's parser writes thumbnails beside the file it reads: read copies, never the
    # shared corpus itself.
    originals = tmp_path / "originals"
    originals.mkdir()
    copies = []
    for name, _, _ in FAMILIES:
        copy = originals / Path(name).name
        shutil.copyfile(GCODE / name, copy)
        copies.append(copy)
    before = _metadata(moonraker_python, copies)
    after = _metadata(moonraker_python, outputs)
    for (name, slicer, had_line), out, total, copy in zip(FAMILIES, outputs, totals, copies,
                                                          strict=True):
        meta = after[str(out)]
        assert meta["slicer"] == slicer, name
        # Every parser rounds to the second at most (KISSlicer: minutes with 2 decimals).
        assert meta["estimated_time"] == pytest.approx(total, abs=0.6), name
        original = before[str(copy)].get("estimated_time")
        assert (original is not None) == had_line, name


def test_added_time_lines_are_where_moonraker_looks_and_a_second_run_is_byte_identical(
        corpus_root: Path, tmp_path: Path) -> None:
    limits, _ = limits_from_printer_cfg(CORPUS_CFG)
    # (file, where the line goes, the line): SuperSlicer's parser reads the last MiB, Bambu
    # Studio's and IceSL's the first, where it stands right before kestimator's marker.
    expected = (
        ("superslicer/cancelobj_ss2.4_inverted_pyramid.gcode", "tail",
         b"; estimated printing time (normal mode) = 13m 2s"),
        ("bambustudio/gcodeparsersharp_bs1.6.2.gcode", "head",
         b"; estimated printing time (normal mode) = 18m 3s"),
        ("icesl/cancelobj_icesl_2021-09.gcode", "head", b"; estimated_print_time_s : 549"),
    )
    for name, where, line in expected:
        once = tmp_path / "once.gcode"
        twice = tmp_path / "twice.gcode"
        inject_file(GCODE / name, limits, output=str(once))
        data = once.read_bytes()
        lines = data.splitlines()
        if where == "tail":
            # The last line before the progress table, which ends the file.
            content = data[:data.index(b"\n" + HEADER_PREFIX) + 1]
            assert content.splitlines()[-1] == line and content.endswith(b"\n"), name
            assert data.endswith(b"\n") and read_table_file(once).content_bytes == len(content)
        else:
            marker = next(i for i, text in enumerate(lines) if text.startswith(b"; kestimator "))
            assert lines[marker - 1] == line, name
        assert lines.count(line) == 1, name
        # Everything else is the original file with kestimator's usual lines.
        inject_file(once, limits, output=str(twice))
        assert twice.read_bytes() == data, name
    for name in NO_MOONRAKER_TIME:
        out = tmp_path / "slic3r.gcode"
        inject_file(GCODE / name, limits, output=str(out))
        assert b"; estimated printing time" not in out.read_bytes()
