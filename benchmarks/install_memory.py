"""Peak memory of `pip install` of a fresh clone, summed over the whole process tree.

`/usr/bin/time -v` reports only the largest single process; a build runs pip, the build
backend (mypy type-checking, mypyc generating C), gcc and cc1 side by side. This script
clones the checkout's HEAD into a temporary folder (no `build/` left from an earlier
build), makes a virtualenv with the given Python (default: Debian's own /usr/bin/python3,
whose build flags cost gcc the most), runs `pip install -v <clone>` in it and samples
/proc every 50 ms: the RSS of pip and of every process below it, summed. It prints one
result line (the row for benchmarks/RESULTS.md) and exits 1 if the peak is over --limit.

It runs the README's first command as a user does (`python3 -m venv .venv && .venv/bin/pip
install -q '.[cli]' && .venv/bin/kestimator inject examples/hex_nut_prusaslicer.gcode ...`,
with `-v` for the build's line) and prints that command's CPU and wall time as a whole, and
the load average around it (wall time on a shared host is noise; CPU time much less so).
`--jobs N` sets KESTIMATOR_BUILD_JOBS (`--jobs 1`: one compile at a time, as setup.py does
on a small host); without it setup.py decides from the CPUs and memory here.

It also prints the command's wall time by phase, from pip's `-v` lines as they arrive: the
venv, pip's steps before the build (setuptools and mypy into the isolated build environment,
the metadata), mypy's child writing the C, the compiles and the wheel (and each group's
library, from its `building '...' extension` line to its link), installing the wheel and
rich, the `inject`.
On an idle machine the phases are the command's critical path.

    python3 benchmarks/install_memory.py [--python /usr/bin/python3] [--limit 300] [--jobs N]
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent
# The pip -v lines that start each phase of `pip install`, in order.
PHASE_MARKS = (
    ("pip before the build", "Installing build dependencies: started"),
    ("mypy writes the C", "Building wheel for kestimator (pyproject.toml): started"),
    ("compiling, the wheel", "running build_ext"),
    ("installing", "Building wheel for kestimator (pyproject.toml): finished"),
)
GROUP_START = re.compile(r"building '(\w+)__mypyc' extension")
GROUP_LINK = re.compile(r" -shared .*/(\w+)__mypyc\.")
PAGE_KIB = os.sysconf("SC_PAGE_SIZE") // 1024
INTERVAL_S = 0.05


def _children() -> dict[int, list[int]]:
    """Every process's children, from /proc/<pid>/stat (parent pid is field 4)."""
    tree: dict[int, list[int]] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open("/proc/%s/stat" % name, "rb") as f:
                stat = f.read()
        except OSError:
            continue
        # The command name (field 2) is in parentheses and may hold spaces.
        fields = stat[stat.rfind(b")") + 2:].split()
        tree.setdefault(int(fields[1]), []).append(int(name))
    return tree


def _rss_kib(pid: int) -> tuple[int, str]:
    """A process's resident set (KiB) and its command name; (0, "") once it is gone."""
    try:
        with open("/proc/%d/statm" % pid, "rb") as f:
            pages = int(f.read().split()[1])
        with open("/proc/%d/comm" % pid, encoding="utf-8", errors="replace") as f:
            return pages * PAGE_KIB, f.read().strip()
    except (OSError, IndexError, ValueError):
        return 0, ""


class TreeSampler(threading.Thread):
    """Polls the tree under `root` until stopped; keeps the peak of the summed RSS."""

    def __init__(self, root: int) -> None:
        super().__init__(daemon=True)
        self.root = root
        self.stopped = threading.Event()
        self.peak_kib = 0
        self.peak_at_s = 0.0
        self.peak_members: list[tuple[str, int]] = []
        self.largest_kib = 0
        self.largest_name = ""
        self.samples = 0

    def run(self) -> None:
        start = time.monotonic()
        while not self.stopped.is_set():
            tree = _children()
            pids, members, total = [self.root], [], 0
            while pids:
                pid = pids.pop()
                kib, name = _rss_kib(pid)
                if kib:
                    total += kib
                    members.append((name, kib))
                    if kib > self.largest_kib:
                        self.largest_kib, self.largest_name = kib, name
                pids.extend(tree.get(pid, ()))
            self.samples += 1
            if total > self.peak_kib:
                self.peak_kib, self.peak_at_s = total, time.monotonic() - start
                self.peak_members = sorted(members, key=lambda m: -m[1])
            self.stopped.wait(INTERVAL_S)


def _clone(target: Path) -> Path:
    """A fresh clone of this checkout's HEAD (what a user's `git clone` holds)."""
    clone = target / "kestimator"
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(HERE), str(clone)],
                   check=True, timeout=300)
    return clone


def _phases(marks: dict[str, float], pip_started: float,
            groups: dict[str, list[float]]) -> str:
    """The phases' wall seconds in order ('venv 4.1, pip before the build 12.0, ...'), and
    each group library's compile within the compiles."""
    times = dict(marks)
    times.setdefault("pip before the build", pip_started)
    order = ["venv", *[name for name, _ in PHASE_MARKS], "inject", "end"]
    # venv ends where pip starts; a phase whose line never came (a pure build) is left out.
    present = [name for name in order if name in times]
    times["pip before the build"] = min(times["pip before the build"], pip_started)
    parts = []
    for name, following in zip(present, present[1:]):
        end = pip_started if name == "venv" else times[following]
        parts.append("%s %.1f" % (name, end - times[name]))
        if name == "compiling, the wheel" and groups:
            parts[-1] += " (%s)" % ", ".join(
                "%s %.1f" % (group, end_s - start_s)
                for group, (start_s, end_s) in sorted(groups.items(), key=lambda g: g[1][0]))
    return ", ".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", default="/usr/bin/python3",
                        help="the Python the venv is made from (default: /usr/bin/python3)")
    parser.add_argument("--limit", type=float, default=300.0,
                        help="MiB the process tree's peak must stay under (default: 300)")
    parser.add_argument("--keep-log", metavar="FILE", help="write pip's output here")
    parser.add_argument("--jobs", type=int, metavar="N",
                        help="C compiles at once (KESTIMATOR_BUILD_JOBS); default: setup.py's")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="kestimator-install-mem-") as tmp:
        root = Path(tmp)
        clone = _clone(root)
        venv = clone / ".venv"
        env = dict(os.environ)
        for name in ("PYTHONPATH", "VIRTUAL_ENV", "KESTIMATOR_BUILD", "KESTIMATOR_BUILD_JOBS"):
            env.pop(name, None)
        if args.jobs:
            env["KESTIMATOR_BUILD_JOBS"] = str(args.jobs)
        first_rusage = resource.getrusage(resource.RUSAGE_CHILDREN)
        first_started = time.monotonic()
        subprocess.run([args.python, "-m", "venv", str(venv)], check=True, timeout=300,
                       cwd=clone)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        started = time.monotonic()
        log = open(args.keep_log or os.devnull, "wb")
        process = subprocess.Popen(
            [str(venv / "bin" / "pip"), "install", "-v", "--no-cache-dir",
             "--disable-pip-version-check", ".[cli]"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, cwd=clone)
        sampler = TreeSampler(process.pid)
        sampler.start()
        output = b""
        marks: dict[str, float] = {"venv": first_started}
        groups: dict[str, list[float]] = {}
        assert process.stdout is not None
        for chunk in iter(process.stdout.readline, b""):
            now = time.monotonic()
            output += chunk
            log.write(chunk)
            text = chunk.decode(errors="replace")
            for name, mark in PHASE_MARKS:
                if mark in text and name not in marks:
                    marks[name] = now
            started_group, linked_group = GROUP_START.search(text), GROUP_LINK.search(text)
            if started_group:
                groups[started_group.group(1)] = [now, now]
            elif linked_group and linked_group.group(1) in groups:
                groups[linked_group.group(1)][1] = now
        process.wait()
        marks["pip's end"] = time.monotonic()
        sampler.stopped.set()
        sampler.join()
        log.close()
        wall = time.monotonic() - started
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        if process.returncode != 0:
            sys.stderr.write(output.decode(errors="replace")[-4000:])
            sys.stderr.write("pip install failed (%d)\n" % process.returncode)
            return 2
        subprocess.run([str(venv / "bin" / "kestimator"), "inject",
                        "examples/hex_nut_prusaslicer.gcode", "-o", "hex_nut_klipper.gcode",
                        "--printer-cfg", "examples/printer.cfg"], check=True, env=env,
                       cwd=clone, stdout=subprocess.DEVNULL, timeout=300)
        marks["inject"] = marks["pip's end"]
        first_wall = time.monotonic() - first_started
        marks["end"] = first_started + first_wall
        first_after = resource.getrusage(resource.RUSAGE_CHILDREN)
        first_cpu = (first_after.ru_utime - first_rusage.ru_utime) + (
            first_after.ru_stime - first_rusage.ru_stime)
        build = [line.strip() for line in output.decode(errors="replace").splitlines()
                 if "kestimator build: " in line]
        version = subprocess.run([str(venv / "bin" / "kestimator"), "--version"],
                                 capture_output=True, text=True, timeout=60).stdout.strip()
    peak = sampler.peak_kib / 1024
    python = subprocess.run([args.python, "-c", "import platform; print("
                             "platform.python_implementation(), platform.python_version())"],
                            capture_output=True, text=True, timeout=60).stdout.strip()
    print("python: %s (%s); %s; build line: %s" % (
        args.python, python, version, build[0] if build else "none"))
    print("peak summed RSS %.0f MiB at %.1f s (%s); largest single process %.0f MiB (%s); "
          "CPU %.1f s, wall %.1f s, %d samples, %s" % (
              peak, sampler.peak_at_s,
              ", ".join("%s %.0f" % (n, k / 1024) for n, k in sampler.peak_members[:6]),
              sampler.largest_kib / 1024, sampler.largest_name, cpu, wall, sampler.samples,
              platform.machine()))
    load_after = os.getloadavg()
    print("README's first command (venv, pip install '.[cli]', inject): CPU %.1f s, wall %.1f s "
          "on %d CPUs, KESTIMATOR_BUILD_JOBS=%s; load average %.2f before, %.2f after" % (
              first_cpu, first_wall, os.cpu_count() or 0, args.jobs or "unset",
              load_before[0], load_after[0]))
    print("wall s by phase: %s" % _phases(marks, started, groups))
    if peak >= args.limit:
        print("over the limit: %.0f MiB >= %.0f MiB" % (peak, args.limit))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
