"""Reading and replacing a user's files safely: the one place kestimator opens or writes them.

Owns the rule for every file kestimator reads on the user's behalf (G-code, printer.cfg and
its includes, profiles, klipper_estimator configs): it must be a regular file. A FIFO is
opened without blocking (open() would wait for a writer forever) and refused; a device such
as /dev/zero or /dev/urandom, which never ends, is refused; config files are read with a size
cap, so a huge one is an error, not all of memory.

Also owns every write of a user's file (`inject`'s output, `report`'s page, the file
`kestimator-compat post-process` rewrites; the Cura plugin writes none itself, Cura saves):
`output_target` resolves where an output really goes (a symlink is written through, its
target replaced and the link kept; a character device or FIFO is written straight through;
anything else not a regular file is refused, and so is a file the user may not write);
`write_atomically` writes the content through a callable into a temporary file beside the
destination, fsyncs it and swaps it in with one rename, keeping the replaced file's owner,
group, mode and extended attributes (`keep_attributes`). On any error the destination is
untouched and the temporary file is removed; a hard link's other names keep the old content
(docs/CLI.md). `exclusive` makes two in-place rewrites of one file take turns. Temporary
files are created with SIGTERM/SIGHUP held back (`make_temp_file`), and
`cleanup_on_termination` (installed by the console entry points only, `kestimator.entry`)
turns those signals into `Terminated`, so a stopped run leaves no temporary file behind.
A run killed outright (SIGKILL: Moonraker's time limit) cannot clean up: each temporary
file is flock'ed by its writer for as long as it lives (`lock_as_ours`), and the next write
into that folder removes the ones whose writer is gone (`remove_abandoned_temp_files`);
private temporary folders work the same way (`private_folder`, `remove_abandoned_folders`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import io
import json
import os
import stat
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

try:
    import fcntl
except ImportError:  # Windows: no flock; the compare-before-replace check still holds
    fcntl = None  # type: ignore[assignment]

from kestimator.errors import KestimatorError

# No printer.cfg, profile or klipper_estimator config is anywhere near this big.
CONFIG_MAX_BYTES = 16 * 1024 * 1024
NOT_REGULAR = ("is not a regular file (a device, FIFO or socket): give the %s as a file")
# Temporary files are `.<name>.<random>.kestimator-tmp` beside the output, the name cut to fit
# the directory's name limit (mkstemp's random part is 8 characters).
TEMP_SUFFIX = ".kestimator-tmp"
TEMP_RANDOM_CHARS = 8
DEFAULT_NAME_MAX = 255
# A temporary file (or folder) no process holds locked is a dead run's, except an empty one
# younger than this: its writer may be between creating and locking it.
ABANDONED_EMPTY_AGE_S = 60.0
# The lock file in a private temporary folder (`private_folder`).
FOLDER_LOCK_NAME = ".kestimator-lock"
# Extended attributes that must survive a rewrite (others, like security.selinux, are the
# system's to set and are kept where the kernel lets us).
KEPT_XATTR_NAMESPACES = ("user.", "system.posix_acl_")

# `-` as a file name: standard input where a file is read, standard output where one is
# written (`output_target`, `spooled_stdin`). A file really named `-` is `./-`.
STDIO_NAME = "-"
STDIN_SHOWN = "<stdin>"
STDOUT_SHOWN = "<stdout>"

Write = Callable[[bytes], object]
"""Where content goes: `out.write` of the temporary file (or of the device)."""


def open_regular(path: str | os.PathLike[str], what: str = "G-code") -> io.BufferedReader:
    """Open `path` for binary reading, refusing (one line) anything but a regular file.

    Raises `KestimatorError` naming the file; never blocks on a FIFO.
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    flags |= getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise KestimatorError("cannot read file: %s" % (exc.strerror or exc), path) from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise KestimatorError("is a directory, not a %s file" % what, path)
        if not stat.S_ISREG(st.st_mode):
            raise KestimatorError(NOT_REGULAR % what, path)
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    # Once the file object owns fd, it alone closes it (never twice: EBADF).
    return os.fdopen(fd, "rb")


def read_config_bytes(path: str | os.PathLike[str], what: str = "config",
                      limit: int = CONFIG_MAX_BYTES) -> bytes:
    """The whole of a config file, refusing non-regular files and files over `limit` bytes."""
    with open_regular(path, what) as f:
        try:
            data = f.read(limit + 1)
        except OSError as exc:
            raise KestimatorError("cannot read file: %s" % (exc.strerror or exc),
                                  path) from None
    if len(data) > limit:
        raise KestimatorError("is over %d MiB: not a %s file" % (limit >> 20, what), path)
    return data


class Terminated(BaseException):
    """SIGTERM or SIGHUP arrived: unwinds like Ctrl-C, so temporary files are removed."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _terminate(signum: int, _frame: object) -> None:
    raise Terminated(signum)


def cleanup_on_termination() -> dict[int, Any]:
    """Turn SIGTERM and SIGHUP into `Terminated`, so a run stopped by a service manager or a
    closed terminal removes its temporary file; returns the handlers they had before.

    For programs only: the console entry points install this (`kestimator.entry`), never
    `kestimator.cli.main` or `kestimator.compat.main`, which a library caller (a test, the
    Cura plugin) runs in its own process. The exit status for them is 128 + the signal
    number, as if killed. Outside the main thread nothing is installed.
    """
    import signal

    previous: dict[int, Any] = {}
    for name in ("SIGTERM", "SIGHUP"):
        signum = getattr(signal, name, None)
        if signum is not None:
            try:
                previous[signum] = signal.signal(signum, _terminate)
            except (ValueError, OSError):  # not the main thread
                pass
    return previous


@contextlib.contextmanager
def terminating_cleanly() -> Iterator[None]:
    """`cleanup_on_termination` while the block runs, then the handlers that were there."""
    import signal

    previous = cleanup_on_termination()
    try:
        yield
    finally:
        for signum, handler in previous.items():
            with contextlib.suppress(ValueError, OSError, TypeError):
                signal.signal(signum, handler)


def make_temp_file(prefix: str, suffix: str, directory: str) -> tuple[int, str]:
    """`tempfile.mkstemp` with SIGTERM/SIGHUP held back until its name is known here.

    A signal arriving while the file is being created would otherwise unwind before the
    caller's cleanup knows the name, and leave the file behind. A signal held back is
    delivered on the way out (as `Terminated`), after the file is removed again.
    """
    import signal
    import tempfile

    held = [getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name)]
    mask = getattr(signal, "pthread_sigmask", None)
    if mask is None or not held:  # Windows: no signal masks
        return tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=directory)
    previous = mask(signal.SIG_BLOCK, held)
    try:
        fd, name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=directory)
    except BaseException:
        mask(signal.SIG_SETMASK, previous)
        raise
    try:
        # Unblocking runs the handler of a signal that came meanwhile (it raises here).
        mask(signal.SIG_SETMASK, previous)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(name)
        raise
    return fd, name


def write_json_privately(path: Path, document: object) -> None:
    """Write `document` as JSON to `path` in a directory only the user may enter (created
    0700), through a temporary file renamed into place: never a partial file.

    Raises OSError (the caller words it); the temporary file is removed on any failure.
    """
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    handle, temp = make_temp_file(path.name, ".tmp", str(path.parent))
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            json.dump(document, out, indent=1, sort_keys=True)
        os.replace(temp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temp)
        raise


@dataclasses.dataclass(frozen=True)
class OutputTarget:
    """Where an output really goes: symlinks resolved, what is there now, and how to write.

    `stream` is True for a character device or a FIFO: written straight through, never
    replaced. Otherwise `path` is a regular file (or nothing yet) replaced atomically.
    """

    path: str
    exists: bool
    stream: bool
    st: os.stat_result | None


def output_target(dest: str) -> OutputTarget:
    """Resolve `dest` for writing; refuse what may not or cannot be replaced (one line).

    A symlink is followed (the link stays, its target gets the new content); a character
    device or FIFO is written through; anything else that is not a regular file is refused,
    and so is a regular file the user may not write (even in a directory they may write).
    """
    if dest == STDIO_NAME:
        return OutputTarget(STDIO_NAME, True, True, None)
    real = os.path.realpath(dest)
    try:
        st = os.stat(real)
    except FileNotFoundError:
        return OutputTarget(real, False, False, None)
    except OSError as exc:
        raise KestimatorError("cannot write the output: %s" % (exc.strerror or exc),
                              dest) from None
    if stat.S_ISCHR(st.st_mode) or stat.S_ISFIFO(st.st_mode):
        return OutputTarget(real, True, True, st)
    if not stat.S_ISREG(st.st_mode):
        raise KestimatorError("is not a regular file: it is never replaced", dest)
    if not may_write(real, st):
        raise KestimatorError("you may not write this file (its permissions say so): it "
                              "was left as it is", dest)
    return OutputTarget(real, True, False, st)


def may_write(path: str, st: os.stat_result) -> bool:
    """Whether the user may change the file: its write permission, not the directory's.

    Root may write anything, so for root a file with no write bit at all counts as one the
    user meant to keep (as `rm -i`/editors warn); others ask the kernel (ACLs included).
    """
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        return bool(st.st_mode & 0o222)
    effective = os.access in os.supports_effective_ids
    return os.access(path, os.W_OK, effective_ids=effective)


def same_file(a: str, b: str) -> bool:
    """True if `a` and `b` name one file (False if either cannot be looked at)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


@contextlib.contextmanager
def exclusive(path: str) -> Iterator[None]:
    """Hold an exclusive flock on the file `path` names while it is rewritten in place.

    Two in-place runs on one file take turns: the second waits, then reads the first's
    output (inject is idempotent, so the bytes come out the same). The lock belongs to
    the inode, which os.replace swaps: after the wait, a path that names another file
    now is locked afresh. Writers that take no lock (a slicer still saving) are caught by
    the size/mtime/inode comparison just before the replace (`write_atomically`'s
    `before_replace`).
    """
    locked = None
    while fcntl is not None:
        try:
            f = open(path, "rb")
        except OSError as exc:
            raise KestimatorError("cannot read file: %s" % (exc.strerror or exc),
                                  path) from None
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        except OSError:
            f.close()  # no flock on this filesystem (some network mounts)
            break
        try:
            same = os.stat(path).st_ino == os.fstat(f.fileno()).st_ino
        except OSError:
            same = False
        if same:
            locked = f
            break
        f.close()
    try:
        yield
    finally:
        if locked is not None:
            locked.close()


def lock_as_ours(fd: int) -> bool:
    """Hold an exclusive flock on the open file `fd` until it is closed (or the process
    dies): a mark no other run removes the file under. False where flock is missing."""
    if fcntl is None:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    return True


def _abandoned(path: str, st: os.stat_result, empty_may_be_new: bool = True) -> bool:
    """True when no process holds `path` (a regular file) flock'ed and (`empty_may_be_new`)
    it is not an empty file a writer may be about to lock. Never True where flock cannot
    tell."""
    if fcntl is None:
        return False
    if empty_may_be_new and st.st_size == 0 and _age(st) < ABANDONED_EMPTY_AGE_S:
        return False
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0)
                     | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False  # held: its writer lives (or flock is refused here)
    finally:
        os.close(fd)
    return True


def _age(st: os.stat_result) -> float:
    import time

    return time.time() - st.st_mtime


def remove_abandoned_temp_files(directory: str) -> list[str]:
    """Remove from `directory` the temporary files (`.NAME.*.kestimator-tmp`) of runs that
    died without cleaning up; returns their names. Files of live runs are held locked
    (`write_atomically` locks its own) and stay; so does anything not a regular file."""
    removed: list[str] = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    for entry in entries:
        if not (entry.name.startswith(".") and entry.name.endswith(TEMP_SUFFIX)):
            continue
        try:
            st = entry.stat(follow_symlinks=False)
            if stat.S_ISREG(st.st_mode) and _abandoned(entry.path, st):
                os.unlink(entry.path)
                removed.append(entry.name)
        except OSError:
            continue
    return removed


@contextlib.contextmanager
def private_folder(prefix: str) -> Iterator[str]:
    """A new folder (0700) in the temporary directory, removed with all in it afterwards;
    locked while it lives, so that `remove_abandoned_folders(prefix)` removes it only once
    the process that made it is gone (killed before it could remove it)."""
    import shutil
    import tempfile

    remove_abandoned_folders(prefix)
    folder = tempfile.mkdtemp(prefix=prefix)
    try:
        # Locked under another name first: the lock file is never there unlocked.
        with open(os.path.join(folder, FOLDER_LOCK_NAME + "-new"), "wb") as lock:
            lock_as_ours(lock.fileno())
            os.rename(lock.name, os.path.join(folder, FOLDER_LOCK_NAME))
            yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def remove_abandoned_folders(prefix: str) -> list[str]:
    """Remove the folders `private_folder(prefix)` made in the temporary directory whose
    process died without removing them; returns their names."""
    import shutil
    import tempfile

    removed: list[str] = []
    top = tempfile.gettempdir()
    try:
        entries = list(os.scandir(top))
    except OSError:
        return removed
    for entry in entries:
        if not entry.name.startswith(prefix):
            continue
        try:
            if not entry.is_dir(follow_symlinks=False) or entry.stat().st_uid != os.getuid():
                continue
            lock = os.path.join(entry.path, FOLDER_LOCK_NAME)
            try:
                st = os.stat(lock, follow_symlinks=False)
            except FileNotFoundError:
                # Made, not yet locked (or by a run from before the lock): by age.
                if _age(entry.stat()) < ABANDONED_EMPTY_AGE_S:
                    continue
            else:
                # Empty for its whole life: its lock alone tells.
                if not stat.S_ISREG(st.st_mode) or not _abandoned(lock, st, False):
                    continue
        except OSError:
            continue
        shutil.rmtree(entry.path, ignore_errors=True)
        removed.append(entry.name)
    return removed


def temp_name_prefix(dest: str) -> str:
    """``.<name>.`` for a temporary file beside `dest`, cut so that the whole temporary
    name (random part and suffix added) fits the directory's name limit."""
    directory = os.path.dirname(os.path.abspath(dest))
    try:
        name_max = os.pathconf(directory, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        name_max = DEFAULT_NAME_MAX
    name = os.fsencode(os.path.basename(dest))
    room = max(1, name_max - len(TEMP_SUFFIX) - TEMP_RANDOM_CHARS - 2)
    return "." + os.fsdecode(name[:room]) + "."


def write_atomically(target: OutputTarget, fill: Callable[[Write], object], *,
                     shown: str | None = None, new_mode: int | None = None,
                     before_sync: Callable[[str], object] | None = None,
                     before_replace: Callable[[], object] | None = None) -> None:
    """Write what `fill(write)` writes to `target`, never partially.

    A character device or FIFO (`target.stream`) is written straight through (a FIFO
    without a reader is refused at once instead of blocking). Otherwise the content goes
    into a temporary file beside the destination; `before_sync(temp_name)` may add to it
    once `fill` is done; it is fsynced; `before_replace()` may refuse (raise) at the last
    moment; a destination that exists then keeps its owner, group, mode and extended
    attributes (a new one gets `new_mode`, by default 0666 less the umask); one rename
    swaps it in and the directory is synced. On any failure the temporary file is removed
    and the destination left as it was. Errors are one-line `KestimatorError`s; those about
    opening or writing name `shown` (default: the resolved path), those about the file
    found there name the resolved path.
    """
    dest = target.path
    name = dest if shown is None else shown
    if target.stream:
        _write_stream(dest, fill, name)
        return
    dest_dir = os.path.dirname(dest)
    try:
        fd, tmp = make_temp_file(temp_name_prefix(dest), TEMP_SUFFIX, dest_dir)
    except OSError as exc:
        raise KestimatorError("cannot write next to the output: %s"
                              % (exc.strerror or exc), name) from None
    held = -1
    try:
        # Ours while we live (a second descriptor keeps the lock until the rename is
        # done); what dead runs left beside it goes.
        if lock_as_ours(fd):
            held = os.dup(fd)
        remove_abandoned_temp_files(dest_dir or ".")
        with os.fdopen(fd, "wb") as out:
            fill(out.write)
            out.flush()
            if before_sync is not None:
                before_sync(tmp)
            os.fsync(out.fileno())
        if before_replace is not None:
            before_replace()
        try:
            now_dest = os.stat(dest)
        except FileNotFoundError:
            now_dest = None
        if now_dest is not None:
            if not stat.S_ISREG(now_dest.st_mode):
                raise KestimatorError("is not a regular file: it is never replaced", dest)
            keep_attributes(dest, now_dest, tmp)
        else:
            os.chmod(tmp, 0o666 & ~_umask() if new_mode is None else new_mode)
        os.replace(tmp, dest)
    except KestimatorError:
        _remove_quietly(tmp)
        raise
    except OSError as exc:
        _remove_quietly(tmp)
        raise KestimatorError("cannot write the output: %s" % (exc.strerror or exc),
                              name) from None
    except BaseException:
        _remove_quietly(tmp)
        raise
    finally:
        if held >= 0:
            os.close(held)
    _fsync_dir(dest_dir)


@contextlib.contextmanager
def spooled_stdin(stream: BinaryIO, shown: str = STDIN_SHOWN) -> Iterator[str]:
    """Standard input copied into a temporary file (0600, in the temporary directory,
    removed afterwards) whose name the block gets: the commands read a file twice (the
    estimate, then the slicer's settings, the report's scan or inject's second pass).

    A terminal is refused (one line: the G-code must come through a pipe or `<`), never
    waited on. A `KestimatorError` from the block that names the temporary file names
    `shown` instead.
    """
    import tempfile

    if is_terminal_stream(stream):
        raise KestimatorError("standard input is a terminal: pipe the G-code in (e.g. "
                              "kestimator estimate - < print.gcode) or name the file", shown)
    fd, tmp = make_temp_file("kestimator-stdin.", ".gcode", tempfile.gettempdir())
    try:
        try:
            with os.fdopen(fd, "wb") as out:
                while True:
                    block = stream.read(1 << 20)
                    if not block:
                        break
                    out.write(block)
        except OSError as exc:
            raise KestimatorError("cannot keep standard input in a temporary file: %s"
                                  % (exc.strerror or exc), shown) from None
        try:
            yield tmp
        except KestimatorError as exc:
            if exc.path == tmp:
                exc.path = shown
            raise
    finally:
        _remove_quietly(tmp)


def is_terminal_stream(stream: object) -> bool:
    """True if `stream` is an interactive terminal (False when it cannot tell)."""
    try:
        return bool(stream.isatty())  # type: ignore[attr-defined]
    except (AttributeError, ValueError, OSError):
        return False


def write_bytes_atomically(dest: str, data: bytes) -> None:
    """Write `data` to `dest` as `inject` writes its output (`output_target`'s rules, a
    temporary file synced and renamed, attributes kept): never a partial file."""
    if not dest:
        raise KestimatorError("the output name is empty")
    write_atomically(output_target(dest), lambda write: write(data), shown=dest)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _write_stream(dest: str, fill: Callable[[Write], object], shown: str) -> None:
    """Write a character device or FIFO straight through; a FIFO without a reader is
    refused at once instead of blocking. `-` is standard output (a reader that goes away
    raises BrokenPipeError, which the command line treats as the end it is)."""
    if dest == STDIO_NAME:
        out = sys.stdout.buffer
        try:
            sys.stdout.flush()
            fill(out.write)
            out.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise KestimatorError("cannot write the output: %s" % (exc.strerror or exc),
                                  STDOUT_SHOWN) from None
        return
    try:
        fd = os.open(dest, os.O_WRONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        if exc.errno == errno.ENXIO:
            raise KestimatorError("the FIFO has no reader: nothing was written",
                                  shown) from None
        raise KestimatorError("cannot write the output: %s" % (exc.strerror or exc),
                              shown) from None
    try:
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        with os.fdopen(fd, "wb") as out:
            fill(out.write)
    except OSError as exc:
        raise KestimatorError("cannot write the output: %s" % (exc.strerror or exc),
                              shown) from None


def keep_attributes(dest: str, st: os.stat_result, tmp: str) -> None:
    """Give `tmp` the owner, group, mode and extended attributes of `dest` (its `st`).

    Refuses (one line) when the owner or group cannot be kept: replacing the file would
    hand it to the user running us, and its owner could lose access to it.
    """
    tmp_st = os.stat(tmp)
    if (tmp_st.st_uid, tmp_st.st_gid) != (st.st_uid, st.st_gid):
        try:
            os.chown(tmp, st.st_uid, st.st_gid)
        except OSError:
            raise KestimatorError(
                "cannot keep the file's owner and group (uid %d, gid %d) in a new copy: it "
                "was left as it is" % (st.st_uid, st.st_gid), dest) from None
    # After chown, which clears set-id bits.
    os.chmod(tmp, stat.S_IMODE(st.st_mode))
    _copy_xattrs(dest, tmp)


def _copy_xattrs(dest: str, tmp: str) -> None:
    if not hasattr(os, "listxattr"):
        return
    try:
        names = os.listxattr(dest)
    except OSError:
        return
    for name in names:
        try:
            os.setxattr(tmp, name, os.getxattr(dest, name))
        except OSError as exc:
            if name.startswith(KEPT_XATTR_NAMESPACES):
                raise KestimatorError("cannot keep the extended attribute %s: %s; the file "
                                      "was left as it is" % (name, exc.strerror or exc),
                                      dest) from None


def _remove_quietly(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def _fsync_dir(path: str) -> None:
    """Make the rename durable where the platform allows it (not on Windows)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
