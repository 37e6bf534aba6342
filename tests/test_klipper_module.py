"""The Klipper module (plugins/klipper/kestimator.py) with Klipper's objects stubbed at
the interfaces it uses (tests/klipper_module/stubs.py): what it says, when it asks the
worker again, and that nothing it does can leave it. The same module in real Klipper is
tests/test_klipper_module_real.py."""
from __future__ import annotations

import array
import ast
import base64
import logging
import os
import sys
from typing import Any

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "klipper_module"))
import stubs  # noqa: E402

MOD = stubs.load_module()


def b64(kind: str, values: list[Any]) -> str:
    return base64.b64encode(array.array(kind, values).tobytes()).decode()


def answer(request_id: int, total: float = 100., objects: bool = False,
           source: str = "estimate") -> dict[str, Any]:
    """A worker answer: 1000 bytes of file, time linear in bytes, two objects."""
    doc: dict[str, Any] = {
        "id": request_id, "ok": True, "source": source, "total_s": total,
        "offsets_b64": b64("q", [0, 500, 1000]),
        "times_b64": b64("d", [0., total / 2, total])}
    if objects:
        # names as the file wrote them; Klipper says them upper-cased
        doc.update({"object_names": ["a", "B"], "object_offsets_b64": b64("q", [0, 500]),
                    "object_remaining_b64": b64("d", [60., 30., 40., 20.])})
    return doc


class FakeWorker:
    """Records requests instead of starting a process."""
    def __init__(self) -> None:
        self.requests: list[dict[str, Any]] = []

    def send(self, request: dict[str, Any]) -> None:
        self.requests.append(request)

    def close(self) -> None:
        pass


def printing(options: dict[str, str] | None = None) -> tuple[Any, stubs.Printer, FakeWorker]:
    """A module whose printer is printing /sd/x.gcode, its worker faked."""
    printer = stubs.Printer()
    kest = MOD.load_config(stubs.Config(printer, options))
    printer.send_event("klippy:ready")
    worker = FakeWorker()
    kest.worker = worker
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = "/sd/x.gcode", True
    printer.objects["print_stats"].state = "printing"
    printer.reactor.run_timers()
    return kest, printer, worker


def test_print_start_asks_the_worker_for_the_file_with_the_printers_config() -> None:
    kest, printer, worker = printing()
    assert worker.requests == [{"id": 1, "file": "/sd/x.gcode", "config": "/tmp/printer.cfg",
                                "events": [], "use_table": True, "encoding": "b64"}]
    assert kest.get_status(0.)["state"] == "estimating"


def test_remaining_is_the_tables_time_left_plus_what_klipper_has_queued() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position = 500        # table: 50 s done, 50 s left
    toolhead.lookahead.queue.append(stubs.Move())
    printer.reactor.advance(1.)
    toolhead.plan(40.)   # the moves before byte 500 end at print_time 40
    toolhead.mcu.est = 38.5        # the head is 1.5 s behind them
    printer.reactor.advance(1.)    # (no moves queued now: anchor at print_time 40)
    status = kest.get_status(0.)
    assert status["remaining_s"] == pytest.approx(50. + 1.5)
    assert status["progress"] == pytest.approx(1. - 51.5 / 100.)
    assert status["source"] == "estimate" and status["total_s"] == 100.


def test_paused_time_does_not_count_and_the_eta_moves_with_it() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position = 500
    toolhead.print_time = 60.
    printer.reactor.advance(1.)
    vsd.active = False
    printer.objects["print_stats"].state = "paused"
    toolhead.mcu.est = 200.        # long after the last move
    printer.reactor.advance(1.)
    first = kest.get_status(0.)
    printer.reactor.advance(30.)
    later = kest.get_status(0.)
    assert first["remaining_s"] == later["remaining_s"] == pytest.approx(50.)
    assert later["eta"] > first["eta"]


def test_a_console_M220_is_an_event_at_the_file_position_and_a_new_estimate() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    vsd = printer.objects["virtual_sdcard"]
    vsd.file_position = 700
    printer.gcode.run("M220", S="150")
    assert printer.objects["gcode_move"].speed_factor == 1.5
    assert worker.requests[-1]["events"] == [[700, "M220 S150"]]
    assert worker.requests[-1]["use_table"] is False
    # Until the exact answer the remaining time is scaled, and said to be provisional.
    printer.objects["toolhead"].print_time = 70.
    printer.objects["toolhead"].mcu.est = 70.     # nothing queued ahead of the head
    printer.reactor.advance(1.)
    status = kest.get_status(0.)
    assert status["source"] == "provisional"
    assert status["remaining_s"] == pytest.approx(50. / 1.5, abs=1e-3)
    kest.on_answer(answer(2, total=80.))
    printer.reactor.advance(1.)
    assert kest.get_status(0.)["remaining_s"] == pytest.approx(40.)


def test_an_M220_from_the_file_is_already_in_the_estimate() -> None:
    kest, printer, worker = printing()
    vsd = printer.objects["virtual_sdcard"]
    vsd.cmd_from_sd = True
    printer.gcode.run("M220", S="50")
    assert len(worker.requests) == 1


def test_excluding_an_object_drops_its_time_at_once_then_asks_for_the_exact_one() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1, objects=True))
    vsd = printer.objects["virtual_sdcard"]
    vsd.file_position = 600
    printer.objects["toolhead"].print_time = printer.objects["toolhead"].mcu.est = 10.
    printer.gcode.respond_info("Excluding object B")
    assert worker.requests[-1]["events"] == [[600, "EXCLUDE_OBJECT NAME=B"]]
    printer.reactor.advance(1.)
    status = kest.get_status(0.)
    assert status["remaining_s"] == pytest.approx(50. - 20.)
    assert status["objects"] == {"a": 30., "B": 0.}
    assert status["excluded_objects"] == ["B"]
    printer.gcode.respond_info("Unexcluding object B")
    assert worker.requests[-1]["events"][-1] == [600, "EXCLUDE_OBJECT RESET=1 NAME=B"]


def test_the_progress_M73_sets_follows_klipper_time_even_after_the_files_M73() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    vsd = printer.objects["virtual_sdcard"]
    vsd.file_position = 900
    printer.objects["toolhead"].print_time = printer.objects["toolhead"].mcu.est = 5.
    printer.reactor.advance(1.)
    display = printer.objects["display_status"]
    assert display.progress == pytest.approx(0.5)
    vsd.cmd_from_sd = True
    printer.gcode.run("M73", P="12")      # the file's own, sliced before any change
    assert display.progress == pytest.approx(0.5)


def test_set_progress_off_leaves_display_status_alone() -> None:
    kest, printer, worker = printing({"set_progress": "false"})
    kest.on_answer(answer(1))
    printer.objects["virtual_sdcard"].file_position = 900
    printer.reactor.advance(1.)
    printer.gcode.run("M73", P="12")
    assert printer.objects["display_status"].progress == pytest.approx(0.12)


def test_an_error_disables_the_module_with_one_log_line_and_klipper_goes_on(
        caplog: pytest.LogCaptureFixture) -> None:
    kest, printer, worker = printing()
    kest.on_answer({"id": 1, "ok": True, "total_s": 5.})   # a table without points
    assert kest.disabled
    status = kest.get_status(0.)
    assert "table without points" in status["error"]
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "kestimator" in errors[0].getMessage()
    # Klipper's own M220 and M73 still run; the timer stopped.
    printer.gcode.run("M220", S="50")
    assert printer.objects["gcode_move"].speed_factor == 0.5
    printer.gcode.run("M73", P="40")
    assert printer.objects["display_status"].progress == pytest.approx(0.4)
    printer.reactor.advance(1.)
    assert all(t.waketime == printer.reactor.NEVER for t in printer.reactor.timers)


def test_a_failed_estimate_is_said_in_the_status_and_nothing_else_changes() -> None:
    kest, printer, worker = printing()
    kest.on_answer({"id": 1, "ok": False, "error": "x.gcode:3: bad"})
    assert not kest.disabled
    assert kest.get_status(0.)["error"] == "estimate failed: x.gcode:3: bad"


def test_an_old_answer_is_dropped_for_the_newest_request() -> None:
    kest, printer, worker = printing()
    printer.objects["virtual_sdcard"].file_position = 100
    printer.gcode.run("M220", S="200")
    kest.on_answer(answer(1, total=100.))
    assert kest.table is None
    kest.on_answer(answer(2, total=50.))
    assert kest.table.total_s == 50.


def test_events_are_bounded() -> None:
    kest, printer, worker = printing()
    for k in range(MOD.MAX_EVENTS):
        printer.gcode.run("M220", S=str(100 + k))
    assert not kest.disabled
    printer.gcode.run("M220", S="50")
    assert kest.disabled and "changes in one print" in kest.get_status(0.)["error"]


def test_a_new_print_starts_over() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    printer.send_event("virtual_sdcard:reset_file")
    printer.objects["virtual_sdcard"].path = "/sd/y.gcode"
    printer.reactor.advance(1.)
    assert worker.requests[-1]["file"] == "/sd/y.gcode"
    assert kest.table is None


def test_table_time_is_the_last_point_at_or_before_the_position() -> None:
    table = MOD.Table(answer(1, total=100.))
    assert table.time_at(0) == 0. and table.time_at(250) == 0. and table.time_at(500) == 50.
    assert table.time_at(5000) == 100. and table.time_at(-1) == 0.


def test_the_module_imports_only_the_standard_library() -> None:
    with open(stubs.MODULE_PATH) as f:
        tree = ast.parse(f.read())
    names = {alias.name.split(".")[0] for node in ast.walk(tree)
             if isinstance(node, ast.Import) for alias in node.names}
    names |= {node.module.split(".")[0] for node in ast.walk(tree)
              if isinstance(node, ast.ImportFrom) and node.module}
    assert names <= set(sys.stdlib_module_names)


def test_the_real_worker_answers_through_the_reactors_fd_callback(tmp_path: Any) -> None:
    """The module starts `python -m kestimator.worker` and reads its answer only when the
    reactor says the pipe is readable."""
    gcode = tmp_path / "x.gcode"
    gcode.write_text("G28\nG1 X10 F600\nG1 X20\nG1 X0 Y30\n")
    printer = stubs.Printer(config_file="")
    kest = MOD.load_config(stubs.Config(printer, {"python": sys.executable}))
    printer.send_event("klippy:ready")
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = str(gcode), True
    printer.objects["print_stats"].state = "printing"
    try:
        printer.reactor.run_timers()
        printer.reactor.pump_fds(lambda: kest.table is not None or kest.error is not None)
        assert kest.error is None and kest.table is not None
        # 10 mm at 10 mm/s and the rest; the start of line 3 is after the first move
        assert kest.table.total_s > 1.0
        printer.reactor.advance(1.)
        assert kest.get_status(0.)["remaining_s"] == pytest.approx(kest.table.total_s, abs=1e-3)
    finally:
        kest._stop_worker()


def test_without_kestimator_the_status_says_so_and_klipper_goes_on(tmp_path: Any) -> None:
    """A Python that cannot run the worker (kestimator not there): the module says so in
    its status and klippy.log, and stays out of the way."""
    gcode = tmp_path / "x.gcode"
    gcode.write_text("G1 X10 F600\n")
    bare = tmp_path / "python"
    bare.write_text("#!/bin/sh\nexit 1\n")
    bare.chmod(0o755)
    printer = stubs.Printer()
    kest = MOD.load_config(stubs.Config(printer, {"python": str(bare)}))
    printer.send_event("klippy:ready")
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = str(gcode), True
    printer.objects["print_stats"].state = "printing"
    printer.reactor.run_timers()
    printer.reactor.pump_fds(lambda: kest.error is not None, timeout=30.)
    assert kest.error == "the kestimator worker stopped (python: %s)" % bare
    assert not kest.disabled and kest.worker is None
    printer.gcode.run("M220", S="50")
    assert printer.objects["gcode_move"].speed_factor == 0.5


def test_a_speed_factor_set_before_the_print_is_in_its_estimate() -> None:
    printer = stubs.Printer()
    kest = MOD.load_config(stubs.Config(printer))
    printer.send_event("klippy:ready")
    kest.worker = worker = FakeWorker()
    printer.gcode.run("M220", S="150")
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = "/sd/x.gcode", True
    printer.reactor.run_timers()
    assert worker.requests[-1]["events"] == [[0, "M220 S150"]]
    assert worker.requests[-1]["use_table"] is False


def test_a_late_answer_for_an_earlier_print_is_not_taken_for_this_ones() -> None:
    kest, printer, worker = printing()
    printer.send_event("virtual_sdcard:reset_file")
    printer.objects["virtual_sdcard"].path = "/sd/y.gcode"
    printer.reactor.advance(1.)
    kest.on_answer(answer(1))                       # x.gcode's, arriving late
    assert kest.table is None
    kest.on_answer(answer(worker.requests[-1]["id"]))
    assert kest.table is not None


def test_the_checkout_runs_the_worker_where_kestimator_is_not_installed(
        tmp_path: Any) -> None:
    """Klipper's own Python (no kestimator installed) runs the worker from this checkout,
    the module's file being a link into it."""
    import subprocess

    base = os.path.join(sys.base_prefix, "bin", "python3")
    probe = subprocess.run([base, "-c", "import kestimator"], capture_output=True, cwd="/")
    if probe.returncode == 0:
        pytest.skip("the base Python has kestimator installed")
    gcode = tmp_path / "x.gcode"
    gcode.write_text("G28\nG1 X10 F600\n")
    printer = stubs.Printer(config_file="")
    kest = MOD.load_config(stubs.Config(printer, {"python": base}))
    printer.send_event("klippy:ready")
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = str(gcode), True
    try:
        printer.reactor.run_timers()
        printer.reactor.pump_fds(lambda: kest.table is not None or kest.error is not None)
        assert kest.error is None and kest.table is not None
    finally:
        kest._stop_worker()


def test_a_console_velocity_limit_is_estimated_again_as_typed() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    printer.objects["virtual_sdcard"].file_position = 300
    printer.gcode.run("SET_VELOCITY_LIMIT", ACCEL="1000")
    assert printer.accel == 1000.
    assert worker.requests[-1]["events"] == [[300, "SET_VELOCITY_LIMIT ACCEL=1000"]]
    printer.reactor.advance(1.)
    assert kest.get_status(0.)["source"] == "provisional"
    printer.objects["virtual_sdcard"].cmd_from_sd = True
    printer.gcode.run("SET_VELOCITY_LIMIT", ACCEL="2000")   # the file's own: estimated
    assert len(worker.requests) == 2


def test_a_cancelled_print_has_no_remaining_time() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    printer.reactor.advance(1.)
    assert kest.get_status(0.)["remaining_s"] is not None
    printer.objects["print_stats"].state = "cancelled"
    printer.objects["virtual_sdcard"].active = False
    printer.reactor.advance(1.)
    status = kest.get_status(0.)
    assert status["state"] == "cancelled"
    assert status["remaining_s"] is None and status["progress"] is None


def test_the_python_option_may_start_with_a_tilde() -> None:
    printer = stubs.Printer()
    kest = MOD.load_config(stubs.Config(printer, {"python": "~/kestimator/.venv-host/bin/python"}))
    assert kest.python == os.path.expanduser("~/kestimator/.venv-host/bin/python")
