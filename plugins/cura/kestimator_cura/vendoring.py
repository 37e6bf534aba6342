"""Which kestimator the plugin runs: the copy vendored beside it, never another one.

Owns `use_vendored_core`, called once by the package's ``__init__`` before any module imports
``kestimator``. The built package (``plugins/cura/build.py``) holds the core under
``<plugin>/vendor/kestimator``; the core's own absolute ``kestimator.`` imports must resolve
there even when some other ``kestimator`` is installed in Cura's Python or was imported first,
so the vendored directory goes first on ``sys.path`` and a foreign, already imported
``kestimator`` is dropped from ``sys.modules`` (its users keep their module objects). In a
source checkout there is no ``vendor/`` and the installed core is used.
"""

from __future__ import annotations

import os
import sys

CORE_PACKAGE = "kestimator"
VENDOR_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "vendor")


def _inside(path: str, directory: str) -> bool:
    try:
        return os.path.commonpath([os.path.abspath(path), directory]) == directory
    except ValueError:  # different drives on Windows
        return False


def use_vendored_core(vendor_dir: str = VENDOR_DIR) -> str | None:
    """Make ``import kestimator`` load the copy in ``vendor_dir``; that directory, or None
    when it holds no core (a source checkout, where the installed core is used)."""
    if not os.path.isdir(os.path.join(vendor_dir, CORE_PACKAGE)):
        return None
    loaded = sys.modules.get(CORE_PACKAGE)
    if loaded is not None and not _inside(getattr(loaded, "__file__", None) or "", vendor_dir):
        prefix = CORE_PACKAGE + "."
        for name in [n for n in sys.modules if n == CORE_PACKAGE or n.startswith(prefix)]:
            del sys.modules[name]
    if vendor_dir in sys.path:
        sys.path.remove(vendor_dir)
    sys.path.insert(0, vendor_dir)
    return vendor_dir
