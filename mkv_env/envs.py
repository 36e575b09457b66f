"""Gymnasium environments of the MK-V: ``MKV-v0``/``MKV-v1`` (wander) and ``MKVJam-v0``/
``MKVJam-v1`` (escape a jam). The v1 ids simulate the same robot and arena; only their rewards
(and nothing the robot senses) differ: see :class:`MKVEnvV1` and :class:`MKVJamEnvV1`."""

from __future__ import annotations

import math
import pickle
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from mkv_env import kernel as _kernel
from mkv_env import robot as _robot
from mkv_env.actions import ACTION_NVEC, NOOP_ACTION, OFF, action_space
from mkv_env.jams import SCENARIOS, build_scenario, scenario_code
from mkv_env.params import RobotParams, channel_specs
from mkv_env.sensors import SensorSuite
from mkv_env.tracker import MotionTracker
from mkv_env.world import LAYOUT_ATTEMPTS, World, generate_layout, random_free_pose

#: Observation modes (``gym.make(id, observation=...)``): the sensor readings, the same mapped to
#: [-1, 1], or the shape-from-motion features of the latter (see ``MKVEnv._set_observation``).
OBSERVATIONS = ("raw", "rescaled", "features")

JAM_ATTEMPTS = 50
"""Scenario geometries tried per reset of ``MKVJam-v0`` before the jam counts as unbuildable."""
JAM_DRIVE_MAX_STEPS = 40
"""Control periods of driving forward from the approach pose to get stuck (4 s at 0.1 s)."""
TRAIL_MAX_POINTS = 600
"""Robot positions kept for drawing the trail; the oldest ``TRAIL_DROP_POINTS`` go at once."""
TRAIL_DROP_POINTS = 100


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ValueError(msg)


class MKVEnv(gym.Env):
    """The MK-V robot wandering a cluttered arena.

    ## Description
    A three-wheeled, non-holonomic robot seen from above (pymunk 2-D, no gravity in the plane):
    one powered drive wheel at the rear, fixed in the chassis; one unpowered front steering
    wheel turned by a steering motor between mechanical stops (+-35 deg); a free caster. Both
    motors are DC motors driven open loop with three-valued commands. Wheels resist sideways slip
    up to a traction limit (friction circle), so the robot skids when pushed and, blocked, its
    drive wheel stalls (high current) or spins (slippery floor patches, side load). The arena
    (4 m x 4 m by default) holds seeded random clutter: boxes, cylinders, wall pieces, corners
    and dead ends, some gaps narrower than the robot. The learner sees only sensor channels.

    ## Action Space
    ``MultiDiscrete([3, 3])`` = [drive, steer]: drive 0 reverse, 1 off, 2 forward; steer 0 left,
    1 off, 2 right. "Off" removes the supply but leaves the armature connected: the wheel coasts
    and is damped by back-EMF.

    ## Observation Space
    ``Box(low, high, (10,), float32)`` of raw sensor readings, names in
    ``env.unwrapped.sensor_names``; each is truth + bias + Gaussian noise, quantised, clipped:

    | idx | name             | low   | high | unit         | default noise / quantum        |
    |-----|------------------|-------|------|--------------|--------------------------------|
    | 0   | drive_ticks      | -60   | 60   | ticks/period | exact / 1 tick (128 per rev)   |
    | 1   | roller_ticks     | -60   | 60   | ticks/period | exact / 1 tick, steering wheel |
    | 2   | steer_angle      | -0.8  | 0.8  | rad          | 0.005 / 0.0061 (10-bit pot)    |
    | 3   | compass          | -pi   | pi   | rad          | 2 deg / 1 deg, wrapped         |
    | 4   | bump_front_left  | 0     | 1    | bool         | none                           |
    | 5   | bump_front_right | 0     | 1    | bool         | none                           |
    | 6   | bump_rear        | 0     | 1    | bool         | none                           |
    | 7   | drive_current    | -1.2  | 1.2  | A            | 0.01 / 0.0024 (stall 0.5 A)    |
    | 8   | steer_current    | -1.0  | 1.0  | A            | 0.01 / 0.002 (stall 0.4 A)     |
    | 9   | battery          | 0     | 8    | V            | 0.02 / 0.0078, sags with load  |

    ## Rewards
    Per step: ``progress_reward * forward progress [m]`` (displacement along the heading; negative
    when reversing), minus ``stuck_penalty`` while stuck (commanded to drive, moving slower than
    ``stuck_speed_mps``), minus ``collision_penalty`` for each new contact with an obstacle.

    ## Starting State
    A new seeded layout each reset; the robot at rest at a uniformly random pose at least
    0.26 m from every obstacle, steering centred.

    ## Episode End
    No termination. Truncation after ``max_episode_steps`` (600 steps = 60 s by default, set by
    the registration's TimeLimit).

    ## Info
    Every step: ``stuck``, ``bumped`` (any bump switch), ``collision`` (new contact this step),
    ``distance_m`` (cumulative), ``jams``, ``escapes``, ``collisions`` (counts), ``in_jam``,
    ``pose`` (x [m], y [m], heading [rad]). A jam begins after ``jam_steps`` stuck steps; it is
    escaped once the robot is free: not stuck, ``escape_distance_m`` from where the jam began, no
    obstacle within ``free_clearance_m`` (0.22 m) of its centre (so backing part-way out of a
    dead end does not count), and driving on: its last ``escape_forward_m`` (0.15 m) of travel
    went forward without a stop or reversal (so backing out and reversing forever does not count:
    with it, constant reverse escapes 0 of 100 ``MKVJam-v0`` episodes; without it, 94%).
    No wall-clock values.

    ## Arguments
    ```python
    import gymnasium as gym
    import mkv_env
    env = gym.make("MKV-v0", arena_size_m=4.0, n_clutter=14, sensor_noise=1.0,
                   control_period_s=0.1, substeps=4, max_episode_steps=600)
    ```
    * ``arena_size_m``: side of the square arena [m], 2 to 20.
    * ``n_clutter``: number of clutter items (an L or U counts as one), 0 to 200.
    * ``n_patches``: slippery floor patches; ``patch_friction``: their friction multiplier.
    * ``sensor_noise``: multiplier of every channel's default noise (0 = noise-free).
    * ``sensor_params``: per-channel overrides, ``{"compass": {"bias": 0.1, "quantum": 0}}``.
    * ``robot_params``: overrides of :class:`mkv_env.params.RobotParams` fields.
    * ``control_period_s`` (0.1), ``substeps`` (4): control period and physics substeps.
    * ``stuck_speed_mps``, ``jam_steps``, ``escape_distance_m``, ``escape_forward_m``: the
      stuck/jam/escape measures.
    * ``progress_reward``, ``stuck_penalty``, ``collision_penalty``: reward weights.
    * ``render_mode``: ``"rgb_array"`` or ``"human"`` (pygame, imported lazily).
    * ``kernel``: ``"c"`` (default where the extension is built: the whole step after the action
      is decoded runs compiled, :mod:`mkv_env.kernel`) or ``"python"`` (the reference
      implementation, everything in Python). Both give the same bits. (Reward weights and
      thresholds changed on a live env take effect at its next reset with ``"c"``, at once with
      ``"python"``.)

    ## Version History
    * v0: initial release.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 10}
    _KERNEL_KIND = _kernel.KIND_WANDER

    def __init__(
        self,
        render_mode: str | None = None,
        arena_size_m: float = 4.0,
        n_clutter: int = 14,
        n_patches: int = 2,
        patch_friction: float = 0.3,
        sensor_noise: float = 1.0,
        sensor_params: dict | None = None,
        robot_params: dict | None = None,
        control_period_s: float = 0.1,
        substeps: int = 4,
        stuck_speed_mps: float = 0.02,
        jam_steps: int = 3,
        escape_distance_m: float = 0.3,
        escape_forward_m: float = 0.15,
        progress_reward: float = 10.0,
        stuck_penalty: float = 0.1,
        collision_penalty: float = 0.05,
        kernel: str | None = None,
        observation: str = "raw",
    ):
        custom = _python_overrides(type(self))
        if kernel is None:
            # a subclass that scores or ends steps its own way runs its own Python
            kernel = "python" if custom else _kernel.default_kernel()
        self._check_arguments(custom, kernel, observation, render_mode, arena_size_m, n_clutter,
                              n_patches, patch_friction, control_period_s, substeps,
                              stuck_speed_mps, jam_steps, escape_distance_m, escape_forward_m,
                              progress_reward, stuck_penalty, collision_penalty)
        try:
            self.robot_params = RobotParams.from_overrides(robot_params)
        except TypeError as e:
            raise ValueError(f"bad robot_params: {e}") from None
        self.channel_specs = channel_specs(sensor_params, sensor_noise)

        self.render_mode = render_mode
        self.arena_size_m = float(arena_size_m)
        self.n_clutter, self.n_patches = int(n_clutter), int(n_patches)
        self.patch_friction = float(patch_friction)
        self.control_period_s, self.substeps = float(control_period_s), int(substeps)
        self.progress_reward = float(progress_reward)
        self.stuck_penalty, self.collision_penalty = float(stuck_penalty), float(collision_penalty)

        self._sensors = SensorSuite(self.channel_specs)
        self.sensor_names = list(self._sensors.names)
        self.observation_space = spaces.Box(
            self._sensors.low.astype(np.float32), self._sensors.high.astype(np.float32),
            dtype=np.float32,
        )
        self.action_space = action_space()
        self.observation = observation
        self._features = self._rescale = None
        if observation != "raw":
            self._set_observation(observation)
        self._tracker = MotionTracker(control_period_s, stuck_speed_mps, jam_steps,
                                      escape_distance_m, float(escape_forward_m))
        self._world: World | None = None
        #: True when the kernel slot reset this env in C (a native vector env's autoreset) and
        #: Python has not yet asked for the world it built (:func:`mkv_env.kernel.adopt_world`).
        self._c_world = False
        self.trail: list[tuple[float, float]] = []
        self._renderer = None
        self._last_action = NOOP_ACTION
        self.kernel = kernel
        # the reference runs the robot's Python substep loop; the C kernel the compiled one
        self._robot_kernel = kernel
        self._batch = self._out = None
        self._slot = 0
        self._py_owns = True  # Python's objects hold the newest state (else the kernel's slot)
        #: envs of a vector env's shared batch whose state Python took back (the vector env's
        #: list, which it empties each step); None for an env with a batch of its own
        self._dirty: list | None = None

    def _check_arguments(self, custom, kernel, observation, render_mode, arena_size_m, n_clutter,
                         n_patches, patch_friction, control_period_s, substeps, stuck_speed_mps,
                         jam_steps, escape_distance_m, escape_forward_m, progress_reward,
                         stuck_penalty, collision_penalty) -> None:
        """Every constructor argument in range, else a one-line ValueError naming it."""
        _check(kernel in ("c", "python"),
               f"kernel must be 'c', 'python' or None, got {kernel!r}")
        _check(kernel == "python" or _kernel.AVAILABLE, _kernel.unavailable_reason())
        _check(kernel == "python" or not custom,
               f"kernel='c' runs the rewards of the MK-V ids only; {type(self).__name__} "
               f"overrides {', '.join(custom)}: use kernel='python' (the default for it)")
        _check(observation in OBSERVATIONS,
               f"observation must be one of {OBSERVATIONS}, got {observation!r}")
        _check(render_mode is None or render_mode in self.metadata["render_modes"],
               f"render_mode must be one of {self.metadata['render_modes']} or None, "
               f"got {render_mode!r}")
        _check(_num(arena_size_m) and 2.0 <= arena_size_m <= 20.0,
               f"arena_size_m must be in [2, 20] metres, got {arena_size_m!r}")
        _check(_int(n_clutter) and 0 <= n_clutter <= 200,
               f"n_clutter must be an integer in [0, 200], got {n_clutter!r}")
        _check(_int(n_patches) and 0 <= n_patches <= 20,
               f"n_patches must be an integer in [0, 20], got {n_patches!r}")
        _check(_num(patch_friction) and 0.0 < patch_friction <= 2.0,
               f"patch_friction must be in (0, 2], got {patch_friction!r}")
        _check(_num(control_period_s) and 0.01 <= control_period_s <= 1.0,
               f"control_period_s must be in [0.01, 1] seconds, got {control_period_s!r}")
        _check(_int(substeps) and 1 <= substeps <= 100,
               f"substeps must be an integer in [1, 100], got {substeps!r}")
        _check(control_period_s / substeps <= 0.05,
               f"physics substep control_period_s/substeps = {control_period_s / substeps:.3f} s "
               "is too long (max 0.05 s); raise substeps")
        for name, v in (("stuck_speed_mps", stuck_speed_mps),
                        ("escape_distance_m", escape_distance_m)):
            _check(_num(v) and v > 0, f"{name} must be a positive number, got {v!r}")
        _check(_num(escape_forward_m) and escape_forward_m >= 0,
               f"escape_forward_m must be a number >= 0, got {escape_forward_m!r}")
        _check(_int(jam_steps) and 1 <= jam_steps <= 2**31 - 1,
               f"jam_steps must be an integer in 1..2147483647, got {jam_steps!r}")
        for name, v in (("progress_reward", progress_reward), ("stuck_penalty", stuck_penalty),
                        ("collision_penalty", collision_penalty)):
            _check(_weight(v), f"{name} must be a finite number with |{name}| <= "
                   f"{REWARD_WEIGHT_MAX:g}, got {v!r}")

    # ------------------------------------------------------------------ state owners
    @property
    def world(self) -> World | None:
        """The episode's arena and robot (pymunk objects), current (taken back from the compiled
        kernel when it holds them); None before the first reset."""
        self._to_python()
        return self._world

    @world.setter
    def world(self, value: World | None) -> None:
        self._world = value
        self._c_world = False
        if self._batch is not None and not self._py_owns:  # the slot's state is obsolete
            self._py_owns = True
            if self._dirty is not None:
                self._dirty.append(self)

    def _adopt(self) -> None:
        """Take over the world the kernel slot built at a reset in C, with the episode's
        bookkeeping as a fresh reset leaves it."""
        self._c_world = False
        got = _kernel.adopt_world(self, self._batch, self._slot)
        if got is None:
            return
        world, start = got
        self._world = world
        self._tracker.reset(start, False, 0)
        self._sensors.restart(self.np_random)
        if hasattr(self, "_cells"):
            self._cells = set()
        self.trail = [start[:2]]
        self._last_action = NOOP_ACTION

    @property
    def tracker(self) -> MotionTracker:
        """Ground-truth motion bookkeeping (distance, stuck, jams, escapes) of the episode."""
        self._to_python()
        return self._tracker

    @property
    def sensors(self) -> SensorSuite:
        """The sensor model (channels, noise stream, encoder state)."""
        self._to_python()
        return self._sensors

    def _to_python(self) -> None:
        """Make the Python objects current (pull the kernel slot's state) and theirs to change:
        the next step pushes them back."""
        if self._c_world:
            self._adopt()
        if self._batch is not None and not self._py_owns:
            self._py_owns = True  # (first: pull reads the objects through their properties)
            _kernel.pull(self, self._batch, self._slot)
            if self._dirty is not None:
                self._dirty.append(self)

    def _push(self) -> None:
        """Hand the Python objects' state to the kernel's slot (after a reset, or after Python
        code took it back)."""
        _kernel.push(self, self._batch, self._slot)
        self._py_owns = False

    def _reward_state(self) -> tuple[float, list]:
        """(potential, visited cells) of this env's reward for the kernel's slot: the base env
        keeps neither (subclasses that shape or count do)."""
        return getattr(self, "_phi", 0.0), list(getattr(self, "_cells", ()))

    def _load_reward_state(self, phi: float, cells) -> None:
        """Take the reward state the kernel's slot reached (the reverse of
        :meth:`_reward_state`)."""
        if hasattr(self, "_phi"):
            self._phi = phi
        if hasattr(self, "_cells"):
            self._cells = set(cells)

    def __getstate__(self):
        """The env's state for ``pickle`` and ``copy.deepcopy``. Taking it rebuilds this env's own
        world from the same pickled state first: Chipmunk's spatial index and contact caches are
        rebuilt on unpickling, not copied, so a copy would otherwise find (and solve) contacts in
        another order than the original and part from it at a contact. The original and every
        copy then continue bit for bit (a run that takes a snapshot differs from one that does
        not in the order of contacts after it, never in anything a snapshot is for)."""
        self._to_python()
        if self._world is not None:
            self._world = pickle.loads(pickle.dumps(self._world, pickle.HIGHEST_PROTOCOL))
        state = self.__dict__.copy()
        state["_batch"] = state["_out"] = None  # C memory: a copy gets a batch of its own
        state["_dirty"] = None
        state["_slot"] = 0
        state["_py_owns"] = True
        return state

    def __setstate__(self, state):
        if "world" in state:  # pickled before the world became a property
            state["_world"] = state.pop("world")
        state.setdefault("_c_world", False)
        self.__dict__.update(state)
        if self.kernel == "c" and self._world is not None:
            self._batch, self._out = _kernel.new_batch(self, 1)

    # ------------------------------------------------------------------ observation modes
    def _set_observation(self, mode: str) -> None:
        """``rescaled``: every channel mapped from its Box bounds to [-1, 1] exactly as
        ``gymnasium.wrappers.RescaleObservation`` does (float32); ``features``: the default
        shape-from-motion features (:func:`mkv_env.features.default_feature_spec`: every
        channel, decaying traces, the previous command) of the rescaled channels, built online
        with the commands actually sent. A policy trained on either runs on ``gym.make(id,
        observation=mode)`` with no wrapper."""
        from gymnasium.wrappers.utils import rescale_box

        from .features import FeatureBuilder, default_feature_spec

        box, self._rescale, _ = rescale_box(self.observation_space, np.float32(-1.0),
                                            np.float32(1.0))
        if mode == "rescaled":
            self.observation_space = box
            return
        self._features = FeatureBuilder(default_feature_spec(self.sensor_names, ACTION_NVEC))
        self.observation_space = spaces.Box(-np.inf, np.inf, (self._features.n_features,),
                                            np.float32)

    def _observe(self, obs, action=None):
        """The observation in this env's mode (``action``: the command just sent; None at a
        reset)."""
        x = self._rescale(obs)
        if self._features is None:
            return x
        if action is None:
            self._features.reset()
            return self._features.step(x).astype(np.float32)
        return self._features.step(x, np.asarray(action, dtype=np.int64)).astype(np.float32)

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self._reset_raw(seed=seed, options=options)
        if self._rescale is not None:
            obs = self._observe(obs)
        return obs, info

    def step(self, action):
        out = self._step_raw(action)
        if self._rescale is None:
            return out
        return (self._observe(out[0], action), *out[1:])

    def _reset_raw(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.world = self._build_world()
        self._sensors.reset(self.np_random, self.world)
        self._reset_tracker()
        self.trail = [self._pose()[:2]]
        self._last_action = NOOP_ACTION
        info = self._info(False, False)
        if self.kernel == "c":  # the first observation from the kernel (same bits)
            if self._batch is None:
                self._batch, self._out = _kernel.new_batch(self, 1)
            self._push()
            b, i = self._batch, self._slot
            if not b.read(i):
                b.set_noise(i, self._sensors.draw_block())
                b.read(i)
            obs = self._out["obs"][i].copy()
        else:
            obs = self._sensors.read(self.world)
        if self.render_mode == "human":
            self.render()
        return obs, info

    def _step_raw(self, action):
        if self._world is None and not self._c_world:
            raise RuntimeError("call reset() before step()")
        drive, steer = self._decode(action)
        b = self._batch
        if self.kernel != "c":  # the Python reference
            self.world.step(drive, steer, self.control_period_s, self.substeps)
            return self._after_physics(drive)
        if self._py_owns:
            self._push()
        r = b.step1(self._slot, drive, steer)
        if r is None:  # the slot used up its noise block: the next one, as the reference draws it
            b.set_noise(self._slot, self._sensors.draw_block())
            r = b.step1(self._slot, drive, steer)
        (reward, terminated, stuck, bumped, collision, dist, jams, escapes, collisions, in_jam,
         x, y, heading, cells, escaped) = r
        info = {"stuck": stuck, "bumped": bumped, "collision": collision, "distance_m": dist,
                "jams": jams, "escapes": escapes, "collisions": collisions, "in_jam": in_jam,
                "pose": (x, y, heading)}
        self._kernel_info(info, cells, escaped)
        if self.render_mode is not None:
            self.trail.append((x, y))
            if len(self.trail) > TRAIL_MAX_POINTS:
                del self.trail[:TRAIL_DROP_POINTS]
            if self.render_mode == "human":
                self.render()
        return self._out["obs"][self._slot].copy(), reward, terminated, False, info

    def _kernel_info(self, info: dict, cells: int, escaped: bool) -> None:
        """Add this class's own keys to a step's info built from the kernel's numbers (as
        :meth:`_info` adds them to the reference's)."""

    def _after_physics(self, drive: int):
        """The rest of :meth:`step` once the world has moved: sensors, bookkeeping, reward.
        (:class:`mkv_env.vector.MKVVectorEnv` moves many worlds at once, then calls this.)"""
        obs = self._sensors.read(self.world)
        pose = self._pose()
        progress, stuck, collision, escaped = self._tracker.update(
            pose, drive, self.world.contacts[0], self.world.is_clear)
        reward = self._reward(progress, stuck, collision, escaped)
        terminated = self._terminated(escaped)
        self.trail.append(pose[:2])
        if len(self.trail) > TRAIL_MAX_POINTS:
            del self.trail[:TRAIL_DROP_POINTS]
        if self.render_mode == "human":
            self.render()
        return obs, reward, terminated, False, self._info(stuck, collision)

    def get_keys_to_action(self) -> dict:
        """Arrow keys for :func:`gymnasium.utils.play.play`: up forward, down reverse, left /
        right steer, combinations allowed (opposite arrows cancel).

        Returns a dict from sorted tuples of pygame key codes to ``[drive, steer]`` actions of
        shape (2,) (:func:`mkv_env.teleop.keys_to_action`). No key held is
        ``mkv_env.teleop.NOOP`` (both off): pass it as play()'s ``noop``::

            play(env, keys_to_action=env.unwrapped.get_keys_to_action(), noop=teleop.NOOP)
        """
        from mkv_env.teleop import keys_to_action

        return keys_to_action()

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode= to make()")
            return None
        if self._renderer is None:
            from mkv_env.render import Renderer  # pygame only here

            self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])
        return self._renderer.draw(self)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # ------------------------------------------------------------------ pieces
    def _decode(self, action) -> tuple[int, int]:
        if type(action) is np.ndarray and action.shape == (2,) and action.dtype.kind in "iu":
            a0, a1 = action.tolist()  # the common case (SB3, vector envs, samplers): fast path
            if 0 <= a0 < ACTION_NVEC[0] and 0 <= a1 < ACTION_NVEC[1]:
                self._last_action = (a0, a1)
                return a0 - OFF, OFF - a1
        try:
            a0, a1 = action
            a0, a1 = int(a0), int(a1)
            ok = (a0 == action[0] and a1 == action[1]
                  and 0 <= a0 < ACTION_NVEC[0] and 0 <= a1 < ACTION_NVEC[1])
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(
                f"invalid action {action!r}: expected [drive, steer] with each in {{0, 1, 2}}"
            )
        self._last_action = (a0, a1)
        # motor commands -1/0/+1; steer: 0 = left = +1 (counter-clockwise)
        return a0 - OFF, OFF - a1

    def _build_world(self) -> World:
        rng = self.np_random
        for _ in range(LAYOUT_ATTEMPTS):
            layout = self._generate_layout(rng, self.arena_size_m, self.arena_size_m,
                                           self.n_clutter, self.n_patches, self.patch_friction)
            world = self._new_world(layout, (0.0, 0.0, 0.0))
            pose = random_free_pose(world, rng)
            if pose is not None:
                _place(world, pose)
                return world
        raise RuntimeError("could not find a free start pose; reduce n_clutter")

    def _generate_layout(self, *args, **kwargs):
        """:func:`mkv_env.world.generate_layout`, or its compiled copy with the C kernel."""
        if self.kernel == "c":
            return _kernel.generate_layout(*args, **kwargs)
        return generate_layout(*args, **kwargs)

    def _new_world(self, layout, pose) -> World:
        return World(layout, self.robot_params, pose, robot_kernel=self._robot_kernel,
                     fast_contacts=self.kernel == "c")

    def _reset_tracker(self) -> None:
        self._tracker.reset(self._pose(), False, self.world.contacts[0])

    def _pose(self) -> tuple[float, float, float]:
        x, y, th = self.world.robot.pose()
        return (x, y, math.remainder(th, 2 * math.pi))

    def _reward(self, progress, stuck, collision, escaped) -> float:
        return (self.progress_reward * progress - self.stuck_penalty * stuck
                - self.collision_penalty * collision)

    def _terminated(self, escaped: bool) -> bool:
        return False

    def _info(self, stuck: bool, collision: bool) -> dict[str, Any]:
        t = self._tracker
        return {
            "stuck": bool(stuck),
            "bumped": any(self.world.bumps),
            "collision": bool(collision),
            "distance_m": t.distance_m,
            "jams": t.jams,
            "escapes": t.escapes,
            "collisions": t.collisions,
            "in_jam": t.in_jam,
            "pose": (t.x, t.y, t.heading),
        }


class MKVJamEnv(MKVEnv):
    """The MK-V starting jammed; the task is to get free.

    ## Description
    As ``MKV-v0`` (see :class:`MKVEnv` for the robot, sensors and arguments), but every episode
    starts with the robot physically stuck in one of four situations: against the arena wall
    (head-on or angled), in an arena corner, at the closed end of a U-shaped dead end narrower
    than its turning circle, or wedged in a gap between two cylinders narrower than itself. The
    start is made by driving the robot forward from an approach pose until it has been stuck for
    ``jam_steps`` steps, so the first observation already shows the stalled or spinning drive.

    ## Action Space / Observation Space
    As ``MKV-v0``.

    ## Rewards
    As ``MKV-v0`` plus ``escape_reward`` (default 5) on the step the robot gets free.

    ## Starting State
    A seeded layout, a scenario drawn uniformly from ``scenarios``, the robot jammed in it.
    ``env.unwrapped.scenario`` names it.

    ## Info
    As ``MKV-v0``, plus ``escaped`` (bool) and ``scenario``: the jam's code, a numpy int64 index
    into ``mkv_env.jams.SCENARIOS`` (also ``env.unwrapped.scenario_names``), 0 ``wall``,
    1 ``corner``, 2 ``dead_end``, 3 ``wedge``, whatever subset ``scenarios`` allows;
    ``mkv_env.jams.scenario_name(info["scenario"])`` gives the name. A code, not a string, so
    Gymnasium's array wrappers (``NumpyToTorch``, vector infos as int arrays) take it.

    ## Episode End
    Terminated with ``info["escaped"] = True`` once the robot is free: not stuck,
    ``escape_distance_m`` (0.3 m) from its start, clear of obstacles by 0.22 m, and driving on (the
    last ``escape_forward_m`` = 0.15 m travelled forward without a stop or reversal); truncated
    after ``max_episode_steps``
    (300 steps = 30 s by default).

    ## Arguments
    ```python
    env = gym.make("MKVJam-v0", scenarios=("dead_end", "wedge"), escape_reward=5.0)
    ```
    All ``MKV-v0`` arguments, plus ``scenarios`` (subset of ``mkv_env.jams.SCENARIOS``),
    ``escape_reward`` and ``n_clutter`` (default 10).

    ## Version History
    * v0: initial release.
    """

    _KERNEL_KIND = _kernel.KIND_JAM
    scenario_names = SCENARIOS
    """Names of the ``info["scenario"]`` codes, by code (``mkv_env.jams.SCENARIOS``)."""

    def __init__(self, scenarios=SCENARIOS, escape_reward: float = 5.0, n_clutter: int = 10,
                 **kwargs):
        _check(isinstance(scenarios, (str, tuple, list)),
               f"scenarios must be a scenario name or a list of them (a non-empty subset of "
               f"{SCENARIOS}), got {scenarios!r}")
        scenarios = tuple(scenarios) if not isinstance(scenarios, str) else (scenarios,)
        _check(len(scenarios) > 0 and set(scenarios) <= set(SCENARIOS),
               f"scenarios must be a non-empty subset of {SCENARIOS}, got {scenarios!r}")
        _check(_weight(escape_reward), "escape_reward must be a finite number with "
               f"|escape_reward| <= {REWARD_WEIGHT_MAX:g}, got {escape_reward!r}")
        super().__init__(n_clutter=n_clutter, **kwargs)
        self.scenarios = scenarios
        self.escape_reward = float(escape_reward)
        self.scenario: str | None = None  # the current jam's name; its code goes in info
        self._scenario_code = None

    def _build_world(self) -> World:
        rng = self.np_random
        W = self.arena_size_m
        # the kind is drawn once, only its geometry is retried: kinds that need more attempts
        # to jam must not come up less often
        kind = self.scenarios[int(rng.integers(len(self.scenarios)))]
        for _ in range(JAM_ATTEMPTS):
            walls, boxes, cylinders, reserved, pose = build_scenario(kind, rng, W, W)
            layout = self._generate_layout(rng, W, W, self.n_clutter, self.n_patches,
                                           self.patch_friction, reserved=reserved)
            layout.walls += [tuple(map(float, w)) for w in walls]
            layout.boxes += [tuple(map(float, b)) for b in boxes]
            layout.cylinders += [tuple(map(float, c)) for c in cylinders]
            world = self._new_world(layout, pose)
            if world.robot_overlaps():
                continue
            if _drive_until_jammed(world, self, rng):
                self.scenario, self._scenario_code = kind, scenario_code(kind)
                return world
        raise ValueError("could not build a jam scenario: the robot could not be driven into a "
                         "jam with these parameters (arena_size_m, n_clutter, robot_params: is "
                         "the drive motor too weak or the robot too large?)")

    def _reset_tracker(self) -> None:
        self._tracker.reset(self._pose(), True, self.world.contacts[0])

    def _reward(self, progress, stuck, collision, escaped) -> float:
        return super()._reward(progress, stuck, collision, escaped) + self.escape_reward * escaped

    def _terminated(self, escaped: bool) -> bool:
        return escaped

    def _info(self, stuck: bool, collision: bool) -> dict[str, Any]:
        info = super()._info(stuck, collision)
        info["escaped"] = self._tracker.escapes > 0
        info["scenario"] = self._scenario_code
        return info

    def _kernel_info(self, info: dict, cells: int, escaped: bool) -> None:
        info["escaped"] = escaped
        info["scenario"] = self._scenario_code


COVERAGE_CELL_M = 0.25
"""Side of the square floor cells whose first forward visit ``MKV-v1`` rewards [m]."""


class MKVEnvV1(MKVEnv):
    """The MK-V wandering a cluttered arena, rewarded for exploring it.

    ## Description / Action Space / Observation Space / Starting State / Episode End
    As ``MKV-v0`` (:class:`MKVEnv`): same robot, sensors, arena, seeds and time limit (600 steps).

    ## Rewards
    ``MKV-v0`` pays for forward progress, which a robot circling on the spot (or scraping along a
    wall) can farm forever. ``MKV-v1``'s maximum is the intended behaviour, wandering the whole
    arena and getting out of jams:

    * ``+coverage_reward`` (1.0) for every floor cell (``COVERAGE_CELL_M`` = 0.25 m squares)
      the robot's centre enters for the first time in the episode while driving *forward*
      (circling revisits the same few cells; reversing earns nothing);
    * ``-still_penalty`` (0.05) every step the robot moves slower than ``stuck_speed_mps``,
      whatever it commands (standing still is not the task);
    * ``-stuck_penalty`` (0.1) more while stuck (commanded to drive, not moving);
    * ``-jam_penalty`` (0.1) every step while in a jam (from ``jam_steps`` stuck steps until
      it is escaped, as ``info["in_jam"]``);
    * ``-collision_penalty`` (0.05) for each new contact with an obstacle.

    Returns on unseen seeds (100 episodes each, ``docs/rewards.md``,
    ``benchmarks/reward_table.py``): the scripted teacher is clearly best; standing still,
    circling and reversing forever clearly worst.

    ## Info
    As ``MKV-v0`` plus ``cells_visited`` (cells entered driving forward so far).

    ## Arguments
    All ``MKV-v0`` arguments except ``progress_reward`` (not used), plus ``coverage_reward``,
    ``still_penalty``, ``jam_penalty``.

    ## Version History
    * v1: reward for new ground covered driving forward, penalties while still, stuck and jammed
      (v0: forward progress, which circling farms).
    * v0: initial release.
    """

    _KERNEL_KIND = _kernel.KIND_WANDER_V1
    _COVERAGE_CELL_M = COVERAGE_CELL_M

    def __init__(self, coverage_reward: float = 1.0, still_penalty: float = 0.05,
                 jam_penalty: float = 0.1, stuck_penalty: float = 0.1,
                 collision_penalty: float = 0.05, **kwargs):
        for name, v in (("coverage_reward", coverage_reward), ("still_penalty", still_penalty),
                        ("jam_penalty", jam_penalty)):
            _check(_weight(v), f"{name} must be a finite number with |{name}| <= "
                   f"{REWARD_WEIGHT_MAX:g}, got {v!r}")
        super().__init__(stuck_penalty=stuck_penalty, collision_penalty=collision_penalty,
                         **kwargs)
        self.coverage_reward = float(coverage_reward)
        self.still_penalty, self.jam_penalty = float(still_penalty), float(jam_penalty)
        self._cells: set[tuple[int, int]] = set()

    def _reset_tracker(self) -> None:
        super()._reset_tracker()
        self._cells = set()

    def _reward(self, progress, stuck, collision, escaped) -> float:
        t = self._tracker
        new_cell = 0
        if progress > 0:
            cell = (_cell(t.x, self._slot), _cell(t.y, self._slot))
            if cell not in self._cells:
                self._cells.add(cell)
                new_cell = 1
        still = t.last_step_m < t.stuck_speed_mps * t.period_s
        return (self.coverage_reward * new_cell - self.still_penalty * still
                - self.stuck_penalty * stuck - self.jam_penalty * t.in_jam
                - self.collision_penalty * collision)

    def _info(self, stuck: bool, collision: bool) -> dict[str, Any]:
        info = super()._info(stuck, collision)
        info["cells_visited"] = len(self._cells)
        return info

    def _kernel_info(self, info: dict, cells: int, escaped: bool) -> None:
        info["cells_visited"] = cells


class MKVJamEnvV1(MKVJamEnv):
    """The MK-V starting jammed, rewarded for getting free and driving on.

    ## Description / Action Space / Observation Space / Starting State / Episode End
    As ``MKVJam-v0`` (:class:`MKVJamEnv`): same jams, seeds, escape test and time limit (300 steps);
    terminated on escape.

    ## Rewards
    ``MKVJam-v0`` charges for reversing (negative progress), so standing still is nearly optimal
    for it. ``MKVJam-v1``:

    * ``+escape_reward`` (10) on the step the robot is free (the terminal step);
    * ``-time_penalty`` (0.02) every step until then (standing still or reversing forever costs
      ``0.02 * 300 = 6`` per episode);
    * ``-stuck_penalty`` (0.05) while stuck (pushing against what holds it);
    * ``-collision_penalty`` (0.05) for each new contact;
    * potential-based shaping ``shaping * (phi' - phi)`` with ``phi = min(d / escape_distance_m,
      1)``, ``d`` the distance from where the jam began: moving away is credited, coming back
      debited, so the shaping sums to at most ``shaping`` (0.5) over an episode and cannot be
      farmed (Ng, Harada & Russell 1999: it leaves the optimal policy unchanged).

    Returns on unseen seeds (``docs/rewards.md``): the scripted teacher is clearly best; standing
    still, circling and reversing forever clearly worst.

    ## Arguments
    All ``MKVJam-v0`` arguments except ``progress_reward`` (not used), plus ``time_penalty``
    and ``shaping``.

    ## Version History
    * v1: terminal escape bonus, time penalty, potential shaping on distance from the jam
      (v0: forward progress + escape bonus, under which standing still is nearly optimal).
    * v0: initial release.
    """

    _KERNEL_KIND = _kernel.KIND_JAM_V1

    def __init__(self, escape_reward: float = 10.0, time_penalty: float = 0.02,
                 stuck_penalty: float = 0.05, collision_penalty: float = 0.05,
                 shaping: float = 0.5, **kwargs):
        for name, v in (("time_penalty", time_penalty), ("shaping", shaping)):
            _check(_weight(v), f"{name} must be a finite number with |{name}| <= "
                   f"{REWARD_WEIGHT_MAX:g}, got {v!r}")
        super().__init__(escape_reward=escape_reward, stuck_penalty=stuck_penalty,
                         collision_penalty=collision_penalty, **kwargs)
        self.time_penalty, self.shaping = float(time_penalty), float(shaping)
        self._phi = 0.0

    def _potential(self) -> float:
        t = self._tracker
        d = math.hypot(t.x - t.jam_x, t.y - t.jam_y)
        return min(d / t.escape_distance_m, 1.0)

    def _reset_tracker(self) -> None:
        super()._reset_tracker()
        self._phi = self._potential()

    def _reward(self, progress, stuck, collision, escaped) -> float:
        # the tracker has already moved on: jam_x/jam_y stay where the episode's jam began
        phi = self._potential()
        shaped = self.shaping * (phi - self._phi)
        self._phi = phi
        return (self.escape_reward * escaped - self.time_penalty - self.stuck_penalty * stuck
                - self.collision_penalty * collision + shaped)


def _cell(coordinate: float, robot: int) -> int:
    """The MKV-v1 coverage cell of a coordinate; a ValueError for a robot so far outside the
    arena that its cell leaves the kernel's 32-bit range (the compiled kernel's own check)."""
    f = coordinate / COVERAGE_CELL_M
    c = math.floor(f) if math.isfinite(f) else f
    if not abs(float(c)) < 2147483647.0:
        raise ValueError(f"robot {robot} left the arena (coverage cell out of range)")
    return c


def _drive_until_jammed(world: World, env: MKVEnv, rng,
                        max_steps: int = JAM_DRIVE_MAX_STEPS) -> bool:
    """Drive forward (steering held at a random command) until stuck for jam_steps steps."""
    steer = int(rng.integers(-1, 2))
    limit = env._tracker.stuck_speed_mps * env.control_period_s
    if env.kernel == "c":  # the same loop compiled (mkv_env/_native/)
        robot = world.robot
        _, body, space = robot.pointers(world.space)
        jammed, mu_scale = _robot._fastsim.drive_until_jammed(
            robot.kernel_constants, body, space, robot.state, robot.floor_friction_scale,
            world.layout.patches, steer, env.control_period_s / env.substeps, env.substeps,
            limit, env._tracker.jam_steps, max_steps, world.contacts)
        robot.set_floor_friction_scale(mu_scale)
        return jammed
    run = 0
    x0, y0 = world.robot.body.position
    for _ in range(max_steps):
        world.step(1, steer, env.control_period_s, env.substeps)
        x, y = world.robot.body.position
        run = run + 1 if math.hypot(x - x0, y - y0) < limit else 0
        x0, y0 = x, y
        if run >= env._tracker.jam_steps:
            return world.in_contact
    return False


def _place(world: World, pose) -> None:
    body = world.robot.body
    body.position = pose[:2]
    body.angle = pose[2]
    world.space.reindex_shapes_for_body(body)


#: The step-time methods whose code the compiled kernel carries for the four MK-V classes; a
#: subclass that overrides one of them is stepped by its own Python (kernel "python").
_KERNEL_METHODS = ("step", "_step_raw", "_after_physics", "_reward", "_terminated", "_info",
                   "_kernel_info", "_potential", "_pose", "_decode")


def _python_overrides(cls) -> list[str]:
    """The step-time methods ``cls`` defines differently from the MK-V class it derives from
    (empty for the four registered classes and for subclasses that only change arguments)."""
    base = next((c for c in cls.__mro__ if c in _KERNEL_CLASSES), None)
    if base is None:
        return list(_KERNEL_METHODS)
    return [m for m in _KERNEL_METHODS if getattr(cls, m, None) is not getattr(base, m, None)]


def _num(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) \
        and math.isfinite(v)


#: The largest magnitude of a reward weight (:data:`mkv_env.kernel.REWARD_WEIGHT_MAX`).
REWARD_WEIGHT_MAX = _kernel.REWARD_WEIGHT_MAX


def _weight(v) -> bool:
    return _num(v) and abs(v) <= REWARD_WEIGHT_MAX


def _int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


#: The classes whose step the compiled kernel implements (their _KERNEL_KIND).
_KERNEL_CLASSES = (MKVEnv, MKVJamEnv, MKVEnvV1, MKVJamEnvV1)
