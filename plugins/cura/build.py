"""Build ``dist/kestimator_cura-<version>.curapackage``: the Cura plugin with the core vendored.

Owns the package layout Cura's package manager installs (Uranium ``PackageManager``): a zip
with ``package.json`` at its root and the plugin under ``files/plugins/<id>/``, which Cura
moves to ``<config>/plugins/<id>/<id>/``. The core package ``kestimator/`` of this checkout is
copied to ``files/plugins/<id>/vendor/kestimator/`` (``.py`` files only), so nothing is
installed with pip inside Cura. The plugin's version must equal the core's: one release, one
number. The zip is deterministic (sorted names, fixed timestamps), so a rebuild of the same
tree gives the same bytes.

Usage: ``python3 plugins/cura/build.py [--out-dir DIR]``; prints the package's path.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import zipfile
from collections.abc import Iterator, Sequence
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parents[1]
PLUGIN_ID = "kestimator_cura"
PLUGIN_DIR = HERE / PLUGIN_ID
CORE_DIR = PROJECT / "kestimator"
CORE_PACKAGE = "kestimator"
VENDOR = "vendor"
PACKAGE_SDK_VERSION = "8.0.0"
"""The package's SDK (Cura 5.x); plugin.json lists every SDK the plugin itself loads on."""
LICENSE = "GPL-3.0-or-later"
ZIP_TIMESTAMP = (1980, 1, 1, 0, 0, 0)
_VERSION_RE = re.compile(r'^__version__ = "([^"]+)"', re.MULTILINE)
_SKIPPED_DIRS = frozenset(("__pycache__", VENDOR))


class BuildError(Exception):
    """The tree cannot be packaged as it is."""


def core_version(core_dir: Path = CORE_DIR) -> str:
    """``kestimator.__version__`` read from the source (the installed one may differ)."""
    match = _VERSION_RE.search((core_dir / "__init__.py").read_text(encoding="utf-8"))
    if match is None:
        raise BuildError("no __version__ in %s" % (core_dir / "__init__.py"))
    return match.group(1)


def plugin_metadata(plugin_dir: Path = PLUGIN_DIR) -> dict[str, object]:
    """The plugin's plugin.json."""
    return json.loads((plugin_dir / "plugin.json").read_text(encoding="utf-8"))


def package_json(metadata: dict[str, object]) -> dict[str, object]:
    """Cura's package.json for the plugin described by ``metadata`` (its plugin.json)."""
    return {
        "package_id": PLUGIN_ID,
        "package_type": "plugin",
        "display_name": metadata["name"],
        "description": metadata["description"],
        "package_version": metadata["version"],
        "sdk_version": PACKAGE_SDK_VERSION,
        "sdk_version_semver": PACKAGE_SDK_VERSION,
        "author": {
            "author_id": "kestimator",
            "display_name": metadata["author"],
            },
        "license": LICENSE,
        "tags": ["klipper", "print time", "m73"],
    }


def _tree(root: Path, suffixes: tuple[str, ...]) -> Iterator[Path]:
    for path in sorted(root.rglob("*")):
        relative = path.relative_to(root)
        if any(part in _SKIPPED_DIRS for part in relative.parts[:-1]):
            continue
        if path.is_file() and path.suffix in suffixes:
            yield path


def package_members(plugin_dir: Path = PLUGIN_DIR, core_dir: Path = CORE_DIR,
                    readme: Path = HERE / "README.md") -> list[tuple[str, bytes]]:
    """(name in the zip, content) for every file of the package, package.json first."""
    metadata = plugin_metadata(plugin_dir)
    version = core_version(core_dir)
    if metadata.get("version") != version:
        raise BuildError("plugin.json version %r differs from kestimator %s"
                         % (metadata.get("version"), version))
    base = "files/plugins/%s/" % PLUGIN_ID
    members = [("package.json",
                (json.dumps(package_json(metadata), indent=2) + "\n").encode("utf-8"))]
    members += [(base + path.relative_to(plugin_dir).as_posix(), path.read_bytes())
                for path in _tree(plugin_dir, (".py", ".json"))]
    members.append((base + "README.md", readme.read_bytes()))
    members += [(base + "%s/%s/%s" % (VENDOR, CORE_PACKAGE, path.relative_to(core_dir).as_posix()),
                 path.read_bytes())
                for path in _tree(core_dir, (".py",))]
    return members


def build(out_dir: Path = HERE / "dist") -> Path:
    """Write the .curapackage into ``out_dir`` and return its path."""
    members = package_members()
    version = plugin_metadata()["version"]
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / ("%s-%s.curapackage" % (PLUGIN_ID, version))
    partial = target.with_name(target.name + ".partial")
    with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members:
            info = zipfile.ZipInfo(name, ZIP_TIMESTAMP)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            archive.writestr(info, data)
    partial.replace(target)
    return target


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: build the package and print where it is."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=HERE / "dist",
                        help="where to write the package (default: plugins/cura/dist)")
    args = parser.parse_args(argv)
    try:
        print(build(args.out_dir))
    except (BuildError, OSError) as exc:
        print("build.py: %s" % exc, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
