"""Build `dist/kestimator.pyz`: the whole `kestimator` command in one file, no install needed.

Owns the single-file zipapp that slicer users without pip paste into their post-processing
line (`/path/to/python3 /path/to/kestimator.pyz inject ...`). The archive holds the
`kestimator/` package's Python sources and nothing else (no third-party code, no caches), and
its entry is `kestimator.entry:kestimator`, behind a guard that turns "this python3 is too
old" into one line a slicer's error dialog can show (it runs on 3.9: macOS's own
/usr/bin/python3).

Usage: python3 tools/build_zipapp.py [-o dist/kestimator.pyz]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import zipapp
from collections.abc import Sequence
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
PACKAGE = "kestimator"
ENTRY = "kestimator.entry:kestimator"
MIN_PYTHON = (3, 9)
DEFAULT_OUTPUT = PROJECT / "dist" / "kestimator.pyz"
INTERPRETER = "/usr/bin/env python3"

# Written with % formatting and no annotations so that any old python3 can parse it and
# reach the version check instead of failing on syntax.
MAIN_TEMPLATE = '''\
# Entry point of kestimator.pyz, written by tools/build_zipapp.py: runs %(entry)s.
import sys

if sys.version_info[:2] < %(min_python)r:
    sys.stderr.write("kestimator: error: needs Python %(min_text)s or newer, but %%s is "
                     "%%d.%%d\\n" %% (sys.executable, sys.version_info[0], sys.version_info[1]))
    sys.exit(1)

from %(module)s import %(function)s

sys.exit(%(function)s())
'''


def main_py() -> str:
    """The archive's `__main__.py`: version guard, then `ENTRY`."""
    module, function = ENTRY.split(":")
    return MAIN_TEMPLATE % {
        "entry": ENTRY, "min_python": MIN_PYTHON, "module": module, "function": function,
        "min_text": "%d.%d" % MIN_PYTHON}


def _stage(staging: Path) -> None:
    """Copy the package's .py files (only) and the entry point into `staging`."""
    source = PROJECT / PACKAGE
    for path in sorted(source.rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        target = staging / PACKAGE / path.relative_to(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, target)
    (staging / "__main__.py").write_text(main_py(), encoding="utf-8")


def build(output: Path = DEFAULT_OUTPUT) -> Path:
    """Write the zipapp to `output` (its directory is created) and return the path."""
    output.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="kestimator-pyz-") as tmp:
        staging = Path(tmp)
        _stage(staging)
        zipapp.create_archive(staging, output, interpreter=INTERPRETER, compressed=True)
    return output


def main(argv: Sequence[str] | None = None) -> int:
    """Build the zipapp; print its path."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT,
                        help="where to write the archive (default: %(default)s)")
    args = parser.parse_args(argv)
    print(build(args.output))
    return 0


if __name__ == "__main__":
    sys.exit(main())
