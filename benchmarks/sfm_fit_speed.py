"""Fit and per-observation speed of the eigenspace projector, against named peers in the same run.

Targets: fit on 100,000 samples in under 0.1 s; per-observation prediction at least 10x
faster than an SB3 PPO MlpPolicy ``predict`` on an observation of the same size.

Peers, timed here on the same data:
- fit: ``numpy.linalg.svd`` and ``scipy.linalg.svd`` (thin) of the same standardised matrix, i.e.
  the obvious implementation of the paper's batch SVD (standardisation included in their time);
- per observation: ``stable_baselines3.PPO("MlpPolicy").predict`` (default 64-64 MLP, CPU,
  deterministic) when stable-baselines3 imports; skipped otherwise.

Run: ``.venv/bin/python benchmarks/sfm_fit_speed.py [--samples N] [--features F]
[--blas-threads K]``.
Times are the best of ``--repeat`` runs (least disturbed by other load on the machine).
``--blas-threads`` sets OPENBLAS/OMP/MKL thread counts before numpy is imported: on a shared,
loaded machine multi-threaded BLAS can be several times slower than one thread (busy-waiting
threads), for us and the peers alike.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _parse(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--features", type=int, default=40)
    ap.add_argument("--commands", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--blas-threads", type=int, default=None,
                    help="BLAS threads (default: leave the environment as it is)")
    args = ap.parse_args(argv)
    if args.blas_threads is not None:
        if "numpy" in sys.modules:
            raise SystemExit("--blas-threads must be set before numpy is imported")
        for var in _THREAD_VARS:
            os.environ[var] = str(args.blas_threads)
    return args


if __name__ == "__main__":
    _ARGS = _parse(sys.argv[1:])

import numpy as np  # noqa: E402  (after the BLAS thread variables are set)
import scipy.linalg  # noqa: E402

from sfm_learn.eigenspace.projector import EigenspaceProjector  # noqa: E402


def best_time(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def per_call(fn, calls, repeat):
    return best_time(lambda: [fn() for _ in range(calls)], repeat) / calls


def synthetic(n_samples, n_features, n_commands, seed=0):
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n_samples, 6))
    x = z @ rng.standard_normal((6, n_features + n_commands))
    x += 0.05 * rng.standard_normal(x.shape)
    return x[:, :n_features].copy(), x[:, n_features:].copy()


def standardised_svd(svd, known, missing):
    x = np.hstack([known, missing])
    x = (x - x.mean(axis=0)) / x.std(axis=0)
    return svd(x)


def main(args):
    blas = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    print(f"BLAS threads: {blas}; cpus: {os.cpu_count()}; load average: "
          f"{os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else f"BLAS threads: {blas}")

    known, missing = synthetic(args.samples, args.features, args.commands)
    shape = f"{args.samples} x ({args.features}+{args.commands})"
    rows = []

    t_fit = best_time(lambda: EigenspaceProjector().fit(known, missing), args.repeat)
    t_np = best_time(lambda: standardised_svd(
        lambda x: np.linalg.svd(x, full_matrices=False), known, missing), args.repeat)
    t_sp = best_time(lambda: standardised_svd(
        lambda x: scipy.linalg.svd(x, full_matrices=False, check_finite=False), known, missing),
        args.repeat)
    rows.append((f"fit {shape}", "EigenspaceProjector.fit", t_fit, None))
    rows.append(("", "peer: numpy.linalg.svd (thin)", t_np, t_np / t_fit))
    rows.append(("", "peer: scipy.linalg.svd (thin)", t_sp, t_sp / t_fit))

    batch = 1000
    proj_inc = EigenspaceProjector()
    proj_inc.partial_fit(known[:batch], missing[:batch])
    t_pf = best_time(lambda: proj_inc.partial_fit(known[:batch], missing[:batch]), args.repeat)
    rows.append((f"partial_fit {batch} rows", "EigenspaceProjector.partial_fit", t_pf, None))

    proj = EigenspaceProjector().fit(known, missing)
    obs = known[123].astype(np.float32)
    t_rec = per_call(lambda: proj.reconstruct(obs), 2000, args.repeat)
    rows.append(("per observation", "EigenspaceProjector.reconstruct", t_rec, None))

    # the whole run-time path of the real policy on a real MK-V observation: SfMPolicy.predict
    # (default features: traces + previous command, reconstruct, quantise) vs SB3 PPO predict on
    # the same observation of the same env
    import gymnasium as gym

    from mkv_env.recorder import record
    from sfm_learn.eigenspace.policy import fit_policy

    data = record("MKV-v0", "teacher", 2, 0, {"max_episode_steps": 200})
    policy = fit_policy(data)
    env = gym.make("MKV-v0")
    obs, _ = env.reset(seed=0)
    policy.reset()
    t_pol = per_call(lambda: policy.predict(obs), 2000, args.repeat)
    rows.append(("", f"SfMPolicy.predict (MKV obs, {policy.feature_spec.n_features} feats)",
                 t_pol, None))

    try:
        import torch
        from stable_baselines3 import PPO
    except ImportError as exc:  # optional peer
        print(f"(stable-baselines3 peer skipped: {exc})")
    else:
        ppo = PPO("MlpPolicy", env, device="cpu", seed=0)
        t_ppo = per_call(lambda: ppo.predict(obs, deterministic=True), 300, args.repeat)
        rows.append(("", f"peer: SB3 PPO MlpPolicy.predict (torch {torch.get_num_threads()} thr)",
                     t_ppo, None))
        rows[-3] = (*rows[-3][:3], t_ppo / t_rec)
        rows[-2] = (*rows[-2][:3], t_ppo / t_pol)
        print(f"predict target >= 10x faster than PPO: "
              f"{'met' if t_ppo / t_pol >= 10 else 'MISSED'} ({t_ppo / t_pol:.1f}x)")

    print(f"{'case':<24} {'implementation':<52} {'time':>11} {'peer/ours':>10}")
    for case, impl, t, ratio in rows:
        unit = f"{t * 1e3:8.2f} ms" if t >= 1e-3 else f"{t * 1e6:8.2f} us"
        print(f"{case:<24} {impl:<52} {unit:>11} {'' if ratio is None else f'{ratio:9.1f}x':>10}")
    verdict = "met" if t_fit < 0.1 else "MISSED"
    print(f"\nfit target < 100 ms: {verdict} ({t_fit * 1e3:.1f} ms); "
          f"chosen rank {proj.n_components_}")


if __name__ == "__main__":
    main(_ARGS)
