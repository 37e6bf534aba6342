"""The one place that decides every printer limit for a file, and says where each came from.

Precedence, highest first:

1. ``--set key=value`` (``LimitRequest.overrides``);
2. the real machine: a Klipper printer.cfg or Moonraker (one of them). It decides every setting
   Klipper's configuration holds: the values it sets, and Klipper's defaults for those it leaves
   out, as the printer itself would;
3. a klipper_estimator config file (``LimitRequest.estimator_config``, JSON or JSON5): the values
   it holds, each a stand-in like the ones below (``kestimator.config.klipper_estimator``);
4. the user's profile (``[limits]``; the profile may also name the machine);
5. the slicer's settings embedded in the file, or its ``SLIC3R_*`` post-processing environment:
   guesses about the printer (docs/LIMITS.md);
6. defaults: Klipper's, plus, when no machine config is known, kestimator's assumption that a
   file using G2/G3 or G10/G11 is meant for a printer with [gcode_arcs] / [firmware_retraction].

So the profile and the slicer only stand in where no printer.cfg or Moonraker is known, except
for what no Klipper config holds: which Klipper generation (and version) the printer runs. A
``klipper_version`` gives the generation its release has where no source at least as high
gives ``klipper_generation`` (``_apply_klipper_version``). Every value comes
with its provenance, and what it overrode is kept (``ResolvedLimits.shadowed``) for
``kestimator limits``. In the middle generation (``klipper_generation = "mcr"``) a
``max_accel_to_decel`` without ``minimum_cruise_ratio`` becomes
``minimum_cruise_ratio = 1 - min(1, max_accel_to_decel / max_accel)``, as that Klipper did.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import cast

from kestimator.config.fields import SourcedValues, check_limit_value, parse_limit_text
from kestimator.config.klipper_estimator import estimator_config_values
from kestimator.config.moonraker import DEFAULT_TIMEOUT_S, default_cache_dir, moonraker_values
from kestimator.config.printer_cfg import (
    ABSENT_PROVENANCE,
    KLIPPER_DEFAULT,
    RELATIVE_BOUNDS,
    REQUIRED_FALLBACK,
    printer_cfg_values,
)
from kestimator.config.profile import (
    Profile,
    default_profile_path,
    load_profile,
    toml_available,
)
from kestimator.errors import KestimatorError
from kestimator.kinematics import load_kinematics
from kestimator.limits import FALLBACK_MAX_ACCEL, Limits, klipper_release
from kestimator.macros import MacroTime
from kestimator.slicers import (
    FILE_ORIGIN,
    SettingsCache,
    SlicerInfo,
    SlicerSettings,
    read_slicer_settings,
)
from kestimator.slicers.settings import NO_SETTINGS
from kestimator.stops import DEFAULT_STOP_COMMANDS_SET, slicer_stop_commands

API_KEY_ENVIRONMENT = "MOONRAKER_API_KEY"
"""Where the Moonraker API key may come from when neither --api-key nor the profile gives it."""

SET_SOURCE = "--set"
GUESS_FIX = ("pass --printer-cfg PATH or --moonraker URL, or set printer_cfg or moonraker in "
             "the profile (~/.config/kestimator/config.toml)")
"""How to give the real limits, in every front end's guessed-limits line."""
GUESS_WARNING_START = "no printer.cfg or Moonraker given"
"""How the guessed-limits line (``ResolvedLimits.guess_warning``) begins."""
NO_PRINTER_SECTION_START = "no [printer] section in "
"""How the guessed-limits line begins when the printer.cfg given has no [printer] section
(a moonraker.conf, a macro file): Klipper would not start with it, so its limits are
Klipper's defaults and guesses."""
GUESS_WARNING_STARTS = (GUESS_WARNING_START, NO_PRINTER_SECTION_START)
"""Every way the guessed-limits line begins (front ends say it once, on stderr)."""
NO_CONFIG_FALLBACK = ("kestimator fallback: Klipper requires it and no printer.cfg or "
                      "Moonraker gives it")
GENERATION_DEFAULT = ("kestimator default: mainline Klipper (SET_VELOCITY_LIMIT "
                      "ACCEL_TO_DECEL is ignored)")
VERSION_UNKNOWN = ("kestimator default: not known (no Moonraker asked, no klipper_version "
                   "set): klipper_generation decides")
ASSUMPTIONS = {
    "arcs_enabled": "kestimator assumption: no printer config known, and a file using G2/G3 "
                    "is meant for a printer with [gcode_arcs]",
    "firmware_retraction_enabled": "kestimator assumption: no printer config known, and a "
                                   "file using G10/G11 is meant for a printer with "
                                   "[firmware_retraction]",
}
MACHINE_FIELDS = frozenset(Limits.field_names()) - {"klipper_generation", "klipper_version"}
"""What a printer.cfg or Moonraker decides, by its values or Klipper's defaults."""

# Ranks of the sources, highest first.
LEVEL_SET, LEVEL_MACHINE, LEVEL_ESTIMATOR, LEVEL_PROFILE, LEVEL_SLICER, LEVEL_ASSUMED = range(6)
_STAND_INS = frozenset((LEVEL_ESTIMATOR, LEVEL_PROFILE, LEVEL_SLICER, LEVEL_ASSUMED))
ESTIMATOR_SOURCE_PREFIX = "klipper_estimator config "
MOONRAKER_PREFIX = "moonraker "



@dataclasses.dataclass(frozen=True)
class LimitRequest:
    """Everything that may decide the limits for one file."""

    gcode: str | os.PathLike[str] | None = None
    overrides: Mapping[str, str] = dataclasses.field(default_factory=dict)
    """``--set`` values as typed: field -> text."""
    printer_cfg: str | os.PathLike[str] | None = None
    moonraker_url: str | None = None
    api_key: str | None = dataclasses.field(default=None, repr=False)
    profile: str | os.PathLike[str] | None = None
    """An explicit profile (it must exist); None looks in the default place."""
    use_profile: bool = True
    printer: str | None = None
    """The profile's ``[printers."<name>"]`` table to use."""
    environ: Mapping[str, str] | None = None
    """For ``SLIC3R_*``, the XDG folders and the API key; None means ``os.environ``."""
    read_slicer_environment: bool = True
    cache_directory: Path | None = None
    """Moonraker's cache; None means ``$XDG_CACHE_HOME/kestimator``."""
    estimator_config: str | os.PathLike[str] | None = None
    """A klipper_estimator config file (JSON/JSON5): a stand-in below the machine."""
    running_klipper_version: str | None = None
    """The software_version of the Klipper this runs in (the Klipper module's worker): the
    klipper_version, as a machine's, unless a source names one."""
    guess_fix: str = GUESS_FIX
    """How this front end's user gives the real limits (ends the guessed-limits line)."""
    slicer_cache: SettingsCache | None = dataclasses.field(default=None, compare=False,
                                                            repr=False)
    """The worker's: the slicer's settings read from the same bytes are not parsed again."""


@dataclasses.dataclass(frozen=True)
class Candidate:
    """A value one source proposed for a field."""

    value: object
    source: str
    level: int


@dataclasses.dataclass(frozen=True)
class ResolvedLimits:
    """The limits for a file, where each came from, and what was worth saying."""

    limits: Limits
    sources: Mapping[str, str]
    """Every ``Limits`` field -> where its value came from."""
    shadowed: Mapping[str, tuple[Candidate, ...]]
    """Field -> values lower-ranked (or, under a machine config, ignored) sources proposed."""
    machine: str | None
    """The printer.cfg (its path) or Moonraker (``moonraker <url>``) the values came from;
    None when none is known."""
    profile: str | None
    slicer: SlicerInfo | None
    slicer_settings: SlicerSettings
    warnings: tuple[str, ...]
    homing_time_s: float | None = None
    """Seconds per G28 from the profile (None: not set there)."""
    heat_time_s: float | None = None
    """Seconds per heater wait from the profile (None: not set there)."""
    macro_times: Mapping[str, MacroTime] = dataclasses.field(default_factory=dict)
    """Macro name -> seconds one run takes, from the profile's ``[macros]``."""
    moonraker_api_key: str | None = dataclasses.field(default=None, repr=False)
    """The key the Moonraker of ``machine`` was asked with (never shown)."""
    guess_warning: str | None = None
    """The one line that says the limits are guesses and how to give the real ones (also
    in ``warnings``); None when a printer.cfg with [printer] or Moonraker decided them."""

    @property
    def marker_source(self) -> str:
        """Where the limits came from, for the marker line of a file people share: the kind
        of source and a file or host name, never a directory (``printer_cfg:printer.cfg``,
        ``moonraker:voron.local:7125``, ``guessed:slicer+defaults``, each ``+set`` when
        ``--set`` changed a value)."""
        used = set(self.sources.values())
        if self.machine is not None and self.machine.startswith(MOONRAKER_PREFIX):
            url = self.machine[len(MOONRAKER_PREFIX):].split(" ", 1)[0]
            text = "moonraker:" + _host_of(url)
            if "(cached" in self.machine:
                text += "(cached)"
        elif self.machine is not None:
            text = "printer_cfg:" + os.path.basename(self.machine.rstrip("/\\"))
        else:
            kinds = [kind for kind, found in (
                ("klipper_estimator_config",
                 any(s.startswith(ESTIMATOR_SOURCE_PREFIX) for s in used)),
                ("profile", any(s.startswith("profile ") for s in used)),
                ("slicer", any(s.startswith("slicer:") for s in used))) if found]
            text = "guessed:" + "+".join(kinds + ["defaults"])
        if SET_SOURCE in used:
            text += "+set"
        return "".join(c if c.isprintable() and not c.isspace() else "_" for c in text)

    @property
    def guessed(self) -> bool:
        """True when no printer.cfg or Moonraker is known, or the printer.cfg has no
        [printer] section: the times are approximate."""
        return self.guess_warning is not None

    @property
    def summary(self) -> str:
        """One line for people: the machine, or which stand-ins were used."""
        used = set(self.sources.values())
        parts = [self.machine] if self.machine is not None else []
        if self.machine is None:
            estimator = [s.partition(": ")[0] for s in used
                         if s.startswith(ESTIMATOR_SOURCE_PREFIX)]
            if estimator:
                parts.append(estimator[0])
            if self.profile is not None and any(s.startswith("profile ") for s in used):
                parts.append(self.profile)
            if any(s.startswith("slicer:") for s in used) and self.slicer is not None:
                where = self.slicer_settings.origin or "settings in the file"
                if where == FILE_ORIGIN:
                    where = "settings in the file"
                parts.append(f"{self.slicer.name} {where} (guesses)")
            parts.append("defaults")
        if SET_SOURCE in used:
            parts.append(SET_SOURCE)
        return " + ".join(parts)


def _host_of(url: str) -> str:
    """``host[:port]`` of a URL, without user, password or path."""
    from urllib.parse import urlsplit
    try:
        parts = urlsplit(url if "//" in url else "//" + url)
        host = parts.hostname or "unknown"
        return host + ("" if parts.port is None else ":%d" % parts.port)
    except ValueError:
        return "unknown"


def resolve_limits(request: LimitRequest) -> ResolvedLimits:
    """The ``Limits`` for ``request.gcode`` from every source, in the module's precedence.

    Raises KestimatorError for a bad ``--set``, profile or printer.cfg, for both a printer.cfg
    and a Moonraker URL, for a Moonraker that refuses the request or is offline with nothing
    cached, and for values that contradict each other as Klipper would refuse them.
    """
    environ = request.environ if request.environ is not None else os.environ
    if request.printer_cfg and request.moonraker_url:
        raise KestimatorError("give --printer-cfg or --moonraker, not both")
    overrides = _parse_overrides(request.overrides)
    slicer, slicer_settings = None, NO_SETTINGS
    if request.gcode is not None:
        slicer, slicer_settings = read_slicer_settings(
            request.gcode, environ if request.read_slicer_environment else None,
            request.slicer_cache)
    # Sliced for another firmware's flavour: said first, with how to choose Klipper's.
    warnings: list[str] = [] if slicer_settings.flavour is None else [
        slicer_settings.flavour]
    profile = _profile(request, environ, slicer_settings.printer_preset, warnings)
    machine = _machine(request, profile, environ)
    if machine is not None:
        warnings += machine.warnings
    estimator = None
    if request.estimator_config is not None:
        estimator = estimator_config_values(request.estimator_config)
        warnings += estimator.warnings

    candidates = _candidates(overrides, machine, profile, slicer_settings, warnings,
                             estimator)
    _add_running_version(candidates, request.running_klipper_version, warnings)
    chosen: dict[str, Candidate] = {}
    shadowed: dict[str, tuple[Candidate, ...]] = {}
    for field in Limits.field_names():
        proposed = candidates.get(field, [])
        usable = [c for c in proposed if not (machine is not None and field in MACHINE_FIELDS
                                              and c.level in _STAND_INS)]
        if usable:
            chosen[field] = usable[0]
        shadowed[field] = tuple(c for c in proposed if not usable or c is not usable[0])
    _apply_klipper_version(chosen, warnings)
    _convert_accel_to_decel(chosen)
    limits, chosen = _build(chosen)
    if machine is not None and machine.machine is not None:
        limits = limits.replace(machine=machine.machine)
    # Beyond the defaults (every estimate knows those).
    stops = (slicer_stop_commands(slicer_settings.stop_gcode) | frozenset(
        profile.stop_commands if profile is not None else ())) - DEFAULT_STOP_COMMANDS_SET
    if stops:
        limits = limits.replace(stop_commands=tuple(sorted(stops)))
    # Built once here so that a value Klipper refuses stops now, with its file and line
    # (what it does not model is said by the estimate, which builds it again).
    load_kinematics(limits)
    sources = {field: chosen[field].source if field in chosen
               else _default_source(field, machine is not None)
               for field in Limits.field_names()}
    warnings += _generation_warnings(limits, chosen)
    guess_warning = None
    if machine is None:
        levels = {c.level for c in chosen.values()}
        stand_ins = [text for level, text in ((LEVEL_SET, "--set"),
                                              (LEVEL_ESTIMATOR,
                                               "the klipper_estimator config's"),
                                              (LEVEL_PROFILE, "the profile's"),
                                              (LEVEL_SLICER, "the slicer's guesses"))
                     if level in levels] + ["Klipper's defaults"]
        guess_warning = (
            GUESS_WARNING_START + ": limits are %s (max_velocity %g, max_accel %g), "
            "so times are approximate, moves are not range-checked and G28 homes to 0; %s"
            % (", ".join(stand_ins[:-1]) + " and " + stand_ins[-1] if len(stand_ins) > 1
               else stand_ins[0], limits.max_velocity, limits.max_accel, request.guess_fix))
        warnings.append(guess_warning)
    elif (not machine.description.startswith(MOONRAKER_PREFIX)
          and "printer" not in limits.configured_sections):
        # A printer.cfg without [printer] (Moonraker's settings always have it): used, but
        # named as guessed, as `limits` shows each value.
        guess_warning = (
            NO_PRINTER_SECTION_START + "%s: is this your printer.cfg? Klipper would not "
            "start with it, so its limits are Klipper's defaults and guesses (max_velocity "
            "%g, max_accel %g) and the times are approximate; give the printer.cfg Klipper "
            "runs with, or --moonraker URL" % (machine.description, limits.max_velocity,
                                               limits.max_accel))
        warnings.append(guess_warning)
    return ResolvedLimits(
        limits=limits, sources=sources, shadowed=shadowed,
        machine=machine.description if machine is not None else None,
        profile=profile.description if profile is not None else None,
        slicer=slicer, slicer_settings=slicer_settings, warnings=tuple(warnings),
        homing_time_s=profile.homing_time_s if profile is not None else None,
        heat_time_s=profile.heat_time_s if profile is not None else None,
        macro_times={} if profile is None else {
            name: MacroTime(seconds, profile.description)
            for name, seconds in profile.macros.items()},
        moonraker_api_key=_api_key(request, profile, environ)
        if (machine is not None and machine.description.startswith("moonraker ")) else None,
        guess_warning=guess_warning)


def _parse_overrides(overrides: Mapping[str, str]) -> dict[str, object]:
    parsed: dict[str, object] = {}
    for field, text in overrides.items():
        try:
            parsed[field] = parse_limit_text(field, text)
        except ValueError as exc:
            raise KestimatorError(f"--set {field}: {exc}") from None
    return parsed


def _profile(request: LimitRequest, environ: Mapping[str, str],
             slicer_preset: str | None, warnings: list[str]) -> Profile | None:
    if not request.use_profile:
        if request.printer is not None:
            raise KestimatorError("--printer names a table of the profile, which is not read")
        return None
    if request.profile is not None:
        path = Path(request.profile)
    else:
        path = default_profile_path(environ)
        try:
            found = path.is_file()
        except OSError as exc:
            # An unreadable ~/.config/kestimator or an over-long XDG_CONFIG_HOME: the
            # default profile is optional, so a warning and go on (an error for --printer).
            reason = exc.strerror or str(exc)
            if request.printer is not None:
                raise KestimatorError(f"--printer needs a profile, and {path} cannot be "
                                      f"read: {reason}") from None
            warnings.append(f"profile {path} not read: {reason}")
            return None
        if not found:
            if request.printer is not None:
                raise KestimatorError(f"--printer needs a profile, and there is none at {path}")
            return None
        if not toml_available() and request.printer is None:
            # A slicer hook run by a Python without tomli must not fail every export
            # because a profile exists; the warning says why it was not used.
            warnings.append(f"profile {path} not read: Python {sys.version_info[0]}."
                            f"{sys.version_info[1]} needs the tomli package for it")
            return None
    return load_profile(path, printer=request.printer, slicer_preset=slicer_preset)


def _machine(request: LimitRequest, profile: Profile | None,
             environ: Mapping[str, str]) -> SourcedValues | None:
    """The printer.cfg or Moonraker settings: from the command line, else the profile."""
    printer_cfg = request.printer_cfg
    moonraker_url = request.moonraker_url
    if printer_cfg is None and moonraker_url is None and profile is not None:
        printer_cfg, moonraker_url = profile.printer_cfg, profile.moonraker
    if printer_cfg is not None:
        values, sources, machine = printer_cfg_values(printer_cfg)
        return SourcedValues(os.fspath(printer_cfg), values, sources, machine=machine)
    if moonraker_url is None:
        return None
    api_key = _api_key(request, profile, environ)
    timeout_s = profile.moonraker_timeout_s if profile is not None else None
    cache_directory = request.cache_directory or default_cache_dir(environ)
    return moonraker_values(moonraker_url, api_key,
                            timeout_s if timeout_s is not None else DEFAULT_TIMEOUT_S,
                            cache_directory)


def _api_key(request: LimitRequest, profile: Profile | None,
             environ: Mapping[str, str]) -> str | None:
    """Moonraker's API key: the request's, else the profile's, else the environment's."""
    return (request.api_key or (profile.api_key if profile is not None else None)
            or environ.get(API_KEY_ENVIRONMENT) or None)


def _candidates(overrides: Mapping[str, object], machine: SourcedValues | None,
                profile: Profile | None, slicer: SlicerSettings,
                warnings: list[str], estimator: SourcedValues | None = None
                ) -> dict[str, list[Candidate]]:
    """Field -> what each source proposes, highest rank first."""
    found: dict[str, list[Candidate]] = {}

    def add(field: str, value: object, source: str, level: int) -> None:
        found.setdefault(field, []).append(Candidate(value, source, level))

    for field, value in overrides.items():
        add(field, value, SET_SOURCE, LEVEL_SET)
    if machine is not None:
        for field, value in machine.values.items():
            add(field, value, machine.sources[field], LEVEL_MACHINE)
    if estimator is not None:
        for field, value in estimator.values.items():
            add(field, value, estimator.sources[field], LEVEL_ESTIMATOR)
    if profile is not None:
        for field, value in profile.limits.items():
            add(field, value, profile.limit_sources[field], LEVEL_PROFILE)
    for limit in slicer.limits:
        try:
            value = check_limit_value(limit.field, limit.value)
        except ValueError as exc:
            warnings.append(f"{limit.source}: not used ({exc})")
            continue
        add(limit.field, value, limit.source, LEVEL_SLICER)
    if machine is None:
        for field, text in ASSUMPTIONS.items():
            add(field, True, text, LEVEL_ASSUMED)
    return found


RUNNING_VERSION_SOURCE = "the Klipper the module runs in: software_version"


def _add_running_version(candidates: dict[str, list[Candidate]], version: str | None,
                         warnings: list[str]) -> None:
    """The running Klipper's version, after every source that names one (the user's
    settings win), ranked as a machine's value; one line and nothing when it is no version
    kestimator knows (a Klipper without git reports "?")."""
    if version is None:
        return
    try:
        value = check_limit_value("klipper_version", version)
    except ValueError as exc:
        warnings.append(f"{RUNNING_VERSION_SOURCE}: not used ({exc})")
        return
    candidates.setdefault("klipper_version", []).append(
        Candidate(value, RUNNING_VERSION_SOURCE, LEVEL_MACHINE))


def _apply_klipper_version(chosen: dict[str, Candidate], warnings: list[str]) -> None:
    """The generation the chosen ``klipper_version`` has, where no source at least as high
    gives ``klipper_generation`` (the low-level knob); one line for a version newer than the
    newest known; a KestimatorError for a [printer] option that release refuses to start
    with, as Klipper would."""
    version = chosen.get("klipper_version")
    if version is None:
        return
    text = str(version.value)
    release = klipper_release(text)
    if release.note is not None:
        warnings.append(release.note)
    generation = chosen.get("klipper_generation")
    if generation is None or generation.level > version.level:
        chosen["klipper_generation"] = Candidate(
            release.generation, f"klipper_version {text} ({version.source}): {release.rule}",
            version.level)
    for option, accepted in (("max_accel_to_decel", release.accepts_max_accel_to_decel),
                             ("minimum_cruise_ratio", release.accepts_minimum_cruise_ratio)):
        given = chosen.get(option)
        if accepted or given is None or given.level != LEVEL_MACHINE:
            continue
        klipper = f"{release.app} {text}" + (
            "" if release.note is None else f", taken as {release.rule},")
        raise KestimatorError(f"{given.source}: [printer] has no option '{option}': "
                              f"{klipper} refuses to start with it (Option "
                              f"'{option}' is not valid in section 'printer')")


def _convert_accel_to_decel(chosen: dict[str, Candidate]) -> None:
    """Klipper 2024-03..2025-08 turned [printer] max_accel_to_decel into minimum_cruise_ratio
    when the config gave no minimum_cruise_ratio (klippy/toolhead.py of that time)."""
    generation = chosen.get("klipper_generation")
    accel_to_decel = chosen.get("max_accel_to_decel")
    if (generation is None or generation.value != "mcr" or accel_to_decel is None
            or "minimum_cruise_ratio" in chosen):
        return
    max_accel = chosen.get("max_accel")
    accel = _number(max_accel.value) if max_accel is not None else FALLBACK_MAX_ACCEL
    requested = _number(accel_to_decel.value)
    chosen["minimum_cruise_ratio"] = Candidate(
        1.0 - min(1.0, requested / accel),
        f"converted from max_accel_to_decel ({accel_to_decel.source}) as Klipper "
        f"2024-03..2025-08 did: 1 - min(1, {requested:g} / {accel:g})", accel_to_decel.level)


def _number(value: object) -> float:
    """A value already checked to be a number, as a float."""
    return float(cast(float, value))


def _build(chosen: dict[str, Candidate]) -> tuple[Limits, dict[str, Candidate]]:
    """``Limits`` from the chosen values, with Klipper's cross-field rules enforced: a slicer's
    guess beyond one is capped at the bound, anything else is an error."""
    chosen = dict(chosen)
    limits = Limits.from_values({field: c.value for field, c in chosen.items()})
    for field, bound, allowed, text in RELATIVE_BOUNDS:
        value, limit = getattr(limits, field), getattr(limits, bound)
        candidate = chosen.get(field)
        if candidate is None or allowed(value, limit):
            continue
        if candidate.level not in (LEVEL_SLICER, LEVEL_ASSUMED):
            bound_source = chosen[bound].source if bound in chosen else "default"
            raise KestimatorError(f"{field} {value:g} ({candidate.source}) must be {text} "
                                  f"{bound} {limit:g} ({bound_source}), as Klipper requires")
        chosen[field] = Candidate(limit, f"{candidate.source} (capped: Klipper requires {field} "
                                         f"{text} {bound})", candidate.level)
        limits = Limits.from_values({f: c.value for f, c in chosen.items()})
    return limits, chosen


def _default_source(field: str, have_machine: bool) -> str:
    """Where a value no source set comes from."""
    if field == "klipper_generation":
        return GENERATION_DEFAULT
    if field == "klipper_version":
        return VERSION_UNKNOWN
    text = ABSENT_PROVENANCE.get(field, KLIPPER_DEFAULT)
    if text == REQUIRED_FALLBACK and not have_machine:
        return NO_CONFIG_FALLBACK
    return text


def _generation_warnings(limits: Limits, chosen: Mapping[str, Candidate]) -> list[str]:
    accel_to_decel = chosen.get("max_accel_to_decel")
    if (limits.klipper_generation == "mainline" and accel_to_decel is not None
            and accel_to_decel.level == LEVEL_MACHINE):
        return [f"max_accel_to_decel ({accel_to_decel.source}) is an option mainline Klipper "
                "refuses and ignored here: if the printer runs Klipper from before 2025-08, "
                "set klipper_version to its version (e.g. v0.12.0), or klipper_generation to "
                "\"mcr\" (2024-03..2025-08) or \"absolute\" (older)"]
    return []
