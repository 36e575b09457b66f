"""The scripted teacher, command-script teleop and policy specs."""

import gymnasium as gym
import numpy as np
import pytest

import mkv_env  # noqa: F401
from mkv_env import teacher as T
from mkv_env.policies import (
    PolicySpecError,
    RandomPolicy,
    make_policy,
    register_policy_loader,
)
from mkv_env.recorder import policy_seed, record
from mkv_env.script import (
    ScriptError,
    ScriptPolicy,
    format_script,
    parse_script,
    script_from_actions,
)
from mkv_env.teacher import BACKOFF, CRUISE, TURN, ScriptedTeacher

FWD, OFF, REV = 2, 1, 0
LEFT, RIGHT = 0, 2


def obs(drive_ticks=18, roller_ticks=22, steer=0.0, bumps=(0, 0, 0), current=0.05):
    """A synthetic observation in the env's channel order (cruising freely by default)."""
    o = np.zeros(10, dtype=np.float32)
    o[0], o[1], o[2] = drive_ticks, roller_ticks, steer
    o[4:7] = bumps
    o[7], o[9] = current, 7.1
    return o


def test_sensor_order_matches_env():
    env = gym.make("MKV-v0")
    assert tuple(env.unwrapped.sensor_names) == T.SENSOR_NAMES
    ScriptedTeacher().check_env(env)


def test_cruises_forward_when_free():
    t = ScriptedTeacher(wander_rate_hz=0.0, seed=0)
    for k in range(200):
        a, state = t.predict(obs(), episode_start=(k == 0))
        assert state is None
        assert tuple(a) == (FWD, OFF)
    assert a.shape == (2,) and a.dtype == np.int64


def test_recentres_steering_while_cruising():
    t = ScriptedTeacher(wander_rate_hz=0.0)
    assert t.predict(obs(steer=0.4))[0][1] == RIGHT  # steer_angle is left positive
    assert t.predict(obs(steer=-0.4))[0][1] == LEFT
    assert t.predict(obs(steer=0.01))[0][1] == OFF


def test_bump_backs_off_straight_then_steering_then_turns_the_other_way():
    t = ScriptedTeacher(backoff_s=1.0, straight_s=0.3, turn_s=0.5, wander_rate_hz=0.0, seed=3)
    t.predict(obs(), episode_start=True)
    a, _ = t.predict(obs(bumps=(1, 0, 0), current=0.4))
    assert t.mode[0] == BACKOFF and a[0] == REV
    actions = [a] + [t.predict(obs(drive_ticks=-18, roller_ticks=-22))[0] for _ in range(9)]
    assert all(x[0] == REV for x in actions)
    side = actions[-1][1]
    assert side in (LEFT, RIGHT)
    assert all(x[1] == side for x in actions[3:])          # steering after straight_s
    assert all(x[1] == OFF for x in actions[:3])            # steering centred at first
    turn = [t.predict(obs())[0] for _ in range(5)]
    assert all(x[0] == FWD and x[1] == LEFT + RIGHT - side for x in turn)
    assert t.mode[0] == TURN
    t.predict(obs())
    assert t.mode[0] == CRUISE


def test_rear_bump_cuts_backoff_short():
    t = ScriptedTeacher(backoff_s=2.0, wander_rate_hz=0.0)
    t.predict(obs(bumps=(0, 1, 0)), episode_start=True)  # last command off: no trigger yet
    t.predict(obs())
    t.predict(obs(bumps=(0, 1, 0)))
    assert t.mode[0] == BACKOFF
    t.predict(obs(drive_ticks=-5, bumps=(0, 0, 1)))
    assert t.mode[0] == TURN


@pytest.mark.parametrize("blocked", [
    dict(current=0.45, drive_ticks=4, roller_ticks=5),   # stall current
    dict(drive_ticks=0, roller_ticks=0),                 # wheel does not turn
    dict(drive_ticks=6, roller_ticks=0),                 # wheel spins, roller does not
])
def test_stall_evidence_without_bump_triggers_escape(blocked):
    t = ScriptedTeacher(wander_rate_hz=0.0, stall_steps=2, grace_steps=2)
    for k in range(5):
        t.predict(obs(), episode_start=(k == 0))
    a, _ = t.predict(obs(**blocked))
    assert a[0] == FWD  # one period of evidence is not enough
    a, _ = t.predict(obs(**blocked))
    assert a[0] == REV and t.mode[0] == BACKOFF


def test_start_up_current_is_ignored_during_grace():
    t = ScriptedTeacher(wander_rate_hz=0.0, stall_steps=1, grace_steps=2)
    a, _ = t.predict(obs(current=0.45, drive_ticks=0), episode_start=True)
    a, _ = t.predict(obs(current=0.45, drive_ticks=3))
    assert a[0] == FWD


def test_escape_side_is_random_and_seeded():
    def sides(seed):
        t = ScriptedTeacher(seed=seed, wander_rate_hz=0.0, straight_s=0.0)
        out = []
        for _ in range(60):
            t.predict(obs(), episode_start=True)
            t.predict(obs())
            out.append(int(t.predict(obs(bumps=(1, 1, 0)))[0][1]))
        return out

    s = sides(1)
    assert s == sides(1)
    assert s != sides(2)
    assert 15 < s.count(LEFT) < 45 and s.count(LEFT) + s.count(RIGHT) == 60


def test_wander_steers_sometimes():
    t = ScriptedTeacher(wander_rate_hz=1.0, seed=0)
    steer = [t.predict(obs(), episode_start=(k == 0))[0][1] for k in range(300)]
    assert 0.05 < np.mean(np.array(steer) != OFF) < 0.8
    t0 = ScriptedTeacher(wander_rate_hz=0.0, seed=0)
    assert all(t0.predict(obs())[0][1] == OFF for _ in range(300))


def test_batch_predict_and_per_env_reset():
    t = ScriptedTeacher(wander_rate_hz=0.0, backoff_s=1.0)
    batch = np.stack([obs(), obs(), obs()])
    a, _ = t.predict(batch, episode_start=np.array([True, True, True]))
    assert a.shape == (3, 2)
    t.predict(batch)
    bumped = batch.copy()
    bumped[[0, 2], 4] = 1.0
    a, _ = t.predict(bumped)
    assert list(a[:, 0]) == [REV, FWD, REV]
    assert list(t.mode) == [BACKOFF, CRUISE, BACKOFF]
    t.predict(batch, episode_start=np.array([False, False, True]))
    assert list(t.mode) == [BACKOFF, CRUISE, CRUISE]


def test_batch_in_a_vector_env():
    envs = gym.vector.SyncVectorEnv([lambda: gym.make("MKVJam-v0") for _ in range(3)])
    t = ScriptedTeacher(seed=0)
    o, _ = envs.reset(seed=[10, 11, 12])
    start = np.ones(3, dtype=bool)
    escaped = np.zeros(3, dtype=bool)
    for _ in range(100):
        a, _ = t.predict(o, episode_start=start)
        assert a.shape == (3, 2)
        o, r, term, trunc, info = envs.step(a)
        escaped |= term
        start = term | trunc
        if escaped.all():
            break
    envs.close()
    assert escaped.all()


def test_bad_observation_and_parameters():
    with pytest.raises(ValueError, match="shape"):
        ScriptedTeacher().predict(np.zeros(7))
    with pytest.raises(ValueError, match="backoff_s"):
        ScriptedTeacher(backoff_s=0)
    with pytest.raises(ValueError, match="stall_steps"):
        ScriptedTeacher(stall_steps=0)


def test_teacher_escapes_jams_regression():
    """Seeded regression: the full 200-episode number is in docs/recorder.md."""
    data = record("MKVJam-v0", "teacher", episodes=40, seed=1000)
    last = np.cumsum(data["episode_lengths"]) - 1
    assert data["escaped"][last].mean() >= 0.95


def test_driving_on_into_the_jam_does_not_escape():
    """The escape test above can fail: doing nothing useful does not escape."""
    data = record("MKVJam-v0", ScriptPolicy([0.0], [[FWD, OFF]]), episodes=10, seed=1000)
    last = np.cumsum(data["episode_lengths"]) - 1
    assert data["escaped"][last].mean() < 0.5


# ---------------------------------------------------------------------- command scripts
SCRIPT = """# a short session
0.0  forward off
0.3  forward left   # wander
1.0  2 1
1.5  reverse right
"""


def test_parse_script_words_and_numbers():
    times, cmds = parse_script(SCRIPT)
    assert list(times) == [0.0, 0.3, 1.0, 1.5]
    assert cmds.tolist() == [[FWD, OFF], [FWD, LEFT], [FWD, OFF], [REV, RIGHT]]
    again = parse_script(format_script(times, cmds, header="round trip"))
    assert np.array_equal(again[0], times) and np.array_equal(again[1], cmds)


@pytest.mark.parametrize("text,match", [
    ("0.0 forward\n", ":1: expected"),
    ("0 forward off\n0 forward off\n", ":2: times must increase"),
    ("x forward off\n", "not a number"),
    ("-1 forward off\n", ">= 0"),
    ("0 sideways off\n", "drive must be"),
    ("0 forward 3\n", "steer must be"),
    ("# nothing\n\n", "no commands"),
])
def test_script_errors_name_the_line(text, match):
    with pytest.raises(ScriptError, match=match):
        parse_script(text, "s.txt")


def test_script_policy_timing():
    p = ScriptPolicy(*parse_script(SCRIPT), control_period_s=0.1)
    acts = [tuple(p.predict(obs(), episode_start=(k == 0))[0]) for k in range(20)]
    assert acts[:3] == [(FWD, OFF)] * 3
    assert acts[3:10] == [(FWD, LEFT)] * 7
    assert acts[10:15] == [(FWD, OFF)] * 5
    assert acts[15:] == [(REV, RIGHT)] * 5
    late = ScriptPolicy([0.5], [[FWD, FWD]])
    assert tuple(late.predict(obs())[0]) == (OFF, OFF)  # both off before the first command
    b, _ = p.predict(np.stack([obs(), obs()]), episode_start=[True, True])
    assert b.tolist() == [[FWD, OFF], [FWD, OFF]]


def test_a_recorded_session_written_as_a_script_replays_exactly(tmp_path):
    data = record("MKV-v0", "teacher", episodes=1, seed=7)
    times, cmds = script_from_actions(data["actions"], 0.1)
    path = tmp_path / "session.txt"
    path.write_text(format_script(times, cmds))
    replay = record("MKV-v0", f"script:{path}", episodes=1, seed=7)
    assert np.array_equal(replay["actions"], data["actions"])
    assert np.array_equal(replay["observations"], data["observations"])
    assert np.array_equal(replay["pose"], data["pose"])


# ---------------------------------------------------------------------- policy specs
def test_policy_specs():
    env = gym.make("MKV-v0")
    t = make_policy("teacher:backoff_s=2,stall_steps=3", env, seed=1)
    assert isinstance(t, ScriptedTeacher) and t.backoff_s == 2.0 and t.stall_steps == 3
    assert isinstance(make_policy("random", env, seed=1), RandomPolicy)
    for bad, match in [("nope", "unknown policy spec"), ("teacher:wings=2", "bad teacher option"),
                       ("teacher:backoff_s=-1", "backoff_s"), ("random:3", "no argument"),
                       ("script:", "needs a file"), ("script:/no/such/file", "not found"),
                       ("", "non-empty")]:
        with pytest.raises(PolicySpecError, match=match):
            make_policy(bad, env)


def test_random_policy_is_seeded_and_batched():
    p = RandomPolicy(seed=0)
    a = np.stack([p.predict(obs())[0] for _ in range(200)])
    p.reset(seed=0)
    b = np.stack([p.predict(obs())[0] for _ in range(200)])
    assert np.array_equal(a, b) and set(np.unique(a)) == {0, 1, 2}
    assert p.predict(np.zeros((4, 10)))[0].shape == (4, 2)


def test_lazy_loader_registry():
    calls = []
    register_policy_loader("testonly-lazy", "mkv_env.policies:_load_random", replace=True)
    assert isinstance(make_policy("testonly-lazy", gym.make("MKV-v0")), RandomPolicy)
    register_policy_loader("testonly-missing", "no_such_module_xyz:load", replace=True)
    with pytest.raises(PolicySpecError, match="unavailable"):
        make_policy("testonly-missing:x")
    register_policy_loader("testonly-fn", lambda arg, env, seed: calls.append(arg) or "p",
                           replace=True)
    assert make_policy("testonly-fn:some/path.npz") == "p" and calls == ["some/path.npz"]
    with pytest.raises(ValueError, match="already registered"):
        register_policy_loader("teacher", "x:y")


def test_policy_seed_differs_from_env_seed():
    assert policy_seed(0) != 0 and policy_seed(0) == policy_seed(0) != policy_seed(1)
