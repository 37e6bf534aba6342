"""Mirrors klippy/kinematics/limited_corexz.py of Kalico v2026.07.00 (GNU GPLv3).

Kalico's `limited_corexz` kinematics: corexz's rails, ranges and homing (cartesian's, without
[dual_carriage]) with limited_cartesian's per-axis limits, of which it is a copy, except that
max_x_velocity / max_y_velocity / max_z_velocity default to max_velocity and neither they nor
the max_*_accel options are bounded by max_velocity / max_accel.

Re-implemented from Kalico v2026.07.00 (30c65e09de06), `klippy/kinematics/limited_corexz.py`
(Brandon Smith, after Mael Kerbiriou's limited_cartesian, GNU GPLv3).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig
from kestimator.kinematics.base import Kinematics
from kestimator.kinematics.limited_cartesian import LimitedCartKinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits


class LimitedCoreXZKinematics(LimitedCartKinematics):
    """corexz with limited_cartesian's per-axis velocity and acceleration limits."""

    name = "limited_corexz"
    dual_carriage_axes: tuple[str, ...] = ()
    velocity_default_ratio = 1.0
    bounded = False


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: limited_corexz (Kalico)."""
    return LimitedCoreXZKinematics(config, limits)
