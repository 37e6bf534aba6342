"""plugins/klipper/frontend_settings.py (install.sh --frontend-settings) against the real
Moonraker (PyPI moonraker 0.11.0, tests/moonraker_host.py): Mainsail's and Fluidd's settings set
through Moonraker's database API, and put back on undo; and Mainsail's own code
(tests/frontends/) reading those very database entries shows the module's remaining time."""
from __future__ import annotations

import json
import subprocess
import sys
import urllib.parse
from pathlib import Path
from typing import Any

from tests.conftest import PROJECT
from tests.moonraker_host import (  # noqa: F401 (moonraker_python is the session fixture)
    _free_port,
    _moonraker,
    _request,
    _wait_ready,
    moonraker_python,
)

TOOL = PROJECT / "plugins" / "klipper" / "frontend_settings.py"


def _data(tmp_path: Path, port: int) -> Path:
    data = tmp_path / "printer_data"
    for folder in ("config", "gcodes", "logs", "comms", "database"):
        (data / folder).mkdir(parents=True)
    (data / "config" / "moonraker.conf").write_text(
        "[server]\nhost: 127.0.0.1\nport: %d\nklippy_uds_address: %s\n\n"
        "[machine]\nprovider: none\nvalidate_service: False\n\n"
        "[authorization]\ntrusted_clients:\n  127.0.0.0/8\n"
        % (port, data / "comms" / "klippy.sock"))
    return data


def _tool(base: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(TOOL), "--moonraker", base, *args],
                          capture_output=True, text=True, timeout=60)


def _namespace(base: str, namespace: str) -> dict[str, Any]:
    query = urllib.parse.urlencode({"namespace": namespace})
    try:
        return dict(_request(base + "/server/database/item?" + query)["result"]["value"])
    except Exception:
        return {}


def _item(base: str, namespace: str, key: str, value: Any) -> None:
    _request(base + "/server/database/item", "POST",
             json.dumps({"namespace": namespace, "key": key, "value": value}).encode(),
             {"Content-Type": "application/json"})


def test_the_settings_are_set_through_moonraker_and_undone(
        moonraker_python: str, tmp_path: Path) -> None:  # noqa: F811
    port = _free_port()
    data = _data(tmp_path, port)
    base = "http://127.0.0.1:%d" % port
    with _moonraker(moonraker_python, data, port) as process:
        _wait_ready(base, process, data / "logs" / "stdout.log")
        # The user had chosen an ETA of their own, and a theme; Fluidd was never opened.
        _item(base, "mainsail", "general.calcEtaTime", ["file", "slicer"])
        _item(base, "mainsail", "uiSettings.theme", "dark")
        done = _tool(base)
        assert done.returncode == 0, done.stderr
        mainsail = _namespace(base, "mainsail")
        assert mainsail["general"] == {"calcPrintProgress": "slicer",
                                       "calcEstimateTime": ["file"], "calcEtaTime": ["file"]}
        assert mainsail["uiSettings"] == {"theme": "dark"}
        fluidd = _namespace(base, "fluidd")
        assert fluidd["uiSettings"]["general"]["printProgressCalculation"] == ["slicer"]
        # Twice changes nothing, and keeps the first record of what was there.
        again = _tool(base)
        assert again.returncode == 0 and "nothing to change" in again.stdout
        # The user changes one of them since: theirs stays on undo.
        _item(base, "mainsail", "general.calcEstimateTime", ["filament"])
        undone = _tool(base, "--undo")
        assert undone.returncode == 0, undone.stderr
        mainsail = _namespace(base, "mainsail")
        assert mainsail["general"] == {"calcEtaTime": ["file", "slicer"],
                                       "calcEstimateTime": ["filament"]}
        assert mainsail["uiSettings"] == {"theme": "dark"}
        assert "printProgressCalculation" not in _namespace(base, "fluidd").get(
            "uiSettings", {}).get("general", {})
        assert _namespace(base, "kestimator") == {}


def test_without_moonraker_one_line_says_why(tmp_path: Path) -> None:
    port = _free_port()
    done = _tool("http://127.0.0.1:%d" % port)
    assert done.returncode == 1
    assert done.stdout == ""
    assert len(done.stderr.strip().splitlines()) == 1
    assert "cannot reach Moonraker" in done.stderr
