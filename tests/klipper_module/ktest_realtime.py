"""A test-only Klipper extras module ([ktest_realtime]): batch-mode Klipper printing at
wall-clock speed, as a printer does, with the kestimator module left to itself.

Batch mode (klippy -i/-o) writes to a file instead of an MCU: its clock estimate is a
constant 0, and the toolhead and motion queuing never pause (can_pause is false), so a
whole print runs in a moment and the reactor runs timers only between lines. Here:

- the MCU's clock estimate (mcu.estimated_print_time) is the wall clock;
- the toolhead and motion queuing pause as on a printer (can_pause true), so
  virtual_sdcard waits inside a G1 (toolhead._check_pause) while the queue is full, and the
  reactor runs every timer there, the module's too;
- motion queuing's real background flush handler (_flush_handler) generates steps, not the
  batch-mode one (84104bbbd; v0.12.0, v0.13.0 and Kalico flush in the toolhead, whose
  flush timer is the real one once it may pause);
- G28 is the oracle's instant homing (ORACLE_HOME of ../shared/tools/oracle's probe, which
  is loaded beside this one: batch mode has no endstops); a heater wait with a target
  (M109/M190 S>0) waits for the moves, then `heat_wait` seconds of wall clock, as heating
  takes time on a printer;
- the status is read as Moonraker reads it: one subscription to Klipper's own
  objects/subscribe endpoint (webhooks.QueryStatusHelper), which asks every subscribed
  object's get_status() with one eventtime every 250 ms and sends what changed;
- commands are typed as Moonraker's console types them (gcode.run_script in a reactor
  callback), when the print reaches a fraction of the file or a time after the previous
  one ($KTEST_SCRIPT, JSON: [{"at": 0.4, "cmd": "M220 S150"}, {"after": 3, "cmd": ...}]).

Nothing calls the kestimator module's internals. When the print has ended and every move
has run, the results (JSON) go to $KTEST_OUT (84104bbbd asks at the end of its batch input,
gcode:debuginput_exit; the older releases and Kalico have no such event and end at once
there, so a timer asks too, and run_print.run_klippy holds their input open until the
results are written): the status stream, the commands typed, the
print_time at which the last move ended, the idle gaps (print_time re-synced after the
queue ran dry: a pause, a heater wait), the errors Klipper reported and the runout flushes.
"""
import json
import os
import time

SUBSCRIBE = {
    "print_stats": None, "display_status": None, "virtual_sdcard": None,
    "kestimator": None, "gcode_move": ["speed_factor"], "pause_resume": None,
    "exclude_object": ["excluded_objects", "current_object"],
    "toolhead": ["print_time", "estimated_print_time"],
}
# print_time when the process starts: an MCU that has been up for a while.
CLOCK_START = 100.
SCRIPT_POLL = 0.05
END_POLL = 0.25
END_LIMIT_S = 3600.


class _Connection:
    """A webhooks client connection as Moonraker's: takes the subscription's messages."""

    def __init__(self, sink):
        self.sink = sink

    def is_closed(self):
        return False

    def send(self, msg):
        self.sink(msg.get("params", {}))


class _Request:
    """A web request for objects/subscribe (or register_remote_method), as Moonraker
    sends it."""

    def __init__(self, conn, objects, method=None):
        self.conn = conn
        self.params = {"objects": objects, "response_template": {}, "remote_method": method}

    def get_client_connection(self):
        return self.conn

    def get_dict(self, item, default=None):
        return self.params.get(item, default)

    def get_str(self, item, default=None):
        return self.params.get(item, default)

    def send(self, data):
        self.conn.sink(data)


class KTestRealtime:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.reactor = self.printer.get_reactor()
        self.heat_wait = config.getfloat("heat_wait", 0., minval=0.)
        self.out_path = os.environ.get("KTEST_OUT", "/dev/null")
        self.script = json.loads(os.environ.get("KTEST_SCRIPT", "[]"))
        self.stream = []
        self.remote_calls = []
        self.typed = []
        self.errors = []
        self.end_print_time = None
        self.written = False
        self.last_typed = None
        self.start_wall = time.time()
        self.gcode = self.printer.lookup_object("gcode")
        self.gcode.register_output_handler(self._output)
        self.printer.register_event_handler("klippy:connect", self._connect)
        self.printer.register_event_handler("klippy:ready", self._ready)
        self.printer.register_event_handler("gcode:debuginput_exit", self._exit)

    # The clock, pausing and flushing of a printer
    def _connect(self):
        lookup = self.printer.lookup_object
        offset = CLOCK_START - self.reactor.monotonic()
        self.offset = offset

        def estimated_print_time(eventtime):
            return eventtime + offset
        for _name, mcu in self.printer.lookup_objects(module="mcu"):
            mcu.estimated_print_time = estimated_print_time
        self.toolhead = lookup("toolhead")
        self.toolhead.can_pause = True
        mq = lookup("motion_queuing", None)
        if mq is not None:
            mq.can_pause = True
            mq.flush_timer.callback = mq._flush_handler
        # The look-ahead queue: toolhead.lookahead, toolhead.move_queue before v0.13.0.
        self.lookahead = getattr(self.toolhead, "lookahead", None)
        if self.lookahead is None:
            self.lookahead = self.toolhead.move_queue
        oracle = lookup("oracle_probe")
        self.gcode.register_command("G28", None)
        self.gcode.register_command("G28", oracle.cmd_ORACLE_HOME)

    def _ready(self):
        lookup = self.printer.lookup_object
        self.vsd = lookup("virtual_sdcard")
        for name in ("M109", "M190"):
            original = self.gcode.register_command(name, None)
            if original is not None:
                self.gcode.register_command(name, self._heater_wait(original))
        subscribe = lookup("webhooks")._endpoints["objects/subscribe"]
        objects = dict((k, (list(v) if v is not None else None))
                       for k, v in SUBSCRIBE.items()
                       if self.printer.lookup_object(k, None) is not None)
        conn = _Connection(self._cycle)
        self.reactor.register_callback(lambda e: subscribe(_Request(conn, objects)))
        # Moonraker's notifier registers the remote method "notify" (a macro's
        # action_call_remote_method("notify", name=..., message=...) reaches it): recorded.
        register = lookup("webhooks")._endpoints["register_remote_method"]
        register(_Request(_Connection(self._remote_call), {}, "notify"))
        self.reactor.register_timer(self._script_timer, self.reactor.NOW)
        self.reactor.register_timer(self._end_timer, self.reactor.NOW)

    def _heater_wait(self, original):
        def wait(gcmd):
            original(gcmd)
            if gcmd.get_float("S", 0.) > 0. and self.heat_wait:
                self.toolhead.wait_moves()
                self.reactor.pause(self.reactor.monotonic() + self.heat_wait)
        return wait

    def _output(self, msg):
        if msg.startswith("!!"):
            self.errors.append(msg[2:].strip())

    # What Moonraker receives
    def _cycle(self, params):
        self.stream.append({"eventtime": params.get("eventtime"),
                            "status": params.get("status", {})})

    def _remote_call(self, params):
        self.remote_calls.append({"eventtime": self.reactor.monotonic(),
                                  "params": params})

    # The console
    def _script_timer(self, eventtime):
        if not self.script:
            return self.reactor.NEVER
        entry = self.script[0]
        vsd = self.vsd
        due = False
        if "at" in entry:
            size = vsd.file_size or 0
            due = vsd.is_active() and size and vsd.file_position >= entry["at"] * size
        elif "after" in entry:
            due = (self.last_typed is not None
                   and eventtime >= self.last_typed + entry["after"])
        if due:
            self.script.pop(0)
            self.last_typed = eventtime
            self.reactor.register_callback(
                lambda e, cmd=entry["cmd"]: self._type(cmd))
        return eventtime + SCRIPT_POLL

    def _type(self, cmd):
        start = self.reactor.monotonic()
        record = {"cmd": cmd, "eventtime": start}
        self.typed.append(record)
        try:
            self.gcode.run_script(cmd)
        except Exception as e:
            record["error"] = str(e)
        end = self.reactor.monotonic()
        self.last_typed = end
        record.update({"done_eventtime": end, "position": self.vsd.file_position})

    # The end
    def _exit(self):
        return self._ended(self.reactor.monotonic())

    def _end_timer(self, eventtime):
        return self.reactor.NEVER if self._ended(eventtime) else eventtime + END_POLL

    def _ended(self, now):
        """The results are written: now, if the print has ended and every move has run."""
        if self.written:
            return True
        th = self.toolhead
        print_stats = self.printer.lookup_object("print_stats")
        state = print_stats.get_status(now)["state"]
        finished = (state in ("complete", "cancelled", "error") and not self.script
                    and self.lookahead.get_last() is None
                    and now + self.offset > th.print_time + 0.5)
        if not finished and time.time() - self.start_wall < END_LIMIT_S:
            return False
        self.end_print_time = th.print_time
        self._write(state)
        return True

    def _write(self, state):
        kest = self.printer.lookup_object("kestimator", None)
        worker = getattr(kest, "worker", None)
        proc = getattr(worker, "proc", None)
        oracle = self.printer.lookup_object("oracle_probe")
        with open(self.out_path, "w") as f:
            json.dump({"end_print_time": self.end_print_time, "state": state,
                       "clock_offset": self.offset, "stream": self.stream,
                       "typed": self.typed, "gaps": oracle.syncs,
                       "remote_calls": self.remote_calls,
                       "errors": self.errors, "n_runout_flushes": oracle.n_runout,
                       "stalls": self.toolhead.print_stall,
                       "worker_pid": proc.pid if proc is not None else None}, f)
        self.written = True


def load_config(config):
    return KTestRealtime(config)
