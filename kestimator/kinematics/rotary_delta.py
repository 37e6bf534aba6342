"""Klipper's `rotary_delta` kinematics: not modelled yet, named in a warning.

Mainline Klipper at commit 84104bbbd, `klippy/kinematics/rotary_delta.py`: see
`kestimator.kinematics.unmodelled` for what the stand-in does and does not do.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.kinematics.base import Kinematics, MachineConfig
from kestimator.kinematics.unmodelled import UnmodelledKinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits


def load_kinematics(config: MachineConfig | None, limits: Limits) -> Kinematics:
    """A stand-in for [printer] kinematics: rotary_delta (Z speed limit only, with a warning)."""
    return UnmodelledKinematics("rotary_delta", limits, "not implemented in kestimator yet")
