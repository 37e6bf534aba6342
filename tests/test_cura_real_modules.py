"""The plugin inside Debian's real Cura 4.13 / Uranium 4.13 modules, from load to save.

``tests/cura_harness/uranium_host.py`` runs in Debian's ``/usr/bin/python3`` (where the
``cura`` and ``python3-uranium`` packages put ``cura`` and ``UM``): Uranium's PluginRegistry
loads the bundled PostProcessingPlugin and this plugin, a real CuraEngine slice goes through
backend-done → background Job → message → writeStarted. Run twice: from the source tree (the
checkout's core on the path) and from the built .curapackage (its vendored core only).
"""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import pytest

from .conftest import CORPUS_CFG, IN_CI, PROJECT, load_cura_build_script, without_progress_table
from .cura_harness.curaengine import find_curaengine, slice_cube

sys.path.insert(0, str(PROJECT / "plugins" / "cura"))

from kestimator_cura import klipper_time  # noqa: E402
from kestimator_cura.chunks import split_like_cura  # noqa: E402
from kestimator_cura.machine import LimitsChoice  # noqa: E402

DEBIAN_PYTHON = "/usr/bin/python3"
HARNESS = PROJECT / "tests" / "cura_harness" / "uranium_host.py"
HARNESS_TIMEOUT_S = 300
PAUSE_SCRIPT_LINE = "G4 P1000 ;added by a post-processing script\n"


build = load_cura_build_script()


def _require(ok: bool, what: str) -> None:
    if not ok:
        if IN_CI:
            pytest.fail("%s is required in CI" % what)
        pytest.skip("%s is not installed" % what)


@pytest.fixture(scope="module")
def cube_gcode(tmp_path_factory: pytest.TempPathFactory) -> Path:
    program = find_curaengine()
    _require(program is not None, "CuraEngine with Debian's cura definitions (cura-engine, cura)")
    assert program is not None
    return slice_cube(program, tmp_path_factory.mktemp("curaengine"))


@pytest.fixture(scope="module")
def debian_python() -> str:
    found = Path(DEBIAN_PYTHON).is_file() and subprocess.run(
        [DEBIAN_PYTHON, "-c", "import UM.PluginRegistry, cura.CuraApplication"],
        capture_output=True).returncode == 0
    _require(found, "Debian's Cura 4.13 / Uranium modules (cura, python3-uranium)")
    return DEBIAN_PYTHON


def _run_harness(python: str, plugin_parent: Path, gcode: Path, out: Path,
                 *extra: str) -> dict[str, Any]:
    out.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run([python, str(HARNESS), str(plugin_parent), str(gcode), str(out),
                           str(CORPUS_CFG), *extra], capture_output=True, text=True,
                          timeout=HARNESS_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def source_run(debian_python: str, cube_gcode: Path,
               tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    out = tmp_path_factory.mktemp("source_run")
    return _run_harness(debian_python, PROJECT / "plugins" / "cura", cube_gcode, out,
                        str(PROJECT)), out


@pytest.fixture(scope="module")
def package_run(debian_python: str, cube_gcode: Path,
                tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    root = tmp_path_factory.mktemp("package_run")
    with zipfile.ZipFile(build.build(root / "dist")) as archive:
        archive.extractall(root / "unpacked")
    return _run_harness(debian_python, root / "unpacked" / "files" / "plugins", cube_gcode,
                        root / "out"), root


def _cli_inject(text: str, path: Path) -> bytes:
    path.write_text(text, encoding="utf-8", newline="")
    proc = subprocess.run([sys.executable, "-m", "kestimator", "inject", "--no-profile",
                           "--printer-cfg", str(CORPUS_CFG), "-q", str(path)],
                          capture_output=True, text=True, cwd=PROJECT)
    # 4: Klipper will stop this print (a Cura placeholder left in the file); the times are
    # written all the same.
    assert proc.returncode in (0, 4), proc.stderr
    # The Cura plugin writes no progress table (the Klipper module estimates such a file
    # when its print starts): the rest is inject's, byte for byte.
    return without_progress_table(path.read_bytes())


def test_uranium_plugin_registry_loads_the_extension_with_its_menu(
        source_run: tuple[dict[str, Any], Path]) -> None:
    result, _ = source_run
    assert result["extension_class"] == "KestimatorExtension"
    assert result["menu_name"] == "Klipper print time"
    assert result["menu"] == ["Limits now: Cura's machine settings",
                              "\u2713 Use Cura's machine settings",
                              "Use a Klipper printer.cfg...", "Use Moonraker...",
                              "Show the Klipper print time"]


def test_extensions_menu_names_and_ticks_the_active_limits_source(
        source_run: tuple[dict[str, Any], Path]) -> None:
    result, _ = source_run
    assert result["menu_printer_cfg"][:4] == [
        "Limits now: printer.cfg %s" % CORPUS_CFG, "Use Cura's machine settings",
        "\u2713 Use a Klipper printer.cfg...", "Use Moonraker..."]
    assert result["switched"]["menu"][1] == "\u2713 Use Cura's machine settings"


def test_changing_the_limit_source_after_a_save_times_the_slice_again(
        source_run: tuple[dict[str, Any], Path]) -> None:
    """Bug: the save wrote the marker into Cura's list and startJob() then did nothing."""
    result, out = source_run
    switched = result["switched"]
    assert switched["total_s"] == result["machine"]["total_s"]
    assert switched["total_s"] != result["printer_cfg"]["total_s"]
    assert "Limits: Cura machine settings" in switched["message"]
    assert (out / "switched.gcode").read_bytes() == (out / "machine.gcode").read_bytes()


def test_klipper_time_goes_to_curas_print_information_with_curas_split_and_materials(
        source_run: tuple[dict[str, Any], Path]) -> None:
    result, _ = source_run
    plate, engine_times, engine_amounts = result["panel"]["engine"]
    plate, times, amounts = result["panel"]["last"]
    assert plate == 0 and amounts == engine_amounts
    assert sum(times.values()) == pytest.approx(result["machine"]["total_s"], abs=1e-9)
    assert set(times) == set(engine_times)
    assert times["inset_0"] / times["infill"] == pytest.approx(
        engine_times["inset_0"] / engine_times["infill"])
    assert "Cura's print information shows Klipper's time." in result["machine"]["message"]
    assert "Cura estimated" in result["machine"]["message"]
    assert result["switched"]["panel_total_s"] == pytest.approx(result["machine"]["total_s"])


def test_saved_file_equals_kestimator_inject_and_keeps_the_list(
        source_run: tuple[dict[str, Any], Path], cube_gcode: Path, tmp_path: Path) -> None:
    result, out = source_run
    text = cube_gcode.read_text(encoding="utf-8")
    run = result["printer_cfg"]
    assert run["chunk_count"] == len(split_like_cura(text))
    assert run["same_list_object"]
    assert run["used_background_result"]  # the save did not redo the job's work
    assert (out / "printer_cfg.gcode").read_bytes() == _cli_inject(text, tmp_path / "a.gcode")


def test_background_job_shows_the_klipper_time_before_saving(
        source_run: tuple[dict[str, Any], Path]) -> None:
    result, _ = source_run
    run = result["printer_cfg"]
    minutes, seconds = divmod(round(run["total_s"]), 60)
    assert "Klipper print time: %dm %02ds" % (minutes, seconds) in run["message"]
    assert str(CORPUS_CFG) in run["message"]


def test_second_save_changes_nothing(source_run: tuple[dict[str, Any], Path]) -> None:
    result, out = source_run
    assert result["printer_cfg"]["second_save_unchanged"]
    assert (out / "printer_cfg_again.gcode").read_bytes() == (
        out / "printer_cfg.gcode").read_bytes()


def test_machine_settings_from_the_global_stack_give_the_time(
        source_run: tuple[dict[str, Any], Path], cube_gcode: Path) -> None:
    result, out = source_run
    settings = result["machine_settings"]
    assert settings["machine_max_acceleration_x"] == 9000  # Ender-3 definition's value
    chunks = split_like_cura(cube_gcode.read_text(encoding="utf-8"))
    expected = klipper_time.compute(chunks, LimitsChoice(), settings)
    assert result["machine"]["total_s"] == expected.total_s
    assert (out / "machine.gcode").read_text(encoding="utf-8") == "".join(expected.rewritten)


def test_runs_after_post_processing_scripts_and_times_what_they_added(
        source_run: tuple[dict[str, Any], Path], cube_gcode: Path, tmp_path: Path) -> None:
    result, out = source_run
    chunks = split_like_cura(cube_gcode.read_text(encoding="utf-8"))
    chunks[3] += PAUSE_SCRIPT_LINE
    chunks[0] += ";POSTPROCESSED\n"
    expected = _cli_inject("".join(chunks), tmp_path / "pp.gcode")
    assert (out / "post_processed.gcode").read_bytes() == expected
    assert result["post_processed"]["chunk_count"] == len(chunks)
    assert result["post_processed"]["total_s"] == pytest.approx(
        result["printer_cfg"]["total_s"] + 1.0, abs=0.01)


def test_built_package_runs_on_its_vendored_core_in_uranium(
        package_run: tuple[dict[str, Any], Path],
        source_run: tuple[dict[str, Any], Path]) -> None:
    result, root = package_run
    vendor = root / "unpacked" / "files" / "plugins" / "kestimator_cura" / "vendor"
    assert Path(result["core_file"]).is_relative_to(vendor)
    assert (root / "out" / "printer_cfg.gcode").read_bytes() == (
        source_run[1] / "printer_cfg.gcode").read_bytes()


def test_a_failing_limit_source_is_shown_and_the_save_keeps_curas_gcode(
        source_run: tuple[dict[str, Any], Path], cube_gcode: Path) -> None:
    result, out = source_run
    failed = result["failed"]
    assert failed["job_message"].startswith("No Klipper print time: ")
    assert "absent" in failed["job_message"]
    assert failed["save_message"].startswith("The G-code was saved without Klipper's times")
    assert (out / "failed.gcode").read_bytes() == cube_gcode.read_bytes()
