"""Joint estimator: constant-magnitude rows and known (z, m) pairs in one weighted fit.
The centered and paper routes use known pairs only after the fit, to turn and scale a
calibration found from the magnitude constraint alone. On real rigs (a proof mass held in a
dozen static poses, many samples each) the magnitude rows see few distinct directions, and the
known loads carry shape information that such an alignment throws away. :func:`fit_joint`
minimises, over the calibration ``C`` (dof x p), the offset and the load magnitude ``g``,

    sum_i ((|C (z_i - o)| - g) / sigma_mag)^2 + sum_k |(C (z_k - o) - m_k) / sigma_known|^2,

i.e. a maximum-likelihood fit when the magnitude residuals have standard deviation
``sigma_mag`` and each known load component ``sigma_known`` (both in load units). It works in the
data's rank-r principal subspace (``z = mu + V_r y``), so ``C = K V_r^T`` and ``o = mu + V_r c``
with r^2 + r (+1) parameters; the start is the centered route aligned to the known pairs.
``g`` is fitted unless ``magnitude`` is given; the known pairs fix the frame and the scale.

Defaults: ``magnitude_sigma`` is the magnitude residual rms of the start (the readings' own
scatter in load units). ``known_sigma`` defaults to ``magnitude_sigma / sqrt(n / k)``: each of the
k known pairs weighs as much as an equal share of the n motion rows, which is what a known
reading averaged over a static pose's samples is worth when the rig spends about as long in
every pose. State the real accuracies when known (load application error, samples averaged:
``known_samples``).

How close to least squares with every load known can any estimator come? ``scripts/
calib_rig_bound.py`` computes the Cramer-Rao bound of this model (pose means as sufficient
statistics, unknown pose directions as nuisance parameters): on 12-pose rigs with 4 known loads
the median bound is 1.57x the all-known bound (5-95 %: 1.27-2.49x); with its accuracies stated
(``known_samples``) the joint fit reaches its bound (Monte Carlo: 1.03x of it; docs/calib.md).
With the known loads on the most spread poses (:func:`choose_known_poses`) the bound drops to a
median 1.23x and the joint fit measures 1.31x all-known least squares.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import least_squares

from calib.data.result import CalibrationError, add_uncertainty, propagate
from calib.data.validate import check_matrix
from calib.estimators.bias import _finish, _prepare_source, fit_centered
from calib.estimators.models import summarise_folds
from calib.estimators.sfm import principal
from calib.routes.forward_rows import _forward_step, _starts, fit_forward_rows

#: At most this many (evenly strided) motion rows enter the nonlinear least squares.
#: Decision: docs/calib_design.md D20.
JOINT_MAX_ROWS = 50_000


def fit_joint(
    Z,
    known_Z,
    known_M,
    dof: int = 3,
    magnitude: float | None = None,
    known_sigma: float | None = None,
    magnitude_sigma: float | None = None,
    drop_nonfinite: bool = False,
    known_samples: int | None = None,
    poses="auto",
    cv: bool = False,
    model: str = "affine",
    drift: str = "none",
    robust: bool = False,
):
    """Fit C, offset (and the load magnitude) to motion rows and known pairs together.

    Static-pose logs (a rig: a few hundred readings in each of a dozen poses) go to the
    pose-level fit of :mod:`calib.estimators.rig` when ``poses`` is ``"auto"`` (poses found by
    :func:`calib.estimators.rig.poses.find_poses`) or an array of pose labels per row; the
    Sampson-distance fit
    below is then one of its starts. ``poses=None`` always uses the Sampson-distance fit (as do
    streamed sources). ``cv=True`` adds ``diagnostics["cv_poses"]``: the leave-one-pose-out
    error over the known poses (:func:`leave_one_pose_out`). ``model`` (affine, channel,
    quadratic, auto) and ``drift`` (none, linear, auto) choose the rig fit's second stage
    (:mod:`calib.estimators.models`); ``auto`` keeps the candidate with the lowest
    leave-one-pose-out error
    (``diagnostics["model_selection"]``); other than affine/none they need a static-pose log.
    ``robust=True`` leaves out rows more than 5 robust standard deviations from their pose's
    median on static-pose logs (:func:`calib.estimators.rig.poses.reject_outliers`; the count is in
    the diagnostics), and readings far from the fitted model on logs without static poses
    (:func:`fit_forward_rows`, which tells of them without it).

    Parameters
    ----------
    Z : (n, p) readings of a constant-magnitude load over orientations (static poses welcome);
        an array, a dask array or a :class:`calib.data.stream.ChunkSource` (streamed: the fit uses
        at most :data:`JOINT_MAX_ROWS` strided rows, the other passes are sums)
    known_Z, known_M : (k, p), (k, dof) known pairs; k >= 2 (>= 3 to avoid a mirror image)
    magnitude : the load magnitude of the motion rows; None fits it
    known_sigma, magnitude_sigma : accuracies in load units (see the module docstring)
    known_samples : instead of ``known_sigma``: each known reading is the mean of this many
        readings of the log's kind (a static pose averaged), so its accuracy is
        ``magnitude_sigma / sqrt(known_samples)``; 1 for single readings

    A channel that is an exact affine copy of another (logged twice) is left out of the fit
    and given a column of zeros in C (:mod:`calib.data.copies`).

    Returns a Calibration with ``method="joint"``; diagnostics as the centered route's plus
    ``joint`` (sigmas, fitted magnitude, residual rms of both kinds, solver status) and standard
    errors from the weighted Jacobian.
    """

    from calib.data.copies import fit_without_copies

    # a channel logged twice (an exact affine copy): fitted without it (calib.data.copies)
    out = fit_without_copies(Z, known_Z, lambda Zs, Zk: fit_joint(
        Zs, Zk, known_M, dof, magnitude, known_sigma, magnitude_sigma, drop_nonfinite,
        known_samples, poses, cv, model, drift, robust), dof)
    if out is not None:
        return out
    # the Sampson fit's own warnings reach the user only when it is the fit returned; as a
    # start of the forward or rig fit, those fits report their own
    with warnings.catch_warnings(record=True) as motion_warnings:
        warnings.simplefilter("always")
        motion = _fit_motion(Z, known_Z, known_M, dof, magnitude, known_sigma, magnitude_sigma,
                             drop_nonfinite, known_samples)

    def sampson():
        for m in motion_warnings:
            warnings.warn_explicit(m.message, m.category, m.filename, m.lineno)
        return motion

    from calib.data.stream import is_streamed

    for name, v, allowed in (("model", model, ("affine", "channel", "quadratic", "auto")),
                             ("drift", drift, ("none", "linear", "auto"))):
        if v not in allowed:
            raise CalibrationError(f"{name} must be one of {allowed}, got {v!r}")
    if poses is None or poses is False or is_streamed(Z):
        if model not in ("affine", "auto") or drift not in ("none", "auto"):
            raise CalibrationError(f"model {model}/{drift} needs a static-pose log (the rig "
                                   "fit); this one is fitted by the forward or Sampson route")
        if poses is None or poses is False or dof not in (2, 3):
            return sampson()
        # a log larger than memory: the forward fit on the same strided rows an array gets
        _, _, data = _prepare_source(Z, dof, drop_nonfinite, 0)
        step = _forward_step(data.n)
        rows = data.source.strided(step)
        finite = np.all(np.isfinite(rows), axis=1)
        return fit_forward_rows(rows[finite], known_Z, known_M, dof, magnitude, known_samples,
                                motion, n_total=data.n, known_sigma=known_sigma, robust=robust,
                                row_index=(np.arange(len(finite)) * step)[finite])
    from calib.estimators.models import choose
    from calib.estimators.rig.fit import rig_calibration, rig_pose_loads
    from calib.estimators.rig.poses import find_poses

    Za, _ = check_matrix(Z, "Z", drop_nonfinite)
    if isinstance(poses, str):
        if poses != "auto":
            raise CalibrationError(f"poses must be 'auto', None or labels per row, got {poses!r}")
        labels = find_poses(Za)
    else:
        labels = np.asarray(poses)
        if labels.shape != (len(Za),) or not np.issubdtype(labels.dtype, np.integer):
            raise CalibrationError(f"pose labels must be {len(Za)} integers, got shape "
                                   f"{labels.shape} of {labels.dtype}")
    if labels is None:
        if model not in ("affine", "auto") or drift not in ("none", "auto"):
            raise CalibrationError(f"model {model}/{drift} needs a static-pose log; no static "
                                   "poses were found in this one")
        if dof in (2, 3):
            step = _forward_step(len(Za))
            return fit_forward_rows(Za[::step], known_Z, known_M, dof, magnitude,
                                    known_samples, motion, n_total=len(Za),
                                    known_sigma=known_sigma, robust=robust,
                                    row_index=np.arange(0, len(Za), step))
        return sampson()
    Mk = np.atleast_2d(np.asarray(known_M, float))[:, : motion.C.shape[0]]
    t = np.linspace(0.0, 1.0, len(Za))
    n_rejected = 0
    if robust:
        from calib.estimators.rig.poses import reject_outliers

        labels, n_rejected = reject_outliers(Za, labels)

    def stage1(Zs, lab, Zk, Mk_, motion_fit=None):
        m = motion_fit or _fit_motion(Zs, Zk, Mk_, dof, magnitude, known_sigma,
                                      magnitude_sigma, False, known_samples)
        return rig_pose_loads(Zs, lab, Zk, Mk_, dof, magnitude, known_samples,
                              starts=_starts(Zs, Zk, Mk_, dof, magnitude, m),
                              known_sigma=known_sigma)


    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the starts' own warnings: the final fit reports its own
        try:
            s1 = stage1(Za, labels, known_Z, Mk, motion)
        except CalibrationError as e:
            motion.diagnostics["joint"]["rig_fit_failed"] = str(e)
            if model not in ("affine", "auto") or drift not in ("none", "auto"):
                raise CalibrationError(f"model {model}/{drift} needs the rig fit, which failed: "
                                       f"{e}") from None
            return sampson()
        auto = model == "auto" or drift == "auto"
        skipped = None
        if auto and not cv and _inconsistent(s1):
            # the fit is refused anyway (calib.verdict.reliability): choosing a model by how well it
            # predicts known loads that disagree with the readings means nothing, and the
            # refits crawl (a sign typed wrong: 123 s before this shortcut, 2.5 s with it)
            model = "affine" if model == "auto" else model
            drift = "none" if drift == "auto" else drift
            skipped = ("known loads inconsistent with the readings: the first model kept "
                       "without leave-one-pose-out selection")
        folds = _folds(Za, labels, known_Z, Mk, stage1, t) if (cv or auto) and not skipped else []

        def cv_of(m, d):
            return _fold_errors(folds, Za, m, d)

        model, drift, table = choose(cv_of, s1["pd"].P - s1["pd"].n_extra, Za.shape[1],
                                     model, drift)
        cal = rig_calibration(s1, model, drift, t)
        if cv:
            cal.diagnostics["cv_poses"] = cv_of(model, drift)
        if table:
            cal.diagnostics["model_selection"] = table
        elif skipped:
            cal.diagnostics["model_selection"] = {"chosen": f"{model}/{drift}",
                                                  "skipped": skipped}
        cal.diagnostics["joint"]["outlier_rows_rejected"] = n_rejected if robust else None
    m = motion.diagnostics
    cal.diagnostics["joint"]["sampson_fit"] = {
        k: m["joint"][k] for k in ("magnitude", "converged", "nfev", "known_residual_rms")}
    for key in ("coverage", "rank_gap", "excitation_poor", "n_dropped_nonfinite"):
        if key in m:
            cal.diagnostics[key] = m[key]
    return cal


def _inconsistent(s1: dict) -> bool:
    """Whether the stage-1 fit's known loads fail
    :data:`calib.estimators.rig.fit.KNOWN_INCONSISTENT`."""
    from calib.estimators.rig.fit import KNOWN_INCONSISTENT

    frac = s1.get("consistency", {}).get("fraction", float("nan"))
    return bool(np.isfinite(frac) and frac > KNOWN_INCONSISTENT)


def leave_one_pose_out(Z, labels, known_Z, known_M, fit, t=None) -> dict:
    """Leave-one-pose-out error over the known poses: for each known reading that belongs to a
    pose of ``labels``, refit with that pose left out entirely (its rows and its known load) by
    ``fit(Z, labels, known_Z, known_M)`` and compare the refit's mean load over the pose's rows
    with the known load. The honest estimate for a rig, where every sample of a pose shares its
    errors (sample-level splits see them in training). Returns ``folds``, ``rms`` and
    ``rms_per_axis`` (load units), ``errors`` (folds x r) and ``failed_folds``."""
    t = np.linspace(0.0, 1.0, len(Z)) if t is None else t
    folds = _folds(Z, labels, known_Z, known_M, fit, t)
    return summarise_folds([None if f is None else f[0].apply(np.asarray(Z)[f[1]]).mean(axis=0)
                            - f[2] for f in folds], np.atleast_2d(known_M).shape[1])


def _folds(Z, labels, known_Z, known_M, fit, t) -> list:
    """For each known reading on a pose of ``labels``: (fit without that pose, its rows, its
    known load), or None when the refit failed; ``fit(Z, labels, Zk, Mk)``."""
    from calib.estimators.rig.model import PoseData

    Z = np.asarray(Z, float)
    labels = np.asarray(labels)
    Zk = np.atleast_2d(np.asarray(known_Z, float))
    Mk = np.atleast_2d(np.asarray(known_M, float))
    pd = PoseData(Z, labels, Zk, Mk, Mk.shape[1])
    ids = np.unique(labels[labels >= 0])
    out = []
    for k, j in enumerate(pd.known_pose):
        if j >= len(ids):
            continue  # a known-only reading: no rows to hold out
        hold = labels == ids[j]
        keep = np.ones(len(Zk), bool)
        keep[k] = False
        if keep.sum() < 2:
            out.append(None)
            continue
        try:
            res = fit(Z[~hold], labels[~hold], Zk[keep], Mk[keep])
        except (CalibrationError, np.linalg.LinAlgError):
            out.append(None)
            continue
        out.append((res, np.flatnonzero(hold), Mk[k], t[~hold]))
    return out


def _fold_errors(folds, Z, model, drift) -> dict:
    from calib.estimators.rig.fit import rig_calibration

    errs = []
    for f in folds:
        if f is None:
            errs.append(None)
            continue
        s1, rows, mk, t_rest = f
        try:
            cal = rig_calibration(s1, model, drift, t_rest)
        except CalibrationError:
            errs.append(None)
            continue
        errs.append(cal.apply(Z[rows]).mean(axis=0) - mk)
    r = folds[0][2].shape[0] if folds and folds[0] is not None else 3
    return summarise_folds(errs, r)


def _fit_motion(Z, known_Z, known_M, dof, magnitude, known_sigma, magnitude_sigma,
                drop_nonfinite, known_samples):
    """The Sampson-distance joint fit over the motion rows (module docstring)."""
    if known_Z is None or known_M is None:
        raise CalibrationError("method 'joint' needs known loads (--known)")
    dof, r, data = _prepare_source(Z, dof, drop_nonfinite, 0)
    src, n = data.source, data.n
    Zk, _ = check_matrix(np.atleast_2d(known_Z), "known readings")
    Mk = np.atleast_2d(np.asarray(known_M, float))
    if len(Zk) != len(Mk):
        raise CalibrationError(f"{len(Zk)} known readings but {len(Mk)} known loads")
    if Zk.shape[1] != data.p:
        raise CalibrationError(f"known readings have {Zk.shape[1]} channels, data {data.p}")
    if len(Zk) < 2:
        raise CalibrationError(f"method 'joint' needs at least 2 known loads, got {len(Zk)}")
    Mk = Mk[:, :r]
    for name, v in (("known_sigma", known_sigma), ("magnitude_sigma", magnitude_sigma),
                    ("magnitude", magnitude), ("known_samples", known_samples)):
        if v is not None and not (np.isfinite(v) and v > 0):
            raise CalibrationError(f"{name} must be a positive number, got {v!r}")
    if known_sigma is not None and known_samples is not None:
        raise CalibrationError("give known_sigma or known_samples, not both")

    with warnings.catch_warnings():
        # the start's warnings are not the result's: the final fit reports its own (one source
        # for the summary line and the warnings)
        warnings.simplefilter("ignore")
        start = fit_centered(src, dof, known_Z=Zk, known_M=Mk, magnitude=magnitude)
    mu = data.mean
    step = int(np.ceil(n / JOINT_MAX_ROWS))
    src.want(step)  # gathered during the Gram pass
    s, V = principal(src, center=mu)
    Vr = V[:, :r]
    Y = (src.strided(step) - mu) @ Vr
    Yk = (Zk - mu) @ Vr
    K0 = start.C @ Vr
    c0 = Vr.T @ (start.offset - mu)
    mags0 = np.linalg.norm((Y - c0) @ K0.T, axis=1)
    g0 = float(magnitude) if magnitude is not None else float(np.mean(mags0))
    if magnitude_sigma is None:
        magnitude_sigma = float(np.sqrt(np.mean((mags0 - g0) ** 2))) or 1e-12 * g0
    fit_g = magnitude is None
    nK = r * r
    # Reading noise in counts (per subspace coordinate), from the start's Sampson distances: the
    # magnitude rows are weighted by their distance to the ellipsoid in count space, the
    # first-order maximum-likelihood weighting for readings with equal noise per channel (a
    # plain |C(z - o)| - g residual over-weights the directions where C is large).
    G0 = (Y - c0) @ K0.T
    rho0 = np.maximum(np.linalg.norm(G0, axis=1), 1e-300)
    grad0 = np.linalg.norm((G0 / rho0[:, None]) @ K0, axis=1)
    sigma_y = float(np.sqrt(np.mean(((rho0 - g0) / grad0) ** 2))) or 1e-12
    if known_sigma is None:
        # each known reading averages known_samples readings: count-space residual, sigma/sqrt(N)
        n_avg = known_samples if known_samples is not None else max(n / len(Zk), 1.0)
        known_scale = np.sqrt(n_avg) / sigma_y
    else:
        n_avg = None
        known_scale = 1.0 / known_sigma

    def unpack(x):
        K = x[:nK].reshape(r, r)
        c = x[nK : nK + r]
        g = x[nK + r] if fit_g else float(magnitude)
        return K, c, g

    def residuals(x):
        K, c, g = unpack(x)
        G = (Y - c) @ K.T
        rho = np.maximum(np.linalg.norm(G, axis=1), 1e-300)
        grad = np.maximum(np.linalg.norm((G / rho[:, None]) @ K, axis=1), 1e-300)
        m = (rho - g) / grad / sigma_y  # Sampson distance to the ellipsoid, in noise units
        if n_avg is not None:  # known pairs in count space: y_k - c - K^-1 m_k
            try:
                k = (Yk - c - np.linalg.solve(K, Mk.T).T).ravel() * known_scale
            except np.linalg.LinAlgError:
                k = np.full(Yk.size, 1e150)
        else:  # a stated load accuracy: residuals in load units
            k = ((Yk - c) @ K.T - Mk).ravel() * known_scale
        return np.r_[m, k]

    x0 = np.r_[K0.ravel(), c0, [g0] if fit_g else []]
    sol = least_squares(residuals, x0, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14,
                        max_nfev=200 * (len(x0) + 1))

    def jac(x):
        """Central-difference Jacobian of the residuals (for the covariance)."""
        cols = []
        for j in range(len(x)):
            h = 1e-6 * max(abs(x[j]), 1e-3)
            e = np.zeros(len(x))
            e[j] = h
            cols.append((residuals(x + e) - residuals(x - e)) / (2 * h))
        return np.column_stack(cols)

    K, c, g = unpack(sol.x)
    C = K @ Vr.T
    offset = mu + Vr @ c
    nm = len(Y)
    res = sol.fun
    extra = {
        "joint": {
            "known_sigma": known_sigma if n_avg is None else magnitude_sigma / np.sqrt(n_avg),
            "known_samples": n_avg,
            "reading_sigma_counts": sigma_y,
            "magnitude_sigma": magnitude_sigma,
            "magnitude": float(g),
            "magnitude_fitted": fit_g,
            "n_known": len(Zk),
            "rows_used": nm,
            "magnitude_residual_rms": float(np.sqrt(np.mean(res[:nm] ** 2)) * sigma_y),
            "known_residual_rms": float(np.sqrt(np.mean(res[nm:] ** 2)) / known_scale),
            "nfev": int(sol.nfev),
            "converged": bool(sol.status > 0),
            "start": "centered + alignment",
            "route": "motion rows",
        }
    }
    C_unit = C / g
    cal = _finish(data, C_unit, offset, dof, "joint", s, r, data.nbad, extra, None, None, None,
                  loads=lambda b: (b - offset) @ C_unit.T)
    cal.C = C
    # Gauss-Newton covariance, scaled by the reduced chi-square (misstated sigmas are absorbed);
    # the motion rows used are len(Y) of n
    J = jac(sol.x)
    chi2 = float(res @ res) / max(len(res) - len(sol.x), 1)
    Jm, Jk = J[:nm] * np.sqrt(n / nm), J[nm:]
    try:
        cov = np.linalg.inv(Jm.T @ Jm + Jk.T @ Jk) * chi2
    except np.linalg.LinAlgError:
        cov = np.full((len(sol.x), len(sol.x)), np.inf)

    def fn(x):
        K, c, _ = unpack(x)
        return mu + Vr @ c, K @ Vr.T

    off_se, C_se = propagate(fn, sol.x, cov, len(offset))
    add_uncertainty(cal, off_se, C_se, data.span)
    return cal


def _first_best(raw) -> int:
    """The index of the largest of ``raw`` compared to 10 significant digits (rounding noise,
    directions written to a CSV and read back, must not break a tie differently; exact ties
    go to the first). Only values within 1e-7 of the largest can round to it: those are
    rounded as ``float(f"{x:.10g}")`` does, the rest never need to be."""
    raw = np.asarray(raw, float).ravel()
    top = float(np.max(raw))
    near = np.flatnonzero(raw >= top - 1e-7 * abs(top))
    values, where = np.unique(raw[near], return_inverse=True)  # many exact ties: format once
    rounded = np.array([float(f"{v:.10g}") for v in values])[where.ravel()]
    return int(near[int(np.argmax(rounded))])


def choose_known_poses(directions, k: int = 4) -> np.ndarray:
    """Which ``k`` of a rig's poses should get known loads: the most spread ones.

    ``directions`` (n, r): the poses' load directions (approximate is enough: the rig's design).
    Returns the indices of the k poses maximising ``det(X^T X)`` with ``X = [u 1]`` (the
    D-optimal choice for the affine calibration the known pairs pin down), by exhaustive search
    up to 20,000 subsets, else greedily from the most spread pair and then by exchanges (one
    chosen pose for another, the best swap, while any improves: Fedorov's algorithm); scores
    are compared to 10 significant digits, so that rounding noise cannot change the choice. On
    12-pose rigs with 4 known loads this moves the Cramer-Rao bound from a median 1.55x to
    1.23x the all-known bound, and every rig within 1.5x (scripts/calib_rig_bound.py --design;
    docs/calib.md); on 40-pose payload rigs the exchanges move it from 1.73x (greedy) to 1.69x
    (exhaustive search: 1.66x).
    """
    import itertools
    from math import comb

    U = np.asarray(directions, float)
    if U.ndim != 2 or len(U) < k or k < 1:
        raise CalibrationError(f"need an (n, r) array of n >= k = {k} pose directions, "
                               f"got shape {U.shape}")
    if not np.all(np.isfinite(U)):
        raise CalibrationError("pose directions must be finite")
    U = U / np.maximum(np.linalg.norm(U, axis=1, keepdims=True), 1e-300)
    X = np.column_stack([U, np.ones(len(U))])
    n, d = X.shape

    def dets(sets):  # det(A^T A) (det(A A^T) below d rows) of each index set (a row of sets)
        A = X[sets]
        G = (np.einsum("mia,mib->mab", A, A) if sets.shape[1] >= d
             else np.einsum("mia,mja->mij", A, A))
        return np.linalg.det(G)

    if comb(n, k) <= 20_000:
        sets = np.array(list(itertools.combinations(range(n), k)), int).reshape(-1, k)
        return sets[_first_best(dets(sets))]
    # greedy from the most spread pair, then exchanges (Fedorov) while one improves. The pairs
    # (det of each pair's 2 x 2 Gram matrix) in blocks of rows, never all n^2 at once (a sweep's
    # 100,000 directions): each block's best pair as every pair competed, the first block's
    # on a tie (blocks and the pairs within them come in the order combinations gives)
    if k >= 2:
        q = np.einsum("ia,ia->i", X, X)
        step = max(1, 1_000_000 // n)
        best, best_score = None, -np.inf
        for a in range(0, n - 1, step):
            rows = np.arange(a, min(a + step, n - 1))
            D = q[rows, None] * q[None, :] - (X[rows] @ X.T) ** 2
            D[np.arange(n)[None, :] <= rows[:, None]] = -np.inf  # i < j only
            top = float(D.max())
            ii, jj = np.nonzero(D >= top - 1e-7 * abs(top))  # row-major: i, then j
            pairs = np.column_stack([rows[ii], jj])
            raw = dets(pairs)
            w = _first_best(raw)
            score = float(f"{raw[w]:.10g}")
            if score > best_score:
                best, best_score = [int(pairs[w, 0]), int(pairs[w, 1])], score
    else:
        best = [_first_best(dets(np.arange(n)[:, None]))]
    rest = np.ones(n, bool)
    rest[best] = False
    while len(best) < k:
        cand = np.flatnonzero(rest)
        best.append(int(cand[_first_best(dets(np.column_stack(
            [np.tile(best, (len(cand), 1)), cand])))]))
        rest[best[-1]] = False
    current = float(f"{dets(np.array([best]))[0]:.10g}")
    for _ in range(100):
        cand = np.flatnonzero(rest)
        raw = np.empty((k, len(cand)))
        for a in range(k):  # chosen pose a swapped for each candidate, in index order
            sets = np.tile(best, (len(cand), 1))
            sets[:, a] = cand
            raw[a] = dets(sets)
        flat = _first_best(raw)
        if float(f"{raw.flat[flat]:.10g}") <= current:
            break
        a, c = divmod(flat, len(cand))
        rest[best[a]], rest[cand[c]] = True, False
        current, best[a] = float(f"{raw.flat[flat]:.10g}"), int(cand[c])
    return np.array(sorted(best))
