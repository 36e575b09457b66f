"""The paper's Figure 3 comparison: teacher commands vs what the SfM policy would have done.

The policy is replayed open loop on a recorded (held-out) teacher run: at every step it sees the
recorded sensors (and, if its features include the previous command, the teacher's previous
command), and its command is compared with the teacher's. Three agreements, as in the paper's
section 9:

* ``drive``: fraction of steps where the drive command (reverse/off/forward) is the same;
* ``steer_timing``: fraction of steps where both steer or both do not (steer vs no steer);
* ``steer_direction``: among steps where *both* steer, the fraction steering the same way. The
  teacher picks its escape direction at random, so the paper found this near chance. Once a turn
  has begun, though, the sensors (steering angle, signed steering current) and the previous
  command show which way it goes, so most steps of a turn are easy to continue;
* ``steer_direction_onset``: at each step where the teacher *starts* steering (off before,
  left/right now) and the policy steers too, whether it goes the same way. Only that very step
  counts (``ONSET_WINDOW = 1``): one step later the recorded sensors already show the teacher's
  turn (steering angle, signed steering current), and a replayed policy would just be reading
  the teacher's choice back (with a 5-step window the "agreement" rises to about 0.95 for that
  reason, random escape sides included). ``steer_direction_backoff_onset`` is the same
  restricted to onsets while the teacher reverses: the start of an escape turn, whose side the
  teacher draws at random (the paper's point); other onsets (re-centring, the turn after a
  back-off) follow from the sensors.

Each comes with the score a constant guess would get (the teacher's most frequent value), so a
number can be read against what doing nothing clever achieves.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Comparison", "agreement", "compare"]

OFF = 1
ONSET_WINDOW = 1


def agreement(teacher, policy) -> dict:
    """Agreement metrics between two action arrays (n, 2) of [drive, steer] indices."""
    teacher = np.asarray(teacher)
    policy = np.asarray(policy)
    if teacher.shape != policy.shape or teacher.ndim != 2 or teacher.shape[1] != 2:
        raise ValueError(f"expected two (n, 2) action arrays, got {teacher.shape} and "
                         f"{policy.shape}")
    n = len(teacher)
    if n == 0:
        raise ValueError("no steps to compare")
    t_steer, p_steer = teacher[:, 1] != OFF, policy[:, 1] != OFF
    both = t_steer & p_steer
    drive_counts = np.bincount(teacher[:, 0], minlength=3)
    steer_frac = float(t_steer.mean())
    onsets = np.flatnonzero(t_steer[1:] & ~t_steer[:-1]) + 1
    matches, reversing = [], []
    for t in onsets:  # the policy's first steer within ONSET_WINDOW steps of the teacher's onset
        w = np.flatnonzero(p_steer[t:t + ONSET_WINDOW])
        if w.size:
            matches.append(policy[t + w[0], 1] == teacher[t, 1])
            reversing.append(teacher[t, 0] == 0)
    matches, reversing = np.array(matches, dtype=bool), np.array(reversing, dtype=bool)
    onset_dir = float(np.mean(matches)) if matches.size else None
    backoff_dir = float(np.mean(matches[reversing])) if reversing.any() else None
    if both.any():
        direction = float(np.mean(teacher[both, 1] == policy[both, 1]))
        left = float(np.mean(teacher[t_steer, 1] == 0))
        direction_const = max(left, 1.0 - left)
    else:
        direction = direction_const = None
    return {
        "steps": int(n),
        "drive": float(np.mean(teacher[:, 0] == policy[:, 0])),
        "steer_timing": float(np.mean(t_steer == p_steer)),
        "steer_direction": direction,
        "steer_direction_steps": int(both.sum()),
        "steer_direction_onset": onset_dir,
        "steer_onsets": int(matches.size),
        "steer_direction_backoff_onset": backoff_dir,
        "steer_backoff_onsets": int(reversing.sum()),
        "baseline": {
            "drive": float(drive_counts.max() / n),
            "steer_timing": max(steer_frac, 1.0 - steer_frac),
            "steer_direction": direction_const,
            "steer_direction_onset": 0.5 if onset_dir is not None else None,
            "steer_direction_backoff_onset": 0.5 if backoff_dir is not None else None,
        },
    }


@dataclass
class Comparison:
    """Open-loop replay of a policy on recorded teacher runs."""

    metrics: dict
    per_episode: list[dict]
    teacher: np.ndarray = field(repr=False)
    policy: np.ndarray = field(repr=False)
    values: np.ndarray = field(repr=False)
    episode_slices: list[slice] = field(repr=False)
    control_period_s: float = 0.1


def compare(policy, data) -> Comparison:
    """Replay ``policy`` (an :class:`~sfm_learn.eigenspace.policy.SfMPolicy`) on ``data``."""
    from sfm_learn.eigenspace.policy import episode_starts

    names = list(data.sensor_names)
    if names != list(policy.sensor_names):
        raise ValueError(f"the dataset's sensors [{', '.join(names)}] differ from the policy's "
                         f"[{', '.join(policy.sensor_names)}]")
    teacher = np.asarray(data["actions"], dtype=np.int64)
    values = policy.batch_values(data["observations"], teacher, episode_starts(data))
    predicted = policy.decode(values)
    slices = data.episode_slices()
    per_episode = [dict(agreement(teacher[s], predicted[s]), seed=int(seed))
                   for s, seed in zip(slices, data["episode_seeds"], strict=True)]
    return Comparison(agreement(teacher, predicted), per_episode, teacher, predicted, values,
                      slices, float(data.metadata.get("control_period_s", 0.1)))
