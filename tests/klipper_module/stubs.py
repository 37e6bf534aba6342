"""Klipper's objects, stubbed at the interfaces the kestimator module uses (klippy's
printer, reactor, gcode, toolhead, virtual_sdcard, print_stats, display_status,
gcode_move and configfile section), for tests that run without Klipper."""
from __future__ import annotations

import importlib.util
import os
import select
import sys
import time
from typing import Any, Callable

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PACKAGE_PATH = os.path.join(ROOT, "plugins", "klipper", "kestimator")
NAME = "klippy_extras_kestimator"


def load_module() -> Any:
    """plugins/klipper/kestimator/, loaded as Klipper loads an extras package (its
    __init__.py as a package, its files by their relative imports); loaded afresh each
    time. Its files are the package's attributes (`module.table.Table`)."""
    for name in [name for name in sys.modules if name == NAME or name.startswith(NAME + ".")]:
        del sys.modules[name]
    spec = importlib.util.spec_from_file_location(
        NAME, os.path.join(PACKAGE_PATH, "__init__.py"),
        submodule_search_locations=[PACKAGE_PATH])
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[NAME] = module
    spec.loader.exec_module(module)
    return module


class Timer:
    def __init__(self, callback: Callable[[float], float], waketime: float) -> None:
        self.callback = callback
        self.waketime = waketime


class Reactor:
    NOW = 0.
    NEVER = 9999999999999999.

    def __init__(self) -> None:
        self.now = 100.
        self.timers: list[Timer] = []
        self.fds: dict[int, Callable[[float], None]] = {}
        self.callbacks: list[Callable[[float], None]] = []

    def monotonic(self) -> float:
        return self.now

    def register_timer(self, callback: Callable[[float], float],
                       waketime: float = 9999999999999999.) -> Timer:
        timer = Timer(callback, waketime)
        self.timers.append(timer)
        return timer

    def update_timer(self, timer: Timer, waketime: float) -> None:
        timer.waketime = waketime

    def register_fd(self, fd: int, callback: Callable[[float], None]) -> int:
        self.fds[fd] = callback
        return fd

    def unregister_fd(self, handle: int) -> None:
        self.fds.pop(handle, None)

    def register_callback(self, callback: Callable[[float], None]) -> None:
        self.callbacks.append(callback)

    def run_timers(self) -> None:
        for timer in list(self.timers):
            if timer.waketime <= self.now:
                timer.waketime = timer.callback(self.now)

    def advance(self, seconds: float) -> None:
        self.now += seconds
        self.run_timers()

    def pump_fds(self, until: Callable[[], bool], timeout: float = 60.) -> None:
        """Run fd callbacks (what the reactor does) until `until()` or `timeout`."""
        end = time.monotonic() + timeout
        while not until() and time.monotonic() < end:
            if not self.fds:
                break
            ready, _, _ = select.select(list(self.fds), [], [], 0.05)
            for fd in ready:
                callback = self.fds.get(fd)
                if callback is not None:
                    callback(self.now)


class GCodeCommand:
    def __init__(self, params: dict[str, str], commandline: str = "") -> None:
        self.params = params
        self.commandline = commandline
        self.responses: list[str] = []

    def get_commandline(self) -> str:
        return self.commandline

    def get_float(self, name: str, default: Any = None) -> Any:
        return float(self.params[name]) if name in self.params else default

    def respond_info(self, msg: str) -> None:
        self.responses.append(msg)


class Mutex:
    """Klipper's ReactorMutex as gcode.get_mutex() gives it: held while a script runs."""

    def __init__(self) -> None:
        self.locked = False

    def test(self) -> bool:
        return self.locked


class GCode:
    def __init__(self) -> None:
        self.handlers: dict[str, Callable[[Any], None]] = {}
        self.outputs: list[Callable[[str], None]] = []
        self.mutex = Mutex()

    def get_mutex(self) -> Mutex:
        return self.mutex

    def register_command(self, name: str, func: Any, when_not_ready: bool = False,
                         desc: str | None = None) -> Any:
        if func is None:
            return self.handlers.pop(name, None)
        assert name not in self.handlers, name
        self.handlers[name] = func
        return None

    def register_output_handler(self, callback: Callable[[str], None]) -> None:
        self.outputs.append(callback)

    def respond_info(self, msg: str) -> None:
        for callback in self.outputs:
            callback("// " + msg)

    def run_script(self, script: str) -> None:
        """Klipper's gcode.run_script: each line's command with its KEY=VALUE words."""
        for line in script.split("\n"):
            words = line.split()
            if words and words[0].upper() in self.handlers:
                self.run(words[0].upper(), **dict(w.split("=", 1) for w in words[1:]))

    def run(self, name: str, **params: str) -> GCodeCommand:
        gcmd = GCodeCommand(params, " ".join([name] + ["%s=%s" % kv for kv in params.items()]))
        self.handlers[name](gcmd)
        return gcmd


class Move:
    def __init__(self) -> None:
        self.timing_callbacks: list[Callable[[float], None]] = []


class LookAhead:
    def __init__(self) -> None:
        self.queue: list[Move] = []

    def get_last(self) -> Move | None:
        return self.queue[-1] if self.queue else None

    def plan(self, end_print_time: float) -> None:
        """Flush: every queued move's callbacks with `end_print_time` (one move)."""
        for move in self.queue:
            for callback in move.timing_callbacks:
                callback(end_print_time)
        self.queue = []


class MCU:
    def __init__(self) -> None:
        self.est = 0.

    def estimated_print_time(self, eventtime: float) -> float:
        return self.est


class ToolHead:
    def __init__(self) -> None:
        self.lookahead = LookAhead()
        self.print_time = 0.
        self.mcu = MCU()
        self.limits = {"max_velocity": 300., "max_accel": 3000.,
                       "square_corner_velocity": 5., "minimum_cruise_ratio": .5}

    def get_status(self, eventtime: float) -> dict[str, Any]:
        return dict(self.limits, print_time=self.print_time)

    def plan(self, end_print_time: float) -> None:
        """The look-ahead flushed: its moves end at `end_print_time`, as print_time."""
        self.lookahead.plan(end_print_time)
        self.print_time = end_print_time


class VirtualSD:
    def __init__(self) -> None:
        self.path: str | None = None
        self.active = False
        self.cmd_from_sd = False
        self.file_position = 0
        self.next_file_position = 0

    def file_path(self) -> str | None:
        return self.path

    def is_active(self) -> bool:
        return self.active

    def is_cmd_from_sd(self) -> bool:
        return self.cmd_from_sd


class PrintStats:
    def __init__(self) -> None:
        self.state = "standby"
        self.print_duration = 0.

    def get_status(self, eventtime: float) -> dict[str, Any]:
        return {"state": self.state, "print_duration": self.print_duration}


class DisplayStatus:
    def __init__(self, gcode: GCode) -> None:
        self.progress: float | None = None
        self.message: str | None = None
        self.expire_progress = 0.
        gcode.register_command("M73", self.cmd_M73)

    def get_status(self, eventtime: float) -> dict[str, Any]:
        """As Klipper's: the M73 progress, else (here) 0; M117's message."""
        return {"progress": self.progress if self.progress is not None else 0.,
                "message": self.message}

    def cmd_M73(self, gcmd: GCodeCommand) -> None:
        progress = gcmd.get_float("P")
        if progress is not None:
            self.progress = progress / 100.


class GCodeMove:
    def __init__(self, gcode: GCode) -> None:
        self.speed_factor = 1.
        gcode.register_command("M220", self.cmd_M220)

    def cmd_M220(self, gcmd: GCodeCommand) -> None:
        self.speed_factor = gcmd.get_float("S", 100.) / 100.

    def get_status(self, eventtime: float) -> dict[str, Any]:
        return {"speed_factor": self.speed_factor}


class ConfigFile:
    """Klipper's configfile: the settings printer.cfg gave (here the toolhead's limits as
    they are when the stub starts)."""

    def __init__(self, limits: dict[str, float]) -> None:
        self.settings = {"printer": dict(limits)}

    def get_status(self, eventtime: float) -> dict[str, Any]:
        return {"settings": self.settings}


class Printer:
    def __init__(self, config_file: str = "/tmp/printer.cfg") -> None:
        self.reactor = Reactor()
        self.gcode = GCode()
        self.handlers: dict[str, list[Callable[..., Any]]] = {}
        self.start_args = {"config_file": config_file}
        self.objects: dict[str, Any] = {"gcode": self.gcode, "toolhead": ToolHead(),
                                        "virtual_sdcard": VirtualSD(),
                                        "print_stats": PrintStats()}
        self.objects["display_status"] = DisplayStatus(self.gcode)
        self.objects["gcode_move"] = GCodeMove(self.gcode)
        self.objects["configfile"] = ConfigFile(self.objects["toolhead"].limits)
        self.accel = 3000.
        self.gcode.register_command("SET_VELOCITY_LIMIT", self.cmd_SET_VELOCITY_LIMIT)

    def cmd_SET_VELOCITY_LIMIT(self, gcmd: GCodeCommand) -> None:
        """The toolhead's command (only ACCEL here)."""
        self.accel = gcmd.get_float("ACCEL", self.accel)
        self.objects["toolhead"].limits["max_accel"] = self.accel

    def get_reactor(self) -> Reactor:
        return self.reactor

    def get_start_args(self) -> dict[str, str]:
        return self.start_args

    def lookup_object(self, name: str, default: Any = "<required>") -> Any:
        if name in self.objects:
            return self.objects[name]
        if default == "<required>":
            raise KeyError(name)
        return default

    def lookup_objects(self, module: str | None = None) -> list[tuple[str, Any]]:
        return [(n, o) for n, o in self.objects.items() if module is None or n == module]

    def register_event_handler(self, event: str, callback: Callable[..., Any]) -> None:
        self.handlers.setdefault(event, []).append(callback)

    def send_event(self, event: str, *args: Any) -> None:
        for callback in self.handlers.get(event, []):
            callback(*args)


class Config:
    def __init__(self, printer: Printer, options: dict[str, str] | None = None) -> None:
        self.printer = printer
        self.options = options or {}

    def get_printer(self) -> Printer:
        return self.printer

    def get(self, name: str, default: Any = None) -> Any:
        return self.options.get(name, default)

    def getboolean(self, name: str, default: bool) -> bool:
        value = self.options.get(name)
        return default if value is None else value.lower() in ("1", "true", "yes")

    def getfloat(self, name: str, default: float, minval: float | None = None,
                 maxval: float | None = None) -> float:
        return float(self.options.get(name, default))
