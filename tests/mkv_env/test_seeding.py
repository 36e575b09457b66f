"""EpisodeSeeds makes SB3's evaluate_policy run mkv eval's episodes: the same per-episode returns
for the same SB3 zip (without it they differ)."""

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: E402

import mkv_env  # noqa: E402, F401
import sfm_learn  # noqa: E402, F401
from mkv_env.seeding import EpisodeSeeds  # noqa: E402


def test_evaluate_policy_with_episode_seeds_gives_mkv_evals_returns(tmp_path):
    from sfm_learn.evaluation import evaluate

    model = PPO("MlpPolicy", gym.make("MKVJam-v1"), n_steps=64, batch_size=64, seed=3,
                device="cpu", policy_kwargs={"net_arch": [16]})
    model.learn(128)
    model.save(tmp_path / "ppo.zip")
    seed, n = 5, 4
    ours = evaluate("MKVJam-v1", f"sb3:PPO:{tmp_path / 'ppo.zip'}", n, seed)
    mkv_returns = [r.episode_return for r in ours.records]
    venv = DummyVecEnv([lambda: EpisodeSeeds(gym.make("MKVJam-v1"), seed=seed)])
    returns, _ = evaluate_policy(PPO.load(tmp_path / "ppo.zip", device="cpu"), venv,
                                 n_eval_episodes=n, return_episode_rewards=True)
    np.testing.assert_allclose(returns, mkv_returns, rtol=1e-6)
    plain = DummyVecEnv([lambda: gym.make("MKVJam-v1")])
    plain.seed(seed)
    other, _ = evaluate_policy(PPO.load(tmp_path / "ppo.zip", device="cpu"), plain,
                               n_eval_episodes=n, return_episode_rewards=True)
    assert not np.allclose(other, mkv_returns)  # what a user got before


@pytest.mark.parametrize("bad", [-1, 1.5, True, "3"])
def test_bad_seed_is_refused(bad):
    with pytest.raises(ValueError, match="seed must be"):
        EpisodeSeeds(gym.make("MKV-v0"), seed=bad)
