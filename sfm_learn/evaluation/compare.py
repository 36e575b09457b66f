"""The paper's Figure 3 comparison: a policy's commands against the teacher's on recorded runs.

The policy replays a recorded (held-out) teacher run: at every step it sees the recorded sensors,
and its command is compared with the teacher's. Two replay modes (:data:`MODES`):

* ``free_running`` (the honest one, and what the policy does when it drives): the policy's *own*
  previous commands feed its features (:meth:`predict` step by step, as in closed loop); only the
  sensors come from the recording.
* ``teacher_forced``: the *teacher's* previous command feeds the features (an open-loop replay,
  as the paper's Figure 3 did). A policy whose features include the previous command can then
  score well by echoing the teacher one step late, which is why the ``copy_previous`` baseline
  (the teacher's previous command, verbatim) stands beside it.

Agreement metrics (:func:`agreement`), the same keys for every mode and baseline:

* ``drive``: fraction of steps where the drive command (reverse/off/forward) is the same;
* ``steer_timing``: fraction of steps where both steer or both do not (steer vs no steer);
* ``steer_direction``: among steps where both steer, the fraction steering the same way (once a
  turn has begun the recorded steering angle and current show its side, so this is easy);
* steer *onsets*: a teacher onset is a step where the teacher starts steering (off, or an episode
  start, before; left/right now); a policy onset likewise. For every teacher onset,
  ``onset_hit_w1`` / ``onset_hit_w2``: the fraction at which the policy has an onset within +-1 /
  +-2 steps; ``onset_same_side_w1`` / ``_w2``: the fraction at which that policy onset (the
  nearest one, the earlier on a tie) steers to the same side (a miss counts as not the same
  side); ``onset_side_given_hit_w2``: the same side among hits only (0.5 is a coin). A policy
  onset *after* the teacher's reads the recorded steering angle and current, which already show
  the teacher's side, so ``onset_side_given_early_hit_w2`` keeps only hits where the policy
  starts at or before the teacher (nothing of the teacher's choice recorded yet), and
  ``onset_hit_early_w2`` is the fraction of teacher onsets the policy anticipates that way
  (within 2 steps before, or at, the onset): timing that cannot come from reading the recorded
  steering back. ``onset_hit_w2_chance`` / ``onset_hit_early_w2_chance`` are what the same
  number of policy onsets placed at random would hit (a policy that steers often hits often). The
  ``_backoff`` variants count only onsets while the teacher reverses: the start of an escape turn,
  whose side the teacher draws at random (the paper's point: the side cannot be learned).
  ``onsets`` / ``backoff_onsets`` are the counts; ``ci`` holds 95% percentile-bootstrap intervals
  of every onset fraction, resampling onsets.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mkv_env.actions import OFF, REVERSE
from sfm_learn.eigenspace.policy import episode_starts
from sfm_learn.evaluation.bootstrap import proportion_ci

__all__ = ["MODES", "Comparison", "agreement", "compare", "replay", "onsets"]

MODES = ("teacher_forced", "free_running")
BASELINES = ("copy_previous", "constant")
ONSET_KEYS = ("onset_hit_w1", "onset_hit_w2", "onset_same_side_w1", "onset_same_side_w2",
              "onset_side_given_hit_w2", "onset_hit_early_w2", "onset_side_given_early_hit_w2",
              "onset_hit_w2_backoff",
              "onset_same_side_w2_backoff", "onset_side_given_hit_w2_backoff")


def onsets(steer, episode_start=None) -> np.ndarray:
    """Indices where steering starts: ``steer != off`` now, and off before or an episode start."""
    on = np.asarray(steer) != OFF
    starts = np.zeros(on.shape, dtype=bool) if episode_start is None else np.asarray(
        episode_start, dtype=bool)
    prev_on = np.concatenate([[False], on[:-1]]) & ~starts
    return np.flatnonzero(on & ~prev_on)


def _matches(teacher, policy, starts, window: int):
    """For each teacher onset: (hit, same side) with the nearest policy onset within
    ``window`` steps in the same episode."""
    episode = np.cumsum(starts) if starts is not None else np.zeros(len(teacher), dtype=int)
    t_on = onsets(teacher[:, 1], starts)
    p_on = onsets(policy[:, 1], starts)
    hits = np.zeros(t_on.size, dtype=bool)
    same = np.zeros(t_on.size, dtype=bool)
    early = np.zeros(t_on.size, dtype=bool)
    for k, t in enumerate(t_on):
        near = p_on[(np.abs(p_on - t) <= window) & (episode[p_on] == episode[t])]
        if near.size:
            best = near[np.argmin(np.abs(near - t) * 2 + (near > t))]  # nearest, earlier on tie
            hits[k] = True
            same[k] = policy[best, 1] == teacher[t, 1]
            early[k] = best <= t
    return t_on, hits, same, early


def agreement(teacher, policy, episode_start=None) -> dict:
    """Agreement metrics (module docstring) between two action arrays (n, 2) of [drive, steer]
    indices; ``episode_start`` (n,) marks episode boundaries (onsets never span them)."""
    teacher = np.asarray(teacher)
    policy = np.asarray(policy)
    if teacher.shape != policy.shape or teacher.ndim != 2 or teacher.shape[1] != 2:
        raise ValueError(f"expected two (n, 2) action arrays, got {teacher.shape} and "
                         f"{policy.shape}")
    n = len(teacher)
    if n == 0:
        raise ValueError("no steps to compare")
    starts = None
    if episode_start is not None:
        starts = np.asarray(episode_start, dtype=bool)
        if starts.shape != (n,):
            raise ValueError(f"episode_start must have shape ({n},), got {starts.shape}")
    t_steer, p_steer = teacher[:, 1] != OFF, policy[:, 1] != OFF
    both = t_steer & p_steer
    out = {
        "steps": int(n),
        "drive": float(np.mean(teacher[:, 0] == policy[:, 0])),
        "steer_timing": float(np.mean(t_steer == p_steer)),
        "steer_direction": (float(np.mean(teacher[both, 1] == policy[both, 1]))
                            if both.any() else None),
        "steer_direction_steps": int(both.sum()),
    }
    fractions = {}
    for w in (1, 2):
        t_on, hits, same, early = _matches(teacher, policy, starts, w)
        fractions[f"onset_hit_w{w}"] = hits
        fractions[f"onset_same_side_w{w}"] = same
        if w == 2:
            fractions["onset_side_given_hit_w2"] = same[hits]
            fractions["onset_side_given_early_hit_w2"] = same[hits & early]
            fractions["onset_hit_early_w2"] = hits & early
            backoff = teacher[t_on, 0] == REVERSE
            fractions["onset_hit_w2_backoff"] = hits[backoff]
            fractions["onset_same_side_w2_backoff"] = same[backoff]
            fractions["onset_side_given_hit_w2_backoff"] = same[backoff & hits]
            out["onsets"] = int(t_on.size)
            out["backoff_onsets"] = int(backoff.sum())
            out["policy_onsets"] = int(onsets(policy[:, 1], starts).size)
            # what onsets placed at random (same number) would hit: the chance level
            rate = out["policy_onsets"] / n
            out["onset_hit_w2_chance"] = float(1.0 - (1.0 - rate) ** 5)
            out["onset_hit_early_w2_chance"] = float(1.0 - (1.0 - rate) ** 3)
    for key in ONSET_KEYS:
        v = fractions[key]
        out[key] = float(v.mean()) if v.size else None
    out["ci"] = {key: proportion_ci(fractions[key]) for key in ONSET_KEYS}
    return out


def replay(policy, data, mode: str = "free_running") -> np.ndarray:
    """The policy's commands (n_steps, 2) on a recording, in replay ``mode`` (:data:`MODES`).

    ``free_running`` works for any policy with SB3's ``predict`` (the feature state is its own);
    ``teacher_forced`` needs a policy that can take the recorded previous commands
    (``batch_predict`` of :class:`~sfm_learn.eigenspace.policy.SfMPolicy`, ``batch_actions`` of
    a BC policy).
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    obs = np.asarray(data["observations"])
    starts = episode_starts(data)
    teacher = np.asarray(data["actions"], dtype=np.int64)
    if mode == "teacher_forced":
        for name in ("batch_predict", "batch_actions"):
            if hasattr(policy, name):
                return np.asarray(getattr(policy, name)(obs, teacher, starts), dtype=np.int64)
        raise ValueError(f"{type(policy).__name__} cannot replay teacher-forced (it does not "
                         "take recorded previous commands)")
    if hasattr(policy, "reset"):
        policy.reset()
    out = np.empty_like(teacher)
    for t in range(len(obs)):
        out[t] = policy.predict(obs[t], episode_start=bool(starts[t]))[0]
    return out


def baseline_actions(teacher, starts) -> dict[str, np.ndarray]:
    """The baselines on the same steps: ``copy_previous`` (the teacher's previous command; off/off
    at an episode's first step) and ``constant`` (each command's most frequent value)."""
    teacher = np.asarray(teacher, dtype=np.int64)
    prev = np.vstack([[OFF, OFF], teacher[:-1]])
    prev[np.asarray(starts, dtype=bool)] = [OFF, OFF]
    const = np.array([np.bincount(teacher[:, j], minlength=3).argmax() for j in range(2)])
    return {"copy_previous": prev, "constant": np.tile(const, (len(teacher), 1))}


@dataclass
class Comparison:
    """A policy replayed on recorded teacher runs, in both modes, with the baselines."""

    modes: dict[str, dict]
    """``{"teacher_forced": agreement, "free_running": agreement}``."""
    baselines: dict[str, dict]
    """``{"copy_previous": agreement, "constant": agreement}`` on the same steps."""
    per_episode: list[dict]
    """Per episode: seed and the free-running agreement."""
    teacher: np.ndarray = field(repr=False)
    actions: dict[str, np.ndarray] = field(repr=False)
    """The policy's commands per mode, (n_steps, 2) each."""
    episode_slices: list[slice] = field(repr=False)
    control_period_s: float = 0.1

    def to_dict(self) -> dict:
        return {"modes": self.modes, "baselines": self.baselines, "episodes": self.per_episode}


def compare(policy, data, modes=MODES) -> Comparison:
    """Replay ``policy`` on dataset ``data`` in each of ``modes``; agreement per mode and for the
    baselines."""
    names = list(data.sensor_names)
    if names != list(policy.sensor_names):
        raise ValueError(f"the dataset's sensors [{', '.join(names)}] differ from the policy's "
                         f"[{', '.join(policy.sensor_names)}]")
    teacher = np.asarray(data["actions"], dtype=np.int64)
    starts = episode_starts(data)
    actions = {m: replay(policy, data, m) for m in modes}
    slices = data.episode_slices()
    free = actions.get("free_running", next(iter(actions.values())))
    per_episode = [dict(agreement(teacher[s], free[s]), seed=int(seed))
                   for s, seed in zip(slices, data["episode_seeds"], strict=True)]
    for ep in per_episode:
        ep.pop("ci")
    return Comparison(
        {m: agreement(teacher, a, starts) for m, a in actions.items()},
        {b: agreement(teacher, a, starts) for b, a in baseline_actions(teacher, starts).items()},
        per_episode, teacher, actions, slices,
        float(data.metadata.get("control_period_s", 0.1)))
