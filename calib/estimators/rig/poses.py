"""The static poses of a log (:func:`find_poses`), outlying readings within a pose
(:func:`reject_outliers`), and known readings matched to poses (:func:`match_poses`).
"""

from __future__ import annotations

import numpy as np

#: A pose needs at least this many readings; shorter runs (transitions) are left out.
#: Decision: docs/calib_design.md D24.
MIN_POSE_SAMPLES = 3


#: A jump between consecutive readings starts a new pose when its chi-square (in noise units)
#: has a probability below this under noise alone; the threshold is then raised by half.
#: Decision: docs/calib_design.md D24.
JUMP_PROBABILITY = 1e-6


#: Neighbouring runs whose adjoining readings differ by less than this (rms over channels, noise
#: units) are one pose (a spike or a burst of noise split it).
#: Decision: docs/calib_design.md D24.
MERGE_NOISE_UNITS = 2.0


#: At most this many rows are searched for spatial clusters when the log is not in pose order.
#: Decision: docs/calib_design.md D26.
MAX_CLUSTER_ROWS = 20_000


def find_poses(Z) -> np.ndarray | None:
    """The static pose of every row of ``Z`` (n, p), or None when ``Z`` is not a static-pose log.

    Rows in pose order (a rig log) are split where consecutive readings jump by more than noise
    explains (1.5 times the chi-square quantile of :data:`JUMP_PROBABILITY`; each channel's noise
    from the rms of consecutive differences with the largest 2 % left out, so pose changes do not
    inflate it and integer counts that mostly repeat do not zero it), except around an isolated
    spike (a reading whose neighbours do not jump from each other); neighbouring runs whose
    adjoining readings agree within :data:`MERGE_NOISE_UNITS` are joined again (a spike split
    them), then runs whose means lie within :data:`CLUSTER_NOISE_UNITS` of each other (a pose
    noisier than the rest), and rows left out between two runs of one pose rejoin it. Logs not
    in pose order are clustered in space instead (connected components of readings closer than six
    typical nearest-neighbour distances). Runs shorter than :data:`MIN_POSE_SAMPLES` rows get
    label -1. A log is a static-pose log when at least 3 poses hold at least 80 % of its rows
    with a median of at least 5 rows per pose; otherwise (a continuous motion log) None.
    """
    Z = np.asarray(Z, float)
    n, p = Z.shape
    if n < 3 * MIN_POSE_SAMPLES:
        return None
    span = np.maximum(Z.max(axis=0) - Z.min(axis=0), 1e-300)
    dZ = np.diff(Z, axis=0)
    # each channel's noise from consecutive differences, the largest 2 % (pose changes) left
    # out: a trimmed rms, not the median, which is 0 for integer counts that mostly repeat
    d2 = dZ**2
    cut = np.quantile(d2, 0.98, axis=0)
    kept = np.where(d2 <= cut, d2, np.nan)
    noise = np.sqrt(np.nanmean(kept, axis=0) / 2)
    noise = np.maximum(np.nan_to_num(noise), 1e-6 * span)
    jump = np.sqrt(np.mean((dZ / noise) ** 2, axis=1))
    from scipy.stats import chi2

    threshold = 1.5 * np.sqrt(2 * chi2.isf(JUMP_PROBABILITY, p) / p)
    big = jump > threshold
    # an isolated spike (one reading off, the readings either side of it continuous with each
    # other) is left out without splitting its run: a continuous sweep's spikes chopped it into
    # runs that read as static poses (1 % of a 1,000-reading payload sweep 20 noise levels off:
    # 8 "poses", and the rig fit refused the log for having too few of them); in a static pose
    # it stays out, or rejoins as before where it is near the pose's mean (_fill_gaps)
    skip = np.sqrt(np.mean(((Z[2:] - Z[:-2]) / noise) ** 2, axis=1))  # the row between skipped
    spike = big[:-1] & big[1:] & (skip <= threshold)
    big[:-1][spike] = False
    big[1:][spike] = False
    runs = _runs(np.flatnonzero(big) + 1, n)
    runs[1:-1][spike] = -1
    labels = _merge(Z / noise, runs)
    labels = _fill_gaps(Z / noise, _cluster_runs(Z / noise, labels))
    labels = _join_settling(Z / noise, labels)
    if _is_static(labels):
        return labels
    if n <= MAX_CLUSTER_ROWS:
        labels = _clusters(Z / span)
        if labels is not None and _is_static(labels) and _separated(Z / span, labels):
            return labels
    return None


#: Spatial clusters are static poses only when each one's rms radius is under this fraction of
#: the distance to the nearest other cluster's mean (median over clusters): readings of a static
#: pose scatter by noise, far less than poses lie apart; one reading per pose over a band of
#: directions chains into a few clusters as wide as the gaps between them (ratio 0.3-1).
#: Decision: docs/calib_design.md D26.
CLUSTER_SEPARATION = 0.1


def _separated(X: np.ndarray, labels: np.ndarray) -> bool:
    good = labels >= 0
    ids = np.unique(labels[good])
    means = np.array([X[labels == i].mean(axis=0) for i in ids])
    radius = np.array([np.sqrt(np.mean(np.sum((X[labels == i] - m) ** 2, axis=1)))
                       for i, m in zip(ids, means, strict=True)])
    d = np.linalg.norm(means[:, None] - means[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return bool(np.median(radius / np.maximum(d.min(axis=1), 1e-300)) <= CLUSTER_SEPARATION)


def _runs(starts: np.ndarray, n: int) -> np.ndarray:
    bounds = np.r_[0, starts, n]
    labels = np.full(n, -1)
    k = 0
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b - a >= MIN_POSE_SAMPLES:
            labels[a:b] = k
            k += 1
    return labels


def _merge(X: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Join neighbouring runs (in label order) when the last readings of one and the first of
    the next (up to 5 each) agree within MERGE_NOISE_UNITS: a spike, not a pose change, split
    them (comparing whole means would not do: creep moves a pose's readings)."""
    k = labels.max() + 1
    if k < 2:
        return labels
    new = np.zeros(k, int)
    prev = X[labels == 0]
    for j in range(1, k):
        cur = X[labels == j]
        gap = np.sqrt(np.mean((cur[:5].mean(axis=0) - prev[-5:].mean(axis=0)) ** 2))
        new[j] = new[j - 1] + (0 if gap < MERGE_NOISE_UNITS else 1)
        prev = cur
    out = labels.copy()
    out[labels >= 0] = new[labels[labels >= 0]]
    return out


#: Runs whose means lie within this many noise units (rms over channels) of each other, directly or
#: through a chain of runs, are one pose: a pose noisier than the rest is split into many runs.
#: Decision: docs/calib_design.md D24.
CLUSTER_NOISE_UNITS = 6.0


def _cluster_runs(X: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Join runs (anywhere in the log) whose means are within :data:`CLUSTER_NOISE_UNITS` of
    each other (single linkage): the readings of one static pose that noise bursts split."""
    k = labels.max() + 1
    if k < 2:
        return labels
    from scipy.cluster.hierarchy import fcluster, linkage

    means = np.array([X[labels == j].mean(axis=0) for j in range(k)])
    groups = fcluster(linkage(means, "single"), CLUSTER_NOISE_UNITS * np.sqrt(X.shape[1]),
                      criterion="distance")
    # number the poses in order of first appearance
    order = {g: i for i, g in enumerate(dict.fromkeys(groups))}
    out = labels.copy()
    good = labels >= 0
    out[good] = np.array([order[g] for g in groups])[labels[good]]
    return out


def _fill_gaps(X: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Rows left out between two runs of the same pose rejoin it when they lie within
    :data:`CLUSTER_NOISE_UNITS` of its mean (a burst of noise); a spike stays out."""
    out = labels.copy()
    idx = np.flatnonzero(out >= 0)
    if len(idx) < 2:
        return out
    means = {j: X[labels == j].mean(axis=0) for j in np.unique(labels[labels >= 0])}
    for a, b in zip(idx[:-1], idx[1:], strict=True):
        if b - a > 1 and out[a] == out[b]:
            gap = np.arange(a + 1, b)
            near = np.sqrt(np.mean((X[gap] - means[out[a]]) ** 2, axis=1)) < CLUSTER_NOISE_UNITS
            out[gap[near]] = out[a]
    return out


#: A pose logged for less than this fraction of the median pose's rows, in one run next to a
#: longer pose's run, is a neighbouring pose's settling, not a pose of its own
#: (:func:`_join_settling`).
#: Decision: docs/calib_design.md D25.
SETTLING_FRACTION = 1 / 3


def _join_settling(X: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Short runs that are a neighbouring pose's settling join it.

    A rig's load changes when it moves; a printed or creeping sensor may read a steady but
    different value for its first moments in a pose and then jump to where it stays (seen in a
    real 8-channel printed sensor: 14 % of one pose's log 87 counts away, 28 % of another's).
    That run is as steady as a pose, so the jump detector starts a new pose at both ends; as a
    pose of its own it would get a load direction of its own, which the rig did not apply. A
    pose with fewer than :data:`SETTLING_FRACTION` of the median pose's rows, all in one run
    next to a longer pose's run (rows left out between them aside), is relabelled as that pose:
    of the runs before and after it, the one whose mean is nearer in noise units (a few readings
    that an outlier cut off the start of their pose go back to it). The all-known fit labels
    those rows with the pose's load too."""
    good = labels >= 0
    if good.sum() == 0:
        return labels
    counts = np.bincount(labels[good])
    if len(counts) < 3:
        return labels
    short = counts < SETTLING_FRACTION * np.median(counts)
    if not short.any():
        return labels
    out = labels.copy()
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    ends = np.r_[starts[1:], len(labels)]
    runs = [(int(labels[a]), a, b) for a, b in zip(starts, ends, strict=True) if labels[a] >= 0]
    for i, (lab, a, b) in enumerate(runs):
        if not short[lab] or b - a != counts[lab]:
            continue  # a long pose, or a short one in several runs (a revisited pose)
        here = X[a:b].mean(axis=0)
        near = [(np.linalg.norm(X[labels == runs[nb][0]].mean(axis=0) - here), runs[nb][0])
                for nb in (i + 1, i - 1) if 0 <= nb < len(runs) and not short[runs[nb][0]]]
        if near:
            out[a:b] = min(near)[1]
    # renumber in order of first appearance
    ids = list(dict.fromkeys(out[out >= 0].tolist()))
    remap = np.full(labels.max() + 1, -1)
    remap[ids] = np.arange(len(ids))
    out[out >= 0] = remap[out[out >= 0]]
    return out


def _clusters(X: np.ndarray) -> np.ndarray | None:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    tree = cKDTree(X)
    d, _ = tree.query(X, k=2)
    radius = 6 * float(np.median(d[:, 1]))
    if not radius > 0:
        return None
    pairs = tree.query_pairs(radius, output_type="ndarray")
    n = len(X)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, lab = connected_components(graph, directed=False)
    counts = np.bincount(lab)
    keep = counts >= MIN_POSE_SAMPLES
    remap = np.full(len(counts), -1)
    remap[keep] = np.arange(keep.sum())
    return remap[lab]


def _is_static(labels: np.ndarray) -> bool:
    good = labels >= 0
    if not good.any():
        return False
    counts = np.bincount(labels[good])
    return len(counts) >= 3 and good.mean() >= 0.8 and np.median(counts) >= 5


#: ``robust``: a row further than this many robust standard deviations (1.4826 MAD) from its
#: pose's median on any channel is an outlier.
#: Decision: docs/calib_design.md D49.
OUTLIER_MADS = 5.0


def reject_outliers(Z, labels) -> tuple[np.ndarray, int]:
    """Labels with outlier rows set to -1 (left out of every stage of the fit): rows further
    than :data:`OUTLIER_MADS` robust standard deviations from their pose's median on any
    channel. Returns (labels, number of rows rejected)."""
    Z = np.asarray(Z, float)
    out = np.array(labels, copy=True)
    n0 = int((out >= 0).sum())
    for j in np.unique(out[out >= 0]):
        idx = np.flatnonzero(out == j)
        block = Z[idx]
        med = np.median(block, axis=0)
        mad = 1.4826 * np.median(np.abs(block - med), axis=0)
        mad = np.maximum(mad, 1e-12 * np.maximum(np.abs(med), 1.0))
        bad = np.any(np.abs(block - med) > OUTLIER_MADS * mad, axis=1)
        if (~bad).sum() >= MIN_POSE_SAMPLES:
            out[idx[bad]] = -1
    return out, n0 - int((out >= 0).sum())


def match_poses(Z, known_Z):
    """Rows of ``Z`` that belong to a pose of a known reading: the poses of ``Z``
    (:func:`find_poses`; every row its own pose when none are found) each take the known reading
    nearest their mean in noise units, when it is clearly the nearest (under half the distance
    to the next). Returns (rows, index of the known reading per row, number of poses matched)."""
    Z = np.asarray(Z, float)
    Zk = np.atleast_2d(np.asarray(known_Z, float))
    labels = find_poses(Z)
    if labels is None:
        labels = np.arange(len(Z))
    ids = np.unique(labels[labels >= 0])
    means = np.array([Z[labels == j].mean(axis=0) for j in ids])
    scale = np.maximum(np.std(np.vstack([means, Zk]), axis=0), 1e-300)
    rows, which, matched = [], [], 0
    for j, m in zip(ids, means, strict=True):
        d = np.sqrt(np.mean(((Zk - m) / scale) ** 2, axis=1))
        order = np.argsort(d)
        if len(d) == 1 or d[order[0]] <= 0.5 * d[order[1]]:
            idx = np.flatnonzero(labels == j)
            rows.append(idx)
            which.append(np.full(len(idx), order[0]))
            matched += 1
    if not rows:
        return np.array([], int), np.array([], int), 0
    return np.concatenate(rows), np.concatenate(which), matched
