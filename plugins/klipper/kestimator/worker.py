# kestimator: the worker process and its pipe
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""`python3 -m kestimator.worker`, started from the checkout the module is linked from,
and its pipes, read through the reactor without ever blocking it, every read bounded.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import Any, Callable

# The worker's answer is refused past this many bytes: the largest table
# table.py's limits allow is under 2 MiB with base64 (kestimator/worker.py answers
# at most its own MAX_ANSWER_BYTES, 3.5 MiB).
MAX_ANSWER_BYTES = 4 << 20
# Bytes read from the worker's pipes per callback.
READ_CHUNK = 1 << 16
# The end of the worker's stderr kept, to say why it stopped.
STDERR_TAIL_BYTES = 4096
# A request is never longer (the worker's own MAX_REQUEST_BYTES is 1 MiB).
MAX_REQUEST_BYTES = 1 << 20
# Worker niceness: estimating must never compete with Klipper for the CPU.
WORKER_NICE = 10
# `python3 -m kestimator.worker`. The build in the checkout's .venv-host (install.sh's,
# compiled where it could be) runs when it was built from the commit the checkout is on
# (.venv-host/kestimator-commit, written last by plugins/moonraker/build-venv); else (an
# update not built yet, or no venv) the checkout's own source: always the checkout's code.
WORKER_BOOT = """
import os, runpy, subprocess, sys
root = sys.argv.pop(1)
try:
    with open(os.path.join(root, ".venv-host", "kestimator-commit")) as f:
        built = f.read().strip()
    head = subprocess.run(["git", "-C", root, "rev-parse", "HEAD"], capture_output=True,
                          text=True, timeout=30).stdout.strip()
except (OSError, subprocess.SubprocessError):
    built, head = "", "?"
if built and built == head:
    sys.path.append(root)
else:
    sys.path.insert(0, root)
runpy.run_module("kestimator.worker", run_name="__main__", alter_sys=True)
"""



def _repo_root() -> str:
    # plugins/klipper/kestimator/worker.py in a kestimator checkout, the package linked
    # into klippy/extras/: the checkout is three folders above the real file.
    here = os.path.dirname(os.path.realpath(__file__))
    return os.path.dirname(os.path.dirname(os.path.dirname(here)))


def default_python() -> str:
    """The Python that runs the worker: install.sh's virtualenv when there,
    else Klipper's own Python with the checkout on its path."""
    root = _repo_root()
    venv_python = os.path.join(root, ".venv-host", "bin", "python")
    if os.path.exists(venv_python):
        return venv_python
    return sys.executable



class Worker:
    """The estimating process: JSON lines in, JSON lines out, read through
    the reactor without ever blocking it. Every callback it registers is
    wrapped in `guard`; what it reads per callback is bounded."""

    def __init__(self, reactor: Any, python: str,
                 guard: Callable[[Callable[..., Any]], Callable[..., Any]],
                 on_line: Callable[[bytes | None], Any],
                 on_exit: Callable[[str], Any]) -> None:
        self.reactor = reactor
        self.on_line = on_line
        self.on_exit = on_exit
        env = dict(os.environ)
        env["PYTHONDONTWRITEBYTECODE"] = "1"
        self.proc = subprocess.Popen(
            [python, "-c", WORKER_BOOT, _repo_root()], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            close_fds=True, env=env, cwd="/")
        try:
            os.setpriority(os.PRIO_PROCESS, self.proc.pid, WORKER_NICE)
        except (OSError, AttributeError):
            pass
        assert (self.proc.stdout is not None and self.proc.stdin is not None
                and self.proc.stderr is not None)
        self.out_fd = self.proc.stdout.fileno()
        self.in_fd = self.proc.stdin.fileno()
        self.err_fd = self.proc.stderr.fileno()
        for fd in (self.out_fd, self.in_fd, self.err_fd):
            os.set_blocking(fd, False)
        self.buf = bytearray()
        # Past MAX_ANSWER_BYTES: the rest of that line is dropped as it comes.
        self.skipping = False
        self.err_tail = bytearray()
        # A request not yet taken by the pipe (written as it empties).
        self.unsent = b""
        self.closed = False
        self.fd_handle: Any = reactor.register_fd(self.out_fd,
                                                  guard(self._readable))
        self.err_handle: Any = reactor.register_fd(self.err_fd,
                                                   guard(self._err_readable))

    def send(self, request: dict[str, Any]) -> None:
        data = (json.dumps(request, separators=(",", ":")) + "\n").encode()
        if len(data) > MAX_REQUEST_BYTES:
            raise ValueError("a request over %d bytes" % (MAX_REQUEST_BYTES,))
        self.unsent = data
        self.flush()

    def flush(self) -> bool:
        """Write what the pipe takes of the request; True once all is sent.
        OSError (BrokenPipeError: the worker stopped) for the caller."""
        while self.unsent:
            try:
                written = os.write(self.in_fd, self.unsent[:READ_CHUNK])
            except BlockingIOError:
                return False
            self.unsent = self.unsent[written:]
        return True

    def _readable(self, eventtime: float) -> None:
        if self.closed:
            return
        try:
            data = os.read(self.out_fd, READ_CHUNK)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._read_err()
            self.close()
            self.on_exit(self.cause())
            return
        if self.skipping:
            end = data.find(b"\n")
            if end < 0:
                return
            self.skipping = False
            data = data[end + 1:]
        start = len(self.buf)
        self.buf += data
        end = self.buf.find(b"\n", start)
        while end >= 0 and not self.closed:
            line = bytes(self.buf[:end])
            del self.buf[:end + 1]
            if line.strip():
                self.on_line(line)
            end = self.buf.find(b"\n")
        if len(self.buf) > MAX_ANSWER_BYTES:
            self.buf = bytearray()
            self.skipping = True
            self.on_line(None)

    def _err_readable(self, eventtime: float) -> None:
        self._read_err(1)

    def _read_err(self, reads: int = 16) -> None:
        """Keep the last STDERR_TAIL_BYTES of what the worker said on stderr."""
        for _ in range(reads):
            try:
                data = os.read(self.err_fd, READ_CHUNK)
            except OSError:
                return
            if not data:
                if self.err_handle is not None:
                    self.reactor.unregister_fd(self.err_handle)
                    self.err_handle = None
                return
            self.err_tail += data
            del self.err_tail[:-STDERR_TAIL_BYTES]

    def cause(self) -> str:
        """Why it stopped, on one line: the last line it said on stderr."""
        lines = [line.strip() for line in
                 bytes(self.err_tail).decode("utf-8", "replace").split("\n")]
        lines = [line for line in lines if line]
        code = self.proc.poll()
        status = "exit status %d" % (code,) if code is not None else "stopped"
        if lines:
            return "%s (%s)" % (lines[-1][:300], status)
        return status

    def close(self, kill: bool = False) -> None:
        """Stop it (`kill`: at once, SIGKILL, as when its work is of no use any more: it
        writes nothing but its answers)."""
        self.closed = True
        for attr in ("fd_handle", "err_handle"):
            handle = getattr(self, attr)
            if handle is not None:
                setattr(self, attr, None)
                try:
                    self.reactor.unregister_fd(handle)
                except Exception:
                    pass
        proc = self.proc
        for stream in (proc.stdin, proc.stdout, proc.stderr):
            try:
                if stream is not None:
                    stream.close()
            except Exception:
                pass
        if proc.poll() is None:
            try:
                if kill:
                    proc.kill()
                else:
                    proc.terminate()
            except OSError:
                pass
        # Reap it later without waiting now.
        self.reactor.register_callback(lambda e: self._reap())

    def _reap(self) -> None:
        try:
            self.proc.wait(timeout=0)
        except Exception:
            pass
