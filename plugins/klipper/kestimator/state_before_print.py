# kestimator: the state before the print
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""What the user set at the console before a print, as the commands that set it.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .section import Kestimator


def _differ(live: Any, conf: Any) -> bool:
    try:
        return abs(float(live) - float(conf)) > 1e-9 * max(1., abs(float(conf)))
    except (TypeError, ValueError):
        return False


def _words(pairs: list[tuple[str, Any]]) -> str:
    return " ".join("%s=%.10g" % (word, float(value)) for word, value in pairs)


class StateBeforePrint:
    """What the user set at the console before a print, as commands: Mainsail's and
    Fluidd's limit and speed sliders, a Z offset, pressure advance, retraction and input
    shaper stay until a restart, and the print runs with them. Klipper's own status is
    compared with configfile's settings (printer.cfg as loaded, defaults included); each
    difference is one command, an event at the file's start."""

    def __init__(self, kest: Kestimator) -> None:
        self.kest = kest
        self.lookup = kest.printer.lookup_object

    def read(self, eventtime: float) -> tuple[list[str], list[str]]:
        """(commands, warnings): each part read on its own, so that one Klipper object
        laid out otherwise costs only its part, said in a warning."""
        configfile = self.lookup("configfile", None)
        settings: dict[str, Any] = {}
        if configfile is not None:
            settings = configfile.get_status(eventtime).get("settings", {})
        events: list[str] = []
        warnings = []
        for name, part in (("toolhead limits", self.toolhead),
                           ("speed, flow and offsets", self.gcode_move),
                           ("pressure advance", self.extruders),
                           ("firmware retraction", self.retraction),
                           ("input shaper", self.input_shaper)):
            try:
                events += part(eventtime, settings)
            except Exception as e:
                warnings.append("the %s set before the print could not be read (%s: %s); "
                                "the estimate uses printer.cfg's"
                                % (name, type(e).__name__, str(e)[:100]))
        return events, warnings

    def toolhead(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """SET_VELOCITY_LIMIT (and M204)."""
        th = self.kest.toolhead.get_status(eventtime)
        printer_cfg = settings.get("printer", {})
        limits = [(word, th[key]) for key, word, default in (
            ("max_velocity", "VELOCITY", None), ("max_accel", "ACCEL", None),
            ("square_corner_velocity", "SQUARE_CORNER_VELOCITY", 5.),
            ("minimum_cruise_ratio", "MINIMUM_CRUISE_RATIO", .5))
            if key in th and _differ(th[key], printer_cfg.get(key, default))]
        return ["SET_VELOCITY_LIMIT " + _words(limits)] if limits else []

    def gcode_move(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """M220, M221, SET_GCODE_OFFSET."""
        events: list[str] = []
        if self.kest.gcode_move is None:
            return events
        gm = self.kest.gcode_move.get_status(eventtime)
        if _differ(gm.get("speed_factor", 1.), 1.):
            events.append("M220 S%.10g" % (gm["speed_factor"] * 100.,))
        if _differ(gm.get("extrude_factor", 1.), 1.):
            events.append("M221 S%.10g" % (gm["extrude_factor"] * 100.,))
        origin = list(gm.get("homing_origin", [0., 0., 0.]))[:3]
        offsets = [(axis, v) for axis, v in zip("XYZ", origin) if _differ(v, 0.)]
        if offsets:
            events.append("SET_GCODE_OFFSET " + _words(offsets))
        return events

    def extruders(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """SET_PRESSURE_ADVANCE, per extruder."""
        events: list[str] = []
        for name, obj in self.kest.printer.lookup_objects():
            if (not name.startswith("extruder") or not name[8:].isdigit() and name[8:]
                    or not hasattr(obj, "get_status")):
                continue
            status = obj.get_status(eventtime)
            conf = settings.get(name, {})
            pa = [(word, status[key]) for key, word, option, default in (
                ("pressure_advance", "ADVANCE", "pressure_advance", 0.),
                ("smooth_time", "SMOOTH_TIME", "pressure_advance_smooth_time", .04))
                if key in status and _differ(status[key], conf.get(option, default))]
            if pa:
                events.append("SET_PRESSURE_ADVANCE EXTRUDER=%s %s" % (name, _words(pa)))
        return events

    def retraction(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """SET_RETRACTION."""
        retraction = self.lookup("firmware_retraction", None)
        if retraction is None:
            return []
        status = retraction.get_status(eventtime)
        conf = settings.get("firmware_retraction", {})
        defaults = {"retract_length": 0., "retract_speed": 20.,
                    "unretract_extra_length": 0., "unretract_speed": 10.}
        changed = [(key.upper(), status[key]) for key in sorted(defaults)
                   if key in status and _differ(status[key], conf.get(key, defaults[key]))]
        return ["SET_RETRACTION " + _words(changed)] if changed else []

    def input_shaper(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """SET_INPUT_SHAPER (input_shaper has no status: its shapers' parameters)."""
        shaper = self.lookup("input_shaper", None)
        if shaper is None:
            return []
        conf = settings.get("input_shaper", {})
        parts = []
        for axis_shaper in shaper.get_shapers():
            axis = str(axis_shaper.axis)
            params = axis_shaper.params
            live_type = str(params.shaper_type)
            conf_type = str(conf.get("shaper_type_" + axis,
                                     conf.get("shaper_type", "mzv"))).lower()
            if (_differ(params.shaper_freq, conf.get("shaper_freq_" + axis, 0.))
                    or _differ(params.damping_ratio, conf.get("damping_ratio_" + axis, .1))
                    or live_type != conf_type):
                parts.append("SHAPER_TYPE_%s=%s SHAPER_FREQ_%s=%.10g DAMPING_RATIO_%s=%.10g"
                             % (axis.upper(), live_type, axis.upper(), params.shaper_freq,
                                axis.upper(), params.damping_ratio))
        return ["SET_INPUT_SHAPER " + " ".join(parts)] if parts else []
