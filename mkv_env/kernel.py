"""The compiled step kernel: a whole MK-V control period after the action is decoded, in C.

``mkv_env._fastsim.Batch`` holds N robots ("slots"). Stepping a slot runs, in C, everything
:meth:`mkv_env.envs.MKVEnv.step` does in Python once the action is decoded: the floor-patch lookup
and the wheel/motor substeps with Chipmunk (:meth:`mkv_env.robot.Robot.advance`), the sensors
(:meth:`mkv_env.sensors.SensorSuite.read`: noise rows, quantisation, clipping), the pose and the
tracker (:meth:`mkv_env.tracker.MotionTracker.update`, the free-clearance query included), the
reward and termination of the env's class and the numbers that go into ``info``. Contacts are
counted by C collision callbacks on the World's own count array, and a kernel world's obstacles
are raw Chipmunk shapes (:mod:`mkv_env._chipmunk`).

The Python code stays the reference (``gym.make(id, kernel="python")``). The C copy performs the
same IEEE operations in the same order (``math.hypot`` is CPython's ``vector_norm``, copied; float
``%`` and ``math.remainder`` as CPython computes them; no FMA contraction), so both kernels give the
same bits: ``tests/mkv_env/test_step_kernel.py`` drives both with random actions, parameters and
seeds and compares every observation, reward, flag and info value.

Random numbers stay numpy's: the sensor noise comes from the episode's generator (the env's
``np_random`` at reset) in blocks of 256 rows, as :meth:`SensorSuite.draw_block` draws them. When
the extension is linked with numpy's random library (:data:`NOISE_IN_C`, checked at import), a slot
draws its next block itself with numpy's ``random_standard_normal`` on that generator's bit
generator, on whichever thread steps it; otherwise a slot that has used its block asks for a new
one (``step`` returns the slots that need one, before stepping anything) and Python draws it.
Either way the draws happen in the reference's order.

State moves between Python and C at well-defined points only: a reset ``push``es the Python
objects' state into the slot; reading ``env.tracker``, ``env.sensors`` or ``robot.state`` after C
steps ``pull``s it back (and hands ownership to Python until the next step pushes it again).

A native vector env of MKV-v0 or MKV-v1 resets its envs inside the kernel call too
(:data:`C_RESET`, :func:`setup_resets`): the slot draws the layout and start pose from the
episode's generator and builds the Chipmunk space, obstacles, contact handlers and robot with the
calls pymunk makes, in pymunk's order (so the same hash ids, spatial index and bits), on the worker
thread that resets it. The slot owns that world until Python reads ``env.world`` (or the tracker,
sensors, a pickle): then :func:`adopt_world` wraps the very same Chipmunk objects in pymunk
objects, which own them from then on.
"""

from __future__ import annotations

import array

import numpy as np

from mkv_env import _chipmunk, chipmunk
from mkv_env import robot as _robot
from mkv_env.params import SENSOR_NAMES

_fastsim = _robot._fastsim

#: True when the compiled step kernel can run (built extension and pymunk's cffi layer, and its
#: copy of ``math.hypot`` matches this interpreter's: :func:`_pick_hypot`).
AVAILABLE = _chipmunk.AVAILABLE and hasattr(_fastsim, "Batch")


def _hypot_probes() -> list[tuple[float, float]]:
    """Pairs on which CPython's two ``math.hypot`` algorithms (3.10-3.11 and 3.12+) differ
    somewhere, subnormals included, plus ordinary ones."""
    rng = np.random.default_rng(20261124)
    pairs = []
    for scale in (5e-324, 1e-310, 1e-308, 1e-150, 1e-3, 1.0, 1e3, 1e300):
        a = rng.standard_normal(400) * scale
        b = a * rng.choice([1e-9, 1e-3, 0.5, 1.0, 3.0], size=a.size) * rng.standard_normal(a.size)
        pairs += zip(a.tolist(), b.tolist(), strict=True)
    return pairs


def _pick_hypot() -> bool:
    """Make the kernel use the ``math.hypot`` algorithm of this Python (CPython changed it in
    3.12; both are in _native/pyfloat.c): the one that reproduces ``math.hypot`` on every probe.
    False if neither does (then the kernel is not used: the reference runs)."""
    import math

    probes = _hypot_probes()
    for variant in (0, 1):
        if all(_fastsim.hypot(a, b, variant) == math.hypot(a, b) for a, b in probes):
            _fastsim.hypot(0.0, 0.0, variant)  # (the last call sets the kernel's variant)
            return True
    return False


if AVAILABLE:
    AVAILABLE = _pick_hypot()


def _noise_in_c() -> bool:
    """True when the kernel draws sensor noise itself and its draws are numpy's: the extension
    was linked with numpy's random library and ``random_standard_normal`` there gives what
    ``Generator.standard_normal`` gives here, for every bit generator numpy ships (probed)."""
    if not hasattr(_fastsim, "normals"):
        return False
    for bg in (np.random.PCG64, np.random.PCG64DXSM, np.random.MT19937, np.random.Philox,
               np.random.SFC64):
        c = _fastsim.normals(bg(20261125), 3000)
        if c is None or c != np.random.Generator(bg(20261125)).standard_normal(3000).tolist():
            return False
    return True


if AVAILABLE:
    N_VALUES, N_PARAMS, NOISE_ROWS = _fastsim.N_VALUES, _fastsim.N_PARAMS, _fastsim.NOISE_ROWS

#: True when each slot draws its own sensor-noise blocks in C, from the episode's generator, on
#: whichever thread steps it (same draws as :meth:`SensorSuite.draw_block`); else Python draws
#: every block (``Batch.set_noise``) when the kernel asks for one.
NOISE_IN_C = AVAILABLE and _noise_in_c()

#: True when the extension makes a vector env's per-step result arrays itself (``Batch.collect``,
#: built with numpy's array API); else :class:`mkv_env.vector.MKVVectorEnv` does it in Python.
COLLECT = AVAILABLE and hasattr(_fastsim.Batch, "collect")

#: True when a native vector env can reset its MKV-v0 / MKV-v1 envs inside the kernel call, on
#: the worker threads (``Batch.set_reset``): their worlds are built in C and handed to pymunk
#: only when Python asks for them (:func:`adopt_world`). Needs the noise drawn in C.
C_RESET = NOISE_IN_C and _chipmunk.RESET and hasattr(_fastsim.Batch, "adopt")

#: The env classes' reward/termination rules, as the kernel numbers them.
def unavailable_reason() -> str:
    """Why ``kernel='c'`` cannot run here, in one line."""
    if chipmunk.PROBLEMS:
        return (f"kernel='c' is off: {chipmunk.PROBLEMS[0]} (mkv_env.chipmunk checks pymunk at "
                "import); use kernel='python' (same results)")
    return ("kernel='c' needs the compiled extension mkv_env._fastsim, which is not built "
            "(no C compiler at install time); use kernel='python'")


KIND_WANDER, KIND_JAM, KIND_WANDER_V1, KIND_JAM_V1 = range(4)

#: Names of the kernel's output buffers, in Batch.outputs order: (dtype, width).
OUTPUTS = (
    ("obs", np.float32, len(SENSOR_NAMES)), ("reward", np.float64, 0),
    ("terminated", np.bool_, 0), ("stuck", np.bool_, 0), ("bumped", np.bool_, 0),
    ("collision", np.bool_, 0), ("distance_m", np.float64, 0), ("jams", np.int64, 0),
    ("escapes", np.int64, 0), ("collisions", np.int64, 0), ("in_jam", np.bool_, 0),
    ("pose", np.float64, 3), ("cells_visited", np.int64, 0), ("escaped", np.bool_, 0),
)


def default_kernel() -> str:
    """``"c"`` when the compiled kernel is built and the robot's compiled loop is the default
    (:data:`mkv_env.robot.DEFAULT_KERNEL`), else ``"python"``."""
    return "c" if AVAILABLE and _robot.DEFAULT_KERNEL == "c" else "python"


#: The kernel's per-step numbers grouped by dtype: each is a row of one block, so a vector env
#: snapshots a step with one copy per block (``Outputs.blocks``) instead of one per key.
_BLOCK_ROWS = {
    "f": ("reward", "distance_m"),
    "b": ("terminated", "stuck", "bumped", "collision", "in_jam", "escaped"),
    "i": ("jams", "escapes", "collisions", "cells_visited"),
}


class Outputs(dict):
    """The kernel's output buffers for ``n`` slots, by name (rows of dtype blocks; ``obs`` and
    ``pose`` arrays of their own). ``blocks`` maps "obs", "pose", "f", "b", "i" to the arrays."""

    def __init__(self, n: int):
        super().__init__()
        self.blocks = {
            "obs": np.zeros((n, len(SENSOR_NAMES)), dtype=np.float32),
            "pose": np.zeros((n, 3), dtype=np.float64),
            "f": np.zeros((len(_BLOCK_ROWS["f"]), n), dtype=np.float64),
            "b": np.zeros((len(_BLOCK_ROWS["b"]), n), dtype=np.bool_),
            "i": np.zeros((len(_BLOCK_ROWS["i"]), n), dtype=np.int64),
        }
        where = {k: (blk, r) for blk, rows in _BLOCK_ROWS.items() for r, k in enumerate(rows)}
        for name, dt, _ in OUTPUTS:
            if name in ("obs", "pose"):
                arr = self.blocks[name]
            else:
                blk, r = where[name]
                arr = self.blocks[blk][r]
            assert arr.dtype == dt and arr.flags.c_contiguous
            self[name] = arr

    def snapshot(self) -> dict[str, np.ndarray]:
        """Fresh copies of every output (one copy per block), by name."""
        copies = {k: v.copy() for k, v in self.blocks.items()}
        out = {"obs": copies["obs"], "pose": copies["pose"]}
        for blk, rows in _BLOCK_ROWS.items():
            out.update(zip(rows, copies[blk], strict=True))
        return out


def make_outputs(n: int) -> Outputs:
    """Fresh output buffers for ``n`` slots."""
    return Outputs(n)


def new_batch(env, n: int, num_threads: int = 1):
    """A Batch of ``n`` slots for envs configured like ``env`` (same class and arguments), with
    output buffers attached: (batch, :class:`Outputs`)."""
    b = _fastsim.Batch(n, _robot.kernel_constants(env.robot_params), params(env),
                       sensor_constants(env._sensors), int(num_threads))
    out = make_outputs(n)
    b.outputs(*(out[name] for name, _, _ in OUTPUTS))
    return b, out


def params(env) -> array.array:
    """The kernel's parameter vector (``P_*`` in _native/kernel.h) of an env."""
    from mkv_env.sensors import BATTERY_INTERNAL_OHM, BATTERY_NOMINAL_V
    from mkv_env.tracker import FREE_CLEARANCE_M

    t = env._tracker
    g = getattr
    p = (env.control_period_s / env.substeps, env.substeps, t.period_s, t.stuck_speed_mps,
         t.jam_steps, t.escape_distance_m, t.escape_forward_m, FREE_CLEARANCE_M,
         env._KERNEL_KIND, g(env, "progress_reward", 0.0), env.stuck_penalty,
         env.collision_penalty, g(env, "escape_reward", 0.0), g(env, "coverage_reward", 0.0),
         g(env, "still_penalty", 0.0), g(env, "jam_penalty", 0.0), g(env, "time_penalty", 0.0),
         g(env, "shaping", 0.0), g(env, "_COVERAGE_CELL_M", 0.25), env._sensors._tick_angle,
         BATTERY_NOMINAL_V, BATTERY_INTERNAL_OHM)
    out = array.array("d", map(float, p))
    assert len(out) == N_PARAMS
    for name, v in zip(_WEIGHTS, out[9:18], strict=True):  # set_attr reaches here too
        if not abs(v) <= REWARD_WEIGHT_MAX:
            raise ValueError(f"{name} must be a finite number with |{name}| <= "
                             f"{REWARD_WEIGHT_MAX:g}, got {v!r}")
    return out


#: The largest magnitude of a reward weight (a reward is a weighted sum of per-step quantities
#: of order 1-100 over a few hundred steps: weights near 1.7e308 gave infinite rewards); the
#: envs check it at construction, :func:`params` when a changed weight reaches the kernel.
REWARD_WEIGHT_MAX = 1e6


#: The reward weights of :func:`params` (entries 9-17), by name.
_WEIGHTS = ("progress_reward", "stuck_penalty", "collision_penalty", "escape_reward",
            "coverage_reward", "still_penalty", "jam_penalty", "time_penalty", "shaping")


def sensor_constants(sensors) -> np.ndarray:
    """(inv_q, q, low, high) of every channel, one float64 vector."""
    return np.concatenate([sensors._inv_q, sensors._q, sensors.low, sensors.high])


# ---------------------------------------------------------------------- arena layouts
def _layout_constants() -> np.ndarray:
    from mkv_env import world as w

    return np.array([w.CLUTTER_MARGIN_M, w.CLUTTER_TRIES, *w.BOX_SIDE_M, *w.CYLINDER_RADIUS_M,
                     *w.WALL_PIECE_LENGTH_M, *w.CORNER_ARM_M, *w.DEAD_END_GAP_M,
                     *w.DEAD_END_DEPTH_M, *w.CLUTTER_GAP_M, *w.PATCH_SIDE_M, w.WALL_RADIUS_M,
                     *w._CLUTTER_CDF], dtype=np.float64)


_LAYOUT_CONSTANTS = None


def generate_layout(rng: np.random.Generator, width_m: float = 4.0, height_m: float = 4.0,
                    n_clutter: int = 14, n_patches: int = 2, patch_friction_scale: float = 0.3,
                    reserved=None):
    """:func:`mkv_env.world.generate_layout` computed in C: the same draws from ``rng``'s bit
    generator, the same layout to the bit (``tests/mkv_env/test_step_kernel.py``), ~30x faster.
    (Like every numpy draw, not to be called on one generator from two threads at once.)"""
    from mkv_env.world import Layout

    global _LAYOUT_CONSTANTS
    if _LAYOUT_CONSTANTS is None:
        _LAYOUT_CONSTANTS = _layout_constants()
    W, H = float(width_m), float(height_m)
    boxes, cylinders, walls, patches = _fastsim.generate_layout(
        rng.bit_generator.capsule, W, H, int(n_clutter), int(n_patches),
        float(patch_friction_scale), [tuple(map(float, c)) for c in (reserved or ())],
        _LAYOUT_CONSTANTS)
    lay = Layout(width_m, height_m)
    lay.walls += [(0, 0, W, 0), (W, 0, W, H), (W, H, 0, H), (0, H, 0, 0)]
    lay.walls += walls
    lay.boxes, lay.cylinders, lay.patches = boxes, cylinders, patches
    return lay


# ---------------------------------------------------------------------- state in and out
_WHEEL = ("drive_omega", "steer", "steer_rate", "drive_angle", "roller_angle", "drive_budget",
          "drive_current", "steer_current")
_TRACK = ("x", "y", "heading", "distance_m", "last_step_m", "stuck_run", "jams", "escapes",
          "in_jam", "jam_x", "jam_y", "collisions", "forward_run_m", "_events")
_TRACK_INT = frozenset(("stuck_run", "jams", "escapes", "collisions", "_events"))


def sync_params(env, batch) -> None:
    """Hand ``env``'s parameters (reward weights, thresholds) to ``batch`` when they changed
    since they were last handed over."""
    p = params(env)
    if p != getattr(env, "_kernel_params", None):
        batch.set_params(p)
        env._kernel_params = p


def push(env, batch, slot: int) -> None:
    """Copy ``env``'s Python state (world, wheels, sensors, tracker, reward state) into a slot,
    and its parameters (reward weights, thresholds) into the batch when they changed since."""
    sync_params(env, batch)
    world = env.world
    robot = world.robot
    st, t, s = robot._state, env._tracker, env._sensors
    _, body, space = robot.pointers(world.space)
    batch.bind(slot, body, space, world.contacts, world.layout.patches)
    values = array.array("d", [getattr(st, k) for k in _WHEEL])
    values.append(robot._mu_scale)
    values.extend(map(float, s._last_ticks))
    values.extend(float(getattr(t, k)) for k in _TRACK)
    values.append(getattr(env, "_phi", 0.0))
    if s._block is not None:
        batch.set_noise(slot, s._block)
    if NOISE_IN_C:  # the slot draws its next blocks from the episode's generator itself (a
        # Generator's standard normal only: anything else, e.g. a legacy RandomState, is drawn
        # by Python as the reference draws it)
        gen = s._rng.bit_generator if isinstance(s._rng, np.random.Generator) else None
        batch.set_noise_source(slot, gen,
                               np.asarray(s._std, dtype=np.float64),
                               np.asarray(s._bias, dtype=np.float64))
    batch.load(slot, values, s._row, list(getattr(env, "_cells", ())))


def pull(env, batch, slot: int) -> None:
    """Copy a slot's state back into ``env``'s Python objects (the reverse of :func:`push`)."""
    values, row, noise, cells = batch.state(slot)
    robot = env.world.robot
    st, t, s = robot._state, env._tracker, env._sensors
    for k, v in zip(_WHEEL, values, strict=False):
        setattr(st, k, v)
    robot._mu_scale = values[8]
    s._last_ticks = (int(values[9]), int(values[10]))
    for k, v in zip(_TRACK, values[11:], strict=False):
        setattr(t, k, int(v) if k in _TRACK_INT else v)
    t.in_jam = bool(t.in_jam)
    if hasattr(env, "_phi"):
        env._phi = values[-1]
    if hasattr(env, "_cells"):
        env._cells = set(cells)
    if row != s._row or s._block is None or s._block.tobytes() != noise:
        s._block = np.frombuffer(noise, dtype=np.float64).reshape(NOISE_ROWS, -1).copy()
        s._noise = s._block.tolist()
    s._row = row


# ---------------------------------------------------------------------- resets in C
def reset_constants(env) -> array.array:
    """The constants of a reset in C (``R_*`` in _native/kernel.h) for envs configured like ``env``:
    the arena, obstacles, space, start-pose search and the robot's body and shapes, each
    computed as :class:`~mkv_env.world.World`, :class:`~mkv_env.robot.Robot` and
    :func:`~mkv_env.world.random_free_pose` compute it."""
    from mkv_env import world as w

    p = env.robot_params
    verts, bumpers, r = _robot.shape_geometry(p)
    W = env.arena_size_m
    R = (W, W, env.n_clutter, env.n_patches, env.patch_friction, w.WALL_RADIUS_M,
         w.OBSTACLE_FRICTION, w.OBSTACLE_ELASTICITY, _robot.OBSTACLE, w.SPACE_ITERATIONS,
         w.SPACE_DAMPING, w.ROBOT_CLEARANCE_M + w.WALL_RADIUS_M, w.ROBOT_CLEARANCE_M,
         w.START_POSE_TRIES, w.LAYOUT_ATTEMPTS, p.mass_kg, _robot.moment_of_inertia(p),
         p.chassis_friction, _robot.CHASSIS, _robot.BUMP_FL, _robot.BUMP_FR, _robot.BUMP_REAR,
         *(c for v in verts for c in v), *(c for seg in bumpers for pt in seg for c in pt), r,
         _robot.ROBOT_FILTER.group, *_chipmunk.HANDLER_OFFSETS)
    out = array.array("d", map(float, R))
    assert len(out) == _fastsim.N_RESET
    return out


def setup_resets(env, batch) -> bool:
    """Give ``batch`` the constants to reset envs configured like ``env`` in C; False (nothing
    done) when it cannot: no :data:`C_RESET`, or rendering (the trails are kept in Python).
    Only for the classes of MKV-v0 and MKV-v1 (the caller checks: MKVJam's start search and
    subclasses stay Python)."""
    global _LAYOUT_CONSTANTS
    if not C_RESET or env.render_mode is not None:
        return False
    if _LAYOUT_CONSTANTS is None:
        _LAYOUT_CONSTANTS = _layout_constants()
    batch.set_reset(reset_constants(env), _LAYOUT_CONSTANTS)
    return True


def adopt_world(env, batch, slot: int) -> bool:
    """Hand the world slot ``slot`` built at its last reset in C to Python: ``env.world`` becomes
    a :class:`~mkv_env.world.World` of pymunk objects wrapping the very same Chipmunk space,
    bodies and shapes (so stepping on, in C or Python, gives the same bits), and the env's
    episode bookkeeping is that of a fresh reset; the slot keeps the newest state (``pull``
    brings it to Python on demand). False when the slot holds no world of its own."""
    import pymunk

    from mkv_env.actions import NOOP_ACTION
    from mkv_env.world import Layout, World

    counts = array.array("q", bytes(40))
    got = batch.adopt(slot, counts)
    if got is None:
        return False
    space_p, static_p, body_p, shape_ps, static_cap, walls, boxes, cylinders, patches, start = got
    space = chipmunk.wrap_space(space_p)
    chipmunk.wrap_body(static_p, space, static=True)  # (kept as space.static_body)
    W = H = env.arena_size_m
    lay = Layout(W, H)
    lay.walls += [(0, 0, W, 0), (W, 0, W, H), (W, H, 0, H), (0, H, 0, 0)]
    lay.walls += walls
    lay.boxes, lay.cylinders, lay.patches = boxes, cylinders, patches
    world = World.__new__(World)
    world.layout, world.robot_params, world.space = lay, env.robot_params, space
    world.fast_contacts, world._static, world.contacts = True, static_cap, counts
    _chipmunk.install_contacts(world)
    robot = _robot.Robot.__new__(_robot.Robot)
    robot.params = env.robot_params
    robot.body = chipmunk.wrap_body(body_p, space)
    robot.shapes = tuple(chipmunk.wrap_shape(cls, ptr, robot.body, space) for cls, ptr in zip(
        (pymunk.Poly, pymunk.Segment, pymunk.Segment, pymunk.Segment), shape_ps, strict=True))
    robot._state = _robot.WheelState()
    robot._sync = None
    robot._mu_scale = 1.0
    robot.kernel = env._robot_kernel
    robot._ptrs = None
    robot._precompute()
    world.robot = robot
    env._world = world
    env._tracker.reset(start, False, 0)
    env._sensors._rng = env.np_random
    env._sensors._row = NOISE_ROWS
    env._sensors._last_ticks = (0, 0)
    if hasattr(env, "_cells"):
        env._cells = set()
    env.trail = [start[:2]]
    env._last_action = NOOP_ACTION
    robot._sync = env._to_python
    return True
