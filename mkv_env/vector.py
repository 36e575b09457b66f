"""A native vector env: N MK-V robots stepped in one process by one call into the step kernel.

``gym.make_vec("MKV-v0", num_envs=16, vectorization_mode="vector_entry_point")`` (and the same
for every MK-V id) returns an :class:`MKVVectorEnv`. It holds N ordinary single envs of the id's
class (they build and reset the worlds) and one compiled step kernel with N slots
(:mod:`mkv_env.kernel`): each step is one C call that moves every robot, reads its sensors,
tracks it and scores it, writing observations, rewards, flags and the info numbers straight into
preallocated arrays, with the GIL released and, with ``num_threads=K``, on K threads (each with
a home group of robots, taking the others' unclaimed robots when done; results do not depend on
K). A second C call (``Batch.collect``) turns those buffers into the step's fresh result arrays,
truncation, autoreset flags and Gymnasium's info dict. The envs of ``MKV-v0`` and ``MKV-v1``
that ended are reset inside the kernel call too, on the worker threads (their new worlds are
built in C and handed to pymunk only when Python asks for ``env.world``:
:func:`mkv_env.kernel.adopt_world`); those of the jam ids are reset by Python, while the worker
threads step the others. Env ``i`` of a vector env reset with ``seed``
follows the same trajectory, bit for bit, as a single env reset with ``seed + i`` and given the
same actions (``tests/mkv_env/test_vector.py``); ``kernel="python"`` runs the reference
implementation (each robot's step in Python) instead.

Semantics are Gymnasium 1.x's (those of ``SyncVectorEnv`` over ``gymnasium.make(id)``):

* ``reset(seed=s)`` seeds env i with ``s + i`` (a list gives one seed per env);
  ``options={"reset_mask": mask}`` resets only the masked envs;
* ``autoreset_mode`` (``metadata["autoreset_mode"]``) is ``NEXT_STEP`` by default: the step after
  an episode ends resets that env (its action is ignored; reward 0, not done). ``SAME_STEP``
  (reset at once, ``info["final_obs"]``/``info["final_info"]``) and ``DISABLED`` are accepted as
  the ``autoreset_mode`` keyword;
* truncation after ``max_episode_steps`` (the registration's limit, as ``TimeLimit`` does);
* infos are dicts of arrays with ``_key`` masks; ``info["pose"]`` is a float array (n, 3)
  (``vector_infos=False`` skips them); the per-env dicts are built only when read
  (:attr:`MKVVectorEnv.env_infos`). The jam ids' ``info["scenario"]`` is an int64 array of
  scenario codes (as SyncVectorEnv batches the single envs' numpy ints), named by
  :func:`mkv_env.jams.scenario_name` or ``scenario_names``.

For Stable-Baselines3, wrap it with :class:`mkv_env.sb3_vec.SB3VecEnv`.
"""

from __future__ import annotations

import functools
import operator
import threading
from itertools import chain
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from mkv_env import kernel as _kernel
from mkv_env.actions import ACTION_NVEC, OFF
from mkv_env.envs import TRAIL_DROP_POINTS as _TRAIL_DROP
from mkv_env.envs import TRAIL_MAX_POINTS as _TRAIL_MAX
from mkv_env.envs import MKVEnv, MKVEnvV1, MKVJamEnv, MKVJamEnvV1
from mkv_env.jams import SCENARIO_DTYPE as _SCENARIO_DTYPE

#: The most robots one vector env holds. Above it the constructor refuses in one line.
MAX_ENVS = 65_536

#: Resident memory one robot of a vector env takes (bytes), rounded up from the most measured:
#: 365 KiB (MKV-v1) and 427 KiB (MKVJam-v1) per env at 4,096 envs, ``benchmarks/env_scaling.py``
#: (ten 32 KiB buffers of each robot's Chipmunk space make 320 KiB of it). The constructor refuses
#: in one line where ``num_envs`` of them exceed the memory the machine has available, instead of
#: allocating until it runs out.
ENV_BYTES = 448 * 1024


def _available_bytes() -> int | None:
    """The machine's available memory (``MemAvailable`` of /proc/meminfo), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None

_MODES = {m.value: m for m in AutoresetMode}


def _check_memory(num_envs: int) -> None:
    """Refuse, in one line, ``num_envs`` robots whose memory exceeds what the machine has."""
    avail = _available_bytes()
    if avail is not None and num_envs * ENV_BYTES > avail:
        raise ValueError(f"num_envs={num_envs:,} needs about {num_envs * ENV_BYTES / 2**30:.3g} "
                         f"GiB ({ENV_BYTES // 1024} KiB per robot); this machine has "
                         f"{avail / 2**30:.3g} GiB available")


def _one_thread(method):
    """Refuse a second thread while one is inside this vector env (its kernel state and buffers
    are not shared-safe: two threads stepping one vector env corrupted the heap). A clear
    ``RuntimeError`` instead; the same thread may re-enter (an RLock)."""

    @functools.wraps(method)
    def guarded(self, *args, **kwargs):
        busy = self.__dict__.get("_busy")
        if busy is None:
            busy = self.__dict__.setdefault("_busy", threading.RLock())
        if not busy.acquire(blocking=False):
            raise RuntimeError(f"{type(self).__name__}.{method.__name__}: another thread is "
                               "using this vector env; one vector env serves one thread at a "
                               "time (give each thread its own)")
        try:
            return method(self, *args, **kwargs)
        finally:
            busy.release()

    return guarded
_VALID = frozenset(range(ACTION_NVEC[0]))  # values of an action's entries (both take 0, 1, 2)


class MKVVectorEnv(VectorEnv):
    """``num_envs`` MK-V envs of class ``env_cls`` (built with ``**kwargs``), stepped together.

    Args:
        num_envs: number of robots (>= 1).
        env_cls: :class:`~mkv_env.envs.MKVEnv` or a subclass (the registered ids pick theirs).
        max_episode_steps: truncation limit (None: never truncate).
        autoreset_mode: ``"NextStep"`` (default), ``"SameStep"`` or ``"Disabled"`` (or the
            :class:`gymnasium.vector.AutoresetMode` members).
        vector_infos: False skips building Gymnasium's vector info: ``step`` and ``reset``
            return ``{}`` (plus ``final_obs`` in SameStep mode); the per-env dicts stay readable
            as :attr:`env_infos`.
        num_threads: threads stepping the robots (compiled kernel only; default 1). Each thread
            steps a fixed group of robots with the GIL released; results do not depend on it.
        **kwargs: the single env's arguments (``gym.make(id, **kwargs)``), ``kernel`` included.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"]}

    def __init__(self, num_envs: int, env_cls: type = MKVEnv,
                 max_episode_steps: int | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
                 vector_infos: bool = True, num_threads: int = 1, **kwargs):
        if not (isinstance(num_envs, (int, np.integer)) and not isinstance(num_envs, bool)
                and 1 <= num_envs <= MAX_ENVS):
            raise ValueError(f"num_envs must be an integer in 1..{MAX_ENVS}, got {num_envs!r}")
        _check_memory(int(num_envs))
        if max_episode_steps is not None and not (
                isinstance(max_episode_steps, (int, np.integer)) and max_episode_steps >= 1):
            raise ValueError(f"max_episode_steps must be a positive integer or None, "
                             f"got {max_episode_steps!r}")
        mode = _MODES.get(autoreset_mode, autoreset_mode)
        if not isinstance(mode, AutoresetMode):
            raise ValueError(f"autoreset_mode must be one of {sorted(_MODES)}, "
                             f"got {autoreset_mode!r}")
        if not isinstance(vector_infos, (bool, np.bool_)):
            raise ValueError(f"vector_infos must be True or False, got {vector_infos!r}")
        if not (isinstance(num_threads, (int, np.integer)) and not isinstance(num_threads, bool)
                and 1 <= num_threads <= 256):
            raise ValueError(f"num_threads must be an integer in [1, 256], got {num_threads!r}")
        if kwargs.get("render_mode") not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be 'rgb_array' or None for a vector env, "
                             f"got {kwargs['render_mode']!r}")
        if kwargs.get("observation", "raw") != "raw":
            raise ValueError(f"observation={kwargs['observation']!r} is an option of single envs; "
                             "the native vector env gives raw readings: use "
                             "gym.make_vec(..., vectorization_mode='sync') or rescale the batch")
        _check_env_cls(env_cls)
        self.num_envs = int(num_envs)
        self.envs: list[MKVEnv] = [env_cls(**kwargs) for _ in range(self.num_envs)]
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self.autoreset_mode = mode
        self.metadata = {**self.metadata, "render_fps": env_cls.metadata.get("render_fps", 10),
                         "autoreset_mode": mode}
        self.render_mode = kwargs.get("render_mode")
        first = self.envs[0]
        self.kernel = first.kernel
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.sensor_names = list(first.sensor_names)
        if hasattr(first, "scenario_names"):  # the jam ids: names of the info["scenario"] codes
            self.scenario_names = first.scenario_names
        n = self.num_envs
        self._obs = np.zeros((n, len(self.sensor_names)), dtype=np.float32)
        self._elapsed = np.zeros(n, dtype=np.int64)
        self._autoreset = np.zeros(n, dtype=bool)
        self._ever_reset = np.zeros(n, dtype=bool)  # (a partial reset_mask must not skip one)
        self._everyone = list(range(n))
        self._started = False
        self._env_infos: list[dict | None] = [None] * n
        self._final_env_infos: list[dict | None] = [None] * n
        self._lazy_infos: tuple | None = None  # (arrays, rows) to build env_infos from
        self._lazy_final: tuple | None = None
        self._true_rows: np.ndarray | None = None  # all-True info-mask template (copied per step)
        self.vector_infos = bool(vector_infos)  # False: skip Gymnasium's vector info (SB3VecEnv)
        self._period, self._substeps = first.control_period_s, first.substeps
        self.num_threads = 1
        self._batch = None
        self._collect = None
        self._fast = None  # Batch.vstep where it serves (below)
        self._pending = True
        for i, env in enumerate(self.envs):  # (env i is robot i, in the kernel's slot i)
            env._slot = i
        if self.kernel != "c" and num_threads != 1:
            raise ValueError("num_threads > 1 needs the compiled step kernel (kernel='c'); the "
                             "Python reference steps its robots one by one")
        if self.kernel == "c":  # one kernel for every robot: env i is its slot i
            self._batch, self._out = _kernel.new_batch(first, n, int(num_threads))
            self.num_threads = self._batch.num_threads
            self._dirty: list = []
            for i, env in enumerate(self.envs):
                env._batch, env._out, env._slot, env._dirty = self._batch, self._out, i, self._dirty
            self._obs = self._out["obs"]
            self._kind = env_cls._KERNEL_KIND
            # the per-step bookkeeping, compiled (Batch.collect)
            self._collect = self._batch.collect
            names = list(_INFO_COLUMNS)
            if self._kind == _kernel.KIND_WANDER_V1:
                names.append("cells_visited")
            elif self._kind != _kernel.KIND_WANDER:
                names.append("escaped")
            index = {name: k for k, (name, _, _) in enumerate(_kernel.OUTPUTS)}
            self._col_spec = tuple((k, _MASK_KEY[k], index[k]) for k in names)
            self._max_steps = -1 if self.max_episode_steps is None else self.max_episode_steps
            self._has_scenario = hasattr(first, "scenario")
            # the envs' scenario codes (numpy ints, as their info: SyncVectorEnv's int array)
            self._scenarios = np.zeros(n, dtype=_SCENARIO_DTYPE)
            self._active = np.ones(n, dtype=bool)
            self._idle = np.zeros(n, dtype=bool)
            # autoresets in C (MKV-v0, MKV-v1 without rendering): see kernel.setup_resets
            self._c_reset = (env_cls in (MKVEnv, MKVEnvV1)
                             and _kernel.setup_resets(first, self._batch))
            # the whole NEXT_STEP step in one call (Batch.vstep) where nothing needs Python
            self._fast = (self._batch.vstep
                          if self._c_reset and mode == AutoresetMode.NEXT_STEP else None)

    def __reduce_ex__(self, protocol):
        """Pickling and ``copy.deepcopy`` of a compiled-kernel vector env are refused in one line:
        its robots live in one compiled batch (C state, worker threads) that has no snapshot.
        Its single envs (``.envs[i]``) snapshot exactly; a Python-kernel one pickles as usual."""
        if self._batch is not None:
            raise TypeError("a native vector env (MKVVectorEnv, kernel='c') cannot be pickled or "
                            "copied: its robots live in one compiled batch; snapshot its single "
                            "envs (.envs[i]: exact) or rebuild it with make_vec and the same seeds")
        return super().__reduce_ex__(protocol)

    # ------------------------------------------------------------------ per-env info dicts
    @property
    def env_infos(self) -> list[dict | None]:
        """The per-env info dicts of the last reset/step (None where an env did not report);
        built on first read from the step's arrays."""
        if self._lazy_infos is not None:
            self._env_infos = self._dicts(*self._lazy_infos)
            self._lazy_infos = None
        return self._env_infos

    @env_infos.setter
    def env_infos(self, value) -> None:
        self._env_infos, self._lazy_infos = value, None

    @property
    def final_env_infos(self) -> list[dict | None]:
        """In SameStep mode, the final info dicts of the envs whose episode ended this step."""
        if self._lazy_final is not None:
            self._final_env_infos = self._dicts(*self._lazy_final)
            self._lazy_final = None
        return self._final_env_infos

    @final_env_infos.setter
    def final_env_infos(self, value) -> None:
        self._final_env_infos, self._lazy_final = value, None

    def _dicts(self, cols: dict, rows) -> list[dict | None]:
        """Per-env dicts from info columns (the rows that reported; None elsewhere)."""
        out: list[dict | None] = [None] * self.num_envs
        values = {k: (v.tolist() if v.dtype != object and k not in _NUMPY_SCALAR_KEYS
                      else list(v)) for k, v in cols.items()}
        for i in rows:
            d = {k: values[k][i] for k in cols}
            d["pose"] = tuple(d["pose"])
            out[i] = d
        return out

    @property
    def np_random_seed(self) -> tuple:
        """The seeds of the envs' generators (as ``SyncVectorEnv``)."""
        return tuple(env.np_random_seed for env in self.envs)

    @property
    def np_random(self) -> tuple:
        """The envs' generators (as ``SyncVectorEnv``)."""
        return tuple(env.np_random for env in self.envs)

    # ------------------------------------------------------------------ Gymnasium API
    @_one_thread
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
            if not isinstance(mask, np.ndarray):
                raise TypeError(f"options['reset_mask'] must be a numpy array, got {type(mask)}")
            if mask.shape != (n,):
                raise ValueError(f"options['reset_mask'] must have shape ({n},), "
                                 f"got {mask.shape}")
            if mask.dtype != np.bool_:
                raise TypeError(f"options['reset_mask'] must have dtype bool, got {mask.dtype}")
            if not mask.any():
                raise ValueError("options['reset_mask'] must have at least one True")
            options = options or None
        infos: list[dict | None] = [None] * n
        for i in np.flatnonzero(mask):
            self._obs[i], infos[i] = self.envs[i].reset(seed=seeds[i], options=options)
            self._elapsed[i] = 0
            self._autoreset[i] = False
            if self._batch is not None and self._has_scenario:
                self._scenarios[i] = self.envs[i]._scenario_code
        self._ever_reset |= mask
        self._started = bool(self._ever_reset.all())  # (partial masks: once all have been reset)
        self.env_infos = infos
        return self._obs.copy(), self._gather(infos) if self.vector_infos else {}

    @_one_thread
    def step(self, actions):
        if isinstance(actions, np.ma.MaskedArray):  # its masked entries would be stepped as is
            raise TypeError("actions must be a plain array, not a masked array (np.ma): its "
                            "masked entries would be stepped with whatever values they hold")
        if self._fast is not None and self._started and not self._dirty:
            out = self._step_fast(actions)  # the common case: the whole step in one call
            if out is not None:
                return out
        if not self._started:
            never = np.flatnonzero(~self._ever_reset)
            raise gym.error.ResetNeeded(
                "call reset() before step()" if len(never) == self.num_envs else
                f"env(s) {never[:5].tolist()} were never reset (a partial reset_mask): reset "
                "them before step()")
        if self.autoreset_mode == AutoresetMode.DISABLED and np.count_nonzero(self._autoreset):
            raise gym.error.ResetNeeded(
                f"envs {np.flatnonzero(self._autoreset).tolist()} have ended: with "
                "autoreset_mode Disabled, reset them (options={'reset_mask': ...}) first")
        if self._batch is not None:
            return self._step_kernel(actions)
        return self._step_reference(actions)

    def _step_kernel(self, actions):
        """One step of every robot through the compiled kernel (see the module doc)."""
        self._pending = True
        n = self.num_envs
        acts = self._actions(actions)
        mode = self.autoreset_mode
        # (count_nonzero: ndarray.any costs several times more on a few robots)
        resetting = mode == AutoresetMode.NEXT_STEP and np.count_nonzero(self._autoreset) > 0
        b, envs = self._batch, self.envs
        c_idx, c_mask = (), None
        if resetting:
            active = np.logical_not(self._autoreset, out=self._active)
            reset_idx = np.flatnonzero(self._autoreset).tolist()
            if self._c_reset:  # reset in the kernel call (the others by Python, below)
                c_idx, c_mask, reset_idx = self._c_resets(reset_idx)
        else:
            active, reset_idx = None, ()
        if self._dirty:  # Python code took some envs' state back: hand it to the kernel again
            for env in self._dirty:
                if env._py_owns and env.world is not None:
                    env._push()
            self._dirty.clear()
        # With worker threads, the envs ending last step are reset while the workers step the
        # others (their slots are not stepped this step: nothing is shared).
        overlap = bool(reset_idx) and self.num_threads > 1
        run = b.step_start if overlap else b.step
        extra = () if c_mask is None else (c_mask,)
        try:
            need = run(acts, active, *extra)
        except ValueError as e:  # the kernel checks the values before it steps anything
            raise self._bad_actions(actions, e) from None
        while need is not None:  # robots that used up their noise block and have no generator
            for i in need:       # of their own: Python draws the next, as the reference does
                b.set_noise(i, envs[i]._sensors.draw_block())
            need = run(acts, active, *extra)
        self._reset_in_c(c_idx)
        early = []
        if overlap:
            try:
                for i in reset_idx:
                    early.append((i, *envs[i].reset()))
            finally:
                b.step_finish()
            reset_idx = ()
        want = self.vector_infos
        # the step's arrays, elapsed steps, truncation, autoreset flags and info, compiled
        obs, rewards, terminated, truncated, cols, vinfo = self._collect(
            self._elapsed, self._max_steps, active,
            None if mode == AutoresetMode.SAME_STEP else self._autoreset, self._col_spec, want)
        elapsed = self._elapsed
        if self._has_scenario:
            cols["scenario"] = scen = self._scenarios.copy()
            if want:
                vinfo["scenario"], vinfo["_scenario"] = scen, np.ones(n, dtype=bool)
        if self.render_mode is not None:
            self._trails(active)
        info: dict[str, Any] = {}
        for i in c_idx:
            elapsed[i] = 0
        for i, o, d in early:
            obs[i] = o
            elapsed[i] = 0
            self._put(cols, i, d)
        for i in reset_idx:
            obs[i], d = envs[i].reset()
            elapsed[i] = 0
            self._put(cols, i, d)
        final_lazy = None
        if mode == AutoresetMode.SAME_STEP:
            info, final_lazy = self._same_step_resets(acts, obs, cols, terminated | truncated)
            self._autoreset[:] = False  # (otherwise collect has set the flags in place)
        if want:
            info = {**vinfo, **info} if info else vinfo
        self._lazy_infos = (cols, self._everyone)  # per-env dicts only if someone reads them
        self._lazy_final = final_lazy
        if final_lazy is None:
            self._final_env_infos = [None] * n
        return obs, rewards, terminated, truncated, info

    def _same_step_resets(self, acts, obs, cols, ended):
        """SameStep mode: the envs whose episode ended this step reset at once (in C where the
        kernel can, else by Python), their final observations and infos kept. Returns (the
        step's final-info entries, the lazy final per-env infos or None)."""
        n, b, out, envs, elapsed = self.num_envs, self._batch, self._out, self.envs, self._elapsed
        done = np.flatnonzero(ended)
        if not len(done):
            return {}, None
        final_obs = np.full(n, None, dtype=object)
        final_cols = {k: v.copy() for k, v in cols.items()}
        for i in done:
            final_obs[i] = obs[i].copy()
        c_idx, c_mask, py_idx = (self._c_resets(done.tolist()) if self._c_reset
                                 else ((), None, done))
        if c_idx:  # one more kernel call: these envs reset in C, on the threads
            need = b.step(acts, self._idle, c_mask)
            assert need is None  # (no robot is stepped)
            obs[c_idx] = out["obs"][c_idx]
            for name, _, k in self._col_spec:
                cols[name][c_idx] = out[_kernel.OUTPUTS[k][0]][c_idx]
            self._reset_in_c(c_idx)
            elapsed[c_idx] = 0
        for i in py_idx:
            obs[i], d = envs[i].reset()
            elapsed[i] = 0
            self._put(cols, i, d)
        mask = np.zeros(n, dtype=bool)
        mask[done] = True
        info = {"final_obs": final_obs, "_final_obs": mask,
                "final_info": self._vector_info(final_cols, mask) if self.vector_infos else {},
                "_final_info": mask.copy()}
        return info, (final_cols, done.tolist())

    def _step_fast(self, actions):
        """The whole step in one kernel call (``Batch.vstep``): stepping, the autoresets in C,
        the result arrays and the info; None when this step needs the general path."""
        if self._pending:  # reward weights changed on an env due to reset reach the kernel
            for i in np.flatnonzero(self._autoreset).tolist():
                _kernel.sync_params(self.envs[i], self._batch)
        try:
            r = self._fast(actions, self._elapsed, self._autoreset, self._max_steps,
                           self._col_spec, self.vector_infos)
        except ValueError as e:
            raise self._bad_actions(actions, e) from None
        if r is None:
            return None
        obs, rewards, terminated, truncated, cols, info, reset, self._pending = r
        if reset is not None:
            self._reset_in_c(reset)
        self._lazy_infos = (cols, self._everyone)
        self._lazy_final = None
        self._final_env_infos = [None] * self.num_envs
        return obs, rewards, terminated, truncated, {} if info is None else info

    def _reset_in_c(self, idx) -> None:
        """Envs ``idx`` were reset in C: their Python objects are stale until asked for."""
        envs = self.envs
        for i in idx:
            envs[i]._c_world = True
            envs[i]._py_owns = False

    def _as_array(self, actions) -> np.ndarray:
        try:
            return np.asarray(actions)
        except (ValueError, TypeError):  # ragged lists and the like
            raise self._bad_actions(actions) from None

    def _bad_actions(self, actions, error: ValueError | None = None) -> ValueError:
        """The one-line error for ``actions`` (its type, shape, dtype and first bad entry, never
        the whole array); when the kernel raised ``error`` for actions that are valid, the
        kernel's own error (a robot that left the arena is not an invalid action)."""
        n = self.num_envs
        try:
            a = np.asarray(actions)
        except Exception:  # noqa: BLE001 (anything np.asarray refuses is described by type)
            a = None
        if a is None or a.dtype == object:
            got = type(actions).__name__
        else:
            got = f"{type(actions).__name__} of shape {a.shape} and dtype {a.dtype}"
            if a.shape == (n, 2) and a.dtype.kind in "iubf":
                ok = np.isin(a, (0, 1, 2))
                if ok.all():
                    if error is not None:
                        return error
                else:
                    i, j = (int(k) for k in np.argwhere(~ok)[0])
                    got += f", actions[{i}, {j}] = {a[i, j].item()!r}"
        return ValueError(f"invalid actions ({got}): expected shape ({n}, 2) of [drive, steer] "
                          "with each in {0, 1, 2}")

    def _c_resets(self, idx: list[int]) -> tuple:
        """Of the envs ``idx`` to reset, those the kernel resets in C (its bit generator bound to
        the slot): (their indices, their bool mask or None, the rest, for Python). Reward
        weights changed on one since its last reset reach the kernel now, as a reset's push
        would hand them over."""
        can = self._batch.can_reset
        mine = [i for i in idx if can(i)]
        if not mine:
            return (), None, idx
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[mine] = True
        for i in mine:
            _kernel.sync_params(self.envs[i], self._batch)
        rest = [i for i in idx if not mask[i]] if len(mine) < len(idx) else ()
        return mine, mask, rest

    def _put(self, cols: dict, i: int, d: dict) -> None:
        """Env i's info dict ``d`` (from a reset) into row i of the columns."""
        for k, v in d.items():
            cols[k][i] = v
        if self._has_scenario:
            self._scenarios[i] = d["scenario"]

    def _vector_info(self, cols: dict, mask) -> dict[str, Any]:
        """Gymnasium's vector info from info columns: every key with its ``_key`` mask (all
        True, or ``mask``), as ``VectorEnv._add_info`` builds it from the per-env dicts."""
        n = self.num_envs
        if mask is None:  # fresh all-True rows, one copy of a template (np.ones costs more)
            t = self._true_rows
            if t is None or t.shape[0] != len(cols):
                t = self._true_rows = np.ones((len(cols), n), dtype=bool)
            masks = t.copy()
        else:
            masks = np.repeat(mask[None, :], len(cols), axis=0)
        if mask is None:
            info = dict(cols)
        else:
            info = {k: _masked(v, mask) for k, v in cols.items()}
        info.update(zip(map(_MASK_KEY.__getitem__, cols), masks, strict=True))
        return info

    def _trails(self, active) -> None:
        """Rendering only: each moved robot's trail gets its new position."""
        pose = self._out["pose"]
        for i, env in enumerate(self.envs):
            if active is None or active[i]:
                env.trail.append((float(pose[i, 0]), float(pose[i, 1])))
                if len(env.trail) > _TRAIL_MAX:
                    del env.trail[:_TRAIL_DROP]

    def _actions(self, actions) -> np.ndarray:
        """Actions as a C-contiguous int64 (n, 2) array (the kernel checks the values)."""
        a = actions if isinstance(actions, np.ndarray) else self._as_array(actions)
        n = self.num_envs
        if a.ndim == 0 and a.dtype.kind in "iubfc":  # as SyncVectorEnv: a number can't iterate
            raise TypeError(f"actions must be an array of shape ({n}, 2), got a "
                            f"{type(actions).__name__} {a!r}")
        if a.shape == (n, 2) and a.dtype.kind in "iubf":
            if a.dtype == np.int64 and a.flags.c_contiguous:
                return a
            if a.dtype.kind != "f":
                return np.ascontiguousarray(a, dtype=np.int64)
            if np.isfinite(a).all():
                whole = a.astype(np.int64)
                if np.array_equal(whole, a):  # floats must be whole numbers
                    return whole
        raise self._bad_actions(actions)

    def _step_reference(self, actions):
        """One step of every robot in Python, each scored by its own env's code."""
        n = self.num_envs
        drives, steers = self._commands(actions)
        mode = self.autoreset_mode
        resetting = (np.flatnonzero(self._autoreset).tolist()
                     if mode == AutoresetMode.NEXT_STEP and self._autoreset.any() else [])
        if resetting:
            active = np.flatnonzero(~self._autoreset).tolist()
        else:
            active = self._everyone
        self._move(active, drives, steers)
        envs, obs = self.envs, self._obs
        rewards, terminated = [0.0] * n, [False] * n
        infos: list[dict | None] = [None] * n
        for i in active:  # each robot scored by its own env's code (bit-identical to one env)
            env, d = envs[i], drives[i]
            env._last_action = (d + OFF, OFF - steers[i])
            obs[i], rewards[i], terminated[i], _, infos[i] = env._after_physics(d)
        rewards = np.array(rewards, dtype=np.float64)
        terminated = np.array(terminated, dtype=bool)
        elapsed = self._elapsed
        if resetting:
            moved = ~self._autoreset
            elapsed[moved] += 1
        else:
            moved = None
            elapsed += 1
        if self.max_episode_steps is None:
            truncated = np.zeros(n, dtype=bool)
        else:
            truncated = elapsed >= self.max_episode_steps
            if moved is not None:
                truncated &= moved
        extra: dict[str, Any] = {}
        final: list[dict | None] = [None] * n
        for i in resetting:
            obs[i], infos[i] = envs[i].reset()
            elapsed[i] = 0
        if mode == AutoresetMode.SAME_STEP:
            done = np.flatnonzero(terminated | truncated)
            if len(done):
                final_obs = np.full(n, None, dtype=object)
                for i in done:
                    final_obs[i], final[i] = obs[i].copy(), infos[i]
                    obs[i], infos[i] = envs[i].reset()
                    elapsed[i] = 0
                mask = np.zeros(n, dtype=bool)
                mask[done] = True
                extra = {"final_obs": final_obs, "_final_obs": mask,
                         "final_info": self._gather(final) if self.vector_infos else {},
                         "_final_info": mask.copy()}
            self._autoreset[:] = False
        else:
            self._autoreset = terminated | truncated
        self.env_infos, self.final_env_infos = infos, final
        info = self._gather(infos) if self.vector_infos else {}
        info.update(extra)
        return obs.copy(), rewards, terminated, truncated, info

    @_one_thread
    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode= to "
                            "make_vec()")
            return None
        if not self._started:
            raise gym.error.ResetNeeded("call reset() before render()")
        return tuple(env.render() for env in self.envs)

    @_one_thread
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

    @_one_thread
    def set_attr(self, name: str, values: Any) -> None:
        """Set attribute ``name`` of every env: one value for all, or a list/tuple of num_envs."""
        if not isinstance(values, (list, tuple)):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(f"set_attr needs one value or {self.num_envs} values, "
                             f"got {len(values)}")
        for env, v in zip(self.envs, values, strict=True):
            setattr(env, name, v)

    @_one_thread
    def close_extras(self, **kwargs):
        for env in self.envs:
            env.close()

    # ------------------------------------------------------------------ pieces
    def _commands(self, actions) -> tuple[list[int], list[int]]:
        """Validated actions (n, 2) -> per-env drive and steer motor commands (-1/0/+1 each)."""
        a = actions if isinstance(actions, np.ndarray) else self._as_array(actions)
        if a.ndim == 0 and a.dtype.kind in "iubfc":  # as SyncVectorEnv: a number can't iterate
            raise TypeError(f"actions must be an array of shape ({self.num_envs}, 2), got a "
                            f"{type(actions).__name__} {a!r}")
        if a.shape == (self.num_envs, 2) and a.dtype.kind in "iubf":
            flat = a.ravel().tolist()
            if set(flat) <= _VALID:  # floats must be whole numbers: 1.0 == 1 is in the set
                return [int(x) - OFF for x in flat[0::2]], [OFF - int(x) for x in flat[1::2]]
        raise self._bad_actions(actions)

    def _move(self, idx: list[int], drives: list[int], steers: list[int]) -> None:
        """One control period of physics for the envs ``idx`` (all robots' commands given),
        each robot by its own world's step (the Python reference)."""
        envs = self.envs
        for i in idx:
            envs[i].world.step(drives[i], steers[i], self._period, self._substeps)

    def _gather(self, infos: list[dict | None]) -> dict[str, Any]:
        """Per-env info dicts -> Gymnasium's vector info (arrays plus ``_key`` masks).

        As Gymnasium's ``VectorEnv._add_info``: each key's array takes the type of the first
        reporting env's value (bool, int and float scalars; anything else an object array),
        except that equal-length tuples become float rows (``info["pose"]`` is (n, 3)).
        ``tests/mkv_env/test_vector.py`` checks the two agree on random infos."""
        n = self.num_envs
        present = [i for i, d in enumerate(infos) if d is not None]
        if not present:
            return {}
        rows = [infos[i] for i in present]
        keys = list(rows[0])
        out: dict[str, Any] = {}
        if len(present) == n and all(len(d) == len(keys) for d in rows):
            get = operator.itemgetter(*keys)
            try:  # every env reports the first env's keys (and no others): a column per key
                values = [get(d) for d in rows]
            except KeyError:
                pass
            else:
                columns = (zip(*values, strict=True) if len(keys) > 1
                           else [values])  # one key: itemgetter gives bare values
                mask = np.ones(n, dtype=bool)
                for k, col in zip(keys, columns, strict=True):
                    out[k] = _column(n, present, col)
                    out[f"_{k}"] = mask.copy()
                return out
        # envs report different keys: Gymnasium's rule per key (dtype of the first reporter)
        for k in dict.fromkeys(k for d in rows for k in d):
            idx = [i for i, d in zip(present, rows, strict=True) if k in d]
            out[k] = _column(n, idx, [infos[i][k] for i in idx])
            mask = out[f"_{k}"] = np.zeros(n, dtype=bool)
            mask[idx] = True
        return out


#: "_key", the name of a vector info key's mask.
#: The info keys every robot reports (the kernel's outputs of these names), in order.
_INFO_COLUMNS = ("stuck", "bumped", "collision", "distance_m", "jams", "escapes", "collisions",
                 "in_jam", "pose")
_MASK_KEY = {k: f"_{k}" for k in (*_INFO_COLUMNS, "escaped", "scenario", "cells_visited")}
#: Info keys whose single-env values are numpy scalars (the per-env dicts keep them so).
_NUMPY_SCALAR_KEYS = frozenset({"scenario"})


def _masked(col: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``col`` with the rows outside ``mask`` zeroed (None for objects), as Gymnasium leaves
    the entries of envs that did not report."""
    out = np.zeros_like(col) if col.dtype != object else np.full(col.shape, None, dtype=object)
    out[mask] = col[mask]
    return out


_SCALARS = (int, float, bool)


def _column(n: int, idx: list[int], vals) -> np.ndarray:
    """One info key as an array of n from the values ``vals`` of the envs ``idx`` reporting it.
    Scalars and numpy numbers take the first value's type, equal-length tuples become float rows,
    anything else an object array (zeros / None where an env did not report)."""
    v0 = vals[0]
    full = len(idx) == n
    if type(v0) is tuple and all(type(v) is tuple and len(v) == len(v0) for v in vals):
        arr = np.zeros((n, len(v0)), dtype=np.float64)
        if full:  # one flat list converts 3x faster than the tuples
            arr.ravel()[:] = list(chain.from_iterable(vals))
            return arr
    elif type(v0) in _SCALARS or isinstance(v0, np.number):
        arr = np.zeros(n, dtype=type(v0))
        if full:
            arr[:] = vals
            return arr
    else:
        arr = np.full(n, None, dtype=object)
    for i, v in zip(idx, vals, strict=True):
        arr[i] = v
    return arr


def _check_env_cls(env_cls) -> None:
    """``env_cls`` must be an MK-V env class whose step and reset are its package base's: the
    vector env steps and resets every robot itself (compiled kernel or Python reference) and
    would silently skip a subclass's own ``step``/``reset``."""
    if not (isinstance(env_cls, type) and issubclass(env_cls, MKVEnv)):
        raise TypeError(f"env_cls must be MKVEnv or a subclass, got {env_cls!r}")
    base = next(c for c in env_cls.__mro__ if c in (MKVJamEnvV1, MKVJamEnv, MKVEnvV1, MKVEnv))
    for name in ("step", "reset"):
        if getattr(env_cls, name) is not getattr(base, name):
            raise TypeError(f"{env_cls.__name__} overrides {name}(), which MKVVectorEnv never "
                            f"calls (it steps every robot itself): vectorise it with "
                            "gymnasium.vector.SyncVectorEnv instead")


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
