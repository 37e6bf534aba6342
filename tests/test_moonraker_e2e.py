"""The real Moonraker (PyPI `moonraker`) runs kestimator-compat as its klipper_estimator.

Moonraker is started on 127.0.0.1 with `[analysis]` auto-analysis on and our launcher at
`<data>/tools/klipper_estimator/klipper_estimator_linux`, without Klipper (its socket does
not exist). Corpus files are uploaded through `/server/files/upload`; the stored files,
`/server/files/metadata` and `/server/analysis/estimate` must carry kestimator's times.

Moonraker is installed into a throwaway venv (it pins many packages of its own); set
KESTIMATOR_MOONRAKER_PYTHON to a Python that already has it to skip the install.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from kestimator import __version__, compat
from kestimator.config.klipper_estimator import dump_config
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.estimate import estimate_file
from tests.conftest import CORPUS, CORPUS_CFG, PROJECT

# Shared with test_install_sh.py; test_learn_moonraker_e2e.py and test_moonraker_metadata.py
# import these names from here. moonraker_python is the session fixture.
from tests.moonraker_host import (  # noqa: F401
    HTTP_TIMEOUT_S,
    METADATA_TIMEOUT_S,
    START_TIMEOUT_S,
    _free_port,
    _metadata,
    _moonraker,
    _request,
    _upload,
    _wait_ready,
    moonraker_python,
)

UPLOADS = (
    "prusaslicer/ps25_nut_accelA_small.gcode",
    "cura/cura413_ender3_nut_small.gcode",
)
M73_RE = re.compile(rb"^M73\b.*$", re.MULTILINE)


def _install_estimator(data: Path) -> None:
    """What plugins/moonraker/README.md tells a user to do, pointed at this checkout."""
    tools = data / "tools" / "klipper_estimator"
    tools.mkdir(parents=True)
    launcher = tools / "klipper_estimator_linux"
    script = Path(sys.executable).with_name("kestimator-compat")
    if script.is_file():
        launcher.symlink_to(script)
        return
    launcher.write_text("#!/bin/sh\nPYTHONPATH=%s exec %s -m kestimator.compat \"$@\"\n"
                        % (_sh(str(PROJECT)), _sh(sys.executable)))
    launcher.chmod(0o755)


def _sh(text: str) -> str:
    return "'" + text.replace("'", "'\\''") + "'"


def test_moonraker_upload_stores_kestimator_times_metadata_and_analysis_estimate(
        moonraker_python: str, corpus_root: Path, tmp_path: Path) -> None:  # noqa: F811
    data = tmp_path / "printer_data"
    for folder in ("config", "gcodes", "logs", "comms", "database"):
        (data / folder).mkdir(parents=True)
    _install_estimator(data)
    machine = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False))
    config = data / "config" / "estimator.json"
    config.write_text(json.dumps(dump_config(machine.limits, machine.sources), indent=2))
    port = _free_port()
    (data / "config" / "moonraker.conf").write_text(
        "[server]\nhost: 127.0.0.1\nport: %d\nklippy_uds_address: %s\n\n"
        "[machine]\nprovider: none\nvalidate_service: False\n\n"
        "[authorization]\ntrusted_clients:\n  127.0.0.0/8\n\n"
        "[file_manager]\nenable_object_processing: False\n\n"
        "[analysis]\nplatform: linux\nenable_auto_analysis: True\n"
        "estimator_config: estimator.json\n"
        % (port, data / "comms" / "klippy.sock"))
    base = "http://127.0.0.1:%d" % port
    log = data / "logs" / "stdout.log"
    started = time.monotonic()
    with _moonraker(moonraker_python, data, port) as process:
        info = _wait_ready(base, process, log)
        assert info["klippy_state"] != "ready"  # no Klipper behind it
        status = _request(base + "/server/analysis/status")["result"]
        assert status["estimator_ready"] is True
        assert status["estimator_version"] == __version__
        for relative in UPLOADS:
            source = CORPUS / "gcode" / relative
            limits = resolve_limits(LimitRequest(
                gcode=source, estimator_config=config, use_profile=False,
                read_slicer_environment=False)).limits
            assert limits == machine.limits
            expected = estimate_file(source, limits).total_s
            local = tmp_path / source.name
            shutil.copyfile(source, local)
            assert compat.main(["--config_file", str(config), "post-process",
                                str(local)]) == 0

            _upload(base, source)
            meta = _metadata(base, source.name)
            stored = (data / "gcodes" / source.name).read_bytes()
            # Moonraker stored exactly what kestimator-compat writes (true M73, rewritten
            # time comments, our marker) and ran it once.
            assert stored == local.read_bytes()
            assert stored != source.read_bytes()
            m73 = M73_RE.findall(stored)
            assert m73[0] == b"M73 P0 R%d" % int(expected / 60.0 + 0.5)
            assert m73[-1] == b"M73 P100 R0"
            assert all(re.fullmatch(rb"M73 P\d+ R\d+\r?", line) for line in m73)
            assert b"; kestimator %s klipper_s=%.3f " % (__version__.encode(), expected) \
                in stored
            assert stored.rstrip(b"\r\n").endswith(compat.IDENT_LINE.encode())
            # Moonraker's own slicer parser reads our rewritten estimate.
            assert abs(meta["estimated_time"] - expected) <= 1.0
            assert meta["estimated_time"] != pytest.approx(
                _metadata_of_original(moonraker_python, source), abs=1.0)

            answer = _request(base + "/server/analysis/estimate?" + urllib.parse.urlencode(
                {"filename": source.name}), "POST")["result"]
            assert answer["total_time"] == pytest.approx(expected, abs=1e-6)
            assert answer["num_moves"] > 0
            again = _request(base + "/server/analysis/process?" + urllib.parse.urlencode(
                {"filename": source.name}), "POST")["result"]
            assert again == {"prev_processed": True, "version": __version__,
                             "bypassed": True}
            assert (data / "gcodes" / source.name).read_bytes() == stored
    assert time.monotonic() - started < START_TIMEOUT_S + len(UPLOADS) * METADATA_TIMEOUT_S


def _metadata_of_original(python: str, source: Path) -> float:
    """Moonraker's own estimated_time of the unprocessed file (the slicer's number).

    Read from a copy: Moonraker's parser writes thumbnails beside the file it reads, and
    `source` is in the shared corpus."""
    script = ("import json,sys\nfrom moonraker.components.file_manager import metadata\n"
              "print(json.dumps(metadata.extract_metadata(sys.argv[1], [])))")
    with tempfile.TemporaryDirectory() as scratch:
        copy = Path(scratch) / source.name
        shutil.copyfile(source, copy)
        out = subprocess.run([python, "-c", script, str(copy)], check=True,
                             capture_output=True, timeout=HTTP_TIMEOUT_S).stdout
    return float(json.loads(out)["estimated_time"])
