"""Gymnasium/SB3 conformance, determinism, validation, rendering, soak and memory."""

import gc
import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest
from conftest import FWD, OFF, open_floor, place, run
from gymnasium.utils.env_checker import check_env

import mkv_env  # noqa: F401
from mkv_env.jams import scenario_name

IDS = ["MKV-v0", "MKVJam-v0"]


@pytest.mark.parametrize("env_id", IDS)
def test_gymnasium_check_env_passes_without_warnings(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    env.close()


@pytest.mark.parametrize("env_id", IDS)
def test_sb3_check_env_passes_without_warnings(env_id):
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    env = gym.make(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sb3_checker.check_env(env, warn=True)


def test_string_entry_point_id_resolves():
    env = gym.make("mkv_env:MKV-v0")
    assert env.spec.id == "MKV-v0" and env.spec.max_episode_steps == 600
    assert gym.make("MKVJam-v0").spec.max_episode_steps == 300


def test_async_vector_env_runs():
    envs = gym.make_vec("MKVJam-v0", num_envs=2, vectorization_mode="async")
    obs, info = envs.reset(seed=[1, 2])
    assert obs.shape == (2, 10) and obs.dtype == np.float32
    for _ in range(20):
        obs, rew, term, trunc, info = envs.step(envs.action_space.sample())
    assert np.all(np.isfinite(obs)) and rew.shape == (2,)
    envs.close()


@pytest.mark.parametrize("env_id", IDS)
def test_pickle_round_trip_continues_identically(env_id):
    env = gym.make(env_id)
    env.reset(seed=5)
    run(env, (0, 2), 5)
    clone = pickle.loads(pickle.dumps(env))
    rng = np.random.default_rng(0)
    for a in rng.integers(0, 3, size=(40, 2)):
        o1, r1, *_ = env.step(a)
        o2, r2, *_ = clone.step(a)
        assert np.array_equal(o1, o2) and r1 == r2


@pytest.mark.parametrize("env_id", IDS)
def test_same_seed_and_actions_give_identical_observations(env_id):
    def rollout():
        env = gym.make(env_id)
        obs = [env.reset(seed=42)[0]]
        for a in np.random.default_rng(7).integers(0, 3, size=(150, 2)):
            o, r, te, tr, _ = env.step(a)
            obs.append(o)
            if te or tr:
                obs.append(env.reset()[0])
        return np.array(obs)

    assert np.array_equal(rollout(), rollout())


@pytest.mark.parametrize("env_id", IDS)
def test_different_seeds_give_different_layouts(env_id):
    layouts = []
    for seed in range(5):
        env = gym.make(env_id)
        env.reset(seed=seed)
        lay = env.unwrapped.world.layout
        layouts.append((tuple(lay.walls), tuple(lay.boxes), tuple(lay.cylinders)))
    assert len(set(layouts)) == 5
    assert all(len(w) > 4 or b or c for w, b, c in layouts)  # clutter beyond the boundary


def test_start_pose_is_clear_of_obstacles():
    env = gym.make("MKV-v0").unwrapped
    for seed in range(30):
        env.reset(seed=seed)
        assert not env.world.robot_overlaps()
        assert not env.world.in_contact


def test_jam_env_starts_stuck_and_terminates_with_escaped():
    env = gym.make("MKVJam-v0")
    scenarios = set()
    for seed in range(12):
        obs, info = env.reset(seed=seed)
        code = info["scenario"]  # a numpy int code (array wrappers take it), named by the env
        assert isinstance(code, np.int64)
        assert scenario_name(code) == env.unwrapped.scenario
        scenarios.add(env.unwrapped.scenario_names[code])
        assert info["in_jam"] and info["jams"] == 1 and not info["escaped"]
        # pressing on is hopeless: still stuck after another second
        for _ in range(10):
            obs, r, term, trunc, info = env.step(np.array([FWD, OFF]))
        assert info["stuck"] and not term
    assert scenarios == {"wall", "corner", "dead_end", "wedge"}

    env = gym.make("MKVJam-v0", scenarios=("wall",))
    env.reset(seed=3)
    for _ in range(60):  # back straight off the wall: free, but not escaped until driving on
        obs, r, term, trunc, info = env.step(np.array([0, OFF]))
        assert not term
    for _ in range(40):  # a three-point turn: forward steering hard away from the wall
        obs, r, term, trunc, info = env.step(np.array([FWD, 2]))
        if term:
            break
    assert term and info["escaped"] and info["escapes"] == 1 and r > 4.0


def test_escape_requires_driving_on():
    """Reversing forever frees the robot but is not an escape; the same path counts when the
    forward-travel requirement is switched off."""
    for forward_m, escaped in ((0.15, False), (0.0, True)):
        env = gym.make("MKVJam-v0", scenarios=("wall",), escape_forward_m=forward_m)
        env.reset(seed=3)
        for _ in range(60):
            *_, term, trunc, info = env.step(np.array([0, OFF]))
            if term:
                break
        assert info["escaped"] is escaped


def test_reward_is_forward_progress_minus_penalties():
    env = open_floor()
    _, r, *_ = run(env, (FWD, OFF), 5)[-1]
    assert r == pytest.approx(10.0 * 0.0266, rel=0.05)  # 10 per metre at ~0.27 m/s
    place(env, (3.5, 2.0, 0.0))
    out = run(env, (FWD, OFF), 30)
    assert out[-1][1] == pytest.approx(-0.1, abs=1e-6)  # stuck penalty only
    hits = [k for k, o in enumerate(out) if o[4]["collision"]]
    assert len(hits) == 1 and out[-1][4]["collisions"] == 1
    k = hits[0]
    dx = out[k][4]["pose"][0] - out[k - 1][4]["pose"][0]
    assert out[k][1] == pytest.approx(10.0 * dx - 0.05 - 0.1 * out[k][4]["stuck"], abs=1e-6)


@pytest.mark.parametrize("bad", [
    np.array([3, 0]), np.array([0, -1]), np.array([1.5, 1]), [1], 7, "go", None,
])
def test_invalid_actions_raise_a_clear_error(bad):
    env = gym.make("MKV-v0").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match="invalid action"):
        env.step(bad)


@pytest.mark.parametrize("kwargs, match", [
    (dict(arena_size_m=1.0), "arena_size_m"),
    (dict(n_clutter=-1), "n_clutter"),
    (dict(n_clutter=2.5), "n_clutter"),
    (dict(substeps=0), "substeps"),
    (dict(control_period_s=0.5, substeps=2), "substep"),
    (dict(sensor_noise=-1.0), "sensor_noise"),
    (dict(sensor_params={"sonar": {"bias": 1}}), "unknown sensor channel"),
    (dict(sensor_params={"compass": {"gain": 1}}), "sensor_params"),
    (dict(robot_params={"wheels": 4}), "robot_params"),
    (dict(render_mode="ascii"), "render_mode"),
    (dict(escape_distance_m=0), "escape_distance_m"),
    (dict(escape_forward_m=-1), "escape_forward_m"),
])
@pytest.mark.filterwarnings("ignore:.*render_mode")
def test_bad_kwargs_give_clear_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        gym.make("MKV-v0", **kwargs)


def test_jam_env_rejects_unknown_scenarios():
    with pytest.raises(ValueError, match="scenarios"):
        gym.make("MKVJam-v0", scenarios=("swamp",))


def test_sensor_kwargs_change_readings():
    quiet = open_floor(sensor_noise=0.0)
    biased = open_floor(sensor_noise=0.0, sensor_params={"compass": {"bias": 0.5, "quantum": 0}})
    o1 = run(quiet, (OFF, OFF), 1)[0][0]
    o2 = run(biased, (OFF, OFF), 1)[0][0]
    i = quiet.sensor_names.index("compass")
    assert o2[i] - o1[i] == pytest.approx(0.5, abs=0.01)
    noisy = gym.make("MKV-v0", sensor_noise=3.0).unwrapped
    noisy.reset(seed=0)
    cur = [noisy.step(np.array([OFF, OFF]))[0][7] for _ in range(200)]
    assert 0.02 < np.std(cur) < 0.04  # 3 x the 0.01 A default


def test_rgb_array_render_shows_robot_and_lit_bumpers():
    env = gym.make("MKVJam-v0", render_mode="rgb_array", scenarios=("wall",))
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (600, 600, 3) and frame.dtype == np.uint8
    red = (frame[..., 0] > 200) & (frame[..., 1] < 60) & (frame[..., 2] < 60)
    orange = (frame[..., 0] > 220) & (abs(frame[..., 1].astype(int) - 160) < 15)
    assert red.sum() > 5  # a pressed bumper is lit
    assert orange.sum() > 200  # the chassis
    env.close()


def test_human_render_runs_headless():
    env = gym.make("MKV-v0", render_mode="human")
    env.reset(seed=0)
    env.step(np.array([FWD, OFF]))
    env.close()


@pytest.mark.parametrize("env_id", IDS)
def test_soak_200k_random_steps(env_id):
    """200,000 random steps: no exception, finite observations, robot inside the arena."""
    env = gym.make(env_id)
    env.reset(seed=123)
    size = env.unwrapped.arena_size_m
    low, high = env.observation_space.low, env.observation_space.high
    actions = np.random.default_rng(123).integers(0, 3, size=(200_000, 2))
    xs = np.empty(len(actions))
    ys = np.empty(len(actions))
    finite = True
    inside_bounds = True
    for k, a in enumerate(actions):
        obs, r, te, tr, info = env.step(a)
        finite &= bool(np.isfinite(obs).all()) and np.isfinite(r)
        inside_bounds &= bool((obs >= low).all() and (obs <= high).all())
        xs[k], ys[k] = info["pose"][0], info["pose"][1]
        if te or tr:
            env.reset()
    assert finite and inside_bounds
    assert xs.min() > 0 and xs.max() < size and ys.min() > 0 and ys.max() < size


def test_memory_is_flat_over_1000_resets():
    """Each reset rebuilds the pymunk space; the old one must be freed, nothing may pile up."""
    import weakref

    import pymunk

    from mkv_env.world import World

    env = gym.make("MKVJam-v0")
    env.reset(seed=0)
    for _ in range(50):
        env.reset()
        env.step(np.array([FWD, OFF]))
    gc.collect()
    base_objects = len(gc.get_objects())
    worlds, spaces = weakref.WeakSet(), weakref.WeakSet()
    for _ in range(1000):
        env.reset()
        worlds.add(env.unwrapped.world)
        spaces.add(env.unwrapped.world.space)
        env.step(np.array([FWD, OFF]))
    gc.collect()
    assert len(worlds) == 1 and len(spaces) == 1
    assert all(isinstance(s, pymunk.Space) for s in spaces)
    assert isinstance(next(iter(worlds)), World)
    assert len(gc.get_objects()) < base_objects * 1.01 + 100
