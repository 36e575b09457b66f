"""SB3VecEnv: SB3's VecEnv API over the native vector env, equal to DummyVecEnv of single envs."""

import warnings

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor  # noqa: E402

from mkv_env.sb3_vec import SB3VecEnv  # noqa: E402


def _dummy(env_id, n, seed, **kw):
    def make():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            return gym.make(env_id, **kw)

    venv = DummyVecEnv([make for _ in range(n)])
    venv.seed(seed)
    return venv


@pytest.mark.parametrize("env_id", ["MKVJam-v1", "MKV-v0"])
def test_same_steps_as_dummy_vec_env(env_id):
    a = SB3VecEnv(env_id, n_envs=3, seed=7, max_episode_steps=30)
    b = _dummy(env_id, 3, 7, max_episode_steps=30)
    assert np.array_equal(a.reset(), b.reset())
    rng = np.random.default_rng(0)
    dones = 0
    for _ in range(80):
        act = rng.integers(0, 3, size=(3, 2))
        oa, ra, da, ia = a.step(act)
        ob, rb, db, ib = b.step(act)
        assert oa.tobytes() == ob.tobytes() and np.array_equal(ra, rb)
        assert np.array_equal(da, db)
        for x, y in zip(ia, ib, strict=False):
            assert x.keys() == y.keys()
            for k in y:
                assert np.array_equal(x[k], y[k]), k
        dones += int(da.sum())
    assert dones >= 3
    assert len(a.get_attr("sensor_names")) == 3
    a.close()


def test_ppo_trains_on_it():
    venv = VecMonitor(SB3VecEnv("MKV-v1", n_envs=4, seed=0, max_episode_steps=20))
    model = PPO("MlpPolicy", venv, n_steps=16, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=128)
    assert model.num_timesteps >= 128
    assert len(model.ep_info_buffer) > 0  # episodes ended and were reported


def test_reset_gives_each_env_its_own_options():
    """As SB3's DummyVecEnv: set_options([...]) gives env i options[i] (here: its scenario)."""
    from mkv_env.sb3_vec import SB3VecEnv

    venv = SB3VecEnv("MKVJam-v0", n_envs=3, seed=0)
    seen = []
    for e in venv.venv.envs:
        orig = e.reset

        def rec(*a, _orig=orig, **k):
            seen.append(k.get("options"))
            return _orig(*a, **k)

        e.reset = rec
    venv.set_options([{"a": 1}, None, {"a": 2}])
    venv.reset()
    assert sorted(map(repr, seen)) == sorted(map(repr, [{"a": 1}, None, {"a": 2}]))
    venv.close()
