"""Eigenspace (shape-from-motion) projector: learn a linear sensor -> actuator map from data.

The training matrix has one row per time step, ``x = [known, missing]``: the *known* part is what
the robot senses at run time (sensor features), the *missing* part is what it must produce
(actuator commands). Each column is standardised with training statistics, the thin SVD
``X = U S V^T`` of the standardised matrix is taken and the ``n`` leading right singular vectors are
kept. At run time only the known part is available: the coefficients ``c`` of the kept eigenvectors
are solved by least squares on their known rows, the missing part is read off the missing rows and
un-standardised (paper, section 9; Hancock and Thorpe's eigenspace projection).

Everything after the statistics is linear, so the whole run-time computation folds into one affine
map ``missing = known @ coef_ + intercept_`` precomputed at fit time.

Numerical route (shared by :meth:`EigenspaceProjector.fit` and
:meth:`EigenspaceProjector.partial_fit`, so both give the same model): the data enter only through
the weighted sample count, the column means and a triangular factor ``R`` with
``R^T R = sum_i w_i (x_i - mean)(x_i - mean)^T`` (the centred scatter). ``R`` comes from a
chunked Householder QR of the centred rows, and batches are merged with the square-root form of
Chan et al.'s pairwise update (stack both factors and the scaled mean difference, re-factor).
The singular values of ``R D^-1`` (``D`` = column scales) *are* the singular values of the
standardised training matrix, and its right singular vectors are the same, without ever squaring
the condition number as a Gram-matrix eigendecomposition would.
"""

from __future__ import annotations

import inspect
import numbers
import warnings

import numpy as np
from scipy.linalg import lapack

__all__ = ["EigenspaceProjector", "NotFittedError", "select_rank"]

SOLVERS = ("lstsq", "ridge", "ppca", "ols")

_QR_CHUNK_ROWS = 16384
"""Rows per Householder QR step; measured fastest for ~40 columns (fits in cache, BLAS-3 blocks)."""

_EPS = np.finfo(np.float64).eps


class NotFittedError(ValueError, AttributeError):
    """Raised when an estimator is used before ``fit`` or ``partial_fit``."""


def _svd_flip_rows(vt):
    """Flip the sign of each row of ``vt`` so that its largest-magnitude entry is positive.

    Deterministic signs (scikit-learn's ``svd_flip`` with ``u_based_decision=False``): two fits
    of the same data, or a batch and an incremental fit, give the same components.
    """
    idx = np.argmax(np.abs(vt), axis=1)
    signs = np.sign(vt[np.arange(vt.shape[0]), idx])
    signs[signs == 0] = 1.0
    return vt * signs[:, None]


def select_rank(singular_values, floor, max_rank=None):
    """Choose a rank at the largest ratio of adjacent singular values, guarded by a floor.

    Parameters
    ----------
    singular_values : array-like of shape (k,)
        Non-increasing singular values.
    floor : float
        Values ``s_i <= floor`` are noise level: they are never counted (never kept), and a
        denominator below the floor is clipped to it, so the ratio is ``s_i / max(s_{i+1}, floor)``.
        Clipping matters: without it a noise-level value sitting just above an exact zero (a
        constant or duplicated column) would produce an infinite ratio and be counted.
    max_rank : int or None
        Largest rank to consider (default ``k``).

    Returns
    -------
    rank : int
        In ``[1, max_rank]``. Returns 1 when no value is above the floor.
    ratios : ndarray of shape (m,)
        The guarded ratios for candidate ranks ``1..m`` (``m`` = number of values above the floor,
        capped by ``max_rank``); empty when ``m == 0``.
    """
    s = np.asarray(singular_values, dtype=np.float64)
    k = s.shape[0]
    max_rank = k if max_rank is None else min(int(max_rank), k)
    m = min(int(np.count_nonzero(s > floor)), max_rank)
    if m == 0:
        return 1, np.empty(0)
    num = s[:m]
    den = np.append(s[1:], 0.0)[:m]
    den = np.maximum(den, floor)
    with np.errstate(divide="ignore"):
        ratios = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.inf)
    return int(np.argmax(ratios)) + 1, ratios


def _as_2d_float(a, name):
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array of shape (n_samples, n_{name}); "
                         f"got an array with shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinity")
    return arr


def _centred_r_factor(known, missing, mean):
    """Upper-triangular ``R`` (p x p) with ``R^T R = (X - mean)^T (X - mean)``.

    ``X`` is ``[known, missing]`` side by side (never built as one array).

    Chunked Householder QR: each step factors the previous ``R`` stacked on the next chunk of
    centred rows, so memory stays at one chunk and the full matrix is never concatenated.
    """
    n, n_known = known.shape
    p = n_known + missing.shape[1]
    mean_k, mean_m = mean[:n_known], mean[n_known:]
    r = np.zeros((p, p))
    chunk = min(_QR_CHUNK_ROWS, n)
    buf = np.empty((p + chunk, p), order="F")
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        rows = p + stop - start
        block = buf if rows == buf.shape[0] else np.empty((rows, p), order="F")
        block[:p] = r
        np.subtract(known[start:stop], mean_k, out=block[p:, :n_known])
        np.subtract(missing[start:stop], mean_m, out=block[p:, n_known:])
        qr, _, _, info = lapack.dgeqrf(block, overwrite_a=1)
        if info != 0:  # pragma: no cover - LAPACK argument error, not a data condition
            raise RuntimeError(f"LAPACK dgeqrf failed with info={info}")
        r = np.triu(qr[:p])
    return r


def _make_constant_columns_exact(known, missing, mean, r):
    """For columns that are exactly constant: mean = that value, and a zero column of ``r``.

    Summation round-off leaves a constant column's computed mean off by up to about
    ``n * eps * |value|``; its centred values would then be that tiny offset, which standardisation
    would blow up into a unit-variance noise column. Only columns whose spread is already below
    1e-6 of their magnitude are checked exactly, so this costs nothing on ordinary data.
    Modifies ``mean`` and ``r`` in place.
    """
    n, n_known = known.shape
    spread = np.sqrt(np.einsum("ij,ij->j", r, r) / n)
    for j in np.nonzero(spread <= 1e-6 * np.abs(mean))[0]:
        col = known[:, j] if j < n_known else missing[:, j - n_known]
        if (col == col[0]).all():
            mean[j] = col[0]
            r[:, j] = 0.0


def _merge_r_factors(w_a, mean_a, r_a, w_b, mean_b, r_b):
    """Square-root form of Chan's pairwise merge of (weight, mean, centred scatter) summaries.

    scatter = S_a + S_b + (w_a w_b / w) d d^T with d = mean_a - mean_b; here as a QR of the stacked
    factors, so the merged ``R`` is as accurate as a QR of all the rows at once.
    """
    w = w_a + w_b
    mean = mean_a + (w_b / w) * (mean_b - mean_a)
    d = np.sqrt(w_a * w_b / w) * (mean_a - mean_b)
    stacked = np.asfortranarray(np.vstack([r_a, r_b, d[None, :]]))
    qr, _, _, info = lapack.dgeqrf(stacked, overwrite_a=1)
    if info != 0:  # pragma: no cover
        raise RuntimeError(f"LAPACK dgeqrf failed with info={info}")
    p = r_a.shape[1]
    return w, mean, np.triu(qr[:p])


class EigenspaceProjector:
    """Reconstruct missing (actuator) columns from known (sensor) columns by eigenspace projection.

    Parameters
    ----------
    n_components : int or None, default=None
        Number of right singular vectors to keep. ``None`` chooses it from the data at the largest
        ratio of adjacent singular values ``s_i / s_{i+1}`` (the paper's rule), among values above
        the floor (see ``rank_rtol`` and ``noise_std``), and at most ``n_known`` (more components
        than known columns would leave the coefficients under-determined). An explicit value must
        lie in ``[1, min(n_samples, n_features)]``; above ``n_known`` the ``"lstsq"`` solver returns
        the minimum-norm coefficients.
    rank_rtol : float, default=1e-3
        Floor relative to the largest singular value: ``s_i <= rank_rtol * s_0`` never counts.
        Must be in ``[0, 1)``. A numerical floor ``max(n_samples, n_features) * eps * s_0``
        (round-off: exact zeros from constant or duplicated columns) always applies as well.
    noise_std : float or None, default=None
        Per-entry noise standard deviation *in standardised units* (1.0 would be a column of pure
        noise), if known. Raises the floor to the Marchenko-Pastur upper edge
        ``noise_std * (sqrt(n_samples) + sqrt(n_features))``: the largest singular value that
        noise of that level alone produces. ``None`` uses only the relative and numerical floors.
    solver : {"lstsq", "ridge", "ppca"}, default="lstsq"
        How the coefficients are solved from the known rows ``V_k`` of the kept eigenvectors:

        - ``"lstsq"``: ``c = pinv(V_k) x_k`` (the paper).
        - ``"ridge"``: ``c = (V_k^T V_k + alpha I)^-1 V_k^T x_k``; tends to ``"lstsq"`` as
          ``alpha -> 0``.
        - ``"ppca"``: conditional mean ``E[x_missing | x_known]`` of the probabilistic-PCA model
          (Tipping and Bishop) with isotropic noise variance ``noise_variance_`` = mean of the
          discarded eigenvalues of the standardised covariance. Equivalent to ridge with a
          per-component penalty ``noise_variance_ / (eigenvalue_i - noise_variance_)``, so weak
          components are shrunk more; equals ``"lstsq"`` when nothing is discarded.
        - ``"ols"``: not an eigenspace method but its baseline: ordinary least squares of the
          missing on the known columns (standardised), ignoring the kept components; what any
          linear regression on the same features achieves.
    alpha : float, default=1e-3
        Ridge penalty (``solver="ridge"`` only), >= 0. In units of the squared eigenvector entries
        (each kept eigenvector has unit norm).
    forgetting : float, default=1.0
        Factor in ``(0, 1]`` by which :meth:`partial_fit` multiplies the weight of everything seen
        before each new batch; ``1.0`` weights all samples equally (and then ``partial_fit`` over
        batches equals ``fit`` on their concatenation). With ``forgetting < 1`` a batch ``j``
        batches old has weight ``forgetting ** j``, for drifting data. Ignored by :meth:`fit`.

    Attributes
    ----------
    mean_ : ndarray of shape (n_features,)
        Column means of the training data, ``[known, missing]``.
    scale_ : ndarray of shape (n_features,)
        Column standard deviations (population, ``ddof=0``). Constant columns (standard deviation
        ``<= 10 * eps * |mean|`` or exactly 0) get scale 1: they are centred to zero, carry no
        information, and are never divided by zero.
    components_ : ndarray of shape (n_components_, n_features)
        Kept right singular vectors of the standardised training matrix, sign-fixed so the
        largest-magnitude entry of each is positive.
    singular_values_ : ndarray of shape (min(n_samples, n_features),)
        All singular values of the standardised training matrix, non-increasing.
    explained_variance_ : ndarray of shape (min(n_samples, n_features),)
        ``singular_values_ ** 2 / n_samples_seen_``: eigenvalues of the standardised covariance.
    n_components_ : int
        Number of kept components.
    rank_floor_ : float
        The floor applied to ``singular_values_`` by the rank rule.
    rank_ratios_ : ndarray
        Guarded adjacent ratios the rule compared (empty when ``n_components`` was given).
    noise_variance_ : float
        Mean discarded eigenvalue over the non-constant columns (standardised units).
    n_known_, n_missing_, n_features_in_ : int
        Column counts; ``n_features_in_ = n_known_ + n_missing_``.
    n_samples_seen_ : float
        Effective (forgetting-weighted) number of samples; equals the row count when
        ``forgetting == 1``.
    n_rows_seen_ : int
        Number of rows passed to ``fit``/``partial_fit`` since the last ``fit``.
    coef_ : ndarray of shape (n_known_, n_missing_)
        Precomputed run-time map in original units.
    intercept_ : ndarray of shape (n_missing_,)
        ``reconstruct(known) = known @ coef_ + intercept_``.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> z = rng.standard_normal((500, 2))
    >>> known = z @ rng.standard_normal((2, 6))
    >>> missing = z @ rng.standard_normal((2, 1))
    >>> proj = EigenspaceProjector().fit(known, missing)
    >>> proj.n_components_
    2
    >>> bool(np.allclose(proj.reconstruct(known), missing))
    True
    """

    def __init__(self, n_components=None, *, rank_rtol=1e-3, noise_std=None, solver="lstsq",
                 alpha=1e-3, forgetting=1.0):
        self.n_components = n_components
        self.rank_rtol = rank_rtol
        self.noise_std = noise_std
        self.solver = solver
        self.alpha = alpha
        self.forgetting = forgetting

    # ------------------------------------------------------------------ scikit-learn plumbing
    @classmethod
    def _param_names(cls):
        sig = inspect.signature(cls.__init__)
        return [name for name in sig.parameters if name != "self"]

    def get_params(self, deep=True):
        """Constructor parameters as a dict (scikit-learn convention)."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params):
        """Set constructor parameters; returns self. Takes effect at the next fit/partial_fit."""
        valid = self._param_names()
        for key, value in params.items():
            if key not in valid:
                raise ValueError(f"invalid parameter {key!r} for EigenspaceProjector; "
                                 f"valid parameters are {valid}")
            setattr(self, key, value)
        return self

    def __repr__(self):
        params = inspect.signature(type(self).__init__).parameters
        defaults = {k: v.default for k, v in params.items() if k != "self"}
        changed = [f"{k}={getattr(self, k)!r}" for k in self._param_names()
                   if getattr(self, k) != defaults[k]]
        return f"EigenspaceProjector({', '.join(changed)})"

    def _validate_params(self):
        n = self.n_components
        if n is not None and (isinstance(n, bool) or not isinstance(n, numbers.Integral)):
            raise ValueError(f"n_components must be None or an int; got {n!r}")
        if not (isinstance(self.rank_rtol, numbers.Real) and 0 <= self.rank_rtol < 1):
            raise ValueError(f"rank_rtol must be in [0, 1); got {self.rank_rtol!r}")
        if self.noise_std is not None and not (
                isinstance(self.noise_std, numbers.Real) and self.noise_std >= 0):
            raise ValueError(f"noise_std must be None or a float >= 0; got {self.noise_std!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}; got {self.solver!r}")
        if not (isinstance(self.alpha, numbers.Real) and self.alpha >= 0):
            raise ValueError(f"alpha must be a float >= 0; got {self.alpha!r}")
        if not (isinstance(self.forgetting, numbers.Real) and 0 < self.forgetting <= 1):
            raise ValueError(f"forgetting must be in (0, 1]; got {self.forgetting!r}")

    def _check_is_fitted(self, method):
        if not hasattr(self, "coef_"):
            raise NotFittedError(
                f"This EigenspaceProjector instance is not fitted yet. Call 'fit' or "
                f"'partial_fit' with training data before calling '{method}'.")

    # ------------------------------------------------------------------ learning
    def fit(self, known, missing):
        """Learn the eigenspace from training data.

        Parameters
        ----------
        known : array-like of shape (n_samples, n_known)
            Sensor features (what is available at run time).
        missing : array-like of shape (n_samples, n_missing)
            Actuator commands (what :meth:`reconstruct` produces). A 1-D array is one column.

        Returns
        -------
        self : EigenspaceProjector
        """
        known, missing = self._validate_data(known, missing, reset=True)
        if known.shape[0] < 2:
            raise ValueError(f"fit needs at least 2 samples; got n_samples={known.shape[0]}")
        self._reset_statistics(known.shape[1], missing.shape[1])
        self._accumulate(known, missing, forgetting=1.0)
        return self._finalize()

    def partial_fit(self, known, missing):
        """Update the model with one batch; after all batches it equals ``fit`` on all of them.

        The sufficient statistics (weighted count, mean, triangular factor of the centred scatter)
        are merged exactly, so with ``forgetting=1`` the result equals the batch fit up to
        round-off. With ``forgetting < 1`` the previous statistics are down-weighted by that
        factor before the batch is merged. Shapes as in :meth:`fit`; any batch size >= 1.

        Returns
        -------
        self : EigenspaceProjector
        """
        first = not hasattr(self, "_r")
        if first and hasattr(self, "coef_"):
            raise ValueError("this projector was loaded without its training statistics (an "
                             "older file); partial_fit cannot continue it: fit it again")
        known, missing = self._validate_data(known, missing, reset=first)
        if known.shape[0] < 1:
            raise ValueError("partial_fit needs at least 1 sample; got an empty batch")
        if first:
            self._reset_statistics(known.shape[1], missing.shape[1])
        self._accumulate(known, missing, forgetting=self.forgetting)
        return self._finalize()

    def _validate_data(self, known, missing, reset):
        self._validate_params()
        known = _as_2d_float(known, "known")
        missing = _as_2d_float(missing, "missing")
        if known.shape[0] != missing.shape[0]:
            raise ValueError(f"known and missing must have the same number of rows; got "
                             f"{known.shape[0]} and {missing.shape[0]}")
        if known.shape[1] < 1 or missing.shape[1] < 1:
            raise ValueError(f"need at least one known and one missing column; got "
                             f"n_known={known.shape[1]}, n_missing={missing.shape[1]}")
        if not reset and (known.shape[1], missing.shape[1]) != (self.n_known_, self.n_missing_):
            raise ValueError(
                f"partial_fit got n_known={known.shape[1]}, n_missing={missing.shape[1]}; the "
                f"model was started with n_known={self.n_known_}, n_missing={self.n_missing_}")
        return known, missing

    def _reset_statistics(self, n_known, n_missing):
        p = n_known + n_missing
        self.n_known_ = n_known
        self.n_missing_ = n_missing
        self.n_features_in_ = p
        self._weight = 0.0
        self._mean = np.zeros(p)
        self._r = np.zeros((p, p))
        self.n_rows_seen_ = 0

    def _accumulate(self, known, missing, forgetting):
        n = known.shape[0]
        batch_mean = np.concatenate([known.mean(axis=0), missing.mean(axis=0)])
        batch_r = _centred_r_factor(known, missing, batch_mean)
        _make_constant_columns_exact(known, missing, batch_mean, batch_r)
        if self._weight == 0.0:
            self._weight, self._mean, self._r = float(n), batch_mean, batch_r
        else:
            w_old = self._weight * forgetting
            r_old = self._r * np.sqrt(forgetting)
            self._weight, self._mean, self._r = _merge_r_factors(
                w_old, self._mean, r_old, float(n), batch_mean, batch_r)
        self.n_rows_seen_ += n

    def _finalize(self):
        """Turn the sufficient statistics into the model: scales, SVD, rank, run-time map."""
        p, n_known = self.n_features_in_, self.n_known_
        w, mean, r = self._weight, self._mean, self._r

        std = np.sqrt(np.einsum("ij,ij->j", r, r) / w)
        constant = (std == 0) | (std <= 10 * _EPS * np.abs(mean))
        scale = np.where(constant, 1.0, std)
        r_std = r / scale
        r_std[:, constant] = 0.0  # round-off of a constant column must not become a component

        _, s, vt = np.linalg.svd(r_std)
        k = min(self.n_rows_seen_, p)
        s = s[:k]
        vt = _svd_flip_rows(vt[:k])

        floor = max(self.rank_rtol, max(self.n_rows_seen_, p) * _EPS) * s[0]
        if self.noise_std is not None:
            floor = max(floor, self.noise_std * (np.sqrt(w) + np.sqrt(p)))
        if self.n_components is None:
            n, ratios = select_rank(s, floor, max_rank=n_known)
            if ratios.size == 0 and self.n_rows_seen_ > 1:  # one row: nothing to learn yet
                warnings.warn(f"no singular value is above the floor {floor:.3g} "
                              f"(largest {s[0]:.3g}); keeping 1 component", stacklevel=3)
        else:
            n, ratios = int(self.n_components), np.empty(0)
            if not 1 <= n <= k:
                raise ValueError(f"n_components={n} must be in [1, {k}] "
                                 f"(min(n_samples, n_features)) for this data")

        ev = s**2 / w
        n_informative = p - int(np.count_nonzero(constant))
        discarded = n_informative - n
        noise_var = float(ev[n:].sum() / discarded) if discarded > 0 else 0.0

        self.mean_ = mean.copy()
        self.scale_ = scale
        self.singular_values_ = s
        self.explained_variance_ = ev
        self.components_ = vt[:n].copy()
        self.n_components_ = n
        self.rank_floor_ = float(floor)
        self.rank_ratios_ = ratios
        self.noise_variance_ = noise_var
        self.n_samples_seen_ = w

        if self.solver == "ols":  # the baseline: regression on the known columns, no eigenspace
            gram = r_std.T @ r_std
            std_map = gram[n_known:, :n_known] @ np.linalg.pinv(gram[:n_known, :n_known])
        else:
            std_map = self._standardised_map(ev[:n], noise_var)  # (n_missing, n_known)
        scale_k, scale_m = scale[:n_known], scale[n_known:]
        coef = (std_map / scale_k[None, :] * scale_m[:, None]).T
        self.coef_ = np.ascontiguousarray(coef)
        self.intercept_ = mean[n_known:] - mean[:n_known] @ coef
        return self

    def _standardised_map(self, kept_ev, noise_var):
        """Linear map (n_missing, n_known) from standardised known to standardised missing."""
        v = self.components_.T  # (p, n)
        v_k, v_m = v[: self.n_known_], v[self.n_known_ :]
        n = v.shape[1]
        if self.solver == "lstsq":
            return v_m @ np.linalg.pinv(v_k)
        if self.solver == "ridge":
            gram = v_k.T @ v_k + self.alpha * np.eye(n)
            return v_m @ np.linalg.lstsq(gram, v_k.T, rcond=None)[0]
        # ppca: W = V diag(sqrt(ev - sigma^2));
        # E[x_m | x_k] = W_m (W_k^T W_k + sigma^2 I)^-1 W_k^T x_k
        d = np.sqrt(np.maximum(kept_ev - noise_var, 0.0))
        w_k, w_m = v_k * d, v_m * d
        if noise_var == 0.0:
            return w_m @ np.linalg.pinv(w_k)
        m = w_k.T @ w_k + noise_var * np.eye(n)
        return w_m @ np.linalg.solve(m, w_k.T)

    # ------------------------------------------------------------------ files
    _ARRAYS = ("mean_", "scale_", "singular_values_", "explained_variance_", "components_",
               "coef_", "intercept_", "rank_ratios_")
    _INTS = ("n_components_", "n_known_", "n_missing_", "n_rows_seen_")
    _FLOATS = ("n_samples_seen_", "rank_floor_", "noise_variance_")

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Everything a fitted projector is, as numpy arrays (no pickling needed to store them):
        the constructor parameters (``param.<name>``), the learned attributes, and the sufficient
        statistics ``partial_fit`` continues from (``stat.weight``, ``stat.mean``, ``stat.r``).
        :meth:`from_arrays` rebuilds an equal projector."""
        self._check_is_fitted("to_arrays")
        out = {f"param.{k}": np.asarray("none" if v is None else v)
               for k, v in self.get_params().items()}
        out.update({k: np.asarray(getattr(self, k), dtype=np.float64) for k in self._ARRAYS})
        out.update({k: np.asarray(int(getattr(self, k)), dtype=np.int64) for k in self._INTS})
        out.update({k: np.asarray(float(getattr(self, k))) for k in self._FLOATS})
        if hasattr(self, "_r"):
            out["stat.weight"] = np.asarray(float(self._weight))
            out["stat.mean"] = np.asarray(self._mean, dtype=np.float64)
            out["stat.r"] = np.asarray(self._r, dtype=np.float64)
        return out

    @classmethod
    def from_arrays(cls, arrays) -> EigenspaceProjector:
        """The projector :meth:`to_arrays` stored. Raises ``ValueError`` (one line) for missing,
        mistyped, non-finite or inconsistently shaped entries. Without the ``stat.*`` entries
        the projector predicts but cannot :meth:`partial_fit`."""
        def get(key):
            if key not in arrays:
                raise ValueError(f"projector arrays lack {key!r}")
            return np.asarray(arrays[key])

        params = {}
        for name in cls._param_names():
            key = f"param.{name}"
            if key not in arrays:
                continue  # a parameter added later keeps its default
            v = get(key)
            if v.ndim != 0:
                raise ValueError(f"projector parameter {name} must be a scalar")
            v = v.item()
            params[name] = None if v == "none" else v
        proj = cls(**params)
        try:
            proj._validate_params()
        except (TypeError, ValueError) as e:
            raise ValueError(f"projector parameters: {e}") from None
        for k in cls._ARRAYS:
            a = get(k)
            if a.dtype.kind not in "fiu" or not np.all(np.isfinite(a)):
                raise ValueError(f"projector {k} must be finite numbers")
            setattr(proj, k, a.astype(np.float64))
        for k in cls._INTS:
            a = get(k)
            if a.ndim != 0 or a.dtype.kind not in "iu" or int(a) < 0:
                raise ValueError(f"projector {k} must be a non-negative integer")
            setattr(proj, k, int(a))
        for k in cls._FLOATS:
            a = get(k)
            if a.ndim != 0 or a.dtype.kind not in "fiu" or not np.isfinite(a):
                raise ValueError(f"projector {k} must be a finite number")
            setattr(proj, k, float(a))
        nk, nm, n = proj.n_known_, proj.n_missing_, proj.n_components_
        p = nk + nm
        proj.n_features_in_ = p
        shapes = {"mean_": (p,), "scale_": (p,), "coef_": (nk, nm), "intercept_": (nm,),
                  "components_": (n, p)}
        for k, shape in shapes.items():
            if getattr(proj, k).shape != shape:
                raise ValueError(f"projector {k} has shape {getattr(proj, k).shape}, expected "
                                 f"{shape} for {nk} known and {nm} missing columns, "
                                 f"{n} components")
        if proj.singular_values_.ndim != 1 or not 1 <= n <= max(proj.singular_values_.size, 1):
            raise ValueError(f"projector n_components_={n} does not fit "
                             f"{proj.singular_values_.size} singular values")
        if "stat.r" in arrays:
            proj._weight = float(get("stat.weight"))
            proj._mean = get("stat.mean").astype(np.float64)
            proj._r = get("stat.r").astype(np.float64)
            if proj._mean.shape != (p,) or proj._r.shape != (p, p):
                raise ValueError("projector statistics do not match its column counts")
        return proj

    # ------------------------------------------------------------------ run time
    def reconstruct(self, known):
        """Reconstruct the missing (actuator) part from the known (sensor) part.

        Parameters
        ----------
        known : array-like of shape (n_samples, n_known) or (n_known,)

        Returns
        -------
        missing : ndarray of shape (n_samples, n_missing) or (n_missing,)
            Un-standardised, continuous (no quantisation). 1-D in, 1-D out.
        """
        self._check_is_fitted("reconstruct")
        x = np.asarray(known, dtype=np.float64)
        if x.shape[-1:] != (self.n_known_,) or x.ndim > 2:
            raise ValueError(f"known must have shape (n_samples, {self.n_known_}) or "
                             f"({self.n_known_},); got {x.shape}")
        return x @ self.coef_ + self.intercept_

    def transform(self, known):
        """Eigenspace coefficients ``c`` solved from the known part (the run-time projection).

        Parameters
        ----------
        known : array-like of shape (n_samples, n_known) or (n_known,)

        Returns
        -------
        coefficients : ndarray of shape (n_samples, n_components_) or (n_components_,)
        """
        self._check_is_fitted("transform")
        if self.solver == "ols":
            raise ValueError("solver 'ols' has no eigenspace coefficients to transform to")
        x = np.asarray(known, dtype=np.float64)
        if x.shape[-1:] != (self.n_known_,) or x.ndim > 2:
            raise ValueError(f"known must have shape (n_samples, {self.n_known_}) or "
                             f"({self.n_known_},); got {x.shape}")
        z = (x - self.mean_[: self.n_known_]) / self.scale_[: self.n_known_]
        v_k = self.components_[:, : self.n_known_].T
        if self.solver == "lstsq":
            solve = np.linalg.pinv(v_k)
        elif self.solver == "ridge":
            solve = np.linalg.solve(v_k.T @ v_k + self.alpha * np.eye(v_k.shape[1]), v_k.T)
        else:
            d = np.sqrt(np.maximum(self.explained_variance_[: self.n_components_]
                                   - self.noise_variance_, 0.0))
            w_k = v_k * d
            if self.noise_variance_ == 0.0:
                solve = d[:, None] * np.linalg.pinv(w_k)
            else:
                m = w_k.T @ w_k + self.noise_variance_ * np.eye(v_k.shape[1])
                solve = d[:, None] * np.linalg.solve(m, w_k.T)
        return z @ solve.T
