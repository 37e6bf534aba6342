"""What a person may set for each ``Limits`` field, and the shape every source of limits returns.

Owns the kind of each field (number, flag, text), the checks a value given on the command line
(``--set key=value``) or in a profile must pass (Klipper's own bounds, the same ones the
printer.cfg reader enforces: ``printer_cfg.FLOAT_OPTIONS``), and ``SourcedValues``: the values
one source sets explicitly, each with where it came from. Defaults for what no source sets stay
in ``kestimator.limits``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

from kestimator.config.machine import MachineConfig, arithmetic_violation
from kestimator.config.printer_cfg import FLOAT_OPTIONS
from kestimator.limits import KLIPPER_GENERATIONS, Limits, klipper_release, tuple_field_value

_BOUNDS = {option.field: option for option in FLOAT_OPTIONS}
_TRUE_WORDS = frozenset(("1", "true", "yes", "on"))
_FALSE_WORDS = frozenset(("0", "false", "no", "off"))


@dataclasses.dataclass(frozen=True)
class SourcedValues:
    """The ``Limits`` fields one source sets, and where each one came from."""

    description: str
    """The source as a person would name it: "printer.cfg <path>", "moonraker <url>"."""
    values: Mapping[str, object]
    sources: Mapping[str, str]
    """Field -> provenance text (e.g. "printer.cfg:12", "moonraker <url>: [printer] ...")."""
    warnings: tuple[str, ...] = ()
    machine: MachineConfig | None = None
    """The sections the kinematics reads (printer.cfg and Moonraker only)."""


def field_kind(field: str) -> type:
    """``float``, ``bool`` or ``str``: the type of a ``Limits`` field's values.

    Raises KeyError for a name that is not a ``Limits`` field.
    """
    for spec in dataclasses.fields(Limits):
        if spec.name == field:
            return type(spec.default)
    raise KeyError(field)


def check_limit_value(field: str, value: object) -> object:
    """``value`` for ``field`` as ``Limits`` holds it (ints become floats).

    Raises ValueError saying what is wrong: an unknown field, a wrong type, a number Klipper
    would refuse, a Klipper generation that is not one of ``KLIPPER_GENERATIONS``, a
    ``klipper_version`` that is not a version (`klipper_release`).
    """
    try:
        kind = field_kind(field)
    except KeyError:
        import difflib
        close = difflib.get_close_matches(field, Limits.field_names(), n=1, cutoff=0.6)
        hint = f": did you mean {close[0]}?" if close else ""
        raise ValueError(f"unknown setting {field!r}{hint} (`kestimator limits` lists "
                         "every setting)") from None
    if kind is tuple:
        return tuple_field_value(field, value)
    if kind is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{field} must be true or false, not {value!r}")
        return value
    if kind is str:
        if not isinstance(value, str) or not value.strip():
            raise ValueError(f"{field} must be a non-empty text, not {value!r}")
        if field == "klipper_generation" and value not in KLIPPER_GENERATIONS:
            raise ValueError("klipper_generation must be one of "
                             + ", ".join(KLIPPER_GENERATIONS) + f", not {value!r}")
        if field == "klipper_version":
            klipper_release(value)
            return value.strip()
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{field} must be a number, not {value!r}")
    try:
        number = float(value)
    except OverflowError:  # a 400-digit integer (TOML, JSON)
        raise ValueError(f"{field} must be a finite number, not a {len(str(value))}-digit "
                         "one") from None
    if not math.isfinite(number):
        raise ValueError(f"{field} must be a finite number, not {value!r}")
    spec = _BOUNDS.get(field)
    problem = spec.violation(number) if spec is not None else arithmetic_violation(number)
    if problem is not None:
        raise ValueError(f"{field} {problem}, got {value!r}")
    return number


def parse_limit_text(field: str, text: str) -> object:
    """``text`` (as typed on a command line) for ``field``, checked as ``check_limit_value``.

    Flags take 1/0, true/false, yes/no, on/off. Raises ValueError.
    """
    try:
        kind = field_kind(field)
    except KeyError:
        return check_limit_value(field, text)
    word = text.strip()
    if kind is bool:
        if word.lower() in _TRUE_WORDS:
            return True
        if word.lower() in _FALSE_WORDS:
            return False
        raise ValueError(f"{field} must be true or false, not {text!r}")
    if kind is float:
        try:
            number = float(word)
        except ValueError:
            raise ValueError(f"{field} must be a number, not {text!r}") from None
        return check_limit_value(field, number)
    return check_limit_value(field, word)
