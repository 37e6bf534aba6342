"""A SIGTERM/SIGHUP that arrives while a temporary file is being created leaves no file.

The signal is sent from inside `tempfile.mkstemp`, right after the file exists and before
its name is returned: the window the race in `test_reliability_compat`'s signal test hits
now and then under load.
"""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import threading
from pathlib import Path

import pytest

from kestimator.files import Terminated, cleanup_on_termination, make_temp_file


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="POSIX signal masks")
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_during_temp_file_creation_leaves_no_file(
        signum: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_mkstemp = tempfile.mkstemp

    def mkstemp_then_signal(*args: object, **kwargs: object) -> tuple[int, str]:
        made = real_mkstemp(*args, **kwargs)  # type: ignore[call-overload]
        # To this thread, as a lone CLI process's signal comes to its only thread: a signal
        # sent to the process could go to another thread that does not hold it back (the
        # pytest-xdist worker's), which a kestimator process never has.
        signal.pthread_kill(threading.get_ident(), signum)
        # Give the handler every chance to run before the name is returned.
        for _ in range(1000):
            sys.getrecursionlimit()
        return made  # type: ignore[no-any-return]

    previous = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    cleanup_on_termination()
    try:
        monkeypatch.setattr(tempfile, "mkstemp", mkstemp_then_signal)
        with pytest.raises(Terminated):
            make_temp_file("out.gcode.", ".kestimator-tmp", str(tmp_path))
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    assert os.listdir(tmp_path) == []


_HANDLED = [s for s in (getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None))
            if s is not None]


def _handlers() -> dict[int, object]:
    return {s: signal.getsignal(s) for s in _HANDLED}


@pytest.mark.parametrize("argv", [["estimate", "no-such-file.gcode"], ["limits", "--json",
                                                                       "--no-profile"]])
def test_cli_main_in_process_leaves_the_callers_signal_handlers(
        argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """A library caller (a test, the Cura plugin) keeps its handlers: only the program's
    entry points (kestimator.entry) install kestimator's."""
    from kestimator import cli

    def mine(signum: int, frame: object) -> None:
        raise AssertionError("not called")

    before = _handlers()
    try:
        for s in _HANDLED:
            signal.signal(s, mine)
        cli.main(argv)
        assert _handlers() == {s: mine for s in _HANDLED}
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)  # type: ignore[arg-type]
    assert _handlers() == before
    capsys.readouterr()


@pytest.mark.parametrize("argv", [["--version"], ["estimate", "no-such-file.gcode"]])
def test_compat_main_in_process_leaves_the_callers_signal_handlers(
        argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    from kestimator import compat

    before = _handlers()
    compat.main(argv)
    assert _handlers() == before
    capsys.readouterr()


def test_the_entry_points_install_the_handlers_only_while_main_runs() -> None:
    from kestimator import entry, files

    before = _handlers()
    during: dict[int, object] = {}

    def main() -> int:
        during.update(_handlers())
        return 7

    assert entry.run_program(main) == 7
    assert during == {s: files._terminate for s in _HANDLED}
    assert _handlers() == before


@pytest.mark.skipif(not hasattr(signal, "SIGTERM"), reason="POSIX signals")
def test_a_sigterm_under_the_entry_point_is_128_plus_the_signal() -> None:
    from kestimator import entry

    def main() -> int:
        from kestimator.files import Terminated
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):
                sys.getrecursionlimit()
        except Terminated as exc:
            return 128 + exc.signum
        return 0

    assert entry.run_program(main) == 128 + signal.SIGTERM
