"""Keyboard-less teleop: a plain-text file of timed commands, replayed as a policy.

A teleoperated session can be written down and re-run exactly. The format, one command a line::

    # time_s  drive    steer        (comments start with #; blank lines are ignored)
    0.0       forward  off
    2.5       reverse  left          # back off, steering left
    4.0       2        2             # numbers work too: the env's action values 0, 1, 2

``time_s`` is seconds from the start of the episode (>= 0, strictly increasing down the file).
``drive`` is ``reverse``/``off``/``forward`` or 0/1/2; ``steer`` is ``left``/``off``/``right`` or
0/1/2 (the values of the ``MultiDiscrete([3, 3])`` action). A command holds from its time until the
next command's; before the first command both motors are off; after the last it holds to the end
of the episode. Step ``k`` of an episode (the action sent after ``k`` control periods, at time
``k * control_period_s``) uses the last command whose time is at or before that time.
"""

from __future__ import annotations

import os

import numpy as np

from mkv_env.actions import ACTION_NVEC, NOOP_ACTION, VALUE_NAMES
from mkv_env.batching import as_batch, episode_starts

#: Words of the drive and steer columns -> action values (``reverse``/``off``/``forward``,
#: ``left``/``off``/``right``: :data:`mkv_env.actions.VALUE_NAMES`).
DRIVE_WORDS = {word: i for i, word in enumerate(VALUE_NAMES["drive"])}
STEER_WORDS = {word: i for i, word in enumerate(VALUE_NAMES["steer"])}

# Half a microsecond of slack so "0.3" lands on step 3 despite 3 * 0.1 = 0.30000000000000004.
_EPS_S = 5e-7


class ScriptError(ValueError):
    """A command script that cannot be read or parsed; the message names the file and line."""


def parse_script(text: str, source: str = "<script>") -> tuple[np.ndarray, np.ndarray]:
    """Parse command-script text.

    Returns:
        times_s: float64 array of shape (n_commands,), strictly increasing, >= 0.
        commands: int64 array of shape (n_commands, 2), [drive, steer] action values.

    Raises:
        ScriptError: with ``source:line: what is wrong``.
    """
    times: list[float] = []
    commands: list[tuple[int, int]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        where = f"{source}:{lineno}"
        if len(parts) != 3:
            raise ScriptError(f"{where}: expected 'time_s drive steer', got {line!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise ScriptError(f"{where}: time {parts[0]!r} is not a number") from None
        if not np.isfinite(t) or t < 0:
            raise ScriptError(f"{where}: time must be a finite number >= 0, got {parts[0]}")
        if times and t <= times[-1]:
            raise ScriptError(f"{where}: times must increase, {t:g} s follows {times[-1]:g} s")
        drive = _value(parts[1], DRIVE_WORDS, "drive", where)
        steer = _value(parts[2], STEER_WORDS, "steer", where)
        times.append(t)
        commands.append((drive, steer))
    if not times:
        raise ScriptError(f"{source}: no commands (expected lines of 'time_s drive steer')")
    return np.asarray(times, dtype=np.float64), np.asarray(commands, dtype=np.int64)


def _value(token: str, words: dict[str, int], what: str, where: str) -> int:
    key = token.lower()
    if key in words:
        return words[key]
    numbers = [str(i) for i in range(len(words))]
    if key in numbers:
        return int(key)
    raise ScriptError(
        f"{where}: {what} must be one of {', '.join(words)} or {', '.join(numbers)}; "
        f"got {token!r}"
    )


def format_script(times_s, commands, header: str | None = None) -> str:
    """The text of a command script (inverse of :func:`parse_script`), one line per command."""
    inv_d = {v: k for k, v in DRIVE_WORDS.items()}
    inv_s = {v: k for k, v in STEER_WORDS.items()}
    lines = [f"# {line}" for line in (header or "").splitlines()]
    lines.append("# time_s  drive    steer")
    for t, (d, s) in zip(times_s, commands, strict=True):
        lines.append(f"{float(t):<9.3f} {inv_d[int(d)]:<8} {inv_s[int(s)]}")
    return "\n".join(lines) + "\n"


def script_from_actions(actions, control_period_s: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Compress a per-step action sequence (n_steps, 2) into (times_s, commands) at the changes."""
    actions = np.asarray(actions, dtype=np.int64).reshape(-1, 2)
    if len(actions) == 0:
        raise ValueError("no actions to write")
    change = np.ones(len(actions), dtype=bool)
    change[1:] = np.any(actions[1:] != actions[:-1], axis=1)
    idx = np.flatnonzero(change)
    return idx * float(control_period_s), actions[idx]


class ScriptPolicy:
    """Replays a command script, with the SB3-style ``predict`` of the scripted teacher.

    Args:
        times_s: command times [s] of shape (n_commands,), strictly increasing, >= 0.
        commands: [drive, steer] action values of shape (n_commands, 2).
        control_period_s: the env's control period [s].

    ``predict(obs)`` returns the command for the current step and advances the policy's step
    counter (one per env in a batch of shape (n_envs, 10)); ``episode_start`` resets counters.
    """

    def __init__(self, times_s, commands, control_period_s: float = 0.1):
        times_s = np.asarray(times_s, dtype=np.float64).reshape(-1)
        commands = np.asarray(commands, dtype=np.int64).reshape(-1, 2)
        if len(times_s) == 0 or len(times_s) != len(commands):
            raise ValueError("times_s and commands must be non-empty and of equal length")
        if np.any(np.diff(times_s) <= 0) or times_s[0] < 0:
            raise ValueError("times_s must be >= 0 and strictly increasing")
        if np.any((commands < 0) | (commands >= np.asarray(ACTION_NVEC))):
            raise ValueError("commands must be action values 0, 1 or 2")
        if not control_period_s > 0:
            raise ValueError(f"control_period_s must be > 0, got {control_period_s!r}")
        self.times_s = times_s
        self.commands = commands
        self.control_period_s = float(control_period_s)
        self.source: str | None = None
        self._steps = np.zeros(1, dtype=np.int64)  # per env: control steps since its start

    @classmethod
    def from_file(cls, path, control_period_s: float = 0.1) -> ScriptPolicy:
        """Read a command script; raises :class:`ScriptError` (one line) if it is missing or bad."""
        path = os.fspath(path)
        try:
            with open(path, encoding="utf-8") as f:
                text = f.read()
        except FileNotFoundError:
            raise ScriptError(f"{path}: command script not found") from None
        except (OSError, UnicodeDecodeError) as e:
            raise ScriptError(f"{path}: cannot read command script ({e})") from None
        policy = cls(*parse_script(text, path), control_period_s=control_period_s)
        policy.source = path
        return policy

    @property
    def duration_s(self) -> float:
        """Time of the last command [s]."""
        return float(self.times_s[-1])

    def reset(self, seed: int | None = None) -> None:
        """Restart every env's script from time 0 (``seed`` is accepted and unused)."""
        self._steps[:] = 0

    def action_at(self, step: int) -> np.ndarray:
        """The command in force at control step ``step`` (time ``step * control_period_s``)."""
        k = np.searchsorted(self.times_s, step * self.control_period_s + _EPS_S, side="right")
        if k > 0:
            return self.commands[k - 1].copy()
        return np.array(NOOP_ACTION, dtype=np.int64)

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        """The commands in force for one observation (obs_dim,) or a batch (n_envs, obs_dim).

        Each env index keeps its own step counter (created at 0 the first time a batch reaches
        it); ``episode_start`` (bool or bool array (n_envs,)) restarts the script of those envs.
        Returns ``(actions, None)``, int64 actions of shape (2,) or (n_envs, 2).
        """
        obs, single = as_batch(observation)
        n = obs.shape[0]
        if len(self._steps) < n:
            self._steps = np.concatenate([self._steps, np.zeros(n - len(self._steps), np.int64)])
        steps = self._steps[:n]  # a view: the counters advance in place
        steps[episode_starts(episode_start, n)] = 0
        actions = np.stack([self.action_at(int(k)) for k in steps])
        steps += 1
        return (actions[0] if single else actions), None
