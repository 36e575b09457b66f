"""Calibration models beyond affine, for least squares and the rig fit's second stage, chosen by
held-out error (never by training error, which always prefers the larger model).

- ``affine``: ``m = C (z - offset)``, paper eqs. 2-3;
- ``channel``: every channel first straightened by its own square, ``s_c = z_c - b_c q_c`` with
  ``q_c = ((z_c - centre_c) / scale_c)^2``, then affine: a sensor whose channels each bend with
  their own signal (printed flexures, optical or capacitive gaps). The p gains ``b_c`` are fitted
  in the forward direction, ``z_c = a_c . m + o_c + b_c q_c`` per channel (r + 2 coefficients
  from every pose), so it needs only ``p + 2`` poses; stored as the quadratic terms below with
  ``Q = -C diag(b)``. On a real printed 8-channel sensor it cut least squares' held-out error to
  0.5-0.9x on four load sets of five (1.16x on the fifth; docs/calib.md);
- ``quadratic``: plus a square of every channel, ``Q ((z - centre) / scale)^2``: a sensor whose
  channels bend (strain gauges at large strain, printed flexures). It adds p columns per load
  component, so the poses must outnumber ``2 p + 1`` (a rig of 12 poses with 8 channels cannot
  identify it: :func:`identifiable` says so and ``auto`` skips it);
- ``drift linear``: a load-space term linear in the row's position in the log, fitted beside C
  so that a slow drift does not bias C, then dropped (its mean stays in the offset): new data
  have no position in the calibration log.

:func:`choose` runs the candidates' leave-one-pose-out error and keeps the best.
"""

from __future__ import annotations

import numpy as np

from calib.data.result import Calibration, CalibrationError

#: Decision: docs/calib_design.md D8.
MODELS = ("affine", "channel", "quadratic")
#: Decision: docs/calib_design.md D9.
DRIFTS = ("none", "linear")


def columns(p: int, model: str, drift: str) -> int:
    """Pose-level columns of the design (intercept included); drift varies within poses too."""
    return p + 1 + (p if model == "quadratic" else 0)


def identifiable(n_poses: int, p: int, model: str, drift: str, r: int = 3) -> bool:
    """Enough distinct poses for the model, with one to spare (``channel``: also for each
    channel's forward fit on ``r + 2`` columns)."""
    need = columns(p, model, drift) + 1
    if model == "channel":
        need = max(need, r + 3)
    return n_poses >= need


def channel_bends(Z, M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``channel`` model's straightening: per channel, least squares of ``z_c`` on ``[m, 1,
    q_c]`` over the rows (``q_c = ((z_c - centre_c) / scale_c)^2``); returns (b, centre, scale).
    A channel whose square the loads already explain (a rank-deficient design) gets b_c = 0."""
    Z = np.asarray(Z, float)
    M = np.atleast_2d(np.asarray(M, float))
    center = Z.mean(axis=0)
    scale = np.maximum(Z.std(axis=0), 1e-300)
    q = ((Z - center) / scale) ** 2
    X = np.column_stack([M - M.mean(axis=0), np.ones(len(Z))])
    b = np.zeros(Z.shape[1])
    for c in range(Z.shape[1]):
        Xc = np.column_stack([X, q[:, c] - q[:, c].mean()])
        coef, _, rank, _ = np.linalg.lstsq(Xc, Z[:, c], rcond=None)
        if rank == Xc.shape[1]:
            b[c] = coef[-1]
    return b, center, scale


def fit_model(Z, M, model: str = "affine", drift: str = "none", t=None) -> Calibration:
    """Least squares of loads ``M`` (n, dof) on readings ``Z`` (n, p) under ``model`` and
    ``drift``; ``t`` (n,) each row's position in the log (default the row order, 0..1).

    ``affine`` without drift is :func:`calib.estimators.least_squares.fit_least_squares` with a
    bias. Diagnostics: ``model``, ``drift``, ``drift_per_log`` (dof,: the load change over the log),
    ``residual_rms``, ``n_samples``, ``singular_values`` of the centred design.
    """
    from calib.estimators.least_squares import fit_least_squares

    if model not in MODELS or drift not in DRIFTS:
        raise CalibrationError(f"model must be one of {MODELS} and drift one of {DRIFTS}, got "
                               f"{model!r}, {drift!r}")
    Z = np.asarray(Z, float)
    M = np.atleast_2d(np.asarray(M, float))
    if model == "affine" and drift == "none":
        cal = fit_least_squares(Z, M, bias=True)
        cal.diagnostics.update(model="affine", drift="none")
        return cal
    n, p = Z.shape
    if t is None:
        t = np.linspace(0.0, 1.0, n)
    t = np.asarray(t, float).reshape(n)
    bends = None
    if model == "channel":
        bends, center, scale = channel_bends(Z, M)
        Z = Z - bends * ((Z - center) / scale) ** 2
    zbar, mbar = Z.mean(axis=0), M.mean(axis=0)
    parts = [Z - zbar]
    if model != "channel":
        center = scale = None
    if model == "quadratic":
        center = zbar
        scale = np.maximum(Z.std(axis=0), 1e-300)
        q = ((Z - center) / scale) ** 2
        qbar = q.mean(axis=0)
        parts.append(q - qbar)
    if drift == "linear":
        parts.append((t - t.mean())[:, None])
    X = np.hstack(parts)
    coef, _, rank, sv = np.linalg.lstsq(X, M - mbar, rcond=None)
    if rank < X.shape[1]:
        raise CalibrationError(f"the {model} model{' with drift' if drift != 'none' else ''} is "
                               f"not identified by these data (design rank {rank} of "
                               f"{X.shape[1]})")
    C = coef[:p].T
    d = mbar - C @ zbar
    Q = None
    if model == "quadratic":
        Q = coef[p:2 * p].T
        d = d - Q @ qbar
    elif model == "channel":
        Q = -C * bends
    offset = -np.linalg.pinv(C) @ d
    res = M - mbar - X @ coef
    diag = {
        "n_samples": n,
        "singular_values": sv,
        "residual_rms": float(np.sqrt(np.mean(res**2))),
        "model": model,
        "drift": drift,
        "drift_per_log": coef[-1] if drift == "linear" else np.zeros(M.shape[1]),
    }
    if model == "channel":
        diag["channel_bends"] = bends
    return Calibration(C=C, offset=offset, dof=M.shape[1], method="least_squares",
                       diagnostics=diag, quadratic=Q, quadratic_center=center,
                       quadratic_scale=scale)


def candidates(n_poses: int, p: int, model: str, drift: str) -> list[tuple[str, str]]:
    """The (model, drift) pairs ``auto`` compares (the identifiable ones)."""
    ms = MODELS if model == "auto" else (model,)
    ds = DRIFTS if drift == "auto" else (drift,)
    return [(m, d) for m in ms for d in ds if identifiable(n_poses, p, m, d)]


def choose(cv_of, n_poses: int, p: int, model: str, drift: str) -> tuple[str, str, dict]:
    """Resolve ``auto`` model/drift: ``cv_of(model, drift)`` returns a leave-one-pose-out
    result (dict with ``rms``); the pair with the lowest rms wins. Returns (model, drift,
    table) with every candidate's rms and the identifiability of the skipped ones.

    Keeping the simplest model unless another beat it by one paired standard error (the
    one-standard-error rule) was tried: on simulated rigs with 1 % nonlinearity and drift it was
    worse on 16 of 60 rigs and better on 2 (3.3 +- 1.0 % more held-out error: it turned down the
    channel model the simulated nonlinearity calls for), on a real printed sensor better on 2
    load-set splits and worse on 1."""
    if model != "auto" and drift != "auto":
        if not identifiable(n_poses, p, model, drift):
            raise CalibrationError(
                f"the {model} model needs at least {columns(p, model, drift) + 1} poses with "
                f"{p} channels; the log has {n_poses}")
        return model, drift, {}
    cands = candidates(n_poses, p, model, drift)
    if not cands:
        need = min(columns(p, m, "none") for m in (MODELS if model == "auto" else (model,))) + 1
        raise CalibrationError(f"the {model} model needs at least {need} poses with {p} "
                               f"channels; the log has {n_poses}")
    table = {}
    for m, d in cands:
        cv = cv_of(m, d)
        table[f"{m}/{d}"] = cv["rms"] if cv["folds"] else float("inf")
    best = min(cands, key=lambda c: table[f"{c[0]}/{c[1]}"])
    if not np.isfinite(table[f"{best[0]}/{best[1]}"]):
        best = cands[0]
    skipped = [f"{m}/{d}" for m in (MODELS if model == "auto" else (model,))
               for d in (DRIFTS if drift == "auto" else (drift,)) if (m, d) not in cands]
    return best[0], best[1], {"leave_one_pose_out_rms": table, "chosen": f"{best[0]}/{best[1]}",
                              "not_identified": skipped}


def leave_one_pose_out_ls(Z, M, labels, model: str = "affine", drift: str = "none",
                          t=None) -> dict:
    """Leave-one-pose-out error of least squares (bias on; ``model``/``drift`` of
    :func:`calib.estimators.models.fit_model`, ``t`` each row's position in the log) on a
    static-pose log:
    each pose of ``labels`` (-1 rows unused) is left out in turn, the rest fitted, and the fit's
    mean load over the pose's rows compared with the pose's mean known load. Same keys as
    :func:`calib.routes.joint.leave_one_pose_out`."""
    Z = np.asarray(Z, float)
    M = np.asarray(M, float)
    labels = np.asarray(labels)
    t = np.linspace(0.0, 1.0, len(Z)) if t is None else np.asarray(t, float)
    errors = []
    for j in np.unique(labels[labels >= 0]):
        hold = labels == j
        keep = ~hold & (labels >= 0)
        try:
            cal = fit_model(Z[keep], M[keep], model, drift, t[keep])
        except CalibrationError:
            errors.append(None)
            continue
        errors.append(cal.apply(Z[hold]).mean(axis=0) - M[hold].mean(axis=0))
    return summarise_folds(errors, M.shape[1])


def summarise_folds(errors, r: int) -> dict:
    """A leave-one-pose-out result from per-fold load errors (None: the fold's fit failed):
    ``folds``, ``failed_folds``, ``rms``, ``rms_per_axis`` and ``errors`` (good folds x r)."""
    good = [e for e in errors if e is not None]
    E = np.array(good, float).reshape(-1, r)
    return {
        "folds": len(E),
        "failed_folds": len(errors) - len(good),
        "rms": float(np.sqrt(np.mean(E**2))) if len(E) else float("nan"),
        "rms_per_axis": np.sqrt(np.mean(E**2, axis=0)) if len(E) else np.full(r, np.nan),
        "errors": E,
    }
