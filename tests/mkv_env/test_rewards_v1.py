"""MKV-v1 / MKVJam-v1: rewards whose maximum is the intended behaviour."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import mkv_env  # noqa: F401
from mkv_env.envs import COVERAGE_CELL_M
from mkv_env.policies import make_policy


def run(env_id, spec, seed, **kw):
    env = gym.make(env_id, **kw)
    policy = make_policy(spec, env, seed)
    obs, info = env.reset(seed=seed)
    rewards, infos = [], [info]
    done = False
    while not done:
        a, _ = policy.predict(obs)
        obs, r, term, trunc, info = env.step(a)
        rewards.append(r)
        infos.append(info)
        done = term or trunc
    env.close()
    return np.array(rewards), infos


@pytest.mark.parametrize("env_id", ["MKV-v1", "MKVJam-v1"])
def test_v1_passes_gymnasium_checker(env_id):
    env = gym.make(env_id)
    check_env(env.unwrapped, skip_render_check=True)


@pytest.mark.parametrize("env_id", ["MKV-v1", "MKVJam-v1"])
def test_teacher_beats_every_degenerate_policy(env_id):
    seeds = range(4_000_000, 4_000_004)
    ret = {spec: np.mean([run(env_id, spec, s)[0].sum() for s in seeds])
           for spec in ("teacher", "const:still", "const:circle", "const:reverse")}
    for spec in ("const:still", "const:circle", "const:reverse"):
        assert ret["teacher"] > ret[spec] + 5.0, (spec, ret)


def test_wander_v1_pays_new_cells_driving_forward_only():
    rewards, infos = run("MKV-v1", "const:reverse", 7)
    assert infos[-1]["cells_visited"] == 0          # reversing earns no coverage
    assert rewards.max() <= 0.0
    rewards, infos = run("MKV-v1", "teacher", 7)
    cells = infos[-1]["cells_visited"]
    # every coverage reward is one new cell; cells are bounded by the distance driven
    assert 10 < cells <= infos[-1]["distance_m"] / COVERAGE_CELL_M * 2 + 1
    assert np.sum(rewards > 0.5) == cells


def test_wander_v1_standing_still_pays_the_still_penalty_every_step():
    rewards, _ = run("MKV-v1", "const:still", 3)
    assert len(rewards) == 600
    np.testing.assert_allclose(rewards, -0.05)


def test_jam_v1_shaping_is_bounded_and_escape_is_terminal():
    rewards, infos = run("MKVJam-v1", "teacher", 11, time_penalty=0.0, stuck_penalty=0.0,
                         collision_penalty=0.0, escape_reward=0.0, shaping=1.0)
    # only the potential remains: it telescopes to phi(end) - phi(start) <= 1
    assert -1e-9 <= rewards.sum() <= 1.0 + 1e-9
    assert infos[-1]["escaped"]
    rewards, infos = run("MKVJam-v1", "teacher", 11)
    assert rewards[-1] > 9.0 and infos[-1]["escaped"]


def test_jam_v1_reverse_forever_earns_less_than_standing_still_plus_shaping():
    # reversing can collect at most the shaping (0.5) over standing still's time penalty
    still = run("MKVJam-v1", "const:still", 5)[0].sum()
    rev = run("MKVJam-v1", "const:reverse", 5)[0].sum()
    assert still == pytest.approx(-0.02 * 300, abs=0.01)   # the robot settles a little
    assert rev <= still + 0.5 + 1e-9


def test_v0_is_unchanged_by_v1():
    r0, _ = run("MKV-v0", "teacher", 2)
    assert "cells_visited" not in run("MKV-v0", "const:still", 2)[1][-1]
    assert r0.sum() > 20   # progress reward, as before


@pytest.mark.parametrize("kw", [{"coverage_reward": float("nan")}, {"still_penalty": "x"},
                                {"jam_penalty": None}])
def test_wander_v1_rejects_bad_weights(kw):
    with pytest.raises(ValueError, match="must be a finite number"):
        gym.make("MKV-v1", **kw)


@pytest.mark.parametrize("kw", [{"time_penalty": float("inf")}, {"shaping": "1"}])
def test_jam_v1_rejects_bad_weights(kw):
    with pytest.raises(ValueError, match="must be a finite number"):
        gym.make("MKVJam-v1", **kw)


def test_const_policy_spec():
    env = gym.make("MKV-v1")
    assert tuple(make_policy("const:circle", env).predict(np.zeros(10))[0]) == (2, 0)
    assert tuple(make_policy("const:0,2", env).predict(np.zeros((3, 10)))[0][2]) == (0, 2)
    from mkv_env.policies import PolicySpecError
    for bad in ("const:", "const:3,1", "const:1", "const:spin", "const:a,b"):
        with pytest.raises(PolicySpecError, match="is not an action"):
            make_policy(bad, env)
