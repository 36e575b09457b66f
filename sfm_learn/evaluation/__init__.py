"""Evaluation: policies run on seeded episodes -> per-episode records -> metrics with bootstrap
intervals; the Figure 3 agreement of replayed commands; the feature-set study.

* :mod:`~sfm_learn.evaluation.records`: :class:`EpisodeRecord`, :func:`aggregate`,
  :class:`Evaluation` and its JSON;
* :mod:`~sfm_learn.evaluation.bootstrap`: :func:`bootstrap_ci`, :func:`paired_difference_ci`;
* :mod:`~sfm_learn.evaluation.runner`: :func:`evaluate`, :func:`evaluate_many` (worker processes);
* :mod:`~sfm_learn.evaluation.compare`: agreement of a policy's commands with a recording;
* :mod:`~sfm_learn.evaluation.study`: which features the SfM policy needs.
"""

from sfm_learn.evaluation.bootstrap import bootstrap_ci, paired_difference_ci
from sfm_learn.evaluation.records import (
    METRIC_KEYS,
    EpisodeRecord,
    Evaluation,
    aggregate,
    episode_records,
    evaluations_json,
)
from sfm_learn.evaluation.runner import evaluate, evaluate_many, run_episodes

__all__ = ["METRIC_KEYS", "EpisodeRecord", "Evaluation", "aggregate", "bootstrap_ci",
           "episode_records", "evaluate", "evaluate_many", "evaluations_json",
           "paired_difference_ci", "run_episodes"]
