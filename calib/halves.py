"""Is a log one rig throughout? Its time-ordered halves, fitted alone, compared.

The forward fit (:mod:`calib.forward`) assumes one rig for the whole log: one map ``A``, one
offset ``o``, one load magnitude, one noise level per channel. A log in which one of these
changes while it is recorded (the gripper picks something up, a cable starts to pull, a gain
drifts) breaks that, and the fit bends to it without a sign in its own uncertainty: the misfit
lies in the range of ``A`` (a heavier load reads along the load), where it passes for noise the
channels share, and the predicted held-out error's Monte Carlo draws least squares' error under
that same inflated noise model. On the payload study's default case with the last quarter of
the log 5 % heavier, fits 3.5-18.5x least squares on the same readings were written with exit 0
(docs/calib.md, "A load that changes during the log").

The two halves of the log (in the order given, at most :data:`MAX_READINGS` evenly strided
readings each, the same known readings for both) are each fitted alone by the same forward fit
(its own noise model and whitening), and two tests compare them:

- **loads**: the rms difference ``D`` of the two calibrations' loads on every reading used,
  against its distribution when both fits err only as their covariances say (the inverse Schur
  complement, each channel's variance drawn from its scaled chi-square as in
  :func:`calib.forward.predict_error`; :data:`DRAWS` Monte Carlo draws, p-value
  ``(1 + #{D_null >= D}) / (draws + 1)``);
- **noise**: each channel's fitted noise variance in one half over the other's, an F test on the
  halves' residual degrees of freedom (``P - sum(leverage)``), two-sided, Bonferroni over the
  channels.

The check's p-value is the smaller of the two times 2 (Bonferroni), and
:func:`calib.reliability.assess` refuses a fit whose check falls below :data:`HALVES_P`.
Neither test needs the change to be a load's: a change of gain or offset breaks them too.

Measured (stop 62, docs/calib.md, "A load that changes during the log"): on the payload study's
default case with the last quarter of the log 5 % / 20 % heavier, 17 / 13 of 20 fits refused
by it; fits written beyond 3x least squares on the same readings 4 / 4 before, 0 / 1 after (the
one: 7.3x, p 0.006). What it costs: on the payload study's 540 rigs without a change, good fits
refused (about 2 %, where 0.1 % is nominal): the loads' test holds each half's whitening as
known, the noise test counts degrees of freedom linearly. A repeated channel is refused too
(its pair's variances are not identified apart), and halves of 10 readings are short.
"""

from __future__ import annotations

import numpy as np

from .forward import SEARCH_POSES, _global_cov, _sampler, fit_correlated, gls_inverse
from .result import CalibrationError

#: A check whose p-value falls below this refuses the fit (:func:`calib.reliability.assess`).
HALVES_P = 1e-3
#: Each half is fitted on at most this many evenly strided readings (a sweep's halves): as many
#: as the forward fit searches on (:data:`calib.forward.SEARCH_POSES`), so that a half's channel
#: variances are estimated on every reading it has and the noise test's degrees of freedom,
#: ``P - sum(leverage)``, count readings that estimated them.
MAX_READINGS = SEARCH_POSES
#: Monte Carlo draws of the loads' difference under one rig.
DRAWS = 2000
#: Fewer readings than this in a half: not checked (a half cannot be fitted alone).
MIN_READINGS = 8


def _strided(rows: np.ndarray) -> np.ndarray:
    if len(rows) <= MAX_READINGS:
        return rows
    return rows[np.linspace(0, len(rows) - 1, MAX_READINGS).round().astype(int)]


def check(Z: np.ndarray, problem_of, seed: int = 0, draws: int = DRAWS) -> dict:
    """Fit the halves of the log ``Z`` (n, p) alone and compare them (module docstring).

    ``problem_of(rows)`` builds the forward problem of the readings ``Z[rows]`` with the log's
    known readings (:class:`calib.forward.Problem`). Returns
    ``checked`` False with ``why`` where a half is too short or its fit fails; else
    ``readings`` (per half), ``disagreement_rms`` (D, load units),
    ``disagreement_null_median``, ``p_disagreement``, ``noise_sd_ratio`` (per channel, the
    second half's over the first's), ``p_noise`` and ``p`` (the check's)."""
    from scipy.stats import f as fdist

    Z = np.asarray(Z, float)
    n = len(Z)
    halves = [_strided(h) for h in np.array_split(np.arange(n), 2)]
    if min(len(h) for h in halves) < MIN_READINGS:
        return {"checked": False, "why": f"a half has fewer than {MIN_READINGS} readings"}
    parts = []
    for rows in halves:
        try:
            pr, fit, T, T_inv, _ = fit_correlated(problem_of(rows), seed=seed)
        except (CalibrationError, np.linalg.LinAlgError, ValueError, FloatingPointError) as e:
            return {"checked": False, "why": f"a half's fit failed: {e}"}
        cov = _global_cov(fit)
        if cov is None or not np.all(np.isfinite(fit["A"])):
            return {"checked": False, "why": "a half's fit has no covariance"}
        nth = pr.p * (pr.r + 1)
        # the linear count: the refits' measured degrees of freedom (reweighting_dof, as the
        # predicted error takes them) made the noise test far less calibrated (stop 62)
        dof = np.maximum(pr.P - fit["leverage"].sum(axis=0), 1.0)
        parts.append((pr, fit, T, T_inv, _sampler(cov[:nth, :nth]), dof))
    used = Z[np.sort(np.concatenate(halves))]

    def loads(part, d=None):
        pr, fit, T, T_inv = part[:4]
        A, o = fit["A"], fit["o"]
        if d is not None:
            A, o = A + d[:, : pr.r], o + d[:, pr.r]
        return (used - T_inv @ o) @ (gls_inverse(A, fit["v"]) @ T).T

    L0 = [loads(part) for part in parts]
    D = float(np.sqrt(np.mean(np.sum((L0[0] - L0[1]) ** 2, axis=1))))
    rng = np.random.default_rng(seed)
    null = np.empty(draws)
    for i in range(draws):
        diff = 0.0
        for k, part in enumerate(parts):
            pr, L, dof = part[0], part[4], part[5]
            s = rng.chisquare(dof) / dof  # the true variance an estimate could come from
            d = (L @ rng.standard_normal(len(L))).reshape(pr.p, pr.r + 1) / np.sqrt(s)[:, None]
            diff = diff + (1 - 2 * k) * (loads(part, d) - L0[k])
        null[i] = np.sqrt(np.mean(np.sum(diff**2, axis=1)))
    p_d = float((1 + np.sum(null >= D)) / (draws + 1))
    # each channel's noise in the log's own channels (a whitened half's mapped back), on the
    # degrees of freedom of the fitted channel of its index. Not derived: where a half is
    # whitened, channel c's variance is a sum over the fitted channels. The fewest degrees of
    # freedom among its terms (a bound) left 6 of 8 dangerous changed-load fits written;
    # Satterthwaite's count (terms independent) refused 14 of 60 gauge-mixed rigs without a
    # change, this one 5 (stop 62, docs/calib.md)
    var = [np.einsum("ck,k,ck->c", part[3], part[1]["v"], part[3]) for part in parts]
    dfs = [part[5] for part in parts]
    F = var[1] / np.maximum(var[0], 1e-300)
    d1, d0 = dfs[1], dfs[0]
    tail = 2 * np.minimum(fdist.sf(F, d1, d0), fdist.cdf(F, d1, d0))
    p_f = float(min(1.0, len(F) * np.min(tail)))
    return {"checked": True, "readings": [int(len(h)) for h in halves],
            "disagreement_rms": D, "disagreement_null_median": float(np.median(null)),
            "p_disagreement": p_d, "noise_sd_ratio": np.sqrt(F), "p_noise": p_f,
            "p": float(min(1.0, 2 * min(p_d, p_f)))}
