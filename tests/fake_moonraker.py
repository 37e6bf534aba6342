"""A fake Moonraker for the tests: a bounded local HTTP server answering as Moonraker does.

It listens on 127.0.0.1 only, shuts itself down after SERVER_LIFETIME_S whatever happens,
and answers ``GET /printer/objects/query?configfile=settings`` in Moonraker's format:
``{"result": {"eventtime": ..., "status": {"configfile": {"settings": ...}}}}`` with Klipper's
lower-case, typed settings (and ``GET /printer/info`` with ``{"result": info}`` when given an
``info``; else 404 as a Moonraker without it), refusing a wrong ``X-Api-Key`` with 401 and
``{"error": {"code": 401, "message": "Unauthorized"}}`` as Moonraker's app.py writes errors.
"""

from __future__ import annotations

import http.server
import json
import threading
from typing import Any

SERVER_LIFETIME_S = 30.0
TIMEOUT_S = 2.0
POLL_S = 0.02
API_KEY = "0123456789abcdef0123456789abcdef"
QUERY = "/printer/objects/query?configfile=settings"
INFO = "/printer/info"
# Moonraker's printer.info as a Klipper v0.12.0 host answers it (klippy's webhooks "info").
V0_12_INFO: dict[str, Any] = {
    "state": "ready", "state_message": "Printer is ready", "hostname": "printer",
    "klipper_path": "/home/pi/klipper", "python_path": "/home/pi/klippy-env/bin/python",
    "log_file": "/tmp/klippy.log", "config_file": "/home/pi/printer_data/config/printer.cfg",
    "software_version": "v0.12.0-0-g0d67d9c4", "cpu_info": "4 core ARMv7"}

# What Klipper reports for ../shared/corpus/printer.cfg (values typed, defaults it read
# included), plus sections kestimator must neither read nor cache.
CORPUS_SETTINGS: dict[str, dict[str, Any]] = {
    "mcu": {"serial": "/tmp/klipper_host_mcu", "baud": 250000},
    "printer": {"kinematics": "cartesian", "max_velocity": 300.0, "max_accel": 3000.0,
                "minimum_cruise_ratio": 0.5, "square_corner_velocity": 5.0,
                "max_z_velocity": 15.0, "max_z_accel": 100.0},
    "extruder": {"step_pin": "gpio12", "rotation_distance": 33.5, "nozzle_diameter": 0.4,
                 "filament_diameter": 1.75, "max_extrude_only_velocity": 120.0,
                 "max_extrude_only_accel": 1500.0, "max_extrude_only_distance": 10000.0,
                 "max_extrude_cross_section": 1000.0, "instantaneous_corner_velocity": 1.0,
                 "pressure_advance": 0.0, "min_temp": 0.0, "max_temp": 300.0,
                 "min_extrude_temp": 0.0},
    "heater_bed": {"heater_pin": "gpio16", "min_temp": 0.0, "max_temp": 300.0,
                   "min_extrude_temp": 170.0},
    "gcode_arcs": {"resolution": 1.0},
    "firmware_retraction": {"retract_length": 0.8, "retract_speed": 35.0,
                            "unretract_extra_length": 0.0, "unretract_speed": 35.0},
    "display_status": {},
    "gcode_macro secret": {"gcode": "M118 the-wifi-password"},
    "extruder1": {"step_pin": "gpio20", "rotation_distance": 33.5, "nozzle_diameter": 0.4,
                  "filament_diameter": 1.75, "max_extrude_only_velocity": 120.0,
                  "max_extrude_only_accel": 1500.0, "max_extrude_only_distance": 10000.0,
                  "max_extrude_cross_section": 1000.0, "instantaneous_corner_velocity": 1.0,
                  "pressure_advance": 0.0, "min_temp": 0.0, "max_temp": 300.0,
                  "min_extrude_temp": 0.0},
}


class FakeMoonraker:
    """A bounded local HTTP server speaking Moonraker's printer-object query."""

    def __init__(self, settings: dict[str, dict[str, Any]], api_key: str | None = None,
                 status: int = 200, redirect_to: str | None = None,
                 info: dict[str, Any] | None = None) -> None:
        self.settings = settings
        self.info = info
        self.api_key = api_key
        self.status = status
        self.redirect_to = redirect_to
        self.requests: list[tuple[str, str | None]] = []
        fake = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                fake.requests.append((self.path, self.headers.get("X-Api-Key")))
                if fake.redirect_to is not None:
                    self.send_response(302)
                    self.send_header("Location", fake.redirect_to + self.path)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                if fake.api_key is not None and self.headers.get("X-Api-Key") != fake.api_key:
                    self._answer(401, {"error": {"code": 401, "message": "Unauthorized"}})
                elif fake.status != 200:
                    self._answer(fake.status, {"error": {"code": fake.status,
                                                         "message": "Klippy Disconnected"}})
                elif self.path == INFO and fake.info is not None:
                    self._answer(200, {"result": fake.info})
                elif self.path != QUERY:
                    self._answer(404, {"error": {"code": 404, "message": "Not Found"}})
                else:
                    self._answer(200, {"result": {"eventtime": 578243.57824499, "status": {
                        "configfile": {"settings": fake.settings}}}})

            def _answer(self, status: int, document: dict[str, Any]) -> None:
                body = json.dumps(document).encode("utf-8")
                self.send_response(status)
                self.send_header("Content-Type", "application/json; charset=UTF-8")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: object) -> None:
                """Quiet: the test reports what matters."""

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = "http://127.0.0.1:%d" % self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever,
                                       kwargs={"poll_interval": POLL_S}, daemon=True)
        self.timer = threading.Timer(SERVER_LIFETIME_S, self.server.shutdown)
        self.timer.daemon = True

    def start(self) -> FakeMoonraker:
        self.thread.start()
        self.timer.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the port: the printer is now offline."""
        self.timer.cancel()
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(TIMEOUT_S)
