"""Noise correlated along the log (:func:`serial_correlation`): fewer independent readings than
rows, measured by refits, and the widening of the predicted error it calls for.
"""

from __future__ import annotations

import numpy as np

from calib.estimators.forward.problem import Problem
from calib.estimators.forward.refits import REWEIGHT_REPS, _lag1, _refits, dof_of_logs

#: One-sided significance of a channel's lag-1 residual autocorrelation, in the log's order,
#: before :func:`serial_correlation` takes the log's noise as correlated in time.
#: Decision: docs/calib_design.md D48.
SERIAL_ALPHA = 0.01


#: Rounds, and refits in each, that set the simulated noise's AR coefficient in
#: :func:`serial_correlation` (the refits' residual autocorrelation matched to the log's).
#: Decision: docs/calib_design.md D48.
SERIAL_ROUNDS = 3


#: Decision: docs/calib_design.md D48.
SERIAL_PROBE_REPS = 10


def serial_correlation(pr: Problem, fit: dict, n: int, reps: int = REWEIGHT_REPS,
                       seed: int = 0, alpha: float = SERIAL_ALPHA) -> dict | None:
    """Noise correlated in time in a log of single readings (its first ``n`` poses, in the order
    recorded), and what it does to the fit's uncertainty, measured.

    A sweep read faster than the sensor's noise changes (a filtered output, a slow wander) has
    each reading's noise close to the last one's; the fit's covariance counts every reading as
    independent. On simulated 2,000-reading payload sweeps (1,000 training readings) whose noise
    is an AR(1) along the log, the error measured on a new session lay inside the predicted 95 %
    interval on 4 of 6 rigs at coefficient 0.9 and 0 of 6 at 0.99 (1.8-2.8x the predicted
    median); with this correction on 6 of 6 and 5 of 6 (docs/calib.md, "Noise correlated in
    time").

    Each channel's residuals' lag-1 autocorrelation ``rho`` (in the channels fitted). Where the
    channels together are not significant at ``alpha`` (``n sum rho^2`` against a chi-square
    with ``p`` degrees of freedom) or no channel's exceeds its one-sided ``alpha`` point under
    independence, ``z_alpha / sqrt(n)``, returns None. Otherwise ``reps`` logs are simulated
    from the fit and refitted from its directions (the feasible-GLS rounds, :func:`_refits`)
    twice: with independent noise, and with AR(1) noise along the log on the channels found
    correlated. The residuals' autocorrelation is the noise's attenuated (the fitted directions
    and offsets take up slow noise), so the simulated coefficients are first set, in
    :data:`SERIAL_ROUNDS` rounds of :data:`SERIAL_PROBE_REPS` refits, until the refits'
    residuals reach the log's. Returns

    - ``dof`` (``white_dof``): each channel's variance degrees of freedom from the AR
      (independent) refits (:func:`dof_of_logs`);
    - ``parameter_factor``: per channel, how much wider the refitted ``(a_c, o_c)`` spread
      under the AR noise than under independent noise (in the fit's covariance metric; at least
      1); ``ls_factor`` the same of least squares with every load known (fitted to the same
      correlated readings);
    - ``variance_bias``: per channel found correlated, the AR refits' variance estimates over
      the independent ones' (geometric mean, at most 1; 1 elsewhere): slow noise taken up by
      the fit leaves the variances low;
    - ``rho``, ``correlated`` (the channels found so), ``simulated_rho``.

    :func:`predict_error` takes these (``serial``) for the printed error and interval.

    Why simulated, not a sandwich: a Newey-West covariance of the channels' regression scores
    widened the forward fit's error by too much (measured 0.71-0.89 of its prediction at 0.9;
    the unknown directions carry much of it) and, through the paired ratio, refused 3 of 6 fits
    the oracle makes within 1.5x least squares at 0.99."""
    from scipy.stats import chi2, norm

    n = int(n)
    if n < 8:
        return None
    e = pr.Y[:n] - fit["M"][:n] @ fit["A"].T - fit["o"]
    rho = _lag1(e)
    # the channels together first (Box-Pierce at lag 1: n sum rho^2 against chi-square with a
    # degree of freedom a channel), then each channel one-sided
    if chi2.sf(n * float(np.sum(rho**2)), pr.p) >= alpha:
        return None
    hot = rho > norm.isf(alpha) / np.sqrt(n)
    if not hot.any():
        return None
    white = _refits(pr, fit, reps, seed, spreads=True)
    if white is None:
        return None
    # the residuals' autocorrelation is the noise's attenuated (the fitted directions take up
    # slow noise across the load): the simulated noise's coefficient is set so that the refits'
    # residuals reach the log's, on the rows refitted (a sweep's search subset), in the scale of
    # log(1 - rho)
    rows = white["rows"][white["rows"] < n]
    target = np.minimum(_lag1(e[rows]), 0.9999)
    sim = np.where(hot, np.clip(rho, 0.0, 0.999), 0.0)
    for _ in range(SERIAL_ROUNDS):
        probe = _refits(pr, fit, SERIAL_PROBE_REPS, seed, rho=sim, n=n)
        if probe is None or probe["lag1"] is None:
            return None
        got = np.minimum(probe["lag1"], 0.9999)
        sim = np.where(hot, np.clip(1 - (1 - sim) * (1 - target) / (1 - got), 0.0, 0.999), 0.0)
    red = _refits(pr, fit, reps, seed, rho=sim, n=n, spreads=True)
    if red is None:
        return None
    one = np.ones(pr.p)
    pf = (np.maximum(red["fit_spread"] / np.maximum(white["fit_spread"], 1e-300), 1.0)
          if red["fit_spread"] is not None and white["fit_spread"] is not None else one)
    pl = np.maximum(red["ls_spread"] / np.maximum(white["ls_spread"], 1e-300), 1.0)
    # slow noise is taken up by the fitted directions and offsets beyond what the leverage
    # correction allows for independent noise: the variances come out low, by as much on the
    # refits (their mean log ratio under the AR noise over that under independent noise)
    bias = np.where(hot, np.minimum(np.exp(red["logs"].mean(axis=0)
                                           - white["logs"].mean(axis=0)), 1.0), 1.0)
    return {"rho": rho, "correlated": hot, "simulated_rho": sim, "dof": dof_of_logs(red["logs"]),
            "white_dof": dof_of_logs(white["logs"]),
            "variance_bias": bias,
            "parameter_factor": pf, "ls_factor": pl}
