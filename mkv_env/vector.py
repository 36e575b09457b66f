"""A native vector env: N MK-V robots stepped in one process, their physics in one C call.

``gym.make_vec("MKV-v0", num_envs=16, vectorization_mode="vector_entry_point")`` (and the same
for every MK-V id) returns an :class:`MKVVectorEnv`. It holds N ordinary single envs of the id's
class and, each step, moves all N robots with one call into the compiled substep loop
(:func:`mkv_env._fastsim.advance_many`) before each env reads its sensors and scores the step
exactly as :meth:`mkv_env.envs.MKVEnv.step` does. Because the same code runs per robot, env ``i``
of a vector env reset with ``seed`` follows the same trajectory, bit for bit, as a single env
reset with ``seed + i`` and given the same actions (``tests/mkv_env/test_vector.py``).

Semantics are Gymnasium 1.x's (those of ``SyncVectorEnv`` over ``gymnasium.make(id)``):

* ``reset(seed=s)`` seeds env i with ``s + i`` (a list gives one seed per env);
  ``options={"reset_mask": mask}`` resets only the masked envs;
* ``autoreset_mode`` (``metadata["autoreset_mode"]``) is ``NEXT_STEP`` by default: the step after
  an episode ends resets that env (its action is ignored; reward 0, not done). ``SAME_STEP``
  (reset at once, ``info["final_obs"]``/``info["final_info"]``) and ``DISABLED`` are accepted as
  the ``autoreset_mode`` keyword;
* truncation after ``max_episode_steps`` (the registration's limit, as ``TimeLimit`` does);
* infos are dicts of arrays with ``_key`` masks; ``info["pose"]`` is a float array (n, 3).

For Stable-Baselines3, wrap it with :class:`mkv_env.sb3_vec.SB3VecEnv`.
"""

from __future__ import annotations

import operator
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from mkv_env import robot as _robot
from mkv_env.actions import ACTION_NVEC, OFF
from mkv_env.envs import MKVEnv, MKVEnvV1, MKVJamEnv, MKVJamEnvV1

_MODES = {m.value: m for m in AutoresetMode}
_NVEC = np.array(ACTION_NVEC)


class MKVVectorEnv(VectorEnv):
    """``num_envs`` MK-V envs of class ``env_cls`` (built with ``**kwargs``), stepped together.

    Args:
        num_envs: number of robots (>= 1).
        env_cls: :class:`~mkv_env.envs.MKVEnv` or a subclass (the registered ids pick theirs).
        max_episode_steps: truncation limit (None: never truncate).
        autoreset_mode: ``"NextStep"`` (default), ``"SameStep"`` or ``"Disabled"`` (or the
            :class:`gymnasium.vector.AutoresetMode` members).
        **kwargs: the single env's arguments (``gym.make(id, **kwargs)``).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"]}

    def __init__(self, num_envs: int, env_cls: type = MKVEnv,
                 max_episode_steps: int | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, **kwargs):
        if not (isinstance(num_envs, (int, np.integer)) and not isinstance(num_envs, bool)
                and num_envs >= 1):
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if max_episode_steps is not None and not (
                isinstance(max_episode_steps, (int, np.integer)) and max_episode_steps >= 1):
            raise ValueError(f"max_episode_steps must be a positive integer or None, "
                             f"got {max_episode_steps!r}")
        mode = _MODES.get(autoreset_mode, autoreset_mode)
        if not isinstance(mode, AutoresetMode):
            raise ValueError(f"autoreset_mode must be one of {sorted(_MODES)}, "
                             f"got {autoreset_mode!r}")
        if kwargs.get("render_mode") not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be 'rgb_array' or None for a vector env, "
                             f"got {kwargs['render_mode']!r}")
        self.num_envs = int(num_envs)
        self.envs: list[MKVEnv] = [env_cls(**kwargs) for _ in range(self.num_envs)]
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self.autoreset_mode = mode
        self.metadata = {**self.metadata, "render_fps": env_cls.metadata.get("render_fps", 10),
                         "autoreset_mode": mode}
        self.render_mode = kwargs.get("render_mode")
        first = self.envs[0]
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.sensor_names = list(first.sensor_names)
        n = self.num_envs
        self._obs = np.zeros((n, len(self.sensor_names)), dtype=np.float32)
        self._elapsed = np.zeros(n, dtype=np.int64)
        self._autoreset = np.zeros(n, dtype=bool)
        self._started = False
        self._slot_cache: tuple | None = None
        #: The per-env info dicts of the last reset/step (None where an env did not report), and
        #: in SameStep mode the final infos of the envs that ended; SB3VecEnv reads these.
        self.env_infos: list[dict | None] = [None] * self.num_envs
        self.final_env_infos: list[dict | None] = [None] * self.num_envs
        self.vector_infos = True  # False: skip building Gymnasium's vector info (SB3VecEnv)
        self._period, self._substeps = first.control_period_s, first.substeps
        self._dt = self._period / self._substeps

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: int | list | None = None, options: dict | None = None):
        n = self.num_envs
        if seed is None:
            seeds = [None] * n
        elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            seeds = [int(seed) + i for i in range(n)]
        else:
            seeds = list(seed)
            if len(seeds) != n:
                raise ValueError(f"seed must be None, an int or a list of {n} seeds, "
                                 f"got {len(seeds)} seeds")
        options = dict(options) if options else None
        mask = np.ones(n, dtype=bool)
        if options is not None and "reset_mask" in options:
            mask = options.pop("reset_mask")
            if not (isinstance(mask, np.ndarray) and mask.dtype == np.bool_
                    and mask.shape == (n,) and mask.any()):
                raise ValueError(f"options['reset_mask'] must be a bool array of shape ({n},) "
                                 "with at least one True")
        infos: list[dict | None] = [None] * n
        for i in np.flatnonzero(mask):
            self._obs[i], infos[i] = self.envs[i].reset(seed=seeds[i], options=options)
            self._elapsed[i] = 0
            self._autoreset[i] = False
        self._started = True
        self.env_infos = infos
        return self._obs.copy(), self._gather(infos)

    def step(self, actions):
        if not self._started:
            raise gym.error.ResetNeeded("call reset() before step()")
        n = self.num_envs
        drive, steer = self._commands(actions)
        rewards = np.zeros(n, dtype=np.float64)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        infos: list[dict | None] = [None] * n
        resetting = self._autoreset if self.autoreset_mode == AutoresetMode.NEXT_STEP else None
        if self.autoreset_mode == AutoresetMode.DISABLED and self._autoreset.any():
            raise gym.error.ResetNeeded(
                f"envs {np.flatnonzero(self._autoreset).tolist()} have ended: with "
                "autoreset_mode Disabled, reset them (options={'reset_mask': ...}) first")
        active = np.flatnonzero(~resetting) if resetting is not None else np.arange(n)
        self._move(active, drive, steer)
        limit = self.max_episode_steps
        elapsed = self._elapsed
        obs_rows, rew, term = [], [], []
        for i, d, s in zip(active.tolist(), drive[active].tolist(), steer[active].tolist(),
                           strict=True):
            env = self.envs[i]
            env._last_action = (d + OFF, OFF - s)
            o, r, te, _, infos[i] = env._after_physics(d)
            obs_rows.append(o)
            rew.append(r)
            term.append(te)
        if len(active):
            self._obs[active] = obs_rows
            rewards[active] = rew
            terminated[active] = term
            elapsed[active] += 1
            if limit is not None:
                truncated[active] = elapsed[active] >= limit
        extra: dict[str, Any] = {}
        final: list[dict | None] = [None] * n
        if resetting is not None:
            for i in np.flatnonzero(resetting):
                self._obs[i], infos[i] = self.envs[i].reset()
                self._elapsed[i] = 0
        elif self.autoreset_mode == AutoresetMode.SAME_STEP:
            done = np.flatnonzero(terminated | truncated)
            if len(done):
                final_obs = np.full(n, None, dtype=object)
                for i in done:
                    final_obs[i], final[i] = self._obs[i].copy(), infos[i]
                    self._obs[i], infos[i] = self.envs[i].reset()
                    self._elapsed[i] = 0
                mask = np.zeros(n, dtype=bool)
                mask[done] = True
                extra = {"final_obs": final_obs, "_final_obs": mask,
                         "final_info": self._gather(final) if self.vector_infos else {},
                         "_final_info": mask.copy()}
        self._autoreset = terminated | truncated
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            self._autoreset[:] = False
        self.env_infos, self.final_env_infos = infos, final
        info = self._gather(infos) if self.vector_infos else {}
        info.update(extra)
        return self._obs.copy(), rewards, terminated, truncated, info

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode= to "
                            "make_vec()")
            return None
        return tuple(env.render() for env in self.envs)

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Call method ``name`` of every env (or read attribute ``name``), as SyncVectorEnv."""
        out = []
        for env in self.envs:
            f = getattr(env, name)
            out.append(f(*args, **kwargs) if callable(f) else f)
        return tuple(out)

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Attribute ``name`` of every env."""
        return tuple(getattr(env, name) for env in self.envs)

    def set_attr(self, name: str, values: Any) -> None:
        """Set attribute ``name`` of every env: one value for all, or a list/tuple of num_envs."""
        if not isinstance(values, (list, tuple)):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(f"set_attr needs one value or {self.num_envs} values, "
                             f"got {len(values)}")
        for env, v in zip(self.envs, values, strict=True):
            setattr(env, name, v)

    def close_extras(self, **kwargs):
        for env in self.envs:
            env.close()

    # ------------------------------------------------------------------ pieces
    def _commands(self, actions) -> tuple[np.ndarray, np.ndarray]:
        """Validated actions (n, 2) -> drive and steer motor commands (-1/0/+1 each)."""
        a = np.asarray(actions)
        if a.shape == (self.num_envs, 2) and a.dtype.kind in "iubf":
            with np.errstate(invalid="ignore"):
                ai = a.astype(np.int64)  # floats must be whole numbers
            if (ai == a).all() and (ai >= 0).all() and (ai < _NVEC).all():
                return ai[:, 0] - OFF, OFF - ai[:, 1]
        raise ValueError(f"invalid actions {actions!r}: expected shape ({self.num_envs}, 2) "
                         "of [drive, steer] with each in {0, 1, 2}")

    def _move(self, idx: np.ndarray, drive: np.ndarray, steer: np.ndarray) -> None:
        """One control period of physics for the envs ``idx``, in one C call when possible."""
        if len(idx) == 0:
            return
        slots = self._slots()
        if len(idx) == self.num_envs:
            robots, worlds, bodies, spaces, states = slots
            drives, steers = drive.tolist(), steer.tolist()
        else:
            pick = idx.tolist()
            robots, worlds, bodies, spaces, states = ([col[i] for i in pick] for col in slots)
            drives, steers = drive[idx].tolist(), steer[idx].tolist()
        for w in worlds:
            if w.layout.patches:
                w.robot.set_floor_friction_scale(w.floor_friction_scale())
        fast = _robot._fastsim
        if fast is not None and bodies is not None and not any(
                w.space._bodies_to_check for w in worlds):
            fast.advance_many(robots[0].kernel_constants, bodies, spaces, drives, steers,
                              self._dt, self._substeps, [r._mu_scale for r in robots], states)
        else:  # pure-Python build (or kernel switched off): the same loop, one robot at a time
            for r, w, d, s in zip(robots, worlds, drives, steers, strict=False):
                r.advance(d, s, self._dt, self._substeps, w.space)

    def _slots(self) -> tuple:
        """(robots, worlds, body addresses, space addresses, wheel states) of every env, cached
        until an env gets a new world (a reset). Addresses are None when the compiled loop cannot
        serve every robot."""
        worlds = [env.world for env in self.envs]
        cache = self._slot_cache
        if cache is None or not all(map(operator.is_, worlds, cache[1])):
            robots = [w.robot for w in worlds]
            bodies = spaces = None
            if _robot._fastsim is not None and all(r.kernel == "c" for r in robots):
                ptrs = [r.pointers(w.space) for r, w in zip(robots, worlds, strict=False)]
                bodies, spaces = [p[1] for p in ptrs], [p[2] for p in ptrs]
            cache = self._slot_cache = (robots, worlds, bodies, spaces,
                                        [r.state for r in robots])
        return cache

    def _gather(self, infos: list[dict | None]) -> dict[str, Any]:
        """Per-env info dicts -> Gymnasium's vector info (arrays plus ``_key`` masks)."""
        n = self.num_envs
        present = [i for i, d in enumerate(infos) if d is not None]
        out: dict[str, Any] = {}
        if not present:
            return out
        keys = list(infos[present[0]])
        full = len(present) == n
        mask = np.zeros(n, dtype=bool)
        mask[present] = True
        # one pass over the dicts: every env of a class reports the same keys in the same order
        rows = [infos[i] for i in present]
        if all(list(d) == keys for d in rows):
            columns = list(zip(*(d.values() for d in rows), strict=True))
        else:
            columns = [[d[k] for d in rows] for k in keys]
        for k, vals in zip(keys, columns, strict=True):
            v0 = vals[0]
            if isinstance(v0, tuple):
                arr = np.zeros((n, len(v0)), dtype=np.float64)
            elif type(v0) in (int, float, bool) or isinstance(v0, np.number):
                arr = np.zeros(n, dtype=type(v0))
            else:
                arr = np.full(n, None, dtype=object)
            if full and arr.dtype != object:
                arr[:] = vals
            else:
                for i, v in zip(present, vals, strict=True):
                    arr[i] = v
            out[k] = arr
            out[f"_{k}"] = mask.copy()
        return out


def _creator(env_cls):
    def make(num_envs: int = 1, **kwargs) -> MKVVectorEnv:
        return MKVVectorEnv(num_envs, env_cls, **kwargs)

    make.__name__ = f"make_{env_cls.__name__}_vector"
    make.__doc__ = f"Vector entry point of the {env_cls.__name__} ids (see MKVVectorEnv)."
    return make


#: Vector entry points, one per registered id (``mkv_env/__init__.py``).
wander_v0 = _creator(MKVEnv)
jam_v0 = _creator(MKVJamEnv)
wander_v1 = _creator(MKVEnvV1)
jam_v1 = _creator(MKVJamEnvV1)
