"""SB3's predict contract for the mkv_env policies: one observation or a batch (n_envs, obs_dim),
per-env state and random streams, per-env episode_start; evaluate_policy on a vector env of 2."""

import gymnasium as gym
import numpy as np
import pytest

import mkv_env  # noqa: F401
from mkv_env.batching import env_rng, episode_starts
from mkv_env.policies import RandomPolicy, make_policy
from mkv_env.script import ScriptPolicy
from mkv_env.teacher import ScriptedTeacher

SCRIPT = "0.0 forward off\n0.5 reverse left\n1.2 forward right\n"
# the brief's exact call: gym.make without Monitor (evaluate_policy warns, and still counts right)
no_monitor = pytest.mark.filterwarnings("ignore:Evaluation environment is not wrapped")


def observations(n_steps, n_envs, seed=0):
    """Synthetic readings (n_steps, n_envs, 10): moving forward, now and then a front bump."""
    rng = np.random.default_rng(seed)
    o = np.zeros((n_steps, n_envs, 10), dtype=np.float32)
    o[..., 0] = rng.integers(0, 20, (n_steps, n_envs))
    o[..., 1] = o[..., 0] * 1.2
    o[..., 4] = rng.random((n_steps, n_envs)) < 0.05
    o[..., 7] = 0.05
    return o


@no_monitor
@pytest.mark.parametrize("spec", ["teacher", "random", "script"])
def test_evaluate_policy_with_a_dummy_vec_env_of_two(spec, tmp_path):
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.vec_env import DummyVecEnv

    if spec == "script":
        (tmp_path / "s.txt").write_text(SCRIPT)
        spec = f"script:{tmp_path / 's.txt'}"
    venv = DummyVecEnv([lambda: gym.make("MKVJam-v0")] * 2)
    venv.seed(3)
    policy = make_policy(spec, venv.envs[0], seed=0)
    rewards, lengths = evaluate_policy(policy, venv, n_eval_episodes=4,
                                       return_episode_rewards=True)
    venv.close()
    assert len(rewards) == 4 and all(np.isfinite(rewards)) and all(0 < n <= 300 for n in lengths)


@no_monitor
def test_the_teacher_escapes_in_evaluate_policy():
    """Not only runs: per-env timers make the teacher as good batched as alone."""
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.vec_env import DummyVecEnv

    venv = DummyVecEnv([lambda: gym.make("MKVJam-v0")] * 2)
    venv.seed(100)
    _, lengths = evaluate_policy(ScriptedTeacher(seed=0), venv, n_eval_episodes=6,
                                 return_episode_rewards=True)
    venv.close()
    assert np.mean(np.array(lengths) < 300) >= 0.8  # escaped before the time limit


def per_env_actions(policy, obs, starts):
    """Run a policy over (n_steps, n_envs, 10) observations; actions (n_steps, n_envs, 2)."""
    return np.stack([policy.predict(o, episode_start=s)[0]
                     for o, s in zip(obs, starts, strict=True)])


@pytest.mark.parametrize("make", [
    lambda: ScriptedTeacher(seed=5, wander_rate_hz=2.0),
    lambda: RandomPolicy(seed=5),
])
def test_each_env_has_its_own_stream_whatever_the_batch_size(make):
    obs = observations(200, 3)
    starts = np.zeros((200, 3), dtype=bool)
    starts[0] = True
    three = per_env_actions(make(), obs, starts)
    two = per_env_actions(make(), obs[:, :2], starts[:, :2])
    single = make()
    alone = np.stack([single.predict(o, episode_start=(k == 0))[0]
                      for k, o in enumerate(obs[:, 0])])
    assert three.shape == (200, 3, 2)
    np.testing.assert_array_equal(three[:, 0], alone)      # env 0 = the single-env policy
    np.testing.assert_array_equal(three[:, :2], two)       # env 1 independent of env 2
    same_obs = per_env_actions(make(), np.repeat(obs[:, :1], 2, axis=1), starts[:, :2])
    assert not np.array_equal(same_obs[:, 0], same_obs[:, 1])  # streams differ


def test_env_streams_are_documented_spawns():
    root = np.random.SeedSequence(5)
    a = env_rng(root, 0).random(3)
    np.testing.assert_array_equal(a, np.random.default_rng(5).random(3))
    b = env_rng(root, 2).random(3)
    np.testing.assert_array_equal(b, np.random.default_rng(
        np.random.SeedSequence(5).spawn(3)[2]).random(3))
    np.testing.assert_array_equal(ScriptedTeacher(seed=5).rng.random(3), a)


def test_episode_start_resets_only_its_env():
    """Env 1 restarts its script; env 0 runs on."""
    p = ScriptPolicy([0.0, 0.3], [[2, 1], [0, 0]])
    batch = np.zeros((2, 10))
    for k in range(5):
        a, state = p.predict(batch, episode_start=np.array([k == 0, k == 0]))
    assert state is None and a.tolist() == [[0, 0], [0, 0]]
    a, _ = p.predict(batch, episode_start=np.array([False, True]))
    assert a.tolist() == [[0, 0], [2, 1]]

    t = ScriptedTeacher(seed=0, wander_rate_hz=0.0)
    bumped = np.zeros((2, 10))
    bumped[:, 0], bumped[:, 1], bumped[:, 7] = 18, 22, 0.05
    t.predict(bumped, episode_start=[True, True])
    bumped[:, 4] = 1.0
    a, _ = t.predict(bumped)
    assert a[:, 0].tolist() == [0, 0]  # both back off
    bumped[:, 4] = 0.0
    a, _ = t.predict(bumped, episode_start=np.array([False, True]))
    assert a[:, 0].tolist() == [0, 2]  # env 1 starts over, cruising


def test_a_batch_after_single_observations_keeps_env_0():
    t = ScriptedTeacher(seed=1, wander_rate_hz=3.0)
    alone = ScriptedTeacher(seed=1, wander_rate_hz=3.0)
    obs = observations(60, 2)
    for k in range(30):
        assert np.array_equal(t.predict(obs[k, 0], episode_start=k == 0)[0],
                              alone.predict(obs[k, 0], episode_start=k == 0)[0])
    for k in range(30, 60):  # env 1 joins; env 0 goes on where it was
        a, _ = t.predict(obs[k], episode_start=np.array([False, k == 30]))
        assert np.array_equal(a[0], alone.predict(obs[k, 0])[0])


@pytest.mark.parametrize("policy", [ScriptedTeacher(seed=0), RandomPolicy(seed=0),
                                    ScriptPolicy([0.0], [[2, 1]])])
def test_bad_shapes_are_one_line_value_errors(policy):
    with pytest.raises(ValueError, match="episode_start"):
        policy.predict(np.zeros((3, 10)), episode_start=np.array([True, False]))
    with pytest.raises(ValueError, match="observation must have shape"):
        policy.predict(np.zeros((2, 3, 10)))
    a, state = policy.predict(np.zeros((3, 10)), episode_start=True)
    assert a.shape == (3, 2) and a.dtype == np.int64 and state is None


def test_episode_starts():
    assert episode_starts(None, 2).tolist() == [False, False]
    assert episode_starts(True, 3).tolist() == [True] * 3
    assert episode_starts(np.array([True]), 2).tolist() == [True, True]
    assert episode_starts([0, 1], 2).tolist() == [False, True]
