"""Mirrors klippy/extras/safe_z_home.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's [safe_z_home]: it takes over G28, homes X and Y as G28 would, moves the head to
`home_xy_position`, homes Z there, lifts Z to `z_hop` (before homing too, when Z is below
it) and, with `move_to_previous`, brings X and Y back to where homing X and Y left them.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/extras/safe_z_home.py`
and `klippy/extras/manual_probe.py` (`lookup_z_endstop_config`) (GNU GPLv3). Names follow
upstream.

Its moves are `toolhead.manual_move`s: each is range-checked as Klipper checks it and leaves
the head where Klipper leaves it, but takes no time, as the whole G28 takes none (the
oracle's convention, `--homing-time` adds the time a G28 takes on the printer).
"""

from __future__ import annotations

from collections.abc import Callable

from kestimator.config.machine import MachineConfig, Section
from kestimator.errors import CommandError, KestimatorError
from kestimator.gcode import Command
from kestimator.manual_probe import lookup_z_endstop_config
from kestimator.toolhead import ToolHead

Handler = Callable[[Command], None]


def g28_command(params: dict[str, str]) -> Command:
    """The G28 command upstream builds with `gcode.create_gcode_command`."""
    return Command("G28", params, "G28 " + " ".join(k + v for k, v in params.items()), None)


class SafeZHoming:
    """[safe_z_home]: G28 with Z homed at a chosen XY position."""

    def __init__(self, config: Section, machine: MachineConfig, toolhead: ToolHead,
                 prev_G28: Handler, on_move: Callable[[], None]) -> None:
        self.toolhead = toolhead
        x_pos, y_pos = config.getfloatlist("home_xy_position", count=2)
        self.home_x_pos, self.home_y_pos = x_pos, y_pos
        self.z_hop = config.getfloat("z_hop", 0.0)
        self.z_hop_speed = config.getfloat("z_hop_speed", 15.0, above=0.0)
        zconfig = lookup_z_endstop_config(machine)
        if zconfig is None:
            raise _config_error(config, "Missing Z endstop config for safe_z_homing")
        self.speed = config.getfloat("speed", 50.0, above=0.0)
        self.move_to_previous = config.getboolean("move_to_previous", False)
        # The G28 this one replaces (homing.py's).
        self.prev_G28 = prev_G28
        # gcode_move's toolhead:manual_move handler (reset_last_position).
        self.on_move = on_move
        if machine.has_section("homing_override"):
            raise _config_error(config, "homing_override and safe_z_homing cannot be used "
                                "simultaneously")

    def manual_move(self, coord: list[float | None], speed: float) -> None:
        """toolhead.manual_move, untimed (see the module's docstring)."""
        self.toolhead.untimed_manual_move(coord, speed)
        self.on_move()

    def cmd_G28(self, cmd: Command) -> None:
        """G28 [X] [Y] [Z]: home, with Z homed at home_xy_position."""
        toolhead = self.toolhead
        kin = toolhead.kin

        # Perform Z Hop if necessary
        if self.z_hop != 0.0:
            # Check if Z axis is homed and its last known position
            pos = list(toolhead.commanded_pos)
            if "z" not in kin.homed_axes():
                # Always perform the z_hop if the Z axis is not homed
                pos[2] = 0.0
                toolhead.set_position((pos[0], pos[1], pos[2], pos[3]), "z")
                self.manual_move([None, None, self.z_hop], self.z_hop_speed)
                kin.clear_homing_state("z")
            elif pos[2] < self.z_hop:
                # If the Z axis is homed, and below z_hop, lift it to z_hop
                self.manual_move([None, None, self.z_hop], self.z_hop_speed)

        # Determine which axes we need to home
        need_x, need_y, need_z = [axis in cmd.params for axis in "XYZ"]
        if not need_x and not need_y and not need_z:
            need_x = need_y = need_z = True

        # Home XY axes if necessary
        new_params = {}
        if need_x:
            new_params["X"] = "0"
        if need_y:
            new_params["Y"] = "0"
        if new_params:
            self.prev_G28(g28_command(new_params))

        # Home Z axis if necessary
        if need_z:
            # Throw an error if X or Y are not homed
            homed_axes = kin.homed_axes()
            if "x" not in homed_axes or "y" not in homed_axes:
                raise CommandError("Must home X and Y axes first")
            # Move to safe XY homing position
            prevpos = toolhead.commanded_pos
            self.manual_move([self.home_x_pos, self.home_y_pos], self.speed)
            # Home Z
            self.prev_G28(g28_command({"Z": "0"}))
            # Perform Z Hop again for pressure-based probes
            if self.z_hop:
                pos = list(toolhead.commanded_pos)
                if pos[2] < self.z_hop:
                    self.manual_move([None, None, self.z_hop], self.z_hop_speed)
            # Move XY back to previous positions
            if self.move_to_previous:
                self.manual_move([prevpos[0], prevpos[1]], self.speed)


def _config_error(config: Section, message: str) -> KestimatorError:
    """A config error Klipper refuses to start with, at the section."""
    option = next(iter(config.options), "home_xy_position")
    return config._error(option, message)
