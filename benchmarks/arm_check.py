"""The ARM check: kestimator built and run on the printer host's own CPU gives x86's results.

A Raspberry Pi runs Debian for arm64 (Raspberry Pi OS 64-bit) or armhf (32-bit), and
install.sh compiles kestimator there with that host's gcc. This tool builds a Debian bookworm
chroot for each architecture (.ci/arm-chroot, run through qemu-user), installs this checkout
into it twice with the very pip command install.sh's build runs (plugins/moonraker/build-venv:
`pip install -v --no-cache-dir --force-reinstall`), compiled (KESTIMATOR_BUILD=compiled) and
pure, and runs corpus files through each: every field of the estimate (tests/
estimate_digest.py, floats bit for bit, every layer), `estimate --json`'s bytes and the bytes
`inject` writes (progress table included) must equal what pure CPython gives on this x86 host,
and the total and every layer must be Klipper's own (shared/corpus/reference, the bar of
tests/test_accuracy_corpus.py).

    python3 benchmarks/arm_check.py [--arch arm64] [--arch armhf] [--build compiled]
                                    [--build pure] [--files two|all] [--root DIR]

As root (chroot, mounts), with debootstrap and qemu-user-static installed. Emulated ARM is
slow: the whole check (both architectures, both builds, the 30 corpus files up to 5 MB) takes
hours of one core, so it is this tool, its last result recorded in benchmarks/RESULTS.md.
The chroots stay in --root for the next run (delete the folder to start again); nothing is
mounted in them after the tool exits.

`--install` tries the printer's own path in the arm64 chroot instead: a host as
tests/test_install_sh.py makes one (a git clone of this checkout whose origin is a local bare
repository, a printer data folder with the corpus's printer.cfg, a klipper_estimator for
install.sh to keep, a ~/klipper/klippy/extras for the Klipper module's link), then
`./install.sh` as a user runs it (compiled where gcc is: the default), the Klipper module's
worker started as the module starts it and its first answer, a new commit pulled as
Moonraker's update manager pulls it (git's post-merge hook rebuilds the venv), and the
worker's answer again: each answer's times must be x86's, bit for bit.

`python3 benchmarks/arm_check.py outputs CORPUS_DIR FILE...` is the side that
runs under the interpreter checked (inside the chroot, or on the host for x86's side): one
JSON line per file; `ask-worker CHECKOUT FILE PRINTER_CFG` starts the Klipper module's worker
of CHECKOUT and prints its first answer.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import TracebackType

PROJECT = Path(__file__).resolve().parents[1]
CORPUS = PROJECT.parent / "shared" / "corpus"
CHROOT_SCRIPT = PROJECT / ".ci" / "arm-chroot"
DEFAULT_ROOT = Path("/var/tmp/kestimator-arm")
ARCHES = ("arm64", "armhf")
BUILDS = ("compiled", "pure", "group")
# The "group" build: the compiled build made of one mypyc group (one C file, one gcc run under
# emulation, about a third of the whole build), the smaller ARM step .ci/run takes
# (tests/test_arm_chroot.py). Its modules are the float arithmetic of the two files below:
# the look-ahead (toolhead) and the arcs (gcode_arcs) their G2/G3 lines go through. Built on
# x86 with the float flags taken away and `-march=haswell` (fused multiply-add allowed), this
# group alone gives the 1471.917574 s and 354.288496 s (toolhead alone, or the whole
# per-line group without gcode_arcs, gives Klipper's times: the fused difference is in the
# arcs); with setup.py's flags it must give x86's pure results.
GROUP_MODULES = ("kestimator/toolhead.py", "kestimator/gcode_arcs.py")
GROUP_NAME = "kestimator_hot"
# Where the staged setup.py takes the one group instead of its own: just before it runs.
SETUP_RUNS = 'if __name__ == "__main__" and sys.argv[1:2] == [MYPYC_CHILD]:'
# Where OrcaSlicer 2.3.1's files came out 1471.918 s and 354.288 s with fused multiply-add
# (Klipper: 1473.045 s and 355.192 s).
TWO_FILES = ("orcaslicer/helixscreen_calicat_orca2.3.1_klipper.gcode",
             "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode")
MAX_FILE_BYTES = 5_000_000
# What a build is made from (as in an sdist), and the tool's own side of a run.
SOURCES = ("kestimator", "setup.py", "pyproject.toml", "README.md")
STAGE = "/opt/kestimator-check"
# tests/test_accuracy_corpus.py's bar against Klipper's references.
TOL_ABS_S = 0.01
TOL_REL = 1e-6
BUILD_TIMEOUT_S = 4 * 3600
RUN_TIMEOUT_S = 4 * 3600
REPORTED_PROBLEMS = 8  # per file: every layer after a wrong one is wrong too
CHROOT_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"


# --- the side that runs under the interpreter checked ----------------------------------

def file_outputs(python: str, path: str) -> dict[str, object]:
    """`estimate --json`'s and `inject`'s results for one file (a path relative to the
    corpus, the current folder, timed with its printer.cfg), run by `python` as a user would
    run them (a fresh process each). Relative paths: the JSON and the warnings name the file
    as given, the same on every machine."""
    with tempfile.TemporaryDirectory(prefix="kestimator-arm-") as tmp:
        estimate = subprocess.run(
            [python, "-m", "kestimator", "estimate", path, "--json", "--printer-cfg",
             "printer.cfg"], capture_output=True, timeout=RUN_TIMEOUT_S)
        if estimate.returncode != 0:
            raise RuntimeError("estimate %s: %s" % (path, estimate.stderr.decode()[-500:]))
        out = os.path.join(tmp, "out.gcode")
        inject = subprocess.run(
            [python, "-m", "kestimator", "inject", path, "-o", out, "-q", "--printer-cfg",
             "printer.cfg"], capture_output=True, timeout=RUN_TIMEOUT_S)
        # 4: Klipper would stop this print (pre-flight); the times are written all the same.
        if inject.returncode not in (0, 4):
            raise RuntimeError("inject %s: %s" % (path, inject.stderr.decode()[-500:]))
        with open(out, "rb") as f:
            injected = hashlib.sha256(f.read()).hexdigest()
    document = json.loads(estimate.stdout)
    return {"estimate": hashlib.sha256(estimate.stdout).hexdigest(), "inject": injected,
            "total_s": document["total_s"],
            "layers": [[entry["line"], entry["t"]] for entry in document["layers"]]}


def outputs(corpus: str, names: Sequence[str]) -> Iterator[dict[str, object]]:
    """One record per corpus file (named relative to `corpus`/gcode, timed with
    `corpus`/printer.cfg): the build, the estimate's every field (tests/estimate_digest.py)
    as a hash, and `file_outputs`. Runs in `corpus`, naming files relative to it."""
    import importlib

    # tests/estimate_digest.py: beside this file in the chroot, tests/ on the host.
    estimate_digest = importlib.import_module("estimate_digest")
    from kestimator import build

    os.chdir(corpus)
    for name in names:
        path = os.path.join("gcode", name)
        digest = json.dumps(estimate_digest.digest(path, "printer.cfg"), sort_keys=True)
        record: dict[str, object] = {"file": name, "build": build(),
                                     "digest": hashlib.sha256(digest.encode()).hexdigest()}
        record.update(file_outputs(sys.executable, path))
        yield record


def ask_worker(checkout: str, path: str, printer_cfg: str) -> dict[str, object]:
    """The first answer of the worker the Klipper module (CHECKOUT's plugins/klipper) starts,
    started as it starts it (its WORKER_BOOT, this Python), for `path` on `printer_cfg`."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "kestimator_klipper_worker", os.path.join(checkout, "plugins", "klipper",
                                                  "kestimator", "worker.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    proc = subprocess.Popen([sys.executable, "-c", module.WORKER_BOOT, checkout],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd="/")
    request = {"id": 1, "file": path, "config": printer_cfg}
    out, err = proc.communicate(json.dumps(request).encode() + b"\n", timeout=RUN_TIMEOUT_S)
    lines = out.splitlines()
    if not lines:
        raise RuntimeError("the worker gave no answer: " + err.decode(errors="replace")[-500:])
    answer: dict[str, object] = json.loads(lines[0])
    return answer


# --- the host's side -------------------------------------------------------------------

def corpus_names(which: str) -> list[str]:
    """The corpus files checked: "two" (TWO_FILES) or "all" (every file with a Klipper
    reference, up to MAX_FILE_BYTES), relative to corpus/gcode."""
    if which == "two":
        return list(TWO_FILES)
    names = []
    for ref in sorted((CORPUS / "reference").glob("*/*.json")):
        gcode = CORPUS / json.loads(ref.read_text())["file"]
        if gcode.stat().st_size <= MAX_FILE_BYTES:
            names.append(str(gcode.relative_to(CORPUS / "gcode")))
    return names


def reference(name: str) -> dict[str, object]:
    """Klipper's own times for a corpus file (shared/corpus/reference)."""
    path = CORPUS / "reference" / (name[:-len(".gcode")] + ".json")
    loaded: dict[str, object] = json.loads(path.read_text())
    return loaded


def _within(mine: float, ref: float) -> bool:
    return abs(mine - ref) <= TOL_ABS_S + TOL_REL * ref


def klipper_differences(record: dict[str, object]) -> list[str]:
    """Where a file's `estimate --json` is not Klipper's (total or a layer): empty if none."""
    ref = reference(str(record["file"]))
    found = []
    total = float(record["total_s"])  # type: ignore[arg-type]
    klipper = float(ref["total_s"])  # type: ignore[arg-type]
    if not _within(total, klipper):
        found.append("total %.3f s, Klipper %.3f s" % (total, klipper))
    mine = {int(line): float(t) for line, t in record["layers"]}  # type: ignore[attr-defined]
    for point in ref["checkpoints"]:  # type: ignore[attr-defined]
        if point["kind"] != "layer":
            continue
        if point["line"] not in mine:
            found.append("no layer at line %d" % point["line"])
        elif not _within(mine[point["line"]], point["t"]):
            found.append("layer at line %d: %.3f s, Klipper %.3f s" % (
                point["line"], mine[point["line"]], point["t"]))
    return found


def build_differences(record: dict[str, object], x86: dict[str, object]) -> list[str]:
    """What differs from x86's pure CPython for the same file: empty if nothing."""
    found = [what for what in ("digest", "estimate", "inject") if record[what] != x86[what]]
    if record["total_s"] != x86["total_s"]:
        found.append("total %r s, x86 %r s" % (record["total_s"], x86["total_s"]))
    return found


def x86_outputs(names: Sequence[str]) -> dict[str, dict[str, object]]:
    """The records of pure CPython on this host (this checkout's package)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(PROJECT), str(PROJECT / "tests")]))
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "outputs", str(CORPUS), *names],
        env=env, capture_output=True, text=True,
        timeout=RUN_TIMEOUT_S, cwd=tempfile.gettempdir())
    if proc.returncode != 0:
        raise RuntimeError("x86 outputs failed: " + proc.stderr[-2000:])
    return {str(r["file"]): r for r in map(json.loads, proc.stdout.splitlines())}


class Chroot:
    """A chroot with /proc, /sys and /dev bound while in use (and unbound even on failure)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.mounts: list[Path] = []

    def __enter__(self) -> Chroot:
        try:
            for name in ("proc", "sys", "dev"):
                target = self.root / name
                if subprocess.run(["mountpoint", "-q", str(target)]).returncode == 0:
                    continue
                subprocess.run(["mount", "--rbind", "/" + name, str(target)], check=True)
                self.mounts.insert(0, target)
                subprocess.run(["mount", "--make-rslave", str(target)], check=True)
        except BaseException:
            self.unmount()
            raise
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.unmount()

    def unmount(self) -> None:
        for target in self.mounts:
            if subprocess.run(["umount", "-R", str(target)], capture_output=True).returncode:
                subprocess.run(["umount", "-l", str(target)], capture_output=True)
        self.mounts = []

    def run(self, argv: Sequence[str], env: dict[str, str] | None = None,
            timeout: float = RUN_TIMEOUT_S, cwd: str = "/tmp") -> subprocess.CompletedProcess[str]:
        """`argv` inside the chroot, in a clean environment (pip given the host's CA bundle:
        a proxy between here and the package index may sign with its own)."""
        variables = {"PATH": CHROOT_PATH, "HOME": "/root", "LANG": "C.UTF-8",
                     "PIP_CERT": STAGE + "/ca.crt", "SSL_CERT_FILE": STAGE + "/ca.crt",
                     "PIP_DISABLE_PIP_VERSION_CHECK": "1",
                     "PIP_DEFAULT_TIMEOUT": "180"}
        variables.update(env or {})
        command = ["chroot", str(self.root), "/usr/bin/env", "-i",
                   *("%s=%s" % item for item in variables.items()),
                   "sh", "-c", 'cd "$0" && exec "$@"', cwd, *argv]
        return subprocess.run(command, capture_output=True, text=True, timeout=timeout)


def children_cpu_s() -> float:
    """CPU seconds (user and system) of every child process waited for so far: what a step
    cost on a machine other work shares (qemu's emulation counts as the child's)."""
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    return used.ru_utime + used.ru_stime


def make_chroot(arch: str, root: Path) -> Path:
    """The chroot of `arch` under `root` (.ci/arm-chroot; kept from an earlier run)."""
    target = root / arch
    root.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run([str(CHROOT_SCRIPT), arch, str(target)], capture_output=True,
                          text=True, timeout=BUILD_TIMEOUT_S)
    if proc.returncode != 0:
        raise RuntimeError("%s chroot: %s" % (arch, (proc.stderr or proc.stdout)[-2000:]))
    return target


def stage(chroot: Chroot, names: Sequence[str]) -> None:
    """Copy the sources (one copy per build), the tool, the corpus files and the host's CA
    bundle into the chroot's STAGE, replacing an earlier run's."""
    stage_dir = chroot.root / STAGE.lstrip("/")
    if stage_dir.exists():
        shutil.rmtree(stage_dir)
    ignore = shutil.ignore_patterns("__pycache__", "*.so", "*.pyd", "*.c", "build")
    for kind in BUILDS:
        src = stage_dir / ("src-" + kind)
        src.mkdir(parents=True)
        for name in SOURCES:
            if (PROJECT / name).is_dir():
                shutil.copytree(PROJECT / name, src / name, ignore=ignore)
            else:
                shutil.copyfile(PROJECT / name, src / name)
    group_setup = stage_dir / "src-group" / "setup.py"
    group_setup.write_text(one_group_setup(group_setup.read_text()))
    tools = stage_dir / "tools"
    tools.mkdir()
    shutil.copyfile(Path(__file__).resolve(), tools / "arm_check.py")
    shutil.copyfile(PROJECT / "tests" / "estimate_digest.py", tools / "estimate_digest.py")
    corpus = stage_dir / "corpus"
    for name in names:
        (corpus / "gcode" / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(CORPUS / "gcode" / name, corpus / "gcode" / name)
    shutil.copyfile(CORPUS / "printer.cfg", corpus / "printer.cfg")
    bundle = Path(os.environ.get("SSL_CERT_FILE") or "/etc/ssl/certs/ca-certificates.crt")
    shutil.copyfile(bundle, stage_dir / "ca.crt")


def one_group_setup(text: str) -> str:
    """setup.py's text made to compile GROUP_MODULES alone, in one group, with everything
    else of setup.py (its float flags, its probe, its fallbacks) unchanged."""
    if text.count(SETUP_RUNS) != 1:
        raise RuntimeError("setup.py no longer has %r: the group build cannot be staged"
                           % SETUP_RUNS)
    override = "COMPILED_MODULES = %r\nGROUPS = [(list(COMPILED_MODULES), %r)]\n" % (
        list(GROUP_MODULES), GROUP_NAME)
    return text.replace(SETUP_RUNS, override + SETUP_RUNS)


# Which of setup.py's compiled modules a build's python holds as extensions.
COMPILED_NOW = """\
import importlib, sys
for path in sys.argv[1:]:
    module = importlib.import_module(path[:-len(".py")].replace("/", "."))
    if not module.__file__.endswith(".py"):
        print(path)
"""


@dataclasses.dataclass
class Built:
    """One build installed in the chroot: its python, what it says it is, how long it took
    (wall clock and CPU), which of setup.py's compiled modules it holds compiled."""

    python: str
    version: str
    seconds: float
    cpu_seconds: float
    build_line: str
    meant: list[str]  # the modules its setup.py compiles
    compiled: list[str]  # those it holds compiled


def install(chroot: Chroot, kind: str) -> Built:
    """The checkout installed into a fresh venv in the chroot as install.sh's build does
    (plugins/moonraker/build-venv's pip command), KESTIMATOR_BUILD=`kind` ("group": the
    compiled build of GROUP_MODULES alone)."""
    venv = STAGE + "/venv-" + kind
    src = STAGE + "/src-" + kind
    started, cpu = time.monotonic(), children_cpu_s()
    made = chroot.run(["python3", "-m", "venv", venv])
    if made.returncode != 0:
        raise RuntimeError("venv: " + made.stderr[-2000:])
    python = venv + "/bin/python"
    args = ["install", "-v", "--no-cache-dir", "--force-reinstall"]
    if kind == "pure":  # as build-venv: no mypy to fetch, setuptools in the venv builds it
        got = chroot.run([python, "-m", "pip", "install", "-q", "setuptools>=70.1"],
                         timeout=BUILD_TIMEOUT_S)
        if got.returncode != 0:
            raise RuntimeError("setuptools: " + got.stderr[-2000:])
        args.append("--no-build-isolation")
    proc = chroot.run([python, "-m", "pip", *args, src],
                      env={"KESTIMATOR_BUILD": "pure" if kind == "pure" else "compiled"},
                      timeout=BUILD_TIMEOUT_S)
    seconds, cpu = time.monotonic() - started, children_cpu_s() - cpu
    if proc.returncode != 0:
        raise RuntimeError("pip install (%s): %s" % (kind, (proc.stdout + proc.stderr)[-3000:]))
    lines = [line.strip() for line in (proc.stdout + proc.stderr).splitlines()
             if "kestimator build: " in line]
    version = chroot.run([python, "-m", "kestimator", "--version"])
    if version.returncode != 0:
        raise RuntimeError("kestimator --version: " + version.stderr[-2000:])
    setup_py = (chroot.root / src.lstrip("/") / "setup.py").read_text()
    meant = _compiled_modules_of(setup_py)
    compiled = chroot.run([python, "-c", COMPILED_NOW, *meant])
    if compiled.returncode != 0:
        raise RuntimeError("the compiled modules: " + compiled.stderr[-2000:])
    return Built(python, version.stdout.strip(), seconds, cpu, (lines or ["?"])[0][:120],
                 meant, compiled.stdout.split())


def _compiled_modules_of(setup_py: str) -> list[str]:
    """The modules a staged setup.py compiles (its COMPILED_MODULES, the group build's
    override included), read by running its definitions without building anything."""
    namespace: dict[str, object] = {"__name__": "kestimator_setup", "__file__": str(
        PROJECT / "setup.py")}
    exec(compile(setup_py, "setup.py", "exec"), namespace)  # noqa: S102 (our own setup.py)
    return [str(name) for name in namespace["COMPILED_MODULES"]]  # type: ignore[attr-defined]


def wrong_build(kind: str, built: Built) -> str | None:
    """Why `built` is not the build `kind` asked for (None when it is): the compiled build
    says "compiled" and holds every module setup.py compiles, the group build holds
    GROUP_MODULES compiled and no other, the pure build none."""
    says = "(compiled)" if kind == "compiled" else "(pure Python)"
    if not built.version.endswith(says):
        return "says %r (%s)" % (built.version, built.build_line)
    meant = [] if kind == "pure" else built.meant
    if kind == "group" and sorted(meant) != sorted(GROUP_MODULES):
        return "its setup.py compiles %s, not %s" % (", ".join(meant), ", ".join(GROUP_MODULES))
    if sorted(built.compiled) != sorted(meant):
        return "holds %s compiled, not %s (%s)" % (
            ", ".join(built.compiled) or "nothing", ", ".join(meant) or "nothing",
            built.build_line)
    return None


def chroot_outputs(chroot: Chroot, built: Built,
                   names: Sequence[str]) -> dict[str, dict[str, object]]:
    """The records of one build installed in the chroot."""
    proc = chroot.run([built.python, STAGE + "/tools/arm_check.py", "outputs",
                       STAGE + "/corpus", *names])
    if proc.returncode != 0:
        raise RuntimeError("outputs: " + proc.stderr[-3000:])
    return {str(r["file"]): r for r in map(json.loads, proc.stdout.splitlines())}


@dataclasses.dataclass
class Outcome:
    """One build on one architecture: what differed from x86 and from Klipper, per file."""

    arch: str
    kind: str
    built: Built
    run_seconds: float
    run_cpu_seconds: float
    records: dict[str, dict[str, object]]
    against_x86: dict[str, list[str]]
    against_klipper: dict[str, list[str]]

    @property
    def equal(self) -> bool:
        return not any(self.against_x86.values()) and not any(self.against_klipper.values())


def check(arch: str, kinds: Sequence[str], names: Sequence[str], root: Path,
          x86: dict[str, dict[str, object]]) -> list[Outcome]:
    """Build the chroot of `arch`, install each build of `kinds` and compare it on `names`."""
    found = []
    with Chroot(make_chroot(arch, root)) as chroot:
        stage(chroot, names)
        for kind in kinds:
            built = install(chroot, kind)
            wrong = wrong_build(kind, built)
            if wrong is not None:
                raise RuntimeError("%s %s build: %s" % (arch, kind, wrong))
            started, cpu = time.monotonic(), children_cpu_s()
            records = chroot_outputs(chroot, built, names)
            found.append(Outcome(
                arch, kind, built, time.monotonic() - started, children_cpu_s() - cpu, records,
                {n: build_differences(records[n], x86[n]) for n in names},
                {n: klipper_differences(records[n]) for n in names}))
    return found


# The printer host install_check makes in the chroot (as tests/test_install_sh.py's _host).
HOST = "/root/kestimator-host"
HOME = HOST + "/home"
CHECKOUT = HOME + "/kestimator"
DATA = HOME + "/printer_data"
WORKER_FILE = TWO_FILES[1]
MOONRAKER_CONF = """[server]
host: 127.0.0.1
port: 7125
klippy_uds_address: %s/comms/klippy.sock

[machine]
provider: none
validate_service: False

[authorization]
trusted_clients:
  127.0.0.0/8

[file_manager]
enable_object_processing: False

[update_manager]
enable_system_updates: False
""" % DATA
HOST_SCRIPT = r"""set -eu
cd "$0/source"
git init -q -b main && git add -A
git -c user.name=test -c user.email=test@example.invalid commit -q -m kestimator
git clone -q --bare "$0/source" "$0/origin.git"
mkdir -p "$1" && git clone -q "$0/origin.git" "$1/kestimator"
for folder in config gcodes logs comms database tools/klipper_estimator; do
    mkdir -p "$1/printer_data/$folder"
done
printf '#!/bin/sh
echo "klipper_estimator v3.7.3"
'     > "$1/printer_data/tools/klipper_estimator/klipper_estimator_linux"
chmod 755 "$1/printer_data/tools/klipper_estimator/klipper_estimator_linux"
mkdir -p "$1/klipper/klippy/extras" && : > "$1/klipper/klippy/extras/__init__.py"
git -C "$1/klipper" init -q
"""
# The project's next commit, pushed to the origin, then pulled as Moonraker's update
# manager pulls (git runs the post-merge hook install.sh wrote).
UPDATE_SCRIPT = r"""set -eu
cd "$0/source"
sed -i 's/^__version__ = "\(.*\)"$/__version__ = "\1.1"/' kestimator/__init__.py
git -c user.name=test -c user.email=test@example.invalid commit -q -am "next version"
git push -q "$0/origin.git" main
cd "$1" && git pull -q --ff-only
"""


def _worker_answer(chroot: Chroot, python: str) -> dict[str, object]:
    asked = chroot.run([python, STAGE + "/tools/arm_check.py", "ask-worker", CHECKOUT,
                        DATA + "/gcodes/" + os.path.basename(WORKER_FILE),
                        DATA + "/config/printer.cfg"], cwd="/")
    if asked.returncode != 0:
        raise RuntimeError("ask-worker: " + asked.stderr[-2000:])
    answer: dict[str, object] = json.loads(asked.stdout)
    return answer


def _same_answer(mine: dict[str, object], x86: dict[str, object],
                 paths: tuple[tuple[str, str], tuple[str, str]]) -> bool:
    """The worker's answers agree in everything but how long they took and the paths their
    warnings name (`paths`: this answer's G-code file and printer.cfg, then x86's)."""
    def plain(answer: dict[str, object], names: tuple[str, str]) -> dict[str, object]:
        found = {k: v for k, v in answer.items() if k != "elapsed_s"}
        warnings = [str(w) for w in answer.get("warnings", [])]  # type: ignore[attr-defined]
        for name, stand_in in zip(names, ("FILE", "PRINTER_CFG")):
            warnings = [w.replace(name, stand_in) for w in warnings]
        found["warnings"] = warnings
        return found

    return plain(mine, paths[0]) == plain(x86, paths[1])


def install_check(root: Path, say: Callable[[str], None] = print) -> list[str]:
    """install.sh, the worker's first answer, an update pulled (the hook's rebuild) and the
    worker's answer again, in the arm64 chroot: one line per step ("DIFFERENT ..." when a
    step's result is not what it must be), each given to `say` as soon as it is known (the
    steps take an hour or more under emulation)."""
    x86_paths = (str(CORPUS / "gcode" / WORKER_FILE), str(CORPUS / "printer.cfg"))
    x86 = ask_worker(str(PROJECT), *x86_paths)
    paths = ((DATA + "/gcodes/" + os.path.basename(WORKER_FILE), DATA + "/config/printer.cfg"),
             x86_paths)
    if x86.get("ok") is not True:
        raise RuntimeError("x86's worker: %r" % x86)
    steps: list[str] = []

    def step(line: str) -> None:
        steps.append(line)
        say(line)

    with Chroot(make_chroot("arm64", root)) as chroot:
        stage(chroot, [WORKER_FILE])
        host_dir = chroot.root / HOST.lstrip("/")
        if host_dir.exists():
            shutil.rmtree(host_dir)
        listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                                 "--exclude-standard"], cwd=PROJECT, check=True,
                                capture_output=True).stdout.decode().split("\0")
        for name in filter(None, listed):
            if (PROJECT / name).is_file():
                target = host_dir / "source" / name
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(PROJECT / name, target)
        made = chroot.run(["sh", "-c", HOST_SCRIPT, HOST, HOME])
        if made.returncode != 0:
            raise RuntimeError("the host: " + made.stderr[-2000:])
        data = chroot.root / DATA.lstrip("/")
        shutil.copyfile(CORPUS / "printer.cfg", data / "config" / "printer.cfg")
        (data / "config" / "moonraker.conf").write_text(MOONRAKER_CONF)
        shutil.copyfile(CORPUS / "gcode" / WORKER_FILE,
                        data / "gcodes" / os.path.basename(WORKER_FILE))
        user = {"HOME": HOME, "XDG_CONFIG_HOME": DATA + "/xdg-config"}
        started, cpu = time.monotonic(), children_cpu_s()
        installed = chroot.run([CHECKOUT + "/install.sh", "--allow-root", "--no-restart",
                                "-d", DATA], env=user, timeout=BUILD_TIMEOUT_S, cwd=CHECKOUT)
        seconds, cpu = time.monotonic() - started, children_cpu_s() - cpu
        said = [line for line in installed.stdout.splitlines() if line.startswith(
            ("kestimator build:", "Installed:"))]
        ok = installed.returncode == 0 and any(
            line.endswith("(compiled)") for line in said if line.startswith("Installed:"))
        step("%sinstall.sh: exit %d in %.0f s (CPU %.0f s): %s" % (
            "" if ok else "DIFFERENT ", installed.returncode, seconds, cpu,
            " / ".join(said) or (installed.stdout + installed.stderr)[-1500:]))
        if installed.returncode != 0:
            return steps
        python = CHECKOUT + "/.venv-host/bin/python"
        first = _worker_answer(chroot, python)
        step("%sthe worker's first answer: %s, total %r s (x86: %r s)" % (
            "" if _same_answer(first, x86, paths) else "DIFFERENT ", first.get("source"),
            first.get("total_s"), x86.get("total_s")))
        started, cpu = time.monotonic(), children_cpu_s()
        pulled = chroot.run(["sh", "-c", UPDATE_SCRIPT, HOST, CHECKOUT], env=user,
                            timeout=BUILD_TIMEOUT_S)
        seconds, cpu = time.monotonic() - started, children_cpu_s() - cpu
        head = chroot.run(["git", "-C", CHECKOUT, "rev-parse", "HEAD"]).stdout.strip()
        built = (chroot.root / CHECKOUT.lstrip("/") / ".venv-host" / "kestimator-commit")
        version = chroot.run([CHECKOUT + "/.venv-host/bin/kestimator", "--version"])
        ok = (pulled.returncode == 0 and built.is_file()
              and built.read_text().strip() == head
              and version.stdout.strip().endswith(".1 (compiled)"))
        step("%sthe update's rebuild (git pull, post-merge hook): exit %d in %.0f s "
                     "(CPU %.0f s), %s%s" % ("" if ok else "DIFFERENT ", pulled.returncode,
                                            seconds, cpu,
                               version.stdout.strip(),
                               "" if ok else ": " + (pulled.stdout + pulled.stderr)[-1500:]))
        again = _worker_answer(chroot, python)
        step("%sthe worker's answer after the update: %s, total %r s" % (
            "" if _same_answer(again, x86, paths) else "DIFFERENT ", again.get("source"),
            again.get("total_s")))
    return steps


def report(outcome: Outcome) -> str:
    """A few lines a person reads: the build, its times, what differed."""
    lines = ["%s %s: %s; built in %.0f s (CPU %.0f s), %d files run in %.0f s (CPU %.0f s): %s"
             % (outcome.arch, outcome.kind, outcome.built.version, outcome.built.seconds,
                outcome.built.cpu_seconds, len(outcome.records), outcome.run_seconds,
                outcome.run_cpu_seconds,
                "equal to x86 and to Klipper" if outcome.equal else "DIFFERENT")]
    for name in outcome.records:
        problems = outcome.against_x86[name] + outcome.against_klipper[name]
        if len(problems) > REPORTED_PROBLEMS:
            problems = problems[:REPORTED_PROBLEMS] + ["%d more" % (
                len(problems) - REPORTED_PROBLEMS)]
        if problems:
            lines.append("  %s: %s" % (name, "; ".join(problems)))
    return "\n".join(lines)


def main(argv: Sequence[str]) -> int:
    if argv[:1] == ["outputs"]:
        for record in outputs(argv[1], argv[2:]):
            print(json.dumps(record, sort_keys=True), flush=True)
        return 0
    if argv[:1] == ["ask-worker"]:
        print(json.dumps(ask_worker(argv[1], argv[2], argv[3]), sort_keys=True))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arch", action="append", choices=ARCHES)
    parser.add_argument("--build", action="append", choices=BUILDS)
    parser.add_argument("--files", choices=("two", "all"), default="all")
    parser.add_argument("--root", type=Path, default=DEFAULT_ROOT,
                        help="where the chroots are kept (default: %(default)s)")
    parser.add_argument("--install", action="store_true",
                        help="install.sh, the update hook's rebuild and the worker's "
                             "answers in the arm64 chroot, instead of the builds")
    args = parser.parse_args(argv)
    if args.install:
        try:
            steps = install_check(args.root, lambda line: print(line, flush=True))
        except (RuntimeError, subprocess.SubprocessError, OSError) as exc:
            print("arm64 install: could not run: %s" % exc, flush=True)
            return 1
        return 0 if all(not step.startswith("DIFFERENT") for step in steps) else 1
    names = corpus_names(args.files)
    started = time.monotonic()
    x86 = x86_outputs(names)
    print("x86 pure CPython: %d files in %.0f s; against Klipper: %s" % (
        len(names), time.monotonic() - started,
        "; ".join("%s %s" % (n, d) for n in names for d in klipper_differences(x86[n]))
        or "equal"), flush=True)
    failed = False
    for arch in args.arch or ["arm64"]:
        try:
            for outcome in check(arch, args.build or list(BUILDS), names, args.root, x86):
                print(report(outcome), flush=True)
                failed = failed or not outcome.equal
        except (RuntimeError, subprocess.SubprocessError, OSError) as exc:
            print("%s: could not run: %s" % (arch, exc), flush=True)
            failed = True
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
