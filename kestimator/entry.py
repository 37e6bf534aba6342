"""The console scripts' entry points (`kestimator`, `kestimator-compat`, `python -m kestimator`,
`python -m kestimator.compat`): what only a program, never a library caller, may do.

Owns two things. Ctrl-C while the program's modules are still loading: pip's generated
script imports its target before calling it, so a KeyboardInterrupt during `import
kestimator.cli` would print a traceback; these functions import the real `main` inside a
guard and print one line instead. And the process's signal handlers: `run_program` turns
SIGTERM and SIGHUP into `kestimator.files.Terminated` while `main` runs (a stopped run
removes its temporary file and exits 128 + the signal number), then puts back what was
there. `kestimator.cli.main` and `kestimator.compat.main` install none themselves, so a
library caller keeps its own. And the garbage collector while the program starts: loading
makes about 100,000 objects that all live as long as the program, so no collection runs
while it loads (its walks were a tenth of the start-up), and `run_program` freezes them on CPython
(`gc.freeze`: the collections a long pass triggers do not walk them again). This module
imports nothing at load but `gc`, `sys` and `typing`.
"""

from __future__ import annotations

import gc
import sys
from collections.abc import Callable

EXIT_INTERRUPTED = 1
"""As `kestimator.cli.main` and `kestimator.compat.main` exit on Ctrl-C."""


def run_program(main: Callable[[], int]) -> int:
    """`main()` as the program: SIGTERM/SIGHUP clean up and exit 128 + signal while it runs
    (`kestimator.files.terminating_cleanly`); the handlers before are restored after. The
    objects alive before it are frozen out of the garbage collector's walks (gc.freeze)."""
    from kestimator.files import terminating_cleanly

    freeze = getattr(gc, "freeze", None)  # CPython's; PyPy's gc has none
    if freeze is not None:
        freeze()
    with terminating_cleanly():
        return main()


def kestimator() -> int:
    """`kestimator`: `kestimator.cli.main`, with Ctrl-C during loading one line."""
    gc.disable()
    try:
        from kestimator.cli import main
    except KeyboardInterrupt:
        sys.stderr.write("kestimator: interrupted\n")
        return EXIT_INTERRUPTED
    finally:
        gc.enable()
    return run_program(main)


def kestimator_compat() -> int:
    """`kestimator-compat`: `kestimator.compat.main`, with Ctrl-C during loading one line."""
    gc.disable()
    try:
        from kestimator.compat import main
    except KeyboardInterrupt:
        sys.stderr.write("kestimator-compat: interrupted\n")
        return EXIT_INTERRUPTED
    finally:
        gc.enable()
    return run_program(main)
