"""Helpers shared by the Stable-Baselines3 baselines (:mod:`~sfm_learn.baselines.ppo`,
:mod:`~sfm_learn.baselines.bc`).

- the policy-file container: a zip with a JSON member :data:`META_MEMBER` (``mkv_meta.json``)
  next to the weights, written atomically and deterministically, read back with one-line errors;
- :class:`ActorPolicy`: the SB3 ``predict`` interface over an ``ActorCriticPolicy``, computing
  the action logits directly (no per-step distribution objects) and taking the argmax of each
  command (``deterministic=True``) or sampling from a seeded numpy stream;
- the observation rescaling PPO uses (Gymnasium's ``RescaleObservation`` to [-1, 1]) and a
  picklable env factory for vectorised envs.

Only numpy, gymnasium and the standard library are imported at module level; torch and SB3 are
imported inside functions (``mkv --help`` must stay cheap).
"""

from __future__ import annotations

import io
import json
import os
import zipfile
import zlib

import gymnasium as gym
import numpy as np

from mkv_env.policies import PolicySpecError

META_MEMBER = "mkv_meta.json"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)
KIND_NAMES = {"mkv-ppo": ("ppo", "a PPO model"), "mkv-bc": ("bc", "a behaviour-cloning policy"),
              "mkv-dagger": ("dagger", "a DAgger policy")}


def import_torch(threads: int = 1):
    """Import torch with ``threads`` intra-op threads (the machine is small and shared; the nets
    are tiny, so one thread is also the fastest for single-observation inference)."""
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    return torch


def versions() -> dict:
    """Package versions worth recording next to a trained policy."""
    import stable_baselines3
    import torch

    import sfm_learn

    return {
        "package_version": sfm_learn.__version__,
        "sb3_version": stable_baselines3.__version__,
        "torch_version": torch.__version__,
    }


# ---------------------------------------------------------------------- files
def meta_bytes(meta: dict) -> bytes:
    return (json.dumps(meta, indent=1, sort_keys=True, allow_nan=False) + "\n").encode("utf-8")


def zip_bytes(members: dict[str, bytes]) -> bytes:
    """A deterministic zip (fixed timestamps, given member order) of ``members``."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, data)
    return buf.getvalue()


def add_member(zip_data: bytes, name: str, data: bytes) -> bytes:
    """``zip_data`` with one more member appended (used on SB3's own model zip)."""
    buf = io.BytesIO(zip_data)
    with zipfile.ZipFile(buf, "a", compression=zipfile.ZIP_DEFLATED) as zf:
        info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
        info.compress_type = zipfile.ZIP_DEFLATED
        info.external_attr = 0o644 << 16
        zf.writestr(info, data)
    return buf.getvalue()


def read_policy_zip(path: str, fmt: str, members: tuple[str, ...] = ()) -> tuple[dict, dict]:
    """Open a policy zip written by ``mkv train-ppo`` / ``train-bc`` and check its kind.

    Returns ``(meta, {member: bytes})`` for the requested ``members``. Raises
    :class:`PolicySpecError` with one line for a missing, corrupt or wrong-kind file.
    """
    prefix, what = KIND_NAMES[fmt]
    if not path:
        raise PolicySpecError(f"'{prefix}' needs a file: {prefix}:PATH")
    if not os.path.exists(path):
        raise PolicySpecError(f"{path}: no such file")
    if not os.path.isfile(path):
        raise PolicySpecError(f"{path} is not a regular file (a directory, FIFO or device), "
                              f"not {what} zip")
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
            if META_MEMBER not in names:
                hint = (
                    " (a Stable-Baselines3 zip not written by mkv train-ppo)"
                    if "data" in names
                    else ""
                )
                raise PolicySpecError(f"{path}: not an mkv policy file, no {META_MEMBER}{hint}")
            meta = json.loads(zf.read(META_MEMBER).decode("utf-8"))
            if not isinstance(meta, dict):
                raise PolicySpecError(f"{path}: {META_MEMBER} is not a JSON object")
            got = meta.get("format")
            if got != fmt:
                if got in KIND_NAMES:
                    other, other_what = KIND_NAMES[got]
                    raise PolicySpecError(f"{path} is {other_what}, not {what}; use {other}:{path}")
                raise PolicySpecError(f"{path}: not {what} file (format {got!r})")
            missing = [m for m in members if m not in names]
            if missing:
                raise PolicySpecError(f"{path}: {what} file lacks {', '.join(missing)}")
            data = {m: zf.read(m) for m in members}
    except PolicySpecError:
        raise
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        zlib.error,
        RuntimeError,  # zipfile: a member flagged as encrypted
        EOFError,
        OSError,
        KeyError,
        UnicodeDecodeError,
        json.JSONDecodeError,
        NotImplementedError,
        ValueError,
    ) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise PolicySpecError(
            f"{path}: not a readable {prefix} policy zip (truncated or corrupt: {reason})"
        ) from None
    return meta, data


def check_env(meta: dict, env, path: str) -> None:
    """The env must have the sensor layout and action space the policy was trained with."""
    if env is None:
        return
    base = getattr(env, "unwrapped", env)
    names = list(getattr(base, "sensor_names", []))
    saved = list(meta.get("sensor_names", []))
    if names != saved:
        raise PolicySpecError(
            f"{os.path.basename(path)} was trained on sensors {saved} but env has {names}"
        )
    nvec = getattr(getattr(env, "action_space", None), "nvec", None)
    if nvec is not None and [int(v) for v in np.ravel(nvec)] != list(meta["action_nvec"]):
        raise PolicySpecError(
            f"{os.path.basename(path)} was trained on actions "
            f"{meta['action_nvec']} but env has {np.ravel(nvec).tolist()}"
        )


def rebuild_policy(arg: str, fmt: str, env, make_net, wrap):
    """Load a policy zip of kind ``fmt`` (``mkv-ppo``/``mkv-bc``) for a spec ``prefix:PATH``:
    read and check the zip and the env, build the network with ``make_net(meta, torch)``, load
    its weights (``weights_only``: nothing is unpickled) and return ``wrap(net, meta)``.
    Anything wrong with the file is one :class:`PolicySpecError` line."""
    prefix, what = KIND_NAMES[fmt]
    path = arg.strip()
    meta, files = read_policy_zip(path, fmt, ("policy.pth",))
    check_env(meta, env, path)
    torch = import_torch()
    try:
        net = make_net(meta, torch)
        net.load_state_dict(torch.load(io.BytesIO(files["policy.pth"]), map_location="cpu",
                                       weights_only=True))
        out = wrap(net, meta)
    except PolicySpecError:
        raise
    except Exception as e:  # corrupt weights or metadata: one line
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise PolicySpecError(f"{path}: cannot rebuild {what} ({reason})") from None
    out.spec = f"{prefix}:{path}"
    out.metadata = meta
    return out


# ---------------------------------------------------------------------- observation scaling
def rescale_observation(env: gym.Env) -> gym.Env:
    """``env`` with each observation channel mapped from its ``Box`` bounds to [-1, 1]: Gymnasium's
    own :class:`~gymnasium.wrappers.RescaleObservation` (float32 bounds, so no precision
    warning). PPO trains on this; a PPO zip written by ``mkv train-ppo`` runs under plain
    ``PPO.load`` on ``rescale_observation(gymnasium.make(env_id))``."""
    from gymnasium.wrappers import RescaleObservation

    return RescaleObservation(env, np.float32(-1.0), np.float32(1.0))


def rescale_function(low, high):
    """The map :func:`rescale_observation` applies, rebuilt from saved bounds: ``f(obs)`` for one
    observation or a batch, computed in float32 exactly as the wrapper does."""
    from gymnasium.wrappers.utils import rescale_box

    box = gym.spaces.Box(np.asarray(low, dtype=np.float32), np.asarray(high, dtype=np.float32),
                         dtype=np.float32)
    _, forward, _ = rescale_box(box, np.float32(-1.0), np.float32(1.0))
    return lambda obs: forward(np.asarray(obs, dtype=np.float32))


class FeatureObservation(gym.Wrapper):
    """Observations replaced by the shape-from-motion feature vector of a
    :class:`~mkv_env.features.FeatureSpec` (decaying traces of every channel, the
    previous command, ...), built online from the wrapped env's observations and the actions
    actually sent; reset at every episode start. Gives a reactive policy (PPO's MLP) the same
    short memory the SfM and BC policies see. Features are float32, like the network's input.
    """

    def __init__(self, env: gym.Env, spec: dict):
        from mkv_env.features import FeatureBuilder, FeatureSpec

        super().__init__(env)
        self.builder = FeatureBuilder(FeatureSpec.from_dict(spec))
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.builder.n_features,),
                                                np.float32)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.builder.reset()
        return self.builder.step(obs).astype(np.float32), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        feats = self.builder.step(obs, np.asarray(action, dtype=np.int64))
        return feats.astype(np.float32), reward, terminated, truncated, info


def make_observed_env(env_id: str, make_kwargs: dict, monitor: bool = True) -> gym.Env:
    """Env factory for (possibly subprocess) vector envs of ``mkv train-ppo``:
    ``gym.make(env_id, **make_kwargs)`` (``make_kwargs`` names the observation mode, rescaled
    or features, so the env itself gives the policy's inputs), SB3's Monitor on top. Picklable
    through functools.partial; imports :mod:`mkv_env` so the ids exist in a fresh worker."""
    import mkv_env  # noqa: F401

    env = gym.make(env_id, **make_kwargs)
    if monitor:
        from stable_baselines3.common.monitor import Monitor

        env = Monitor(env)
    return env


def make_rescaled_env(env_id: str, env_kwargs: dict, monitor: bool = True,
                      feature_spec: dict | None = None) -> gym.Env:
    """Env factory for (possibly subprocess) vector envs: picklable through functools.partial,
    and it imports :mod:`mkv_env` so the ids are registered in a fresh worker process. With
    ``feature_spec`` the rescaled observations go through :class:`FeatureObservation`."""
    import mkv_env  # noqa: F401

    env = rescale_observation(gym.make(env_id, **env_kwargs))
    if feature_spec is not None:
        env = FeatureObservation(env, feature_spec)
    if monitor:
        from stable_baselines3.common.monitor import Monitor

        env = Monitor(env)
    return env


# ---------------------------------------------------------------------- predict
class ActorPolicy:
    """SB3 ``predict`` over an SB3 ``ActorCriticPolicy``.

    ``transform(obs_2d) -> inputs_2d`` (float) turns observations into the network's inputs.
    Deterministic actions are the argmax of each command's logits (what SB3's ``predict`` with
    ``deterministic=True`` returns); stochastic ones are drawn from a numpy stream re-seeded by
    :meth:`reset`.
    """

    def __init__(self, policy, nvec, transform=None, seed: int | None = None):
        self.torch = import_torch()
        self.policy = policy
        self.policy.set_training_mode(False)
        self.nvec = [int(v) for v in nvec]
        self.bounds = np.cumsum([0, *self.nvec])
        self.transform = transform
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng(seed)

    def logits(self, inputs) -> np.ndarray:
        """Action logits, shape (n, sum(nvec)), for network inputs of shape (n, n_inputs)."""
        torch = self.torch
        p = self.policy
        with torch.no_grad():
            x = torch.as_tensor(np.asarray(inputs, dtype=np.float32))
            features = p.extract_features(x, p.pi_features_extractor)
            latent = p.mlp_extractor.forward_actor(features)
            return p.action_net(latent).numpy()

    def actions_from_logits(self, logits: np.ndarray, deterministic: bool = True) -> np.ndarray:
        out = np.empty((logits.shape[0], len(self.nvec)), dtype=np.int64)
        for j in range(len(self.nvec)):
            block = logits[:, self.bounds[j] : self.bounds[j + 1]]
            if deterministic:
                out[:, j] = np.argmax(block, axis=1)
            else:
                z = np.exp(block - block.max(axis=1, keepdims=True))
                cdf = np.cumsum(z / z.sum(axis=1, keepdims=True), axis=1)
                u = self.rng.random((block.shape[0], 1))
                out[:, j] = np.minimum((u > cdf).sum(axis=1), self.nvec[j] - 1)
        return out

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        obs = np.asarray(observation, dtype=np.float64)
        single = obs.ndim == 1
        obs2 = obs[None, :] if single else obs
        inputs = obs2 if self.transform is None else self.transform(obs2)
        actions = self.actions_from_logits(self.logits(inputs), deterministic)
        return (actions[0] if single else actions), state


class FeatureActorPolicy:
    """SB3 ``predict`` for a network trained on :class:`FeatureObservation` inputs: observations
    rescaled by ``transform``, then online features per env (each reset by its
    ``episode_start`` or by :meth:`reset`), then the actor; the actions taken are fed back as
    the next step's previous command, exactly as the training wrapper does."""

    def __init__(self, policy, nvec, spec: dict, transform=None, seed: int | None = None):
        from mkv_env.features import FeatureSpec, OnlineFeatures

        self.actor = ActorPolicy(policy, nvec, seed=seed)
        self.transform = transform
        self._online = OnlineFeatures(FeatureSpec.from_dict(spec))

    def reset(self, seed: int | None = None) -> None:
        self.actor.reset(seed)
        self._online.reset()

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        obs, single = self._online.as_batch(observation, "a PPO policy")
        if self.transform is not None:
            obs = self.transform(obs)
        feats = np.stack(self._online.step(obs, episode_start)).astype(np.float32)
        actions = self.actor.actions_from_logits(self.actor.logits(feats), deterministic)
        self._online.set_previous(actions)
        return (actions[0].copy() if single else actions), state
