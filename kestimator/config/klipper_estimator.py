"""klipper_estimator's config files as a source of limits, and writing one from ``Limits``.

Owns the file format of klipper_estimator (Annex-Engineering/klipper_estimator, its
``PrinterLimits`` in lib/src/planner.rs, read with serde and deser_hjson): the keys
``max_velocity``, ``max_acceleration``, ``max_accel_to_decel``, ``square_corner_velocity``,
``instant_corner_velocity``, ``move_checkers`` (a list of ``{"axis_limiter": {"axis": [x, y, z],
"max_velocity": v, "max_accel": a}}`` and ``{"extruder_limiter": {"max_velocity": v,
"max_accel": a}}``) and ``firmware_retraction`` (``retract_length``, ``unretract_extra_length``,
``unretract_speed``, ``retract_speed``, ``lift_z``); the mapping of those onto ``Limits``
fields with provenance ``klipper_estimator config <path>: <key>``; a reader for the JSON5
subset people write by hand (comments, trailing commas, unquoted keys, single-quoted strings);
and ``dump_config``, which writes that format from resolved ``Limits``.

A written config also carries ``kestimator_limits``: every ``Limits`` field as kestimator
resolved it. klipper_estimator ignores keys it does not know; kestimator reads that table
alone when it is there (written from the same limits as the keys beside it), so a
config written by ``dump-config`` times files exactly as the printer would
(arcs, the Klipper generation, the extruder's geometry, which klipper_estimator's own keys
cannot say). Keys missing from a file are not a source: they fall through to the next one
(klipper_estimator itself would use 100 mm/s and 100 mm/s^2 for them).
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping
from typing import Any

from kestimator.config.fields import SourcedValues, check_limit_value
from kestimator.errors import KestimatorError
from kestimator.files import open_regular
from kestimator.limits import Limits, json_value

KESTIMATOR_KEY = "kestimator_limits"
"""The table of a config that holds every ``Limits`` field (kestimator's own extension)."""
MAX_CONFIG_BYTES = 1 << 20
_AXIS_Z = (0.0, 0.0, 1.0)
# klipper_estimator key -> Limits field, for the plain numbers at the top level.
TOP_LEVEL_FIELDS = (
    ("max_velocity", "max_velocity"),
    ("max_acceleration", "max_accel"),
    ("max_accel_to_decel", "max_accel_to_decel"),
    ("square_corner_velocity", "square_corner_velocity"),
    ("instant_corner_velocity", "instantaneous_corner_velocity"),
)
RETRACTION_FIELDS = (
    ("retract_length", "retract_length"),
    ("retract_speed", "retract_speed"),
    ("unretract_extra_length", "unretract_extra_length"),
    ("unretract_speed", "unretract_speed"),
)
_IDENTIFIER_RE = re.compile(r"[A-Za-z_$][A-Za-z0-9_$]*")


def json5_to_json(text: str) -> str:
    """Plain JSON from the JSON5 subset: ``//`` and ``/* */`` comments, trailing commas,
    unquoted keys and single-quoted strings. Newlines are kept, so a JSON error names the
    line of the original text. Raises ValueError for an unterminated string or comment."""
    out: list[str] = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c in "\"'":
            j = i + 1
            chars: list[str] = []
            while j < n and text[j] != c:
                if text[j] == "\\" and j + 1 < n:
                    escaped = text[j + 1]
                    chars.append("'" if escaped == "'" else "\\" + escaped)
                    j += 2
                    continue
                if text[j] == "\n":
                    raise ValueError("line break inside a string")
                chars.append('\\"' if text[j] == '"' else text[j])
                j += 1
            if j >= n:
                raise ValueError("unterminated string")
            out.append('"' + "".join(chars) + '"')
            i = j + 1
        elif text.startswith("//", i):
            end = text.find("\n", i)
            i = n if end < 0 else end
        elif text.startswith("/*", i):
            end = text.find("*/", i + 2)
            if end < 0:
                raise ValueError("unterminated /* comment")
            out.append("\n" * text.count("\n", i, end))
            i = end + 2
        elif c == ",":
            j = i + 1
            while j < n:
                if text[j].isspace():
                    j += 1
                elif text.startswith("//", j):
                    end = text.find("\n", j)
                    j = n if end < 0 else end
                elif text.startswith("/*", j):
                    end = text.find("*/", j + 2)
                    j = n if end < 0 else end + 2
                else:
                    break
            if j >= n or text[j] not in "]}":
                out.append(",")
            i += 1
        else:
            match = _IDENTIFIER_RE.match(text, i)
            if match is not None and (i == 0 or not (text[i - 1].isalnum()
                                                     or text[i - 1] in "_$.")):
                word = match.group(0)
                rest = i + len(word)
                while rest < n and text[rest] in " \t":
                    rest += 1
                if rest < n and text[rest] == ":":
                    out.append('"' + word + '"')
                else:
                    out.append(word)
                i += len(word)
            else:
                out.append(c)
                i += 1
    return "".join(out)


def read_config_document(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The object a klipper_estimator config file (JSON or JSON5) holds.

    Raises KestimatorError naming the file for anything unreadable or not an object.
    """
    where = os.fspath(path)
    try:
        # open_regular: a FIFO or device given as --config_file is refused, never read.
        with open_regular(where, "klipper_estimator config") as f:
            data = f.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise KestimatorError("cannot read the klipper_estimator config: %s"
                              % (exc.strerror or exc), where) from None
    except KestimatorError as exc:
        if exc.message.startswith("cannot read file: "):
            raise KestimatorError("cannot read the klipper_estimator config: "
                                  + exc.message[len("cannot read file: "):], where) from None
        raise
    if len(data) > MAX_CONFIG_BYTES:
        raise KestimatorError("a klipper_estimator config is at most %d bytes"
                              % MAX_CONFIG_BYTES, where)
    try:
        text = data.decode("utf-8-sig")
        document = json.loads(json5_to_json(text))
    except UnicodeDecodeError:
        raise KestimatorError("the klipper_estimator config is not UTF-8 text", where) from None
    except json.JSONDecodeError as exc:
        raise KestimatorError("not a JSON/JSON5 klipper_estimator config: %s" % exc.msg,
                              where, exc.lineno) from None
    except ValueError as exc:
        raise KestimatorError("not a JSON/JSON5 klipper_estimator config: %s" % exc,
                              where) from None
    except RecursionError:
        raise KestimatorError("the klipper_estimator config is nested too deeply", where
                              ) from None
    if not isinstance(document, dict):
        raise KestimatorError("a klipper_estimator config must be one JSON object", where)
    return document


def estimator_config_values(path: str | os.PathLike[str]) -> SourcedValues:
    """The ``Limits`` fields a klipper_estimator config sets, each sourced as
    ``klipper_estimator config <path>: <key>``.

    Raises KestimatorError for a value Klipper would refuse or of the wrong type.
    """
    where = os.fspath(path)
    document = read_config_document(where)
    description = "klipper_estimator config %s" % where
    values: dict[str, object] = {}
    sources: dict[str, str] = {}
    warnings: list[str] = []

    def put(field: str, raw: object, key: str) -> None:
        try:
            values[field] = check_limit_value(field, raw)
        except ValueError as exc:
            raise KestimatorError("%s: %s" % (key, exc), where) from None
        sources[field] = "%s: %s" % (description, key)

    own = document.get(KESTIMATOR_KEY)
    if own is not None:
        # Written by dump-config from the same limits as the keys beside it, and complete.
        if not isinstance(own, dict):
            raise KestimatorError("%s must be an object" % KESTIMATOR_KEY, where)
        for field, raw in own.items():
            put(field, raw, "%s.%s" % (KESTIMATOR_KEY, field))
        return SourcedValues(description, values, sources)
    for key, field in TOP_LEVEL_FIELDS:
        if key in document:
            put(field, document[key], key)
    checkers = document.get("move_checkers", [])
    if not isinstance(checkers, list):
        raise KestimatorError("move_checkers must be a list", where)
    for index, checker in enumerate(checkers):
        key = "move_checkers[%d]" % index
        if not isinstance(checker, dict) or len(checker) != 1:
            raise KestimatorError("%s must be {\"axis_limiter\": {...}} or "
                                  "{\"extruder_limiter\": {...}}" % key, where)
        (kind, body), = checker.items()
        if not isinstance(body, dict):
            raise KestimatorError("%s.%s must be an object" % (key, kind), where)
        if kind == "extruder_limiter":
            for name, field in (("max_velocity", "max_extrude_only_velocity"),
                                ("max_accel", "max_extrude_only_accel")):
                if name in body:
                    put(field, body[name], "%s.extruder_limiter.%s" % (key, name))
        elif kind == "axis_limiter":
            axis = _axis(body.get("axis"))
            if axis == _AXIS_Z:
                for name, field in (("max_velocity", "max_z_velocity"),
                                    ("max_accel", "max_z_accel")):
                    if name in body:
                        put(field, body[name], "%s.axis_limiter.%s" % (key, name))
            else:
                warnings.append("%s: %s: an axis limit on %s is not a Klipper [printer] "
                                "setting kestimator models (only Z has one); not used"
                                % (description, key, body.get("axis")))
        else:
            raise KestimatorError("%s: unknown move checker %r" % (key, kind), where)
    retraction = document.get("firmware_retraction")
    if retraction is not None:
        if not isinstance(retraction, dict):
            raise KestimatorError("firmware_retraction must be an object", where)
        values["firmware_retraction_enabled"] = True
        sources["firmware_retraction_enabled"] = "%s: firmware_retraction" % description
        for name, field in RETRACTION_FIELDS:
            if name in retraction:
                put(field, retraction[name], "firmware_retraction.%s" % name)
        lift = retraction.get("lift_z", 0.0)
        if lift not in (0, 0.0):
            warnings.append("%s: firmware_retraction.lift_z = %r: Klipper's "
                            "[firmware_retraction] has no Z lift; not used"
                            % (description, lift))
    return SourcedValues(description, values, sources, tuple(warnings))


def _axis(raw: object) -> tuple[float, float, float] | None:
    if (not isinstance(raw, list) or len(raw) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in raw)):
        return None
    # hypot, not the square root of a sum of squares: [1e200, 0, 0] is a direction too,
    # and its square overflows.
    length = math.hypot(*(float(v) for v in raw))
    if length == 0.0 or not math.isfinite(length):
        return None
    x, y, z = (abs(float(v)) / length for v in raw)
    return (x, y, z)


def accel_to_decel_equivalent(limits: Limits) -> float:
    """klipper_estimator's ``max_accel_to_decel`` that plans as these limits do: the value
    itself in the "absolute" generation, else max_accel * (1 - minimum_cruise_ratio)."""
    if limits.klipper_generation == "absolute" and limits.max_accel_to_decel > 0.0:
        return limits.max_accel_to_decel
    return limits.max_accel * (1.0 - limits.minimum_cruise_ratio)


def dump_config(limits: Limits, sources: Mapping[str, str] | None = None) -> dict[str, Any]:
    """A klipper_estimator config for ``limits``, plus the ``kestimator_limits`` table.

    ``sources`` (field -> provenance), when given, is kept as ``kestimator_sources`` so a
    reader can see where each value came from; both readers ignore it.
    """
    document: dict[str, Any] = {
        "max_velocity": limits.max_velocity,
        "max_acceleration": limits.max_accel,
        "max_accel_to_decel": accel_to_decel_equivalent(limits),
        "square_corner_velocity": limits.square_corner_velocity,
        "instant_corner_velocity": limits.instantaneous_corner_velocity,
        "move_checkers": [
            {"axis_limiter": {"axis": list(_AXIS_Z), "max_velocity": limits.max_z_velocity,
                              "max_accel": limits.max_z_accel}},
            {"extruder_limiter": {"max_velocity": limits.max_extrude_only_velocity,
                                  "max_accel": limits.max_extrude_only_accel}},
        ],
    }
    if limits.firmware_retraction_enabled:
        document["firmware_retraction"] = {
            "retract_length": limits.retract_length,
            "unretract_extra_length": limits.unretract_extra_length,
            "unretract_speed": limits.unretract_speed,
            "retract_speed": limits.retract_speed,
            "lift_z": 0.0,
        }
    # max_accel_to_decel 0 and klipper_version "" mean "not set" in Limits, values no
    # config may hold.
    document[KESTIMATOR_KEY] = {field: json_value(getattr(limits, field))
                                for field in Limits.field_names()
                                if not (field in ("max_accel_to_decel", "klipper_version")
                                        and not getattr(limits, field))}
    if sources is not None:
        document["kestimator_sources"] = dict(sources)
    return document
