"""Autoresets inside the kernel call (``Batch.set_reset``): a native vector env of MKV-v0 or
MKV-v1 builds the next episode's world in C on the worker threads and hands it to pymunk only
when Python asks (:func:`mkv_env.kernel.adopt_world`). The episodes are the reference's, bit
for bit, whenever and however Python looks at the envs in between; the adopted worlds are
ordinary pymunk worlds (stepping, pickling, rendering, collection)."""

import gc
import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mkv_env  # noqa: F401
from mkv_env import _chipmunk
from mkv_env import kernel as kernel_mod
from mkv_env.envs import MKVEnv, MKVEnvV1
from mkv_env.vector import MKVVectorEnv

needs_c_reset = pytest.mark.skipif(not kernel_mod.AVAILABLE, reason="compiled kernel not built")


def _vec(env_cls, n, kernel="c", **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return MKVVectorEnv(n, env_cls, kernel=kernel, **kw)


def _run(venv, steps, seed, actions_seed, look=None):
    """Rows of everything a step returns; ``look(t, venv)`` may touch the envs after step t."""
    obs, info = venv.reset(seed=seed)
    rows = [(obs.tobytes(), repr(sorted((k, np.asarray(v).tobytes()) for k, v in info.items())))]
    rng = np.random.default_rng(actions_seed)
    for t in range(steps):
        obs, r, te, tr, info = venv.step(rng.integers(0, 3, size=(venv.num_envs, 2)))
        rows.append((obs.tobytes(), r.tobytes(), te.tobytes(), tr.tobytes(),
                     repr(venv.env_infos), repr(venv.final_env_infos),
                     repr(sorted((k, np.asarray(v).tobytes()) for k, v in info.items()
                                 if k not in ("final_obs", "final_info")))))
        if look is not None:
            rows.append(look(t, venv))
    return rows


def _snapshot(env):
    """What Python sees of an env: its world, tracker, sensors and wheel state."""
    w = env.world
    if w._static is not None:  # a kernel world's raw obstacle shapes, handed to pymunk (as a
        _chipmunk.adopt_static(w)  # pickle does) to be compared with the reference's
    t = env.tracker
    lay = w.layout
    shapes = sorted((s._hashid, type(s).__name__, tuple(s.bb)) for s in w.space.shapes)
    return (repr((lay.walls, lay.boxes, lay.cylinders, lay.patches)), repr(shapes),
            repr(w.robot.pose()), repr(w.robot.state), repr(vars(t)), list(w.contacts),
            env.sensors._row, repr(env.sensors._last_ticks), len(w.space.bodies))


@needs_c_reset
@pytest.mark.parametrize("env_cls", [MKVEnv, MKVEnvV1])
@pytest.mark.parametrize("mode", ["NextStep", "SameStep"])
def test_resets_in_c_happen_and_give_the_reference_episodes(env_cls, mode):
    venv = _vec(env_cls, 4, max_episode_steps=25, autoreset_mode=mode, num_threads=2)
    assert venv._c_reset
    seen = []

    def look(t, v):  # count the envs waiting with a world built in C (not yet adopted)
        seen.append(sum(e._c_world for e in v.envs))
        return None

    got = _run(venv, 120, 7, 1, look)
    ref = _run(_vec(env_cls, 4, kernel="python", max_episode_steps=25, autoreset_mode=mode),
               120, 7, 1, lambda t, v: None)
    assert max(seen) == 4  # every env was reset in C, and nothing adopted its world
    assert got == ref


@needs_c_reset
def test_touching_envs_between_steps_adopts_their_worlds_and_changes_nothing():
    def look(t, v):  # a different env, a different view, every few steps
        if t % 7 == 3:
            return _snapshot(v.envs[t % v.num_envs])
        if t % 11 == 5:
            env = v.envs[(t + 1) % v.num_envs]
            return repr((env.world.robot.pose(), env.tracker.distance_m))
        return None

    got = _run(_vec(MKVEnvV1, 5, max_episode_steps=20), 150, 11, 2, look)
    ref = _run(_vec(MKVEnvV1, 5, kernel="python", max_episode_steps=20), 150, 11, 2, look)
    assert got == ref


@needs_c_reset
def test_an_adopted_world_is_the_world_python_builds():
    """Right after a reset in C, the adopted world equals the one Python builds for the same
    generator state: the same layout, shapes (hash ids, bounding boxes), bodies, pose, state."""
    venv = _vec(MKVEnv, 3, max_episode_steps=10)
    ref = _vec(MKVEnv, 3, kernel="python", max_episode_steps=10)
    for v in (venv, ref):
        v.reset(seed=5)
        for _ in range(11):  # the 11th step resets every env
            v.step(np.ones((3, 2), dtype=np.int64))
    assert all(e._c_world for e in venv.envs)
    for a, b in zip(venv.envs, ref.envs, strict=True):
        assert _snapshot(a) == _snapshot(b)
        assert a.world.fast_contacts and a.world.robot.kernel == "c"
        assert a.np_random.bit_generator.state == b.np_random.bit_generator.state


@needs_c_reset
def test_adopted_worlds_step_in_python_pickle_render_and_collect():
    venv = _vec(MKVEnv, 3, max_episode_steps=8, render_mode="rgb_array")
    assert not venv._c_reset  # rendering keeps the trails in Python: Python resets
    venv = _vec(MKVEnv, 3, max_episode_steps=8)
    venv.reset(seed=1)
    for _ in range(9):
        venv.step(np.full((3, 2), 2, dtype=np.int64))
    env = venv.envs[0]
    clone = pickle.loads(pickle.dumps(env))  # adopts, then pymunk pickles the world
    ref = pickle.loads(pickle.dumps(clone))
    ref.kernel = "python"  # the reference steps the same world in Python
    for a in np.random.default_rng(0).integers(0, 3, size=(30, 2)):
        r1, r2 = clone.step(a), ref.step(a)
        assert r1[0].tobytes() == r2[0].tobytes() and r1[1] == r2[1] and r1[4] == r2[4]
    clone.render_mode = "rgb_array"
    frame = clone.render()
    assert frame.ndim == 3 and frame.shape[2] == 3
    # worlds built in C and never adopted, adopted worlds kept after their slot moved on,
    # and whole vector envs go away in any order without touching freed memory
    kept = []
    for k in range(6):
        v = _vec(MKVEnvV1, 4, max_episode_steps=3, num_threads=2)
        v.reset(seed=k)
        for t in range(12):
            v.step(np.random.default_rng(t).integers(0, 3, size=(4, 2)))
            if t % 4 == k % 4:
                kept.append(v.envs[t % 4].world)
        if k % 2:
            del v
            gc.collect()
    for w in kept:
        assert len(w.space.shapes) == 4 and w.robot.pose()[0] > 0
    del kept
    gc.collect()


_params = st.fixed_dictionaries({
    "arena_size_m": st.sampled_from([2.0, 3.0, 4.0, 6.5]),
    "n_clutter": st.integers(0, 40),
    "n_patches": st.integers(0, 5),
    "patch_friction": st.floats(0.05, 2.0),
    "sensor_noise": st.sampled_from([0.0, 1.0, 3.0]),
    "robot_params": st.fixed_dictionaries({
        "length_m": st.floats(0.2, 0.4), "width_m": st.floats(0.15, 0.3),
        "mass_kg": st.floats(1.0, 8.0), "bumper_gap_m": st.floats(0.0, 0.03),
        "chassis_friction": st.floats(0.1, 1.2)}),
})


@needs_c_reset
@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(v1=st.booleans(), params=_params, seed=st.integers(0, 2**31 - 1),
       mode=st.sampled_from(["NextStep", "SameStep"]), threads=st.integers(1, 3),
       max_steps=st.integers(1, 30), look_every=st.integers(2, 40))
def test_resets_in_c_agree_for_random_parameters_and_seeds(v1, params, seed, mode, threads,
                                                           max_steps, look_every):
    env_cls = MKVEnvV1 if v1 else MKVEnv

    def look(t, v):
        return _snapshot(v.envs[t % v.num_envs]) if t % look_every == 0 else None

    kw = dict(params, max_episode_steps=max_steps, autoreset_mode=mode)
    try:
        ref = _run(_vec(env_cls, 3, kernel="python", **kw), 60, seed, seed + 1, look)
    except RuntimeError as e:  # no free start pose in this arena: the kernel says so too
        with pytest.raises(RuntimeError, match=str(e)):
            _run(_vec(env_cls, 3, num_threads=threads, **kw), 60, seed, seed + 1, look)
        return
    assert _run(_vec(env_cls, 3, num_threads=threads, **kw), 60, seed, seed + 1, look) == ref


@needs_c_reset
def test_jam_ids_and_subclasses_keep_python_resets():
    class Mine(MKVEnv):
        pass

    for cls in (Mine,):
        assert not _vec(cls, 2)._c_reset
    jam = gym.make_vec("MKVJam-v0", num_envs=2, vectorization_mode="vector_entry_point")
    assert not jam.unwrapped._c_reset
    jam.close()
