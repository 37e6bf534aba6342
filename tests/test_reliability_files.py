"""What `inject` does to the file system object it writes (issue 20, items 1, 2, 9, 12, 13).

Symlinks are written through (the target changes, the link stays a link); a character
device or a FIFO given as the output is written straight through, never replaced; nothing
that is not a regular file is replaced. The owner, group, mode and extended attributes of
the file survive the atomic replace; a file the user may not write is refused with one
line. Temp names fit the file system's name limit, so a 255-byte name works. Tests that need
root (chown to another user) skip as non-root, those that need non-root skip as root.
"""

from __future__ import annotations

import errno
import os
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.errors import KestimatorError
from kestimator.rewrite import inject_file

from .conftest import CORPUS_CFG, PROJECT

BODY = b"M83\n;LAYER_CHANGE\nG1 X10 E1 F3000\n;LAYER_CHANGE\nG1 X20 E1\nG1 Y20 E1\n"
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
NOBODY_UID = 65534
NOGROUP_GID = 65534


@pytest.fixture(scope="module")
def limits():  # type: ignore[no-untyped-def]
    return limits_from_printer_cfg(CORPUS_CFG)[0]


@pytest.fixture()
def expected(tmp_path: Path, limits) -> bytes:  # type: ignore[no-untyped-def]
    ref = tmp_path / "ref" / "print.gcode"
    ref.parent.mkdir()
    ref.write_bytes(BODY)
    inject_file(ref, limits)
    return ref.read_bytes()


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(PROJECT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _run(*args: str, **kwargs) -> subprocess.CompletedProcess[bytes]:  # type: ignore[no-untyped-def]
    kwargs.setdefault("timeout", 60)
    return subprocess.run([sys.executable, "-m", "kestimator", *args], env=_env(),
                          capture_output=True, **kwargs)


def _leftovers(folder: Path) -> list[str]:
    return [name for name in os.listdir(folder) if "kestimator" in name]


# Item 1: links, devices, FIFOs
def test_in_place_through_a_symlink_updates_the_target_and_keeps_the_link(
        tmp_path: Path, limits, expected: bytes) -> None:  # type: ignore[no-untyped-def]
    target = tmp_path / "real.gcode"
    target.write_bytes(BODY)
    link = tmp_path / "link.gcode"
    link.symlink_to("real.gcode")
    inject_file(link, limits)
    assert link.is_symlink() and os.readlink(link) == "real.gcode"
    assert target.read_bytes() == expected
    assert not _leftovers(tmp_path)


def test_output_through_a_symlink_updates_the_target_and_keeps_the_link(
        tmp_path: Path, limits, expected: bytes) -> None:  # type: ignore[no-untyped-def]
    src = tmp_path / "in.gcode"
    src.write_bytes(BODY)
    sub = tmp_path / "elsewhere"
    sub.mkdir()
    target = sub / "out.gcode"
    target.write_bytes(b"old\n")
    link = tmp_path / "out.gcode"
    link.symlink_to(target)
    inject_file(src, limits, output=str(link))
    assert link.is_symlink()
    assert target.read_bytes() == expected
    assert not _leftovers(tmp_path) and not _leftovers(sub)


def test_output_to_a_character_device_is_written_straight_through(
        tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    src = tmp_path / "in.gcode"
    src.write_bytes(BODY)
    before = os.stat(os.devnull)
    inject_file(src, limits, output=os.devnull)
    after = os.stat(os.devnull)
    assert stat.S_ISCHR(after.st_mode) and after.st_ino == before.st_ino
    assert src.read_bytes() == BODY


def test_output_to_a_fifo_is_written_straight_through(
        tmp_path: Path, limits, expected: bytes) -> None:  # type: ignore[no-untyped-def]
    src = tmp_path / "in.gcode"
    src.write_bytes(BODY)
    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    got: list[bytes] = []
    # The reader is there before the writer comes (opened without blocking, then read).
    read_fd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    os.set_blocking(read_fd, True)
    # A writer held open until inject is done, so the reader sees no end of file before.
    hold_fd = os.open(fifo, os.O_WRONLY)

    def read_all() -> None:
        with os.fdopen(read_fd, "rb") as f:
            got.append(f.read())

    reader = threading.Thread(target=read_all)
    reader.start()
    try:
        inject_file(src, limits, output=str(fifo))
    finally:
        os.close(hold_fd)
        reader.join(10)
    assert got == [expected]
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert not _leftovers(tmp_path)


def test_output_to_a_fifo_without_a_reader_is_refused_without_blocking(
        tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    src = tmp_path / "in.gcode"
    src.write_bytes(BODY)
    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    with pytest.raises(KestimatorError, match="no reader"):
        inject_file(src, limits, output=str(fifo))
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


def test_a_fifo_as_input_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "in.gcode"
    os.mkfifo(fifo)
    for command in ("inject", "estimate"):
        run = _run(command, "--printer-cfg", str(CORPUS_CFG), str(fifo), timeout=20)
        assert run.returncode == 1
        assert b"not a regular file" in run.stderr and len(run.stderr.splitlines()) == 1
        assert stat.S_ISFIFO(os.stat(fifo).st_mode)


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom", "/dev/stdin"])
def test_a_device_as_input_is_refused_and_never_replaced(device: str) -> None:
    if not os.path.exists(device):
        pytest.skip("no %s here" % device)
    before = os.stat(device)
    run = _run("inject", "--printer-cfg", str(CORPUS_CFG), device, stdin=subprocess.DEVNULL,
               timeout=20)
    assert run.returncode == 1, run.stderr
    assert b"not a regular file" in run.stderr and len(run.stderr.splitlines()) == 1
    after = os.stat(device)
    assert stat.S_IFMT(after.st_mode) == stat.S_IFMT(before.st_mode)


def test_a_directory_as_output_is_refused(tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    src = tmp_path / "in.gcode"
    src.write_bytes(BODY)
    out = tmp_path / "out.gcode"
    out.mkdir()
    with pytest.raises(KestimatorError):
        inject_file(src, limits, output=str(out))
    assert out.is_dir() and not _leftovers(tmp_path)


# Item 2: owner, group, mode, xattrs; files the user may not write
@pytest.mark.skipif(not IS_ROOT, reason="only root can give a file to another user")
def test_owner_group_and_mode_survive_an_in_place_rewrite_as_root(
        tmp_path: Path, limits, expected: bytes) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    os.chown(work, NOBODY_UID, NOGROUP_GID)
    os.chmod(work, 0o640)
    inject_file(work, limits)
    st = os.stat(work)
    assert (st.st_uid, st.st_gid, stat.S_IMODE(st.st_mode)) == (NOBODY_UID, NOGROUP_GID,
                                                                 0o640)
    assert work.read_bytes() == expected


@pytest.mark.skipif(IS_ROOT, reason="root may keep any group")
def test_a_shared_group_survives_an_in_place_rewrite(
        tmp_path: Path, limits, expected: bytes) -> None:  # type: ignore[no-untyped-def]
    groups = [g for g in os.getgroups() if g != os.getegid()]
    if not groups:
        pytest.skip("this user is in no second group")
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    os.chown(work, -1, groups[0])
    os.chmod(work, 0o664)
    inject_file(work, limits)
    assert os.stat(work).st_gid == groups[0]
    assert work.read_bytes() == expected


def _xattrs_supported(path: Path) -> bool:
    try:
        os.setxattr(path, "user.kestimator_probe", b"1")
    except (OSError, AttributeError) as exc:
        if isinstance(exc, AttributeError) or exc.errno in (errno.ENOTSUP, errno.EPERM,
                                                            errno.EOPNOTSUPP):
            return False
        raise
    os.removexattr(path, "user.kestimator_probe")
    return True


def test_user_xattrs_survive_an_in_place_rewrite(
        tmp_path: Path, limits, expected: bytes) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    if not _xattrs_supported(work):
        pytest.skip("no user xattrs on this file system")
    os.setxattr(work, "user.origin", b"slicer")
    inject_file(work, limits)
    assert os.getxattr(work, "user.origin") == b"slicer"
    assert work.read_bytes() == expected


def test_a_read_only_file_is_refused_with_one_line_even_in_a_writable_directory(
        tmp_path: Path) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    os.chmod(work, 0o444)
    run = _run("inject", "--printer-cfg", str(CORPUS_CFG), str(work))
    assert run.returncode == 1
    assert b"may not write" in run.stderr and len(run.stderr.splitlines()) == 1
    assert work.read_bytes() == BODY and stat.S_IMODE(os.stat(work).st_mode) == 0o444
    assert not _leftovers(tmp_path)


@pytest.mark.skipif(not IS_ROOT, reason="only root can make a file it may not write")
def test_another_users_read_only_file_is_refused_as_that_user_would_be(
        tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    os.chown(work, NOBODY_UID, NOGROUP_GID)
    os.chmod(work, 0o444)
    with pytest.raises(KestimatorError, match="may not write"):
        inject_file(work, limits)
    assert work.read_bytes() == BODY


def test_output_to_a_read_only_file_is_refused(tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    src = tmp_path / "in.gcode"
    src.write_bytes(BODY)
    out = tmp_path / "out.gcode"
    out.write_bytes(b"keep\n")
    os.chmod(out, 0o444)
    with pytest.raises(KestimatorError, match="may not write"):
        inject_file(src, limits, output=str(out))
    assert out.read_bytes() == b"keep\n"


# Item 12: long names
@pytest.mark.parametrize("length", [200, 232, 250, 255])
def test_a_file_name_at_the_file_systems_limit_is_rewritten(
        tmp_path: Path, limits, expected: bytes, length: int) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / ("p" * (length - len(".gcode")) + ".gcode")
    work.write_bytes(BODY)
    inject_file(work, limits)
    assert work.read_bytes() == expected
    assert not [name for name in os.listdir(tmp_path) if name.startswith(".")]


# Item 13: the report, empty names, newlines in names
def test_report_onto_its_own_gcode_is_refused(tmp_path: Path) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    run = _run("report", "--printer-cfg", str(CORPUS_CFG), str(work), "-o", str(work))
    assert run.returncode == 1 and len(run.stderr.splitlines()) == 1
    assert work.read_bytes() == BODY


@pytest.mark.parametrize("command", ["inject", "report"])
def test_an_empty_output_name_is_refused(command: str, tmp_path: Path) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    run = _run(command, "--printer-cfg", str(CORPUS_CFG), str(work), "-o", "")
    assert run.returncode == 1 and b"empty" in run.stderr
    assert len(run.stderr.splitlines()) == 1 and work.read_bytes() == BODY


def test_the_report_is_written_atomically_keeping_the_link_and_mode(tmp_path: Path) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    target = tmp_path / "real.html"
    target.write_text("old")
    os.chmod(target, 0o640)
    link = tmp_path / "report.html"
    link.symlink_to("real.html")
    run = _run("report", "--printer-cfg", str(CORPUS_CFG), str(work), "-o", str(link))
    assert run.returncode == 0, run.stderr
    assert link.is_symlink() and target.read_text().startswith("<!")
    assert stat.S_IMODE(os.stat(target).st_mode) == 0o640
    assert not _leftovers(tmp_path)


def test_a_newline_in_the_file_name_keeps_the_success_message_on_one_line(
        tmp_path: Path) -> None:
    work = tmp_path / "two\nlines.gcode"
    work.write_bytes(BODY)
    run = _run("inject", "--printer-cfg", str(CORPUS_CFG), str(work))
    assert run.returncode == 0, run.stderr
    assert len(run.stdout.splitlines()) == 1 and b"two\\nlines" in run.stdout


def _bounded_memory() -> None:
    """Child: a 1 GiB address-space cap, so reading a device to its end fails fast."""
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))


def _refused_settings_file(*args: str, source: Path) -> None:
    run = _run("estimate", *args, str(source), stdin=subprocess.DEVNULL, timeout=30,
               preexec_fn=_bounded_memory)
    assert run.returncode == 1, run.stderr
    assert b"not a regular file" in run.stderr, run.stderr
    assert len(run.stderr.splitlines()) == 1, run.stderr


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom", "fifo"])
def test_a_device_or_fifo_as_printer_cfg_is_refused_without_reading_it(
        device: str, tmp_path: Path) -> None:
    source = tmp_path / "print.gcode"
    source.write_bytes(BODY)
    if device == "fifo":
        device = str(tmp_path / "printer.cfg")
        os.mkfifo(device)
    _refused_settings_file("--printer-cfg", device, source=source)


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom", "fifo"])
def test_a_device_or_fifo_in_an_include_is_refused_without_reading_it(
        device: str, tmp_path: Path) -> None:
    source = tmp_path / "print.gcode"
    source.write_bytes(BODY)
    if device == "fifo":
        device = str(tmp_path / "extra.cfg")
        os.mkfifo(device)
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(CORPUS_CFG.read_text() + "\n[include %s]\n" % device)
    _refused_settings_file("--printer-cfg", str(cfg), source=source)


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom", "fifo"])
def test_a_device_or_fifo_as_the_profile_is_refused_without_reading_it(
        device: str, tmp_path: Path) -> None:
    source = tmp_path / "print.gcode"
    source.write_bytes(BODY)
    if device == "fifo":
        device = str(tmp_path / "profile.toml")
        os.mkfifo(device)
    _refused_settings_file("--printer-cfg", str(CORPUS_CFG), "--profile", device,
                           source=source)


def test_a_huge_printer_cfg_is_refused_by_its_size(tmp_path: Path) -> None:
    source = tmp_path / "print.gcode"
    source.write_bytes(BODY)
    cfg = tmp_path / "printer.cfg"
    with open(cfg, "wb") as f:
        f.truncate(64 << 20)  # sparse: 64 MiB of NULs, over the config cap
    run = _run("estimate", "--printer-cfg", str(cfg), str(source), timeout=30)
    assert run.returncode == 1, run.stderr
    assert b"MiB" in run.stderr and len(run.stderr.splitlines()) == 1, run.stderr


@pytest.mark.parametrize("content, expected", [
    (b'[printers."a"]\nnote = "caf\xe9"\n', b"not UTF-8 text"),
    (b"x = " + b"[" * 10000 + b"]" * 10000 + b"\n", b"not valid TOML"),
])
def test_a_profile_with_a_bad_byte_or_deep_nesting_is_one_line_exit_1(
        content: bytes, expected: bytes, tmp_path: Path) -> None:
    source = tmp_path / "print.gcode"
    source.write_bytes(BODY)
    profile = tmp_path / "profile.toml"
    profile.write_bytes(content)
    run = _run("estimate", "--printer-cfg", str(CORPUS_CFG), "--profile", str(profile),
               str(source))
    assert run.returncode == 1, run.stderr
    assert expected in run.stderr and len(run.stderr.splitlines()) == 1, run.stderr


# One implementation of replacing a user's file

REPLACING_CALLS = frozenset(("replace", "rename", "mkstemp", "NamedTemporaryFile"))


def test_only_kestimator_files_replaces_or_creates_temporary_files() -> None:
    """inject, report and compat all replace a file through kestimator.files: no other
    module of the package renames one into place or makes a temporary file."""
    import ast

    offenders = []
    for path in sorted((PROJECT / "kestimator").rglob("*.py")):
        relative = path.relative_to(PROJECT).as_posix()
        if relative == "kestimator/files.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                    node.func.attr in REPLACING_CALLS and isinstance(node.func.value, ast.Name) \
                    and node.func.value.id in ("os", "tempfile", "shutil"):
                offenders.append("%s:%d: %s.%s" % (relative, node.lineno, node.func.value.id,
                                                   node.func.attr))
    assert not offenders


_HOLD_LOCKED = r"""
import fcntl, sys, time
f = open(sys.argv[1], "rb")
fcntl.flock(f.fileno(), fcntl.LOCK_EX)
print("locked", flush=True)
time.sleep(300)
"""


@pytest.mark.skipif(sys.platform == "win32", reason="flock")
def test_a_write_removes_the_temp_files_of_dead_runs_beside_it_never_a_live_ones(
        tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    """A run killed outright leaves `.NAME.*.kestimator-tmp` (full size, hidden): the next
    write into that folder removes it. One whose writer lives (it holds it flock'ed) stays,
    as does a just-made empty one (its writer may not have locked it yet)."""
    gcode = tmp_path / "a.gcode"
    gcode.write_bytes(BODY)
    dead = tmp_path / ".big.gcode.x1y2z3w4.kestimator-tmp"
    dead.write_bytes(BODY * 1000)
    live = tmp_path / ".b.gcode.a1b2c3d4.kestimator-tmp"
    live.write_bytes(BODY)
    just_made = tmp_path / ".c.gcode.e5f6g7h8.kestimator-tmp"
    just_made.write_bytes(b"")
    other = tmp_path / ".not-ours.tmp"
    other.write_bytes(b"x")
    holder = subprocess.Popen([sys.executable, "-c", _HOLD_LOCKED, str(live)],
                              stdout=subprocess.PIPE)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == b"locked\n"
        inject_file(gcode, limits)
        assert not dead.exists()
        assert live.read_bytes() == BODY and just_made.exists() and other.exists()
    finally:
        holder.kill()
        holder.wait()
    inject_file(gcode, limits)
    assert not live.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [gcode.name, just_made.name, other.name])
