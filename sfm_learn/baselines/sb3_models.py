"""The ``sb3:ALGO:PATH`` policy spec: any model zip saved by plain Stable-Baselines3 or rl-zoo3.

::

    mkv eval --env MKVJam-v0 --policy sb3:PPO:logs/ppo/MKVJam-v0_1/MKVJam-v0.zip --episodes 50

``ALGO`` names the class that saved the zip (case-insensitive): ``PPO``, ``A2C``, ``DQN``,
``SAC``, ``TD3``, ``DDPG`` from stable-baselines3, and ``RecurrentPPO``, ``TRPO``, ``QRDQN``,
``ARS`` from sb3-contrib when it is installed. The model must have been trained on the env's own
observation and action spaces (the loader checks them; DQN-style algorithms need a ``Discrete``
action space, which the MK-V envs do not have, so they are refused with that reason).

Observations are passed to the model as the env gives them, except:

* a zip written by ``mkv train-ppo``, ``mkv train-bc`` or ``mkv train-dagger`` (it carries
  ``mkv_meta.json``) is loaded by the project's own loader (``ppo:``, ``bc:``, ``dagger:``), which
  rebuilds the inputs it was trained on (rescaling, SfM features with the previous command), so
  ``sb3:PPO:FILE.zip`` and ``ppo:``/``bc:``/``dagger:FILE.zip`` act the same (PPO is the SB3 class
  of all three networks; another class name is refused in one line);
* rl-zoo3's observation normalisation: a ``vecnormalize.pkl`` beside the zip or in a folder named
  after the zip (rl-zoo3's ``<run>/<env>.zip`` + ``<run>/<env>/vecnormalize.pkl``), and nowhere
  else, is applied with its saved statistics (frozen).

Other rl-zoo3 wrappers (frame stacking, custom env wrappers) are not reproduced.

The returned policy has SB3's ``predict`` and passes ``state`` and ``episode_start`` through, so a
recurrent model (RecurrentPPO) keeps its memory across the steps of an episode: the episode
runners hand back the ``state`` it returns.

Trust: nothing in the zip or the ``vecnormalize.pkl`` runs as code. SB3 keeps some of a model's
settings as cloudpickle payloads (``:serialized:`` entries of the zip's ``data`` JSON); every one
is replaced before SB3 sees it (``custom_objects``): the spaces by the env's own (after checking
the zip's readable shape and type against them), the policy class by the algorithm's
``MlpPolicy`` class, ``policy_kwargs`` rebuilt from their readable JSON through allowlists
(``net_arch``, activation functions of ``torch.nn``, ...), schedules by constants and training
state by nothing. Weights are read with ``torch.load(weights_only=True)``. ``vecnormalize.pkl`` is
read by a restricted unpickler that admits only numpy arrays, Gymnasium spaces and SB3's
``VecNormalize``/``RunningMeanStd``. A zip that cannot be read this way (a custom policy class,
unknown ``policy_kwargs``) is refused in one line; ``mkv ... --trust-pickle`` (the environment
variable ``MKV_TRUST_PICKLE=1``) loads it the way ``ALGO.load`` does, unpickling included, for
files you trust as you would a Python script.
"""

from __future__ import annotations

import importlib
import json
import os
import pickle
import re
import zipfile

import numpy as np

from mkv_env.policies import PolicySpecError

__all__ = ["ALGORITHMS", "SB3Model", "TRUST_ENV", "check_spec", "find_vecnormalize",
           "load_spec", "trusted"]

#: Environment variable that lets sb3: specs unpickle (set by ``--trust-pickle``; inherited by
#: evaluation workers).
TRUST_ENV = "MKV_TRUST_PICKLE"


def trusted() -> bool:
    """True when the user allowed unpickling (``--trust-pickle`` / ``MKV_TRUST_PICKLE=1``)."""
    return os.environ.get(TRUST_ENV, "") == "1"

#: Algorithm name (lower case) -> (module, class).
ALGORITHMS = {
    "ppo": ("stable_baselines3", "PPO"),
    "a2c": ("stable_baselines3", "A2C"),
    "dqn": ("stable_baselines3", "DQN"),
    "sac": ("stable_baselines3", "SAC"),
    "td3": ("stable_baselines3", "TD3"),
    "ddpg": ("stable_baselines3", "DDPG"),
    "recurrentppo": ("sb3_contrib", "RecurrentPPO"),
    "trpo": ("sb3_contrib", "TRPO"),
    "qrdqn": ("sb3_contrib", "QRDQN"),
    "ars": ("sb3_contrib", "ARS"),
}

# What rl-zoo3's enjoy.py passes so zips from other SB3 versions load without their schedules.
_CUSTOM_OBJECTS = {"learning_rate": 0.0, "lr_schedule": lambda _: 0.0,
                   "clip_range": lambda _: 0.0}


class SB3Model:
    """SB3's ``predict`` over a loaded model, with the observation transform it was trained with.

    ``predict`` takes one observation or a batch (n_envs, n_obs) and returns the model's own
    ``(actions, state)``; ``episode_start`` is passed as one bool per env.
    """

    def __init__(self, model, transform=None, spec: str = "sb3", observer=None):
        self.model = model
        self.transform = transform
        self.spec = spec
        self.observer = observer

    def reset(self, seed: int | None = None) -> None:
        """Seed the model's sampling (used by ``deterministic=False``); a new episode."""
        if seed is not None:
            self.model.set_random_seed(int(seed) % 2**32)
        if self.observer is not None:
            self.observer.online.reset()

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        obs = np.asarray(observation)
        if self.transform is not None:
            obs = self.transform(obs)
        n_envs = 1 if obs.ndim == 1 else obs.shape[0]
        if episode_start is not None:
            episode_start = np.broadcast_to(
                np.asarray(episode_start, dtype=bool).reshape(-1), (n_envs,)).copy()
        if self.observer is None:
            return self.model.predict(obs, state=state, episode_start=episode_start,
                                      deterministic=deterministic)
        batch, single = self.observer.online.as_batch(obs, self.spec)
        inputs = np.stack(self.observer.online.step(batch, episode_start)).astype(np.float32)
        actions, state = self.model.predict(inputs, state=state, episode_start=episode_start,
                                            deterministic=deterministic)
        self.observer.online.set_previous(np.asarray(actions).reshape(len(batch), -1))
        return (actions[0] if single else actions), state


class EnvObservation:
    """An MK-V env's observation mode (``gym.make(id, observation=...)``) rebuilt from raw
    readings, for a model trained on such an env (an rl-zoo3 run whose ``env_kwargs`` name
    it): ``transform`` rescales to [-1, 1] exactly as the env does; for ``features`` the
    ``online`` builder adds the SfM features with each env's previous command."""

    def __init__(self, mode: str, sensor_names, low, high, action_nvec):
        from mkv_env.features import OnlineFeatures, default_feature_spec
        from sfm_learn.baselines.sb3 import rescale_function

        self.mode = mode
        self.transform = rescale_function(low, high)
        spec = default_feature_spec(list(sensor_names), list(action_nvec))
        self.online = OnlineFeatures(spec) if mode == "features" else None
        n = spec.n_features if mode == "features" else len(sensor_names)
        import gymnasium as gym

        self.space = (gym.spaces.Box(-np.inf, np.inf, (n,), np.float32) if mode == "features"
                      else gym.spaces.Box(-1.0, 1.0, (n,), np.float32))


def zoo_observation(path: str) -> str | None:
    """The env observation mode an rl-zoo3 run trained with (``env_kwargs: {observation: ...}``
    in ``<folder>/<zip stem>/config.yml``), or None (no such file, no such key, unreadable)."""
    folder = os.path.dirname(os.path.abspath(path))
    stem = os.path.splitext(os.path.basename(path))[0]
    cfg = os.path.join(folder, stem, "config.yml")
    if not os.path.isfile(cfg) or os.path.getsize(cfg) > 1_000_000:
        return None
    try:
        import yaml

        with open(cfg, encoding="utf-8") as f:
            # rl-zoo3's config.yml is a python-tagged OrderedDict: read as a plain mapping by a
            # SafeLoader that admits that one tag (nothing is built from any other python tag)
            doc = yaml.load(f, Loader=yaml_loader_base())  # noqa: S506
    except Exception:  # a damaged or foreign config: not an mkv observation mode
        return None
    kw = doc.get("env_kwargs") if isinstance(doc, dict) else None
    mode = kw.get("observation") if isinstance(kw, dict) else None
    return mode if mode in ("rescaled", "features") else None


def yaml_loader_base():
    """yaml's SafeLoader (or a stand-in without PyYAML), with rl-zoo3's OrderedDict tag."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def ordered(loader, node):
        pairs = loader.construct_sequence(node.value[0], deep=True) if node.value else []
        return {k: v for k, v in pairs}

    Loader.add_constructor("tag:yaml.org,2002:python/object/apply:collections.OrderedDict",
                           ordered)
    return Loader


def find_vecnormalize(path: str) -> str | None:
    """rl-zoo3's ``vecnormalize.pkl`` for a model zip at ``path``: in rl-zoo3's own layout
    (``<folder>/<zip stem>/vecnormalize.pkl``) or beside the zip, as a regular file; else None."""
    folder = os.path.dirname(os.path.abspath(path))
    stem = os.path.splitext(os.path.basename(path))[0]
    for candidate in (os.path.join(folder, stem, "vecnormalize.pkl"),
                      os.path.join(folder, "vecnormalize.pkl")):
        if os.path.isfile(candidate):
            return candidate
    return None


#: What a vecnormalize.pkl may name: numpy arrays and scalars, Gymnasium spaces, SB3's own
#: normalisation classes. Anything else (a payload's os.system, builtins.eval, ...) is refused.
_PICKLE_ALLOWED = {
    ("stable_baselines3.common.vec_env.vec_normalize", "VecNormalize"),
    ("stable_baselines3.common.running_mean_std", "RunningMeanStd"),
    ("gymnasium.spaces.box", "Box"), ("gymnasium.spaces.discrete", "Discrete"),
    ("gymnasium.spaces.multi_discrete", "MultiDiscrete"),
    ("gymnasium.spaces.multi_binary", "MultiBinary"), ("gymnasium.spaces.dict", "Dict"),
    ("gymnasium.spaces.tuple", "Tuple"), ("collections", "OrderedDict"),
    ("numpy", "dtype"), ("numpy", "ndarray"),
    ("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"), ("numpy.core.multiarray", "scalar"),
    ("numpy.random._pickle", "__generator_ctor"), ("numpy.random._pickle", "__bit_generator_ctor"),
    ("numpy.random._pickle", "__randomstate_ctor"),
    ("numpy.random._pcg64", "PCG64"), ("numpy.random._mt19937", "MT19937"),
    ("numpy.random.bit_generator", "SeedSequence"),
    ("numpy.random.bit_generator", "__pyx_unpickle_SeedSequence"),
}


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if (module, name) not in _PICKLE_ALLOWED:
            raise pickle.UnpicklingError(f"it names {module}.{name}, which is not a numpy "
                                         "array, a space or SB3's VecNormalize")
        return super().find_class(module, name)


def _read_vecnormalize(pkl: str):
    from stable_baselines3.common.vec_env import VecNormalize

    with open(pkl, "rb") as f:
        stats = pickle.load(f) if trusted() else _RestrictedUnpickler(f).load()
    if not isinstance(stats, VecNormalize):
        raise PolicySpecError(f"{pkl}: holds a {type(stats).__name__}, not SB3's VecNormalize "
                              "statistics")
    return stats


def _vecnormalize_transform(pkl: str):
    stats = _read_vecnormalize(pkl)
    if not getattr(stats, "norm_obs", False):
        return None
    return lambda obs: stats.normalize_obs(np.asarray(obs, dtype=np.float32))


# ---------------------------------------------------------------------- reading a zip safely
def _zip_data(path: str, algo: str) -> dict:
    """The zip's ``data`` member as JSON (read as text: nothing unpickled)."""
    why = None
    try:
        with zipfile.ZipFile(path) as zf:
            data = json.loads(zf.read("data"))
        if not isinstance(data, dict):
            why = "its 'data' member is not a JSON object"
    except KeyError:
        why = "no 'data' member"
    except zipfile.BadZipFile:
        why = "not a zip file"
    except (OSError, ValueError, RecursionError) as e:
        why = f"unreadable 'data' member: {type(e).__name__}"
    if why is not None:
        raise PolicySpecError(f"{path}: cannot load it as a {algo} zip ({why})")
    return data


def _serialized(item) -> bool:
    return isinstance(item, dict) and ":serialized:" in item


#: Keys that tell which algorithm saved a zip (all must be in its data), and keys it must not have.
_ALGO_SIGNS = {
    "PPO": ({"clip_range", "n_epochs"}, {"cg_max_steps"}),
    "RecurrentPPO": ({"clip_range", "n_epochs"}, {"cg_max_steps"}),
    "A2C": ({"n_steps", "vf_coef"}, {"clip_range", "n_epochs", "cg_max_steps"}),
    "TRPO": ({"cg_max_steps", "n_critic_updates"}, set()),
    "DQN": ({"exploration_fraction", "target_update_interval"}, set()),
    "QRDQN": ({"exploration_fraction", "target_update_interval"}, set()),
    "SAC": ({"target_entropy", "tau"}, set()),
    "TD3": ({"policy_delay", "target_policy_noise"}, set()),
    "DDPG": ({"policy_delay", "target_policy_noise"}, set()),
    "ARS": ({"n_delta", "n_top"}, set()),
}


def _saved_by(data: dict) -> str | None:
    """The algorithm that wrote ``data`` (None if it matches none)."""
    module = data.get("policy_class", {})
    module = module.get("__module__", "") if isinstance(module, dict) else ""
    for name, (need, never) in _ALGO_SIGNS.items():
        if need <= data.keys() and not never & data.keys():
            if name in ("PPO", "RecurrentPPO"):
                return "RecurrentPPO" if "recurrent" in module else "PPO"
            if name in ("DQN", "QRDQN"):
                return "QRDQN" if "qrdqn" in module else "DQN"
            return name
    return None


def _check_algorithm(data: dict, cls, path: str) -> None:
    saved = _saved_by(data)
    want = cls.__name__
    same = saved == want or {saved, want} == {"TD3", "DDPG"}
    if saved is not None and not same:
        raise PolicySpecError(f"{path} was saved by {saved}, not {want}: use sb3:{saved}:{path}")


_ACTIVATIONS = ("Tanh", "ReLU", "ELU", "LeakyReLU", "GELU", "SiLU", "Sigmoid", "SELU", "Mish",
                "Softplus", "Hardtanh", "Identity")
_OPTIMIZERS = ("Adam", "AdamW", "RMSprop", "SGD")
_CLASS_RE = re.compile(r"^<class '([A-Za-z0-9_.]+)'>$")
# policy_kwargs entries that are plain JSON values
_PLAIN_KWARGS = {"net_arch", "ortho_init", "log_std_init", "squash_output", "use_expln",
                 "full_std", "share_features_extractor", "normalize_images", "lstm_hidden_size",
                 "n_lstm_layers", "shared_lstm", "enable_critic_lstm", "n_critics",
                 "optimizer_kwargs", "features_extractor_kwargs", "lstm_kwargs", "n_quantiles",
                 "dueling", "use_sde", "clip_mean", "with_bias"}


def _class_named(text, module_prefix: str, allowed: tuple[str, ...]):
    """The class that SB3 wrote as ``"<class 'torch.nn.modules.activation.Tanh'>"``, if it is in
    ``allowed`` and under ``module_prefix``; else None."""
    m = _CLASS_RE.match(text) if isinstance(text, str) else None
    if m is None:
        return None
    module, _, name = m.group(1).rpartition(".")
    if name not in allowed or not module.startswith(module_prefix):
        return None
    return getattr(importlib.import_module(module), name, None)


def _policy_kwargs(item, path: str) -> dict:
    """``policy_kwargs`` rebuilt from the readable part of its JSON (allowlisted keys only)."""
    out = {}
    for key, value in item.items():
        if key in (":type:", ":serialized:"):
            continue
        if key in _PLAIN_KWARGS:
            out[key] = value
        elif key == "activation_fn":
            cls = _class_named(value, "torch.nn", _ACTIVATIONS)
            if cls is None:
                raise PolicySpecError(f"{path}: policy_kwargs activation_fn {value!r} is not a "
                                      "torch.nn activation this loader knows (--trust-pickle to "
                                      "unpickle it)")
            out[key] = cls
        elif key == "optimizer_class":
            cls = _class_named(value, "torch.optim", _OPTIMIZERS)
            if cls is None:
                raise PolicySpecError(f"{path}: policy_kwargs optimizer_class {value!r} is not "
                                      "one this loader knows (--trust-pickle to unpickle it)")
            out[key] = cls
        elif key == "features_extractor_class":
            cls = _class_named(value, "stable_baselines3.common.torch_layers",
                               ("FlattenExtractor",))
            if cls is None:
                raise PolicySpecError(f"{path}: policy_kwargs features_extractor_class {value!r} "
                                      "is custom code (--trust-pickle to unpickle it)")
            out[key] = cls
        else:
            raise PolicySpecError(f"{path}: policy_kwargs has {key!r}, which this loader does "
                                  "not rebuild without unpickling (--trust-pickle to allow it)")
    return out


def _space_matches(item, space) -> bool:
    """Does the readable part of a serialized space (its type and shape) describe ``space``?"""
    if not isinstance(item, dict):
        return False
    if not str(item.get(":type:", "")).endswith(f".{type(space).__name__}'>"):
        return False
    shape = item.get("_shape")
    if shape is not None and tuple(shape) != tuple(space.shape or ()):
        return False
    nvec = item.get("nvec")
    return nvec is None or hasattr(space, "nvec") and nvec == str(space.nvec)


_METHOD_RE = re.compile(r"^<function ([A-Za-z_][A-Za-z0-9_]*)\.")


def _policy_class(item, cls, path: str):
    """The algorithm's own policy class that the zip names (by module and by the class name in
    its methods' readable names); never unpickled. A custom class is refused."""
    module = item.get("__module__") if isinstance(item, dict) else None
    names = {m.group(1) for v in (item.values() if isinstance(item, dict) else ())
             if isinstance(v, str) and (m := _METHOD_RE.match(v))}
    for policy in dict.fromkeys(cls.policy_aliases.values()):
        if policy.__module__ == module and (not names or policy.__name__ in names):
            return policy
    raise PolicySpecError(f"{path}: its policy class ({module}: {', '.join(sorted(names)) or '?'})"
                          f" is not one of {cls.__name__}'s own (--trust-pickle to unpickle it)")


def _safe_custom_objects(data: dict, cls, env, path: str) -> dict:
    """``custom_objects`` for :meth:`cls.load` that replace every ``:serialized:`` entry of the
    zip's data, so nothing is unpickled (see the module doc)."""
    name = os.path.basename(path)
    out = {"learning_rate": 0.0, "lr_schedule": lambda _: 0.0, "clip_range": lambda _: 0.0}
    for key in ("action_space", "observation_space"):  # checked first, actions first
        item = data.get(key)
        if not _serialized(item):
            continue
        if env is None:
            raise PolicySpecError(f"{path}: loading an SB3 zip without unpickling needs the env "
                                  "(its spaces replace the zip's)")
        space = getattr(env, key)
        if not _space_matches(item, space):
            kind = str(item.get(":type:", "?")).rpartition(".")[2].rstrip("'>")
            shape = tuple(item.get("_shape") or ())
            if key == "action_space":
                raise PolicySpecError(f"{name} ({cls.__name__}) acts in a {kind} of shape {shape}"
                                      f" {item.get('nvec', '')} but the env's action space is "
                                      f"{space}")
            raise PolicySpecError(f"{name} ({cls.__name__}) expects observations of shape "
                                  f"{shape} ({kind}) but the env gives {space.shape}")
        out[key] = space
    for key, item in data.items():
        if not _serialized(item) or key in out:
            continue
        if key == "policy_class":
            out[key] = _policy_class(item, cls, path)
        elif key == "policy_kwargs":
            out[key] = _policy_kwargs(item, path)
        elif key in ("clip_range_vf",):
            out[key] = lambda _: 0.0
        else:  # training state (buffers' classes, last observations, noise): not needed to act
            out[key] = None
    return out


def _algorithm(name: str):
    key = name.strip().lower().replace("-", "").replace("_", "")
    if key not in ALGORITHMS:
        raise PolicySpecError(f"unknown SB3 algorithm {name!r}; known: "
                              + ", ".join(cls for _, cls in ALGORITHMS.values()))
    module, cls = ALGORITHMS[key]
    try:
        return getattr(importlib.import_module(module), cls)
    except ImportError:
        extra = "sb3-contrib" if module == "sb3_contrib" else "stable-baselines3"
        raise PolicySpecError(f"sb3:{cls} needs {extra} (pip install {extra})") from None


def check_spec(arg: str):
    """Validate ``ALGO:PATH`` without reading the file: (algorithm class, path)."""
    algo, sep, path = arg.partition(":")
    path = path.strip()
    if not sep or not algo.strip() or not path:
        raise PolicySpecError("sb3 needs an algorithm and a file: sb3:ALGO:PATH, e.g. "
                              "sb3:PPO:model.zip")
    cls = _algorithm(algo)
    if not os.path.exists(path):
        raise PolicySpecError(f"{path}: no such file")
    if os.path.isdir(path):
        raise PolicySpecError(f"{path} is a directory, not a model zip")
    if not os.path.isfile(path):
        raise PolicySpecError(f"{path} is not a regular file")
    return cls, path


def _project_format(path: str) -> str | None:
    """``mkv-ppo`` / ``mkv-bc`` / ``mkv-dagger`` for a zip the project wrote, else None."""
    try:
        with zipfile.ZipFile(path) as zf:
            if "mkv_meta.json" not in zf.namelist():
                return None
            meta = json.loads(zf.read("mkv_meta.json"))
    except (zipfile.BadZipFile, OSError, ValueError, RecursionError):
        return None
    fmt = meta.get("format") if isinstance(meta, dict) else None
    return fmt if fmt in ("mkv-ppo", "mkv-bc", "mkv-dagger") else None


def load_spec(arg: str, env, seed):
    """``sb3:ALGO:PATH`` -> :class:`SB3Model` (nothing unpickled unless :func:`trusted`); a zip
    the project wrote goes to its own loader (module doc)."""
    cls, path = check_spec(arg)
    fmt = _project_format(path)
    if fmt is not None:
        kind = fmt.removeprefix("mkv-")
        if cls.__name__ != "PPO":
            raise PolicySpecError(f"{path} was written by mkv train-{kind} (an SB3 PPO policy "
                                  f"network): load it as sb3:PPO:{path} or {kind}:{path}")
        module = importlib.import_module(f"sfm_learn.baselines.{kind}")
        return module.load_spec(path, env, seed)
    from sfm_learn.baselines.sb3 import import_torch

    import_torch()
    observer = None
    mode = zoo_observation(path)
    if mode is not None and env is not None and hasattr(env.unwrapped, "sensor_names") and (
            getattr(env.unwrapped, "observation", "raw") == "raw"):
        # trained on gym.make(id, observation=mode): rebuild that observation from the readings
        space = env.observation_space
        observer = EnvObservation(mode, env.unwrapped.sensor_names, space.low, space.high,
                                  env.action_space.nvec)
        env = _SpacesOf(observer.space, env.action_space)
    if trusted():
        custom = _CUSTOM_OBJECTS
    else:
        data = _zip_data(path, cls.__name__)
        _check_algorithm(data, cls, path)
        custom = _safe_custom_objects(data, cls, env, path)
    try:
        model = cls.load(path, device="cpu", custom_objects=custom)
    except Exception as e:  # a corrupt or foreign file: one line
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise PolicySpecError(f"{path}: cannot load it as a {cls.__name__} zip ({reason})") \
            from None
    if env is not None:
        _check_spaces(model, env, path, cls.__name__)
    transform = None
    pkl = find_vecnormalize(path)
    if pkl is not None:
        try:
            transform = _vecnormalize_transform(pkl)
        except PolicySpecError:
            raise
        except pickle.UnpicklingError as e:
            raise PolicySpecError(f"{pkl}: refused: {e} (--trust-pickle to unpickle it anyway)") \
                from None
        except Exception as e:
            raise PolicySpecError(f"{pkl}: cannot read the normalisation statistics "
                                  f"({type(e).__name__})") from None
    if observer is not None:
        transform = observer.transform
    policy = SB3Model(model, transform, spec=f"sb3:{cls.__name__}:{path}", observer=observer)
    if seed is not None:
        policy.reset(seed)
    return policy


class _SpacesOf:
    """The spaces a model is checked against (an env's, or those of an observation mode)."""

    def __init__(self, observation_space, action_space):
        self.observation_space, self.action_space = observation_space, action_space
        self.unwrapped = self


def _check_spaces(model, env, path: str, algo: str) -> None:
    name = os.path.basename(path)
    m_act, e_act = model.action_space, env.action_space
    if type(m_act) is not type(e_act) or getattr(m_act, "shape", None) != e_act.shape or (
            hasattr(e_act, "nvec") and not np.array_equal(m_act.nvec, e_act.nvec)):
        raise PolicySpecError(f"{name} ({algo}) acts in {m_act} but the env's action space is "
                              f"{e_act}")
    m_obs, e_obs = model.observation_space, env.observation_space
    if getattr(m_obs, "shape", None) != getattr(e_obs, "shape", None):
        raise PolicySpecError(f"{name} ({algo}) expects observations of shape {m_obs.shape} but "
                              f"the env gives {e_obs.shape}")
