"""The compiled substep loop (mkv_env._fastsim) gives the same bits as the Python loops.

Two implementations of ``Robot.advance`` exist: ``"c"`` (default when built) and ``"python"``
(the reference loop, on pymunk's public properties only). Any difference would silently change
every trajectory, recording and result, so
whole episodes are compared bit for bit, in the regimes that take different branches: cruising,
steering against the stops, wall contacts and jams, wheels sliding on slippery floors.
"""

import math
import shutil
import sysconfig
import warnings

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import mkv_env.robot as robot_mod
from mkv_env.teacher import ScriptedTeacher

KERNELS = [k for k in ("c", "python")
           if k != "c" or robot_mod._fastsim is not None]


def _episode(kernel, env_id, seed, steps, teacher, monkeypatch, **kwargs):
    monkeypatch.setattr(robot_mod, "DEFAULT_KERNEL", kernel)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        env = gym.make(env_id, **kwargs)
    obs, _ = env.reset(seed=seed)
    assert env.unwrapped.world.robot.kernel == kernel
    pol = ScriptedTeacher(seed=seed) if teacher else None
    rng = np.random.default_rng(seed)
    rows = [obs.tobytes()]
    for _ in range(steps):
        a = pol.predict(obs)[0] if pol else rng.integers(0, 3, size=2)
        obs, r, te, tr, info = env.step(a)
        s = env.unwrapped.world.robot.state
        rows.append(obs.tobytes() + np.array(
            [r, *info["pose"], s.drive_omega, s.steer, s.steer_rate, s.drive_angle,
             s.roller_angle, s.drive_budget, s.drive_current, s.steer_current]).tobytes())
        if te or tr:
            break
    env.close()
    return rows


def test_the_compiled_kernel_is_built_where_a_compiler_exists():
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(cc) is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler on this machine: the pure-Python loop is used")
    assert robot_mod._fastsim is not None, "mkv_env._fastsim was not built (pip install -e .)"
    assert robot_mod.DEFAULT_KERNEL == "c"


@pytest.mark.parametrize("env_id,teacher,kwargs", [
    ("MKV-v0", True, {}),
    ("MKV-v0", False, {}),
    ("MKVJam-v1", False, {}),
    # slippery everywhere: the wheels slide, the projected Gauss-Seidel branch runs
    ("MKV-v1", False, {"robot_params": {"tire_friction": 0.05}}),
])
def test_kernels_give_identical_episodes(env_id, teacher, kwargs, monkeypatch):
    ref = _episode("python", env_id, 7, 300, teacher, monkeypatch, **kwargs)
    assert len(ref) > 20
    for k in KERNELS:
        got = _episode(k, env_id, 7, 300, teacher, monkeypatch, **kwargs)
        assert got == ref, f"kernel {k!r} differs from 'python' at step {_first_diff(got, ref)}"


def _first_diff(a, b):
    pairs = enumerate(zip(a, b, strict=False))
    return next((i for i, (x, y) in pairs if x != y), min(len(a), len(b)))


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), friction=st.floats(0.02, 2.0),
       supply=st.floats(2.0, 24.0), clutter=st.integers(0, 40))
def test_kernels_agree_for_random_robots_and_arenas(seed, friction, supply, clutter):
    mp = pytest.MonkeyPatch()
    try:
        kw = {"n_clutter": clutter, "robot_params": {
            "tire_friction": friction,
            "drive_motor": {"supply_v": supply}}}
        ref = _episode("python", "MKV-v0", seed, 60, False, mp, **kw)
        for k in KERNELS:
            assert _episode(k, "MKV-v0", seed, 60, False, mp, **kw) == ref
    finally:
        mp.undo()


def test_sliding_branch_is_exercised_by_the_slippery_case(monkeypatch):
    if robot_mod._fastsim is None:
        pytest.skip("compiled kernel not built")
    calls = []

    def counting(a, b):
        calls.append(1)
        return math.hypot(a, b)

    # the robot's compiled loop on its own (the step kernel uses its C copy of math.hypot,
    # tests/mkv_env/test_step_kernel.py): it calls back the hypot it was bound to
    robot_mod.bind_kernel(counting)
    try:
        env = gym.make("MKV-v1", kernel="python", robot_params={"tire_friction": 0.05})
        env.unwrapped._robot_kernel = "c"
        env.reset(seed=7)
        assert env.unwrapped.world.robot.kernel == "c"
        rng = np.random.default_rng(7)
        for _ in range(100):
            env.step(rng.integers(0, 3, size=2))
    finally:
        robot_mod.bind_kernel()
    assert len(calls) > 100


def _python_quantize(truth, suite):
    return np.array(
        [min(max(round(x * iq) * q, lo), hi)
         for x, iq, q, lo, hi in zip(truth, suite._inv_q_l, suite._q_l, suite._low_l,
                                     suite._high_l, strict=False)], dtype=np.float32)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(
    st.floats(-100, 100, allow_nan=False),
    st.integers(-200, 200).map(lambda k: k * 0.5),        # exact halves: ties to even
    st.floats(-1e-3, 1e-3),                                 # rounds to (negative) zero
), min_size=10, max_size=10))
def test_compiled_quantize_matches_python_bit_for_bit(truth):
    if robot_mod._fastsim is None:
        pytest.skip("compiled kernel not built")
    from mkv_env.params import channel_specs
    from mkv_env.sensors import SensorSuite

    suite = SensorSuite(channel_specs(None, 1.0))
    out = np.zeros(10, dtype=np.float32)
    robot_mod._fastsim.quantize(truth, suite._inv_q, suite._q, suite.low, suite.high, out)
    assert out.tobytes() == _python_quantize(truth, suite).tobytes()


def test_compiled_quantize_rejects_bad_input():
    if robot_mod._fastsim is None:
        pytest.skip("compiled kernel not built")
    q = np.ones(3)
    with pytest.raises(ValueError):
        robot_mod._fastsim.quantize([1.0, float("nan"), 0.0], q, q, q - 5, q + 5,
                                    np.zeros(3, np.float32))
    with pytest.raises(ValueError):  # wrong dtype of out
        robot_mod._fastsim.quantize([1.0, 2.0, 3.0], q, q, q, q, np.zeros(3))
