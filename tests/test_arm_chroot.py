"""kestimator built and run on arm64 (the printer host's CPU) gives x86's and Klipper's results.

The first test is .ci/run's ARM step: in the arm64 Debian bookworm chroot .ci/run builds
(.ci/arm-chroot, run through qemu-user; KESTIMATOR_ARM64_ROOT), benchmarks/arm_check.py
installs the checkout with build-venv's pip command as one compiled mypyc group (the
look-ahead and the arcs, whose fused multiply-adds once made calicat and xyzcube wrong on
arm64), and it must equal pure CPython on this x86 host in every field, every layer,
`estimate --json`'s bytes and `inject`'s bytes, and Klipper's references, on calicat and
xyzcube. Every other module runs there as pure Python under arm64's CPython, so the
group build also holds pure Python on arm64 to x86's bits; the pure build of the two
modules would only add their own Python to that, and CPython's float operations are one
IEEE rounding each on every CPU, while the math functions they call (sin, cos, pow: libm's;
atan2, hypot: CPython's math module) are those the compiled group calls. The whole check
(every build, the pure one too, 30 files, armhf, install.sh) is the tool's, its last
result in benchmarks/RESULTS.md.

The other tests pin the tool's judgement: what it calls a difference from x86 and from
Klipper, on the numbers fused multiply-add once gave on arm64 (calicat 1471.918 s against
Klipper's 1473.045 s, xyzcube 354.288 s against 355.192 s), and which build it calls which.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from .conftest import IN_CI, PROJECT, load_script

ROOT_ENVIRONMENT = "KESTIMATOR_ARM64_ROOT"


def _arm_check() -> ModuleType:
    return load_script("arm_check_benchmark", PROJECT / "benchmarks" / "arm_check.py")


def _arm64_root() -> Path:
    """The arm64 chroot .ci/run built (skips outside CI without one; fails under CI)."""
    given = os.environ.get(ROOT_ENVIRONMENT, "")
    problem = None
    if not given or not (Path(given) / "usr" / "bin" / "python3").exists():
        problem = "no arm64 chroot in %s (.ci/arm-chroot arm64 DIR builds one)" % (
            ROOT_ENVIRONMENT)
    elif os.geteuid() != 0:
        problem = "the arm64 chroot needs root (chroot, mounts)"
    elif shutil.which("chroot") is None or shutil.which("mount") is None:
        problem = "chroot or mount is missing"
    if problem is not None:
        if IN_CI:
            pytest.fail(problem + ": .ci/run builds it")
        pytest.skip(problem)
    return Path(given)


def test_arm64_one_compiled_group_equals_x86_and_klipper_on_two_files() -> None:
    root = _arm64_root()
    arm_check = _arm_check()
    names = list(arm_check.TWO_FILES)
    x86 = arm_check.x86_outputs(names)
    assert {n: arm_check.klipper_differences(x86[n]) for n in names} == {n: [] for n in names}
    with arm_check.Chroot(root) as chroot:
        arch = chroot.run(["dpkg", "--print-architecture"])
        assert arch.stdout.strip() == "arm64", arch
        arm_check.stage(chroot, names)
        built = arm_check.install(chroot, "group")
        assert arm_check.wrong_build("group", built) is None, built
        records = arm_check.chroot_outputs(chroot, built, names)
        found = {n: (arm_check.build_differences(records[n], x86[n]),
                     arm_check.klipper_differences(records[n])) for n in names}
    assert found == {n: ([], []) for n in names}
    # Nothing stays mounted in the chroot once the check is done (.ci/run removes it).
    assert not any(os.path.ismount(root / name) for name in ("proc", "sys", "dev"))


def test_the_group_build_compiles_the_look_ahead_and_the_arcs_with_setup_pys_flags() -> None:
    arm_check = _arm_check()
    own = (PROJECT / "setup.py").read_text()
    staged = arm_check.one_group_setup(own)
    assert arm_check._compiled_modules_of(staged) == list(arm_check.GROUP_MODULES)
    namespace: dict[str, object] = {"__name__": "staged", "__file__": str(PROJECT / "setup.py")}
    exec(compile(staged, "setup.py", "exec"), namespace)
    assert namespace["GROUPS"] == [(list(arm_check.GROUP_MODULES), arm_check.GROUP_NAME)]
    # Only the modules and groups differ: the float flags, the probe and the rest are setup.py's.
    assert staged.replace(staged[staged.rindex("COMPILED_MODULES = ["):staged.index(
        arm_check.SETUP_RUNS)], "") == own
    with pytest.raises(RuntimeError, match="cannot be staged"):
        arm_check.one_group_setup(own.replace(arm_check.SETUP_RUNS, "if True:"))


def test_a_build_is_called_what_it_holds_compiled() -> None:
    arm_check = _arm_check()
    group = list(arm_check.GROUP_MODULES)
    every = arm_check._compiled_modules_of((PROJECT / "setup.py").read_text())

    def built(version: str, meant: list[str], compiled: list[str]) -> object:
        return arm_check.Built("python", "kestimator 0.1.0 (%s)" % version, 1.0, 1.0,
                               "kestimator build: ...", meant, compiled)

    assert arm_check.wrong_build("group", built("pure Python", group, group)) is None
    assert arm_check.wrong_build("compiled", built("compiled", every, every)) is None
    assert arm_check.wrong_build("pure", built("pure Python", every, [])) is None
    # mypyc failed and the build fell back to the pure package, or compiled one module only.
    assert "holds nothing compiled" in arm_check.wrong_build(
        "group", built("pure Python", group, []))
    assert "holds kestimator/toolhead.py compiled" in arm_check.wrong_build(
        "group", built("pure Python", group, group[:1]))
    assert "compiles" in arm_check.wrong_build("group", built("pure Python", every, every))
    assert "says" in arm_check.wrong_build("compiled", built("pure Python", every, []))
    assert "holds" in arm_check.wrong_build("compiled", built("compiled", every, every[:-1]))
    assert "says" in arm_check.wrong_build("pure", built("compiled", every, every))


def test_a_total_a_second_off_klippers_is_reported() -> None:
    arm_check = _arm_check()
    name = arm_check.TWO_FILES[0]
    ref = arm_check.reference(name)
    layers = [[p["line"], p["t"]] for p in ref["checkpoints"] if p["kind"] == "layer"]
    right = {"file": name, "total_s": ref["total_s"], "layers": layers}
    assert arm_check.klipper_differences(right) == []
    fused = dict(right, total_s=1471.918)
    assert arm_check.klipper_differences(fused) == ["total 1471.918 s, Klipper 1473.045 s"]
    last = dict(right, layers=layers[:-1] + [[layers[-1][0], layers[-1][1] - 0.5]])
    assert len(arm_check.klipper_differences(last)) == 1
    assert "no layer at line" in arm_check.klipper_differences(
        dict(right, layers=layers[1:]))[0]


def test_a_build_differing_from_x86_in_any_output_is_reported() -> None:
    arm_check = _arm_check()
    x86 = {"digest": "a", "estimate": "b", "inject": "c", "total_s": 355.191976}
    assert arm_check.build_differences(dict(x86), x86) == []
    assert arm_check.build_differences(dict(x86, inject="d"), x86) == ["inject"]
    assert arm_check.build_differences(dict(x86, digest="e", total_s=354.288), x86) == [
        "digest", "total 354.288 s, x86 355.191976 s"]


def test_the_checked_files_are_the_two_and_every_referenced_one_up_to_5_mb() -> None:
    arm_check = _arm_check()
    every = arm_check.corpus_names("all")
    if not every:
        pytest.skip("the shared corpus is not beside this checkout")
    assert set(arm_check.TWO_FILES) <= set(every)
    assert len(every) >= 30


def test_the_records_are_the_same_wherever_the_corpus_lies(tmp_path: Path) -> None:
    # The chroot holds its own copy of the corpus: a path in the JSON or a warning would
    # make every file differ from x86 though every number agreed.
    arm_check = _arm_check()
    name = arm_check.TWO_FILES[1]
    if not (arm_check.CORPUS / "gcode" / name).is_file():
        pytest.skip("the shared corpus is not beside this checkout")
    copy = tmp_path / "elsewhere"
    (copy / "gcode" / name).parent.mkdir(parents=True)
    shutil.copyfile(arm_check.CORPUS / "gcode" / name, copy / "gcode" / name)
    shutil.copyfile(arm_check.CORPUS / "printer.cfg", copy / "printer.cfg")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(PROJECT), str(PROJECT / "tests")]))
    records = [subprocess.run(
        [sys.executable, str(PROJECT / "benchmarks" / "arm_check.py"), "outputs", str(corpus),
         name], env=env, capture_output=True, text=True, check=True, cwd=tmp_path).stdout
        for corpus in (arm_check.CORPUS, copy)]
    assert records[0] == records[1]
    assert arm_check.klipper_differences(json.loads(records[0])) == []


def test_worker_answers_agree_but_for_the_paths_they_name_and_differ_in_a_time(
        tmp_path: Path) -> None:
    # --install compares the worker's answer in the chroot (the file in the printer's
    # gcodes folder) with x86's (the file in the corpus): the warnings name each path.
    arm_check = _arm_check()
    name = arm_check.WORKER_FILE
    if not (arm_check.CORPUS / "gcode" / name).is_file():
        pytest.skip("the shared corpus is not beside this checkout")
    here = (str(arm_check.CORPUS / "gcode" / name), str(arm_check.CORPUS / "printer.cfg"))
    elsewhere = (str(tmp_path / "gcodes" / "x.gcode"), str(tmp_path / "printer.cfg"))
    (tmp_path / "gcodes").mkdir()
    shutil.copyfile(here[0], elsewhere[0])
    shutil.copyfile(here[1], elsewhere[1])
    x86 = arm_check.ask_worker(str(PROJECT), *here)
    moved = arm_check.ask_worker(str(PROJECT), *elsewhere)
    assert x86["ok"] is True and any(here[0] in str(w) for w in x86["warnings"])
    assert x86 != moved
    assert arm_check._same_answer(moved, x86, (elsewhere, here))
    times = list(moved["times"])
    times[-1] += 1e-9
    assert not arm_check._same_answer(dict(moved, times=times), x86, (elsewhere, here))
