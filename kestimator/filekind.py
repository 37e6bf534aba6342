"""Files given as G-code that are something else: what they are, in one line for the user.

Owns the recognition of the inputs people pass by mistake (a 3MF project, an STL model in
binary or ASCII form, a Klipper config, another zip archive) from the first bytes of the file,
and the sentence that says what the file is and what to do instead. `what_is_not_gcode`
returns None for anything that may be G-code: the check only refuses what cannot be.
Standard library only.
"""

from __future__ import annotations

import math
import re
import struct

__all__ = ["SNIFF_BYTES", "what_is_not_gcode"]

SNIFF_BYTES = 64 * 1024
"""How much of a file's start the check reads."""

ZIP_MAGIC = b"PK\x03\x04"
STL_HEADER_BYTES = 80
STL_COUNT_BYTES = 4
STL_TRIANGLE_BYTES = 50
# A zip member that makes an archive a 3MF (the 3MF core spec's model part and its types).
_3MF_MEMBERS = (b"3D/3dmodel.model", b"[Content_Types].xml", b"Metadata/plate_")
_ASCII_STL_RE = re.compile(rb"\A\s*solid\b[^\n]*\n\s*(?:facet\s+normal|endsolid)\b", re.I)
# A Klipper config section header: `[printer]`, `[stepper_x]`, `[include mainsail.cfg]`.
_SECTION_RE = re.compile(rb"\[[A-Za-z_][\w .\-/*]*\]\s*\Z")

THREE_MF = "a 3MF project, not G-code: export plain G-code from the slicer and give that file"
STL = "an STL model, not G-code: slice it first and give the G-code file"
KLIPPER_CONFIG = "a Klipper config file, not G-code: did you mean --printer-cfg?"
ZIP = "a zip archive, not G-code: unpack it and give the G-code file"


def what_is_not_gcode(start: bytes, size: int, name: str = "") -> str | None:
    """What the file is, as one sentence, if its first bytes show it is not G-code.

    `start` is the file's first bytes (up to SNIFF_BYTES), `size` its length in bytes and
    `name` its name (only its extension is looked at, for a zip).
    """
    if start.startswith(ZIP_MAGIC):
        if name.lower().endswith(".3mf") or any(m in start for m in _3MF_MEMBERS):
            return THREE_MF
        return ZIP
    if _is_binary_stl(start, size, name):
        return STL
    if _ASCII_STL_RE.match(start):
        return STL
    if _is_klipper_config(start):
        return KLIPPER_CONFIG
    return None


def _is_binary_stl(start: bytes, size: int, name: str = "") -> bool:
    """80 header bytes, a triangle count, and 50 bytes per triangle after it.

    Exactly that size is an STL. So is a file whose size does not match its count (padded
    by its exporter, cut short by a copy, a wrong count) when its first triangles read as
    triangles (`_facets_look_binary`), and an empty STL (a zero count and nothing after it)
    named ``.stl``: timing any of them would say "0s" for a file that is not G-code.
    """
    head = STL_HEADER_BYTES + STL_COUNT_BYTES
    if size < head or len(start) < head:
        return False
    (count,) = struct.unpack_from("<I", start, STL_HEADER_BYTES)
    if count > 0 and size == head + STL_TRIANGLE_BYTES * count:
        return True
    if count == 0 and size == head:
        return name.lower().endswith(".stl") and _has_binary_bytes(start[STL_HEADER_BYTES:])
    return _facets_look_binary(start)


# Checked triangles: enough that text cannot pass by chance, few enough to be in `start`.
STL_FACETS_CHECKED = 4
# Coordinates beyond a kilometre in mm are no model; a unit normal is |n| = 1 (0 when unset).
STL_MAX_COORDINATE = 1e6
STL_NORMAL_SLACK = 0.05
# Bytes that no text file holds (C0 controls but tab, LF, VT, FF, CR; ESC is allowed).
_BINARY_BYTES_RE = re.compile(rb"[\x00-\x08\x0e-\x1a\x1c-\x1f]")


def _has_binary_bytes(data: bytes) -> bool:
    return _BINARY_BYTES_RE.search(data) is not None


def _facets_look_binary(start: bytes) -> bool:
    """The first triangles after the header are binary STL facets: bytes no text holds, and
    in each a unit (or zero) normal and finite vertices of model size."""
    head = STL_HEADER_BYTES + STL_COUNT_BYTES
    facets = min(STL_FACETS_CHECKED, (len(start) - head) // STL_TRIANGLE_BYTES)
    if facets < 1:
        return False
    end = head + facets * STL_TRIANGLE_BYTES
    if not _has_binary_bytes(start[head:end]):
        return False
    for offset in range(head, end, STL_TRIANGLE_BYTES):
        values = struct.unpack_from("<12f", start, offset)
        if not all(abs(v) <= STL_MAX_COORDINATE for v in values):  # NaN fails too
            return False
        length = math.sqrt(sum(v * v for v in values[:3]))
        if length != 0.0 and abs(length - 1.0) > STL_NORMAL_SLACK:
            return False
    return True


def _is_klipper_config(start: bytes) -> bool:
    """The first line that is neither blank nor a comment is a `[section]` header.

    No G-code line starts with `[`; every Klipper config starts with a section (options
    outside one are an error to Klipper).
    """
    for raw in start.split(b"\n"):
        line = raw.strip()
        if not line or line.startswith((b"#", b";")):
            continue
        return _SECTION_RE.match(line) is not None
    return False
