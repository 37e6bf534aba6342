"""`inject` in place under faults: the path holds the untouched original or the complete
new file, never anything else, and a normal error leaves no temporary file behind.

Faults: a full disk (an injected ENOSPC at write and at fsync, and a real 1.5 MB tmpfs
when this machine lets us mount one), a read-only directory (EROFS/EACCES injected at the
temp file and at the replace, which also holds for root; a real read-only tmpfs when
mountable), a file that vanishes or changes between the two passes, two runs at once,
and `python -m kestimator inject` killed with SIGKILL at 20 seeded random moments.

A SIGKILL leaves its temporary file (`.<name>.<random>.kestimator-tmp` beside the file):
nothing can remove it from a killed process. It never replaces the file, and a later
normal run works and leaves it alone for the user to delete.
"""

from __future__ import annotations

import contextlib
import errno
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from kestimator import rewrite
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.errors import KestimatorError
from kestimator.rewrite import inject_file

from .conftest import CORPUS, CORPUS_CFG, PROJECT

BIG = CORPUS / "gcode" / "prusaslicer" / "cancelobj_ps2.3.3_issue1.gcode"
SMALL_BODY = b"M83\n;LAYER_CHANGE\nG1 X10 E1 F3000\n;LAYER_CHANGE\nG1 X20 E1\nG1 Y20 E1\n"
TEMP_RE = re.compile(r"^\..+\.[^.]+\.kestimator-tmp$")
KILL_RUNS = 20
KILL_SEED = 9
CONCURRENT_ROUNDS = 3
CONCURRENT_RUNS = 3
TMPFS_BYTES = 1_500_000


@pytest.fixture(scope="module")
def limits():  # type: ignore[no-untyped-def]
    return limits_from_printer_cfg(CORPUS_CFG)[0]


@pytest.fixture(scope="module")
def big_expected(tmp_path_factory: pytest.TempPathFactory, limits, corpus_root) -> bytes:
    """The complete output of one normal run on the big corpus file."""
    work = tmp_path_factory.mktemp("expected") / BIG.name
    shutil.copyfile(BIG, work)
    # What the command line records for --printer-cfg: the kind of source and the file name.
    inject_file(work, limits, limits_source="printer_cfg:" + CORPUS_CFG.name)
    return work.read_bytes()


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(PROJECT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "kestimator", "inject", "--quiet", *args]


def _small(tmp_path: Path) -> Path:
    work = tmp_path / "print.gcode"
    work.write_bytes(SMALL_BODY)
    return work


def _expected_small(tmp_path: Path, limits) -> bytes:  # type: ignore[no-untyped-def]
    ref = tmp_path / "ref" / "print.gcode"
    ref.parent.mkdir()
    ref.write_bytes(SMALL_BODY)
    inject_file(ref, limits)
    data = ref.read_bytes()
    shutil.rmtree(ref.parent)
    return data


# Disk full
class _FullDisk:
    """A file object that takes `room` bytes, then fails like a full disk."""

    def __init__(self, real, room: int) -> None:  # type: ignore[no-untyped-def]
        self._real = real
        self._room = room

    def write(self, chunk: bytes) -> int:
        if len(chunk) > self._room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self._room -= len(chunk)
        return self._real.write(chunk)

    def writelines(self, chunks) -> None:  # type: ignore[no-untyped-def]
        for chunk in chunks:
            self.write(chunk)

    def __getattr__(self, name: str):  # type: ignore[no-untyped-def]
        return getattr(self._real, name)

    def __enter__(self):  # type: ignore[no-untyped-def]
        return self

    def __exit__(self, *exc: object) -> None:
        self._real.close()


@pytest.mark.parametrize("room", [0, 10, 100])
def test_disk_full_while_writing_the_temp_file_keeps_the_original_and_no_temp(
        room: int, tmp_path: Path, limits, monkeypatch: pytest.MonkeyPatch) -> None:
    work = _small(tmp_path)
    real_fdopen = os.fdopen
    monkeypatch.setattr(rewrite.os, "fdopen",
                        lambda fd, *a, **k: _FullDisk(real_fdopen(fd, *a, **k), room))
    with pytest.raises(KestimatorError, match="No space left on device") as info:
        inject_file(work, limits)
    assert info.value.path == str(work)
    assert work.read_bytes() == SMALL_BODY
    assert os.listdir(tmp_path) == ["print.gcode"]


def test_disk_full_at_fsync_keeps_the_original_and_no_temp(
        tmp_path: Path, limits, monkeypatch: pytest.MonkeyPatch) -> None:
    work = _small(tmp_path)

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(rewrite.os, "fsync", full)
    with pytest.raises(KestimatorError, match="No space left on device"):
        inject_file(work, limits)
    assert work.read_bytes() == SMALL_BODY
    assert os.listdir(tmp_path) == ["print.gcode"]


@contextlib.contextmanager
def _tmpfs(where: Path, size: int) -> Iterator[Path]:
    where.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=%d" % size, "tmpfs",
                           str(where)], capture_output=True, check=False)
    if proc.returncode != 0:
        pytest.skip("cannot mount a tmpfs here (the injected variants cover this)")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], capture_output=True, check=False)


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("mount") is None,
                    reason="mounting a tmpfs needs root")
def test_a_real_full_tmpfs_keeps_the_original_and_no_temp(tmp_path: Path,
                                                         corpus_root) -> None:
    with _tmpfs(tmp_path / "small_disk", TMPFS_BYTES) as disk:
        work = disk / BIG.name
        shutil.copyfile(BIG, work)
        original = work.read_bytes()
        proc = subprocess.run(_cli(str(work)), capture_output=True, text=True,
                              env=_env(), check=False)
        assert proc.returncode == 1
        assert "No space left on device" in proc.stderr
        assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
        assert work.read_bytes() == original
        assert os.listdir(disk) == [BIG.name]


# Read-only directory (root ignores permission bits, so the errors are injected)
@pytest.mark.parametrize("code", [errno.EROFS, errno.EACCES])
@pytest.mark.parametrize("where", ["mkstemp", "chmod", "replace"])
def test_read_only_directory_gives_one_line_and_keeps_the_file(
        where: str, code: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    from kestimator import cli

    work = _small(tmp_path)

    def refuse(*args: object, **kwargs: object) -> None:
        raise OSError(code, os.strerror(code))

    target = tempfile if where == "mkstemp" else rewrite.os
    monkeypatch.setattr(target, where, refuse)
    assert cli.main(["inject", str(work)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and os.strerror(code) in err and str(work) in err
    assert work.read_bytes() == SMALL_BODY
    assert os.listdir(tmp_path) == ["print.gcode"]


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("mount") is None,
                    reason="a read-only mount needs root")
def test_a_real_read_only_mount_keeps_the_file(tmp_path: Path) -> None:
    with _tmpfs(tmp_path / "ro", 1 << 20) as disk:
        work = disk / "print.gcode"
        work.write_bytes(SMALL_BODY)
        remount = subprocess.run(["mount", "-o", "remount,ro", str(disk)],
                                 capture_output=True, check=False)
        if remount.returncode != 0:
            pytest.skip("cannot remount read-only here")
        proc = subprocess.run(_cli(str(work)), capture_output=True, text=True,
                              env=_env(), check=False)
        assert proc.returncode == 1
        assert "Read-only file system" in proc.stderr and "Traceback" not in proc.stderr
        assert work.read_bytes() == SMALL_BODY


# The file vanishes or changes between the passes
def _between_passes(monkeypatch: pytest.MonkeyPatch, action) -> None:  # type: ignore[no-untyped-def]
    real_plan = rewrite.plan_file

    def plan_then_act(*args, **kwargs):  # type: ignore[no-untyped-def]
        result = real_plan(*args, **kwargs)
        action()
        return result

    monkeypatch.setattr(rewrite, "plan_file", plan_then_act)


def test_a_file_that_vanishes_between_the_passes_is_not_recreated(
        tmp_path: Path, limits, monkeypatch: pytest.MonkeyPatch) -> None:
    work = _small(tmp_path)
    _between_passes(monkeypatch, work.unlink)
    with pytest.raises(KestimatorError) as info:
        inject_file(work, limits)
    assert info.value.path == str(work)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("how", ["append", "replace_file", "truncate"])
def test_a_file_changed_between_the_passes_is_left_as_it_is_now(
        how: str, tmp_path: Path, limits, monkeypatch: pytest.MonkeyPatch) -> None:
    work = _small(tmp_path)
    changed = {"append": SMALL_BODY + b"G1 X30 E1\n", "replace_file": b"G1 X1 F60\n",
               "truncate": SMALL_BODY[:20]}[how]

    def change() -> None:
        if how == "replace_file":
            other = tmp_path / "other"
            other.write_bytes(changed)
            os.replace(other, work)
        else:
            with open(work, "r+b") as f:
                f.truncate(0)
                f.write(changed)

    _between_passes(monkeypatch, change)
    with pytest.raises(KestimatorError, match="changed while it was being processed"):
        inject_file(work, limits)
    assert work.read_bytes() == changed
    assert os.listdir(tmp_path) == ["print.gcode"]


def test_a_file_changed_during_the_second_pass_is_left_as_it_is_now(
        tmp_path: Path, limits, monkeypatch: pytest.MonkeyPatch) -> None:
    work = _small(tmp_path)
    changed = SMALL_BODY + b"; the slicer was still writing\n"
    real_fsync = os.fsync

    def fsync_while_the_slicer_appends(fd: int) -> None:
        real_fsync(fd)
        with open(work, "ab") as f:
            f.write(changed[len(SMALL_BODY):])

    monkeypatch.setattr(rewrite.os, "fsync", fsync_while_the_slicer_appends)
    with pytest.raises(KestimatorError, match="changed while it was being processed"):
        inject_file(work, limits)
    assert work.read_bytes() == changed
    assert os.listdir(tmp_path) == ["print.gcode"]


# Two runs at once
def test_concurrent_in_place_runs_take_turns_and_give_the_single_run_output(
        tmp_path: Path, big_expected: bytes, corpus_root) -> None:
    """flock on the file serialises runs; the second one re-reads the first's output."""
    work = tmp_path / BIG.name
    for _ in range(CONCURRENT_ROUNDS):
        shutil.copyfile(BIG, work)
        procs = [subprocess.Popen(_cli("--printer-cfg", str(CORPUS_CFG), str(work)),
                                  env=_env(), stderr=subprocess.PIPE, text=True)
                 for _ in range(CONCURRENT_RUNS)]
        errors = [proc.communicate(timeout=120)[1] for proc in procs]
        assert [proc.returncode for proc in procs] == [0] * CONCURRENT_RUNS, errors
        assert work.read_bytes() == big_expected
        assert os.listdir(tmp_path) == [BIG.name]


def test_a_run_waits_for_the_lock_and_then_processes_the_replaced_file(
        tmp_path: Path, limits) -> None:
    import fcntl
    import threading

    work = _small(tmp_path)
    expected = _expected_small(tmp_path, limits)
    holder = open(work, "rb")
    fcntl.flock(holder.fileno(), fcntl.LOCK_EX)
    outcome: list[object] = []
    runner = threading.Thread(target=lambda: outcome.append(inject_file(work, limits)))
    runner.start()
    time.sleep(0.3)
    assert runner.is_alive() and work.read_bytes() == SMALL_BODY
    # While it waits, another writer swaps the file: the waiter must lock the new one.
    swapped = tmp_path / "swap"
    swapped.write_bytes(SMALL_BODY)
    os.replace(swapped, work)
    holder.close()
    runner.join(30)
    assert not runner.is_alive() and outcome
    assert work.read_bytes() == expected


# SIGKILL at random moments
def test_sigkill_at_random_moments_leaves_the_original_or_the_complete_output(
        tmp_path: Path, big_expected: bytes, corpus_root) -> None:
    original = BIG.read_bytes()
    work = tmp_path / BIG.name
    shutil.copyfile(BIG, work)
    command = _cli("--printer-cfg", str(CORPUS_CFG), str(work))
    started = time.monotonic()
    subprocess.run(command, env=_env(), check=True)
    run_s = time.monotonic() - started
    rng = random.Random(KILL_SEED)
    outcomes = {"original": 0, "complete": 0}
    for _ in range(KILL_RUNS):
        shutil.copyfile(BIG, work)
        proc = subprocess.Popen(command, env=_env())
        time.sleep(rng.uniform(0.0, run_s * 1.2))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        data = work.read_bytes()
        assert data in (original, big_expected)
        outcomes["original" if data == original else "complete"] += 1
        for name in os.listdir(tmp_path):
            if name != BIG.name:
                assert TEMP_RE.match(name), name
                os.unlink(tmp_path / name)
    assert sum(outcomes.values()) == KILL_RUNS
    # A temp file left by a kill does not disturb a later normal run, which removes it (no
    # live run holds it locked).
    shutil.copyfile(BIG, work)
    leftover = tmp_path / ("." + BIG.name + ".killed.kestimator-tmp")
    leftover.write_bytes(original[:1000])
    subprocess.run(command, env=_env(), check=True)
    assert work.read_bytes() == big_expected
    assert sorted(os.listdir(tmp_path)) == [BIG.name]
