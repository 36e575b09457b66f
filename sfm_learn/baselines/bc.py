"""``mkv train-bc`` and the ``bc:PATH`` policy spec: behaviour cloning of an SB3 policy.

::

    mkv train-bc DATA.npz --out bc.zip [--epochs 30] [--batch-size 256] [--lr 1e-3] [--seed 0]
                 [--held-out 0.2] [--features default|raw] [--quiet]
    mkv eval --env MKVJam-v0 --policy bc:bc.zip --episodes 50 --seed 1000

An SB3 ``ActorCriticPolicy`` (tanh MLP, policy net 64x64; its value head is unused) is trained
by plain supervised learning: minibatch Adam on the negative log-likelihood of the dataset's
[drive, steer] commands under the policy's ``MultiDiscrete([3, 3])`` action distribution (the sum
of the two categorical cross-entropies). Inputs are, by default, the same features the
shape-from-motion policy uses (:func:`~mkv_env.features.default_feature_spec`:
every channel,
decaying traces, the previous command), or with ``--features raw`` the raw observation; each
input column is standardised with training-set statistics stored in the file.

Whole episodes are held out (:func:`mkv_env.dataset.split_by_episode`, ``--held-out`` fraction,
seeded by ``--seed``) to *measure*: a first network trained on the other episodes gives the
held-out accuracy, then the saved policy is trained again on every episode (same seed,
``--epochs`` and ``--min-updates``; ``teacher_steps`` counts all rows,
``validation_trained_steps`` the first network's), so the validation never takes data from
the policy. A fit runs ``--epochs`` passes, or more when
those give fewer than ``--min-updates`` minibatch updates (default 1,000): at 1,200 teacher steps
30 epochs are only 150 Adam steps, which left BC underfitted (:func:`planned_epochs`). Per
command it reports held-out accuracy next to the majority-class baseline (always predicting the
training set's most frequent value: the teacher mostly drives
forward with the steering off, so raw accuracy flatters) and the recall of each value
(reverse/off/forward, left/off/right).

File format (format_version 2; :func:`read_metadata`): a Stable-Baselines3 PPO model zip, so
``PPO.load(path)`` reads it, whose network takes the env's own observation
(``gym.make(env_id, **make_kwargs)``, ``observation="features"``, or ``"rescaled"`` for
``--features raw``: the standardisation and the rescaling are folded into its first layers,
:func:`fold_inputs`), plus ``mkv_meta.json``. The ``bc:`` loader reads only ``policy.pth``
(``weights_only=True``) and ``mkv_meta.json`` and feeds the same inputs (format_version 1 files,
an unfolded network on standardised raw features, still load). ``mkv_meta.json``: ``format``
(``"mkv-bc"``), ``make_kwargs``, ``obs_rescale``,
``env_id``/``env_kwargs``/``control_period_s`` of the dataset, ``sensor_names``, ``action_nvec``,
``action_names``, ``features`` (``"default"``/``"raw"``), ``feature_spec``
(:meth:`FeatureSpec.to_dict`), ``input_mean``/``input_std``, ``net_arch``, ``activation``,
``teacher_steps`` (training rows), ``teacher_episodes``, ``held_out_steps``/``_episodes``,
``epochs`` (run), ``epochs_requested``, ``min_updates``, ``updates``, ``batch_size``, ``lr``,
``seed``, ``train_wall_s``, ``held_out`` (accuracy, majority
baseline, recall per command, joint accuracy, NLL), ``history`` (per-epoch losses and
accuracies), ``dataset`` (file name, ``content_sha256``, recording policy), versions.

At run time (``bc:PATH``) the feature builder runs online: it is reset at every episode start
(``reset(seed)``, which the episode runners call, or ``episode_start=True``), fed each observation
with the command the policy itself sent at the previous step, and the action is the argmax of
each command's logits (``deterministic=False`` samples instead).

Measured (one thread, shared 2-core machine): 30 epochs on 9,600 rows take about 2 s. Trained on
20 teacher episodes of ``MKV-v0`` (held-out accuracy drive 0.995, steer 0.924 against
majority-class 0.662 / 0.324), BC escapes 0.92 of 50 ``MKVJam-v0`` jams (seeds 1000..1049;
teacher 1.00, random 0.04) and matches the teacher's 14.7 m per ``MKV-v0`` episode; with
``--features raw`` it escapes 0.64.
"""

from __future__ import annotations

import io
import os
import time

import numpy as np

from mkv_env.actions import ACTION_NAMES, ACTION_NVEC, VALUE_NAMES
from sfm_common.files import atomic_write_bytes
from sfm_learn.baselines import sb3

FORMAT = "mkv-bc"
FORMAT_VERSION = 1
DEFAULT_NET_ARCH = {"pi": [64, 64], "vf": []}
MIN_UPDATES = 1000
DEFAULTS = {"epochs": 30, "batch_size": 256, "lr": 1e-3, "held_out": 0.2,
            "min_updates": MIN_UPDATES}


def planned_epochs(n_rows: int, epochs: int, batch_size: int, min_updates: int) -> int:
    """Epochs a fit runs: ``epochs``, or more when that gives fewer than ``min_updates`` minibatch
    updates (small data). At 1,200 rows 30 epochs are 150 Adam steps and left BC underfitted (it
    failed on 9 of 20 development training sets; 150 epochs: 1 of 20, 600: 0 of 20)."""
    batches = max(1, -(-int(n_rows) // int(batch_size)))
    return max(int(epochs), -(-int(min_updates) // batches))


def min_rows(n_features: int) -> int:
    """Fewest training rows behaviour cloning accepts on ``n_features`` inputs: one more.

    Why: the network's first layer is a linear map of the standardised features, and ``n``
    training rows, centred by that standardisation, span at most ``n - 1`` directions of the
    feature space; below ``n_features + 1`` rows some direction is never seen varying and the
    network's response along it is its random initialisation, not anything learned (the same
    floor as the SfM fit's inputs, :func:`sfm_learn.eigenspace.policy.min_fit_rows`, whose
    stacked rows add the command columns). Nothing else in the code needs more: the per-column
    statistics need 2 rows, a minibatch shorter than ``batch_size`` is one full-batch Adam step
    (:func:`planned_epochs` counts the updates, so fewer rows than ``--batch-size`` still get
    ``--min-updates`` of them), and a command value absent from the rows is simply never the
    majority class. A floor of identifiability, not of quality (1,200 teacher steps
    and up)."""
    return int(n_features) + 1


def check_rows(data, *, held_out: float = 0.0, seed: int = 0, features: str = "default",
               what: str = "the dataset") -> None:
    """ValueError (one line naming ``what``, its rows and the minimum) unless ``data`` has
    :func:`min_rows` rows and, when ``held_out`` splits it (two or more episodes), the network
    that measures the held-out accuracy is trained on that many too (the held-out part always
    has rows: whole episodes, at least one)."""
    from mkv_env.dataset import split_by_episode

    n_features = feature_spec(list(data.metadata["sensor_names"]), features).n_features
    need = min_rows(n_features)
    why = f"behaviour cloning on {n_features} {features} features needs at least {need}"
    if data.n_steps < need:
        raise ValueError(f"{what} has {data.n_steps} rows; {why} (one more than its features)")
    train_set, held_set = split_by_episode(data, held_out, seed)
    if held_set.n_steps and train_set.n_steps < need:
        raise ValueError(f"{what}: holding out {held_set.n_episodes} of {data.n_episodes} "
                         f"episodes (fraction {held_out:g}) leaves {train_set.n_steps} training "
                         f"rows; {why}: hold out less (--held-out 0) or record more episodes")


# ---------------------------------------------------------------------- features
def feature_spec(sensor_names, features: str = "default"):
    from mkv_env.features import FeatureSpec, default_feature_spec

    if features == "default":
        return default_feature_spec(sensor_names, ACTION_NVEC, ACTION_NAMES)
    if features == "raw":
        return FeatureSpec(
            obs_names=tuple(sensor_names), action_nvec=ACTION_NVEC, action_names=ACTION_NAMES
        )
    raise ValueError(f"features must be 'default' or 'raw', got {features!r}")


def dataset_features(builder, data):
    """Batch features of every row of a dataset (episode starts from its ``step`` column)."""
    return builder.transform(data["observations"], data["actions"], data["step"] == 0)


def build_policy(n_inputs: int, net_arch, lr: float = 1e-3):
    import gymnasium as gym
    import numpy as np
    from stable_baselines3.common.policies import ActorCriticPolicy

    from sfm_learn.baselines.sb3 import import_torch

    torch = import_torch()
    return ActorCriticPolicy(
        gym.spaces.Box(-np.inf, np.inf, (n_inputs,), np.float32),
        gym.spaces.MultiDiscrete(list(ACTION_NVEC)),
        lambda _: lr,
        net_arch=net_arch,
        activation_fn=torch.nn.Tanh,
    )


# ---------------------------------------------------------------------- metrics
def action_metrics(pred, true, majority) -> dict:
    """Accuracy, majority-class baseline and per-value recall of each command."""
    import numpy as np

    out = {"accuracy": {}, "majority_accuracy": {}, "recall": {}, "support": {}}
    for j, name in enumerate(ACTION_NAMES):
        p, t = pred[:, j], true[:, j]
        out["accuracy"][name] = float(np.mean(p == t)) if len(t) else None
        out["majority_accuracy"][name] = float(np.mean(t == majority[j])) if len(t) else None
        out["recall"][name] = [
            float(np.mean(p[t == v] == v)) if np.any(t == v) else None
            for v in range(ACTION_NVEC[j])
        ]
        out["support"][name] = [int(np.sum(t == v)) for v in range(ACTION_NVEC[j])]
    out["joint_accuracy"] = float(np.mean(np.all(pred == true, axis=1))) if len(true) else None
    return out


# ---------------------------------------------------------------------- training
def train(
    data,
    *,
    epochs: int = 30,
    batch_size: int = 256,
    lr: float = 1e-3,
    seed: int = 0,
    held_out: float = 0.2,
    features: str = "default",
    net_arch=None,
    on_epoch=None,
    refit: bool = True,
    min_updates: int = MIN_UPDATES,
    on_refit=None,
):
    """Behaviour-clone ``data`` (a :class:`mkv_env.dataset.Dataset`); returns ``(policy, meta)``.

    ``on_epoch(epoch, record)`` is called after each epoch with that epoch's losses/accuracies
    (``record["of"]``: the epochs this fit runs, :func:`planned_epochs`).
    With ``held_out > 0`` a first network trained on the other episodes measures the held-out
    accuracy; with ``refit`` (the default) the returned policy is then trained again, same
    seed, ``epochs`` and ``min_updates``, on every episode; ``on_refit(epoch, record)`` is
    ``on_epoch`` of that refit (no held-out numbers). The refit plans its epochs from all rows
    (:func:`planned_epochs`): when ``min_updates`` raises them, its larger minibatch count per
    epoch gives fewer epochs than the held-out fit ran. So the validation never costs the
    policy data (at 1,200 teacher steps a 20 % split left BC on two thirds of its data and
    failed on 2 of 3 new training sets). ``refit=False`` returns the validation
    network itself. Fewer rows than :func:`min_rows` (in all, or left for the validation
    network by the split) raise ValueError before any training (:func:`check_rows`).
    """
    import numpy as np

    from mkv_env.dataset import split_by_episode
    from mkv_env.features import FeatureBuilder

    sensor_names = list(data.metadata["sensor_names"])
    acts = data["actions"]
    if (
        acts.ndim != 2
        or acts.shape[1] != len(ACTION_NVEC)
        or np.any(acts < 0)
        or np.any(acts >= np.array(ACTION_NVEC))
    ):
        raise ValueError(
            f"dataset actions must be [drive, steer] indices in 0..2, got shape {acts.shape}"
        )
    check_rows(data, held_out=held_out, seed=seed, features=features)
    train_set, held_set = split_by_episode(data, held_out, seed)
    spec = feature_spec(sensor_names, features)
    builder = FeatureBuilder(spec)
    x_train = dataset_features(builder, train_set)
    y_train = train_set["actions"].astype(np.int64)
    x_held = dataset_features(builder, held_set) if held_set.n_steps else None
    y_held = held_set["actions"].astype(np.int64)
    policy, fit = fit_features(x_train, y_train, x_held, y_held, spec.n_features, epochs=epochs,
                               batch_size=batch_size, lr=lr, seed=seed, net_arch=net_arch,
                               on_epoch=on_epoch, min_updates=min_updates)
    validation_steps = int(train_set.n_steps)
    if refit and held_set.n_steps:
        held_metrics, history = fit["held_out"], fit["history"]
        train_set = data
        x_all = dataset_features(builder, data)
        policy, fit = fit_features(x_all, data["actions"].astype(np.int64), None, y_held,
                                   spec.n_features, epochs=epochs, batch_size=batch_size, lr=lr,
                                   seed=seed, net_arch=net_arch, min_updates=min_updates,
                                   on_epoch=on_refit)
        fit["held_out"], fit["history"] = held_metrics, history
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "env_id": data.metadata.get("env_id"),
        "env_kwargs": data.metadata.get("env_kwargs", {}),
        "control_period_s": data.metadata.get("control_period_s"),
        "sensor_names": sensor_names,
        "action_nvec": list(ACTION_NVEC),
        "action_names": list(ACTION_NAMES),
        "features": features,
        "feature_spec": spec.to_dict(),
        **fit,
        "teacher_steps": int(train_set.n_steps),
        "teacher_episodes": int(train_set.n_episodes),
        "held_out_steps": int(held_set.n_steps),
        "held_out_episodes": int(held_set.n_episodes),
        "held_out_fraction": float(held_out),
        # held-out metrics come from a network trained on these many steps; the saved policy
        # was refitted on every step (teacher_steps) unless refit=False
        "validation_trained_steps": validation_steps,
        "refit_on_all": bool(refit and held_set.n_steps),
        "seed": int(seed),
        "dataset": {
            "content_sha256": data.metadata.get("content_sha256"),
            "policy": data.metadata.get("policy"),
            "n_steps": int(data.n_steps),
            "n_episodes": int(data.n_episodes),
        },
        **sb3.versions(),
    }
    return policy, meta


def fit_features(x_train, y_train, x_held, y_held, n_features: int, *, epochs: int = 30,
                 batch_size: int = 256, lr: float = 1e-3, seed: int = 0, net_arch=None,
                 on_epoch=None, policy=None, min_updates: int = MIN_UPDATES):
    """The supervised core of BC (and of each DAgger round): standardise the inputs with
    training statistics, minibatch Adam on the NLL of the commands. ``x_held`` may be None.
    ``policy`` continues training an existing network (a DAgger round's warm start). It runs
    :func:`planned_epochs` epochs: ``epochs``, or enough for ``min_updates`` minibatch updates.

    Returns ``(policy, fit)``; ``fit`` holds ``input_mean``/``input_std``, ``net_arch``,
    ``activation``, ``majority_class``, ``epochs``, ``batch_size``, ``lr``, ``train_wall_s``,
    ``train_accuracy``, ``held_out`` and ``history``.
    """
    import numpy as np

    torch = sb3.import_torch()
    net_arch = dict(DEFAULT_NET_ARCH if net_arch is None else net_arch)
    mean = x_train.mean(axis=0)
    std = x_train.std(axis=0)
    std = np.where(std > 1e-8, std, 1.0)
    majority = [
        int(np.bincount(y_train[:, j], minlength=n).argmax()) for j, n in enumerate(ACTION_NVEC)
    ]

    torch.manual_seed(int(seed))
    if policy is None:
        policy = build_policy(n_features, net_arch, lr)
    policy.set_training_mode(True)
    opt = torch.optim.Adam(policy.parameters(), lr=lr)
    xt = torch.as_tensor(((x_train - mean) / std).astype(np.float32))
    yt = torch.as_tensor(y_train)
    xh = None if x_held is None else torch.as_tensor(((x_held - mean) / std).astype(np.float32))
    yh = None if y_held is None else torch.as_tensor(y_held)
    rng = np.random.default_rng(seed)
    n = len(xt)
    view = sb3.ActorPolicy(policy, ACTION_NVEC)
    history = []
    requested = int(epochs)
    epochs = planned_epochs(n, requested, batch_size, min_updates)
    updates = 0
    t0 = time.perf_counter()
    for epoch in range(1, epochs + 1):
        policy.set_training_mode(True)
        order = torch.as_tensor(rng.permutation(n))
        total = 0.0
        for i in range(0, n, batch_size):
            idx = order[i : i + batch_size]
            nll = -policy.get_distribution(xt[idx]).log_prob(yt[idx]).mean()
            opt.zero_grad(set_to_none=True)
            nll.backward()
            opt.step()
            updates += 1
            total += nll.item() * len(idx)
        policy.set_training_mode(False)
        rec = {"epoch": epoch, "of": epochs, "train_nll": total / n}
        if xh is not None:
            with torch.no_grad():
                rec["held_out_nll"] = float(-policy.get_distribution(xh).log_prob(yh).mean())
            pred = view.actions_from_logits(view.logits(xh.numpy()))
            m = action_metrics(pred, y_held, majority)
            rec["held_out_accuracy"] = m["accuracy"]
            rec["held_out_joint_accuracy"] = m["joint_accuracy"]
        history.append(rec)
        if on_epoch is not None:
            on_epoch(epoch, rec)
    train_wall = time.perf_counter() - t0

    held = None
    if xh is not None:
        pred = view.actions_from_logits(view.logits(xh.numpy()))
        held = action_metrics(pred, y_held, majority)
        held["nll"] = history[-1]["held_out_nll"]
    train_pred = view.actions_from_logits(view.logits(xt.numpy()))
    return policy, {
        "input_mean": mean.tolist(),
        "input_std": std.tolist(),
        "net_arch": net_arch,
        "activation": "tanh",
        "majority_class": dict(zip(ACTION_NAMES, majority, strict=True)),
        "epochs": int(epochs),
        "epochs_requested": requested,
        "min_updates": int(min_updates),
        "updates": int(updates),
        "batch_size": int(batch_size),
        "lr": float(lr),
        "train_wall_s": round(train_wall, 3),
        "train_accuracy": action_metrics(train_pred, y_train, majority)["accuracy"],
        "held_out": held,
        "history": history,
    }


def env_observation(meta: dict) -> str:
    """The env observation mode whose output a saved BC/DAgger network takes directly:
    ``features`` for the default SfM features, ``rescaled`` for ``--features raw``."""
    return "features" if meta.get("features", "default") == "default" else "rescaled"


def fold_inputs(policy, meta: dict, low, high):
    """A copy of the trained network that takes the env's own observation in mode
    :func:`env_observation` (features of the readings rescaled to [-1, 1]) instead of
    standardised features of the raw readings: both maps are affine per column (traces and
    history start at the episode's first reading, the previous command is unchanged), so they
    fold into the first layers of the policy and value nets. Returns the new network."""
    from mkv_env.features import FeatureSpec

    torch = sb3.import_torch()
    spec = FeatureSpec.from_dict(meta["feature_spec"])
    if spec.history and spec.history_pad != "edge":
        raise ValueError("only edge-padded histories fold into the network")
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    a_ch = 2.0 / (high - low)
    b_ch = -1.0 - 2.0 * low / (high - low)
    index = {c: i for i, c in enumerate(spec.obs_names)}
    names = list(spec.feature_names)
    a, b = np.ones(len(names)), np.zeros(len(names))
    for j, name in enumerate(names):
        head = name.split("[")[0].split("~")[0]
        if head in index and not (name.endswith("[t-1]") and head in spec.action_names):
            a[j], b[j] = a_ch[index[head]], b_ch[index[head]]
    mean = np.asarray(meta["input_mean"], np.float64)
    std = np.asarray(meta["input_std"], np.float64)
    # u = (f_raw - mean) / std with f_raw = (f_res - b) / a:  u = s * f_res + t
    scale = 1.0 / (a * std)
    shift = -(b / a + mean) / std
    folded = build_policy(len(names), meta["net_arch"])
    folded.load_state_dict(policy.state_dict())
    ext = folded.mlp_extractor
    firsts = [m[0] for m in (ext.policy_net, ext.value_net)
              if len(m) and isinstance(m[0], torch.nn.Linear)]
    if not len(ext.policy_net):
        firsts.append(folded.action_net)  # pi=[]: the action head reads the inputs directly
    if not len(ext.value_net):
        firsts.append(folded.value_net)  # vf=[]: so does the value head
    with torch.no_grad():
        for layer in firsts:
            W = layer.weight.double()
            layer.bias.copy_((layer.bias.double() + W @ torch.as_tensor(shift)).float())
            layer.weight.copy_((W * torch.as_tensor(scale)[None, :]).float())
    return folded


def save(policy, meta: dict, path: str) -> None:
    """A Stable-Baselines3 PPO model zip (``PPO.load`` reads it) whose policy is the trained
    network folded onto the env's own observation (:func:`fold_inputs`), plus
    ``mkv_meta.json``; written atomically. ``gym.make(meta["env_id"], **meta["make_kwargs"])``
    gives that observation, so plain SB3 runs the policy with no project code."""
    import gymnasium as gym

    import mkv_env  # noqa: F401

    torch = sb3.import_torch()
    from stable_baselines3 import PPO

    meta = dict(meta)
    kwargs = dict(meta.get("env_kwargs") or {})
    mode = env_observation(meta)
    raw = gym.make(meta["env_id"], **kwargs)
    low, high = raw.observation_space.low, raw.observation_space.high
    raw.close()
    folded = fold_inputs(policy, meta, low, high)
    env = gym.make(meta["env_id"], **kwargs, observation=mode)
    acts = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU}
    model = PPO("MlpPolicy", env, n_steps=2, batch_size=2, device="cpu",
                policy_kwargs={"net_arch": dict(meta["net_arch"]),
                               "activation_fn": acts[meta.get("activation", "tanh")]})
    model.policy.load_state_dict(folded.state_dict())
    env.close()
    meta.update(format_version=2, make_kwargs={**kwargs, "observation": mode},
                inputs="the env observation of make_kwargs (standardisation folded into the "
                "network)",
                obs_rescale={"low": np.asarray(low, float).tolist(),
                             "high": np.asarray(high, float).tolist(), "to": [-1.0, 1.0]})
    buf = io.BytesIO()
    model.save(buf)
    atomic_write_bytes(path, sb3.add_member(buf.getvalue(), sb3.META_MEMBER,
                                            sb3.meta_bytes(meta)))


def read_metadata(path: str) -> dict:
    """The ``mkv_meta.json`` of a ``mkv train-bc`` zip (raises PolicySpecError, one line)."""

    return sb3.read_policy_zip(os.fspath(path), FORMAT)[0]


# ---------------------------------------------------------------------- bc:PATH
class BCPolicy:
    """A behaviour-cloned policy with SB3's ``predict`` (one observation or a batch of envs)."""

    def __init__(self, policy, meta: dict, seed: int | None = None):
        import numpy as np

        from mkv_env.features import FeatureBuilder, FeatureSpec, OnlineFeatures

        self.meta = self.metadata = meta
        spec = FeatureSpec.from_dict(meta["feature_spec"])
        self.builder = FeatureBuilder(spec)
        self.mean = np.asarray(meta["input_mean"], dtype=np.float64)
        self.std = np.asarray(meta["input_std"], dtype=np.float64)
        if self.mean.shape != (self.builder.n_features,) or self.std.shape != self.mean.shape:
            raise ValueError("input statistics do not match the feature spec")
        self.transform = None
        if meta.get("format_version", 1) >= 2:
            # the network takes features of the readings rescaled to [-1, 1] (the env's
            # observation="features"/"rescaled"), its standardisation folded in (fold_inputs)
            r = meta["obs_rescale"]
            n = len(spec.obs_names)
            if len(r["low"]) != n or len(r["high"]) != n:
                raise ValueError("obs_rescale does not match the sensor names")
            self.transform = sb3.rescale_function(r["low"], r["high"])
            self.mean = np.zeros_like(self.mean)
            self.std = np.ones_like(self.std)
        self.actor = sb3.ActorPolicy(policy, meta["action_nvec"], seed=seed)
        self._online = OnlineFeatures(spec)

    def reset(self, seed: int | None = None) -> None:
        """Start of an episode in every env: forget feature histories and previous commands."""
        self.actor.reset(seed)
        self._online.reset()

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        """SB3's ``predict``: ``(actions, state)`` for one observation (n_obs,) or a batch
        (n_envs, n_obs); each env keeps its own features, reset by its ``episode_start``."""
        import numpy as np

        obs, single = self._online.as_batch(observation, "a BC policy")
        if self.transform is not None:
            obs = self.transform(obs)
        feats = self._online.step(obs, episode_start)
        x = (np.stack(feats) - self.mean) / self.std
        actions = self.actor.actions_from_logits(self.actor.logits(x), deterministic)
        self._online.set_previous(actions)
        return (actions[0].copy() if single else actions), state

    def batch_actions(self, observations, actions, episode_start=None):
        """Deterministic actions for a whole recording at once (batch features with the given
        previous ``actions``): equals :meth:`predict` step by step when ``actions`` are the
        policy's own."""
        if self.transform is not None:
            observations = self.transform(observations)
        x = (self.builder.transform(observations, actions, episode_start) - self.mean) / self.std
        return self.actor.actions_from_logits(self.actor.logits(x))


def load_spec(arg, env, seed):
    """``bc:PATH`` -> :class:`BCPolicy`."""
    return sb3.rebuild_policy(
        arg, FORMAT, env,
        lambda meta, torch: build_policy(len(meta["input_mean"]), meta["net_arch"]),
        lambda net, meta: BCPolicy(net, meta, seed))


__all__ = [
    "BCPolicy",
    "DEFAULTS",
    "VALUE_NAMES",
    "check_rows",
    "load_spec",
    "min_rows",
    "read_metadata",
    "save",
    "train",
]
