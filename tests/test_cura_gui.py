"""The built plugin in the real Cura GUIs under Xvfb (tests/cura_harness/gui_check.py).

- Cura 4.13: Debian's, on this system, with Debian's python3-pyqt6 installed beside its
  PyQt5 (the plugin's dialogs once picked PyQt6 there and Qt aborted Cura).
- Cura 5.0: Debian trixie's, in a chroot made by ``.ci/cura5-chroot DIR`` and named by
  ``KESTIMATOR_CURA5_ROOT`` (``.ci/run`` builds one for the run and removes it afterwards;
  a developer points the variable at an existing one). Running it needs root (chroot and
  bind mounts).

Both install the package through Cura's own package manager, slice, read the message and
Cura's print-information panel, save through Cura's GCodeWriter, and drive the Extensions
menu's dialogs. Outside CI a missing Cura, Xvfb, chroot or root skips; under ``CI=true`` it
fails. About a minute each, one Cura at a time.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import CORPUS_CFG, IN_CI

pytestmark = pytest.mark.wall_clock  # tests/conftest.py starts it first
SCRIPT = Path(__file__).resolve().parent / "cura_harness" / "gui_check.py"
CURA5_ROOT_VARIABLE = "KESTIMATOR_CURA5_ROOT"
GUI_TIMEOUT_S = 900


def _require(ok: bool, what: str) -> None:
    if not ok:
        if IN_CI:
            pytest.fail("required under CI: %s" % what)
        pytest.skip("missing: %s" % what)


def _run(*args: str) -> str:
    proc = subprocess.run([sys.executable, str(SCRIPT), "--printer-cfg", str(CORPUS_CFG),
                           *args], capture_output=True, text=True, timeout=GUI_TIMEOUT_S)
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-3000:]
    assert "RESULT: PASS" in proc.stdout
    return proc.stdout


def test_plugin_end_to_end_in_cura_4_13_gui_with_pyqt6_installed_beside_pyqt5() -> None:
    missing = [p for p in ("xvfb-run", "cura", "CuraEngine") if shutil.which(p) is None]
    _require(not missing, ", ".join(missing))
    has_pyqt6 = subprocess.run(["/usr/bin/python3", "-c", "import PyQt6.QtWidgets"],
                               capture_output=True).returncode == 0
    _require(has_pyqt6, "Debian's python3-pyqt6 beside Cura 4.13 (it makes the binding "
                        "choice matter)")
    out = _run("--cura", "4.13")
    assert "'binding': 'PyQt5', 'kind': 'QFileDialog'" in out


def test_plugin_end_to_end_in_cura_5_gui_in_a_debian_trixie_chroot() -> None:
    root = os.environ.get(CURA5_ROOT_VARIABLE, "")
    _require(bool(root) and Path(root, "usr/bin/cura").is_file(),
             "a Cura 5 chroot (.ci/cura5-chroot DIR; %s=DIR)" % CURA5_ROOT_VARIABLE)
    _require(os.geteuid() == 0, "root (chroot and bind mounts)")
    out = _run("--cura", "5.0", "--root", root)
    assert "'binding': 'PyQt6', 'kind': 'QFileDialog'" in out
    assert "PASS: disabling the plugin puts Cura's time back in the panel" in out
