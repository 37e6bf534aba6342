"""`kestimator-compat` under bad input, concurrency and signals (issue 20, items 5, 10, 12, 13).

Every internal error is one line (never a traceback in Moonraker's log); concurrent
post-process runs on one file take turns (the file lock of `inject_file`); a 250-byte file
name works and no error names a temporary file; SIGTERM and SIGHUP leave no temporary file;
the temporary file exists only while the output is being written.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kestimator import compat

from .conftest import CORPUS, CORPUS_CFG, PROJECT

BODY = b"M83\n;LAYER_CHANGE\nG1 X10 E1 F3000\nG1 X20 E1\n"
BIG = CORPUS / "gcode" / "prusaslicer" / "cancelobj_ps2.3.3_issue1.gcode"
CONCURRENT = 4
SIGNAL_RUNS = 6


@pytest.fixture(autouse=True)
def _no_profile(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(PROJECT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _compat(*args: str) -> list[str]:
    return [sys.executable, "-m", "kestimator.compat", *args]


def _estimator_config(tmp_path: Path) -> Path:
    cfg = tmp_path / "ke.json"
    cfg.write_text('{"max_velocity": 300, "max_acceleration": 3000, '
                   '"square_corner_velocity": 5}')
    return cfg


def _leftovers(folder: Path) -> list[str]:
    return [name for name in os.listdir(folder) if "kestimator" in name]


@pytest.mark.parametrize("config", ["[" * 10000 + "]" * 10000,
                                    '{"max_velocity": 1e308, "max_acceleration": 1e308}',
                                    '{"square_corner_velocity": 1e200}'])
def test_a_hostile_klipper_estimator_config_is_one_line_not_a_traceback(
        config: str, tmp_path: Path) -> None:
    cfg = tmp_path / "ke.json"
    cfg.write_text(config)
    work = tmp_path / "f.gcode"
    work.write_bytes(BODY)
    for command in (["estimate", "-f", "json", str(work)], ["post-process", str(work)]):
        run = subprocess.run(_compat("--config_file", str(cfg), *command), env=_env(),
                             capture_output=True, timeout=60)
        assert run.returncode == 1, run.stderr
        assert b"Traceback" not in run.stderr and len(run.stderr.splitlines()) == 1
        assert work.read_bytes() == BODY


def test_an_internal_error_in_compat_is_one_line(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    def broken(*_args: object, **_kwargs: object) -> None:
        raise MemoryError()

    monkeypatch.setattr(compat, "resolve_limits", broken)
    work = tmp_path / "f.gcode"
    work.write_bytes(BODY)
    assert compat.main(["post-process", str(work)]) == compat.EXIT_FAILURE
    err = capsys.readouterr().err
    assert err.startswith("kestimator-compat: internal error: MemoryError")
    assert len(err.splitlines()) == 1 and work.read_bytes() == BODY


def test_compat_post_process_of_a_250_byte_name_works_and_names_no_temp_file(
        tmp_path: Path) -> None:
    work = tmp_path / ("p" * 244 + ".gcode")
    work.write_bytes(BODY)
    run = subprocess.run(_compat("--config_file", str(_estimator_config(tmp_path)),
                                 "post-process", str(work)), env=_env(),
                         capture_output=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert work.read_bytes().rstrip().endswith(compat.IDENT_LINE.encode())
    assert not _leftovers(tmp_path)


def test_concurrent_compat_runs_take_turns_and_all_succeed(tmp_path: Path) -> None:
    cfg = _estimator_config(tmp_path)
    ref = tmp_path / "ref" / "f.gcode"
    ref.parent.mkdir()
    ref.write_bytes(BODY)
    subprocess.run(_compat("--config_file", str(cfg), "post-process", str(ref)), env=_env(),
                   check=True, capture_output=True, timeout=60)
    work = tmp_path / "f.gcode"
    work.write_bytes(BODY)
    runs = [subprocess.Popen(_compat("--config_file", str(cfg), "post-process", str(work)),
                             env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            for _ in range(CONCURRENT)]
    results = [(run.wait(120), run.stderr.read() if run.stderr else b"") for run in runs]
    for run in runs:
        for stream in (run.stdout, run.stderr):
            if stream is not None:
                stream.close()
    assert all(status == 0 for status, _ in results), results
    assert work.read_bytes() == ref.read_bytes()
    assert not _leftovers(tmp_path)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
@pytest.mark.parametrize("program", ["cli", "compat"])
def test_sigterm_and_sighup_leave_no_temp_file(
        signum: int, program: str, tmp_path: Path, corpus_root: Path) -> None:
    work = tmp_path / BIG.name
    cfg = _estimator_config(tmp_path)
    for run_index in range(SIGNAL_RUNS):
        shutil.copyfile(BIG, work)
        original = work.read_bytes()
        argv = (_compat("--config_file", str(cfg), "post-process", str(work))
                if program == "compat" else
                [sys.executable, "-m", "kestimator", "inject", "-q", "--printer-cfg",
                 str(CORPUS_CFG), str(work)])
        proc = subprocess.Popen(argv, env=_env(), stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE)
        # Wait until the temporary file exists (pass 2), or a moment into pass 1.
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and proc.poll() is None:
            if _leftovers(tmp_path) or (run_index % 2 and time.monotonic() > deadline - 19.7):
                break
            time.sleep(0.005)
        proc.send_signal(signum)
        proc.wait(60)
        err = proc.stderr.read() if proc.stderr else b""
        if proc.stderr is not None:
            proc.stderr.close()
        assert b"Traceback" not in err, err
        assert not _leftovers(tmp_path), (run_index, err)
        data = work.read_bytes()
        assert data == original or proc.returncode == 0


_INTERRUPT_ON_IMPORT = """
import sys
class _CtrlC:
    def find_spec(self, name, path=None, target=None):
        if name == "kestimator.estimate":
            raise KeyboardInterrupt
        return None
sys.meta_path.insert(0, _CtrlC())
"""


def _console_scripts() -> dict[str, str]:
    try:
        import tomllib
    except ImportError:  # Python < 3.11
        import tomli as tomllib  # type: ignore[no-redef]
    with open(PROJECT / "pyproject.toml", "rb") as f:
        return dict(tomllib.load(f)["project"]["scripts"])


@pytest.mark.parametrize("script", ["kestimator", "kestimator-compat", "-m"])
def test_ctrl_c_while_modules_load_is_one_line_not_a_traceback(script: str) -> None:
    """Ctrl-C while the console script imports its modules (pressed early in a slow start):
    the program pip generates from [project.scripts] (and `python -m kestimator`) prints one
    line, never a KeyboardInterrupt traceback."""
    if script == "-m":
        run_code = "import runpy; runpy.run_module('kestimator', run_name='__main__')"
    else:
        module, attr = _console_scripts()[script].split(":")
        # What pip's console-script wrapper does.
        run_code = "import sys\nfrom %s import %s\nsys.exit(%s())" % (module, attr, attr)
    run = subprocess.run([sys.executable, "-c", _INTERRUPT_ON_IMPORT + run_code, "--version"],
                         env=_env(), capture_output=True, timeout=60)
    assert b"Traceback" not in run.stderr, run.stderr
    assert len(run.stderr.splitlines()) == 1 and b"interrupted" in run.stderr, run.stderr
    assert run.returncode == 1  # as main() exits on Ctrl-C
