"""The MK-V's commands: one action-space definition that the envs, the teacher, the policies and
the learners all read.

An action is ``[drive, steer]``, each a three-valued open-loop motor command
(``MultiDiscrete([3, 3])``): drive 0 reverse, 1 off, 2 forward; steer 0 left, 1 off, 2 right.
"""

from __future__ import annotations

from gymnasium import spaces

#: Command names, in action order.
ACTION_NAMES: tuple[str, ...] = ("drive", "steer")
#: Values per command (``MultiDiscrete.nvec``).
ACTION_NVEC: tuple[int, ...] = (3, 3)
#: What each value of each command means.
VALUE_NAMES: dict[str, tuple[str, str, str]] = {
    "drive": ("reverse", "off", "forward"),
    "steer": ("left", "off", "right"),
}
#: Value indices.
REVERSE, OFF, FORWARD = 0, 1, 2
LEFT, RIGHT = 0, 2
#: Both motors off (the action before any command, and teleop's "no key pressed").
NOOP_ACTION: tuple[int, int] = (OFF, OFF)


def action_space() -> spaces.MultiDiscrete:
    """The action space of every MK-V env: ``MultiDiscrete([3, 3])`` = [drive, steer]."""
    return spaces.MultiDiscrete(list(ACTION_NVEC))


__all__ = ["ACTION_NAMES", "ACTION_NVEC", "FORWARD", "LEFT", "NOOP_ACTION", "OFF", "REVERSE",
           "RIGHT", "VALUE_NAMES", "action_space"]
