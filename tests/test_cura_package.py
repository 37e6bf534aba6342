"""The built .curapackage: Cura's zip layout, ids and versions, and a core that is its own."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import kestimator

from .conftest import CORPUS_CFG, PROJECT, load_cura_build_script

build = load_cura_build_script()
PLUGIN_ID = "kestimator_cura"
BASE = "files/plugins/%s/" % PLUGIN_ID


@pytest.fixture(scope="module")
def package(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build.build(tmp_path_factory.mktemp("dist"))


def test_package_is_named_by_plugin_id_and_version(package: Path) -> None:
    assert package.name == "%s-%s.curapackage" % (PLUGIN_ID, kestimator.__version__)


def test_package_has_cura_layout_ids_and_versions(package: Path) -> None:
    with zipfile.ZipFile(package) as archive:
        assert archive.testzip() is None
        names = archive.namelist()
        meta = json.loads(archive.read("package.json"))
        plugin = json.loads(archive.read(BASE + "plugin.json"))
    assert names[0] == "package.json"
    assert all(name.startswith(BASE) for name in names[1:])
    assert meta["package_id"] == PLUGIN_ID and meta["package_type"] == "plugin"
    assert meta["package_version"] == plugin["version"] == kestimator.__version__
    assert meta["sdk_version"] == meta["sdk_version_semver"] == "8.0.0"
    assert meta["display_name"] == plugin["name"] and meta["license"] == "GPL-3.0-or-later"
    assert "8.0.0" in plugin["supported_sdk_versions"]
    assert {"name", "author", "version", "description"} <= set(plugin)
    assert {BASE + "__init__.py", BASE + "extension.py", BASE + "README.md"} <= set(names)
    assert not any("__pycache__" in name or name.endswith(".pyc") for name in names)
    assert PLUGIN_ID != "kestimator"


def test_package_vendors_every_core_module(package: Path) -> None:
    core = PROJECT / "kestimator"
    expected = {BASE + "vendor/kestimator/" + path.relative_to(core).as_posix()
                for path in core.rglob("*.py") if "__pycache__" not in path.parts}
    with zipfile.ZipFile(package) as archive:
        vendored = {name for name in archive.namelist() if "/vendor/" in name}
        assert vendored == expected
        for name in expected:
            relative = name[len(BASE + "vendor/kestimator/"):]
            assert archive.read(name) == (core / relative).read_bytes()


def test_package_ships_the_plugin_folder_and_no_test_equipment(package: Path) -> None:
    plugin = PROJECT / "plugins" / "cura" / PLUGIN_ID
    expected = {BASE + path.relative_to(plugin).as_posix() for path in plugin.rglob("*")
                if path.suffix in (".py", ".json") and "__pycache__" not in path.parts}
    expected.add(BASE + "README.md")
    with zipfile.ZipFile(package) as archive:
        shipped = {name for name in archive.namelist()[1:] if "/vendor/" not in name}
    assert shipped == expected
    assert not any("cura_harness" in name or "gui_check" in name or "uranium_host" in name
                   for name in shipped)


def test_rebuild_gives_the_same_bytes(package: Path, tmp_path: Path) -> None:
    assert build.build(tmp_path).read_bytes() == package.read_bytes()


def test_build_refuses_a_plugin_version_other_than_the_core(tmp_path: Path) -> None:
    plugin_dir = tmp_path / PLUGIN_ID
    plugin_dir.mkdir()
    metadata = build.plugin_metadata()
    metadata["version"] = "0.0.0-other"
    (plugin_dir / "plugin.json").write_text(json.dumps(metadata))
    with pytest.raises(build.BuildError, match="differs"):
        build.package_members(plugin_dir=plugin_dir)


def test_unpacked_plugin_runs_its_vendored_core_over_another_kestimator(
        package: Path, tmp_path: Path) -> None:
    with zipfile.ZipFile(package) as archive:
        archive.extractall(tmp_path)
    plugins = tmp_path / "files" / "plugins"
    # The checkout's kestimator is imported first, as another plugin might have done.
    script = (
        "import sys, json\n"
        "import kestimator\n"
        "first = kestimator.__file__\n"
        "sys.path.insert(0, %r)\n"
        "from kestimator_cura import klipper_time, machine\n"
        "import kestimator.limits\n"
        "choice = machine.LimitsChoice('printer_cfg', printer_cfg=%r)\n"
        "out = klipper_time.compute([';FLAVOR:Marlin\\n', 'G28\\nG1 X100 F6000\\n'], choice, {})\n"
        "print(json.dumps([first, kestimator.__file__, kestimator.limits.__file__,"
        " out.total_s]))\n" % (str(plugins), str(CORPUS_CFG)))
    env = dict(os.environ, PYTHONPATH=str(PROJECT))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=tmp_path, env=env)
    assert proc.returncode == 0, proc.stderr
    first, core, limits_module, total_s = json.loads(proc.stdout)
    vendor = str(plugins / PLUGIN_ID / "vendor" / "kestimator")
    assert not first.startswith(vendor)
    assert core.startswith(vendor) and limits_module.startswith(vendor)
    assert total_s > 0
