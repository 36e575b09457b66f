"""Policy evaluation on seeded episodes: per-episode records, then aggregate metrics.

Every policy (teacher, random, command script, SfM, PPO, BC) is evaluated the same way: episode
``i`` resets the env with seed ``seed + i``; the episode is recorded with
:mod:`mkv_env.recorder` (so metrics come from the same ground-truth ``info`` a dataset stores);
each episode becomes an :class:`EpisodeRecord`; :func:`aggregate` turns a list of records into the
metrics below. Records are plain, picklable and independent of one another, so a caller can run
seeds in worker processes, evaluate several policies on the same seeds, or bootstrap confidence
intervals by resampling records and calling :func:`aggregate` again.

Metrics (:data:`METRIC_KEYS`; ``None`` where undefined):

* ``escape_rate``: fraction of episodes that ended escaped (envs that report ``escaped``, e.g.
  ``MKVJam-v0``; ``None`` otherwise).
* ``mean_escape_time_s``: mean time to escape over escaped episodes [s] (``None`` if none escaped
  or the env has no escapes).
* ``distance_m``: mean distance travelled per episode [m].
* ``stuck_fraction``: stuck steps / all steps, pooled over episodes.
* ``collisions_per_min``: new collisions / simulated minutes, pooled over episodes.
* ``mean_return``: mean undiscounted episode return.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from mkv_env.dataset import Dataset
from mkv_env.recorder import record

METRIC_KEYS = ("escape_rate", "mean_escape_time_s", "distance_m", "stuck_fraction",
               "collisions_per_min", "mean_return")

METRIC_LABELS = {
    "escape_rate": "escape rate",
    "mean_escape_time_s": "mean time to escape [s]",
    "distance_m": "distance per episode [m]",
    "stuck_fraction": "stuck fraction",
    "collisions_per_min": "collisions per minute",
    "mean_return": "mean return",
}


@dataclass(frozen=True)
class EpisodeRecord:
    """What one episode did (ground truth), enough to aggregate every metric."""

    seed: int
    steps: int
    duration_s: float
    episode_return: float
    distance_m: float
    stuck_steps: int
    collisions: int
    jams: int
    escapes: int
    escaped: bool | None
    """Ended escaped; ``None`` when the env does not report escapes."""
    escape_time_s: float | None
    """Time of the first escaped step [s]; ``None`` if not escaped."""
    scenario: str | None = None


def episode_records(data: Dataset) -> list[EpisodeRecord]:
    """One :class:`EpisodeRecord` per episode of a recorded dataset."""
    dt = float(data.metadata["control_period_s"])
    scen = data.metadata.get("episode_scenarios") or [None] * data.n_episodes
    out = []
    for e, rows in enumerate(data.episode_slices()):
        last = rows.stop - 1
        escaped = escape_time = None
        if "escaped" in data:
            flags = data["escaped"][rows]
            escaped = bool(flags[-1])
            if flags.any():
                escape_time = (int(np.argmax(flags)) + 1) * dt
        n = rows.stop - rows.start
        out.append(EpisodeRecord(
            seed=int(data["episode_seeds"][e]),
            steps=int(n),
            duration_s=n * dt,
            episode_return=float(data["rewards"][rows].sum()),
            distance_m=float(data["distance_m"][last]),
            stuck_steps=int(data["stuck"][rows].sum()),
            collisions=int(data["collisions"][last]),
            jams=int(data["jams"][last]),
            escapes=int(data["escapes"][last]),
            escaped=escaped,
            escape_time_s=escape_time,
            scenario=scen[e],
        ))
    return out


def aggregate(records: Sequence[EpisodeRecord]) -> dict[str, float | None]:
    """The metrics of :data:`METRIC_KEYS` from episode records (see the module docstring)."""
    if not records:
        raise ValueError("no episode records to aggregate")
    steps = sum(r.steps for r in records)
    minutes = sum(r.duration_s for r in records) / 60.0
    has_escape = all(r.escaped is not None for r in records)
    escape_rate = mean_escape_time = None
    if has_escape:
        escape_rate = sum(bool(r.escaped) for r in records) / len(records)
        times = [r.escape_time_s for r in records if r.escape_time_s is not None]
        mean_escape_time = float(np.mean(times)) if times else None
    return {
        "escape_rate": escape_rate,
        "mean_escape_time_s": mean_escape_time,
        "distance_m": float(np.mean([r.distance_m for r in records])),
        "stuck_fraction": sum(r.stuck_steps for r in records) / steps if steps else None,
        "collisions_per_min": (sum(r.collisions for r in records) / minutes
                               if minutes > 0 else None),
        "mean_return": float(np.mean([r.episode_return for r in records])),
    }


@dataclass
class Evaluation:
    """One policy on one env over seeds ``seed .. seed + episodes - 1``."""

    env: str
    policy: str
    episodes: int
    seed: int
    metrics: dict[str, float | None]
    records: list[EpisodeRecord] = field(default_factory=list, repr=False)
    env_kwargs: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The ``mkv eval --json`` document: exactly env, policy, episodes, seed, metrics."""
        return {
            "env": self.env,
            "policy": self.policy,
            "episodes": self.episodes,
            "seed": self.seed,
            "metrics": {k: _json_number(self.metrics[k]) for k in METRIC_KEYS},
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2) + "\n"

    def records_as_dicts(self) -> list[dict]:
        return [asdict(r) for r in self.records]


def run_episodes(env_id: str, policy, seeds: Sequence[int] | None = None, *, episodes: int = 0,
                 seed: int = 0, env_kwargs: dict | None = None,
                 on_episode: Callable[[int, int], None] | None = None) -> list[EpisodeRecord]:
    """Run ``policy`` (spec string or object with ``predict``) and return one record per episode.

    Give either consecutive seeds by ``episodes`` and ``seed`` (episode ``i`` uses ``seed + i``),
    or ``seeds`` as a list of consecutive integers (a worker's share of a larger evaluation).
    """
    if seeds is not None:
        seeds = [int(s) for s in seeds]
        if not seeds or seeds != list(range(seeds[0], seeds[0] + len(seeds))):
            raise ValueError("seeds must be a non-empty run of consecutive integers")
        seed, episodes = seeds[0], len(seeds)
    data = record(env_id, policy, episodes, seed, env_kwargs, on_episode=on_episode)
    return episode_records(data)


def evaluate(env_id: str, policy, episodes: int, seed: int = 0, env_kwargs: dict | None = None,
             on_episode: Callable[[int, int], None] | None = None,
             policy_name: str | None = None) -> Evaluation:
    """Evaluate one policy on seeded episodes; returns records and aggregate metrics.

    Args:
        env_id: registered Gymnasium id (``"MKV-v0"``, ``"MKVJam-v0"``).
        policy: a spec string (``"teacher"``, ``"random"``, ``"script:PATH"``, plug-in specs) or an
            object with SB3 ``predict``.
        episodes: number of episodes (>= 1); episode ``i`` uses env seed ``seed + i``.
        seed: first env seed.
        env_kwargs: extra ``gymnasium.make`` arguments.
        on_episode: progress callback ``(episode_index, n_steps)``.
        policy_name: name for reports (default: the spec, or the policy's ``spec`` attribute).
    """
    records = run_episodes(env_id, policy, episodes=episodes, seed=seed, env_kwargs=env_kwargs,
                           on_episode=on_episode)
    name = policy_name or (policy if isinstance(policy, str)
                           else getattr(policy, "spec", type(policy).__name__))
    return Evaluation(env_id, name, int(episodes), int(seed), aggregate(records), records,
                      dict(env_kwargs or {}))


def format_table(evaluations: Sequence[Evaluation]) -> str:
    """A plain-text table: one row per metric, one column per evaluation (policy)."""
    if not evaluations:
        return ""
    heads = [e.policy for e in evaluations]
    label_w = max(len(v) for v in METRIC_LABELS.values())
    col_w = [max(10, len(h)) for h in heads]
    first = evaluations[0]
    lines = [f"{first.env}: {first.episodes} episodes, seeds {first.seed}.."
             f"{first.seed + first.episodes - 1}"]
    lines.append(f"{'metric':<{label_w}}  " + "  ".join(
        f"{h:>{w}}" for h, w in zip(heads, col_w, strict=True)))
    for key in METRIC_KEYS:
        cells = [_fmt(e.metrics[key]) for e in evaluations]
        lines.append(f"{METRIC_LABELS[key]:<{label_w}}  " + "  ".join(
            f"{c:>{w}}" for c, w in zip(cells, col_w, strict=True)))
    return "\n".join(lines)


def _fmt(v) -> str:
    if v is None:
        return "-"
    return f"{v:.3f}"


def _json_number(v):
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None
