"""Cura's G-code chunk list, estimated and rewritten with Klipper's times; no Cura needed.

Owns the plugin's view of ``scene.gcode_dict[plate]``: a list of text chunks, element 0 the
header CuraEngine sends last (``;FLAVOR:``, ``;TIME:``, ...) and one element per layer message.
The two passes of ``kestimator inject`` run over the chunks' lines as if they were one file
(lines end at LF, as the core reads files): `plan_chunks` is pass 1 (the estimate and the
rewrite plan), `rewrite_chunks` is pass 2 (the core's own ``Rewriter``, one line at a time).
Each output line goes back into the chunk its input line came from, so the list keeps its
length and every line kestimator does not own keeps its chunk and its bytes. A line split
across two chunks (never seen from CuraEngine, but nothing forbids it) keeps its pieces in
their chunks; lines inserted before it join the first piece's chunk, lines after it the last.

`split_like_cura` cuts a whole CuraEngine file into the list Cura would hold, for tests and
tools: CuraEngine's CLI writes no layer-message boundaries, so it approximates them (see there).
"""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Iterator, Sequence

from kestimator.api import (
    DETECT_WINDOW_BYTES,
    MARKER_PREFIX,
    Estimate,
    InjectPlan,
    Limits,
    MacroTimes,
    Rewriter,
    SlicerInfo,
    detect_slicer,
    parse_marker,
    plan_lines,
)

# Cura decodes the engine's bytes as UTF-8 with "replace"; surrogateescape round-trips
# whatever a post-processing script may have put in, byte for byte.
ENCODING = "utf-8"
ENCODING_ERRORS = "surrogateescape"
SOURCE_NAME = "<Cura G-code>"
"""What messages call the G-code: it is not a file yet."""
GENERATED_WITH = ";Generated with Cura_SteamEngine"
LAYER_PREFIX = ";LAYER:"

_Pieces = list[tuple[int, bytes]]
"""One line as (chunk index, bytes) pieces: one piece unless the line spans chunks."""


def _encode(chunk: str) -> bytes:
    return chunk.encode(ENCODING, ENCODING_ERRORS)


def iter_line_pieces(chunks: Sequence[str]) -> Iterator[_Pieces]:
    """Every line of the joined chunks (split at LF, endings kept), as chunk pieces."""
    pending: _Pieces = []
    for index, chunk in enumerate(chunks):
        for line in io.BytesIO(_encode(chunk)):
            if pending or not line.endswith(b"\n"):
                pending.append((index, line))
                if line.endswith(b"\n"):
                    yield pending
                    pending = []
            else:
                yield [(index, line)]
    if pending:
        yield pending


def iter_lines(chunks: Sequence[str]) -> Iterator[bytes]:
    """The joined chunks' lines as bytes, exactly as the core reads a file's lines."""
    for pieces in iter_line_pieces(chunks):
        yield pieces[0][1] if len(pieces) == 1 else b"".join(part for _, part in pieces)


def same_chunks(a: Sequence[str], b: Sequence[str]) -> bool:
    """True if two chunk lists hold the same text chunk for chunk (identity first: cheap)."""
    return len(a) == len(b) and all(x is y or x == y for x, y in zip(a, b, strict=True))


def is_processed(chunks: Sequence[str]) -> bool:
    """True if kestimator's marker line, in its exact format (`parse_marker`), is in the
    chunks (they were rewritten already); a user's ``; kestimator ...`` comment is not."""
    for chunk in chunks:
        if MARKER_PREFIX not in chunk:
            continue
        for line in chunk.splitlines():
            if MARKER_PREFIX in line and parse_marker(line) is not None:
                return True
    return False


def _head_and_tail(chunks: Sequence[str]) -> tuple[bytes, bytes]:
    """The joined chunks' first and last DETECT_WINDOW_BYTES, as the core's detection reads
    a file (whole lines only)."""
    head_parts: list[bytes] = []
    size = 0
    for chunk in chunks:
        if size >= DETECT_WINDOW_BYTES:
            break
        data = _encode(chunk)
        head_parts.append(data)
        size += len(data)
    head = b"".join(head_parts)
    tail_parts: list[bytes] = []
    size = 0
    for chunk in reversed(chunks):
        if size > DETECT_WINDOW_BYTES:
            break
        data = _encode(chunk)
        tail_parts.append(data)
        size += len(data)
    tail = b"".join(reversed(tail_parts))
    if len(head) > DETECT_WINDOW_BYTES:
        head = head[:head.rfind(b"\n", 0, DETECT_WINDOW_BYTES) + 1]
    if len(tail) > DETECT_WINDOW_BYTES:
        tail = tail[len(tail) - DETECT_WINDOW_BYTES:]
        tail = tail[tail.find(b"\n") + 1:]
    return head, tail


def detect_chunks(chunks: Sequence[str]) -> SlicerInfo:
    """Which slicer wrote the chunks and its own estimate (Cura's ``;TIME:``)."""
    return detect_slicer(*_head_and_tail(chunks))


def file_ends(chunks: Sequence[str]) -> tuple[bytes, bytes]:
    """The bytes the core's adapters read settings from (first and last MiB)."""
    return _head_and_tail(chunks)


@dataclasses.dataclass(frozen=True)
class ChunkPlan:
    """Pass 1 over a chunk list: what Klipper computes and how pass 2 rewrites it."""

    plan: InjectPlan
    estimate: Estimate
    slicer: SlicerInfo
    slicer_estimate_s: float | None
    """Cura's own estimate (kept from the marker when the chunks were rewritten before)."""
    limits_source: str

    @property
    def total_s(self) -> float:
        """Klipper's print time in seconds."""
        return self.estimate.total_s


def plan_chunks(chunks: Sequence[str], limits: Limits, limits_source: str,
                macros: MacroTimes | None = None) -> ChunkPlan:
    """Pass 1: estimate the chunks with progress samples and build the rewrite plan.

    The core's ``plan_lines`` on the joined lines. Raises KestimatorError when the G-code
    has no moves or the planner cannot time it.
    """
    head, tail = _head_and_tail(chunks)
    plan, est, slicer, slicer_s = plan_lines(iter_lines(chunks), head, tail, limits,
                                             limits_source, path=SOURCE_NAME,
                                             macros=macros)
    return ChunkPlan(plan=plan, estimate=est, slicer=slicer, slicer_estimate_s=slicer_s,
                     limits_source=limits_source)


def rewrite_chunks(chunks: Sequence[str], plan: InjectPlan) -> list[str]:
    """Pass 2: the chunks with Klipper's M73 lines, time comments and marker, same length.

    A chunk whose bytes come out unchanged is returned as the very same string.
    """
    out: list[list[bytes]] = [[] for _ in chunks]
    process = Rewriter(plan).process
    for pieces in iter_line_pieces(chunks):
        if len(pieces) == 1:
            index, raw = pieces[0]
            out[index].extend(process(raw))
            continue
        raw = b"".join(part for _, part in pieces)
        produced = process(raw)
        first, last = pieces[0][0], pieces[-1][0]
        if not any(item is raw for item in produced):
            out[first].extend(produced)  # the line itself was rewritten or dropped
            continue
        position = next(i for i, item in enumerate(produced) if item is raw)
        out[first].extend(produced[:position])
        for index, part in pieces:
            out[index].append(part)
        out[last].extend(produced[position + 1:])
    result: list[str] = []
    for chunk, parts in zip(chunks, out, strict=True):
        data = b"".join(parts)
        result.append(chunk if data == _encode(chunk)
                      else data.decode(ENCODING, ENCODING_ERRORS))
    return result


def split_like_cura(text: str) -> list[str]:
    """A whole CuraEngine G-code file cut into the list Cura's ``gcode_dict`` holds.

    Cura builds the list from the engine's messages: the header (prefix message) becomes
    element 0 and each g-code layer message is appended. A file has no message boundaries,
    so this cuts where those messages start in practice: element 0 is everything before
    ``;Generated with Cura_SteamEngine`` (the header), element 1 the start G-code up to the
    first ``;LAYER:<n>``, then one element per ``;LAYER:<n>`` line (the last one also holds
    the end G-code). Joining the list gives back ``text`` exactly.
    """
    chunks: list[str] = []
    current: list[str] = []
    seen_generated = False
    pieces = text.split("\n")
    lines = [piece + "\n" for piece in pieces[:-1]] + ([pieces[-1]] if pieces[-1] else [])
    for line in lines:
        starts_chunk = False
        if not seen_generated and line.startswith(GENERATED_WITH):
            seen_generated = True
            starts_chunk = True
        elif line.startswith(LAYER_PREFIX) and line[len(LAYER_PREFIX):].strip().lstrip(
                "-").isdigit():
            starts_chunk = True
        if starts_chunk and (current or not chunks):
            chunks.append("".join(current))
            current = []
        current.append(line)
    chunks.append("".join(current))
    return chunks
