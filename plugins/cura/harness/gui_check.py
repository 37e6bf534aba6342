"""Manual check: the built plugin inside a running Cura 4.13 GUI under Xvfb.

Owns nothing the plugin ships. It builds the package, installs it into a throw-away HOME's
Cura 4.13 plugin folder next to a small helper plugin (``gui_check_helper``, written here),
and starts ``xvfb-run cura cube.stl`` twice:

1. *seed*: the helper accepts the user agreement and adds a Creality Ender-3 (what the
   first-run wizard would do), saves Cura's settings and quits;
2. *check*: Cura starts with that printer and the cube, slices it (auto-slicing), our plugin
   times it in its background job and shows its message. The helper logs every message Cura
   shows (``visibleMessageAdded``) and, once ours appeared, saves the G-code through an
   output device it registers with Cura's ``OutputDeviceManager`` (so ``writeStarted`` runs
   exactly as for *Save to Disk*, whose file dialog cannot be driven reliably), then takes
   no further action. The script takes a screenshot and stops Cura.

Each step prints PASS or FAIL, from ``cura.log`` lines and the saved file.
Usage: ``python3 plugins/cura/harness/gui_check.py [--keep DIR]``; exit status 0 if all pass.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from harness.curaengine import write_cube_stl  # noqa: E402

CURA_VERSION = "4.13"
SCREEN = "1600x1000x24"
SEED_TIMEOUT_S = 60
CHECK_TIMEOUT_S = 90

HELPER_JSON = """{"name": "gui_check_helper", "author": "kestimator", "version": "1.0.0",
 "description": "kestimator gui_check helper", "supported_sdk_versions": ["7.9.0", "8.0.0"],
 "api": 7}
"""

HELPER_PY = r'''
import os
from UM.Application import Application
from UM.Extension import Extension
from UM.Logger import Logger
from UM.OutputDevice.OutputDevice import OutputDevice
from UM.PluginRegistry import PluginRegistry

MODE = os.environ.get("GUI_CHECK_MODE", "")
OUT = os.environ.get("GUI_CHECK_OUT", "")


class SaveDevice(OutputDevice):
    """Writes like LocalFileOutputDevice, to a fixed path instead of asking for one."""

    def requestWrite(self, nodes, file_name=None, limit_mimetypes=None, file_handler=None,
                     filter_by_machine=False, **kwargs):
        self.writeStarted.emit(self)
        writer = PluginRegistry.getInstance().getPluginObject("GCodeWriter")
        with open(OUT, "w", encoding="utf-8") as stream:
            ok = writer.write(stream, nodes)
        Logger.log("i", "gui_check: saved %s ok=%s", OUT, ok)
        self.writeFinished.emit(self)


class Helper(Extension):
    def __init__(self, app):
        super().__init__()
        self._app = app
        self._saved = False
        app.initializationFinished.connect(self._started)
        app.visibleMessageAdded.connect(self._message)

    def _started(self):
        manager = self._app.getMachineManager()
        Logger.log("i", "gui_check: started mode=%s machine=%s", MODE,
                   manager.activeMachine is not None)
        if MODE == "seed":
            self._app.getPreferences().setValue("general/accepted_user_agreement", True)
            self._app.getPreferences().setValue("general/auto_slice", True)  # off by default
            if manager.activeMachine is None:
                manager.addMachine("creality_ender3")
            self._app.saveSettings()
            Logger.log("i", "gui_check: seeded")
            self._app.callLater(self._app.closeApplication)
        else:
            self._device = SaveDevice("gui_check_save")
            self._app.getOutputDeviceManager().addOutputDevice(self._device)

    def _message(self, message):
        Logger.log("i", "gui_check: message title=%r text=%r", message.getTitle(),
                   message.getText())
        if MODE == "check" and "kestimator" not in (message.getTitle() or ""):
            # Debian's broken bundled plugins (TrimeshReader...) fill the message stack: hide
            # them so ours is visible on the screenshot.
            self._app.callLater(message.hide)
        if (MODE == "check" and not self._saved and "kestimator" in (message.getTitle() or "")):
            self._saved = True
            self._app.callLater(self._save)

    def _save(self):
        scene = self._app.getController().getScene()
        self._device.requestWrite([scene.getRoot()])


def getMetaData():
    return {}


def register(app):
    return {"extension": Helper(app)}
'''


def _log_path(home: Path) -> Path:
    return home / ".local/share/cura" / CURA_VERSION / "cura.log"


def install(home: Path) -> None:
    """The built package's plugin folder and the helper, into HOME's Cura plugin folder."""
    plugins = home / ".local/share/cura" / CURA_VERSION / "plugins"
    plugins.mkdir(parents=True, exist_ok=True)
    dist = home / "dist"
    subprocess.run([sys.executable, str(HERE.parent / "build.py"), "--out-dir", str(dist)],
                   check=True, capture_output=True)
    package = next(dist.glob("*.curapackage"))
    prefix = "files/plugins/"
    with zipfile.ZipFile(package) as archive:
        for name in archive.namelist():
            if name.startswith(prefix) and not name.endswith("/"):
                target = plugins / name[len(prefix):]
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(archive.read(name))
    helper = plugins / "gui_check_helper"
    helper.mkdir(exist_ok=True)
    (helper / "plugin.json").write_text(HELPER_JSON)
    (helper / "__init__.py").write_text(HELPER_PY)


def start_cura(home: Path, mode: str, args: list[str], out: Path) -> subprocess.Popen:
    env = dict(os.environ, HOME=str(home), GUI_CHECK_MODE=mode, GUI_CHECK_OUT=str(out),
               LIBGL_ALWAYS_SOFTWARE="1", XDG_CONFIG_HOME=str(home / ".config"),
               XDG_DATA_HOME=str(home / ".local/share"), XDG_CACHE_HOME=str(home / ".cache"))
    with open(home / ("cura-%s.out" % mode), "w") as output:
        return subprocess.Popen(["xvfb-run", "-a", "-s", "-screen 0 %s" % SCREEN, "cura"] + args,
                                env=env, stdout=output, stderr=subprocess.STDOUT,
                                start_new_session=True)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def wait_for(log: Path, pattern: str, timeout: float, proc: subprocess.Popen) -> str | None:
    deadline = time.monotonic() + timeout
    regex = re.compile(pattern)
    while time.monotonic() < deadline:
        if log.is_file():
            for line in log.read_text(errors="replace").splitlines():
                if regex.search(line):
                    return line
        if proc.poll() is not None and not log.is_file():
            return None
        time.sleep(0.5)
    return None


def screenshot(proc: subprocess.Popen, target: Path) -> bool:
    """``import -window root`` on the Xvfb display xvfb-run started (found from its children)."""
    if shutil.which("import") is None:
        return False
    found = subprocess.run(["ps", "-o", "args=", "--ppid", str(proc.pid)], capture_output=True,
                           text=True).stdout
    match = re.search(r"Xvfb (:\d+) .*-auth (\S+)", found)
    if match is None:
        return False
    env = dict(os.environ, DISPLAY=match.group(1), XAUTHORITY=match.group(2))
    return subprocess.run(["import", "-window", "root", str(target)], env=env,
                          capture_output=True).returncode == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, help="work in DIR and keep it (logs, screenshot)")
    args = parser.parse_args(argv)
    for program in ("xvfb-run", "cura"):
        if shutil.which(program) is None:
            print("FAIL: %s not found" % program)
            return 2
    home = args.keep or Path(tempfile.mkdtemp(prefix="kestimator-gui-"))
    home.mkdir(parents=True, exist_ok=True)
    results: list[tuple[str, bool, str]] = []

    def step(name: str, ok: bool, evidence: str) -> bool:
        results.append((name, ok, evidence))
        print("%s: %s -- %s" % ("PASS" if ok else "FAIL", name, evidence), flush=True)
        return ok

    try:
        install(home)
        log = _log_path(home)
        out = home / "saved.gcode"
        seed = start_cura(home, "seed", [], out)
        line = wait_for(log, r"gui_check: seeded", SEED_TIMEOUT_S, seed)
        try:
            seed.wait(20)
        except subprocess.TimeoutExpired:
            pass
        stop(seed)
        if not step("seed a printer (first-run wizard skipped)", line is not None, line or ""):
            return 1
        log.rename(log.with_name("cura-seed.log"))
        cube = write_cube_stl(home / "cube.stl", 20.0)
        cura = start_cura(home, "check", [str(cube)], out)
        try:
            line = wait_for(log, r"Loaded plugin kestimator_cura", 60, cura)
            step("plugin loaded by PluginRegistry", line is not None, line or "")
            line = wait_for(log, r"gui_check: started mode=check machine=True", 60, cura)
            step("Cura started with the printer, no wizard", line is not None, line or "")
            line = wait_for(log, r"Slicing took|Backend finished slicing|"
                                 r"_onSlicingFinished|Slicing finished", CHECK_TIMEOUT_S, cura)
            step("Cura sliced the cube", line is not None, line or "")
            line = wait_for(log, r"gui_check: message title='Klipper print time", 30, cura)
            step("kestimator's message shown after its background job", line is not None,
                 (line or "")[-300:])
            line = wait_for(log, r"gui_check: saved", 30, cura)
            saved = out.read_text(errors="replace") if out.is_file() else ""
            step("G-code saved through OutputDeviceManager", line is not None, line or "")
            marker = [x for x in saved.splitlines() if x.startswith("; kestimator")]
            m73 = [x for x in saved.splitlines() if x.startswith("M73 ")]
            step("saved file has the kestimator marker", bool(marker), marker[0] if marker else "")
            step("saved file has M73 lines", bool(m73), "%d M73 lines" % len(m73))
            time.sleep(3)  # let Qt Quick draw the message
            shot = home / "screenshot.png"
            # Informational: a screenshot that cannot be taken (no ImageMagick) fails nothing.
            print("%s: screenshot -- %s" % ("INFO" if screenshot(cura, shot) else "NOTE",
                                              shot if shot.is_file() else "not taken"))
            errors = [x for x in log.read_text(errors="replace").splitlines()
                      if "kestimator" in x and ("ERROR" in x or "Traceback" in x)]
            step("no kestimator errors in cura.log", not errors, "; ".join(errors[:3]))
        finally:
            stop(cura)
    finally:
        if args.keep is None:
            shutil.rmtree(home, ignore_errors=True)
    failed = [name for name, ok, _ in results if not ok]
    print("RESULT: %s" % ("PASS" if not failed else "FAIL (%s)" % ", ".join(failed)))
    return 0 if not failed else 1


if __name__ == "__main__":
    sys.exit(main())
