"""Build script: the core compiled with mypyc when it can be, the pure package otherwise.

`pip install .` (and a wheel built with `pip wheel .` or `python -m build`) compiles the
hot-path modules below from the very same .py sources with mypyc (mypy's compiler) when
this is CPython, mypy can be imported and a C compiler with Python's headers works. In
every other case (PyPy, no compiler, no headers, a mypyc failure) it installs the pure-Python
package unchanged, and so it does with less than BUILD_MEMORY_MIB of memory free. Either way
it prints one line saying which and why (pip shows build output only with `-v`;
`kestimator --version` says "compiled" or "pure Python" afterwards).

Memory (a small board runs Klipper beside the install): mypy runs in a child process that
has exited before gcc starts, the modules are compiled in three groups (three C files, one
gcc at a time) and gcc's garbage collector is told to keep its heap small. The install's peak,
summed over every process, is measured by benchmarks/install_memory.py.

KESTIMATOR_BUILD=pure forces the pure package; KESTIMATOR_BUILD=compiled makes any reason
not to compile an error instead of a fallback. An editable install (`pip install -e .`,
the development set-up) stays pure unless KESTIMATOR_BUILD=compiled.
"""

from __future__ import annotations

import os
import pickle
import platform
import subprocess
import sys
import sysconfig
import tempfile

from setuptools import setup
from setuptools.command.build_ext import build_ext

# The modules mypyc compiles: every module on the per-line path (the kinematics' check_move
# runs for every move). The rest of the package (CLI, slicer detection, config, rewrite)
# is I/O-bound and stays Python.
HERE = os.path.dirname(os.path.abspath(__file__))
COMPILED_MODULES = [
    "kestimator/gcode.py",
    "kestimator/motion_queuing.py",
    "kestimator/extruder.py",
    "kestimator/toolhead.py",
    "kestimator/gcode_move.py",
    "kestimator/gcode_arcs.py",
    "kestimator/firmware_retraction.py",
    "kestimator/input_shaper.py",
    "kestimator/bed_mesh.py",
    "kestimator/skew_correction.py",
    "kestimator/interpreter.py",
    "kestimator/segments.py",
    "kestimator/estimate.py",
    "kestimator/config/machine.py",
    "kestimator/progress_table.py",
] + sorted("kestimator/kinematics/" + name
           for name in os.listdir(os.path.join(HERE, "kestimator", "kinematics"))
           if name.endswith(".py"))
# mypyc's compilation groups: each is one C file, one gcc run and one shared library. One
# group for everything made a 10 MiB C file that took cc1 448 MiB (670 MiB for the whole
# install with Debian's Python); a group per module repeats mypyc's runtime in each (twice
# the CPU) and cannot hold a package's __init__. Three groups: the per-line loop and
# everything it calls for a plain move (estimate -> gcode -> gcode_move -> toolhead) in one,
# as a call across groups goes through a table of pointers; the other commands and
# transforms in the second; the kinematics (called through the kinematics' class) in the third.
KINEMATICS = [m for m in COMPILED_MODULES if m.startswith("kestimator/kinematics/")]
GROUPS: list[tuple[list[str], str | None]] = [
    (["kestimator/gcode.py", "kestimator/motion_queuing.py", "kestimator/extruder.py",
      "kestimator/toolhead.py", "kestimator/gcode_move.py", "kestimator/segments.py",
      "kestimator/estimate.py"], "kestimator_core"),
    (["kestimator/interpreter.py", "kestimator/gcode_arcs.py",
      "kestimator/firmware_retraction.py", "kestimator/input_shaper.py",
      "kestimator/bed_mesh.py", "kestimator/skew_correction.py",
      "kestimator/config/machine.py", "kestimator/progress_table.py"], "kestimator_commands"),
    (KINEMATICS, "kestimator_kinematics"),
]
PREFIX = "kestimator build: "
MYPYC_CHILD = "--kestimator-mypyc-child"
# The install's measured peak, summed over pip, the build, mypy and gcc, is 279 MiB with
# Debian's Python 3.11 (benchmarks/install_memory.py); below this much free memory the
# install is the pure package. KESTIMATOR_BUILD_MEMORY_MIB sets another bar (a board with
# zram, say); KESTIMATOR_BUILD=compiled compiles whatever is free.
BUILD_MEMORY_MIB = 300
# gcc's garbage collector tuned for a small board: collect when the heap grows by 10 %
# past 16 MiB. On this 24 GiB host gcc's defaults (grow 100 % past 128 MiB) let cc1 reach
# twice the memory for the largest module; the code made is the same (gcc's own docs:
# the parameters change only when memory is collected), the compile takes ~15 % more CPU.
_GCC_MEMORY_FLAGS = ["--param=ggc-min-expand=10", "--param=ggc-min-heapsize=16384"]
_COMPILER_FLAGS: list[str] = []  # _GCC_MEMORY_FLAGS when the probe's compiler takes them


def _say(message: str) -> None:
    # stderr: a PEP 517 frontend keeps stdout for itself in some versions.
    sys.stderr.write(PREFIX + message + "\n")
    sys.stderr.flush()


def _c_compiler_problem() -> str | None:
    """Why a C extension cannot be built here (None when a test one compiles)."""
    try:
        from setuptools._distutils.ccompiler import new_compiler
        from setuptools._distutils.sysconfig import customize_compiler
    except ImportError:  # pragma: no cover - very old setuptools
        from distutils.ccompiler import new_compiler  # type: ignore[no-redef]
        from distutils.sysconfig import customize_compiler  # type: ignore[no-redef]
    include = sysconfig.get_paths()["include"]
    if not os.path.exists(os.path.join(include, "Python.h")):
        return "Python's C headers are missing (%s/Python.h; Debian: python3-dev)" % include
    compiler = new_compiler()
    customize_compiler(compiler)
    with tempfile.TemporaryDirectory(prefix="kestimator-cc-") as tmp:
        source = os.path.join(tmp, "probe.c")
        with open(source, "w", encoding="ascii") as f:
            f.write("#include <Python.h>\nint kestimator_probe(void) { return 0; }\n")
        try:
            compiler.compile([source], output_dir=tmp, include_dirs=[include])
        except Exception as exc:  # CompileError, or the compiler program is missing
            return "no working C compiler (%s)" % (str(exc).splitlines() or ["?"])[0]
        try:  # gcc takes the memory flags; another compiler (clang) may not
            compiler.compile([source], output_dir=tmp, include_dirs=[include],
                             extra_postargs=["-Werror", *_GCC_MEMORY_FLAGS])
        except Exception:
            _COMPILER_FLAGS.clear()
        else:
            _COMPILER_FLAGS[:] = _GCC_MEMORY_FLAGS
    return None


def _memory_problem() -> str | None:
    """Why memory is too short to compile (None when there is enough, or it is not known).

    Compiling needs BUILD_MEMORY_MIB free (available RAM plus free swap): on a board that is
    also running Klipper, the kernel's out-of-memory killer could pick Klipper instead."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            info = {line.split(":")[0]: int(line.split()[1]) for line in f if ":" in line}
        free_mib = (info["MemAvailable"] + info.get("SwapFree", 0)) // 1024
    except (OSError, KeyError, ValueError, IndexError):
        return None
    wanted = os.environ.get("KESTIMATOR_BUILD_MEMORY_MIB", "").strip()
    need = int(wanted) if wanted.isdigit() else BUILD_MEMORY_MIB
    if free_mib < need:
        return "only %d MiB of memory free (RAM and swap); compiling needs %d MiB" % (
            free_mib, need)
    return None


def _pure_reason() -> str | None:
    """Why this build installs the pure package (None: compile)."""
    wanted = os.environ.get("KESTIMATOR_BUILD", "").strip().lower()
    if wanted not in ("", "pure", "compiled"):
        raise SystemExit(PREFIX + "KESTIMATOR_BUILD must be 'pure' or 'compiled', not %r"
                         % wanted)
    if wanted == "pure":
        return "KESTIMATOR_BUILD=pure"
    reason = None
    if platform.python_implementation() != "CPython":
        reason = "%s runs the pure package (its JIT is fast on it)" % (
            platform.python_implementation())
    elif "editable_wheel" in sys.argv and wanted != "compiled":
        reason = "editable install (development); `pip install .` compiles"
    else:
        try:
            import mypyc.build  # noqa: F401
        except ImportError:
            reason = "mypy (which ships mypyc) is not installed"
        else:
            reason = (None if wanted == "compiled" else _memory_problem()) \
                or _c_compiler_problem()
    if reason is not None and wanted == "compiled":
        raise SystemExit(PREFIX + "KESTIMATOR_BUILD=compiled, but " + reason)
    return reason


class BuildExtOrPure(build_ext):
    """build_ext that falls back to the pure package if the C build fails."""

    def run(self) -> None:
        try:
            super().run()
        except Exception as exc:
            if os.environ.get("KESTIMATOR_BUILD", "").strip().lower() == "compiled":
                raise
            _say("pure Python (compiling failed: %s)" % str(exc).splitlines()[0])
            self.extensions = []


# setuptools commands that only write metadata: a PEP 517 frontend runs them first, in
# their own process; compiling there would only repeat the work (and the line).
METADATA_ONLY = {"egg_info", "dist_info"}


def _mypyc_in_child() -> list[object]:
    """mypyc's C sources and extensions, made in a child process.

    Type-checking and generating C takes mypy about 165 MiB; in a child that memory is the
    system's again before gcc starts (a process seldom returns freed memory), so the build's
    peak is mypy's or one gcc's, never both (benchmarks/install_memory.py)."""
    with tempfile.TemporaryDirectory(prefix="kestimator-mypyc-") as tmp:
        result = os.path.join(tmp, "extensions.pickle")
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), MYPYC_CHILD, result],
                              cwd=HERE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        if proc.returncode != 0:
            lines = proc.stdout.decode(errors="replace").strip().splitlines()
            if proc.returncode < 0:
                why = "killed by signal %d (out of memory?)" % -proc.returncode
            else:
                why = (lines or ["exit status %d" % proc.returncode])[-1]
            raise RuntimeError(why)
        with open(result, "rb") as f:
            modules: list[object] = pickle.load(f)  # noqa: S301 (our own child's)
    for extension in modules:
        extension.extra_compile_args = [  # type: ignore[attr-defined]
            *extension.extra_compile_args, *_COMPILER_FLAGS]  # type: ignore[attr-defined]
    return modules


def _mypyc_child(result: str) -> None:
    """The child's work: mypycify (writes build/*.c), its extensions pickled to `result`."""
    from mypyc.build import mypycify
    modules = mypycify(["--ignore-missing-imports", *COMPILED_MODULES],
                       opt_level="3", debug_level="0", separate=GROUPS)
    with open(result, "wb") as f:
        pickle.dump(list(modules), f)


def _ext_modules() -> list[object]:
    commands = [arg for arg in sys.argv[1:] if not arg.startswith("-")]
    if commands and set(commands[:1]) <= METADATA_ONLY:
        return []
    reason = _pure_reason()
    if reason is not None:
        _say("pure Python (%s)" % reason)
        return []
    try:
        modules = _mypyc_in_child()
    except Exception as exc:
        if os.environ.get("KESTIMATOR_BUILD", "").strip().lower() == "compiled":
            raise
        _say("pure Python (mypyc failed: %s)" % exc)
        return []
    _say("compiled with mypyc: %s" % ", ".join(
        m[len("kestimator/"):-len(".py")] for m in COMPILED_MODULES))
    return list(modules)


# setuptools' PEP 517 backend runs this file as __main__ too; imported (the tests), it only
# defines the lists above.
if __name__ == "__main__" and sys.argv[1:2] == [MYPYC_CHILD]:
    _mypyc_child(sys.argv[2])
elif __name__ == "__main__":
    setup(ext_modules=_ext_modules(), cmdclass={"build_ext": BuildExtOrPure})
