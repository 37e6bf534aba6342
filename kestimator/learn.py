"""What a printer's own job history teaches: the time before the first extrusion, per timelapse
frame and per tool change, and whether the printer runs slower than the planner.

Owns reading Moonraker's history (``GET /server/history/list``: ``{"result": {"count", "jobs":
[{"job_id", "filename", "status", "start_time", "end_time", "print_duration",
"total_duration", "filament_used", "metadata", "auxiliary_data", "exists"}]}}``, see
moonraker/components/history.py), matching each job to the file it printed (``exists`` is
Moonraker's check that the file is still there with the modification time stored in the job's
metadata: a file re-sliced or replaced since was printed with another config), timing that file
with this printer's limits, the robust statistics, and the store: one JSON file per printer
beside the Moonraker settings cache (``learned-<hash of the URL>.json``).

Klipper's ``print_stats`` (klippy/extras/print_stats.py at 84104bbbd) gives, for a job that was
not paused, ``total_duration - print_duration`` = the time before the first extrusion, and
``print_duration`` = everything after it. So per job: start = total - print - (Klipper's motion
before the first extrusion); per frame = (print - motion after the first extrusion) / frames.
Each series is reduced newest first to its median; values further from it than
``OUTLIER_MADS`` scaled median absolute deviations (at least ``MIN_TOLERANCE_R`` of the median,
and ``MIN_TOLERANCE_S``) are rejected (a pause or a filament change lengthens one job), and a
value needs ``MIN_JOBS`` jobs left.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import urllib.parse
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from kestimator.config.moonraker import (
    API_KEY_HEADER,
    MAX_ANSWER_BYTES,
    Deadline,
    cache_path,
    clean_api_key,
    default_cache_dir,
    normalise_url,
    read_bounded,
)
from kestimator.config.resolve import ResolvedLimits
from kestimator.errors import KestimatorError
from kestimator.estimate import Estimate, estimate_file
from kestimator.files import make_temp_file, write_json_privately
from kestimator.limits import Limits
from kestimator.macros import LEARNED_PREP_LABEL, TOOL_CHANGE, MacroTime, MacroTimes

HISTORY_PATH = "/server/history/list"
FILES_PATH = "/server/files/gcodes/"
MAX_HISTORY_JOBS = 50
MIN_JOBS = 3
OUTLIER_MADS = 3.0
MAD_TO_SIGMA = 1.4826
MIN_TOLERANCE_R = 0.02
MIN_TOLERANCE_S = 1.0
# A motion correction is kept only when the printer is slower than the planner by more
# than this ratio and by more than twice the spread.
MIN_SLOWDOWN_R = 0.01
FRAME_MACRO = "TIMELAPSE_TAKE_FRAME"
_TOOL_RE = re.compile(r"T\d+$")
STORE_FORMAT = 1
COMPLETED = "completed"
MAX_FILE_BYTES = 1 << 31
MAX_HISTORY_BYTES = MAX_ANSWER_BYTES
# One deadline for the whole of `kestimator learn` (history, downloads, timing), seconds.
DEFAULT_DEADLINE_S = 600.0
# A socket read waits at most this long (within the deadline).
READ_TIMEOUT_S = 30.0
# The largest value the store keeps (seconds; a ratio for the motion correction).
MAX_VALUE = 1e7
_DATE_STORED = "%Y-%m-%dT%H:%M:%SZ"


@dataclasses.dataclass(frozen=True)
class LearnedValue:
    """One learned number: the median of the jobs kept, their spread, how many."""

    value: float
    spread: float
    """Scaled median absolute deviation of the jobs kept (same unit as value)."""
    jobs: int
    rejected: int


@dataclasses.dataclass(frozen=True)
class LearnedTimes:
    """What one printer's history taught, and when."""

    url: str
    learned_at: str
    before_first_extrusion_s: LearnedValue | None = None
    per_run_s: Mapping[str, LearnedValue] = dataclasses.field(default_factory=dict)
    """``TIMELAPSE_TAKE_FRAME`` per frame, ``T`` per tool change (any T<n>)."""
    motion_ratio: LearnedValue | None = None
    """Actual / planned motion time, only when measurably above 1."""
    jobs_read: int = 0
    notes: tuple[str, ...] = ()

    def source(self, value: LearnedValue) -> str:
        """``learned from 5 prints (spread 2.1 s, 2026-11-23)``."""
        return "learned from %d prints (spread %.3g s, %s)" % (
            value.jobs, value.spread, self.learned_at[:10])

    def macro_times(self, profile: Mapping[str, MacroTime] | None = None) -> MacroTimes:
        """The profile's macro times with the learned ones over them."""
        macros = dict(profile or {})
        for name, value in self.per_run_s.items():
            macros[name] = MacroTime(value.value, self.source(value))
        prep = self.before_first_extrusion_s
        ratio = self.motion_ratio
        return MacroTimes(macros=macros, before_first_extrusion=None if prep is None
                          else MacroTime(prep.value, self.source(prep)),
                          motion_ratio=None if ratio is None else MacroTime(
                              ratio.value, "learned from %d prints (spread %.1f %%, %s)" % (
                                  ratio.jobs, 100 * ratio.spread, self.learned_at[:10])))

    def lines(self) -> list[str]:
        """For people: one line per learned value."""
        out = []
        prep = self.before_first_extrusion_s
        if prep is not None:
            out.append("time %s: %.1f s (%s)" % (LEARNED_PREP_LABEL, prep.value,
                                                 self.source(prep)))
        names = {FRAME_MACRO: "per timelapse frame", TOOL_CHANGE: "per tool change"}
        for name, value in sorted(self.per_run_s.items()):
            out.append("%s (%s): %.2f s (%s)" % (names.get(name, "per run"), name,
                                                 value.value, self.source(value)))
        ratio = self.motion_ratio
        if ratio is not None:
            out.append("motion: the printer takes %.1f %% longer than Klipper's planner "
                       "(spread %.1f %%, %d prints)" % (100 * (ratio.value - 1),
                                                        100 * ratio.spread, ratio.jobs))
        if not out:
            out.append("nothing learned yet: %d jobs read, at least %d usable ones are "
                       "needed per value" % (self.jobs_read, MIN_JOBS))
        return out


def robust(values: Sequence[float]) -> tuple[LearnedValue | None, list[int]]:
    """Median of `values` (newest first) without outliers, and the indexes rejected."""
    import statistics  # only when learning: a start-up cost for every command under PyPy

    if not values:
        return None, []
    median = statistics.median(values)
    mad = MAD_TO_SIGMA * statistics.median(abs(v - median) for v in values)
    tolerance = max(OUTLIER_MADS * mad, MIN_TOLERANCE_R * abs(median), MIN_TOLERANCE_S)
    kept = [v for v in values if abs(v - median) <= tolerance]
    rejected = [i for i, v in enumerate(values) if abs(v - median) > tolerance]
    if len(kept) < MIN_JOBS:
        return None, rejected
    centre = statistics.median(kept)
    spread = MAD_TO_SIGMA * statistics.median(abs(v - centre) for v in kept)
    return LearnedValue(centre, spread, len(kept), len(rejected)), rejected


def value_problem(value: LearnedValue, ratio: bool = False) -> str | None:
    """Why the store would not keep `value` (None: usable). `learn` checks with this before
    storing and the loader when reading, so learn never stores what would be ignored.

    `ratio`: the motion correction (actual / planned, only above 1); else seconds (0 or more).
    """
    if not all(isinstance(n, float) and math.isfinite(n) for n in (value.value, value.spread)):
        return "not a finite number"
    if ratio and value.value <= 1.0:
        return "%.4g is not above 1" % value.value
    if value.value < 0.0:
        return "%.3g s is negative" % value.value
    if value.value >= MAX_VALUE:
        return "%.3g is too large" % value.value
    if value.spread < 0.0:
        return "its spread %.3g is negative" % value.spread
    if value.jobs < MIN_JOBS:
        return "%d jobs are fewer than %d" % (value.jobs, MIN_JOBS)
    if value.rejected < 0:
        return "a negative count of rejected jobs"
    return None


def _kept(value: LearnedValue | None, what: str, why_negative: str, notes: list[str],
          ratio: bool = False) -> LearnedValue | None:
    """`value` if the store would keep it; else None and a note saying why not."""
    problem = None if value is None else value_problem(value, ratio)
    if problem is None:
        return value
    if value is not None and value.value < 0.0:
        problem += " (%s)" % why_negative
    notes.append("%s not stored: %s" % (what, problem))
    return None


@dataclasses.dataclass(frozen=True)
class JobTiming:
    """One completed job and Klipper's times for its file."""

    job_id: str
    filename: str
    total_duration: float
    print_duration: float
    motion_before_s: float
    motion_after_s: float
    frames: int
    tool_changes: int


def timing_of(job: Mapping[str, Any], est: Estimate) -> JobTiming:
    """Pair a job with the estimate of its file (no macro times: Klipper's motion only)."""
    first = est.first_extrusion_t if est.first_extrusion_t is not None else est.total_s
    ignored = est.ignored_commands
    return JobTiming(
        job_id=str(job.get("job_id")), filename=str(job.get("filename")),
        total_duration=float(job["total_duration"]),
        print_duration=float(job["print_duration"]), motion_before_s=first,
        motion_after_s=est.total_s - first, frames=ignored.get(FRAME_MACRO, 0),
        # The first T command selects the tool the print starts with: no change.
        tool_changes=max(0, sum(n for name, n in ignored.items() if _TOOL_RE.match(name)) - 1))


def learn_from(timings: Sequence[JobTiming], url: str, learned_at: str, jobs_read: int,
               notes: Sequence[str]) -> LearnedTimes:
    """The statistics over the matched jobs (newest first)."""
    notes = list(notes)
    prep_values = [t.total_duration - t.print_duration - t.motion_before_s for t in timings]
    prep, rejected = robust(prep_values)
    notes += ["job %s (%s): time before the first extrusion %.0f s is an outlier (a pause?)"
              % (timings[i].job_id, timings[i].filename, prep_values[i]) for i in rejected]
    prep = _kept(prep, "time %s" % LEARNED_PREP_LABEL,
                 "total_duration - print_duration is shorter than Klipper's own motion "
                 "before the first extrusion: the printer adds no time there", notes)
    plain = [t for t in timings if not t.frames and not t.tool_changes and t.motion_after_s > 0]
    ratio, _ = robust([t.print_duration / t.motion_after_s for t in plain]) if plain \
        else (None, [])
    factor = 1.0
    if ratio is not None and (ratio.value - 1.0 <= max(MIN_SLOWDOWN_R, 2 * ratio.spread)):
        ratio = None
    ratio = _kept(ratio, "motion correction", "", notes, ratio=True)
    if ratio is not None:
        factor = ratio.value
    per_run: dict[str, LearnedValue] = {}
    for name, count in ((FRAME_MACRO, lambda t: t.frames if not t.tool_changes else 0),
                        (TOOL_CHANGE, lambda t: t.tool_changes if not t.frames else 0)):
        usable = [t for t in timings if count(t) > 0]
        values = [(t.print_duration - factor * t.motion_after_s) / count(t) for t in usable]
        learned, rejected = robust(values)
        notes += ["job %s (%s): %.2f s per run of %s is an outlier" % (
            usable[i].job_id, usable[i].filename, values[i], name) for i in rejected]
        learned = _kept(learned, "time per run of %s" % name,
                        "print_duration is shorter than Klipper's motion after the first "
                        "extrusion", notes)
        if learned is not None:
            per_run[name] = learned
    return LearnedTimes(url=url, learned_at=learned_at, before_first_extrusion_s=prep,
                        per_run_s=per_run, motion_ratio=ratio, jobs_read=jobs_read,
                        notes=tuple(notes))


class _TimeUpError(KestimatorError):
    """The deadline of the whole `learn` passed (worded by `learn_from_moonraker`)."""


class _Client:
    """GET requests to one Moonraker: no proxy, no redirects, the key in its header only,
    every connection cut when the one deadline of the whole `learn` passes."""

    def __init__(self, url: str, api_key: str | None, deadline: Deadline) -> None:
        import urllib.request

        class NoRedirect(urllib.request.HTTPRedirectHandler):
            def redirect_request(self, req: urllib.request.Request, fp: Any, code: int,
                                 msg: str, headers: Any, newurl: str) -> None:
                return None

        self.url = url
        # Whitespace (CR/LF) stripped, control characters refused without showing the key.
        self.api_key = clean_api_key(api_key)
        self.deadline = deadline
        self.opener = urllib.request.build_opener(urllib.request.ProxyHandler({}),
                                                  NoRedirect(), *deadline.handlers())

    def check_time(self) -> None:
        if self.deadline.expired:
            raise _TimeUpError("deadline")

    def open(self, path: str) -> Any:
        import http.client
        import urllib.error
        import urllib.request

        self.check_time()
        request = urllib.request.Request(self.url + path)
        if self.api_key:
            request.add_header(API_KEY_HEADER, self.api_key)
        try:
            return self.opener.open(request, timeout=max(0.01, min(
                READ_TIMEOUT_S, self.deadline.remaining())))
        except urllib.error.HTTPError as exc:
            exc.close()
            if exc.code in (401, 403):
                raise KestimatorError(f"Moonraker at {self.url} refused the request "
                                      f"({exc.code}): give its API key with --api-key") from None
            raise KestimatorError(f"Moonraker at {self.url} answered {exc.code} to "
                                  f"{path.split('?')[0]}") from None
        except (urllib.error.URLError, http.client.HTTPException, OSError, ValueError) as exc:
            self.check_time()
            why = getattr(exc, "reason", None) or exc
            raise KestimatorError(f"Moonraker at {self.url} did not answer ({why})") from None

    def read(self, response: Any, limit: int) -> bytes:
        """At most `limit` + 1 bytes of `response`, within the deadline."""
        import http.client

        try:
            body = read_bounded(response, self.deadline, limit)
        except (http.client.HTTPException, OSError, ValueError) as exc:
            self.check_time()
            raise KestimatorError(f"Moonraker at {self.url} broke off its answer ({exc})"
                                  ) from None
        self.check_time()  # a body cut by the deadline ends early: never taken as whole
        return body

    def jobs(self, limit: int) -> list[dict[str, Any]]:
        """The newest `limit` jobs (however many the server sends)."""
        with self.open(f"{HISTORY_PATH}?limit={limit}&order=desc") as response:
            body = self.read(response, MAX_HISTORY_BYTES)
        if len(body) > MAX_HISTORY_BYTES:
            raise KestimatorError(f"Moonraker at {self.url} answered more than "
                                  f"{MAX_HISTORY_BYTES} bytes for its job history")
        try:
            jobs = json.loads(body)["result"]["jobs"]
        except (ValueError, KeyError, TypeError, IndexError, RecursionError):
            raise KestimatorError(f"Moonraker at {self.url} did not answer with its job "
                                  "history (result.jobs)") from None
        if not isinstance(jobs, list):
            raise KestimatorError(f"Moonraker at {self.url}: result.jobs is not a list")
        return [job for job in jobs[:limit] if isinstance(job, dict)]

    def download(self, filename: str, directory: str) -> str:
        path = os.path.join(directory, "job.gcode")
        with self.open(FILES_PATH + urllib.parse.quote(filename)) as response, \
                open(path, "wb") as out:
            done = 0
            while True:
                block = self.read(response, 1 << 20)
                if not block:
                    break
                done += len(block)
                if done > MAX_FILE_BYTES:
                    raise KestimatorError(f"{filename} on Moonraker is too large to learn from")
                out.write(block)
        return path


def _job_problem(job: Mapping[str, Any]) -> str | None:
    status = job.get("status")
    if status != COMPLETED:
        return "status %s" % _shown(status)
    if not job.get("exists", False):
        return "its file is gone or changed since (printed with another slicing or config)"
    for key in ("total_duration", "print_duration"):
        value = job.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                0.0 <= value < 1e9):
            return "no usable %s" % key
    if not isinstance(job.get("filename"), str) or not job["filename"]:
        return "no file name"
    return None


def _shown(value: object) -> str:
    """A value from a server, safe to print: printable ASCII, at most 60 characters."""
    if isinstance(value, (dict, list)):  # never str() of a nested answer: its depth, its size
        return "<%s>" % type(value).__name__
    try:
        text = value[:60] if isinstance(value, str) else str(value)[:60]
    except ValueError:  # an int too long to show
        text = "<number>"
    return "".join(c if " " <= c <= "~" else "?" for c in text)


def _now_text() -> str:
    import datetime

    return datetime.datetime.now(datetime.timezone.utc).strftime(_DATE_STORED)


def learn_from_moonraker(url: str, limits: Limits, api_key: str | None = None,
                         deadline_s: float = DEFAULT_DEADLINE_S,
                         max_jobs: int = MAX_HISTORY_JOBS,
                         now: Callable[[], str] = _now_text,
                         started: float | None = None) -> LearnedTimes:
    """Read the history, time each completed job's file with `limits`, learn.

    At most `max_jobs` jobs are read whatever the server sends; `deadline_s` bounds the whole
    (every request, every download and the timing), counted from `started` (a
    ``time.monotonic()``; default: now): when it passes, KestimatorError.
    """
    import time

    url = normalise_url(url)
    spent = 0.0 if started is None else time.monotonic() - started
    deadline = Deadline(deadline_s - spent)
    try:
        client = _Client(url, api_key, deadline)
        return _learn(client, limits, max(1, max_jobs), now)
    except _TimeUpError:
        raise KestimatorError(f"learn did not finish within {deadline_s:g} s (Moonraker at "
                              f"{url} answered too slowly, or too much to time): nothing "
                              "stored; give more time with --timeout") from None
    finally:
        deadline.cancel()


def _learn(client: _Client, limits: Limits, max_jobs: int,
           now: Callable[[], str]) -> LearnedTimes:
    import tempfile

    jobs = client.jobs(max_jobs)
    notes: list[str] = []
    timings: list[JobTiming] = []
    estimates: dict[str, Estimate] = {}

    def in_time(_bytes_read: int) -> None:
        client.check_time()

    with tempfile.TemporaryDirectory(prefix="kestimator-learn-") as directory:
        for job in jobs:
            client.check_time()
            label = "job %s (%s)" % (_shown(job.get("job_id")), _shown(job.get("filename")))
            problem = _job_problem(job)
            if problem is not None:
                notes.append("%s: not used, %s" % (label, problem))
                continue
            filename = job["filename"]
            est = estimates.get(filename)
            if est is None:
                try:
                    est = estimate_file(client.download(filename, directory), limits,
                                        progress=in_time)
                except _TimeUpError:
                    raise
                except KestimatorError as exc:
                    notes.append("%s: not used, %s" % (label, _shown(exc.message)))
                    continue
                estimates[filename] = est
            timings.append(timing_of(dict(job, job_id=_shown(job.get("job_id")),
                                          filename=_shown(filename)), est))
    client.check_time()
    return learn_from(timings, client.url, now(), len(jobs), notes)


def moonraker_url_of(resolved: ResolvedLimits) -> str | None:
    """The Moonraker the limits came from (also from its offline cache), if any."""
    machine = resolved.machine or ""
    if not machine.startswith("moonraker "):
        return None
    return machine.split()[1]


def learned_for(resolved: ResolvedLimits) -> LearnedTimes | None:
    """What was learned for the Moonraker the limits came from, if anything."""
    return learned_with_warnings(resolved)[0]


def learned_with_warnings(resolved: ResolvedLimits
                          ) -> tuple[LearnedTimes | None, tuple[str, ...]]:
    """What was learned for the Moonraker the limits came from, and what of it is not used
    (see `load_with_warnings`)."""
    url = moonraker_url_of(resolved)
    return (None, ()) if url is None else load_with_warnings(url)


def macro_times_for(resolved: ResolvedLimits, use_learned: bool = True) -> MacroTimes:
    """The profile's macro times, with what was learned for this printer over them
    (``warnings``: what of the learned store is not used, for the caller to show)."""
    learned, warnings = learned_with_warnings(resolved) if use_learned else (None, ())
    if learned is None:
        return MacroTimes(macros=dict(resolved.macro_times), warnings=warnings)
    return dataclasses.replace(learned.macro_times(resolved.macro_times), warnings=warnings)


def store_path(url: str, directory: Path) -> Path:
    """The learned times of one Moonraker, beside its settings cache."""
    settings = cache_path(normalise_url(url), directory)
    return settings.with_name(settings.name.replace("moonraker-", "learned-", 1))


def check_store(url: str, directory: Path | None = None) -> Path:
    """The store of `url`, once its directory is known to take a file: made (0700) if
    missing and a file created in it and removed. `learn` calls this before downloading
    anything. KestimatorError (one line) if it cannot be written."""
    directory = directory if directory is not None else default_cache_dir(os.environ)
    path = store_path(url, directory)
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        handle, temp = make_temp_file(".learn-check-", ".tmp", str(path.parent))
        os.close(handle)
        os.unlink(temp)
    except OSError as exc:
        raise KestimatorError(_unwritable(path, exc)) from None
    return path


def _unwritable(path: Path, exc: OSError) -> str:
    return ("cannot store the learned times in %s: %s (set $XDG_CACHE_HOME to a directory "
            "you may write)" % (path.parent, exc.strerror or exc))


def save(learned: LearnedTimes, directory: Path | None = None) -> Path:
    """Write the learned times atomically; the file's path (KestimatorError if it cannot)."""
    directory = directory if directory is not None else default_cache_dir(os.environ)
    path = store_path(learned.url, directory)
    document = {"format": STORE_FORMAT, **dataclasses.asdict(learned)}
    try:
        write_json_privately(path, document)
    except OSError as exc:
        raise KestimatorError(_unwritable(path, exc)) from None
    return path


def _value(raw: object, ratio: bool = False) -> LearnedValue | None:
    """One stored value; ValueError (why) for one the store would not keep."""
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ValueError("not an object")
    numbers = [raw.get(key) for key in ("value", "spread", "jobs", "rejected")]
    if any(isinstance(n, bool) or not isinstance(n, (int, float)) for n in numbers) or not all(
            isinstance(n, int) for n in numbers[2:]):
        raise ValueError("not {value, spread, jobs, rejected} numbers")
    value = LearnedValue(float(raw["value"]), float(raw["spread"]), int(raw["jobs"]),
                         int(raw["rejected"]))
    problem = value_problem(value, ratio)
    if problem is not None:
        raise ValueError(problem)
    return value


def load(url: str, directory: Path | None = None) -> LearnedTimes | None:
    """The stored learned times of the Moonraker at `url`, None if none (or unusable)."""
    return load_with_warnings(url, directory)[0]


def load_with_warnings(url: str, directory: Path | None = None
                       ) -> tuple[LearnedTimes | None, tuple[str, ...]]:
    """The stored learned times of the Moonraker at `url` (None if there are none or the
    file is unusable) and one warning per value, or for the whole file, not used.

    A value the store would not keep is dropped on its own: the others are still used."""
    directory = directory if directory is not None else default_cache_dir(os.environ)
    url = normalise_url(url)
    path = store_path(url, directory)
    redo = "run kestimator learn again"
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None, ()
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else "not UTF-8 text"
        return None, ("learned times in %s not used: %s" % (path, why),)
    try:
        document = json.loads(text)
        if not isinstance(document, dict):
            raise ValueError("not a JSON object")
        if document.get("format") != STORE_FORMAT:
            raise ValueError("format %s, not %d" % (_shown(document.get("format")),
                                                   STORE_FORMAT))
        if document.get("url") != url:
            raise ValueError("written for another URL")
        learned_at = document["learned_at"]
        raw_per_run = document.get("per_run_s") or {}
        jobs_read = document.get("jobs_read", 0)
        notes = document.get("notes") or []
        if not (isinstance(learned_at, str) and isinstance(raw_per_run, dict)
                and isinstance(jobs_read, int) and isinstance(notes, list)):
            raise ValueError("learned_at, per_run_s, jobs_read or notes of the wrong type")
    except (ValueError, KeyError, RecursionError) as exc:
        why = "not JSON" if isinstance(exc, (json.JSONDecodeError, RecursionError)) else (
            "no %s" % exc if isinstance(exc, KeyError) else str(exc))
        return None, ("learned times in %s not used: %s (%s)" % (path, why, redo),)
    warnings: list[str] = []

    def kept(name: str, raw: object, ratio: bool = False) -> LearnedValue | None:
        try:
            return _value(raw, ratio)
        except ValueError as exc:
            warnings.append("learned %s in %s not used: %s (%s)" % (name, path, exc, redo))
            return None

    prep = kept("time " + LEARNED_PREP_LABEL, document.get("before_first_extrusion_s"))
    per_run = {str(name): kept("time per run of " + _shown(name), raw)
               for name, raw in raw_per_run.items()}
    ratio = kept("motion correction", document.get("motion_ratio"), ratio=True)
    learned = LearnedTimes(
        url=url, learned_at=learned_at, before_first_extrusion_s=prep,
        per_run_s={name: v for name, v in per_run.items() if v is not None},
        motion_ratio=ratio, jobs_read=jobs_read,
        notes=tuple(note for note in notes if isinstance(note, str)))
    return learned, tuple(warnings)
