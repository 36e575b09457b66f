"""Keyboard teleop: the arrow-key mapping, gymnasium's play() accepting it, the recording loop
(driven by scripted key presses) and the one-line refusal without a display."""

import os

import gymnasium as gym
import numpy as np
import pytest

import mkv_env  # noqa: F401
from mkv_env.recorder import EpisodeRecorder, record

pygame = pytest.importorskip("pygame")
from mkv_env import teleop  # noqa: E402


def test_the_arrows_reach_all_nine_actions_and_no_key_is_off():
    env = gym.make("MKV-v0", render_mode="rgb_array")
    mapping = env.unwrapped.get_keys_to_action()
    actions = {tuple(a) for a in mapping.values()} | {tuple(teleop.NOOP)}
    assert actions == {(d, s) for d in range(3) for s in range(3)}
    assert tuple(teleop.NOOP) == (1, 1)
    assert mapping[(pygame.K_UP,)].tolist() == [2, 1]
    assert mapping[tuple(sorted((pygame.K_DOWN, pygame.K_LEFT)))].tolist() == [0, 0]
    assert all(k == tuple(sorted(k)) for k in mapping)
    env.close()


def test_gymnasium_play_accepts_the_mapping(monkeypatch):
    """play() finds the env's mapping itself (no MissingKeysToAction) and runs until the window
    closes; here a QUIT event closes it at once."""
    from gymnasium.utils import play as play_module

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = gym.make("MKV-v0", render_mode="rgb_array", max_episode_steps=5)
    real_get = pygame.event.get
    monkeypatch.setattr(pygame.event, "get", lambda: [pygame.event.Event(pygame.QUIT)]
                        + list(real_get()))
    play_module.play(env, noop=teleop.NOOP, fps=1000)
    env.close()


def test_a_keyboard_run_records_exactly_what_the_keys_commanded():
    keys = [{pygame.K_UP}] * 8 + [{pygame.K_DOWN, pygame.K_RIGHT}] * 5 + [set()] * 3 \
        + [{pygame.K_LEFT}] * 100
    env = gym.make("MKVJam-v0", render_mode="rgb_array", max_episode_steps=12)
    stream = iter(keys)
    recorder = EpisodeRecorder(env.unwrapped.sensor_names)
    n = teleop.drive_episodes(env, [3, 4], recorder, lambda: next(stream))
    assert n == 2
    from mkv_env.recorder import recording_metadata

    data = recorder.to_dataset(recording_metadata(env, "MKVJam-v0", {"max_episode_steps": 12},
                                                  "human:keyboard", 3))
    expect = np.array([[2, 1]] * 8 + [[0, 2]] * 4)
    np.testing.assert_array_equal(data["actions"][:12], expect)
    # the same actions replayed by the recorder's own runner give the same dataset rows
    script = iter(data["actions"])

    class Replay:
        def predict(self, obs, state=None, episode_start=None, deterministic=True):
            return next(script), None

    again = record("MKVJam-v0", Replay(), 2, 3, {"max_episode_steps": 12})
    for key in ("observations", "actions", "rewards", "stuck", "episode_seeds"):
        np.testing.assert_array_equal(again[key], data[key])
    env.close()


def test_teleop_refuses_headless_in_one_line(tmp_path, capsys, monkeypatch):
    from sfm_learn.cli import main

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    code = main(["teleop", "--out", str(tmp_path / "run.npz")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "needs a display" in err
    assert "script:" in err and not os.path.exists(tmp_path / "run.npz")
