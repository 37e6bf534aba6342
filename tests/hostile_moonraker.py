"""A hostile Moonraker for the tests: a bounded loopback server that answers badly on purpose.

It listens on 127.0.0.1 only, serves each connection in a daemon thread, stops itself after
LIFETIME_S whatever happens, and behaves as one of:

- ``silent``: accepts and never answers;
- ``drip``: a valid-looking answer one byte every DRIP_S (forever, within LIFETIME_S);
- ``garbage``: random bytes, then closes;
- ``huge``: a 200 status with an endless JSON-looking body (stops at HUGE_BYTES);
- ``redirect``: 302 to a second loopback listener that records the headers it gets;
- ``echo_key``: 401 whose error message echoes the X-Api-Key sent, with ANSI escapes, CR and
  a 1 MB line.
"""

from __future__ import annotations

import random
import socket
import threading
import time
from collections.abc import Callable

LIFETIME_S = 20.0
DRIP_S = 0.2
HUGE_BYTES = 64 * 1024 * 1024
BEHAVIOURS = ("silent", "drip", "garbage", "huge", "redirect", "echo_key")


def read_request(conn: socket.socket, alive: Callable[[], bool]) -> bytes:
    """An HTTP request's head (at most 64 KiB), read while `alive()`."""
    data = b""
    while b"\r\n\r\n" not in data and len(data) < 65536 and alive():
        try:
            chunk = conn.recv(4096)
        except TimeoutError:
            continue
        if not chunk:
            break
        data += chunk
    return data


class HostileMoonraker:
    """``with HostileMoonraker("drip") as server: server.url``."""

    def __init__(self, behaviour: str) -> None:
        if behaviour not in BEHAVIOURS:
            raise ValueError(behaviour)
        self.behaviour = behaviour
        self.seen_headers: list[bytes] = []
        self._stop = threading.Event()
        self._listener = self._listen()
        self._sink = self._listen() if behaviour == "redirect" else None
        self.url = "http://127.0.0.1:%d" % self._listener.getsockname()[1]

    def _listen(self) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", 0))
        sock.listen(16)
        sock.settimeout(0.1)
        return sock

    def __enter__(self) -> HostileMoonraker:
        self._started = time.monotonic()
        threading.Thread(target=self._accept, args=(self._listener, self._serve),
                         daemon=True).start()
        if self._sink is not None:
            threading.Thread(target=self._accept, args=(self._sink, self._record),
                             daemon=True).start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._listener.close()
        if self._sink is not None:
            self._sink.close()

    def _alive(self) -> bool:
        return not self._stop.is_set() and time.monotonic() - self._started < LIFETIME_S

    def _accept(self, listener: socket.socket, handler) -> None:  # type: ignore[no-untyped-def]
        while self._alive():
            try:
                conn, _ = listener.accept()
            except (TimeoutError, OSError):
                continue
            threading.Thread(target=self._guarded, args=(handler, conn), daemon=True).start()

    def _guarded(self, handler, conn: socket.socket) -> None:  # type: ignore[no-untyped-def]
        try:
            conn.settimeout(1.0)
            handler(conn, self._read_request(conn))
        except OSError:
            pass
        finally:
            conn.close()

    def _read_request(self, conn: socket.socket) -> bytes:
        return read_request(conn, self._alive)

    def _record(self, conn: socket.socket, request: bytes) -> None:
        self.seen_headers.append(request)
        conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\n{}")

    def _serve(self, conn: socket.socket, request: bytes) -> None:
        behaviour = self.behaviour
        if behaviour == "silent":
            while self._alive():
                time.sleep(0.05)
        elif behaviour == "drip":
            answer = (b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\n"
                      b"Content-Length: 100000000\r\n\r\n" + b"{" + b" " * 10 ** 6)
            for i in range(len(answer)):
                if not self._alive():
                    break
                conn.sendall(answer[i:i + 1])
                time.sleep(DRIP_S)
        elif behaviour == "garbage":
            conn.sendall(random.Random(7).randbytes(5000))
        elif behaviour == "huge":
            conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\n\r\n"
                         b'{"result": {"status": {"configfile": {"settings": {"x": "')
            sent = 0
            block = b"A" * 65536
            while sent < HUGE_BYTES and self._alive():
                conn.sendall(block)
                sent += len(block)
        elif behaviour == "redirect":
            assert self._sink is not None
            conn.sendall(b"HTTP/1.1 302 Found\r\nLocation: http://127.0.0.1:%d/steal\r\n"
                         b"Content-Length: 0\r\n\r\n" % self._sink.getsockname()[1])
        elif behaviour == "echo_key":
            key = b""
            for line in request.split(b"\r\n"):
                if line.lower().startswith(b"x-api-key:"):
                    key = line.split(b":", 1)[1].strip()
            message = (b"\x1b[31mbad key " + key + b"\r\x1b[2Kfake prompt$ "
                       + b"B" * 1_000_000 + b"\nsecond line")
            body = b'{"error": {"code": 401, "message": "%s"}}' % message.replace(
                b"\\", b"\\\\").replace(b'"', b'\\"').replace(b"\x1b", b"\\u001b").replace(
                b"\r", b"\\r").replace(b"\n", b"\\n")
            conn.sendall(b"HTTP/1.1 401 Unauthorized\r\nContent-Length: %d\r\n\r\n"
                         % len(body) + body)
