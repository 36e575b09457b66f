"""The arena: walls, seeded clutter, slippery floor patches, and the pymunk space holding the robot.

A layout is plain data (:class:`Layout`: lists of tuples), generated from a numpy Generator and
then built into static pymunk shapes. Keeping the layout as data lets the renderer draw it,
pickling rebuild it, and tests inspect it without touching pymunk.
"""

from __future__ import annotations

import array
import bisect
import math
from dataclasses import dataclass, field

import numpy as np
import pymunk

from mkv_env import _chipmunk
from mkv_env.chipmunk import c_object
from mkv_env.chipmunk import cp as _cp
from mkv_env.chipmunk import ffi as _ffi
from mkv_env.params import RobotParams
from mkv_env.robot import (
    BUMP_FL,
    BUMP_FR,
    BUMP_REAR,
    CHASSIS,
    OBSTACLE,
    ROBOT_FILTER,
    Robot,
)

WALL_RADIUS_M = 0.04
"""Half thickness of arena walls and wall pieces [m]; far above the <1 cm a substep moves."""
ROBOT_CLEARANCE_M = 0.26
"""Free radius required around a start position [m] (robot circumradius 0.19 m + margin)."""
START_POSE_TRIES = 200
"""Random positions tried per layout for a clear start pose."""
LAYOUT_ATTEMPTS = 20
"""Fresh layouts tried per reset of ``MKV-v0`` before giving up on a free start pose."""
OBSTACLE_FRICTION = 0.6
"""Coulomb friction coefficient of obstacles and walls (against the chassis and bumpers)."""
OBSTACLE_ELASTICITY = 0.0
"""Restitution of obstacles: bumps do not bounce."""
SPACE_ITERATIONS = 10
"""Chipmunk solver iterations per step."""
SPACE_DAMPING = 0.6
"""Fraction of velocity kept per second by every body: the rolling resistance of the caster and
wheels (40 % of the speed lost per second)."""


@dataclass
class Layout:
    """Obstacles and floor of one arena, in world metres.

    boxes: (cx, cy, w, h, angle); cylinders: (cx, cy, r); walls: (ax, ay, bx, by) segments of
    radius WALL_RADIUS_M (the arena boundary included); patches: (x0, y0, x1, y1, friction_scale).
    """

    width_m: float
    height_m: float
    boxes: list = field(default_factory=list)
    cylinders: list = field(default_factory=list)
    walls: list = field(default_factory=list)
    patches: list = field(default_factory=list)


def _bounding(kind: str, spec) -> tuple[float, float, float]:
    """Centre and radius of a circle around an obstacle (for spacing clutter)."""
    if kind == "box":
        cx, cy, w, h, _ = spec
        return cx, cy, 0.5 * math.hypot(w, h)
    if kind == "cylinder":
        return spec
    ax, ay, bx, by = spec
    return 0.5 * (ax + bx), 0.5 * (ay + by), 0.5 * math.hypot(bx - ax, by - ay) + WALL_RADIUS_M


def dead_end_walls(cx, cy, angle, gap_m, depth_m) -> list[tuple[float, float, float, float]]:
    """Three wall segments forming a U open towards ``angle`` (inner width ``gap_m``)."""
    c, s = math.cos(angle), math.sin(angle)
    half = 0.5 * gap_m + WALL_RADIUS_M

    def w(x, y):
        return (cx + c * x - s * y, cy + s * x + c * y)

    back_l, back_r = w(0.0, half), w(0.0, -half)
    open_l, open_r = w(depth_m, half), w(depth_m, -half)
    return [(*back_l, *back_r), (*back_l, *open_l), (*back_r, *open_r)]


# ---------------------------------------------------------------------- clutter generator
CLUTTER_KINDS = ("box", "cylinder", "wall", "corner", "dead_end")
CLUTTER_PROBS = (0.32, 0.24, 0.16, 0.16, 0.12)
"""Chance of each clutter kind per placed item."""
CLUTTER_TRIES = 30
"""Placement attempts per item before it is given up."""
CLUTTER_MARGIN_M = 0.35
"""Item centres keep this far from the arena walls [m]."""
BOX_SIDE_M = (0.15, 0.5)
"""Box side lengths, uniform [m]."""
CYLINDER_RADIUS_M = (0.06, 0.2)
"""Cylinder radius, uniform [m]."""
WALL_PIECE_LENGTH_M = (0.4, 1.1)
"""Free-standing wall piece length, uniform [m]."""
CORNER_ARM_M = (0.35, 0.8)
"""Arm lengths of an L corner, uniform [m]."""
DEAD_END_GAP_M = (0.3, 0.45)
"""Inner width of a U dead end, uniform [m] (the robot is 0.22 m wide, turns on ~0.5 m)."""
DEAD_END_DEPTH_M = (0.4, 0.75)
"""Depth of a U dead end, uniform [m]."""
CLUTTER_GAP_M = (0.1, 0.6)
"""Clearance between an item and everything placed before it, uniform [m]: some gaps are
narrower than the robot, so wandering robots wedge themselves."""
PATCH_SIDE_M = (0.5, 1.0)
"""Side lengths of a slippery floor patch, uniform [m]."""


def generate_layout(
    rng: np.random.Generator,
    width_m: float = 4.0,
    height_m: float = 4.0,
    n_clutter: int = 14,
    n_patches: int = 2,
    patch_friction_scale: float = 0.3,
    reserved: list[tuple[float, float, float]] | None = None,
) -> Layout:
    """Random clutter: boxes, cylinders, wall pieces, corners (L) and dead ends (U).

    ``reserved`` lists circles (cx, cy, r) to keep free (e.g. a jam scenario's structure).
    Gaps between obstacles are drawn from 0.1 m to 0.6 m: some narrower than the robot (0.22 m
    wide), so wandering robots wedge themselves.
    """
    lay = Layout(width_m, height_m)
    W, H = width_m, height_m
    lay.walls += [(0, 0, W, 0), (W, 0, W, H), (W, H, 0, H), (0, H, 0, 0)]
    circles = list(reserved or [])
    kinds, margin = CLUTTER_KINDS, CLUTTER_MARGIN_M
    rng = _ScalarDraws(rng)
    for _ in range(n_clutter):
        for _attempt in range(CLUTTER_TRIES):
            kind = kinds[rng.choice_clutter()]
            cx, cy = rng.uniform(margin, W - margin), rng.uniform(margin, H - margin)
            ang = rng.uniform(-math.pi, math.pi)
            if kind == "box":
                items = [("box", (cx, cy, rng.uniform(*BOX_SIDE_M), rng.uniform(*BOX_SIDE_M),
                                  ang))]
            elif kind == "cylinder":
                items = [("cylinder", (cx, cy, rng.uniform(*CYLINDER_RADIUS_M)))]
            elif kind == "wall":
                half = 0.5 * rng.uniform(*WALL_PIECE_LENGTH_M)
                dx, dy = half * math.cos(ang), half * math.sin(ang)
                items = [("wall", (cx - dx, cy - dy, cx + dx, cy + dy))]
            elif kind == "corner":
                la, lb = rng.uniform(*CORNER_ARM_M), rng.uniform(*CORNER_ARM_M)
                ex, ey = cx + la * math.cos(ang), cy + la * math.sin(ang)
                fx, fy = cx - lb * math.sin(ang), cy + lb * math.cos(ang)
                items = [("wall", (cx, cy, ex, ey)), ("wall", (cx, cy, fx, fy))]
            else:
                segs = dead_end_walls(cx, cy, ang, rng.uniform(*DEAD_END_GAP_M),
                                      rng.uniform(*DEAD_END_DEPTH_M))
                items = [("wall", sg) for sg in segs]
            bounds = [_bounding(k, sp) for k, sp in items]
            if not all(_inside(b, W, H) for b in bounds):
                continue
            gap = rng.uniform(*CLUTTER_GAP_M)
            if any(
                math.hypot(bx - ox, by - oy) < br + orad + gap
                for bx, by, br in bounds[:1] + bounds[1:]
                for ox, oy, orad in circles
            ):
                continue
            for k, sp in items:
                getattr(lay, {"box": "boxes", "cylinder": "cylinders", "wall": "walls"}[k]).append(
                    tuple(float(v) for v in sp)
                )
            circles += bounds
            break
    for _ in range(n_patches):
        pw, ph = rng.uniform(*PATCH_SIDE_M), rng.uniform(*PATCH_SIDE_M)
        x0, y0 = rng.uniform(0, W - pw), rng.uniform(0, H - ph)
        lay.patches.append((x0, y0, x0 + pw, y0 + ph, float(patch_friction_scale)))
    return lay


#: Cumulative clutter-kind probabilities exactly as ``Generator.choice(k, p=...)`` forms them.
_CLUTTER_CDF = np.cumsum(np.asarray(CLUTTER_PROBS, dtype=np.float64))
_CLUTTER_CDF = (_CLUTTER_CDF / _CLUTTER_CDF[-1]).tolist()


class _ScalarDraws:
    """``uniform(a, b)`` and the clutter-kind ``choice`` of a numpy Generator, one scalar at a time,
    drawing the same doubles and returning the same values as ``Generator.uniform`` (``a + (b - a)
    * random()``) and ``Generator.choice(k, p=CLUTTER_PROBS)`` (``searchsorted(cdf, random(),
    'right')``) but without their per-call argument handling, which made up most of a reset.
    ``tests/mkv_env/test_world.py`` checks both against numpy draw for draw."""

    __slots__ = ("random",)

    def __init__(self, rng: np.random.Generator):
        self.random = rng.random

    def uniform(self, low: float, high: float) -> float:
        return low + (high - low) * self.random()

    def choice_clutter(self) -> int:
        return bisect.bisect_right(_CLUTTER_CDF, self.random())


def _inside(bound, W, H) -> bool:
    cx, cy, r = bound
    return r < cx < W - r and r < cy < H - r


def _on_begin(arbiter, space, counts):
    a, b = arbiter.shapes
    t = a.collision_type if a.collision_type != OBSTACLE else b.collision_type
    counts[t] += 1
    counts[0] += 1  # contact events since the space was built


def _on_separate(arbiter, space, counts):
    a, b = arbiter.shapes
    t = a.collision_type if a.collision_type != OBSTACLE else b.collision_type
    counts[t] -= 1


def add_obstacles(space: pymunk.Space, layout: Layout, dx: float = 0.0) -> None:
    """The layout's walls, boxes and cylinders as static shapes of ``space``, shifted ``dx``
    metres along x (benchmarks put several arenas side by side in one space)."""
    sb = space.static_body
    shapes = []
    for ax, ay, bx, by in layout.walls:
        shapes.append(pymunk.Segment(sb, (ax + dx, ay), (bx + dx, by), WALL_RADIUS_M))
    for cx, cy, w, h, ang in layout.boxes:
        t = pymunk.Transform.translation(cx + dx, cy).rotated(ang)
        verts = [(-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2)]
        shapes.append(pymunk.Poly(sb, verts, transform=t))
    for cx, cy, r in layout.cylinders:
        shapes.append(pymunk.Circle(sb, r, (cx + dx, cy)))
    for s in shapes:
        s.collision_type = OBSTACLE
        s.friction = OBSTACLE_FRICTION
        s.elasticity = OBSTACLE_ELASTICITY
    space.add(*shapes)


def count_contacts(space: pymunk.Space, counts=None):
    """Count robot-obstacle contacts of ``space`` in ``counts`` (made if None: an int64
    ``array.array`` of 5, which the compiled step kernel's callbacks can also write; indexed by
    the robot part's collision type, ``counts[0]`` the contact events), which is returned."""
    counts = array.array("q", bytes(40)) if counts is None else counts
    for ctype in (CHASSIS, BUMP_FL, BUMP_FR, BUMP_REAR):
        space.on_collision(ctype, OBSTACLE, begin=_on_begin, separate=_on_separate, data=counts)
    return counts


class World:
    """A built layout plus the robot, stepping physics at a fixed substep.

    Attributes:
        contacts: list indexed by collision type; ``contacts[BUMP_FL]`` etc. are the number of
            obstacle shapes touching that part now; ``contacts[0]`` counts contact events.
    """

    def __init__(self, layout: Layout, robot_params: RobotParams, pose,
                 iterations: int = SPACE_ITERATIONS,
                 robot_kernel: str | None = None, fast_contacts: bool = False):
        self.layout = layout
        self.robot_params = robot_params
        self.space = space = pymunk.Space()
        space.iterations = iterations
        space.damping = SPACE_DAMPING
        #: True for the compiled step kernel's worlds: obstacles are raw Chipmunk shapes
        #: (:func:`mkv_env._chipmunk.add_static`) and contacts are counted by C callbacks
        #: (:func:`mkv_env._chipmunk.install_contacts`); the same shapes and counts as pymunk's.
        self.fast_contacts = bool(fast_contacts)
        self._static = None
        if fast_contacts:
            self._static = _chipmunk.add_static(self, WALL_RADIUS_M, OBSTACLE_FRICTION,
                                                OBSTACLE_ELASTICITY)
            self.contacts = array.array("q", bytes(40))
            _chipmunk.install_contacts(self)
        else:
            add_obstacles(space, layout)
            self.contacts = count_contacts(space)
        self.robot = Robot(space, robot_params, pose[:2], pose[2])
        if robot_kernel is not None:
            self.robot.kernel = robot_kernel

    @classmethod
    def adopted(cls, layout: Layout, robot_params: RobotParams, space: pymunk.Space, static,
                counts: array.array) -> World:
        """A fast-contacts world around a space built elsewhere (a reset in the compiled
        kernel: :func:`mkv_env.kernel.adopt_world`): its obstacles' capsule ``static``, its
        contact counts ``counts`` (handlers installed here); the caller sets ``robot``."""
        world = cls.__new__(cls)
        world.layout, world.robot_params, world.space = layout, robot_params, space
        world.fast_contacts, world._static, world.contacts = True, static, counts
        _chipmunk.install_contacts(world)
        return world

    def __getstate__(self):
        if self._static is not None:  # raw obstacle shapes: pymunk takes them over to pickle
            _chipmunk.adopt_static(self)
        return self.__dict__.copy()

    def __setstate__(self, state):
        self.__dict__.update(state)
        if state.get("fast_contacts"):  # Chipmunk-level handlers are not pickled by pymunk
            _chipmunk.install_contacts(self)

    # ------------------------------------------------------------------ stepping
    def step(self, drive_cmd: int, steer_cmd: int, period_s: float, substeps: int) -> None:
        """Advance one control period with constant motor commands (-1, 0, +1 each).

        The floor under the drive wheel is looked up once per period (it moves < 3 cm).
        """
        robot = self.robot
        if self.layout.patches:
            robot.set_floor_friction_scale(self.floor_friction_scale())
        robot.advance(drive_cmd, steer_cmd, period_s / substeps, substeps, self.space)

    def floor_friction_scale(self) -> float:
        """Friction multiplier under the drive wheel (slippery patches)."""
        x, y, th = self.robot.pose()
        xd = self.robot_params.drive_x_m
        x, y = x + xd * math.cos(th), y + xd * math.sin(th)
        for x0, y0, x1, y1, scale in self.layout.patches:
            if x0 <= x <= x1 and y0 <= y <= y1:
                return scale
        return 1.0

    # ------------------------------------------------------------------ queries
    def is_clear(self, x: float, y: float, radius: float = ROBOT_CLEARANCE_M) -> bool:
        """True when no obstacle lies within ``radius`` of (x, y) (robot shapes ignored)."""
        if _cp is not None:  # Chipmunk's own query (pymunk's wraps the same call)
            return _cp.cpSpacePointQueryNearest(c_object(self.space), (x, y), radius, ROBOT_FILTER,
                                                _ffi.NULL) == _ffi.NULL
        return self.space.point_query_nearest((x, y), radius, ROBOT_FILTER) is None

    def robot_overlaps(self) -> bool:
        """True when any robot shape intersects an obstacle (used to validate start poses)."""
        if self.fast_contacts:
            return _chipmunk.overlaps(self)
        for shape in self.robot.shapes:
            for info in self.space.shape_query(shape):
                if info.shape.body is not self.robot.body:
                    return True
        return False

    @property
    def bumps(self) -> tuple[bool, bool, bool]:
        c = self.contacts
        return c[BUMP_FL] > 0, c[BUMP_FR] > 0, c[BUMP_REAR] > 0

    @property
    def in_contact(self) -> bool:
        c = self.contacts
        return (c[CHASSIS] + c[BUMP_FL] + c[BUMP_FR] + c[BUMP_REAR]) > 0


def random_free_pose(world: World, rng: np.random.Generator, tries: int = START_POSE_TRIES):
    """A uniformly random pose whose footprint is clear of obstacles, or None."""
    W, H = world.layout.width_m, world.layout.height_m
    m = ROBOT_CLEARANCE_M + WALL_RADIUS_M
    for _ in range(tries):
        x, y = rng.uniform(m, W - m), rng.uniform(m, H - m)
        if world.is_clear(x, y):
            return (float(x), float(y), float(rng.uniform(-math.pi, math.pi)))
    return None
