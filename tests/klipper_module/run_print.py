"""Run a virtual-SD print of a G-code file in real Klipper (the oracle's, batch mode) with
the kestimator module loaded, sampling what it says against what Klipper takes.

    python3 tests/klipper_module/run_print.py FILE.gcode [--user LINE_FRACTION:CMD ...]
        [--inject] [--samples N] [--exclude-object]

Needs the oracle set up (../shared/tools/oracle/README.md): ORACLE_KLIPPER (a Klipper
84104bbbd tree with out/klipper.dict) and ORACLE_PYTHON (its venv). The module, this
directory's ktest_probe.py and the oracle's oracle_probe.py are linked into
klippy/extras/, as a user links an add-on.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any, Callable

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
SHARED = os.path.join(os.path.dirname(ROOT), "shared")
ORACLE_DIR = os.path.join(SHARED, "tools", "oracle")
CORPUS_CFG = os.path.join(SHARED, "corpus", "printer.cfg")
MODULE = os.path.join(ROOT, "plugins", "klipper", "kestimator")


def oracle_paths() -> tuple[str, str] | None:
    """(Klipper tree, its Python) when the oracle is set up here, else None."""
    klipper = os.environ.get("ORACLE_KLIPPER", os.path.expanduser("~/oracle/klipper"))
    python = os.environ.get("ORACLE_PYTHON", os.path.expanduser("~/oracle/venv/bin/python"))
    if (os.path.exists(os.path.join(klipper, "klippy", "klippy.py"))
            and os.path.exists(os.path.join(klipper, "out", "klipper.dict"))
            and os.path.exists(python)):
        return klipper, python
    return None


def run_klippy(cfg: str, batch: str, log: str, out: str, env: dict[str, str],
               timeout: float, klipper_tree: tuple[str, str] | None = None
               ) -> dict[str, Any]:
    """Klipper's klippy.py in batch mode on `cfg` with the commands of `batch`, the test
    module writing its results (JSON) to `out`: those results, with `returncode`.
    `klipper_tree`: (Klipper tree, its Python) instead of the oracle's."""
    paths = klipper_tree or oracle_paths()
    if paths is None:
        raise RuntimeError("the oracle's Klipper is not set up (ORACLE_KLIPPER)")
    klipper, kpython = paths
    with open(os.path.join(klipper, "klippy", "extras", "virtual_sdcard.py")) as f:
        waits_for_print = "gcode:debuginput_exit" in f.read()
    if waits_for_print:
        proc = subprocess.run(
            [kpython, os.path.join(klipper, "klippy", "klippy.py"), cfg, "-i", batch,
             "-o", "/dev/null", "-d", os.path.join(klipper, "out", "klipper.dict"), "-l", log],
            env=env, stdin=subprocess.DEVNULL, capture_output=True, cwd=klipper,
            timeout=timeout)
        returncode = proc.returncode
    else:
        returncode = _run_klippy_until(out, klipper, kpython, cfg, batch, log, env, timeout)
    if not os.path.exists(out):
        with open(log, errors="replace") as f:
            tail = f.read()[-3000:]
        raise RuntimeError("Klipper did not finish the print (rc %d):\n%s"
                           % (returncode, tail))
    with open(out) as f:
        result: dict[str, Any] = json.load(f)
    result["returncode"] = returncode
    return result


def _run_klippy_until(out: str, klipper: str, kpython: str, cfg: str, batch: str,
                      log: str, env: dict[str, str], timeout: float) -> int:
    """klippy.py in batch mode where the end of the batch input ends Klipper at once, its
    print not waited for (v0.12.0, v0.13.0, Kalico: their virtual_sdcard has no
    gcode:debuginput_exit handler): the input is a pipe, held open until the test module
    wrote `out` (or Klipper stopped). Its return code."""
    fifo = batch + ".fifo"
    os.mkfifo(fifo)
    # Read-write: opening never waits for Klipper, and the pipe ends (EOF) at our close.
    fd = os.open(fifo, os.O_RDWR)
    try:
        with open(batch, "rb") as f:
            os.write(fd, f.read())
        with open(log + ".out", "wb") as output:
            proc = subprocess.Popen(
                [kpython, os.path.join(klipper, "klippy", "klippy.py"), cfg, "-i", fifo,
                 "-o", "/dev/null", "-d", os.path.join(klipper, "out", "klipper.dict"),
                 "-l", log], env=env, stdin=subprocess.DEVNULL, stdout=output,
                stderr=subprocess.STDOUT, cwd=klipper)
            try:
                deadline = time.monotonic() + timeout
                while (proc.poll() is None and not os.path.exists(out)
                       and time.monotonic() < deadline):
                    time.sleep(0.1)
                os.close(fd)
                fd = -1
                return proc.wait(max(1., deadline - time.monotonic()))
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
    finally:
        if fd >= 0:
            os.close(fd)


def _link(src: str, klipper: str, name: str) -> None:
    """Point klippy/extras/`name` at `src` (a module's file, or a package's folder as the
    kestimator module is). Prints run in parallel threads and processes, so the link is
    made under a name of its own and renamed over `dst`: a check-then-create raced
    (FileExistsError) when two prints linked the same module at once."""
    dst = os.path.join(klipper, "klippy", "extras", name)
    if os.path.isdir(src):
        # A package's earlier shape, one file linked as NAME.py: the package shadows it
        # (Python imports a folder's package before a module of the same name), and it
        # would be left broken once the checkout it points into moves on.
        old = dst + ".py"
        if os.path.islink(old):
            try:
                os.unlink(old)
            except FileNotFoundError:
                pass
    if os.path.lexists(dst) and os.path.realpath(dst) == os.path.realpath(src):
        return
    tmp = "%s.%d.%d.tmp" % (dst, os.getpid(), threading.get_ident())
    os.symlink(src, tmp)
    os.replace(tmp, dst)


def _is_move(line: bytes) -> bool:
    word = line.lstrip()[:3].upper()
    return word in (b"G1 ", b"G0 ", b"G2 ", b"G3 ") or word.rstrip() in (b"G1", b"G0")


def make_test_file(src: str, dst: str, samples: int,
                   users: list[tuple[float, str]]) -> list[int]:
    """Copy `src` to `dst` with KTEST_SAMPLE lines spread over its moves, KTEST_USER lines
    at the given fractions of its moves (each followed by a sample), and KTEST_END.
    Returns the 1-based lines of `dst` where each user command sits."""
    with open(src, "rb") as f:
        lines = f.read().split(b"\n")
    if lines and lines[-1] == b"":
        lines.pop()
    moves = [i for i, line in enumerate(lines) if _is_move(line)]
    at: dict[int, list[bytes]] = {}
    for k in range(samples):
        # before the move at this fraction (k = 0: before the first move)
        i = moves[min(len(moves) - 1, int(len(moves) * k / samples))]
        at.setdefault(i, [])
    for fraction, command in users:
        i = moves[min(len(moves) - 1, int(len(moves) * fraction))]
        at.setdefault(i, []).append(command.encode())
    out: list[bytes] = []
    user_lines = []
    sample_id = 0
    for i, line in enumerate(lines):
        if i in at:
            for command in at[i]:
                user_lines.append(len(out) + 1)
                out.append(b'KTEST_USER CMD="' + command + b'"')
            sample_id += 1
            out.append(b"KTEST_SAMPLE ID=%d" % sample_id)
        out.append(line)
    sample_id += 1
    out.append(b"KTEST_SAMPLE ID=%d" % sample_id)
    out.append(b"KTEST_END")
    with open(dst, "wb") as f:
        f.write(b"\n".join(out) + b"\n")
    return user_lines


def run_print(src: str, work: str, samples: int = 12,
              users: list[tuple[float, str]] | None = None, inject: bool = False,
              base_cfg: str = CORPUS_CFG, python: str | None = None,
              extra_cfg: str = "",
              finish_file: Callable[[str], None] | None = None,
              klipper_tree: tuple[str, str] | None = None) -> dict[str, Any]:
    """Print `src` in Klipper with the module; returns the probe's results, each sample
    with `truth_s` (Klipper's remaining time from there) and `error_s`. `klipper_tree`:
    (Klipper tree, its Python) to print in instead of the oracle's."""
    paths = klipper_tree or oracle_paths()
    if paths is None:
        raise RuntimeError("the oracle's Klipper is not set up (ORACLE_KLIPPER)")
    klipper, _ = paths
    python = python or sys.executable
    sd = os.path.join(work, "sd")
    os.makedirs(sd, exist_ok=True)
    test_file = os.path.join(sd, "test.gcode")
    user_lines = make_test_file(src, test_file, samples, users or [])
    cfg = os.path.join(work, "printer.cfg")
    with open(cfg, "w") as f:
        f.write("[include %s]\n\n[virtual_sdcard]\npath: %s\n\n[exclude_object]\n\n"
                "[display_status]\n\n[oracle_probe]\n\n[ktest_probe]\n\n"
                "[kestimator]\npython: %s\n\n%s" % (os.path.abspath(base_cfg), sd, python,
                                                    extra_cfg))
    if inject:
        subprocess.run([python, "-m", "kestimator", "inject", test_file, "--printer-cfg", cfg],
                       check=True, capture_output=True, cwd=work)
    if finish_file is not None:
        finish_file(test_file)
    _link(MODULE, klipper, "kestimator")
    _link(os.path.join(HERE, "ktest_probe.py"), klipper, "ktest_probe.py")
    _link(os.path.join(ORACLE_DIR, "oracle_probe.py"), klipper, "oracle_probe.py")
    batch = os.path.join(work, "batch.gcode")
    with open(batch, "w") as f:
        f.write("ORACLE_ORIGIN\nORACLE_HOME ZERO=1\nSDCARD_PRINT_FILE FILENAME=test.gcode\n")
    out = os.path.join(work, "ktest.json")
    log = os.path.join(work, "klippy.log")
    env = dict(os.environ, KTEST_OUT=out, ORACLE_OUT=os.path.join(work, "oracle.json"))
    result = run_klippy(cfg, batch, log, out, env, 1800., klipper_tree)
    end = result["end_print_time"]
    for sample in result["samples"]:
        sample["truth_s"] = end - sample["print_time"]
        if sample.get("remaining_s") is not None:
            sample["error_s"] = sample["remaining_s"] - sample["truth_s"]
    result["user_lines"] = user_lines
    result["test_file"] = test_file
    return result


# The module's bars against Klipper: plain prints 0.5 s + 0.2 %; after a typed change 1 s + 1 %,
# from 2 s of print time after it; the answer to a change within 2 s.
PLAIN_ABS, PLAIN_REL = 0.5, 0.002
CHANGED_ABS, CHANGED_REL = 1.0, 0.01
ANSWER_WITHIN_S = 2.0


def samples_off_bar(samples: list[dict[str, Any]], absolute: float,
                    relative: float) -> list[Any]:
    """The samples whose remaining_s is missing or off Klipper's truth by more than
    `absolute` + `relative` x the truth: (id, remaining_s, truth_s) of each."""
    return [(s["id"], s["remaining_s"], round(s["truth_s"], 3)) for s in samples
            if s.get("remaining_s") is None
            or abs(s["error_s"]) > absolute + relative * s["truth_s"]]


def samples_after_change(result: dict[str, Any], answer_within_s: float) -> list[dict[str, Any]]:
    """The samples from the one typed change on: the worker asked and answered within
    `answer_within_s`."""
    (user,) = result["users"]
    assert user["asked"] and user["answered"]
    assert user["answer_wait_s"] < answer_within_s
    change_t = next(s["print_time"] for s in result["samples"]
                    if s["position"] >= user["position"])
    return [s for s in result["samples"] if s["print_time"] >= change_t]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("gcode")
    ap.add_argument("--samples", type=int, default=12)
    ap.add_argument("--user", action="append", default=[],
                    help="FRACTION:COMMAND, e.g. 0.4:M220 S150")
    ap.add_argument("--inject", action="store_true")
    ap.add_argument("--keep", action="store_true")
    args = ap.parse_args()
    users = []
    for spec in args.user:
        fraction, command = spec.split(":", 1)
        users.append((float(fraction), command))
    work = tempfile.mkdtemp(prefix="ktest-")
    try:
        result = run_print(args.gcode, work, args.samples, users, args.inject)
        json.dump(result, sys.stdout, indent=1)
        sys.stdout.write("\n")
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
