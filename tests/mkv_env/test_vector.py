"""The native vector env: Gymnasium 1.x vector semantics, and the same bits as single envs."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv, VectorEnv
from hypothesis import given, settings
from hypothesis import strategies as st

import mkv_env  # noqa: F401
import mkv_env.robot as robot_mod
from mkv_env.vector import MKVVectorEnv

IDS = ("MKV-v0", "MKVJam-v0", "MKV-v1", "MKVJam-v1")


def _native(env_id, n, **kw):
    return gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **kw)


def _sync(env_id, n, mode=AutoresetMode.NEXT_STEP, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return SyncVectorEnv([lambda: gym.make(env_id, **kw) for _ in range(n)],
                             autoreset_mode=mode)


def _same_info(a, b):
    assert set(a) == set(b)
    for k in b:
        va, vb = a[k], b[k]
        if k == "pose":
            # (float rows here; Gymnasium's object array has None where an env did not report)
            vb = np.array([[0.0] * 3 if x is None else list(x) for x in vb])
        if k == "final_info":
            _same_info(va, vb)
            continue
        if k == "final_obs":
            for x, y in zip(va, vb, strict=False):
                assert (x is None and y is None) or x.tobytes() == y.tobytes()
            continue
        assert np.array_equal(np.asarray(va), np.asarray(vb)), k
        if k != "pose":  # the same dtypes too (info["scenario"]: int64 codes)
            assert np.asarray(va).dtype == np.asarray(vb).dtype, k


@pytest.mark.parametrize("env_id", IDS)
def test_every_id_has_a_native_vector_env(env_id):
    envs = gym.make_vec(env_id, num_envs=3)  # the vector entry point is the default
    assert isinstance(envs.unwrapped, MKVVectorEnv)
    obs, info = envs.reset(seed=0)
    assert obs.shape == (3, 10) and obs.dtype == np.float32
    assert envs.observation_space.contains(obs)
    obs, rew, term, trunc, info = envs.step(envs.action_space.sample())
    assert envs.observation_space.contains(obs)
    assert rew.shape == (3,) and rew.dtype == np.float64
    assert term.dtype == np.bool_ and trunc.dtype == np.bool_
    assert info["pose"].shape == (3, 3) and info["_pose"].all()
    envs.close()


@pytest.mark.parametrize("env_id", IDS)
def test_same_bits_as_sync_vector_env_of_single_envs_with_autoreset(env_id):
    n, limit = 3, 60  # a short limit: several truncations and resets in the run
    a = _native(env_id, n, max_episode_steps=limit)
    b = _sync(env_id, n, max_episode_steps=limit)
    oa, ia = a.reset(seed=5)
    ob, ib = b.reset(seed=5)
    assert oa.tobytes() == ob.tobytes()
    _same_info(ia, ib)
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(200):
        act = rng.integers(0, 3, size=(n, 2))
        ra, rb = a.step(act), b.step(act)
        for x, y in zip(ra[:4], rb[:4], strict=False):
            assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
        _same_info(ra[4], rb[4])
        ends += int((ra[2] | ra[3]).sum())
    assert ends >= n * 2


def test_same_step_autoreset_matches_gymnasium():
    a = _native("MKVJam-v1", 3, max_episode_steps=40, autoreset_mode="SameStep")
    b = _sync("MKVJam-v1", 3, AutoresetMode.SAME_STEP, max_episode_steps=40)
    assert a.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    a.reset(seed=1), b.reset(seed=1)
    rng = np.random.default_rng(1)
    finals = 0
    for _ in range(120):
        act = rng.integers(0, 3, size=(3, 2))
        ra, rb = a.step(act), b.step(act)
        for x, y in zip(ra[:4], rb[:4], strict=False):
            assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
        _same_info(ra[4], rb[4])
        finals += int(ra[4].get("_final_obs", np.zeros(3, bool)).sum())
    assert finals >= 3


@pytest.mark.parametrize("kernel", ["c", "python"])
@pytest.mark.parametrize("env_id", ["MKVJam-v0", "MKVJam-v1"])
def test_disabled_autoreset_and_masked_resets_match_gymnasium(env_id, kernel):
    """Disabled autoreset with partial resets (one env mid-episode, then those that ended): the
    infos, the int scenario codes and their ``_scenario`` masks included, as SyncVectorEnv's."""
    a = _native(env_id, 3, max_episode_steps=4, autoreset_mode="Disabled", kernel=kernel)
    b = _sync(env_id, 3, AutoresetMode.DISABLED, max_episode_steps=4, kernel=kernel)
    oa, ia = a.reset(seed=7)
    ob, ib = b.reset(seed=7)
    _same_info(ia, ib)
    rng = np.random.default_rng(3)
    partial = 0
    done = np.zeros(3, dtype=bool)
    for t in range(14):
        mask = np.array([False, True, False]) if t == 2 else done
        if mask.any():
            (oa, ia), (ob, ib) = (venv.reset(options={"reset_mask": mask}) for venv in (a, b))
            assert oa.tobytes() == ob.tobytes()
            _same_info(ia, ib)
            assert ia["_scenario"].tolist() == mask.tolist()
            partial += not mask.all()
        act = rng.integers(0, 3, size=(3, 2))
        ra, rb = a.step(act), b.step(act)
        for x, y in zip(ra[:4], rb[:4], strict=False):
            assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
        _same_info(ra[4], rb[4])
        done = ra[2] | ra[3]
    assert partial >= 2


def test_env_i_equals_a_single_env_seeded_seed_plus_i():
    envs = _native("MKV-v1", 4)
    obs, _ = envs.reset(seed=100)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        single = gym.make("MKV-v1")
    o2, _ = single.reset(seed=102)
    assert obs[2].tobytes() == o2.tobytes()
    rng = np.random.default_rng(2)
    for _ in range(100):
        act = rng.integers(0, 3, size=(4, 2))
        obs, rew, *_ = envs.step(act)
        o2, r2, *_ = single.step(act[2])
        assert obs[2].tobytes() == o2.tobytes() and rew[2] == r2


def test_reset_mask_and_disabled_autoreset():
    envs = _native("MKVJam-v0", 2, max_episode_steps=5, autoreset_mode="Disabled")
    envs.reset(seed=0)
    for _ in range(5):
        *_, trunc, _ = envs.step(np.ones((2, 2), dtype=int))
    assert trunc.all()
    with pytest.raises(gym.error.ResetNeeded):
        envs.step(np.ones((2, 2), dtype=int))
    obs, info = envs.reset(options={"reset_mask": np.array([True, False])})
    assert info["_pose"].tolist() == [True, False]
    with pytest.raises(gym.error.ResetNeeded):  # env 1 still ended
        envs.step(np.ones((2, 2), dtype=int))
    envs.reset(options={"reset_mask": np.array([False, True])})
    envs.step(np.ones((2, 2), dtype=int))


@pytest.mark.parametrize("bad", [np.ones((3, 2)), np.full((2, 2), 3), np.full((2, 2), 0.5),
                                 [[0, 1]], "x", np.full((2, 2), -1), np.full((2, 2), np.nan),
                                 np.full((2, 2), 1 + 1e-12), np.ones((2, 2), dtype=complex)])
def test_bad_actions_and_arguments_are_one_line_errors(bad):
    envs = _native("MKV-v0", 2)
    envs.reset(seed=0)
    with pytest.raises(ValueError, match="expected shape"):
        envs.step(bad)


def test_bad_construction_and_order():
    with pytest.raises(ValueError, match="num_envs"):
        MKVVectorEnv(0)
    with pytest.raises(ValueError, match="autoreset_mode"):
        MKVVectorEnv(2, autoreset_mode="sometimes")
    with pytest.raises(ValueError, match="n_clutter"):
        _native("MKV-v0", 2, n_clutter=-1)
    with pytest.raises(gym.error.ResetNeeded):
        _native("MKV-v0", 2).step(np.ones((2, 2), dtype=int))
    with pytest.raises(ValueError, match="seed"):
        _native("MKV-v0", 2).reset(seed=[1, 2, 3])


def test_returned_arrays_are_not_reused_and_reset_is_deterministic():
    envs = _native("MKV-v0", 2)
    o1, _ = envs.reset(seed=3)
    o1_copy = o1.copy()
    o2, *_ = envs.step(np.full((2, 2), 2))
    assert o1.tobytes() == o1_copy.tobytes() and o1 is not o2
    o3, _ = envs.reset(seed=3)
    assert o3.tobytes() == o1_copy.tobytes()


def test_pure_python_build_gives_the_same_bits(monkeypatch):
    act = np.random.default_rng(4).integers(0, 3, size=(50, 3, 2))
    a = _native("MKV-v0", 3)
    a.reset(seed=9)
    ref = [a.step(x)[0].tobytes() for x in act]
    monkeypatch.setattr(robot_mod, "_fastsim", None)  # the vector env falls back per robot
    b = _native("MKV-v0", 3)
    b.reset(seed=9)
    assert [b.step(x)[0].tobytes() for x in act] == ref


def test_gymnasium_vector_wrappers_work_on_it():
    from gymnasium.wrappers.vector import RecordEpisodeStatistics

    envs = RecordEpisodeStatistics(_native("MKVJam-v1", 2, max_episode_steps=10))
    envs.reset(seed=0)
    seen = False
    for _ in range(12):
        *_, info = envs.step(np.full((2, 2), 1))
        seen = seen or "episode" in info
    assert seen


def test_render_rgb_array():
    envs = _native("MKV-v0", 2, render_mode="rgb_array")
    envs.reset(seed=0)
    frames = envs.render()
    assert len(frames) == 2 and frames[0].ndim == 3
    with pytest.raises(ValueError, match="render_mode"):
        _native("MKV-v0", 2, render_mode="human")


def test_call_get_attr_set_attr_as_sync_vector_env():
    envs = _native("MKV-v0", 2)
    envs.reset(seed=0)
    assert envs.get_attr("sensor_names")[1][0] == "drive_ticks"
    assert envs.call("get_keys_to_action")[0].keys() == envs.envs[0].get_keys_to_action().keys()
    assert envs.call("sensor_names")[0] == envs.envs[0].sensor_names  # attributes too
    envs.set_attr("stuck_penalty", [0.5, 0.7])
    assert envs.get_attr("stuck_penalty") == (0.5, 0.7)
    with pytest.raises(ValueError, match="set_attr"):
        envs.set_attr("stuck_penalty", [1.0])


def test_actions_in_any_numeric_form_give_the_same_step():
    """Whole-number floats, bools, unsigned and nested lists are the same actions as int64."""
    a = np.array([[2, 0], [1, 1]])
    b = (a > 0).astype(int)
    want_a, want_b = _run_once(a), _run_once(b)
    assert not np.array_equal(want_a, want_b)  # the two actions do drive differently
    for form in (a.astype(float), a.astype(np.uint8), a.tolist()):
        np.testing.assert_array_equal(_run_once(form), want_a)
    np.testing.assert_array_equal(_run_once(a > 0), want_b)


def _run_once(action):
    envs = _native("MKV-v0", 2)
    envs.reset(seed=4)
    obs = [envs.step(action)[0] for _ in range(5)]
    envs.close()
    return np.array(obs)


_INFO_VALUES = {
    bool: st.booleans(),
    int: st.integers(-10**6, 10**6),
    float: st.floats(allow_nan=False, width=64),
    tuple: st.tuples(*[st.floats(-1e6, 1e6)] * 3),
    list: st.lists(st.tuples(st.integers()), max_size=3),  # ragged: an object array
    str: st.text(max_size=3),
}


@st.composite
def _env_infos(draw):
    """A vector env's per-env info dicts: one type per key, some envs silent (None), some keys
    missing in some envs (or every env reporting the same keys)."""
    n = draw(st.integers(1, 6))
    types = draw(st.dictionaries(st.sampled_from("abcdefg"), st.sampled_from(list(_INFO_VALUES)),
                                 min_size=1, max_size=5))
    same = draw(st.booleans())
    infos = []
    for _ in range(n):
        if not same and draw(st.booleans()):
            infos.append(None)
            continue
        keys = list(types) if same else draw(st.lists(st.sampled_from(list(types)),
                                                      unique=True, min_size=1))
        infos.append({k: draw(_INFO_VALUES[types[k]]) for k in keys})
    return infos


@settings(max_examples=150, deadline=None)
@given(_env_infos())
def test_vector_infos_match_gymnasiums_own_batching(infos):
    """_gather gives what Gymnasium's VectorEnv._add_info builds from the same per-env dicts,
    except that tuples become float rows (info['pose'] is an (n, 3) array)."""
    n = len(infos)
    venv = MKVVectorEnv.__new__(MKVVectorEnv)
    venv.num_envs = n
    got = venv._gather(infos)
    want: dict = {}
    for i, d in enumerate(infos):
        if d is not None:
            want = VectorEnv._add_info(venv, want, d, i)
    assert set(got) == set(want)
    for k, w in want.items():
        g = got[k]
        if w.dtype == object and any(isinstance(v, tuple) for v in w):
            first = next(v for v in w if isinstance(v, tuple))
            assert g.dtype == np.float64 and g.shape == (n, len(first))
            for i, v in enumerate(w):
                np.testing.assert_array_equal(g[i], v if v is not None else np.zeros(len(first)))
        else:
            assert g.dtype == w.dtype and g.shape == w.shape
            assert list(g) == list(w)


def test_vector_infos_off_gives_empty_infos_and_the_same_steps():
    on = gym.make_vec("MKV-v0", num_envs=3, vectorization_mode="vector_entry_point")
    off = gym.make_vec("MKV-v0", num_envs=3, vectorization_mode="vector_entry_point",
                       vector_infos=False)
    o_on, i_on = on.reset(seed=2)
    o_off, i_off = off.reset(seed=2)
    assert i_off == {} and "pose" in i_on
    acts = np.random.default_rng(0).integers(0, 3, size=(20, 3, 2))
    for a in acts:
        r_on, r_off = on.step(a), off.step(a)
        for x, y in zip(r_on[:4], r_off[:4], strict=True):
            np.testing.assert_array_equal(x, y)
        assert r_off[4] == {}
        assert [d["pose"] for d in off.unwrapped.env_infos] == list(map(tuple, r_on[4]["pose"]))
    with pytest.raises(ValueError, match="vector_infos"):
        gym.make_vec("MKV-v0", num_envs=2, vectorization_mode="vector_entry_point",
                     vector_infos="no")


@pytest.mark.parametrize("kernel", ["c", "python"])
def test_deviations_from_sync_vector_env_are_gone(kernel):
    """What Gymnasium's own vector tests found: the native env now behaves as SyncVectorEnv."""
    from mkv_env import kernel as kernel_mod

    if kernel == "c" and not kernel_mod.AVAILABLE:
        pytest.skip("compiled kernel not built")
    kw = {"kernel": kernel}
    native = gym.make_vec("MKV-v0", num_envs=2, vectorization_mode="vector_entry_point",
                          render_mode="rgb_array", **kw)
    sync = gym.make_vec("MKV-v0", num_envs=2, vectorization_mode="sync",
                        render_mode="rgb_array", **kw)
    for venv in (native, sync):
        with pytest.raises(gym.error.ResetNeeded):
            venv.render()
    for venv in (native, sync):
        venv.reset(seed=5)
    assert native.np_random_seed == sync.np_random_seed == (5, 6)
    for bad, err in ((1, TypeError), (np.int64(2), TypeError), ("x", ValueError)):
        for venv in (native, sync):
            with pytest.raises(err):
                venv.step(bad)
    for mask, err in (([True, False], TypeError), (np.array([1, 0]), TypeError),
                      (np.array([True]), ValueError), (np.array([False, False]), ValueError)):
        for venv in (native, sync):
            with pytest.raises(err):
                venv.reset(options={"reset_mask": mask})
    native.close()
    sync.close()
