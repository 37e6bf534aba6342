"""Which Qt binding the plugin talks to: the one the running Cura uses; no Cura import.

Owns the choice between PyQt6 (Cura 5) and PyQt5 (Cura 4). Both can be installed at once
(Debian: python3-pyqt6 beside Cura 4.13's python3-pyqt5); a widget made with the binding
Cura does not run has no QApplication and Qt aborts the whole process.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Mapping
from types import ModuleType
from typing import Any

QT_BINDINGS = ("PyQt6", "PyQt5")
"""Cura 5 runs PyQt6, Cura 4 PyQt5; a system may have both installed (Debian: python3-pyqt6
beside Cura 4.13's python3-pyqt5)."""


def qt_binding_name(modules: Mapping[str, Any] | None = None) -> str:
    """The Qt binding this Cura runs: the one whose QtCore is loaded and has the application
    object; else the one loaded; else the first importable (no Cura: tests only).

    Importing a binding merely because it is installed is wrong: in a PyQt5 Cura, a PyQt6
    widget has no QApplication of its own and Qt aborts the process.
    """
    loaded = sys.modules if modules is None else modules
    present = [name for name in QT_BINDINGS if loaded.get(name + ".QtCore") is not None]
    for name in present:
        application = getattr(loaded[name + ".QtCore"], "QCoreApplication", None)
        if application is not None and application.instance() is not None:
            return name
    if present:
        return present[0]
    for name in QT_BINDINGS:
        try:
            importlib.import_module(name + ".QtCore")
        except ImportError:
            continue
        return name
    raise ImportError("no Qt binding (PyQt6 or PyQt5) can be imported")


def qt_module(name: str) -> ModuleType:
    """``QtWidgets``, ``QtCore``... of the binding `qt_binding_name` picks."""
    return importlib.import_module("%s.%s" % (qt_binding_name(), name))
