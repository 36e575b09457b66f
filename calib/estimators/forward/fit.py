"""The forward fit by maximum likelihood (:func:`fit_forward`): starts, alternation, LM and the
feasible-GLS rounds; the lowest cost under the final weights wins.
"""

from __future__ import annotations

import numpy as np

from calib.data.result import CalibrationError
from calib.estimators.forward.lockstep import Batch, alternate_batch, solve_batch
from calib.estimators.forward.problem import (
    SEARCH_POSES,
    Problem,
    _search_pick,
    alternate,
    cost,
    curvature,
    linear_fit,
    reinfer,
    solve,
)
from calib.estimators.forward.variances import _feasible_gls, estimate_variances, start_variances

#: Starts with every unknown direction drawn uniformly, alternated; the best distinct ones are
#: refined by LM.
#: Decision: docs/calib_design.md D36.
RANDOM_STARTS = 8


def _directions(L):
    L = np.asarray(L, float)
    n = np.linalg.norm(L, axis=1)
    if not np.all(np.isfinite(L)) or np.any(n <= 0):
        return None
    return L / n[:, None]


def _solve_starts(pr: Problem, starts: list, W) -> list:
    """:func:`solve` of every start (dicts with ``U``, ``g``, ``start``) under the weights
    ``W`` from the linear fit at its directions, in lockstep (:func:`~.lockstep.solve_batch`):
    :func:`solve`'s dicts with the start's name, in order. Raises where any solve would."""
    if not starts:
        return []
    U = np.array([f["U"] for f in starts], float)
    U /= np.linalg.norm(U, axis=2, keepdims=True)
    g = np.array([float(pr.magnitude if not pr.fit_g else f["g"]) for f in starts])
    Ao = [linear_fit(pr, pr.loads(Ui, gi), W) for Ui, gi in zip(U, g, strict=True)]
    b = len(starts)
    out = solve_batch(Batch(pr, np.broadcast_to(pr.Y, (b, *pr.Y.shape))), U, g,
                      np.broadcast_to(W, (b, *W.shape)), np.array([a for a, _ in Ao]),
                      np.array([o for _, o in Ao]))
    return [{"A": out["A"][i], "o": out["o"][i], "g": float(out["g"][i]), "U": out["U"][i],
             "M": out["M"][i], "cost": float(out["cost"][i]),
             "converged": bool(out["converged"][i]),
             "iterations": int(out["iterations"][i]), "W": W, "start": f["start"]}
            for i, f in enumerate(starts)]


def _refit_starts(pr: Problem, starts: list, W) -> list:
    """Every start's fit solved again from its directions under the weights ``W``
    (:func:`_solve_starts`); one by one where that fails, a start whose solve fails left
    out."""
    try:
        return _solve_starts(pr, starts, W)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        pass
    refit = []
    for f in starts:
        try:
            refit.append({**solve(pr, f["U"], f["g"], W), "start": f["start"]})
        except (np.linalg.LinAlgError, ValueError):
            continue
    return refit


def fit_forward(pr: Problem, start_loads: dict | None = None, seed: int = 0,
                random_starts: int = RANDOM_STARTS, restarts: int = 2,
                only: dict | None = None, v0: np.ndarray | None = None) -> dict:
    """The maximum-likelihood forward fit of a rig (module docstring).

    ``start_loads``: named (P, r) arrays of every pose's load as another route estimates them
    (the closed-form routes' calibrations applied to the pose means); their directions at the
    unknown poses start the search. ``only``: named unit directions (nu, r) that are the *only*
    starts (the oracle: the true directions). ``v0``: channel variances to start the
    feasible-GLS rounds from (default: weights that favour no channel). Returns the final fit
    (:func:`solve`'s dict) plus ``v`` (pose-level variance per channel), ``W``, ``starts``
    (every start: name, cost under the final weights, converged, iterations),
    ``chosen_start``, ``rounds`` (feasible-GLS rounds), ``g0``, ``v0`` (as given: the rounds'
    start, which :func:`reweighting_dof` repeats).
    """
    rng = np.random.default_rng(seed)
    known_mag = np.linalg.norm(pr.known_M, axis=1)
    g0 = pr.magnitude if pr.magnitude is not None else float(np.median(known_mag))
    nu = len(pr.unknown)
    if nu == 0:
        raise CalibrationError("every pose has a known load: use least squares")
    # the search runs on at most SEARCH_POSES unknown poses (evenly strided)
    if nu > SEARCH_POSES:
        pick = _search_pick(nu)
        sp = pr.sub(pr.unknown[pick])
    else:
        pick, sp = np.arange(nu), pr
    # start weights that favour no channel (and are equivariant): each channel's variance left
    # after regressing it on the others (start_variances), else its spread
    psi = start_variances(pr) if v0 is None else None
    W0 = (sp.weights(np.asarray(v0, float)) if v0 is not None
          else np.broadcast_to(1.0 / np.sqrt(psi) if psi is not None else 1.0 / pr.spread,
                               (sp.P, sp.p)).copy())
    named = []
    if only is not None:
        for name, U in only.items():
            named.append((name, np.asarray(U, float)[pick]))
    else:
        # 1. the affine map of the known poses (r + 1 spanning loads), extended by |m| = g
        X = np.column_stack([pr.known_M, np.ones(len(pr.known))])
        if len(X) >= pr.r + 1 and np.linalg.matrix_rank(X) == pr.r + 1:
            Bk = np.linalg.lstsq(X, pr.Y[pr.known], rcond=None)[0]
            A, o = Bk[: pr.r].T, Bk[pr.r]
            Ws = W0[0]
            Aw = A * Ws[:, None]
            got = _directions(((sp.Y[sp.unknown] - o) * Ws) @ np.linalg.pinv(Aw).T)
            if got is not None:
                named.append(("affine map of the known poses", got))
        for name, L in (start_loads or {}).items():
            got = _directions(np.asarray(L, float)[pr.unknown][pick])
            if got is not None:
                named.append((name, got))
    results = []

    def run(name, U, W, alt=True):
        out = []
        try:
            f = solve(sp, U, g0, W)
            out.append({**f, "start": name})
            if alt:
                Ua = alternate(sp, U, g0, W)
                if not np.allclose(Ua, U):
                    f = solve(sp, Ua, g0, W)
                    out.append({**f, "start": f"{name}, alternated"})
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            pass
        return out

    def run_many(starts, W, alt=True):
        """:func:`run` of every ``(name, U)`` at once, in the same order: the alternations in
        lockstep (:func:`~.lockstep.alternate_batch`), every solve in one batch; one by one
        where that fails."""
        if not starts:
            return []
        try:
            Ua = alternate_batch(sp, np.array([U for _, U in starts], float), g0, W) if alt \
                else None
            todo = []
            for i, (name, U) in enumerate(starts):
                todo.append({"U": U, "g": g0, "start": name})
                if alt and not np.allclose(Ua[i], U):
                    todo.append({"U": Ua[i], "g": g0, "start": f"{name}, alternated"})
            return _solve_starts(sp, todo, W)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            return [f for name, U in starts for f in run(name, U, W, alt)]

    results += run_many(named, W0)
    if only is None:
        pool = []
        Us = []
        for _ in range(random_starts):
            U = rng.standard_normal((len(sp.unknown), sp.r))
            Us.append(U / np.linalg.norm(U, axis=1, keepdims=True))
        try:  # every random start alternated at once; one by one where that fails
            alts = list(alternate_batch(sp, np.array(Us), g0, W0)) if Us else []
        except (np.linalg.LinAlgError, ValueError):
            alts = []
            for U in Us:
                try:
                    alts.append(alternate(sp, U, g0, W0))
                except (np.linalg.LinAlgError, ValueError):
                    alts.append(None)
        for i, Ua in enumerate(alts):
            if Ua is None:
                continue
            A, o = linear_fit(sp, sp.loads(Ua, g0), W0)
            pool.append((cost(sp, A, o, sp.loads(Ua, g0), W0), i, Ua))
        results += run_many([(f"random directions {i + 1}, alternated", Ua)
                             for _, i, Ua in sorted(pool, key=lambda t: t[:2])[:2]], W0, alt=False)
    if not results:
        raise CalibrationError("no start of the forward fit gave finite directions")
    best = min(results, key=lambda f: f["cost"])
    if only is None:
        # every unknown direction turned by about 20 degrees
        results += run_many([(f"perturbed restart {i + 1}",
                              best["U"] + rng.normal(scale=0.35, size=best["U"].shape))
                             for i in range(restarts)], W0)
        best = min(results, key=lambda f: f["cost"])
    # feasible GLS on the search subset: rounds from the best start until the variances settle
    # (variances from its residuals, refit); then every start refitted under those final
    # weights and the lowest cost kept: the returned fit is the best of all starts under one
    # objective
    best, v, rounds = _feasible_gls(sp, best, v0)
    Wf = sp.weights(v)
    others = [f for f in results if f["start"] != best["start"]]
    results = [best] + _refit_starts(sp, others, Wf)
    best = min(results, key=lambda f: f["cost"])
    # every pose: the search subset's model placed on the other poses by the global step, then
    # refined together, the variances re-estimated once on every pose (settled on the subset's
    # hundreds of poses; a sweep's tens of thousands would only refine them, at a full solve
    # per round)
    if sp is not pr:
        W = pr.weights(v)
        U = reinfer(pr, best["A"], best["o"], best["g"], W)
        U[pick] = best["U"]
        best = {**solve(pr, U, best["g"], W, best["A"], best["o"]), "start": best["start"]}
        v = estimate_variances(pr, best)
        best = {**solve(pr, best["U"], best["g"], pr.weights(v), best["A"], best["o"]),
                "start": best["start"]}
        rounds += 1
    starts = [{"start": f["start"], "cost": f["cost"], "converged": f["converged"],
               "iterations": f["iterations"]} for f in results]
    return {**best, **curvature(pr, best), "v": v, "starts": starts,
            "chosen_start": best["start"], "rounds": rounds, "g0": g0, "v0": v0}
