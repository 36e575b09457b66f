"""Studies of the SfM policy over several training sets: which features it needs, the paper's own
configuration, and the kept rank (docs/sfm.md).

:func:`run_study` fits every configuration (:class:`StudyConfig`: features, solver, thresholds,
rank) on every training set (teacher recordings with different seeds), and measures per fit:

* free-running agreement with held-out teacher runs (:func:`~sfm_learn.evaluation.compare.
  compare`: drive, steer timing, steer onsets hit within +-2 steps);
* the closed loop on the same env seeds for every fit: escape rate on ``MKVJam-v1``, stuck
  fraction and distance on ``MKV-v1`` (the v0 ids give the same numbers: only their rewards
  differ, and the study reports no reward; all fits evaluated together by
  :func:`~sfm_learn.evaluation.runner.evaluate_many`, so worker processes share them out).

Results are one row per (configuration, training set); tables report the mean over training
sets with the range [min..max], so one lucky training set cannot carry a conclusion.
``scripts/sfm_study.py`` runs the full studies; ``mkv demo`` runs them on its own data.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from mkv_env.features import FeatureSpec, default_feature_spec
from mkv_env.params import SENSOR_NAMES
from sfm_learn.eigenspace.policy import fit_policy
from sfm_learn.evaluation.compare import compare
from sfm_learn.evaluation.runner import evaluate_many

__all__ = ["COLUMNS", "FEATURE_CONFIGS", "StudyConfig", "rank_configs", "run_study",
           "study_by_key", "StudyResult"]

_NO_CURRENTS = tuple(n for n in SENSOR_NAMES if not n.endswith("_current"))
_NO_BUMPS = tuple(n for n in SENSOR_NAMES if not n.startswith("bump_"))
_T = (0.5, 0.8)
_DEFAULT = {"trace_decays": _T, "prev_action": "signed"}
_PAPER_FIT = {"solver": "lstsq", "thresholds": "fixed", "min_support": 0}


@dataclass(frozen=True)
class StudyConfig:
    """One configuration: ``key`` (stable, for code), ``label`` (for tables),
    :class:`FeatureSpec` keyword arguments and :func:`fit_policy` keyword arguments."""

    key: str
    label: str
    features: dict = field(default_factory=dict)
    fit: dict = field(default_factory=dict)


#: The feature-set study, in table order.
FEATURE_CONFIGS = (
    StudyConfig("paper", "paper: raw sensors, lstsq, fixed +-0.5", {}, _PAPER_FIT),
    StudyConfig("raw_ppca", "raw sensors, ppca, learned thresholds"),
    StudyConfig("prev", "sensors + prev command", {"prev_action": "signed"}),
    StudyConfig("traces", "sensors + traces", {"trace_decays": _T}),
    StudyConfig("default", "sensors + traces + prev (default)", _DEFAULT),
    StudyConfig("default_ols", "default features, OLS (no eigenspace)", _DEFAULT,
                {"solver": "ols"}),
    StudyConfig("default_lstsq", "default features, lstsq solver", _DEFAULT, {"solver": "lstsq"}),
    StudyConfig("default_onehot", "default, one-hot commands", _DEFAULT, {"encoding": "onehot"}),
    StudyConfig("history2_prev", "sensors + 2-step history + prev",
                {"history": 2, "prev_action": "signed"}),
    StudyConfig("no_currents", "default without currents", {"channels": _NO_CURRENTS, **_DEFAULT}),
    StudyConfig("no_bumps", "default without bumps", {"channels": _NO_BUMPS, **_DEFAULT}),
)

#: Columns of a study row.
COLUMNS = ("rank", "known", "drive", "steer_timing", "onset_hit_w2", "escape_rate",
           "stuck_fraction", "distance_m")


def rank_configs(sensor_names, preset: str, ranks: Sequence[int] | None = None
                 ) -> list[StudyConfig]:
    """One configuration per kept rank n for the ``default`` or ``paper`` preset (all ranks
    1..n_known by default)."""
    names = tuple(sensor_names)
    if preset == "default":
        features, fit = _DEFAULT, {}
        n_max = default_feature_spec(names).n_features
    elif preset == "paper":
        features, fit = {}, _PAPER_FIT
        n_max = len(names)
    else:
        raise ValueError(f"preset must be 'default' or 'paper', got {preset!r}")
    ranks = range(1, n_max + 1) if ranks is None else [r for r in ranks if 1 <= r <= n_max]
    return [StudyConfig(f"{preset}_n{n}", f"{preset}, n = {n}", features,
                        {**fit, "n_components": int(n)}) for n in ranks]


@dataclass
class StudyResult:
    """Rows of a study: ``values[c, s, :]`` holds :data:`COLUMNS` for configuration ``c`` on
    training set ``s``; ``rule_rank[c, s]`` is the rank the largest-ratio rule would pick."""

    configs: list[StudyConfig]
    values: np.ndarray
    rule_rank: np.ndarray
    seed: int
    jam_episodes: int
    wander_episodes: int

    def column(self, name: str) -> np.ndarray:
        """(n_configs, n_sets) values of one column."""
        return self.values[:, :, COLUMNS.index(name)]


def run_study(trains: Sequence, held, configs: Sequence[StudyConfig], *,
              jam_episodes: int = 100, wander_episodes: int = 20, seed: int = 1000,
              workers: int = 1, on_episode: Callable[[], None] | None = None,
              jam_env: str = "MKVJam-v1", wander_env: str = "MKV-v1") -> StudyResult:
    """Fit every configuration on every training set; measure free-running agreement on ``held``
    and the closed loop on env seeds ``seed ..``; returns a :class:`StudyResult`."""
    names = tuple(trains[0].sensor_names)
    configs = list(configs)
    values = np.full((len(configs), len(trains), len(COLUMNS)), np.nan)
    rule = np.zeros((len(configs), len(trains)), dtype=int)
    with tempfile.TemporaryDirectory(prefix="mkv-study-") as tmp:
        specs = []
        for c, config in enumerate(configs):
            spec = FeatureSpec(obs_names=names, **config.features)
            for s, train in enumerate(trains):
                pol = fit_policy(train, spec, **config.fit)
                rule[c, s] = _rule_rank(pol)
                free = compare(pol, held, modes=("free_running",)).modes["free_running"]
                values[c, s, :5] = (pol.n_components, pol.projector.n_known_, free["drive"],
                                    free["steer_timing"], free["onset_hit_w2"])
                specs.append(f"sfm:{pol.save(os.path.join(tmp, f'c{c}_s{s}.npz'))}")
        tick = None if on_episode is None else (lambda *a: on_episode())
        jam = evaluate_many(jam_env, specs, jam_episodes, seed, workers=workers,
                            on_episode=tick, n_boot=0)
        wander = evaluate_many(wander_env, specs, wander_episodes, seed, workers=workers,
                               on_episode=tick, n_boot=0)
    for k, (j, w) in enumerate(zip(jam, wander, strict=True)):
        c, s = divmod(k, len(trains))
        values[c, s, 5:] = (j.metrics["escape_rate"], w.metrics["stuck_fraction"],
                            w.metrics["distance_m"])
    return StudyResult(configs, values, rule, seed, jam_episodes, wander_episodes)


def _rule_rank(policy) -> int:
    """The rank the paper's rule picks on this policy's spectrum (whatever rank was kept)."""
    from sfm_learn.eigenspace.projector import select_rank

    proj = policy.projector
    return int(select_rank(proj.singular_values_, proj.rank_floor_,
                           max_rank=proj.n_known_)[0])


def study_by_key(result: StudyResult) -> dict[str, np.ndarray]:
    """``{config.key: mean over training sets of each column}``."""
    return {c.key: result.values[i].mean(axis=0) for i, c in enumerate(result.configs)}
