"""The first match of a line-anchored pattern in a file's first and last MiB, found fast.

Slicer comments are searched for with patterns such as ``^; filament used \\[mm\\] = (.+)$``
(MULTILINE) over two MiB of text. Python's regex engine has no shortcut for a pattern that
starts with ``^`` and tries it at every position; ``str.find`` of the literal text after the
``^`` skips to the only places a match can start (a line start followed by that text).
`search` gives exactly what ``pattern.search(text)`` gives.
"""

from __future__ import annotations

import re
from typing import AnyStr

# Characters that end the literal text after the leading "^".
_SPECIAL = frozenset("\\.[](){}*+?|^$")
# A quantifier after the literal applies to its last character, which is then not certain.
_QUANTIFIERS = frozenset("*+?{")
_MIN_LITERAL = 2
_literals: dict[object, object] = {}


def _literal(pattern: re.Pattern[AnyStr]) -> AnyStr | None:
    """The text every match starts with at a line start, or None if that is not known."""
    try:
        return _literals[pattern]  # type: ignore[return-value]
    except KeyError:
        pass
    source = pattern.pattern
    text = source.decode("latin-1") if isinstance(source, bytes) else source
    found: str | None = None
    if (pattern.flags & re.MULTILINE and not pattern.flags & (re.IGNORECASE | re.VERBOSE)
            and text.startswith("^") and "|" not in text):
        end = 1
        while end < len(text) and text[end] not in _SPECIAL:
            end += 1
        if end < len(text) and text[end] in _QUANTIFIERS:
            end -= 1
        if end - 1 >= _MIN_LITERAL:
            found = text[1:end]
    literal: object = (found.encode("latin-1") if isinstance(source, bytes) and found
                       is not None else found)
    _literals[pattern] = literal
    return literal  # type: ignore[return-value]


def search(pattern: re.Pattern[AnyStr], text: AnyStr) -> re.Match[AnyStr] | None:
    """``pattern.search(text)``, trying the pattern only where a line starts with its
    literal text (every match of such a pattern starts there)."""
    literal = _literal(pattern)
    if literal is None:
        return pattern.search(text)
    newline = b"\n"[0] if isinstance(text, bytes) else "\n"
    at = text.find(literal)
    while at >= 0:
        if at == 0 or text[at - 1] == newline:
            match = pattern.match(text, at)
            if match is not None:
                return match
        at = text.find(literal, at + 1)
    return None
