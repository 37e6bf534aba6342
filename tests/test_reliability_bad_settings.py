"""Issue 20 item 5: hostile settings sources end in one clear line, never "internal error".

Each case goes through the real command line (`python -m kestimator`, and
`python -m kestimator.compat` where it applies): exit status 1 and one line naming the
problem, or a warning and a normal run where the source is optional (the default profile).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import CORPUS_CFG, PROJECT

BODY = b"M83\n;LAYER_CHANGE\nG1 X10 E1 F3000\nG1 X20 E1\n"


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(PROJECT) + os.pathsep + env.get("PYTHONPATH", "")
    env.update(extra)
    return env


def _run(*args: str, module: str = "kestimator", env: dict[str, str] | None = None,
         **kwargs) -> subprocess.CompletedProcess[bytes]:  # type: ignore[no-untyped-def]
    return subprocess.run([sys.executable, "-m", module, *args], env=env or _env(),
                          capture_output=True, timeout=60, **kwargs)


def _one_line_failure(run: subprocess.CompletedProcess[bytes], expected: bytes) -> None:
    assert run.returncode == 1, run.stderr
    assert b"internal error" not in run.stderr, run.stderr
    assert expected in run.stderr and len(run.stderr.splitlines()) == 1, run.stderr


@pytest.fixture()
def gcode(tmp_path: Path) -> Path:
    path = tmp_path / "print.gcode"
    path.write_bytes(BODY)
    return path


def test_an_over_long_xdg_config_home_warns_and_goes_on(gcode: Path) -> None:
    run = _run("estimate", "--printer-cfg", str(CORPUS_CFG), str(gcode),
               env=_env(XDG_CONFIG_HOME="/" + "a" * 5000))
    assert run.returncode == 0, run.stderr
    assert b"not read" in run.stdout + run.stderr and b"internal error" not in run.stderr


def test_an_unreadable_config_directory_warns_and_goes_on(
        gcode: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """~/.config/kestimator without search permission: stat() of the profile in it fails
    with EACCES (simulated: the suite runs as root, for whom no directory is unreadable)."""
    import errno

    from kestimator import cli

    config_dir = tmp_path / "config"
    real_stat = os.stat

    def stat_denied(path, *args, **kwargs):  # type: ignore[no-untyped-def]
        if str(path).startswith(str(config_dir / "kestimator")):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_stat(path, *args, **kwargs)

    monkeypatch.setenv("XDG_CONFIG_HOME", str(config_dir))
    monkeypatch.setattr(os, "stat", stat_denied)
    status = cli.main(["estimate", "--printer-cfg", str(CORPUS_CFG), str(gcode)])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert "Permission denied" in captured.out + captured.err
    assert "internal error" not in captured.err


def test_a_huge_moonraker_timeout_in_the_profile_is_one_line(tmp_path: Path,
                                                               gcode: Path) -> None:
    profile = tmp_path / "profile.toml"
    profile.write_text('moonraker = "http://127.0.0.1:9"\nmoonraker_timeout_s = 1e308\n')
    _one_line_failure(_run("estimate", "--profile", str(profile), str(gcode)),
                      b"moonraker_timeout_s")


@pytest.mark.parametrize("url", ["http://[::1", "http://host:99999"])
def test_a_malformed_moonraker_url_is_one_line(url: str, gcode: Path, tmp_path: Path) -> None:
    _one_line_failure(_run("estimate", "--moonraker", url, str(gcode)), b"not a Moonraker URL")
    run = _run("--config_moonraker_url", url, "dump-config", module="kestimator.compat")
    assert run.returncode == 1 and b"internal error" not in run.stderr, run.stderr
    assert b"not a Moonraker URL" in run.stderr and len(run.stderr.splitlines()) == 1


def test_a_64_character_host_label_is_one_line(gcode: Path) -> None:
    run = _run("estimate", "--moonraker", "http://%s.invalid" % ("a" * 64), str(gcode))
    assert run.returncode == 1 and b"internal error" not in run.stderr, run.stderr
    assert len(run.stderr.splitlines()) == 1, run.stderr


def test_a_1500_deep_include_chain_is_one_line(tmp_path: Path, gcode: Path) -> None:
    for i in range(1500):
        (tmp_path / ("inc%d.cfg" % i)).write_text("[include inc%d.cfg]\n" % (i + 1))
    (tmp_path / "inc1500.cfg").write_bytes(CORPUS_CFG.read_bytes())
    _one_line_failure(_run("estimate", "--printer-cfg", str(tmp_path / "inc0.cfg"),
                           str(gcode)), b"nested more than")


def test_square_corner_velocity_1e200_in_the_profile_is_one_line(tmp_path: Path,
                                                                 gcode: Path) -> None:
    profile = tmp_path / "profile.toml"
    profile.write_text('[printers."a"]\nprinter_cfg = "%s"\n[printers."a".limits]\n'
                       "square_corner_velocity = 1e200\n" % CORPUS_CFG)
    _one_line_failure(_run("estimate", "--profile", str(profile), "--printer", "a",
                           str(gcode)), b"square_corner_velocity")


_OUT_OF_MEMORY = """
import sys
import kestimator.estimate as e
def _boom(*a, **k):
    raise MemoryError
e.estimate_file = _boom
e.estimate_lines = _boom
import kestimator.cli, kestimator.compat
kestimator.cli.estimate_lines = _boom
kestimator.compat.estimate_file = _boom
kestimator.compat.estimate_lines = _boom
main = kestimator.compat.main if sys.argv[1] == "compat" else kestimator.cli.main
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("program", ["cli", "compat"])
def test_memory_error_is_one_line_exit_1(program: str, gcode: Path, tmp_path: Path) -> None:
    if program == "cli":
        args = ["estimate", "--printer-cfg", str(CORPUS_CFG), str(gcode)]
    else:
        cfg = tmp_path / "ke.json"
        cfg.write_text('{"max_velocity": 300, "max_acceleration": 3000}')
        args = ["--config_file", str(cfg), "estimate", str(gcode)]
    run = subprocess.run([sys.executable, "-c", _OUT_OF_MEMORY, program, *args], env=_env(),
                         capture_output=True, timeout=60)
    _one_line_failure(run, b"out of memory")
