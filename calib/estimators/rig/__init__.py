"""Static-pose rigs: find the poses of a log, and the pose-level joint fit.
A real calibration rig holds a weighed mass in a dozen static poses and logs a few hundred
readings in each; a few poses get known loads (their mean reading and the applied load). What
such data determine is a *forward* model of the pose means,

    zbar_j = A m_j + o + e_j,        m_j = m_k (known poses),  m_j = g u_j (the others, |u_j| = 1),

``A`` (p x r) and ``o`` (p) the sensor's linear response and offset, ``u_j`` the unknown pose
directions (two angles each, nuisance parameters) and ``g`` the magnitude of the mass. With 12
poses of 8 channels that is 96 numbers for 32 + 16 + 1 parameters: well determined, which the
inverse model ``m = C z + d`` on the same data is not (27 parameters against the 12 known
components and 8 magnitudes). :func:`fit_rig` fits it in two stages:

1. **Pose loads.** The forward model by maximum likelihood,
:func:`calib.estimators.forward.fit.fit_forward`
   on the pose means: the same estimator as a log without static poses (one reading per pose
   or a sweep), here with each pose mean's variance ``v_c + s_c^2 / n_j`` (``s_c`` the
   within-pose scatter, ``n_j`` the pose's readings, ``v_c`` each channel's pose-level variance
   from the residuals, leverage-corrected, in feasible-GLS rounds until it settles: a real
   sensor's misfit, nonlinearity, creep, hysteresis, is far larger than its sampling noise and
   differs by channel). Its starts: the affine map of the known poses, the Sampson-distance
   joint fit and the centered route aligned to the known loads (handed in), random
   directions, each *alternated* (the model fitted at the current loads, then every unknown
   pose moved to its best direction on its sphere: a global step per pose, which LM's local
   steps cannot take), and perturbed restarts of the best; the lowest cost under the final
   weights is kept and every start's cost is in the diagnostics. The magnitude is held at the
   known loads' when they are one weighed mass (within :data:`SAME_MAGNITUDE`), else fitted.
   A per-channel **bending term** (:class:`ForwardModel` with ``bend``) is then tried from
   those directions and kept when an F-test supports it (:data:`BEND_P`).
   Then the **index model** (:class:`IndexModel`): every channel a polynomial (degree 2 or 3)
   of its own linear signal ``a_c . m``, ``a_c`` fitted with the curvature and the directions,
   the magnitude held at the known loads' when they are one mass; a higher degree is kept when
   a nested F-test finds it significant and it predicts left-out poses better, and the index
   model replaces the forward model's loads when it is kept. A printed or
   capacitive channel bends along the one direction it senses: on a real printed sensor this
   took the worst load set from 5.9x to 1.8x least squares with every load known.
2. **Calibration.** Least squares on every row with its pose's load: the known loads where
   known, ``g u_j`` elsewhere; exactly what least squares with every load known does, with the
   estimated loads in place of the unknown ones. Fitting the rows (not the pose means) shrinks
   ``C`` along noisy channel combinations the way the all-known fit does, and the affine map on
   all p channels absorbs part of a sensor's nonlinearity through its redundant channels.

Measured on :func:`calib.simulation.simulate.simulate_rig` rigs (``scripts/calib_rig_study.py``):
within
1.1-1.4x of least squares with every load known, where the Sampson-distance fit (``rig=False``)
was 1.3-2x and up to 5x on nonlinear sensors. See docs/calib.md.

Modules: :mod:`.poses` (finding the static poses of a log), :mod:`.model` (the pose data and
the forward and index models), :mod:`.fit` (the two stages).
"""
