"""Misfits no noise model explains: readings far from the fitted model
(:func:`outlying_readings`), and the direction test for a sensor not linear in the load
(:func:`direction_misfit`).
"""

from __future__ import annotations

import numpy as np

from calib.estimators.forward.problem import SEARCH_POSES, Problem, _search_pick, _unit

#: Significance level of :func:`direction_misfit`'s test (one-sided, by permutation).
#: Decision: docs/calib_design.md D53.
DIRECTION_ALPHA = 0.01


#: Permutations of :func:`direction_misfit`'s null (its p-value's resolution: 1 / 201).
#: Decision: docs/calib_design.md D53.
DIRECTION_PERMUTATIONS = 200


#: :func:`outlying_readings`: a reading is outlying where its tail probability is below this
#: over the number of readings (Bonferroni: a log of gaussian readings has none flagged in about
#: 999 of 1,000 fits, whatever its length)
#: Decision: docs/calib_design.md D50.
OUTLIER_ALPHA = 1e-3


def outlying_readings(pr: Problem, fit: dict, alpha: float = OUTLIER_ALPHA) -> dict | None:
    """Readings that lie far from the fitted model (a spike, a glitch, a known load stated for
    the wrong reading), from a log of single readings.

    Each reading's residual, every channel scaled by its fitted noise, gives ``d``, its sum of
    squares: chi-square with ``p - (r - 1)`` degrees of freedom at an unknown pose of the stated
    magnitude (its direction takes up ``r - 1``; ``p - r`` where the magnitude is fitted). A
    known reading's is taken as the same: the few known readings pin the fit's rotation, so the
    fit takes up as much of theirs (measured on clean payload rigs, the mean ``d`` at the known
    readings: 6.17 with 8 channels, 8.99 with 12; at the unknown ones 5.86 and 9.73, of 6 and 10
    degrees of freedom; with ``p`` degrees of freedom a known reading's test missed more). A
    spike inflates the fitted noise it is scaled by, so ``d`` is first divided by the unknown
    poses' median of it over the chi-square's median (a robust scale, 1 under the model). A
    reading is flagged where its tail probability is below ``alpha / P``. Units, channel order
    and offsets do not change it. Returns ``{"poses", "p_values", "scale", "min_p_value"}``
    (the flagged poses' indices into ``pr.Y``, their tail probabilities, the robust scale, and
    the smallest tail probability of all), or None with fewer than 10 unknown poses."""
    from scipy.stats import chi2

    un = pr.unknown
    if len(un) < 10:
        return None
    E = ((pr.Y - fit["M"] @ fit["A"].T - fit["o"]) * np.sqrt(pr.counts)[:, None]
         / np.sqrt(fit["v"]))
    if not np.all(np.isfinite(E)):
        return None
    d = np.sum(E**2, axis=1)
    df = float(pr.p - pr.r if pr.fit_g else pr.p - pr.r + 1)
    scale = float(np.median(d[un]) / chi2.median(df))
    if not scale > 0:
        return None
    pv = chi2.sf(d / scale, df)
    out = np.flatnonzero(pv < alpha / pr.P)
    return {"poses": out, "p_values": pv[out], "scale": scale, "min_p_value": float(pv.min())}


def direction_misfit(pr: Problem, fit: dict, permutations: int = DIRECTION_PERMUTATIONS,
                     seed: int = 0) -> dict | None:
    """Whether a fit's residuals are a smooth function of the load's direction (a sensor that
    is not linear in the load: a gauge's nonlinearity, cross-talk) rather than noise, from a log
    of single readings.

    Noise at one reading is independent of the next; a misfit that depends on the load's
    direction is nearly the same at nearby directions. Each unknown pose's residual (every
    channel scaled by its fitted noise) is paired with the pose nearest to it in fitted
    direction, and ``rho``, the sum of the pairs' products over the sum of squares (about the
    misfit's share of the residual variance), is tested against the same statistic with the
    pairs drawn at random (``permutations`` of them; one-sided p-value, ``(1 + #null >= rho) /
    (1 + permutations)``). The fitted directions make neighbouring residuals slightly
    anti-correlated under noise alone, so the permutation null is conservative.

    A log whose readings follow a path has neighbours in direction that are neighbours in time
    too, where noise correlated in time (a slow wander, drift) would read as misfit. So pairs
    closer in the log than ``window`` readings are not paired, ``window`` the first lag at which
    the residuals' autocorrelation (averaged over the channels) falls inside its 95 % band under
    independence, ``2 / sqrt(n)``, and the null's random pairs are drawn as far apart in the log
    as the neighbours are (the neighbours' lags shuffled among the readings): what noise
    correlated in time adds to ``rho`` it adds to the null alike. (With the window alone,
    AR(0.9) sweeps of 1,000 training readings were found nonlinear on 3 of 4; with the matched
    null on none, and an AR(0.99) sweep still on 1 of 4: where the noise is that slow the
    caller does not use the test, :func:`calib.routes.forward_rows.fit_forward_rows`.) Long logs
    are tested on their :data:`SEARCH_POSES` evenly strided unknown poses (in the log's order).

    Measured (docs/calib.md, "Gauges that are not linear"): on payload rigs whose
    gauges are 2 % nonlinear p < 0.01 on 8 of 10, at 5 % on 10 of 10; on 40 rigs with linear
    gauges (independent or gauge-mixed noise, 6 or 8 or 12 channels) p >= 0.18; on the real
    wrist sensor (42 fits) p >= 0.10. Units, channel order and offsets do not change it
    (residuals scaled by their channel's noise). Returns ``{"rho", "p_value", "pairs",
    "window", "median_angle_deg"}``, or None with fewer than 10 unknown poses."""
    un = pr.unknown
    if len(un) > SEARCH_POSES:
        un = un[_search_pick(len(un))]
    n = len(un)
    if n < 10:
        return None
    E = ((pr.Y[un] - fit["M"][un] @ fit["A"].T - fit["o"]) * np.sqrt(pr.counts[un])[:, None]
         / np.sqrt(fit["v"]))
    if not np.all(np.isfinite(E)):
        return None
    U = _unit(fit["M"][un])
    # the window: the first lag whose channel-averaged autocorrelation is insignificant
    Ec = E - E.mean(axis=0)
    g0 = np.maximum(np.sum(Ec * Ec, axis=0), 1e-300)
    band = 2.0 / np.sqrt(n)
    window = n // 4
    for lag in range(1, n // 4):
        if float(np.mean(np.sum(Ec[lag:] * Ec[:-lag], axis=0) / g0)) < band:
            window = lag
            break
    G = U @ U.T
    idx = np.arange(n)
    G[np.abs(idx[:, None] - idx[None, :]) < window] = -np.inf  # itself and its time neighbours
    k = np.argmax(G, axis=1)
    ok = np.isfinite(G[idx, k])
    if ok.sum() < 10:
        return None
    i, k = idx[ok], k[ok]
    den = float(np.sum(E[i] ** 2))
    if not den > 0:
        return None
    rho = float(np.sum(E[i] * E[k])) / den
    rng = np.random.default_rng(seed)
    lags = np.abs(k - i)
    hits = 0
    for _ in range(permutations):
        # the null's pairs are as far apart in the log as the neighbours are (their lags
        # shuffled), in a random direction: noise correlated in time weighs on both alike
        lag = rng.permutation(lags)
        up = i + lag
        down = i - lag
        pick_up = (rng.random(len(i)) < 0.5) & (up < n) | (down < 0)
        kk = np.where(pick_up, up, down)
        kk = np.clip(kk, 0, n - 1)
        hits += float(np.sum(E[i] * E[kk])) / den >= rho
    ang = np.degrees(np.arccos(np.clip(np.sum(U[i] * U[k], axis=1), -1.0, 1.0)))
    return {"rho": rho, "p_value": (1.0 + hits) / (1.0 + permutations), "pairs": int(len(i)),
            "window": int(window), "median_angle_deg": float(np.median(ang))}
