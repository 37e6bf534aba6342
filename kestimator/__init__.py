"""kestimator: print-time estimates that equal what Klipper's motion planner computes.

The core (this package) uses only the standard library (plus tomli before Python 3.11).
Code outside the package (the Cura plugin, other front ends) imports it through
`kestimator.api`; the console scripts start in `kestimator.entry`.
Klipper's look-ahead is re-implemented from Klipper3d/klipper (GPLv3, Kevin O'Connor and
contributors); see kestimator/toolhead.py.
"""

__version__ = "0.1.0"


def build() -> str:
    """"compiled" when the core's per-line modules are the mypyc-compiled extensions that
    `pip install .` builds with a C compiler (setup.py), else "pure Python"."""
    from kestimator import gcode

    return "compiled" if gcode.COMPILED else "pure Python"
