"""Static-pose rigs: find the poses of a log, and the pose-level joint fit.

A real calibration rig holds a weighed mass in a dozen static poses and logs a few hundred
readings in each; a few poses get known loads (their mean reading and the applied load). What
such data determine is a *forward* model of the pose means,

    zbar_j = A m_j + o + e_j,        m_j = m_k (known poses),  m_j = g u_j (the others, |u_j| = 1),

``A`` (p x r) and ``o`` (p) the sensor's linear response and offset, ``u_j`` the unknown pose
directions (two angles each, nuisance parameters) and ``g`` the magnitude of the mass. With 12
poses of 8 channels that is 96 numbers for 32 + 16 + 1 parameters: well determined, which the
inverse model ``m = C z + d`` on the same data is not (27 parameters against the 12 known
components and 8 magnitudes). :func:`fit_rig` fits it in two stages:

1. **Pose loads.** The forward model by maximum likelihood, :func:`calib.forward.fit_forward`
   on the pose means: the same estimator as a log without static poses (one reading per pose
   or a sweep), here with each pose mean's variance ``v_c + s_c^2 / n_j`` (``s_c`` the
   within-pose scatter, ``n_j`` the pose's readings, ``v_c`` each channel's pose-level variance
   from the residuals, leverage-corrected, in feasible-GLS rounds until it settles: a real
   sensor's misfit, nonlinearity, creep, hysteresis, is far larger than its sampling noise and
   differs by channel). Its starts: the affine map of the known poses, the Sampson-distance
   joint fit and the centered route aligned to the known loads (handed in), random
   directions, each *alternated* (the model fitted at the current loads, then every unknown
   pose moved to its best direction on its sphere: a global step per pose, which LM's local
   steps cannot take), and perturbed restarts of the best; the lowest cost under the final
   weights is kept and every start's cost is in the diagnostics. The magnitude is held at the
   known loads' when they are one weighed mass (within :data:`SAME_MAGNITUDE`), else fitted.
   A per-channel **bending term** (:class:`ForwardModel` with ``bend``) is then tried from
   those directions and kept when an F-test supports it (:data:`BEND_P`).
   Then the **index model** (:class:`IndexModel`): every channel a polynomial (degree 2 or 3)
   of its own linear signal ``a_c . m``, ``a_c`` fitted with the curvature and the directions,
   the magnitude held at the known loads' when they are one mass; a higher degree is kept when
   a nested F-test finds it significant and it predicts left-out poses better, and the index
   model replaces the forward model's loads when it is kept. A printed or
   capacitive channel bends along the one direction it senses: on a real printed sensor this
   took the worst load set from 5.9x to 1.8x least squares with every load known.
2. **Calibration.** Least squares on every row with its pose's load: the known loads where
   known, ``g u_j`` elsewhere; exactly what least squares with every load known does, with the
   estimated loads in place of the unknown ones. Fitting the rows (not the pose means) shrinks
   ``C`` along noisy channel combinations the way the all-known fit does, and the affine map on
   all p channels absorbs part of a sensor's nonlinearity through its redundant channels.

Measured on :func:`calib.simulate.simulate_rig` rigs (``scripts/calib_rig_study.py``): within
1.1-1.4x of least squares with every load known, where the Sampson-distance fit (``rig=False``)
was 1.3-2x and up to 5x on nonlinear sensors. See docs/calib.md.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.optimize import least_squares

from ._numdiff import batched_jacobian
from ._validate import check_matrix
from .forward import Problem, fit_forward, grid
from .forward import tangents as _tangents
from .result import Calibration, CalibrationError

#: A pose needs at least this many readings; shorter runs (transitions) are left out.
MIN_POSE_SAMPLES = 3
#: A jump between consecutive readings starts a new pose when its chi-square (in noise units)
#: has a probability below this under noise alone; the threshold is then raised by half.
JUMP_PROBABILITY = 1e-6
#: Neighbouring runs whose adjoining readings differ by less than this (rms over channels, noise
#: units) are one pose (a spike or a burst of noise split it).
MERGE_NOISE_UNITS = 2.0
#: At most this many rows are searched for spatial clusters when the log is not in pose order.
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


#: The forward model gets a bending term per channel when an F-test gives p below this.
BEND_P = 0.01

#: The index refinement (:class:`IndexModel`): polynomial degrees up to 1 + this are tried
#: per channel, each kept when an F-test against the lower one gives p below :data:`BEND_P` and
#: its leave-one-pose-out error is lower.
INDEX_DEGREE = 2
#: Known loads whose magnitudes are within this relative spread are one weighed mass: the index
#: refinement holds every pose's load at their magnitude (and :mod:`calib.reliability` checks the
#: fitted magnitude against it).
SAME_MAGNITUDE = 0.05
#: Rounds of feasible GLS reweighting of the index refinement (channel weights from the
#: highest-degree fit's own residuals).
INDEX_REWEIGHT = 2

#: ``robust``: a row further than this many robust standard deviations (1.4826 MAD) from its
#: pose's median on any channel is an outlier.
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


# ------------------------------------------------------------------------------- the fit


class PoseData:
    """Pose means, counts and within-pose noise of a labelled log, with the known loads matched."""

    def __init__(self, Z, labels, known_Z, known_M, r, known_samples=None):
        Z = np.asarray(Z, float)
        labels = np.asarray(labels)
        good = labels >= 0
        ids = np.unique(labels[good])
        self.rows = Z[good]
        lab = np.searchsorted(ids, labels[good])
        self.row_pose = lab
        P, p = len(ids), Z.shape[1]
        self.counts = np.bincount(lab, minlength=P).astype(float)
        self.means = np.zeros((P, p))
        np.add.at(self.means, lab, self.rows)
        self.means /= self.counts[:, None]
        resid = self.rows - self.means[lab]
        dof = max(len(self.rows) - P, 1)
        self.sigma = np.maximum(np.sqrt((resid**2).sum(axis=0) / dof),
                                1e-9 * np.maximum(np.ptp(Z, axis=0), 1e-300))
        self.p, self.r = p, r
        # known readings -> poses: the nearest pose mean in noise units when it is clearly the
        # nearest (under a quarter of the distance to the next); else a known-only pose
        Zk = np.atleast_2d(np.asarray(known_Z, float))
        Mk = np.atleast_2d(np.asarray(known_M, float))[:, :r]
        self.known_pose = np.full(len(Zk), -1)
        extra_means, extra_counts = [], []
        n_extra = float(known_samples) if known_samples else float(np.median(self.counts))
        taken = set()
        for k, zk in enumerate(Zk):
            d = np.sqrt(np.mean(((self.means - zk) / self.sigma) ** 2, axis=1))
            order = np.argsort(d)
            j = int(order[0])
            second = d[order[1]] if P > 1 else np.inf
            if j not in taken and d[j] <= 0.25 * second:
                self.known_pose[k] = j
                taken.add(j)
            else:
                self.known_pose[k] = P + len(extra_means)
                extra_means.append(zk)
                extra_counts.append(n_extra)
        if extra_means:
            self.means = np.vstack([self.means, extra_means])
            self.counts = np.r_[self.counts, extra_counts]
        self.P = len(self.means)
        self.known_M = Mk
        self.unknown = np.setdiff1d(np.arange(self.P), self.known_pose)
        self.n_extra = len(extra_means)


@functools.lru_cache(maxsize=4)
def sphere_grid(n: int, r: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (r = 3: a Fibonacci lattice) or the
    circle (r = 2) (:func:`calib.forward.grid`); cached, read-only."""
    out = grid(r, n)
    out.flags.writeable = False
    return out


#: Rig fits: known loads further than this fraction of the load from a rotation of what the
#: readings alone imply are inconsistent (simulated imperfect rigs: up to 12 % with 5 % creep
#: and 3 % hysteresis, at most 3.4 % otherwise; two swapped known loads: median 17 %); such a
#: fit is refused (:mod:`calib.reliability`) and chooses no model by held-out error.
KNOWN_INCONSISTENT = 0.15
#: Directions tried per unknown pose by the rig fit's global re-inference (:meth:`ForwardModel.
#: alternate`): about 5 degrees apart on the sphere.
SPHERE_GRID = 2000
#: Starts of the bent forward model (:class:`ForwardModel` with ``bend``) with every unknown
#: direction drawn uniformly on the sphere, besides the affine fit's directions: each is
#: alternated to a pose-by-pose optimum (cheap), and the :data:`RANDOM_REFINED` best distinct
#: ones are refined jointly by LM.
RANDOM_STARTS = 12
#: 6: with 2 the bent search of a simulated rig at 15 % nonlinearity (seed 14, the known loads on
#: the first 4 poses) stopped at 3.8x the cost the true directions lead to once the affine stage
#: was :func:`calib.forward.fit_forward`; with 4, after the static rigs' variances were moderated
#: across channels (:func:`calib.forward.moderate_variances`), it stopped at 7.7x there (1 of 80
#: simulated rigs at 5 and 15 % nonlinearity, seeds 10-49); with 6 every one of the 80 reaches
#: the cost of the true directions (with :data:`RANDOM_NFEV`, as fast as 4 were without it).
RANDOM_REFINED = 6
#: Levenberg-Marquardt iterations a random start of the bent model is refined for (the named
#: starts get 400). Every converged refinement of the simulated target-case rigs took at most 22;
#: a start far from any basin (its cost hundreds of times the best) could run the 400, 4 s each
#: on a 12-pose rig, which took one rig's fit from 3 to 11 s. The cheapest refinement, if its
#: budget ran out, is finished from where it stopped.
RANDOM_NFEV = 50
#: Two alternated starts are distinct when some pose's directions differ by more than this.
DISTINCT_DEG = 10.0


def _wls(X, Y, W):
    """Weighted least squares of every column of Y (P, p) on its own design X (P, k) or (p, P,
    k), weights W (P, p); returns the coefficients (p, k) and the weighted residuals (P, p)."""
    Xc = np.broadcast_to(X, (Y.shape[1],) + X.shape[-2:]) if X.ndim == 2 else X
    coef, resid = _wls_batch(Xc[None], Y, W)
    return coef[0], resid[0]


def _wls_batch(X, Y, W):
    """:func:`_wls` for a batch of designs X (b, p, P, k) (one per channel and batch member):
    coefficients (b, p, k) and weighted residuals (b, P, p)."""
    Xw = X * W.T[None, :, :, None]
    yw = (Y * W).T
    scale = np.maximum(np.sqrt((Xw**2).sum(axis=2)), 1e-300)  # column scaling
    Xs = Xw / scale[:, :, None, :]
    G = np.einsum("bcpk,bcpl->bckl", Xs, Xs)
    h = np.einsum("bcpk,cp->bck", Xs, yw)
    try:
        b = np.linalg.solve(G, h[..., None])[..., 0]
    except np.linalg.LinAlgError:
        b = np.stack([np.stack([np.linalg.lstsq(Xs[i, c], yw[c], rcond=None)[0]
                                for c in range(Xs.shape[1])]) for i in range(len(Xs))])
    coef = b / scale
    resid = yw[None] - np.einsum("bcpk,bck->bcp", Xw, coef)
    return coef, resid.transpose(0, 2, 1)


class ForwardModel:
    """zbar_j = A m_j + o by variable projection over the unknown directions and g; with
    ``bend`` each channel also gets ``b_c (a_c . m)^2``."""

    def __init__(self, pd: PoseData, magnitude=None):
        self.pd = pd
        self.magnitude = magnitude
        self.fit_g = magnitude is None
        # the pose means centred per channel for the solves (the offsets add the centre back):
        # a channel whose offset is a thousand times its spread would otherwise lose three
        # digits to cancellation in every residual, enough to make LM's finite-difference
        # Jacobian noise and stop it short (the rig route's equivariance test found one)
        self.center = pd.means.mean(axis=0)
        self.centered = pd.means - self.center

    def loads(self, x, U0, T):
        """Every pose's load (P, r) at the parameters x: direction steps in the tangent planes T
        of U0, then (when fitted) g."""
        return self.loads_batch(np.asarray(x, float)[None], U0, T)[0]

    def loads_batch(self, xs, U0, T):
        """:meth:`loads` for every row of xs: (b, P, r)."""
        pd = self.pd
        nt = T.shape[1]
        nu = len(pd.unknown)
        Ms = np.zeros((len(xs), pd.P, pd.r))
        Ms[:, pd.known_pose] = pd.known_M
        V = U0 + np.einsum("bma,mad->bmd", xs[:, : nt * nu].reshape(len(xs), nu, nt), T)
        g = xs[:, -1:, None] if self.fit_g else self.magnitude
        Ms[:, pd.unknown] = g * V / np.linalg.norm(V, axis=2, keepdims=True)
        return Ms

    bend = False  # per-channel bending term (a_c . m)^2 in the forward model

    def coefficients(self, M, W):
        """The per-channel model fitted to the pose means at loads M, weights W: a dict with
        ``B`` ((r+1, p): the affine pass), ``resid`` (weighted residuals of the model, (P, p))
        and for ``bend`` ``a`` (p, r), ``S`` and ``bent`` ((p, r+2): affine part and bend
        gain of each channel)."""
        return {k: v[0] for k, v in self.coefficients_batch(np.asarray(M)[None], W).items()}

    def coefficients_batch(self, Ms, W):
        """:meth:`coefficients` for a batch of loads Ms (b, P, r), every entry with a leading
        batch axis (LM's finite-difference Jacobian: one call for all its columns)."""
        pd = self.pd
        X = np.concatenate([Ms, np.ones(Ms.shape[:2] + (1,))], axis=2)
        Xc = np.broadcast_to(X[:, None], (len(Ms), pd.p) + X.shape[1:])
        coef, resid = _wls_batch(Xc, self.centered, W)
        coef[:, :, pd.r] += self.center
        out = {"B": coef.transpose(0, 2, 1), "resid": resid}
        if self.bend:
            a = coef[:, :, : pd.r]
            s2 = np.einsum("bPr,bcr->bPc", Ms, a) ** 2  # (b, P, p)
            S = np.maximum(s2.max(axis=1), 1e-300)
            bendcol = (s2 / S[:, None, :]).transpose(0, 2, 1)[..., None]
            bent, out["resid"] = _wls_batch(np.concatenate([Xc, bendcol], axis=3),
                                            self.centered, W)
            bent[:, :, pd.r] += self.center
            out.update(a=a, S=S, bent=bent)
        return out

    def linear(self, M, W):
        """Weighted least squares per channel of the pose means on [M 1]; (B (r+1, p), resid).
        With ``bend`` the residuals are those of the bent model; B stays the affine part."""
        c = self.coefficients(M, W)
        return c["B"], c["resid"]

    def predict(self, coef, M):
        """The model's pose means (n, p) at loads M (n, r)."""
        if not self.bend:
            return M @ coef["B"][:-1] + coef["B"][-1]
        b = coef["bent"]
        r = self.pd.r
        return M @ b[:, :r].T + b[:, r] + b[:, r + 1] * (M @ coef["a"].T) ** 2 / coef["S"]

    def reinfer(self, M, W, g):
        """Every unknown pose's load moved to the direction on the sphere of radius g (a grid of
        :data:`SPHERE_GRID`) that the model fitted at M explains best: a global step per pose."""
        coef = self.coefficients(M, W)
        grid = g * sphere_grid(SPHERE_GRID, self.pd.r)
        pred = self.predict(coef, grid) - self.center
        out = M.copy()
        u = self.pd.unknown
        # |W_j (zbar_j - pred)|^2 for every pose and grid point, expanded (centred): (nu, grid)
        W2 = W[u] ** 2
        Y = self.centered[u]
        cost = (np.sum(W2 * Y**2, axis=1)[:, None] - 2 * (W2 * Y) @ pred.T + W2 @ (pred**2).T)
        out[u] = grid[np.argmin(cost, axis=1)]
        return out

    def _at(self, U, g):
        """Every pose's load: the known ones, and g U at the unknown poses."""
        M = np.zeros((self.pd.P, self.pd.r))
        M[self.pd.known_pose] = self.pd.known_M
        M[self.pd.unknown] = g * U
        return M

    def cost(self, U, g, W) -> float:
        """The weighted cost with the unknown poses at unit directions U and magnitude g."""
        return float((self.coefficients(self._at(U, g), W)["resid"] ** 2).sum())

    def alternate(self, U, g, W, iters=25):
        """Unit directions of the unknown poses after alternating the model fit and
        :meth:`reinfer` from U (stops when no pose moves)."""
        M = self._at(U, g)
        for _ in range(iters):
            new = self.reinfer(M, W, g)
            if np.array_equal(new, M):
                break
            M = new
        V = M[self.pd.unknown]
        return V / np.linalg.norm(V, axis=1, keepdims=True)

    def solve(self, U0, g0, W, max_nfev=400):
        """LM from unit directions U0 (of the unknown poses) and magnitude g0."""
        T = _tangents(U0)
        x0 = np.zeros(T.shape[1] * len(U0) + (1 if self.fit_g else 0))
        if self.fit_g:
            x0[-1] = g0

        def batch(xs):  # residuals of every row of xs: (b, P * p)
            return self.coefficients_batch(self.loads_batch(xs, U0, T), W)["resid"].reshape(
                len(xs), -1)

        def fun(x):
            return batch(x[None])[0]

        sol = least_squares(fun, x0, jac=batched_jacobian(batch), method="lm", xtol=1e-12,
                            ftol=1e-12, gtol=1e-12, max_nfev=max_nfev * (len(x0) + 1))
        M = self.loads(sol.x, U0, T)
        U = M[self.pd.unknown]
        g = float(sol.x[-1]) if self.fit_g else float(self.magnitude)
        return {"U": U / np.linalg.norm(U, axis=1, keepdims=True), "g": g,
                "cost": float(2 * sol.cost), "converged": bool(sol.status > 0),
                "nfev": int(sol.nfev), "M": M}


class IndexModel:
    """A forward model in which every channel is a polynomial of its own linear signal,

        zbar_jc = o_c + u_jc + sum_{k=2..d+1} b_ck s_c (u_jc / s_c)^k,    u_jc = a_c . m_j / g,

    (a Wiener model: a printed flexure, a gap or a gauge that stiffens or softens along the one
    load direction it senses; ``s_c`` the channel's spread over the poses, for scaling). Unlike
    the bending term of :class:`ForwardModel`, whose direction is frozen at the affine fit's,
    ``a_c`` is fitted with the curvature and the loads. Fitted by LM over the unknown poses'
    directions and every channel's (a_c, o_c, b_c) together, at a held magnitude ``g``. With
    ``free`` every pose's direction is unknown (the known loads ignored): the consistency check.
    On a real printed 8-channel sensor (docs/calib.md) it took the pose loads of the worst load
    set from 5.9x to 1.8x least squares with every load known."""

    def __init__(self, pd: PoseData, g: float, M0: np.ndarray, free: bool = False):
        self.pd, self.g = pd, float(g)
        self.free = free
        self.unknown = np.arange(pd.P) if free else pd.unknown
        U0 = M0[self.unknown]
        self.U0 = U0 / np.linalg.norm(U0, axis=1, keepdims=True)
        self.T = _tangents(self.U0)
        self.ng = self.T.shape[1] * len(self.unknown)
        self.scale = np.maximum(pd.means.std(axis=0), 1e-300)
        # fitted to the pose means centred per channel (the offsets in theta are from the
        # centre), for the reason :class:`ForwardModel` gives
        self.Y = pd.means - pd.means.mean(axis=0)

    def loads_batch(self, xs):
        """The loads (b, P, r) of direction steps xs[:, :ng]."""
        pd = self.pd
        nt = self.T.shape[1]
        Ms = np.zeros((len(xs), pd.P, pd.r))
        if not self.free:
            Ms[:, pd.known_pose] = pd.known_M
        V = self.U0 + np.einsum("bma,mad->bmd",
                                xs[:, : self.ng].reshape(len(xs), len(self.unknown), nt), self.T)
        Ms[:, self.unknown] = self.g * V / np.linalg.norm(V, axis=2, keepdims=True)
        return Ms

    def predict(self, Ms, theta, deg):
        """Pose means (b, P, p) at loads Ms (b, P, r), channel parameters theta (b, p, r+1+deg)."""
        r = self.pd.r
        u = np.einsum("bPr,bcr->bPc", Ms / self.g, theta[:, :, :r])
        pred = u + theta[:, None, :, r]
        for k in range(deg):
            pred = pred + theta[:, None, :, r + 1 + k] * self.scale * (u / self.scale) ** (k + 2)
        return pred

    def start(self, deg):
        """Parameters at the start directions: the affine fit per channel, no curvature."""
        pd = self.pd
        X = np.column_stack([self.loads_batch(np.zeros((1, self.ng)))[0] / self.g,
                             np.ones(pd.P)])
        B = np.linalg.lstsq(X, self.Y, rcond=None)[0]
        return np.r_[np.zeros(self.ng), np.column_stack([B.T, np.zeros((pd.p, deg))]).ravel()]

    def grow(self, x, deg):
        """Parameters of degree ``deg`` as a start of degree ``deg + 1`` (zero new term)."""
        th = x[self.ng:].reshape(self.pd.p, -1)
        return np.r_[x[: self.ng], np.column_stack([th, np.zeros(self.pd.p)]).ravel()]

    def solve(self, deg, W, x0=None, max_nfev=20):
        """LM from x0 (default :meth:`start`), at most ``max_nfev`` evaluations per parameter
        (converged fits take under 2; known loads that contradict the readings can crawl for
        200); a dict as :meth:`ForwardModel.solve`'s plus ``x``, ``deg`` and the weighted
        residuals ``resid`` (P, p)."""
        pd = self.pd
        x0 = self.start(deg) if x0 is None else x0
        k = pd.r + 1 + deg

        def batch(xs):
            Ms = self.loads_batch(xs)
            th = xs[:, self.ng:].reshape(len(xs), pd.p, k)
            return ((self.Y - self.predict(Ms, th, deg)) * W).reshape(len(xs), -1)

        sol = least_squares(lambda x: batch(x[None])[0], x0, jac=batched_jacobian(batch),
                            method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                            max_nfev=max_nfev * (len(x0) + 1))
        M = self.loads_batch(sol.x[None])[0]
        U = M[pd.unknown]
        return {"U": U / np.linalg.norm(U, axis=1, keepdims=True), "g": self.g,
                "cost": float(2 * sol.cost), "converged": bool(sol.status > 0),
                "nfev": int(sol.nfev), "M": M, "x": sol.x, "deg": deg,
                "resid": sol.fun.reshape(pd.P, pd.p)}

    def holdout(self, fit, W) -> float:
        """Leave-one-pose-out error of a fit: for every pose, the model refitted without it (from
        ``fit``), then its readings predicted (an unknown pose at the direction on its sphere,
        of :data:`SPHERE_GRID` then LM, that explains them best); the sum over poses of the
        weighted squared reading residuals. The held-out side of the degree choice: a degree
        that fits the poses it was given but not the next one is overfitted."""
        pd, deg = self.pd, fit["deg"]
        k = pd.r + 1 + deg
        grid = sphere_grid(SPHERE_GRID, pd.r)
        unknown = set(self.unknown.tolist())
        total = 0.0
        for j in range(pd.P):
            Wj = np.array(W, float)
            Wj[j] = 0.0
            f = self.solve(deg, Wj, fit["x"])
            th = f["x"][self.ng:].reshape(1, pd.p, k)

            def misfit(V, th=th, j=j):  # weighted residuals of pose j at directions V (n, r)
                U = V / np.linalg.norm(V, axis=1, keepdims=True)
                return (self.Y[j] - self.predict(U[None] * self.g, th, deg)[0]) * W[j]

            if j not in unknown:
                total += float(np.sum(misfit(f["M"][j][None]) ** 2))
                continue
            u_fit = f["M"][j] / self.g
            u_grid = grid[np.argmin(np.sum(misfit(grid) ** 2, axis=1))]
            # the grid's best is a second start only when it is not the fitted direction's basin
            starts = [u_fit] if u_fit @ u_grid > np.cos(np.radians(DISTINCT_DEG)) else [
                u_fit, u_grid]
            best = np.inf
            for u in starts:
                T = _tangents(u[None])[0]
                sol = least_squares(lambda a, u=u, T=T: misfit((u + a @ T)[None])[0],
                                    np.zeros(len(T)), method="lm")
                best = min(best, float(2 * sol.cost))
            total += best
        return total

    def reweighted(self, fit):
        """Feasible GLS weights (P, p) from a fit's own residuals: each channel's pose-level
        residual variance (over the residual degrees of freedom) plus each pose mean's sampling
        variance."""
        pd = self.pd
        raw = fit["resid"] / fit["W"]
        n_par = pd.r + 1 + fit["deg"] + self.ng / pd.p
        v = (raw**2).sum(axis=0) / max(pd.P - n_par, 1.0)
        return 1.0 / np.sqrt(v[None, :] + (pd.sigma**2)[None, :] / pd.counts[:, None])


def _index_refinement(pd: PoseData, final: dict, g: float):
    """The :class:`IndexModel` from the first stage's directions: weights by
    :data:`INDEX_REWEIGHT` rounds of feasible GLS on the highest degree, then degrees 0..
    :data:`INDEX_DEGREE` under those weights, each kept over the one below when an F-test gives
    p < :data:`BEND_P` *and* it predicts left-out poses better (:meth:`IndexModel.holdout`).
    Returns (diagnostics, the chosen fit, the model, its weights), or None when no curvature
    is identifiable (too few poses).

    Both tests, because either alone chose wrongly on a real printed sensor (docs/calib.md): the
    F-test kept a cubic that predicted left-out poses worse (3 N set, first-half samples: pose
    loads 1.47x -> 2.37x least squares with every load known), the held-out error alone a cubic
    the F-test did not support (same set, alternate samples: 1.22x -> 1.63x)."""
    from scipy.stats import f as f_dist

    model = IndexModel(pd, g, final["M"])
    n_res = pd.P * pd.p

    def dof(d):
        return n_res - pd.p * (pd.r + 1 + d) - model.ng

    degs = [d for d in range(INDEX_DEGREE + 1) if dof(d) >= pd.p]
    if len(degs) < 2:
        return None
    top = degs[-1]
    W = np.broadcast_to(1.0 / model.scale, (pd.P, pd.p))
    x = None
    for _ in range(INDEX_REWEIGHT):
        fit = model.solve(top, W, x)
        x = fit["x"]
        W = model.reweighted({**fit, "W": W})
    fits, x = [], None
    for d in degs:
        fits.append(model.solve(d, W, x))
        x = model.grow(fits[-1]["x"], d)
    held = [None] * len(degs)  # leave-one-pose-out errors, computed when a test needs them

    def holdout(d):
        if held[d] is None:
            held[d] = model.holdout(fits[d], W)
        return held[d]

    chosen, p_values = 0, []
    for d in degs[1:]:
        c0, c1 = fits[chosen]["cost"], fits[d]["cost"]
        extra = pd.p * (d - chosen)
        F = ((c0 - c1) / extra) / (c1 / dof(d)) if c1 > 0 else np.inf
        p_value = float(f_dist.sf(F, extra, dof(d)))
        p_values.append(p_value)
        if p_value < BEND_P and fits[d]["converged"] and holdout(d) < holdout(chosen):
            chosen = d
    diag = {"used": chosen > 0, "degree": chosen + 1, "g": g,
            "costs": [f["cost"] for f in fits], "p_values": p_values, "holdout": held,
            "converged": [f["converged"] for f in fits]}
    return diag, fits[chosen], model, W


def _known_consistency(pd: PoseData, final: dict, W, bend: bool = False) -> dict:
    """How far the known loads are from what the readings alone say: the forward model the fit
    chose (the index model when ``final`` is its fit; else ``bend``: with its per-channel bending
    terms) refitted with every pose's direction free (magnitude held at the fit's), turned onto
    the known loads by the best rotation; the rms of what remains, in load units and as a
    fraction of the load. Measured on simulated rigs (imperfect sensors, misaligned mounts):
    0.3-8 % of the load; two known loads swapped: mostly 3-55 %. On a real printed sensor
    (index model): 1.3-12.5 % on fits within 1.0-2.5x least squares with every load known (the
    bent model's free fit: 4-19 %, and 53 % on a 5.9x fit)."""
    import copy

    M = final["M"]
    if "deg" in final:  # the index model (:class:`IndexModel`): its own free fit
        im = IndexModel(pd, final["g"], M, free=True)
        x0 = np.r_[np.zeros(im.ng), final["x"][-pd.p * (pd.r + 1 + final["deg"]):]]
        out = im.solve(final["deg"], W, x0)
        A = out["x"][im.ng:].reshape(pd.p, -1)[:, : pd.r] / final["g"]
        raw = out["resid"] / W
        return _rotation_miss(pd, out["M"], raw @ np.linalg.pinv(A).T, out["converged"])
    free = copy.copy(pd)
    free.known_pose = np.array([], int)
    free.unknown = np.arange(pd.P)
    free.known_M = np.zeros((0, pd.r))
    fm = ForwardModel(free, magnitude=final["g"])
    fm.bend = bend
    out = fm.solve(M / np.linalg.norm(M, axis=1, keepdims=True), final["g"], W)
    # the free fit's own misfit in load units: its pose-mean residuals through the pseudo-inverse
    # of its A (what the readings cannot explain, even with every direction free)
    B, raw = fm.linear(out["M"], W)
    misfit = (raw / W) @ np.linalg.pinv(B[:pd.r].T).T
    return _rotation_miss(pd, out["M"], misfit, out["converged"])


def _rotation_miss(pd: PoseData, M_free, misfit, converged) -> dict:
    """The known loads against the free fit's loads at their poses turned by the best rotation
    (:func:`_known_consistency`); ``misfit`` the free fit's residuals in load units."""
    MA = M_free[pd.known_pose]
    if pd.r == 3 and len(MA) >= 2:
        P_, _, Qt = np.linalg.svd(MA.T @ pd.known_M)
        R = (P_ @ Qt).T
    elif pd.r == 2 and len(MA) >= 1:
        P_, _, Qt = np.linalg.svd(MA.T @ pd.known_M)
        R = (P_ @ Qt).T
    else:
        return {"residual_rms": float("nan"), "fraction": float("nan")}
    res = MA @ R.T - pd.known_M
    rms = float(np.sqrt(np.mean(res**2)))
    scale = float(np.median(np.linalg.norm(pd.known_M, axis=1)))
    spread = float(np.sqrt(np.mean(misfit**2)))
    return {"residual_rms": rms, "fraction": rms / scale if scale > 0 else float("nan"),
            "free_fit_misfit_rms": spread,
            "ratio": rms / spread if spread > 0 else float("inf"),
            "converged": converged}


def fit_rig(Z, labels, known_Z, known_M, dof: int = 3, magnitude: float | None = None,
            known_samples: int | None = None, restarts: int = 2, seed: int = 0,
            starts: dict | None = None, known_sigma: float | None = None,
            model: str = "affine", drift: str = "none", t=None) -> Calibration:
    """The pose-level joint fit (module docstring): :func:`rig_pose_loads` (stage 1) then
    :func:`rig_calibration` (stage 2); see the former for the arguments."""
    s1 = rig_pose_loads(Z, labels, known_Z, known_M, dof, magnitude, known_samples, restarts,
                        seed, starts, known_sigma)
    return rig_calibration(s1, model, drift, t)


def rig_pose_loads(Z, labels, known_Z, known_M, dof: int = 3, magnitude: float | None = None,
                   known_samples: int | None = None, restarts: int = 2, seed: int = 0,
                   starts: dict | None = None, known_sigma: float | None = None,
                   random_starts: int = RANDOM_STARTS) -> dict:
    """The pose-level joint fit (module docstring): forward model for the unknown pose loads,
    then least squares on every row with its pose's load.

    ``labels``: the pose of every row (:func:`find_poses`; -1 rows are left out). ``starts``:
    extra named calibrations (objects with ``apply``) whose loads at the pose means start the
    directions. ``known_sigma`` (stated accuracy of the known loads) is recorded for the
    reliability checks; the fit itself treats known loads as exact and weighs pose means by
    their scatter (``known_samples`` only weighs known readings that match no pose).
    Returns the stage-1 state for :func:`rig_calibration` (``model``/``drift``: the second
    stage's model, :func:`calib.models.fit_model`; ``t`` each row's position in the log,
    default the row order), which returns a Calibration with ``method="joint"`` and
    ``diagnostics["joint"]``.
    """
    if dof not in (2, 3):
        raise CalibrationError(f"the rig fit is for dof 2 or 3, got {dof}")
    r = dof
    Zk, _ = check_matrix(np.atleast_2d(known_Z), "known readings")
    Mk = np.atleast_2d(np.asarray(known_M, float))
    pd = PoseData(Z, labels, Zk, Mk, r, known_samples)
    if len(pd.unknown) == 0:
        raise CalibrationError("every pose has a known load: use least squares")
    known_mag = np.linalg.norm(pd.known_M, axis=1)
    # the affine forward model: calib.forward's maximum-likelihood fit on the pose means (its
    # own starts, the closed-form routes among them, and settled channel variances), the same
    # estimator as logs without static poses; the magnitude held at the known loads' when they
    # are one weighed mass (as that route does), else fitted
    g_one = (float(magnitude) if magnitude is not None
             else float(np.median(known_mag)) if len(known_mag) and known_mag.max()
             <= (1 + SAME_MAGNITUDE) * known_mag.min() else None)
    pr = Problem(pd.means, pd.counts, pd.sigma, pd.known_pose, pd.known_M, g_one)
    start_loads = {}
    for name, cal in (starts or {}).items():
        try:
            L = cal.apply(pd.means)
        except (CalibrationError, ValueError):
            continue
        if np.all(np.isfinite(L)):
            start_loads[name] = L
    try:
        ff = fit_forward(pr, start_loads, seed=seed, restarts=restarts)
    except (np.linalg.LinAlgError, ValueError) as e:
        raise CalibrationError(f"the rig fit found no finite pose directions: {e}") from None
    fm = ForwardModel(pd, g_one)
    v = ff["v"]
    W2 = pr.weights(v)
    g_fit = float(ff["g"])
    final = {"U": ff["U"], "g": g_fit, "M": pr.loads(ff["U"], g_fit),
             "cost": fm.cost(ff["U"], g_fit, W2), "converged": bool(ff["converged"]),
             "nfev": int(ff["iterations"]), "start": ff["chosen_start"]}
    best = final
    candidates = [{"start": s["start"], "cost": s["cost"], "converged": s["converged"],
                   "nfev": s["iterations"]} for s in ff["starts"]]
    rng = np.random.default_rng(seed)
    solved = {}

    def refine(label, U0, g, model, weights, into, max_nfev=400):
        # alternations end on grid points: equal starts are solved once
        key = (id(model), id(weights), g, max_nfev, np.round(U0, 12).tobytes())
        if key in solved:
            if solved[key] is not None:
                into.append({**solved[key], "start": label})
            return
        try:
            res = model.solve(U0, g, weights, max_nfev=max_nfev)
        except (np.linalg.LinAlgError, ValueError):
            return
        solved[key] = res
        into.append({**res, "start": label})

    def add_start(name, U, g, model, weights, into):
        """Refine a start by LM, and also its pose-by-pose alternation."""
        if U is None or not np.all(np.isfinite(U)):
            return
        refine(name, U, g, model, weights, into)
        try:
            U1 = model.alternate(U, g, weights)
        except (np.linalg.LinAlgError, ValueError):
            return
        refine(f"{name}, alternated", U1, g, model, weights, into)

    def random_directions():
        U = rng.standard_normal((len(pd.unknown), r))
        return U / np.linalg.norm(U, axis=1, keepdims=True)

    def random_starts_refined(g, model, weights, into, label=""):
        """Directions drawn uniformly, alternated to pose-by-pose optima; the
        :data:`RANDOM_REFINED` cheapest distinct ones refined by LM."""
        pool = []
        for i in range(random_starts):
            try:
                U1 = model.alternate(random_directions(), g, weights)
                pool.append((model.cost(U1, g, weights), i, U1))
            except (np.linalg.LinAlgError, ValueError):
                continue
        kept = []
        for _, i, U1 in sorted(pool, key=lambda t: t[:2]):
            if len(kept) == RANDOM_REFINED:
                break
            if all(np.min(np.sum(U1 * V, axis=1)) < np.cos(np.radians(DISTINCT_DEG))
                   for V in kept):
                kept.append(U1)
                refine(f"random start {i + 1}{label}, alternated", U1, g, model, weights, into,
                       max_nfev=RANDOM_NFEV)

    # a channel that bends with its own signal (printed flexures, capacitive gaps): the nested
    # model with b_c (a_c . m)^2 per channel, kept when an F-test says it fits significantly
    # better (p < BEND_P); on a real printed sensor it halved the pose loads' error on 3 of 5
    # load sets (docs/calib.md)
    bend = {"used": False}
    n_res = pd.P * pd.p
    k0 = (pd.r + 1) * pd.p + 2 * len(pd.unknown) + fm.fit_g
    dof1 = n_res - k0 - pd.p
    if dof1 > 0:
        from scipy.stats import f as f_dist

        fb = ForwardModel(pd, g_one)
        fb.bend = True
        bent = []
        add_start("final, bent", final["U"], final["g"], model=fb, weights=W2, into=bent)
        random_starts_refined(final["g"], model=fb, weights=W2, into=bent, label=" (bent)")
        cand = min(bent, key=lambda c: c["cost"]) if bent else {"converged": False}
        if not cand["converged"] and "U" in cand:  # a random start's budget ran out: finish it
            try:
                cand = {**fb.solve(cand["U"], cand["g"], W2), "start": cand["start"]}
            except (np.linalg.LinAlgError, ValueError):
                pass
        if cand["converged"] and cand["cost"] < final["cost"]:
            F = ((final["cost"] - cand["cost"]) / pd.p) / (cand["cost"] / dof1)
            p_value = float(f_dist.sf(F, pd.p, dof1))
            bend = {"used": p_value < BEND_P, "F": float(F), "p_value": p_value,
                    "cost_affine": final["cost"], "cost_bent": cand["cost"]}
            if bend["used"]:
                final = cand
                fm = fb
    # every channel a polynomial of its own signal (:class:`IndexModel`), from these directions,
    # at the magnitude of the one weighed mass when the known loads share it (else the fit's)
    g_hold = g_one if g_one is not None else final["g"]
    index = {"used": False}
    W_final, forward = W2, final
    got = _index_refinement(pd, final, g_hold)
    if got is not None:
        index, fit, _, W_index = got
        if index["used"]:
            final, W_final = {**fit, "start": f"{final['start']}, index model"}, W_index
    return {"bend": bend, "index": index, "pd": pd, "fm": fm, "final": final, "best": best,
            "forward": forward, "W2": W2, "W_final": W_final, "v": v, "candidates": candidates,
            "consistency": _known_consistency(pd, final, W_final, fm.bend),
            "labels": np.asarray(labels), "n": int(len(np.asarray(Z))), "dof": dof,
            "known_sigma": known_sigma, "known_samples": known_samples}


def rig_calibration(s1: dict, model: str = "affine", drift: str = "none", t=None) -> Calibration:
    """Stage 2 of :func:`fit_rig` on a stage-1 result (:func:`rig_pose_loads`)."""
    from .models import fit_model

    pd, fm, final, best, W2, v = (s1[k] for k in ("pd", "fm", "final", "best", "W2", "v"))
    candidates, consistency, labels, dof = (s1[k] for k in ("candidates", "consistency",
                                                            "labels", "dof"))
    known_sigma, known_samples = s1["known_sigma"], s1["known_samples"]
    r = pd.r
    M_pose = final["M"]
    # stage 2: least squares on every row with its pose's load (extra known-only poses as their
    # reading repeated as often as they weigh)
    rows, row_loads = pd.rows, M_pose[pd.row_pose]
    n_all = len(np.asarray(labels))
    t_all = np.linspace(0.0, 1.0, n_all) if t is None else np.asarray(t, float).reshape(n_all)
    t_rows = t_all[np.asarray(labels) >= 0]
    if drift != "none":
        # drift fitted across poses only: each row at its pose's mean time. Within a pose the
        # time order is creep (a printed sensor's channels trend within every pose), which a row
        # time reads as drift: on a real one `auto` then chose channel/linear at 4.27x least
        # squares on load set 4; at the pose's mean time it gives 1.92x, as without drift. On
        # simulated rigs the two time bases fit alike (mean log ratio within 0.1 % of each other)
        rp = np.asarray(pd.row_pose)
        sums = np.bincount(rp, weights=t_rows, minlength=pd.P)
        t_rows = (sums / np.maximum(np.bincount(rp, minlength=pd.P), 1))[rp]
    real = len(pd.counts) - pd.n_extra
    if pd.n_extra:
        reps = np.maximum(np.round(pd.counts[real:]).astype(int), 1)
        rows = np.vstack([rows, np.repeat(pd.means[real:], reps, axis=0)])
        row_loads = np.vstack([row_loads, np.repeat(M_pose[real:], reps, axis=0)])
        t_rows = np.r_[t_rows, np.full(reps.sum(), t_rows.mean())]
    ls = fit_model(rows, row_loads, model, drift, t_rows)
    C = ls.C
    d = -C @ ls.offset
    # the offset: the forward model's o moved within C's row space so that C (z - offset)
    # reproduces the least-squares loads exactly (a physical offset, not the min-norm one)
    B, _ = fm.linear(M_pose, W2)
    o_fwd = B[r]
    offset = o_fwd + np.linalg.pinv(C) @ (-d - C @ o_fwd)
    ls.offset = offset
    L = ls.apply(pd.means)
    mags = np.linalg.norm(L[pd.unknown], axis=1)
    g = final["g"]
    known_res = L[pd.known_pose] - pd.known_M
    # the calibration's misfit at the poses whose loads were fitted, every component: what the
    # known readings' misfit is compared with (the magnitude scatter alone misses the direction
    # part of an affine map's misfit to a bending sensor: 0.16 against 0.25 N on a real one)
    fitted_res = L[pd.unknown] - M_pose[pd.unknown]
    diag = {
        "n_samples": s1["n"],
        "n_dropped_nonfinite": 0,
        "singular_values": ls.diagnostics["singular_values"],
        "condition_number_C": float(np.linalg.cond(C)),
        "residual_rms": ls.diagnostics["residual_rms"],
        "joint": {
            "route": "poses",
            "known_sigma": known_sigma,
            "known_samples": known_samples,
            "n_poses": int(pd.P),
            "n_known": int(len(pd.known_M)),
            "n_known_matched_to_poses": int(len(pd.known_M) - pd.n_extra),
            "rows_left_out": int((np.asarray(labels) < 0).sum()),
            "magnitude": g,
            "magnitude_fitted": fm.fit_g,
            "pose_magnitude_residual_rms": float(np.sqrt(np.mean((mags - g) ** 2))),
            "pose_residual_rms": (float(np.sqrt(np.mean(fitted_res**2))) if fitted_res.size
                                  else float("nan")),
            "known_residual_rms": float(np.sqrt(np.mean(known_res**2))),
            "known_residuals": known_res,
            "channel_noise": pd.sigma,
            "channel_pose_residual_rms": np.sqrt(v),
            "starts": [{"start": c["start"], "cost": c["cost"], "converged": c["converged"],
                        "nfev": c["nfev"]} for c in candidates],
            "chosen_start": best["start"],
            "bend": s1["bend"],
            "index_model": s1.get("index", {"used": False}),
            "known_consistency": consistency,
            "converged": bool(final["converged"]),
            "nfev": int(final["nfev"]),
        },
    }
    diag["joint"].update(model=model, drift=drift,
                         drift_per_log=ls.diagnostics.get("drift_per_log"))
    return Calibration(C=C, offset=offset, dof=dof, method="joint", diagnostics=diag,
                       quadratic=ls.quadratic, quadratic_center=ls.quadratic_center,
                       quadratic_scale=ls.quadratic_scale)
