"""kestimator for Cura: Klipper's own print time in Cura and in every saved G-code file.

Owns the plugin's entry points Uranium calls (``getMetaData``, ``register``). The plugin id
(``kestimator_cura``, the folder's name) differs from the core's import name ``kestimator``,
which the built package vendors under ``vendor/`` (see ``vendoring.py``). This file imports
nothing of Cura or of the core at module level and stays readable by old Pythons, so a Cura
whose Python is too old gets a menu entry that says so instead of a broken plugin.
"""

from __future__ import annotations

import sys
from typing import Any

from .vendoring import use_vendored_core

use_vendored_core()

MIN_PYTHON = (3, 9)
"""The core's own minimum (Cura 5 bundles 3.10 or newer; Cura 4.13's own builds bundle 3.8)."""


def getMetaData() -> dict[str, Any]:
    """Uranium reads the rest of the metadata from plugin.json."""
    return {}


def register(app: Any) -> dict[str, Any]:
    """Uranium's entry point: the one extension this plugin provides."""
    if sys.version_info < MIN_PYTHON:
        from UM.Extension import Extension
        from UM.Message import Message

        needs = "kestimator needs Python %d.%d or newer; this Cura runs Python %d.%d." % (
            MIN_PYTHON + sys.version_info[:2])
        placeholder = Extension()
        placeholder.setMenuName("Klipper print time")
        placeholder.addMenuItem("Why is it off?",
                                lambda: Message(text=needs, title="kestimator").show())
        return {"extension": placeholder}
    from .extension import KestimatorExtension

    return {"extension": KestimatorExtension(app)}
