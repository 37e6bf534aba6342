"""benchmarks/arm_check.py's judgement: what it calls a difference from x86 and from Klipper.

The tool builds kestimator in a Debian ARM chroot run through qemu-user and compares every
file's estimate, `estimate --json` bytes and `inject` bytes with pure CPython on this x86
host, and its totals and layers with Klipper's references; here its comparisons are pinned
on the numbers fused multiply-add once gave on arm64 (calicat 1471.918 s against Klipper's
1473.045 s, xyzcube 354.288 s against 355.192 s).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from .conftest import PROJECT


def _arm_check() -> ModuleType:
    spec = importlib.util.spec_from_file_location("arm_check_benchmark",
                                                  PROJECT / "benchmarks" / "arm_check.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


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
