"""A test-only Klipper extras module ([ktest_probe]): drives and samples the kestimator
module during a batch-mode virtual-SD print of real Klipper.

It loads beside the oracle's own probe ([oracle_probe], ../shared/tools/oracle), whose
conventions it keeps so that Klipper's times are those of the oracle: G28 is the oracle's
instant homing (ORACLE_HOME), a heater wait flushes the look-ahead as a real printer's does,
and step generation is flushed in the background without ever running the look-ahead dry
(batch mode's "flush everything" timer branch would plan queued moves to a stop that a real
printer never makes). Commands, placed in the file under test:

  KTEST_SAMPLE ID=n      - note the print_time at which every earlier move has ended and
                           what kestimator says is left from there (its status_at)
  KTEST_USER CMD="..."   - run CMD as if typed in the console between two lines (not from
                           the file), then wait (wall clock, at most 20 s) for kestimator's
                           answer to it, timing that wait
  KTEST_END              - wait for every move (M400), note the end print_time, write
                           the results (JSON) to $KTEST_OUT

Klipper's remaining time at a sample is end - print_time(sample).
"""
import json
import os
import time

BG_FAUX_LAG = 1.5   # as motion_queuing._flush_handler_debug
BG_BATCH = 0.25
MAX_WAIT_S = 20.0


class KTestProbe:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.reactor = self.printer.get_reactor()
        self.gcode = self.printer.lookup_object("gcode")
        self.out_path = os.environ.get("KTEST_OUT", "/dev/null")
        self.samples = []
        self.users = []
        self.start_wait_s = None
        self.end_print_time = None
        self.first_sample = True
        for name in ("SAMPLE", "USER", "END", "KILL_WORKER"):
            self.gcode.register_command("KTEST_" + name, getattr(self, "cmd_KTEST_" + name))
        self.printer.register_event_handler("klippy:connect", self._handle_connect)
        self.printer.register_event_handler("klippy:ready", self._handle_ready)

    def _handle_connect(self):
        self.toolhead = self.printer.lookup_object("toolhead")
        # motion_queuing's batch-mode flush (84104bbbd) replaced; older releases and Kalico
        # have no motion_queuing and their toolhead's own flush timer is left as it is (the
        # oracle probe's n_runout, 0 in every test, shows it never ran the look-ahead dry).
        self.mq = self.printer.lookup_object("motion_queuing", None)
        if self.mq is not None:
            self.mq.flush_timer.callback = self._bg_flush
        oracle = self.printer.lookup_object("oracle_probe")
        self.gcode.register_command("G28", None)
        self.gcode.register_command("G28", oracle.cmd_ORACLE_HOME)

    def _handle_ready(self):
        self.vsd = self.printer.lookup_object("virtual_sdcard")
        self.kest = self.printer.lookup_object("kestimator")
        for name in ("M109", "M190", "TEMPERATURE_WAIT"):
            original = self.gcode.register_command(name, None)
            if original is None:
                continue

            def waited(gcmd, original=original, name=name):
                original(gcmd)
                if name == "TEMPERATURE_WAIT" or gcmd.get_float("S", 0.) > 0.:
                    self.toolhead.wait_moves()
            self.gcode.register_command(name, waited)

    def _bg_flush(self, eventtime):
        mq = self.mq
        faux_time = mq.need_flush_time - BG_FAUX_LAG
        while mq.last_step_gen_time < faux_time:
            mq._advance_flush_time(0., mq.last_step_gen_time + BG_BATCH)
        mq.do_kick_flush_timer = True
        return self.reactor.NEVER

    def _wait(self, done, limit=MAX_WAIT_S):
        start = time.monotonic()
        while not done() and time.monotonic() - start < limit:
            self.reactor.pause(self.reactor.monotonic() + 0.005)
        return time.monotonic() - start

    def cmd_KTEST_SAMPLE(self, gcmd):
        kest = self.kest
        if self.first_sample:
            # The print's start: kestimator reads the file's table or estimates it.
            self.first_sample = False
            self.start_wait_s = self._wait(lambda: kest.table is not None
                                           or kest.disabled)
        position = self.vsd.file_position
        if not kest.disabled:
            kest.anchor_here(position)
        sample = {"id": gcmd.get_int("ID"), "position": position}
        self.samples.append(sample)

        def planned(print_time, sample=sample):
            sample["print_time"] = print_time
            if kest.disabled:
                # Off (a hook missing): only Klipper's time is sampled.
                sample.update(remaining_s=None, source=None, objects={})
                return
            status = kest.status_at(print_time, self.reactor.monotonic())
            sample["remaining_s"] = status["remaining_s"]
            sample["source"] = status["source"]
            sample["objects"] = status["objects"]
        last = self._last_move()
        if last is None:
            planned(self.toolhead.print_time)
        else:
            last.timing_callbacks.append(planned)

    def _last_move(self):
        # get_last is renamed last_queued_move in the test tree where the module must
        # find that hook missing (tests/test_klipper_module_hooks.py).
        queue = getattr(self.toolhead, "lookahead", None) or self.toolhead.move_queue
        get_last = getattr(queue, "get_last", None) or queue.last_queued_move
        return get_last()

    def cmd_KTEST_USER(self, gcmd):
        command = gcmd.get("CMD")
        kest = self.kest
        # As on a printer, where it updates twice a second: the status is there by now.
        self._wait(lambda: kest.status.get("remaining_s") is not None, limit=2.0)
        before = kest.request_id
        self.vsd.cmd_from_sd = False
        try:
            self.gcode.run_script_from_command(command)
        finally:
            self.vsd.cmd_from_sd = True
        asked = kest.request_id != before
        waited = self._wait(lambda: kest.pending_id is None)
        display = self.printer.lookup_object("display_status", None)
        self.users.append({"command": command, "position": self.vsd.file_position,
                           "asked": asked, "answer_wait_s": round(waited, 3),
                           "answered": kest.pending_id is None,
                           "message": display.message if display is not None else None,
                           "remaining_s": kest.get_status(
                               self.reactor.monotonic())["remaining_s"]})

    def cmd_KTEST_KILL_WORKER(self, gcmd):
        """Kill kestimator's worker (SIGKILL), as the kernel's OOM killer would."""
        worker = self.kest.worker
        if worker is not None:
            os.kill(worker.proc.pid, 9)
            worker.proc.wait()

    @staticmethod
    def _memory_kib(pid):
        """VmRSS and VmHWM (peak) of a process, KiB."""
        out = {}
        try:
            with open("/proc/%s/status" % (pid,)) as f:
                for line in f:
                    if line.startswith(("VmRSS:", "VmHWM:")):
                        out[line.split(":")[0]] = int(line.split()[1])
        except OSError:
            pass
        return out

    def cmd_KTEST_END(self, gcmd):
        self.toolhead.wait_moves()
        worker = self.kest.worker
        memory = {"klippy": self._memory_kib("self"),
                  "worker": self._memory_kib(worker.proc.pid) if worker else {}}
        self.end_print_time = self.toolhead.print_time
        oracle = self.printer.lookup_object("oracle_probe")
        with open(self.out_path, "w") as f:
            json.dump({"end_print_time": self.end_print_time, "samples": self.samples,
                       "users": self.users, "start_wait_s": self.start_wait_s,
                       "n_runout_flushes": oracle.n_runout, "syncs": oracle.syncs,
                       "origin": oracle.origin, "errors": oracle.errors,
                       "max_callback_ms": self.kest.max_callback_ms,
                       "table_bytes": self.kest.table.nbytes if self.kest.table else 0,
                       "memory_kib": memory,
                       "kestimator_error": self.kest.error,
                       "kestimator_status": self.kest.get_status(self.reactor.monotonic()),
                       # display_status answering through the module (set_progress)
                       "display_status_wrapped": "get_status" in vars(
                           self.printer.lookup_object("display_status")),
                       "display_status": self.printer.lookup_object(
                           "display_status").get_status(self.reactor.monotonic())}, f)


def load_config(config):
    return KTestProbe(config)
