"""Intervals over everything that varies: training sets *and* evaluation episodes.

A claims sweep evaluates every policy (one per training set) on the same evaluation episodes,
so a learner's outcomes form a matrix ``Y[set, episode]`` whose two factors are *crossed*: the
training sets are a sample of the training sets the learner could have been given, the episodes
a sample of the episodes it could meet. An interval over training sets alone (the episodes held
fixed) leaves out the episodes' own sampling variance, and is too narrow for the claim a reader
takes from it ("this learner escapes 0.97 of jams"); a second evaluation bank then lands outside
it more often than the stated 5 %.

:func:`crossed_bootstrap` resamples both factors independently (the "pigeonhole" bootstrap of
crossed random effects, A. B. Owen, *The pigeonhole bootstrap*, Ann. Appl. Stat. 1 (2007)): each
resample draws training sets with replacement and, independently, episodes with replacement, and
takes the mean of the drawn sub-matrix. Owen shows its variance estimate is slightly
conservative (it counts the interaction term once too often); it is the standard choice for
crossed designs. Episodes come in *banks* (disjoint seed ranges): with at least
:data:`MIN_BANKS_AS_LEVEL` banks, each resample first draws banks with replacement and then
episodes within each drawn bank (the bank a level of the bootstrap); with fewer, episodes are
drawn within each bank (stratified), since two banks are too few to resample.

Paired differences (learner a minus learner b on the same training-set seeds and the same
episodes) resample the difference matrix ``Ya - Yb`` the same way, so what the two share cancels.

A confidence interval of a level is about the mean; the value a *rerun* measures (new training
sets on a new bank) has its own sampling error on top, so it falls outside that interval more
often than the stated rate (about 20-25 % for a 95 % interval when the rerun is one bank).
:func:`replication_interval` gives where a rerun lands: the published mean's bootstrap error and
the rerun's own (:func:`replication_draws`: sets and one bank's episodes drawn anew), as the
difference of independent draws; :func:`level` states it simultaneously over a family of levels
(Bonferroni), so that every level of a table holds on one replication with the stated
probability.

Verdicts over a table of comparisons are family-wise: :func:`holm` adjusts the bootstrap
p-values by Holm's step-down method (S. Holm, Scand. J. Statist. 6 (1979)), and each comparison
is shown with the percentile interval at its Holm step's level, which excludes 0 exactly when the
adjusted test rejects. :func:`min_detectable_effect` states the smallest true difference the
design finds with 80 % power at that level.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

#: Resamples of every bootstrap (seeded: the same rows give the same text).
RESAMPLES = 4000
#: With this many banks or more, banks are resampled as a level of the bootstrap.
MIN_BANKS_AS_LEVEL = 3
#: The family-wise error rate of a table's verdicts.
ALPHA = 0.05
#: The power at which :func:`min_detectable_effect` states the smallest detectable difference.
POWER = 0.8


#: Results of :func:`level` and :func:`paired` already computed in this process, keyed by a
#: digest of every input (the bootstraps are seeded, so equal inputs give equal results): the
#: claims tables and sentences state the same levels and pairs, and ``mkv demo`` prints both.
_MEMO: OrderedDict = OrderedDict()
_MEMO_SIZE = 512


def _digest(*parts) -> bytes:
    h = hashlib.blake2b(digest_size=20)
    for part in parts:
        if isinstance(part, np.ndarray):
            a = np.ascontiguousarray(part)
            h.update(repr((a.dtype.str, a.shape)).encode())
            h.update(a.tobytes())
        else:
            h.update(repr(part).encode())
        h.update(b"\0")
    return h.digest()


def _memo(key: bytes, compute):
    if key in _MEMO:
        _MEMO.move_to_end(key)
        return _MEMO[key]
    value = compute()
    _MEMO[key] = value
    if len(_MEMO) > _MEMO_SIZE:
        _MEMO.popitem(last=False)
    return value


@dataclass(frozen=True)
class Outcomes:
    """Per-episode outcomes of several policies of one learner on shared evaluation episodes.

    ``values``: ``(n_sets, n_episodes)``, row i the policy trained on training set ``sets[i]``;
    ``banks``: the bank of every episode column (``(n_episodes,)`` ints).
    """

    sets: tuple
    values: np.ndarray
    banks: np.ndarray

    def __post_init__(self):
        v = np.asarray(self.values, dtype=float)
        b = np.asarray(self.banks)
        if v.ndim != 2 or v.shape[0] != len(self.sets) or b.shape != (v.shape[1],):
            raise ValueError(f"outcomes: values {v.shape} do not match {len(self.sets)} sets "
                             f"and {b.shape} banks")
        if not np.all(np.isfinite(v)):
            raise ValueError("outcomes: every value must be finite")
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "banks", b)

    def common(self, other: Outcomes) -> tuple[np.ndarray, np.ndarray]:
        """The rows of both for the training sets they share, in the same order."""
        if not np.array_equal(self.banks, other.banks):
            raise ValueError("paired outcomes must come from the same evaluation episodes")
        shared = [s for s in self.sets if s in set(other.sets)]
        ia = [self.sets.index(s) for s in shared]
        ib = [other.sets.index(s) for s in shared]
        return self.values[ia], other.values[ib]


def _counts(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``shape`` counts of how often each (row, col) pair occurs (``rows`` broadcast against
    ``cols``; lists of such pairs are pooled): ``np.add.at`` of ones, by one ``bincount``."""
    if isinstance(cols, list):
        flat = np.concatenate([(np.broadcast_to(r, c.shape) * shape[1] + c).ravel()
                               for r, c in zip(rows, cols, strict=True)])
    else:
        flat = (np.broadcast_to(rows, cols.shape) * shape[1] + cols).ravel()
    return np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape).astype(float)


def _episode_weights(banks: np.ndarray, rng: np.random.Generator, resamples: int) -> np.ndarray:
    """``(resamples, n_episodes)`` counts: how often each episode is drawn in each resample."""
    labels, inverse = np.unique(banks, return_inverse=True)
    shape = (resamples, len(banks))
    members = [np.flatnonzero(inverse == k) for k in range(len(labels))]
    rows, cols = [], []
    if len(labels) >= MIN_BANKS_AS_LEVEL:
        # banks with replacement, then episodes within each drawn bank
        drawn = rng.integers(0, len(labels), size=(resamples, len(labels)))
        for k, idx in enumerate(members):
            times = (drawn == k).sum(axis=1)  # how often bank k was drawn in each resample
            for t in np.unique(times[times > 0]):
                at = np.flatnonzero(times == t)
                picks = rng.integers(0, len(idx), size=(len(at), t * len(idx)))
                rows.append(at[:, None])
                cols.append(idx[picks])
    else:
        for idx in members:  # stratified: episodes within each bank
            picks = rng.integers(0, len(idx), size=(resamples, len(idx)))
            rows.append(np.arange(resamples)[:, None])
            cols.append(idx[picks])
    return _counts(rows, cols, shape)


def crossed_bootstrap(values: np.ndarray, banks: np.ndarray, seed: int = 0,
                      resamples: int = RESAMPLES) -> np.ndarray:
    """The bootstrap distribution (``(resamples,)``) of the mean of ``values[set, episode]``,
    resampling training sets and episodes (and banks: module docstring) independently."""
    v = np.asarray(values, dtype=float)
    if v.ndim != 2 or v.shape[0] < 1 or v.shape[1] < 1:
        raise ValueError(f"need a (sets, episodes) matrix with both at least 1, got {v.shape}")
    rng = np.random.default_rng(seed)
    n_sets = v.shape[0]
    set_w = rng.multinomial(n_sets, np.full(n_sets, 1.0 / n_sets), size=resamples).astype(float)
    ep_w = _episode_weights(np.asarray(banks), rng, resamples)
    per_set = (ep_w @ v.T) / ep_w.sum(axis=1, keepdims=True)  # (resamples, n_sets)
    return (set_w * per_set).sum(axis=1) / n_sets


def replication_draws(values: np.ndarray, banks: np.ndarray, n_sets: int | None = None,
                      n_episodes: int | None = None, seed: int = 0,
                      resamples: int = RESAMPLES) -> np.ndarray:
    """Bootstrap draws (``(resamples,)``) of a *rerun's* mean: ``n_sets`` new training sets
    (default: as many as ``values`` has rows) evaluated on a new bank of ``n_episodes`` episodes
    (default: the size of one bank). The new sets are drawn from the rows, the new bank's
    episodes from one bank drawn at random (from every episode when there are fewer than
    :data:`MIN_BANKS_AS_LEVEL` banks: too few to tell banks apart), both with replacement."""
    v = np.asarray(values, dtype=float)
    b = np.asarray(banks)
    labels, inverse = np.unique(b, return_inverse=True)
    members = [np.flatnonzero(inverse == k) for k in range(len(labels))]
    n_sets = v.shape[0] if n_sets is None else int(n_sets)
    n_episodes = min(len(m) for m in members) if n_episodes is None else int(n_episodes)
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, v.shape[0], size=(resamples, n_sets))
    if len(labels) >= MIN_BANKS_AS_LEVEL:
        bank = rng.integers(0, len(labels), size=resamples)
        cols = np.empty((resamples, n_episodes), int)
        for k, idx in enumerate(members):
            at = np.flatnonzero(bank == k)
            cols[at] = idx[rng.integers(0, len(idx), size=(len(at), n_episodes))]
    else:
        cols = rng.integers(0, v.shape[1], size=(resamples, n_episodes))
    # the mean of v[rows_i][:, cols_i] without the (n_sets, n_episodes) gathers
    col_w = _counts(np.arange(resamples)[:, None], cols, (resamples, v.shape[1])) / n_episodes
    per_row = col_w @ v.T  # (resamples, n_rows): each row's mean over the drawn episodes
    return np.take_along_axis(per_row, rows, axis=1).mean(axis=1)


def replication_interval(values: np.ndarray, banks: np.ndarray, confidence: float,
                         seed: int = 0, resamples: int = RESAMPLES, n_sets: int | None = None,
                         n_episodes: int | None = None) -> tuple[float, float]:
    """Where a rerun's mean (:func:`replication_draws`) lands with probability ``confidence``:
    both the published mean's error and the rerun's own, ``rerun - published`` drawn as the
    difference of independent bootstrap draws around the mean, kept within the data's range."""
    v = np.asarray(values, dtype=float)
    pub = crossed_bootstrap(v, banks, seed, resamples)
    rep = replication_draws(v, banks, n_sets, n_episodes, seed + 1, resamples)
    lo, hi = percentile_interval(np.clip(rep - pub + v.mean(), v.min(), v.max()), confidence)
    return lo, hi


def percentile_interval(draws: np.ndarray, level: float) -> tuple[float, float]:
    lo, hi = np.percentile(draws, [50 * (1 - level), 50 * (1 + level)])
    return float(lo), float(hi)


def level(out: Outcomes, seed: int = 0, resamples: int = RESAMPLES,
          confidence: float = 1 - ALPHA, family: int = 1) -> dict:
    """A learner's level (mean over training sets and episodes): ``ci`` its crossed confidence
    interval (at ``confidence``), ``replication`` the interval a rerun of one bank (as many new
    training sets, a new bank of one bank's episodes) lands in, simultaneous over ``family``
    levels (Bonferroni: each at ``1 - (1 - confidence) / family``)."""
    key = _digest("level", out.sets, out.values, out.banks, seed, resamples, confidence, family)
    return dict(_memo(key, lambda: _level(out, seed, resamples, confidence, family)))


def _level(out: Outcomes, seed: int, resamples: int, confidence: float, family: int) -> dict:
    draws = crossed_bootstrap(out.values, out.banks, seed, resamples)
    rep_level = 1 - (1 - confidence) / max(family, 1)
    # enough draws that each tail of the replication interval holds about 50 of them
    rep = replication_interval(out.values, out.banks, rep_level, seed,
                               max(resamples, int(np.ceil(100 / (1 - rep_level)))))
    return {"mean": float(out.values.mean()), "ci": percentile_interval(draws, confidence),
            "replication": rep, "family": int(family), "n_sets": len(out.sets),
            "n_episodes": out.values.shape[1], "n_banks": len(np.unique(out.banks))}


def paired(a: Outcomes, b: Outcomes, seed: int = 0, resamples: int = RESAMPLES) -> dict | None:
    """``a - b`` over their common training sets and the shared episodes: mean, bootstrap draws,
    two-sided percentile-bootstrap p-value and standard error; None without a common set."""
    key = _digest("paired", a.sets, a.values, a.banks, b.sets, b.values, b.banks, seed,
                  resamples)
    r = _memo(key, lambda: _paired(a, b, seed, resamples))
    return None if r is None else {**r, "draws": r["draws"].copy()}


def _paired(a: Outcomes, b: Outcomes, seed: int, resamples: int) -> dict | None:
    va, vb = a.common(b)
    if len(va) == 0:
        return None
    d = va - vb
    draws = crossed_bootstrap(d, a.banks, seed, resamples)
    below, above = float(np.mean(draws <= 0)), float(np.mean(draws >= 0))
    p = min(1.0, 2 * min(below, above))
    return {"n": len(va), "mean": float(d.mean()), "draws": draws, "p": max(p, 1.0 / resamples),
            "se": float(draws.std(ddof=1))}


def holm(p_values, alpha: float = ALPHA) -> list[dict]:
    """Holm's step-down adjustment of ``p_values`` (one family): per comparison, its adjusted
    p-value, the level its interval is shown at (``1 - alpha / (m - rank)``, rank from 0 by p)
    and whether it is rejected (every smaller p rejected too)."""
    p = np.asarray(p_values, dtype=float)
    m = len(p)
    order = np.argsort(p, kind="stable")
    out: list[dict] = [{} for _ in range(m)]
    running, still = 0.0, True
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        step = alpha / (m - rank)
        still = still and p[i] <= step
        out[i] = {"p_adjusted": running, "confidence": 1 - step, "rejected": bool(still)}
    return out


def min_detectable_effect(se: float, m: int, alpha: float = ALPHA, power: float = POWER) -> float:
    """The smallest true paired difference a two-sided test at the Bonferroni level ``alpha / m``
    rejects with probability ``power``, for a difference whose standard error is ``se``."""
    return float((norm.ppf(1 - alpha / (2 * m)) + norm.ppf(power)) * se)


def table(pairs: dict, seed: int = 0, resamples: int = RESAMPLES, alpha: float = ALPHA) -> dict:
    """One family of paired comparisons, ``{name: (Outcomes a, Outcomes b)}`` -> ``{name:
    {"n", "mean", "ci", "confidence", "p", "p_adjusted", "verdict", "mde"}}``; ``verdict`` is
    ``"a"``, ``"b"`` or None (no clear difference) by Holm over the family."""
    results = {}
    for k, (name, (a, b)) in enumerate(pairs.items()):
        r = paired(a, b, seed + k, resamples)
        if r is not None:
            results[name] = r
    adj = holm([r["p"] for r in results.values()], alpha)
    m = len(results)
    out = {}
    for (name, r), h in zip(results.items(), adj, strict=True):
        ci = percentile_interval(r["draws"], h["confidence"])
        verdict = None
        if h["rejected"] and (ci[0] > 0 or ci[1] < 0):
            verdict = "a" if r["mean"] > 0 else "b"
        out[name] = {"n": r["n"], "mean": r["mean"], "ci": ci, "confidence": h["confidence"],
                     "p": r["p"], "p_adjusted": h["p_adjusted"], "verdict": verdict,
                     "mde": min_detectable_effect(r["se"], m, alpha)}
    return out
