"""Mirrors klippy/extras/input_shaper.py at Klipper commit 84104bbbd (GNU GPLv3).

Owns [input_shaper]'s shaper per axis and SET_INPUT_SHAPER. An input shaper changes no
move's time; it widens the step-generation scan window (`kestimator.stepgen`), which
decides the pause after a full stop, and a new shaper stops step generation first.
"""

from __future__ import annotations

from kestimator.errors import CommandError, fixed
from kestimator.gcode import Command, command_params, get_float
from kestimator.limits import Limits
from kestimator.stepgen import (
    SHAPER_MAX_DAMPING,
    ShaperError,
    shaper_name,
    shaper_pulses,
    shaper_window,
)
from kestimator.toolhead import ToolHead

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class InputShaper:
    """Each axis's (shaper_type, frequency, damping ratio)."""

    def __init__(self, limits: Limits, toolhead: ToolHead) -> None:
        self.toolhead = toolhead
        self.shapers: dict[str, tuple[str, float, float]] = {}
        if limits.input_shaper_enabled:
            for axis in "xyz":
                self.shapers[axis] = (getattr(limits, "shaper_type_" + axis),
                                      getattr(limits, "shaper_freq_" + axis),
                                      getattr(limits, "damping_ratio_" + axis))

    def scan_windows(self) -> list[float]:
        """The scan window each axis's shaper adds (shapers Klipper cannot build add none)."""
        windows = []
        for shaper_type, freq, damping in self.shapers.values():
            try:
                windows.append(shaper_window(*shaper_pulses(shaper_type, freq, damping)))
            except ShaperError:
                continue
        return windows

    def cmd_SET_INPUT_SHAPER(self, cmd: Command) -> None:
        """New shaper parameters: a full stop of step generation, then the new window."""
        params = command_params(cmd)
        if not params:
            return
        for axis in "xyz":
            shaper_type, freq, damping = self.shapers[axis]
            up = axis.upper()
            new_type = params.get("SHAPER_TYPE", params.get("SHAPER_TYPE_" + up, shaper_type))
            name = shaper_name(new_type.lower())
            if name not in SHAPER_MAX_DAMPING:
                raise CommandError("Unsupported shaper type: %s" % new_type)
            new_damping = get_float(params, "DAMPING_RATIO_" + up, damping, minval=0.0)
            if new_damping > SHAPER_MAX_DAMPING[name]:
                raise CommandError("Too high value of damping_ratio=%s for shaper %s on "
                                   "axis %s" % (fixed(new_damping), new_type, up))
            new_freq = get_float(params, "SHAPER_FREQ_" + up, freq, minval=0.0)
            try:
                shaper_pulses(new_type.lower(), new_freq, new_damping)
            except ShaperError as exc:
                raise CommandError(str(exc)) from None
            self.shapers[axis] = (new_type.lower(), new_freq, new_damping)
        self.toolhead.flush_step_generation()
        self.toolhead.motion_queuing.check_step_generation_scan_windows()
