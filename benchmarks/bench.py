"""Throughput and memory of `kestimator inject` and `estimate` against a plain line copy.

Each measurement runs in a fresh child process, so its peak RSS is that child's alone
(`ru_maxrss` of RUSAGE_CHILDREN, read right after the one child has exited). Case 1 is
the large PrusaSlicer file; case 2 is that file concatenated with itself 4 times (written
to a temporary directory and deleted afterwards), to show memory does not grow with size.
A dated row per case and build is appended to benchmarks/RESULTS.md.

Under CPython both builds are measured side by side (`--build both`, the default): the
pure package of this checkout, and the mypyc-compiled one, which this script builds first
(`pip install` of a copy of the sources into a temporary venv, KESTIMATOR_BUILD=compiled,
the build's time printed). Runs of the copy and of both builds alternate, so load on a
shared host falls on all of them alike; each ratio is to the copy of the same run, the
least of its COPY_RUNS runs a round (the short copy needs more samples to hold still).

    python benchmarks/bench.py [--python PYTHON] [--build pure|compiled|both] [--repeat N]
                               [--env KEY=VALUE ...] [--no-concat] [--no-record] [--note TEXT]

In the same run: klipper_estimator's `estimate` and `post-process` (the build in
../shared/peers, when there), with each build's CPU as a ratio to theirs; and, on the 1x
file, the CPU of the worker's answers (`ANSWER_SRC`) for each build: the first answer with
and without checkpoints, the Klipper module's requests after changes at 10 %, 50 % and
90 % of the file, and a whole pass (a second table in RESULTS.md; `--no-answers` skips it).

Before any run, the measured packages' bytecode is compiled (`compileall`, as `pip install`
does for an installed package), so no measured run compiles source: with
PYTHONDONTWRITEBYTECODE set, a checkout would otherwise be compiled afresh in every run
(about 0.07 s of PyPy's and 0.06 s of CPython's start-up on this host).

`--env` sets a variable for every measured run (the copy too), e.g. PyPy's nursery:
`--python pypy3 --env PYPY_GC_NURSERY=16M`. PyPy sizes its nursery to half the last-level
cache it detects; this VM reports a 480 MiB L3, so PyPy's default nursery is 240 MiB,
which costs RSS and time on every run (a desktop CPU's L3 gives 4-16 MiB).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DEFAULT_FILE = os.path.join(ROOT, "..", "shared", "corpus", "gcode", "prusaslicer",
                            "ps25_bunny120_fast_fwretract_large.gcode")
RESULTS = os.path.join(HERE, "RESULTS.md")
CONCAT_COPIES = 4
PEERS = os.path.join(ROOT, "..", "shared", "peers")
PEER = os.path.join(PEERS, "klipper_estimator")
PEER_CONFIG = os.path.join(PEERS, "klipper_estimator_corpus.json")
CORPUS_CFG = os.path.join(ROOT, "..", "shared", "corpus", "printer.cfg")
MIB = 1024 * 1024

# The baseline: the cheapest honest pure-Python pass over the same lines.
# It is run COPY_RUNS times a round, the others once: every ratio divides by its least time,
# and a 0.2 s run moves by 10-15 % with the host's start-up jitter (the least of three
# copies was 0.20-0.23 s in runs of one evening, the estimate 4.65-4.71 s), which alone
# moved the pure estimate from 23.4x to 20.8x the copy; the least of 12 holds still.
COPY_RUNS = 4
COPY_SRC = """
import sys
with open(sys.argv[1], "rb") as inp, open(sys.argv[2], "wb") as out:
    for line in inp:
        out.write(line)
"""
# The worker's answers after changes at 10 %, 50 % and 90 % of the file (issue 37), CPU
# seconds of each, in one process: the first answer (one pass, taking checkpoints), the same
# without checkpoints, then the Klipper module's requests through a print (each holds every
# change so far), and a whole pass with the last request's changes for comparison.
ANSWER_SRC = """
import json, os, sys, time
from kestimator import resume, worker
path, config = sys.argv[1], sys.argv[2]
size = os.path.getsize(path)
def ask(events):
    request = worker._checked({"id": 1, "file": path, "config": config, "events": events,
                               "use_table": False})
    t0 = time.process_time()
    doc = worker.answer(request)
    cpu = time.process_time() - t0
    assert doc["ok"], doc
    doc.pop("elapsed_s")
    return cpu, json.dumps(doc, sort_keys=True)
out = {}
limit = resume.MAX_CHECKPOINT_BYTES
resume.MAX_CHECKPOINT_BYTES = 0
worker._resumable = None
out["pass_no_checkpoints"] = ask([])[0]
resume.MAX_CHECKPOINT_BYTES = limit
worker._resumable = None
out["first"] = ask([])[0]
out["checkpoint_mib"] = worker._resumable.nbytes / 1048576.0
out["checkpoints"] = len(worker._resumable.checkpoints)
events = []
for fraction, command in ((0.1, "M220 S150"), (0.5, "SET_VELOCITY_LIMIT ACCEL=1500"),
                          (0.9, "M220 S70")):
    events.append([int(size * fraction), command])
    out["change_%d" % round(fraction * 100)], last = ask(list(events))
worker._resumable = None
out["whole_pass"], whole = ask(list(events))
if whole != last:
    sys.exit("the resumed answer differs from the whole pass's")
print(json.dumps(out))
"""
WRAP_SRC = """
import resource, subprocess, sys, time
with open(sys.argv[1], "wb") as out:
    t0 = time.perf_counter()
    rc = subprocess.call(sys.argv[2:], stdout=out)
    wall = time.perf_counter() - t0
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(wall, ru.ru_maxrss, rc, ru.ru_utime + ru.ru_stime)
"""


def measure(python: str, argv: list[str], stdout_path: str,
            extra_env: dict[str, str] | None = None,
            checkout: bool = True) -> tuple[float, float, float]:
    """Wall seconds, peak RSS (MiB) and CPU seconds of `python argv...` in a fresh process.

    A wrapper process starts exactly one child, so RUSAGE_CHILDREN's ru_maxrss (kB on
    Linux) is that child's own peak. With `checkout`, this checkout's package is imported
    (the pure build); without, the one installed beside `python` (the compiled venv).
    """
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    if checkout:
        env["PYTHONPATH"] = ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")
    env.update(extra_env or {})
    proc = subprocess.run([sys.executable, "-c", WRAP_SRC, stdout_path, python] + argv,
                          stdout=subprocess.PIPE, env=env, check=True, cwd=HERE)
    wall_s, rss_kb, rc, cpu_s = proc.stdout.split()
    if rc != b"0":
        sys.exit("benchmark run failed (rc %s): %s %s" % (rc.decode(), python, " ".join(argv)))
    return float(wall_s), int(rss_kb) / 1024.0, float(cpu_s)


def build_compiled(python: str, tmpdir: str) -> tuple[str, float]:
    """Build and install the compiled package into a venv; its python and the build's time."""
    src = os.path.join(tmpdir, "src")
    os.mkdir(src)
    for name in ("kestimator", "setup.py", "pyproject.toml", "README.md"):
        source = os.path.join(ROOT, name)
        if os.path.isdir(source):
            shutil.copytree(source, os.path.join(src, name),
                            ignore=shutil.ignore_patterns("__pycache__", "*.so"))
        else:
            shutil.copyfile(source, os.path.join(src, name))
    env_dir = os.path.join(tmpdir, "venv-compiled")
    subprocess.run([python, "-m", "venv", env_dir], check=True)
    venv_python = os.path.join(env_dir, "bin", "python")
    t0 = time.perf_counter()
    proc = subprocess.run([venv_python, "-m", "pip", "install", "-v", "--no-deps", src],
                          env=dict(os.environ, KESTIMATOR_BUILD="compiled"),
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    build_s = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit("building the compiled package failed:\n" + proc.stdout[-3000:])
    for line in proc.stdout.splitlines():
        if "kestimator build:" in line:
            print(line.strip())
    return venv_python, build_s


def compile_bytecode(python: str, package_dir: str) -> None:
    """Write `python`'s bytecode for every module under `package_dir` (py_compile writes it
    whatever PYTHONDONTWRITEBYTECODE says), as an installed package has it."""
    subprocess.run([python, "-m", "compileall", "-q", package_dir], check=True,
                   stdout=subprocess.DEVNULL)


def installed_package_dir(python: str) -> str:
    """Where `python` imports kestimator from when this checkout is not on its path."""
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    out = subprocess.run([python, "-c", "import os, kestimator; "
                          "print(os.path.dirname(kestimator.__file__))"],
                         stdout=subprocess.PIPE, check=True, cwd=HERE, env=env, text=True)
    return out.stdout.strip()


# What a run gives: wall seconds (the least of the runs), peak RSS in MiB (the greatest),
# and the CPU seconds of the run with the least wall time.
Run = tuple[float, float, float]


@dataclasses.dataclass
class Case:
    """One file's measurements: each run by name ("copy", "estimate", "inject compiled",
    "klipper_estimator estimate", ...) and what the estimates said of the file."""

    size_mb: float
    runs: dict[str, Run]
    n_moves: int = 0
    total_s: float = 0.0


def bench_case(python: str, path: str, tmpdir: str, repeat: int,
               extra_env: dict[str, str] | None = None,
               compiled_python: str | None = None) -> Case:
    size_mb = os.path.getsize(path) / 1e6
    out = os.path.join(tmpdir, "out.gcode")
    stdout_path = os.path.join(tmpdir, "stdout")
    runs: dict[str, tuple[str, list[str], bool]] = {
        "copy": (python, ["-c", COPY_SRC, path, out], True),
        "estimate": (python, ["-m", "kestimator", "estimate", path, "--json"], True),
        "inject": (python, ["-m", "kestimator", "inject", path, "-o", out, "-q"], True),
    }
    if compiled_python is not None:
        runs["estimate compiled"] = (compiled_python, ["-m", "kestimator", "estimate", path,
                                                       "--json"], False)
        runs["inject compiled"] = (compiled_python, ["-m", "kestimator", "inject", path, "-o",
                                                     out, "-q"], False)
    peer_file = os.path.join(tmpdir, "peer.gcode")
    if os.access(PEER, os.X_OK):
        # klipper_estimator, in the same run: its estimate, and its post-process (which
        # rewrites the file in place: a fresh copy before each run, not measured).
        runs["klipper_estimator estimate"] = (PEER, ["--config_file", PEER_CONFIG, "estimate",
                                                     "-f", "json", path], False)
        runs["klipper_estimator post-process"] = (PEER, ["--config_file", PEER_CONFIG,
                                                         "post-process", peer_file], False)
    res = Case(size_mb, {})
    best = res.runs
    said: tuple[int, float] | None = None
    samples = [name for name in runs for _ in range(COPY_RUNS if name == "copy" else 1)]
    for _ in range(repeat):
        for name in samples:
            run_python, argv, checkout = runs[name]
            if name.endswith("post-process"):
                shutil.copyfile(path, peer_file)
            wall, rss, cpu = measure(run_python, argv, stdout_path, extra_env, checkout)
            prev = best.get(name)
            peak = rss if prev is None else max(rss, prev[1])
            if prev is None or wall < prev[0]:
                best[name] = (wall, peak, cpu)
            else:
                best[name] = (prev[0], peak, prev[2])
            if name.startswith("estimate"):
                with open(stdout_path, encoding="utf-8") as f:
                    doc = json.load(f)
                this = (doc["n_moves"], doc["total_s"])
                if said is not None and this != said:
                    sys.exit("the builds disagree: %r" % name)
                said = this
                res.n_moves, res.total_s = this
            if os.path.exists(out):
                os.unlink(out)
    return res


def for_build(res: Case, build: str) -> Case:
    """`res` with the given build's estimate and inject under the plain names."""
    if build == "pure":
        return res
    runs = dict(res.runs)
    runs["estimate"] = res.runs["estimate " + build]
    runs["inject"] = res.runs["inject " + build]
    return dataclasses.replace(res, runs=runs)


def report(label: str, res: Case) -> list[str]:
    runs = res.runs
    copy_t, _rss, copy_cpu = runs["copy"]
    lines = ["%s: %.1f MB, %d moves, total_s %r" % (label, res.size_mb, res.n_moves,
                                                   res.total_s)]
    for name in ("copy", "estimate", "inject", "estimate compiled", "inject compiled",
                 "klipper_estimator estimate", "klipper_estimator post-process"):
        if name not in runs:
            continue
        wall, rss, cpu = runs[name]
        lines.append("  %-30s %7.2f s  %9.0f moves/s  %6.1f MB/s  %5.2fx copy  %6.1f MiB"
                     "  (CPU %.2f s, %.2fx copy's CPU)" % (
                         name, wall, res.n_moves / wall, res.size_mb / wall, wall / copy_t,
                         rss, cpu, cpu / copy_cpu))
    for ours, theirs in (("estimate compiled", "klipper_estimator estimate"),
                         ("inject compiled", "klipper_estimator post-process")):
        if ours in runs and theirs in runs:
            lines.append("  CPU %s / %s: %.2f" % (ours, theirs, runs[ours][2] / runs[theirs][2]))
    return lines


def answer_times(python: str, path: str, repeat: int, checkout: bool,
                 extra_env: dict[str, str] | None = None) -> dict[str, float]:
    """CPU seconds of the worker's answers (ANSWER_SRC), the least of `repeat` processes."""
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    if checkout:
        env["PYTHONPATH"] = ROOT
    env.update(extra_env or {})
    best: dict[str, float] = {}
    for _ in range(repeat):
        with tempfile.TemporaryDirectory(prefix="kestimator-home-") as home:
            # A new user's home: no profile, no learned times.
            env.update(HOME=home, XDG_CONFIG_HOME=os.path.join(home, "config"),
                       XDG_CACHE_HOME=os.path.join(home, "cache"))
            out = subprocess.run([python, "-c", ANSWER_SRC, path, os.path.abspath(CORPUS_CFG)],
                                 stdout=subprocess.PIPE, env=env, check=True, cwd=HERE)
        for key, value in json.loads(out.stdout).items():
            best[key] = value if key not in best else min(best[key], value)
    return best


def answer_report(build: str, times: dict[str, float]) -> list[str]:
    whole = times["whole_pass"]
    lines = ["  answers, %s: first %.3f s CPU (%.3f s without checkpoints: %+.0f %%), %d "
             "checkpoints %.1f MiB; whole pass %.3f s" % (
                 build, times["first"], times["pass_no_checkpoints"],
                 100.0 * (times["first"] / times["pass_no_checkpoints"] - 1.0),
                 times["checkpoints"], times["checkpoint_mib"], whole)]
    for pct in (10, 50, 90):
        t = times["change_%d" % pct]
        # One decimal: issue 37's bar (15 % at 90 %) is close enough to need it.
        lines.append("    change at %d %%: %.3f s CPU = %.1f %% of a whole pass"
                     % (pct, t, 100.0 * t / whole))
    return lines


def answer_row(python: str, build: str, times: dict[str, float], note: str) -> str:
    whole = times["whole_pass"]
    return ("| %s | %s | %.2f | %.2f | %.2f | %s | %d / %.1f | %s |" % (
        datetime.date.today().isoformat(),
        python_name(python) + (" compiled" if build == "compiled" else ""),
        whole, times["first"], times["pass_no_checkpoints"],
        " / ".join("%.3f (%.1f %%)" % (times["change_%d" % p], 100.0 * times["change_%d" % p]
                                       / whole) for p in (10, 50, 90)),
        times["checkpoints"], times["checkpoint_mib"], note))


ANSWERS_HEAD = ("\n## The worker's answer after a change (issue 37)\n\n"
                "CPU seconds of the worker's answers on the 1x file, the least of the runs: "
                "a whole pass with the three changes; the first answer (one pass taking "
                "checkpoints) and the same pass without them; the answers to the Klipper "
                "module's requests after changes at 10 %, 50 % and 90 % of the file (each "
                "holding the changes before it), with their share of a whole pass.\n\n"
                "| date | python | whole pass s | first answer s | without checkpoints s "
                "| change at 10 / 50 / 90 % s | checkpoints / MiB | note |\n"
                "|---|---|---|---|---|---|---|---|\n")


def append_answer_rows(rows: list[str]) -> None:
    with open(RESULTS, encoding="utf-8") as f:
        text = f.read()
    if ANSWERS_HEAD not in text:
        text = text.rstrip("\n") + "\n" + ANSWERS_HEAD
    start = text.index(ANSWERS_HEAD) + len(ANSWERS_HEAD)
    end = start
    while text.startswith("|", end):
        end = text.index("\n", end) + 1
    with open(RESULTS, "w", encoding="utf-8") as f:
        f.write(text[:end] + "".join(row + "\n" for row in rows) + text[end:])


def md_row(label: str, python: str, res: Case, note: str, build: str = "pure") -> str:
    copy_t = res.runs["copy"][0]
    est_t, est_rss, _cpu = res.runs["estimate"]
    inj_t, inj_rss, _cpu = res.runs["inject"]
    return ("| %s | %s | %s | %.1f | %.2f | %.2f (%.1fx) | %.2f (%.1fx) | %.0f / %.0f | "
            "%.0f | %s |" % (
                datetime.date.today().isoformat(),
                python_name(python) + (" compiled" if build == "compiled" else ""), label,
                res.size_mb, copy_t, est_t, est_t / copy_t, inj_t, inj_t / copy_t,
                est_rss, inj_rss, res.n_moves / est_t, note))


def python_name(python: str) -> str:
    out = subprocess.run([python, "-c", "import platform;print(platform."
                          "python_implementation(), platform.python_version())"],
                         stdout=subprocess.PIPE, check=True)
    return out.stdout.decode().strip()


HEADER = """# Benchmarks

Produced by `python benchmarks/bench.py`. Times are the best of the runs, each in a fresh
process; RSS is that process's peak. Ratios are to a plain Python line copy of the same file
in the same run. Targets (issue 8): inject <= 8x, estimate <= 6x (CPython), PyPy <= 4x,
peak RSS <= 64 MiB on both cases.

"""
TABLE_HEAD = ("| date | python | case | MB | copy s | estimate s (ratio) | inject s (ratio) "
              "| RSS est / inj MiB | moves/s (est) | note |\n"
              "|---|---|---|---|---|---|---|---|---|---|\n")


def append_rows(rows: list[str]) -> None:
    if not os.path.exists(RESULTS):
        with open(RESULTS, "w", encoding="utf-8") as f:
            f.write(HEADER + TABLE_HEAD)
    with open(RESULTS, encoding="utf-8") as f:
        lines = f.read().splitlines(keepends=True)
    # Rows go right after the last row of the first table (notes may follow it).
    start = next(i for i, line in enumerate(lines) if line.startswith("| date |"))
    end = start
    while end < len(lines) and lines[end].startswith("|"):
        end += 1
    lines[end:end] = [row + "\n" for row in rows]
    with open(RESULTS, "w", encoding="utf-8") as f:
        f.write("".join(lines))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--file", default=DEFAULT_FILE)
    parser.add_argument("--python", default=sys.executable)
    parser.add_argument("--build", choices=("pure", "compiled", "both"), default=None,
                        help="which build(s) to measure (default: both under CPython, "
                        "pure under PyPy)")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--no-concat", action="store_true")
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument("--no-answers", action="store_true",
                        help="skip the worker's answers after a change")
    parser.add_argument("--note", default="")
    parser.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                        help="set for every measured run (repeatable)")
    args = parser.parse_args()
    path = os.path.abspath(args.file)
    extra_env = dict(item.split("=", 1) for item in args.env)
    note = "; ".join(filter(None, [" ".join(args.env), args.note]))
    build = args.build or ("pure" if python_name(args.python).startswith("PyPy") else "both")
    builds = ["pure", "compiled"] if build == "both" else [build]
    load = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory(prefix="kestimator-bench-") as tmpdir:
        compiled_python = None
        if "compiled" in builds:
            compiled_python, build_s = build_compiled(args.python, tmpdir)
            print("compiled build (pip install, mypyc + C compiler): %.1f s" % build_s)
            compile_bytecode(compiled_python, installed_package_dir(compiled_python))
        compile_bytecode(args.python, os.path.join(ROOT, "kestimator"))
        cases = [("1x", path)]
        if not args.no_concat:
            big = os.path.join(tmpdir, "concat4.gcode")
            with open(big, "wb") as out:
                for _ in range(CONCAT_COPIES):
                    with open(path, "rb") as inp:
                        shutil.copyfileobj(inp, out, 1 << 20)
            cases.append(("%dx" % CONCAT_COPIES, big))
        answer_rows = []
        for label, case_path in cases:
            res = bench_case(args.python, case_path, tmpdir, args.repeat, extra_env,
                             compiled_python)
            print("\n".join(report(label, res)), flush=True)
            for one in builds:
                rows.append(md_row(label, args.python, for_build(res, one), note, one))
            if label != "1x" or args.no_answers:
                continue
            for one in builds:
                one_python = compiled_python if one == "compiled" else args.python
                assert one_python is not None
                times = answer_times(one_python, case_path, args.repeat, one == "pure",
                                     extra_env)
                print("\n".join(answer_report(one, times)), flush=True)
                answer_rows.append(answer_row(args.python, one, times, note))
    load = max(load, os.getloadavg()[0])
    print("host:", platform.node(), platform.processor() or platform.machine(),
          "load average (1 min) up to %.1f" % load)
    if not args.no_record:
        append_rows([row.replace(" |\n", " |") for row in rows])
        if answer_rows:
            append_answer_rows(answer_rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
