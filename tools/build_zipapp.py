"""Build `dist/kestimator.pyz`: the whole `kestimator` command in one file, no install needed.

Owns the single-file zipapp that slicer users without pip paste into their post-processing
line (`/path/to/python3 /path/to/kestimator.pyz inject ...`). The archive holds the
`kestimator/` package's Python sources and `tomli`'s (pure Python, MIT, with its licence: the
profile is TOML, and Python before 3.11 has no `tomllib`), nothing else (no caches), and its
entry is `kestimator.entry:kestimator`, behind a guard that turns "this python3 is too old"
into one line a slicer's error dialog can show (it runs on 3.9: macOS's own
/usr/bin/python3). tomli's sources come from the tomli this Python imports, else from its
pure wheel, fetched with `pip download`.

Usage: python3 tools/build_zipapp.py [-o dist/kestimator.pyz]
"""

from __future__ import annotations

import argparse
import importlib.util
import shutil
import subprocess
import sys
import tempfile
import zipapp
import zipfile
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


TOMLI = "tomli"
TOMLI_REQUIREMENT = "tomli>=1.1"
TOMLI_LICENCE = "tomli/LICENSE"
"""Where tomli's licence goes in the archive (MIT asks for it beside the code)."""


class BuildError(Exception):
    """The archive cannot be built: one line for the person building it."""


def installed_tomli() -> dict[str, bytes] | None:
    """tomli's sources and licence as archive name -> bytes, from the tomli this Python
    imports (its .py files: a compiled wheel ships them beside its extension modules), or
    None when it has none."""
    spec = importlib.util.find_spec(TOMLI)
    if spec is None or spec.origin is None:
        return None
    from importlib import metadata

    package = Path(spec.origin).parent
    files = {"tomli/" + path.relative_to(package).as_posix(): path.read_bytes()
             for path in sorted(package.rglob("*.py")) if "__pycache__" not in path.parts}
    licence = [f for f in metadata.distribution(TOMLI).files or ()
               if f.name.upper().startswith(("LICENSE", "LICENCE", "COPYING"))]
    if not licence:
        raise BuildError("the installed tomli carries no licence file to ship with it")
    files[TOMLI_LICENCE] = Path(str(licence[0].locate())).read_bytes()
    return files


def wheel_tomli(wheel: Path) -> dict[str, bytes]:
    """tomli's sources and licence from a tomli wheel (the pure one: .py files only)."""
    files: dict[str, bytes] = {}
    with zipfile.ZipFile(wheel) as archive:
        for name in archive.namelist():
            if name.startswith("tomli/") and name.endswith(".py"):
                files[name] = archive.read(name)
            elif ".dist-info/" in name and name.rsplit("/", 1)[-1].upper().startswith(
                    ("LICENSE", "LICENCE", "COPYING")):
                files[TOMLI_LICENCE] = archive.read(name)
    if "tomli/__init__.py" not in files or TOMLI_LICENCE not in files:
        raise BuildError("%s holds no tomli package with its licence" % wheel)
    return files


def downloaded_tomli(directory: Path) -> dict[str, bytes]:
    """tomli's pure wheel fetched with pip into `directory`, read by `wheel_tomli`."""
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
         "--platform", "any", "--implementation", "py", "--abi", "none",
         "--python-version", "%d.%d" % MIN_PYTHON, "-d", str(directory), TOMLI_REQUIREMENT],
        capture_output=True, text=True)
    wheels = sorted(directory.glob("tomli-*-py3-none-any.whl"))
    if proc.returncode != 0 or not wheels:
        raise BuildError("the archive carries tomli (Python 3.9 and 3.10 read the profile "
                         "with it), and this Python has none and pip could not fetch it: "
                         "pip install tomli (or pip download tomli), then build again")
    return wheel_tomli(wheels[-1])


def _stage(staging: Path) -> None:
    """Copy the package's .py files (only), tomli's and the entry point into `staging`."""
    source = PROJECT / PACKAGE
    for path in sorted(source.rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        target = staging / PACKAGE / path.relative_to(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, target)
    tomli = installed_tomli()
    if tomli is None:
        download = staging.parent / "tomli-download"
        download.mkdir()
        tomli = downloaded_tomli(download)
    for name, data in tomli.items():
        target = staging / name
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    (staging / "__main__.py").write_text(main_py(), encoding="utf-8")


def build(output: Path = DEFAULT_OUTPUT) -> Path:
    """Write the zipapp to `output` (its directory is created) and return the path."""
    output.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="kestimator-pyz-") as tmp:
        staging = Path(tmp) / "archive"
        staging.mkdir()
        _stage(staging)
        zipapp.create_archive(staging, output, interpreter=INTERPRETER, compressed=True)
    return output


def main(argv: Sequence[str] | None = None) -> int:
    """Build the zipapp; print its path."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT,
                        help="where to write the archive (default: %(default)s)")
    args = parser.parse_args(argv)
    try:
        print(build(args.output))
    except BuildError as exc:
        sys.stderr.write("build_zipapp: error: %s\n" % exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
