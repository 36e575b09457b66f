"""``mkv train-ppo`` and the ``ppo:PATH`` policy spec: Stable-Baselines3 PPO on the env reward.

::

    mkv train-ppo --env MKVJam-v0 --timesteps 100000 --out ppo.zip [--seed 0] [--n-envs 2]
                  [--vec sync|async] [--eval-every STEPS] [--eval-episodes 10]
                  [--eval-seed 10000] [--checkpoint-dir DIR] [--env-kwargs JSON] [--quiet]
    mkv eval --env MKVJam-v0 --policy ppo:ppo.zip --episodes 50 --seed 1000

Training: SB3 ``PPO("MlpPolicy")`` on ``n_envs`` copies of the env (``DummyVecEnv`` for
``--vec sync``, ``SubprocVecEnv`` for ``async``; env ``i`` of the vector is reset first with seed
``seed + i``), actions ``MultiDiscrete([3, 3])``. The policy sees the raw sensor observation
with each channel mapped from its ``Box`` bounds to [-1, 1] (a fixed scaling stored in the file,
no running statistics). Hyperparameters (:data:`DEFAULTS`, chosen for this small problem: 10
inputs, 9 actions, episodes of 300-600 steps): rollouts of ``n_steps=512`` steps per env,
minibatch 64, 4 epochs per rollout, Adam 3e-4, gamma 0.99, GAE lambda 0.95, clip 0.2, entropy
coefficient 0.01 (keeps the 3x3 command distribution from collapsing early), tanh MLP 64x64 for
both policy and value. A budget smaller than one rollout shrinks ``n_steps`` (and the minibatch)
to fit, so tiny test budgets run as asked. SB3 always finishes a rollout, so the steps actually
used are ``timesteps`` rounded up to a multiple of ``n_steps * n_envs``.

Evaluation (the learning curve): before training and then at the first rollout boundary at or
after every ``--eval-every`` env steps (default: a tenth of the budget), and once at the end, the
current policy runs ``--eval-episodes`` episodes on the fixed seeds ``eval_seed + i`` with
deterministic (argmax) actions through :func:`sfm_learn.evaluation.evaluate`, the same runner and
metrics as ``mkv eval``. Each point holds ``env_steps`` (steps trained on, exactly), ``wall_s``
(training wall time so far, evaluation and checkpoint time excluded), ``mean_return``,
``escape_rate`` (``null`` on envs without escapes, e.g. ``MKV-v0``) and ``distance_m``. With
``--checkpoint-dir``, every evaluation also writes ``DIR/ppo_<steps>.zip`` (a full, loadable file).

File format: SB3's own model zip (``PPO.load(path)`` works on it) plus one extra member
``mkv_meta.json`` (:func:`read_metadata`): ``format`` (``"mkv-ppo"``), ``env_id``,
``env_kwargs``, ``sensor_names``, ``action_nvec``, ``obs_scaling`` (``centre``, ``half``),
``seed``, ``n_envs``, ``vec``, ``timesteps`` (env steps used), ``timesteps_requested``,
``train_wall_s``, ``eval_wall_s``, ``hyperparameters``, ``eval`` (episodes, seed),
``learning_curve``, ``final_eval``, ``package_version``, ``sb3_version``, ``torch_version``.
The ``ppo:PATH`` loader rebuilds the policy network from ``policy.pth`` (weights only, no
unpickling of ``data``), checks the env's sensor layout and returns an object with SB3 ``predict``.

Measured (2-core machine shared with other jobs; SB3 2.9.2, torch 2.13 CPU, one thread): about
1,900 env steps/s of training on ``MKV-v0`` with the default 2 sync envs (3,300 with 8 envs; the
SB3 per-step policy call dominates, not the env), about 1,450 on ``MKVJam-v0`` (its resets
simulate the robot into the jam). On ``MKV-v0`` PPO (seed 0; 10 evaluation episodes) reaches a
return of 53 after 10k steps but is unstable (0-1 at 20k-30k, 46-51 from 40k to 100k except 20
at 70k); the teacher scores 46 while driving 14.7 m per episode, PPO drives 5-7 m.
On ``MKVJam-v0`` with the env's default reward PPO learns to stand still
(return 0, escape rate 0 at 50k and 100k steps; also with ``ent_coef`` 0.05, ``gamma`` 0.995 or
``escape_reward`` 20): backing out costs negative progress reward, and the teacher itself only
earns a mean return of about 0.2 there, so "off" is nearly optimal for this reward.
"""

from __future__ import annotations

import functools
import io
import math
import os
import time

import numpy as np

from sfm_common.files import atomic_write_bytes
from sfm_learn.baselines import sb3

FORMAT = "mkv-ppo"
FORMAT_VERSION = 3  # 3: optional feature_spec; 2: obs_rescale (RescaleObservation); 1: obs_scaling
OBSERVATIONS = ("raw", "features")

#: PPO hyperparameters used unless overridden on the command line.
DEFAULTS = {
    "n_steps": 512,
    "batch_size": 64,
    "n_epochs": 4,
    "learning_rate": 3e-4,
    "gamma": 0.99,
    "gae_lambda": 0.95,
    "clip_range": 0.2,
    "ent_coef": 0.01,
    "vf_coef": 0.5,
    "max_grad_norm": 0.5,
    "net_arch": [64, 64],
}


HYPERPARAMS_FILE = os.path.join(os.path.dirname(__file__), "hyperparams", "ppo.yml")
"""The packaged rl-zoo3-style hyperparameter file (one entry per env id, plus ``default``)."""
_HP_KEYS = {"n_envs", "n_timesteps", "observation", *DEFAULTS}


def load_hyperparameters(env_id: str, path: str | None = None) -> dict:
    """The hyperparameter entry of ``env_id`` (else ``default``) in an rl-zoo3-style YAML file
    (:data:`HYPERPARAMS_FILE` when ``path`` is None), over :data:`DEFAULTS`; ValueError (one
    line) on a missing/unreadable file, unknown keys or values of the wrong kind."""
    try:
        import yaml
    except ImportError:
        raise ValueError("reading a hyperparameter file needs PyYAML: pip install pyyaml") from None
    path = HYPERPARAMS_FILE if path is None else os.fspath(path)
    if os.path.exists(path) and not os.path.isfile(path):  # a FIFO or device would block
        raise ValueError(f"hyperparameter file {path} is not a regular file")
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except OSError as e:
        raise ValueError(f"cannot read hyperparameter file {path}: {e.strerror}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise ValueError(f"hyperparameter file {path} is not valid YAML: "
                         f"{str(e).splitlines()[0]}") from None
    except RecursionError:
        raise ValueError(f"hyperparameter file {path} is nested too deeply") from None
    if not isinstance(doc, dict):
        raise ValueError(f"hyperparameter file {path} must map env ids to settings")
    entry = doc.get(env_id, doc.get("default", {}))
    if not isinstance(entry, dict):
        raise ValueError(f"hyperparameter entry for {env_id} in {path} is not a mapping")
    entry = _from_rl_zoo3(dict(entry), env_id, path)
    unknown = set(entry) - _HP_KEYS
    if unknown:
        raise ValueError(f"unknown hyperparameter(s) {sorted(unknown)} in {path}; "
                         f"known: {sorted(_HP_KEYS)}")
    hp = {**DEFAULTS, "n_envs": 2, "n_timesteps": 100_000, "observation": "raw", **entry}
    ints = ("n_envs", "n_timesteps", "n_steps", "batch_size", "n_epochs")
    floats = ("learning_rate", "gamma", "gae_lambda", "clip_range", "ent_coef", "vf_coef",
              "max_grad_norm")
    try:
        for k in ints:
            v = hp[k]
            if isinstance(v, bool) or float(v) != int(v) or int(v) < 1:
                raise ValueError(k)
            hp[k] = int(v)
        for k in floats:
            if isinstance(hp[k], bool) or not math.isfinite(float(hp[k])) or float(hp[k]) < 0:
                raise ValueError(k)
            hp[k] = float(hp[k])
        arch = hp["net_arch"]
        if (not isinstance(arch, list) or not arch
                or not all(isinstance(u, int) and 1 <= u <= 4096 for u in arch)):
            raise ValueError("net_arch")
    except (TypeError, ValueError) as e:
        raise ValueError(f"hyperparameter {e.args[0] if e.args else ''} of {env_id} in {path} "
                         "has a bad value") from None
    if hp["observation"] not in OBSERVATIONS:
        raise ValueError(f"observation of {env_id} in {path} must be one of {OBSERVATIONS}")
    return hp


#: rl-zoo3 keys this trainer cannot honour, and why (a one-line refusal names them).
_ZOO_REFUSED = {
    "env_wrapper": "env wrappers are not applied by mkv train-ppo (its own wrappers: "
                   "RescaleObservation and, with observation: features, FeatureObservation)",
    "frame_stack": "frame stacking is not applied by mkv train-ppo",
    "callback": "callbacks are not loaded from a hyperparameter file",
    "vec_env_wrapper": "vec env wrappers are not applied by mkv train-ppo",
    "policy_delay": "not a PPO setting", "train_freq": "not a PPO setting",
}


def _zoo_policy_kwargs(text, env_id: str, path: str) -> dict:
    """rl-zoo3's ``policy_kwargs: "dict(net_arch=[64, 64], activation_fn=nn.Tanh)"`` read as
    data (``ast``, nothing evaluated): net_arch (a list of widths) and a Tanh activation, the
    tanh MLP this trainer builds; anything else is refused."""
    import ast

    where = f"policy_kwargs of {env_id} in {path}"
    if isinstance(text, dict):
        items = text
    else:
        try:
            node = ast.parse(str(text), mode="eval").body
        except SyntaxError:
            raise ValueError(f"{where} is not dict(...)") from None
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id == "dict" and not node.args):
            raise ValueError(f"{where} must be dict(key=value, ...)")
        items = {}
        for kw in node.keywords:
            if kw.arg == "activation_fn":
                items[kw.arg] = ast.unparse(kw.value)
            else:
                try:
                    items[kw.arg] = ast.literal_eval(kw.value)
                except ValueError:
                    raise ValueError(f"{where}: {kw.arg} is not a plain value") from None
    out = {}
    for key, value in items.items():
        if key == "net_arch":
            if isinstance(value, dict) and value.get("pi") == value.get("vf"):
                value = value.get("pi")
            if isinstance(value, list) and value and isinstance(value[0], dict):
                value = value[0].get("pi") if value[0].get("pi") == value[0].get("vf") else None
            out["net_arch"] = value
        elif key == "activation_fn":
            if str(value).rsplit(".", 1)[-1] != "Tanh":
                raise ValueError(f"{where}: activation_fn {value} is not supported (mkv "
                                 "train-ppo builds a tanh MLP)")
        elif key == "ortho_init" and value is True:
            pass  # SB3's default
        else:
            raise ValueError(f"{where}: {key} is not supported by mkv train-ppo")
    return out


def _from_rl_zoo3(entry: dict, env_id: str, path: str) -> dict:
    """An rl-zoo3 entry in this trainer's terms: ``policy: MlpPolicy`` and ``normalize: false``
    accepted, ``policy_kwargs`` read as data, what cannot be honoured refused in one line."""
    where = f"{env_id} in {path}"
    if "policy" in entry:
        if entry.pop("policy") != "MlpPolicy":
            raise ValueError(f"policy of {where}: only MlpPolicy is supported")
    if "normalize" in entry:
        norm = entry.pop("normalize")
        if norm not in (False, "false", "False", None):
            raise ValueError(f"normalize of {where}: VecNormalize is not supported by mkv "
                             "train-ppo, which rescales observations to [-1, 1] itself "
                             "(RescaleObservation); use normalize: false")
    if "policy_kwargs" in entry:
        entry.update(_zoo_policy_kwargs(entry.pop("policy_kwargs"), env_id, path))
    if "env_kwargs" in entry:  # rl-zoo3's way to name the env's observation mode
        kw = entry.pop("env_kwargs")
        if not isinstance(kw, dict) or set(kw) - {"observation"}:
            raise ValueError(f"env_kwargs of {where}: only {{observation: rescaled | features}} "
                             "is read from a hyperparameter file (give other env kwargs with "
                             "--env-kwargs)")
        obs = kw.get("observation", "rescaled")
        if obs not in ("rescaled", "features"):
            raise ValueError(f"env_kwargs.observation of {where} must be rescaled or features "
                             "(mkv train-ppo always rescales the readings to [-1, 1])")
        entry["observation"] = "raw" if obs == "rescaled" else "features"
    for key in list(entry):
        if key in _ZOO_REFUSED:
            raise ValueError(f"{key} of {where}: {_ZOO_REFUSED[key]}")
        if isinstance(entry[key], str) and entry[key].startswith("lin_"):
            raise ValueError(f"{key} of {where}: schedules ({entry[key]}) are not supported; "
                             "give a number")
    return entry


# ---------------------------------------------------------------------- training
def rollout_steps(timesteps: int, n_envs: int, n_steps: int) -> int:
    """Rollout steps per env: ``n_steps``, shrunk for budgets smaller than one rollout."""
    if timesteps < n_envs * n_steps:
        return max(2, math.ceil(timesteps / n_envs))
    return n_steps


def planned_timesteps(timesteps: int, n_envs: int, n_steps: int) -> int:
    """Env steps PPO will actually take: ``timesteps`` rounded up to whole rollouts (SB3 always
    finishes a rollout)."""
    per_rollout = n_envs * rollout_steps(timesteps, n_envs, n_steps)
    return math.ceil(timesteps / per_rollout) * per_rollout


def check_env(env_id: str, env_kwargs: dict):
    """Make the env once (fail fast, one line) and return its sensor names, action nvec, bounds."""
    from mkv_env.recorder import make_env

    env = make_env(env_id, env_kwargs)
    try:
        space = env.action_space
        if not hasattr(space, "nvec"):
            raise ValueError(f"env {env_id!r} has action space {space}, expected MultiDiscrete")
        names = list(getattr(env.unwrapped, "sensor_names", []))
        if not names:
            raise ValueError(f"env {env_id!r} does not name its sensor channels")
        obs = env.observation_space
        return names, [int(v) for v in space.nvec], obs.low, obs.high
    finally:
        env.close()


def _evaluate(env_id, env_kwargs, policy, episodes, seed) -> dict:
    from sfm_learn.evaluation import evaluate

    m = evaluate(env_id, policy, episodes, seed, env_kwargs).metrics
    return {
        "mean_return": m["mean_return"],
        "escape_rate": m["escape_rate"],
        "distance_m": m["distance_m"],
        "stuck_fraction": m["stuck_fraction"],
    }


def fmt_point(pt: dict) -> str:
    text = f"steps {pt['env_steps']}: return {pt['mean_return']:.2f}"
    if pt.get("escape_rate") is not None:
        text += f", escape rate {pt['escape_rate']:.2f}"
    text += f", distance {pt['distance_m']:.2f} m"
    if pt.get("stuck_fraction") is not None:
        text += f", stuck {pt['stuck_fraction']:.3f}"
    return text


def train(
    env_id: str,
    timesteps: int,
    *,
    seed: int = 0,
    n_envs: int = 2,
    vec: str = "sync",
    env_kwargs: dict | None = None,
    eval_every: int | None = None,
    eval_episodes: int = 10,
    eval_seed: int = 10_000,
    checkpoint_dir: str | None = None,
    hyperparameters: dict | None = None,
    observation: str = "raw",
    eval_at=None,
    progress=None,
    log=None,
    tensorboard_dir: str | None = None,
):
    """Train PPO; returns ``(model, meta)``. ``progress`` has ``update(n)``; ``log(line)`` gets
    one line per evaluation. Writes checkpoints (atomically) when ``checkpoint_dir`` is given.

    ``eval_at``: evaluate (and checkpoint) at the first rollout boundary at or after each of these
    env-step counts instead of every ``eval_every`` steps (a sweep's budgets).

    ``observation``: ``"raw"`` (the rescaled sensor vector) or ``"features"`` (the SfM/BC default
    features of the rescaled sensors and the previous command, :class:`sb3.FeatureObservation`).

    ``tensorboard_dir``: SB3's logger writes TensorBoard events there (``PPO_<seed>_<n>``
    subfolders: rollout returns and lengths, losses, and every evaluation point as
    ``eval/mean_return``, ``eval/escape_rate``, ``eval/distance_m``); needs ``tensorboard``.
    """

    torch = sb3.import_torch()
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    if observation not in OBSERVATIONS:
        raise ValueError(f"observation must be one of {OBSERVATIONS}, got {observation!r}")
    env_kwargs = dict(env_kwargs or {})
    if "observation" in env_kwargs:
        raise ValueError("env kwargs must not set 'observation': train-ppo chooses it (raw: the "
                         "rescaled readings; features: their SfM features)")
    sensor_names, nvec, low, high = check_env(env_id, env_kwargs)
    scale = sb3.rescale_function(low, high)
    feature_spec = None
    if observation == "features":
        from mkv_env.features import default_feature_spec

        feature_spec = default_feature_spec(sensor_names, nvec).to_dict()
    hp = dict(DEFAULTS)
    hp.update(hyperparameters or {})
    hp["n_steps"] = rollout_steps(timesteps, n_envs, hp["n_steps"])
    per_rollout = n_envs * hp["n_steps"]
    hp["batch_size"] = max(2, min(hp["batch_size"], per_rollout))
    planned = planned_timesteps(timesteps, n_envs, hp["n_steps"])
    eval_every = eval_every or max(1, timesteps // 10)

    # the env gives the policy's inputs itself (gym.make(id, observation=...)): the zip runs on
    # gym.make(env_id, **meta["make_kwargs"]) with plain SB3 and no wrapper
    make_kwargs = {**env_kwargs, "observation": "features" if observation == "features"
                   else "rescaled"}
    fns = [functools.partial(sb3.make_observed_env, env_id, make_kwargs) for _ in range(n_envs)]
    venv = SubprocVecEnv(fns) if vec == "async" else DummyVecEnv(fns)
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "env_id": env_id,
        "env_kwargs": env_kwargs,
        "make_kwargs": make_kwargs,
        "sensor_names": sensor_names,
        "action_nvec": nvec,
        "obs_rescale": {"low": np.asarray(low, dtype=float).tolist(),
                        "high": np.asarray(high, dtype=float).tolist(), "to": [-1.0, 1.0],
                        "wrapper": "gymnasium.wrappers.RescaleObservation"},
        "observation": observation,
        "feature_spec": feature_spec,
        "seed": int(seed),
        "n_envs": int(n_envs),
        "vec": vec,
        "timesteps_requested": int(timesteps),
        "timesteps": 0,
        "hyperparameters": hp,
        "activation": "tanh",
        "eval": {
            "episodes": int(eval_episodes),
            "seed": int(eval_seed),
            "every": int(eval_every),
            "deterministic": True,
        },
        "learning_curve": [],
        "final_eval": None,
        "train_wall_s": 0.0,
        "eval_wall_s": 0.0,
        **sb3.versions(),
    }
    state = {"excluded": 0.0, "next_eval": 0, "start": 0.0}
    marks = sorted({0, *(int(b) for b in eval_at)}) if eval_at is not None else None

    def policy_view(model):
        if feature_spec is not None:
            return sb3.FeatureActorPolicy(model.policy, nvec, feature_spec, transform=scale)
        return sb3.ActorPolicy(model.policy, nvec, transform=scale)

    def do_eval(model):
        t0 = time.perf_counter()
        steps = int(model.num_timesteps)
        wall = t0 - state["start"] - state["excluded"]
        point = {
            "env_steps": steps,
            "wall_s": round(wall, 3),
            **_evaluate(env_id, env_kwargs, policy_view(model), eval_episodes, eval_seed),
        }
        meta["learning_curve"].append(point)
        meta["final_eval"] = point
        if log is not None:
            log(fmt_point(point))
        if tensorboard_dir:
            for key in ("mean_return", "escape_rate", "distance_m"):
                if point.get(key) is not None:
                    model.logger.record(f"eval/{key}", float(point[key]))
            model.logger.dump(steps)
        if checkpoint_dir:
            meta["timesteps"], meta["train_wall_s"] = steps, round(wall, 3)
            save(model, meta, os.path.join(checkpoint_dir, f"ppo_{steps:08d}.zip"))
        state["excluded"] += time.perf_counter() - t0
        meta["eval_wall_s"] = round(state["excluded"], 3)
        if marks is not None:
            state["next_eval"] = next((b for b in marks if b > steps), math.inf)
        while state["next_eval"] <= steps:
            state["next_eval"] += eval_every

    class _Callback(BaseCallback):
        def _on_rollout_start(self) -> None:
            # parameters here are exactly those trained on num_timesteps env steps
            if self.model.num_timesteps >= state["next_eval"]:
                do_eval(self.model)
                self.model.policy.set_training_mode(False)

        def _on_step(self) -> bool:
            if progress is not None:
                progress.update(n_envs)
            return True

    try:
        import warnings

        with warnings.catch_warnings():
            # a budget smaller than one rollout shrinks n_steps; SB3 then warns that the minibatch
            # does not divide the rollout (a truncated last minibatch: harmless)
            warnings.filterwarnings("ignore", message="You have specified a mini-batch size")
            model = _make_ppo(PPO, venv, seed, hp, torch)
        if tensorboard_dir:
            from stable_baselines3.common.logger import configure

            n = 1 + sum(1 for d in os.listdir(tensorboard_dir)
                        if d.startswith(f"PPO_{seed}_")) if os.path.isdir(tensorboard_dir) else 1
            model.set_logger(configure(os.path.join(tensorboard_dir, f"PPO_{seed}_{n}"),
                                       ["tensorboard"]))
        else:
            # no logger output: SB3's default logger makes an empty /tmp/SB3-<date> folder
            model.set_logger(Logger(None, []))
        state["start"] = time.perf_counter()
        model.learn(total_timesteps=int(timesteps), callback=_Callback())
        if (
            not meta["learning_curve"]
            or meta["learning_curve"][-1]["env_steps"] != model.num_timesteps
        ):
            do_eval(model)
        total = time.perf_counter() - state["start"]
    finally:
        try:
            venv.close()
        except (EOFError, OSError):  # workers already gone (Ctrl-C reaches them too)
            pass
    meta["timesteps"] = int(model.num_timesteps)
    meta["timesteps_planned"] = int(planned)
    meta["train_wall_s"] = round(total - state["excluded"], 3)
    meta["eval_wall_s"] = round(state["excluded"], 3)
    meta["final_eval"] = meta["learning_curve"][-1]
    return model, meta


def _make_ppo(PPO, venv, seed, hp, torch):
    return PPO(
        "MlpPolicy",
        venv,
        seed=int(seed),
        device="cpu",
        verbose=0,
        n_steps=hp["n_steps"],
        batch_size=hp["batch_size"],
        n_epochs=hp["n_epochs"],
        learning_rate=hp["learning_rate"],
        gamma=hp["gamma"],
        gae_lambda=hp["gae_lambda"],
        clip_range=hp["clip_range"],
        ent_coef=hp["ent_coef"],
        vf_coef=hp["vf_coef"],
        max_grad_norm=hp["max_grad_norm"],
        policy_kwargs={"net_arch": list(hp["net_arch"]), "activation_fn": torch.nn.Tanh},
    )


def save(model, meta: dict, path: str) -> None:
    """SB3's model zip plus ``mkv_meta.json``, written atomically."""

    buf = io.BytesIO()
    model.save(buf)
    atomic_write_bytes(
        path, sb3.add_member(buf.getvalue(), sb3.META_MEMBER, sb3.meta_bytes(meta))
    )


def read_metadata(path: str) -> dict:
    """The ``mkv_meta.json`` of a ``mkv train-ppo`` zip (raises PolicySpecError, one line)."""

    return sb3.read_policy_zip(os.fspath(path), FORMAT)[0]


# ---------------------------------------------------------------------- ppo:PATH
def observation_transform(meta: dict, n: int):
    """The observation map the policy was trained under: ``obs_rescale`` (format 2, Gymnasium's
    RescaleObservation) or ``obs_scaling`` (format 1: centre / half-range in float64)."""
    if "obs_rescale" in meta:
        low = np.asarray(meta["obs_rescale"]["low"], dtype=np.float64)
        high = np.asarray(meta["obs_rescale"]["high"], dtype=np.float64)
        if low.shape != (n,) or high.shape != (n,):
            raise ValueError("obs_rescale does not match the sensor names")
        return sb3.rescale_function(low, high)
    centre = np.asarray(meta["obs_scaling"]["centre"], dtype=np.float64)
    half = np.asarray(meta["obs_scaling"]["half"], dtype=np.float64)
    if centre.shape != (n,) or half.shape != (n,):
        raise ValueError("obs_scaling does not match the sensor names")
    return lambda o: (np.asarray(o, dtype=np.float64) - centre) / half


def load_spec(arg, env, seed):
    """``ppo:PATH`` -> a policy with SB3 ``predict`` (deterministic = argmax actions)."""

    def make_net(meta, torch):
        import gymnasium as gym
        from stable_baselines3.common.policies import ActorCriticPolicy

        n = len(meta["sensor_names"])
        if meta.get("feature_spec") is not None:
            from mkv_env.features import FeatureSpec

            n = FeatureSpec.from_dict(meta["feature_spec"]).n_features
        acts = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU}
        return ActorCriticPolicy(
            gym.spaces.Box(-np.inf, np.inf, (n,), np.float32),
            gym.spaces.MultiDiscrete(meta["action_nvec"]),
            lambda _: 0.0,
            net_arch=list(meta["hyperparameters"]["net_arch"]),
            activation_fn=acts[meta.get("activation", "tanh")],
        )

    def wrap(net, meta):
        transform = observation_transform(meta, len(meta["sensor_names"]))
        if meta.get("feature_spec") is not None:
            return sb3.FeatureActorPolicy(net, meta["action_nvec"], meta["feature_spec"],
                                          transform=transform, seed=seed)
        return sb3.ActorPolicy(net, meta["action_nvec"], transform=transform, seed=seed)

    return sb3.rebuild_policy(arg, FORMAT, env, make_net, wrap)


__all__ = ["DEFAULTS", "HYPERPARAMS_FILE", "OBSERVATIONS", "check_env", "fmt_point",
           "load_hyperparameters", "load_spec", "observation_transform", "planned_timesteps",
           "read_metadata", "save", "train"]
