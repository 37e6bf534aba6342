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
        os.kill(os.getpid(), signum)
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
