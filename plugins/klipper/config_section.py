"""Find and comment out the `[kestimator]` section of a printer.cfg and of the files it
`[include]`s, so that Klipper starts once the module is gone (`install.sh --uninstall`).

    python3 plugins/klipper/config_section.py find PRINTER_CFG
    python3 plugins/klipper/config_section.py comment PRINTER_CFG

Klipper stops at start with "Section 'kestimator' is not a valid config section" when
printer.cfg has the section but klippy/extras/ no longer has the module. This script reads the
files as Klipper's configfile.py does (`ConfigFileReader._parse_config` and
`_resolve_include` of Klipper 84104bbbd: `#` starts a comment anywhere on a line,
`[include GLOB]` is relative to the including file, its matches read in sorted order, a missing
file that is no glob is an error, a file included inside itself is an error) and finds each
`[kestimator]` header and the lines up to the next section header.

`find` prints `FILE:LINE` for each such header. `comment` puts `#` before each of the
section's lines that Klipper reads (the header, its options and their continuation lines) as
Klipper's own SAVE_CONFIG comments out a value (`ConfigAutoSave._strip_duplicates`): every
other byte of every file stays as it was (line endings included), a file reached through a
symbolic link is edited where the link points, and its mode and owner stay. Every file is
checked for writing (a file without its owner's write bit counts as read-only, for root
too) before the first one is changed. One line per commented section; errors
are one line on stderr naming the file (and line), exit status 1, and no file changed.
Standard library only: install.sh runs it with the system's python3.
"""
from __future__ import annotations

import glob
import os
import re
import stat
import sys

# configparser.RawConfigParser.SECTCRE, which Klipper's reader matches each line with.
SECTCRE = re.compile(r"\[(?P<header>.+)\]")
SECTION = "kestimator"


class ConfigError(Exception):
    """A config file Klipper would not read either (the message names it)."""


class Section:
    """One `[kestimator]` section: its file, its header's line (1-based) and the indexes of
    the lines Klipper reads in it."""

    def __init__(self, filename: str, header_line: int) -> None:
        self.filename = filename
        self.header_line = header_line
        self.read_lines: list[int] = []


def _read_config_file(filename: str) -> list[bytes]:
    """The file's lines split at '\\n', each with its own '\\r' if it has one (the bytes
    joined by '\\n' again are the file)."""
    try:
        with open(filename, "rb") as f:
            return f.read().split(b"\n")
    except OSError as exc:
        raise ConfigError("Unable to open config file %s: %s" % (filename, exc.strerror)) \
            from None


def _klipper_text(line: bytes) -> str:
    """The line as Klipper parses it: '\\r\\n' read as '\\n', everything from '#' gone."""
    text = line.decode("utf-8", "surrogateescape")
    if text.endswith("\r"):
        text = text[:-1]
    pos = text.find("#")
    return text if pos < 0 else text[:pos]


def _header(text: str) -> str | None:
    """The section name of a header line (at the line's start, as sections are written)."""
    if text[:1].isspace():
        return None
    mo = SECTCRE.match(text.strip())
    return mo.group("header") if mo else None


def _parse_config(filename: str, found: list[Section], visited: set[str]) -> None:
    path = os.path.abspath(filename)
    if path in visited:
        raise ConfigError("Recursive include of config file '%s'" % (filename,))
    visited.add(path)
    current: Section | None = None
    for index, line in enumerate(_read_config_file(filename)):
        text = _klipper_text(line)
        header = _header(text)
        if header is not None:
            current = None
            if header.startswith("include "):
                _resolve_include(filename, header[8:], found, visited)
            elif header == SECTION:
                current = Section(filename, index + 1)
                current.read_lines.append(index)
                found.append(current)
            continue
        stripped = text.strip()
        if current is not None and stripped and not stripped.startswith(";"):
            current.read_lines.append(index)
    visited.remove(path)


def _resolve_include(source_filename: str, include_spec: str, found: list[Section],
                     visited: set[str]) -> None:
    dirname = os.path.dirname(source_filename)
    include_glob = os.path.join(dirname, include_spec.strip())
    include_filenames = glob.glob(include_glob)
    if not include_filenames and not glob.has_magic(include_glob):
        raise ConfigError("Include file '%s' does not exist" % (include_glob,))
    for include_filename in sorted(include_filenames):
        _parse_config(include_filename, found, visited)


def find_sections(printer_cfg: str) -> list[Section]:
    """Every `[kestimator]` section Klipper reads from printer_cfg and its includes."""
    found: list[Section] = []
    _parse_config(printer_cfg, found, set())
    return found


def _write_keeping_file(filename: str, data: bytes) -> None:
    """Replace the file's bytes where a symbolic link points, keeping its mode and owner."""
    real = os.path.realpath(filename)
    before = os.stat(real)
    temporary = real + ".kestimator-tmp"
    try:
        with open(temporary, "wb") as f:
            f.write(data)
        os.chmod(temporary, before.st_mode & 0o7777)
        if os.geteuid() == 0:
            os.chown(temporary, before.st_uid, before.st_gid)
        os.replace(temporary, real)
    finally:
        if os.path.lexists(temporary):
            os.remove(temporary)


def comment_sections(printer_cfg: str) -> list[Section]:
    """Put '#' before each line Klipper reads in each `[kestimator]` section; the sections."""
    sections = find_sections(printer_cfg)
    files: dict[str, list[Section]] = {}
    for section in sections:
        files.setdefault(section.filename, []).append(section)
    for filename in files:
        real = os.path.realpath(filename)
        # A file without its owner's write bit is read-only by choice, for root too.
        if not os.access(real, os.W_OK) or not os.stat(real).st_mode & stat.S_IWUSR \
                or not os.access(os.path.dirname(real), os.W_OK):
            raise ConfigError("%s:%d: cannot write %s (nothing was changed)"
                              % (filename, files[filename][0].header_line, real))
    for filename, in_file in files.items():
        lines = _read_config_file(filename)
        for section in in_file:
            for index in section.read_lines:
                lines[index] = b"#" + lines[index]
        _write_keeping_file(filename, b"\n".join(lines))
    return sections


def main(argv: list[str]) -> int:
    if len(argv) != 3 or argv[1] not in ("find", "comment"):
        print("usage: config_section.py find|comment PRINTER_CFG", file=sys.stderr)
        return 2
    action, printer_cfg = argv[1], argv[2]
    try:
        if action == "find":
            for section in find_sections(printer_cfg):
                print("%s:%d" % (section.filename, section.header_line))
        else:
            for section in comment_sections(printer_cfg):
                print("%s:%d: [%s] commented out" % (section.filename, section.header_line,
                                                     SECTION))
    except ConfigError as exc:
        print("config_section.py: %s" % exc, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
