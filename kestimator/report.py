"""`kestimator report`: one self-contained HTML page with inline SVG charts.

Owns what the report shows and how it is drawn: a banner of what the user must know first
(guessed limits, warnings), the remaining time the printer's display would show (the
slicer's own M73 R / ;TIME_ELAPSED: against Klipper's truth), time per layer (with Z), per
object, per feature, the speed moves reach against the speed they ask for (where acceleration
costs time), filament, and the limits with their sources. The page loads nothing from the
network and runs no script; charts are drawn in a 400-unit-wide SVG so text stays at least
11 CSS px on a 390 px phone, with ticks on round values. Standard library only.
"""

from __future__ import annotations

import bisect
import dataclasses
import html
import math
import os
import re
from collections.abc import Mapping, Sequence

from kestimator import __version__
from kestimator.cli_output import (
    parts_to_json,
    printable,
    shown_warnings,
    stop_rows,
    untimed_by_kind,
    untimed_detail,
    untimed_summary,
)
from kestimator.durations import format_duration
from kestimator.errors import KestimatorError
from kestimator.estimate import Estimate, ProgressCallback, estimate_lines, iter_lines
from kestimator.limits import Limits
from kestimator.macros import MacroTimes
from kestimator.preflight import KIND_STOP, summary_lines
from kestimator.rewrite import slicer_of_file
from kestimator.slicers import SlicerInfo
from kestimator.toolhead import Move

SPEED_BIN_V = 10.0
_M73_R_RE = re.compile(rb"^\s*M73\s+(?:[^;]*\s)?R(\d+(?:\.\d+)?)")
_TIME_ELAPSED_RE = re.compile(rb"^;TIME_ELAPSED:(\d+(?:\.\d+)?)")
_Z_RE = re.compile(rb"^\s*G[01]\s[^;]*Z(-?\d+(?:\.\d+)?|-?\.\d+)")
# Chart geometry in SVG user units. Charts are at most 520 px wide on screen (ticks at most
# 16 px on a desktop); at 390 px (366 px of chart) a unit is 0.915 px, so TICK_FONT-unit
# ticks render at 11.4 px.
CHART_W = 400
CHART_H = 250
PAD_L, PAD_R, PAD_T, PAD_B = 58, 14, 12, 46
TICK_FONT = 12.5
LABEL_FONT = 13.0
# Round steps for time axes (seconds) and for other axes (x a power of ten).
TIME_STEPS = (1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800, 21600,
              43200, 86400)
NUMBER_STEPS = (1.0, 2.0, 2.5, 5.0)
MAX_TICKS = 5
COLORS = ("#2f6fdf", "#e0702a", "#3a9d5d", "#b8408f", "#8a6d3b", "#5a5a5a", "#c23b3b",
          "#17a2b8")
# The stops' lines on the remaining-time chart, and how many are drawn at most.
STOP_COLOR = COLORS[6]
MAX_STOP_MARKS = 200


@dataclasses.dataclass
class SpeedBin:
    """Kinematic moves whose allowed cruise speed falls in one SPEED_BIN_V-wide bin."""

    distance_mm: float = 0.0
    time_s: float = 0.0
    ideal_s: float = 0.0
    reached_v_mm: float = 0.0  # sum of cruise speed x distance

    @property
    def mean_reached_v(self) -> float:
        """Distance-weighted mean of the peak speed the moves reached."""
        return self.reached_v_mm / self.distance_mm if self.distance_mm else 0.0


class SpeedStats:
    """Move observer: how far each move's peak falls short of the speed it may go."""

    def __init__(self) -> None:
        self.bins: dict[int, SpeedBin] = {}

    def __call__(self, moves: list[Move], start_t: float) -> None:
        bins = self.bins
        for move in moves:
            if not move.is_kinematic_move:
                continue
            allowed_v = math.sqrt(move.max_cruise_v2)
            key = int(allowed_v // SPEED_BIN_V)
            b = bins.get(key)
            if b is None:
                b = bins[key] = SpeedBin()
            b.distance_mm += move.move_d
            b.time_s += move.accel_t + move.cruise_t + move.decel_t
            b.ideal_s += move.move_d / allowed_v
            b.reached_v_mm += move.cruise_v * move.move_d

    @property
    def lost_s(self) -> float:
        """Time spent below the allowed speed (accelerating and decelerating)."""
        return sum(b.time_s - b.ideal_s for b in self.bins.values())


@dataclasses.dataclass
class ReportData:
    """Everything the page shows."""

    estimate: Estimate
    slicer: SlicerInfo
    limits_source: str
    speed: SpeedStats
    # (Klipper time s, remaining time the slicer's display shows s), in file order.
    slicer_remaining: list[tuple[float, float]]
    # Where slicer_remaining comes from ("M73 R", ";TIME_ELAPSED:") or "" when nowhere.
    remaining_source: str
    # Z (mm) of each layer marker in est.layers (None where no Z move follows it).
    layer_z: list[float | None]
    # Warnings about the limits (e.g. guessed), shown in the banner.
    limit_warnings: list[str] = dataclasses.field(default_factory=list)
    # Limit name -> (value, where it came from).
    limit_rows: list[tuple[str, str, str]] = dataclasses.field(default_factory=list)
    guessed_limits: bool = False


def _escape(text: str) -> str:
    """`text` for the page: what could make a name display as something it is not (bidi
    overrides and isolates, control characters) and undecodable bytes of a file name are
    shown as escapes, as the terminal shows them (`cli_output.printable`), then HTML-escaped.

    Every string from a file, a path, a server or a setting reaches the page through this.
    """
    return html.escape(printable(text))


def _time_at_line(est: Estimate, line: int) -> float:
    """Time every move before `line` has finished, from the progress samples."""
    i = bisect.bisect_left(est.sample_lines, line)
    return est.sample_times[i - 1] if i else 0.0


def collect(path: str, limits: Limits, limits_source: str, homing_time: float = 0.0,
            heat_time: float = 0.0, macros: MacroTimes | None = None,
            limit_warnings: Sequence[str] = (),
            limit_sources: Mapping[str, str] | None = None,
            guessed_limits: bool = False,
            bytes_read: ProgressCallback | None = None,
            shown: str | None = None) -> ReportData:
    """Estimate the file with move statistics; read the slicer's remaining time and Z.

    `shown` is the name the page gives the file (default `path`; `<stdin>` when `path` is a
    temporary copy of standard input)."""
    speed = SpeedStats()
    if os.path.isdir(path):
        raise KestimatorError("is a directory, not a G-code file", path)
    est = estimate_lines(iter_lines(path, bytes_read), limits, path if shown is None else shown,
                         homing_time=homing_time, heat_time=heat_time, macros=macros,
                         sample=True, observer=speed)
    slicer = slicer_of_file(path)  # through our marker in an injected file
    m73: list[tuple[float, float]] = []
    elapsed: list[tuple[float, float]] = []
    layer_lines = [line for line, _ in est.layers]
    layer_z: list[float | None] = [None] * len(layer_lines)
    next_layer = 0   # index of the first layer whose marker is still ahead
    waiting = -1     # the layer whose Z is not known yet
    z_now: float | None = None
    with open(path, "rb") as f:
        for lineno, raw in enumerate(f, 1):
            while next_layer < len(layer_lines) and layer_lines[next_layer] <= lineno:
                waiting = next_layer
                next_layer += 1
            first = raw[:1]
            if first in (b"G", b"g", b" ", b"\t"):
                if b"Z" in raw:
                    zm = _Z_RE.match(raw)
                    if zm is not None:
                        z_now = float(zm.group(1))
                if waiting >= 0 and b"E" in raw and (b"X" in raw or b"Y" in raw):
                    # The layer's Z: where its first extruding move runs (after any Z hop).
                    layer_z[waiting] = z_now
                    waiting = -1
                continue
            if first in (b"M", b"m"):
                match = _M73_R_RE.match(raw)
                if match is not None:
                    m73.append((_time_at_line(est, lineno), 60.0 * float(match.group(1))))
            elif first == b";":
                if raw.startswith(b";TIME_ELAPSED:"):
                    em = _TIME_ELAPSED_RE.match(raw)
                    if em is not None:
                        elapsed.append((_time_at_line(est, lineno), float(em.group(1))))
                elif waiting >= 0 and raw.startswith(b";Z:"):
                    try:
                        layer_z[waiting] = float(raw[3:])
                        waiting = -1
                    except ValueError:
                        pass
    if m73:
        remaining, source = m73, "M73 R"
    elif elapsed and slicer.estimate_s is not None:
        total = slicer.estimate_s
        remaining = [(0.0, total)] + [(t, max(0.0, total - e)) for t, e in elapsed]
        source = ";TIME_ELAPSED:"
    else:
        remaining, source = [], ""
    rows = [(name, _limit_value(getattr(limits, name, None)), src)
            for name, src in sorted((limit_sources or {}).items())]
    return ReportData(estimate=est, slicer=slicer, limits_source=limits_source, speed=speed,
                      slicer_remaining=remaining, remaining_source=source, layer_z=layer_z,
                      limit_warnings=list(limit_warnings), limit_rows=rows,
                      guessed_limits=guessed_limits)


def _limit_value(value: object) -> str:
    if isinstance(value, float):
        return "%g" % value
    return "" if value is None else str(value)


def time_step(span_s: float) -> float:
    """A round time step (1 s .. 1 day) giving at most MAX_TICKS steps over `span_s`."""
    for step in TIME_STEPS:
        if span_s <= step * MAX_TICKS:
            return float(step)
    return float(TIME_STEPS[-1]) * math.ceil(span_s / (TIME_STEPS[-1] * MAX_TICKS))


def number_step(span: float) -> float:
    """A round step (1, 2, 2.5 or 5 x 10^k) giving at most MAX_TICKS steps over `span`."""
    if span <= 0:
        return 1.0
    exp = 10.0 ** math.floor(math.log10(span / MAX_TICKS))
    for mult in NUMBER_STEPS + (10.0,):
        if span <= mult * exp * MAX_TICKS:
            return mult * exp
    return 10.0 * exp


def tick_time(seconds: float) -> str:
    """A tick label for a round time: `0`, `45s`, `10m`, `1h`, `1h 30m`."""
    whole = int(round(seconds))
    if whole == 0:
        return "0"
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    parts = []
    if hours:
        parts.append("%dh" % hours)
    if minutes:
        parts.append("%dm" % minutes)
    if secs:
        parts.append("%ds" % secs)
    return " ".join(parts)


class Axis:
    """A linear axis from 0 to a round maximum with ticks on every round step."""

    def __init__(self, max_value: float, timed: bool) -> None:
        step = time_step(max_value) if timed else number_step(max_value)
        self.step = step
        self.max = step * max(1, math.ceil(max_value / step - 1e-9))
        self.timed = timed

    def ticks(self) -> list[tuple[float, str]]:
        n = int(round(self.max / self.step))
        return [(k * self.step, tick_time(k * self.step) if self.timed
                 else "%g" % (k * self.step)) for k in range(n + 1)]


PLOT_W = CHART_W - PAD_L - PAD_R
PLOT_H = CHART_H - PAD_T - PAD_B


def _x(axis: Axis, value: float) -> float:
    return PAD_L + PLOT_W * value / axis.max


def _y(axis: Axis, value: float) -> float:
    return PAD_T + PLOT_H - PLOT_H * value / axis.max


def _axes(x_axis: Axis | None, y_axis: Axis, x_label: str, y_label: str,
          x_ticks: Sequence[tuple[float, str]] | None = None) -> list[str]:
    """Frame, grid, round ticks and axis labels of a chart."""
    out = ['<rect x="%d" y="%d" width="%d" height="%d" class="frame"/>'
           % (PAD_L, PAD_T, PLOT_W, PLOT_H)]
    for value, label in y_axis.ticks():
        y = _y(y_axis, value)
        out.append('<line x1="%d" x2="%d" y1="%.1f" y2="%.1f" class="grid"/>'
                   % (PAD_L, PAD_L + PLOT_W, y, y))
        out.append('<text x="%d" y="%.1f" class="tick" text-anchor="end">%s</text>'
                   % (PAD_L - 5, y + 4, _escape(label)))
    if x_ticks is None and x_axis is not None:
        x_ticks = [(_x(x_axis, v), label) for v, label in x_axis.ticks()]
    for i, (x, label) in enumerate(x_ticks or ()):
        # The first and last labels are anchored inside the plot so none is clipped.
        anchor = "middle"
        if x_axis is not None and i == 0 and x <= PAD_L + 1:
            anchor = "start"
        elif x_axis is not None and x >= PAD_L + PLOT_W - 1:
            anchor = "end"
        out.append('<line x1="%.1f" x2="%.1f" y1="%d" y2="%d" class="axis"/>'
                   % (x, x, PAD_T + PLOT_H, PAD_T + PLOT_H + 4))
        out.append('<text x="%.1f" y="%d" class="tick" text-anchor="%s">%s</text>'
                   % (x, PAD_T + PLOT_H + 17, anchor, _escape(label)))
    out.append('<text x="%d" y="%d" class="label" text-anchor="middle">%s</text>'
               % (PAD_L + PLOT_W // 2, CHART_H - 6, _escape(x_label)))
    out.append('<text x="14" y="%d" class="label" text-anchor="middle" '
               'transform="rotate(-90 14 %d)">%s</text>'
               % (PAD_T + PLOT_H // 2, PAD_T + PLOT_H // 2, _escape(y_label)))
    return out


def _svg(chart_id: str, title: str, body: list[str], height: float = CHART_H) -> str:
    return ('<svg id="%s" class="chart" viewBox="0 0 %d %d" role="img" '
            'preserveAspectRatio="xMidYMid meet"><title>%s</title>%s</svg>'
            % (chart_id, CHART_W, math.ceil(height), _escape(title), "".join(body)))


def remaining_error(data: ReportData) -> tuple[float, float] | None:
    """The slicer's remaining time minus Klipper's where it is furthest off: (at t, error s)."""
    total = data.estimate.total_s
    worst: tuple[float, float] | None = None
    for t, shown in data.slicer_remaining:
        error = shown - max(0.0, total - t)
        if worst is None or abs(error) > abs(worst[1]):
            worst = (t, error)
    return worst


def remaining_chart(data: ReportData) -> str:
    """Lines: the remaining time Klipper's truth gives, and what the slicer's display shows."""
    total = data.estimate.total_s or 1.0
    x_axis = Axis(total, timed=True)
    y_max = max([total] + [r for _, r in data.slicer_remaining])
    y_axis = Axis(y_max, timed=True)
    body = _axes(x_axis, y_axis, "print time (Klipper)", "time remaining")
    body.append('<polyline class="series truth" fill="none" stroke="%s" stroke-width="3" '
                'points="%.1f,%.1f %.1f,%.1f"><title>Klipper (true)</title></polyline>'
                % (COLORS[2], _x(x_axis, 0), _y(y_axis, total), _x(x_axis, total),
                   _y(y_axis, 0)))
    if data.slicer_remaining:
        # The display holds a value until the next update: draw steps.
        points = []
        previous: float | None = None
        for t, shown in data.slicer_remaining:
            if previous is not None:
                points.append("%.1f,%.1f" % (_x(x_axis, t), _y(y_axis, previous)))
            points.append("%.1f,%.1f" % (_x(x_axis, t), _y(y_axis, shown)))
            previous = shown
        body.append('<polyline class="series slicer" fill="none" stroke="%s" '
                    'stroke-width="2" points="%s"><title>%s (%s)</title></polyline>'
                    % (COLORS[1], " ".join(points), _escape(data.slicer.name),
                       _escape(data.remaining_source)))
    body.extend(stop_marks(data.estimate, x_axis, y_axis))
    return _svg("chart-remaining", "Time remaining on the printer's display", body)


def stop_marks(est: Estimate, x_axis: Axis, y_axis: Axis) -> list[str]:
    """A dashed vertical line at each stop's time (kestimator.stops), titled with its
    command, line and time (at most MAX_STOP_MARKS: the page stays small)."""
    marks = []
    for stop in est.stops[:MAX_STOP_MARKS]:
        x = _x(x_axis, stop.time_s)
        marks.append('<line class="stop" x1="%.1f" x2="%.1f" y1="%.1f" y2="%.1f" stroke="%s" '
                     'stroke-width="2" stroke-dasharray="5 3"><title>%s, line %d: %s</title>'
                     '</line>' % (x, x, _y(y_axis, y_axis.max), _y(y_axis, 0.0), STOP_COLOR,
                                  _escape(stop.command), stop.line,
                                  _escape(format_duration(stop.time_s))))
    return marks


def stops_table(est: Estimate) -> str:
    """The stops: command, line, layer, Klipper time from the start, time since the last
    stop (cli_output.stop_rows, as `estimate` lists them)."""
    if not est.stops:
        return ""
    rows = stop_rows({"stops": [{"command": s.command, "line": s.line, "layer": s.layer,
                                 "time_s": s.time_s} for s in est.stops],
                      "total_s": est.total_s, "stops_unlisted": est.stops_unlisted})
    head = "".join("<th>%s</th>" % title for title in ("Stop", "Line", "Layer", "At",
                                                         "After"))
    body = "".join("<tr>%s</tr>" % "".join("<td>%s</td>" % _escape(cell) for cell in row)
                   for row in rows)
    unlisted = ("<p class=\"note\">%d more stops not listed.</p>" % est.stops_unlisted
                if est.stops_unlisted else "")
    return ("<h2>When the printer waits for you</h2><p class=\"note\">Each stop (a colour "
            "change, a pause: the dashed lines on the first chart) with Klipper's time from "
            "the start, and since the last stop.</p><table class=\"stops\"><tr>%s</tr>%s"
            "</table>%s" % (head, body, unlisted))


def layer_chart(est: Estimate, layer_z: Sequence[float | None]) -> str:
    """Bars: seconds each layer takes (from one layer marker to the next, or the end)."""
    starts = [t for _, t in est.layers]
    if not starts:
        return '<p class="empty">The file has no layer markers.</p>'
    ends = starts[1:] + [est.total_s]
    durations = [max(0.0, b - a) for a, b in zip(starts, ends)]  # noqa: B905
    y_axis = Axis(max(durations), timed=True)
    n = len(durations)
    bar_w = PLOT_W / n
    layer_axis = Axis(float(n), timed=False)
    ticks = [(PAD_L + bar_w * (max(v, 1) - 0.5), "%d" % max(v, 1))
             for v, _ in layer_axis.ticks() if v <= n]
    body = _axes(None, y_axis, "layer", "time per layer", ticks)
    for i, d in enumerate(durations):
        h = PLOT_H * d / y_axis.max
        z = layer_z[i] if i < len(layer_z) else None
        body.append('<rect class="bar" x="%.2f" y="%.2f" width="%.2f" height="%.2f" '
                    'fill="%s"><title>layer %d%s: %s</title></rect>'
                    % (PAD_L + i * bar_w, PAD_T + PLOT_H - h, max(bar_w * 0.85, 0.4), h,
                       COLORS[0], i + 1, "" if z is None else " (Z %g mm)" % z,
                       format_duration(d)))
    return _svg("chart-layers", "Time per layer", body)


def _hbars(chart_id: str, title: str, items: Sequence[tuple[float, str]],
           total: float) -> str:
    """Horizontal bars with the name above each bar and time and share beside it."""
    row_h = 38
    height = 8 + row_h * len(items)
    bar_max = CHART_W - 16 - 120
    t_max = max(t for t, _ in items) or 1.0
    body = []
    for i, (t, name) in enumerate(items):
        y = 8 + i * row_h
        w = bar_max * t / t_max
        short = name if len(name) <= 44 else name[:43] + "\u2026"
        body.append('<text x="8" y="%d" class="tick name">%s</text>'
                    % (y + 12, _escape(short)))
        body.append('<rect class="bar" x="8" y="%d" width="%.1f" height="14" fill="%s" '
                    'data-seconds="%.6f"><title>%s: %s</title></rect>'
                    % (y + 17, max(w, 0.5), COLORS[i % len(COLORS)], t, _escape(name),
                       format_duration(t)))
        body.append('<text x="%.1f" y="%d" class="tick">%s \u00b7 %.0f %%</text>'
                    % (8 + max(w, 0.5) + 5, y + 29, format_duration(t),
                       100.0 * t / total if total else 0.0))
    return _svg(chart_id, title, body, height)


def feature_chart(est: Estimate) -> str:
    """Horizontal bars: time per feature (;TYPE: / ; FEATURE:)."""
    items = sorted(((t, name) for name, t in est.features.items() if t > 0.0005),
                   reverse=True)
    if not items:
        return '<p class="empty">The file names no features.</p>'
    return _hbars("chart-features", "Time per feature", items, est.total_s)


def object_chart(est: Estimate) -> str:
    """Horizontal bars: time per object, in the order they first print."""
    items = [(t, name) for name, t in est.objects.items() if t > 0.0005]
    if not items:
        return ('<p class="empty">The file labels no objects (no EXCLUDE_OBJECT, M486 or '
                '<code>; printing object</code> lines).</p>')
    return _hbars("chart-objects", "Time per object", items, est.total_s)


def speed_chart(speed: SpeedStats) -> str:
    """Per allowed-speed bin: the mean peak speed reached (dots) against the diagonal."""
    if not speed.bins:
        return '<p class="empty">No kinematic moves.</p>'
    keys = sorted(speed.bins)
    axis = Axis((keys[-1] + 1) * SPEED_BIN_V, timed=False)
    body = _axes(axis, axis, "speed allowed (mm/s)", "speed reached (mm/s)")
    body.append('<line x1="%d" y1="%d" x2="%d" y2="%d" class="diag"/>'
                % (PAD_L, PAD_T + PLOT_H, PAD_L + PLOT_W, PAD_T))
    t_max = max(b.time_s for b in speed.bins.values()) or 1.0
    for key in keys:
        b = speed.bins[key]
        allowed = (key + 0.5) * SPEED_BIN_V
        body.append('<circle class="dot" cx="%.1f" cy="%.1f" r="%.1f" fill="%s" '
                    'fill-opacity="0.7"><title>allowed %d-%d mm/s: reached %.0f mm/s on '
                    'average, %s of which %s below speed</title></circle>'
                    % (_x(axis, allowed), _y(axis, b.mean_reached_v), dot_radius(b.time_s, t_max),
                       COLORS[3], key * SPEED_BIN_V, (key + 1) * SPEED_BIN_V,
                       b.mean_reached_v, format_duration(b.time_s),
                       format_duration(b.time_s - b.ideal_s)))
    return _svg("chart-speed", "Speed reached against speed allowed", body)


def dot_radius(time_s: float, t_max: float) -> float:
    """A dot's radius (SVG units): its area grows with the time its moves take."""
    return 2.5 + 9.0 * math.sqrt(max(time_s, 0.0) / t_max)


def speed_legend(speed: SpeedStats) -> str:
    """What a dot's size means: three sample dots with their times."""
    if not speed.bins:
        return ""
    t_max = max(b.time_s for b in speed.bins.values()) or 1.0
    samples = []
    for fraction in (1.0, 0.25, 0.04):
        t = t_max * fraction
        r = dot_radius(t, t_max)
        samples.append('<span><svg class="swatch" width="%d" height="%d" aria-hidden="true">'
                       '<circle cx="%.1f" cy="%.1f" r="%.1f" fill="%s" fill-opacity="0.7"/>'
                       '</svg>%s</span>' % (2 * r + 2, 2 * r + 2, r + 1, r + 1, r, COLORS[3],
                                            format_duration(t)))
    return '<p class="legend">Dot size = time the moves take: %s</p>' % "".join(samples)


_CSS = """
body{font:15px/1.45 system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;
background:#f6f7f9;color:#1d232b}
main{max-width:760px;margin:0 auto;padding:12px}
h1{font-size:1.25em;margin:.4em 0;overflow-wrap:anywhere}h2{font-size:1.05em;margin:1.3em 0 .3em}
p{margin:.3em 0 .6em}.note{color:#444;font-size:.9em}
.banner{background:#fff4dc;border:1px solid #e8b04a;border-radius:8px;padding:8px 12px;
margin:8px 0;font-size:.9em;overflow-wrap:anywhere}
.banner.bad{background:#fde8e8;border-color:#d05050}.banner ul{margin:.3em 0;padding-left:1.2em}
.cards{display:flex;flex-wrap:wrap;gap:8px}
.card{background:#fff;border-radius:8px;padding:8px 12px;flex:1 1 140px;
box-shadow:0 1px 2px #0001;min-width:0;overflow-wrap:anywhere}
.card b{display:block;font-size:1.2em}.card span{color:#4b5560;font-size:.85em}
.chart{display:block;width:100%;max-width:520px;height:auto;background:#fff;border-radius:8px;
box-shadow:0 1px 2px #0001;min-width:0;overflow-wrap:anywhere}
.frame{fill:none;stroke:#c9ced6}.grid{stroke:#eceff3}.axis{stroke:#9aa3ad}
.diag{stroke:#9aa3ad;stroke-dasharray:4 4}
.tick{font-size:12.5px;fill:#4b5560}.tick.name{fill:#1d232b}.label{font-size:13px;fill:#333}
.legend{font-size:.9em}.legend span{display:inline-block;margin-right:14px;white-space:nowrap}
.legend i{display:inline-block;width:14px;height:3px;margin-right:5px;vertical-align:middle}
.swatch{vertical-align:middle;margin:0 4px}
table{border-collapse:collapse;font-size:.85em;background:#fff;width:100%}
td,th{border-bottom:1px solid #e3e6ea;padding:3px 6px;text-align:left;vertical-align:top}
td:last-child{overflow-wrap:anywhere}td:nth-child(2){white-space:nowrap}
details{margin:.4em 0}summary{cursor:pointer;font-size:.9em}
p.empty{color:#4b5560}footer{color:#4b5560;font-size:.8em;margin:2em 0 1em}
"""


def minutes(seconds: float) -> str:
    """A signed difference in minutes: `-4.2 min`, `+137 min`."""
    value = seconds / 60.0
    return ("%+.1f min" if abs(value) < 10 else "%+.0f min") % value


def _remaining_text(data: ReportData) -> str:
    name = _escape(data.slicer.name)
    if not data.slicer_remaining:
        return ("<p>%s wrote no remaining time into the file (no <code>M73 R</code> and no "
                "<code>;TIME_ELAPSED:</code>), so the printer's display can only guess; "
                "<code>kestimator inject</code> writes Klipper's.</p>" % name)
    worst = remaining_error(data)
    assert worst is not None
    at, error = worst
    return ("<p>The printer's display shows what %s wrote (%s); Klipper's planner needs the "
            "time on the green line. The display is off by up to <b>%s</b> "
            "(%s into the print)%s.</p>"
            % (name, _escape(data.remaining_source), minutes(error),
               _escape(format_duration(at)),
               ": it says the print ends sooner than it will" if error < 0 else
               ": it says the print takes longer than it will" if error > 0 else ""))


def _banner(data: ReportData) -> str:
    est = data.estimate
    parts = []
    if data.guessed_limits:
        parts.append('<div class="banner bad"><b>Guessed limits.</b> No printer.cfg or '
                     'Moonraker was given, so the times below use stand-in limits and may '
                     'be wrong: pass <code>--printer-cfg</code> or <code>--moonraker</code>.'
                     '</div>')
    findings = [finding.to_json() for finding in est.preflight]
    preflight = summary_lines(findings)
    if preflight:
        stops = any(f["kind"] == KIND_STOP for f in findings)
        parts.append('<div class="banner%s"><b>%s</b><ul>%s</ul></div>'
                     % (" bad" if stops else "", _escape(preflight[0]),
                        "".join("<li>%s</li>" % _escape(line.strip())
                                for line in preflight[1:])))
    # Untimed commands are one grouped line, as in the text summary (not one warning each).
    doc = {"warnings": list(data.limit_warnings) + list(est.warnings),
           # The page has no stderr: the guessed-limits warning stays in the list.
           "limits_guessed": False,
           "untimed_commands": untimed_by_kind(
               est, {source["name"] for source in parts_to_json(est)["sources"]})}
    untimed = untimed_summary(doc)
    notes = ([untimed.replace(" (--verbose lists them)", ": " + "; ".join(untimed_detail(doc)))]
             if untimed else []) + shown_warnings(doc)
    if notes:
        shown = "".join("<li>%s</li>" % _escape(w) for w in notes[:20])
        more = len(notes) - 20 + est.warnings_dropped
        parts.append('<div class="banner"><b>%d warning%s</b> (what Klipper would do '
                     'differently, or what the estimate cannot know)<ul>%s</ul>%s</div>'
                     % (len(notes) + est.warnings_dropped, "" if len(notes) == 1 else "s",
                        shown, "<p>... and %d more</p>" % more if more > 0 else ""))
    return "".join(parts)


def _filament_text(data: ReportData) -> str:
    return ("<p>The moves push <b>%.2f m</b> of filament (net of retractions, after "
            "M221).</p>" % (data.estimate.filament_mm / 1000.0))


# The limits that decide most of a print's time, shown first; the rest fold away.
MAIN_LIMITS = ("kinematics", "max_velocity", "max_accel", "minimum_cruise_ratio",
               "square_corner_velocity", "max_z_velocity", "max_z_accel")


def _limit_rows(rows: Sequence[tuple[str, str, str]]) -> str:
    # Long names break at their underscores, never mid-word.
    return "".join("<tr><td>%s</td><td>%s</td><td>%s</td></tr>"
                   % (_escape(n).replace("_", "_<wbr>"), _escape(v), _escape(s))
                   for n, v, s in rows)


def _limits_table(data: ReportData) -> str:
    if not data.limit_rows:
        return "<p>Limits: %s</p>" % _escape(data.limits_source)
    main = sorted((r for r in data.limit_rows if r[0] in MAIN_LIMITS),
                  key=lambda r: MAIN_LIMITS.index(r[0]))
    rest = [r for r in data.limit_rows if r[0] not in MAIN_LIMITS]
    head = "<tr><th>limit</th><th>value</th><th>from</th></tr>"
    out = "<p>%s</p><table>%s%s</table>" % (_escape(data.limits_source), head,
                                            _limit_rows(main))
    if rest:
        out += ("<details><summary>%d more limits</summary><table>%s%s</table></details>"
                % (len(rest), head, _limit_rows(rest)))
    return out


def parts_cards(est: Estimate) -> list[tuple[str, str]]:
    """The parts of the total, when time was added for macros, waits or a learned start."""
    if not est.timed_parts:
        return []
    parts = est.parts
    cards = [("Motion (Klipper's planner)", format_duration(parts.motion_s)),
             ("Macros and prep", format_duration(parts.added_s))]
    cards += [("%s x%d" % (p.name, p.count), "%s, %s" % (format_duration(p.seconds), p.source))
              for p in est.timed_parts]
    if parts.before_first_extrusion_s:
        cards.append(("Before the first extrusion",
                      format_duration(parts.before_first_extrusion_s)))
    return cards


def render_html(data: ReportData) -> str:
    """The whole page."""
    est = data.estimate
    slicer = data.slicer
    cards = [("Klipper time", format_duration(est.total_s))] + parts_cards(est)
    if slicer.estimate_s is not None:
        diff = slicer.estimate_s - est.parts.motion_s  # the slicer times the moves only
        cards.append(("%s said" % slicer.name, "%s (%s)" % (
            format_duration(slicer.estimate_s), minutes(diff))))
    if est.first_layer_s is not None:
        cards.append(("First layer", format_duration(est.first_layer_s)))
    cards.append(("Layers", str(len(est.layers))))
    cards.append(("Filament", "%.2f m" % (est.filament_mm / 1000.0)))
    lost = data.speed.lost_s
    share = 100.0 * lost / est.total_s if est.total_s else 0.0
    cards.append(("Lost to acceleration", "%s (%.0f %%)" % (format_duration(lost), share)))
    card_html = "".join('<div class="card"><span>%s</span><b>%s</b></div>'
                        % (_escape(k), _escape(v)) for k, v in cards)
    legend = ('<p class="legend"><span><i style="background:%s"></i>Klipper (true)</span>%s'
              '</p>' % (COLORS[2], '' if not data.slicer_remaining else
                        '<span><i style="background:%s"></i>%s (%s)</span>'
                        % (COLORS[1], _escape(slicer.name),
                           _escape(data.remaining_source))))
    name = os.path.basename(est.path)
    return """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>%(title)s</title><style>%(css)s</style></head>
<body><main data-total-s="%(total).6f">
<h1>%(title)s</h1>
%(banner)s
<div class="cards">%(cards)s</div>
<h2>What the printer's display says</h2>%(remaining_text)s%(legend)s%(remaining)s
%(stops)s
<h2>Time per layer</h2>
<p class="note">Each bar is one layer, from its layer marker to the next; touch a bar for
its Z height and time.</p>%(layers)s
<h2>Time per object</h2>
<p class="note">Time spent inside each labelled object; "(no object)" is start, end and
travel between objects.</p>%(objects)s
<h2>Time per feature</h2>
<p class="note">Time per extrusion role the slicer named, largest first.</p>%(features)s
<h2>Where time is lost to acceleration</h2>
<p class="note">Each dot is the moves whose speed limit falls in one %(bin)g mm/s band: the
further it sits below the dashed line, the more of their time goes to speeding up and
slowing down (%(lost)s in all, %(share).0f %% of the print).</p>%(speed_legend)s%(speed)s
<h2>Filament</h2>%(filament)s
<h2>Limits and where they came from</h2>%(limits)s
<footer>kestimator %(version)s &middot; Klipper's planner replayed on %(file)s</footer>
</main></body></html>
""" % {
        "title": _escape("Klipper time for " + name), "css": _CSS, "cards": card_html,
        "banner": _banner(data), "remaining_text": _remaining_text(data),
        "legend": legend, "remaining": remaining_chart(data), "stops": stops_table(est),
        "layers": layer_chart(est, data.layer_z), "objects": object_chart(est),
        "features": feature_chart(est), "speed": speed_chart(data.speed),
        "speed_legend": speed_legend(data.speed), "bin": SPEED_BIN_V,
        "lost": _escape(format_duration(lost)), "share": share,
        "filament": _filament_text(data), "limits": _limits_table(data),
        "version": __version__, "file": _escape(name), "total": est.total_s,
    }
