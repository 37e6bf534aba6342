"""The whole test suite's time on an idle 2-core machine, derived from each file's measured
CPU and wall seconds (tests/file_times.json, which `pytest --record-file-times
tests/file_times.json` writes), for 2, 3 and 4 pytest-xdist processes.

A shared machine's wall times are noise, its CPU times much less so; this derives what an
idle machine would take from them:

- a file marked `wall_clock` (the real-time prints, the Cura GUIs) takes its measured wall
  seconds wherever it runs (pessimistic: the load stretched them too), using its CPU seconds
  spread over them;
- any other file computes: alone on an idle core it takes its CPU seconds times `--factor`
  (1 by default; more for what the CPU seconds miss: waits on pipes and the network, the CPU
  of processes a test kills rather than waits for). A whole run on an idle machine gives the
  factor: the one for which this prints the time that run took.

The files start in the order tests/conftest.py gives them, each in the first free process
(`--dist loadfile`); the running files share the cores as the kernel shares them (none
gets more than it can use, the rest evenly). `--overhead` adds each process's start and
collection (not in the files' times). It prints the longest files and one line per
process count.

    python3 benchmarks/suite_time.py [--times tests/file_times.json] [--cores 2]
        [--factor 1.0] [--overhead 15]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PROJECT = Path(__file__).resolve().parents[1]
STEP_S = 0.25


@dataclass
class File:
    """A test file: its CPU seconds and the fewest wall seconds it can take."""

    name: str
    cpu_s: float
    wall_s: float  # on an idle machine: cpu_s (CPU-bound) or the measured wall (waiting)
    waiting: bool


def files_from(times: dict[str, dict[str, Any]], factor: float = 1.0) -> list[File]:
    """The files in tests/conftest.py's order: wall_clock ones first (the longest first), then
    the most CPU seconds first."""
    out = []
    for name, entry in times.items():
        cpu, wall, waiting = float(entry["cpu_s"]), float(entry["wall_s"]), entry["wall_clock"]
        out.append(File(name, cpu, wall if waiting else cpu * factor, bool(waiting)))
    return sorted(out, key=lambda f: (not f.waiting, -f.wall_s if f.waiting else -f.cpu_s))


def share(wants: list[float], cores: float) -> list[float]:
    """Cores given to processes wanting `wants` each: none more than it wants, the rest
    evenly (water-filling)."""
    given = [0.0] * len(wants)
    left = cores
    order = sorted(range(len(wants)), key=lambda i: wants[i])
    for position, i in enumerate(order):
        fair = left / (len(order) - position)
        given[i] = min(wants[i], fair)
        left -= given[i]
    return given


def simulate(files: list[File], workers: int, cores: float, overhead_s: float) -> float:
    """Seconds until the last file ends, `workers` processes on `cores` cores."""
    queue = [f for f in files if f.wall_s > 0]
    running: list[tuple[File, float]] = []  # (file, fraction done)
    free = workers
    # Every process starts and collects the suite before its first file.
    clock = overhead_s * max(1.0, workers / cores)
    while queue or running:
        while free and queue:
            running.append((queue.pop(0), 0.0))
            free -= 1
        wants = [f.cpu_s / f.wall_s for f, _ in running]
        given = share(wants, cores)
        still = []
        for (f, done), want, got in zip(running, wants, given):
            done += (got / want if want > 0 else 1.0) * STEP_S / f.wall_s
            if done >= 1.0:
                free += 1
            else:
                still.append((f, done))
        running = still
        clock += STEP_S
    return clock


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--times", type=Path, default=PROJECT / "tests" / "file_times.json")
    parser.add_argument("--cores", type=float, default=2.0)
    parser.add_argument("--factor", type=float, default=1.0,
                        help="idle wall seconds per CPU second of a file that computes")
    parser.add_argument("--overhead", type=float, default=15.0,
                        help="each process's start and collection, CPU seconds")
    args = parser.parse_args(argv)
    files = files_from(json.loads(args.times.read_text()), args.factor)
    total_cpu = sum(f.cpu_s for f in files)
    print("%-42s %9s %9s %s" % ("file", "cpu s", "idle s", ""))
    for f in sorted(files, key=lambda f: -f.wall_s)[:15]:
        print("%-42s %9.1f %9.1f %s" % (f.name, f.cpu_s, f.wall_s,
                                        "waits on the clock" if f.waiting else ""))
    print("%d files, %d tests, %.1f CPU minutes (%.1f min on %g cores at best)" % (
        len(files), sum(int(e["tests"]) for e in json.loads(args.times.read_text()).values()),
        total_cpu / 60, total_cpu / 60 / args.cores, args.cores))
    for workers in (2, 3, 4):
        total = simulate(files, workers, args.cores, args.overhead)
        print("-n %d on %g idle cores: %d min %02d s" % (workers, args.cores, total // 60,
                                                      total % 60))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
