"""The Cura-facing layer: menu, preferences, background job, message, and the save hook.

Owns only how Cura (Uranium) calls the plugin; everything it computes is in the Cura-free
modules (`klipper_time`, `chunks`, `machine`). The flow:

1. When the backend reports ``BackendState.Done`` the extension waits for the next event
   loop tick (``callLater``: the backend is still filling in ``{print_time}`` and the like
   in the same call), takes a snapshot of ``scene.gcode_dict[active plate]`` and the machine
   settings, and starts a ``Job``: limits, estimate and rewrite run on a worker thread, so
   Cura's UI never waits on them (a Moonraker request included).
2. The job's ``finished`` signal comes back on the GUI thread (Uranium queues an ``Auto``
   signal emitted off the main thread); the Klipper time is shown in a ``Message``.
3. ``OutputDeviceManager.writeStarted`` runs the save hook. It is connected when
   ``pluginsLoaded`` fires, after every plugin's ``__init__`` connected its own handlers, so
   it runs after the bundled PostProcessingPlugin's scripts (Uranium calls a signal's
   handlers in the order they were connected). The list is rewritten in place, keeping its
   shape; if the chunks are not those the job timed (a script changed them, or the job has
   not finished), the work is done there and then. Chunks that already carry kestimator's
   marker are left alone, so nothing is processed twice.
"""

from __future__ import annotations

import os
from typing import Any

from UM.Backend.Backend import BackendState
from UM.Extension import Extension
from UM.Job import Job
from UM.Logger import Logger
from UM.Message import Message

from kestimator.errors import KestimatorError

from .chunks import is_processed, same_chunks
from .klipper_time import Outcome, compute
from .machine import (
    EXTRUDER_KEYS,
    MACHINE_KEYS,
    SOURCE_MACHINE,
    SOURCE_MOONRAKER,
    SOURCE_PRINTER_CFG,
    LimitsChoice,
)

PREFERENCE_SOURCE = "kestimator/limits_source"
PREFERENCE_PRINTER_CFG = "kestimator/printer_cfg"
PREFERENCE_MOONRAKER_URL = "kestimator/moonraker_url"
MENU_NAME = "Klipper print time"
MESSAGE_TITLE = "Klipper print time (kestimator)"
MESSAGE_LIFETIME_S = 0
"""0: the message stays until the user closes it or the next slice replaces it."""
MENU_USE_MACHINE = "Use Cura's machine settings"
MENU_USE_PRINTER_CFG = "Use a Klipper printer.cfg..."
MENU_USE_MOONRAKER = "Use Moonraker..."
MENU_SHOW = "Show the Klipper print time"


def _qt_widgets() -> Any:
    """QtWidgets of the Qt binding this Cura runs (PyQt6 from Cura 5, PyQt5 before)."""
    try:
        from PyQt6 import QtWidgets
    except ImportError:
        from PyQt5 import QtWidgets
    return QtWidgets


class KlipperTimeJob(Job):
    """Computes one slice's Klipper time and rewritten chunks on a worker thread."""

    def __init__(self, chunks: list[str], choice: LimitsChoice,
                 settings: dict[str, object], generation: int) -> None:
        super().__init__()
        self.chunks = tuple(chunks)
        self.choice = choice
        self.settings = settings
        self.generation = generation

    def run(self) -> None:
        """Job entry point (worker thread): sets the Outcome, or the KestimatorError."""
        try:
            self.setResult(compute(self.chunks, self.choice, self.settings))
        except KestimatorError as exc:
            self.setError(exc)


class KestimatorExtension(Extension):
    """The plugin object Cura registers: one per application."""

    def __init__(self, application: Any) -> None:
        super().__init__()
        self._application = application
        self._outcome: Outcome | None = None
        # The chunks the last job failed on and why: a save of the same chunks does not
        # try again (a Moonraker that is offline would make Cura wait once more).
        self._failure: tuple[tuple[str, ...], str] | None = None
        self._generation = 0
        self._message: Message | None = None
        self._connected = False
        self._jobs: list[KlipperTimeJob] = []
        preferences = application.getPreferences()
        preferences.addPreference(PREFERENCE_SOURCE, SOURCE_MACHINE)
        preferences.addPreference(PREFERENCE_PRINTER_CFG, "")
        preferences.addPreference(PREFERENCE_MOONRAKER_URL, "")
        self.setMenuName(MENU_NAME)
        self.addMenuItem(MENU_USE_MACHINE, self.useMachineSettings)
        self.addMenuItem(MENU_USE_PRINTER_CFG, self.askPrinterCfg)
        self.addMenuItem(MENU_USE_MOONRAKER, self.askMoonraker)
        self.addMenuItem(MENU_SHOW, self.showLastTime)
        plugins_loaded = getattr(application, "pluginsLoaded", None)
        if plugins_loaded is None:
            self.connectSignals()
        else:
            plugins_loaded.connect(self.connectSignals)

    # Wiring
    def connectSignals(self) -> None:
        """Hook the save and the end of slicing (once every plugin has been loaded)."""
        if self._connected:
            return
        self._connected = True
        self._application.getOutputDeviceManager().writeStarted.connect(self._onWriteStarted)
        backend = self._application.getBackend()
        if backend is not None:
            backend.backendStateChange.connect(self._onBackendStateChange)

    def _currentChunks(self) -> list[str] | None:
        scene = self._application.getController().getScene()
        gcode_dict = getattr(scene, "gcode_dict", None)
        if not gcode_dict:
            return None
        plate = self._application.getMultiBuildPlateModel().activeBuildPlate
        chunks = gcode_dict.get(plate)
        return chunks if chunks else None

    def _machineSettings(self) -> dict[str, object]:
        stack = self._application.getGlobalContainerStack()
        if stack is None:
            return {}
        values = {key: stack.getProperty(key, "value") for key in MACHINE_KEYS}
        extruders = getattr(stack, "extruderList", None) or [stack]
        values.update({key: extruders[0].getProperty(key, "value") for key in EXTRUDER_KEYS})
        return values

    def limitsChoice(self) -> LimitsChoice:
        """The limit source the preferences name (Cura's machine if they are unusable)."""
        preferences = self._application.getPreferences()
        source = str(preferences.getValue(PREFERENCE_SOURCE) or SOURCE_MACHINE)
        try:
            return LimitsChoice(source=source,
                                printer_cfg=str(preferences.getValue(PREFERENCE_PRINTER_CFG)
                                                or ""),
                                moonraker_url=str(preferences.getValue(PREFERENCE_MOONRAKER_URL)
                                                  or ""))
        except ValueError:
            Logger.log("w", "kestimator: unknown limits source %r, using Cura's machine", source)
            return LimitsChoice()

    # Slicing finished: time it in the background
    def _onBackendStateChange(self, state: Any) -> None:
        if state == BackendState.Done:
            self._application.callLater(self.startJob)
        elif state in (BackendState.NotStarted, BackendState.Processing):
            self._generation += 1  # results still on their way are for the old G-code
            self._outcome = None
            self._failure = None
            self._hideMessage()

    def startJob(self) -> KlipperTimeJob | None:
        """Time the current slice on a worker thread; the job, or None if nothing to do."""
        chunks = self._currentChunks()
        if chunks is None or is_processed(chunks):
            return None
        self._generation += 1
        job = KlipperTimeJob(chunks, self.limitsChoice(), self._machineSettings(),
                             self._generation)
        job.finished.connect(self._onJobFinished)
        self._jobs.append(job)  # Uranium's signals hold weak references only
        job.start()
        return job

    def _onJobFinished(self, job: KlipperTimeJob) -> None:
        if job in self._jobs:
            self._jobs.remove(job)
        if job.generation != self._generation:
            return
        error = job.getError()
        if error is not None:
            self._failure = (job.chunks, str(error))
            self._show("No Klipper print time: %s" % error, warning=True)
            return
        self._failure = None
        self._outcome = job.getResult()
        self.showLastTime()

    # Saving
    def _onWriteStarted(self, output_device: Any = None) -> None:
        try:
            self.processForSave()
        except KestimatorError as exc:
            self._show("The G-code was saved without Klipper's times: %s" % exc, warning=True)
        except Exception:  # a plugin bug must never stop Cura from saving
            Logger.logException("e", "kestimator: could not add Klipper's times")

    def processForSave(self) -> bool:
        """Rewrite the active plate's chunks in place; True if they were rewritten."""
        chunks = self._currentChunks()
        if chunks is None:
            return False
        if is_processed(chunks):
            Logger.log("d", "kestimator: the G-code already has Klipper's times")
            return False
        failure = self._failure
        if failure is not None and same_chunks(chunks, failure[0]):
            raise KestimatorError(failure[1])
        outcome = self._outcome
        if outcome is None or not outcome.matches(chunks):
            Logger.log("i", "kestimator: the G-code changed since slicing (post-processing "
                            "scripts?) or was not timed yet: timing it now")
            outcome = compute(chunks, self.limitsChoice(), self._machineSettings())
            self._outcome = outcome
        outcome.apply_to(chunks)
        return True

    # Preferences (Extensions menu)
    def _setChoice(self, source: str, key: str | None = None, value: str = "") -> None:
        preferences = self._application.getPreferences()
        if key is not None:
            preferences.setValue(key, value)
        preferences.setValue(PREFERENCE_SOURCE, source)
        self._outcome = None
        self._failure = None
        self.startJob()

    def useMachineSettings(self) -> None:
        """Menu: time with Cura's machine settings."""
        self._setChoice(SOURCE_MACHINE)

    def askPrinterCfg(self) -> None:
        """Menu: pick a Klipper printer.cfg."""
        widgets = _qt_widgets()
        current = str(self._application.getPreferences().getValue(PREFERENCE_PRINTER_CFG)
                      or "")
        path, _ = widgets.QFileDialog.getOpenFileName(
            None, "Klipper printer.cfg", os.path.dirname(current) if current else "",
            "Klipper config (*.cfg);;All files (*)")
        if path:
            self._setChoice(SOURCE_PRINTER_CFG, PREFERENCE_PRINTER_CFG, path)

    def askMoonraker(self) -> None:
        """Menu: give the printer's Moonraker URL."""
        widgets = _qt_widgets()
        current = str(self._application.getPreferences().getValue(PREFERENCE_MOONRAKER_URL)
                      or "")
        url, ok = widgets.QInputDialog.getText(
            None, "Moonraker", "Moonraker URL (e.g. http://printer.local):",
            widgets.QLineEdit.EchoMode.Normal, current)
        if ok and url.strip():
            self._setChoice(SOURCE_MOONRAKER, PREFERENCE_MOONRAKER_URL, url.strip())

    # Messages
    def showLastTime(self) -> None:
        """Menu, and the end of a job: show the last Klipper time."""
        if self._outcome is None:
            self._show("Slice a model first; its Klipper print time shows here. Limits: %s."
                       % self.limitsChoice().description)
        else:
            self._show(self._outcome.summary())

    def lastOutcome(self) -> Outcome | None:
        """The last computed result (None before the first slice is timed)."""
        return self._outcome

    def _hideMessage(self) -> None:
        if self._message is not None:
            self._message.hide()
            self._message = None

    def _show(self, text: str, warning: bool = False) -> None:
        self._hideMessage()
        options: dict[str, Any] = {}
        message_type = getattr(Message, "MessageType", None)
        if warning and message_type is not None:
            options["message_type"] = message_type.WARNING
        self._message = Message(text=text, title=MESSAGE_TITLE, lifetime=MESSAGE_LIFETIME_S,
                                **options)
        self._message.show()

