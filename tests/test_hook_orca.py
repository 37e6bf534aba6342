"""OrcaSlicer and Bambu Studio files through the post-processing hook, run as those slicers run it.

OrcaSlicer and Bambu Studio inherit PrusaSlicer's contract (src/libslic3r/GCode/PostProcessor.cpp
in all three): on Linux and macOS each script line runs as `$SHELL -c "<line> '<gcode>'"`
(/bin/sh without SHELL) with every config key in the environment as `SLIC3R_<KEY>` plus
`SLIC3R_PP_HOST` and `SLIC3R_PP_OUTPUT_NAME`. A GUI export hands over a copy named
`.<pid>.gcode.pp` in the temp folder; an upload to a printer host hands over an extension-less
temp file whose output name is the name on the host. The corpus files are copied into such
places (never edited in the repository) and the hook line from plugins/orca/README.md runs on
them: the installed command for exports, the zipapp for uploads. Without `--printer-cfg`, the
`SLIC3R_*` environment must stand in for the settings block a file may lack.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from .conftest import CORPUS_CFG
from .test_hook_checks import (
    COMMENT_TOLERANCE_S,
    HOOK_CORPUS,
    build_zipapp,
    estimate_json,
    hook_problems,
    isolated_environment,
    paste_line,
    untouched_lines,
)

CONFIG_BLOCK_START = "; CONFIG_BLOCK_START"
CONFIG_BLOCK_END = "; CONFIG_BLOCK_END"
POSIX_SHELL = "/bin/sh"
# Every corpus file's config block has hundreds of keys; the hook must cope with all of them.
MIN_SLIC3R_KEYS = 200
HOOK_TIMEOUT_S = 300

# (temp file name, SLIC3R_PP_HOST): a GUI export's copy, and an upload's extension-less file.
EXPORT = (".4242.gcode.pp", "File")
UPLOAD = (".Slic3rUpload.3f2a-91c4-5d7e-b810", "OctoPrint")


@pytest.fixture(scope="module")
def zipapp(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_zipapp(tmp_path_factory.mktemp("pyz"))


def slicer_environment(gcode: Path, host: str, output_name: str,
                       home: Path) -> dict[str, str]:
    """The environment Orca/Bambu give a script: theirs, plus the file's config as SLIC3R_*."""
    env = isolated_environment(home)
    inside = False
    for raw in gcode.read_text(encoding="utf-8", errors="replace").splitlines():
        if raw.startswith(CONFIG_BLOCK_START):
            inside = True
        elif raw.startswith(CONFIG_BLOCK_END):
            break
        elif inside and raw.startswith("; ") and " = " in raw:
            key, value = raw[2:].split(" = ", 1)
            env["SLIC3R_" + key.strip().upper()] = value
    env["SLIC3R_PP_HOST"] = host
    env["SLIC3R_PP_OUTPUT_NAME"] = output_name
    return env


def run_like_the_slicer(line: str, gcode: Path,
                        env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """Run one post-processing line as PostProcessor.cpp does on POSIX."""
    quoted = "'" + str(gcode).replace("'", "'\\''") + "'"
    return subprocess.run([env.get("SHELL", POSIX_SHELL), "-c", line + " " + quoted],
                          env=env, capture_output=True, text=True, timeout=HOOK_TIMEOUT_S)


def place_like_the_slicer(source: Path, tmp_path: Path, temp_name: str) -> Path:
    """Copy a corpus file to the slicer's temp name, writable as the slicer's own copy is."""
    temp_dir = tmp_path / "tmp"
    temp_dir.mkdir()
    gcode = temp_dir / temp_name
    shutil.copyfile(source, gcode)
    gcode.chmod(0o644)
    return gcode


def output_name(host: str, source: Path, tmp_path: Path) -> str:
    """SLIC3R_PP_OUTPUT_NAME: the final path for a file export, the host's name for uploads."""
    name = source.stem + ".gcode"
    return str(tmp_path / "prints" / name) if host == "File" else name


@pytest.mark.parametrize(("scenario", "entry"), [(EXPORT, "command"), (UPLOAD, "zipapp")],
                         ids=["gui-export-temp-copy-via-command", "upload-temp-file-via-zipapp"])
@pytest.mark.parametrize("source", HOOK_CORPUS, ids=lambda p: p.parent.name + "/" + p.name)
def test_the_hook_writes_klipper_times_into_orca_and_bambu_files(
        source: Path, scenario: tuple[str, str], entry: str, corpus_root: Path, zipapp: Path,
        tmp_path: Path) -> None:
    temp_name, host = scenario
    gcode = place_like_the_slicer(source, tmp_path, temp_name)
    env = slicer_environment(source, host, output_name(host, source, tmp_path), tmp_path)
    assert sum(key.startswith("SLIC3R_") for key in env) > MIN_SLIC3R_KEYS

    proc = run_like_the_slicer(paste_line(entry, zipapp, CORPUS_CFG), gcode, env)

    # 4: Klipper will stop this print (one line on stderr for the slicer's dialog); the
    # times are written all the same.
    assert proc.returncode in (0, 4), proc.stderr
    assert proc.returncode == 0 or proc.stderr.startswith(
        "kestimator: Klipper will stop this print at line ")
    assert sorted(p.name for p in gcode.parent.iterdir()) == [temp_name]
    assert hook_problems(gcode, CORPUS_CFG, tmp_path) == []
    assert untouched_lines(gcode.read_bytes()) == untouched_lines(source.read_bytes())


def test_running_the_hook_twice_changes_nothing(corpus_root: Path, zipapp: Path,
                                                tmp_path: Path) -> None:
    # Re-exporting or a second script line must not stack markers or drift the times.
    source = HOOK_CORPUS[0]
    gcode = place_like_the_slicer(source, tmp_path, EXPORT[0])
    env = slicer_environment(source, "File", output_name("File", source, tmp_path), tmp_path)
    line = paste_line("command", zipapp, CORPUS_CFG)
    assert run_like_the_slicer(line, gcode, env).returncode == 0
    once = gcode.read_bytes()
    assert run_like_the_slicer(line, gcode, env).returncode == 0
    assert gcode.read_bytes() == once


@pytest.mark.parametrize("entry", ["command", "zipapp"])
def test_a_failing_hook_says_why_in_one_line_and_leaves_the_file_as_the_slicer_wrote_it(
        entry: str, corpus_root: Path, zipapp: Path, tmp_path: Path) -> None:
    source = HOOK_CORPUS[-1]
    gcode = place_like_the_slicer(source, tmp_path, EXPORT[0])
    missing_cfg = tmp_path / "no-such-dir" / "printer.cfg"
    env = slicer_environment(source, "File", output_name("File", source, tmp_path), tmp_path)

    proc = run_like_the_slicer(paste_line(entry, zipapp, missing_cfg), gcode, env)

    assert proc.returncode == 1
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("kestimator: error: ")
    assert str(missing_cfg) in lines[0]
    assert gcode.read_bytes() == source.read_bytes()
    assert sorted(p.name for p in gcode.parent.iterdir()) == [EXPORT[0]]


@pytest.mark.parametrize("source", HOOK_CORPUS, ids=lambda p: p.parent.name + "/" + p.name)
def test_without_a_printer_cfg_the_hook_reads_the_slicer_settings_from_its_environment(
        source: Path, corpus_root: Path, zipapp: Path, tmp_path: Path) -> None:
    # The file keeps no config block here, so only SLIC3R_* can tell the hook what the
    # slicer's machine limits were; with them it must agree with the file as the slicer wrote it.
    gcode = place_like_the_slicer(source, tmp_path, EXPORT[0])
    gcode.write_bytes(without_config_block(source.read_bytes()))
    env = slicer_environment(source, "File", output_name("File", source, tmp_path), tmp_path)
    plain = isolated_environment(tmp_path)
    with_environment_s = estimate_json(gcode, None, env)["total_s"]
    assert with_environment_s == pytest.approx(estimate_json(source, None, plain)["total_s"])
    assert abs(with_environment_s - estimate_json(gcode, None, plain)["total_s"]) > (
        COMMENT_TOLERANCE_S)

    proc = run_like_the_slicer(paste_line("command", zipapp, None), gcode, env)

    assert proc.returncode in (0, 4), proc.stderr  # 4: Klipper will stop this print
    assert hook_problems(gcode, None, tmp_path, env) == []


def without_config_block(data: bytes) -> bytes:
    """The file minus its `; CONFIG_BLOCK_START` ... `; CONFIG_BLOCK_END` lines."""
    kept = []
    inside = False
    for raw in data.split(b"\n"):
        if raw.startswith(CONFIG_BLOCK_START.encode()):
            inside = True
        elif raw.startswith(CONFIG_BLOCK_END.encode()):
            inside = False
        elif not inside:
            kept.append(raw)
    return b"\n".join(kept)
