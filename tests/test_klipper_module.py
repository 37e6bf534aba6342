"""The Klipper module (the package plugins/klipper/kestimator/) with Klipper's objects stubbed at
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
import time
from typing import Any

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "klipper_module"))
import stubs  # noqa: E402

from tests.conftest import CORPUS, CORPUS_CFG  # noqa: E402

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
    unsent = b""

    def __init__(self) -> None:
        self.requests: list[dict[str, Any]] = []
        self.killed = False

    def send(self, request: dict[str, Any]) -> None:
        self.requests.append(request)

    def close(self, kill: bool = False) -> None:
        self.killed = kill


def printing(options: dict[str, str] | None = None, software_version: str | None = None,
             printer: stubs.Printer | None = None, path: str = "/sd/x.gcode"
             ) -> tuple[Any, stubs.Printer, FakeWorker]:
    """A module whose printer is printing `path`, its worker faked; `software_version`
    the Klipper's start args report."""
    printer = printer or stubs.Printer()
    if software_version is not None:
        printer.start_args["software_version"] = software_version
    kest = MOD.load_config(stubs.Config(printer, options))
    printer.send_event("klippy:ready")
    kest._stop_worker()            # the one started at klippy:ready
    worker = FakeWorker()
    kest.worker = worker
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = path, True
    printer.objects["print_stats"].state = "printing"
    printer.reactor.run_timers()
    return kest, printer, worker


def test_print_start_asks_the_worker_for_the_file_with_the_printers_config_and_version(
        ) -> None:
    kest, printer, worker = printing(software_version="v0.13.0-730-g84104bbbd")
    assert worker.requests == [{"id": 1, "file": "/sd/x.gcode", "config": "/tmp/printer.cfg",
                                "events": [], "use_table": True, "encoding": "b64",
                                "klipper_version": "v0.13.0-730-g84104bbbd"}]
    assert kest.get_status(0.)["state"] == "estimating"


@pytest.mark.parametrize("software_version", [None, "?", "", 12])
def test_a_klipper_that_does_not_report_its_version_sends_none(software_version: Any) -> None:
    """Absent, or Klipper's own "?" (a tree without git): the user's settings decide."""
    printer = stubs.Printer()
    if software_version is not None:
        printer.start_args["software_version"] = software_version
    kest, printer, worker = printing(printer=printer)
    assert "klipper_version" not in worker.requests[0]


def test_kalico_sends_its_version_with_its_name_first_as_printer_info_has_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Kalico's klippy package names itself (klippy/__init__.py APP_NAME = "Kalico") and its
    start args hold the bare git version."""
    package = type(sys)("kalico_klippy")
    package.APP_NAME = "Kalico"  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "kalico_klippy", package)
    kalico_printer = type("Printer", (stubs.Printer,), {"__module__": "kalico_klippy.printer"})
    kest, printer, worker = printing(software_version="v2026.07.00-0-g30c65e09",
                                     printer=kalico_printer())
    assert worker.requests[0]["klipper_version"] == "Kalico v2026.07.00-0-g30c65e09"


def test_a_v0_12_0_klipper_gets_v0_12_0s_times_from_the_worker(
        tmp_path: Any, monkeypatch: pytest.MonkeyPatch, corpus_root: Any) -> None:
    """The module in Klipper v0.12.0 sends its version; the worker estimates with v0.12.0's
    semantics (max_accel_to_decel absolute, its junction and print-time rules): real
    v0.12.0's own time (tests/oracle_refs_releases/klipper-v0.12.0) on a file that changes
    the acceleration, 12.9 s away from what the same config gives without it. A version the
    printer.cfg names wins over the running Klipper's."""
    import json

    from kestimator import worker as worker_module
    for key, folder in (("HOME", ""), ("XDG_CONFIG_HOME", "config"),
                        ("XDG_CACHE_HOME", "cache")):
        monkeypatch.setenv(key, str(tmp_path / folder))
    v0_12 = os.path.join(os.path.dirname(os.path.abspath(__file__)), "oracle_refs_releases",
                         "klipper-v0.12.0")
    with open(os.path.join(v0_12, "accelctl_orca1.5.0_klipper_m204.json")) as f:
        ref = json.load(f)
    kest, printer, fake = printing(
        software_version="v0.12.0-0-g0d67d9c4", path=str(corpus_root / ref["file"]),
        printer=stubs.Printer(config_file=os.path.join(v0_12, "printer.cfg")))
    (request,) = fake.requests
    assert request["klipper_version"] == "v0.12.0-0-g0d67d9c4"

    def total(req: dict[str, Any]) -> float:
        doc = worker_module.handle(json.dumps(req).encode())
        assert doc["ok"], doc
        return float(doc["total_s"])

    with_version = total(request)
    without = total({k: v for k, v in request.items() if k != "klipper_version"})
    named = tmp_path / "named.cfg"
    with open(request["config"]) as f:
        named.write_text("# kestimator: klipper_version = v0.12.0-119-g0105aa330\n" + f.read())
    user_named = total(dict(request, config=str(named)))
    want = float(ref["total_s"])
    assert abs(with_version - want) <= 0.01 + 1e-6 * want, (with_version, want)
    assert want - without > 10.0
    # v0.12.0-119 turns max_accel_to_decel into minimum_cruise_ratio: another time.
    assert abs(user_named - with_version) > 1.0


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
    first = kest.get_status(printer.reactor.monotonic())
    printer.reactor.advance(30.)
    later = kest.get_status(printer.reactor.monotonic())
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
    # keyed as Klipper names them (upper-cased), to be joined to exclude_object's status
    assert status["objects"] == {"A": 30., "B": 0.}
    assert status["excluded_objects"] == ["B"]
    kest.on_answer(answer(2, objects=True))
    printer.gcode.respond_info("Unexcluding object B")
    assert worker.requests[-1]["events"][-1] == [600, "EXCLUDE_OBJECT RESET=1 NAME=B"]


def test_display_status_progress_makes_duration_over_progress_the_remaining_time() -> None:
    """Mainsail's "file" estimate is D / progress - D with D the print duration: with
    progress D / (D + R) in the same status cycle, that is R, the module's time."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    vsd = printer.objects["virtual_sdcard"]
    vsd.file_position = 500                   # 50 s left by the table
    printer.objects["toolhead"].print_time = printer.objects["toolhead"].mcu.est = 5.
    printer.objects["print_stats"].print_duration = 30.
    printer.reactor.advance(1.)
    display = printer.objects["display_status"]
    progress = display.get_status(0.)["progress"]
    assert progress == pytest.approx(30. / 80.)
    assert 30. / progress - 30. == pytest.approx(kest.get_status(0.)["remaining_s"])
    vsd.cmd_from_sd = True
    printer.gcode.run("M73", P="12")      # the file's own, sliced before any change
    assert display.get_status(0.)["progress"] == pytest.approx(30. / 80.)
    # Paused: the duration stands still, and so does the progress (no expiry).
    printer.objects["print_stats"].state = "paused"
    printer.reactor.advance(30.)
    assert display.get_status(0.)["progress"] == pytest.approx(30. / 80.)


def test_set_progress_off_leaves_display_status_alone() -> None:
    kest, printer, worker = printing({"set_progress": "false"})
    kest.on_answer(answer(1))
    printer.objects["virtual_sdcard"].file_position = 900
    printer.reactor.advance(1.)
    printer.gcode.run("M73", P="12")
    display = printer.objects["display_status"]
    assert display.get_status(0.)["progress"] == pytest.approx(0.12)
    assert "get_status" not in vars(display)


def test_an_error_disables_the_module_with_one_log_line_and_klipper_goes_on(
        caplog: pytest.LogCaptureFixture) -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))

    def broken(eventtime: float) -> dict[str, Any]:
        raise KeyError("state")
    printer.objects["print_stats"].get_status = broken     # an error in an update
    printer.reactor.advance(1.)
    assert kest.disabled
    status = kest.get_status(0.)
    assert status["error"] == "KeyError: 'state'"
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
    """Past MAX_EVENTS changes (at different file positions) the print is no longer
    followed, and the status says so; the module goes on for the next print."""
    kest, printer, worker = printing()
    vsd = printer.objects["virtual_sdcard"]
    for k in range(MOD.events.MAX_EVENTS):
        vsd.file_position = k
        printer.gcode.run("M220", S=str(100 + k))
    assert not kest.disabled and kest.failed is None
    vsd.file_position += 1
    printer.gcode.run("M220", S="50")
    printer.reactor.advance(1.)
    status = kest.get_status(0.)
    assert "changes in one print" in status["error"] and status["state"] == "error"
    assert status["remaining_s"] is None and not kest.disabled
    assert len(kest.events) == MOD.events.MAX_EVENTS


def test_speed_changes_at_one_file_position_are_one_event() -> None:
    """A macro loop of M220s runs between two lines: only the last factor counts."""
    kest, printer, worker = printing()
    printer.objects["virtual_sdcard"].file_position = 300
    for k in range(2 * MOD.events.MAX_EVENTS):
        printer.gcode.run("M220", S=str(50 + k))
    printer.gcode.run("SET_VELOCITY_LIMIT", ACCEL="1000")
    printer.gcode.run("SET_VELOCITY_LIMIT", ACCEL="1000")
    assert kest.failed is None and kest.events == [
        (300, "M220 S%d" % (50 + 2 * MOD.events.MAX_EVENTS - 1)),
        (300, "SET_VELOCITY_LIMIT ACCEL=1000")]


def test_a_new_print_starts_over() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    printer.send_event("virtual_sdcard:reset_file")
    printer.objects["virtual_sdcard"].path = "/sd/y.gcode"
    printer.reactor.advance(1.)
    assert worker.requests[-1]["file"] == "/sd/y.gcode"
    assert kest.table is None


def test_table_time_is_the_last_point_at_or_before_the_position() -> None:
    table = MOD.table.Table(answer(1, total=100.))
    assert table.time_at(0) == 0. and table.time_at(250) == 0. and table.time_at(500) == 50.
    assert table.time_at(5000) == 100. and table.time_at(-1) == 0.


def test_the_module_is_a_package_of_files_under_400_lines_with_load_config_in_init() -> None:
    """Shaped as klippy's extras packages (extras/display/): __init__.py holds
    `load_config` and imports, every other file one concern under 400 lines, and the
    hooks taken from Klipper listed in one file."""
    files = sorted(name for name in os.listdir(stubs.PACKAGE_PATH) if name.endswith(".py"))
    assert "__init__.py" in files and len(files) > 2
    for name in files:
        with open(os.path.join(stubs.PACKAGE_PATH, name)) as f:
            assert len(f.read().splitlines()) < 400, name
    with open(os.path.join(stubs.PACKAGE_PATH, "__init__.py")) as f:
        tree = ast.parse(f.read())
    defined = [node for node in tree.body
               if not isinstance(node, (ast.Import, ast.ImportFrom, ast.Expr))]
    assert [(type(node), getattr(node, "name", None)) for node in defined] == [
        (ast.FunctionDef, "load_config")]
    assert MOD.load_config is not None and not hasattr(MOD, "load_config_prefix")
    holders = []
    for name in files:
        with open(os.path.join(stubs.PACKAGE_PATH, name)) as f:
            if "KLIPPER_HOOKS: " in f.read():
                holders.append(name)
    assert holders == ["hooks.py"]


def test_the_module_imports_only_the_standard_library_and_its_own_files() -> None:
    files = sorted(name for name in os.listdir(stubs.PACKAGE_PATH) if name.endswith(".py"))
    own = {name[:-3] for name in files}
    for name in files:
        with open(os.path.join(stubs.PACKAGE_PATH, name)) as f:
            tree = ast.parse(f.read())
        names = {alias.name.split(".")[0] for node in ast.walk(tree)
                 if isinstance(node, ast.Import) for alias in node.names}
        names |= {node.module.split(".")[0] for node in ast.walk(tree)
                  if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module}
        assert names <= set(sys.stdlib_module_names), name
        # Its own files by relative imports only (`from . import x`, `from .x import y`):
        # Klipper imports the package as extras.kestimator, Kalico as
        # klippy.extras.kestimator.
        relative = {node.module or alias.name for node in ast.walk(tree)
                    if isinstance(node, ast.ImportFrom) and node.level > 0
                    for alias in node.names}
        assert all(node.level in (0, 1) for node in ast.walk(tree)
                   if isinstance(node, ast.ImportFrom)), name
        assert relative <= own, name


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
    assert kest.error.startswith("the kestimator worker stopped (python: %s): " % bare)
    assert not kest.disabled and kest.worker is None
    printer.gcode.run("M220", S="50")
    assert printer.objects["gcode_move"].speed_factor == 0.5


def test_a_speed_factor_set_before_the_print_is_in_its_estimate() -> None:
    printer = stubs.Printer()
    kest = MOD.load_config(stubs.Config(printer))
    printer.send_event("klippy:ready")
    kest._stop_worker()
    kest.worker = worker = FakeWorker()
    printer.gcode.run("M220", S="150")
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = "/sd/x.gcode", True
    printer.reactor.run_timers()
    assert worker.requests[-1]["events"] == [[0, "M220 S150"]]
    assert worker.requests[-1]["use_table"] is False


def test_a_new_print_stops_the_worker_busy_with_the_last_and_asks_a_fresh_one(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """x.gcode's estimate is still running when y.gcode starts: that worker is killed (its
    answer is of no use) and y's request goes at once to a new one, not counted as a
    restart; an answer for x arriving late all the same is not taken for y's."""
    kest, printer, worker = printing()
    fresh = FakeWorker()
    monkeypatch.setattr(MOD.estimates, "Worker", lambda *args, **kw: fresh)
    printer.send_event("virtual_sdcard:reset_file")
    assert worker.killed and kest.worker is fresh
    printer.objects["virtual_sdcard"].path = "/sd/y.gcode"
    printer.reactor.advance(1.)
    assert [r["file"] for r in fresh.requests] == ["/sd/y.gcode"]
    assert kest.restarts == 0
    kest.on_answer(answer(1))                       # x.gcode's, arriving late
    assert kest.table is None
    kest.on_answer(answer(fresh.requests[-1]["id"]))
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


# Issue 33: nothing that arrives can reach Klipper's reactor, the status never lies,
# and every callback stays short.

FAKE_WORKER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "klipper_module",
                           "fake_worker.py")


def fake_python(tmp_path: Any, mode: str) -> str:
    """A `python` for the module's option that runs tests/klipper_module/fake_worker.py."""
    path = tmp_path / ("python-" + mode)
    path.write_text("#!/bin/sh\nexec '%s' '%s' %s\n" % (sys.executable, FAKE_WORKER, mode))
    path.chmod(0o755)
    return str(path)


def start_print(printer: stubs.Printer, path: str = "/sd/x.gcode") -> None:
    vsd = printer.objects["virtual_sdcard"]
    vsd.path, vsd.active = path, True
    printer.objects["print_stats"].state = "printing"
    printer.reactor.run_timers()


def unknown(status: dict[str, Any]) -> bool:
    """Nothing about the time is claimed."""
    return (status["remaining_s"] is None and status["progress"] is None
            and status["eta"] is None and status["total_s"] is None
            and status["source"] is None and status["objects"] == {})


def test_an_oversized_answer_never_reaches_the_reactor_and_is_not_accumulated(
        tmp_path: Any) -> None:
    printer = stubs.Printer(config_file="")
    kest = MOD.load_config(stubs.Config(printer, {"python": fake_python(tmp_path, "huge")}))
    printer.send_event("klippy:ready")
    start_print(printer, str(tmp_path / "x.gcode"))
    worker = kest.worker
    longest = [0]

    def until() -> bool:
        if kest.worker is not None:
            longest[0] = max(longest[0], len(kest.worker.buf))
        return kest.error is not None
    try:
        printer.reactor.pump_fds(until)   # raises if the fd callback lets anything out
        assert "too large" in kest.error
        assert longest[0] <= MOD.worker.MAX_ANSWER_BYTES
        assert not kest.disabled and unknown(kest.get_status(0.))
        # refused, not retried: the same request would get the same answer
        assert kest.worker is worker
    finally:
        kest._stop_worker()


def test_a_line_that_is_not_json_never_reaches_the_reactor(tmp_path: Any) -> None:
    printer = stubs.Printer(config_file="")
    kest = MOD.load_config(stubs.Config(printer, {"python": fake_python(tmp_path, "garbage")}))
    printer.send_event("klippy:ready")
    start_print(printer, str(tmp_path / "x.gcode"))
    try:
        printer.reactor.pump_fds(lambda: kest.error is not None)
        assert "not JSON" in kest.error and "this is not JSON" in kest.error
        assert not kest.disabled and unknown(kest.get_status(0.))
    finally:
        kest._stop_worker()


def test_every_callback_the_module_registers_is_guarded() -> None:
    """An exception inside any of them disables the module; none leaves it."""
    kest, printer, worker = printing()
    kest.on_answer(answer(1))

    def boom(*args: Any) -> Any:
        raise RuntimeError("boom")
    printer.objects["print_stats"].get_status = boom
    printer.reactor.advance(1.)                  # the update timer
    assert kest.disabled and "boom" in kest.error
    for callbacks in printer.handlers.values():
        for callback in callbacks:
            callback()                          # event handlers: nothing leaves them
    printer.gcode.respond_info("Excluding object B")
    printer.gcode.run("M220", S="50")
    printer.gcode.run("KESTIMATOR_STATUS")


def test_after_an_error_the_status_says_what_is_no_longer_known() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1, objects=True))
    vsd = printer.objects["virtual_sdcard"]
    vsd.file_position = 600
    printer.reactor.advance(1.)
    display = printer.objects["display_status"]
    printer.gcode.run("M73", P="12")
    assert kest.get_status(0.)["remaining_s"] is not None
    assert display.get_status(0.)["progress"] != pytest.approx(0.12)
    printer.objects["toolhead"].mcu.estimated_print_time = None   # an error in an update
    printer.reactor.advance(1.)
    assert kest.disabled
    status = kest.get_status(0.)
    assert status["state"] == "error" and "TypeError" in status["error"]
    assert unknown(status)
    # display_status says Klipper's own again
    assert display.get_status(0.)["progress"] == pytest.approx(0.12)
    gcmd = printer.gcode.run("KESTIMATOR_STATUS")
    assert any("TypeError" in line for line in gcmd.responses)


def test_a_failed_re_estimate_clears_the_time_and_is_not_retried() -> None:
    kest, printer, worker = printing()
    kest.on_answer(answer(1))
    vsd = printer.objects["virtual_sdcard"]
    vsd.file_position = 500
    printer.reactor.advance(1.)
    printer.gcode.run("M220", S="150")
    printer.reactor.advance(1.)
    assert kest.get_status(0.)["source"] == "provisional"
    kest.on_answer({"id": 2, "ok": False, "error": "no such file: /sd/x.gcode"})
    printer.reactor.advance(1.)
    status = kest.get_status(0.)
    assert status["state"] == "error" and "no such file" in status["error"]
    assert unknown(status) and not kest.disabled
    printer.gcode.run("M220", S="120")
    printer.reactor.advance(30.)
    assert len(worker.requests) == 2


def test_a_worker_that_dies_is_restarted_with_a_back_off_a_bounded_number_of_times(
        tmp_path: Any, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    printer = stubs.Printer(config_file="")
    kest = MOD.load_config(stubs.Config(printer, {"python": fake_python(tmp_path, "die")}))
    printer.send_event("klippy:ready")
    start_print(printer, str(tmp_path / "x.gcode"))
    try:
        starts = []
        for _ in range(10):
            pid = kest.worker.proc.pid if kest.worker is not None else None
            if pid is not None and pid not in starts:
                starts.append(pid)
            printer.reactor.pump_fds(lambda: kest.worker is None, timeout=10.)
            assert "killed while estimating" in kest.error
            if "no more" in kest.error:
                break
            printer.reactor.advance(60.)
        assert len(starts) == 1 + MOD.estimates.MAX_RESTARTS    # klippy:ready's and the restarts
        assert unknown(kest.get_status(0.)) and kest.get_status(0.)["state"] == "error"
        restarts = [r for r in caplog.records if "restarting the worker" in r.getMessage()]
        assert len(restarts) == MOD.estimates.MAX_RESTARTS
    finally:
        kest._stop_worker()


def test_the_worker_starts_at_ready_not_in_a_timer(monkeypatch: pytest.MonkeyPatch,
                                                   tmp_path: Any) -> None:
    gcode = tmp_path / "x.gcode"
    gcode.write_text("G28\nG1 X10 F600\n")
    printer = stubs.Printer(config_file="")
    kest = MOD.load_config(stubs.Config(printer, {"python": sys.executable}))
    printer.send_event("klippy:ready")
    try:
        assert kest.worker is not None
        started = []
        real_popen = MOD.worker.subprocess.Popen
        monkeypatch.setattr(MOD.worker.subprocess, "Popen",
                            lambda *a, **k: started.append(a) or real_popen(*a, **k))
        start_print(printer, str(gcode))
        printer.reactor.pump_fds(lambda: kest.table is not None or kest.error is not None)
        assert kest.table is not None and started == []
    finally:
        kest._stop_worker()


def test_a_worker_that_cannot_start_says_why(tmp_path: Any) -> None:
    printer = stubs.Printer(config_file="")
    kest = MOD.load_config(stubs.Config(printer, {"python": fake_python(tmp_path,
                                                                        "stderr-exit")}))
    printer.send_event("klippy:ready")
    start_print(printer, str(tmp_path / "x.gcode"))
    try:
        printer.reactor.pump_fds(lambda: kest.worker is None and kest.error is not None)
        assert "No module named 'kestimator'" in kest.error
        assert "No module named 'kestimator'" in kest.get_status(0.)["error"]
    finally:
        kest._stop_worker()


def test_a_worker_that_died_before_the_write_is_handled_not_raised(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Any) -> None:
    """The race behind the flaky test: the worker has exited when the request is written
    (BrokenPipeError). Here it always has."""
    real_popen = MOD.worker.subprocess.Popen

    def exited(*a: Any, **k: Any) -> Any:
        proc = real_popen(*a, **k)
        proc.wait()
        return proc
    monkeypatch.setattr(MOD.worker.subprocess, "Popen", exited)
    bare = tmp_path / "python"
    bare.write_text("#!/bin/sh\nexit 1\n")
    bare.chmod(0o755)
    printer = stubs.Printer()
    kest = MOD.load_config(stubs.Config(printer, {"python": str(bare)}))
    printer.send_event("klippy:ready")
    start_print(printer, str(tmp_path / "x.gcode"))
    try:
        printer.reactor.pump_fds(lambda: kest.error is not None, timeout=10.)
        assert not kest.disabled
        assert kest.error.startswith("the kestimator worker stopped (python: %s)" % bare)
    finally:
        kest._stop_worker()


def big_answer(request_id: int, **fields: Any) -> dict[str, Any]:
    doc = answer(request_id, objects=True)
    doc.update(fields)
    return doc


@pytest.mark.parametrize("case", [
    "objects", "names", "points", "object_points", "long_name", "oversized_b64"])
def test_answers_beyond_the_workers_own_limits_are_refused_in_a_short_callback(
        case: str) -> None:
    kest, printer, worker = printing()
    n = {"objects": MOD.table.MAX_OBJECTS + 1, "names": 200000}.get(case)
    if n is not None:
        doc = big_answer(1, object_names=["o%d" % i for i in range(n)],
                         object_offsets_b64=b64("q", [0]),
                         object_remaining_b64=b64("d", [1.] * n))
    elif case == "points":
        m = MOD.table.MAX_TIME_POINTS + 1
        doc = big_answer(1, offsets_b64=b64("q", list(range(m))),
                         times_b64=b64("d", [i / m for i in range(m)]), total_s=1.)
    elif case == "object_points":
        m = MOD.table.MAX_OBJECT_POINTS + 1
        doc = big_answer(1, object_offsets_b64=b64("q", list(range(m))),
                         object_remaining_b64=b64("d", [0.] * (2 * m)))
    elif case == "long_name":
        doc = big_answer(1, object_names=["a", "B" * 2700000])
    else:
        doc = big_answer(1, times_b64="A" * (16 << 20))
    printer.reactor.advance(1.)
    kest.max_callback_ms = 0.
    kest.on_answer(doc)
    printer.reactor.advance(1.)
    status = kest.get_status(0.)
    assert not kest.disabled and kest.table is None
    assert "refused" in status["error"] and unknown(status)
    assert len(repr(status)) < 5000
    assert kest.max_callback_ms < 50.


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("fields", [
    {"total_s": NAN}, {"total_s": INF}, {"total_s": -1.}, {"total_s": "100"},
    {"times_b64": b64("d", [0., NAN, 100.])}, {"times_b64": b64("d", [0., INF, 100.])},
    {"times_b64": b64("d", [-1., 50., 100.])}, {"times_b64": b64("d", [0., 60., 50.])},
    {"offsets_b64": b64("q", [0, 600, 500])}, {"offsets_b64": b64("q", [-5, 500, 1000])},
    {"object_remaining_b64": b64("d", [60., NAN, 40., 20.])},
    {"object_remaining_b64": b64("d", [60., 30., 40., -1.])},
    {"object_remaining_b64": b64("d", [160., 30., 40., 20.])},
    {"object_offsets_b64": b64("q", [500, 0])},
], ids=repr)
def test_values_from_the_worker_are_checked_before_they_are_used(
        fields: dict[str, Any]) -> None:
    kest, printer, worker = printing()
    kest.on_answer(big_answer(1, **fields))
    printer.reactor.advance(1.)
    status = kest.get_status(0.)
    assert not kest.disabled and kest.table is None
    assert "refused" in status["error"] and unknown(status)


class PipeWorker(FakeWorker):
    """The worker's real input pipe: a request that does not fit raises as os.write does."""
    def __init__(self) -> None:
        super().__init__()
        self.room = 64 << 10

    def send(self, request: dict[str, Any]) -> None:
        import json
        size = len(json.dumps(request)) + 1
        if size > self.room:
            raise BlockingIOError(11, "Resource temporarily unavailable")
        self.room -= size
        super().send(request)


def test_a_burst_of_console_speed_changes_asks_once_for_the_latest() -> None:
    kest, printer, worker = printing()
    kest.worker = worker = PipeWorker()
    kest.in_flight = None
    kest.pending_id = None
    kest._request()                       # the print's first request, in flight
    vsd = printer.objects["virtual_sdcard"]
    vsd.file_position = 500
    for k in range(300):                  # a macro loop: no file line in between
        printer.gcode.run("M220", S=str(100 + k))
    assert not kest.disabled and kest.error is None
    assert len(worker.requests) == 1      # nothing more while one is in flight
    kest.on_answer(answer(worker.requests[0]["id"]))
    assert len(worker.requests) == 2      # the superseded one is not used, one more asked
    assert kest.table is None
    assert worker.requests[-1]["events"] == [[500, "M220 S399"]]
    kest.on_answer(answer(worker.requests[-1]["id"], total=40.))
    assert kest.table.total_s == 40. and len(worker.requests) == 2


def test_names_with_a_quote_or_a_space_are_excluded_and_re_estimated(tmp_path: Any) -> None:
    """Klipper takes NAME="it's" and NAME='my part'; the event the worker runs through
    kestimator's interpreter names them the same, and their time goes."""
    import shlex
    lines = ["G28", "G90", "M83"]
    names = {"it's": '"it\'s"', "my part": "'my part'", "plain": "plain"}
    for i, quoted in enumerate(names.values()):
        lines.append("EXCLUDE_OBJECT_DEFINE NAME=%s CENTER=%d,%d" % (quoted, 40 * i, 40 * i))
    for layer in range(3):
        lines += [";LAYER_CHANGE", "G1 Z%.1f F600" % (0.2 + 0.2 * layer)]
        for i, quoted in enumerate(names.values()):
            lines.append("EXCLUDE_OBJECT_START NAME=%s" % quoted)
            lines += ["G1 X%d Y%d E0.5 F1200" % (40 * i + (k % 2) * 20, 40 * i + 2 * k)
                      for k in range(10)]
            lines.append("EXCLUDE_OBJECT_END NAME=%s" % quoted)
    gcode = tmp_path / "x.gcode"
    gcode.write_text("\n".join(lines) + "\n")
    first_layer = gcode.read_bytes().index(b";LAYER_CHANGE")
    for name in ("it's", "my part"):
        printer = stubs.Printer(config_file="")
        kest = MOD.load_config(stubs.Config(printer, {"python": sys.executable}))
        printer.send_event("klippy:ready")
        try:
            start_print(printer, str(gcode))
            printer.reactor.pump_fds(lambda k=kest: k.table is not None or k.error is not None)
            assert kest.error is None
            before = kest.table
            left = before.objects_at(first_layer)[name]
            assert left > 1.
            printer.objects["virtual_sdcard"].file_position = first_layer
            printer.gcode.respond_info("Excluding object %s" % name.upper())
            event = kest.events[-1][1]
            assert shlex.split(event) == ["EXCLUDE_OBJECT", "NAME=%s" % name.upper()]
            printer.reactor.pump_fds(
                lambda k=kest, b=before: k.table is not b or k.error is not None)
            assert kest.error is None and kest.table.source == "estimate"
            # (the object's time left is what its moves take; travel to it stays)
            assert (before.total_s - 1.05 * left < kest.table.total_s
                    < before.total_s - 0.5 * left)
        finally:
            kest._stop_worker()


def test_the_modules_limits_are_the_table_writers() -> None:
    """The module refuses what the worker's writer never writes, and nothing it writes."""
    from kestimator import progress_table, worker

    assert MOD.table.MAX_TIME_POINTS == progress_table.MAX_TABLE_POINTS
    assert MOD.table.MAX_OBJECT_POINTS == progress_table.MAX_OBJECT_POINTS
    assert MOD.table.MAX_OBJECTS == progress_table.MAX_OBJECTS
    assert MOD.table.MAX_NAME_CHARS >= progress_table.MAX_NAME_BYTES
    assert worker.MAX_ANSWER_BYTES < MOD.worker.MAX_ANSWER_BYTES


def _table_after(kest: Any, printer: stubs.Printer, path: str) -> float:
    """Seconds from the start of the print of `path` until the module has its table."""
    started = time.monotonic()
    start_print(printer, path)
    printer.reactor.pump_fds(lambda: kest.table is not None or kest.error is not None,
                             timeout=600.)
    assert kest.error is None and kest.table is not None, kest.error
    return time.monotonic() - started


def test_a_print_started_after_a_cancel_gets_its_time_without_waiting_for_the_last_file(
        tmp_path: Any) -> None:
    """A 40 MB file's print is cancelled while its file is being estimated and a 4-layer
    print starts: its time comes within 3 s of what its own estimate takes alone (the
    cancelled file's estimate, tens of seconds, is stopped)."""
    big = CORPUS / "gcode" / "prusaslicer" / "ps25_bunny120_fast_fwretract_large.gcode"
    small = CORPUS / "gcode" / "prusaslicer" / "ps25_nut_accelA_small.gcode"
    printer = stubs.Printer(config_file=str(CORPUS_CFG))
    kest = MOD.load_config(stubs.Config(printer, {"python": sys.executable}))
    printer.send_event("klippy:ready")
    try:
        alone = _table_after(kest, printer, str(small))
        printer.send_event("virtual_sdcard:reset_file")
        start_print(printer, str(big))
        printer.reactor.pump_fds(lambda: False, timeout=2.)  # the worker is reading it
        assert kest.in_flight is not None and kest.table is None
        busy = kest.worker.proc
        printer.objects["print_stats"].state = "cancelled"
        printer.objects["virtual_sdcard"].active = False
        printer.reactor.advance(1.)
        printer.send_event("virtual_sdcard:reset_file")
        after_cancel = _table_after(kest, printer, str(small))
        assert kest.path == str(small)
        assert after_cancel <= alone + 3.0, (after_cancel, alone)
        assert busy.wait(timeout=10) is not None  # the cancelled file's worker is gone
    finally:
        kest._stop_worker()


def stops_answer(request_id: int, **fields: Any) -> dict[str, Any]:
    """`answer` with two stops: M600 at byte 600 (line 30, 60 s) and PAUSE at byte 900
    (line 45, 90 s)."""
    doc = answer(request_id)
    doc.update({"stop_offsets": [600, 900], "stop_times": [60., 90.],
                "stop_commands": ["M600", "PAUSE"], "stop_lines": [30, 45]})
    doc.update(fields)
    return doc


def test_the_next_stop_is_the_tables_time_to_it_from_where_the_head_is() -> None:
    kest, printer, worker = printing()
    kest.on_answer(stops_answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position = 500        # table: 50 s done
    toolhead.lookahead.queue.append(stubs.Move())
    printer.reactor.advance(1.)
    toolhead.plan(40.)
    toolhead.mcu.est = 38.5        # the head 1.5 s behind the moves queued
    printer.reactor.advance(1.)
    now = printer.reactor.monotonic()
    status = kest.get_status(now)
    stop = status["next_stop"]
    assert (stop["command"], stop["line"]) == ("M600", 30)
    assert stop["in_s"] == pytest.approx(60. - 50. + 1.5)
    assert stop["eta"] == pytest.approx(status["eta"] - status["remaining_s"] + stop["in_s"])


def test_paused_at_a_stop_the_next_one_is_named_and_none_after_the_last() -> None:
    kest, printer, worker = printing()
    kest.on_answer(stops_answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position = 600        # the M600 line is next: still ahead
    toolhead.print_time = 60.
    toolhead.mcu.est = 59.
    printer.reactor.advance(1.)
    assert kest.get_status(printer.reactor.monotonic())["next_stop"]["command"] == "M600"
    vsd.file_position = 610        # M600 ran (PAUSE): the file is read past it
    vsd.active = False
    printer.objects["print_stats"].state = "paused"
    toolhead.mcu.est = 200.        # the head stands
    printer.reactor.advance(1.)
    first = kest.get_status(printer.reactor.monotonic())["next_stop"]
    printer.reactor.advance(30.)
    later = kest.get_status(printer.reactor.monotonic())["next_stop"]
    assert (first["command"], first["line"]) == ("PAUSE", 45)
    # (the table's time at byte 600 is its point at 500's: 50 s)
    assert first["in_s"] == later["in_s"] == pytest.approx(90. - 50.)  # stands while paused
    assert later["eta"] > first["eta"]
    vsd.file_position, vsd.active = 950, True
    printer.objects["print_stats"].state = "printing"
    toolhead.print_time, toolhead.mcu.est = 300., 299.
    printer.reactor.advance(1.)
    assert kest.get_status(printer.reactor.monotonic())["next_stop"] is None


def test_a_speed_change_scales_the_time_to_the_next_stop_until_estimated_again() -> None:
    kest, printer, worker = printing()
    kest.on_answer(stops_answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position = 500
    toolhead.print_time, toolhead.mcu.est = 50., 50.
    printer.reactor.advance(1.)
    printer.gcode.run("M220", S="200")
    stop = kest.get_status(printer.reactor.monotonic())["next_stop"]
    assert stop["in_s"] == pytest.approx((60. - 50.) / 2.)
    kest.on_answer(stops_answer(2, stop_times=[55., 70.]))
    stop = kest.get_status(printer.reactor.monotonic())["next_stop"]
    assert stop["in_s"] == pytest.approx(5.)


@pytest.mark.parametrize("bad", [
    {"stop_times": [90., 60.]}, {"stop_times": [60., 1000.]}, {"stop_offsets": [900, 600]},
    {"stop_offsets": [600]}, {"stop_commands": ["M600", "X" * 65]},
    {"stop_offsets": list(range(1001)), "stop_times": [1.] * 1001,
     "stop_commands": ["M600"] * 1001}, {"stop_offsets": [600, True]}])
def test_stops_from_the_worker_are_checked_before_they_are_used(bad: dict[str, Any]) -> None:
    kest, printer, worker = printing()
    kest.on_answer(stops_answer(1, **bad))
    status = kest.get_status(0.)
    assert status["state"] == "error" and status["next_stop"] is None
    assert "refused" in status["error"]


def test_display_next_stop_shows_the_time_to_it_but_never_over_the_users_message() -> None:
    kest, printer, worker = printing({"display_next_stop": "True"})
    kest.on_answer(stops_answer(1))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    display = printer.objects["display_status"]
    vsd.file_position = 500
    toolhead.print_time, toolhead.mcu.est = 50., 50.
    printer.reactor.advance(1.)
    assert display.message == "M600 in 10s"
    display.message = "Hello"      # the user's M117
    vsd.file_position = 950
    printer.reactor.advance(1.)
    assert display.message == "Hello"
    display.message = None         # the user's M117 with no text
    vsd.file_position = 700
    printer.reactor.advance(1.)
    assert display.message == "PAUSE in 40s"
    vsd.file_position = 950        # after the last stop: ours is cleared
    printer.reactor.advance(1.)
    assert display.message is None


def test_without_display_next_stop_the_display_message_is_left_alone() -> None:
    kest, printer, worker = printing()
    kest.on_answer(stops_answer(1))
    printer.objects["virtual_sdcard"].file_position = 500
    printer.reactor.advance(1.)
    assert printer.objects["display_status"].message is None
    assert kest.get_status(printer.reactor.monotonic())["next_stop"] is not None


def test_the_modules_stop_limits_are_the_table_writers() -> None:
    from kestimator import progress_table

    assert MOD.table.MAX_STOPS == progress_table.MAX_TABLE_STOPS
    assert MOD.table.MAX_STOP_COMMAND_CHARS == progress_table.MAX_STOP_COMMAND_BYTES


def test_after_resuming_from_a_stop_it_stays_behind() -> None:
    """Paused at the M600 with the head standing a little short of its time by the table,
    then resumed: the next stop is the PAUSE, from the moment it stood there on."""
    kest, printer, worker = printing()
    kest.on_answer(stops_answer(1, stop_times=[50.3, 90.]))
    toolhead, vsd = printer.objects["toolhead"], printer.objects["virtual_sdcard"]
    vsd.file_position = 610
    vsd.active = False
    printer.objects["print_stats"].state = "paused"
    toolhead.print_time, toolhead.mcu.est = 60., 200.
    printer.reactor.advance(1.)
    assert kest.get_status(printer.reactor.monotonic())["next_stop"]["command"] == "PAUSE"
    vsd.active = True
    printer.objects["print_stats"].state = "printing"
    toolhead.mcu.est = 201.
    printer.reactor.advance(0.5)
    stop = kest.get_status(printer.reactor.monotonic())["next_stop"]
    assert stop["command"] == "PAUSE"
