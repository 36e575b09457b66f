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
``np_random`` at reset) in blocks of 256 rows, as :meth:`SensorSuite.draw_block` draws them. The
extension is linked with numpy's random library (checked at import: :func:`_noise_in_c`; a
mismatch turns the kernel off): a slot draws its next block itself with numpy's
``random_standard_normal`` on that generator's bit generator, on whichever thread steps it. A slot
with no generator of its own (one shared by two robots, a legacy ``RandomState``) asks for a new
block when it has used its own (``step`` returns the slots that need one, before stepping
anything) and Python draws it. Either way the draws happen in the reference's order.

State moves between Python and C at well-defined points only: a reset ``push``es the Python
objects' state (each owner's ``to_state()``) into the slot, and the robot hands its wheel state
over; reading ``env.world``, ``env.tracker`` or ``env.sensors`` after C steps ``pull``s it back
(each owner's ``load_state()``) and hands ownership to Python until the next step pushes it
again.

A native vector env of MKV-v0 or MKV-v1 resets its envs inside the kernel call too
(:func:`setup_resets`): the slot draws the layout and start pose from the
episode's generator and builds the Chipmunk space, obstacles, contact handlers and robot with the
calls pymunk makes, in pymunk's order (so the same hash ids, spatial index and bits), on the worker
thread that resets it. The slot owns that world until Python reads ``env.world`` (or the tracker,
sensors, a pickle): then :func:`adopt_world` wraps the very same Chipmunk objects in pymunk
objects, which own them from then on.
"""

from __future__ import annotations

import array

import numpy as np

from mkv_env import _chipmunk, chipmunk, layouts
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


#: Why the kernel is off although the extension is built ("" when it is on or not built).
_OFF = ""
if AVAILABLE and not _pick_hypot():
    AVAILABLE, _OFF = False, "its copy of math.hypot does not match this interpreter's"


def _noise_in_c() -> bool:
    """True when the kernel draws sensor noise itself and its draws are numpy's: the extension
    was linked with numpy's random library and ``random_standard_normal`` there gives what
    ``Generator.standard_normal`` gives here, for every bit generator numpy ships (probed)."""
    for bg in (np.random.PCG64, np.random.PCG64DXSM, np.random.MT19937, np.random.Philox,
               np.random.SFC64):
        c = _fastsim.normals(bg(20261125), 3000)
        if c != np.random.Generator(bg(20261125)).standard_normal(3000).tolist():
            return False
    return True


if AVAILABLE and not _noise_in_c():
    AVAILABLE, _OFF = False, "its numpy random library draws differently from this numpy's"

if AVAILABLE:
    N_VALUES, N_PARAMS, NOISE_ROWS = _fastsim.N_VALUES, _fastsim.N_PARAMS, _fastsim.NOISE_ROWS


def unavailable_reason() -> str:
    """Why ``kernel='c'`` cannot run here, in one line."""
    if chipmunk.PROBLEMS:
        return (f"kernel='c' is off: {chipmunk.PROBLEMS[0]} (mkv_env.chipmunk checks pymunk at "
                "import); use kernel='python' (same results)")
    if _OFF:
        return f"kernel='c' is off: {_OFF} (rebuild mkv_env); use kernel='python' (same results)"
    return ("kernel='c' needs the compiled extension mkv_env._fastsim, which is not built "
            "(no C compiler at install time); use kernel='python'")


#: The env classes' reward/termination rules, as the kernel numbers them.
KIND_WANDER, KIND_JAM, KIND_WANDER_V1, KIND_JAM_V1 = range(4)

#: The kernel's output buffers (layout O) by the kernel's name: (the name Python uses, dtype,
#: width per slot, 0 for a scalar). :data:`OUTPUTS` puts them in the kernel's order.
_OUTPUTS = {
    "OBS": ("obs", np.float32, len(SENSOR_NAMES)), "REW": ("reward", np.float64, 0),
    "TERM": ("terminated", np.bool_, 0), "STUCK": ("stuck", np.bool_, 0),
    "BUMPED": ("bumped", np.bool_, 0), "COLL": ("collision", np.bool_, 0),
    "DIST": ("distance_m", np.float64, 0), "JAMS": ("jams", np.int64, 0),
    "ESC": ("escapes", np.int64, 0), "COLLS": ("collisions", np.int64, 0),
    "IN_JAM": ("in_jam", np.bool_, 0), "POSE": ("pose", np.float64, 3),
    "CELLS": ("cells_visited", np.int64, 0), "ESCAPED": ("escaped", np.bool_, 0),
}
_FORMATS = {"f": np.float32, "d": np.float64, "?": np.bool_, "q": np.int64}


def _outputs() -> tuple:
    """:data:`_OUTPUTS` in the order of the kernel's layout O, each checked against the kernel's
    buffer format and width (:class:`mkv_env.layouts.LayoutMismatch` when they differ)."""
    if not layouts.LAYOUTS:
        return tuple(_OUTPUTS.values())
    layouts.check_names("O", _OUTPUTS)
    out = []
    for name, _, width, fmt in layouts.fields("O"):
        py, dtype, w = _OUTPUTS[name]
        if _FORMATS.get(fmt) is not dtype or max(w, 1) != width:
            raise layouts.LayoutMismatch(f"layout O: output {name} is {fmt!r} x {width} in the "
                                         f"compiled kernel, {np.dtype(dtype).char!r} x {max(w, 1)} "
                                         "in Python: the build is stale (rebuild mkv_env)")
        out.append((py, dtype, w))
    return tuple(out)


#: Names of the kernel's output buffers, in Batch.outputs order: (name, dtype, width).
OUTPUTS = _outputs()


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
    weights = {key: float(getattr(env, attr, 0.0)) for key, attr in _WEIGHTS.items()}
    for key, v in weights.items():  # set_attr reaches here too
        name = _WEIGHTS[key]
        if not abs(v) <= REWARD_WEIGHT_MAX:
            raise ValueError(f"{name} must be a finite number with |{name}| <= "
                             f"{REWARD_WEIGHT_MAX:g}, got {v!r}")
    return layouts.pack("P", {
        "DT": env.control_period_s / env.substeps, "SUBSTEPS": env.substeps,
        "PERIOD": t.period_s, "STUCK_SPEED": t.stuck_speed_mps, "JAM_STEPS": t.jam_steps,
        "ESC_DIST": t.escape_distance_m, "ESC_FWD": t.escape_forward_m,
        "FREE_CLEAR": FREE_CLEARANCE_M, "KIND": env._KERNEL_KIND, **weights,
        "CELL": getattr(env, "_COVERAGE_CELL_M", 0.25), "TICK": env._sensors._tick_angle,
        "BATT_V": BATTERY_NOMINAL_V, "BATT_R": BATTERY_INTERNAL_OHM})


#: The largest magnitude of a reward weight (a reward is a weighted sum of per-step quantities
#: of order 1-100 over a few hundred steps: weights near 1.7e308 gave infinite rewards); the
#: envs check it at construction, :func:`params` when a changed weight reaches the kernel.
REWARD_WEIGHT_MAX = 1e6


#: The reward weights of :func:`params`: the kernel's name -> the env's attribute (0 when the
#: env's class has none).
_WEIGHTS = {"PROGRESS": "progress_reward", "STUCK_PEN": "stuck_penalty",
            "COLL_PEN": "collision_penalty", "ESC_REWARD": "escape_reward",
            "COVERAGE": "coverage_reward", "STILL_PEN": "still_penalty",
            "JAM_PEN": "jam_penalty", "TIME_PEN": "time_penalty", "SHAPING": "shaping"}


def sensor_constants(sensors) -> np.ndarray:
    """(inv_q, q, low, high) of every channel, one float64 vector."""
    return np.concatenate([sensors._inv_q, sensors._q, sensors.low, sensors.high])


# ---------------------------------------------------------------------- arena layouts
def _layout_constants() -> np.ndarray:
    from mkv_env import world as w

    pairs = {"BOX": w.BOX_SIDE_M, "CYL": w.CYLINDER_RADIUS_M, "WALL": w.WALL_PIECE_LENGTH_M,
             "ARM": w.CORNER_ARM_M, "GAP": w.DEAD_END_GAP_M, "DEPTH": w.DEAD_END_DEPTH_M,
             "CGAP": w.CLUTTER_GAP_M, "PATCH": w.PATCH_SIDE_M}
    values = {f"{k}{i}": v[i] for k, v in pairs.items() for i in (0, 1)}
    return np.array(layouts.pack("L", {
        "MARGIN": w.CLUTTER_MARGIN_M, "TRIES": w.CLUTTER_TRIES, **values,
        "WALL_R": w.WALL_RADIUS_M, "CDF": w._CLUTTER_CDF}), dtype=np.float64)


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
#: A slot's doubles (layouts S and V) by the kernel's names: the wheel state's attributes ...
_WHEEL = {"WW": "drive_omega", "DELTA": "steer", "RATE": "steer_rate",
          "DRIVE_ANGLE": "drive_angle", "ROLLER_ANGLE": "roller_angle", "BUDGET": "drive_budget",
          "I_DRIVE": "drive_current", "I_STEER": "steer_current"}
#: ... and the tracker's (:meth:`MotionTracker.state`; the rest of V: MU, TICK_D, TICK_R and PHI
#: are the robot's, the sensors' and the env's)
_TRACK = {"X": "x", "Y": "y", "HEAD": "heading", "DIST": "distance_m", "LAST": "last_step_m",
          "STUCK_RUN": "stuck_run", "JAMS": "jams", "ESCAPES": "escapes", "IN_JAM": "in_jam",
          "JAM_X": "jam_x", "JAM_Y": "jam_y", "COLLS": "collisions", "FWD": "forward_run_m",
          "EVENTS": "_events"}


def sync_params(env, batch) -> None:
    """Hand ``env``'s parameters (reward weights, thresholds) to ``batch`` when they changed
    since they were last handed over."""
    p = params(env)
    if p != getattr(env, "_kernel_params", None):
        batch.set_params(p)
        env._kernel_params = p


def push(env, batch, slot: int) -> None:
    """Copy ``env``'s Python state (world, wheels, sensors, tracker, reward state) into a slot,
    and its parameters (reward weights, thresholds) into the batch when they changed since. The
    robot then hands its wheel state over (:meth:`~mkv_env.robot.Robot.hand_over`) until
    :func:`pull` gives it back."""
    sync_params(env, batch)
    world = env.world
    robot = world.robot
    wheels, sensed, tracked = robot.to_state(), env.sensors.to_state(), env.tracker.to_state()
    phi, cells = env._reward_state()
    _, body, space = robot.pointers(world.space)
    batch.bind(slot, body, space, world.contacts, world.layout.patches)
    values = layouts.pack("S", {k: wheels[a] for k, a in _WHEEL.items()})
    values.extend(layouts.pack("V", {
        "MU": wheels["mu_scale"], "TICK_D": sensed["last_ticks"][0],
        "TICK_R": sensed["last_ticks"][1], **{k: tracked[a] for k, a in _TRACK.items()},
        "PHI": phi}, start=len(values)))
    if sensed["block"] is not None:
        batch.set_noise(slot, sensed["block"])
    # the slot draws its next blocks from the episode's generator itself (a Generator's standard
    # normal only: anything else, e.g. a legacy RandomState, is drawn by Python as the reference
    # draws it)
    rng = sensed["rng"]
    gen = rng.bit_generator if isinstance(rng, np.random.Generator) else None
    batch.set_noise_source(slot, gen, np.asarray(sensed["std"], dtype=np.float64),
                           np.asarray(sensed["bias"], dtype=np.float64))
    batch.load(slot, values, sensed["row"], list(cells))
    robot.hand_over()


def pull(env, batch, slot: int) -> None:
    """Copy a slot's state back into ``env``'s Python objects (the reverse of :func:`push`),
    each through its owner's ``load_state``."""
    values, row, noise, cells = batch.state(slot)
    wheel, v = layouts.unpack("S", values), layouts.unpack("V", values)
    env.world.robot.load_state({**{a: wheel[k] for k, a in _WHEEL.items()}, "mu_scale": v["MU"]})
    env.sensors.load_state({"row": row, "block": noise,
                            "last_ticks": (int(v["TICK_D"]), int(v["TICK_R"]))})
    env.tracker.load_state({a: v[k] for k, a in _TRACK.items()})
    env._load_reward_state(v["PHI"], cells)


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
    fl, fr, rb = ([c for pt in seg for c in pt] for seg in bumpers)
    begin, separate, data = _chipmunk.HANDLER_OFFSETS
    return layouts.pack("R", {
        "W": W, "H": W, "NCLUTTER": env.n_clutter, "NPATCH": env.n_patches,
        "PSCALE": env.patch_friction, "WALL_R": w.WALL_RADIUS_M, "OBS_FRIC": w.OBSTACLE_FRICTION,
        "OBS_ELAST": w.OBSTACLE_ELASTICITY, "OBS_TYPE": _robot.OBSTACLE,
        "ITER": w.SPACE_ITERATIONS, "DAMP": w.SPACE_DAMPING,
        "MARGIN": w.ROBOT_CLEARANCE_M + w.WALL_RADIUS_M, "CLEAR": w.ROBOT_CLEARANCE_M,
        "TRIES": w.START_POSE_TRIES, "ATTEMPTS": w.LAYOUT_ATTEMPTS, "MASS": p.mass_kg,
        "MOMENT": _robot.moment_of_inertia(p), "FRIC": p.chassis_friction,
        "TYPES": (_robot.CHASSIS, _robot.BUMP_FL, _robot.BUMP_FR, _robot.BUMP_REAR),
        "CHASSIS": [c for v in verts for c in v], "FL": fl, "FR": fr, "RB": rb, "BUMP_R": r,
        "GROUP": _robot.ROBOT_FILTER.group, "H_BEGIN": begin, "H_SEP": separate,
        "H_DATA": data})


def setup_resets(env, batch) -> bool:
    """Give ``batch`` the constants to reset envs configured like ``env`` in C; False (nothing
    done) when it cannot: rendering (the trails are kept in Python).
    Only for the classes of MKV-v0 and MKV-v1 (the caller checks: MKVJam's start search and
    subclasses stay Python)."""
    global _LAYOUT_CONSTANTS
    if env.render_mode is not None:
        return False
    if _LAYOUT_CONSTANTS is None:
        _LAYOUT_CONSTANTS = _layout_constants()
    batch.set_reset(reset_constants(env), _LAYOUT_CONSTANTS)
    return True


def adopt_world(env, batch, slot: int):
    """Hand the world slot ``slot`` built at its last reset in C to Python: a
    :class:`~mkv_env.world.World` of pymunk objects wrapping the very same Chipmunk space,
    bodies and shapes (so stepping on, in C or Python, gives the same bits), configured as
    ``env`` (read only), and the start pose; the env takes them (``MKVEnv._adopt``), and the
    slot keeps the newest state (``pull`` brings it to Python on demand). None when the slot
    holds no world of its own."""
    import pymunk

    from mkv_env.world import Layout, World

    counts = array.array("q", bytes(40))
    got = batch.adopt(slot, counts)
    if got is None:
        return None
    space_p, static_p, body_p, shape_ps, static_cap, walls, boxes, cylinders, patches, start = got
    space = chipmunk.wrap_space(space_p)
    chipmunk.wrap_body(static_p, space, static=True)  # (kept as space.static_body)
    W = H = env.arena_size_m
    lay = Layout(W, H)
    lay.walls += [(0, 0, W, 0), (W, 0, W, H), (W, H, 0, H), (0, H, 0, 0)]
    lay.walls += walls
    lay.boxes, lay.cylinders, lay.patches = boxes, cylinders, patches
    world = World.adopted(lay, env.robot_params, space, static_cap, counts)
    body = chipmunk.wrap_body(body_p, space)
    shapes = tuple(chipmunk.wrap_shape(cls, ptr, body, space) for cls, ptr in zip(
        (pymunk.Poly, pymunk.Segment, pymunk.Segment, pymunk.Segment), shape_ps, strict=True))
    world.robot = _robot.Robot.adopted(env.robot_params, body, shapes, env._robot_kernel)
    return world, start
