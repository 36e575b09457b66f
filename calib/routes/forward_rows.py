"""The joint route on a log without static poses (one reading per pose, or a sweep): the
forward maximum-likelihood fit on the rows (:func:`fit_forward_rows`), its noise tests, outlying
readings and predicted held-out error.
"""

from __future__ import annotations

import warnings

import numpy as np

from calib.data.result import CalibrationError, add_uncertainty
from calib.data.validate import check_matrix
from calib.estimators.bias import fit_bias
from calib.verdict.predicted_error import one_sided
from calib.verdict.reliability import KNOWN_INFLUENCE_MAX

#: A known reading within this fraction of every channel's spread of a row of the log is that
#: row (the known loads given for readings of the log itself, as `calib plan` recommends).
#: Decision: docs/calib_design.md D37.
SAME_READING = 1e-6


#: Logs without static poses: at most this many (evenly strided) readings enter the forward
#: fit, every one its own pose (a slow sweep's neighbouring readings carry nearly the same load:
#: on a simulated 100,000-reading payload sweep, 50,000 strided readings measured a held-out
#: error 1.0266x least squares with every load known, all 100,000 1.0258x, in 9.6 s against
#: 16.5 s, one run each).
#: Decision: docs/calib_design.md D75.
FORWARD_MAX_ROWS = 50_000


def _forward_step(n: int) -> int:
    return max(int(np.ceil(n / FORWARD_MAX_ROWS)), 1)


def fit_forward_rows(Z, known_Z, known_M, dof, magnitude=None, known_samples=None,
                     motion=None, seed: int = 0, n_total: int | None = None,
                     known_sigma: float | None = None, robust: bool = False,
                     row_index=None):
    """A log with no static poses (one reading per pose, or a continuous sweep): every reading
    its own pose in the maximum-likelihood forward fit (:mod:`calib.estimators.forward`), the
    Sampson and
    centered routes among its starts. A known reading that is a row of the log makes that row
    a known pose; any other known reading is a pose of its own, the mean of ``known_samples``
    readings (default 1). The calibration is the fit's ``C = (A^T V^-1 A)^-1 A^T V^-1`` with
    ``V`` the estimated channel variances, the offset its ``o``. ``known_sigma`` (the stated
    loads' own error per component, load units) widens the predicted held-out error: the known
    loads' error moves the fit, and held-out loads are stated as accurately
    (:func:`calib.verdict.predicted_error.predict_error`); the fit's weights do not use it.

    Readings far from the fitted model (:func:`calib.estimators.forward.misfit.outlying_readings`:
    a spike, a
    glitch) are told, by their row (``row_index``: each row's index in the user's log; default
    ``0..n-1``), and the predicted error then states no upper end. A known reading among them
    whose removal moves the loads by more than the predicted error
    (:data:`KNOWN_INFLUENCE_MAX`) makes the verdict refuse the fit
    (:func:`calib.verdict.reliability.assess`). ``robust=True`` leaves them out and fits once more
    (known readings too, while at least ``dof`` known loads remain); their rows are in
    ``diagnostics["joint"]["outlier_rows_rejected"]``."""
    from calib.data.result import (
        Calibration,
        channel_span,
        coverage_diagnostics,
        excitation_is_poor,
        warn,
    )
    from calib.estimators.forward.correlated import fit_correlated
    from calib.estimators.forward.misfit import DIRECTION_ALPHA, outlying_readings
    from calib.estimators.forward.problem import Problem
    from calib.verdict.predicted_error import gls_inverse, predict_error
    from calib.verdict.serial import serial_correlation

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
    from calib.estimators.rig.fit import SAME_MAGNITUDE

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
        # docstring of calib.verdict.reliability)
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
    from calib.estimators.forward.refits import _global_cov

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


def _told_outliers(found, n, rows_of, known, order) -> dict | None:
    """:func:`calib.estimators.forward.misfit.outlying_readings`' poses as the user's rows and
    known loads: ``rows`` (the log's rows that are not known readings, as indices in the user's log,
    ``rows_of``), ``log_rows`` (every flagged row, as indices into this fit's ``Z``), ``known``
    (the caller's indices of the known loads whose reading is flagged; the problem's known pose
    ``known[i]`` is the caller's known load ``order[i]``; a known reading that is a row of the
    log is both)."""
    if found is None:
        return None
    from calib.estimators.forward.misfit import OUTLIER_ALPHA

    poses = np.asarray(found["poses"], int)
    log_rows = poses[poses < n]
    hit = set(poses.tolist())
    flagged_known = sorted(int(order[i]) for i, pose in enumerate(known) if pose in hit)
    return {"rows": rows_of[np.setdiff1d(log_rows, known)], "log_rows": log_rows,
            "known": np.asarray(flagged_known, int), "p_values": np.asarray(found["p_values"]),
            "scale": found["scale"], "min_p_value": found["min_p_value"], "alpha": OUTLIER_ALPHA}


def _starts(Z, known_Z, known_M, dof, magnitude, motion):
    starts = {"Sampson-distance joint fit": motion}
    try:
        starts["centered + alignment"] = fit_bias(Z, dof, known_Z=known_Z, known_M=known_M,
                                                  magnitude=magnitude)
    except CalibrationError:
        pass
    return starts
