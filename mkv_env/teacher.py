"""The scripted teleop teacher: a stand-in for the paper's human operator of the MK-V.

The paper (section 9) teleoperated the MK-V "in a cluttered environment allowing it to wander while
bumping into obstacles"; the operator drove forward, and when the robot bumped or stalled backed it
off while steering, then drove on. The steering *direction* while escaping was random, which is why
the learned policy matched *when* to steer but not *which way*. :class:`ScriptedTeacher` does the
same, looking at the sensor channels only (never at ``info`` or the true pose).

What it looks at, per environment, each control period (channel names of
``env.unwrapped.sensor_names``, in the default observation order):

* ``bump_front_left``, ``bump_front_right`` (> 0.5): a front bump while driving forward starts an
  escape at once.
* ``bump_rear`` (> 0.5): while backing off, ends the back-off early (the tail hit something).
* ``drive_current`` [A]: at or above ``stall_current_a`` (default 0.3 A; the drive motor stalls
  at 0.5 A, cruises near 0.05 A) for ``stall_steps`` periods while commanding forward: stalled.
* ``drive_ticks``: at most ``still_ticks`` (1) ticks per period for ``stall_steps`` periods while
  commanding forward: the wheel does not turn.
* ``roller_ticks`` vs ``drive_ticks``: the free-rolling steering wheel turns about 1.2 ticks per
  drive tick when the robot rolls; fewer than ``spin_ratio`` (0.3) of the drive ticks for
  ``stall_steps`` periods while the drive wheel turns forward (>= 3 ticks) means the drive wheel
  spins or slips in place.
* ``steer_angle`` [rad]: to bring the steering back to centre while cruising (the steering motor
  has no position control; "off" leaves the wheel where it is).

``drive_ticks`` and ``drive_current`` are ignored for ``grace_steps`` periods after the drive
command changes direction, while the motor accelerates (start-up current is high).
``compass``, ``steer_current`` and ``battery`` are not used: superfluous, as on the real robot.

Behaviour (a small state machine per environment):

1. **cruise**: drive forward. Now and then (a Poisson process at ``wander_rate_hz``) steer left or
   right (seeded coin) for a random time up to ``wander_turn_s``; otherwise re-centre the steering.
2. **back off** (on a bump or stall): reverse for ``backoff_s``: the first ``straight_s`` with the
   steering re-centred (so the robot backs straight out of a narrow dead end instead of turning
   sideways inside it), then steering to a random side (seeded coin, the paper's random escape
   direction). A rear bump cuts it short.
3. **turn**: drive forward for ``turn_s`` steering to the other side, so that back-off and turn
   together make a three-point turn away from the obstacle; then cruise. A bump or stall during
   the turn starts a new back-off with a fresh random direction.
"""

from __future__ import annotations

import math

import numpy as np

from mkv_env.actions import FORWARD, LEFT, OFF, REVERSE, RIGHT
from mkv_env.batching import as_batch, env_rng, episode_starts
from mkv_env.params import SENSOR_NAMES

# Observation indices (the env's fixed channel order; checked by ScriptedTeacher.check_env).
_DRIVE_TICKS, _ROLLER_TICKS, _STEER_ANGLE = (SENSOR_NAMES.index(n) for n in (
    "drive_ticks", "roller_ticks", "steer_angle"))
_BUMP_FL, _BUMP_FR, _BUMP_REAR = (SENSOR_NAMES.index(n) for n in (
    "bump_front_left", "bump_front_right", "bump_rear"))
_DRIVE_CURRENT = SENSOR_NAMES.index("drive_current")

# Teacher modes.
CRUISE, BACKOFF, TURN = 0, 1, 2

_REVERSE, _OFF, _FORWARD = REVERSE, OFF, FORWARD
_LEFT, _RIGHT = LEFT, RIGHT


class _EnvState:
    """The teacher's memory of one env: its mode, timers and its own random stream."""

    __slots__ = ("mode", "timer", "side", "wander", "evidence", "since_change", "last_drive",
                 "rng")

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.reset()

    def reset(self) -> None:
        """Forget the timers (a new episode); the random stream goes on."""
        self.mode = CRUISE
        self.timer = 0               # periods left in back off / turn / wander
        self.side = _LEFT            # escape steer action (0 left, 2 right)
        self.wander = _OFF           # current wander steer action
        self.evidence = 0            # consecutive periods of stall evidence
        self.since_change = 0        # periods since the drive direction changed
        self.last_drive = _OFF


class ScriptedTeacher:
    """Wander, and back off while steering (random side) on a bump or a stall.

    Args:
        backoff_s: time to reverse after a bump or stall [s].
        turn_s: time to drive forward steering the other way after the back-off [s].
        straight_s: the first part of the back-off, steering re-centred [s] (< backoff_s to
            steer at all while backing off).
        wander_rate_hz: mean rate of wander steering episodes while cruising [1/s].
        wander_turn_s: longest wander steering episode [s] (each lasts uniform(0.2 s, this)).
        stall_current_a: drive current at or above which the drive counts as stalled [A].
        stall_steps: consecutive control periods of stall/no-motion/spin evidence before escaping.
        still_ticks: drive encoder ticks per period at or below which the wheel counts as still.
        spin_ratio: roller/drive tick ratio below which the drive wheel counts as spinning.
        centre_rad: dead band of the steering re-centring while cruising [rad].
        grace_steps: periods after a change of drive direction during which stalls are ignored.
        control_period_s: the env's control period [s] (0.1 for ``MKV-v0``).
        seed: seed of the teacher's random streams (escape and wander directions, wander
            timing). :meth:`reset` re-seeds them.

    Use it like any SB3 policy::

        teacher = ScriptedTeacher(seed=0)
        obs, info = env.reset(seed=0)
        action, _ = teacher.predict(obs, episode_start=True)

    ``predict`` takes one observation of shape (10,) or a batch (n_envs, 10) from a vector env and
    returns actions of shape (2,) or (n_envs, 2), int64. A single observation is env 0. The
    teacher keeps one state (mode, timers, random stream) per env index itself, created the first
    time a batch reaches that index (it is not a recurrent policy, so the returned ``state`` is
    ``None``); pass ``episode_start`` (bool, or array of shape (n_envs,)) to reset the timers of
    the envs that start a new episode.

    Random streams (:mod:`mkv_env.batching`): env 0 draws from ``self.rng`` =
    ``numpy.random.default_rng(seed)``; env ``i >= 1`` from
    ``default_rng(SeedSequence(seed).spawn(i + 1)[i])``. Each env's escape and wander choices thus
    depend only on the seed and that env's own observations, not on the other envs or the batch
    size.
    """

    def __init__(
        self,
        backoff_s: float = 1.5,
        turn_s: float = 1.0,
        straight_s: float = 0.5,
        wander_rate_hz: float = 0.3,
        wander_turn_s: float = 1.0,
        stall_current_a: float = 0.3,
        stall_steps: int = 2,
        still_ticks: float = 1.0,
        spin_ratio: float = 0.3,
        centre_rad: float = 0.08,
        grace_steps: int = 2,
        control_period_s: float = 0.1,
        seed: int | None = None,
    ):
        for name, v in (("backoff_s", backoff_s), ("turn_s", turn_s),
                        ("wander_turn_s", wander_turn_s), ("control_period_s", control_period_s),
                        ("stall_current_a", stall_current_a), ("centre_rad", centre_rad)):
            if not (_real(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if not (_real(straight_s) and straight_s >= 0):
            raise ValueError(f"straight_s must be a number >= 0, got {straight_s!r}")
        if not (_real(wander_rate_hz) and wander_rate_hz >= 0):
            raise ValueError(f"wander_rate_hz must be a number >= 0, got {wander_rate_hz!r}")
        if not (_real(spin_ratio) and 0 <= spin_ratio < 1):
            raise ValueError(f"spin_ratio must be in [0, 1), got {spin_ratio!r}")
        if not (_real(still_ticks) and still_ticks >= 0):
            raise ValueError(f"still_ticks must be a number >= 0, got {still_ticks!r}")
        for name, v in (("stall_steps", stall_steps), ("grace_steps", grace_steps)):
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 0):
                raise ValueError(f"{name} must be an integer >= 0, got {v!r}")
        if stall_steps < 1:
            raise ValueError(f"stall_steps must be >= 1, got {stall_steps!r}")
        self.backoff_s = float(backoff_s)
        self.turn_s = float(turn_s)
        self.straight_s = float(straight_s)
        self.wander_rate_hz = float(wander_rate_hz)
        self.wander_turn_s = float(wander_turn_s)
        self.stall_current_a = float(stall_current_a)
        self.stall_steps = int(stall_steps)
        self.still_ticks = float(still_ticks)
        self.spin_ratio = float(spin_ratio)
        self.centre_rad = float(centre_rad)
        self.grace_steps = int(grace_steps)
        self.control_period_s = float(control_period_s)
        self.seed = seed
        self._seed_streams(seed)

    # ------------------------------------------------------------------ public API
    def reset(self, seed: int | None = None) -> None:
        """Forget every env's timers; with ``seed``, restart every env's random stream from it."""
        if seed is not None:
            self.seed = seed
            self._seed_streams(seed)
        else:
            for env in self._envs:
                env.reset()

    def check_env(self, env) -> None:
        """Raise ValueError unless ``env`` has the MK-V's sensor channels in the expected order."""
        names = tuple(getattr(getattr(env, "unwrapped", env), "sensor_names", ()))
        if names != SENSOR_NAMES:
            raise ValueError(f"ScriptedTeacher needs sensor channels {SENSOR_NAMES}, got {names}")

    @property
    def rng(self) -> np.random.Generator:
        """Env 0's random stream (the only one a single-env user ever touches)."""
        return self._envs[0].rng

    @property
    def mode(self) -> np.ndarray:
        """Current mode per env index seen so far (0 cruise, 1 back off, 2 turn), (n_envs,)."""
        return np.array([env.mode for env in self._envs[:self._n]], dtype=np.int64)

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        """Actions for one observation (10,) or a batch (n_envs, 10).

        Args:
            observation: sensor readings in ``SENSOR_NAMES`` order, shape (10,) or (n_envs, 10).
            state: ignored (SB3's recurrent state; the teacher keeps its own per-env state).
            episode_start: None, a bool, or bool array (n_envs,): envs whose episode begins with
                this observation (their timers are reset first).
            deterministic: accepted for SB3 compatibility and ignored: the random choices
                (escape side, wander) come from the seeded per-env streams either way.

        Returns:
            ``(actions, None)``, actions int64 of shape (2,) or (n_envs, 2) = [drive, steer].
        """
        obs, single = as_batch(observation, len(SENSOR_NAMES), np.float64)
        n = obs.shape[0]
        starts = episode_starts(episode_start, n)
        while len(self._envs) < n:
            self._envs.append(_EnvState(env_rng(self._seed_seq, len(self._envs))))
        self._n = n
        actions = np.empty((n, 2), dtype=np.int64)
        for i in range(n):
            env = self._envs[i]
            if starts[i]:
                env.reset()
            actions[i] = self._act(env, obs[i])
        return (actions[0] if single else actions), None

    # ------------------------------------------------------------------ internals
    def _seed_streams(self, seed: int | None) -> None:
        """Fresh per-env states (timers cleared) whose streams start from ``seed``."""
        self._seed_seq = np.random.SeedSequence(seed)
        n = max(1, len(getattr(self, "_envs", ())))
        self._envs = [_EnvState(env_rng(self._seed_seq, i)) for i in range(n)]
        self._n = getattr(self, "_n", 0)  # the batch size of the last predict

    def _periods(self, seconds: float) -> int:
        return max(1, round(seconds / self.control_period_s))

    def _blocked(self, env: _EnvState, o: np.ndarray) -> bool:
        """Bump, stall, still wheel or wheel spin while the last command drove forward."""
        if env.last_drive != _FORWARD:
            env.evidence = 0
            return False
        if o[_BUMP_FL] > 0.5 or o[_BUMP_FR] > 0.5:
            return True
        if env.since_change < self.grace_steps:
            env.evidence = 0
            return False
        ticks, roller = o[_DRIVE_TICKS], o[_ROLLER_TICKS]
        stalled = o[_DRIVE_CURRENT] >= self.stall_current_a
        still = ticks <= self.still_ticks
        spinning = ticks >= 3 and abs(roller) < self.spin_ratio * ticks
        env.evidence = env.evidence + 1 if (stalled or still or spinning) else 0
        return env.evidence >= self.stall_steps

    def _start_backoff(self, env: _EnvState) -> None:
        env.mode = BACKOFF
        env.timer = self._periods(self.backoff_s)
        env.side = _LEFT if env.rng.random() < 0.5 else _RIGHT
        env.evidence = 0

    def _act(self, env: _EnvState, o: np.ndarray) -> tuple[int, int]:
        blocked = self._blocked(env, o)
        mode = env.mode
        if mode != BACKOFF and blocked:
            self._start_backoff(env)
            mode = BACKOFF
        elif mode == BACKOFF:
            env.timer -= 1
            if env.timer <= 0 or o[_BUMP_REAR] > 0.5:
                mode = env.mode = TURN
                env.timer = self._periods(self.turn_s)
        elif mode == TURN:
            env.timer -= 1
            if env.timer <= 0:
                mode = env.mode = CRUISE
                env.timer = 0
                env.wander = _OFF

        if mode == BACKOFF:
            elapsed = self._periods(self.backoff_s) - env.timer
            if elapsed < round(self.straight_s / self.control_period_s):
                action = (_REVERSE, self._centre(o))
            else:
                action = (_REVERSE, env.side)
        elif mode == TURN:
            action = (_FORWARD, _LEFT + _RIGHT - env.side)
        else:
            action = (_FORWARD, self._wander_steer(env, o))

        drive = action[0]
        if drive != env.last_drive:
            env.since_change = 0
            env.evidence = 0
        else:
            env.since_change += 1
        env.last_drive = drive
        return action

    def _wander_steer(self, env: _EnvState, o: np.ndarray) -> int:
        if env.timer > 0:
            env.timer -= 1
            return env.wander
        p = 1.0 - math.exp(-self.wander_rate_hz * self.control_period_s)
        if env.rng.random() < p:
            env.wander = _LEFT if env.rng.random() < 0.5 else _RIGHT
            env.timer = self._periods(env.rng.uniform(0.2, self.wander_turn_s)) - 1
            return env.wander
        return self._centre(o)

    def _centre(self, o: np.ndarray) -> int:
        angle = o[_STEER_ANGLE]  # left positive; steer action 0 turns left
        if angle > self.centre_rad:
            return _RIGHT
        if angle < -self.centre_rad:
            return _LEFT
        return _OFF


def _real(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) \
        and math.isfinite(v)
