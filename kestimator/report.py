"""`kestimator report`: one self-contained HTML page with inline SVG charts.

Owns what the report shows and how it is drawn: time per layer, progress over time
(Klipper's truth against the slicer's own M73 where the file has them), time per feature,
and the speed moves reach against the speed they ask for (where acceleration costs time).
The page loads nothing from the network and runs no script; charts scale to the screen,
so it reads on a phone. Standard library only.
"""

from __future__ import annotations

import bisect
import dataclasses
import html
import math
import os
import re
from collections.abc import Sequence

from kestimator import __version__
from kestimator.durations import format_duration
from kestimator.estimate import Estimate, ProgressCallback, estimate_file
from kestimator.limits import Limits
from kestimator.macros import MacroTimes
from kestimator.planner import Move
from kestimator.rewrite import slicer_of_file
from kestimator.slicers import SlicerInfo

SPEED_BIN_V = 10.0
_M73_P_RE = re.compile(rb"^\s*M73\s+(?:[^;]*\s)?P(\d+(?:\.\d+)?)")
CHART_W = 640
CHART_H = 260
PAD_L, PAD_R, PAD_T, PAD_B = 56, 16, 16, 40
COLORS = ("#2f6fdf", "#e0702a", "#3a9d5d", "#b8408f", "#8a6d3b", "#5a5a5a", "#c23b3b",
          "#17a2b8")


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
    slicer_progress: list[tuple[float, float]]  # (Klipper time s, slicer's M73 percent)


def _time_at_line(est: Estimate, line: int) -> float:
    """Time every move before `line` has finished, from the progress samples."""
    i = bisect.bisect_left(est.sample_lines, line)
    return est.sample_times[i - 1] if i else 0.0


def collect(path: str, limits: Limits, limits_source: str, homing_time: float = 0.0,
            heat_time: float = 0.0, macros: MacroTimes | None = None,
            bytes_read: ProgressCallback | None = None) -> ReportData:
    """Estimate the file with move statistics and read the slicer's own M73 progress
    (`bytes_read` hears the bytes the estimate has read, for a progress bar)."""
    speed = SpeedStats()
    est = estimate_file(path, limits, homing_time=homing_time, heat_time=heat_time,
                        macros=macros,
                        sample=True, observer=speed, progress=bytes_read)
    slicer = slicer_of_file(path)  # through our marker in an injected file
    progress: list[tuple[float, float]] = []
    with open(path, "rb") as f:
        for lineno, raw in enumerate(f, 1):
            if raw[:1] not in (b"M", b"m", b" ", b"\t"):
                continue
            match = _M73_P_RE.match(raw)
            if match is not None:
                progress.append((_time_at_line(est, lineno), float(match.group(1))))
    return ReportData(estimate=est, slicer=slicer, limits_source=limits_source, speed=speed,
                      slicer_progress=progress)


def _nice_max(value: float) -> float:
    if value <= 0:
        return 1.0
    exp = 10 ** math.floor(math.log10(value))
    for step in (1, 2, 2.5, 5, 10):
        if value <= step * exp:
            return step * exp
    return 10 * exp


def _axes(x_label: str, y_label: str, y_max: float, y_fmt: str = "%g",
          x_ticks: Sequence[tuple[float, str]] = ()) -> list[str]:
    """Frame, grid and labels of a chart whose plot area maps y in [0, y_max]."""
    plot_w, plot_h = CHART_W - PAD_L - PAD_R, CHART_H - PAD_T - PAD_B
    out = ['<rect x="%d" y="%d" width="%d" height="%d" class="frame"/>'
           % (PAD_L, PAD_T, plot_w, plot_h)]
    for k in range(5):
        value = y_max * k / 4
        y = PAD_T + plot_h - plot_h * k / 4
        out.append('<line x1="%d" x2="%d" y1="%.1f" y2="%.1f" class="grid"/>'
                   % (PAD_L, PAD_L + plot_w, y, y))
        out.append('<text x="%d" y="%.1f" class="tick" text-anchor="end">%s</text>'
                   % (PAD_L - 6, y + 4, html.escape(y_fmt % value)))
    for x, label in x_ticks:
        out.append('<text x="%.1f" y="%d" class="tick" text-anchor="middle">%s</text>'
                   % (x, PAD_T + plot_h + 16, html.escape(label)))
    out.append('<text x="%d" y="%d" class="label" text-anchor="middle">%s</text>'
               % (PAD_L + plot_w // 2, CHART_H - 4, html.escape(x_label)))
    out.append('<text x="12" y="%d" class="label" text-anchor="middle" '
               'transform="rotate(-90 12 %d)">%s</text>'
               % (PAD_T + plot_h // 2, PAD_T + plot_h // 2, html.escape(y_label)))
    return out


def _svg(chart_id: str, title: str, body: list[str]) -> str:
    return ('<svg id="%s" class="chart" viewBox="0 0 %d %d" role="img" '
            'preserveAspectRatio="xMidYMid meet"><title>%s</title>%s</svg>'
            % (chart_id, CHART_W, CHART_H, html.escape(title), "".join(body)))


def layer_chart(est: Estimate) -> str:
    """Bars: seconds each layer takes (from one layer marker to the next, or the end)."""
    starts = [t for _, t in est.layers]
    if not starts:
        return '<p class="empty">The file has no layer markers.</p>'
    ends = starts[1:] + [est.total_s]
    durations = [max(0.0, b - a) for a, b in zip(starts, ends, strict=True)]
    y_max = _nice_max(max(durations))
    plot_w, plot_h = CHART_W - PAD_L - PAD_R, CHART_H - PAD_T - PAD_B
    n = len(durations)
    bar_w = plot_w / n
    ticks = [(PAD_L + bar_w * (i + 0.5), str(i + 1))
             for i in range(0, n, max(1, n // 8))]
    body = _axes("layer", "seconds", y_max, x_ticks=ticks)
    for i, d in enumerate(durations):
        h = plot_h * d / y_max
        body.append('<rect class="bar" x="%.2f" y="%.2f" width="%.2f" height="%.2f" '
                    'fill="%s"><title>layer %d: %.1f s</title></rect>'
                    % (PAD_L + i * bar_w, PAD_T + plot_h - h, max(bar_w * 0.85, 0.5), h,
                       COLORS[0], i + 1, d))
    return _svg("chart-layers", "Time per layer", body)


def progress_chart(data: ReportData) -> str:
    """Lines: Klipper's true progress over time, and the slicer's M73 P at the same moments."""
    total = data.estimate.total_s or 1.0
    plot_w, plot_h = CHART_W - PAD_L - PAD_R, CHART_H - PAD_T - PAD_B

    def xy(t: float, pct: float) -> str:
        return "%.1f,%.1f" % (PAD_L + plot_w * t / total, PAD_T + plot_h - plot_h * pct / 100)

    ticks = [(PAD_L + plot_w * k / 4, format_duration(total * k / 4)) for k in range(5)]
    body = _axes("Klipper time", "% done", 100.0, "%g%%", ticks)
    body.append('<polyline class="series" fill="none" stroke="%s" stroke-width="2.5" '
                'points="%s %s"><title>Klipper (true)</title></polyline>'
                % (COLORS[2], xy(0, 0), xy(total, 100)))
    if data.slicer_progress:
        points = " ".join(xy(t, p) for t, p in data.slicer_progress)
        body.append('<polyline class="series" fill="none" stroke="%s" stroke-width="2" '
                    'points="%s"><title>%s M73</title></polyline>'
                    % (COLORS[1], points, html.escape(data.slicer.name)))
    return _svg("chart-progress", "Progress over time", body)


def feature_chart(est: Estimate) -> str:
    """Horizontal bars: seconds per feature (;TYPE: / ; FEATURE:)."""
    items = sorted(((t, name) for name, t in est.features.items() if t > 0), reverse=True)
    if not items:
        return '<p class="empty">The file names no features.</p>'
    row_h = 22
    height = PAD_T + row_h * len(items) + 8
    label_w = 190
    bar_max = CHART_W - label_w - 90
    t_max = items[0][0]
    body = []
    for i, (t, name) in enumerate(items):
        y = PAD_T + i * row_h
        w = bar_max * t / t_max
        body.append('<text x="%d" y="%d" class="tick" text-anchor="end">%s</text>'
                    % (label_w - 8, y + 15, html.escape(name[:28])))
        body.append('<rect class="bar" x="%d" y="%d" width="%.1f" height="%d" fill="%s">'
                    '<title>%s: %.1f s</title></rect>'
                    % (label_w, y + 3, max(w, 0.5), row_h - 6, COLORS[i % len(COLORS)],
                       html.escape(name), t))
        body.append('<text x="%.1f" y="%d" class="tick">%s</text>'
                    % (label_w + w + 6, y + 15, format_duration(t)))
    return ('<svg id="chart-features" class="chart" viewBox="0 0 %d %d" role="img">'
            '<title>Time per feature</title>%s</svg>' % (CHART_W, height, "".join(body)))


def speed_chart(speed: SpeedStats) -> str:
    """Per requested-speed bin: the mean peak speed reached (dots) against the diagonal."""
    if not speed.bins:
        return '<p class="empty">No kinematic moves.</p>'
    keys = sorted(speed.bins)
    v_max = _nice_max((keys[-1] + 1) * SPEED_BIN_V)
    plot_w, plot_h = CHART_W - PAD_L - PAD_R, CHART_H - PAD_T - PAD_B
    ticks = [(PAD_L + plot_w * k / 4, "%g" % (v_max * k / 4)) for k in range(5)]
    body = _axes("speed asked for (mm/s)", "speed reached (mm/s)", v_max, x_ticks=ticks)
    body.append('<line x1="%d" y1="%d" x2="%d" y2="%d" class="diag"/>'
                % (PAD_L, PAD_T + plot_h, PAD_L + plot_w, PAD_T))
    t_max = max(b.time_s for b in speed.bins.values()) or 1.0
    for key in keys:
        b = speed.bins[key]
        asked = (key + 0.5) * SPEED_BIN_V
        cx = PAD_L + plot_w * asked / v_max
        cy = PAD_T + plot_h - plot_h * b.mean_reached_v / v_max
        r = 3 + 9 * math.sqrt(b.time_s / t_max)
        body.append('<circle class="dot" cx="%.1f" cy="%.1f" r="%.1f" fill="%s" '
                    'fill-opacity="0.7"><title>asked %d-%d mm/s: reached %.0f mm/s on average,'
                    ' %.0f s of which %.0f s below speed</title></circle>'
                    % (cx, cy, r, COLORS[3], key * SPEED_BIN_V, (key + 1) * SPEED_BIN_V,
                       b.mean_reached_v, b.time_s, b.time_s - b.ideal_s))
    return _svg("chart-speed", "Speed reached against speed asked for", body)


_CSS = """
body{font:15px/1.45 system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;
background:#f6f7f9;color:#1d232b}
main{max-width:760px;margin:0 auto;padding:12px}
h1{font-size:1.3em;margin:.4em 0}h2{font-size:1.05em;margin:1.2em 0 .4em}
.cards{display:flex;flex-wrap:wrap;gap:8px}
.card{background:#fff;border-radius:8px;padding:8px 12px;flex:1 1 140px;
box-shadow:0 1px 2px #0001}
.card b{display:block;font-size:1.25em}.card span{color:#5b6570;font-size:.85em}
.chart{width:100%;height:auto;background:#fff;border-radius:8px;box-shadow:0 1px 2px #0001}
.frame{fill:none;stroke:#c9ced6}.grid{stroke:#eceff3}.diag{stroke:#9aa3ad;stroke-dasharray:4 4}
.tick{font-size:11px;fill:#5b6570}.label{font-size:12px;fill:#333}
.legend span{display:inline-block;margin-right:14px}.legend i{display:inline-block;width:12px;
height:3px;margin-right:5px;vertical-align:middle}
p.empty{color:#5b6570}footer{color:#5b6570;font-size:.8em;margin:2em 0 1em}
ul.warn{font-size:.85em;color:#7a4b00;word-break:break-word}
"""


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
        motion_s = est.parts.motion_s  # the slicer times the moves only
        diff = 100.0 * (slicer.estimate_s - motion_s) / motion_s if motion_s else 0.0
        said = "%s (%+.0f %%)" % (format_duration(slicer.estimate_s), diff)
        cards.append(("%s said" % slicer.name, said))
    if est.first_layer_s is not None:
        cards.append(("First layer", format_duration(est.first_layer_s)))
    cards.append(("Layers", str(len(est.layers))))
    lost = data.speed.lost_s
    cards.append(("Below full speed", "%s (%.0f %%)" % (
        format_duration(lost), 100.0 * lost / est.total_s if est.total_s else 0.0)))
    card_html = "".join('<div class="card"><span>%s</span><b>%s</b></div>'
                        % (html.escape(k), html.escape(v)) for k, v in cards)
    legend = ('<p class="legend"><span><i style="background:%s"></i>Klipper</span>%s</p>'
              % (COLORS[2], '' if not data.slicer_progress else
                 '<span><i style="background:%s"></i>%s M73</span>'
                 % (COLORS[1], html.escape(slicer.name))))
    warnings = "".join("<li>%s</li>" % html.escape(w) for w in est.warnings[:20])
    name = os.path.basename(est.path)
    return """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>%(title)s</title><style>%(css)s</style></head>
<body><main>
<h1>%(title)s</h1>
<div class="cards">%(cards)s</div>
<h2>Time per layer</h2>%(layers)s
<h2>Progress over time</h2>%(legend)s%(progress)s
<h2>Time per feature</h2>%(features)s
<h2>Speed reached against speed asked for</h2>
<p>Each dot is the moves whose allowed speed falls in one %(bin)g mm/s band; its size is
the time they take. Dots below the dashed line lose time to acceleration.</p>%(speed)s
%(warnings)s
<footer>kestimator %(version)s &middot; Klipper's planner replayed on %(file)s &middot;
limits: %(source)s</footer>
</main></body></html>
""" % {
        "title": html.escape("Klipper time for " + name), "css": _CSS, "cards": card_html,
        "layers": layer_chart(est), "legend": legend, "progress": progress_chart(data),
        "features": feature_chart(est), "speed": speed_chart(data.speed),
        "bin": SPEED_BIN_V,
        "warnings": ('<h2>Warnings</h2><ul class="warn">%s</ul>' % warnings) if warnings else "",
        "version": __version__, "file": html.escape(name),
        "source": html.escape(data.limits_source),
    }
