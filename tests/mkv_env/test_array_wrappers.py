"""The jam ids under Gymnasium's array wrappers: ``info["scenario"]`` is an integer code (a string
in info breaks ``NumpyToTorch``), named by ``mkv_env.jams.scenario_name``."""

import warnings

import gymnasium as gym
import numpy as np
import pytest

import mkv_env  # noqa: F401
from mkv_env.jams import SCENARIOS, scenario_code, scenario_name

JAM_IDS = ("MKVJam-v0", "MKVJam-v1")


def _make(env_id, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return gym.make(env_id, **kw)


def _make_vec(env_id, n, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **kw)


def test_codes_map_to_names_and_back():
    assert SCENARIOS == ("wall", "corner", "dead_end", "wedge")
    for i, name in enumerate(SCENARIOS):
        code = scenario_code(name)
        assert isinstance(code, np.int64) and code == i
        assert scenario_name(code) == scenario_name(int(code)) == name
        assert scenario_name(np.array(i, dtype=np.int8)) == name  # 0-d integer arrays too
    for bad in (-1, 4, 1.0, np.float64(2.0), True, "wall", None, np.array([1, 2])):
        with pytest.raises(ValueError, match="scenario code"):
            scenario_name(bad)
    with pytest.raises(ValueError, match="unknown jam scenario"):
        scenario_code("swamp")


@pytest.mark.parametrize("env_id", JAM_IDS)
@pytest.mark.parametrize("kernel", ["c", "python"])
def test_info_code_names_the_jam_built(env_id, kernel):
    """The code in info is the scenario the env built, whichever subset ``scenarios`` allows (a
    code is the kind's index in SCENARIOS, not in the subset)."""
    env = _make(env_id, scenarios=("dead_end", "wedge"), kernel=kernel)
    assert env.unwrapped.scenario_names == SCENARIOS
    seen = set()
    for seed in range(6):
        _, info = env.reset(seed=seed)
        code = info["scenario"]
        assert isinstance(code, np.int64)
        assert scenario_name(code) == env.unwrapped.scenario in ("dead_end", "wedge")
        seen.add(int(code))
        *_, info = env.step(np.array([1, 1]))
        assert isinstance(info["scenario"], np.int64) and info["scenario"] == code
    assert seen == {2, 3}


@pytest.mark.parametrize("env_id", JAM_IDS)
@pytest.mark.parametrize("kernel", ["c", "python"])
def test_vector_info_is_an_int_array_named_by_the_envs(env_id, kernel):
    envs = _make_vec(env_id, 3, kernel=kernel)
    assert envs.unwrapped.scenario_names == SCENARIOS
    _, info = envs.reset(seed=4)
    assert info["scenario"].dtype == np.int64 and info["_scenario"].all()
    names = [scenario_name(c) for c in info["scenario"]]
    assert names == list(envs.unwrapped.get_attr("scenario"))
    envs.step(np.ones((3, 2), dtype=np.int64))
    # the per-env dicts (what SB3VecEnv hands on) keep the single env's numpy int
    assert all(isinstance(d["scenario"], np.int64) for d in envs.unwrapped.env_infos)
    envs.close()


@pytest.mark.parametrize("env_id", JAM_IDS)
def test_numpy_to_torch_wraps_the_single_env(env_id):
    torch = pytest.importorskip("torch")
    pytest.importorskip("array_api_compat")  # NumpyToTorch's own dependency (gymnasium[torch])
    from gymnasium.wrappers import NumpyToTorch

    env = NumpyToTorch(_make(env_id, max_episode_steps=4))
    obs, info = env.reset(seed=1)
    assert isinstance(obs, torch.Tensor) and obs.shape == (10,)
    assert info["scenario"].dtype == torch.int64 and info["scenario"].ndim == 0
    assert scenario_name(info["scenario"]) == env.unwrapped.scenario
    for _ in range(4):
        obs, reward, terminated, truncated, info = env.step(torch.tensor([2, 1]))
        assert isinstance(obs, torch.Tensor) and isinstance(reward, float)
        assert isinstance(info["scenario"], torch.Tensor) and isinstance(info["escaped"],
                                                                         torch.Tensor)
        assert scenario_name(info["scenario"]) == env.unwrapped.scenario
    assert truncated or terminated
    env.close()


@pytest.mark.parametrize("env_id", JAM_IDS)
@pytest.mark.parametrize("mode", ["NextStep", "Disabled"])
def test_numpy_to_torch_wraps_the_vector_env(env_id, mode):
    """Across autoresets (a 3-step limit), every info key converts: ``scenario`` an int64 tensor
    with its mask. (In SameStep mode the step an episode ends adds ``final_obs``, an object
    array, which ``NumpyToTorch`` cannot convert for any env, Gymnasium's own included.)"""
    torch = pytest.importorskip("torch")
    pytest.importorskip("array_api_compat")
    from gymnasium.wrappers.vector import NumpyToTorch

    n = 3
    envs = NumpyToTorch(_make_vec(env_id, n, max_episode_steps=3, autoreset_mode=mode))
    obs, info = envs.reset(seed=2)
    assert isinstance(obs, torch.Tensor) and obs.shape == (n, 10)
    action = torch.ones((n, 2), dtype=torch.int64)
    for t in range(8):
        if mode == "Disabled" and t == 3:
            obs, info = envs.reset(options={"reset_mask": np.array([True, False, True])})
            assert info["_scenario"].tolist() == [True, False, True]
            assert info["scenario"][1] == 0  # not reported: zero, as Gymnasium leaves it
            break
        obs, reward, terminated, truncated, info = envs.step(action)
        assert isinstance(reward, torch.Tensor) and reward.shape == (n,)
        assert info["scenario"].dtype == torch.int64 and info["_scenario"].all()
        names = [scenario_name(c) for c in info["scenario"]]
        assert names == list(envs.unwrapped.get_attr("scenario"))
    envs.close()
