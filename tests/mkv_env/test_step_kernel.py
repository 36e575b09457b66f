"""The compiled step kernel (mkv_env/kernel.py, the Batch of _fastsim.c) gives the bits of the
Python reference (``kernel="python"``): every observation, reward, flag and info value, for all
four ids, random actions, parameters and seeds, single envs and vector envs (every autoreset
mode, one and several threads); and the recorded fingerprints of every id are unchanged."""

import importlib.util
import math
import os
import pickle
import struct
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mkv_env  # noqa: F401
from mkv_env import kernel as kernel_mod

IDS = ("MKV-v0", "MKVJam-v0", "MKV-v1", "MKVJam-v1")
needs_c = pytest.mark.skipif(not kernel_mod.AVAILABLE, reason="compiled kernel not built")

# scripts/env_fingerprint.py --episodes 3 --steps 200, recorded before the step kernel existed
FINGERPRINTS = {"MKV-v0": "b26c6aec4be61f77", "MKVJam-v0": "e122c4fc65612fba",
                "MKV-v1": "b0ab5090ce0aced4", "MKVJam-v1": "97a9d7d540261518"}


def _fingerprint_module():
    path = Path(__file__).resolve().parents[2] / "scripts" / "env_fingerprint.py"
    spec = importlib.util.spec_from_file_location("env_fingerprint", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("kernel", [pytest.param("c", marks=needs_c), "python"])
def test_recorded_fingerprints_are_unchanged(kernel):
    fp = _fingerprint_module()
    got = {env_id: fp.fingerprint(env_id, 3, 200, kernel) for env_id in IDS}
    assert got == FINGERPRINTS


def _bits(x) -> bytes:
    return struct.pack("<d", x)


@needs_c
@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True), st.floats(allow_nan=True,
                                                                  allow_infinity=True))
def test_c_hypot_and_modulo_are_pythons_bit_for_bit(a, b):
    from mkv_env import _fastsim

    h = math.hypot(a, b)
    assert _bits(_fastsim.hypot(a, b)) == _bits(h) or (math.isnan(h) and
                                                      math.isnan(_fastsim.hypot(a, b)))
    if math.isfinite(a) and math.isfinite(b) and b != 0.0:
        assert _bits(_fastsim.pymod(a, b)) == _bits(a % b)


@needs_c
def test_c_hypot_on_many_random_pairs_and_subnormals():
    from mkv_env import _fastsim

    rng = np.random.default_rng(3)
    for scale in (5e-324, 1e-310, 1e-150, 1e-3, 1.0, 1e5, 1e150, 1e300):
        a = rng.standard_normal(20_000) * scale
        b = a * rng.choice([1e-9, 1e-3, 0.5, 1.0, 3.0], size=a.size) * rng.standard_normal(a.size)
        for x, y in zip(a.tolist(), b.tolist(), strict=True):
            assert _bits(_fastsim.hypot(x, y)) == _bits(math.hypot(x, y)), (x, y)


def _rollout(env, seed: int, steps: int, actions_seed: int):
    """Every step's observation bytes, reward, flags and info (repr), resets included."""
    obs, info = env.reset(seed=seed)
    rows = [(obs.tobytes(), repr(info))]
    rng = np.random.default_rng(actions_seed)
    for _ in range(steps):
        obs, r, te, tr, info = env.step(rng.integers(0, 3, size=2))
        rows.append((obs.tobytes(), _bits(r), te, tr, repr(info)))
        if te or tr:
            obs, info = env.reset()
            rows.append((obs.tobytes(), repr(info)))
    return rows


def _make(env_id, kernel, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return gym.make(env_id, kernel=kernel, **kw)


@needs_c
@pytest.mark.parametrize("env_id", IDS)
def test_kernels_give_the_same_episodes(env_id):
    for seed in range(2):
        ref = _rollout(_make(env_id, "python"), seed, 650, seed)
        got = _rollout(_make(env_id, "c"), seed, 650, seed)
        assert got == ref


_params = st.fixed_dictionaries({
    "n_clutter": st.integers(0, 30),
    "n_patches": st.integers(0, 6),
    "patch_friction": st.floats(0.05, 2.0),
    "sensor_noise": st.sampled_from([0.0, 0.5, 1.0, 3.0]),
    "stuck_speed_mps": st.floats(0.005, 0.2),
    "jam_steps": st.integers(1, 6),
    "escape_distance_m": st.floats(0.05, 0.6),
    "escape_forward_m": st.floats(0.0, 0.3),
    "stuck_penalty": st.floats(-1.0, 1.0),
    "collision_penalty": st.floats(-1.0, 1.0),
    "robot_params": st.fixed_dictionaries({
        "tire_friction": st.floats(0.03, 1.5),
        "drive_motor": st.fixed_dictionaries({"supply_v": st.floats(3.0, 20.0)})}),
})


@needs_c
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(env_id=st.sampled_from(IDS), params=_params, seed=st.integers(0, 2**31 - 1),
       actions_seed=st.integers(0, 1000), max_steps=st.integers(5, 120))
def test_kernels_agree_for_random_parameters_seeds_and_actions(env_id, params, seed,
                                                                actions_seed, max_steps):
    kw = dict(params, max_episode_steps=max_steps)
    if env_id.startswith("MKVJam"):
        kw["n_clutter"] = min(kw["n_clutter"], 10)
    try:
        ref_env = _make(env_id, "python", **kw)
        ref = _rollout(ref_env, seed, 150, actions_seed)
    except ValueError as e:  # a jam these parameters cannot build: both kernels say so
        with pytest.raises(ValueError, match=str(e)[:30]):
            _rollout(_make(env_id, "c", **kw), seed, 150, actions_seed)
        return
    assert _rollout(_make(env_id, "c", **kw), seed, 150, actions_seed) == ref


@needs_c
def test_reading_python_state_mid_episode_hands_it_back_and_forth():
    """env.tracker / robot.state read (and changed) between C steps are pulled from and pushed
    back to the kernel: the episode is the reference's."""
    ref, got = _make("MKVJam-v1", "python"), _make("MKVJam-v1", "c")
    rng = np.random.default_rng(0)
    for env in (ref, got):
        env.reset(seed=11)
    for t in range(200):
        a = rng.integers(0, 3, size=2)
        r1, r2 = ref.step(a), got.step(a)
        assert r1[0].tobytes() == r2[0].tobytes() and repr(r1[1:]) == repr(r2[1:])
        if t % 37 == 0:
            u1, u2 = ref.unwrapped, got.unwrapped
            assert vars(u1.tracker) == vars(u2.tracker)
            assert u1.world.robot.state == u2.world.robot.state
            assert u1.sensors._row == u2.sensors._row
            u1.tracker.distance_m += 1.0  # a change made in Python reaches the kernel
            u2.tracker.distance_m += 1.0
        if r1[2] or r1[3]:
            ref.reset()
            got.reset()


@needs_c
@pytest.mark.parametrize("env_id", IDS)
def test_pickled_c_env_continues_as_the_reference(env_id):
    ref, got = _make(env_id, "python"), _make(env_id, "c")
    for env in (ref, got):
        env.reset(seed=4)
    rng = np.random.default_rng(1)
    for a in rng.integers(0, 3, size=(30, 2)):
        ref.step(a)
        got.step(a)
    got = pickle.loads(pickle.dumps(got))
    for a in rng.integers(0, 3, size=(300, 2)):
        r1, r2 = ref.step(a), got.step(a)
        assert r1[0].tobytes() == r2[0].tobytes() and repr(r1[1:]) == repr(r2[1:])
        if r1[2] or r1[3]:
            break


def test_without_the_compiled_kernel_everything_runs_on_the_reference(monkeypatch):
    monkeypatch.setattr(kernel_mod, "AVAILABLE", False)
    env = _make("MKV-v0", None)
    assert env.unwrapped.kernel == "python"
    env.reset(seed=0)
    env.step(np.array([2, 1]))
    with pytest.raises(ValueError, match="kernel='c' needs the compiled extension"):
        _make("MKV-v0", "c")
    venv = gym.make_vec("MKV-v1", num_envs=2, vectorization_mode="vector_entry_point")
    assert venv.unwrapped.kernel == "python"
    venv.reset(seed=0)
    venv.step(np.ones((2, 2), dtype=np.int64))


@pytest.mark.parametrize("bad", ["C", "cuda", 1, ""])
def test_bad_kernel_is_a_one_line_error(bad):
    with pytest.raises(ValueError, match="kernel must be"):
        _make("MKV-v0", bad)


# ---------------------------------------------------------------------- vector envs
def _vector_run(env_id, kernel, mode, threads, n=5, steps=260, seed=3, max_steps=40,
                vector_infos=True):
    kw = {"kernel": kernel, "autoreset_mode": mode, "max_episode_steps": max_steps,
          "vector_infos": vector_infos}
    if kernel == "c":
        kw["num_threads"] = threads
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **kw)
    rows = []
    obs, info = venv.reset(seed=seed)
    rows.append((obs.tobytes(), _info_bytes(info)))
    rng = np.random.default_rng(seed)
    ended = np.zeros(n, dtype=bool)
    for _ in range(steps):
        if mode == "Disabled" and ended.any():
            obs, info = venv.reset(options={"reset_mask": ended.copy()})
            rows.append((obs.tobytes(), _info_bytes(info)))
        obs, r, te, tr, info = venv.step(rng.integers(0, 3, size=(n, 2)))
        ended = te | tr
        rows.append((obs.tobytes(), r.tobytes(), te.tobytes(), tr.tobytes(), _info_bytes(info),
                     repr(venv.unwrapped.env_infos), repr(venv.unwrapped.final_env_infos)))
    venv.close()
    return rows


def _info_bytes(info) -> list:
    out = []
    for k in sorted(info):
        v = info[k]
        if k in ("final_info",):
            out.append((k, _info_bytes(v)))
        elif isinstance(v, np.ndarray) and v.dtype == object:
            out.append((k, repr([x.tobytes() if isinstance(x, np.ndarray) else x for x in v])))
        else:
            out.append((k, str(v.dtype), v.shape, v.tobytes()))
    return out


@needs_c
@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("mode", ["NextStep", "SameStep", "Disabled"])
def test_vector_kernel_equals_the_reference_in_every_autoreset_mode(env_id, mode):
    ref = _vector_run(env_id, "python", mode, 1)
    for threads in (1, 2, 3):
        assert _vector_run(env_id, "c", mode, threads) == ref, (mode, threads)


@needs_c
def test_vector_results_do_not_depend_on_the_thread_count():
    ref = _vector_run("MKV-v1", "c", "NextStep", 1, n=16, steps=400, max_steps=150)
    for threads in (2, 4, 16):
        assert _vector_run("MKV-v1", "c", "NextStep", threads, n=16, steps=400,
                           max_steps=150) == ref


@needs_c
def test_vector_without_infos_keeps_per_env_dicts():
    a = _vector_run("MKVJam-v1", "c", "SameStep", 2, vector_infos=False)
    b = _vector_run("MKVJam-v1", "python", "SameStep", 1, vector_infos=False)
    assert a == b
    assert all(r[4] == [] or all(k[0] in ("final_obs", "_final_obs", "final_info",
                                           "_final_info") for k in r[4]) for r in a[1:])


@needs_c
def _plain(state):
    """A bit generator's state with its arrays as lists (comparable with ==)."""
    if isinstance(state, dict):
        return {k: _plain(v) for k, v in state.items()}
    return state.tolist() if isinstance(state, np.ndarray) else state


@needs_c
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**63), kind=st.sampled_from(["PCG64", "PCG64DXSM", "MT19937",
                                                          "Philox", "SFC64"]),
       k=st.integers(0, 3000))
def test_noise_drawn_in_c_is_numpys_standard_normal(seed, kind, k):
    """The kernel's own draws (numpy's random library, linked) are Generator.standard_normal's
    and leave the generator where numpy leaves it."""
    from mkv_env import _fastsim

    bg = getattr(np.random, kind)
    g1, g2 = bg(seed), np.random.Generator(bg(seed))
    got = _fastsim.normals(g1, k)
    assert [_bits(x) for x in got] == [_bits(x) for x in g2.standard_normal(k).tolist()]
    assert _plain(g1.state) == _plain(g2.bit_generator.state)


@needs_c
@pytest.mark.parametrize("env_id", ["MKV-v0", "MKVJam-v1"])
def test_noise_drawn_by_the_kernel_gives_the_references_run(env_id):
    """The kernel refills its slots' noise blocks on its threads with the reference's bits
    (Python's refill, for a generator two robots share, is in the shared-generator test)."""
    ref = _vector_run(env_id, "python", "NextStep", 1, n=4, steps=700, max_steps=300)
    assert _vector_run(env_id, "c", "NextStep", 2, n=4, steps=700, max_steps=300) == ref


@needs_c
@pytest.mark.parametrize("mode", ["NextStep", "SameStep", "Disabled"])
def test_compiled_vector_bookkeeping_gives_the_references_run(mode):
    """Batch.collect (the per-step result arrays, elapsed, truncation, autoreset flags and
    Gymnasium's info, compiled) gives the reference's bits."""
    ref = _vector_run("MKVJam-v1", "python", mode, 1)
    assert _vector_run("MKVJam-v1", "c", mode, 2) == ref
    assert _vector_run("MKV-v1", "c", mode, 1) == _vector_run("MKV-v1", "python", mode, 1)


@needs_c
def test_a_steps_results_are_its_own_arrays():
    """What step() returns is never overwritten by the next step (fresh arrays, masks too), and
    collect refuses buffers of the wrong kind in one line."""
    venv = gym.make_vec("MKV-v1", num_envs=3, vectorization_mode="vector_entry_point")
    venv.reset(seed=2)
    first = venv.step(np.full((3, 2), 2))
    kept = [first[0].copy(), first[1].copy(), {k: v.copy() for k, v in first[4].items()}]
    for _ in range(5):
        venv.step(np.zeros((3, 2), dtype=np.int64))
    assert first[0].tobytes() == kept[0].tobytes() and first[1].tobytes() == kept[1].tobytes()
    assert all(np.array_equal(first[4][k], v) for k, v in kept[2].items())
    first[4]["_stuck"][0] = False  # masks are the caller's to change
    b = venv.unwrapped._batch
    with pytest.raises(ValueError, match="elapsed must be int64"):
        b.collect(np.zeros(3, dtype=np.int32), -1, None, None, (), False)
    with pytest.raises(ValueError, match="active must be bool"):
        b.collect(np.zeros(3, dtype=np.int64), -1, np.zeros(2, bool), None, (), False)
    with pytest.raises(ValueError, match="output index"):
        b.collect(np.zeros(3, dtype=np.int64), -1, None, None, (("a", "_a", 99),), True)
    venv.close()


@needs_c
def test_a_generator_shared_by_two_robots_is_drawn_in_robot_order():
    """Two envs handed one generator: the kernel does not draw from it on two threads (both
    slots fall back to Python's draws, in slot order), so the run is the reference's."""
    def run(kernel):
        kw = {"kernel": kernel, "max_episode_steps": 10_000}
        if kernel == "c":
            kw["num_threads"] = 2
        venv = gym.make_vec("MKV-v1", num_envs=2, vectorization_mode="vector_entry_point", **kw)
        venv.reset(seed=5)
        shared = np.random.default_rng(77)
        for e in venv.unwrapped.envs:
            e.np_random = shared
        obs, _ = venv.reset()  # no seed: both episodes draw from the one generator
        rows = [obs.tobytes()]
        for a in np.random.default_rng(1).integers(0, 3, size=(600, 2, 2)):
            rows.append(venv.step(a)[0].tobytes())
        venv.close()
        return rows, shared.bit_generator.state

    assert run("c") == run("python")
    b = kernel_mod._fastsim.Batch  # the binding says so: the second slot refuses the first's
    venv = gym.make_vec("MKV-v1", num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    batch, g = venv.unwrapped._batch, np.random.default_rng(3).bit_generator
    z = np.zeros(10)
    assert isinstance(batch, b)
    assert batch.set_noise_source(0, g, z, z) is True
    assert batch.set_noise_source(1, g, z, z) is False
    assert batch.set_noise_source(0, None, z, z) is False
    venv.close()


def test_vector_env_rejects_bad_thread_counts():
    for bad in (0, -1, 1.5, True, 1000):
        with pytest.raises(ValueError, match="num_threads"):
            gym.make_vec("MKV-v0", num_envs=2, vectorization_mode="vector_entry_point",
                         num_threads=bad)


# ---------------------------------------------------------------------- resets
@needs_c
@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), size=st.floats(2.0, 20.0), n_clutter=st.integers(0, 80),
       n_patches=st.integers(0, 8), patch=st.floats(0.05, 2.0),
       reserved=st.lists(st.tuples(st.floats(0, 20), st.floats(0, 20), st.floats(0, 2)),
                         max_size=3))
def test_compiled_layout_generator_draws_and_builds_the_same_arena(seed, size, n_clutter,
                                                                  n_patches, patch, reserved):
    from mkv_env import world

    r1, r2 = np.random.default_rng(seed), np.random.default_rng(seed)
    ref = world.generate_layout(r1, size, size, n_clutter, n_patches, patch, reserved=reserved)
    got = kernel_mod.generate_layout(r2, size, size, n_clutter, n_patches, patch,
                                     reserved=reserved)
    assert got == ref
    assert r1.bit_generator.state == r2.bit_generator.state  # the same draws, no more, no less


@needs_c
def test_kernel_worlds_survive_many_resets_pickles_and_collections():
    """Kernel worlds own raw Chipmunk obstacle shapes (mkv_env/_chipmunk.py): freeing, pickling
    (pymunk adopts them, cached contacts included) and garbage collection in any order stay
    memory-safe, and a pickled jam env continues as the original."""
    import gc

    for env_id in ("MKV-v0", "MKVJam-v1"):
        for k in range(12):
            env = _make(env_id, "c")
            env.reset(seed=k)
            for a in np.random.default_rng(k).integers(0, 3, size=(6, 2)):
                env.step(a)
            clone = pickle.loads(pickle.dumps(env))
            assert len(clone.unwrapped.world.space.shapes) == len(env.unwrapped.world.space.shapes)
            for a in np.random.default_rng(k + 100).integers(0, 3, size=(10, 2)):
                r1, r2 = env.step(a), clone.step(a)
                assert r1[0].tobytes() == r2[0].tobytes() and r1[1] == r2[1]
            del env, clone
            if k % 4 == 0:
                gc.collect()


def test_threads_without_the_compiled_kernel_are_refused():
    with pytest.raises(ValueError, match="num_threads > 1 needs the compiled step kernel"):
        gym.make_vec("MKV-v0", num_envs=2, vectorization_mode="vector_entry_point",
                     kernel="python", num_threads=2)


@needs_c
def test_reward_weights_changed_on_a_live_env_apply_from_the_next_reset():
    ref, got = _make("MKV-v0", "python"), _make("MKV-v0", "c")
    for env in (ref, got):
        env.reset(seed=3)
        env.unwrapped.progress_reward = -7.0
        env.unwrapped.stuck_penalty = 2.5
        env.reset(seed=4)
    rng = np.random.default_rng(2)
    for a in rng.integers(0, 3, size=(80, 2)):
        r1, r2 = ref.step(a), got.step(a)
        assert _bits(r1[1]) == _bits(r2[1])


@needs_c
@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_process_steps_a_threaded_vector_env_with_threads_of_its_own():
    """After a fork the child has none of the parent's worker threads: it starts its own
    instead of waiting for ones that do not exist; both processes get the same results."""
    import multiprocessing as mp

    venv = gym.make_vec("MKV-v1", num_envs=4, vectorization_mode="vector_entry_point",
                        num_threads=2)
    venv.reset(seed=0)
    acts = np.random.default_rng(0).integers(0, 3, size=(30, 4, 2))
    venv.step(acts[0])  # the parent's threads exist now

    def run(q):
        q.put([venv.step(a)[0].tobytes() for a in acts[1:]])

    ctx = mp.get_context("fork")
    q = ctx.Queue()
    child = ctx.Process(target=run, args=(q,))
    child.start()
    got = q.get(timeout=60)
    child.join(timeout=60)
    assert child.exitcode == 0
    assert got == [venv.step(a)[0].tobytes() for a in acts[1:]]


def test_a_subclass_with_its_own_reward_runs_its_own_python():
    """The compiled kernel carries the four MK-V classes' rewards only: a subclass overriding
    _reward (or any step-time method) gets kernel='python' by default and refuses 'c'; one that
    only changes arguments keeps the compiled kernel."""
    from mkv_env.envs import MKVEnv, MKVJamEnvV1

    class Bonus(MKVEnv):
        def _reward(self, progress, stuck, collision, escaped):
            return 1.0

    class Quieter(MKVJamEnvV1):
        def __init__(self, **kw):
            super().__init__(time_penalty=0.0, **kw)

    env = Bonus()
    assert env.kernel == "python"
    env.reset(seed=0)
    assert env.step(np.array([2, 1]))[1] == 1.0
    with pytest.raises(ValueError, match="overrides _reward"):
        Bonus(kernel="c")
    assert Quieter().kernel == kernel_mod.default_kernel()


@needs_c
def test_a_kernel_whose_noise_draws_differ_is_off_and_says_why():
    """Two paths only: where the linked numpy random library draws differently from this
    numpy's, the whole kernel is off (no Python-drawn-noise variant of it), the envs run the
    reference, and asking for kernel='c' says why in one line."""
    import subprocess
    import sys

    prog = (
        "import mkv_env._fastsim as f; f.normals = lambda g, k: [0.0] * k\n"
        "import gymnasium as gym, mkv_env, mkv_env.kernel as K\n"
        "assert not K.AVAILABLE\n"
        "env = gym.make('MKV-v1'); env.reset(seed=0); env.step(env.action_space.sample())\n"
        "try:\n"
        "    gym.make('MKV-v1', kernel='c')\n"
        "except Exception as e:\n"
        "    print(str(e))\n")
    out = subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True,
                         timeout=120, env=dict(os.environ, SDL_VIDEODRIVER="dummy"))
    assert out.returncode == 0, out.stderr
    msg = out.stdout.strip()
    assert "draws differently" in msg and "kernel='python'" in msg and "\n" not in msg


@needs_c
def test_the_kernels_noise_block_is_the_sensor_suites():
    """A slot's noise block has the rows of SensorSuite's (SensorSuite.load reshapes by them)."""
    from mkv_env import sensors

    assert kernel_mod.NOISE_ROWS == sensors._NOISE_BLOCK


def test_the_kernel_carries_the_whole_tracker_and_robot_state():
    """Every field of MotionTracker.to_state() and Robot.to_state() has a place in the slot's
    state, and no other."""
    from mkv_env.robot import Robot
    from mkv_env.tracker import MotionTracker

    assert sorted(kernel_mod._TRACK.values()) == sorted(MotionTracker.STATE)
    assert sorted([*kernel_mod._WHEEL.values(), "mu_scale"]) == sorted(Robot.STATE)


@needs_c
def test_a_world_held_across_c_steps_never_shows_stale_wheels():
    """While the kernel steps the robot, its wheel state lives in the slot: a world reference
    taken before the steps refuses to show its wheels (one-line RuntimeError) instead of stale
    ones; taking ``env.world`` again brings the current state back, the reference's."""
    ref, got = _make("MKV-v1", "python").unwrapped, _make("MKV-v1", "c").unwrapped
    for env in (ref, got):
        env.reset(seed=3)
    held = got.world
    rng = np.random.default_rng(3)
    for a in rng.integers(0, 3, size=(25, 2)):
        ref.step(a)
        got.step(a)
    with pytest.raises(RuntimeError, match="held by the compiled kernel") as e:
        _ = held.robot.state
    assert "\n" not in str(e.value)
    assert got.world is held  # the same objects, brought up to date
    assert held.robot.state == ref.world.robot.state
    assert held.robot.to_state() == ref.world.robot.to_state()
    got.step(np.array([2, 1]))
    ref.step(np.array([2, 1]))
    assert got.world.robot.state == ref.world.robot.state


def test_robot_sensors_and_tracker_states_round_trip():
    """to_state() then load_state() on a fresh owner gives the same state (what push and pull
    rely on), for the robot, the sensor suite and the tracker."""
    a, b = _make("MKVJam-v1", "python").unwrapped, _make("MKVJam-v1", "python").unwrapped
    a.reset(seed=5)
    b.reset(seed=6)
    for x in np.random.default_rng(5).integers(0, 3, size=(40, 2)):
        a.step(x)
    b.world.robot.load_state(a.world.robot.to_state())
    assert b.world.robot.to_state() == a.world.robot.to_state()
    b.tracker.load_state(a.tracker.to_state())
    assert b.tracker.to_state() == a.tracker.to_state()
    sa = a.sensors.to_state()
    b.sensors.load_state(sa)
    sb = b.sensors.to_state()
    assert sb["row"] == sa["row"] and sb["last_ticks"] == sa["last_ticks"]
    assert sb["block"].tobytes() == sa["block"].tobytes()


@needs_c
def test_reading_the_world_every_step_leaves_no_references_behind():
    """A single env pulled back to Python every step and reset often (a renderer, a teacher
    that reads the world) keeps no growing list of itself: its reference count is flat."""
    import sys

    env = _make("MKVJam-v1", "c").unwrapped
    env.reset(seed=2)
    rng = np.random.default_rng(2)
    counts = []
    for t in range(300):
        _, _, term, trunc, _ = env.step(rng.integers(0, 3, size=2))
        _ = env.world.robot.state
        if term or trunc or t % 50 == 49:
            env.reset()
        if t in (20, 299):
            counts.append(sys.getrefcount(env))
    assert counts[1] <= counts[0]
