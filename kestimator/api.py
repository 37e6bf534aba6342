"""kestimator's public API: the names a front end outside the core may import.

Owns no behaviour, only names: each is defined by the module that owns it and re-exported
here, so the Cura plugin (plugins/cura/kestimator_cura, which imports nothing of the core
but this module; tests/test_public_api.py checks it) and the Moonraker drop-in
(`kestimator.compat`) depend on these names, not on where the core keeps them. A change
inside the core that moves one changes this file, not them.

- Errors: `KestimatorError` (one line for the user; `.path` names the file).
- Limits: `Limits` (every printer limit Klipper's planner uses), `MacroTimes` (seconds per
  macro or step the planner cannot time); from the real machine: `limits_from_printer_cfg`,
  `moonraker_values`, and the resolver that weighs every source (`LimitRequest`,
  `ResolvedLimits`, `resolve_limits`, `resolve_machine_limits`, `macro_times_for`,
  `learned_macro_times`).
- Estimating: `estimate_file`, `estimate_lines` (over `iter_lines(path)`, a file's lines
  in bounded memory, when the estimate must name the file otherwise), their result
  `Estimate`, the planned `Move` an observer hears, `NO_FEATURE`, and `format_duration`
  (``1h 02m 03s``).
- Rewriting (``kestimator inject``'s two passes): `plan_lines` (pass 1 over byte lines:
  the estimate and an `InjectPlan`), `Rewriter` (pass 2, line by line), `inject_file` (both
  over a file, replaced atomically) and its `InjectResult`, `check_gcode_file`, and the
  marker line that says a file was rewritten (`MARKER_PREFIX`, `parse_marker`).
- Slicers: `detect_slicer` (which slicer wrote a file's first and last bytes, and its own
  estimate: `SlicerInfo`), `DETECT_WINDOW_BYTES` (how many bytes of each end it reads),
  `adapter_for` (a slicer family's settings reader and mapper), `FileEnds`, and the
  settings it maps (`SlicerConfig`, `SlicerValue`).

The resolver's names load it on first use (PEP 562 ``__getattr__``), so importing this
module costs no more than the estimate itself; `resolve_machine_limits` raises ImportError
if the resolver cannot be imported, and a caller may fall back to `limits_from_printer_cfg`
or `moonraker_values`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from kestimator.config.moonraker import moonraker_values
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.durations import format_duration
from kestimator.errors import KestimatorError
from kestimator.estimate import Estimate, estimate_file, estimate_lines, iter_lines
from kestimator.limits import Limits
from kestimator.macros import MacroTimes
from kestimator.rewrite import (
    MARKER_PREFIX,
    InjectPlan,
    InjectResult,
    Rewriter,
    check_gcode_file,
    inject_file,
    parse_marker,
    plan_lines,
)
from kestimator.segments import NO_FEATURE
from kestimator.slicers import SlicerInfo, adapter_for
from kestimator.slicers import detect as detect_slicer
from kestimator.slicers.base import DETECT_WINDOW_BYTES, FileEnds
from kestimator.slicers.settings import SlicerConfig, SlicerValue
from kestimator.toolhead import Move

if TYPE_CHECKING:
    from kestimator.config.resolve import LimitRequest, ResolvedLimits, resolve_limits
    from kestimator.learn import macro_times_for

__all__ = [
    "DETECT_WINDOW_BYTES", "MARKER_PREFIX", "NO_FEATURE",
    "Estimate", "FileEnds", "InjectPlan", "InjectResult", "KestimatorError", "LimitRequest",
    "Limits", "MacroTimes", "Move", "ResolvedLimits", "Rewriter", "SlicerConfig",
    "SlicerInfo", "SlicerValue",
    "adapter_for", "check_gcode_file", "detect_slicer", "estimate_file", "estimate_lines",
    "format_duration", "inject_file", "iter_lines", "learned_macro_times",
    "limits_from_printer_cfg", "macro_times_for", "moonraker_values", "parse_marker",
    "plan_lines", "resolve_limits", "resolve_machine_limits",
]

_RESOLVER_NAMES = frozenset(("LimitRequest", "ResolvedLimits", "resolve_limits"))


def __getattr__(name: str) -> Any:
    """The resolver's names, imported when first asked for."""
    if name in _RESOLVER_NAMES:
        from kestimator.config import resolve

        value = getattr(resolve, name)
    elif name == "macro_times_for":
        from kestimator import learn

        value = learn.macro_times_for
    else:
        raise AttributeError("module %r has no attribute %r" % (__name__, name))
    globals()[name] = value
    return value


def resolve_machine_limits(printer_cfg: str | None = None, moonraker_url: str | None = None,
                           environ: Mapping[str, str] | None = None) -> ResolvedLimits:
    """The limits of the machine a printer.cfg or a Moonraker URL names, decided exactly as
    ``kestimator estimate --no-profile --printer-cfg/--moonraker`` decides them (no profile,
    no slicer environment; Moonraker's API key from ``MOONRAKER_API_KEY`` in `environ`).

    Raises `KestimatorError` when the source cannot be used, ImportError when the resolver
    cannot be imported.
    """
    from kestimator.config.resolve import LimitRequest, resolve_limits

    return resolve_limits(LimitRequest(printer_cfg=printer_cfg, moonraker_url=moonraker_url,
                                       use_profile=False, read_slicer_environment=False,
                                       environ=environ))


def learned_macro_times(resolved: ResolvedLimits) -> MacroTimes | None:
    """The times ``kestimator learn`` stored for the Moonraker `resolved` came from (before
    the first extrusion, per timelapse frame, per tool change), or None."""
    from kestimator import learn

    learned = learn.learned_for(resolved)
    return None if learned is None else learned.macro_times()
