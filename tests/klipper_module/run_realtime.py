"""Print a G-code file in real Klipper at wall-clock speed, as a printer does, with the
kestimator module loaded, and hold what the module said against what Klipper then took.

    python3 tests/klipper_module/run_realtime.py FILE.gcode [--cfg EXTRA.cfg]
        [--before CMD ...] [--at FRACTION:CMD ...] [--after SECONDS:CMD ...]
        [--heat-wait S] [--inject] [--keep]

The print takes as long as it takes on a printer (batch-mode Klipper made real-time by
ktest_realtime.py, beside this file). Needs the oracle's Klipper (run_print.oracle_paths),
or another tree given as `klipper_tree` (Klipper v0.12.0, v0.13.0, Kalico v2026.07.00:
tests/test_klipper_module_realtime.py RELEASES), run as run_print runs it.
Commands given with --before are typed at the console before the print starts (they
persist, as Mainsail's limit sliders do until a restart); --at types a command when the
print reaches a fraction of the file, --after that many seconds after the previous one.

Each status cycle (Klipper's own objects/subscribe, every 250 ms) becomes a sample with
`truth_s`: the printing time Klipper then really took from that moment to the last move's
end, idle gaps (the head waiting through a pause or a heater wait, print_time re-synced
after) left out, as the module leaves them out.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from typing import Any

import run_print

HERE = run_print.HERE


def _merge(stream: list[dict[str, Any]], offset: float) -> list[dict[str, Any]]:
    """The status stream (what changed each cycle) as full states, one per cycle."""
    state: dict[str, dict[str, Any]] = {}
    samples = []
    for cycle in stream:
        for name, fields in cycle["status"].items():
            state.setdefault(name, {}).update(fields)
        eventtime = cycle["eventtime"]
        samples.append({"eventtime": eventtime, "print_time": eventtime + offset,
                        "status": json.loads(json.dumps(state))})
    return samples


def truth_at(print_time: float, end: float, gaps: list[list[float]]) -> float:
    """Printing time from `print_time` to `end`, idle gaps (old, new print_time) left out."""
    left = end - print_time
    for old, new in gaps:
        left -= max(0., min(new, end) - max(old, print_time))
    return max(0., left)


def run_realtime(src: str, work: str, extra_cfg: str = "", before: list[str] | None = None,
                 script: list[dict[str, Any]] | None = None, heat_wait: float = 0.,
                 inject: bool = False, base_cfg: str = run_print.CORPUS_CFG,
                 python: str | None = None, timeout: float = 1800.,
                 klipper_tree: tuple[str, str] | None = None) -> dict[str, Any]:
    """Print `src` at wall-clock speed with the module; the results of ktest_realtime with
    `samples` (each status cycle's `id` (its index), full status, `truth_s`, and `error_s`
    where the module had a remaining time). `klipper_tree`: (Klipper tree, its Python) to
    print in instead of the oracle's."""
    paths = klipper_tree or run_print.oracle_paths()
    if paths is None:
        raise RuntimeError("the oracle's Klipper is not set up (ORACLE_KLIPPER)")
    klipper, _ = paths
    python = python or sys.executable
    sd = os.path.join(work, "sd")
    os.makedirs(sd, exist_ok=True)
    test_file = os.path.join(sd, "test.gcode")
    shutil.copyfile(src, test_file)
    cfg = os.path.join(work, "printer.cfg")
    with open(cfg, "w") as f:
        f.write("[include %s]\n\n[virtual_sdcard]\npath: %s\n\n[exclude_object]\n\n"
                "[display_status]\n\n[pause_resume]\n\n[oracle_probe]\n\n"
                "[ktest_realtime]\nheat_wait: %r\n\n[kestimator]\npython: %s\n\n%s"
                % (os.path.abspath(base_cfg), sd, heat_wait, python, extra_cfg))
    if inject:
        subprocess.run([python, "-m", "kestimator", "inject", test_file, "--printer-cfg", cfg],
                       check=True, capture_output=True, cwd=work)
    run_print._link(run_print.MODULE, klipper, "kestimator")
    run_print._link(os.path.join(HERE, "ktest_realtime.py"), klipper, "ktest_realtime.py")
    run_print._link(os.path.join(run_print.ORACLE_DIR, "oracle_probe.py"), klipper,
                    "oracle_probe.py")
    batch = os.path.join(work, "batch.gcode")
    with open(batch, "w") as f:
        f.write("ORACLE_HOME ZERO=1\n")   # the estimator's start convention (run_print)
        for command in before or []:
            f.write(command + "\n")
        f.write("SDCARD_PRINT_FILE FILENAME=test.gcode\n")
    out = os.path.join(work, "ktest.json")
    log = os.path.join(work, "klippy.log")
    env = dict(os.environ, KTEST_OUT=out, ORACLE_OUT=os.path.join(work, "oracle.json"),
               KTEST_SCRIPT=json.dumps(script or []))
    result = run_print.run_klippy(cfg, batch, log, out, env, timeout, paths)
    end = result["end_print_time"]
    samples = _merge(result.pop("stream"), result["clock_offset"])
    for index, sample in enumerate(samples):
        sample["id"] = index
        sample["truth_s"] = truth_at(sample["print_time"], end, result["gaps"])
        kest = sample["status"].get("kestimator", {})
        sample["remaining_s"] = kest.get("remaining_s")
        if sample["remaining_s"] is not None:
            sample["error_s"] = sample["remaining_s"] - sample["truth_s"]
    result["samples"] = samples
    result["klippy_log"] = log
    return result


# The status cycles the bars apply to: from 10 s of print_duration, and from
# run_print.ANSWER_WITHIN_S after a typed command (the module's answer to a change is due
# by then). Typed commands that do not change the time left: a pause's time is left out; a
# display message; an echo.
FROM_DURATION_S = 10.0
SETTLE_S = run_print.ANSWER_WITHIN_S
TIMELESS = ("PAUSE", "RESUME", "M117", "ECHO")


def checked_samples(samples: list[dict[str, Any]], typed: list[dict[str, Any]]
                    ) -> list[tuple[dict[str, Any], float, float]]:
    """The samples the bars apply to, each with its bar (absolute, relative: run_print's
    plain one, or its changed one once a command was typed): from 10 s of print_duration,
    leaving out the 2 s after each typed command. A change typed later makes what Klipper
    then takes differ from what anyone could know before it: a print with a change is
    checked from 2 s after it (its only one that changes the time)."""
    changes = [t for t in typed if t["cmd"].split()[0] not in TIMELESS]
    start = changes[-1]["done_eventtime"] + SETTLE_S if changes else 0.
    out = []
    for sample in samples:
        stats = sample["status"].get("print_stats", {})
        if stats.get("state") not in ("printing", "paused"):
            continue
        if stats.get("print_duration", 0.) < FROM_DURATION_S:
            continue
        eventtime = sample["eventtime"]
        if eventtime < start:
            continue
        if any(t["eventtime"] <= eventtime < t["done_eventtime"] + SETTLE_S for t in typed):
            continue
        changed = any(t["done_eventtime"] <= eventtime for t in typed)
        bar = ((run_print.CHANGED_ABS, run_print.CHANGED_REL) if changed
               else (run_print.PLAIN_ABS, run_print.PLAIN_REL))
        out.append((sample, bar[0], bar[1]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("gcode")
    ap.add_argument("--cfg", help="extra printer.cfg text from this file")
    ap.add_argument("--before", action="append", default=[])
    ap.add_argument("--at", action="append", default=[], help="FRACTION:COMMAND")
    ap.add_argument("--after", action="append", default=[], help="SECONDS:COMMAND")
    ap.add_argument("--heat-wait", type=float, default=0.)
    ap.add_argument("--inject", action="store_true")
    ap.add_argument("--keep", action="store_true")
    args = ap.parse_args()
    script: list[dict[str, Any]] = []
    for spec in args.at:
        fraction, command = spec.split(":", 1)
        script.append({"at": float(fraction), "cmd": command})
    for spec in args.after:
        seconds, command = spec.split(":", 1)
        script.append({"after": float(seconds), "cmd": command})
    extra = open(args.cfg).read() if args.cfg else ""
    work = tempfile.mkdtemp(prefix="ktest-rt-")
    try:
        result = run_realtime(args.gcode, work, extra, args.before, script, args.heat_wait,
                              args.inject)
        worst = max((s for s in result["samples"] if s.get("error_s") is not None),
                    key=lambda s: abs(s["error_s"]), default=None)
        json.dump({k: v for k, v in result.items() if k != "samples"}, sys.stdout, indent=1)
        print("\nsamples: %d, worst: %s" % (len(result["samples"]), worst and {
            k: worst[k] for k in ("print_time", "remaining_s", "truth_s", "error_s")}))
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print("kept", work)


if __name__ == "__main__":
    main()
