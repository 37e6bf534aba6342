"""A Moonraker with a job history, for `kestimator learn` tests: bounded, loopback only.

It listens on 127.0.0.1 only, serves each connection in a daemon thread and stops itself
after LIFETIME_S whatever happens. It answers, as Moonraker does:

- ``GET /printer/objects/query?configfile=settings``: Klipper's settings (`settings`);
- ``GET /server/history/list?...``: ``{"result": {"count", "jobs"}}`` (or `history_body`,
  raw bytes, when given);
- ``GET /server/files/gcodes/<name>``: the bytes of `files[name]`, 404 if unknown.

A path named in `drip` (``"history"`` or ``"files"``) is answered one byte every DRIP_S
instead, for ever (within LIFETIME_S). Every request path is recorded in `paths`.
"""

from __future__ import annotations

import json
import socket
import threading
import time
import urllib.parse
from typing import Any

from tests.fake_moonraker import CORPUS_SETTINGS
from tests.hostile_moonraker import read_request

LIFETIME_S = 20.0
DRIP_S = 0.2
SETTINGS_PATH = "/printer/objects/query?configfile=settings"
HISTORY_PREFIX = "/server/history/list"
FILES_PREFIX = "/server/files/gcodes/"


def completed_job(n: int, filename: str, total_s: float, print_s: float) -> dict[str, Any]:
    """One finished job as ``/server/history/list`` lists it."""
    return {"job_id": "%06X" % n, "filename": filename, "status": "completed",
            "start_time": 1_763_000_000.0 + 7200 * n, "end_time": 1_763_000_000.0 + 7200 * n
            + total_s, "print_duration": print_s, "total_duration": total_s,
            "filament_used": 100.0, "metadata": {}, "auxiliary_data": [], "exists": True}


class HistoryMoonraker:
    """``with HistoryMoonraker(jobs, files) as server: server.url``."""

    def __init__(self, jobs: list[dict[str, Any]], files: dict[str, bytes] | None = None,
                 drip: tuple[str, ...] = (), history_body: bytes | None = None,
                 settings: dict[str, dict[str, Any]] | None = None) -> None:
        self.jobs = jobs
        self.files = files or {}
        self.drip = drip
        self.history_body = history_body
        self.settings = CORPUS_SETTINGS if settings is None else settings
        self.paths: list[str] = []
        self._stop = threading.Event()
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(16)
        self._listener.settimeout(0.1)
        self.url = "http://127.0.0.1:%d" % self._listener.getsockname()[1]

    def __enter__(self) -> HistoryMoonraker:
        self._started = time.monotonic()
        threading.Thread(target=self._accept, daemon=True).start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._listener.close()

    def downloads(self) -> list[str]:
        """The file names downloaded, in order."""
        return [urllib.parse.unquote(p[len(FILES_PREFIX):]) for p in self.paths
                if p.startswith(FILES_PREFIX)]

    def _alive(self) -> bool:
        return not self._stop.is_set() and time.monotonic() - self._started < LIFETIME_S

    def _accept(self) -> None:
        while self._alive():
            try:
                conn, _ = self._listener.accept()
            except (TimeoutError, OSError):
                continue
            threading.Thread(target=self._guarded, args=(conn,), daemon=True).start()

    def _guarded(self, conn: socket.socket) -> None:
        try:
            conn.settimeout(1.0)
            request = self._read_request(conn)
            path = request.split(b" ", 2)[1].decode("latin-1") if b" " in request else ""
            self.paths.append(path)
            self._serve(conn, path)
        except (OSError, IndexError):
            pass
        finally:
            conn.close()

    def _read_request(self, conn: socket.socket) -> bytes:
        return read_request(conn, self._alive)

    def _serve(self, conn: socket.socket, path: str) -> None:
        kind = ("history" if path.startswith(HISTORY_PREFIX) else
                "files" if path.startswith(FILES_PREFIX) else "settings")
        if kind in self.drip:
            head = b"HTTP/1.1 200 OK\r\nContent-Length: 100000000\r\n\r\n"
            conn.sendall(head)
            while self._alive():
                conn.sendall(b"[" if kind == "history" else b";")
                time.sleep(DRIP_S)
            return
        if kind == "settings" and path == SETTINGS_PATH:
            body = json.dumps({"result": {"eventtime": 1.0, "status": {
                "configfile": {"settings": self.settings}}}}).encode()
        elif kind == "history":
            body = self.history_body if self.history_body is not None else json.dumps(
                {"result": {"count": len(self.jobs), "jobs": self.jobs}}).encode()
        elif kind == "files" and urllib.parse.unquote(path[len(FILES_PREFIX):]) in self.files:
            body = self.files[urllib.parse.unquote(path[len(FILES_PREFIX):])]
        else:
            body = b'{"error": {"code": 404, "message": "Not Found"}}'
            conn.sendall(b"HTTP/1.1 404 Not Found\r\nContent-Length: %d\r\n\r\n" % len(body)
                         + body)
            return
        conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\n"
                     b"Content-Length: %d\r\nConnection: close\r\n\r\n" % len(body) + body)
