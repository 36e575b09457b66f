"""The recorder: what it stores matches what the env did, step by step."""

import gymnasium as gym
import numpy as np
import pytest

import mkv_env  # noqa: F401
from mkv_env.recorder import make_env, policy_seed, record, summarize


@pytest.fixture(scope="module")
def wander():
    return record("MKV-v0", "teacher", episodes=2, seed=5, env_kwargs={"max_episode_steps": 150})


def test_replaying_the_actions_reproduces_every_row(wander):
    """Observations, rewards, flags and info come from the env, aligned with the actions."""
    env = gym.make("MKV-v0", max_episode_steps=150)
    for e, rows in enumerate(wander.episode_slices()):
        obs, _ = env.reset(seed=int(wander["episode_seeds"][e]))
        for r in range(rows.start, rows.stop):
            assert np.array_equal(wander["observations"][r], obs)
            obs, reward, term, trunc, info = env.step(wander["actions"][r])
            assert wander["rewards"][r] == reward
            assert (wander["terminated"][r], wander["truncated"][r]) == (term, trunc)
            assert wander["distance_m"][r] == info["distance_m"]
            assert tuple(wander["pose"][r]) == info["pose"]
            for k in ("stuck", "bumped", "collision", "in_jam", "jams", "escapes", "collisions"):
                assert wander[k][r] == info[k], k
        assert np.array_equal(wander["final_observations"][e], obs)
        assert wander["truncated"][rows.stop - 1]
    assert "escaped" not in wander and wander.metadata["episode_scenarios"] is None


def test_jam_episodes_end_on_escape():
    data = record("MKVJam-v0", "teacher", episodes=3, seed=2)
    for rows in data.episode_slices():
        esc = data["escaped"][rows]
        assert esc[-1] and not esc[:-1].any()
        assert data["terminated"][rows.stop - 1] and not data["terminated"][rows][:-1].any()
    assert all(s in mkv_env.jams.SCENARIOS for s in data.metadata["episode_scenarios"])
    s = summarize(data)
    assert s["episodes"] == 3 and s["escapes"] == 3 and s["jams"] >= 3
    assert s["steps"] == data.n_steps and 0 <= s["stuck_fraction"] <= 1


def test_episode_i_does_not_depend_on_earlier_episodes(wander):
    alone = record("MKV-v0", "teacher", episodes=1, seed=6, env_kwargs={"max_episode_steps": 150})
    rows = wander.episode_slices()[1]
    assert np.array_equal(alone["actions"], wander["actions"][rows])
    assert np.array_equal(alone["observations"], wander["observations"][rows])


def test_policy_objects_and_max_steps():
    class Forward:
        def predict(self, observation, state=None, episode_start=None, deterministic=True):
            return np.array([2, 1]), None

    data = record("MKV-v0", Forward(), episodes=2, seed=0, max_steps=7)
    assert list(data["episode_lengths"]) == [7, 7] and data["truncated"][[6, 13]].all()
    assert (data["actions"] == [2, 1]).all() and data.metadata["policy"] == "Forward"


def test_bad_arguments():
    with pytest.raises(ValueError, match="cannot make env"):
        make_env("NoSuchEnv-v0")
    with pytest.raises(ValueError, match="episodes"):
        record("MKV-v0", "teacher", episodes=0)
    with pytest.raises(ValueError, match="seed"):
        record("MKV-v0", "teacher", episodes=1, seed=-1)


def test_policy_seed_is_used_per_episode():
    """The random policy is re-seeded per episode from the env seed: reproducible on its own."""
    a = record("MKV-v0", "random", episodes=2, seed=3, env_kwargs={"max_episode_steps": 20})
    b = record("MKV-v0", "random", episodes=1, seed=4, env_kwargs={"max_episode_steps": 20})
    assert np.array_equal(a["actions"][20:], b["actions"])
    assert policy_seed(3) != policy_seed(4)


class CountingPolicy:
    """A recurrent-style policy: its state counts the steps of the episode, and it drives forward
    only when the state handed back to it is the count it returned (reverse otherwise)."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        if episode_start:
            assert state is None  # a new episode starts without memory
        count = 0 if state is None else state
        self.seen = getattr(self, "seen", []) + [count]
        return np.array([2 if count == len(self.seen) - 1 - self.offset else 0, 1]), count + 1

    def reset(self, seed=None):
        self.offset = len(getattr(self, "seen", []))


def test_the_runner_hands_the_policy_its_state_back():
    policy = CountingPolicy()
    data = record("MKVJam-v0", policy, 3, 0, {"max_episode_steps": 30})
    # every step drove forward: the state came back each step and restarted every episode
    assert data.n_steps > 3 and np.all(data["actions"][:, 0] == 2)
    starts = np.flatnonzero(data["step"] == 0)
    assert [policy.seen[i] for i in starts] == [0, 0, 0]


def test_min_steps_tops_up_episodes_that_ended_early():
    """A jam env's teacher escapes in a few dozen steps: min_steps records further episodes
    (the next seeds, each capped at what is missing) until exactly that many steps are there."""
    short = record("MKVJam-v1", "teacher", 1, seed=70_000, max_steps=300)
    assert short.n_steps < 300  # the teacher escaped early
    full = record("MKVJam-v1", "teacher", 1, seed=70_000, max_steps=300, min_steps=300)
    assert full.n_steps == 300 and full.n_episodes > 1
    seeds = full.arrays["episode_seeds"].tolist()
    assert seeds == list(range(70_000, 70_000 + full.n_episodes))
    n0 = short.n_steps  # the first episode is the same recording
    assert np.array_equal(full.arrays["observations"][:n0], short.arrays["observations"])


def test_min_steps_leaves_a_recording_that_reaches_it_unchanged():
    a = record("MKV-v1", "teacher", 2, seed=71_000, max_steps=50)
    b = record("MKV-v1", "teacher", 2, seed=71_000, max_steps=50, min_steps=100)
    assert a.n_steps == b.n_steps == 100
    for k, v in a.arrays.items():
        assert np.array_equal(v, b.arrays[k]), k


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "10"])
def test_min_steps_must_be_a_positive_integer(bad):
    with pytest.raises(ValueError, match="min_steps must be a positive integer"):
        record("MKV-v1", "teacher", 1, seed=0, max_steps=5, min_steps=bad)
