"""Policy specs shared by every command: ``teacher``, ``random``, ``script:PATH``, and plug-ins.

A *policy* here is anything with the stable-baselines3 method
``predict(observation, state=None, episode_start=None, deterministic=True) -> (action, state)``,
optionally with ``reset(seed=None)``, which the episode runners call at the start of every episode
with that episode's seed (so a seeded policy replays exactly).

Specs understood here:

* ``teacher`` or ``teacher:key=value,...``: :class:`mkv_env.teacher.ScriptedTeacher` with optional
  parameter overrides, e.g. ``teacher:backoff_s=2,wander_rate_hz=0``.
* ``random``: uniformly random actions from the env's action space (seeded).
* ``script:PATH``: replay a command script (:mod:`mkv_env.script`).
* ``const:NAME`` or ``const:D,S``: the same action every step, for degenerate baselines:
  ``still`` (off, off), ``circle`` (forward, left), ``reverse`` (reverse, off), ``forward``
  (forward, off), or the action indices themselves (``const:2,0``).

Other packages add prefixes with :func:`register_policy_loader`, giving either a callable or a
``"module:function"`` string that is imported only when the spec is used (so ``mkv eval --policy
teacher`` never imports torch). ``mkv_env`` itself never imports ``sfm_learn``; ``sfm_learn``
registers ``sfm:``, ``ppo:`` and ``bc:`` from its side.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable

import numpy as np

from mkv_env.actions import ACTION_NVEC
from mkv_env.batching import as_batch, env_rng, episode_starts
from mkv_env.script import ScriptError, ScriptPolicy
from mkv_env.teacher import ScriptedTeacher


class PolicySpecError(ValueError):
    """A policy spec that names no known policy or cannot be loaded; the message is one line."""


# A loader gets the text after "prefix:" ("" if none), the env (for spaces, control period) and
# a seed, and returns a policy.
Loader = Callable[[str, object, "int | None"], object]

_LOADERS: dict[str, Loader | str] = {}


def register_policy_loader(prefix: str, loader: Loader | str, *, replace: bool = False) -> None:
    """Make ``prefix`` or ``prefix:ARG`` a valid policy spec.

    Args:
        prefix: the spec's name, letters/digits/``_``/``-`` (``"sfm"`` for ``sfm:PATH``).
        loader: ``loader(arg, env, seed) -> policy``, or a ``"package.module:function"`` string
            naming such a function, imported on first use.
        replace: allow overriding an existing prefix.
    """
    if not prefix or not all(c.isalnum() or c in "_-" for c in prefix):
        raise ValueError(f"policy prefix must be a non-empty word, got {prefix!r}")
    if prefix in _LOADERS and not replace and _LOADERS[prefix] != loader:
        raise ValueError(f"policy prefix {prefix!r} is already registered")
    if isinstance(loader, str) and ":" not in loader:
        raise ValueError(f"lazy loader must be 'module:function', got {loader!r}")
    _LOADERS[prefix] = loader


def known_prefixes() -> list[str]:
    return sorted(_LOADERS)


def make_policy(spec: str, env=None, seed: int | None = None):
    """Build the policy named by ``spec`` for ``env`` (a Gymnasium env, used for its spaces and
    control period). Raises :class:`PolicySpecError` with a one-line message on a bad spec.

    Specs (the ``--policy`` values of ``mkv eval/record/play``; :func:`known_prefixes` lists the
    registered ones): ``teacher`` (the scripted teacher), ``random``, ``const:NAME`` (one
    command), ``script:PATH`` (a text file of commands), ``sfm:PATH`` (``mkv fit``), ``bc:PATH``
    (``mkv train-bc``), ``dagger:PATH`` (``mkv train-dagger``), ``ppo:PATH``
    (``mkv train-ppo``), ``sb3:ALGO:PATH`` (any SB3 / rl-zoo3 zip, and the project's zips).

    The returned object has SB3's ``predict(obs, state=None, episode_start=None,
    deterministic=False) -> (actions, state)`` for one raw observation of ``env`` or a batch, and
    ``reset(seed)``; learned policies rebuild their own inputs (rescaling, SfM features) from
    the env's raw readings, so give them an env made with the default ``observation="raw"``.
    ``seed`` seeds the policy's own randomness (random actions, sampling). Nothing in a file is
    unpickled (docs/trust.md).

    >>> import gymnasium as gym, mkv_env
    >>> env = gym.make("MKVJam-v1")
    >>> policy = make_policy("teacher", env, seed=0)
    >>> obs, _ = env.reset(seed=1)
    >>> action, _ = policy.predict(obs, deterministic=True)
    """
    if not isinstance(spec, str) or not spec.strip():
        raise PolicySpecError(f"policy spec must be a non-empty string, got {spec!r}")
    prefix, _, arg = spec.strip().partition(":")
    if prefix not in _LOADERS:
        raise PolicySpecError(
            f"unknown policy spec {spec!r}; known: "
            + ", ".join(p + {"teacher": "", "random": "", "const": ":NAME"}.get(p, ":PATH")
                        for p in known_prefixes())
        )
    loader = _LOADERS[prefix]
    if isinstance(loader, str):
        module, _, func = loader.partition(":")
        try:
            loader = getattr(importlib.import_module(module), func)
        except (ImportError, AttributeError) as e:
            raise PolicySpecError(f"policy {prefix!r} is unavailable: {e}") from None
    try:
        return loader(arg, env, seed)
    except PolicySpecError:
        raise
    except (ScriptError, FileNotFoundError) as e:
        raise PolicySpecError(str(e)) from None


def describe(policy) -> str:
    """A short name for a policy object (for reports)."""
    return getattr(policy, "spec", None) or type(policy).__name__


class RandomPolicy:
    """Uniformly random actions of a ``MultiDiscrete`` space, from seeded numpy streams.

    Args:
        nvec: values per command, shape (n_commands,) (default the MK-V's ``ACTION_NVEC``).
        seed: seed of the streams; :meth:`reset` re-seeds them.

    ``predict`` takes one observation (obs_dim,) or a batch (n_envs, obs_dim) and returns int64
    actions of shape (n_commands,) or (n_envs, n_commands). Env 0 (and a single observation)
    draws from ``self.rng`` = ``numpy.random.default_rng(seed)``, env ``i >= 1`` from its own
    stream ``default_rng(SeedSequence(seed).spawn(i + 1)[i])`` (:mod:`mkv_env.batching`), so an
    env's actions do not depend on the batch size. ``episode_start`` is accepted and changes
    nothing (the streams run on across episodes).
    """

    def __init__(self, nvec=ACTION_NVEC, seed: int | None = None):
        self.nvec = np.asarray(nvec, dtype=np.int64).reshape(-1)
        self._seed_streams(seed)

    def reset(self, seed: int | None = None) -> None:
        """With ``seed``, restart every env's stream from it (without, nothing to forget)."""
        if seed is not None:
            self._seed_streams(seed)

    @property
    def rng(self) -> np.random.Generator:
        """Env 0's random stream."""
        return self._rngs[0]

    def _seed_streams(self, seed: int | None) -> None:
        self._seed_seq = np.random.SeedSequence(seed)
        self._rngs = [env_rng(self._seed_seq, 0)]

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        """``(actions, None)`` for one observation or a batch (see the class docstring)."""
        obs, single = as_batch(observation)
        n = obs.shape[0]
        episode_starts(episode_start, n)  # validated only
        while len(self._rngs) < n:
            self._rngs.append(env_rng(self._seed_seq, len(self._rngs)))
        k = len(self.nvec)
        a = np.concatenate([rng.integers(0, self.nvec, size=(1, k), dtype=np.int64)
                            for rng in self._rngs[:n]])
        return (a[0] if single else a), None


def _control_period(env) -> float:
    return float(getattr(getattr(env, "unwrapped", env), "control_period_s", 0.1))


def _load_teacher(arg: str, env, seed):
    kwargs = {}
    names = {f for f in inspect.signature(ScriptedTeacher).parameters} - {"seed"}
    for item in filter(None, (s.strip() for s in arg.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or key not in names:
            raise PolicySpecError(
                f"bad teacher option {item!r}; expected key=value with key among "
                + ", ".join(sorted(names))
            )
        try:
            num = float(value)
            kwargs[key] = int(num) if key in ("stall_steps", "grace_steps") and num.is_integer() \
                else num
        except ValueError:
            raise PolicySpecError(f"teacher option {key} must be a number, got {value!r}") from None
    kwargs.setdefault("control_period_s", _control_period(env))
    try:
        teacher = ScriptedTeacher(seed=seed, **kwargs)
    except ValueError as e:
        raise PolicySpecError(f"bad teacher option: {e}") from None
    if env is not None:
        try:
            teacher.check_env(env)
        except ValueError as e:
            raise PolicySpecError(str(e)) from None
    teacher.spec = "teacher" + (f":{arg}" if arg else "")
    return teacher


def _load_random(arg: str, env, seed):
    if arg:
        raise PolicySpecError(f"'random' takes no argument, got 'random:{arg}'")
    nvec = getattr(getattr(env, "action_space", None), "nvec", ACTION_NVEC)
    policy = RandomPolicy(nvec, seed)
    policy.spec = "random"
    return policy


#: Named constant actions of ``const:NAME`` ([drive, steer] indices).
CONST_ACTIONS = {"still": (1, 1), "circle": (2, 0), "reverse": (0, 1), "forward": (2, 1)}


class ConstantPolicy:
    """The same action every step (``const:`` specs): standing still, circling forever,
    reversing forever; the degenerate behaviours a reward must not favour."""

    def __init__(self, action):
        self.action = np.asarray(action, dtype=np.int64)

    def reset(self, seed: int | None = None) -> None:
        """Nothing to forget."""

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        obs, single = as_batch(observation)
        actions = np.tile(self.action, (len(obs), 1))
        return (actions[0] if single else actions), state


def _load_const(arg: str, env, seed):
    nvec = tuple(int(n) for n in getattr(getattr(env, "action_space", None), "nvec", ACTION_NVEC))
    if arg in CONST_ACTIONS:
        action = CONST_ACTIONS[arg]
    else:
        try:
            action = tuple(int(v) for v in arg.split(","))
        except ValueError:
            action = ()
        if len(action) != len(nvec) or not all(
                0 <= a < n for a, n in zip(action, nvec, strict=True)):
            raise PolicySpecError(
                f"const:{arg} is not an action: give one of {', '.join(CONST_ACTIONS)} or "
                f"{len(nvec)} comma-separated indices below {list(nvec)}, e.g. const:2,1")
    policy = ConstantPolicy(action)
    policy.spec = f"const:{arg}"
    return policy


def _load_script(arg: str, env, seed):
    if not arg:
        raise PolicySpecError("'script' needs a file: script:PATH")
    policy = ScriptPolicy.from_file(arg, _control_period(env))
    policy.spec = f"script:{arg}"
    return policy


register_policy_loader("teacher", _load_teacher)
register_policy_loader("random", _load_random)
register_policy_loader("script", _load_script)
register_policy_loader("const", _load_const)

__all__ = [
    "CONST_ACTIONS", "ConstantPolicy", "PolicySpecError", "RandomPolicy", "describe",
    "known_prefixes", "make_policy",
    "register_policy_loader",
]
