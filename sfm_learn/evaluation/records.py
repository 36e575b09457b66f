"""What an evaluation measures: one record per episode, the metrics over records, and the
evaluation result with its JSON form.

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
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from mkv_env.dataset import Dataset

__all__ = ["METRIC_KEYS", "CI_LEVEL", "N_BOOT", "EpisodeRecord", "Evaluation", "aggregate",
           "episode_records", "evaluations_json"]

METRIC_KEYS = ("escape_rate", "mean_escape_time_s", "distance_m", "stuck_fraction",
               "collisions_per_min", "mean_return")

#: Default number of bootstrap resamples and confidence level.
N_BOOT = 2000
CI_LEVEL = 0.95


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
    metrics_ci: dict[str, list[float] | None] | None = None
    """Bootstrap interval per metric (:func:`bootstrap_ci`); ``None`` if not computed."""
    ci_level: float = CI_LEVEL
    n_boot: int = N_BOOT
    training_sets: int = 1
    """How many independently trained copies of the policy the records pool (:func:`pool`):
    ``training_sets x episodes`` records, each seed once per copy."""

    def to_dict(self) -> dict:
        """The ``mkv eval --json`` document: exactly env, policy, episodes, seed, metrics and
        metrics_ci (same keys as metrics, each ``[low, high]`` or ``None``); plus
        ``training_sets`` for a pooled evaluation."""
        ci = self.metrics_ci or {}
        doc = {
            "env": self.env,
            "policy": self.policy,
            "episodes": self.episodes,
            "seed": self.seed,
            "metrics": {k: _json_number(self.metrics[k]) for k in METRIC_KEYS},
            "metrics_ci": {k: _json_interval(ci.get(k)) for k in METRIC_KEYS},
        }
        if self.training_sets != 1:
            doc["training_sets"] = self.training_sets
        return doc

    def to_json(self) -> str:
        return _dumps(self.to_dict())

    def records_as_dicts(self) -> list[dict]:
        return [asdict(r) for r in self.records]


def evaluations_json(evaluations: Sequence[Evaluation]) -> str:
    """The ``mkv eval --json`` file: one :meth:`Evaluation.to_dict` object for one evaluation,
    a list of them (in the given order) for several."""
    if not evaluations:
        raise ValueError("no evaluations")
    doc = (evaluations[0].to_dict() if len(evaluations) == 1
           else [e.to_dict() for e in evaluations])
    return _dumps(doc)


_PAIR = re.compile(r"\[\n\s*(-?[0-9][0-9.eE+-]*),\n\s*(-?[0-9][0-9.eE+-]*)\n\s*\]")


def _dumps(doc) -> str:
    """Indented JSON with each ``[low, high]`` interval on one line (a JSON string never holds a
    raw newline, so only number pairs can match)."""
    return _PAIR.sub(r"[\1, \2]", json.dumps(doc, indent=2)) + "\n"


def _json_number(v):
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _json_interval(ci):
    if ci is None:
        return None
    low, high = _json_number(ci[0]), _json_number(ci[1])
    return None if low is None or high is None else [low, high]

