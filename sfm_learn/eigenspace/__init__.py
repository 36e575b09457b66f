"""The paper's learner: an eigenspace projector over stacked sensor features and motor commands.

* :mod:`~sfm_learn.eigenspace.projector`: :class:`EigenspaceProjector` (standardise, SVD, rank by
  the largest adjacent singular-value ratio, run-time projection; incremental fitting);
* :mod:`~mkv_env.features`: :class:`FeatureSpec` / :class:`FeatureBuilder` (sensor
  channels, history, decaying traces, previous command; batch equals online);
* :mod:`~sfm_learn.eigenspace.policy`: :class:`SfMPolicy` and :func:`fit_policy` (quantised
  three-valued commands, SB3 ``predict``, policy files).
"""

from mkv_env.features import FeatureBuilder, FeatureSpec, default_feature_spec
from sfm_learn.eigenspace.policy import SfMPolicy, fit_policy
from sfm_learn.eigenspace.projector import EigenspaceProjector

__all__ = ["EigenspaceProjector", "FeatureBuilder", "FeatureSpec", "SfMPolicy",
           "default_feature_spec", "fit_policy"]
