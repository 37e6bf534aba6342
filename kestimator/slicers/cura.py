"""Cura (CuraEngine) files.

Owns how they are recognised (``;Generated with Cura_SteamEngine <version>``) and where Cura's
own estimate is: ``;TIME:<s>`` in the header (Griffin flavour: ``;PRINT.TIME:<s>``). Like
Moonraker, the largest such value in the first MiB counts.

CuraEngine writes its header before it knows the print time; run from the command line the
header stays as written, with ``;TIME:6666`` and an empty bounding box (``;MINX:2.14748e+06``,
larger than ``;MAXX:``; ``GCodeExport::getFileHeader`` in Ultimaker/CuraEngine). The Cura
application replaces that header with the real one. 6666 is therefore a placeholder unless the
header's bounding box was filled in; the Griffin header leaves ``;PRINT.TIME:`` out instead.

Also owns Cura's settings: the ``;SETTING_3`` lines at the end of a saved file (JSON, escaped for
G-code comments as Cura's GCodeWriter does, holding the user's and the quality profile's
changes as INI text; machine limits are rarely among them), the ``;FLAVOR:`` header, and
``map_cura_settings``, which the Cura plugin calls with the active machine's values.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping

from kestimator.slicers.base import (
    FileEnds,
    KlipperTimes,
    SlicerAdapter,
    SlicerInfo,
    first_group,
    foreign_flavour_line,
    replace_group,
)
from kestimator.slicers.settings import (
    LeastOf,
    SlicerConfig,
    SlicerLimit,
    SlicerSettings,
    SlicerValue,
    flag,
    number,
)

CURA_PLACEHOLDER_TIME_S = 6666.0
"""What CuraEngine writes in ``;TIME:`` while it does not know the print time yet."""

_VERSION_RE = re.compile(r"^;Generated with Cura_SteamEngine (\S+)", re.MULTILINE)
_TIME_RE = re.compile(r"^;TIME:(\d+(?:\.\d+)?)\s*$", re.MULTILINE)
_GRIFFIN_TIME_RE = re.compile(r"^;PRINT\.TIME:(\d+(?:\.\d+)?)\s*$", re.MULTILINE)
_FLOAT = r"(-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?)"
_MIN_X_RE = re.compile(r"^;MINX:" + _FLOAT, re.MULTILINE)
_MAX_X_RE = re.compile(r"^;MAXX:" + _FLOAT, re.MULTILINE)


# ;TIME:<whole seconds> and ;PRINT.TIME:<whole seconds> in the header; ;TIME_ELAPSED:<%f>
# at the end of every layer: the time every move before it has finished.
_TIME_LINE_RE = re.compile(r"(?P<key>;TIME:|;PRINT\.TIME:)(?P<t>\d+(?:\.\d+)?)\s*")
_ELAPSED_LINE_RE = re.compile(r";TIME_ELAPSED:(?P<t>-?\d+(?:\.\d+)?)\s*")
ELAPSED_PREFIX = ";TIME_ELAPSED:"


def _has_filled_bounding_box(head: str) -> bool:
    """True if the header's bounding box was written after slicing (MINX <= MAXX)."""
    min_x_mm = first_group(_MIN_X_RE, head)
    max_x_mm = first_group(_MAX_X_RE, head)
    return min_x_mm is not None and max_x_mm is not None and float(min_x_mm) <= float(max_x_mm)


def cura_estimate_s(head: str) -> float | None:
    """Largest real ``;TIME:``/``;PRINT.TIME:`` in ``head``, None if only placeholders or none."""
    times_s = [float(value) for value in _TIME_RE.findall(head)]
    if not _has_filled_bounding_box(head):
        times_s = [time_s for time_s in times_s if time_s != CURA_PLACEHOLDER_TIME_S]
    times_s += [float(value) for value in _GRIFFIN_TIME_RE.findall(head)]
    return max(times_s, default=None)


# --- settings ---------------------------------------------------------------------------------

SETTING_PREFIX = ";SETTING_3 "
FLAVOR_KEY = ";FLAVOR:"
"""Key under which the header's flavor joins the settings (it is not a Cura setting name)."""
_FLAVOR_RE = re.compile(r"^;FLAVOR:(\S+)", re.MULTILINE)
# GCodeWriter escapes backslash, LF and CR so the JSON fits in comments; undo exactly that.
_UNESCAPE = {"\\\\": "\\", "\\n": "\n", "\\r": "\r"}
_UNESCAPE_RE = re.compile(r"\\\\|\\n|\\r")
_FORMULA_PREFIX = "="
CURA_UNLIMITED_FEEDRATE = 299792458000.0
"""Cura's default machine_max_feedrate_*: "no limit"."""
# Cura's RepRap flavor writes accelerations as M204 P / M204 T lines (GCodeExport in
# Ultimaker/CuraEngine), which Klipper ignores.
_IGNORED_M204_FLAVORS = frozenset(("RepRap",))
# ;FLAVOR: values (CuraEngine's flavorToString) -> the firmware they are for: "RepRap" is the
# menu's "RepRap (RepRap)", RepRapFirmware's G-code ("RepRap (Marlin/Sprinter)" writes Marlin).
CURA_FLAVOURS = {"RepRap": "RepRapFirmware", "UltiGCode": "Ultimaker's UltiGCode",
                 "Griffin": "Ultimaker's Griffin", "Makerbot": "MakerBot"}

_CURA_RULES = (
    LeastOf("max_velocity", ("machine_max_feedrate_x", "machine_max_feedrate_y")),
    LeastOf("max_accel", ("machine_max_acceleration_x", "machine_max_acceleration_y")),
    LeastOf("max_z_velocity", ("machine_max_feedrate_z",)),
    LeastOf("max_z_accel", ("machine_max_acceleration_z",)),
    LeastOf("max_extrude_only_velocity", ("machine_max_feedrate_e",)),
    LeastOf("max_extrude_only_accel", ("machine_max_acceleration_e",)),
    LeastOf("square_corner_velocity", ("machine_max_jerk_xy",)),
    LeastOf("nozzle_diameter", ("machine_nozzle_size",)),
    LeastOf("filament_diameter", ("material_diameter",)),
)
_FEEDRATE_KEYS = frozenset(("machine_max_feedrate_x", "machine_max_feedrate_y",
                            "machine_max_feedrate_z", "machine_max_feedrate_e"))


def _ini_values(text: str) -> dict[str, str]:
    """The [values] section of one serialised Cura profile."""
    import configparser  # here: only Cura 3MF profiles need it (1 ms of every start)

    parser = configparser.ConfigParser(interpolation=None)
    try:
        parser.read_string(text)
    except configparser.Error:
        return {}
    return dict(parser["values"]) if parser.has_section("values") else {}


def read_setting_3(text: str) -> SlicerConfig:
    """The settings in the ``;SETTING_3`` lines of ``text``: the global profile's changes,
    overridden by the first extruder's. Empty when there are none or they do not parse."""
    chunks = [line[len(SETTING_PREFIX):] for line in text.splitlines()
              if line.startswith(SETTING_PREFIX)]
    if not chunks:
        return {}
    escaped = "".join(chunks)
    try:
        data = json.loads(_UNESCAPE_RE.sub(lambda m: _UNESCAPE[m.group(0)], escaped))
    except json.JSONDecodeError:
        return {}
    if not isinstance(data, dict):
        return {}
    profiles = [data.get("global_quality")]
    extruders = data.get("extruder_quality")
    if isinstance(extruders, list) and extruders:
        profiles.append(extruders[0])
    config: SlicerConfig = {}
    for profile in profiles:
        if isinstance(profile, str):
            config.update({key: SlicerValue(key, value)
                           for key, value in _ini_values(profile).items()})
    return config


def map_cura_settings(config: Mapping[str, SlicerValue]) -> SlicerSettings:
    """What Cura settings (key -> value as Cura stores it) stand for in Klipper.

    Formulas (values starting with ``=``) are not evaluated, and a feedrate of
    ``CURA_UNLIMITED_FEEDRATE`` is no limit; both are left out.
    """
    usable: dict[str, SlicerValue] = {}
    notes: list[str] = []
    for key, value in config.items():
        if value.text.startswith(_FORMULA_PREFIX):
            if any(key in rule.keys for rule in _CURA_RULES):
                notes.append(f"{value.source}: a formula, not evaluated")
            continue
        value_n = number(value)
        if key in _FEEDRATE_KEYS and value_n is not None and value_n >= CURA_UNLIMITED_FEEDRATE:
            continue
        usable[key] = value
    limits = [limit for rule in _CURA_RULES if (limit := rule.apply(usable)) is not None]
    firmware = usable.get("machine_firmware_retract")
    if firmware is not None and flag(firmware):
        limits.append(SlicerLimit("firmware_retraction_enabled", True, firmware.source))
        for field, keys in (("retract_length", ("retraction_amount",)),
                            ("retract_speed", ("retraction_retract_speed", "retraction_speed")),
                            ("unretract_speed", ("retraction_prime_speed", "retraction_speed"))):
            for key in keys:
                value_n = number(usable.get(key))
                if value_n is not None:
                    limits.append(SlicerLimit(field, value_n, usable[key].source))
                    break
    flavor = usable.get(FLAVOR_KEY)
    if flavor is not None and flavor.text in _IGNORED_M204_FLAVORS:
        notes.append(f"{flavor.source}: Cura writes any accelerations it sets as M204 P "
                     "(print) and M204 T (travel) on separate lines, which Klipper ignores (it "
                     "needs S, or P and T together); the print runs at max_accel unless macros "
                     "set it")
    return SlicerSettings(limits=tuple(limits), notes=tuple(notes))


class CuraAdapter(SlicerAdapter):
    """Files written by CuraEngine, from the Cura application or its command line."""

    family = "cura"
    time_comment_prefixes = (";TIME:", ";PRINT.TIME:", ELAPSED_PREFIX)
    flavour_keys = (FLAVOR_KEY,)
    mark_prefixes = (ELAPSED_PREFIX,)

    def detect(self, ends: FileEnds) -> SlicerInfo | None:
        match = _VERSION_RE.search(ends.head)
        if match is None:
            return None
        return SlicerInfo(
            name="Cura",
            family=self.family,
            version=match.group(1),
            estimate_s=cura_estimate_s(ends.head),
            first_layer_estimate_s=None,
        )

    def rewrite_time_comment(self, text: str, line: int, times: KlipperTimes) -> str | None:
        """``;TIME:``/``;PRINT.TIME:`` get the total, each ``;TIME_ELAPSED:`` its own time."""
        if text.startswith(ELAPSED_PREFIX):
            match = _ELAPSED_LINE_RE.fullmatch(text)
            elapsed_s = times.marks.get(line)
            if match is None or elapsed_s is None:
                return None
            return replace_group(match, "t", "%f" % elapsed_s)
        match = _TIME_LINE_RE.fullmatch(text)
        if match is None:
            return None
        return replace_group(match, "t", "%d" % round(times.total_s))

    def read_settings(self, ends: FileEnds) -> SlicerConfig:
        """``;SETTING_3`` from the end of the file, and the ``;FLAVOR:`` header."""
        config = read_setting_3(ends.tail)
        flavor = first_group(_FLAVOR_RE, ends.head)
        if flavor is not None:
            config[FLAVOR_KEY] = SlicerValue(FLAVOR_KEY, flavor)
        return config

    def map_settings(self, config: SlicerConfig) -> SlicerSettings:
        """Cura keys, mapped as docs/LIMITS.md says."""
        return map_cura_settings(config)

    def foreign_flavour(self, info: SlicerInfo, config: SlicerConfig) -> str | None:
        """The ``;FLAVOR:`` header, when not Marlin: Cura has no Klipper flavor, and
        Klipper's G-code is Marlin's (Klipper's docs/Slicers.md)."""
        flavor = config.get(FLAVOR_KEY)
        if flavor is None or flavor.text.startswith("Marlin"):
            return None
        return foreign_flavour_line(
            CURA_FLAVOURS.get(flavor.text, flavor.text), flavor.source,
            "in Cura choose Preferences > Configure Cura > Printers > Machine Settings > "
            "G-code flavor: Marlin, and slice again")
