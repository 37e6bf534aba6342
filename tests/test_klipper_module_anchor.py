"""The Klipper module's tie to Klipper's clock, as a printer runs it (Klipper's objects
stubbed, tests/klipper_module/stubs.py): on a printer the module's timer runs while
virtual_sdcard waits inside a line, so the anchor is taken at the next line start; and the
state the user set at the console before the print is part of the estimate. The same in
real Klipper printing at wall-clock speed: tests/test_klipper_module_realtime.py."""
from __future__ import annotations

from typing import Any

import pytest

from tests.klipper_module import stubs
from tests.test_klipper_module import b64, printing


def answer(request_id: int) -> dict[str, Any]:
    """A worker answer: 1000 bytes of file, 100 s, a point every 100 bytes (10 s)."""
    return {"id": request_id, "ok": True, "source": "estimate", "total_s": 100.,
            "offsets_b64": b64("q", list(range(0, 1001, 100))),
            "times_b64": b64("d", [float(t) for t in range(0, 101, 10)])}


def test_inside_a_line_the_timer_asks_and_the_next_line_start_anchors() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    # An arc at byte 400 has queued half of its moves; the timer runs inside it.
    vsd.file_position, vsd.next_file_position, vsd.cmd_from_sd = 400, 500, True
    toolhead.lookahead.queue.append(stubs.Move())
    before = kest.anchor
    printer.reactor.advance(1.)
    assert kest.anchor == before and kest.want_anchor
    # The arc's last moves are queued; virtual_sdcard hands Klipper the next line.
    toolhead.lookahead.queue.append(stubs.Move())
    vsd.file_position = 500
    printer.gcode.run_script("G1 X10")
    toolhead.plan(40.)     # the moves before byte 500 end at print_time 40
    assert kest.anchor == (40., 500) and not kest.want_anchor
    toolhead.mcu.est = 39.
    printer.reactor.advance(1.)
    assert kest.get_status(0.)["remaining_s"] == pytest.approx(50. + 1.)


def test_no_anchor_is_taken_from_a_line_half_queued() -> None:
    """Anchoring at the line's start or end while it runs would count its queued half
    twice or not at all."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position, vsd.next_file_position, vsd.cmd_from_sd = 400, 500, True
    toolhead.lookahead.queue.append(stubs.Move())
    before = kest.anchor
    for _ in range(5):
        printer.reactor.advance(0.5)
    toolhead.plan(40.)
    assert kest.anchor == before and kest.anchor_pending == 0


def test_a_script_run_while_a_line_holds_the_gcode_mutex_takes_no_anchor() -> None:
    """A delayed_gcode (the guide's stop notice) or a typed command while virtual_sdcard
    waits inside a line: Klipper runs it once the line is done, so it is no line start
    (anchoring there counted the line's queued half as still to come: 0.7 s too much);
    the next line start anchors."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position, vsd.next_file_position, vsd.cmd_from_sd = 400, 500, True
    toolhead.lookahead.queue.append(stubs.Move())
    printer.reactor.advance(1.)
    before = kest.anchor
    assert kest.want_anchor
    printer.gcode.mutex.locked = True            # the line at byte 400 runs
    printer.gcode.run_script("SET_GCODE_VARIABLE MACRO=X VARIABLE=Y VALUE=1")
    toolhead.plan(40.)
    assert kest.anchor == before and kest.want_anchor
    printer.gcode.mutex.locked = False           # the line is done: the next one starts
    vsd.file_position = 500
    toolhead.lookahead.queue.append(stubs.Move())
    printer.gcode.run_script("G1 X10")
    toolhead.plan(45.)
    assert kest.anchor == (45., 500)


def test_a_typed_command_anchors_before_it_runs() -> None:
    """A PAUSE's park move (typed, not the file's) never counts as the file's time."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position, vsd.cmd_from_sd = 500, False
    toolhead.lookahead.queue.append(stubs.Move())
    printer.gcode.register_command("PAUSE", lambda gcmd: None)
    printer.gcode.run_script("PAUSE")
    toolhead.plan(40.)
    assert kest.anchor == (40., 500)


def test_past_the_anchor_a_moving_head_goes_on_to_the_end_of_its_line() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))     # 1000 bytes, 100 s, linear
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position = 100
    printer.reactor.advance(1.)   # between lines: anchored at once (nothing queued)
    toolhead.print_time = 10.
    assert kest.anchor is not None
    kest.anchor = (10., 100)      # the moves before byte 100 end at print_time 10
    kest.anchor_idle = False      # (planned with moves queued: the head moves on)
    # A long macro line from byte 100 to 300 is running; Klipper has planned its moves.
    vsd.cmd_from_sd, vsd.next_file_position = True, 300
    toolhead.print_time = 60.
    assert kest.remaining_at(10.) == pytest.approx(90.)
    assert kest.remaining_at(15.) == pytest.approx(85.)
    # never past the end of the line being run (byte 300: 70 s left)
    assert kest.remaining_at(40.) == pytest.approx(70.)


def test_an_idle_head_past_the_anchor_loses_no_time() -> None:
    """A heater wait: every move has run, nothing is queued, the time left stands."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead = printer.objects["toolhead"]
    kest.anchor = (10., 100)
    toolhead.print_time = 10.
    assert kest.remaining_at(10.) == kest.remaining_at(60.) == pytest.approx(90.)


def test_moves_still_running_after_the_file_ends_are_still_time_left() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position = 900
    printer.reactor.advance(1.)
    # The file is read to its end; its last moves end at print_time 52.
    vsd.file_position, vsd.active, vsd.path = 1000, False, None
    printer.objects["print_stats"].state = "complete"
    toolhead.print_time = 52.
    toolhead.mcu.est = 50.
    printer.reactor.advance(0.5)
    assert kest.get_status(0.)["remaining_s"] == pytest.approx(2.)
    toolhead.mcu.est = 53.
    printer.reactor.advance(0.5)
    assert kest.get_status(0.)["remaining_s"] == 0.


def test_limits_and_factors_set_before_the_print_are_events_at_its_start() -> None:
    """Mainsail's and Fluidd's sliders send SET_VELOCITY_LIMIT and M220 from the console;
    they stay until a restart, and the next print runs with them."""
    printer = stubs.Printer()
    kest = MOD_load(printer)
    printer.send_event("klippy:ready")
    printer.gcode.run("SET_VELOCITY_LIMIT", ACCEL="1500")
    printer.gcode.run("M220", S="150")
    worker = _fake_worker(kest)
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = "/sd/x.gcode", True
    printer.objects["print_stats"].state = "printing"
    printer.reactor.run_timers()
    (request,) = worker.requests
    assert request["events"] == [[0, "SET_VELOCITY_LIMIT ACCEL=1500"], [0, "M220 S150"]]
    assert request["use_table"] is False


def test_a_printer_as_its_config_says_adds_nothing_to_the_print() -> None:
    kest, printer, worker = printing()
    assert worker.requests[0]["events"] == []
    assert kest.state_before_print(0.) == []


def MOD_load(printer: stubs.Printer) -> object:  # noqa: N802
    from tests.test_klipper_module import MOD
    return MOD.load_config(stubs.Config(printer))


def _fake_worker(kest: object) -> object:
    from tests.test_klipper_module import FakeWorker
    worker = FakeWorker()
    kest.worker = worker  # type: ignore[attr-defined]
    return worker


def test_the_status_is_of_the_eventtime_it_is_asked_for() -> None:
    """webhooks asks every object with one eventtime per cycle; the module's last update
    may be up to an interval older, and its time must not lag by that."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position, toolhead.print_time = 500, 50.   # moves before byte 500 end at 50
    toolhead.mcu.est = 40.
    printer.reactor.advance(0.5)
    assert kest.get_status(0.)["remaining_s"] == pytest.approx(60.)
    toolhead.mcu.estimated_print_time = lambda eventtime: 40. + eventtime
    assert kest.get_status(0.25)["remaining_s"] == pytest.approx(59.75)


def test_moves_waiting_for_the_queue_to_prime_are_not_yet_time_done() -> None:
    """After a heater wait the next lines' moves sit in the look-ahead queue while Klipper
    primes it: the head is idle, the time left stands."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    kest.anchor = (10., 100)      # the moves before byte 100 ended at 10, then the wait
    toolhead.print_time = 10.
    vsd.cmd_from_sd, vsd.next_file_position = True, 300
    toolhead.lookahead.queue.append(stubs.Move())
    assert kest.remaining_at(13.) == pytest.approx(90.)


def test_an_anchor_taken_with_nothing_queued_moves_to_where_klipper_primes_again() -> None:
    """A heater wait ran the queue dry at print_time 10; the next line anchors with nothing
    queued; Klipper primes the queue again at 14 (toolhead:sync_print_time): the moves
    from that line on start there, and the 4 s between are no progress."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    toolhead.print_time = 10.
    vsd.file_position, vsd.cmd_from_sd = 100, True
    kest.want_anchor = True
    printer.gcode.run_script("G1 X1")           # the line after the wait: nothing queued
    assert kest.anchor == (10., 100) and kest.anchor_idle
    toolhead.print_time = 15.                   # its moves planned from 14 on
    assert kest.remaining_at(13.) == pytest.approx(90.)
    printer.send_event("toolhead:sync_print_time", 0., 13.75, 14.)
    assert kest.anchor == (14., 100)
    assert kest.remaining_at(13.) == pytest.approx(91.)
    vsd.next_file_position = 300
    assert kest.remaining_at(14.5) == pytest.approx(89.5)


def test_an_idle_gap_after_a_planned_anchor_is_no_progress() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    kest.anchor, kest.anchor_idle = (10., 100), False
    vsd.cmd_from_sd, vsd.next_file_position = True, 300
    toolhead.print_time = 12.                   # moves to 12, then the queue ran dry
    printer.send_event("toolhead:sync_print_time", 0., 15.75, 16.)
    toolhead.print_time = 18.
    assert kest.want_anchor
    assert kest.remaining_at(17.) == pytest.approx(90.)     # not 83: no base to go on from


def test_the_state_before_the_print_is_read_before_the_files_first_line() -> None:
    """SDCARD_PRINT_FILE resets virtual_sdcard before it starts the file; the file's own
    first lines (an OrcaSlicer SET_VELOCITY_LIMIT) may run before the module's next update
    and are the file's, already in its estimate and its table."""
    printer = stubs.Printer()
    kest = MOD_load(printer)
    printer.send_event("klippy:ready")
    printer.gcode.run("M220", S="150")            # typed at the console
    worker = _fake_worker(kest)
    printer.send_event("virtual_sdcard:reset_file")
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active, vsd.cmd_from_sd = "/sd/x.gcode", True, True
    printer.gcode.run("SET_VELOCITY_LIMIT", ACCEL="5000")    # the file's line 1
    printer.objects["print_stats"].state = "printing"
    printer.reactor.run_timers()
    (request,) = worker.requests
    assert request["events"] == [[0, "M220 S150"]]


def test_a_state_that_cannot_be_read_is_a_warning_not_an_error() -> None:
    printer = stubs.Printer()
    kest = MOD_load(printer)
    printer.send_event("klippy:ready")
    printer.gcode.run("M220", S="150")

    def broken(eventtime: float) -> dict[str, float]:
        raise KeyError("max_accel")
    printer.objects["toolhead"].get_status = broken
    events = kest.state_before_print(0.)
    assert events == ["M220 S150"]
    assert not kest.disabled
    (warning,) = kest.state_warnings
    assert "toolhead limits" in warning and "printer.cfg" in warning
