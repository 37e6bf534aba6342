"""Progress tables the writer never writes, for the tests of the reader and the worker
(issue 33): the payload built by hand with the table's own varint writer, so that counts
may pass the writer's limits and values may be ones it never writes (a negative time left),
then encoded by the table's own encoder."""

from __future__ import annotations

from collections.abc import Sequence

from kestimator.progress_table import VERSION_WITHOUT_SETTINGS, ProgressTable, _Writer


def forge_payload(content_bytes: int, total_ms: int, points: Sequence[tuple[int, int]],
                  names: Sequence[bytes] = (), object_offsets: Sequence[int] = (),
                  remaining_ms: Sequence[Sequence[int]] = (),
                  remaining_raw: bytes | None = None) -> bytes:
    """A version-1 payload: `points` as (offset, ms) pairs, `remaining_ms[i][j]` object i's
    milliseconds left at object_offsets[j] (any sign), or `remaining_raw` in their place
    (the bytes as they are, whatever the counts declare)."""
    out = _Writer()
    out.uint(VERSION_WITHOUT_SETTINGS)
    out.uint(content_bytes)
    out.uint(total_ms)
    out.uint(len(points))
    previous_offset = previous_ms = 0
    for offset, ms in points:
        out.uint(offset - previous_offset)
        out.uint(ms - previous_ms)
        previous_offset, previous_ms = offset, ms
    out.uint(len(names))
    for name in names:
        out.uint(len(name))
        out.raw(name)
    out.uint(len(object_offsets))
    previous_offset = 0
    for offset in object_offsets:
        out.uint(offset - previous_offset)
        previous_offset = offset
    if remaining_raw is not None:
        out.raw(remaining_raw)
    for column in remaining_ms:
        previous_ms = 0
        for ms in column:
            out.sint(ms - previous_ms)
            previous_ms = ms
    return out.bytes()


def forged_block(payload: bytes, content_bytes: int) -> bytes:
    """The table lines `ProgressTable.encode` writes, around `payload` (the file's first
    `content_bytes` bytes go before them)."""
    table = ProgressTable(total_s=0.0, content_bytes=content_bytes, offsets=[0], times=[0.0])
    object.__setattr__(table, "payload", lambda: payload)
    return table.encode()


def huge_table_payload(content_bytes: int, objects: int = 4000, points: int = 4000) -> bytes:
    """A payload declaring `objects` x `points` object values (one byte each, zero): the
    red team's 16 KB compressed table that once decoded to 16 M floats."""
    return forge_payload(content_bytes, 100_000, [(0, 0), (content_bytes, 100_000)],
                         names=[b"O%d" % i for i in range(objects)],
                         object_offsets=list(range(1, points + 1)),
                         remaining_raw=b"\x00" * (objects * points))
