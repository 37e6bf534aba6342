"""`mypyc_attr` for the pure build: the class decorator mypyc reads, here doing nothing.

Owns the mypyc class attributes the source uses: ``@mypyc_attr(serializable=True,
allow_interpreted_subclasses=True)`` on the planner's classes, so that the compiled build
can pickle them (kestimator.resume saves the planner; a native class is otherwise created
only through its ``__init__``, with its arguments). allow_interpreted_subclasses because
with serializable alone this mypyc's tp_init is a no-op: the class called from Python
would stay empty. Both cost about 5 % of the compiled estimate's CPU (mypyc gives up its
always-defined attribute analysis for such classes; benchmarks/RESULTS.md).

A module imports mypy_extensions' own (mypyc knows the decorator by that name,
and drops it from the compiled class) and, where mypy_extensions is not installed (the
printer host, the Cura plugin), this one, so the core needs nothing outside the standard
library. (Not `if TYPE_CHECKING: ... else: ...`: mypyc compiles that else branch as
unreachable code, which raises when the compiled module is imported.)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def mypyc_attr(*_flags: str, **_attrs: object) -> Callable[[T], T]:
    """A class decorator that leaves the class as it is (mypyc reads its arguments)."""
    def keep(cls: T) -> T:
        return cls
    return keep
