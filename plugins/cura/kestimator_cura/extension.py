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

import gc
import os
from collections.abc import Mapping
from typing import Any

from UM.Backend.Backend import BackendState
from UM.Extension import Extension
from UM.Job import Job
from UM.Logger import Logger
from UM.Message import Message

from kestimator.api import KestimatorError

from .chunks import is_processed, same_chunks
from .klipper_time import Outcome, compute, klipper_feature_times
from .machine import (
    API_KEY_ENVIRONMENT,
    EXTRUDER_KEYS,
    MACHINE_KEYS,
    SOURCE_MACHINE,
    SOURCE_MOONRAKER,
    SOURCE_PRINTER_CFG,
    LimitsChoice,
)
from .qt import qt_module

PREFERENCE_SOURCE = "kestimator/limits_source"
PREFERENCE_PRINTER_CFG = "kestimator/printer_cfg"
PREFERENCE_MOONRAKER_URL = "kestimator/moonraker_url"
PREFERENCE_MOONRAKER_API_KEY = "kestimator/moonraker_api_key"
"""Stored in cura.cfg like every preference; never logged, never shown (password field)."""
MENU_NAME = "Klipper print time"
MESSAGE_TITLE = "Klipper print time (kestimator)"
MESSAGE_LIFETIME_S = 0
"""0: the message stays until the user closes it or the next slice replaces it."""
MENU_USE_MACHINE = "Use Cura's machine settings"
MENU_USE_PRINTER_CFG = "Use a Klipper printer.cfg..."
MENU_USE_MOONRAKER = "Use Moonraker..."
MENU_SHOW = "Show the Klipper print time"
MENU_ACTIVE = "Limits now: "
"""The first item: the active source, named (clicking it shows the last time)."""
MENU_TICK = "\u2713 "
"""Before the item of the active source."""
MENU_SOURCES = {MENU_USE_MACHINE: SOURCE_MACHINE, MENU_USE_PRINTER_CFG: SOURCE_PRINTER_CFG,
                MENU_USE_MOONRAKER: SOURCE_MOONRAKER}
DIALOG_MOONRAKER_URL = "Moonraker"
DIALOG_MOONRAKER_KEY = "Moonraker API key"


def _qt_widgets() -> Any:
    """QtWidgets of the Qt binding this Cura runs (see `qt_binding_name`)."""
    return qt_module("QtWidgets")


def extension_models() -> list[Any]:
    """The Extensions-menu models (Uranium's ``ExtensionModel``) QML created: in Cura 4 one
    for the menu bar and one for Cura's own use, in Cura 5 one in ``ExtensionMenu.qml``.
    QML parents them differently in each version, so they are looked up among the live
    Python objects rather than in the window's object tree."""
    try:
        from UM.Qt.Bindings.ExtensionModel import ExtensionModel
    except ImportError:
        return []
    return [obj for obj in gc.get_objects() if isinstance(obj, ExtensionModel)]


class KlipperTimeJob(Job):
    """Computes one slice's Klipper time and rewritten chunks on a worker thread."""

    def __init__(self, chunks: list[str], choice: LimitsChoice,
                 settings: dict[str, object], generation: int,
                 environ: Mapping[str, str] | None = None) -> None:
        super().__init__()
        self.chunks = tuple(chunks)
        self.choice = choice
        self.settings = settings
        self.generation = generation
        self.environ = environ

    def run(self) -> None:
        """Job entry point (worker thread): sets the Outcome, or the KestimatorError."""
        try:
            self.setResult(compute(self.chunks, self.choice, self.settings, self.environ))
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
        # (source, rewritten) last written into Cura's list: that list now carries our
        # marker, and a new limit source is timed from the source chunks again.
        self._applied: tuple[tuple[str, ...], tuple[str, ...]] | None = None
        self._generation = 0
        self._message: Message | None = None
        self._connected = False
        self._jobs: list[KlipperTimeJob] = []
        self._panel = PrintInformationPanel(application)
        preferences = application.getPreferences()
        preferences.addPreference(PREFERENCE_SOURCE, SOURCE_MACHINE)
        preferences.addPreference(PREFERENCE_PRINTER_CFG, "")
        preferences.addPreference(PREFERENCE_MOONRAKER_URL, "")
        preferences.addPreference(PREFERENCE_MOONRAKER_API_KEY, "")
        self.setMenuName(MENU_NAME)
        self._menu: list[tuple[str, Any]] = [
            (MENU_ACTIVE, self.showLastTime),
            (MENU_USE_MACHINE, self.useMachineSettings),
            (MENU_USE_PRINTER_CFG, self.askPrinterCfg),
            (MENU_USE_MOONRAKER, self.askMoonraker),
            (MENU_SHOW, self.showLastTime),
        ]
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
            self._panel.connect(backend)
        registry = self._registry()
        changed = getattr(registry, "pluginsEnabledOrDisabledChanged", None)  # Uranium 5
        if changed is not None:
            changed.connect(self._onPluginsEnabledOrDisabled)

    def _registry(self) -> Any:
        getter = getattr(self._application, "getPluginRegistry", None)
        return getter() if getter is not None else None

    def isDisabled(self) -> bool:
        """True once the user disabled the plugin (Cura keeps it loaded until a restart):
        Cura's own times are back in the panel and saves are left as Cura makes them."""
        registry = self._registry()
        plugin_id = self.getPluginId()
        getter = getattr(registry, "getDisabledPlugins", None)
        return bool(plugin_id) and getter is not None and plugin_id in getter()

    def _onPluginsEnabledOrDisabled(self) -> None:
        if self.isDisabled():
            self._panel.restore()
            self._hideMessage()

    def _currentChunks(self) -> list[str] | None:
        scene = self._application.getController().getScene()
        gcode_dict = getattr(scene, "gcode_dict", None)
        if not gcode_dict:
            return None
        plate = self._activePlate()
        chunks = gcode_dict.get(plate)
        return chunks if chunks else None

    def _activePlate(self) -> int:
        return int(self._application.getMultiBuildPlateModel().activeBuildPlate)

    def _sourceChunks(self) -> tuple[list[str], tuple[str, ...]] | None:
        """Cura's live list and the chunks to time: the list itself, or, when it holds what
        our last save wrote into it, the chunks it held before. None when there is nothing
        to time, or the list carries a marker not written here (left alone)."""
        live = self._currentChunks()
        if live is None:
            return None
        applied = self._applied
        if applied is not None and same_chunks(live, applied[1]):
            return live, applied[0]
        if is_processed(live):
            return None
        return live, tuple(live)

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

    def _environ(self) -> dict[str, str]:
        """The process environment, with the API key from the preferences if one is set
        there (it wins over ``MOONRAKER_API_KEY``)."""
        environ = dict(os.environ)
        key = str(self._application.getPreferences().getValue(PREFERENCE_MOONRAKER_API_KEY)
                  or "").strip()
        if key:
            environ[API_KEY_ENVIRONMENT] = key
        return environ

    # Slicing finished: time it in the background
    def _onBackendStateChange(self, state: Any) -> None:
        if state == BackendState.Done:
            self._application.callLater(self.startJob)
        elif state in (BackendState.NotStarted, BackendState.Processing):
            self._generation += 1  # results still on their way are for the old G-code
            self._outcome = None
            self._failure = None
            self._applied = None
            self._panel.forget()  # Cura resets its panel for the new slice itself
            self._hideMessage()

    def startJob(self) -> KlipperTimeJob | None:
        """Time the current slice on a worker thread; the job, or None if nothing to do."""
        if self.isDisabled():
            return None
        found = self._sourceChunks()
        if found is None:
            return None
        self._generation += 1
        job = KlipperTimeJob(list(found[1]), self.limitsChoice(), self._machineSettings(),
                             self._generation, self._environ())
        job.finished.connect(self._onJobFinished)
        self._jobs.append(job)  # Uranium's signals hold weak references only
        job.start()
        return job

    def _onJobFinished(self, job: KlipperTimeJob) -> None:
        if job in self._jobs:
            self._jobs.remove(job)
        if job.generation != self._generation or self.isDisabled():
            return
        error = job.getError()
        if error is not None:
            self._failure = (job.chunks, str(error))
            self._panel.restore()
            self._show("No Klipper print time: %s" % error, warning=True)
            return
        self._failure = None
        self._outcome = job.getResult()
        self._panel.show(self._activePlate(), self._outcome.total_s)
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
        if self.isDisabled():
            return False
        found = self._sourceChunks()
        if found is None:
            if self._currentChunks() is not None:
                Logger.log("d", "kestimator: the G-code already has a kestimator marker")
            return False
        live, source = found
        failure = self._failure
        if failure is not None and same_chunks(source, failure[0]):
            raise KestimatorError(failure[1])
        outcome = self._outcome
        if outcome is None or not outcome.matches(source):
            Logger.log("i", "kestimator: the G-code changed since slicing (post-processing "
                            "scripts?) or was not timed yet: timing it now")
            outcome = compute(source, self.limitsChoice(), self._machineSettings(),
                              self._environ())
            self._outcome = outcome
        if same_chunks(live, outcome.rewritten):
            Logger.log("d", "kestimator: the G-code already has these Klipper times")
            return False
        outcome.apply_to(live, source)
        self._applied = (outcome.source_chunks, outcome.rewritten)
        return True

    # Extensions menu
    def menuLabels(self) -> list[str]:
        """The menu's item texts now: the active source is named and ticked."""
        source = self.limitsChoice().source
        labels = []
        for key, _ in self._menu:
            if key == MENU_ACTIVE:
                labels.append(MENU_ACTIVE + self.limitsChoice().description)
            elif MENU_SOURCES.get(key) == source:
                labels.append(MENU_TICK + key)
            else:
                labels.append(key)
        return labels

    def getMenuItemList(self) -> list[str]:
        """Uranium's ExtensionModel reads the items here (Extension's own list is unused)."""
        return self.menuLabels()

    def activateMenuItem(self, name: str) -> None:
        """Uranium calls this with the text of the item the user clicked."""
        for (key, function), label in zip(self._menu, self.menuLabels(), strict=True):
            if name in (label, key) or (key == MENU_ACTIVE and name.startswith(MENU_ACTIVE)):
                function()
                return
        Logger.log("w", "kestimator: no menu item %r", name)

    def _refreshMenu(self) -> None:
        """Rename the items of the Extensions menus Cura already built: Uranium's
        ExtensionModel reads an extension's items once, into a ListModel per menu, and has
        no way to refresh them. Those models are found among the live objects and their rows
        renamed with ListModel.setProperty (public), the way QML's bindings pick it up."""
        labels = self.menuLabels()
        renamed = 0
        for model in extension_models():
            for item in model.items:
                actions = item.get("actions")
                if item.get("extension") is not self or actions is None:
                    continue
                for row, label in enumerate(labels):
                    if row < actions.count:
                        actions.setProperty(row, "text", label)
                renamed += 1
        Logger.log("d", "kestimator: menu items renamed in %d menu(s)", renamed)

    # Preferences (Extensions menu)
    def _setChoice(self, source: str, key: str | None = None, value: str = "") -> None:
        preferences = self._application.getPreferences()
        if key is not None:
            preferences.setValue(key, value)
        preferences.setValue(PREFERENCE_SOURCE, source)
        self._outcome = None
        self._failure = None
        self._refreshMenu()
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
        """Menu: give the printer's Moonraker URL, then its API key (if it needs one)."""
        widgets = _qt_widgets()
        preferences = self._application.getPreferences()
        current = str(preferences.getValue(PREFERENCE_MOONRAKER_URL) or "")
        url, ok = widgets.QInputDialog.getText(
            None, DIALOG_MOONRAKER_URL, "Moonraker URL (e.g. http://printer.local):",
            widgets.QLineEdit.EchoMode.Normal, current)
        if not ok or not url.strip():
            return
        key = str(preferences.getValue(PREFERENCE_MOONRAKER_API_KEY) or "")
        new_key, ok = widgets.QInputDialog.getText(
            None, DIALOG_MOONRAKER_KEY,
            "Moonraker API key, if Moonraker asks for one (empty: none).\n"
            "Kept in Cura's preferences (cura.cfg).",
            widgets.QLineEdit.EchoMode.Password, key)
        if ok:
            preferences.setValue(PREFERENCE_MOONRAKER_API_KEY, new_key.strip())
        self._setChoice(SOURCE_MOONRAKER, PREFERENCE_MOONRAKER_URL, url.strip())

    # Messages
    def showLastTime(self) -> None:
        """Menu, and the end of a job: show the last Klipper time."""
        if self._outcome is None:
            self._show("Slice a model first; its Klipper print time shows here. Limits: %s."
                       % self.limitsChoice().description)
        else:
            self._show(self._outcome.summary(
                in_panel=self._panel.showing,
                cura_estimate_s=self._panel.curaEstimate(self._activePlate())))

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


class PrintInformationPanel:
    """Klipper's time in Cura's own print-information panel (under the preview, in the save
    dialog), through the backend's ``printDurationMessage`` signal.

    Cura has no API to set the print time. ``CuraEngineBackend.printDurationMessage`` (plate,
    seconds per feature, material amounts) is the public signal Cura's ``PrintInformation``
    takes the time from; this records what the engine sent and emits it again with each
    feature's time scaled so the total is Klipper's (the per-feature tooltip keeps Cura's
    proportions, the material amounts are Cura's). ``restore`` emits Cura's own again. A
    message from the engine after ours (it may come after the slice is done) is recorded as
    Cura's and ours is put back on the next event-loop tick.
    """

    def __init__(self, application: Any) -> None:
        self._application = application
        self._backend: Any = None
        self._emitting = False
        self._cura: dict[int, tuple[dict[str, float], list[float]]] = {}
        self._shown: tuple[int, float] | None = None
        """(plate, Klipper seconds) while the panel shows Klipper's time."""

    def connect(self, backend: Any) -> None:
        """Listen to the engine's durations (call once)."""
        signal = getattr(backend, "printDurationMessage", None)
        if signal is None:
            Logger.log("w", "kestimator: this Cura has no printDurationMessage; Cura's panel "
                            "keeps its own time")
            return
        self._backend = backend
        signal.connect(self._onPrintDuration)

    def _onPrintDuration(self, plate: int | None, times: Mapping[str, float] | None,
                         amounts: Any) -> None:
        # Cura emits (None, {}, []) when the scene changes: never raise into Cura here.
        if self._emitting or plate is None:
            return
        self._cura[int(plate)] = (dict(times or {}), list(amounts or []))
        shown = self._shown
        if shown is not None and shown[0] == int(plate) and times:
            self._application.callLater(self.show, shown[0], shown[1])

    def show(self, plate: int, total_s: float) -> bool:
        """Put Klipper's ``total_s`` into the panel of build plate ``plate``."""
        cura = self._cura.get(plate)
        if self._backend is None or cura is None or not cura[0]:
            return False
        self._emit(plate, klipper_feature_times(cura[0], total_s), cura[1])
        self._shown = (plate, total_s)
        return True

    def restore(self) -> None:
        """Cura's own time back into the panel."""
        shown = self._shown
        self._shown = None
        if shown is not None and shown[0] in self._cura:
            times, amounts = self._cura[shown[0]]
            self._emit(shown[0], dict(times), amounts)

    def curaEstimate(self, plate: int) -> float | None:
        """Cura's own total for ``plate`` as the engine reported it (None if unknown)."""
        cura = self._cura.get(plate)
        if cura is None:
            return None
        total = sum(value for value in cura[0].values() if value == value and value > 0)
        return float(total) if total > 0 else None

    @property
    def showing(self) -> bool:
        """True while the panel shows Klipper's time."""
        return self._shown is not None

    def forget(self) -> None:
        """A new slice is on its way: Cura resets and refills the panel itself."""
        self._shown = None

    def _emit(self, plate: int, times: dict[str, float], amounts: list[float]) -> None:
        self._emitting = True
        try:
            self._backend.printDurationMessage.emit(plate, times, list(amounts))
        finally:
            self._emitting = False
