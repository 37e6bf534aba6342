"""What Mainsail and Fluidd show during a print, computed by their own code.

`show(cycles, settings)` runs Mainsail's and Fluidd's store code (printer getters, mutations,
default states, unmodified, from the pinned tarballs in ../shared/upstream) in node on a
status stream, one full merged Klipper status per cycle, and returns per cycle what each
getter returned. The node side (unpacked sources, `npm ci` of this harness, esbuild bundles)
is prepared once into a cache directory keyed by everything it is built from; see README.md.

    python3 tests/frontends/frontends.py CYCLES.json [SETTINGS.json]   # JSON lines out
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parents[1]
UPSTREAM = Path(os.environ.get("KESTIMATOR_UPSTREAM", PROJECT.parent / "shared" / "upstream"))
# front end -> (tarball, commit); the tarballs are unmodified `git archive` exports.
SOURCES = {
    "mainsail": ("mainsail-df0ef3e34b57.tar.gz", "df0ef3e34b57"),
    "fluidd": ("fluidd-192279a8c642.tar.gz", "192279a8c642"),
}
# Our own harness files, copied beside the harness's node_modules in the cache.
HARNESS_FILES = ("package.json", "package-lock.json", "build.mjs", "run.mjs",
                 "mainsail.js", "fluidd.js")

# The settings (Moonraker database: namespace -> {key: value}) that make each front end show
# kestimator's time: Mainsail's progress from M73 (display_status.progress), its estimate and
# ETA from "file" (print_duration / progress - print_duration with that progress); Fluidd's
# progress from M73 (its time left and ETA have no setting that uses it; README.md).
KESTIMATOR_SETTINGS: dict[str, dict[str, Any]] = {
    "mainsail": {"general.calcPrintProgress": "slicer",
                 "general.calcEstimateTime": ["file"],
                 "general.calcEtaTime": ["file"]},
    "fluidd": {"uiSettings.general.printProgressCalculation": ["slicer"]},
}
# Moonraker's server.files.metadata fields the getters read (Mainsail's printer.current_file,
# Fluidd's files store entry): the rest of the metadata is passed through untouched.
METADATA_FIELDS = ("filename", "gcode_start_byte", "gcode_end_byte", "filament_total",
                   "estimated_time", "job_id")


class FrontendsUnavailableError(RuntimeError):
    """node, npm or the pinned sources are missing."""


def cache_root() -> Path:
    explicit = os.environ.get("KESTIMATOR_FRONTENDS_CACHE")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "kestimator-frontends"


def _programs() -> tuple[str, str]:
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        raise FrontendsUnavailableError("node and npm are needed (missing: %s)" % ", ".join(
            name for name, path in (("node", node), ("npm", npm)) if path is None))
    return node, npm


def _key() -> str:
    """A digest of everything the prepared directory is made from."""
    digest = hashlib.sha256()
    for name in HARNESS_FILES:
        digest.update(name.encode() + b"\0" + (HERE / name).read_bytes())
    for tarball, commit in SOURCES.values():
        path = UPSTREAM / tarball
        if not path.is_file():
            raise FrontendsUnavailableError("the pinned source %s is missing" % path)
        stat = path.stat()
        digest.update(("%s %s %d\0" % (tarball, commit, stat.st_size)).encode())
    return digest.hexdigest()[:16]


def _unpack_sources(tarball: Path, dest: Path) -> None:
    """Only src/ of a front end's export (all the bundle reads), as ROOT/src."""
    with tarfile.open(tarball) as tar:
        members = []
        for member in tar.getmembers():
            parts = member.name.split("/", 1)
            if len(parts) == 2 and parts[1].startswith("src/") and (member.isfile()
                                                                      or member.isdir()):
                member.name = parts[1]
                members.append(member)
        if sys.version_info >= (3, 12):
            tar.extractall(dest, members=members, filter="data")
        else:
            tar.extractall(dest, members=members)


def prepare() -> Path:
    """The prepared directory (harness with node_modules, bundles in out/): built on first use,
    then reused while nothing it is made from changes."""
    node, npm = _programs()
    commits = "-".join(commit for _, commit in SOURCES.values())
    target = cache_root() / ("%s-%s" % (commits, _key()))
    if (target / "out" / "ready").exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(str(target) + ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # parallel test workers build it once
        if (target / "out" / "ready").exists():
            return target
        work = Path(tempfile.mkdtemp(prefix=target.name + ".", dir=target.parent))
        try:
            for name in HARNESS_FILES:
                shutil.copyfile(HERE / name, work / name)
            for front, (tarball, _) in SOURCES.items():
                _unpack_sources(UPSTREAM / tarball, work / front)
            _run([npm, "ci", "--no-audit", "--no-fund", "--loglevel=error"], work, 600)
            _run([node, "build.mjs", "mainsail", "fluidd", "out"], work, 300)
            (work / "out" / "ready").write_text("")
            shutil.rmtree(target, ignore_errors=True)
            work.rename(target)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return target


def _run(argv: list[str], cwd: Path, timeout: float, stdin: str | None = None) -> str:
    proc = subprocess.run(argv, cwd=cwd, input=stdin, capture_output=True, text=True,
                          timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError("%s failed (rc %d):\n%s%s" % (" ".join(argv), proc.returncode,
                                                         proc.stdout[-3000:],
                                                         proc.stderr[-3000:]))
    return proc.stdout


def nested(flat: dict[str, Any]) -> dict[str, Any]:
    """A namespace's value as Moonraker holds it after post_item with dotted keys."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        node = out
        *parents, last = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    return out


def _number(value: Any) -> float | None:
    """A getter's time as a number (Mainsail's come as toFixed(0) strings, or 0)."""
    if value is None:
        return None
    return float(value)


def show(cycles: list[dict[str, Any]], settings: dict[str, dict[str, Any]],
         metadata: dict[str, Any] | None = None,
         history: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """What Mainsail and Fluidd show at each cycle.

    cycles: {"eventtime": s, "status": {object: {field: value}}} with the full merged status
    (optional "wallclock": s, the time the front end's clock reads; default eventtime).
    settings: Moonraker database entries, {"mainsail": {"general.calcPrintProgress":
    "slicer", ...}, "fluidd": {"uiSettings.general.printProgressCalculation": [...]}}; keys
    not given keep the front end's own defaults. metadata: Moonraker's server.files.metadata
    answer for the printing file (filename as print_stats.filename; the getters read
    METADATA_FIELDS). history: server.history.list jobs (Fluidd's "actual" time when the
    file's job_id names a completed job).

    Each result: {"eventtime", "now_ms", "mainsail": {getter: value, ...}, "fluidd": {...}},
    the raw getter values plus numbers: progress, file_s, filament_s, slicer_s, estimate_s
    (Mainsail's "Estimate"), actual_s (Fluidd), eta_left_s (ETA minus the clock).
    """
    directory = prepare()
    node, _ = _programs()
    document = {"cycles": cycles, "metadata": metadata, "history": history or [],
                "database": {ns: nested(values) for ns, values in settings.items()}}
    text = _run([node, "run.mjs", "out"], directory, 600, json.dumps(document))
    results = []
    for line in text.splitlines():
        row = json.loads(line)
        now = row["now_ms"]
        m = row["mainsail"]
        eta = m["getEstimatedTimeETA"]
        m.update(progress=m["getPrintPercent"], file_s=_number(m["getEstimatedTimeFile"]),
                 filament_s=_number(m["getEstimatedTimeFilament"]),
                 slicer_s=_number(m["getEstimatedTimeSlicer"]),
                 estimate_s=_number(m["getEstimatedTimeAvg"]),
                 eta_left_s=(eta - now) / 1000. if eta else None)
        f = row["fluidd"]
        est = f["getTimeEstimates"]
        f.update(progress=f["getPrintProgress"], file_s=est["fileLeft"],
                 slicer_s=est["slicerLeft"], actual_s=est["actualLeft"],
                 eta_left_s=(est["eta"] - now) / 1000.)
        results.append(row)
    return results


def realtime_view(result: dict[str, Any], settings: dict[str, dict[str, Any]] | None = None,
                  metadata: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Per sample of a real-time print (tests/klipper_module/run_realtime.run_realtime's result:
    `samples` with the full `status`, `eventtime`, `truth_s`), what Mainsail and Fluidd show and
    how far it is from the time Klipper then really took. settings: KESTIMATOR_SETTINGS unless
    given. metadata: Moonraker's for the file (default: its filename only, so the file-position
    progress falls back to virtual_sdcard.progress and there is no slicer time)."""
    samples = result["samples"]
    if metadata is None:
        names = [s["status"].get("print_stats", {}).get("filename") for s in samples]
        metadata = {"filename": next((n for n in names if n), "test.gcode")}
    shown = show([{"eventtime": s["eventtime"], "status": s["status"]} for s in samples],
                 KESTIMATOR_SETTINGS if settings is None else settings, metadata)
    rows = []
    for sample, row in zip(samples, shown):
        truth = sample["truth_s"]
        m, f = row["mainsail"], row["fluidd"]
        view: dict[str, Any] = {
            "eventtime": sample["eventtime"], "truth_s": truth,
            "kestimator_s": sample.get("remaining_s"),
            "mainsail_progress": m["progress"], "mainsail_estimate_s": m["estimate_s"],
            "mainsail_eta_left_s": m["eta_left_s"],
            "fluidd_progress": f["progress"], "fluidd_file_s": f["file_s"],
            "fluidd_eta_left_s": f["eta_left_s"]}
        for name in ("mainsail_estimate_s", "mainsail_eta_left_s", "fluidd_file_s",
                     "fluidd_eta_left_s"):
            value = view[name]
            view[name[:-2] + "_error_s"] = (
                None if value is None or not value else value - truth)
        rows.append(view)
    return rows


def main() -> None:
    cycles = json.loads(Path(sys.argv[1]).read_text())
    settings = json.loads(Path(sys.argv[2]).read_text()) if len(sys.argv) > 2 else {}
    for row in show(cycles, settings):
        print(json.dumps(row))


if __name__ == "__main__":
    main()
