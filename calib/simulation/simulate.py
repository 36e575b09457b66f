"""Sensor simulator: a constant-magnitude load moved over orientations, seen through a shape matrix.

Model (paper eqs. 4, 6, 15): ``z_i^T = m_i^T S + z0^T + e_i^T``, ``Z = M S + 1 z0^T + E`` with
``S`` of shape (dof, p), loads ``M`` of shape (n, dof), offsets ``z0`` of shape (p,) and per-channel
noise ``E``. For a 6-DOF force/torque sensor the load of a proof mass at lever arm ``r`` is
``m = [F, r x F]``, so ``M`` (n x 6) still has rank 3.

The paper's section 8 set-up is :func:`paper_trial`: the 3 x 8 calibration matrix ``C`` printed
there, 176 samples, uniform noise, constant offsets, Trials 1-4.

Scale: the paper's ``C`` maps raw counts to unit force, so its shape matrix, given by
``S^T = C^+`` (eq. 5 read backwards), has entries +-16.67 (x and y channels) and 12.5 (z channels).
A unit force therefore produces at most 16.67 counts, while the
paper states that "the maximum signal for all illustrated trials was about 150". We read this as a
force of magnitude ``PAPER_FORCE_MAGNITUDE = 9`` (9 * 16.67 = 150.0 counts peak), which also makes
the quoted noise percentages right: peak noise 3 = 2 %, 15 = 10 %, 25 = 16.7 % ("about 17 %") of
150.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.data.result import CalibrationError
from calib.estimators.ft6 import skew

#: The paper's idealised 3-DOF calibration matrix (section 8), shape (3, 8): counts -> unit force.
#: Decision: docs/calib_design.md D22.
PAPER_C = np.array(
    [
        [0.03, 0, 0, 0, -0.03, 0, 0, 0],
        [0, 0, 0.03, 0, 0, 0, -0.03, 0],
        [0, 0.02, 0, 0.02, 0, 0.02, 0, 0.02],
    ]
)

#: Force magnitude that gives the paper's "maximum signal about 150" counts (see module docstring).
#: Decision: docs/calib_design.md D22.
PAPER_FORCE_MAGNITUDE = 9.0

#: Samples per trial in the paper.
#: Decision: docs/calib_design.md D22.
PAPER_N_SAMPLES = 176

#: Trials 1-4 of section 8: true offsets, uniform peak noise per channel, and the paper's reported
#: recovered offsets, std of the smoothed magnitude and mean magnitude (with / without offset calc).
#: Trial 4 prints seven peak-noise values (15 15 25 15 15 25 15) for eight channels; the text says
#: only two sense elements are raised to ~17 %, so the missing eighth value is 15 (channels 3 and 6,
#: 1-based, carry 25). Trial 3 prints seven error percentages; the eighth is lost in the paper.
#: Decision: docs/calib_design.md D22.
PAPER_TRIALS = {
    1: {
        "offset": [3.0, 2.5, -2.5, 2.0, 4.0, -2.5, 5.0, -3.0],
        "peak_noise": [0.0] * 8,
        "paper_recovered": [2.98, 2.50, -2.59, 2.00, 4.02, -2.50, 5.09, -3.00],
        "paper_std": {"with_offset": 0.00026, "without_offset": 0.011},
        "paper_mean": {"with_offset": 0.9998, "without_offset": 0.9997},
    },
    2: {
        "offset": [-10.0, 12.5, 12.5, 14.5, 17.5, -12.5, 7.5, -17.5],
        "peak_noise": [3.0] * 8,
        "paper_recovered": [-12.7, 12.3, 12.9, 14.4, 20.1, -12.7, 7.1, -17.5],
        "paper_std": {"with_offset": 0.0077, "without_offset": 0.039},
        "paper_mean": {"with_offset": 0.992, "without_offset": 0.995},
    },
    3: {
        "offset": [-30.0, 25.0, 25.0, 20.0, 35.0, -25.0, 1.0, -39.0],
        "peak_noise": [15.0] * 8,
        "paper_recovered": [-48.7, 26.7, 34.3, 20.1, 54.2, -25.1, -8.3, -38.1],
        "paper_std": {"with_offset": 0.052, "without_offset": 0.101},
        "paper_mean": {"with_offset": 0.964, "without_offset": 0.968},
    },
    4: {
        "offset": [-30.0, 25.0, 25.0, 20.0, 35.0, -25.0, 1.0, -39.0],
        "peak_noise": [15.0, 15.0, 25.0, 15.0, 15.0, 25.0, 15.0, 15.0],
        "paper_recovered": [-66.7, 23.3, 41.1, 18.5, 70.8, -27.5, -16.7, -42.1],
        "paper_std": {"with_offset": 0.092, "without_offset": 0.093},
        "paper_mean": {"with_offset": 0.927, "without_offset": 0.970},
    },
}


def paper_shape_matrix() -> np.ndarray:
    """Shape matrix S (3, 8) of the paper's sensor in counts per unit force: ``S^T = C^+``
    (eq. 5)."""
    return np.linalg.pinv(PAPER_C).T


@dataclass
class SensorData:
    """One simulated data set.

    Attributes
    ----------
    Z : ndarray (n, p)      raw readings with offsets and noise
    loads : ndarray (n, dof) applied loads m_i (forces, and torques for dof 6)
    directions : ndarray (n, r) unit force directions
    S : ndarray (dof, p)    shape matrix used
    offset : ndarray (p,)   true offsets z0
    magnitude : float       force magnitude
    """

    Z: np.ndarray
    loads: np.ndarray
    directions: np.ndarray
    S: np.ndarray
    offset: np.ndarray
    magnitude: float

    @property
    def C(self) -> np.ndarray:
        """True calibration matrix ``(S^T)^+``, shape (dof, p)."""
        return np.linalg.pinv(self.S.T)


def sample_directions(
    n: int, r: int, rng, cap_half_angle_deg: float | None = None, axis=None
) -> np.ndarray:
    """Unit vectors, shape (n, r), uniform over the circle (r=2) / sphere (r=3) or a cap of them.

    ``cap_half_angle_deg`` limits directions to within that angle of ``axis`` (default: last axis,
    i.e. +z, or +y in the plane); None or >= 180 means everywhere. Uniform in area on the cap.
    """
    rng = np.random.default_rng(rng)
    cap = 180.0 if cap_half_angle_deg is None else float(cap_half_angle_deg)
    if not 0 < cap <= 180:
        raise CalibrationError(f"cap half-angle must be in (0, 180] degrees, got {cap}")
    a = np.radians(cap)
    if r == 2:
        t = rng.uniform(-a, a, n)
        u = np.column_stack([np.sin(t), np.cos(t)])
    elif r == 3:
        cz = rng.uniform(np.cos(a), 1.0, n)
        phi = rng.uniform(0, 2 * np.pi, n)
        sz = np.sqrt(np.clip(1 - cz**2, 0, None))
        u = np.column_stack([sz * np.cos(phi), sz * np.sin(phi), cz])
    else:
        raise CalibrationError(f"force dimension must be 2 or 3, got {r}")
    if axis is not None:
        u = u @ _rotation_to(np.asarray(axis, float), r).T
    return u


def _rotation_to(axis: np.ndarray, r: int) -> np.ndarray:
    """Rotation taking the last basis vector to ``axis`` (normalised)."""
    b = axis / np.linalg.norm(axis)
    e = np.zeros(r)
    e[-1] = 1.0
    if r == 2:
        c, s = b[1], b[0]
        return np.array([[c, s], [-s, c]]).T
    v = np.cross(e, b)
    c = float(e @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def lever_matrix(lever_arm) -> np.ndarray:
    """G of shape (6, 3) with ``[F; r x F] = G F`` for a proof mass at ``lever_arm`` (3,)."""
    return np.vstack([np.eye(3), skew(lever_arm)])


def random_shape(dof: int, p: int, rng, condition: float = 5.0) -> np.ndarray:
    """A random full-rank shape matrix S (dof, p) with singular values spread over ``condition``."""
    rng = np.random.default_rng(rng)
    if p < dof:
        raise CalibrationError(f"need p >= dof channels, got p={p}, dof={dof}")
    U, _ = np.linalg.qr(rng.normal(size=(dof, dof)))
    V, _ = np.linalg.qr(rng.normal(size=(p, dof)))
    s = np.geomspace(condition, 1.0, dof) * rng.uniform(0.8, 1.2, dof)
    return (U * s) @ V.T


def simulate(
    S,
    n: int,
    rng=None,
    magnitude: float = 1.0,
    cap_half_angle_deg: float | None = None,
    noise=0.0,
    noise_kind: str = "uniform",
    offset=None,
    lever_arm=None,
    axis=None,
) -> SensorData:
    """Simulate ``n`` readings of a constant-magnitude load moved over orientations.

    Parameters
    ----------
    S : array of shape (dof, p), dof in {2, 3, 6}
    n : int, number of samples
    rng : seed or numpy Generator
    magnitude : force magnitude (the proof mass weight)
    cap_half_angle_deg : None for all orientations, else the half-angle of the cap of directions
    noise : float or array (p,); half-width ("peak noise") for ``uniform``, std for ``gaussian``
    noise_kind : "uniform" or "gaussian"
    offset : None or array (p,), constant sensor bias
    lever_arm : array (3,), required for dof 6 (proof-mass position); torque = r x F
    axis : centre of the cap (default +z / +y)

    Returns
    -------
    SensorData
    """
    rng = np.random.default_rng(rng)
    S = np.atleast_2d(np.asarray(S, float))
    dof, p = S.shape
    if dof not in (2, 3, 6):
        raise CalibrationError(f"S must have 2, 3 or 6 rows, got {dof}")
    r = 2 if dof == 2 else 3
    u = sample_directions(n, r, rng, cap_half_angle_deg, axis)
    F = magnitude * u
    if dof == 6:
        if lever_arm is None:
            raise CalibrationError("a 6-DOF simulation needs the proof mass lever_arm (3,)")
        loads = F @ lever_matrix(lever_arm).T
    else:
        loads = F
    Z = loads @ S
    z0 = np.zeros(p) if offset is None else np.asarray(offset, float).reshape(p)
    Z = Z + z0
    Z = Z + make_noise((n, p), noise, noise_kind, rng)
    return SensorData(Z=Z, loads=loads, directions=u, S=S, offset=z0, magnitude=float(magnitude))


def make_noise(shape, level, kind: str, rng) -> np.ndarray:
    """Per-channel noise of ``shape`` (n, p); ``level`` scalar or (p,)."""
    level = np.broadcast_to(np.asarray(level, float), (shape[1],))
    if kind == "uniform":
        return rng.uniform(-1.0, 1.0, shape) * level
    if kind == "gaussian":
        return rng.normal(size=shape) * level
    raise CalibrationError(f"noise_kind must be 'uniform' or 'gaussian', got {kind!r}")


def paper_trial(
    trial: int,
    rng=None,
    n: int = PAPER_N_SAMPLES,
    cap_half_angle_deg: float | None = None,
    noise_scale: float = 1.0,
) -> SensorData:
    """The paper's section 8 Trial ``trial`` (1-4): 176 samples, uniform noise, its offsets.

    ``noise_scale`` multiplies the trial's peak noise (for noise sweeps).
    """
    if trial not in PAPER_TRIALS:
        raise CalibrationError(f"trial must be one of {sorted(PAPER_TRIALS)}, got {trial}")
    t = PAPER_TRIALS[trial]
    return simulate(
        paper_shape_matrix(),
        n,
        rng=rng,
        magnitude=PAPER_FORCE_MAGNITUDE,
        cap_half_angle_deg=cap_half_angle_deg,
        noise=np.asarray(t["peak_noise"]) * noise_scale,
        noise_kind="uniform",
        offset=t["offset"],
    )


@dataclass
class RigData:
    """A simulated static-pose calibration rig (:func:`simulate_rig`).

    Attributes
    ----------
    Z : ndarray (n, p)        readings in time order (pose after pose)
    pose : ndarray (n,)       the pose index of every reading
    stated_loads : (P, r)     the loads the operator believes were applied (weighed mass times
                              the rig's design direction): what a real rig's "known load" is
    true_loads : (n, r)       the loads really applied (weighing error, mount misalignment)
    directions : (P, r)       the rig's design directions (unit)
    S : (r, p), offset : (p,) the linear part of the sensor and its offset at time 0
    magnitude : float         the stated load magnitude
    noise_cov : (p, p) | None the readings' noise covariance where the simulator knows it
                              exactly (:func:`simulate_payload_rig`; None otherwise)
    """

    Z: np.ndarray
    pose: np.ndarray
    stated_loads: np.ndarray
    true_loads: np.ndarray
    directions: np.ndarray
    S: np.ndarray
    offset: np.ndarray
    magnitude: float
    noise_cov: np.ndarray | None = None

    def split(self, kind: str = "alternate"):
        """Train and test row indices: half the samples of every pose each.

        ``alternate``: even samples train, odd test; ``halves``: the first half of every pose
        trains, the second tests (harder: drift and creep differ between them); ``poses``:
        every reading of the even poses trains, of the odd poses tests (rigs with one reading
        per pose: the test loads are new directions).
        """
        idx = np.arange(len(self.Z))
        within = idx - np.searchsorted(self.pose, self.pose)  # sample number inside its pose
        counts = np.bincount(self.pose)[self.pose]
        if kind == "poses":
            train = self.pose % 2 == 0
        elif kind == "alternate":
            train = within % 2 == 0
        elif kind == "halves":
            train = within < counts // 2
        else:
            raise CalibrationError("split kind must be 'alternate', 'halves' or 'poses', got "
                                   f"{kind!r}")
        return idx[train], idx[~train]

    def pose_means(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """Mean reading of every pose over ``rows``, and the pose indices: (P, p), (P,)."""
        rows = np.asarray(rows)
        poses = np.unique(self.pose[rows])
        means = np.array([self.Z[rows][self.pose[rows] == j].mean(axis=0) for j in poses])
        return means, poses


def _smooth_wander(n: int, rng) -> np.ndarray:
    """A smooth temperature-like signal over n samples in about [-1, 1]: three random sinusoids
    with periods of 0.3-2 log lengths."""
    t = np.arange(n) / max(n, 1)
    periods = rng.uniform(0.3, 2.0, 3)
    phases = rng.uniform(0, 2 * np.pi, 3)
    amps = rng.uniform(0.5, 1.0, 3)
    w = sum(a * np.sin(2 * np.pi * t / T + ph)
            for a, T, ph in zip(amps, periods, phases, strict=True))
    return w / amps.sum()


def simulate_rig(
    rng=None,
    poses: int = 12,
    samples: int = 200,
    p: int = 8,
    magnitude: float = 10.0,
    directions=None,
    condition: tuple[float, float] = (1.0, 10.0),
    counts_per_unit: float = 10.0,
    noise: float = 0.002,
    nonlinearity: float = 0.01,
    drift: float = 0.005,
    wander: float = 0.003,
    creep: float = 0.01,
    hysteresis: float = 0.003,
    mass_error: float = 0.002,
    misalignment_deg: float = 0.5,
    outliers: float = 0.0,
) -> RigData:
    """A static-pose rig: a weighed mass held in ``poses`` orientations, ``samples`` readings each.

    What a real printed or strain-gauge 3-axis sensor on such a rig adds to the linear model
    (every level a fraction of each channel's full-scale signal ``fs_j = magnitude |S_j|``):

    - ``noise``: per-sample Gaussian noise, each channel's level times a factor in [0.5, 2];
    - ``nonlinearity``: each channel adds ``fs_j (a_j x^2 + b_j x^3)``, ``x`` its linear signal
      over ``fs_j`` and ``a_j, b_j`` uniform in +-``nonlinearity``;
    - ``drift``: offsets moving linearly over the log, up to ``drift`` at its end;
    - ``wander``: a smooth temperature-like signal (shared) times per-channel coefficients;
    - ``creep``: after each pose change the reading approaches its new value exponentially,
      starting ``creep`` of the step short (time constant a fifth of a pose's samples);
    - ``hysteresis``: a persistent ``hysteresis`` fraction of the last step stays behind;
    - ``mass_error``: the true mass differs from the weighed one by this relative std;
    - ``misalignment_deg``: each pose's true direction is off its design by this std (degrees);
    - ``outliers``: this fraction of readings gets a spike of 20 noise levels on one channel.

    Directions default to ``poses`` random directions over the sphere. Seeded, deterministic.
    """
    rng = np.random.default_rng(rng)
    if poses < 2 or samples < 2 or p < 3:
        raise CalibrationError("a rig needs >= 2 poses, >= 2 samples per pose and >= 3 channels")
    U = (sample_directions(poses, 3, rng) if directions is None
         else np.asarray(directions, float))
    if U.shape != (poses, 3):
        raise CalibrationError(f"directions must have shape ({poses}, 3), got {U.shape}")
    U = U / np.linalg.norm(U, axis=1, keepdims=True)
    S = random_shape(3, p, rng, condition=rng.uniform(*condition)) * counts_per_unit
    fs = magnitude * np.linalg.norm(S, axis=0)  # full-scale signal per channel (counts)
    z0 = rng.normal(size=p) * fs
    true_mag = magnitude * (1 + mass_error * rng.normal())
    # true directions: the design rotated by a small random angle per pose
    true_U = np.empty_like(U)
    for j in range(poses):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = np.radians(misalignment_deg) * rng.normal()
        Kx = skew(axis)
        R = np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx
        true_U[j] = R @ U[j]
    n = poses * samples
    pose = np.repeat(np.arange(poses), samples)
    F = true_mag * true_U[pose]
    lin = F @ S
    x = lin / fs
    a = rng.uniform(-1, 1, p) * nonlinearity
    b = rng.uniform(-1, 1, p) * nonlinearity
    Z = z0 + lin + fs * (a * x**2 + b * x**3)
    tfrac = np.arange(n) / max(n - 1, 1)
    Z += np.outer(tfrac, rng.uniform(-1, 1, p) * drift * fs)
    Z += np.outer(_smooth_wander(n, rng), rng.uniform(-1, 1, p) * wander * fs)
    # creep and hysteresis from each pose change (the first pose comes from the unloaded state)
    pose_lin = true_mag * true_U @ S
    prev = np.vstack([np.zeros(p), pose_lin[:-1]])
    step = pose_lin - prev
    k = np.tile(np.arange(samples), poses)
    tau = max(samples / 5, 1.0)
    Z -= creep * step[pose] * np.exp(-k / tau)[:, None]
    Z -= hysteresis * step[pose]
    Z += rng.normal(size=(n, p)) * (noise * fs * np.exp(rng.uniform(np.log(0.5), np.log(2), p)))
    if outliers > 0:
        hit = rng.random(n) < outliers
        ch = rng.integers(0, p, n)
        Z[hit, ch[hit]] += 20 * noise * fs[ch[hit]] * rng.choice([-1, 1], hit.sum())
    return RigData(Z=Z, pose=pose, stated_loads=magnitude * U, true_loads=F, directions=U,
                   S=S, offset=z0, magnitude=float(magnitude))


def simulate_payload_rig(
    rng=None,
    poses: int = 40,
    p: int = 8,
    readings: int = 1,
    sweep: bool = False,
    tilt_deg: tuple[float, float] = (30.0, 90.0),
    mass_kg: tuple[float, float] = (0.3, 3.0),
    com_m: tuple[float, float] = (0.02, 0.15),
    scales: tuple[float, float] = (1e-2, 1e2),
    noise: tuple[float, float] = (0.002, 0.02),
    misalignment_deg: float = 0.0,
    mass_error: float = 0.0,
    wrench: bool = False,
    gauges: int = 0,
    nonlinearity: float = 0.0,
    nonlinearity_kind: str = "direction",
) -> RigData:
    """A robot wrist holding a gripper on a 6-axis force/torque sensor: the load is the gripper's
    weight in the sensor frame, known from the robot's kinematics.

    - The gripper's mass is uniform in ``mass_kg`` (weight ``9.81 m`` N), its centre of mass
      ``com_m`` metres from the sensor's origin in a random direction, so the wrench is
      ``[F; r x F]`` (forces in N, torques in N*m: rank 3, as the paper's section 5 says).
    - ``p`` raw gauge channels read ``G^T [F; T] + offset``: every gauge mixes forces and
      torques (a random 6 x p map), then gets its own scale, log-uniform in ``scales`` (counts,
      volts, microstrain: units never agree); ``p = 6`` with ``scales = (1, 1)`` is a sensor
      that reports the wrench itself; ``wrench=True`` is a commercial F/T sensor's output (6
      channels, forces in N, torques in N*m, no mixing). With ``gauges=q`` (and ``wrench``)
      that output is what the sensor's factory matrix computes from ``q`` strain gauges, each
      with its own noise (``noise`` of its own spread; torques weigh on a gauge as forces at
      5 cm): the wrench channels' noise is then correlated, one gauge's noise reading on a
      force and a torque at once.
    - Noise per channel: a fraction of that channel's spread over the loads, log-uniform in
      ``noise``.
    - Orientations a wrist reaches: gravity in the sensor frame ``tilt_deg`` degrees from the
      sensor's axis (the tool axis 30-90 degrees from vertical by default; ``(0, 70)`` a cap),
      any roll. ``readings`` readings per pose (static), or with ``sweep`` one continuous slow
      motion of ``poses * readings`` readings (a smooth random path through the band; every
      reading its own pose).
    - ``misalignment_deg`` (kinematic error of the stated direction, std) and ``mass_error``
      (relative std of the weighed mass) make the stated loads differ from the applied ones.
    - ``nonlinearity``: every channel also reads a smooth function of the load that no affine
      map holds (a gauge's nonlinearity, cross-talk): ``nonlinearity`` times its spread times
      ``u^T Q_c u``, ``u`` the applied load's direction and ``Q_c`` a random symmetric matrix
      scaled to a largest absolute eigenvalue of 1 (so at most that fraction of the spread). Its
      draws come after every other draw: a rig without it is the same rig. With
      ``nonlinearity_kind="signal"`` each channel's own linear signal is bent instead (a gauge
      or amplifier that is not linear in its strain, :func:`simulate_rig`'s kind): it adds
      ``spread (a x^2 + b x^3)``, ``x`` its linear signal over its spread and ``a, b`` uniform
      in +-``nonlinearity``. A misfit of this kind is one the direction test finds less often
      (docs/calib.md, "Gauges that are not linear").

    Returns :class:`RigData`; ``S`` is the (3, p) map from the force to the readings (its
    linear part, with ``nonlinearity``), ``stated_loads`` the kinematic loads per pose. Seeded,
    deterministic.
    """
    rng = np.random.default_rng(rng)
    if poses < 2 or readings < 1 or p < 3:
        raise CalibrationError("a payload rig needs >= 2 poses, >= 1 reading each, >= 3 channels")
    if gauges and (not wrench or int(gauges) < 6):
        raise CalibrationError("gauges: a wrench output (wrench=True) from >= 6 gauges")
    for name, pair in (("mass_kg", mass_kg), ("com_m", com_m), ("scales", scales),
                       ("noise", noise)):
        a, b = (float(t) for t in pair)
        if not (np.isfinite(a) and np.isfinite(b) and 0 < a <= b):
            raise CalibrationError(f"{name} must be a range 0 < low <= high, got {pair}")
    try:
        nl = float(nonlinearity)
    except (TypeError, ValueError):
        nl = float("nan")
    if not (np.isfinite(nl) and 0 <= nl < 1):
        raise CalibrationError(f"nonlinearity must be a fraction 0 <= x < 1 of each channel's "
                               f"spread, got {nonlinearity!r}")
    if nonlinearity_kind not in ("direction", "signal"):
        raise CalibrationError(f"nonlinearity_kind must be 'direction' or 'signal', got "
                               f"{nonlinearity_kind!r}")
    lo, hi = (float(t) for t in tilt_deg)
    if not 0 <= lo < hi <= 180:
        raise CalibrationError(f"tilt_deg must be 0 <= low < high <= 180, got {tilt_deg}")
    n = poses * readings
    weight = 9.81 * rng.uniform(*mass_kg)
    r_com = rng.normal(size=3)
    r_com *= rng.uniform(*com_m) / np.linalg.norm(r_com)
    L = lever_matrix(r_com)  # (6, 3): wrench = L F
    if wrench:
        p = 6
        S = L.T.copy()  # (3, 6): the wrench itself
    else:
        G = rng.normal(size=(6, p))
        S = L.T @ G  # (3, p) before the channel scales
        S *= (np.exp(rng.uniform(np.log(scales[0]), np.log(scales[1]), p))
              / np.linalg.norm(S, axis=0))
    ca, cb = np.cos(np.radians(lo)), np.cos(np.radians(hi))
    if sweep:
        # a smooth path: tilt and azimuth as slow random sinusoids over the band
        t = np.linspace(0.0, 1.0, n)
        w = _smooth_wander(n, rng)
        cz = cb + (ca - cb) * (0.5 + 0.5 * np.clip(w, -1, 1))
        phi = 2 * np.pi * (rng.uniform() + rng.uniform(1.0, 3.0) * t)
        pose = np.arange(n)
    else:
        cz = rng.uniform(cb, ca, poses)
        phi = rng.uniform(0, 2 * np.pi, poses)
        pose = np.repeat(np.arange(poses), readings)
    sz = np.sqrt(np.clip(1 - cz**2, 0, None))
    U = np.column_stack([sz * np.cos(phi), sz * np.sin(phi), cz])
    true_U = U.copy()
    if misalignment_deg > 0:
        for j in range(len(U)):
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            Kx = skew(axis)
            a = np.radians(misalignment_deg) * rng.normal()
            true_U[j] = (np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx) @ U[j]
    true_w = weight * (1 + mass_error * rng.normal())
    F = true_w * true_U[pose]
    lin = F @ S
    spread = weight * np.linalg.norm(S, axis=0)  # each channel's spread over the load sphere
    z0 = rng.normal(size=p) * spread * rng.uniform(0.1, 10.0, p)
    levels = spread * np.exp(rng.uniform(np.log(noise[0]), np.log(noise[1]), p))
    if wrench and gauges:
        # each gauge's response to the wrench; a sensor's rated torque is about its rated force
        # times a few centimetres (e.g. 80 N and 4 N*m), so torques weigh 1 / (5 cm)
        G = rng.normal(size=(6, int(gauges))) * np.r_[np.ones(3), np.full(3, 20.0)][:, None]
        g_levels = (weight * np.linalg.norm(S @ G, axis=0)
                    * np.exp(rng.uniform(np.log(noise[0]), np.log(noise[1]), int(gauges))))
        Gp = np.linalg.pinv(G)
        Z = z0 + lin + (rng.normal(size=(n, int(gauges))) * g_levels) @ Gp
        cov = Gp.T @ (g_levels[:, None] ** 2 * Gp)
    else:
        Z = z0 + lin + rng.normal(size=lin.shape) * levels
        cov = np.diag(levels**2)
    if nl > 0 and nonlinearity_kind == "signal":  # (drawn last, as below)
        a, b = rng.uniform(-1, 1, (2, Z.shape[1])) * nl
        x = lin / spread
        Z = Z + spread * (a * x**2 + b * x**3)
    elif nl > 0:  # (drawn last: the rest of the rig is the one drawn without it)
        Q = rng.normal(size=(Z.shape[1], 3, 3))
        Q = Q + Q.transpose(0, 2, 1)
        Q /= np.abs(np.linalg.eigvalsh(Q)).max(axis=1)[:, None, None]
        u = true_U[pose]
        Z = Z + nl * spread * np.einsum("ja,cab,jb->jc", u, Q, u)
    return RigData(Z=Z, pose=pose, stated_loads=weight * U, true_loads=F, directions=U, S=S,
                   offset=z0, magnitude=float(weight), noise_cov=cov)
