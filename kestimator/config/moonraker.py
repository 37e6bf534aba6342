"""A live printer's Klipper settings, read from Moonraker, with a cache for when it is offline.

Owns the requests (``GET <url>/printer/objects/query?configfile=settings``, then
``GET <url>/printer/info`` for the Klipper version it runs, the API key in the
``X-Api-Key`` header when there is one, a timeout, no proxy and no redirects so the key goes to
that host only), the answer's shape (Moonraker wraps Klipper's status as ``{"result":
{"eventtime": ..., "status": {"configfile": {"settings": {section: {option: value}}}}}}``;
Klipper lists every option it read, its defaults included, with lower-case names and typed
values), the mapping of those settings onto ``Limits`` fields (the option table of the
printer.cfg reader), and the cache: one JSON file per Moonraker URL in
``$XDG_CACHE_HOME/kestimator/`` (``~/.cache/kestimator/``), holding only the sections kestimator
reads. The API key is never written anywhere and never part of a message.
"""

from __future__ import annotations

import json
import math
import os
import re
import urllib.parse
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from kestimator.config.fields import SourcedValues
from kestimator.config.machine import MachineConfig, is_machine_section
from kestimator.config.printer_cfg import (
    EXTRUDER_STEPPER_OPTIONS,
    FLOAT_OPTIONS,
    HEATER_OPTIONS,
    MACRO_PREFIX,
    MAX_EXTRUDERS,
    STEPPER_OPTIONS,
)
from kestimator.errors import KestimatorError
from kestimator.files import read_config_bytes, write_json_privately
from kestimator.limits import (
    FALLBACK_MAX_ACCEL,
    FALLBACK_MAX_VELOCITY_V,
    ExtruderLimits,
    ExtruderStepperLimits,
    heater_limits,
    heater_sections,
    klipper_release,
)

if TYPE_CHECKING:
    import datetime
    import urllib.error
# urllib.request and http.client are imported where a request is made: they take longer
# to import (0.1 s under PyPy) than a small file takes to estimate, and most runs have no
# Moonraker to ask; datetime too (1.5 ms of every compiled estimate).

DEFAULT_TIMEOUT_S = 3.0
QUERY_PATH = "/printer/objects/query?configfile=settings"
INFO_PATH = "/printer/info"
API_KEY_HEADER = "X-Api-Key"
CACHED_SECTIONS = ("printer", "extruder", "gcode_arcs", "firmware_retraction",
                   "input_shaper")
"""The Klipper sections kestimator reads (and [extruderN]), besides the kinematics' ones
(``config.machine.is_machine_section``: [stepper_*], [dual_carriage], probes) and the heaters'
ranges ([heater_bed], [heater_generic NAME]: `HEATER_OPTIONS` only); of the others (macros
included: their templates may hold anything) only the names are cached."""
_EXTRUDER_RE = re.compile(r"extruder[1-9][0-9]?$")
MAX_ANSWER_BYTES = 16 * 1024 * 1024
# Server text shown to the user (error messages, reasons) is cut to this many characters;
# an error body is read only this far.
MAX_SERVER_TEXT = 200
MAX_ERROR_BODY_BYTES = 64 * 1024
READ_CHUNK_BYTES = 64 * 1024
HTTP_NOT_FOUND = 404
CACHE_FORMAT = 1
_SECTION_FLAGS = (("gcode_arcs", "arcs_enabled"),
                  ("firmware_retraction", "firmware_retraction_enabled"),
                  ("input_shaper", "input_shaper_enabled"))
_TIME_SHOWN = "%Y-%m-%dT%H:%MZ"
_TIME_STORED = "%Y-%m-%dT%H:%M:%SZ"

Settings = dict[str, dict[str, Any]]
"""Klipper's ``configfile.settings``: section -> option -> value."""


class MoonrakerUnreachableError(KestimatorError):
    """Moonraker did not answer, or Klipper behind it was not ready: the cache may stand in."""


def normalise_url(url: str) -> str:
    """``http(s)://host[:port][/path]`` without a trailing slash (``http://`` if none given).

    Raises KestimatorError for anything else; a URL holding a user name, password or query
    is refused without being repeated, as it may hold a secret.
    """
    text = url.strip()
    if "://" not in text:
        text = "http://" + text
    try:
        parts = urllib.parse.urlsplit(text)
        if "@" in parts.netloc or parts.query or parts.fragment:
            raise KestimatorError("a Moonraker URL must be http(s)://host[:port][/path], "
                                  "without a user, password or query; pass an API key with "
                                  "--api-key")
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError("no host")
        parts.port  # noqa: B018 - raises ValueError for a port out of range
    except ValueError:  # "http://[::1" (Invalid IPv6 URL), a bad port
        raise KestimatorError(f"not a Moonraker URL: {url!r} (expected http://host:7125)"
                              ) from None
    return f"{parts.scheme}://{parts.netloc}{parts.path.rstrip('/')}"


def default_cache_dir(environ: Mapping[str, str]) -> Path:
    """``$XDG_CACHE_HOME/kestimator`` (``~/.cache/kestimator`` when it is unset)."""
    base = environ.get("XDG_CACHE_HOME") or os.path.join(
        environ.get("HOME") or os.path.expanduser("~"), ".cache")
    return Path(base) / "kestimator"


def cache_path(url: str, directory: Path) -> Path:
    """The cache file of one (normalised) Moonraker URL."""
    import hashlib  # here: under PyPy it loads OpenSSL, which most runs never need

    digest = hashlib.sha256(url.encode("utf-8")).hexdigest()[:16]
    return directory / f"moonraker-{digest}.json"


def clean_api_key(api_key: str | None) -> str | None:
    """The key with surrounding whitespace (a CR or LF from a file or a paste) removed.

    Raises KestimatorError, without repeating the key, when control characters or spaces
    remain inside it: such a key cannot be sent, and an error quoting it would leak it.
    """
    if api_key is None:
        return None
    key = api_key.strip()
    if not key:
        return None
    if not all(33 <= ord(ch) < 127 for ch in key):
        raise KestimatorError("the Moonraker API key holds spaces, control or non-ASCII "
                              "characters (not shown): check --api-key, $MOONRAKER_API_KEY "
                              "or the profile")
    return key


def server_text(text: object, secret: str | None = None) -> str:
    """Text a server sent, safe to show: one line of printable characters, at most
    MAX_SERVER_TEXT characters, with `secret` (the API key) blanked out."""
    shown = str(text)
    if secret:
        shown = shown.replace(secret, "<API key>")
    shown = "".join(ch if ch.isprintable() else " " for ch in shown[:MAX_SERVER_TEXT * 4])
    shown = " ".join(shown.split())
    if secret:
        shown = shown.replace(secret, "<API key>")
    if len(shown) > MAX_SERVER_TEXT:
        shown = shown[:MAX_SERVER_TEXT] + "..."
    return shown


def fetch_settings(url: str, api_key: str | None = None,
                   timeout_s: float = DEFAULT_TIMEOUT_S) -> Settings:
    """Klipper's ``configfile.settings`` from the Moonraker at (normalised) ``url``.

    Raises as `_fetch` does."""
    return _settings_from_answer(_fetch(url, QUERY_PATH, api_key, timeout_s), url)


def fetch_klipper_version(url: str, api_key: str | None = None,
                          timeout_s: float = DEFAULT_TIMEOUT_S) -> tuple[str | None, str | None]:
    """(the Klipper version, a warning): ``software_version`` of Moonraker's printer.info
    (``GET <url>/printer/info``), the app's name first where it is not Klipper ("Kalico
    v2026.07.00-0-g30c65e09"). (None, None) where Moonraker does not answer it or Klipper
    does not know its version ("?"); (None, a line saying so, its text sanitised) where it is
    not a version kestimator reads."""
    try:
        body = _fetch(url, INFO_PATH, api_key, timeout_s)
        info = json.loads(body)["result"]
        version, app = info["software_version"], info.get("app", "Klipper")
    except KestimatorError:
        return None, None
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
        return None, f"Moonraker at {url} answered printer.info without a software_version"
    if not isinstance(version, str) or not isinstance(app, str):
        return None, f"Moonraker at {url} answered printer.info without a software_version"
    if version.strip() in ("", "?"):
        return None, None  # Klipper's own "not known" (a tree without git or .version file)
    text = version if app.strip().lower() in ("", "klipper") else f"{app.strip()} {version}"
    try:
        klipper_release(text)
    except ValueError:
        return None, (f"Moonraker at {url}: printer.info reports {server_text(text)!r}, not "
                      "a Klipper version kestimator knows; the settings decide "
                      "klipper_generation")
    return text.strip(), None


def _fetch(url: str, path: str, api_key: str | None, timeout_s: float) -> bytes:
    """The body of Moonraker's answer to ``GET <url><path>``.

    ``timeout_s`` bounds the whole request (connect, headers and body), not each socket
    read: a server dripping one byte a second is cut off at the deadline. Raises
    MoonrakerUnreachableError when Moonraker does not answer in time or answers that Klipper
    is not ready (5xx), and KestimatorError when it refuses the request (a missing or wrong
    API key) or answers something else than settings. Server text in errors is sanitised and
    bounded (`server_text`) and never holds the key.
    """
    import http.client
    import urllib.error
    import urllib.request

    key = clean_api_key(api_key)

    class NoRedirect(urllib.request.HTTPRedirectHandler):
        """Refuse redirects: a redirected request would carry the API key elsewhere."""

        def redirect_request(self, req: urllib.request.Request, fp: Any, code: int,
                             msg: str, headers: Any, newurl: str) -> None:
            return None

    deadline = _Deadline(timeout_s)
    request = urllib.request.Request(url + path, headers={"Accept": "application/json"})
    if key:
        request.add_header(API_KEY_HEADER, key)
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}), NoRedirect(),
                                         *deadline.handlers())
    try:
        try:
            with opener.open(request, timeout=timeout_s) as response:
                body = _read_bounded(response, deadline)
        except urllib.error.HTTPError as exc:
            try:
                status, reason = exc.code, server_text(_error_message(exc), key)
            finally:
                exc.close()
            if status in (401, 403):
                raise KestimatorError(f"Moonraker at {url} refused the request ({status} "
                                      f"{reason}): give its API key with --api-key or in the "
                                      "profile") from None
            if status >= 500 or status == HTTP_NOT_FOUND:
                # Moonraker registers Klipper's endpoints (this query among them) only once
                # Klipper has connected: without a running Klipper it answers 404.
                raise MoonrakerUnreachableError(
                    f"Moonraker at {url} answered {status} {reason}" + (
                        " (no Klipper connected to it)" if status == HTTP_NOT_FOUND else "")
                ) from None
            raise KestimatorError(f"Moonraker at {url} answered {status} {reason}") from None
        except (urllib.error.URLError, http.client.HTTPException, OSError, ValueError) as exc:
            if deadline.expired:
                raise MoonrakerUnreachableError(
                    f"Moonraker at {url} did not answer within {timeout_s:g} s") from None
            why = server_text(getattr(exc, "reason", None) or exc, key)
            raise MoonrakerUnreachableError(f"Moonraker at {url} did not answer ({why})"
                                            ) from None
    finally:
        deadline.cancel()
    if deadline.expired:
        raise MoonrakerUnreachableError(
            f"Moonraker at {url} did not answer within {timeout_s:g} s")
    if len(body) > MAX_ANSWER_BYTES:
        raise KestimatorError(f"Moonraker at {url} answered more than {MAX_ANSWER_BYTES} bytes")
    return body


def _read_bounded(response: Any, deadline: _Deadline, limit: int = MAX_ANSWER_BYTES) -> bytes:
    """The body, at most `limit` + 1 bytes, read until the deadline (the caller checks
    ``deadline.expired``: a body cut off by it ends early)."""
    parts: list[bytes] = []
    size = 0
    while size <= limit and not deadline.expired:
        chunk = response.read1(READ_CHUNK_BYTES) if hasattr(response, "read1") else \
            response.read(READ_CHUNK_BYTES)
        if not chunk:
            break
        parts.append(chunk)
        size += len(chunk)
    return b"".join(parts)


read_bounded = _read_bounded


class _Deadline:
    """One deadline for a whole HTTP request: when it passes, the connection's socket is
    shut down from a timer thread, so a blocked read returns at once (a per-read socket
    timeout alone lets a server drip one byte per timeout for ever)."""

    def __init__(self, seconds: float) -> None:
        import threading
        import time

        self.expired = False
        self._end = time.monotonic() + max(seconds, 0.0)
        self._sockets: list[Any] = []
        self._lock = threading.Lock()
        self._timer = threading.Timer(max(seconds, 0.0), self._expire)
        self._timer.daemon = True
        self._timer.start()

    def _expire(self) -> None:
        import socket

        with self._lock:
            self.expired = True
            for sock in self._sockets:
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def cancel(self) -> None:
        self._timer.cancel()

    def remaining(self) -> float:
        """Seconds left (0 once passed)."""
        import time

        return 0.0 if self.expired else max(0.0, self._end - time.monotonic())

    def watch(self, sock: Any) -> None:
        with self._lock:
            self._sockets.append(sock)
            if self.expired:
                import socket

                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def handlers(self) -> list[Any]:
        """urllib handlers whose connections register their socket with this deadline."""
        import http.client
        import urllib.request

        deadline = self

        class Connection(http.client.HTTPConnection):
            def connect(self) -> None:
                super().connect()
                deadline.watch(self.sock)

        class SecureConnection(http.client.HTTPSConnection):
            def connect(self) -> None:
                super().connect()
                deadline.watch(self.sock)

        class Handler(urllib.request.HTTPHandler):
            def http_open(self, req: Any) -> Any:
                return self.do_open(Connection, req)

        class SecureHandler(urllib.request.HTTPSHandler):
            def https_open(self, req: Any) -> Any:
                return self.do_open(SecureConnection, req)

        return [Handler(), SecureHandler()]


Deadline = _Deadline
"""One deadline shared by several requests (``kestimator learn``): each connection made
through its `handlers` is cut when it passes."""


def _error_message(exc: Any) -> str:
    """Moonraker's ``{"error": {"message": ...}}``, else the HTTP reason (raw: the caller
    sanitises it)."""
    try:
        message = json.loads(exc.read(MAX_ERROR_BODY_BYTES))["error"]["message"]
    except (ValueError, KeyError, TypeError, OSError, RecursionError):
        return str(exc.reason)
    return str(message)


def _settings_from_answer(body: bytes, url: str) -> Settings:
    try:
        settings = json.loads(body)["result"]["status"]["configfile"]["settings"]
    except (ValueError, KeyError, TypeError, RecursionError):
        raise KestimatorError(f"Moonraker at {url} did not answer with Klipper's settings "
                              "(result.status.configfile.settings)") from None
    if not isinstance(settings, dict) or not all(
            isinstance(options, dict) for options in settings.values()):
        raise KestimatorError(f"Moonraker at {url} answered settings of an unknown shape")
    return settings


def settings_values(settings: Mapping[str, Mapping[str, Any]], description: str,
                    klipper_version: str | None = None) -> SourcedValues:
    """The ``Limits`` fields Klipper's settings give, each sourced as
    ``<description>: [section] option``, and ``klipper_version`` (printer.info's, sourced
    ``<description>: printer.info software_version``) where it is known.

    Where the version is not known, the Klipper generation is inferred where the settings
    tell it: ``max_accel_to_decel`` without ``minimum_cruise_ratio`` is only read by Klipper
    before 2024-03 ("absolute"), both together only by Klipper from 2024-03 to 2025-08
    ("mcr"). Raises KestimatorError for a value Klipper could not have accepted (a damaged
    cache).
    """
    values: dict[str, object] = {}
    sources: dict[str, str] = {}
    for spec in FLOAT_OPTIONS:
        raw = settings.get(spec.section, {}).get(spec.option)
        if raw is None:
            continue
        where = f"{description}: [{spec.section}] {spec.option}"
        value = _number(raw)
        problem = "is not a number" if value is None else spec.violation(value)
        if problem is not None:
            raise KestimatorError(f"{where} = {raw!r} {problem}")
        values[spec.field] = value
        sources[spec.field] = where
    shaper = settings.get("input_shaper", {})
    for axis in "xyz":
        raw = shaper.get("shaper_type_" + axis, shaper.get("shaper_type"))
        if isinstance(raw, str) and raw:
            values["shaper_type_" + axis] = raw
            sources["shaper_type_" + axis] = f"{description}: [input_shaper] shaper_type_{axis}"
    _extra_extruders(settings, description, values, sources)
    _heaters(settings, description, values, sources)
    _extruder_steppers(settings, description, values, sources)
    values["configured_sections"] = tuple(sorted(str(name).lower() for name in settings))
    sources["configured_sections"] = f"{description}: its sections"
    # Macros by name only (""): known commands, not run. Their text may hold anything and
    # is never cached, so the live answer keeps it out too (live and cached agree).
    macros = tuple((name[len(MACRO_PREFIX):].strip().upper(), "")
                   for name in settings if name.startswith(MACRO_PREFIX))
    if macros:
        values["gcode_macros"] = macros
        sources["gcode_macros"] = f"{description}: [gcode_macro ...]"
    printer = settings.get("printer", {})
    kinematics = printer.get("kinematics")
    if isinstance(kinematics, str) and kinematics:
        values["kinematics"] = kinematics
        sources["kinematics"] = f"{description}: [printer] kinematics"
    for section, field in _SECTION_FLAGS:
        if section in settings:
            values[field] = True
            sources[field] = f"{description}: [{section}]"
    if klipper_version is not None:
        values["klipper_version"] = klipper_version
        sources["klipper_version"] = f"{description}: printer.info software_version"
    elif "max_accel_to_decel" in printer:
        both = "minimum_cruise_ratio" in printer
        values["klipper_generation"] = "mcr" if both else "absolute"
        sources["klipper_generation"] = (
            f"{description}: [printer] reports max_accel_to_decel "
            + ("and minimum_cruise_ratio (only Klipper 2024-03..2025-08 reads both)" if both
               else "without minimum_cruise_ratio (Klipper before 2024-03)"))
    return SourcedValues(description, values, sources,
                         machine=machine_from_settings(settings, description))


def machine_from_settings(settings: Mapping[str, Mapping[str, Any]],
                          description: str) -> MachineConfig:
    """The kinematics' sections of Klipper's settings, as the text a printer.cfg would hold
    (so the kinematics read both the same way), each sourced ``<description>: [section]``."""
    return MachineConfig.build(description, {
        name: {option: (_as_text(value), f"{description}: [{name}] {option}")
               for option, value in _machine_options(name, options).items()}
        for name, options in settings.items() if is_machine_section(name)})


def _machine_options(name: str, options: Mapping[str, Any]) -> Mapping[str, Any]:
    """A machine section's settings, without [homing_override]'s gcode: like a macro's, its
    text is never taken from Moonraker nor cached (it may hold anything)."""
    if name == "homing_override":
        return {option: value for option, value in options.items() if option != "gcode"}
    return options


def _as_text(value: object) -> str:
    """A settings value as printer.cfg text: lists (gear_ratio) as "a:b, c:d"."""
    if isinstance(value, (list, tuple)):
        return ", ".join(":".join(_as_text(v) for v in item) if isinstance(item, (list, tuple))
                         else _as_text(item) for item in value)
    return str(value)


def _extra_extruders(settings: Mapping[str, Mapping[str, Any]], description: str,
                     values: dict[str, object], sources: dict[str, str]) -> None:
    """[extruder1] ... as Klipper loads them (in order, until one is missing)."""
    extruders = []
    max_velocity = _number(settings.get("printer", {}).get("max_velocity"))
    max_accel = _number(settings.get("printer", {}).get("max_accel"))
    for index in range(1, MAX_EXTRUDERS):
        name = f"extruder{index}"
        section = settings.get(name)
        if not isinstance(section, Mapping):
            break
        found: dict[str, object] = {}
        for spec in FLOAT_OPTIONS:
            raw = section.get(spec.option)
            if spec.section != "extruder" or raw is None:
                continue
            value = _number(raw)
            problem = "is not a number" if value is None else spec.violation(value)
            if problem is not None:
                raise KestimatorError(f"{description}: [{name}] {spec.option} = {raw!r} "
                                      f"{problem}")
            found[spec.option] = value
        found["has_stepper"] = any(option in section for option in STEPPER_OPTIONS)
        extruders.append(ExtruderLimits.from_values(
            name, found, max_velocity or FALLBACK_MAX_VELOCITY_V,
            max_accel or FALLBACK_MAX_ACCEL))
    if extruders:
        values["extruders"] = tuple(extruders)
        sources["extruders"] = f"{description}: " + ", ".join(
            f"[{e.name}]" for e in extruders)


def _heaters(settings: Mapping[str, Mapping[str, Any]], description: str,
             values: dict[str, object], sources: dict[str, str]) -> None:
    """Each heater's range, where the settings give its min_temp and max_temp."""
    heaters = []
    sections = [str(name).lower() for name in settings]
    for name in heater_sections(sections):
        section = next(options for key, options in settings.items()
                       if str(key).lower() == name)
        if "min_temp" not in section or "max_temp" not in section:
            continue
        numbers = []
        for option in HEATER_OPTIONS:
            raw = section.get(option)
            value = None if raw is None else _number(raw)
            if raw is not None and value is None:
                raise KestimatorError(f"{description}: [{name}] {option} = {raw!r} is not a "
                                      "number")
            numbers.append(value)
        # The settings hold min_extrude_temp's default too (170, even above a bed's
        # max_temp), which Klipper does not check.
        found = heater_limits(name, numbers[0] or 0.0, numbers[1] or 0.0, numbers[2],
                              given=False)
        if isinstance(found, str):
            raise KestimatorError(f"{description}: [{name}] {found}")
        heaters.append(found)
    if heaters:
        values["heaters"] = tuple(heaters)
        sources["heaters"] = f"{description}: " + ", ".join(f"[{h.name}]" for h in heaters)


EXTRUDER_STEPPER_PREFIX = "extruder_stepper "


def _extruder_steppers(settings: Mapping[str, Mapping[str, Any]], description: str,
                       values: dict[str, object], sources: dict[str, str]) -> None:
    """Each [extruder_stepper NAME] whose settings say which extruder it follows (Klipper
    always reports that option; a section without it is one cached by name only)."""
    steppers = []
    for key, section in settings.items():
        name = str(key).lower()
        if not name.startswith(EXTRUDER_STEPPER_PREFIX) or not isinstance(section, Mapping) \
                or not isinstance(section.get("extruder"), str):
            continue
        found: dict[str, float] = {}
        for option, spec in EXTRUDER_STEPPER_OPTIONS.items():
            raw = section.get(option)
            if raw is None:
                continue
            value = _number(raw)
            problem = "is not a number" if value is None else spec.violation(value)
            if problem is not None or value is None:
                raise KestimatorError(f"{description}: [{name}] {option} = {raw!r} {problem}")
            found[option] = value
        steppers.append(ExtruderStepperLimits(name.split()[-1], section["extruder"].strip(),
                                              **found))
    if steppers:
        values["extruder_steppers"] = tuple(steppers)
        sources["extruder_steppers"] = f"{description}: " + ", ".join(
            f"[extruder_stepper {e.name}]" for e in steppers)


def _number(raw: object) -> float | None:
    if isinstance(raw, bool):
        return None
    try:
        value = float(raw)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _utc_now() -> datetime.datetime:
    import datetime

    return datetime.datetime.now(datetime.timezone.utc)


def moonraker_values(url: str, api_key: str | None = None,
                     timeout_s: float = DEFAULT_TIMEOUT_S,
                     cache_directory: Path | None = None,
                     now: Callable[[], datetime.datetime] = _utc_now) -> SourcedValues:
    """The printer's settings from Moonraker at ``url``, cached on success; when the printer
    is offline, the cached ones, described as "(cached <time>, printer offline)".

    ``cache_directory`` None means ``default_cache_dir(os.environ)``. Raises KestimatorError
    when Moonraker refuses the request, or is offline with nothing cached.
    """
    url = normalise_url(url)
    directory = cache_directory if cache_directory is not None else default_cache_dir(os.environ)
    path = cache_path(url, directory)
    try:
        settings = fetch_settings(url, api_key, timeout_s)
    except MoonrakerUnreachableError as exc:
        cached = _read_cache(path, url)
        if cached is None:
            raise KestimatorError(f"{exc.message}, and no settings of it are cached in "
                                  f"{directory}") from None
        settings, fetched, cached_version = cached
        shown = fetched.strftime(_TIME_SHOWN)
        found = settings_values(settings, f"moonraker {url} (cached {shown}, printer offline)",
                                cached_version)
        return SourcedValues(found.description, found.values, found.sources,
                             (f"{exc.message}: using its settings cached at {shown}",),
                             machine=found.machine)
    version, version_warning = fetch_klipper_version(url, api_key, timeout_s)
    found = settings_values(settings, f"moonraker {url}", version)
    warnings: tuple[str, ...] = () if version_warning is None else (version_warning,)
    problem = _write_cache(path, url, settings, now(), version)
    if problem is not None:
        warnings += (problem,)
    if warnings:
        return SourcedValues(found.description, found.values, found.sources, warnings,
                             machine=found.machine)
    return found


def _write_cache(path: Path, url: str, settings: Settings,
                 fetched: datetime.datetime, version: str | None = None) -> str | None:
    """Store the sections kestimator reads and the Klipper version (atomically); a warning
    text if that failed."""
    import datetime

    document: dict[str, object] = {
        "format": CACHE_FORMAT,
        "url": url,
        "fetched": fetched.astimezone(datetime.timezone.utc).strftime(_TIME_STORED),
        "settings": {name: _cached_options(name, options)
                     for name, options in settings.items()},
    }
    if version is not None:
        document["klipper_version"] = version
    try:
        write_json_privately(path, document)
    except OSError as exc:
        return f"could not cache Moonraker's settings in {path}: {exc.strerror or exc}"
    return None


def _cached_options(name: str, options: Mapping[str, Any]) -> dict[str, Any]:
    """What the cache keeps of one section's settings."""
    if name in CACHED_SECTIONS or _EXTRUDER_RE.match(name) or is_machine_section(name):
        return dict(_machine_options(name, options))
    if name in heater_sections([name]):
        return {option: options[option] for option in HEATER_OPTIONS if option in options}
    if name.startswith(EXTRUDER_STEPPER_PREFIX):
        return {option: options[option] for option in ("extruder", *EXTRUDER_STEPPER_OPTIONS)
                if option in options}
    return {}


def _read_cache(path: Path, url: str
                ) -> tuple[Settings, datetime.datetime, str | None] | None:
    """(settings, when fetched, the Klipper version if known) from the cache file of ``url``,
    None if there is none.

    Raises KestimatorError for a cache file that is there but damaged (not our JSON, another
    URL's, sections that are not tables): reported as such, not as "nothing cached".
    """
    import datetime

    if not path.exists():
        return None
    try:
        document = json.loads(read_config_bytes(path, "cache").decode("utf-8"))
        fetched = datetime.datetime.strptime(document["fetched"], _TIME_STORED).replace(
            tzinfo=datetime.timezone.utc)
        settings = document["settings"]
        version = document.get("klipper_version")
        usable = (document.get("url") == url and isinstance(settings, dict)
                  and all(isinstance(options, dict) for options in settings.values())
                  and (version is None or isinstance(version, str)))
        if version is not None:
            klipper_release(version)
    except KestimatorError as exc:
        raise KestimatorError(f"the settings cache is unusable: {exc.message}", path) from None
    except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError):
        usable = False
    if not usable:
        raise KestimatorError("the settings cache is corrupt (delete it; the next run with "
                              "the printer online writes it again)", path)
    return settings, fetched, version
