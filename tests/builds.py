"""What the builds are compared on: every corpus file and generated programs, through the CLI
(`estimate --json` bytes, `inject` bytes) and field by field (tests/estimate_digest.py).

Shared by tests/test_compiled_build.py (mypyc-compiled vs pure CPython) and
tests/test_pypy.py (PyPy vs pure CPython). The pure CPython side of the corpus files is
computed once in a whole run (conftest.once_per_run: whichever process asks first), so every
comparison, in whichever process, reuses it.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
import random
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

from .conftest import CORPUS, CORPUS_CFG, PROJECT, corpus_files, once_per_run

DIGEST_SCRIPT = PROJECT / "tests" / "estimate_digest.py"
RUN_TIMEOUT_S = 900

# Every command that changes the G-code or planner state between moves, in one file.
STATE_CHANGING_PROGRAM = """\
;LAYER_CHANGE
G28
M83
G1 X10 Y10 Z0.2 F6000
G1 X20 Y10 E1.5 F1200
G91
G1 X5 Y5 E0.5
G1 X-5 Z0.1
G90
M82
G92 E0
G1 X30 Y30 E2 F3000
M221 S90
G1 X35 Y30 E3
M220 S150
G1 X40 Y30 E4
;TYPE:Perimeter
SET_GCODE_OFFSET Z=0.05 MOVE=1
G1 X45 Y35 E5
SAVE_GCODE_STATE NAME=a
G91
G1 X1 Y1
RESTORE_GCODE_STATE NAME=a MOVE=1
G1 X50 Y35 E6
M204 S500
G1 X60 Y35 E7
SET_VELOCITY_LIMIT VELOCITY=50 ACCEL=800 SQUARE_CORNER_VELOCITY=2 MINIMUM_CRUISE_RATIO=0.2
G1 X70 Y45 E8
G10
G1 X80 Y45
G11
G2 X90 Y45 I5 J0 E9
;TIME_ELAPSED:12.5
G1 X90 Y60 E9000
G1 E-30 F100
G4 P250
M400
G1 X1 Y1 E9001 F999999
;LAYER_CHANGE
G1 Z5 F600
G1 X100 Y100 Z10 E9002
SET_KINEMATIC_POSITION X=0 Y=0 Z=0
G1 X10 Y10
M109 S200
G92 X0 Y0
G1 X5 Y5 E9003
M84
G1 X1 Y1
"""
_OTHER_LINES = (
    "G90", "G91", "M82", "M83", "G92 E0", "G92 X1", "M221 S80", "M220 S120", "G10", "G11",
    "M204 S700", "SET_VELOCITY_LIMIT VELOCITY=40", "G4 P10", "M400", "G28 X", ";TYPE:Skirt",
    ";LAYER_CHANGE", "SAVE_GCODE_STATE", "RESTORE_GCODE_STATE MOVE=1", "g1 x3 y4",
    "G1 X1 Y2 ; comment", "G1 F1500 X3 Y3 E0.1", "G2 X5 Y5 I1 J1", "M84", ";TIME_ELAPSED:1",
    "G1 X1.0000000000000000001 Y-0.00000000000000001", "G1 X1e3", "G1 F0.0001 X2")
N_RANDOM_PROGRAMS = 40
# Values at the ends of what a float holds: where PyPy and CPython once parted (a `**` that
# overflows is an error on CPython and inf on PyPy; PyPy's "%.3f" of 1e50 and above is
# "1e+50"). The builds must agree on these too: same fields, or the same error.
_EXTREME_LINES = (
    "SET_VELOCITY_LIMIT SQUARE_CORNER_VELOCITY=1e300", "SET_VELOCITY_LIMIT ACCEL=1e-300",
    "SET_VELOCITY_LIMIT VELOCITY=1e300", "SET_VELOCITY_LIMIT VELOCITY=1e-300",
    "M204 S1e300", "M204 S1e-300", "G1 X1e60", "G1 Y-1e60 Z1e55", "G1 E1e55", "G1 E-1e60",
    "G1 X1e200 F1e300", "G1 F1e-300 X2", "G92 X1e300", "G92 E-1e300", "M220 S1e300",
    "M220 S1e-300", "M221 S1e300", "M221 S1e-300", "G4 P1e300", "G4 P1e20",
    "SET_RETRACTION RETRACT_LENGTH=1e60 RETRACT_SPEED=1e300", "G10", "G11",
    "SET_GCODE_OFFSET Z=1e300 MOVE=1", "G2 X1e60 Y5 I1e60 J0", "G2 X5 Y5 I1e-300 J1e-300",
    "; ESTIMATOR_ADD_TIME 1e300", "G1 X1e300 Y1e300", "G1 X1.7976931348623157e308",
    "SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO=0.999999999999")
N_EXTREME_PROGRAMS = 40


def _random_program(rng: random.Random) -> str:
    lines = []
    for _ in range(rng.randint(1, 120)):
        if rng.random() < 0.25:
            lines.append(rng.choice(_OTHER_LINES))
            continue
        words = ["G%d" % rng.randint(0, 1)]
        for axis in "XYZE":
            if rng.random() < 0.6:
                words.append("%s%s" % (axis, round(rng.uniform(-200.0, 200.0),
                                                   rng.randint(0, 6))))
        if rng.random() < 0.3:
            words.append("F%s" % rng.choice(("60", "1200", "9000", "0", "-5", "30000.5")))
        lines.append(" ".join(words))
    return "\n".join(lines) + "\n"


def _extreme_program(rng: random.Random) -> str:
    lines = ["G28", "M83"]
    for _ in range(rng.randint(3, 40)):
        if rng.random() < 0.2:
            lines.append(rng.choice(_EXTREME_LINES))
            continue
        words = ["G1"] + ["%s%s" % (axis, round(rng.uniform(-50.0, 250.0), 3))
                          for axis in "XYZE" if rng.random() < 0.6]
        if rng.random() < 0.3:
            words.append("F%d" % rng.choice((60, 1200, 9000)))
        lines.append(" ".join(words))
    return "\n".join(lines) + "\n"


def extreme_programs(folder: Path) -> list[Path]:
    """Only the seeded programs with extreme values, written into `folder`."""
    extreme = random.Random(7)
    paths = []
    for i in range(N_EXTREME_PROGRAMS):
        path = folder / ("extreme%02d.gcode" % i)
        path.write_text(_extreme_program(extreme), encoding="ascii")
        paths.append(path)
    return paths


def generated_programs(folder: Path) -> list[Path]:
    """The state-changing program, seeded random ones and seeded ones with extreme values,
    written into `folder`."""
    rng = random.Random(15)
    texts = [STATE_CHANGING_PROGRAM] + [_random_program(rng) for _ in range(N_RANDOM_PROGRAMS)]
    extreme = random.Random(7)
    texts += [_extreme_program(extreme) for _ in range(N_EXTREME_PROGRAMS)]
    paths = []
    for i, text in enumerate(texts):
        path = folder / ("program%02d.gcode" % i)
        path.write_text(text, encoding="ascii")
        paths.append(path)
    return paths


def transform_runs(folder: Path) -> list[tuple[Path, list[Path]]]:
    """(printer.cfg, G-code files) of every bed_mesh / skew_correction reference
    (tests/oracle_refs/transforms), with the extreme programs run through a mesh and a skew
    too: the move transforms' arithmetic must be the same bits in every build."""
    from .oracle_refs.transforms.runs import HERE, RUNS, derive

    runs: dict[str, list[Path]] = {}
    for cfg, gcode, commands in RUNS:
        out = folder / cfg
        out.mkdir(exist_ok=True)
        runs.setdefault(cfg, []).append(derive(gcode, commands, out))
    extreme = folder / "extreme"
    extreme.mkdir(exist_ok=True)
    loads = "G28\nSKEW_PROFILE LOAD=my_skew\nBED_MESH_PROFILE LOAD=default\n"
    for path in extreme_programs(extreme):
        path.write_text(loads + path.read_text(), encoding="ascii")
        runs["mesh_skew"].append(path)
    return [(HERE / cfg / "printer.cfg", paths) for cfg, paths in runs.items()]


def compared_files() -> list[Path]:
    """Every corpus file (the builds must agree on all of them)."""
    return corpus_files()


def _env(extra: dict[str, str] | None, on_path: bool) -> dict[str, str]:
    env = dict(os.environ, PYPY_GC_NURSERY="16M")
    env.pop("PYTHONPATH", None)
    if on_path:
        env["PYTHONPATH"] = str(PROJECT)
    env.update(extra or {})
    return env


def cli_outputs(python: str, path: Path, on_path: bool = True) -> tuple[bytes, str]:
    """`estimate --json` stdout and the sha256 of what `inject` writes, run by `python`.

    With `on_path`, the checkout's package is imported (pure CPython, PyPy); without it the
    one installed in `python`'s environment (the compiled build's venv).
    """
    env = _env(None, on_path)
    with tempfile.TemporaryDirectory(prefix="kestimator-builds-") as tmp:
        estimate = subprocess.run(
            [python, "-m", "kestimator", "estimate", str(path), "--json", "--printer-cfg",
             str(CORPUS_CFG)], env=env, cwd=tmp, capture_output=True, timeout=RUN_TIMEOUT_S)
        assert estimate.returncode == 0, estimate.stderr.decode()
        out = Path(tmp) / "out.gcode"
        inject = subprocess.run(
            [python, "-m", "kestimator", "inject", str(path), "-o", str(out), "-q",
             "--printer-cfg", str(CORPUS_CFG)], env=env, cwd=tmp, capture_output=True,
            timeout=RUN_TIMEOUT_S)
        # 4: Klipper will stop this print (pre-flight); the times are written all the same.
        assert inject.returncode in (0, 4), inject.stderr.decode()
        return estimate.stdout, hashlib.sha256(out.read_bytes()).hexdigest()


@functools.cache
def pure_cli_outputs(path: Path) -> tuple[bytes, str]:
    """`cli_outputs` of the pure package under this CPython (computed once per run: the
    corpus's files are read-only)."""
    def make(_: Path) -> list[str]:
        stdout, digest = cli_outputs(sys.executable, path)
        return [stdout.decode("latin-1"), digest]

    stdout, digest = once_per_run("pure cli_outputs %s %s" % (path, CORPUS_CFG), make)
    return stdout.encode("latin-1"), digest


def digests(python: str, paths: Sequence[Path], on_path: bool = True,
            printer_cfg: Path = CORPUS_CFG) -> list[str]:
    """tests/estimate_digest.py's lines for `paths` timed with `printer_cfg`, run by `python`
    (first line: the build). The pure package under this CPython gives the corpus's files'
    lines once per run (they are read-only); the other files' lines are computed each time."""
    if python != sys.executable or not on_path:
        return _run_digests(python, paths, on_path, printer_cfg)
    shared = [path for path in paths if CORPUS in path.parents]
    own = [path for path in paths if CORPUS not in path.parents]
    lines: dict[Path, str] = {}
    build_line = None
    if shared:
        names = "\n".join(map(str, shared))
        shared_lines = once_per_run(
            "pure digests %s\n%s" % (printer_cfg, names),
            lambda _: _run_digests(sys.executable, shared, True, printer_cfg))
        build_line = shared_lines[0]
        lines.update(zip(shared, shared_lines[1:]))
    if own or not shared:
        own_lines = _run_digests(sys.executable, own, True, printer_cfg)
        build_line = own_lines[0]
        lines.update(zip(own, own_lines[1:]))
    assert build_line is not None and len(lines) == len(set(paths))
    return [build_line] + [lines[path] for path in paths]


def _run_digests(python: str, paths: Sequence[Path], on_path: bool,
                 printer_cfg: Path) -> list[str]:
    proc = subprocess.run(
        [python, str(DIGEST_SCRIPT), str(printer_cfg), *map(str, paths)],
        env=_env(None, on_path), cwd=tempfile.gettempdir(), capture_output=True, text=True,
        timeout=RUN_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def setup_py_module() -> ModuleType:
    """The project's setup.py loaded as a module (its flags, groups and probes), unrun."""
    spec = importlib.util.spec_from_file_location("kestimator_setup", PROJECT / "setup.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
