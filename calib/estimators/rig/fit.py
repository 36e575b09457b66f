"""The static-pose rig fit (:func:`fit_rig`): the loads of the poses (:func:`rig_pose_loads`),
then least squares on every row with its pose's load (:func:`rig_calibration`).
See :mod:`calib.estimators.rig`.
"""

from __future__ import annotations

import numpy as np

from calib.data.result import Calibration, CalibrationError
from calib.data.validate import check_matrix
from calib.estimators.forward.fit import fit_forward
from calib.estimators.forward.problem import Problem
from calib.estimators.rig.model import DISTINCT_DEG, ForwardModel, IndexModel, PoseData

#: The forward model gets a bending term per channel when an F-test gives p below this.
#: Decision: docs/calib_design.md D30.
BEND_P = 0.01


#: The index refinement (:class:`IndexModel`): polynomial degrees up to 1 + this are tried
#: per channel, each kept when an F-test against the lower one gives p below :data:`BEND_P` and
#: its leave-one-pose-out error is lower.
#: Decision: docs/calib_design.md D30.
INDEX_DEGREE = 2


#: Known loads whose magnitudes are within this relative spread are one weighed mass: the index
#: refinement holds every pose's load at their magnitude (and :mod:`calib.verdict.reliability`
#: checks the fitted magnitude against it).
#: Decision: docs/calib_design.md D29.
SAME_MAGNITUDE = 0.05


#: Rounds of feasible GLS reweighting of the index refinement (channel weights from the
#: highest-degree fit's own residuals).
#: Decision: docs/calib_design.md D30.
INDEX_REWEIGHT = 2


#: Rig fits: known loads further than this fraction of the load from a rotation of what the
#: readings alone imply are inconsistent (simulated imperfect rigs: up to 12 % with 5 % creep
#: and 3 % hysteresis, at most 3.4 % otherwise; two swapped known loads: median 17 %); such a
#: fit is refused (:mod:`calib.verdict.reliability`) and chooses no model by held-out error.
#: Decision: docs/calib_design.md D71.
KNOWN_INCONSISTENT = 0.15


#: Starts of the bent forward model (:class:`ForwardModel` with ``bend``) with every unknown
#: direction drawn uniformly on the sphere, besides the affine fit's directions: each is
#: alternated to a pose-by-pose optimum (cheap), and the :data:`RANDOM_REFINED` best distinct
#: ones are refined jointly by LM.
#: Decision: docs/calib_design.md D31.
BENT_RANDOM_STARTS = 12


#: 6: with 2 the bent search of a simulated rig at 15 % nonlinearity (seed 14, the known loads on
#: the first 4 poses) stopped at 3.8x the cost the true directions lead to once the affine stage
#: was :func:`calib.estimators.forward.fit.fit_forward`; with 4, after the static rigs' variances
#: were moderated
#: across channels (:func:`calib.estimators.forward.variances.moderate_variances`), it stopped at
#: 7.7x there (1 of 80
#: simulated rigs at 5 and 15 % nonlinearity, seeds 10-49); with 6 every one of the 80 reaches
#: the cost of the true directions (with :data:`RANDOM_NFEV`, as fast as 4 were without it).
#: Decision: docs/calib_design.md D31.
RANDOM_REFINED = 6


#: Levenberg-Marquardt iterations a random start of the bent model is refined for (the named
#: starts get 400). Every converged refinement of the simulated target-case rigs took at most 22;
#: a start far from any basin (its cost hundreds of times the best) could run the 400, 4 s each
#: on a 12-pose rig, which took one rig's fit from 3 to 11 s. The cheapest refinement, if its
#: budget ran out, is finished from where it stopped.
#: Decision: docs/calib_design.md D31.
RANDOM_NFEV = 50


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
                   random_starts: int = BENT_RANDOM_STARTS) -> dict:
    """The pose-level joint fit (module docstring): forward model for the unknown pose loads,
    then least squares on every row with its pose's load.

    ``labels``: the pose of every row (:func:`find_poses`; -1 rows are left out). ``starts``:
    extra named calibrations (objects with ``apply``) whose loads at the pose means start the
    directions. ``known_sigma`` (stated accuracy of the known loads) is recorded for the
    reliability checks; the fit itself treats known loads as exact and weighs pose means by
    their scatter (``known_samples`` only weighs known readings that match no pose).
    Returns the stage-1 state for :func:`rig_calibration` (``model``/``drift``: the second
    stage's model, :func:`calib.estimators.models.fit_model`; ``t`` each row's position in the log,
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
    # the affine forward model: calib.estimators.forward's maximum-likelihood fit on the pose means
    # (its own starts, the closed-form routes among them, and settled channel variances), the same
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
    from calib.estimators.models import fit_model

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
