"""Build script: the core compiled with mypyc when it can be, the pure package otherwise.

`pip install .` (and a wheel built with `pip wheel .` or `python -m build`) compiles the
hot-path modules below from the very same .py sources with mypyc (mypy's compiler) when
this is CPython, mypy can be imported and a C compiler with Python's headers works. In
every other case (PyPy, no compiler, no headers, a mypyc failure) it installs the pure-Python
package unchanged, and so it does with less than BUILD_MEMORY_MIB of memory free. Either way
it prints one line saying which and why (pip shows build output only with `-v`;
`kestimator --version` says "compiled" or "pure Python" afterwards).

Memory (a small board runs Klipper beside the install): mypy runs in a child process that
has exited before gcc starts, the modules are compiled in three groups (three C files) and
gcc's garbage collector is told to keep its heap small. The C files are compiled one at a
time, or one per CPU where RAM beyond BUILD_MEMORY_MIB holds a compiler more
(compile_jobs; KESTIMATOR_BUILD_JOBS=N sets it). The install's peak, summed over every
process, and the README's first command's time are measured by benchmarks/install_memory.py.

Float arithmetic: Klipper's planner is Python, whose every float operation is one
IEEE double operation rounded once. A C compiler may do otherwise: fuse `a*b + c` into one
multiply-add (GCC's default on aarch64, clang's within an expression, any compiler given
-march=haswell or -mfma), keep x87 intermediates in 80 bits, or take -ffast-math (whose link
step also switches the CPU's denormals to zero) from the user's CFLAGS. Every compiled module
is built with FLOAT_FLAGS after the user's flags (the last flag wins), linked with
FLOAT_LINK_FLAGS, and a probe library built the same way must compute what Python computes
before anything is compiled; a compiler that will not is refused (the pure package, and why).

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
# The install's measured peak, summed over pip, the build, mypy and gcc, is 295 MiB with
# Debian's Python 3.11, at mypy's phase (benchmarks/install_memory.py --jobs 1); below
# this much free memory the install is the pure package. KESTIMATOR_BUILD_MEMORY_MIB sets
# another bar (a board with zram, say); KESTIMATOR_BUILD=compiled compiles whatever is free.
BUILD_MEMORY_MIB = 300
# gcc's garbage collector tuned for a small board: collect when the heap grows by 10 %
# past 16 MiB. On this 24 GiB host gcc's defaults (grow 100 % past 128 MiB) let cc1 reach
# twice the memory for the largest module; the code made is the same (gcc's own docs:
# the parameters change only when memory is collected), the compile takes ~15 % more CPU.
_GCC_MEMORY_FLAGS = ["--param=ggc-min-expand=10", "--param=ggc-min-heapsize=16384"]
_COMPILER_FLAGS: list[str] = []  # _GCC_MEMORY_FLAGS when the probe's compiler takes them
# What one more compiler running at once needs: cc1's largest peak, on the core group's
# C file, is 184 MiB (/usr/bin/time, gcc 12, the flags above; the commands group's, 201 MiB
# at -O3, is 168 MiB at -O1). The C files are compiled one at a time unless RAM beyond
# BUILD_MEMORY_MIB holds another (compile_jobs).
COMPILE_JOB_MIB = 250
# mypyc's optimisation level (-O3): the probe below is compiled at it too, as contraction
# into a multiply-add is an optimisation.
OPT_LEVEL = "3"
# Each group's level, given after mypyc's -O3 (gcc takes the last). The per-line path (core)
# keeps -O3. The other two are compiled at -O1: gcc at -O1 takes 35 % less CPU on them
# (commands 32 -> 21 s, kinematics 17 -> 11 s) and less memory (the commands group's cc1
# 201 -> 168 MiB), and the estimate's instruction count moves by under 0.6 %, as their code
# is mostly calls into Python's C API (benchmarks/RESULTS.md, "The first command in under
# a minute"). Core first in GROUPS: with two CPUs the compiles end together.
# -ffp-contract=off and the rest of FLOAT_FLAGS hold at every level; -O1 does a subset of
# -O3's transformations.
GROUP_OPT_LEVELS = {"kestimator_core": "3", "kestimator_commands": "1",
                    "kestimator_kinematics": "1"}
# Float arithmetic as CPython's, whatever CFLAGS say (they come first on gcc's command line,
# these last): no contraction into fused multiply-adds, none of -ffast-math's parts (each
# named, as -fno-fast-math leaves one the user set alone), and on x87 every assignment
# rounded to a double, as CPython's every operation is (mypyc gives each operation its own
# assignment). The first set the compiler takes without a warning is used: GCC's, clang's.
FLOAT_FLAG_SETS = (
    ["-ffp-contract=off", "-fno-fast-math", "-fno-unsafe-math-optimizations",
     "-fno-associative-math", "-fno-reciprocal-math", "-fno-finite-math-only",
     "-fsigned-zeros", "-fno-single-precision-constant", "-fexcess-precision=standard"],
    ["-ffp-contract=off", "-fno-fast-math", "-fno-unsafe-math-optimizations",
     "-fno-associative-math", "-fno-reciprocal-math", "-fno-finite-math-only",
     "-fsigned-zeros", "-fno-approx-func", "-fhonor-nans", "-fhonor-infinities"],
)
# At the link: -ffast-math, -funsafe-math-optimizations or -Ofast in CFLAGS (which distutils
# passes to the link too) make gcc link crtfastmath.o, whose constructor sets flush-to-zero
# for the whole Python process when the library loads; a later -fno-... or -O<level> undoes
# each (gcc's driver takes the last of a switch and its negation).
FLOAT_LINK_FLAGS = ["-fno-fast-math", "-fno-unsafe-math-optimizations", "-O" + OPT_LEVEL]
FLOAT_FLAGS: list[str] = []  # the set the probe's compiler takes
# The probe: a = b = 1 + 2**-30, c = -(1 + 2**-29). Python rounds a*b to 1 + 2**-29 and
# a*b + c is 0.0; fused (one rounding) or kept in a wider register it is 2**-60. The first
# function is mypyc's form (an assignment per operation), the second one expression (which
# clang contracts by default; C lets an x87 compiler keep it wide, so it is only checked
# where FLT_EVAL_METHOD is 0).
FLOAT_PROBE_C = """\
#include <float.h>
double kestimator_statements(double a, double b, double c) {
    double t = a * b;
    double u = t + c;
    return u;
}
double kestimator_expression(double a, double b, double c) {
#if defined(FLT_EVAL_METHOD) && FLT_EVAL_METHOD == 0
    return a * b + c;
#else
    return kestimator_statements(a, b, c);
#endif
}
"""
# Run by this Python with the probe library: exit 3 if its arithmetic is not Python's, 4 if
# loading it switched denormals to zero (flush-to-zero, denormals-are-zero), 0 if all is well.
FLOAT_PROBE_PY = """\
import ctypes, sys
lib = ctypes.CDLL(sys.argv[1])
a, c = 1.0 + 2.0 ** -30, -(1.0 + 2.0 ** -29)
for name in ("kestimator_statements", "kestimator_expression"):
    f = getattr(lib, name)
    f.restype, f.argtypes = ctypes.c_double, [ctypes.c_double] * 3
    if f(a, a, c) != a * a + c:
        sys.exit(3)
m = sys.float_info.min
if m / 2.0 == 0.0 or (m / 2.0) * 2.0 != m:
    sys.exit(4)
"""


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
        return _float_problem(compiler, tmp)


def _float_problem(compiler: object, tmp: str) -> str | None:
    """Why this compiler's float arithmetic would not be Python's (None: it is, with
    FLOAT_FLAGS set to the flags that make it so)."""
    source = os.path.join(tmp, "float_probe.c")
    with open(source, "w", encoding="ascii") as f:
        f.write(FLOAT_PROBE_C)
    FLOAT_FLAGS.clear()
    objects: list[str] = []
    for flags in FLOAT_FLAG_SETS:
        try:  # -Werror: a compiler that ignores a flag it does not know says so in a warning
            objects = compiler.compile(  # type: ignore[attr-defined]
                [source], output_dir=tmp,
                extra_postargs=["-O" + OPT_LEVEL, "-Werror", *_COMPILER_FLAGS, *flags])
        except Exception:
            continue
        FLOAT_FLAGS[:] = flags
        break
    else:
        return ("the C compiler does not take %s (its float arithmetic could differ from "
                "Python's)" % " ".join(FLOAT_FLAG_SETS[0][:2]))
    library = os.path.join(tmp, "float_probe.so")
    try:
        compiler.link_shared_object(  # type: ignore[attr-defined]
            objects, library, extra_postargs=FLOAT_LINK_FLAGS)
    except Exception as exc:
        return "the C compiler cannot link a shared library (%s)" % (
            str(exc).splitlines() or ["?"])[0]
    check = subprocess.run([sys.executable, "-c", FLOAT_PROBE_PY, library],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if check.returncode == 3:
        return ("the C compiler fuses or widens float arithmetic even with %s (its results "
                "would differ from Python's)" % " ".join(FLOAT_FLAGS))
    if check.returncode == 4:
        return ("a library linked with these flags switches denormal floats to zero "
                "(-ffast-math in LDFLAGS?); its results would differ from Python's")
    # Any other outcome (no ctypes, a library this Python cannot load: cross-compiling) leaves
    # the flags alone to keep the arithmetic Python's.
    return None


def _meminfo_mib() -> dict[str, int] | None:
    """/proc/meminfo in MiB (None where there is none)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            return {line.split(":")[0]: int(line.split()[1]) // 1024
                    for line in f if ":" in line}
    except (OSError, ValueError, IndexError):
        return None


def _memory_need_mib() -> int:
    wanted = os.environ.get("KESTIMATOR_BUILD_MEMORY_MIB", "").strip()
    return int(wanted) if wanted.isdigit() else BUILD_MEMORY_MIB


def _memory_problem() -> str | None:
    """Why memory is too short to compile (None when there is enough, or it is not known).

    Compiling needs BUILD_MEMORY_MIB free (available RAM plus free swap): on a board that is
    also running Klipper, the kernel's out-of-memory killer could pick Klipper instead."""
    info = _meminfo_mib()
    if info is None or "MemAvailable" not in info:
        return None
    free_mib = info["MemAvailable"] + info.get("SwapFree", 0)
    need = _memory_need_mib()
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


def compile_jobs() -> int:
    """How many C files to compile at once: one per CPU while RAM (not swap) holds another
    compiler beside the install's BUILD_MEMORY_MIB; one where that is not known.

    KESTIMATOR_BUILD_JOBS=N sets it."""
    wanted = os.environ.get("KESTIMATOR_BUILD_JOBS", "").strip()
    if wanted.isdigit() and int(wanted) >= 1:
        return int(wanted)
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    info = _meminfo_mib()
    if info is None or "MemAvailable" not in info:
        return 1
    spare = info["MemAvailable"] - _memory_need_mib()
    return max(1, min(cpus, 1 + spare // COMPILE_JOB_MIB))


class BuildExtOrPure(build_ext):
    """build_ext that falls back to the pure package if the C build fails, and compiles
    compile_jobs() extensions at once (setuptools' own --parallel)."""

    def finalize_options(self) -> None:
        super().finalize_options()
        if not self.parallel and self.extensions:
            jobs = compile_jobs()
            self.parallel = jobs if jobs > 1 else None

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
    # The three groups' libraries first, in GROUPS' order (the longest compile first): run
    # side by side on two CPUs, core runs on one while commands then kinematics run on the
    # other, and the modules' small shims fill in around them (the two end together).
    libraries = {"%s__mypyc" % name: (index, ["-O" + GROUP_OPT_LEVELS.get(str(name), OPT_LEVEL)])
                 for index, (_, name) in enumerate(GROUPS)}
    modules.sort(key=lambda extension: libraries.get(  # type: ignore[attr-defined]
        extension.name, (len(GROUPS), []))[0])  # type: ignore[attr-defined]
    for extension in modules:
        level = libraries.get(extension.name, (0, []))[1]  # type: ignore[attr-defined]
        extension.extra_compile_args = [  # type: ignore[attr-defined]
            *extension.extra_compile_args,  # type: ignore[attr-defined]
            *level, *_COMPILER_FLAGS, *FLOAT_FLAGS]
        extension.extra_link_args = [  # type: ignore[attr-defined]
            *extension.extra_link_args, *FLOAT_LINK_FLAGS]  # type: ignore[attr-defined]
    return modules


def _mypyc_child(result: str) -> None:
    """The child's work: mypycify (writes build/*.c), its extensions pickled to `result`."""
    from mypyc.build import mypycify
    modules = mypycify(["--ignore-missing-imports", *COMPILED_MODULES],
                       opt_level=OPT_LEVEL, debug_level="0", separate=GROUPS)
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
