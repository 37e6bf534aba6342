"""What every kinematics shares: the interface `ToolHead` calls (a move Klipper rejects
raises `move.move_error()`, as upstream). The machine description a kinematics is built
from (`MachineConfig`, its sections read with Klipper's getters, and rails) is
`kestimator.config.machine`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from kestimator.toolhead import Move, ToolHead

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

Position = tuple[float, float, float, float]


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Kinematics:
    """The interface `ToolHead` uses; the base does what Klipper's `none` kinematics does."""

    name = "none"

    def __init__(self) -> None:
        self.warnings: list[str] = []
        """What this kinematics does that kestimator does not model (said once per file)."""
        self.unchecked: str | None = None
        """Why moves are not range-checked as Klipper checks them (None: they are)."""
        self.commands: dict[str, str] = {}
        """G-code commands the kinematics adds that change motion and are not modelled:
        command -> why (the interpreter warns where they run)."""

    def check_move(self, move: Move) -> None:
        """Raise MoveError for a move Klipper rejects; lower its speed/accel where the
        kinematics limits it."""

    def attach_toolhead(self, toolhead: ToolHead) -> None:
        """The toolhead that checks its moves here: upstream's kinematics get it when they
        are made, and those that read its live limits (Kalico's limited_*) keep it."""

    def kinematics_limits(self) -> tuple[list[float] | None, list[float], bool] | None:
        """The per-axis limits SET_KINEMATICS_LIMIT changes (X, Y, Z velocities or None, X,
        Y, Z accelerations, whether they scale with the toolhead's acceleration), for the
        kinematics that register it (Kalico's limited_*); None for the others."""
        return None

    def set_kinematics_limits(self, velocities: list[float] | None,
                              accels: list[float] | None, scale: bool | None) -> None:
        """SET_KINEMATICS_LIMIT: set what is given (only where `kinematics_limits` is)."""

    def set_position(self, newpos: Position, homing_axes: str) -> None:
        """The toolhead jumped to newpos; ``homing_axes`` ("xyz" letters) are now homed."""

    def clear_homing_state(self, clear_axes: str) -> None:
        """SET_KINEMATIC_POSITION CLEAR: ``clear_axes`` ("xyz" letters) are no longer homed."""

    def homed_axes(self) -> str:
        """The homed axes ("xyz" letters): upstream's ``get_status()['homed_axes']``, which
        [safe_z_home] reads (none.py: none)."""
        return ""

    def home(self, pos: Position, axes: list[int]) -> tuple[Position, str]:
        """Where G28 of ``axes`` (0..2) leaves the head, and the axes it homed: as the
        oracle's stand-in for homing does (klippy's G28 ends there)."""
        newpos = list(pos)
        for axis in axes:
            newpos[axis] = 0.0
        return (newpos[0], newpos[1], newpos[2], newpos[3]), "".join("xyz"[a] for a in axes)
