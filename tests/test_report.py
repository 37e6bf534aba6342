"""`kestimator report`: a self-contained page that a real browser draws readably.

The Chromium tests render the reports of corpus files (one per slicer family, files with
labelled objects, one with guessed limits) at a phone's 390 px and a desktop's 1280 px and
measure the page as laid out, with a test-only script appended to a copy of the page.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from typing import Any

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.limits import Limits
from kestimator.report import (
    Axis,
    ReportData,
    collect,
    remaining_error,
    render_html,
    tick_time,
)

from .conftest import CORPUS_CFG, require_program

CHART_IDS = ("chart-remaining", "chart-layers", "chart-features", "chart-speed")
BENCHY = "gcode/prusaslicer/gcodepreview_benchy_ps2.6.1.gcode"
# (corpus file, uses printer.cfg): one per slicer family, objects, guessed limits.
PAGES = {
    "prusaslicer": (BENCHY, True),
    "orca-objects": ("gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode", True),
    "prusa-4-objects": ("gcode/prusaslicer/ps25_torus_x4_labels_marlin.gcode", True),
    "cura-guessed": ("gcode/cura/cura413_ender3_nut_small.gcode", False),
    "generic-ideamaker": ("gcode/ideamaker/cancelobj_ideamaker4.2.0.gcode", True),
}
WIDTHS = (390, 1280)
MIN_FONT_PX = 11.0
# Appended by the test only: measures the laid-out page and prints the result as JSON.
MEASURE_JS = """<script>
function rect(e) { var b = e.getBoundingClientRect();
  return {l: b.left, r: b.right, t: b.top, b: b.bottom, w: b.width, h: b.height}; }
var out = {charts: {}, texts: [], html_fonts: [], viewport: document.documentElement.clientWidth,
           scroll_w: document.documentElement.scrollWidth};
document.querySelectorAll("svg.chart").forEach(function (svg) {
  var box = rect(svg), scale = box.w / svg.viewBox.baseVal.width;
  var marks = svg.querySelectorAll("rect.bar, circle.dot, polyline.series");
  var chart = {box: box, marks: marks.length, bars: []};
  svg.querySelectorAll("text").forEach(function (t) {
    out.texts.push({chart: svg.id, text: t.textContent, box: rect(t), svg: box,
                    px: parseFloat(getComputedStyle(t).fontSize) * scale});
  });
  svg.querySelectorAll("rect.bar[data-seconds]").forEach(function (r) {
    chart.bars.push(parseFloat(r.getAttribute("data-seconds")));
  });
  var truth = svg.querySelector("polyline.truth"), slicer = svg.querySelector("polyline.slicer");
  if (truth && slicer) {
    var a = truth.points.getItem(0), b = truth.points.getItem(1), gap = 0;
    for (var i = 0; i < slicer.points.numberOfItems; i++) {
      var p = slicer.points.getItem(i);
      var y = a.y + (b.y - a.y) * (p.x - a.x) / (b.x - a.x);
      gap = Math.max(gap, Math.abs(p.y - y) * scale);
    }
    chart.series_gap_px = gap;
  }
  out.charts[svg.id] = chart;
});
var walker = document.createTreeWalker(document.querySelector("main"), NodeFilter.SHOW_TEXT);
while (walker.nextNode()) {
  var node = walker.currentNode, el = node.parentElement;
  if (!node.textContent.trim() || el.closest("svg")) continue;
  var r = document.createRange(); r.selectNodeContents(node); var b = r.getBoundingClientRect();
  out.html_fonts.push({text: node.textContent.slice(0, 40),
                       px: parseFloat(getComputedStyle(el).fontSize), l: b.left, r: b.right});
}
out.total_s = parseFloat(document.querySelector("main").getAttribute("data-total-s"));
parent.postMessage(JSON.stringify(out), "*");
</script>"""
# Headless Chromium keeps its window at least 500 px wide: the report is laid out in an
# iframe exactly `width` px wide, which is its viewport; it posts its measurements here.
FRAME_PAGE = """<!DOCTYPE html><html><body style="margin:0">
<iframe src="%(src)s" style="border:0;width:%(width)dpx;height:900px"></iframe>
<script>
window.addEventListener("message", function (event) {
  var pre = document.createElement("pre"); pre.id = "measured";
  pre.textContent = event.data; document.body.appendChild(pre);
});
</script></body></html>"""


@pytest.fixture(scope="module")
def cfg_limits() -> Limits:
    return limits_from_printer_cfg(CORPUS_CFG)[0]


@pytest.fixture(scope="module")
def reports(corpus_root: Path, cfg_limits: Limits) -> dict[str, tuple[ReportData, str]]:
    out = {}
    for key, (rel, with_cfg) in PAGES.items():
        if with_cfg:
            data = collect(str(corpus_root / rel), cfg_limits, str(CORPUS_CFG))
        else:
            resolved = resolve_limits(LimitRequest(
                gcode=str(corpus_root / rel), use_profile=False, environ={},
                read_slicer_environment=False))
            data = collect(str(corpus_root / rel), resolved.limits, resolved.summary,
                           limit_warnings=resolved.warnings, limit_sources=resolved.sources,
                           guessed_limits=resolved.machine is None)
        out[key] = (data, render_html(data))
    return out


def test_report_is_self_contained(reports: dict[str, tuple[ReportData, str]]) -> None:
    for _, page in reports.values():
        assert "<script" not in page
        assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", page)
        assert "http://" not in page and "https://" not in page
        for chart_id in CHART_IDS:
            assert 'id="%s"' % chart_id in page
        assert 'name="viewport"' in page


def test_report_shows_klipper_and_slicer_times(
        reports: dict[str, tuple[ReportData, str]]) -> None:
    data, page = reports["prusaslicer"]
    assert "41m 55s" in page          # Klipper: 2515.2 s
    assert "PrusaSlicer said" in page and "38m 43s" in page
    assert page.count('class="bar"') >= 160  # one bar per layer, plus features
    worst = remaining_error(data)
    assert worst is not None and worst[1] < -180   # M73 R is minutes short
    assert "(M73 R)" in page


def test_guessed_limits_are_a_banner_above_the_numbers(
        reports: dict[str, tuple[ReportData, str]]) -> None:
    page = reports["cura-guessed"][1]
    assert page.index("Guessed limits") < page.index('class="cards"')
    assert page.index("no printer.cfg or Moonraker given") < page.index('class="cards"')
    assert "(;TIME_ELAPSED:)" in page


def test_a_file_without_remaining_time_says_so(corpus_root: Path, cfg_limits: Limits) -> None:
    data = collect(str(corpus_root / "gcode/prusaslicer/ps25_sphere_reprap_noM73.gcode"),
                   cfg_limits, "printer.cfg")
    page = render_html(data)
    assert not data.slicer_remaining
    assert "wrote no remaining time into the file" in page


def test_layers_carry_their_z(reports: dict[str, tuple[ReportData, str]]) -> None:
    data, page = reports["prusaslicer"]
    assert data.layer_z[0] == pytest.approx(0.3)  # ;Z:0.3 after the first ;LAYER_CHANGE
    assert "layer 2 (Z 0.6 mm)" in page  # ;Z:0.6, not the 0.5 mm Z hop before it


def test_axis_ticks_fall_on_round_values() -> None:
    assert [label for _, label in Axis(2515.2, timed=True).ticks()] == [
        "0", "10m", "20m", "30m", "40m", "50m"]
    assert [label for _, label in Axis(8242.0, timed=True).ticks()] == [
        "0", "30m", "1h", "1h 30m", "2h", "2h 30m"]
    assert [label for _, label in Axis(160.0, timed=False).ticks()] == [
        "0", "50", "100", "150", "200"]
    assert [v for v, _ in Axis(95.0, timed=False).ticks()] == [0, 20, 40, 60, 80, 100]
    assert tick_time(5400) == "1h 30m" and tick_time(45) == "45s"


def _measure(browser: str, page: str, width: int, tmp_path: Path) -> dict[str, Any]:
    report_path = tmp_path / ("report-%d.html" % width)
    report_path.write_text(page.replace("</body>", MEASURE_JS + "</body>"), encoding="utf-8")
    html_path = tmp_path / ("frame-%d.html" % width)
    html_path.write_text(FRAME_PAGE % {"src": report_path.name, "width": width},
                         encoding="utf-8")
    proc = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--hide-scrollbars",
         "--user-data-dir=%s" % (tmp_path / ("profile-%d" % width)),
         "--window-size=%d,1000" % max(width, 800), "--virtual-time-budget=3000", "--dump-dom",
         html_path.as_uri()],
        capture_output=True, text=True, timeout=120)
    match = re.search(r'<pre id="measured">(.*?)</pre>', proc.stdout, re.S)
    assert match, proc.stderr[-2000:]
    text = match.group(1).replace("&quot;", '"').replace("&lt;", "<").replace(
        "&gt;", ">").replace("&amp;", "&")
    measured: dict[str, Any] = json.loads(text)
    return measured


@pytest.mark.parametrize("key", sorted(PAGES))
def test_chromium_draws_every_chart_readably_at_phone_and_desktop_width(
        key: str, reports: dict[str, tuple[ReportData, str]], tmp_path: Path) -> None:
    browser = require_program("chromium")
    data, page = reports[key]
    for width in WIDTHS:
        m = _measure(browser, page, width, tmp_path)
        viewport = m["viewport"]
        assert viewport == width, m["viewport"]
        assert m["scroll_w"] <= viewport, (width, "page wider than the screen")
        expected = set(CHART_IDS) | ({"chart-objects"} if data.estimate.objects else set())
        assert expected <= set(m["charts"]), (width, sorted(m["charts"]))
        for chart_id, chart in m["charts"].items():
            box = chart["box"]
            # Axis charts keep their aspect ratio; bar lists grow with their rows.
            min_h = 30 if chart_id in ("chart-features", "chart-objects") else 180
            assert min_h < box["h"] and 300 <= box["w"] <= viewport, (width, chart_id, box)
            assert chart["marks"] > 0, (width, chart_id)
        for t in m["texts"]:
            svg, b = t["svg"], t["box"]
            where = (width, t["chart"], t["text"], b, svg)
            assert svg["l"] - 0.5 <= b["l"] and b["r"] <= svg["r"] + 0.5, where
            assert svg["t"] - 0.5 <= b["t"] and b["b"] <= svg["b"] + 0.5, where
            assert 0 <= b["l"] and b["r"] <= viewport, where
            assert t["px"] >= MIN_FONT_PX, where
        for f in m["html_fonts"]:
            assert f["px"] >= MIN_FONT_PX, (width, f)
            assert -0.5 <= f["l"] and f["r"] <= viewport + 0.5, (width, f)
        # The display's two series differ where the slicer's estimate differs from Klipper's.
        remaining = m["charts"]["chart-remaining"]
        worst = remaining_error(data)
        if worst is not None and abs(worst[1]) > 0.05 * data.estimate.total_s:
            assert remaining["series_gap_px"] >= 5, (width, remaining)
        elif worst is None:
            assert "series_gap_px" not in remaining
        # Per-object times, read back from the page, sum to the print's time.
        if data.estimate.objects:
            bars = m["charts"]["chart-objects"]["bars"]
            assert len(bars) >= 2
            assert sum(bars) == pytest.approx(m["total_s"], abs=1.0)
            assert m["total_s"] == pytest.approx(data.estimate.total_s, abs=1e-5)


def test_preflight_and_untimed_commands_are_banners_not_one_warning_per_command(
        reports: dict[str, tuple[ReportData, str]]) -> None:
    # The Orca file runs EXCLUDE_OBJECT_*, SET_PRINT_STATS_INFO and macros the corpus
    # printer.cfg does not configure: Klipper skips them, and the page says so above the
    # numbers, with the untimed commands grouped in one line as the text summary does.
    page = reports["orca-objects"][1]
    cards = page.index('class="cards"')
    assert page.index("Pre-flight: ") < cards
    assert page.index("commands skipped") < cards
    assert re.search(r"\d+ macros?, \d+ module commands?", page)
    assert "is not a Klipper command" not in page
