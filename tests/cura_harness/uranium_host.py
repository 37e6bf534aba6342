"""Drive the plugin inside Debian's real Uranium/Cura 4.13 modules, without a display.

Owns the host side of ``tests/test_cura_real_modules.py``: run with Debian's
``/usr/bin/python3`` (where ``python3-uranium`` and ``cura`` install ``UM`` and ``cura``), it
builds an application on Uranium's real ``UM.Application.Application`` (with an event queue
standing in for Qt's event loop), loads the bundled PostProcessingPlugin and this plugin
through Uranium's real ``PluginRegistry`` (plugin.json, SDK check, ``register``), then plays
what Cura does: slicing finishes (``backendStateChange(Done)``), the event loop runs (the
plugin's ``Job`` runs on ``JobQueue``'s worker thread and its result comes back as a queued
signal), and the user saves (``writeStarted``, after which Cura's GCodeWriter joins the
list). The scene, backend, build-plate model and global stack are stand-ins: a real
``CuraApplication`` needs a display and OpenGL. Prints one JSON object on stdout.

Usage: uranium_host.py PLUGIN_PARENT_DIR GCODE OUT_DIR PRINTER_CFG [CORE_PARENT_DIR]
"""

# Cura's and Uranium's attribute names (backendStateChange, activeBuildPlate, ...) are
# mixedCase: the stand-ins must use them as they are.
# ruff: noqa: N815

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from UM.Application import Application
from UM.Backend.Backend import BackendState
from UM.JobQueue import JobQueue
from UM.OutputDevice.OutputDeviceManager import OutputDeviceManager
from UM.PluginRegistry import PluginRegistry
from UM.Preferences import Preferences
from UM.Signal import Signal

CURA_PLUGINS = "/usr/lib/cura/plugins"
CURA_DEFINITIONS = Path("/usr/share/cura/resources/definitions")
MACHINE_DEFINITION = "creality_ender3"
JOB_TIMEOUT_S = 60.0
PAUSE_SCRIPT_LINE = "G4 P1000 ;added by a post-processing script\n"


class Stack:
    """Stand-in global stack: getProperty(key, "value") from a machine definition's
    defaults (the definition's overrides over fdmprinter's, as Cura resolves them when the
    user changed nothing and no formula applies)."""

    metaDataChanged = Signal()  # PostProcessingPlugin listens to it

    def __init__(self, machine: str) -> None:
        self.values: dict[str, Any] = {}
        self._load("fdmprinter")
        self._load(machine)

    def _load(self, name: str) -> None:
        document = json.loads((CURA_DEFINITIONS / (name + ".def.json")).read_text())
        parent = document.get("inherits")
        if parent and parent != "fdmprinter" and name != "fdmprinter":
            self._load(parent)
        self._collect(document.get("settings", {}))
        for key, override in document.get("overrides", {}).items():
            if "default_value" in override:
                self.values[key] = override["default_value"]

    def _collect(self, settings: dict[str, Any]) -> None:
        for key, setting in settings.items():
            if "default_value" in setting:
                self.values[key] = setting["default_value"]
            self._collect(setting.get("children", {}))

    def getProperty(self, key: str, prop: str) -> Any:
        return self.values.get(key) if prop == "value" else None


class Scene:
    def __init__(self) -> None:
        self.gcode_dict: dict[int, list[str]] = {}


class Controller:
    def __init__(self) -> None:
        self.scene = Scene()

    def getScene(self) -> Scene:
        return self.scene


class Backend:
    backendStateChange = Signal()
    printDurationMessage = Signal()  # CuraEngineBackend's; PrintInformation listens to it


ENGINE_TIMES = {"inset_0": 300.0, "infill": 200.0, "travel": 100.0, "none": 0.0}
"""What the engine reports per feature for the slice (a stand-in: any positive split)."""
ENGINE_AMOUNTS = [1234.5]


class BuildPlates:
    activeBuildPlate = 0


class Device:
    def getId(self) -> str:
        return "local_file"


class Host(Application):
    """Uranium's Application with a plain event queue instead of Qt's event loop."""

    pluginsLoaded = Signal()  # QtApplication's signal, emitted after all plugins loaded
    mainWindowChanged = Signal()  # CuraApplication's; PostProcessingPlugin listens to it

    def __init__(self) -> None:
        super().__init__(name="cura", version="4.13.0", api_version="7.9.0")
        Signal._app = self  # what Application.initialize() does first: signals use it
        Signal._signalQueue = self
        self._events: deque[Any] = deque()
        self._lock = threading.Lock()
        self._preferences = Preferences()
        self._job_queue = JobQueue()  # as QtApplication.initialize() creates it
        self._output_device_manager = OutputDeviceManager()
        self._controller = Controller()
        self._backend = Backend()
        self._plates = BuildPlates()
        self._stack = Stack(MACHINE_DEFINITION)
        self.shown: list[str] = []
        self.showMessageSignal.connect(self.showMessage)  # as QtApplication wires them
        self.hideMessageSignal.connect(self.hideMessage)
        self._plugin_registry = PluginRegistry(self)
        self._plugin_registry.addType("extension", self.addExtension)  # as QtApplication does

    def functionEvent(self, event: Any) -> None:
        with self._lock:
            self._events.append(event)

    def runEvents(self) -> int:
        ran = 0
        while True:
            with self._lock:
                if not self._events:
                    return ran
                event = self._events.popleft()
            event.call()
            ran += 1

    def showMessage(self, message: Any) -> None:
        self.shown.append(message.getText())

    def hideMessage(self, message: Any) -> None:
        pass

    def getGlobalContainerStack(self) -> Stack:
        return self._stack

    def getMultiBuildPlateModel(self) -> BuildPlates:
        return self._plates

    def getBackend(self) -> Backend:
        return self._backend

    def getController(self) -> Controller:
        return self._controller

    def getPluginRegistry(self) -> PluginRegistry:
        return self._plugin_registry


class PanelRecorder:
    """What Cura's PrintInformation receives from printDurationMessage."""

    def __init__(self) -> None:
        self.seen: list[tuple[int, dict[str, float], list[float]]] = []

    def record(self, plate: int, times: dict[str, float], amounts: list[float]) -> None:
        self.seen.append((plate, dict(times), list(amounts)))


class PauseScript:
    """What a post-processing script does: returns the list with a dwell added to layer 1."""

    def execute(self, data: list[str]) -> list[str]:
        data[3] = data[3] + PAUSE_SCRIPT_LINE
        return data


def split_chunks(text: str) -> list[str]:
    from kestimator_cura.chunks import split_like_cura

    return split_like_cura(text)


def slice_done_and_wait(host: Host, extension: Any) -> Any:
    """Slicing finished: run the event loop until the plugin's job has reported."""
    before = len(host.shown)
    host.getBackend().backendStateChange.emit(BackendState.Processing)
    host.getBackend().printDurationMessage.emit(0, dict(ENGINE_TIMES), list(ENGINE_AMOUNTS))
    host.getBackend().backendStateChange.emit(BackendState.Done)
    return wait_for_message(host, extension, before)


def wait_for_message(host: Host, extension: Any, before: int) -> Any:
    """Run the event loop until the plugin shows a message (its job reported)."""
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while len(host.shown) == before:
        if time.monotonic() > deadline:
            raise SystemExit("the plugin's job did not report within %s s" % JOB_TIMEOUT_S)
        host.runEvents()
        time.sleep(0.01)
    return extension.lastOutcome()


def save(host: Host, path: Path) -> None:
    """writeStarted, then what GCodeWriter writes: the list's chunks, joined."""
    host.getOutputDeviceManager().writeStarted.emit(Device())
    chunks = host.getController().getScene().gcode_dict[0]
    path.write_text("".join(chunks), encoding="utf-8", newline="")


def main(argv: list[str]) -> int:
    plugin_parent, gcode, out_dir, printer_cfg = argv[1:5]
    if len(argv) > 5:
        sys.path.insert(0, argv[5])  # a source checkout: the core is not vendored there
    out = Path(out_dir)
    host = Host()
    registry = host.getPluginRegistry()
    registry.addPluginLocation(CURA_PLUGINS)
    registry.addPluginLocation(plugin_parent)
    registry.loadPlugin("PostProcessingPlugin")
    registry.loadPlugin("kestimator_cura")
    host.pluginsLoaded.emit()
    extension = registry.getPluginObject("kestimator_cura")
    recorder = PanelRecorder()  # Uranium's signals hold weak references: keep it here
    host.getBackend().printDurationMessage.connect(recorder.record)
    panel = recorder.seen
    post_processing = registry.getPluginObject("PostProcessingPlugin")
    import kestimator

    text = Path(gcode).read_text(encoding="utf-8")
    scene = host.getController().getScene()
    preferences = host.getPreferences()
    result: dict[str, Any] = {
        "core_file": kestimator.__file__,
        "extension_class": type(extension).__name__,
        "menu": extension.getMenuItemList(),
        "menu_name": extension.getMenuName(),
        "machine_settings": extension._machineSettings(),
    }

    # 1. Cura's machine settings (the default).
    chunks = split_chunks(text)
    scene.gcode_dict = {0: chunks}
    outcome = slice_done_and_wait(host, extension)
    result["machine"] = {"message": host.shown[-1], "total_s": outcome.total_s,
                         "limits_source": outcome.limits.source}
    result["panel"] = {"last": panel[-1], "engine": panel[0]}
    save(host, out / "machine.gcode")

    # 2. A printer.cfg from the preferences; no post-processing scripts.
    preferences.setValue("kestimator/limits_source", "printer_cfg")
    preferences.setValue("kestimator/printer_cfg", printer_cfg)
    chunks = split_chunks(text)
    scene.gcode_dict = {0: chunks}
    outcome = slice_done_and_wait(host, extension)
    list_before = scene.gcode_dict[0]
    save(host, out / "printer_cfg.gcode")
    result["printer_cfg"] = {
        "message": host.shown[-1], "total_s": outcome.total_s,
        "same_list_object": scene.gcode_dict[0] is list_before,
        "used_background_result": extension.lastOutcome() is outcome,
        "chunk_count": len(scene.gcode_dict[0]),
    }
    first_save = list(scene.gcode_dict[0])
    save(host, out / "printer_cfg_again.gcode")
    result["printer_cfg"]["second_save_unchanged"] = scene.gcode_dict[0] == first_save
    result["menu_printer_cfg"] = extension.getMenuItemList()

    # 2b. After that save, the user switches back to Cura's machine settings (menu): the
    # saved list carries the marker, yet it is timed again and the next save has the new
    # times.
    before = len(host.shown)
    extension.activateMenuItem("Use Cura's machine settings")
    wait_for_message(host, extension, before)
    result["switched"] = {"message": host.shown[-1],
                          "total_s": extension.lastOutcome().total_s,
                          "menu": extension.getMenuItemList(),
                          "panel_total_s": sum(panel[-1][1].values())}
    save(host, out / "switched.gcode")
    preferences.setValue("kestimator/limits_source", "printer_cfg")

    # 3. With a post-processing script: it runs first, the plugin times what it wrote.
    post_processing._script_list = [PauseScript()]
    chunks = split_chunks(text)
    scene.gcode_dict = {0: chunks}
    slice_done_and_wait(host, extension)
    save(host, out / "post_processed.gcode")
    result["post_processed"] = {"total_s": extension.lastOutcome().total_s,
                                "chunk_count": len(scene.gcode_dict[0])}
    post_processing._script_list = []

    # 4. A printer.cfg that is not there: the job reports it, the save keeps Cura's G-code.
    preferences.setValue("kestimator/printer_cfg", str(out / "absent" / "printer.cfg"))
    chunks = split_chunks(text)
    scene.gcode_dict = {0: chunks}
    slice_done_and_wait(host, extension)
    job_message = host.shown[-1]
    save(host, out / "failed.gcode")
    result["failed"] = {"job_message": job_message, "save_message": host.shown[-1]}

    print(json.dumps(result))
    os._exit(0)  # JobQueue's worker threads never end by themselves


if __name__ == "__main__":
    main(sys.argv)
