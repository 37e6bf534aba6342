"""Issue 38 item 1: an upload Moonraker labels after kestimator-compat keeps a valid table.

The real Moonraker (PyPI `moonraker` 0.11.0, with preprocess_cancellation) runs with
``[file_manager] enable_object_processing: True``: it runs our estimator first and labels the
objects after it. The stored file must carry Moonraker's labels and a table made for the
labelled file: the worker follows it (`source: table`) with the times of a fresh estimate of
that file, and `kestimator inject` of the stored file changes nothing.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from kestimator import compat
from kestimator.config.klipper_estimator import dump_config
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.estimate import estimate_file
from kestimator.moonraker_labels import Labeller, table_for_labelled_file, table_points
from kestimator.progress_table import content_matches, read_table_file, spacing_bound
from kestimator.rewrite import inject_file
from tests.conftest import CORPUS, CORPUS_CFG, PROJECT
from tests.moonraker_host import (  # noqa: F401 (moonraker_python is the session fixture)
    _free_port,
    _metadata,
    _moonraker,
    _upload,
    _wait_ready,
    moonraker_python,
)
from tests.test_moonraker_e2e import _install_estimator

# PrusaSlicer 2.4 and 2.5 ("; printing object"), PrusaSlicer 2.3.3 (its settings block read
# from the file's end: the table goes before it), Cura (";MESH:"), and one in CRLF.
UPLOADS = (
    "prusaslicer/cancelobj_ps2.4.0a1_arcwelder.gcode",
    "prusaslicer/ps25_torus_x4_labels_marlin.gcode",
    "prusaslicer/cancelobj_ps2.3.3_issue1.gcode",
    "cura/cancelobj_cura4.10.0.gcode",
)
CRLF_SOURCE = "prusaslicer/cancelobj_ps2.4.0a1_arcwelder.gcode"


def _ask_worker(tmp_path: Path, path: Path, use_table: bool = True) -> dict[str, Any]:
    env = dict(os.environ, PYTHONPATH=str(PROJECT), HOME=str(tmp_path),
               XDG_CONFIG_HOME=str(tmp_path / "worker-config"),
               XDG_CACHE_HOME=str(tmp_path / "worker-cache"))
    request = {"id": 1, "file": str(path), "config": str(CORPUS_CFG), "events": [],
               "use_table": use_table}
    done = subprocess.run([sys.executable, "-m", "kestimator.worker"], env=env,
                          input=json.dumps(request).encode() + b"\n", capture_output=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.splitlines()[0])  # type: ignore[no-any-return]


def test_an_upload_moonraker_labels_keeps_a_table_made_for_the_labelled_file(
        moonraker_python: str, tmp_path: Path) -> None:  # noqa: F811
    data = tmp_path / "printer_data"
    for folder in ("config", "gcodes", "logs", "comms", "database"):
        (data / folder).mkdir(parents=True)
    _install_estimator(data)
    profile = data / "xdg-config" / "kestimator" / "config.toml"
    profile.parent.mkdir(parents=True)
    profile.write_text('printer_cfg = %s\n' % json.dumps(str(CORPUS_CFG)))
    machine = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False))
    (data / "config" / "estimator.json").write_text(
        json.dumps(dump_config(machine.limits, machine.sources)))
    port = _free_port()
    (data / "config" / "moonraker.conf").write_text(
        "[server]\nhost: 127.0.0.1\nport: %d\nklippy_uds_address: %s\n\n"
        "[machine]\nprovider: none\nvalidate_service: False\n\n"
        "[authorization]\ntrusted_clients:\n  127.0.0.0/8\n\n"
        "[file_manager]\nenable_object_processing: True\n\n"
        "[analysis]\nplatform: linux\nenable_auto_analysis: True\n"
        "estimator_config: estimator.json\n"
        % (port, data / "comms" / "klippy.sock"))
    crlf = tmp_path / "upload" / ("crlf_" + Path(CRLF_SOURCE).name)
    crlf.parent.mkdir()
    crlf.write_bytes((CORPUS / "gcode" / CRLF_SOURCE).read_bytes().replace(b"\n", b"\r\n"))
    sources = [CORPUS / "gcode" / name for name in UPLOADS] + [crlf]
    limits = limits_from_printer_cfg(CORPUS_CFG)[0]
    base = "http://127.0.0.1:%d" % port
    with _moonraker(moonraker_python, data, port) as process:
        _wait_ready(base, process, data / "logs" / "stdout.log")
        for source in sources:
            _upload(base, source)
            meta = _metadata(base, source.name)
            stored = data / "gcodes" / source.name
            text = stored.read_bytes()
            # Moonraker labelled it after us (its own labelling ran, not ours) ...
            assert meta["file_processors"] == ["klipper_estimator", "preprocess_cancellation"]
            assert b"\nEXCLUDE_OBJECT_DEFINE NAME=" in text
            assert b"; Pre-Processed for Cancel-Object support" in text
            # ... and the table holds for the labelled file.
            table = read_table_file(stored)
            with open(stored, "rb") as f:
                assert content_matches(f, table)
            fresh = estimate_file(stored, limits).total_s
            answer = _ask_worker(tmp_path, stored)
            assert answer["ok"] and answer["source"] == "table", answer
            assert answer["warnings"] == []
            assert abs(answer["total_s"] - fresh) < 0.001
            # At every line, the table's time is the fresh estimate's, within the table's
            # interpolation bound.
            estimated = _ask_worker(tmp_path, stored, use_table=False)
            assert estimated["ok"] and estimated["source"] == "estimate", estimated
            assert len(estimated["offsets"]) > 100
            for offset, t in zip(estimated["offsets"], estimated["times"]):
                assert abs(table.time_at(offset) - t) <= spacing_bound(fresh - t) + 0.002
            assert text.rstrip(b"\r\n").endswith(compat.IDENT_LINE.encode())


class _MovingLabeller(Labeller):
    """A labelling that inserts one line more each time it runs, so our output's table can
    never be made to hold for what it makes."""

    def label(self, uploaded: str, copy: str) -> bool:
        runs = getattr(self, "runs", 0) + 1
        object.__setattr__(self, "runs", runs)
        body = Path(copy).read_bytes()
        Path(copy).write_bytes(b"; moved\n" * runs + body)
        return True


def test_a_labelling_that_does_not_repeat_leaves_the_unlabelled_table_and_says_why(
        tmp_path: Path) -> None:
    source = CORPUS / "gcode" / UPLOADS[0]
    output = tmp_path / source.name
    shutil.copyfile(source, output)
    limits = limits_from_printer_cfg(CORPUS_CFG)[0]
    inject_file(output, limits)
    before = output.read_bytes()
    done = table_for_labelled_file(str(output), str(source), _MovingLabeller("", ""),
                                   lambda copy: table_points(copy, limits))
    assert not done.labelled
    assert "the table holds for the unlabelled file only" in done.why
    assert output.read_bytes() == before


def test_without_moonraker_as_parent_post_process_labels_nothing(tmp_path: Path) -> None:
    """Run by anything but Moonraker's metadata run (here: pytest), post-process is the
    plain inject: the file keeps its unlabelled table."""
    source = CORPUS / "gcode" / UPLOADS[0]
    output = tmp_path / source.name
    shutil.copyfile(source, output)
    assert compat.main(["post-process", str(output)]) == 0
    assert b"EXCLUDE_OBJECT_DEFINE" not in output.read_bytes()
    with open(output, "rb") as f:
        assert content_matches(f, read_table_file(output))


@pytest.mark.parametrize("config, found", [
    ({"check_objects": True}, True),
    ({"check_objects": False}, False),
    ({}, False),
    ([1, 2], False),
])
def test_the_labeller_is_moonrakers_only_when_its_metadata_run_processes_objects(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, config: object, found: bool) -> None:
    from kestimator import moonraker_labels

    script = tmp_path / "moonraker" / "components" / "file_manager" / "metadata.py"
    script.parent.mkdir(parents=True)
    script.write_text("")
    cfg = tmp_path / "md.json"
    cfg.write_text(json.dumps(config))
    monkeypatch.setattr(moonraker_labels, "_parent_args",
                        lambda pid: ["/venv/bin/python", str(script), "-c", str(cfg)])
    got = moonraker_labels.moonraker_labeller(os.getpid())
    assert (got == Labeller("/venv/bin/python", str(script))) is found
    monkeypatch.setattr(moonraker_labels, "_parent_args", lambda pid: ["/bin/sh", "-c", "x"])
    assert moonraker_labels.moonraker_labeller(os.getpid()) is None


# Moonraker's metadata run as far as kestimator-compat sees it: a `metadata.py -c CONFIG`
# parent (with object processing on) that runs the estimator on the file, and a labelling
# (its BaseSlicer/process_objects) that takes long: Moonraker's time limit kills the
# estimator (SIGKILL) while it labels.
_SLOW_METADATA = r'''
import json, os, subprocess, sys, time
if __name__ == "__main__":
    config = json.load(open(sys.argv[2]))
    estimator = subprocess.Popen(config["command"])
    with open(config["pid_file"], "w") as f:
        f.write(str(estimator.pid))
    estimator.wait()
else:
    class BaseSlicer:
        @classmethod
        def from_file(cls, path):
            return cls()

    def process_objects(path, slicer):
        import tempfile
        tempfile.mkstemp(prefix="labelling-")  # as Moonraker's does, in TMPDIR
        with open(os.environ["LABELLER_PID_FILE"], "w") as f:
            f.write(str(os.getpid()))
        time.sleep(300)
        return False
'''


def _gone(pid: int) -> bool:
    try:
        with open("/proc/%d/stat" % pid) as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def _wait_for(path: Path, timeout: float = 120.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and path.read_text().strip():
            return int(path.read_text())
        time.sleep(0.05)
    pytest.fail("%s was never written" % path)


def test_a_post_process_killed_while_labelling_leaves_nothing_behind(tmp_path: Path) -> None:
    """Killed (SIGKILL) while Moonraker's labelling runs ahead: the labelling program exits
    with it, and the next run into the folder removes the copy beside the file (hidden, full
    size) and the private folder in TMPDIR; the uploaded file is as it was."""
    script = tmp_path / "moonraker" / "components" / "file_manager" / "metadata.py"
    script.parent.mkdir(parents=True)
    script.write_text(_SLOW_METADATA)
    gcodes = tmp_path / "gcodes"
    gcodes.mkdir()
    temp = tmp_path / "tmp"
    temp.mkdir()
    source = CORPUS / "gcode" / UPLOADS[1]
    upload = gcodes / source.name
    shutil.copyfile(source, upload)
    machine = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False))
    estimator_cfg = tmp_path / "estimator.json"
    estimator_cfg.write_text(json.dumps(dump_config(machine.limits, machine.sources)))
    config = tmp_path / "md.json"
    config.write_text(json.dumps({
        "check_objects": True, "pid_file": str(tmp_path / "estimator.pid"),
        "command": [sys.executable, "-m", "kestimator.compat", "--config_file",
                    str(estimator_cfg), "post-process", str(upload)]}))
    env = dict(os.environ, PYTHONPATH=str(PROJECT), TMPDIR=str(temp),
               LABELLER_PID_FILE=str(tmp_path / "labeller.pid"),
               XDG_CONFIG_HOME=str(tmp_path / "config"), XDG_CACHE_HOME=str(tmp_path / "cache"))
    metadata = subprocess.Popen([sys.executable, str(script), "-c", str(config)], env=env,
                                cwd=str(tmp_path))
    try:
        estimator = _wait_for(tmp_path / "estimator.pid")
        labeller = _wait_for(tmp_path / "labeller.pid")
        hidden = [p for p in gcodes.iterdir() if p.name.endswith(".kestimator-tmp")]
        assert hidden and [p.name for p in temp.iterdir()]
        os.kill(estimator, signal.SIGKILL)  # Moonraker's time limit
        metadata.wait(timeout=30)
        deadline = time.monotonic() + 5.0
        while not _gone(labeller) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(labeller), "the labelling runs on without its parent"
    finally:
        metadata.kill()
        metadata.wait(timeout=30)
        if (tmp_path / "labeller.pid").exists() and not _gone(int(
                (tmp_path / "labeller.pid").read_text())):
            os.kill(int((tmp_path / "labeller.pid").read_text()), signal.SIGKILL)
    assert upload.read_bytes() == source.read_bytes()
    # The next upload's run (not labelling: no Moonraker above it) into the same folder.
    other = gcodes / "other.gcode"
    shutil.copyfile(CORPUS / "gcode" / UPLOADS[0], other)
    done = subprocess.run([sys.executable, "-m", "kestimator.compat", "--config_file",
                           str(estimator_cfg), "post-process", str(other)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in gcodes.iterdir()) == sorted([upload.name, other.name])
    assert list(temp.iterdir()) == []
