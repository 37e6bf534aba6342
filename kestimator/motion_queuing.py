"""Mirrors klippy/extras/motion_queuing.py at Klipper commit 84104bbbd (GNU GPLv3).

Owns when step generation has caught up with the moves, which is all that decides print
time in batch mode: `PrinterMotionQueuing` keeps how far steps have been generated
(`last_step_gen_time`), how far they must be (`need_step_gen_time`) and the widest step
scan window of any stepper (`kin_flush_delay`, from `kestimator.stepgen`). After a full
stop of step generation (homing, motors off, a new pressure-advance window), Klipper
restarts `kin_flush_delay` after the last step was generated, which itself came
`kin_flush_delay` after the last move: the gap `ToolHead` counts.

Upstream's MCU clock, trapq and background flush timer have no part in the time and are
left out; `calc_step_gen_restart` drops its estimated print time (batch mode has none).
"""

from __future__ import annotations

from collections.abc import Callable

from kestimator.stepgen import SDS_CHECK_TIME_T, kin_flush_delay

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class PrinterMotionQueuing:
    """Step-generation bookkeeping, as the toolhead consults it."""

    def __init__(self) -> None:
        self.kin_flush_delay = SDS_CHECK_TIME_T
        # -inf until the first move: before it, Klipper's start buffer dominates.
        self.last_step_gen_time = float("-inf")
        self.need_step_gen_time = float("-inf")
        # What gives the steppers' scan windows (extruders, input shapers): upstream asks
        # each stepper's kinematics.
        self.scan_window_sources: list[Callable[[], list[float]]] = []

    def register_scan_windows(self, source: Callable[[], list[float]]) -> None:
        """`source()` gives some steppers' scan windows from now on."""
        self.scan_window_sources.append(source)

    def get_kin_flush_delay(self) -> float:
        """The widest step-generation scan window (seconds)."""
        return self.kin_flush_delay

    def check_step_generation_scan_windows(self) -> None:
        """A stepper's scan window changed: the widest window of any (every extruder's
        pressure-advance smoothing, every input shaper) is the flush delay."""
        windows: list[float] = []
        for source in self.scan_window_sources:
            windows.extend(source())
        self.kin_flush_delay = kin_flush_delay(windows)

    def flush_all_steps(self) -> None:
        """Generate every step that moves so far need."""
        if self.need_step_gen_time > self.last_step_gen_time:
            self.last_step_gen_time = self.need_step_gen_time

    def calc_step_gen_restart(self) -> float:
        """The earliest print time at which steps may be generated again."""
        return self.last_step_gen_time + self.kin_flush_delay

    def note_mcu_movequeue_activity(self, mq_time: float) -> None:
        """Moves up to `mq_time` are queued: their steps are needed up to a scan window
        later."""
        mq_time = mq_time + self.kin_flush_delay
        if mq_time > self.need_step_gen_time:
            self.need_step_gen_time = mq_time
