"""`kestimator report`: a self-contained page whose charts a real browser draws."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.report import collect, render_html

from .conftest import CORPUS_CFG, IN_CI

CHART_IDS = ("chart-layers", "chart-progress", "chart-features", "chart-speed")
BENCHY = "gcode/prusaslicer/gcodepreview_benchy_ps2.6.1.gcode"
# Appended by the test only: measures every chart as laid out and prints the result.
MEASURE_JS = """<script>
var out = {};
document.querySelectorAll("svg.chart").forEach(function (svg) {
  var box = svg.getBoundingClientRect();
  out[svg.id] = {w: box.width, h: box.height,
                 marks: svg.querySelectorAll("rect.bar, circle.dot, polyline.series").length};
});
out.viewport = document.documentElement.clientWidth;
var pre = document.createElement("pre"); pre.id = "measured";
pre.textContent = JSON.stringify(out); document.body.appendChild(pre);
</script>"""


@pytest.fixture(scope="module")
def benchy_html(corpus_root: Path) -> str:
    limits, _ = limits_from_printer_cfg(CORPUS_CFG)
    data = collect(str(corpus_root / BENCHY), limits, "printer.cfg")
    return render_html(data)


def test_report_is_self_contained(benchy_html: str) -> None:
    assert "<script" not in benchy_html
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", benchy_html)
    assert "http://" not in benchy_html and "https://" not in benchy_html
    for chart_id in CHART_IDS:
        assert 'id="%s"' % chart_id in benchy_html
    assert 'name="viewport"' in benchy_html


def test_report_shows_klipper_and_slicer_times(benchy_html: str) -> None:
    assert "41m 55s" in benchy_html          # Klipper: 2515.2 s
    assert "PrusaSlicer said" in benchy_html and "38m 43s" in benchy_html
    assert benchy_html.count('class="bar"') >= 160  # one bar per layer, plus features


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def test_charts_are_drawn_by_headless_chromium(benchy_html: str, tmp_path: Path) -> None:
    browser = _chromium()
    if browser is None:
        if IN_CI:
            pytest.fail("chromium is not installed (.ci/run installs it)")
        pytest.skip("chromium is not installed")
    page = tmp_path / "report.html"
    page.write_text(benchy_html.replace("</body>", MEASURE_JS + "</body>"), encoding="utf-8")
    proc = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--user-data-dir=%s" % (tmp_path / "profile"),
         "--window-size=390,844", "--virtual-time-budget=3000", "--dump-dom",
         page.as_uri()],
        capture_output=True, text=True, timeout=120)
    match = re.search(r'<pre id="measured">(.*?)</pre>', proc.stdout, re.S)
    assert match, proc.stderr[-2000:]
    measured = json.loads(match.group(1).replace("&quot;", '"'))
    viewport = measured["viewport"]
    assert viewport < 760  # narrower than the page's widest layout: the phone case
    for chart_id in CHART_IDS:
        box = measured[chart_id]
        # Each chart fills the narrow screen (less the page margin), with height and content.
        assert viewport - 40 <= box["w"] <= viewport and box["h"] > 100, (chart_id, box)
        assert box["marks"] > 0, chart_id
