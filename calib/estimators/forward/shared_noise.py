"""Noise shared by the channels: the residuals' covariance within the model's range and its
complement, the range level, and the attenuation of the loads it causes.
"""

from __future__ import annotations

import numpy as np

from calib.estimators.forward.problem import SEARCH_POSES, Problem, _unit, tangents


def _range_and_complement(pr: Problem, fit: dict):
    """A fit's residuals, in channels scaled by its noise (``sd``), as ``A_s eta + N xi``:
    ``eta`` (P, r) in load units along the span of ``A_s = A / sd``, ``xi`` (P, p - r) along an
    orthonormal basis ``N`` of its complement. Returns ``(Bm, eta, xi, sd, G0)`` with ``Bm =
    [A_s N]`` and ``G0 = (A_s^T A_s)^-1`` (the covariance of ``eta`` were the scaled noise
    white)."""
    r = pr.r
    sd = np.sqrt(fit["v"])
    As = fit["A"] / sd[:, None]
    E = (pr.Y - fit["M"] @ fit["A"].T - fit["o"]) * np.sqrt(pr.counts)[:, None] / sd
    Q, _ = np.linalg.qr(As, mode="complete")
    Bm = np.column_stack([As, Q[:, r:]])
    coef = np.linalg.solve(Bm, E.T).T
    return Bm, coef[:, :r], coef[:, r:], sd, np.linalg.inv(As.T @ As)


def _shared_noise(pr: Problem, fit: dict) -> dict | None:
    """How much of the noise along the span of ``A`` the noise outside it predicts, and the
    channels' noise covariance that follows.

    In channels scaled by the fit's noise the residual is ``A_s eta + N xi``
    (:func:`_range_and_complement`). ``xi`` is seen whole at every pose. ``eta`` is not: a
    pose's fitted direction takes up its two tangent components, and what is left is its
    radial part ``u^T eta`` (exactly, to first order, whatever the weights), at a known pose
    all of it. Independent channel noise makes ``eta`` and ``xi`` independent; noise the
    channels share (a wrench mixed from gauges) makes ``eta = Gamma xi + eps``. ``Gamma`` (r, p
    - r) is the least-squares regression of the radial parts on ``u (x) xi`` (a known pose's
    three components on ``I (x) xi``), each row weighted by its variance under independence
    (``u^T G0 u``). Its Wald statistic ``W`` on ``m = r (p - r)`` coefficients tests ``Gamma =
    0`` (``W / m ~ F(m, n - m)``, ``n`` the rows), and ``Gamma`` is shrunk by the positive-part
    James-Stein factor ``1 - (m - 2) (n - m) / ((n - m + 2) W)`` (``m >= 3``; a weak estimate
    is pulled toward independence by as much as it is noise, a strong one is kept). Why not the
    full covariance: its part inside the span is seen one radial component per pose, and a free
    direction per pose makes its likelihood unbounded (docs/calib.md); the calibration needs
    only ``Gamma`` and the covariance of ``xi``, the rest (``eps``'s covariance, taken as the
    radial residuals' variance ``c`` times ``G0``) only weighs the directions. ``c``'s degrees
    of freedom: the rows less the regression's ``m`` and the ``r (r + 1)`` that the fitted ``A``
    and ``o`` take from the range (one more with a fitted magnitude; exact to first order,
    whatever the weights and poses: with ``P / (P - r - 1)``, as for ``xi``, ``c`` came out
    0.77x its truth at 40 poses).

    Returns ``{"p_value", "wald", "m", "shrink", "gamma", "gamma_ls", "gamma_cov", "S",
    "parts", "rows"}`` (``gamma_ls`` the unshrunk estimate, ``gamma_cov`` its covariance
    (row-major ``vec``, at the rows' variance ``c``), ``S`` the covariance in ``pr``'s channels,
    ``rows`` what :func:`_radial_share` needs), None
    when there is nothing to test (``p <= r``, or fewer rows than coefficients)."""
    r, p = pr.r, pr.p
    if p <= r:
        return None
    Bm, eta, xi, sd, G0 = _range_and_complement(pr, fit)
    P = pr.P
    dofc = P / max(P - r - 1, 1)  # (A and o took r + 1 degrees of freedom per channel)
    Cxi = xi.T @ xi / P * dofc
    known = np.zeros(P, bool)
    known[pr.known] = True
    U = _unit(fit["M"])
    iu = ~known
    wu = 1.0 / np.sqrt(np.einsum("ja,ab,jb->j", U[iu], G0, U[iu]))
    X = [np.einsum("ja,jb->jab", U[iu], xi[iu]).reshape(-1, r * (p - r)) * wu[:, None]]
    y = [np.sum(U[iu] * eta[iu], axis=1) * wu]
    As = Bm[:, :r]
    L = np.linalg.cholesky(As.T @ As)  # L^T G0 L = I (G0 = (A_s^T A_s)^-1)
    if known.any():  # every component, rotated to unit variance under independence
        X.append(np.einsum("ab,jc->jbac", L, xi[known]).reshape(-1, r * (p - r)))
        y.append((eta[known] @ L).ravel())
    X, y = np.vstack(X), np.concatenate(y)
    n, m = X.shape
    if n <= m + 2 or not np.all(np.isfinite(X)) or not np.all(np.isfinite(y)):
        return None
    XtX = X.T @ X
    try:
        g = np.linalg.solve(XtX, X.T @ y)
        XtX_inv = np.linalg.inv(XtX)
    except np.linalg.LinAlgError:
        return None
    res = y - X @ g
    s2 = float(res @ res) / (n - m)
    # the range's own variance: the rows' residual degrees of freedom are n - m less the
    # r (r + 1) that the fitted A and o take from the range (its part of every channel's
    # coefficients; the magnitude one more where fitted: exact to first order, whatever the
    # weights and the poses)
    c = float(res @ res) / max(n - m - r * (r + 1) - (1 if pr.fit_g else 0), 1)
    if not s2 > 0:
        return None
    from scipy import stats

    wald = float(g @ XtX @ g) / s2
    shrink = (max(0.0, 1.0 - (m - 2) * (n - m) / ((n - m + 2) * wald)) if m >= 3 and wald > 0
              else 1.0)
    gamma = (shrink * g).reshape(r, p - r)
    parts = (Bm, sd, c, Cxi)
    return {"p_value": float(stats.f.sf(wald / m, m, n - m)), "wald": wald, "m": int(m),
            "shrink": float(shrink), "gamma": gamma, "gamma_ls": g.reshape(r, p - r),
            "gamma_cov": c * XtX_inv, "S": _shared_covariance(parts, gamma), "parts": parts,
            "rows": (U[iu], wu, L if known.any() else None, int(known.sum()), n),
            # the regression's residuals as seen in the range (coordinates where independent
            # noise is white): one component along a_j at each unknown pose, three at a known
            "radial": ((U[iu] @ np.linalg.inv(L).T) * wu[:, None], res[:int((~known).sum())],
                       res[int((~known).sum()):].reshape(-1, r), n,
                       m + r * (r + 1) + (1 if pr.fit_g else 0))}


def _shared_covariance(parts, gamma, K=None) -> np.ndarray:
    """The channels' covariance (in the fitted channels) that a shared part ``gamma`` (r, p - r)
    implies, from :func:`shared_noise`'s ``parts = (Bm, sd, c, Cxi)``: ``cov(eta) = c G0 + gamma
    Cxi gamma^T``, ``cov(eta, xi) = gamma Cxi``, ``cov(xi) = Cxi``. In the scaled channels that
    is ``c Qa Qa^T + (A_s gamma + N) Cxi (A_s gamma + N)^T`` (``Qa`` an orthonormal basis of
    ``A_s``'s span: ``A_s G0 A_s^T = Qa Qa^T`` without forming ``G0``, which an ill-conditioned
    ``A_s`` makes lose every digit). ``K``: the range's own covariance in place of ``c I`` (in
    the coordinates where independent noise is white; a draw of :func:`_range_draws`). Many
    draws at once: ``gamma`` (m, r, p - r) and ``K`` (m, r, r) give (m, p, p)."""
    Bm, sd, c, Cxi = parts
    r = gamma.shape[-2]
    As, N = Bm[:, :r], Bm[:, r:]
    if K is None:
        Qa, _ = np.linalg.qr(As)
        R = c * (Qa @ Qa.T)
    else:  # K in the coordinates eps' = L^T eps (L L^T = A_s^T A_s): A_s L^-T K L^-1 A_s^T
        B = np.linalg.solve(np.linalg.cholesky(As.T @ As), As.T).T  # orthonormal columns
        R = B @ K @ B.T
    Kx = As @ gamma + N
    S = (R + Kx @ Cxi @ np.swapaxes(Kx, -1, -2)) * np.outer(sd, sd)
    return 0.5 * (S + np.swapaxes(S, -1, -2))


#: At most this many entries (``(P p)^2``) in :func:`attenuation`'s dense hat matrix (128 MB).
#: Decision: docs/calib_design.md D47.
HAT_ENTRIES = 16_000_000


def _radial_share(sn: dict, delta):
    """The variance a shared part ``delta`` (r, p - r) left unexplained would add to
    :func:`shared_noise`'s regression rows, on average (``delta Cxi delta^T`` read as each
    row reads the range). It cannot exceed the rows' residual variance ``c``: draws of the
    shared part's error are held to it (:func:`predict_error`). Many draws at once: ``delta``
    (m, r, p - r) gives (m,)."""
    U, wu, L, n_known, n = sn["rows"]
    D = delta @ sn["parts"][3] @ np.swapaxes(delta, -1, -2)
    q = np.sum(D * ((U * (wu**2)[:, None]).T @ U), axis=(-2, -1))  # sum_j wu_j^2 u_j^T D u_j
    if L is not None:
        q = q + n_known * np.sum(D * (L @ L.T), axis=(-2, -1))  # trace(L^T D L)
    return q / n if np.ndim(q) else float(q / n)


def _projected_blocks(G4, H, F1, F2) -> np.ndarray:
    """Every pose's (p, p) block of ``R (I (x) S) R^T`` (``R = I - G`` the residual projection
    of the linearised fit, ``G4`` its hat matrix as (P, p, P, p), ``H`` the diagonal blocks) for
    a pose covariance ``S = F1 F2^T`` (symmetric)."""
    S = F1 @ F2.T
    HS = H @ S
    GF1 = np.einsum("jaib,bq->jaiq", G4, F1)
    GF2 = np.einsum("jaib,bq->jaiq", G4, F2) if F2 is not F1 else GF1
    return S[None] - HS - HS.transpose(0, 2, 1) + np.einsum("jaiq,jbiq->jab", GF1, GF2)


def _attenuation(pr: Problem, fit: dict, sn: dict | None = None) -> np.ndarray | None:
    """How much of a shared part the regression of :func:`shared_noise` recovers: ``Lambda``
    (m, m) with ``E[gamma_ls] = Lambda vec(delta)`` for residual noise whose shared part is
    ``delta`` (in the fit's scaled channels, to first order about ``delta = 0``).

    The fitted directions and ``A`` take up part of a shared disturbance: a direction fitted
    under per-channel weights leans toward it, and ``A`` with it, the same at every pose, so the
    regression sees less of it than there is (simulated on gauge-mixed wrench rigs: 0.55-0.6 of
    it; 0.95 with the true directions). Exact to first order: the fit's residuals are ``R e``
    with ``R`` the residual projection of its linearised weighted least squares (directions,
    ``A``, ``o`` and ``g`` together), so the regression's expected cross products are linear in
    the noise covariance, ``E[X^T y] = sum_j f_j(R_j S R_j^T)``, and ``Lambda = E[X^T X]^-1
    dE[X^T y] / d delta``. The rounds of :func:`fit_correlated` stop where the estimate is 0,
    so what is left of the shared part has the regression's error divided by ``Lambda``:
    :func:`predict_error` draws it so. Costs a dense hat matrix of the fit (``(P p)^2``
    entries): on at most :data:`SEARCH_POSES` unknown poses and :data:`HAT_ENTRIES` entries (an
    evenly strided subset beyond; fewer poses attenuate more, so the subset errs wide). None
    where there is nothing to test."""
    r, p = pr.r, pr.p
    nu = len(pr.unknown)
    most = max(min(SEARCH_POSES, int(np.sqrt(HAT_ENTRIES) / p) - len(pr.known)), 1)
    if nu > most:
        pick = np.unique(np.linspace(0, nu - 1, most).round().astype(int))
        rows = np.sort(np.r_[pr.known, pr.unknown[pick]])
        q = pr.sub(pr.unknown[pick])
        fit = {**fit, "W": fit["W"][rows], "M": fit["M"][rows], "U": fit["U"][pick]}
        pr, sn = q, None
    sn = sn if sn is not None else shared_noise(pr, fit)
    if sn is None:
        return None
    P = pr.P
    W, A, U, g = fit["W"], fit["A"], fit["U"], fit["g"]
    u = pr.unknown
    k = r - 1
    nt = p * (r + 1) + (1 if pr.fit_g else 0)
    X1 = np.column_stack([pr.loads(U, g), np.ones(P)])
    J = np.zeros((P, p, nt + len(u) * k))
    for c in range(p):
        J[:, c, c * (r + 1):(c + 1) * (r + 1)] = -W[:, c:c + 1] * X1
    Jphi = -(W[u] * g)[:, :, None] * np.einsum("jkr,cr->jck", tangents(U), A)
    for i, j in enumerate(u):
        J[j, :, nt + i * k: nt + (i + 1) * k] = Jphi[i]
    if pr.fit_g:
        J[u, :, nt - 1] = -W[u] * (U @ A.T)
    J = J.reshape(P * p, -1)
    if not np.all(np.isfinite(J)):
        return None
    Q, Rq = np.linalg.qr(J)
    keep = np.abs(np.diag(Rq)) > 1e-10 * np.abs(np.diag(Rq)).max()
    Q = Q[:, keep]
    G4 = (Q @ Q.T).reshape(P, p, P, p)
    H = np.einsum("jajb->jab", G4)
    Bm, _, c, Cxi = sn["parts"]
    As, N = Bm[:, :r], Bm[:, r:]
    Binv = np.linalg.inv(Bm)
    Pa, Pn = Binv[:r], Binv[r:]
    G0 = np.linalg.inv(As.T @ As)
    L = np.linalg.cholesky(np.linalg.inv(G0))
    known = np.zeros(P, bool)
    known[pr.known] = True
    iu = ~known
    Uu = _unit(fit["M"])[iu]
    wu2 = 1.0 / np.einsum("ja,ab,jb->j", Uu, G0, Uu)
    m = r * (p - r)
    # E[X^T X] at delta = 0: the pose covariance c Qa Qa^T + N Cxi N^T
    Qa, _ = np.linalg.qr(As)
    w, V = np.linalg.eigh(Cxi)
    F0 = np.column_stack([np.sqrt(c) * Qa, N @ (V * np.sqrt(np.clip(w, 0, None)))])
    Cr = _projected_blocks(G4, H, F0, F0)
    Cxx = np.einsum("ca,jab,eb->jce", Pn, Cr, Pn)
    EX = np.einsum("j,ja,jb,jce->acbe", wu2, Uu, Uu, Cxx[iu]).reshape(m, m)
    EX += np.einsum("ab,jce->acbe", L @ L.T, Cxx[known]).reshape(m, m)
    # dE[X^T y] / d delta_ab: the pose covariance's derivative A_s e_a (N Cxi e_b)^T + transpose
    NC = N @ Cxi
    D = np.empty((m, m))
    for a in range(r):
        for b in range(p - r):
            F1 = np.column_stack([As[:, a], NC[:, b]])
            F2 = np.column_stack([NC[:, b], As[:, a]])
            Cr = _projected_blocks(G4, H, F1, F2)
            Cxe = np.einsum("ca,jab,eb->jce", Pn, Cr, Pa)
            out = np.einsum("j,ja,jc->ac", wu2, Uu, np.einsum("jce,je->jc", Cxe[iu], Uu))
            out += np.einsum("ab,jce,eb->ac", L, Cxe[known], L)
            D[:, a * (p - r) + b] = out.ravel()
    try:
        lam = np.linalg.solve(EX, D)
    except np.linalg.LinAlgError:
        return None
    return lam if np.all(np.isfinite(lam)) else None


def shared_noise(pr: Problem, fit: dict) -> dict | None:
    """:func:`_shared_noise`, or None where its linear algebra fails (a singular or non-finite
    regression on a degenerate fit): the callers then treat the noise as independent, as they
    do where there is nothing to test, rather than stop."""
    try:
        with np.errstate(all="ignore"):
            sn = _shared_noise(pr, fit)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    if sn is None or not all(np.all(np.isfinite(sn[k])) for k in ("S", "gamma_cov")):
        return None
    return sn


#: :func:`range_level` needs at least this many degrees of freedom of the radial residuals.
#: Decision: docs/calib_design.md D60.
RANGE_LEVEL_MIN_DOF = 5


def range_level(pr: Problem, fit: dict) -> tuple[float, int] | None:
    """Where the channels' variances are not identified (Ledermann's bound, as
    :data:`UNIDENTIFIED_ROUNDS`: p <= 5 channels for 3 load components), the noise level along
    the span of ``A``, where the calibration's error lives, measured on the fit's radial
    residuals: ``(c, dof)``, ``c`` their variance over what the fitted variances predict for
    them (:func:`_shared_noise`'s ``c``, about 1 where they are right) on ``dof`` degrees of
    freedom; None where the variances are identified, or where there is nothing to measure.

    Why: with one complement dimension or two, the rounds settle each channel's variance where
    their start and the directions' give-and-take leave it, 0.4-38x its truth on 4-channel
    payload rigs, and the refits that measure the variances' spread start there too, so they
    do not see it (degrees of freedom up to 2e12). The radial residuals see the noise the
    calibration carries directly: one number per unknown pose, three per known one. On 30
    4-channel payload rigs (seeds 10,000-10,029) ``c`` correlated 0.70 in logs with
    the measured error's square over its prediction, and :func:`predict_error` drawing the
    level from it (a scaled inverse chi-square) held the measured error in its 95 % interval
    on 29 of 30 (24 of 30 without the level)."""
    if (pr.p - pr.r) ** 2 >= pr.p + pr.r:
        return None
    sn = shared_noise(pr, fit)
    if sn is None:
        return None
    c = float(sn["parts"][2])
    dof = int(sn["radial"][3] - sn["radial"][4])
    if not (np.isfinite(c) and c > 0) or dof < RANGE_LEVEL_MIN_DOF:
        return None
    return c, dof


def attenuation(pr: Problem, fit: dict, sn: dict | None = None) -> np.ndarray | None:
    """:func:`_attenuation`, or None where its linear algebra fails or gives a non-finite
    ``Lambda`` (:func:`predict_error` then draws the regression's error unattenuated)."""
    try:
        with np.errstate(all="ignore"):
            lam = _attenuation(pr, fit, sn)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    return lam if lam is not None and np.all(np.isfinite(lam)) else None
