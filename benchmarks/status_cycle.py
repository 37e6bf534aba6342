"""What the Klipper module adds to each of Klipper's status cycles (issue 34).

Moonraker subscribes to display_status and kestimator; Klipper's webhooks asks each object's
get_status() once per 250 ms cycle, in the reactor. The module answers both at the asked
eventtime: display_status's progress D / (D + R) and its own remaining time. This times
those two calls on the module with Klipper's objects stubbed (tests/klipper_module/
stubs.py) and the largest table the worker may send (20,002 points, 200 objects x 500
points, 1,000 stops: the next one is computed at each call), against display_status's own
get_status without the module.

    python3 benchmarks/status_cycle.py [--cycles N]
"""
from __future__ import annotations

import argparse
import array
import base64
import os
import sys
import time
from typing import Any

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests", "klipper_module"))
import stubs  # noqa: E402


def _b64(kind: str, values: list[Any]) -> str:
    return base64.b64encode(array.array(kind, values).tobytes()).decode()


def _largest_answer(request_id: int) -> dict[str, Any]:
    points = 20002
    objects, object_points = 200, 500
    stops = 1000
    return {"id": request_id, "ok": True, "source": "estimate", "total_s": 20000.,
            "offsets_b64": _b64("q", [i * 1000 for i in range(points)]),
            "times_b64": _b64("d", [i * 20000. / (points - 1) for i in range(points)]),
            "object_names": ["OBJECT_%03d" % i for i in range(objects)],
            "object_offsets_b64": _b64("q", [i * 40000 for i in range(object_points)]),
            "object_remaining_b64": _b64("d", [
                100. * (object_points - j) / object_points
                for i in range(objects) for j in range(object_points)]),
            "stop_offsets": [i * 20000 for i in range(stops)],
            "stop_times": [i * 20. for i in range(stops)],
            "stop_commands": ["M600"] * stops, "stop_lines": [i * 400 for i in range(stops)]}


def _per_call_us(func: Any, cycles: int) -> float:
    start = time.perf_counter()
    for k in range(cycles):
        func(1000. + k * 0.25)
    return (time.perf_counter() - start) / cycles * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cycles", type=int, default=20000)
    args = ap.parse_args()
    module = stubs.load_module()
    printer = stubs.Printer()
    display = printer.objects["display_status"]
    klipper_own = display.get_status
    kest = module.load_config(stubs.Config(printer))
    printer.send_event("klippy:ready")
    kest._stop_worker()     # the one started at klippy:ready: answers are given here

    class _Quiet:
        unsent = b""

        def send(self, request: dict[str, Any]) -> None:
            pass

        def close(self) -> None:
            pass
    kest.worker = _Quiet()
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = "/sd/x.gcode", True
    printer.objects["print_stats"].state = "printing"
    printer.objects["print_stats"].print_duration = 600.
    printer.reactor.run_timers()
    kest.on_answer(_largest_answer(kest.request_id))
    vsd.file_position = 10_000_000
    toolhead = printer.objects["toolhead"]
    toolhead.print_time = toolhead.mcu.est = 5000.
    printer.reactor.advance(1.)
    assert kest.get_status(0.)["remaining_s"] is not None, kest.get_status(0.)
    assert kest.get_status(0.)["next_stop"] is not None
    own = _per_call_us(klipper_own, args.cycles)
    answered = _per_call_us(display.get_status, args.cycles)
    status = _per_call_us(kest.get_status, args.cycles)
    print("per status cycle, %d cycles, Python %s:" % (args.cycles, sys.version.split()[0]))
    print("  display_status.get_status, Klipper's own (stub): %.1f us" % own)
    print("  display_status.get_status, answered by the module: %.1f us (+%.1f us)"
          % (answered, answered - own))
    print("  kestimator.get_status: %.1f us" % status)
    print("  added per cycle: %.3f ms" % ((answered - own + status) / 1000.))


if __name__ == "__main__":
    main()
