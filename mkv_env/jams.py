"""Jam scenarios for ``MKVJam-v0``: structures and approach poses that wedge the robot.

Each builder returns ``(extra walls, extra boxes, extra cylinders, reserved circles, pose)``:
the structure to add to the arena, the region clutter must keep clear, and an approach pose a
little short of contact. The env then drives the robot forward until it is physically stuck,
so every episode starts in a real jam, not a pose that merely looks like one.
"""

from __future__ import annotations

import math
import operator

import numpy as np

from mkv_env.world import dead_end_walls

SCENARIOS = ("wall", "corner", "dead_end", "wedge")
"""Kinds of jam: head-on/angled into the arena wall; into an arena corner; inside a U-shaped dead
end; wedged in a gap between two cylinders narrower than the robot. A kind's index here is its
code, ``info["scenario"]`` of the jam envs (:func:`scenario_code`, :func:`scenario_name`)."""

SCENARIO_DTYPE = np.int64
"""Type of the scenario codes in ``info`` (a numpy integer: Gymnasium's array wrappers, such as
``NumpyToTorch``, convert it; a string they cannot)."""


def scenario_code(name: str) -> np.int64:
    """The code of jam scenario ``name``: its index in :data:`SCENARIOS`, as a numpy int64."""
    try:
        return SCENARIO_DTYPE(SCENARIOS.index(name))
    except ValueError:
        raise ValueError(f"unknown jam scenario {name!r}; known: {', '.join(SCENARIOS)}") from None


def scenario_name(code) -> str:
    """The name of the jam scenario with code ``code`` (``info["scenario"]``): a Python or numpy
    integer, or a 0-d integer array or tensor (anything ``operator.index`` takes)."""
    try:
        i = None if isinstance(code, (bool, np.bool_)) else operator.index(code)
    except TypeError:
        i = None
    if i is None or not 0 <= i < len(SCENARIOS):
        raise ValueError(f"not a jam scenario code: {code!r} (codes are 0..{len(SCENARIOS) - 1}: "
                         f"{', '.join(SCENARIOS)})")
    return SCENARIOS[i]


# wall: approach a random point of an arena wall
WALL_END_MARGIN_M = 0.7
"""The contact point keeps this far from the wall's ends [m]."""
WALL_APPROACH_M = 0.36
"""Start this far from the wall, facing it [m]."""
WALL_HEADING_JITTER_RAD = 0.7
"""Heading off the wall normal, uniform +- [rad]."""
WALL_CLEAR_RADIUS_M = 0.55
"""Clutter keeps out of this circle around the start [m]."""
# corner: approach an arena corner along its diagonal
CORNER_APPROACH_M = 0.5
"""Start this far from each wall of the corner [m]."""
CORNER_HEADING_JITTER_RAD = 0.4
"""Heading off the corner's diagonal, uniform +- [rad]."""
CORNER_CLEAR_RADIUS_M = 0.6
"""Clutter keeps out of this circle around the start [m]."""
# dead_end: drive into a U narrower than the turning circle
DEAD_END_GAP_M = (0.30, 0.40)
"""Inner width, uniform [m]."""
DEAD_END_DEPTH_M = (0.55, 0.8)
"""Depth, uniform [m]."""
DEAD_END_MARGIN_M = 0.6
"""The U keeps this far (plus its depth) from the arena walls [m]."""
DEAD_END_START_M = 0.30
"""Start this far inside the U's mouth [m]."""
DEAD_END_HEADING_JITTER_RAD = 0.1
"""Heading off the U's axis (facing its closed end), uniform +- [rad]."""
DEAD_END_CLEAR_PAD_M = 0.7
"""Clutter keeps out of the U's half-depth circle plus this [m]."""
# wedge: drive into a gap between two cylinders narrower than the robot (0.22 m)
WEDGE_RADIUS_M = (0.08, 0.18)
"""Cylinder radii, uniform [m]."""
WEDGE_GAP_M = (0.12, 0.19)
"""Gap between the cylinders, uniform [m]."""
WEDGE_MARGIN_M = 0.9
"""The gap keeps this far from the arena walls [m]."""
WEDGE_START_M = 0.33
"""Start this far before the gap, facing it [m]."""
WEDGE_HEADING_JITTER_RAD = 0.25
"""Heading off the line through the gap, uniform +- [rad]."""
WEDGE_CLEAR_RADIUS_M = 0.8
"""Clutter keeps out of this circle around the gap [m]."""


def build_scenario(kind: str, rng: np.random.Generator, W: float, H: float):
    if kind == "wall":
        side = int(rng.integers(4))
        t = rng.uniform(WALL_END_MARGIN_M, (W if side % 2 == 0 else H) - WALL_END_MARGIN_M)
        # inward normal n and the wall point for sides bottom, right, top, left
        pts = [((t, 0.0), (0, 1)), ((W, t), (-1, 0)), ((t, H), (0, -1)), ((0.0, t), (1, 0))]
        (px, py), (nx, ny) = pts[side]
        heading = math.atan2(-ny, -nx) + rng.uniform(-WALL_HEADING_JITTER_RAD,
                                                     WALL_HEADING_JITTER_RAD)
        x, y = px + WALL_APPROACH_M * nx, py + WALL_APPROACH_M * ny
        return [], [], [], [(x, y, WALL_CLEAR_RADIUS_M)], (x, y, heading)
    if kind == "corner":
        cx, cy = [(0.0, 0.0), (W, 0.0), (W, H), (0.0, H)][int(rng.integers(4))]
        dx, dy = (1 if cx == 0 else -1), (1 if cy == 0 else -1)
        d = CORNER_APPROACH_M
        x, y = cx + dx * d, cy + dy * d
        heading = math.atan2(-dy, -dx) + rng.uniform(-CORNER_HEADING_JITTER_RAD,
                                                     CORNER_HEADING_JITTER_RAD)
        return [], [], [], [(x, y, CORNER_CLEAR_RADIUS_M)], (x, y, heading)
    if kind == "dead_end":
        gap, depth = rng.uniform(*DEAD_END_GAP_M), rng.uniform(*DEAD_END_DEPTH_M)
        ang = rng.uniform(-math.pi, math.pi)
        m = depth + DEAD_END_MARGIN_M
        cx, cy = rng.uniform(m, W - m), rng.uniform(m, H - m)
        walls = dead_end_walls(cx, cy, ang, gap, depth)
        x, y = cx + DEAD_END_START_M * math.cos(ang), cy + DEAD_END_START_M * math.sin(ang)
        heading = ang + math.pi + rng.uniform(-DEAD_END_HEADING_JITTER_RAD,
                                              DEAD_END_HEADING_JITTER_RAD)
        mx, my = cx + 0.5 * depth * math.cos(ang), cy + 0.5 * depth * math.sin(ang)
        return walls, [], [], [(mx, my, 0.5 * depth + DEAD_END_CLEAR_PAD_M)], (x, y, heading)
    if kind == "wedge":
        r1, r2 = rng.uniform(*WEDGE_RADIUS_M), rng.uniform(*WEDGE_RADIUS_M)
        gap = rng.uniform(*WEDGE_GAP_M)
        ang = rng.uniform(-math.pi, math.pi)
        m = WEDGE_MARGIN_M
        gx, gy = rng.uniform(m, W - m), rng.uniform(m, H - m)
        px, py = -math.sin(ang), math.cos(ang)  # across the gap
        c1 = (gx + px * (gap / 2 + r1), gy + py * (gap / 2 + r1), r1)
        c2 = (gx - px * (gap / 2 + r2), gy - py * (gap / 2 + r2), r2)
        back = WEDGE_START_M
        x, y = gx - back * math.cos(ang), gy - back * math.sin(ang)
        heading = ang + rng.uniform(-WEDGE_HEADING_JITTER_RAD, WEDGE_HEADING_JITTER_RAD)
        return [], [], [c1, c2], [(gx, gy, WEDGE_CLEAR_RADIUS_M)], (x, y, heading)
    raise ValueError(f"unknown jam scenario {kind!r}; known: {', '.join(SCENARIOS)}")
