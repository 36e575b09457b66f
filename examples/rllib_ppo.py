"""RLlib PPO on the MK-V (``mkv_env:MKV-v1``) with env runners.

Needs RLlib, which is *not* in this package's extras: ``ray[rllib]`` pins gymnasium 1.2.2 while the
package is developed on gymnasium 1.4 (both satisfy its ``gymnasium>=1.0,<2``). Use its own
environment::

    python -m venv rl && rl/bin/pip install torch==2.13.0 'ray[rllib]==2.60.0' -e .
    rl/bin/python examples/rllib_ppo.py --iterations 5 --env-runners 2

The env id carries its module (``"mkv_env:MKV-v1"``): each env runner is a separate process, and
the prefix makes Gymnasium import ``mkv_env`` there, which registers the ids (a plain ``"MKV-v1"``
fails inside the runners with ``NameNotFound``).
"""

from __future__ import annotations

import argparse


def build(env_id: str = "mkv_env:MKV-v1", env_runners: int = 2, seed: int = 0,
          train_batch: int = 2000):
    """An RLlib PPO algorithm on ``env_id`` with ``env_runners`` remote env runners."""
    from ray.rllib.algorithms.ppo import PPOConfig

    config = (
        PPOConfig()
        .environment(env_id)
        .env_runners(num_env_runners=env_runners, num_envs_per_env_runner=1,
                     rollout_fragment_length="auto")
        .training(train_batch_size_per_learner=train_batch, minibatch_size=250,
                  num_epochs=4, lr=3e-4, gamma=0.99)
        .debugging(seed=seed)
    )
    return config.build_algo()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="mkv_env:MKV-v1")
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--env-runners", type=int, default=2)
    args = ap.parse_args()
    import ray

    # a new local Ray of its own ("local"): not RAY_ADDRESS's, nor the one a dead `ray start`
    # left in /tmp/ray/ray_current_cluster (which would refuse num_cpus)
    ray.init(address="local", num_cpus=max(2, args.env_runners + 1), include_dashboard=False,
             log_to_driver=False)
    algo = build(args.env, args.env_runners)
    try:
        for i in range(args.iterations):
            result = algo.train()
            runners = result.get("env_runners", {})
            print(f"iteration {i + 1}: env steps {runners.get('num_env_steps_sampled_lifetime')}"
                  f", mean episode return {runners.get('episode_return_mean')}", flush=True)
    finally:
        algo.stop()
        ray.shutdown()


if __name__ == "__main__":
    main()
