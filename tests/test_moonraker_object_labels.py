"""An upload Moonraker labels after kestimator-compat keeps a valid table (issue 38 item 1),
at a cost that fits Moonraker's time limit (issue 49 items 1 and 2).

The real Moonraker (PyPI `moonraker` 0.11.0, with preprocess_cancellation) runs with
``[file_manager] enable_object_processing: True``: it runs our estimator first and labels the
objects after it. The stored file of a PrusaSlicer-labelled upload must carry Moonraker's
labels and a table made for the labelled file: the worker follows it (`source: table`) with
the times of a fresh estimate of that file, the objects named as the labels name them.
Labels of other slicers are said and left to the estimate at print start; so is a labelling
that does not fit in the processor's time; a run killed at that limit leaves nothing.
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
from kestimator.moonraker_labels import NICE_ENVIRONMENT, SHARE_ENVIRONMENT, Labeller
from kestimator.progress_table import (
    TableError,
    content_matches,
    read_table_file,
    spacing_bound,
)
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
# from the file's end: the table goes before it), and one in CRLF; Cura (";MESH:") is not
# labelled ahead.
UPLOADS = (
    "prusaslicer/cancelobj_ps2.4.0a1_arcwelder.gcode",
    "prusaslicer/ps25_torus_x4_labels_marlin.gcode",
    "prusaslicer/cancelobj_ps2.3.3_issue1.gcode",
)
CURA_UPLOAD = "cura/cancelobj_cura4.10.0.gcode"
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
        moonraker_python: str, tmp_path: Path,  # noqa: F811
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Moonraker's labelling runs ahead on idle CPU time only by default. A test host running
    # three test processes on two CPUs has none (the labelling got no CPU at all and was
    # stopped at its deadline): it runs at a nice value, as a host whose CPU is never idle is
    # told to, and may take more than half a post-process (the share itself: the tests below).
    monkeypatch.setenv(NICE_ENVIRONMENT, "0")
    monkeypatch.setenv(SHARE_ENVIRONMENT, "20")
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
        "estimator_config: estimator.json\nestimator_timeout: 600\n"
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
                assert content_matches(f, table), source.name
            fresh = estimate_file(stored, limits).total_s
            answer = _ask_worker(tmp_path, stored)
            assert answer["ok"] and answer["source"] == "table", answer
            assert answer["warnings"] == []
            assert abs(answer["total_s"] - fresh) < 0.001
            # At every line, the table's time is the fresh estimate's, within the table's
            # interpolation bound; its objects are the labelled file's, with their times.
            estimated = _ask_worker(tmp_path, stored, use_table=False)
            assert estimated["ok"] and estimated["source"] == "estimate", estimated
            assert len(estimated["offsets"]) > 100
            for offset, t in zip(estimated["offsets"], estimated["times"]):
                assert abs(table.time_at(offset) - t) <= spacing_bound(fresh - t) + 0.002
            assert len(table.object_names) > 1
            assert table.object_names == estimated["object_names"]
            for k, remaining in enumerate(table.object_remaining):
                assert remaining == pytest.approx(estimated["object_remaining"][k], abs=1e-3)
            assert table.object_offsets == estimated["object_offsets"]
            assert text.rstrip(b"\r\n").endswith(compat.IDENT_LINE.encode())
        # Cura's labels: processed and labelled all the same, the table left to the print's
        # start (it holds for the unlabelled file).
        cura = CORPUS / "gcode" / CURA_UPLOAD
        _upload(base, cura)
        meta = _metadata(base, cura.name)
        stored = data / "gcodes" / cura.name
        assert meta["file_processors"] == ["klipper_estimator", "preprocess_cancellation"]
        assert b"\nEXCLUDE_OBJECT_DEFINE NAME=" in stored.read_bytes()
        with pytest.raises(TableError, match="changed after its table was written"):
            read_table_file(stored)



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
    ({"check_objects": True}, Labeller("/venv/bin/python", "", 120.0, 300.0)),
    ({"check_objects": True, "processors": [
        {"name": "klipper_estimator", "timeout": 600}, {"name": "other", "timeout": 30}]},
     Labeller("/venv/bin/python", "", 600.0, 630.0)),
    ({"check_objects": False}, None),
    ({}, None),
    ([1, 2], None),
])
def test_the_labeller_is_moonrakers_only_when_its_metadata_run_processes_objects(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, config: object,
        found: Labeller | None) -> None:
    """... with its time limits: ours (the klipper_estimator processor's, 120 s when not
    given) and the metadata run's (the processors' together, at least 300 s)."""
    from kestimator import moonraker_labels

    script = tmp_path / "moonraker" / "components" / "file_manager" / "metadata.py"
    script.parent.mkdir(parents=True)
    script.write_text("")
    cfg = tmp_path / "md.json"
    cfg.write_text(json.dumps(config))
    monkeypatch.setattr(moonraker_labels, "_parent_args",
                        lambda pid: ["/venv/bin/python", str(script), "-c", str(cfg)])
    got = moonraker_labels.moonraker_labeller(os.getpid())
    if found is None:
        assert got is None
    else:
        assert got == Labeller(found.python, str(script), found.processor_timeout_s,
                               found.metadata_timeout_s, 0.0)
    monkeypatch.setattr(moonraker_labels, "_parent_args", lambda pid: ["/bin/sh", "-c", "x"])
    assert moonraker_labels.moonraker_labeller(os.getpid()) is None


@pytest.mark.parametrize("value, nice", [(None, None), ("7", 7), ("0", 0), ("20", None),
                                         ("-5", None), ("idle", None)])
def test_the_labelling_runs_on_idle_cpu_time_unless_the_host_asks_for_a_nice_value(
        monkeypatch: pytest.MonkeyPatch, value: str | None, nice: int | None) -> None:
    """By default Moonraker's labelling run ahead gets idle CPU time only (SCHED_IDLE: our own
    run never waits for it); KESTIMATOR_LABEL_AHEAD_NICE=0..19 runs it at that nice value
    instead (never above our own priority), for a host whose CPU is never idle."""
    from kestimator import moonraker_labels

    if value is None:
        monkeypatch.delenv(NICE_ENVIRONMENT, raising=False)
    else:
        monkeypatch.setenv(NICE_ENVIRONMENT, value)
    assert moonraker_labels.label_nice() == nice
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        moonraker_labels._lower_priority(child.pid, moonraker_labels.label_nice())
        if nice is None:
            assert os.sched_getscheduler(child.pid) == os.SCHED_IDLE
        else:
            assert os.sched_getscheduler(child.pid) == os.SCHED_OTHER
            assert os.getpriority(os.PRIO_PROCESS, child.pid) == max(
                nice, os.getpriority(os.PRIO_PROCESS, 0))
    finally:
        child.kill()
        child.wait()


# Moonraker's metadata run as far as kestimator-compat sees it: a `metadata.py -c CONFIG`
# parent (with object processing on) that runs the estimator on the file, and a labelling
# (its BaseSlicer/process_objects) that takes long (LABELLING=slow), or labels Cura's way
# (LABELLING=cura).
_FAKE_METADATA = r'''
import json, os, subprocess, sys, time
if __name__ == "__main__":
    config = json.load(open(sys.argv[2]))
    estimator = subprocess.Popen(config["command"])
    with open(config["pid_file"], "w") as f:
        f.write(str(estimator.pid))
    sys.exit(estimator.wait())
else:
    class BaseSlicer:
        @classmethod
        def from_file(cls, path):
            return Cura() if os.environ["LABELLING"] == "cura" else cls()

    class Cura(BaseSlicer):
        pass

    def process_objects(path, slicer):
        import tempfile
        tempfile.mkstemp(prefix="labelling-")  # as Moonraker's does, in TMPDIR
        with open(os.environ["LABELLER_PID_FILE"], "w") as f:
            f.write(str(os.getpid()))
        if os.environ["LABELLING"] == "slow":
            time.sleep(300)
        return True
'''


def _metadata_run(tmp_path: Path, labelling: str, upload: Path, timeout: float = 600.0,
                  share: str = "20") -> tuple[subprocess.Popen[bytes], dict[str, str], Path]:
    """Moonraker's metadata run (faked as above) on `upload`, with `timeout` as our
    processor's limit and `share` as the labelling's (SHARE_ENVIRONMENT); the process, the
    environment and the estimator config."""
    script = tmp_path / "moonraker" / "components" / "file_manager" / "metadata.py"
    script.parent.mkdir(parents=True)
    script.write_text(_FAKE_METADATA)
    temp = tmp_path / "tmp"
    temp.mkdir()
    machine = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False))
    estimator_cfg = tmp_path / "estimator.json"
    estimator_cfg.write_text(json.dumps(dump_config(machine.limits, machine.sources)))
    config = tmp_path / "md.json"
    command = [sys.executable, "-m", "kestimator.compat", "--config_file", str(estimator_cfg),
               "post-process", str(upload)]
    config.write_text(json.dumps({
        "check_objects": True, "pid_file": str(tmp_path / "estimator.pid"),
        "command": command,
        "processors": [{"name": "klipper_estimator", "command": command,
                        "timeout": timeout}]}))
    env = dict(os.environ, PYTHONPATH=str(PROJECT), TMPDIR=str(temp), LABELLING=labelling,
               # The labelling runs on idle CPU time only: on a loaded test host it may
               # take more than its share (the share itself is the "slow" case's).
               **{SHARE_ENVIRONMENT: share},
               LABELLER_PID_FILE=str(tmp_path / "labeller.pid"),
               XDG_CONFIG_HOME=str(tmp_path / "config"), XDG_CACHE_HOME=str(tmp_path / "cache"))
    process = subprocess.Popen([sys.executable, str(script), "-c", str(config)], env=env,
                               cwd=str(tmp_path), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE)
    return process, env, estimator_cfg


@pytest.mark.parametrize("labelling, timeout, share, why", [
    # No time left: the processor's limit (2 s) is all margin.
    ("slow", 2.0, "20", "not labelled ahead: that does not fit in the time left (its "
                        "limit: 2 s)"),
    # Time left, but the labelling takes more than its share (the default's).
    ("slow", 600.0, "0.5", "not labelled ahead (its labelling takes longer than there is "
                           "time for)"),
    ("cura", 600.0, "20", "(cura labels), which is not done ahead: its table is estimated "
                          "at print start"),
])
def test_labelling_ahead_that_cannot_be_done_is_said_in_one_line_and_the_upload_processed(
        tmp_path: Path, labelling: str, timeout: float, share: str, why: str) -> None:
    """With no time left of the processor's limit (less the margin kept), past the
    labelling's share of a plain post-process, or for labels not done ahead (Cura's), the
    file is processed as a plain post-process, one line says why, and Moonraker's labelling
    run ahead is stopped."""
    gcodes = tmp_path / "gcodes"
    gcodes.mkdir()
    source = CORPUS / "gcode" / UPLOADS[1]
    upload = gcodes / source.name
    shutil.copyfile(source, upload)
    process, _, _ = _metadata_run(tmp_path, labelling, upload, timeout, share)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, err
    said = [line for line in err.decode().splitlines() if "warning" not in line]
    assert len(said) == 1 and why in said[0] and str(upload) in said[0], said
    assert b"Klipper time" in out
    assert compat.IDENT_LINE.encode() in upload.read_bytes()
    with open(upload, "rb") as f:
        assert content_matches(f, read_table_file(upload))
    deadline = time.monotonic() + 5.0
    while _running_in(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _running_in(tmp_path) == []  # Moonraker's labelling run ahead is stopped
    assert list((tmp_path / "tmp").iterdir()) == []
    assert sorted(p.name for p in gcodes.iterdir()) == [upload.name]


def _gone(pid: int) -> bool:
    try:
        with open("/proc/%d/stat" % pid) as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def _running_in(folder: Path) -> list[int]:
    """The processes (not zombies) whose command line names something in `folder`."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if str(folder).encode() in (entry / "cmdline").read_bytes() and not _gone(
                    int(entry.name)):
                found.append(int(entry.name))
        except OSError:
            continue
    return found


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
    gcodes = tmp_path / "gcodes"
    gcodes.mkdir()
    source = CORPUS / "gcode" / UPLOADS[1]
    upload = gcodes / source.name
    shutil.copyfile(source, upload)
    metadata, env, estimator_cfg = _metadata_run(tmp_path, "slow", upload)
    temp = tmp_path / "tmp"
    try:
        estimator = _wait_for(tmp_path / "estimator.pid")
        labeller = _wait_for(tmp_path / "labeller.pid")
        # Killed at Moonraker's time limit while it writes its output and labels ahead.
        deadline = time.monotonic() + 120.0
        while (not any(p.name.endswith(".kestimator-tmp") for p in gcodes.iterdir())
               and time.monotonic() < deadline):
            time.sleep(0.005)
        os.kill(estimator, signal.SIGKILL)
        assert [p for p in gcodes.iterdir() if p.name.endswith(".kestimator-tmp")]
        assert [p.name for p in temp.iterdir()]
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
