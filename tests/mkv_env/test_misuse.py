"""Misuse reproducers that are input checks: each is one clear line, never a
MaskError, an OverflowError, a 'NoneType' error, an allocation without end, or a message that
prints the whole action array."""

import gymnasium as gym
import numpy as np
import pytest

import mkv_env  # noqa: F401  (registers the ids)
from mkv_env import kernel as kernel_mod
from mkv_env.vector import MAX_ENVS


@pytest.fixture(scope="module")
def vec():
    v = gym.make_vec("MKV-v1", num_envs=3, vectorization_mode="vector_entry_point")
    v.reset(seed=0)
    yield v
    v.close()


def _one_line(e):
    assert "\n" not in str(e), str(e)
    return str(e)


def test_a_masked_action_array_is_refused(vec):
    a = np.ma.masked_array(np.ones((3, 2), int), mask=[[0, 1], [0, 0], [0, 0]])
    with pytest.raises(TypeError, match="masked array") as e:
        vec.step(a)
    _one_line(e.value)


@pytest.mark.parametrize("actions", [
    np.full((3, 2), 7), np.array([[b"a", b"b"]] * 3), np.ones((3, 2), complex),
    np.ones((3, 2)) * 0.5, np.ones((40, 2), int), [[1, 1]] * 3 + [[1]]])
def test_bad_actions_are_one_line_without_the_array(vec, actions):
    with pytest.raises((ValueError, TypeError)) as e:
        vec.step(actions)
    msg = _one_line(e.value)
    assert "expected shape (3, 2)" in msg or "array of shape (3, 2)" in msg, msg
    assert len(msg) < 300, msg


def test_the_first_bad_entry_is_named(vec):
    a = np.ones((3, 2), int)
    a[2, 1] = 9
    with pytest.raises(ValueError, match=r"actions\[2, 1\] = 9"):
        vec.step(a)


def test_valid_actions_step_after_refusals(vec):
    obs, *_ = vec.step(np.ones((3, 2), int))
    assert obs.shape[0] == 3


@pytest.mark.parametrize("n", [0, -1, MAX_ENVS + 1, 2**40, 2.0, True])
def test_num_envs_out_of_range_is_refused_before_allocating(n):
    with pytest.raises(ValueError, match="num_envs") as e:
        gym.make_vec("MKV-v0", num_envs=n, vectorization_mode="vector_entry_point")
    _one_line(e.value)


def test_num_envs_beyond_the_machines_memory_is_refused_before_allocating(monkeypatch):
    """The refusal compares num_envs x ENV_BYTES with the memory available: 2 robots are refused
    where 512 KiB are available and built where 10 MiB are."""
    from mkv_env import vector

    monkeypatch.setattr(vector, "_available_bytes", lambda: 2**19)
    with pytest.raises(ValueError, match="num_envs=2 needs about .* GiB available") as e:
        gym.make_vec("MKV-v1", num_envs=2, vectorization_mode="vector_entry_point")
    _one_line(e.value)
    monkeypatch.setattr(vector, "_available_bytes", lambda: 10 * 2**20)
    envs = gym.make_vec("MKV-v1", num_envs=2, vectorization_mode="vector_entry_point")
    assert envs.num_envs == 2
    envs.close()


def test_available_memory_is_read_from_the_machine():
    from mkv_env import vector

    avail = vector._available_bytes()
    assert avail is None or avail > vector.ENV_BYTES


@pytest.mark.parametrize("kw,match", [({"jam_steps": 2**70}, "jam_steps"),
                                      ({"jam_steps": 0}, "jam_steps"),
                                      ({"scenarios": None}, "scenarios"),
                                      ({"scenarios": 3}, "scenarios"),
                                      ({"scenarios": ()}, "scenarios"),
                                      ({"scenarios": ["wall", "nowhere"]}, "scenarios")])
def test_jam_settings_out_of_range_are_one_line(kw, match):
    with pytest.raises(ValueError, match=match) as e:
        gym.make("MKVJam-v1", **kw)
    _one_line(e.value)


def test_two_threads_on_one_vector_env_get_a_clear_error_not_a_corrupt_heap():
    """Two Python threads stepping one vector env corrupted the heap (free(): invalid next
    size, SIGABRT); now the second is refused with a RuntimeError and the env stays usable."""
    import threading

    v = gym.make_vec("MKV-v1", num_envs=8, vectorization_mode="vector_entry_point",
                     num_threads=2)
    v.reset(seed=0)
    errors = []

    def run():
        for _ in range(2000):
            try:
                v.step(np.ones((8, 2), int))
            except RuntimeError as e:
                errors.append(str(e))
                return

    threads = [threading.Thread(target=run) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors and all("another thread" in e for e in errors)
    obs, *_ = v.step(np.ones((8, 2), int))
    assert np.all(np.isfinite(obs))
    v.close()


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs os.fork")
@pytest.mark.parametrize("threads", [1, 2, 8])
def test_a_forked_child_steps_closes_and_collects_without_hanging(threads):
    """After a fork the child has none of the parent's worker threads: stepping (it starts its
    own), closing, garbage collection and interpreter exit must neither hang nor crash (the
    batch's mutex and condition variable, which count the parent's waiters, are not destroyed
    in the child)."""
    import gc
    import os
    import time

    for what in ("step", "close", "gc"):
        v = gym.make_vec("MKV-v0", num_envs=8, vectorization_mode="vector_entry_point",
                         num_threads=threads)
        v.reset(seed=0)
        for _ in range(3):
            v.step(np.ones((8, 2), int))
        time.sleep(0.2)  # the workers wait for work
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child
            code = 0
            try:
                if what == "step":
                    for _ in range(3):
                        v.step(np.ones((8, 2), int))
                elif what == "close":
                    v.close()
                else:
                    del v
                    gc.collect()
            except BaseException:  # noqa: BLE001
                code = 3
            os._exit(code)
        deadline = time.monotonic() + 20
        status = None
        while time.monotonic() < deadline:
            done, st = os.waitpid(pid, os.WNOHANG)
            if done:
                status = os.waitstatus_to_exitcode(st)
                break
            time.sleep(0.02)
        if status is None:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
        v.close()
        assert status == 0, f"{what} at {threads} threads: {'hung' if status is None else status}"


@pytest.mark.parametrize("name", ["progress_reward", "stuck_penalty", "collision_penalty"])
def test_reward_weights_are_bounded_at_construction_and_after_set_attr(name):
    """Weights near 1.7e308 gave infinite rewards."""
    from mkv_env.envs import REWARD_WEIGHT_MAX

    with pytest.raises(ValueError, match=name) as e:
        gym.make("MKV-v1", **{name: 1.7e308})
    _one_line(e.value)
    v = gym.make_vec("MKV-v1", num_envs=2, vectorization_mode="vector_entry_point")
    v.reset(seed=0)
    v.set_attr(name, [REWARD_WEIGHT_MAX * 10, 1.0])
    with pytest.raises(ValueError, match=name):
        for _ in range(3):
            v.step(np.ones((2, 2), int))
            v.reset(seed=1)
    v.close()


def test_a_subclass_overriding_step_is_refused_not_silently_ignored():
    from mkv_env.envs import MKVEnv
    from mkv_env.vector import MKVVectorEnv

    class OwnStep(MKVEnv):
        def step(self, action):  # pragma: no cover - never called: that is the point
            raise AssertionError

    with pytest.raises(TypeError, match="overrides step") as e:
        MKVVectorEnv(2, OwnStep)
    _one_line(e.value)
    with pytest.raises(TypeError, match="env_cls"):
        MKVVectorEnv(2, dict)

    class Tuned(MKVEnv):  # a subclass that changes only parameters is fine
        pass

    v = MKVVectorEnv(2, Tuned)
    v.reset(seed=0)
    v.close()


@pytest.mark.parametrize("kernel", ["python", "c"] if kernel_mod.AVAILABLE else ["python"])
def test_a_step_with_an_env_never_reset_is_one_clear_line(kernel):
    """A first reset whose reset_mask leaves an env out used to leave it without a world (the
    python kernel's AttributeError, the C kernel's "slot has no world" at the next step): the
    step now says which envs were never reset, in one line; once they are, it steps."""
    v = gym.make_vec("MKV-v1", num_envs=3, vectorization_mode="vector_entry_point",
                     kernel=kernel)
    v.reset(seed=0, options={"reset_mask": np.array([True, False, True])})
    with pytest.raises(gym.error.ResetNeeded, match=r"env\(s\) \[1\] were never reset") as e:
        v.step(np.ones((3, 2), dtype=np.int64))
    assert "\n" not in str(e.value)
    obs, _ = v.reset(seed=5, options={"reset_mask": np.array([False, True, False])})
    assert obs.shape == (3, 10)
    v.step(np.ones((3, 2), dtype=np.int64))
    v.close()


@pytest.mark.parametrize("kernel", ["python", "c"] if kernel_mod.AVAILABLE else ["python"])
@pytest.mark.parametrize("vector", [False, True])
def test_a_kernel_error_is_raised_as_itself_in_one_line(kernel, vector):
    """A robot moved so far out of the arena that its MKV-v1 coverage cell leaves the 32-bit
    range: both kernels raise the same one-line "left the arena" error naming the robot, never
    "invalid actions" with the array printed."""
    if vector:
        env = gym.make_vec("MKV-v1", num_envs=3, vectorization_mode="vector_entry_point",
                           kernel=kernel)
        env.reset(seed=0)
        env.unwrapped.envs[1].world.robot.body.position = (1e12, 1e12)
        action, robot = np.ones((3, 2), dtype=np.int64), 1
    else:
        env = gym.make("MKV-v1", kernel=kernel)
        env.reset(seed=0)
        env.unwrapped.world.robot.body.position = (1e12, 1e12)
        action, robot = np.ones(2, dtype=np.int64), 0
    with pytest.raises(ValueError) as e:
        env.step(action)
    assert _one_line(e.value) == f"robot {robot} left the arena (coverage cell out of range)"
    env.close()
