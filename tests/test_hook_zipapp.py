"""kestimator.pyz, built by tools/build_zipapp.py: one file any python3 >= 3.9 runs, no install.

Users without pip paste `/path/to/python3 /path/to/kestimator.pyz inject ...` into their
slicer. These tests build it into a temporary folder and pin that it holds the package's
sources and tomli's (with its licence) and nothing else, that it runs with no site-packages
at all (`-I -S`) and writes the same bytes as the installed command, that a real Python 3.9
(no tomllib: macOS's own /usr/bin/python3 is 3.9) runs the argument-free hook with the
profile, and that a too old python3 gets one readable line.
"""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from kestimator import __version__

from .conftest import IN_CI, PROJECT
from .test_hook_checks import build_zipapp, installed_command, isolated_environment

EXAMPLE = PROJECT / "examples" / "hex_nut_prusaslicer.gcode"
PRINTER_CFG = PROJECT / "examples" / "printer.cfg"
# No site-packages, no user site, no PYTHONPATH: only the standard library and the archive.
BARE_PYTHON = (sys.executable, "-I", "-S")
RUN_TIMEOUT_S = 300


@pytest.fixture(scope="module")
def zipapp(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_zipapp(tmp_path_factory.mktemp("pyz"))


def run(*args: str | Path, env: dict[str, str] | None = None
        ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(a) for a in args], env=env, capture_output=True, text=True,
                          timeout=RUN_TIMEOUT_S)


def _tomli_sources() -> dict[str, Path]:
    spec = importlib.util.find_spec("tomli")
    assert spec is not None and spec.origin is not None, "tomli is a test requirement"
    package = Path(spec.origin).parent
    return {"tomli/" + p.relative_to(package).as_posix(): p for p in package.rglob("*.py")
            if "__pycache__" not in p.parts}


def test_the_zipapp_holds_the_package_sources_tomli_and_its_entry_only(zipapp: Path) -> None:
    sources = {"kestimator/" + p.relative_to(PROJECT / "kestimator").as_posix(): p
               for p in (PROJECT / "kestimator").rglob("*.py") if "__pycache__" not in p.parts}
    tomli = _tomli_sources()
    with zipfile.ZipFile(zipapp) as archive:
        files = {name for name in archive.namelist() if not name.endswith("/")}
        assert files == set(sources) | set(tomli) | {"__main__.py", "tomli/LICENSE"}
        for name, path in {**sources, **tomli}.items():
            assert archive.read(name) == path.read_bytes(), name
        assert b"MIT License" in archive.read("tomli/LICENSE")
        assert "kestimator.entry" in archive.read("__main__.py").decode()


def python39() -> str:
    """A Python 3.9 interpreter: CPython's python3.9 where one runs, else Debian bookworm's
    pypy3 (PyPy 7.3.11 speaks Python 3.9; .ci/run installs it). Under CI one must exist."""
    probe = "import sys; print('%d.%d' % sys.version_info[:2])"
    for name in ("python3.9", "pypy3"):
        found = shutil.which(name)
        if found is None:
            continue
        proc = subprocess.run([found, "-c", probe], capture_output=True, text=True,
                              timeout=RUN_TIMEOUT_S)
        if proc.returncode == 0 and proc.stdout.strip() == "3.9":
            return found
    message = "no Python 3.9 (python3.9 or bookworm's pypy3) is installed"
    if IN_CI:
        pytest.fail(message + " (.ci/run installs pypy3)")
    pytest.skip(message)


def test_python_3_9_runs_the_argument_free_hook_with_the_profile(
        zipapp: Path, tmp_path: Path) -> None:
    py39 = python39()
    # The premise: no tomllib, no tomli of its own (-I -S: no site-packages).
    assert run(py39, "-I", "-S", "-c", "import tomllib").returncode != 0
    assert run(py39, "-I", "-S", "-c", "import tomli").returncode != 0
    env = isolated_environment(tmp_path)
    profile = Path(env["XDG_CONFIG_HOME"]) / "kestimator" / "config.toml"
    profile.parent.mkdir(parents=True)
    profile.write_text("printer_cfg = %r\nheat_time_s = 90\n" % str(PRINTER_CFG))
    via_profile = tmp_path / "profile.gcode"
    via_options = tmp_path / "options.gcode"
    shutil.copyfile(EXAMPLE, via_profile)
    shutil.copyfile(EXAMPLE, via_options)

    hook = run(py39, "-I", "-S", zipapp, "inject", via_profile, env=env)
    assert hook.returncode == 0, hook.stderr
    assert hook.stderr == ""
    assert "Klipper time" in hook.stdout
    options = run(installed_command(), "inject", via_options, "--no-profile", "--printer-cfg",
                  PRINTER_CFG, "--heat-time", "90", env=env)
    assert options.returncode == 0, options.stderr
    assert via_profile.read_bytes() != EXAMPLE.read_bytes()
    assert via_profile.read_bytes() == via_options.read_bytes()


def test_the_zipapp_needs_no_installed_package(zipapp: Path) -> None:
    # The premise: this interpreter, bare, cannot import kestimator from anywhere else.
    assert run(*BARE_PYTHON, "-c", "import kestimator").returncode != 0
    proc = run(*BARE_PYTHON, zipapp, "--version")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "kestimator %s (pure Python)" % __version__


def test_the_zipapp_and_the_installed_command_write_the_same_bytes(
        zipapp: Path, tmp_path: Path) -> None:
    via_zipapp = tmp_path / "zipapp.gcode"
    via_command = tmp_path / "command.gcode"
    shutil.copyfile(EXAMPLE, via_zipapp)
    shutil.copyfile(EXAMPLE, via_command)

    env = isolated_environment(tmp_path)
    first = run(*BARE_PYTHON, zipapp, "inject", via_zipapp, "--printer-cfg", PRINTER_CFG,
                env=env)
    second = run(installed_command(), "inject", via_command, "--printer-cfg", PRINTER_CFG,
                 env=env)

    assert first.returncode == 0, first.stderr
    assert second.returncode == 0, second.stderr
    assert via_zipapp.read_bytes() != EXAMPLE.read_bytes()
    assert via_zipapp.read_bytes() == via_command.read_bytes()


def test_a_too_old_python3_gets_one_line_saying_what_is_needed(zipapp: Path) -> None:
    # Pretend to be a Python 3.8 (3.9, macOS's own /usr/bin/python3, is supported), and run
    # the archive as python does.
    pretend = ("import runpy, sys\n"
               "archive = sys.argv[1]\n"
               "sys.version_info = (3, 8, 10, 'final', 0)\n"
               "sys.argv = [archive, 'inject', 'print.gcode']\n"
               "runpy.run_path(archive, run_name='__main__')\n")
    proc = run(*BARE_PYTHON, "-c", pretend, zipapp)
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == [
        "kestimator: error: needs Python 3.9 or newer, but %s is 3.8" % sys.executable]
