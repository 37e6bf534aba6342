"""setup.py's float guard: the compiled build's C arithmetic is Python's, whatever CFLAGS say.

setup.py appends FLOAT_FLAGS (no fused multiply-add, none of -ffast-math, x87 rounding at
every assignment) after the user's flags and FLOAT_LINK_FLAGS to the link, and before it
compiles anything it builds a probe library the same way and checks, in this Python, that
`a*b + c` gives Python's result and that loading it left denormals alone. These tests pin
the probe on real compilers (GCC, and clang where installed): it fails on a library built
with fused arithmetic or linked with -ffast-math, and passes with the user's
`-march=haswell -ffp-contract=fast`, `-ffast-math` and `-Ofast` once the flags are added;
a compiler that takes none of the flags is refused; and on 32-bit x87 GCC's code rounds
each operation to a double, as CPython does, once they are added.
The whole-corpus proof on a real build is tests/test_compiled_build.py's FMA-allowed build.
"""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from .builds import setup_py_module
from .conftest import require_program

# CFLAGS a user (or a distribution) may build with: each makes gcc or clang fuse, or take
# -ffast-math's liberties, unless setup.py's flags undo it.
HOSTILE_CFLAGS = (
    "-march=haswell -ffp-contract=fast",
    "-O3 -mfma -ffast-math",
    "-Ofast -march=haswell",
    "-mfma -funsafe-math-optimizations -ffinite-math-only -fno-signed-zeros",
)


def _fma_cpu() -> None:
    """Skip where this CPU cannot run fused multiply-adds (the probe would pass vacuously)."""
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("the hostile flags here are x86's (-march=haswell, -mfma)")
    with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
        if " fma" not in f.read():
            pytest.skip("this CPU has no FMA instructions")


def _probe_exit(setup_py: ModuleType, library: Path) -> int:
    return subprocess.run([sys.executable, "-c", setup_py.FLOAT_PROBE_PY, str(library)],
                          capture_output=True).returncode


def _library(compiler: str, tmp_path: Path, flags: list[str]) -> Path:
    setup_py = setup_py_module()
    source = tmp_path / "probe.c"
    source.write_text(setup_py.FLOAT_PROBE_C, encoding="ascii")
    library = tmp_path / "probe.so"
    subprocess.run([compiler, "-shared", "-fPIC", *flags, str(source), "-o", str(library)],
                   check=True, capture_output=True)
    return library


@pytest.mark.parametrize("compiler", ["gcc", "clang"])
def test_the_probe_fails_a_library_built_with_fused_multiply_add(
        compiler: str, tmp_path: Path) -> None:
    _fma_cpu()
    library = _library(require_program(compiler), tmp_path, ["-O3", "-march=haswell",
                                                       "-ffp-contract=fast"])
    assert _probe_exit(setup_py_module(), library) == 3


def test_the_probe_fails_a_library_whose_link_zeroes_denormals(tmp_path: Path) -> None:
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("crtfastmath.o's flush-to-zero is x86's")
    library = _library(require_program("gcc"), tmp_path, ["-O2", "-ffast-math"])
    assert _probe_exit(setup_py_module(), library) == 4


@pytest.mark.parametrize("cflags", HOSTILE_CFLAGS)
@pytest.mark.parametrize("compiler", ["gcc", "clang"])
def test_the_float_flags_undo_fused_and_fast_math_cflags(
        compiler: str, cflags: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    _fma_cpu()
    path = require_program(compiler)
    # Without setup.py's flags these CFLAGS break Python's arithmetic on this CPU...
    setup_py = setup_py_module()
    unguarded = _library(path, tmp_path, ["-O3", *cflags.split()])
    assert _probe_exit(setup_py, unguarded) in (3, 4)
    # ...and setup.py's own probe, with the user's CFLAGS in the environment, passes.
    monkeypatch.setenv("CC", path)
    monkeypatch.delenv("LDSHARED", raising=False)
    monkeypatch.setenv("CFLAGS", cflags)
    monkeypatch.setenv("LDFLAGS", cflags)
    assert setup_py._c_compiler_problem() is None
    assert setup_py.FLOAT_FLAGS in [list(flags) for flags in setup_py.FLOAT_FLAG_SETS]
    assert "-ffp-contract=off" in setup_py.FLOAT_FLAGS


def test_a_compiler_that_takes_no_float_flags_is_refused(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # A cc that compiles plain C but refuses every -f flag: the build must not go on
    # unguarded (setup.py then installs the pure package and says this line's reason).
    gcc = require_program("gcc")
    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\nfor a in \"$@\"; do case \"$a\" in -ffp-contract=*) "
                    "echo \"cc: unknown option $a\" >&2; exit 1;; esac; done\n"
                    "exec %s \"$@\"\n" % gcc, encoding="ascii")
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    monkeypatch.delenv("CFLAGS", raising=False)
    problem = setup_py_module()._c_compiler_problem()
    assert problem is not None and "-ffp-contract=off" in problem


def test_on_x87_each_operation_is_rounded_to_a_double_as_cpython_rounds_it(
        tmp_path: Path) -> None:
    # 32-bit x86 without SSE2 computes in 80-bit x87 registers; CPython rounds every
    # operation's result to a double (it is stored in a float object). GCC keeps mypyc's
    # `t = a * b; u = t + c` in a register unless told -fexcess-precision=standard, which
    # stores and reloads t (fstpl, fldl). Assembly only: no 32-bit libc or Python is needed.
    gcc = require_program("gcc")
    source = tmp_path / "probe.c"
    setup_py = setup_py_module()
    source.write_text(setup_py.FLOAT_PROBE_C, encoding="ascii")

    def statements_asm(flags: list[str]) -> list[str]:
        proc = subprocess.run([gcc, "-m32", "-mfpmath=387", "-O3", *flags, "-S", "-o", "-",
                               str(source)], capture_output=True, text=True)
        if proc.returncode != 0:
            pytest.skip("this gcc cannot target 32-bit x86: %s" % proc.stderr.strip()[:200])
        body = proc.stdout.split("kestimator_statements:", 1)[1].split("\tret", 1)[0]
        return [line.split()[0] for line in body.splitlines()
                if line.strip().startswith("f")]

    unguarded = statements_asm([])
    assert "fmull" in unguarded and "fstpl" not in unguarded[:unguarded.index("faddl")]
    guarded = statements_asm(setup_py.FLOAT_FLAG_SETS[0])
    product = guarded.index("fmull")
    assert guarded[product + 1:product + 3] == ["fstpl", "fldl"]
    assert guarded.index("faddl") > product + 2
