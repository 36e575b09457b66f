"""Ground-truth bookkeeping every evaluation needs: distance, stuck, jams and escapes.

Nothing here is visible to the learner; it feeds ``info`` and the reward.
"""

from __future__ import annotations

import math

FREE_CLEARANCE_M = 0.22
"""Obstacle-free radius around the robot's centre that counts as free [m] (circumradius 0.19 m)."""


class MotionTracker:
    """Per-step motion measures of the robot, from its true pose.

    Args:
        period_s: control period [s].
        stuck_speed_mps: below this speed a robot commanded to drive counts as stuck.
        jam_steps: consecutive stuck steps that make a jam.
        escape_distance_m: distance from where a jam began that counts as free (when not stuck).
        escape_forward_m: forward travel, uninterrupted by reversing or stopping, that the robot
            must have just made when it is free: an escape means driving on, not only backing
            out (without it, a robot that reverses forever "escapes" most jams).
    """

    def __init__(self, period_s, stuck_speed_mps, jam_steps, escape_distance_m,
                 escape_forward_m=0.0):
        self.period_s = period_s
        self.stuck_speed_mps = stuck_speed_mps
        self.jam_steps = jam_steps
        self.escape_distance_m = escape_distance_m
        self.escape_forward_m = escape_forward_m

    def reset(self, pose, jammed: bool = False, contact_events: int = 0) -> None:
        self.x, self.y, self.heading = pose
        self.distance_m = 0.0
        self.last_step_m = 0.0
        self.stuck_run = 0
        self.jams = 1 if jammed else 0
        self.escapes = 0
        self.in_jam = jammed
        self.jam_x, self.jam_y = self.x, self.y
        self.collisions = 0
        self.forward_run_m = 0.0
        self._events = contact_events

    #: The episode state :meth:`to_state` gives and :meth:`load_state` takes (the rest is
    #: configuration).
    STATE = ("x", "y", "heading", "distance_m", "last_step_m", "stuck_run", "jams", "escapes",
             "in_jam", "jam_x", "jam_y", "collisions", "forward_run_m", "_events")
    _INT = frozenset(("stuck_run", "jams", "escapes", "collisions", "_events"))

    def to_state(self) -> dict:
        """The episode state by name (:data:`STATE`)."""
        return {name: getattr(self, name) for name in self.STATE}

    def load_state(self, state: dict) -> None:
        """Take an episode state another owner has reached (the compiled step kernel's slot:
        :func:`mkv_env.kernel.pull`), as plain numbers: the counts as ints, ``in_jam`` a bool."""
        for name in self.STATE:
            value = state[name]
            setattr(self, name, int(value) if name in self._INT else value)
        self.in_jam = bool(self.in_jam)

    def update(self, pose, drive_cmd: int, contact_events: int, is_clear=None):
        """Advance one step. Returns (progress_m, stuck, new_collision, escaped_now).

        ``is_clear(x, y, radius)`` tells whether no obstacle lies within ``radius`` of (x, y); a
        jam is escaped only where it is true for FREE_CLEARANCE_M.
        """
        x, y, heading = pose
        dx, dy = x - self.x, y - self.y
        step = math.hypot(dx, dy)
        mid = self.heading + 0.5 * math.remainder(heading - self.heading, 2 * math.pi)
        progress = dx * math.cos(mid) + dy * math.sin(mid)
        self.x, self.y, self.heading = x, y, heading
        self.distance_m += step
        self.last_step_m = step
        stuck = drive_cmd != 0 and step < self.stuck_speed_mps * self.period_s
        self.stuck_run = self.stuck_run + 1 if stuck else 0
        new_collision = contact_events > self._events
        if new_collision:
            self.collisions += 1
        self._events = contact_events
        # forward travel since the robot last reversed or stood still (1 mm/step counts as moving)
        self.forward_run_m = self.forward_run_m + progress if progress > 1e-3 else 0.0
        escaped_now = False
        if self.in_jam:
            if (not stuck
                    and self.forward_run_m >= self.escape_forward_m
                    and math.hypot(x - self.jam_x, y - self.jam_y) >= self.escape_distance_m
                    and (is_clear is None or is_clear(x, y, FREE_CLEARANCE_M))):
                self.in_jam = False
                self.escapes += 1
                escaped_now = True
        elif self.stuck_run >= self.jam_steps:
            self.in_jam = True
            self.jams += 1
            self.jam_x, self.jam_y = x, y
        return progress, stuck, new_collision, escaped_now
