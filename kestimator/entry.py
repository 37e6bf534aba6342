"""The console scripts' entry points (`kestimator`, `kestimator-compat`, `python -m kestimator`).

Owns one thing: Ctrl-C while the program's modules are still loading. pip's generated script
imports its target before calling it, so a KeyboardInterrupt during `import kestimator.cli`
would print a traceback; these functions import the real `main` inside a guard and print one
line instead. This module imports nothing but `sys`.
"""

from __future__ import annotations

import sys

EXIT_INTERRUPTED = 1
"""As `kestimator.cli.main` and `kestimator.compat.main` exit on Ctrl-C."""


def kestimator() -> int:
    """`kestimator`: `kestimator.cli.main`, with Ctrl-C during loading one line."""
    try:
        from kestimator.cli import main
    except KeyboardInterrupt:
        sys.stderr.write("kestimator: interrupted\n")
        return EXIT_INTERRUPTED
    return main()


def kestimator_compat() -> int:
    """`kestimator-compat`: `kestimator.compat.main`, with Ctrl-C during loading one line."""
    try:
        from kestimator.compat import main
    except KeyboardInterrupt:
        sys.stderr.write("kestimator-compat: interrupted\n")
        return EXIT_INTERRUPTED
    return main()
