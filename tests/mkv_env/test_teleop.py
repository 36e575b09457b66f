"""Keyboard teleop: the arrow-key mapping, gymnasium's play() driving the robot with it, the
recording loop (driven by scripted key events) and the one-line refusal without a display."""

import os
import sys

import gymnasium as gym
import numpy as np
import pytest

import mkv_env  # noqa: F401
from mkv_env.recorder import EpisodeRecorder, record, recording_metadata

pygame = pytest.importorskip("pygame")
from mkv_env import teleop  # noqa: E402

UP, DOWN, LEFT, RIGHT = pygame.K_UP, pygame.K_DOWN, pygame.K_LEFT, pygame.K_RIGHT


def key(kind, code):
    return pygame.event.Event(kind, key=code)


def press(code):
    return key(pygame.KEYDOWN, code)


def release(code):
    return key(pygame.KEYUP, code)


def scripted_events(monkeypatch, frames):
    """Make pygame.event.get return ``frames[k]`` on its k-th call (then QUIT forever)."""
    it = iter(frames)
    monkeypatch.setattr(pygame.event, "get",
                        lambda *a, **k: next(it, [pygame.event.Event(pygame.QUIT)]))


class Replay:
    """Sends the given actions in order (an SB3-style policy)."""

    def __init__(self, actions):
        self.actions = iter(np.asarray(actions))

    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        return next(self.actions), None


def test_the_arrows_reach_all_nine_actions_and_no_key_is_off():
    env = gym.make("MKV-v0", render_mode="rgb_array")
    mapping = env.unwrapped.get_keys_to_action()
    assert len(mapping) == 15  # every combination of the four arrows a player can hold
    assert all(k == tuple(sorted(k)) and k for k in mapping)
    assert all(a in env.action_space for a in mapping.values())
    actions = {tuple(a) for a in mapping.values()} | {tuple(teleop.NOOP)}
    assert actions == {(d, s) for d in range(3) for s in range(3)}
    assert tuple(teleop.NOOP) == (1, 1)

    def act(*keys):
        return mapping[tuple(sorted(keys))].tolist()

    assert act(UP) == [2, 1] and act(DOWN) == [0, 1] and act(LEFT) == [1, 0]
    assert act(RIGHT) == [1, 2] and act(DOWN, LEFT) == [0, 0] and act(UP, RIGHT) == [2, 2]
    assert act(UP, DOWN) == [1, 1] and act(LEFT, RIGHT) == [1, 1]  # opposites cancel
    assert act(UP, DOWN, LEFT) == [1, 0] and act(UP, LEFT, RIGHT) == [2, 1]
    assert teleop.action_for(set(), mapping).tolist() == [1, 1]
    assert teleop.action_for({UP, pygame.K_a}, mapping).tolist() == [2, 1]  # other keys ignored
    env.close()


def test_gymnasium_play_drives_the_robot_with_the_envs_own_mapping(monkeypatch):
    """play() finds get_keys_to_action itself (no MissingKeysToAction) and steps the env with
    the arrows held; with no key held it sends the noop."""
    import matplotlib

    backend = matplotlib.get_backend()
    from gymnasium.utils import play as play_module

    # gymnasium's play module selects matplotlib's TkAgg backend when it is imported (for its
    # PlayPlot): every later figure in this process then needs a display, and the plotting
    # tests that ran after this one on the same worker failed headless. Give
    # the process its backend back.
    matplotlib.use(backend)
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = gym.make("MKV-v0", render_mode="rgb_array", max_episode_steps=50)
    # one list of events per frame; play() steps once per frame after the first
    scripted_events(monkeypatch, [[press(UP)], [press(LEFT)], [release(UP)], [release(LEFT)],
                                  [press(DOWN), press(RIGHT)], []])
    sent = []
    play_module.play(env, noop=teleop.NOOP, fps=1000,
                     callback=lambda o0, o1, a, *rest: sent.append(np.asarray(a).tolist()))
    assert sent == [[2, 1], [2, 0], [1, 0], [1, 1], [0, 2], [0, 2]]
    env.close()


def test_a_keyboard_run_records_exactly_what_the_keys_commanded():
    keys = [{UP}] * 8 + [{DOWN, RIGHT}] * 5 + [set()] * 3 + [{LEFT}] * 100
    env = gym.make("MKVJam-v0", render_mode="rgb_array", max_episode_steps=12)
    stream = iter(keys)
    recorder = EpisodeRecorder(env.unwrapped.sensor_names)
    n = teleop.drive_episodes(env, [3, 4], recorder, lambda: next(stream))
    assert n == 2
    data = recorder.to_dataset(recording_metadata(env, "MKVJam-v0", {"max_episode_steps": 12},
                                                  "human:keyboard", 3))
    expect = np.array([[2, 1]] * 8 + [[0, 2]] * 4)
    np.testing.assert_array_equal(data["actions"][:12], expect)
    # the same actions run by the recorder's own loop give the same dataset, row for row
    again = record("MKVJam-v0", Replay(data["actions"]), 2, 3, {"max_episode_steps": 12})
    assert set(again.arrays) == set(data.arrays)
    for k in data.arrays:
        np.testing.assert_array_equal(again[k], data[k], err_msg=k)
    env.close()


def test_record_keyboard_from_key_events_equals_the_recorder(monkeypatch):
    """The whole record_keyboard path (window, event loop, key state) under SDL's dummy driver,
    with the keyboard replaced by a script of pygame events, one list per control step."""
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setattr(teleop, "_no_display_reason", lambda: None)
    frames = ([[press(UP)]] + [[]] * 5 + [[press(LEFT)]] + [[]] * 3
              + [[release(UP), release(LEFT), press(DOWN)], [press(RIGHT)], [], [release(DOWN)]]
              + [[]] * 12 + [[press(pygame.K_ESCAPE)]])
    scripted_events(monkeypatch, frames)
    kwargs = {"max_episode_steps": 10}
    data = teleop.record_keyboard("MKVJam-v0", 5, seed=7, env_kwargs=kwargs, fps=1000)
    # steps 0-9: episode 1 (seed 7); 10-19: episode 2 (seed 8); Escape in episode 3 drops it
    assert data.n_episodes == 2 and data["episode_seeds"].tolist() == [7, 8]
    acts = data["actions"]
    assert acts[:6].tolist() == [[2, 1]] * 6 and acts[6:10].tolist() == [[2, 0]] * 4
    assert acts[10:13].tolist() == [[0, 1], [0, 2], [0, 2]] and acts[13].tolist() == [1, 2]
    assert data.metadata["policy"] == "human:keyboard"
    again = record("MKVJam-v0", Replay(acts), 2, 7, kwargs)
    for k in data.arrays:
        np.testing.assert_array_equal(again[k], data[k], err_msg=k)
    assert {k: v for k, v in data.metadata.items() if k not in ("policy", "checksum")} \
        == {k: v for k, v in again.metadata.items() if k not in ("policy", "checksum")}


def test_record_keyboard_refuses_headless_in_one_line(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    assert not teleop.has_display()
    with pytest.raises(teleop.TeleopError) as e:
        teleop.record_keyboard("MKV-v0", 1)
    msg = str(e.value)
    assert isinstance(e.value, RuntimeError) and "\n" not in msg
    assert "needs a display" in msg and "SDL_VIDEODRIVER is dummy" in msg
    assert "script:PATH" in msg
    with pytest.raises(ValueError, match="episodes"):
        teleop.record_keyboard("MKV-v0", 0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="X/Wayland variables: linux")
def test_has_display_on_linux(monkeypatch):
    monkeypatch.delenv("SDL_VIDEODRIVER", raising=False)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert not teleop.has_display()
    with pytest.raises(teleop.TeleopError, match="neither DISPLAY nor WAYLAND_DISPLAY"):
        teleop.record_keyboard("MKV-v0", 1)
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    assert teleop.has_display()
    monkeypatch.setenv("SDL_VIDEODRIVER", "offscreen")
    assert not teleop.has_display()


def test_teleop_refuses_headless_in_one_line(tmp_path, capsys, monkeypatch):
    from sfm_learn.cli import main

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    code = main(["teleop", "--out", str(tmp_path / "run.npz")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "needs a display" in err
    assert "script:" in err and not os.path.exists(tmp_path / "run.npz")


# A display that has no server: an X display number nobody serves, a Wayland socket that does not
# exist. SDL then falls back to its offscreen driver; teleop must refuse instead of recording.
_NO_SERVER = [("DISPLAY", ":987"), ("WAYLAND_DISPLAY", "/nonexistent/mkv-wayland-0")]


def _serverless(monkeypatch, var, value):
    if var == "DISPLAY" and os.path.exists("/tmp/.X11-unix/X987"):
        pytest.skip("an X server answers on :987 here")
    monkeypatch.delenv("SDL_VIDEODRIVER", raising=False)
    for v in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(v, raising=False)
    monkeypatch.setenv(var, value)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="X/Wayland variables: linux")
@pytest.mark.parametrize("var,value", _NO_SERVER)
def test_record_keyboard_refuses_a_display_without_a_server(monkeypatch, var, value):
    _serverless(monkeypatch, var, value)
    assert teleop.has_display()  # the variables alone look fine: only opening tells
    with pytest.raises(teleop.TeleopError) as e:
        teleop.record_keyboard("MKV-v0", 1, fps=1000)
    msg = str(e.value)
    assert "\n" not in msg and f"{var}={value}" in msg and "no display server" in msg
    assert "script:PATH" in msg
    assert not pygame.display.get_init()  # left closed for whoever opens it next


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="X/Wayland variables: linux")
@pytest.mark.parametrize("var,value", _NO_SERVER)
def test_teleop_cli_refuses_a_display_without_a_server(tmp_path, capfd, monkeypatch, var, value):
    from sfm_learn.cli import main

    _serverless(monkeypatch, var, value)
    out = tmp_path / "run.npz"
    code = main(["teleop", "--out", str(out), "--fps", "60"])
    err = capfd.readouterr().err
    assert code == 2 and err.count("\n") == 1, err  # SDL's own chatter is silenced too
    assert "no display server" in err and "offscreen" in err and not out.exists()


def test_a_headless_driver_is_accepted_only_when_asked_for(monkeypatch):
    """The fallback is what is refused; SDL_VIDEODRIVER=dummy named on purpose (the scripted
    test path above) still opens."""
    class FakeDisplay:
        def __init__(self, driver):
            self.driver, self.open = driver, False

        def init(self):
            self.open = True

        def quit(self):
            self.open = False

        def get_driver(self):
            return self.driver

    class FakePygame:
        error = pygame.error

        def __init__(self, driver):
            self.display = FakeDisplay(driver)

    monkeypatch.setenv("DISPLAY", ":5")
    for driver, asked, ok in [("offscreen", "", False), ("dummy", "", False),
                              ("offscreen", "x11,offscreen", False), ("x11", "", True),
                              ("wayland", "", True), ("dummy", "dummy", True),
                              ("offscreen", "offscreen", True)]:
        monkeypatch.setenv("SDL_VIDEODRIVER", asked)
        fake = FakePygame(driver)
        if ok:
            teleop._init_display(fake)
            assert fake.display.open
        else:
            with pytest.raises(teleop.TeleopError, match=f"fell back to its {driver} driver"):
                teleop._init_display(fake)
            assert not fake.display.open
