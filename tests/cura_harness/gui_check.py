"""End-to-end check: the built plugin inside a running Cura GUI under Xvfb (Cura 4.13 or 5.0).

Owns nothing the plugin ships. Two Curas are driven the same way; what differs between them
is in `CuraTarget` alone (config folder name, where the log goes, how Cura is started):

- ``--cura 4.13``: Debian bookworm's Cura 4.13 (PyQt5) of this system. With Debian's
  python3-pyqt6 installed beside it, it proves the plugin's dialogs use PyQt5 there.
- ``--cura 5.0 --root DIR``: Debian trixie's Cura 5.0.0 (PyQt6, Python 3.13) and CuraEngine
  5.0.0 in a chroot made by ``.ci/cura5-chroot DIR``. /proc, /sys and /dev are bind-mounted
  into it while Cura runs and unmounted afterwards, also on failure (needs root).

Cura is started twice in a throw-away HOME, with a small helper plugin (``gui_check_helper``,
written here into Cura's plugin folder; it is test equipment, not the product):

1. *seed*: the helper accepts the user agreement, adds a Creality Ender-3, turns
   auto-slicing on (off by default in 4.13), hands the built ``.curapackage`` to Cura's own
   package manager (``PackageManager.installPackage``, what dropping the file on Cura does)
   and quits; Cura installs the package when it starts next.
2. *check*: Cura starts with the cube, slices it with its CuraEngine, and the helper plays a
   user: waits for the plugin's message; reads Cura's print-information panel
   (``PrintInformation.currentPrintTime``); takes a screenshot of the window; saves through
   Cura's GCodeWriter (an output device registered with the OutputDeviceManager, so
   ``writeStarted`` runs as for *Save to Disk*); picks a printer.cfg through the Extensions
   menu's model (``ExtensionModel.subMenuTriggered``, what the QML menu item calls) and the
   plugin's real QFileDialog; saves again; enters a Moonraker URL and API key in the plugin's
   QInputDialogs (the URL is unreachable: the message says so and Cura's own time is back in
   the panel); switches back to Cura's machine settings; moves the cube (Cura slices again,
   the new slice is timed and shown); and, where Uranium signals it (Cura 5), disables the
   plugin and reads the panel once more.

Each step prints PASS or FAIL from the helper's log lines and the saved files.
Usage: ``gui_check.py [--cura 4.13|5.0] [--root DIR] [--printer-cfg CFG] [--keep DIR]``;
exit status 0 if all pass.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parents[1]
BUILD_SCRIPT = PROJECT / "plugins" / "cura" / "build.py"
sys.path.insert(0, str(HERE))  # run as a script, beside curaengine.py
from curaengine import write_cube_stl  # noqa: E402

SCREEN = "1600x1000x24"
SEED_TIMEOUT_S = 120
STEP_TIMEOUT_S = 180
PORT_WAIT_S = 90
CURA_BACKEND_PORT = 49674
"""Where Cura's backend (UM/Backend/Backend.py, 4.13 and 5.0) listens for CuraEngine."""
API_KEY = "k19-gui-check-secret-5f3a"
"""The API key typed into the plugin's dialog; it must reach cura.cfg and no log."""
MOONRAKER_URL = "http://127.0.0.1:9"
"""Nothing listens there: the limits source fails at once."""
CHROOT_MOUNTS = ("proc", "sys", "dev")
CHROOT_PATH = "/usr/sbin:/usr/bin:/sbin:/bin"


class CuraTarget:
    """One Cura to drive: every difference between Cura 4.13 and 5.0 lives here."""

    def __init__(self, version: str, root: Path | None = None) -> None:
        self.version = version
        self.root = root
        """The chroot Cura runs in (None: this system's Cura)."""

    @property
    def config_folder(self) -> str:
        """Cura's version folder under ~/.local/share/cura and ~/.config/cura."""
        return self.version

    def host_path(self, inside: str) -> Path:
        """A path as Cura sees it, on this system."""
        return Path(inside) if self.root is None else self.root / inside.lstrip("/")

    def make_home(self) -> tuple[Path, str]:
        """A throw-away HOME: (path here, path as Cura sees it)."""
        parent = None if self.root is None else self.root / "tmp"
        home = Path(tempfile.mkdtemp(prefix="kestimator-gui-", dir=parent))
        home.chmod(0o755)
        inside = str(home) if self.root is None else "/" + str(home.relative_to(self.root))
        return home, inside

    def plugins_folder(self, home: Path) -> Path:
        return home / ".local/share/cura" / self.config_folder / "plugins"

    def log_text(self, home: Path) -> str:
        """What Cura logged: cura.log (Cura 4.13 writes it; Cura 5 from Debian writes it
        too, but its console logger is where early lines go) and Cura's stdout, together."""
        parts = []
        for path in (home / ".local/share/cura" / self.config_folder / "cura.log",
                     home / "cura-stdout.txt"):
            if path.is_file():
                parts.append(path.read_text(errors="replace"))
        return "\n".join(parts)

    def command(self, home_inside: str, env: dict[str, str], args: list[str]) -> list[str]:
        """The command line that starts Cura under xvfb-run with ``env``."""
        cura = ["xvfb-run", "-a", "-s", "-screen 0 %s" % SCREEN, "cura"] + args
        environment = ["%s=%s" % item for item in sorted(env.items())]
        if self.root is None:
            return ["env"] + environment + cura
        return ["chroot", str(self.root), "/usr/bin/env", "-i", "PATH=" + CHROOT_PATH,
                "LANG=C.UTF-8"] + environment + cura

    @contextlib.contextmanager
    def mounted(self) -> Iterator[None]:
        """/proc, /sys and /dev inside the chroot while Cura runs; unmounted in any case."""
        if self.root is None:
            yield
            return
        done: list[Path] = []
        try:
            for name in CHROOT_MOUNTS:
                target = self.root / name
                if subprocess.run(["mountpoint", "-q", str(target)]).returncode == 0:
                    continue
                subprocess.run(["mount", "--rbind", "/" + name, str(target)], check=True)
                done.append(target)
                subprocess.run(["mount", "--make-rslave", str(target)], check=True)
            yield
        finally:
            for target in reversed(done):
                subprocess.run(["umount", "-R", str(target)], capture_output=True)
                if subprocess.run(["mountpoint", "-q", str(target)]).returncode == 0:
                    subprocess.run(["umount", "-l", str(target)], capture_output=True)


HELPER_JSON = """{"name": "gui_check_helper", "author": "kestimator", "version": "1.0.0",
 "description": "kestimator gui_check helper", "supported_sdk_versions": ["7.9.0", "8.0.0"],
 "api": 7}
"""

HELPER_PY = r'''
import json
import os
import sys

from UM.Extension import Extension
from UM.Logger import Logger
from UM.OutputDevice.OutputDevice import OutputDevice
from UM.PluginRegistry import PluginRegistry

BINDING = "PyQt6" if "PyQt6.QtCore" in sys.modules else "PyQt5"
if BINDING == "PyQt6":
    from PyQt6.QtCore import QMetaObject, QTimer
    from PyQt6.QtWidgets import QApplication, QFileDialog, QInputDialog, QLineEdit
else:
    from PyQt5.QtCore import QMetaObject, QTimer
    from PyQt5.QtWidgets import QApplication, QFileDialog, QInputDialog, QLineEdit

MODE = os.environ.get("GUI_CHECK_MODE", "")
OUT = os.environ.get("GUI_CHECK_OUT", "")
PACKAGE = os.environ.get("GUI_CHECK_PACKAGE", "")
PRINTER_CFG = os.environ.get("GUI_CHECK_PRINTER_CFG", "")
MOONRAKER_URL = os.environ.get("GUI_CHECK_MOONRAKER_URL", "")
API_KEY = os.environ.get("GUI_CHECK_API_KEY", "")
PLUGIN = "kestimator_cura"
TITLE = "Klipper print time (kestimator)"


def note(what, **values):
    Logger.log("i", "gui_check: %s %s", what, json.dumps(values, sort_keys=True))


def accept(dialog):
    """Qt 6 made QFileDialog.accept() protected (PyQt6 refuses to call it on a dialog C++
    made); its slot is still reachable through the meta-object system, in both bindings."""
    QMetaObject.invokeMethod(dialog, "accept")


class SaveDevice(OutputDevice):
    """Writes like LocalFileOutputDevice through Cura's GCodeWriter, to a fixed path."""

    def requestWrite(self, nodes, file_name=None, limit_mimetypes=None, file_handler=None,
                     filter_by_machine=False, **kwargs):
        self.writeStarted.emit(self)
        writer = PluginRegistry.getInstance().getPluginObject("GCodeWriter")
        with open(file_name, "w", encoding="utf-8") as stream:
            ok = writer.write(stream, nodes)
        note("saved", path=file_name, ok=bool(ok))
        self.writeFinished.emit(self)


class DialogDriver:
    """Answers the next modal dialogs as a user would: a file, or texts, then OK."""

    def __init__(self, answers):
        self.answers = list(answers)
        self.timer = QTimer()
        self.timer.setInterval(300)
        self.timer.timeout.connect(self.tick)
        self.timer.start()

    def tick(self):
        dialog = QApplication.activeModalWidget()
        if dialog is None or not self.answers:
            return
        answer = self.answers.pop(0)
        if isinstance(dialog, QFileDialog):
            # What a user types into the file name field, then Open.
            edit = dialog.findChild(QLineEdit, "fileNameEdit")
            if edit is not None:
                edit.setText(answer)
            else:
                dialog.selectFile(answer)
            note("dialog", kind="QFileDialog", title=dialog.windowTitle(), binding=BINDING,
                 native_field=edit is not None)
            accept(dialog)
        elif isinstance(dialog, QInputDialog):
            secret = dialog.textEchoMode() == QLineEdit.EchoMode.Password
            dialog.setTextValue(answer)
            note("dialog", kind="QInputDialog", title=dialog.windowTitle(),
                 password=bool(secret), binding=BINDING)
            dialog.accept()
        else:
            self.answers.insert(0, answer)
            return
        if not self.answers:
            self.timer.stop()


class Helper(Extension):
    def __init__(self, app):
        super().__init__()
        self._app = app
        self._step = 0
        self._messages = 0
        self._driver = None
        app.initializationFinished.connect(self._started)
        app.visibleMessageAdded.connect(self._message)

    def _started(self):
        window = self._app.getMainWindow()
        if window is not None and MODE == "check":
            window.setGeometry(0, 0, 1600, 1000)  # no window manager: fill the screen
        manager = self._app.getMachineManager()
        note("started", mode=MODE, machine=manager.activeMachine is not None,
             binding=BINDING, python=sys.version.split()[0])
        if MODE == "seed":
            preferences = self._app.getPreferences()
            preferences.setValue("general/accepted_user_agreement", True)
            preferences.setValue("general/auto_slice", True)
            if manager.activeMachine is None:
                manager.addMachine("creality_ender3")
            package_id = self._app.getPackageManager().installPackage(PACKAGE)
            note("package scheduled", package_id=package_id)
            self._app.saveSettings()
            note("seeded")
            self._app.callLater(self._app.closeApplication)
        else:
            self._device = SaveDevice("gui_check_save")
            self._app.getOutputDeviceManager().addOutputDevice(self._device)

    # What the user sees
    def _panel_s(self):
        duration = self._app.getPrintInformation().currentPrintTime
        if duration is None:
            return None
        return ((duration.days * 24 + duration.hours) * 60 + duration.minutes) * 60 \
            + duration.seconds

    def _extension(self):
        return PluginRegistry.getInstance().getPluginObject(PLUGIN)

    def _menu_models(self):
        import gc
        from UM.Qt.Bindings.ExtensionModel import ExtensionModel
        return [m for m in gc.get_objects() if isinstance(m, ExtensionModel)]

    def _menu_texts(self):
        """The texts of our submenu as Cura's Extensions menu holds them."""
        found = []
        for model in self._menu_models():
            for item in model.items:
                if item.get("extension") is self._extension() and item.get("actions"):
                    actions = item["actions"]
                    found.append([actions.getItem(i)["text"] for i in range(actions.count)])
        return found

    def _trigger(self, prefix):
        """Click the menu item whose text starts with prefix, as the QML menu does."""
        for model in self._menu_models():
            for item in model.items:
                if item.get("extension") is self._extension() and item.get("actions"):
                    actions = item["actions"]
                    for i in range(actions.count):
                        text = actions.getItem(i)["text"]
                        if text.lstrip("\u2713 ").startswith(prefix):
                            note("menu", text=text)
                            model.subMenuTriggered(item["name"], text)
                            return True
        note("menu missing", prefix=prefix)
        return False

    def _report(self, name):
        extension = self._extension()
        outcome = extension.lastOutcome()
        note("state", name=name, panel_s=self._panel_s(),
             klipper_s=outcome.total_s if outcome is not None else None,
             cura_s=extension._panel.curaEstimate(0),
             menu=self._menu_texts())

    def _screenshot(self, name):
        path = os.path.join(os.path.dirname(OUT), name + ".png")
        image = self._app.getMainWindow().grabWindow()
        note("screenshot", path=path, ok=bool(image.save(path)))

    def _save(self, name):
        scene = self._app.getController().getScene()
        self._device.requestWrite([scene.getRoot()], os.path.join(os.path.dirname(OUT),
                                                                  name + ".gcode"))

    # The script
    def _message(self, message):
        title = message.getTitle() or ""
        if MODE != "check":
            return
        if title != TITLE:
            # Broken bundled plugins of the distribution fill the message stack: hide them
            # so ours is visible on the screenshots.
            self._app.callLater(message.hide)
            return
        self._messages += 1
        note("message", number=self._messages, text=message.getText())
        self._app.callLater(self._next)

    def _later(self, ms, function):
        QTimer.singleShot(ms, function)

    def _next(self):
        self._step += 1
        step = self._step
        note("step", number=step)
        if step == 1:  # timed with Cura's machine settings
            self._report("machine")
            self._save("machine")
            self._later(2000, lambda: self._screenshot("machine"))
            self._later(2500, self._pick_printer_cfg)
        elif step == 2:  # timed with the printer.cfg picked after a save
            self._report("printer_cfg")
            self._save("printer_cfg")
            self._later(2000, lambda: self._screenshot("printer_cfg"))
            self._later(2500, self._enter_moonraker)
        elif step == 3:  # Moonraker cannot be reached
            self._report("moonraker")
            note("api key stored", stored=self._app.getPreferences().getValue(
                "kestimator/moonraker_api_key") == API_KEY)
            self._later(1500, lambda: self._trigger("Use Cura's machine settings"))
        elif step == 4:  # back to Cura's machine settings
            self._report("machine_again")
            self._later(2500, self._move_cube)
        elif step == 5:  # the scene changed: Cura sliced again, the new slice is timed
            self._report("moved")
            self._later(2500, self._finish)

    def _move_cube(self):
        from UM.Math.Vector import Vector
        from UM.Operations.TranslateOperation import TranslateOperation
        from UM.Scene.Iterator.DepthFirstIterator import DepthFirstIterator
        root = self._app.getController().getScene().getRoot()
        for node in DepthFirstIterator(root):
            if node.callDecoration("isSliceable"):
                TranslateOperation(node, Vector(40, 0, 30)).push()
                note("moved", name=node.getName())
                return

    def _pick_printer_cfg(self):
        self._driver = DialogDriver([PRINTER_CFG])
        self._trigger("Use a Klipper printer.cfg")

    def _enter_moonraker(self):
        self._driver = DialogDriver([MOONRAKER_URL, API_KEY])
        self._trigger("Use Moonraker")

    def _finish(self):
        self._screenshot("final")
        registry = PluginRegistry.getInstance()
        if hasattr(registry, "pluginsEnabledOrDisabledChanged"):
            registry.disablePlugin(PLUGIN)
            self._report("disabled")
        self._app.saveSettings()
        note("done")


def getMetaData():
    return {}


def register(app):
    return {"extension": Helper(app)}
'''


def build_package(out_dir: Path) -> Path:
    """The .curapackage of this checkout (plugins/cura/build.py)."""
    subprocess.run([sys.executable, str(BUILD_SCRIPT), "--out-dir", str(out_dir)],
                   check=True, capture_output=True)
    return next(out_dir.glob("*.curapackage"))


def install_helper(target: CuraTarget, home: Path) -> None:
    helper = target.plugins_folder(home) / "gui_check_helper"
    helper.mkdir(parents=True, exist_ok=True)
    (helper / "plugin.json").write_text(HELPER_JSON)
    (helper / "__init__.py").write_text(HELPER_PY)


def start_cura(target: CuraTarget, home: Path, home_inside: str, mode: str,
               args: list[str], extra: dict[str, str]) -> subprocess.Popen[bytes]:
    env = {"HOME": home_inside, "GUI_CHECK_MODE": mode,
           "GUI_CHECK_OUT": home_inside + "/out/x", "LIBGL_ALWAYS_SOFTWARE": "1",
           "XDG_CONFIG_HOME": home_inside + "/.config",
           "XDG_DATA_HOME": home_inside + "/.local/share",
           "XDG_CACHE_HOME": home_inside + "/.cache", "QT_QPA_PLATFORMTHEME": ""}
    env.update(extra)
    command = target.command(home_inside, env, args)
    outfile = home / "cura-stdout.txt"
    with open(outfile, "a") as output:
        output.write("\n=== %s ===\n" % mode)
        output.flush()
        return subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT,
                                start_new_session=True)


def stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


_NOTE_RE = re.compile(r"gui_check: (.+?) (\{.*\})\s*$")


def notes(text: str) -> list[tuple[str, dict[str, object]]]:
    """The helper's ``gui_check: <what> {json}`` lines, in order (each once)."""
    found: list[tuple[str, dict[str, object]]] = []
    seen: set[str] = set()
    for line in text.splitlines():
        match = _NOTE_RE.search(line)
        if match is None:
            continue
        key = match.group(0)
        if key in seen:  # Cura 5 logs each line to cura.log and to stdout
            continue
        seen.add(key)
        try:
            found.append((match.group(1), json.loads(match.group(2))))
        except ValueError:
            continue
    return found


def wait_backend_port(timeout: float = PORT_WAIT_S) -> None:
    """Wait until Cura's backend port can be bound, as Cura binds it (no SO_REUSEADDR).

    A Cura that was just stopped (the seed run, the other Cura's test) leaves the port in
    TIME_WAIT for up to a minute; the next Cura then moves to the next port through its
    socket-error path, a path the Cura 5 run stalled on once in CI. Waiting keeps every run
    on the ordinary start-up path."""
    deadline = time.monotonic() + timeout
    while True:
        probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            probe.bind(("127.0.0.1", CURA_BACKEND_PORT))
            return
        except OSError:
            if time.monotonic() >= deadline:
                print("NOTE: port %d still busy after %.0f s; Cura will pick the next one"
                      % (CURA_BACKEND_PORT, timeout), flush=True)
                return
        finally:
            probe.close()
        time.sleep(0.5)


def log_tail(target: CuraTarget, home: Path, lines: int = 40, width: int = 240) -> str:
    """The end of Cura's own log (cura.log is written line by line; its stdout is
    block-buffered and cut mid-line when Cura is killed), each line shortened."""
    log = home / ".local/share/cura" / target.config_folder / "cura.log"
    text = log.read_text(errors="replace") if log.is_file() else target.log_text(home)
    return "\n".join("  " + line[:width] for line in text.splitlines()[-lines:])


def wait_for(target: CuraTarget, home: Path, what: str, timeout: float,
             proc: subprocess.Popen[bytes]) -> list[tuple[str, dict[str, object]]]:
    """Wait until the helper noted ``what``; all its notes so far (empty on timeout)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = notes(target.log_text(home))
        if any(name == what for name, _ in found):
            return found
        if proc.poll() is not None:
            return []
        time.sleep(0.5)
    return []


def _helper_started(target: CuraTarget, home: Path) -> bool:
    return any(name == "started" and values.get("mode") == "check"
               for name, values in notes(target.log_text(home)))


def _state(found: list[tuple[str, dict[str, object]]], name: str) -> dict[str, object]:
    for what, values in found:
        if what == "state" and values.get("name") == name:
            return values
    return {}


def _first_menu(state: dict[str, object]) -> list[str]:
    """Our submenu's texts in the first Extensions-menu model found ([] if none)."""
    menus = state.get("menu")
    if isinstance(menus, list) and menus and isinstance(menus[0], list):
        return [str(x) for x in menus[0]]
    return []


def _messages(found: list[tuple[str, dict[str, object]]]) -> list[str]:
    return [str(values["text"]) for what, values in found if what == "message"]


def run(target: CuraTarget, printer_cfg: Path, keep: Path | None) -> int:
    """All steps against ``target``; 0 if all pass."""
    missing = [p for p in ("xvfb-run", "cura", "CuraEngine")
               if not (shutil.which(p) if target.root is None
                       else target.host_path("/usr/bin/" + p).exists())]
    if missing:
        print("FAIL: missing %s" % ", ".join(missing))
        return 2
    home, home_inside = target.make_home()
    results: list[tuple[str, bool]] = []

    def step(name: str, ok: bool, evidence: object) -> bool:
        results.append((name, ok))
        print("%s: %s -- %s" % ("PASS" if ok else "FAIL", name, str(evidence)[:400]),
              flush=True)
        return ok

    try:
        out = home / "out"
        out.mkdir()
        package = build_package(home / "dist")
        install_helper(target, home)
        shutil.copyfile(printer_cfg, home / "printer.cfg")
        write_cube_stl(home / "cube.stl", 20.0)
        extra = {"GUI_CHECK_PACKAGE": "%s/dist/%s" % (home_inside, package.name),
                 "GUI_CHECK_PRINTER_CFG": home_inside + "/printer.cfg",
                 "GUI_CHECK_MOONRAKER_URL": MOONRAKER_URL, "GUI_CHECK_API_KEY": API_KEY}
        with target.mounted():
            wait_backend_port()
            seed = start_cura(target, home, home_inside, "seed", [], extra)
            try:
                found = wait_for(target, home, "seeded", SEED_TIMEOUT_S, seed)
                try:
                    seed.wait(30)
                except subprocess.TimeoutExpired:
                    pass
            finally:
                stop(seed)
            scheduled = [v for n, v in found if n == "package scheduled"]
            if not step("seed: printer added, package handed to Cura's package manager",
                        bool(scheduled) and scheduled[0].get("package_id") == "kestimator_cura",
                        scheduled):
                return 1
            log = home / ".local/share/cura" / target.config_folder / "cura.log"
            if log.is_file():
                log.rename(log.with_name("cura-seed.log"))
            for attempt in (1, 2):
                wait_backend_port()
                cura = start_cura(target, home, home_inside, "check",
                                  [home_inside + "/cube.stl"], extra)
                try:
                    found = wait_for(target, home, "done", STEP_TIMEOUT_S, cura)
                    time.sleep(1)
                    found = found and notes(target.log_text(home))
                finally:
                    stop(cura)
                if found or attempt == 2:
                    break
                # Cura died or stalled before the script's end. Seen rarely, on loaded
                # machines, with no kestimator error: a crash in Cura 4.13's startup
                # threads, and Cura 5 going silent right after starting CuraEngine (its
                # Backend's socket close can deadlock, as its own source notes). Once more,
                # from the same seeded home; a failure the plugin causes happens again and
                # fails, with both logs kept.
                print("NOTE: Cura %s before the end (attempt 1); once more. Its last log "
                      "lines:\n%s" % ("stalled" if _helper_started(target, home) else "exited",
                                      log_tail(target, home)), flush=True)
                if log.is_file():
                    log.rename(log.with_name("cura-attempt1.log"))
                shutil.move(str(home / "cura-stdout.txt"), str(home / "cura-attempt1.txt"))
        text = target.log_text(home)
        installed = target.plugins_folder(home) / "kestimator_cura" / "kestimator_cura"
        step("Cura's package manager installed the package", (installed / "plugin.json")
             .is_file() and (installed / "vendor" / "kestimator").is_dir(), installed)
        step("plugin loaded by Cura", "Loaded plugin kestimator_cura" in text,
             [x for x in text.splitlines() if "Loaded plugin kestimator_cura" in x][:1])
        started = [v for n, v in notes(text) if n == "started" and v.get("mode") == "check"]
        step("Cura started with the printer and the Qt binding expected",
             bool(started) and started[0].get("machine") is True, started)
        if not found:
            print("Cura's last log lines:\n" + log_tail(target, home), flush=True)
        step("helper ran to the end", bool(found), "" if found else "see the log lines above")
        messages = _messages(found)
        step("kestimator's message after the background job (CuraEngine slice)",
             bool(messages) and messages[0].startswith("Klipper print time: "), messages[:1])
        step("the message keeps Cura's estimate for comparison",
             bool(messages) and "Cura estimated " in messages[0], messages[:1])
        machine = _state(found, "machine")
        klipper_s = machine.get("klipper_s")
        step("Cura's print-information panel shows Klipper's time",
             isinstance(klipper_s, float) and machine.get("panel_s") == round(klipper_s)
             and klipper_s != machine.get("cura_s"),
             machine)
        saved = (out / "machine.gcode").read_text(errors="replace") \
            if (out / "machine.gcode").is_file() else ""
        lines = saved.splitlines()
        marker = [x for x in lines if x.startswith("; kestimator")]
        m73 = [x for x in lines if x.startswith("M73 ")]
        time_line = [x for x in lines if x.startswith(";TIME:")]
        step("saved through Cura's GCodeWriter: marker, M73 lines, Klipper's ;TIME:",
             bool(marker) and len(m73) > 10 and isinstance(klipper_s, float)
             and time_line[:1] == [";TIME:%d" % round(klipper_s)],
             (marker[:1], len(m73), time_line[:1]))
        dialogs = [v for n, v in found if n == "dialog"]
        step("printer.cfg picked in the plugin's QFileDialog",
             any(d.get("kind") == "QFileDialog" for d in dialogs), dialogs)
        cfg = _state(found, "printer_cfg")
        step("after a save, a new limits source is timed again (message, panel)",
             len(messages) >= 2 and "printer.cfg" in messages[1]
             and cfg.get("klipper_s") != klipper_s
             and isinstance(cfg.get("klipper_s"), float)
             and cfg.get("panel_s") == round(cfg["klipper_s"]),  # type: ignore[arg-type]
             (messages[1:2], cfg))
        cfg_saved = (out / "printer_cfg.gcode").read_text(errors="replace") \
            if (out / "printer_cfg.gcode").is_file() else ""
        cfg_marker = [x for x in cfg_saved.splitlines() if x.startswith("; kestimator")]
        step("the next save carries the new times",
             bool(cfg_marker) and "printer.cfg" in cfg_marker[0]
             and ";TIME:%d" % round(float(cfg.get("klipper_s") or 0)) in cfg_saved,
             cfg_marker[:1])
        menu = _first_menu(cfg)
        step("the Extensions menu names and ticks the active source",
             bool(menu) and menu[0].startswith("Limits now: printer.cfg")
             and "\u2713 Use a Klipper printer.cfg..." in menu, cfg.get("menu"))
        step("Moonraker URL and API key entered in the plugin's dialogs (key as a password)",
             [d.get("password") for d in dialogs if d.get("kind") == "QInputDialog"]
             == [False, True], dialogs)
        stored = [v for n, v in found if n == "api key stored"]
        step("the API key is kept in Cura's preferences",
             bool(stored) and stored[0].get("stored") is True, stored)
        step("the API key appears in no log", API_KEY not in text.replace(
            '"GUI_CHECK_API_KEY": "%s"' % API_KEY, ""), "")
        moon = _state(found, "moonraker")
        cura_s = machine.get("cura_s")
        step("Moonraker unreachable: the message says so, Cura's own time is back",
             len(messages) >= 3 and messages[2].startswith("No Klipper print time")
             and isinstance(cura_s, float) and moon.get("panel_s") == round(cura_s)
             and cura_s != klipper_s, (messages[2:3], moon))
        again = _state(found, "machine_again")
        step("back to Cura's machine settings through the menu",
             again.get("panel_s") == machine.get("panel_s")
             and "\u2713 Use Cura's machine settings" in _first_menu(again), again)
        moved = _state(found, "moved")
        step("the scene changed: Cura sliced again and the new slice's time is in the panel",
             len(messages) >= 5 and isinstance(moved.get("klipper_s"), float)
             and moved.get("panel_s") == round(moved["klipper_s"]),  # type: ignore[arg-type]
             (messages[4:5], moved))
        disabled = _state(found, "disabled")
        if disabled:
            moved_cura = moved.get("cura_s")
            step("disabling the plugin puts Cura's time back in the panel",
                 isinstance(moved_cura, float) and disabled.get("panel_s") == round(moved_cura)
                 and moved_cura != moved.get("klipper_s"), disabled)
        for name in ("machine", "final"):
            print("INFO: screenshot %s -- %s" % (name, out / (name + ".png")))
        errors = [x for x in text.splitlines()
                  if "kestimator" in x and ("ERROR" in x or "Traceback" in x)]
        step("no kestimator errors logged", not errors, errors[:3])
    finally:
        if keep is not None:
            keep.mkdir(parents=True, exist_ok=True)
            for path in sorted(home.rglob("*")):
                if path.is_file() and (path.suffix in (".png", ".gcode", ".log", ".txt")
                                       or path.name == "cura.cfg"):
                    shutil.copy2(path, keep / path.name)
        shutil.rmtree(home, ignore_errors=True)
    failed = [name for name, ok in results if not ok]
    print("RESULT: %s" % ("PASS" if not failed else "FAIL (%s)" % ", ".join(failed)))
    return 0 if not failed else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cura", choices=("4.13", "5.0"), default="4.13")
    parser.add_argument("--root", type=Path, help="the chroot of .ci/cura5-chroot (5.0)")
    parser.add_argument("--printer-cfg", type=Path,
                        default=PROJECT.parent / "shared" / "corpus" / "printer.cfg")
    parser.add_argument("--keep", type=Path, help="copy logs, saves, screenshots to DIR")
    args = parser.parse_args(argv)
    if args.cura == "5.0" and args.root is None:
        parser.error("--cura 5.0 needs --root (a chroot made by .ci/cura5-chroot)")
    target = CuraTarget(args.cura, args.root.resolve() if args.root else None)
    return run(target, args.printer_cfg, args.keep)


if __name__ == "__main__":
    sys.exit(main())
