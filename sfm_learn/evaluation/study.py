"""Which features does the linear SfM policy need? The feature-set study (docs/sfm.md).

:func:`feature_study` fits the policy with each configuration of :data:`CONFIGS` on one or more
teacher recordings and measures, per fit, open-loop agreement on held-out teacher runs
(:func:`~sfm_learn.evaluation.compare.compare`) and the closed loop: escape rate on
``MKVJam-v0`` and stuck
fraction / distance on ``MKV-v0`` (:func:`sfm_learn.evaluation.evaluate`, same seeds for every
configuration). ``scripts/sfm_feature_study.py`` runs it on three training sets; ``mkv demo``
runs it on the demo's own training data.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from sfm_learn.eigenspace.features import FeatureSpec
from sfm_learn.eigenspace.policy import fit_policy
from sfm_learn.evaluation import evaluate
from sfm_learn.evaluation.compare import compare

__all__ = ["COLUMNS", "CONFIGS", "StudyConfig", "feature_study", "study_by_key"]

_NO_CURRENTS = ("drive_ticks", "roller_ticks", "steer_angle", "compass", "bump_front_left",
                "bump_front_right", "bump_rear", "battery")
_NO_BUMPS = ("drive_ticks", "roller_ticks", "steer_angle", "compass", "drive_current",
             "steer_current", "battery")
_T = (0.5, 0.8)



@dataclass(frozen=True)
class StudyConfig:
    """One configuration of the study: ``key`` (stable, for code), ``label`` (for tables),
    :class:`FeatureSpec` keyword arguments and :func:`fit_policy` keyword arguments."""

    key: str
    label: str
    features: dict = field(default_factory=dict)
    fit: dict = field(default_factory=dict)


_DEFAULT = {"trace_decays": _T, "prev_action": "signed"}

#: The configurations, in table order.
CONFIGS = (
    StudyConfig("paper_sensors", "sensors only (paper)"),
    StudyConfig("paper_sensors_lstsq", "sensors, lstsq solver", {}, {"solver": "lstsq"}),
    StudyConfig("prev", "sensors + prev command", {"prev_action": "signed"}),
    StudyConfig("traces", "sensors + traces", {"trace_decays": _T}),
    StudyConfig("default", "sensors + traces + prev (default)", _DEFAULT),
    StudyConfig("default_lstsq", "default, lstsq solver", _DEFAULT, {"solver": "lstsq"}),
    StudyConfig("default_onehot", "default, one-hot commands", _DEFAULT, {"encoding": "onehot"}),
    StudyConfig("history2_prev", "sensors + 2-step history + prev",
                {"history": 2, "prev_action": "signed"}),
    StudyConfig("no_currents", "default without currents", {"channels": _NO_CURRENTS, **_DEFAULT}),
    StudyConfig("no_bumps", "default without bumps", {"channels": _NO_BUMPS, **_DEFAULT}),
)
COLUMNS = ("rank", "known", "drive", "steer_timing", "escape_rate", "stuck_fraction",
           "distance_m")


def feature_study(trains: Sequence, held, *, jam_episodes: int = 100, wander_episodes: int = 20,
                  seed: int = 1000, configs=CONFIGS,
                  on_config: Callable[[str], None] | None = None
                  ) -> list[tuple[StudyConfig, np.ndarray]]:
    """Fit every configuration on every training set; returns ``(config, results)`` pairs with
    ``results`` of shape (len(trains), len(COLUMNS)), in the order of ``configs``."""
    names = tuple(trains[0].sensor_names)
    rows = []
    for config in configs:
        res = []
        for tr in trains:
            pol = fit_policy(tr, FeatureSpec(obs_names=names, **config.features), **config.fit)
            m = compare(pol, held).metrics
            ej = evaluate("MKVJam-v0", pol, jam_episodes, seed).metrics
            ew = evaluate("MKV-v0", pol, wander_episodes, seed).metrics
            res.append((pol.n_components, pol.projector.n_known_, m["drive"], m["steer_timing"],
                        ej["escape_rate"], ew["stuck_fraction"], ew["distance_m"]))
        rows.append((config, np.array(res, dtype=float)))
        if on_config is not None:
            on_config(config.label)
    return rows


def study_by_key(rows) -> dict[str, np.ndarray]:
    """``{config.key: mean over training sets}`` of :func:`feature_study` rows."""
    return {config.key: r.mean(axis=0) for config, r in rows}
