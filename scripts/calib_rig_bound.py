"""How well can any estimator calibrate a static-pose rig with only a few known loads?

The Cramer-Rao bound of the joint model, against least squares with every load known, on the
rigs of ``scripts/calib_study.py`` (12 poses of a 3.03 N proof mass, 100 samples per pose,
Gaussian noise 0.05 counts, a random 3 x 8 shape, k poses with known loads). Pose means are
sufficient statistics (iid Gaussian noise), so the model is: pose mean ``zbar_j = A m_j + o`` with
``m_j`` known for the k known poses and ``m_j = g u(theta_j, phi_j)`` (two unknown angles each,
nuisance parameters) for the others; ``A`` (8 x 3) and ``o`` (8) are the calibration. The
magnitude ``g`` is the known loads' (all poses hold the same proof mass, so the known loads tie
it; ``bounds(..., magnitude_known=False)`` frees it, which throws that tie away). The load error
of a calibration on a test load m is ``-C (dA m + do)`` to first order
(``C = A^+``); its mean square over 300 test loads is evaluated under the bound's covariance and
under the all-known least squares covariance, and the ratio of their square roots is printed per
rig (median and 5-95 % range over rigs). Then a Monte-Carlo check on a few rigs: many noisy
logs each, the joint fit (accuracies stated: ``known_samples=100``) and least squares with every
load known, each against its own bound (an efficient estimator reaches it), and their ratio.

    python scripts/calib_rig_bound.py [--rigs 200] [--mc-rigs 12] [--draws 30] [--design spread]

``--design spread`` puts the known loads on the most spread poses
(:func:`calib.routes.joint.choose_known_poses`) instead of the first (random) ones.

Writes nothing; docs/calib.md quotes its output.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.estimators.least_squares import fit_least_squares  # noqa: E402
from calib.routes.joint import choose_known_poses, fit_joint  # noqa: E402
from calib.simulation.simulate import random_shape, sample_directions  # noqa: E402

POSES, SAMPLES, NOISE, LOAD = 12, 100, 0.05, 3.03


#: Which poses get the known loads: "first" (random poses) or "spread" (choose_known_poses).
DESIGN = "first"


def rig(seed, known: int = 4):
    """The study's rig for ``seed``: shape S (3, 8), offsets, loads F (12, 3) with the poses that
    get known loads first, and the generator."""
    rng = np.random.default_rng(seed)
    S = random_shape(3, 8, rng, condition=rng.uniform(1, 10)) * 10
    z0 = rng.normal(size=8) * 20
    F = LOAD * sample_directions(POSES, 3, rng)
    if DESIGN == "spread":
        first = choose_known_poses(F, known)
        F = F[np.r_[first, np.setdiff1d(np.arange(POSES), first)]]
    return S, z0, F, rng


def _unit(th, ph):
    return np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def _load_error_ms(A, cov, test):
    """Mean over test loads and components of the squared first-order load error."""
    C = np.linalg.pinv(A)  # (3, 8)
    p = A.shape[0]
    total = 0.0
    for m in test:
        G = np.zeros((3, 3 * p + p))
        for a in range(p):
            G[:, a * 3:(a + 1) * 3] = -np.outer(C[:, a], m)
            G[:, 3 * p + a] = -C[:, a]
        total += np.trace(G @ cov @ G.T)
    return total / len(test) / 3


def bounds(seed: int, known: int, magnitude_known: bool) -> tuple[float, float]:
    """RMS load error [N] (vector length, over 300 test loads) under (the joint model's
    Cramer-Rao bound, the all-known bound) for rig ``seed``."""
    S, _, F, _ = rig(seed, known)
    A = S.T
    p = A.shape[0]
    s2 = NOISE**2 / SAMPLES  # variance of a pose mean
    unknown = list(range(known, POSES))
    npar = 4 * p + 2 * len(unknown) + (0 if magnitude_known else 1)
    J = np.zeros((POSES * p, npar))
    eps = 1e-7
    for j in range(POSES):
        rows = slice(p * j, p * (j + 1))
        for a in range(p):
            J[p * j + a, a * 3:(a + 1) * 3] = F[j]
            J[p * j + a, 3 * p + a] = 1.0
        if j >= known:  # unknown direction: two angles (nuisance), and the magnitude
            t = 4 * p + 2 * unknown.index(j)
            u = F[j] / LOAD
            th, ph = np.arccos(np.clip(u[2], -1, 1)), np.arctan2(u[1], u[0])
            d_th = (_unit(th + eps, ph) - _unit(th - eps, ph)) / (2 * eps)
            d_ph = (_unit(th, ph + eps) - _unit(th, ph - eps)) / (2 * eps)
            J[rows, t] = A @ d_th * LOAD
            J[rows, t + 1] = A @ d_ph * LOAD
            if not magnitude_known:
                J[rows, -1] = A @ u
    cov = np.linalg.pinv(J.T @ J / s2)[:4 * p, :4 * p]
    Jl = J[:, :4 * p]
    cov_ls = np.linalg.inv(Jl.T @ Jl / s2)
    test = LOAD * sample_directions(300, 3, np.random.default_rng(10_000 + seed))
    return (float(np.sqrt(3 * _load_error_ms(A, cov, test))),
            float(np.sqrt(3 * _load_error_ms(A, cov_ls, test))))


def bound_ratio(seed: int, known: int, magnitude_known: bool) -> float:
    """The joint model's bound over the all-known bound, for rig ``seed``."""
    b, b_all = bounds(seed, known, magnitude_known)
    return b / b_all


def monte_carlo(seed: int, known: int, draws: int) -> tuple[float, float]:
    """RMS load error vector length [N] over ``draws`` noisy logs of one rig: (joint fit with
    ``known_samples`` stated, least squares with every load known)."""
    S, z0, F, _ = rig(seed, known)
    test = LOAD * sample_directions(300, 3, np.random.default_rng(10_000 + seed))
    Zt = test @ S + z0
    ej, el = [], []
    for d in range(draws):
        rng = np.random.default_rng(seed * 1000 + d)
        Z = np.repeat(F @ S + z0, SAMPLES, axis=0) + rng.normal(size=(POSES * SAMPLES, 8)) * NOISE
        Zk = Z.reshape(POSES, SAMPLES, 8)[:known].mean(axis=1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            j = fit_joint(Z, Zk, F[:known], known_samples=SAMPLES)
            ls = fit_least_squares(Z, np.repeat(F, SAMPLES, axis=0), bias=True)
        ej.append(np.mean(np.sum((j.apply(Zt) - test) ** 2, axis=1)))
        el.append(np.mean(np.sum((ls.apply(Zt) - test) ** 2, axis=1)))
    return float(np.sqrt(np.mean(ej))), float(np.sqrt(np.mean(el)))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rigs", type=int, default=200)
    ap.add_argument("--mc-rigs", type=int, default=12, help="rigs of the Monte-Carlo check")
    ap.add_argument("--draws", type=int, default=30, help="noisy logs per Monte-Carlo rig")
    ap.add_argument("--design", choices=("first", "spread"), default="first",
                    help="known loads on the first (random) poses or on the most spread ones")
    a = ap.parse_args(argv)
    global DESIGN
    DESIGN = a.design
    print(f"known poses: {a.design}")
    print("Cramer-Rao bound on the load error, relative to the bound with all 12 loads known "
          f"({a.rigs} rigs): median [5 %, 95 %]")
    for k in (2, 3, 4, 6):
        r = [bound_ratio(s, k, True) for s in range(a.rigs)]
        print(f"  {k} known loads: {np.median(r):.2f} [{np.percentile(r, 5):.2f}, "
              f"{np.percentile(r, 95):.2f}]")
    print(f"\nMonte Carlo, 4 known loads ({a.mc_rigs} rigs x {a.draws} logs): RMS load error "
          "against each estimator's bound, and joint / least squares all-known")
    eff_j, eff_l, ratio = [], [], []
    for s in range(a.mc_rigs):
        mj, ml = monte_carlo(s, 4, a.draws)
        bj, bl = bounds(s, 4, True)
        eff_j.append(mj / bj)
        eff_l.append(ml / bl)
        ratio.append(mj / ml)
        print(f"  rig {s:2d}: joint {mj:.2e} N (bound {bj:.2e}), least squares {ml:.2e} N "
              f"(bound {bl:.2e}), ratio {mj / ml:.2f}")
    print(f"  median: joint / its bound {np.median(eff_j):.2f}, least squares / its bound "
          f"{np.median(eff_l):.2f}, joint / least squares {np.median(ratio):.2f} "
          f"[{min(ratio):.2f}, {max(ratio):.2f}]")


if __name__ == "__main__":
    main()
