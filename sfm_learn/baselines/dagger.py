"""``mkv train-dagger`` and the ``dagger:PATH`` policy spec: DAgger with the scripted teacher.

::

    mkv train-dagger --env MKV-v1 --rounds 4 --steps 12000 --out dagger.zip [--seed 0]
    mkv eval --env MKVJam-v1 --policy dagger:dagger.zip --episodes 50 --seed 2000000

DAgger (Ross, Gordon & Bagnell, AISTATS 2011) fixes behaviour cloning's distribution shift by
labelling the states the *learner* visits. Round 0 is behaviour cloning: the teacher drives. In
every later round the current network drives (mixing coefficient beta_i = 1 for i = 0, else 0,
the choice the paper recommends in practice) while the scripted teacher runs in shadow on the same
observations and labels every step with the command it would send. All rows are aggregated and
the network is refitted from scratch on them. Each round collects ``steps / rounds`` labelled steps
(episodes on seeds ``seed + 1000 * round + i``, run to their end, the last one cut where the
round's budget runs out), so the teacher is queried exactly ``steps`` times, the budget that
compares with BC's and SfM's teacher steps.

The teacher in shadow keeps its own timers as if its commands had been sent (it has no other way
to know what it "is doing"); its labels react to what the sensors show (bumps, stalls, spinning),
which is what the learner needs to be corrected on.

Network, features, inputs and the file are behaviour cloning's
(:func:`sfm_learn.baselines.bc.fit_features`, the default features built from the observations
and the commands actually sent); the file's format is ``mkv-dagger`` with the BC members plus
``dagger`` metadata (rounds, rows per round, the teacher's agreement with the learner per round).
"""

from __future__ import annotations

import os

import numpy as np

from mkv_env.actions import ACTION_NVEC
from sfm_learn.baselines import bc, sb3

FORMAT = "mkv-dagger"
FORMAT_VERSION = 1
DEFAULTS = {"rounds": 4, "epochs": 30, "batch_size": 256, "lr": 1e-3}


def round_steps(steps: int, rounds: int) -> list[int]:
    """Teacher queries of each round: ``steps`` shared out, the first rounds one more."""
    return [steps // rounds + (1 if r < steps % rounds else 0) for r in range(rounds)]


def min_steps(n_features: int, rounds: int) -> int:
    """Fewest teacher queries (``steps``) DAgger accepts over ``rounds`` rounds on
    ``n_features`` inputs.

    Round 0's network is fitted on round 0's rows alone, and it drives round 1, so those rows
    must identify it: :func:`sfm_learn.baselines.bc.min_rows` (features + 1). Round 0 gets
    ``ceil(steps / rounds)`` of them (:func:`round_steps`), hence ``steps >=
    (min_rows - 1) * rounds + 1``; every later refit has more rows (all rounds so far). And at
    least 2 per round, the floor the rollouts always had."""
    return max(2 * rounds, (bc.min_rows(n_features) - 1) * rounds + 1)


def check_steps(steps: int, rounds: int, n_features: int, what: str = "steps") -> None:
    """ValueError (one line naming ``what``, the rows round 0 gets and the minimum) when
    ``steps`` is below :func:`min_steps`."""
    need = min_steps(n_features, rounds)
    if steps < need:
        raise ValueError(
            f"{what} {steps} is too small for {rounds} round{'s' if rounds != 1 else ''} "
            f"(at least {need}): round 0 gets {round_steps(steps, rounds)[0]} teacher steps and "
            f"its fit on {n_features} features needs at least {bc.min_rows(n_features)} rows")


def check_budget(env_id: str, steps: int, rounds: int, env_kwargs: dict | None = None,
                 what: str = "steps") -> None:
    """:func:`check_steps` for ``env_id`` (made once to read its sensors), before any run."""
    from mkv_env.recorder import make_env

    env = make_env(env_id, dict(env_kwargs or {}))
    try:
        names = list(env.unwrapped.sensor_names)
    finally:
        env.close()
    check_steps(steps, rounds, bc.feature_spec(names, "default").n_features, what)


def _rollout(env, actor, teacher, first_seed: int, n_steps: int):
    """Run ``actor`` (None: the teacher itself) for ``n_steps`` steps, episodes on seeds
    ``first_seed + i``; the teacher labels every step. Returns observations, actions sent,
    teacher labels, episode-start flags, and the number of episodes (begun)."""
    obs_l, sent_l, label_l, start_l = [], [], [], []
    episodes = 0
    while len(obs_l) < n_steps:
        seed = first_seed + episodes
        episodes += 1
        obs, _ = env.reset(seed=int(seed))
        teacher.reset(seed=int(seed))
        if actor is not None:
            actor.reset(seed=int(seed))
        start = True
        while len(obs_l) < n_steps:
            label, _ = teacher.predict(obs, episode_start=start)
            if actor is None:
                action = label
            else:
                action, _ = actor.predict(obs, episode_start=start)
            obs_l.append(np.asarray(obs, dtype=np.float64))
            sent_l.append(np.asarray(action, dtype=np.int64))
            label_l.append(np.asarray(label, dtype=np.int64))
            start_l.append(start)
            start = False
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
    return (np.array(obs_l), np.array(sent_l), np.array(label_l), np.array(start_l, dtype=bool),
            episodes)


def train(env_id: str, steps: int, *, rounds: int = 4, seed: int = 0,
          env_kwargs: dict | None = None, epochs: int = 30, batch_size: int = 256,
          lr: float = 1e-3, teacher: str = "teacher", on_round=None,
          min_updates: int = bc.MIN_UPDATES):
    """Run DAgger; returns ``(policy, meta)``. ``on_round(round, info)`` after every round.
    Each round's refit runs ``epochs``, or enough for ``min_updates`` minibatch updates
    (:func:`sfm_learn.baselines.bc.planned_epochs`). ``steps`` below :func:`min_steps` raise
    ValueError before any episode runs."""
    from mkv_env.features import FeatureBuilder
    from mkv_env.policies import make_policy
    from mkv_env.recorder import make_env

    if not (isinstance(rounds, int) and 1 <= rounds <= 100):
        raise ValueError(f"rounds must be an integer in 1..100, got {rounds!r}")
    if not (isinstance(steps, int) and steps >= 2 * rounds):
        raise ValueError(f"steps must be an integer >= 2 per round ({2 * rounds}), got {steps!r}")
    env_kwargs = dict(env_kwargs or {})
    env = make_env(env_id, env_kwargs)
    try:
        sensor_names = list(env.unwrapped.sensor_names)
        expert = make_policy(teacher, env, seed)
        spec = bc.feature_spec(sensor_names, "default")
        check_steps(steps, rounds, spec.n_features)
        builder = FeatureBuilder(spec)
        per_round = round_steps(steps, rounds)
        parts, log = [], []
        policy, fit, learner = None, None, None
        for r in range(rounds):
            obs, sent, labels, starts, episodes = _rollout(env, learner, expert,
                                                           seed + 1000 * r, per_round[r])
            parts.append((obs, sent, labels, starts))
            x = np.concatenate([builder.transform(o, s, st) for o, s, _, st in parts])
            y = np.concatenate([lab for _, _, lab, _ in parts])
            policy, fit = bc.fit_features(x, y, None, None, spec.n_features, epochs=epochs,
                                          batch_size=batch_size, lr=lr, seed=seed + r,
                                          min_updates=min_updates)
            meta_now = {"feature_spec": spec.to_dict(), "action_nvec": list(ACTION_NVEC), **fit}
            learner = bc.BCPolicy(policy, meta_now, seed=seed)
            info = {"round": r, "rows": int(len(obs)), "episodes": episodes,
                    "total_rows": int(len(x)),
                    "driver": "teacher" if r == 0 else "learner",
                    "agreement": float(np.mean(np.all(sent == labels, axis=1)))}
            log.append(info)
            if on_round is not None:
                on_round(r, info)
    finally:
        env.close()
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "env_id": env_id,
        "env_kwargs": env_kwargs,
        "control_period_s": float(getattr(env.unwrapped, "control_period_s", 0.1)),
        "sensor_names": sensor_names,
        "action_nvec": list(ACTION_NVEC),
        "action_names": list(bc.ACTION_NAMES),
        "features": "default",
        "feature_spec": spec.to_dict(),
        **fit,
        "teacher_steps": int(sum(i["rows"] for i in log)),
        "teacher": teacher,
        "seed": int(seed),
        "dagger": {"rounds": rounds, "beta": "1 in round 0, else 0", "log": log},
        **sb3.versions(),
    }
    return policy, meta


def save(policy, meta: dict, path: str) -> None:
    """The BC container (``policy.pth`` + ``mkv_meta.json``), format ``mkv-dagger``."""
    bc.save(policy, meta, path)


def read_metadata(path: str) -> dict:
    """The ``mkv_meta.json`` of a ``mkv train-dagger`` zip (PolicySpecError, one line)."""
    return sb3.read_policy_zip(os.fspath(path), FORMAT)[0]


def load_spec(arg, env, seed):
    """``dagger:PATH`` -> :class:`sfm_learn.baselines.bc.BCPolicy`."""
    return sb3.rebuild_policy(
        arg, FORMAT, env,
        lambda meta, torch: bc.build_policy(len(meta["input_mean"]), meta["net_arch"]),
        lambda net, meta: bc.BCPolicy(net, meta, seed))


__all__ = ["DEFAULTS", "FORMAT", "check_budget", "check_steps", "load_spec", "min_steps",
           "read_metadata", "round_steps", "save", "train"]
