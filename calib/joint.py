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

from ._validate import check_matrix
from .bias import _finish, _prepare_source, fit_bias, fit_centered
from .models import summarise_folds
from .result import CalibrationError, add_uncertainty, propagate
from .sfm import principal

#: At most this many (evenly strided) motion rows enter the nonlinear least squares.
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
    pose-level fit of :mod:`calib.rig` when ``poses`` is ``"auto"`` (poses found by
    :func:`calib.rig.find_poses`) or an array of pose labels per row; the Sampson-distance fit
    below is then one of its starts. ``poses=None`` always uses the Sampson-distance fit (as do
    streamed sources). ``cv=True`` adds ``diagnostics["cv_poses"]``: the leave-one-pose-out
    error over the known poses (:func:`leave_one_pose_out`). ``model`` (affine, channel,
    quadratic, auto) and ``drift`` (none, linear, auto) choose the rig fit's second stage
    (:mod:`calib.models`); ``auto`` keeps the candidate with the lowest leave-one-pose-out error
    (``diagnostics["model_selection"]``); other than affine/none they need a static-pose log.
    ``robust=True`` leaves out rows more than 5 robust standard deviations from their pose's
    median on static-pose logs (:func:`calib.rig.reject_outliers`; the count is in the
    diagnostics), and readings far from the fitted model on logs without static poses
    (:func:`fit_forward_rows`, which tells of them without it).

    Parameters
    ----------
    Z : (n, p) readings of a constant-magnitude load over orientations (static poses welcome);
        an array, a dask array or a :class:`calib.stream.ChunkSource` (streamed: the fit uses at
        most :data:`JOINT_MAX_ROWS` strided rows, the other passes are sums)
    known_Z, known_M : (k, p), (k, dof) known pairs; k >= 2 (>= 3 to avoid a mirror image)
    magnitude : the load magnitude of the motion rows; None fits it
    known_sigma, magnitude_sigma : accuracies in load units (see the module docstring)
    known_samples : instead of ``known_sigma``: each known reading is the mean of this many
        readings of the log's kind (a static pose averaged), so its accuracy is
        ``magnitude_sigma / sqrt(known_samples)``; 1 for single readings

    A channel that is an exact affine copy of another (logged twice) is left out of the fit
    and given a column of zeros in C (:mod:`calib.copies`).

    Returns a Calibration with ``method="joint"``; diagnostics as the centered route's plus
    ``joint`` (sigmas, fitted magnitude, residual rms of both kinds, solver status) and standard
    errors from the weighted Jacobian.
    """

    from .copies import fit_without_copies

    # a channel logged twice (an exact affine copy): fitted without it (calib.copies)
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

    from .stream import is_streamed

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
    from .models import choose
    from .rig import find_poses, rig_calibration, rig_pose_loads

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
        from .rig import reject_outliers

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
            # the fit is refused anyway (calib.reliability): choosing a model by how well it
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


#: A known reading within this fraction of every channel's spread of a row of the log is that
#: row (the known loads given for readings of the log itself, as `calib plan` recommends).
SAME_READING = 1e-6


#: Logs without static poses: at most this many (evenly strided) readings enter the forward
#: fit, every one its own pose (a slow sweep's neighbouring readings carry nearly the same load:
#: on a simulated 100,000-reading payload sweep, 50,000 strided readings measured a held-out
#: error 1.0266x least squares with every load known, all 100,000 1.0258x, in 9.6 s against
#: 16.5 s, one run each).
FORWARD_MAX_ROWS = 50_000


def _forward_step(n: int) -> int:
    return max(int(np.ceil(n / FORWARD_MAX_ROWS)), 1)


def fit_forward_rows(Z, known_Z, known_M, dof, magnitude=None, known_samples=None,
                     motion=None, seed: int = 0, n_total: int | None = None,
                     known_sigma: float | None = None, robust: bool = False,
                     row_index=None):
    """A log with no static poses (one reading per pose, or a continuous sweep): every reading
    its own pose in the maximum-likelihood forward fit (:mod:`calib.forward`), the Sampson and
    centered routes among its starts. A known reading that is a row of the log makes that row
    a known pose; any other known reading is a pose of its own, the mean of ``known_samples``
    readings (default 1). The calibration is the fit's ``C = (A^T V^-1 A)^-1 A^T V^-1`` with
    ``V`` the estimated channel variances, the offset its ``o``. ``known_sigma`` (the stated
    loads' own error per component, load units) widens the predicted held-out error: the known
    loads' error moves the fit, and held-out loads are stated as accurately
    (:func:`calib.forward.predict_error`); the fit's weights do not use it.

    Readings far from the fitted model (:func:`calib.forward.outlying_readings`: a spike, a
    glitch) are told, by their row (``row_index``: each row's index in the user's log; default
    ``0..n-1``), and the predicted error then states no upper end. A known reading among them
    whose removal moves the loads by more than the predicted error
    (:data:`KNOWN_INFLUENCE_MAX`) makes the verdict refuse the fit
    (:func:`calib.reliability.assess`). ``robust=True`` leaves them out and fits once more
    (known readings too, while at least ``dof`` known loads remain); their rows are in
    ``diagnostics["joint"]["outlier_rows_rejected"]``."""
    from .forward import (
        DIRECTION_ALPHA,
        Problem,
        fit_correlated,
        gls_inverse,
        outlying_readings,
        predict_error,
        serial_correlation,
    )
    from .result import Calibration, channel_span, coverage_diagnostics, excitation_is_poor, warn

    Z = np.asarray(Z, float)
    Zk, _ = check_matrix(np.atleast_2d(known_Z), "known readings")
    Mk = np.atleast_2d(np.asarray(known_M, float))[:, :dof]
    if known_sigma is not None and not known_sigma < np.median(np.linalg.norm(Mk, axis=1)):
        raise CalibrationError(f"known_sigma {known_sigma:g} is as large as the known loads "
                               "themselves: nothing to calibrate against")
    spread = np.maximum(Z.std(axis=0), 1e-300)
    rows, extra = [], []
    for k, zk in enumerate(Zk):
        d = np.max(np.abs(Z - zk) / spread, axis=1)
        j = int(np.argmin(d))
        if d[j] <= SAME_READING and j not in rows:
            rows.append(j)
        else:
            extra.append(k)
    Y = np.vstack([Z, Zk[extra]]) if extra else Z
    n_known = float(known_samples) if known_samples else 1.0
    counts = np.r_[np.ones(len(Z)), np.full(len(extra), n_known)]
    known = np.r_[np.asarray(rows, int), len(Z) + np.arange(len(extra))].astype(int)
    order = np.r_[[k for k in range(len(Zk)) if k not in extra], extra].astype(int)
    Mk = Mk[order]
    mags = np.linalg.norm(Mk, axis=1)
    from .rig import SAME_MAGNITUDE

    g = (float(magnitude) if magnitude is not None
         else float(np.median(mags)) if mags.max() <= (1 + SAME_MAGNITUDE) * mags.min()
         else None)
    # no pose repeats: each channel's variance is one reading's, a known reading stated as the
    # mean of known_samples readings weighs that many times more (Problem.weights)
    pr = Problem(Y, counts, None, known, Mk, magnitude=g)
    starts = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the starts' warnings: this fit reports its own
        closed_form = _starts(Z, Zk[order], Mk, dof, magnitude, motion)  # Mk is in order
    for name, cal in closed_form.items():
        try:
            starts[name] = cal.apply(Y)
        except (CalibrationError, ValueError):
            continue
    # noise the channels share (a wrench mixed from gauges): refit in whitened channels; the
    # problem and fit below are in the channels fitted, the calibration mapped back
    pr, fit, T, T_inv, correlation = fit_correlated(pr, starts, seed=seed)
    misfit = correlation.pop("direction_misfit", None)
    rows_of = np.arange(len(Z)) if row_index is None else np.asarray(row_index)
    outliers = _told_outliers(outlying_readings(pr, fit), len(Z), rows_of, known, order)
    flagged = outliers is not None and len(outliers["rows"]) + len(outliers["known"]) > 0
    without = None  # the fit without the flagged readings
    drop_known = []
    if flagged:
        drop_known = outliers["known"] if len(Zk) - len(outliers["known"]) >= dof else []
    # refitted: with robust where anything can be left out; else to weigh a flagged known
    # reading, which needs it left out (each refit has fewer known loads: the depth is bounded)
    if flagged and (len(drop_known) or (robust and len(outliers["log_rows"]))):
        keep = np.setdiff1d(np.arange(len(Z)), outliers["log_rows"])
        keep_k = np.setdiff1d(np.arange(len(Zk)), drop_known)
        with warnings.catch_warnings(record=True) as refit_warnings:
            warnings.simplefilter("always")
            without = fit_forward_rows(
                Z[keep], Zk[keep_k], np.atleast_2d(np.asarray(known_M, float))[keep_k], dof,
                magnitude, known_samples, motion, seed, n_total, known_sigma, robust=False,
                row_index=rows_of[keep])
        without.diagnostics["joint"]["outlier_rows_rejected"] = [
            int(r) for r in rows_of[outliers["log_rows"]]]
        without.diagnostics["joint"]["outlier_known_rejected"] = [int(k) for k in drop_known]
        if robust:
            for m in refit_warnings:
                warnings.warn_explicit(m.message, m.category, m.filename, m.lineno)
            return without
    if flagged:
        named = ", ".join(str(int(r)) for r in outliers["rows"][:10])
        more = f" and {len(outliers['rows']) - 10} more" if len(outliers["rows"]) > 10 else ""
        if len(outliers["rows"]):
            warn(f"{len(outliers['rows'])} reading(s) lie far from the fitted model (row(s) "
                 f"{named}{more}, counted from 0 among the data rows; chi-square tail below "
                 f"{outliers['alpha']:.2g}): a spike or glitch moves the fit, and the predicted "
                 "error does not count them; --robust (robust=True) leaves them out")
    C = gls_inverse(fit["A"], fit["v"]) @ T
    offset = T_inv @ fit["o"]
    # noise correlated in time (a sweep read faster than its noise changes): the log's readings
    # are worth fewer independent ones, measured on refits (serial_correlation)
    serial = serial_correlation(pr, fit, len(Z), seed=seed)
    # a misfit that depends on the load's direction (a sensor not linear in the load): told, not
    # refused (the fit is at its model's optimum; its predicted error takes the misfit for
    # noise). Not where the noise is correlated in time: slow noise along a path that returns
    # to its directions defeats the test's null (an AR(0.99) sweep was found nonlinear)
    nonlinear = False
    if isinstance(misfit, dict):
        misfit["tested"] = serial is None
        nonlinear = serial is None and misfit["p_value"] < DIRECTION_ALPHA
        if nonlinear:
            warn(f"the residuals of nearby load directions agree (neighbour correlation "
                 f"{misfit['rho']:.2f}, p = {misfit['p_value']:.2g}): the sensor is not linear "
                 "in the load, and the predicted error and its ratio to least squares take that "
                 "misfit for noise, so both can be low: no upper end of the error is stated; "
                 "measure the error on known loads left out of the fit (calib evaluate; "
                 "docs/calib.md, 'Gauges that are not linear')")
    pred = predict_error(pr, fit, seed=seed, load_sd=known_sigma or 0.0,
                         whitened=bool(correlation.get("used")), serial=serial)
    if pred is not None and serial is not None:
        # the verdict's paired ratio stays the independent-noise model's: on AR(0.99) sweeps the
        # measured ratios (1.04-1.41x) lay about its upper end (1.21-1.31x) and far below the
        # widened one's (1.9-2.9x, which refused fits the oracle makes within 1.5x); on the real
        # wrist sensor, whose residuals are correlated along the poses' order, the widened ratio
        # refused 3 of 40 random known sets more, two of them 1.10x and 1.17x (docs/calib.md,
        # "Noise correlated in time")
        white = predict_error(pr, fit, seed=seed, load_sd=known_sigma or 0.0,
                              whitened=bool(correlation.get("used")), dof=serial["white_dof"])
        if white is not None:
            pred = {**pred, "ratio": white["ratio"], "upper_ratio": white["upper_ratio"]}
    if pred is not None and nonlinear:
        pred = one_sided(pred)
    elif pred is not None and flagged and len(outliers["rows"]):
        # readings the noise model does not hold (spikes) move the fit by more than its Monte
        # Carlo draws: on spiked sweeps the interval held 1 of 4 (docs/calib.md, "Readings far
        # from the model"); the lower end stays
        pred = one_sided(pred, because="readings far from the model")
    if flagged and len(outliers["known"]):
        # how far the flagged known reading(s) move the fit: the log's loads with and without
        # them, over the fit's own predicted held-out error. Beyond 1 the stated error does not
        # hold (assess refuses); a tail draw of heavy-tailed noise moves it less (module
        # docstring of calib.reliability)
        influence = None
        if without is not None and pred is not None:
            d = (Z - offset) @ C.T - without.apply(Z)
            influence = float(np.sqrt(np.mean(np.sum(d**2, axis=1))) / pred["rms"])
        outliers["known_influence"] = influence
        ks = ", ".join(str(int(k)) for k in outliers["known"])
        moved = ("" if influence is None else
                 f"; leaving it out moves the loads by {influence:.2g}x the predicted error")
        bad = influence is None or influence > KNOWN_INFLUENCE_MAX
        warn(f"the reading of known load(s) {ks} (counted from 0) lies far from the fitted model "
             f"(a spike, or the load stated for another reading){moved}"
             + (": the fit is not reliable (measure that known load again, or --robust leaves "
                "it out while enough known loads remain)" if bad else ""))
    from .forward import _global_cov

    cov = _global_cov(fit)
    nth = pr.p * (pr.r + 1)
    if cov is not None:
        io = np.arange(pr.p) * (pr.r + 1) + pr.r
        off_se = np.sqrt(np.clip(np.diag(T_inv @ cov[np.ix_(io, io)] @ T_inv.T), 0, None))
        g_rel_se = (float(np.sqrt(cov[nth, nth])) / fit["g"]) if pr.fit_g else None
        # C's standard errors by the delta method on the GLS inverse (A's columns)
        J = []
        eps = 1e-6
        base = C.ravel()
        for c in range(pr.p):
            for a in range(pr.r):
                A1 = fit["A"].copy()
                h = eps * max(abs(A1[c, a]), 1e-12 + np.abs(fit["A"]).max())
                A1[c, a] += h
                J.append(((gls_inverse(A1, fit["v"]) @ T).ravel() - base) / h)
        J = np.array(J).T  # (dof*p, p*r)
        idx = np.array([c * (pr.r + 1) + a for c in range(pr.p) for a in range(pr.r)])
        covA = cov[np.ix_(idx, idx)]
        C_se = np.sqrt(np.clip(np.einsum("ia,ab,ib->i", J, covA, J), 0, None)).reshape(C.shape)
    else:
        off_se = np.full(pr.p, np.inf)
        C_se = np.full(C.shape, np.inf)
        g_rel_se = float("inf") if pr.fit_g else None
    loads = (Z - offset) @ C.T
    mag = np.linalg.norm(loads, axis=1)
    U = fit["M"] / np.linalg.norm(fit["M"], axis=1, keepdims=True)
    cov_d = coverage_diagnostics(U[: len(Z)])
    known_res = (Zk[order] - offset) @ C.T - Mk
    diag = {
        "n_samples": int(len(Z) if n_total is None else n_total),
        "n_dropped_nonfinite": 0,
        "rows_used": int(len(Z)),
        "singular_values": np.linalg.svd(Z - Z.mean(axis=0), compute_uv=False),
        "condition_number_C": float(np.linalg.cond(C)),
        "residual_rms": float(np.sqrt(np.mean((mag - fit["g"]) ** 2))),
        "coverage": cov_d,
        "excitation_poor": bool(excitation_is_poor(cov_d)),
        "joint": {
            "route": "forward",
            "readings_per_pose": 1,
            "n_poses": int(pr.P),
            "n_known": int(len(Mk)),
            "n_known_matched_to_rows": int(len(rows)),
            "known_samples": known_samples,
            "magnitude": float(fit["g"]),
            "magnitude_fitted": pr.fit_g,
            "channel_noise": np.sqrt(np.einsum("ck,k,ck->c", T_inv, fit["v"], T_inv)),
            "noise_correlation": correlation,
            "pose_magnitude_residual_rms": float(np.sqrt(np.mean((mag - fit["g"]) ** 2))),
            "pose_residual_rms": float(np.sqrt(np.mean(np.sum(
                (loads - fit["M"][: len(Z)]) ** 2, axis=1)) / dof)),
            "known_residual_rms": float(np.sqrt(np.mean(known_res**2))),
            "known_residuals": known_res,
            "starts": fit["starts"],
            "chosen_start": fit["chosen_start"],
            "reweight_rounds": fit["rounds"],
            "cost": fit["cost"],
            "converged": bool(fit["converged"]),
            "nfev": int(fit["iterations"]),
            "predicted_error": pred,
            "serial_correlation": serial,
            "direction_misfit": misfit,
            "outlying_readings": outliers,
            "outlier_rows_rejected": [] if robust else None,
            "outlier_known_rejected": [] if robust else None,
            "magnitude_rel_stderr": g_rel_se,
        },
    }
    cal = Calibration(C=C, offset=offset, dof=dof, method="joint", diagnostics=diag)
    add_uncertainty(cal, off_se, C_se, channel_span(Z),
                    offset_cov=None if cov is None else T_inv @ cov[np.ix_(io, io)] @ T_inv.T,
                    load_span=np.ptp(loads, axis=0))
    return cal


#: A known reading flagged by :func:`calib.forward.outlying_readings` whose removal moves the
#: log's loads by more than this multiple of the fit's predicted held-out error makes the fit
#: unreliable: the error it states does not hold. 1 is the fit's own unit, not tuned (measured
#: on payload rigs: a 30-standard-deviation spike on a known reading 1.4-5.4, a 10 sd one
#: 0.8-1.6; the known readings that heavy-tailed (t3) noise's tail draws flagged 0.4-0.8).
KNOWN_INFLUENCE_MAX = 1.0


def _told_outliers(found, n, rows_of, known, order) -> dict | None:
    """:func:`calib.forward.outlying_readings`' poses as the user's rows and known loads:
    ``rows`` (the log's rows that are not known readings, as indices in the user's log,
    ``rows_of``), ``log_rows`` (every flagged row, as indices into this fit's ``Z``), ``known``
    (the caller's indices of the known loads whose reading is flagged; the problem's known pose
    ``known[i]`` is the caller's known load ``order[i]``; a known reading that is a row of the
    log is both)."""
    if found is None:
        return None
    from .forward import OUTLIER_ALPHA

    poses = np.asarray(found["poses"], int)
    log_rows = poses[poses < n]
    hit = set(poses.tolist())
    flagged_known = sorted(int(order[i]) for i, pose in enumerate(known) if pose in hit)
    return {"rows": rows_of[np.setdiff1d(log_rows, known)], "log_rows": log_rows,
            "known": np.asarray(flagged_known, int), "p_values": np.asarray(found["p_values"]),
            "scale": found["scale"], "min_p_value": found["min_p_value"], "alpha": OUTLIER_ALPHA}


def one_sided(pred: dict, because: str = "not linear") -> dict:
    """The predicted error of a fit whose sensor reads as not linear in the load
    (:func:`calib.forward.direction_misfit` found): no upper end is stated.

    The Monte Carlo of :func:`calib.forward.predict_error` takes the misfit for independent
    noise, and the fitted directions take up the part of it across the load that the held-out
    loads then carry: the measured error lies above the interval, never below it (payload rigs
    2 % and 5 % nonlinear, seeds 20,000-20,029: 5 of 30 and 12 of 30 above, every one of them
    found by the test; 0 below). Nothing in a one-reading log prices that part (docs/calib.md,
    "Gauges that are not linear"), so the upper end is withdrawn (``inf``; ``null`` in the
    written file) rather than stated at a coverage it does not have; the lower end stays (the
    error of an affine sensor is the least this one's can be). The affine model's interval is
    kept as ``interval_if_linear``. The verdict's ratio (``ratio``, ``upper_ratio``) stays the
    affine model's: the fit is at its model's optimum, and refusing every fit found would
    refuse those the oracle makes within 1.5x least squares. ``because`` (stored as
    ``no_upper_end_because``): "not linear", or "readings far from the model" where
    :func:`calib.forward.outlying_readings` flagged unknown readings (spikes the noise model
    does not hold; ``robust=True`` leaves them out)."""
    lo, hi = pred["interval"]
    return {**pred, "interval": [lo, float("inf")], "upper_bounded": False,
            "no_upper_end_because": because,
            "interval_if_linear": [lo, hi], "interval_ratio": float("inf"),
            "interval_ratio_if_linear": pred["interval_ratio"]}


def _inconsistent(s1: dict) -> bool:
    """Whether the stage-1 fit's known loads fail :data:`calib.rig.KNOWN_INCONSISTENT`."""
    from .rig import KNOWN_INCONSISTENT

    frac = s1.get("consistency", {}).get("fraction", float("nan"))
    return bool(np.isfinite(frac) and frac > KNOWN_INCONSISTENT)


def _starts(Z, known_Z, known_M, dof, magnitude, motion):
    starts = {"Sampson-distance joint fit": motion}
    try:
        starts["centered + alignment"] = fit_bias(Z, dof, known_Z=known_Z, known_M=known_M,
                                                  magnitude=magnitude)
    except CalibrationError:
        pass
    return starts


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
    from .rig import PoseData

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
    from .rig import rig_calibration

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
