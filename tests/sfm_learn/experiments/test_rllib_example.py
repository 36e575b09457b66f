"""examples/rllib_ppo.py: one RLlib PPO iteration with 2 env runners (skipped without RLlib,
which is not part of this package's extras: see docs/scale.md)."""

import importlib.util
import pathlib

import pytest

pytest.importorskip("ray.rllib")

EXAMPLE = pathlib.Path(__file__).resolve().parents[3] / "examples" / "rllib_ppo.py"


def test_one_iteration_with_two_env_runners():
    import ray

    spec = importlib.util.spec_from_file_location("rllib_ppo", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    ray.init(address="local", num_cpus=3, include_dashboard=False, log_to_driver=False)
    try:
        algo = mod.build("mkv_env:MKV-v1", env_runners=2, train_batch=500)
        result = algo.train()
        assert result["env_runners"]["num_env_steps_sampled_lifetime"] >= 500
        algo.stop()
    finally:
        ray.shutdown()
