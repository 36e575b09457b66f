"""Percentile-bootstrap confidence intervals over episodes, on :func:`scipy.stats.bootstrap`.

Resamples are episode indices drawn from a fixed stream that depends only on the number of
records (:func:`resample_rng`), so

* the same records always give the same intervals (no clock, no OS entropy), and
* policies evaluated on the same seeds are resampled with the same episodes: a *paired*
  bootstrap, so the interval of a difference between two policies reflects how they differ, not
  how hard the drawn episodes were (:func:`paired_difference_ci`).

Every metric of :func:`~sfm_learn.evaluation.records.aggregate` is computed on every resample at
once (:func:`resampled_metrics`). A metric can be undefined on a resample (the mean escape time of
a resample without an escape): such resamples are dropped for that metric, so its interval is
conditional on the metric existing.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np
from scipy import stats

from sfm_learn.evaluation.records import (
    CI_LEVEL,
    METRIC_KEYS,
    N_BOOT,
    EpisodeRecord,
    aggregate,
)

__all__ = ["bootstrap_ci", "paired_difference_ci", "proportion_ci", "resampled_metrics",
           "resample_rng"]

# Fixed entropy of the bootstrap stream (with the number of records): no clock, no OS entropy.
_BOOT_ENTROPY = 0x5EEDB007
# Resamples are drawn in one block up to this many indices (memory ~ 8 bytes each); larger
# problems are drawn in batches (a different, equally fixed, stream).
_MAX_BLOCK = 40_000_000


def resample_rng(n: int) -> np.random.Generator:
    """The generator of resample indices for ``n`` records (depends only on ``n``)."""
    if n < 1:
        raise ValueError(f"need at least one record, got {n}")
    return np.random.default_rng(np.random.SeedSequence([_BOOT_ENTROPY, int(n)]))


def resampled_metrics(records: Sequence[EpisodeRecord],
                      idx: np.ndarray) -> dict[str, np.ndarray]:
    """Every metric of :func:`aggregate` for each row of resample indices ``idx`` (k, n), at once.

    Row ``j`` equals ``aggregate([records[i] for i in idx[j]])`` (up to rounding), with NaN where
    that metric is undefined for the resample (e.g. mean escape time when it has no escape).
    """
    if not records:
        raise ValueError("no episode records to resample")
    idx = np.asarray(idx)
    steps = np.array([r.steps for r in records], dtype=np.float64)[idx]
    dur = np.array([r.duration_s for r in records], dtype=np.float64)[idx]
    out = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        if all(r.escaped is not None for r in records):
            esc = np.array([bool(r.escaped) for r in records], dtype=np.float64)[idx]
            out["escape_rate"] = esc.mean(axis=1)
            has_t = np.array([r.escape_time_s is not None for r in records])[idx]
            t = np.array([r.escape_time_s or 0.0 for r in records], dtype=np.float64)[idx]
            cnt = has_t.sum(axis=1)
            out["mean_escape_time_s"] = np.where(cnt > 0, t.sum(axis=1) / cnt, np.nan)
        else:
            out["escape_rate"] = out["mean_escape_time_s"] = np.full(len(idx), np.nan)
        out["distance_m"] = np.array([r.distance_m for r in records])[idx].mean(axis=1)
        tot_steps = steps.sum(axis=1)
        stuck = np.array([r.stuck_steps for r in records], dtype=np.float64)[idx].sum(axis=1)
        out["stuck_fraction"] = np.where(tot_steps > 0, stuck / tot_steps, np.nan)
        minutes = dur.sum(axis=1) / 60.0
        coll = np.array([r.collisions for r in records], dtype=np.float64)[idx].sum(axis=1)
        out["collisions_per_min"] = np.where(minutes > 0, coll / minutes, np.nan)
        out["mean_return"] = np.array([r.episode_return for r in records])[idx].mean(axis=1)
    return {k: out[k] for k in METRIC_KEYS}


def _bootstrap(n: int, statistic, level: float, n_boot: int):
    """Percentile bootstrap of ``statistic(idx) -> (k, m)`` over resamples ``idx`` (m, n) of
    ``range(n)``; returns the (k, n_boot) distribution and the (k, 2) interval, with resamples
    where a statistic is NaN dropped for that statistic."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"confidence level must be in (0, 1), got {level!r}")
    if n_boot < 1:
        raise ValueError(f"n_boot must be a positive integer, got {n_boot!r}")
    if n == 1:  # every resample is the one record (scipy needs two)
        idx = np.zeros((int(n_boot), 1), dtype=np.int64)
        dist = np.atleast_2d(statistic(idx))
        return dist, np.repeat(dist[:, :1], 2, axis=1)
    batch = None if n * n_boot <= _MAX_BLOCK else max(1, _MAX_BLOCK // n)
    with warnings.catch_warnings():
        # NaN resamples (undefined metric) make scipy's interval NaN and warn; they are
        # handled below from the bootstrap distribution.
        warnings.simplefilter("ignore", stats.DegenerateDataWarning)
        res = stats.bootstrap((np.arange(n),), statistic, n_resamples=int(n_boot), batch=batch,
                              vectorized=True, method="percentile", confidence_level=level,
                              rng=resample_rng(n))
    dist = np.atleast_2d(res.bootstrap_distribution)
    ci = np.stack([np.atleast_1d(res.confidence_interval.low),
                   np.atleast_1d(res.confidence_interval.high)], axis=-1)
    q = [(1.0 - level) / 2.0, (1.0 + level) / 2.0]
    for k in np.flatnonzero(~np.isfinite(ci).all(axis=1)):
        vals = dist[k][np.isfinite(dist[k])]
        ci[k] = np.quantile(vals, q) if vals.size else np.nan
    return dist, ci


def bootstrap_ci(records: Sequence[EpisodeRecord], level: float = CI_LEVEL,
                 n_boot: int = N_BOOT,
                 metrics: dict[str, float | None] | None = None) -> dict[str, list[float] | None]:
    """Percentile-bootstrap confidence intervals of every metric, over episodes.

    Returns ``{key: [low, high]}`` with the keys of :data:`METRIC_KEYS`; ``None`` where the metric
    itself is ``None``. Each interval is widened, if need be, to contain the point estimate (this
    matters only for tiny samples and rounding). With one episode every interval is ``[m, m]``.
    """
    if metrics is None:
        metrics = aggregate(records)

    def statistic(idx, axis=-1):
        m = resampled_metrics(records, np.atleast_2d(idx))
        return np.stack([m[k] for k in METRIC_KEYS])

    _, ci = _bootstrap(len(records), statistic, level, n_boot)
    out: dict[str, list[float] | None] = {}
    for key, (low, high) in zip(METRIC_KEYS, ci, strict=True):
        point = metrics[key]
        if point is None or not np.isfinite(low):
            out[key] = None
            continue
        out[key] = [min(float(low), float(point)), max(float(high), float(point))]
    return out


def paired_difference_ci(a: Sequence[EpisodeRecord], b: Sequence[EpisodeRecord], key: str,
                         level: float = CI_LEVEL,
                         n_boot: int = N_BOOT) -> tuple[float, list[float]] | None:
    """Metric ``key`` of ``a`` minus that of ``b`` with a paired percentile-bootstrap interval.

    ``a`` and ``b`` must be records of the same seeds (two policies evaluated on the same
    episodes); each resample draws the same episodes for both. An interval that excludes 0 is the
    usual reading of "a significant difference" at that level. Resamples where either metric is
    undefined are dropped; ``None`` if the difference itself is undefined.
    """
    if [r.seed for r in a] != [r.seed for r in b]:
        raise ValueError("a paired comparison needs records of the same seeds, in order")
    if key not in METRIC_KEYS:
        raise ValueError(f"unknown metric {key!r}; known: {', '.join(METRIC_KEYS)}")
    ma, mb = aggregate(a)[key], aggregate(b)[key]
    if ma is None or mb is None:
        return None
    d = float(ma - mb)

    def statistic(idx, axis=-1):
        idx = np.atleast_2d(idx)
        return (resampled_metrics(a, idx)[key] - resampled_metrics(b, idx)[key])[None, :]

    dist, ci = _bootstrap(len(a), statistic, level, n_boot)
    if not np.isfinite(ci[0]).all():
        return d, [d, d]
    return d, [min(float(ci[0, 0]), d), max(float(ci[0, 1]), d)]


def proportion_ci(successes, level: float = CI_LEVEL, n_boot: int = N_BOOT) -> list[float] | None:
    """Percentile-bootstrap interval of the fraction of True in ``successes`` (resampling its
    entries, the same fixed stream as the episode bootstrap); None when it is empty."""
    x = np.asarray(successes, dtype=np.float64).reshape(-1)
    if x.size == 0:
        return None
    _, ci = _bootstrap(x.size, lambda idx, axis=-1: x[np.atleast_2d(idx)].mean(axis=-1)[None, :],
                       level, n_boot)
    p = float(x.mean())
    return [min(float(ci[0, 0]), p), max(float(ci[0, 1]), p)]
