"""install.sh on a Klipper host: the real Moonraker runs kestimator after it, its update
manager lists the checkout, a second run changes nothing and --uninstall undoes it byte for byte.

The host is a temporary data folder (HOME) with a git clone of this project whose origin is a
local bare repository (no network), a printer.cfg from the corpus and a stand-in
klipper_estimator that install.sh must keep and --uninstall must bring back. The build is the
pure one (KESTIMATOR_BUILD=pure), so no mypy is fetched and nothing is compiled; the compiled
install (about 45 s of CPU) runs with KESTIMATOR_TEST_COMPILED_INSTALL=1 (tests/
test_compiled_build.py covers the mypyc build itself).
"""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
import time
import urllib.error
import urllib.parse
from pathlib import Path

import pytest

from kestimator import __version__, compat
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.estimate import estimate_file
from tests.conftest import (
    CORPUS,
    CORPUS_CFG,
    IN_CI,
    PROJECT,
    load_script,
    require_klipper,
    require_program,
)
from tests.moonraker_host import (  # noqa: F401 (moonraker_python is the session fixture)
    _free_port,
    _metadata,
    _moonraker,
    _request,
    _upload,
    _wait_ready,
    moonraker_python,
)

UPLOAD = "prusaslicer/ps25_nut_accelA_small.gcode"
FAKE_ESTIMATOR = b"#!/bin/sh\necho 'klipper_estimator v3.7.3'\n"
FAKE_RELEASE = b'{"project_name": "klipper_estimator", "version": "v3.7.3"}'
INSTALL_TIMEOUT_S = 300.0
UPDATE_TIMEOUT_S = 60.0
COMPILED_ENVIRONMENT = "KESTIMATOR_TEST_COMPILED_INSTALL"


def _git(*args: str, cwd: Path) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True,
                          text=True, timeout=60).stdout


IDENTITY = ("-c", "user.name=test", "-c", "user.email=test@example.invalid")


def _copy_project(source: Path) -> None:
    """This project's files as they are now (uncommitted changes included) into `source`."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                             "--exclude-standard"], cwd=PROJECT, check=True,
                            capture_output=True, timeout=60).stdout.decode().split("\0")
    for name in filter(None, listed):
        path = PROJECT / name
        if path.is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, source / name)


def _checkout(root: Path, commit: str | None = None) -> Path:
    """`git clone` of this project as it is now (uncommitted changes included), or as it was
    at `commit` of its history, with a local bare repository as its origin."""
    require_program("git")
    source = root / "source"
    if commit is None:
        _copy_project(source)
    else:
        source.mkdir(parents=True)
        archive = subprocess.run(["git", "archive", commit], cwd=PROJECT, check=True,
                                 capture_output=True, timeout=60).stdout
        subprocess.run(["tar", "-x", "-C", str(source)], input=archive, check=True,
                       timeout=60)
    _git("init", "-q", "-b", "main", cwd=source)
    _git("add", "-A", cwd=source)
    _git(*IDENTITY, "commit", "-q", "-m", "kestimator", cwd=source)
    _git("clone", "-q", "--bare", str(source), str(root / "origin.git"), cwd=root)
    checkout = root / "home" / "kestimator"
    checkout.parent.mkdir(parents=True)
    _git("clone", "-q", str(root / "origin.git"), str(checkout), cwd=root)
    return checkout


def _host(home: Path, port: int) -> tuple[Path, bytes]:
    data = home / "printer_data"
    for folder in ("config", "gcodes", "logs", "comms", "database"):
        (data / folder).mkdir(parents=True)
    shutil.copyfile(CORPUS_CFG, data / "config" / "printer.cfg")
    tools = data / "tools" / "klipper_estimator"
    tools.mkdir(parents=True)
    (tools / "klipper_estimator_linux").write_bytes(FAKE_ESTIMATOR)
    (tools / "klipper_estimator_linux").chmod(0o755)
    (tools / "release_info.json").write_bytes(FAKE_RELEASE)
    # A host's moonraker.conf, without systemd (provider: none) and no system updates.
    conf = ("[server]\nhost: 127.0.0.1\nport: %d\nklippy_uds_address: %s\n\n"
            "[machine]\nprovider: none\nvalidate_service: False\n\n"
            "[authorization]\ntrusted_clients:\n  127.0.0.0/8\n\n"
            "[file_manager]\nenable_object_processing: False\n\n"
            "[update_manager]\nenable_system_updates: False\n"
            % (port, data / "comms" / "klippy.sock")).encode()
    (data / "config" / "moonraker.conf").write_bytes(conf)
    # A Klipper checkout (~/klipper) the Klipper module links into.
    extras = home / "klipper" / "klippy" / "extras"
    extras.mkdir(parents=True)
    (extras / "__init__.py").write_text("")
    _git("init", "-q", cwd=home / "klipper")
    return data, conf


def _environment(data: Path) -> dict[str, str]:
    """Moonraker's user as tests/moonraker_host.py starts Moonraker: HOME is the data folder's
    parent here, the profile in XDG_CONFIG_HOME (the same for install.sh and Moonraker)."""
    env = dict(os.environ, HOME=str(data.parent), XDG_CONFIG_HOME=str(data / "xdg-config"),
               KESTIMATOR_BUILD="pure")
    for name in ("PYTHONPATH", "VIRTUAL_ENV", "PIP_REQUIRE_VIRTUALENV"):
        env.pop(name, None)
    return env


def _install(checkout: Path, data: Path, *options: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(checkout / "install.sh"), "--allow-root", "--no-restart",
                           "-d", str(data), *options],
                          env=_environment(data), capture_output=True, text=True,
                          timeout=INSTALL_TIMEOUT_S, stdin=subprocess.DEVNULL)


def _update_status(base: str) -> dict:
    """kestimator's entry in /machine/update/status, once the update manager has read it."""
    deadline = time.monotonic() + UPDATE_TIMEOUT_S
    entry: dict = {}
    while time.monotonic() < deadline:
        info = _request(base + "/machine/update/status")["result"]["version_info"]
        entry = info.get("kestimator", {})
        if entry.get("is_valid") and entry.get("version") not in (None, "", "?"):
            return entry
        time.sleep(0.5)
    pytest.fail("kestimator is not valid in /machine/update/status: %r" % entry)


def test_install_sh_moonraker_runs_kestimator_updates_it_and_uninstall_restores(
        moonraker_python: str, corpus_root: Path, tmp_path: Path) -> None:  # noqa: F811
    checkout = _checkout(tmp_path)
    port = _free_port()
    data, conf_before = _host(tmp_path / "home", port)
    conf = data / "config" / "moonraker.conf"
    tools = data / "tools" / "klipper_estimator"

    first = _install(checkout, data, "-y")
    assert first.returncode == 0, first.stdout + first.stderr
    assert "kestimator build: pure Python (KESTIMATOR_BUILD=pure)" in first.stdout
    assert "Moonraker not restarted (--no-restart)" in first.stdout
    link = tools / "klipper_estimator_linux"
    assert os.readlink(link) == str(checkout / "plugins" / "moonraker" / "klipper_estimator")
    assert (tools / "klipper_estimator_linux.orig").read_bytes() == FAKE_ESTIMATOR
    installed = conf.read_bytes()
    assert installed.startswith(conf_before)
    added = installed[len(conf_before):].decode()
    assert "[analysis]\nenable_auto_analysis: True\n" in added
    assert "enable_estimator_updates: False\n" in added
    assert ("[update_manager kestimator]\ntype: git_repo\npath: %s\norigin: %s\n"
            "primary_branch: main\nmanaged_services: klipper moonraker\n"
            "install_script: install.sh\n"
            % (checkout, tmp_path / "origin.git")) in added
    assert "[update_manager]\n" not in added  # the host has one
    backups = list(conf.parent.glob("moonraker.conf.*.kestimator.bak"))
    assert [b.read_bytes() for b in backups] == [conf_before]
    profile = data / "xdg-config" / "kestimator" / "config.toml"
    assert 'printer_cfg = "%s"' % (data / "config" / "printer.cfg") in profile.read_text()
    # The Klipper module is linked as add-ons are, and Klipper's git status stays clean.
    klipper = tmp_path / "home" / "klipper"
    module_link = klipper / "klippy" / "extras" / "kestimator"
    assert os.readlink(module_link) == str(checkout / "plugins" / "klipper" / "kestimator")
    assert "kestimator" not in _git("status", "--porcelain", cwd=klipper)
    assert "add a [kestimator] section to printer.cfg" in first.stdout

    base = "http://127.0.0.1:%d" % port
    source = CORPUS / "gcode" / UPLOAD
    expected = estimate_file(source, resolve_limits(LimitRequest(
        printer_cfg=CORPUS_CFG, use_profile=False)).limits).total_s
    with _moonraker(moonraker_python, data, port) as process:
        _wait_ready(base, process, data / "logs" / "stdout.log")
        status = _request(base + "/server/analysis/status")["result"]
        assert status["estimator_ready"] is True
        assert status["estimator_version"] == __version__
        _upload(base, source)
        meta = _metadata(base, source.name)
        stored = (data / "gcodes" / source.name).read_bytes()
        assert b"; kestimator %s klipper_s=%.3f " % (__version__.encode(), expected) in stored
        assert stored.rstrip(b"\r\n").endswith(compat.IDENT_LINE.encode())
        assert abs(meta["estimated_time"] - expected) <= 1.0
        answer = _request(base + "/server/analysis/estimate?" + urllib.parse.urlencode(
            {"filename": source.name}), "POST")["result"]
        assert answer["total_time"] == pytest.approx(expected, abs=1e-6)
        entry = _update_status(base)
        assert entry["configured_type"] == "git_repo"
        assert entry["is_dirty"] is False
        assert entry["warnings"] == []

    # After an update through Moonraker (a git pull, no rebuild) the checkout's own code
    # answers until install.sh builds the new commit.
    stamp = checkout / ".venv-host" / "kestimator-commit"
    built = stamp.read_bytes()
    stamp.write_text("0" * 40 + "\n")
    answer = subprocess.run([str(link), "--version"], env=_environment(data),
                            capture_output=True, text=True, timeout=60)
    assert answer.stdout.startswith("klipper_estimator %s " % __version__), answer.stderr
    stamp.write_bytes(built)

    second = _install(checkout, data, "-y")
    assert second.returncode == 0, second.stdout + second.stderr
    assert conf.read_bytes() == installed
    assert "moonraker.conf: nothing to add." in second.stdout
    assert "Installing kestimator" not in second.stdout  # the venv is this commit's already
    assert len(list(conf.parent.glob("moonraker.conf.*.kestimator.bak"))) == 1

    removed = _install(checkout, data, "--uninstall")
    assert removed.returncode == 0, removed.stdout + removed.stderr
    assert conf.read_bytes() == conf_before
    assert not link.is_symlink()
    assert link.read_bytes() == FAKE_ESTIMATOR
    assert stat.S_IMODE(link.stat().st_mode) == 0o755
    assert (tools / "release_info.json").read_bytes() == FAKE_RELEASE
    assert not (tools / "klipper_estimator_linux.orig").exists()
    assert not profile.exists()
    assert not (tools / "default_estimator_cfg.json").exists()
    assert not (checkout / ".venv-host").exists()
    assert _git("status", "--porcelain", cwd=checkout) == ""
    assert not module_link.is_symlink() and not module_link.exists()
    assert not (checkout / ".git" / "hooks" / "post-merge").exists()


def test_install_sh_refuses_root_and_says_why(tmp_path: Path) -> None:
    if os.geteuid() != 0:
        pytest.skip("runs as root only")
    proc = subprocess.run([str(PROJECT / "install.sh"), "-d", str(tmp_path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert "refusing to run as root" in proc.stderr
    assert "--allow-root" in proc.stderr
    assert not any(tmp_path.iterdir())


def test_install_sh_help_and_unknown_option(tmp_path: Path) -> None:
    run = [str(PROJECT / "install.sh"), "--allow-root"]
    shown = subprocess.run([*run, "-h"], capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0
    for option in ("-d DIR", "-y", "--uninstall", "--no-restart", "--allow-root"):
        assert option in shown.stdout
    wrong = subprocess.run([*run, "--frobnicate"], capture_output=True, text=True, timeout=60)
    assert wrong.returncode == 1 and "unknown option: --frobnicate" in wrong.stderr


def test_install_sh_is_shellcheck_clean() -> None:
    shellcheck = require_program("shellcheck")
    proc = subprocess.run([shellcheck, "install.sh", "plugins/moonraker/klipper_estimator"],
                          cwd=PROJECT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def _path_without(tmp_path: Path, left_out: tuple[str, ...]) -> Path:
    """A folder of links to every program on PATH but `left_out` (the first of each name)."""
    programs = tmp_path / "bin"
    programs.mkdir()
    for folder in os.environ.get("PATH", "").split(os.pathsep):
        if not os.path.isdir(folder):
            continue
        for name in os.listdir(folder):
            target = programs / name
            if name not in left_out and not os.path.lexists(target):
                target.symlink_to(os.path.join(folder, name))
    return programs


def test_install_sh_names_missing_apt_packages_and_stops(tmp_path: Path) -> None:
    """Without gcc and without -y it says which apt packages to install and changes nothing."""
    data, conf_before = _host(tmp_path / "home", 7125)
    programs = _path_without(tmp_path, ("gcc",))
    env = dict(_environment(data), PATH=str(programs))
    env.pop("KESTIMATOR_BUILD")
    proc = subprocess.run([str(PROJECT / "install.sh"), "--allow-root", "--no-restart",
                           "-d", str(data)], env=env, capture_output=True, text=True,
                          timeout=60, stdin=subprocess.DEVNULL)
    assert proc.returncode == 1
    assert "missing apt packages: gcc\n" in proc.stderr
    assert "sudo apt-get install gcc" in proc.stderr and "-y" in proc.stderr
    assert (data / "config" / "moonraker.conf").read_bytes() == conf_before
    assert proc.stdout == ""  # nothing done


def test_install_sh_compiled_build(tmp_path: Path) -> None:
    if os.environ.get(COMPILED_ENVIRONMENT) != "1":
        pytest.skip("the compiled install takes ~45 s: %s=1 runs it" % COMPILED_ENVIRONMENT)
    require_program("gcc")
    checkout = _checkout(tmp_path)
    data, _ = _host(tmp_path / "home", 7125)
    env = _environment(data)
    env.pop("KESTIMATOR_BUILD")
    proc = subprocess.run([str(checkout / "install.sh"), "--allow-root", "--no-restart",
                           "-d", str(data)], env=env, capture_output=True, text=True,
                          timeout=INSTALL_TIMEOUT_S, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "kestimator build: compiled with mypyc\n" in proc.stdout
    assert "Installed: kestimator %s (compiled)" % __version__ in proc.stdout


# --- after --uninstall: every byte back, nothing of ours, Klipper starts (issue 35) -----------

KESTIMATOR_SECTION = b"# the time module\n[kestimator]\nupdate_interval: 1.0\n  \n; mine\n"
KESTIMATOR_SECTION_COMMENTED = (b"# the time module\n#[kestimator]\n#update_interval: 1.0\n"
                                b"  \n; mine\n")


def _tree(root: Path, skip: Path | None) -> dict[str, tuple[object, ...]]:
    """Every file, link and folder under root (but skip): bytes, targets and modes. A rustup
    on the test machine's PATH writes ~/.rustup the first time a build runs its proxies: not
    install.sh's, and not on a printer host."""
    found: dict[str, tuple[object, ...]] = {}
    for folder, folders, files in os.walk(root):
        here = Path(folder)
        folders[:] = [name for name in folders
                      if here / name != skip and here / name != root / ".rustup"]
        for name in folders + files:
            path = here / name
            relative = str(path.relative_to(root))
            mode = stat.S_IMODE(path.lstat().st_mode)
            if path.is_symlink():
                found[relative] = ("link", os.readlink(path))
            elif path.is_dir():
                found[relative] = ("folder", mode)
            else:
                found[relative] = ("file", path.read_bytes(), mode)
    return found


def _klipper_host(home: Path, data_name: str = "printer_data",
                  port: int = 7125) -> tuple[Path, Path]:
    """A host as _host makes it, its ~/klipper the oracle's real klippy (the module links into
    its extras/), printer.cfg including kestimator.cfg with the user's [kestimator] section."""
    klipper, _ = require_klipper()
    data, _ = _host(home, port)
    if data_name != data.name:
        data = data.rename(data.parent / data_name)
    shutil.rmtree(home / "klipper" / "klippy")
    shutil.copytree(Path(klipper) / "klippy", home / "klipper" / "klippy", symlinks=True,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "kestimator.py",
                                                  "kestimator"))
    config = data / "config"
    with open(config / "printer.cfg", "ab") as f:
        f.write(b"\n[include kestimator.cfg]\n")
    (config / "kestimator.cfg").write_bytes(KESTIMATOR_SECTION)
    return data, home / "klipper"


def _klipper_starts(klipper_home: Path, printer_cfg: Path, log: Path) -> tuple[bool, str]:
    """Klipper (batch mode, the oracle's MCU dictionary) started on printer_cfg, through its
    configuration to 'Configured MCU' and out: (whether it did, its log's end). Its Python
    writes .pyc files as on a host (the module's in its package's __pycache__)."""
    oracle_klipper, python = require_klipper()
    env = dict(os.environ, HOME=str(klipper_home.parent))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    batch = log.with_suffix(".batch")
    batch.write_text("")
    proc = subprocess.run(
        [python, str(klipper_home / "klippy" / "klippy.py"), str(printer_cfg), "-i", str(batch),
         "-o", "/dev/null", "-d", str(Path(oracle_klipper) / "out" / "klipper.dict"),
         "-l", str(log)], stdin=subprocess.DEVNULL, capture_output=True, cwd=klipper_home,
        timeout=120, env=env)
    text = log.read_text(errors="replace")
    started = proc.returncode == 0 and "Configured MCU" in text and "Config error" not in text
    return started, text[-1500:]


@pytest.mark.parametrize("case", ["plain", "symlinked_conf", "crlf_conf", "exclude_no_newline",
                                  "quote_in_data_path"])
def test_install_sh_uninstall_gives_back_every_byte_and_klipper_starts(
        case: str, corpus_root: Path, tmp_path: Path) -> None:
    checkout = _checkout(tmp_path)
    home = tmp_path / "home"
    data, klipper = _klipper_host(
        home, 'printer "one"_data' if case == "quote_in_data_path" else "printer_data")
    conf = data / "config" / "moonraker.conf"
    exclude = klipper / ".git" / "info" / "exclude"
    if case == "symlinked_conf":
        # Configs kept in a git folder, moonraker.conf a link to its file there.
        kept = home / "printer-configs" / "moonraker.conf"
        kept.parent.mkdir()
        conf.rename(kept)
        conf.symlink_to(kept)
    elif case == "crlf_conf":
        conf.write_bytes(conf.read_bytes().replace(b"\n", b"\r\n"))
    elif case == "exclude_no_newline":
        exclude.write_bytes(exclude.read_bytes() + b"klippy/extras/led_effect.py")
    # A host where Klipper has run: its own .pyc files are there (it stops at the section).
    assert not _klipper_starts(klipper, data / "config" / "printer.cfg", tmp_path / "0.log")[0]
    before = _tree(home, checkout)
    exclude_before = exclude.read_bytes()

    installed = _install(checkout, data)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    started, log = _klipper_starts(klipper, data / "config" / "printer.cfg", tmp_path / "on.log")
    assert started, log  # the module is there: Klipper takes the section
    # Klipper loaded the package (its Python compiled it where the link points).
    assert list((checkout / "plugins" / "klipper" / "kestimator" / "__pycache__").glob(
        "section.*.pyc"))
    if case == "symlinked_conf":
        assert os.readlink(conf) == str(home / "printer-configs" / "moonraker.conf")
        assert b"[update_manager kestimator]" in kept.read_bytes()
    elif case == "crlf_conf":
        added = conf.read_bytes()
        assert b"\r\n[update_manager kestimator]\r\n" in added
        assert b"\n" not in added.replace(b"\r\n", b"")
    elif case == "exclude_no_newline":
        again = _install(checkout, data)
        assert again.returncode == 0, again.stdout + again.stderr
        assert exclude.read_bytes() == exclude_before + b"\nklippy/extras/kestimator\n"
    elif case == "quote_in_data_path":
        if sys.version_info >= (3, 11):
            import tomllib
        else:
            import tomli as tomllib

        profile = data / "xdg-config" / "kestimator" / "config.toml"
        with open(profile, "rb") as f:
            assert tomllib.load(f)["printer_cfg"] == str(data / "config" / "printer.cfg")
        assert (data / "tools" / "klipper_estimator" / "default_estimator_cfg.json").exists()

    removed = _install(checkout, data, "--uninstall", "-y")
    assert removed.returncode == 0, removed.stdout + removed.stderr
    if case == "symlinked_conf":
        assert os.readlink(conf) == str(kept)  # still the link, its file without our lines
        assert b"kestimator" not in kept.read_bytes()
    elif case == "crlf_conf":
        assert conf.read_bytes() == before[str(conf.relative_to(home))][1]
    assert "kestimator.cfg:2: [kestimator] commented out" in removed.stdout
    after = _tree(home, checkout)
    user_cfg = str((data / "config" / "kestimator.cfg").relative_to(home))
    assert after.pop(user_cfg)[1] == KESTIMATOR_SECTION_COMMENTED
    before.pop(user_cfg)
    assert after == before
    assert _git("status", "--porcelain", cwd=checkout) == ""
    started, log = _klipper_starts(klipper, data / "config" / "printer.cfg", tmp_path / "off.log")
    assert started, log


def test_install_sh_uninstall_without_consent_stops_before_changing_anything(
        corpus_root: Path, tmp_path: Path) -> None:
    """Without -y and without a terminal to ask, --uninstall names the [kestimator] section
    that would keep Klipper from starting, says what to do, and changes nothing."""
    checkout = _checkout(tmp_path)
    home = tmp_path / "home"
    data, klipper = _klipper_host(home)
    installed = _install(checkout, data)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    before = _tree(home, None)
    refused = _install(checkout, data, "--uninstall")
    assert refused.returncode == 1
    assert refused.stdout == ""
    assert "[kestimator] is in %s:2 " % (data / "config" / "kestimator.cfg") in refused.stderr
    assert "--uninstall -y" in refused.stderr and "Nothing was changed." in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    assert _tree(home, None) == before  # type: ignore[arg-type]
    started, log = _klipper_starts(klipper, data / "config" / "printer.cfg", tmp_path / "k.log")
    assert started, log


def test_install_sh_refuses_a_read_only_moonraker_conf_before_changing_anything(
        tmp_path: Path) -> None:
    checkout = _checkout(tmp_path)
    home = tmp_path / "home"
    data, _ = _host(home, 7125)
    conf = data / "config" / "moonraker.conf"
    conf.chmod(0o444)
    before = _tree(home, checkout)
    refused = _install(checkout, data, "-y")
    assert refused.returncode == 1
    assert refused.stdout == ""
    assert refused.stderr == ("install.sh: cannot write %s (or its folder): make it writable, "
                              "then run ./install.sh again. Nothing was changed.\n" % conf)
    assert _tree(home, checkout) == before
    assert not (checkout / ".venv-host").exists()
    # Installed, then made read-only: --uninstall refuses the same way, before anything.
    conf.chmod(0o644)
    installed = _install(checkout, data)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    conf.chmod(0o444)
    middle = _tree(home, None)
    refused = _install(checkout, data, "--uninstall", "-y")
    assert refused.returncode == 1 and "cannot write %s" % conf in refused.stderr
    assert _tree(home, None) == middle  # type: ignore[arg-type]


def _fake_systemctl(tmp_path: Path, present: bool) -> dict[str, str]:
    """A PATH whose systemctl fails as in a container without systemd (and records its
    arguments), or that has no systemctl at all."""
    programs = _path_without(tmp_path, ("systemctl", "sudo"))
    if present:
        fake = programs / "systemctl"
        fake.write_text('#!/bin/sh\necho "$@" >> "%s"\necho "System has not been booted with '
                        'systemd as init system (PID 1). Can\'t operate." >&2\nexit 1\n'
                        % (tmp_path / "systemctl.args"))
        fake.chmod(0o755)
    return {"PATH": str(programs)}


@pytest.mark.parametrize("systemctl", ["fails", "missing"])
def test_install_sh_failed_moonraker_restart_says_what_is_installed_and_what_to_restart(
        systemctl: str, tmp_path: Path) -> None:
    """-y on a KIAUH multi-instance host (this data folder's Moonraker is moonraker-1) where
    the restart cannot happen: exit 0 after the whole install, the unit named in words."""
    checkout = _checkout(tmp_path)
    data, _ = _host(tmp_path / "home", 7125)
    units = tmp_path / "systemd"
    units.mkdir()
    (units / "moonraker.service").write_text(
        "[Service]\nEnvironmentFile=%s/printer_data/systemd/moonraker.env\n" % (tmp_path / "x"))
    (units / "moonraker-1.service").write_text(
        "[Service]\nEnvironmentFile=%s/systemd/moonraker.env\n" % data)
    env = dict(_environment(data), KESTIMATOR_SYSTEMD_DIR=str(units),
               **_fake_systemctl(tmp_path, systemctl == "fails"))
    proc = subprocess.run([str(checkout / "install.sh"), "--allow-root", "-y", "-d", str(data)],
                          env=env, capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S,
                          stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    reason = ("System has not been booted with systemd as init system (PID 1). Can't operate."
              if systemctl == "fails" else "this host has no systemctl")
    assert ("WARNING: Moonraker was not restarted (systemctl restart moonraker-1: %s).\n"
            % reason) in proc.stdout
    assert ("kestimator (kestimator %s (pure Python)) is installed: Moonraker's "
            "klipper_estimator runs it and moonraker.conf has its lines, but Moonraker runs "
            "them only once restarted. Restart Moonraker yourself for it to take effect (sudo "
            "systemctl restart moonraker-1" % __version__) in proc.stdout
    if systemctl == "fails":
        assert (tmp_path / "systemctl.args").read_text() == "restart moonraker-1\n"
    removed = subprocess.run([str(checkout / "install.sh"), "--allow-root", "-y", "--uninstall",
                              "-d", str(data)], env=env, capture_output=True, text=True,
                             timeout=INSTALL_TIMEOUT_S, stdin=subprocess.DEVNULL)
    assert removed.returncode == 0, removed.stdout + removed.stderr
    assert "kestimator is uninstalled, but Moonraker still runs it until it restarts. " \
        "Restart Moonraker yourself" in removed.stdout


def test_install_sh_uninstall_asks_at_a_terminal_before_commenting_out_the_section(
        tmp_path: Path) -> None:
    """At a terminal, --uninstall asks: no stops before anything, yes comments it out."""
    import pty

    checkout = _checkout(tmp_path)
    data, _ = _host(tmp_path / "home", 7125)
    printer_cfg = data / "config" / "printer.cfg"
    user_cfg = printer_cfg.read_bytes() + b"\n[kestimator]\nset_progress: False\n"
    printer_cfg.write_bytes(user_cfg)
    installed = _install(checkout, data)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    line = len(user_cfg.split(b"\n")) - 2

    def uninstall(answer: bytes) -> subprocess.CompletedProcess[str]:
        leader, follower = pty.openpty()
        try:
            os.write(leader, answer + b"\n")
            return subprocess.run([str(checkout / "install.sh"), "--allow-root", "--no-restart",
                                   "--uninstall", "-d", str(data)], env=_environment(data),
                                  capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S,
                                  stdin=follower)
        finally:
            os.close(leader)
            os.close(follower)

    before = _tree(tmp_path / "home", None)
    refused = uninstall(b"n")
    assert refused.returncode == 1
    assert "Klipper does not start with a [kestimator] section and no module: %s:%d" % (
        printer_cfg, line) in refused.stdout
    assert "Nothing was changed." in refused.stderr
    assert _tree(tmp_path / "home", None) == before
    agreed = uninstall(b"y")
    assert agreed.returncode == 0, agreed.stdout + agreed.stderr
    assert printer_cfg.read_bytes() == user_cfg.replace(
        b"\n[kestimator]\nset_progress: False\n", b"\n#[kestimator]\n#set_progress: False\n")
    assert not (data / "config" / "moonraker.conf.kestimator.bak").exists()
    assert not os.path.lexists(tmp_path / "home" / "klipper" / "klippy" / "extras" /
                               "kestimator")


def test_install_sh_uninstall_again_after_an_old_uninstall_comments_out_the_section(
        tmp_path: Path) -> None:
    """An earlier install.sh's --uninstall removed the module's link and left the section
    (Klipper no longer starts): --uninstall -y run again comments it out."""
    checkout = _checkout(tmp_path)
    data, _ = _host(tmp_path / "home", 7125)
    printer_cfg = data / "config" / "printer.cfg"
    user_cfg = printer_cfg.read_bytes() + b"[kestimator]\n"
    printer_cfg.write_bytes(user_cfg)
    installed = _install(checkout, data)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    (tmp_path / "home" / "klipper" / "klippy" / "extras" / "kestimator").unlink()
    removed = _install(checkout, data, "--uninstall", "-y")
    assert removed.returncode == 0, removed.stdout + removed.stderr
    assert printer_cfg.read_bytes() == user_cfg[:-len(b"[kestimator]\n")] + b"#[kestimator]\n"
    # Someone else's kestimator.py, or kestimator package, in extras/: their module, their
    # section, left alone.
    extras = tmp_path / "home" / "klipper" / "klippy" / "extras"
    printer_cfg.write_bytes(user_cfg)
    (extras / "kestimator.py").write_text("")
    again = _install(checkout, data, "--uninstall", "-y")
    assert again.returncode == 0, again.stdout + again.stderr
    assert printer_cfg.read_bytes() == user_cfg
    (extras / "kestimator.py").unlink()
    (extras / "kestimator").mkdir()
    (extras / "kestimator" / "__init__.py").write_text("")
    again = _install(checkout, data, "--uninstall", "-y")
    assert again.returncode == 0, again.stdout + again.stderr
    assert printer_cfg.read_bytes() == user_cfg
    assert (extras / "kestimator" / "__init__.py").exists()


def _update_through_moonraker(base: str) -> None:
    """What the update panel's button does: refresh, then update kestimator. This host has no
    systemd (`[machine] provider: none`), so Moonraker's last step, restarting the managed
    services (Klipper here), answers 503 "Service Actions Not Available"; the pull and what
    git ran during it are done by then (git_deploy.py: pull, dependencies, restart)."""
    _request(base + "/machine/update/refresh?name=kestimator", "POST")
    try:
        # The answer comes when the update is done: the build (in git's hook) included.
        _request(base + "/machine/update/upgrade?name=kestimator", "POST",
                 timeout=INSTALL_TIMEOUT_S)
    except urllib.error.HTTPError as exc:
        assert (exc.code, exc.reason) == (503, "Service Actions Not Available"), exc


def _worker_build(checkout: Path) -> tuple[str, str]:
    """The version and file of the kestimator the Klipper module's worker imports: its boot
    (WORKER_BOOT) run with the venv's Python, printing them instead of serving."""
    boot = _klipper_worker().WORKER_BOOT
    run = 'runpy.run_module("kestimator.worker", run_name="__main__", alter_sys=True)'
    assert run in boot
    probe = boot.replace(run, "import kestimator; print(kestimator.__version__, "
                              "kestimator.__file__, kestimator.build())")
    out = subprocess.run([str(checkout / ".venv-host" / "bin" / "python"), "-c", probe,
                          str(checkout)], capture_output=True, text=True, timeout=60,
                         cwd="/", check=True).stdout.split(None, 2)
    return out[0], out[1] + " " + out[2].strip()


def _klipper_worker():  # type: ignore[no-untyped-def]
    """The Klipper module's worker.py (its WORKER_BOOT), standard library only."""
    return load_script("kestimator_klipper_worker",
                       PROJECT / "plugins" / "klipper" / "kestimator" / "worker.py")


def test_update_from_moonraker_builds_the_new_commit_and_the_panel_shows_its_version(
        moonraker_python: str, tmp_path: Path) -> None:  # noqa: F811
    """An update from the panel (Moonraker's own git pull) leaves the new commit built in
    .venv-host (git's post-merge hook runs plugins/moonraker/build-venv before Moonraker
    restarts anything): Moonraker's estimator and the Klipper module's worker run the new
    code, the build stays the kind it was, and the panel's version is the project's tag."""
    compiled = os.environ.get(COMPILED_ENVIRONMENT) == "1"
    checkout = _checkout(tmp_path)
    port = _free_port()
    data, _ = _host(tmp_path / "home", port)
    env = _environment(data)
    if compiled:
        env.pop("KESTIMATOR_BUILD")
    first = subprocess.run([str(checkout / "install.sh"), "--allow-root", "--no-restart",
                            "-d", str(data), "-y"], env=env, capture_output=True, text=True,
                           timeout=INSTALL_TIMEOUT_S, stdin=subprocess.DEVNULL)
    assert first.returncode == 0, first.stdout + first.stderr
    kind = "compiled" if compiled else "pure Python"
    assert "Installed: kestimator %s (%s)" % (__version__, kind) in first.stdout
    assert "Tagged v%s" % __version__ in first.stdout
    assert _git("describe", "--tags", cwd=checkout).strip() == "v" + __version__
    assert _git("config", "remote.origin.tagOpt", cwd=checkout).strip() == "--no-tags"
    assert (checkout / ".git" / "hooks" / "post-merge").is_file()
    conf = (data / "config" / "moonraker.conf").read_text()
    assert "managed_services: klipper moonraker\n" in conf  # the Klipper module is linked
    assert _worker_build(checkout)[0] == __version__

    # The project's next commit: a new version, pushed to the origin.
    source = tmp_path / "source"
    init = source / "kestimator" / "__init__.py"
    new_version = __version__ + ".1"
    init.write_text(init.read_text().replace('__version__ = "%s"' % __version__,
                                             '__version__ = "%s"' % new_version))
    _git("-c", "user.name=test", "-c", "user.email=test@example.invalid", "commit", "-q",
         "-am", "version " + new_version, cwd=source)
    _git("push", "-q", str(tmp_path / "origin.git"), "main", cwd=source)
    new_commit = _git("rev-parse", "HEAD", cwd=source).strip()

    base = "http://127.0.0.1:%d" % port
    with _moonraker(moonraker_python, data, port) as process:
        _wait_ready(base, process, data / "logs" / "stdout.log")
        before = _update_status(base)
        assert before["version"] == "v%s-0" % __version__, before  # not v0.0.0-N
        _update_through_moonraker(base)
        deadline = time.monotonic() + INSTALL_TIMEOUT_S
        while (time.monotonic() < deadline and (checkout / ".venv-host" /
               "kestimator-commit").read_text(errors="replace").strip() != new_commit):
            time.sleep(0.5)
        assert _git("rev-parse", "HEAD", cwd=checkout).strip() == new_commit
        assert (checkout / ".venv-host" / "kestimator-commit").read_text() == new_commit + "\n"
        _request(base + "/machine/update/refresh?name=kestimator", "POST")
        after = _update_status(base)
        log = (data / "logs" / "moonraker.log").read_text(errors="replace")
        assert after["version"] == "v%s-0" % new_version, (after, log[-3000:])
    # build-venv ran (its stamp above is written by nothing else), and built as before.
    pip_log = (checkout / ".venv-host" / "pip.log").read_text(errors="replace")
    assert "kestimator build: %s" % ("compiled with mypyc" if compiled
                                      else "pure Python") in pip_log
    # The estimator Moonraker runs and the worker answer with the new commit's build.
    link = data / "tools" / "klipper_estimator" / "klipper_estimator_linux"
    answer = subprocess.run([str(link), "--version"], env=env, capture_output=True,
                            text=True, timeout=60)
    assert answer.stdout.startswith("klipper_estimator %s " % new_version), answer.stderr
    installed = subprocess.run([str(checkout / ".venv-host" / "bin" / "kestimator"),
                                "--version"], capture_output=True, text=True, timeout=60)
    assert installed.stdout.strip() == "kestimator %s (%s)" % (new_version, kind)
    version, where = _worker_build(checkout)
    assert version == new_version
    assert ".venv-host" in where and where.endswith(kind)
    # A commit that is not built yet: the worker runs the checkout's source instead.
    (checkout / ".venv-host" / "kestimator-commit").write_text("0" * 40 + "\n")
    version, where = _worker_build(checkout)
    assert version == new_version and where.startswith(str(checkout / "kestimator"))


# The module's file before it was a package: installs made then linked it into extras/.
ONE_FILE_MODULE = "plugins/klipper/kestimator.py"


def _one_file_module_commit() -> str:
    """The newest commit of this project whose Klipper module was one file (ONE_FILE_MODULE)."""
    require_program("git")
    last = subprocess.run(["git", "log", "-1", "--format=%H", "HEAD", "--", ONE_FILE_MODULE],
                          cwd=PROJECT, capture_output=True, text=True, timeout=60).stdout.strip()
    if not last:
        message = "this checkout's history does not reach the one-file Klipper module"
        if IN_CI:
            pytest.fail(message)
        pytest.skip(message)
    there = subprocess.run(["git", "cat-file", "-e", "%s:%s" % (last, ONE_FILE_MODULE)],
                           cwd=PROJECT, capture_output=True, timeout=60).returncode == 0
    return last if there else _git("rev-parse", last + "^", cwd=PROJECT).strip()


def test_an_update_from_the_one_file_module_links_the_package_and_klipper_loads_it(
        moonraker_python: str, corpus_root: Path, tmp_path: Path) -> None:  # noqa: F811
    """A host installed when the Klipper module was one file (klippy/extras/kestimator.py,
    linked by that commit's install.sh, compiled by Klipper's Python), updated from the panel
    to this commit: git's hook links the package (klippy/extras/kestimator) in the file's
    place, Klipper's exclude names it, nothing of the file is left, and real Klipper starts
    with the [kestimator] section, loading the package. --uninstall then gives it all back."""
    old = _one_file_module_commit()
    checkout = _checkout(tmp_path, old)
    port = _free_port()
    home = tmp_path / "home"
    data, klipper = _klipper_host(home, port=port)
    printer_cfg = data / "config" / "printer.cfg"
    extras = klipper / "klippy" / "extras"
    exclude = klipper / ".git" / "info" / "exclude"
    # Klipper's tree as the user has it (its own .pyc files aside: its runs here write them).
    def klipper_tree() -> dict[str, tuple[object, ...]]:
        return {name: value for name, value in _tree(klipper, None).items()
                if "__pycache__" not in name}
    before = klipper_tree()
    installed = _install(checkout, data)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    assert os.readlink(extras / "kestimator.py") == str(checkout / ONE_FILE_MODULE)
    started, log = _klipper_starts(klipper, printer_cfg, tmp_path / "old.log")
    assert started, log
    assert list((extras / "__pycache__").glob("kestimator.*.pyc"))

    # This commit, pushed to the origin, and pulled by Moonraker's update manager.
    source = tmp_path / "source"
    _git("rm", "-r", "-q", ".", cwd=source)
    _copy_project(source)
    _git("add", "-A", cwd=source)
    _git(*IDENTITY, "commit", "-q", "-m", "the Klipper module as a package", cwd=source)
    _git("push", "-q", str(tmp_path / "origin.git"), "main", cwd=source)
    new_commit = _git("rev-parse", "HEAD", cwd=source).strip()
    base = "http://127.0.0.1:%d" % port
    stamp = checkout / ".venv-host" / "kestimator-commit"
    # Moonraker runs as the user it was installed by, HOME theirs (git's hook looks for
    # Klipper at ~/klipper, where that install.sh linked the file).
    with _moonraker(moonraker_python, data, port, home=home) as process:
        _wait_ready(base, process, data / "logs" / "stdout.log")
        _update_status(base)  # the update manager has read the checkout
        _update_through_moonraker(base)
        deadline = time.monotonic() + INSTALL_TIMEOUT_S
        while (time.monotonic() < deadline
               and stamp.read_text(errors="replace").strip() != new_commit):
            time.sleep(0.5)
    assert _git("rev-parse", "HEAD", cwd=checkout).strip() == new_commit
    assert stamp.read_text() == new_commit + "\n"
    assert os.readlink(extras / "kestimator") == str(checkout / "plugins" / "klipper" /
                                                     "kestimator")
    assert not os.path.lexists(extras / "kestimator.py")
    assert not list((extras / "__pycache__").glob("kestimator.*.pyc"))
    lines = exclude.read_text().splitlines()
    assert lines.count("klippy/extras/kestimator") == 1
    assert "klippy/extras/kestimator.py" not in lines
    assert "kestimator" not in _git("status", "--porcelain", "--ignored=no", cwd=klipper)
    started, log = _klipper_starts(klipper, printer_cfg, tmp_path / "new.log")
    assert started, log
    assert list((checkout / "plugins" / "klipper" / "kestimator" / "__pycache__").glob(
        "section.*.pyc"))

    removed = _install(checkout, data, "--uninstall", "-y")
    assert removed.returncode == 0, removed.stdout + removed.stderr
    assert (data / "config" / "kestimator.cfg").read_bytes() == KESTIMATOR_SECTION_COMMENTED
    assert klipper_tree() == before


def _mainsail_general(base: str) -> dict:
    query = urllib.parse.urlencode({"namespace": "mainsail"})
    return dict(_request(base + "/server/database/item?" + query)["result"]["value"]
                .get("general", {}))


def test_uninstall_without_moonraker_keeps_what_puts_the_frontend_settings_back_later(
        moonraker_python: str, tmp_path: Path) -> None:  # noqa: F811
    """--frontend-settings through a Moonraker on a port of its own; --uninstall while that
    Moonraker is down stops before changing anything and says Moonraker must run; once it
    runs, --uninstall (without --moonraker: the address is remembered) puts Mainsail's
    settings back and removes kestimator."""
    checkout = _checkout(tmp_path)
    port = _free_port()
    data, conf_before = _host(tmp_path / "home", port)
    base = "http://127.0.0.1:%d" % port
    ours = {"calcPrintProgress": "slicer", "calcEstimateTime": ["file"],
            "calcEtaTime": ["file"]}
    with _moonraker(moonraker_python, data, port) as process:
        _wait_ready(base, process, data / "logs" / "stdout.log")
        _request(base + "/server/database/item", "POST",
                 b'{"namespace": "mainsail", "key": "general.calcEtaTime", '
                 b'"value": ["file", "slicer"]}', {"Content-Type": "application/json"})
        installed = _install(checkout, data, "--frontend-settings", "--moonraker", base)
        assert installed.returncode == 0, installed.stdout + installed.stderr
        assert _mainsail_general(base) == ours
    link = data / "tools" / "klipper_estimator" / "klipper_estimator_linux"
    conf = data / "config" / "moonraker.conf"
    installed_conf = conf.read_bytes()

    refused = _install(checkout, data, "--uninstall")
    assert refused.returncode == 1
    assert "Moonraker at %s did not answer" % base in refused.stderr
    assert "Nothing was changed." in refused.stderr
    assert link.is_symlink() and conf.read_bytes() == installed_conf
    assert (checkout / ".venv-host").is_dir()

    with _moonraker(moonraker_python, data, port) as process:
        _wait_ready(base, process, data / "logs" / "stdout.log")
        removed = _install(checkout, data, "--uninstall")
        assert removed.returncode == 0, removed.stdout + removed.stderr
        assert _mainsail_general(base) == {"calcEtaTime": ["file", "slicer"]}
        kept = _request(base + "/server/database/list")["result"]
    assert "kestimator" not in kept.get("namespaces", [])
    assert "calcEtaTime back to" in removed.stdout
    assert conf.read_bytes() == conf_before
    assert not link.is_symlink() and link.read_bytes() == FAKE_ESTIMATOR
    assert not (data / "tools" / "klipper_estimator" / "kestimator-install.state").exists()


@pytest.mark.parametrize("name", ['kest"imator', "kest$imator", "kest`x`imator"])
def test_install_sh_refuses_a_checkout_path_pip_and_the_update_hook_break_on(
        tmp_path: Path, name: str) -> None:
    """A '"' or '$' in the checkout's path broke every update (git's hook, and pip: '$name'
    is a variable to setuptools, and its scripts start through sh in double quotes): the
    install stops at once, naming the path, with nothing changed."""
    cloned = _checkout(tmp_path)
    checkout = cloned.parent / name
    cloned.rename(checkout)
    home = tmp_path / "home"
    data, _ = _host(home, 7125)
    before = _tree(home, None)
    refused = _install(checkout, data, "-y", "--frontend-settings")
    assert refused.returncode == 1
    assert refused.stdout == ""
    assert "path %s holds one of" % checkout in refused.stderr
    assert "Nothing was changed." in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    assert _tree(home, None) == before  # type: ignore[arg-type]
