"""A real screenshot of Mainsail's status panel during a print, fed by a recorded status stream.

Builds Mainsail (the pinned upstream tarball, unmodified sources) once into a cache directory,
serves the built UI beside a small fake Moonraker of our own (JSON-RPC over a websocket, on
127.0.0.1 only) that answers what Mainsail asks on connect with the printer's state at one
status cycle of a recording, and has headless Chromium photograph the status panel.

    python3 tools/mainsail_screenshot.py            # docs/images/mainsail_status_kestimator.png
    python3 tools/mainsail_screenshot.py KTEST.json [--at 0.4] [--out PNG] [--tz UTC]
    python3 tools/mainsail_screenshot.py [KTEST.json] --serve [--play]   # browse it yourself
    python3 tools/mainsail_screenshot.py KTEST.json --save-recording OUT.json.gz
    python3 tools/mainsail_screenshot.py --prepare-only                  # just build the UI

KTEST.json is what tests/klipper_module/run_realtime.py FILE.gcode --keep leaves (its
`stream`: each status cycle's Moonraker-style notify_status_update params, {eventtime,
status}); the G-code is read from `sd/<print_stats.filename>` beside it (or --gcode) for the
file's metadata, and the printer's config from `printer.cfg` beside it ([include]s
followed). --save-recording packs those into one small file; the default recording,
tools/mainsail_screenshot/ps25_nut_accelA_small.recording.json.gz, is the one the docs image
is made from (the G-code is then read from the corpus, ../shared/corpus or
$KESTIMATOR_CORPUS, and checked by its sha256).

The shown cycle is the first one printing whose display_status.progress reaches --at.
Mainsail's Moonraker database namespace "mainsail" holds
tools/mainsail_screenshot/mainsail_namespace.json (the three settings that make it show the
module's time). The browser's clock is held at the cycle's wall time (kestimator.eta -
kestimator.remaining_s), so the ETA shown is the module's ETA, written in --tz (en-US, 12-hour).
The tool prints what Mainsail should show (Estimate = D / progress - D, ETA = now + that), the
panel's text, and exits 1 if the two differ. A recording older than the module's
D / (D + R) display_status (where display_status.progress was kestimator.progress, 1 - R / T)
is detected and display_status.progress recomputed per cycle as D / (D + R) from
print_stats.print_duration and kestimator.remaining_s of that cycle (--progress forces or
keeps it).

The recording subscribes only what the module's tests need, so what a real Klipper always
has and the panel's Speed, Flow and Layer read (gcode_move's position and speed,
motion_report, toolhead's limits) is derived from the G-code at the cycle's file position
(derived_objects); the progress, Estimate, Slicer, Total, Filament and ETA come from the
recording alone.

Needs: node 20+ and npm (the npm registry reachable for the first build), chromium (Debian:
apt-get install -y chromium), Python 3.9+ (standard library only) and the pinned tarball
../shared/upstream/mainsail-df0ef3e34b57.tar.gz ($KESTIMATOR_UPSTREAM overrides the
directory). The build goes to ~/.cache/kestimator-mainsail-ui/<commit>/ ($XDG_CACHE_HOME
honoured, $KESTIMATOR_MAINSAIL_UI_CACHE overrides): the tarball unpacked, a build-time copy of
package.json without `cypress` and with `@vitejs/plugin-vue2` for `@pedrolamas/plugin-vue2`
(which this registry lacks; esbuild for its TypeScript), a copy of vite.config.ts with that
import and without the vite-plugin-checker type check (it fails on the dropped cypress
types), `npm install --legacy-peer-deps` (about 570 MB) and `vite build`: about 40 s with
npm's download cache warm. Nothing of Mainsail is copied into this project.
"""

from __future__ import annotations

import argparse
import base64
import datetime
import gzip
import hashlib
import http.server
import io
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parent
SUPPORT = HERE / "mainsail_screenshot"
UPSTREAM = Path(os.environ.get("KESTIMATOR_UPSTREAM", PROJECT.parent / "shared" / "upstream"))
TARBALL, COMMIT = "mainsail-df0ef3e34b57.tar.gz", "df0ef3e34b57"
WS_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
CORPUS = Path(os.environ.get("KESTIMATOR_CORPUS", PROJECT.parent / "shared" / "corpus"))
DEFAULT_OUT = PROJECT / "docs" / "images" / "mainsail_status_kestimator.png"
# The recording docs/images/mainsail_status_kestimator.png is made from (--save-recording).
RECORDING = SUPPORT / "ps25_nut_accelA_small.recording.json.gz"
# Klipper objects Mainsail's dashboard looks for that the recording does not subscribe.
EXTRA_OBJECTS = ("configfile", "webhooks")


# ---------------------------------------------------------------------------------------------
# Building Mainsail in the cache


def cache_root() -> Path:
    explicit = os.environ.get("KESTIMATOR_MAINSAIL_UI_CACHE")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "kestimator-mainsail-ui"


def _build_package_json(text: str) -> str:
    """package.json for the build: cypress dropped, the registry's Vue 2 plugin for Pedro
    Lamas's fork, esbuild (that plugin compiles TypeScript in .vue files with it)."""
    package = json.loads(text)
    dev = package["devDependencies"]
    dev.pop("cypress", None)
    dev.pop("@pedrolamas/plugin-vue2", None)
    dev["@vitejs/plugin-vue2"] = "^2.3.4"
    dev["esbuild"] = "^0.25.0"
    return json.dumps(package, indent=4) + "\n"


def _build_vite_config(text: str) -> str:
    """vite.config.ts for the build: the replacement plugin's import, no type-check plugin."""
    if "@pedrolamas/plugin-vue2" not in text:
        raise RuntimeError("vite.config.ts no longer imports @pedrolamas/plugin-vue2")
    text = text.replace("@pedrolamas/plugin-vue2", "@vitejs/plugin-vue2")
    text, n = re.subn(r"\n        checker\(\{.*?\n        \}\),", "", text, flags=re.S)
    if n != 1:
        raise RuntimeError("vite.config.ts: the checker({...}) plugin entry was not found")
    return text


def prepare_ui(log: Callable[[str], None] = print) -> Path:
    """Mainsail built into the cache (once); the path of its dist/."""
    tarball = UPSTREAM / TARBALL
    root = cache_root() / COMMIT
    dist = root / "mainsail" / "dist"
    stamp = root / "built.stamp"
    if stamp.is_file() and (dist / "index.html").is_file():
        return dist
    for program in ("node", "npm"):
        if shutil.which(program) is None:
            raise RuntimeError("%s is needed to build Mainsail" % program)
    if not tarball.is_file():
        raise RuntimeError("the pinned Mainsail tarball is missing: %s" % tarball)
    started = time.monotonic()
    if root.exists():
        shutil.rmtree(root)
    root.mkdir(parents=True)
    log("unpacking %s into %s" % (tarball.name, root))
    with tarfile.open(tarball) as tar:
        if sys.version_info >= (3, 12):
            tar.extractall(root, filter="data")
        else:
            tar.extractall(root)  # noqa: S202 - our own pinned export
    src = root / "mainsail"
    package = src / "package.json"
    package.write_text(_build_package_json(package.read_text()))
    config = src / "vite.config.kestimator.ts"
    config.write_text(_build_vite_config((src / "vite.config.ts").read_text()))
    log("npm install (about 570 MB of node_modules) ...")
    subprocess.run(["npm", "install", "--legacy-peer-deps", "--no-audit", "--no-fund"],
                   cwd=src, check=True, timeout=1800)
    log("vite build ...")
    subprocess.run(["npx", "vite", "build", "--config", config.name], cwd=src, check=True,
                   timeout=1800)
    stamp.write_text("built in %.0f s\n" % (time.monotonic() - started))
    log("Mainsail built in %.0f s" % (time.monotonic() - started))
    return dist


# ---------------------------------------------------------------------------------------------
# The recording: per-cycle states, the shown cycle, the file's metadata, the printer's config


def load_recording(path: Path) -> dict[str, Any]:
    """A kept ktest.json or a saved recording (gzip-compressed if its name ends in .gz)."""
    data = path.read_bytes()
    if path.suffix == ".gz":
        data = gzip.decompress(data)
    recording: dict[str, Any] = json.loads(data)
    return recording


def save_recording(ktest: Path, out: Path) -> None:
    """A kept run_realtime.py directory's ktest.json as one small file: the status stream, the
    printer's config (read from printer.cfg beside it, [include]s followed, local paths of
    the harness left out) and the printed file as a corpus path when it is a corpus file."""
    kept = json.loads(ktest.read_text())
    stream = kept["stream"]
    filename = merged_cycles(stream)[-1]["status"]["print_stats"]["filename"]
    config = read_printer_cfg(ktest.parent / "printer.cfg")
    config.get("kestimator", {}).pop("python", None)
    config.get("virtual_sdcard", {}).pop("path", None)
    recording: dict[str, Any] = {
        "about": "A Klipper status stream (Moonraker notify_status_update params per cycle) "
                 "recorded by tests/klipper_module/run_realtime.py --keep; see "
                 "tools/mainsail_screenshot.py",
        "stream": stream, "config": config}
    for key in ("clock_offset", "end_print_time", "gaps", "state"):
        if key in kept:
            recording[key] = kept[key]
    printed = (ktest.parent / "sd" / filename).read_bytes()
    digest = hashlib.sha256(printed).hexdigest()
    for candidate in sorted(CORPUS.glob("gcode/**/*.gcode")):
        if candidate.stat().st_size == len(printed) and \
                hashlib.sha256(candidate.read_bytes()).hexdigest() == digest:
            recording["gcode"] = str(candidate.relative_to(CORPUS))
            break
    recording["gcode_sha256"] = digest
    text = json.dumps(recording, separators=(",", ":"), sort_keys=True).encode()
    out.write_bytes(gzip.compress(text, 9, mtime=0) if out.suffix == ".gz" else text)


def merged_cycles(stream: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each cycle's full state (the stream carries only what changed)."""
    state: dict[str, dict[str, Any]] = {}
    cycles = []
    for cycle in stream:
        for name, fields in cycle["status"].items():
            state.setdefault(name, {}).update(fields)
        cycles.append({"eventtime": cycle["eventtime"], "status": json.loads(json.dumps(state))})
    return cycles


def d_over_d_plus_r(status: dict[str, Any]) -> float | None:
    """D / (D + R) from print_stats.print_duration and kestimator.remaining_s, or None."""
    stats, module = status.get("print_stats", {}), status.get("kestimator", {})
    if stats.get("state") not in ("printing", "paused"):
        return None
    remaining = module.get("remaining_s")
    duration = stats.get("print_duration")
    if remaining is None or duration is None or duration + remaining <= 0:
        return None
    return float(duration) / (float(duration) + float(remaining))


def progress_is_old_style(cycles: list[dict[str, Any]]) -> bool:
    """True for a recording from before the module's D / (D + R): its display_status.progress
    was the module's own progress, 1 - R / T (kestimator.progress), on most printing cycles."""
    same = total = 0
    for cycle in cycles:
        status = cycle["status"]
        shown = status.get("display_status", {}).get("progress")
        own = status.get("kestimator", {}).get("progress")
        if d_over_d_plus_r(status) is None or shown is None or own is None:
            continue
        total += 1
        same += abs(float(shown) - float(own)) < 1e-9
    return total > 0 and same * 2 > total


def recompute_progress(stream: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The stream with display_status.progress = D / (D + R) added to each printing cycle."""
    state: dict[str, dict[str, Any]] = {}
    out = []
    for cycle in stream:
        for name, fields in cycle["status"].items():
            state.setdefault(name, {}).update(fields)
        status = json.loads(json.dumps(cycle["status"]))
        progress = d_over_d_plus_r(state)
        if progress is not None:
            status.setdefault("display_status", {})["progress"] = progress
        out.append({"eventtime": cycle["eventtime"], "status": status})
    return out


def choose_cycle(cycles: list[dict[str, Any]], at: float) -> int:
    for index, cycle in enumerate(cycles):
        status = cycle["status"]
        if (status.get("print_stats", {}).get("state") == "printing"
                and status.get("kestimator", {}).get("remaining_s") is not None
                and float(status.get("display_status", {}).get("progress") or 0.) >= at):
            return index
    raise RuntimeError("no printing cycle reaches progress %.2f" % at)


def _duration_s(text: str) -> float:
    total = 0.
    for value, unit in re.findall(r"(\d+(?:\.\d+)?)\s*([dhms])", text):
        total += float(value) * {"d": 86400, "h": 3600, "m": 60, "s": 1}[unit]
    return total


def gcode_metadata(path: Path, filename: str) -> dict[str, Any]:
    """Moonraker-style server.files.metadata for a G-code file, from its slicer comments
    (PrusaSlicer / SuperSlicer / OrcaSlicer style) and its first and last G-code lines."""
    data = path.read_bytes()
    meta: dict[str, Any] = {"filename": filename, "size": len(data),
                            "modified": path.stat().st_mtime}
    lines = data.split(b"\n")
    start = end = None
    offset = 0
    for line in lines:
        stripped = line.strip()
        if stripped and not stripped.startswith(b";"):
            if start is None:
                start = offset
            end = offset + len(line) + 1
        offset += len(line) + 1
    if start is not None and end is not None:
        meta["gcode_start_byte"], meta["gcode_end_byte"] = start, min(end, len(data))
    text = data.decode("utf-8", "replace")
    first = re.search(r"^; generated by (\S+) (\S+)", text, re.M)
    if first:
        meta["slicer"], meta["slicer_version"] = first.group(1), first.group(2)
    found = re.search(r"^; estimated printing time \(normal mode\) = (.+)$", text, re.M)
    if found:
        meta["estimated_time"] = round(_duration_s(found.group(1)))
    for key, pattern in (("filament_total", r"^; filament used \[mm\] = ([\d.]+)"),
                         ("layer_height", r"^; layer_height = ([\d.]+)"),
                         ("first_layer_height", r"^; first_layer_height = ([\d.]+)"),
                         ("nozzle_diameter", r"^; nozzle_diameter = ([\d.]+)")):
        found = re.search(pattern, text, re.M)
        if found:
            meta[key] = float(found.group(1))
    heights = [float(z) for z in re.findall(r"^;Z:([\d.]+)", text, re.M)]
    if heights:
        meta["object_height"] = max(heights)
    return meta


def read_printer_cfg(path: Path) -> dict[str, dict[str, str]]:
    """Klipper's config sections (lower-case names and keys), [include]s followed."""
    sections: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    key = None
    for raw in path.read_text().splitlines():
        line = re.split(r"\s[#;]", raw, maxsplit=1)[0].rstrip()
        if not line.strip() or line.lstrip().startswith(("#", ";")):
            continue
        header = re.match(r"^\[([^\]]+)\]", line)
        if header:
            name = header.group(1).strip()
            if name.startswith("include "):
                included = (path.parent / name[len("include "):].strip()).resolve()
                for sub, values in read_printer_cfg(included).items():
                    sections.setdefault(sub, {}).update(values)
                current = None
            else:
                current = sections.setdefault(name.lower(), {})
            key = None
            continue
        if current is None:
            continue
        if line[0].isspace() and key is not None:
            current[key] += "\n" + line.strip()
            continue
        pair = re.match(r"^([^:=]+)[:=](.*)$", line)
        if pair:
            key = pair.group(1).strip().lower()
            current[key] = pair.group(2).strip()
    return sections


def typed_settings(config: dict[str, dict[str, str]]) -> dict[str, dict[str, Any]]:
    """configfile.settings as Klipper types them: numbers as numbers."""
    settings: dict[str, dict[str, Any]] = {}
    for section, values in config.items():
        settings[section] = {}
        for key, value in values.items():
            try:
                settings[section][key] = float(value)
            except ValueError:
                settings[section][key] = value
    return settings


def gcode_state_at(data: bytes, file_position: int) -> dict[str, Any]:
    """The G-code's state once Klipper has read up to `file_position`: position (X, Y, Z, E),
    the feed rate (mm/min) and the last move's direction (dx, dy, dz, de)."""
    pos = {"X": 0., "Y": 0., "Z": 0., "E": 0.}
    feed, last = 1500., (0., 0., 0., 0.)
    absolute, absolute_e = True, True
    for raw in data[:file_position].split(b"\n"):
        line = raw.split(b";", 1)[0].decode("ascii", "replace").strip().upper()
        if not line:
            continue
        words = line.split()
        cmd = words[0]
        args = {}
        for word in words[1:]:
            try:
                args[word[0]] = float(word[1:])
            except (ValueError, IndexError):
                pass
        if cmd == "G90":
            absolute = absolute_e = True
        elif cmd == "G91":
            absolute = absolute_e = False
        elif cmd == "M82":
            absolute_e = True
        elif cmd == "M83":
            absolute_e = False
        elif cmd == "G92":
            for axis in pos:
                if axis in args:
                    pos[axis] = args[axis]
        elif cmd in ("G0", "G1"):
            before = dict(pos)
            for axis in pos:
                if axis in args:
                    relative = not (absolute_e if axis == "E" else absolute)
                    pos[axis] = pos[axis] + args[axis] if relative else args[axis]
            if "F" in args:
                feed = args["F"]
            delta = tuple(pos[a] - before[a] for a in ("X", "Y", "Z", "E"))
            if any(delta[:3]):
                last = (delta[0], delta[1], delta[2], delta[3])
    return {"position": [pos["X"], pos["Y"], pos["Z"], pos["E"]], "feed": feed, "last": last}


def _axis_limit(settings: dict[str, dict[str, Any]], axis: str, key: str) -> float:
    return float(settings.get("stepper_" + axis, {}).get(key, 0.))


def derived_objects(gcode: bytes, status: dict[str, Any],
                    settings: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """What Klipper always has and the recording did not subscribe, from the G-code at the
    cycle's file position: gcode_move's position and requested speed, motion_report (the
    nominal speed of the move being printed, capped at max_velocity, and its extrusion
    rate), toolhead's limits and homed axes. Only the status panel's Speed, Flow and Layer
    read these; its progress and times come from the recording alone."""
    at = gcode_state_at(gcode, int(status.get("virtual_sdcard", {}).get("file_position", 0)))
    factor = float(status.get("gcode_move", {}).get("speed_factor", 1.))
    printer = settings.get("printer", {})
    max_velocity = float(printer.get("max_velocity", 300.))
    dx, dy, dz, de = at["last"]
    distance = (dx * dx + dy * dy + dz * dz) ** .5
    velocity = min(at["feed"] / 60. * factor, max_velocity)
    extruder_velocity = velocity * de / distance if distance > 0 else 0.
    position = at["position"]
    return {
        "gcode_move": {"speed": at["feed"], "gcode_position": position, "position": position,
                       "homing_origin": [0., 0., 0., 0.], "absolute_coordinates": True,
                       "absolute_extrude": False, "extrude_factor": 1.},
        "motion_report": {"live_position": position, "live_velocity": velocity,
                          "live_extruder_velocity": extruder_velocity,
                          "steppers": [], "trapq": []},
        "toolhead": {"homed_axes": "xyz", "max_velocity": max_velocity,
                     "max_accel": float(printer.get("max_accel", 3000.)),
                     "square_corner_velocity": float(printer.get("square_corner_velocity", 5.)),
                     "minimum_cruise_ratio": float(printer.get("minimum_cruise_ratio", .5)),
                     "position": position, "extruder": "extruder",
                     "axis_minimum": [_axis_limit(settings, a, "position_min") for a in "xyz"]
                     + [0.],
                     "axis_maximum": [_axis_limit(settings, a, "position_max") for a in "xyz"]
                     + [0.]},
    }


# ---------------------------------------------------------------------------------------------
# Websocket framing (RFC 6455), enough for JSON text messages both ways


def ws_send(out: io.BufferedIOBase, text: str, mask: bool, lock: threading.Lock) -> None:
    payload = text.encode()
    head = bytearray([0x81])
    mask_bit = 0x80 if mask else 0
    if len(payload) < 126:
        head.append(mask_bit | len(payload))
    elif len(payload) < 1 << 16:
        head.append(mask_bit | 126)
        head += struct.pack(">H", len(payload))
    else:
        head.append(mask_bit | 127)
        head += struct.pack(">Q", len(payload))
    if mask:
        key = os.urandom(4)
        head += key
        payload = bytes(b ^ key[i % 4] for i, b in enumerate(payload))
    with lock:
        out.write(bytes(head) + payload)
        out.flush()


def _read_exact(inp: io.BufferedIOBase, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = inp.read(n - len(data))
        if not chunk:
            raise ConnectionError("websocket closed")
        data += chunk
    return data


def ws_receive(inp: io.BufferedIOBase) -> tuple[int, bytes]:
    """The next whole message: (opcode, payload); continuation frames joined."""
    message = b""
    opcode = None
    while True:
        b0, b1 = _read_exact(inp, 2)
        length = b1 & 0x7F
        if length == 126:
            length = struct.unpack(">H", _read_exact(inp, 2))[0]
        elif length == 127:
            length = struct.unpack(">Q", _read_exact(inp, 8))[0]
        key = _read_exact(inp, 4) if b1 & 0x80 else None
        payload = _read_exact(inp, length)
        if key is not None:
            payload = bytes(b ^ key[i % 4] for i, b in enumerate(payload))
        frame_op = b0 & 0x0F
        if frame_op >= 8:  # control frames may come between fragments
            return frame_op, payload
        if opcode is None:
            opcode = frame_op
        message += payload
        if b0 & 0x80:
            return opcode, message


# ---------------------------------------------------------------------------------------------
# The fake Moonraker


class FakeMoonraker:
    """Answers Mainsail's JSON-RPC requests with the recorded printer at one cycle."""

    def __init__(self, cycles: list[dict[str, Any]], stream: list[dict[str, Any]], index: int,
                 metadata: dict[str, Any], config: dict[str, dict[str, str]],
                 namespace: dict[str, Any], gcode: bytes = b"", play: bool = False) -> None:
        self.cycles, self.stream, self.index = cycles, stream, index
        self.metadata, self.play = metadata, play
        self.database: dict[str, dict[str, Any]] = {"mainsail": namespace, "maintenance": {}}
        shown = cycles[index]["status"]
        settings = typed_settings(config)
        # recorded fields over the derived ones (derived_objects: what was not recorded)
        self.state: dict[str, dict[str, Any]] = derived_objects(gcode, shown, settings)
        for name, fields in json.loads(json.dumps(shown)).items():
            self.state.setdefault(name, {}).update(fields)
        self.state["configfile"] = {"config": config, "settings": settings, "warnings": [],
                                    "save_config_pending": False}
        self.state["webhooks"] = {"state": "ready", "state_message": "Printer is ready"}
        self.eventtime = float(cycles[index]["eventtime"])
        self.started = time.time()

    # -- JSON-RPC methods --------------------------------------------------------------------

    def call(self, method: str, params: dict[str, Any]) -> Any:
        handler = getattr(self, "rpc_" + method.replace(".", "_"), None)
        if handler is None:
            raise KeyError(method)
        return handler(params)

    def rpc_server_connection_identify(self, params: dict[str, Any]) -> Any:
        return {"connection_id": 1}

    def rpc_server_info(self, params: dict[str, Any]) -> Any:
        return {"klippy_connected": True, "klippy_state": "ready",
                "components": ["database", "file_manager", "klippy_apis", "machine",
                               "data_store", "proc_stats", "webcam"],
                "failed_components": [], "registered_directories": ["gcodes", "config"],
                "warnings": [], "websocket_count": 1, "moonraker_version": "v0.9.3",
                "missing_klippy_requirements": [], "api_version": [1, 5, 0],
                "api_version_string": "1.5.0"}

    def rpc_server_config(self, params: dict[str, Any]) -> Any:
        return {"config": {"server": {"host": "127.0.0.1"}, "file_manager": {}},
                "orig": {}, "files": []}

    def rpc_machine_system_info(self, params: dict[str, Any]) -> Any:
        return {"system_info": {"cpu_info": {"cpu_count": 1, "processor": "", "model": "",
                                             "total_memory": 0, "memory_units": "kB"},
                                "distribution": {"name": "kestimator screenshot"},
                                "available_services": [], "service_state": {},
                                "virtualization": {}, "network": {}}}

    def rpc_machine_proc_stats(self, params: dict[str, Any]) -> Any:
        return {"moonraker_stats": [], "throttled_state": None, "cpu_temp": None,
                "network": {}, "system_cpu_usage": {}, "system_memory": {},
                "system_uptime": 3600.0, "websocket_connections": 1}

    def rpc_server_database_list(self, params: dict[str, Any]) -> Any:
        return {"namespaces": sorted(self.database), "backups": []}

    def rpc_server_database_get_item(self, params: dict[str, Any]) -> Any:
        namespace = params.get("namespace", "")
        if namespace not in self.database:
            raise LookupError("Namespace '%s' not found" % namespace)
        value: Any = self.database[namespace]
        for part in (params.get("key") or "").split(".") if params.get("key") else []:
            if not isinstance(value, dict) or part not in value:
                raise LookupError("Key '%s' in namespace '%s' not found"
                                  % (params.get("key"), namespace))
            value = value[part]
        return {"namespace": namespace, "key": params.get("key"), "value": value}

    def rpc_server_database_post_item(self, params: dict[str, Any]) -> Any:
        target = self.database.setdefault(params["namespace"], {})
        parts = str(params["key"]).split(".")
        for part in parts[:-1]:
            target = target.setdefault(part, {})
        target[parts[-1]] = params.get("value")
        return {"namespace": params["namespace"], "key": params["key"],
                "value": params.get("value")}

    def rpc_server_webcams_list(self, params: dict[str, Any]) -> Any:
        return {"webcams": []}

    def rpc_printer_info(self, params: dict[str, Any]) -> Any:
        return {"state": "ready", "state_message": "Printer is ready",
                "hostname": "kestimator", "software_version": "v0.13.0", "cpu_info": "",
                "klipper_path": "", "python_path": "", "log_file": "", "config_file": "",
                "app": "Klipper"}

    def rpc_server_gcode_store(self, params: dict[str, Any]) -> Any:
        return {"gcode_store": []}

    def rpc_server_temperature_store(self, params: dict[str, Any]) -> Any:
        return {}

    def rpc_printer_objects_list(self, params: dict[str, Any]) -> Any:
        return {"objects": sorted(self.state)}

    def _objects(self, wanted: dict[str, Any]) -> dict[str, Any]:
        status: dict[str, Any] = {}
        for name, fields in wanted.items():
            if name == "gcode":
                status[name] = {"commands": {}}
            elif name in self.state:
                obj = self.state[name]
                status[name] = (dict(obj) if not fields
                                else {k: obj[k] for k in fields if k in obj})
        return status

    def rpc_printer_objects_subscribe(self, params: dict[str, Any]) -> Any:
        return {"eventtime": self.eventtime, "status": self._objects(params.get("objects", {}))}

    def rpc_printer_objects_query(self, params: dict[str, Any]) -> Any:
        return {"eventtime": self.eventtime, "status": self._objects(params.get("objects", {}))}

    def rpc_server_files_metadata(self, params: dict[str, Any]) -> Any:
        if params.get("filename") != self.metadata["filename"]:
            raise LookupError("Metadata not available for <%s>" % params.get("filename"))
        return self.metadata

    def rpc_server_files_get_directory(self, params: dict[str, Any]) -> Any:
        files = []
        if str(params.get("path", "gcodes")).strip("/") == "gcodes":
            files.append({"filename": self.metadata["filename"], "size": self.metadata["size"],
                          "modified": self.metadata["modified"], "permissions": "rw"})
        return {"dirs": [], "files": files, "root_info": {"name": "gcodes", "permissions": "rw"},
                "disk_usage": {"total": 1 << 34, "used": 1 << 30, "free": (1 << 34) - (1 << 30)}}

    def rpc_server_files_list(self, params: dict[str, Any]) -> Any:
        return [{"path": self.metadata["filename"], "size": self.metadata["size"],
                 "modified": self.metadata["modified"], "permissions": "rw"}]

    def rpc_server_files_roots(self, params: dict[str, Any]) -> Any:
        return [{"name": "gcodes", "path": "/gcodes", "permissions": "rw"},
                {"name": "config", "path": "/config", "permissions": "rw"}]

    # -- notifications -----------------------------------------------------------------------

    def notifications(self) -> list[tuple[float, dict[str, Any]]]:
        """(seconds after subscription, message) for the cycles after the shown one."""
        if not self.play:
            return []
        base = self.eventtime
        return [(float(cycle["eventtime"]) - base,
                 {"jsonrpc": "2.0", "method": "notify_status_update",
                  "params": [cycle["status"], cycle["eventtime"]]})
                for cycle in self.stream[self.index + 1:]]


def make_handler(app: FakeMoonraker, dist: Path) -> type[http.server.BaseHTTPRequestHandler]:
    class Handler(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, directory=str(dist), **kwargs)

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002
            pass

        def end_headers(self) -> None:
            self.send_header("Cache-Control", "no-store")
            super().end_headers()

        def do_GET(self) -> None:
            if self.path.split("?")[0] == "/websocket":
                self._websocket()
            elif self.path.split("?")[0].startswith(("/server/", "/printer/", "/machine/")):
                self.send_error(404)
            else:
                super().do_GET()

        def _websocket(self) -> None:
            key = self.headers.get("Sec-WebSocket-Key", "")
            accept = base64.b64encode(hashlib.sha1((key + WS_GUID).encode()).digest()).decode()
            self.send_response_only(101, "Switching Protocols")
            self.send_header("Upgrade", "websocket")
            self.send_header("Connection", "Upgrade")
            self.send_header("Sec-WebSocket-Accept", accept)
            super(http.server.SimpleHTTPRequestHandler, self).end_headers()
            self.wfile.flush()
            lock = threading.Lock()
            closed = threading.Event()
            subscribed = threading.Event()
            threading.Thread(target=self._notify, args=(lock, closed, subscribed),
                             daemon=True).start()
            try:
                while True:
                    opcode, payload = ws_receive(self.rfile)
                    if opcode == 8:
                        break
                    if opcode == 9:
                        with lock:
                            self.wfile.write(bytes([0x8A, len(payload)]) + payload)
                        continue
                    if opcode != 1:
                        continue
                    request = json.loads(payload)
                    for message in request if isinstance(request, list) else [request]:
                        reply = self._answer(message)
                        if reply is not None:
                            ws_send(self.wfile, json.dumps(reply), False, lock)
                        if message.get("method") == "printer.objects.subscribe":
                            subscribed.set()
            except (ConnectionError, OSError):
                pass
            finally:
                closed.set()
                self.close_connection = True

        def _answer(self, message: dict[str, Any]) -> dict[str, Any] | None:
            if "id" not in message:
                return None
            try:
                result = app.call(message["method"], message.get("params") or {})
            except KeyError:
                return {"jsonrpc": "2.0", "id": message["id"],
                        "error": {"code": -32601, "message": "Method not found"}}
            except LookupError as exc:
                return {"jsonrpc": "2.0", "id": message["id"],
                        "error": {"code": 404, "message": str(exc)}}
            return {"jsonrpc": "2.0", "id": message["id"], "result": result}

        def _notify(self, lock: threading.Lock, closed: threading.Event,
                    subscribed: threading.Event) -> None:
            """The cycles after the shown one (with --play), and Moonraker's proc stats every
            second (Mainsail closes a socket silent for 10 s)."""
            subscribed.wait()
            start = time.monotonic()
            pending = app.notifications()
            next_stats = start
            try:
                while not closed.is_set():
                    now = time.monotonic()
                    while pending and start + pending[0][0] <= now:
                        ws_send(self.wfile, json.dumps(pending.pop(0)[1]), False, lock)
                    if now >= next_stats:
                        ws_send(self.wfile, json.dumps(
                            {"jsonrpc": "2.0", "method": "notify_proc_stat_update",
                             "params": [{"moonraker_stats": {"time": time.time(),
                                                             "cpu_usage": 0., "memory": 0,
                                                             "mem_units": "kB"},
                                         "cpu_temp": None, "network": {},
                                         "system_cpu_usage": {},
                                         "websocket_connections": 1}]}), False, lock)
                        next_stats = now + 1.
                    closed.wait(0.05)
            except OSError:
                pass

    return Handler


def serve(app: FakeMoonraker, dist: Path, port: int = 0) -> http.server.ThreadingHTTPServer:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", port), make_handler(app, dist))
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


# ---------------------------------------------------------------------------------------------
# Headless Chromium through the DevTools protocol


class Chromium:
    """A headless Chromium and one page, driven over the DevTools websocket."""

    def __init__(self, width: int, height: int, tz: str) -> None:
        program = next((p for p in ("chromium", "chromium-browser", "google-chrome")
                        if shutil.which(p)), None)
        if program is None:
            raise RuntimeError("chromium is needed (Debian: apt-get install -y chromium)")
        self.profile = tempfile.mkdtemp(prefix="kestimator-chromium-")
        argv = [program, "--headless=new", "--disable-gpu", "--no-first-run",
                "--no-default-browser-check", "--hide-scrollbars", "--mute-audio",
                "--remote-debugging-port=0", "--remote-debugging-address=127.0.0.1",
                "--user-data-dir=" + self.profile, "--window-size=%d,%d" % (width, height),
                "--force-device-scale-factor=1", "--lang=en-US", "--accept-lang=en-US",
                "about:blank"]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            argv.insert(1, "--no-sandbox")
        env = dict(os.environ, TZ=tz, LANG="en_US.UTF-8")
        self.proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     env=env)
        url = None
        assert self.proc.stderr is not None
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            line = self.proc.stderr.readline().decode(errors="replace")
            if not line:
                break
            found = re.search(r"DevTools listening on (ws://\S+)", line)
            if found:
                url = found.group(1)
                break
        if url is None:
            self.close()
            raise RuntimeError("chromium did not start its DevTools endpoint")
        threading.Thread(target=self._drain, daemon=True).start()
        host, port, path = re.match(r"ws://([^:/]+):(\d+)(/.*)", url).groups()  # type: ignore
        self.sock = socket.create_connection((host, int(port)), timeout=60)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(("GET %s HTTP/1.1\r\nHost: %s:%s\r\nUpgrade: websocket\r\n"
                           "Connection: Upgrade\r\nSec-WebSocket-Key: %s\r\n"
                           "Sec-WebSocket-Version: 13\r\n\r\n" % (path, host, port, key)).encode())
        self.stream: Any = self.sock.makefile("rwb")
        status = self.stream.readline()
        if b" 101 " not in status:
            raise RuntimeError("DevTools websocket refused: %r" % status)
        while self.stream.readline() not in (b"\r\n", b"\n", b""):
            pass
        self.lock = threading.Lock()
        self.next_id = 0
        self.session: str | None = None

    def _drain(self) -> None:
        assert self.proc.stderr is not None
        for _ in self.proc.stderr:
            pass

    def send(self, method: str, params: dict[str, Any] | None = None,
             session: bool = True) -> Any:
        self.next_id += 1
        message: dict[str, Any] = {"id": self.next_id, "method": method, "params": params or {}}
        if session and self.session:
            message["sessionId"] = self.session
        ws_send(self.stream, json.dumps(message), True, self.lock)
        while True:
            opcode, payload = ws_receive(self.stream)
            if opcode != 1:
                continue
            reply = json.loads(payload)
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError("%s: %s" % (method, reply["error"]))
                return reply.get("result", {})

    def open_page(self, width: int, height: int, clock_ms: float | None) -> None:
        targets = self.send("Target.getTargets", session=False)["targetInfos"]
        page = next(t["targetId"] for t in targets if t["type"] == "page")
        self.session = self.send("Target.attachToTarget", {"targetId": page, "flatten": True},
                                 session=False)["sessionId"]
        self.send("Page.enable")
        self.send("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})
        if clock_ms is not None:
            self.send("Page.addScriptToEvaluateOnNewDocument", {"source": CLOCK_JS % clock_ms})

    def evaluate(self, expression: str) -> Any:
        result = self.send("Runtime.evaluate", {"expression": expression,
                                                "returnByValue": True, "awaitPromise": True})
        return result.get("result", {}).get("value")

    def close(self) -> None:
        try:
            if getattr(self, "stream", None) is not None:
                self.send("Browser.close", session=False)
        except (OSError, ConnectionError, RuntimeError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        shutil.rmtree(self.profile, ignore_errors=True)


# The page's clock held at the shown cycle's wall time (ms since the epoch): `new Date()` and
# `Date.now()` say that instant, so Mainsail's ETA (now + remaining) is the module's ETA.
CLOCK_JS = """(() => {
  const fixed = %r;
  const RealDate = Date;
  class HeldDate extends RealDate {
    constructor(...args) { if (args.length === 0) { super(fixed); } else { super(...args); } }
    static now() { return fixed; }
  }
  globalThis.Date = HeldDate;
})();"""

# The status panel once it shows the print: its box and its text, else null.
PANEL_JS = """(() => {
  const panel = document.querySelector('.status-panel');
  if (!panel) return null;
  const text = panel.innerText;
  if (!/Estimate\\s+\\d+:\\d\\d:\\d\\d/.test(text)) return null;
  if (!/ETA\\s+\\d\\d:\\d\\d/.test(text)) return null;
  const box = panel.getBoundingClientRect();
  return {x: box.x, y: box.y, width: box.width, height: box.height, text: text};
})()"""


def screenshot(url: str, out: Path, width: int, height: int, clock_ms: float | None, tz: str,
               timeout: float = 60.) -> dict[str, Any]:
    """Load `url` in headless Chromium, wait for the status panel, photograph it."""
    browser = Chromium(width, height, tz)
    try:
        browser.open_page(width, height, clock_ms)
        browser.send("Page.navigate", {"url": url})
        deadline = time.monotonic() + timeout
        panel = None
        while time.monotonic() < deadline:
            panel = browser.evaluate(PANEL_JS)
            if panel:
                break
            time.sleep(0.5)
        if not panel:
            text = browser.evaluate("document.body ? document.body.innerText : ''")
            raise RuntimeError("the status panel never showed the print; page text:\n%s" % text)
        time.sleep(2.0)  # the progress circle's animation
        panel = browser.evaluate(PANEL_JS)
        margin = 8
        clip = {"x": max(0., panel["x"] - margin), "y": max(0., panel["y"] - margin),
                "width": panel["width"] + 2 * margin, "height": panel["height"] + 2 * margin,
                "scale": 1}
        shot = browser.send("Page.captureScreenshot", {"format": "png", "clip": clip,
                                                       "captureBeyondViewport": True})
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(base64.b64decode(shot["data"]))
        return dict(panel)
    finally:
        browser.close()


# ---------------------------------------------------------------------------------------------


def hms(seconds: float) -> str:
    """As Mainsail writes a duration it got as whole seconds (toFixed(0))."""
    s = round(seconds)
    return "%d:%02d:%02d" % (s // 3600, s % 3600 // 60, s % 60)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ktest", nargs="?", default=str(RECORDING),
                    help="ktest.json kept by run_realtime.py --keep, or a recording saved "
                         "with --save-recording (default: %(default)s)")
    ap.add_argument("--at", type=float, default=0.4,
                    help="show the first printing cycle whose progress reaches this (0.4)")
    ap.add_argument("--gcode", help="the printed file (default: sd/<filename> beside KTEST)")
    ap.add_argument("--printer-cfg", help="printer.cfg (default: the one beside KTEST)")
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="PNG to write (%(default)s)")
    ap.add_argument("--tz", default="UTC", help="time zone the ETA is written in (UTC)")
    ap.add_argument("--window", default="1400x900", help="browser window WxH (1400x900)")
    ap.add_argument("--progress", choices=("auto", "recompute", "keep"), default="auto",
                    help="display_status.progress: recompute D/(D+R) if the recording "
                         "predates it (auto), always, or keep the recorded one")
    ap.add_argument("--serve", action="store_true",
                    help="no screenshot: serve until Ctrl-C and print the address")
    ap.add_argument("--play", action="store_true",
                    help="after the shown cycle, replay the rest of the stream in real time")
    ap.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (any free one)")
    ap.add_argument("--prepare-only", action="store_true", help="only build Mainsail")
    ap.add_argument("--save-recording", metavar="OUT.json.gz",
                    help="no screenshot: save KTEST (a kept run_realtime.py directory's "
                         "ktest.json) as a self-contained recording and exit")
    args = ap.parse_args(argv)

    started = time.monotonic()
    if args.save_recording:
        save_recording(Path(args.ktest), Path(args.save_recording))
        print("wrote %s" % args.save_recording)
        return 0
    dist = prepare_ui()
    if args.prepare_only:
        print("Mainsail built: %s (%.1f s)" % (dist, time.monotonic() - started))
        return 0
    ktest_path = Path(args.ktest)
    recording = load_recording(ktest_path)
    stream = recording["stream"]
    cycles = merged_cycles(stream)
    old = progress_is_old_style(cycles)
    if args.progress == "recompute" or (args.progress == "auto" and old):
        print("display_status.progress recomputed as D / (D + R) per cycle"
              + (" (the recording predates the module's D / (D + R))" if old else ""))
        stream = recompute_progress(stream)
        cycles = merged_cycles(stream)
    index = choose_cycle(cycles, args.at)
    status = cycles[index]["status"]
    filename = status["print_stats"]["filename"]
    if args.gcode:
        gcode = Path(args.gcode)
    elif "gcode" in recording:
        gcode = CORPUS / recording["gcode"]
    else:
        gcode = ktest_path.parent / "sd" / filename
    if "gcode_sha256" in recording and \
            hashlib.sha256(gcode.read_bytes()).hexdigest() != recording["gcode_sha256"]:
        raise SystemExit("%s is not the file that was printed (sha256 differs)" % gcode)
    metadata = gcode_metadata(gcode, filename)
    cfg_path = Path(args.printer_cfg) if args.printer_cfg else ktest_path.parent / "printer.cfg"
    if args.printer_cfg or "config" not in recording:
        config = read_printer_cfg(cfg_path) if cfg_path.is_file() else {}
    else:
        config = recording["config"]
    namespace = json.loads((SUPPORT / "mainsail_namespace.json").read_text())
    app = FakeMoonraker(cycles, stream, index, metadata, config, namespace,
                        gcode=gcode.read_bytes(), play=args.play)
    server = serve(app, dist, args.port)
    url = "http://127.0.0.1:%d/" % server.server_address[1]

    duration = float(status["print_stats"]["print_duration"])
    progress = float(status["display_status"]["progress"])
    module = status["kestimator"]
    shown_estimate = round(duration / progress - duration)
    wall = None
    if module.get("eta") is not None and module.get("remaining_s") is not None:
        wall = float(module["eta"]) - float(module["remaining_s"])
    print("cycle %d of %d (eventtime %.3f): print_duration %.3f s, display_status.progress "
          "%.5f, kestimator.remaining_s %.3f"
          % (index, len(cycles), cycles[index]["eventtime"], duration, progress,
             module["remaining_s"]))
    eta_text = "--"
    if wall is not None:
        os.environ["TZ"] = args.tz
        if hasattr(time, "tzset"):
            time.tzset()
        eta_at = datetime.datetime.fromtimestamp(wall + shown_estimate)
        eta_text = eta_at.strftime("%I:%M %p")  # en-US: Mainsail writes 12-hour times
        print("browser clock held at %s %s (kestimator.eta - remaining_s)"
              % (datetime.datetime.fromtimestamp(wall).strftime("%Y-%m-%d %H:%M:%S"), args.tz))
    print("Mainsail should show: progress %d %%, Estimate %s (D/p - D = %.3f s), ETA %s %s, "
          "Slicer %s" % (int(progress * 100), hms(shown_estimate), duration / progress - duration,
                         eta_text, args.tz,
                         hms(metadata["estimated_time"] - duration)
                         if "estimated_time" in metadata else "--"))
    try:
        if args.serve:
            print("serving Mainsail and the fake Moonraker at %s (Ctrl-C to stop)" % url)
            while True:
                time.sleep(3600)
        width, height = (int(v) for v in args.window.lower().split("x"))
        panel = screenshot(url, Path(args.out), width, height,
                           wall * 1000. if wall is not None else None, args.tz)
        print("status panel text:\n  " + "\n  ".join(
            line for line in panel["text"].splitlines() if line.strip()))
        expected = [("Estimate", hms(shown_estimate)), ("ETA", eta_text)]
        words = panel["text"].split()
        wrong = [(label, value) for label, value in expected
                 if value != "--" and " ".join(words).find("%s %s" % (label, value)) < 0]
        if wrong:
            print("NOT as expected: %s" % wrong, file=sys.stderr)
            return 1
        print("wrote %s (%d bytes, %dx%d) in %.1f s" % (
            args.out, Path(args.out).stat().st_size, panel["width"], panel["height"],
            time.monotonic() - started))
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
