"""Jam scenarios for ``MKVJam-v0``: structures and approach poses that wedge the robot.

Each builder returns ``(extra walls, extra boxes, extra cylinders, reserved circles, pose)``:
the structure to add to the arena, the region clutter must keep clear, and an approach pose a
little short of contact. The env then drives the robot forward until it is physically stuck,
so every episode starts in a real jam, not a pose that merely looks like one.
"""

from __future__ import annotations

import math

import numpy as np

from mkv_env.world import dead_end_walls

SCENARIOS = ("wall", "corner", "dead_end", "wedge")
"""Kinds of jam: head-on/angled into the arena wall; into an arena corner; inside a U-shaped dead
end; wedged in a gap between two cylinders narrower than the robot."""


def build_scenario(kind: str, rng: np.random.Generator, W: float, H: float):
    if kind == "wall":
        side = int(rng.integers(4))
        t = rng.uniform(0.7, (W if side % 2 == 0 else H) - 0.7)
        # inward normal n and the wall point for sides bottom, right, top, left
        pts = [((t, 0.0), (0, 1)), ((W, t), (-1, 0)), ((t, H), (0, -1)), ((0.0, t), (1, 0))]
        (px, py), (nx, ny) = pts[side]
        heading = math.atan2(-ny, -nx) + rng.uniform(-0.7, 0.7)
        x, y = px + 0.36 * nx, py + 0.36 * ny
        return [], [], [], [(x, y, 0.55)], (x, y, heading)
    if kind == "corner":
        cx, cy = [(0.0, 0.0), (W, 0.0), (W, H), (0.0, H)][int(rng.integers(4))]
        dx, dy = (1 if cx == 0 else -1), (1 if cy == 0 else -1)
        d = 0.5
        x, y = cx + dx * d, cy + dy * d
        heading = math.atan2(-dy, -dx) + rng.uniform(-0.4, 0.4)
        return [], [], [], [(x, y, 0.6)], (x, y, heading)
    if kind == "dead_end":
        gap, depth = rng.uniform(0.30, 0.40), rng.uniform(0.55, 0.8)
        ang = rng.uniform(-math.pi, math.pi)
        m = depth + 0.6
        cx, cy = rng.uniform(m, W - m), rng.uniform(m, H - m)
        walls = dead_end_walls(cx, cy, ang, gap, depth)
        x, y = cx + 0.30 * math.cos(ang), cy + 0.30 * math.sin(ang)
        heading = ang + math.pi + rng.uniform(-0.1, 0.1)
        mx, my = cx + 0.5 * depth * math.cos(ang), cy + 0.5 * depth * math.sin(ang)
        return walls, [], [], [(mx, my, 0.5 * depth + 0.7)], (x, y, heading)
    if kind == "wedge":
        r1, r2 = rng.uniform(0.08, 0.18), rng.uniform(0.08, 0.18)
        gap = rng.uniform(0.12, 0.19)
        ang = rng.uniform(-math.pi, math.pi)
        m = 0.9
        gx, gy = rng.uniform(m, W - m), rng.uniform(m, H - m)
        px, py = -math.sin(ang), math.cos(ang)  # across the gap
        c1 = (gx + px * (gap / 2 + r1), gy + py * (gap / 2 + r1), r1)
        c2 = (gx - px * (gap / 2 + r2), gy - py * (gap / 2 + r2), r2)
        back = 0.33
        x, y = gx - back * math.cos(ang), gy - back * math.sin(ang)
        heading = ang + rng.uniform(-0.25, 0.25)
        return [], [], [c1, c2], [(gx, gy, 0.8)], (x, y, heading)
    raise ValueError(f"unknown jam scenario {kind!r}; known: {', '.join(SCENARIOS)}")
