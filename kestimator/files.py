"""Opening a user's file for reading without hanging or reading without end.

Owns the rule for every file kestimator reads on the user's behalf (G-code, printer.cfg and
its includes, profiles, klipper_estimator configs): it must be a regular file. A FIFO is
opened without blocking (open() would wait for a writer forever) and refused; a device such
as /dev/zero or /dev/urandom, which never ends, is refused; config files are read with a size
cap, so a huge one is an error, not all of memory.
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
from pathlib import Path
from typing import BinaryIO

from kestimator.errors import KestimatorError

# No printer.cfg, profile or klipper_estimator config is anywhere near this big.
CONFIG_MAX_BYTES = 16 * 1024 * 1024
NOT_REGULAR = ("is not a regular file (a device, FIFO or socket): give the %s as a file")


def open_regular(path: str | os.PathLike[str], what: str = "G-code") -> BinaryIO:
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


def cleanup_on_termination() -> None:
    """Turn SIGTERM and SIGHUP into `Terminated` (the command lines call this first), so a
    run stopped by a service manager or a closed terminal removes its temporary file.

    The exit status for them is 128 + the signal number, as if killed.
    """
    import signal

    for name in ("SIGTERM", "SIGHUP"):
        signum = getattr(signal, name, None)
        if signum is not None:
            try:
                signal.signal(signum, _terminate)
            except (ValueError, OSError):  # not the main thread
                pass


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
