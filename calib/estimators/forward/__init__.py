"""The forward model ``z = A m + o`` fitted by maximum likelihood, whatever the readings per pose.
Every rig, one statistical model: pose ``j`` is seen as the mean ``y_j`` of its ``n_j``
readings (``n_j = 1`` for one reading per pose, every reading its own pose for a slow
continuous sweep), its load ``m_j`` known (the known loads) or ``g u_j`` with ``u_j`` an unknown
unit direction and ``g`` the load magnitude (held at the known loads' when they are one mass,
or given). Each channel ``c`` has its own noise, so

    y_jc = a_c . m_j + o_c + e_jc,     var(e_jc) = v_c + s_c^2 / n_j,

with ``s_c`` the within-pose scatter (estimated from repeats, 0 when no pose repeats) and
``v_c`` each channel's pose-level variance (model misfit, and the whole reading noise when
poses do not repeat). For fixed variances the negative log-likelihood is the weighted sum of
squares ``sum_jc (y_jc - a_c . m_j - o_c)^2 / var_jc``; the variances are re-estimated from the
residuals, each divided by ``1 - h`` with ``h`` its own leverage (:func:`estimate_variances`),
in rounds of feasible generalised least squares until they settle (at most
:data:`MAX_REWEIGHT_ROUNDS`). Not to an exact fixed point: without repeated readings the
likelihood with a free variance per channel is unbounded (see :data:`REWEIGHT_TOL`).

The weighted least squares is solved by Levenberg-Marquardt on all parameters at once, the
directions eliminated pose by pose through the Schur complement (the bundle-adjustment trick: a
pose's 2 angles touch only its own readings), so a step costs ``O(P p^2 r^2)``: a 100,000-reading
sweep takes about 17 s. Starts (:func:`fit_forward`): the affine map of the known poses extended to
the others by the magnitude constraint, calibrations handed in (the closed-form routes), random
directions, each also *alternated* (the model refitted at the directions, then every unknown pose
moved to the best direction on its sphere, exactly: a global step per pose), and perturbed restarts
of the best; every start's cost under the final weights is reported, the lowest wins.

Everything here is equivariant to the channels' units, order and offsets: the start weights
are each channel's spread, the estimated variances scale with the channel, the model has a free
offset per channel.

The covariance of ``(A, o, g)`` with the directions as nuisance parameters is the inverse of the
Schur complement at the optimum (the Cramer-Rao bound of the model at the estimated variances);
:func:`predict_error` turns it into the held-out load error expected of the calibration.

Modules: :mod:`.problem` (the model and its solver), :mod:`.variances` (per-channel noise
variances), :mod:`.fit` (:func:`~.fit.fit_forward`), :mod:`.lockstep` (many logs or starts of
one rig solved at once), :mod:`.refits` (refits of the noise and the effective degrees of
freedom), :mod:`.shared_noise` (noise shared by channels, range level),
:mod:`.correlated` (noise correlated across channels and the whitened fit), :mod:`.misfit`
(readings far from the model; the direction test for a sensor not linear in the load).
"""
