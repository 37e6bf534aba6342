"""Step-generation scan windows: how long Klipper waits before motion restarts after a full stop.

Owns what widens Klipper's `kin_flush_delay` (mainline Klipper at commit 84104bbbd, GNU GPLv3):
`klippy/extras/motion_queuing.py` `check_step_generation_scan_windows` takes the largest
`gen_steps_pre_active` / `gen_steps_post_active` of any stepper that has a motion queue, and
never less than `SDS_CHECK_TIME` (1 ms). Two things set those windows:

- pressure advance (`klippy/chelper/kin_extruder.c` `extruder_set_pressure_advance`): half of
  `pressure_advance_smooth_time` on each side, but only while `pressure_advance` is non-zero
  (`klippy/kinematics/extruder.py` `_set_pressure_advance` passes a smooth time of 0 then);
  every extruder stepper counts, active or not, as long as it is synced to a motion queue;
- the input shaper (`klippy/chelper/kin_shaper.c` `init_shaper`, `shift_pulses`,
  `shaper_note_generation_time`): the shaper's pulses, normalised and centred on their
  amplitude-weighted mean time; the window is the span from that mean to the first and last
  pulse. The pulses come from `klippy/extras/shaper_defs.py`.

A full stop of step generation (`flush_step_generation`) followed by motion costs
`2 x kin_flush_delay`: one delay after the last move before its steps are all generated, one
before the next move may start (`calc_step_gen_restart`).
"""

from __future__ import annotations

import math
import re

from kestimator.errors import fixed

# motion_queuing.SDS_CHECK_TIME: the step+dir+step filter's scan window.
SDS_CHECK_TIME_T = 0.001
# shaper_defs.DEFAULT_DAMPING_RATIO and SHAPER_VIBRATION_REDUCTION.
DEFAULT_DAMPING_RATIO = 0.1
SHAPER_VIBRATION_REDUCTION = 20.0
# The largest pressure_advance_smooth_time Klipper accepts.
MAX_SMOOTH_TIME_T = 0.200
# Shaper name -> largest damping ratio (shaper_defs.INPUT_SHAPERS).
SHAPER_MAX_DAMPING = {"zv": 0.99, "mzv": 0.99, "zvd": 0.99, "ei": 0.4, "2hump_ei": 0.3,
                      "3hump_ei": 0.2}
# kin_shaper.c: at most this many pulses.
MAX_SHAPER_PULSES = 5
_SHAPER_CALL_RE = re.compile(r"(\w+)\s*\((.*)\)$")
_SHAPER_ARG_RE = re.compile(r"(?:(\w+)\s*=\s*)?\s*([\d.]+)")

class ShaperError(ValueError):
    """Klipper refuses these shaper parameters (its text)."""


def shaper_name(shaper_type: str) -> str:
    """The base name of a shaper type such as ``mzv`` or ``mzv(n=4)``."""
    match = _SHAPER_CALL_RE.match(shaper_type)
    return match.group(1) if match else shaper_type


def _zv(freq: float, damping: float) -> tuple[list[float], list[float]]:
    df = math.sqrt(1.0 - math.pow(damping, 2.0))
    k = math.exp(-damping * math.pi / df)
    t_d = 1.0 / (freq * df)
    return [1.0, k], [0.0, 0.5 * t_d]


def _zvd(freq: float, damping: float) -> tuple[list[float], list[float]]:
    df = math.sqrt(1.0 - math.pow(damping, 2.0))
    k = math.exp(-damping * math.pi / df)
    t_d = 1.0 / (freq * df)
    return [1.0, 2.0 * k, math.pow(k, 2.0)], [0.0, 0.5 * t_d, t_d]


def _solve_least_squares(rows: list[list[float]], rhs: list[float]) -> list[float] | None:
    """x minimising |rows x - rhs| through the normal equations (as mathutil does)."""
    n = len(rows[0])
    mtm = [[sum(r[i] * r[j] for r in rows) for j in range(n)] for i in range(n)]
    mtb = [sum(rows[k][i] * rhs[k] for k in range(len(rows))) for i in range(n)]
    for col in range(n):
        pivot = max(range(col, n), key=lambda i: abs(mtm[i][col]))
        if abs(mtm[pivot][col]) < 1e-12:
            return None
        mtm[col], mtm[pivot] = mtm[pivot], mtm[col]
        mtb[col], mtb[pivot] = mtb[pivot], mtb[col]
        for i in range(n):
            if i != col:
                factor = mtm[i][col] / mtm[col][col]
                for j in range(col, n):
                    mtm[i][j] -= factor * mtm[col][j]
                mtb[i] -= factor * mtb[col]
    return [mtb[i] / mtm[i][i] for i in range(n)]


def _mzv_coeffs(n: int, t: float) -> tuple[list[float], list[float]]:
    if n < 3:
        raise ShaperError("Too small n=%d, must be at least 3" % n)
    if n <= 2 * t + 1 + 1e-7:
        raise ShaperError("Too large t=%s for n=%d, must be less than %s"
                          % (fixed(t, 6), n, fixed(0.5 * (n - 1), 6)))
    tau = t * (n - 2.0) / (n - 2.0 * t - 1.0)
    times = [i * t / (n - 1.0) for i in range(n)]
    rows = [[1.0] * n]
    rhs = [1.0]
    for i in range(n - 1):
        w = [2.0 * math.pi * (1.0 + i / tau) * tj for tj in times]
        rows.append([math.cos(x) for x in w])
        rows.append([math.sin(x) for x in w])
        rhs.extend((0.0, 0.0))
    amps = _solve_least_squares(rows, rhs)
    if amps is None:
        raise ShaperError("Ill-formed shaper with n=%d, t=%s" % (n, fixed(t, 6)))
    if any(a < -0.00001 for a in amps):
        raise ShaperError("Negative-valued shaper with n=%d, t=%s" % (n, fixed(t, 6)))
    return amps, times


def _mzv(freq: float, damping: float, n: float = 3, t: float = 0.0,
         tau: float = 0.0) -> tuple[list[float], list[float]]:
    n_i = int(n)
    if not tau and not t:
        t = 0.75
    elif tau:
        t = tau * (n_i - 1.0) / (n_i + 2.0 * tau - 2.0)
    amps, times = _mzv_coeffs(n_i, t)
    df = math.sqrt(1.0 - math.pow(damping, 2.0))
    k = math.exp(-2.0 * t * damping * math.pi / ((n_i - 1.0) * df))
    t_d = 1.0 / (freq * df)
    kp = k
    for i in range(1, n_i):
        times[i] *= t_d
        amps[i] *= kp
        kp *= k
    return amps, times


def _ei(freq: float, damping: float) -> tuple[list[float], list[float]]:
    v_tol = 1.0 / SHAPER_VIBRATION_REDUCTION
    df = math.sqrt(1.0 - math.pow(damping, 2.0))
    t_d = 1.0 / (freq * df)
    dr = damping
    a1 = (0.24968 + 0.24961 * v_tol) + ((0.80008 + 1.23328 * v_tol)
                                        + (0.49599 + 3.17316 * v_tol) * dr) * dr
    a3 = (0.25149 + 0.21474 * v_tol) + ((-0.83249 + 1.41498 * v_tol)
                                        + (0.85181 - 4.90094 * v_tol) * dr) * dr
    a2 = 1.0 - a1 - a3
    t2 = 0.4999 + (((0.46159 + 8.57843 * v_tol) * v_tol)
                   + (((4.26169 - 108.644 * v_tol) * v_tol)
                      + ((1.75601 + 336.989 * v_tol) * v_tol) * dr) * dr) * dr
    return [a1, a2, a3], [0.0, t2 * t_d, t_d]


# Expansion coefficients of the multi-hump EI shapers (shaper_defs.py), in damping ratio.
_HUMP_COEFFS = {
    "2hump_ei": (
        [[0.0, 0.0, 0.0, 0.0], [0.49890, 0.16270, -0.54262, 6.16180],
         [0.99748, 0.18382, -1.58270, 8.17120], [1.49920, -0.09297, -0.28338, 1.85710]],
        [[0.16054, 0.76699, 2.26560, -1.22750], [0.33911, 0.45081, -2.58080, 1.73650],
         [0.34089, -0.61533, -0.68765, 0.42261], [0.15997, -0.60246, 1.00280, -0.93145]]),
    "3hump_ei": (
        [[0.0, 0.0, 0.0, 0.0], [0.49974, 0.23834, 0.44559, 12.4720],
         [0.99849, 0.29808, -2.36460, 23.3990], [1.49870, 0.10306, -2.01390, 17.0320],
         [1.99960, -0.28231, 0.61536, 5.40450]],
        [[0.11275, 0.76632, 3.29160, -1.44380], [0.23698, 0.61164, -2.57850, 4.85220],
         [0.30008, -0.19062, -2.14560, 0.13744], [0.23775, -0.73297, 0.46885, -2.08650],
         [0.11244, -0.45439, 0.96382, -1.46000]]),
}


def _hump_ei(name: str, freq: float, damping: float) -> tuple[list[float], list[float]]:
    t_coeffs, a_coeffs = _HUMP_COEFFS[name]
    period = 1.0 / freq
    times: list[float] = []
    amps: list[float] = []
    for index, t_row in enumerate(t_coeffs):
        a_row = a_coeffs[index]
        k = len(t_row)
        u = t_row[k - 1]
        v = a_row[k - 1]
        for j in range(k - 1):
            u = u * damping + t_row[k - j - 2]
            v = v * damping + a_row[k - j - 2]
        times.append(u * period)
        amps.append(v)
    return amps, times


def shaper_pulses(shaper_type: str, freq: float, damping: float
                  ) -> tuple[list[float], list[float]]:
    """(amplitudes, times) of a shaper as shaper_defs.init_shaper builds them.

    A frequency of 0 means no shaping (no pulses). Raises ShaperError with Klipper's text.
    """
    if not freq:
        return [], []
    name = shaper_type
    args_l: list[float] = []
    args_kv: dict[str, float] = {}
    match = _SHAPER_CALL_RE.match(shaper_type)
    if match:
        name = match.group(1)
        for key, raw in _SHAPER_ARG_RE.findall(match.group(2)):
            value = float(raw) if "." in raw else int(raw)
            if key:
                args_kv[key] = value
            else:
                args_l.append(value)
        if args_l and args_kv:
            raise ShaperError("Failed to initialize shaper: Mixing named and non-named "
                              "shaper parameters is not supported")
    if name not in SHAPER_MAX_DAMPING:
        raise ShaperError("Unsupported shaper type: %s" % shaper_type)
    try:
        if name == "mzv":
            return _mzv(freq, damping, *args_l, **args_kv)
        if args_l or args_kv:
            raise TypeError("%s takes no parameters" % name)
        if name == "zv":
            return _zv(freq, damping)
        if name == "zvd":
            return _zvd(freq, damping)
        if name == "ei":
            return _ei(freq, damping)
        return _hump_ei(name, freq, damping)
    except ShaperError as exc:
        raise ShaperError("Failed to initialize shaper: %s" % exc) from None
    except TypeError as exc:
        raise ShaperError("Failed to initialize shaper %s: %s" % (shaper_type, exc)) from None


def shaper_window(amps: list[float], times: list[float]) -> float:
    """The scan window (max of gen_steps_pre_active and post_active) of a shaper's pulses.

    kin_shaper.c reverses the pulses, normalises them and shifts them by their weighted mean
    time: the window reaches from that mean back to the first pulse and on to the last.
    """
    if not amps:
        return 0.0
    if len(amps) > MAX_SHAPER_PULSES or any(
            times[i - 1] >= times[i] for i in range(1, len(times))):
        # input_shaper_set_shaper_params fails and Klipper disables this shaper.
        return 0.0
    inv_sum = 1.0 / sum(amps)
    reversed_t = [-t for t in reversed(times)]
    reversed_a = [a * inv_sum for a in reversed(amps)]
    shift = sum(reversed_a[i] * reversed_t[i] for i in range(len(reversed_t)))
    pulses_t = [t - shift for t in reversed_t]
    return max(pulses_t[-1], -pulses_t[0], 0.0)


def pressure_advance_window(pressure_advance: float, smooth_time: float) -> float:
    """An extruder stepper's scan window: half the smooth time, while advance is on."""
    return smooth_time * 0.5 if pressure_advance else 0.0


def kin_flush_delay(windows: list[float]) -> float:
    """motion_queuing's kin_flush_delay from every stepper's scan window."""
    return max([SDS_CHECK_TIME_T] + windows)
