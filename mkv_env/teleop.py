"""Human teleoperation with the arrow keys, recorded into the dataset format.

::

    import gymnasium as gym
    from gymnasium.utils.play import play
    import mkv_env
    env = gym.make("MKV-v0", render_mode="rgb_array")
    play(env, keys_to_action=env.unwrapped.get_keys_to_action(), noop=mkv_env.teleop.NOOP)

or ``mkv teleop --env MKV-v0 --episodes 3 --out run.npz``, which records every step of a keyboard
run like ``mkv record`` does for a policy (the paper's teleoperated demonstrations, by a person).

Keys: up = drive forward, down = reverse, left / right = steer; combinations drive and steer at
once; no key = both motors off. Escape (or closing the window) ends the run. Needs a display;
headless machines drive the robot with command scripts (``script:PATH``) instead.

The only modules that import pygame are this one and :mod:`mkv_env.render` (both draw).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence

import numpy as np

from mkv_env.actions import FORWARD, LEFT, OFF, REVERSE, RIGHT

__all__ = ["NOOP", "TeleopError", "drive_episodes", "has_display", "keys_to_action",
           "record_keyboard"]

#: The action when no key is pressed: both motors off.
NOOP = np.array([OFF, OFF], dtype=np.int64)

# (drive, steer) per arrow-key combination, by key name (pygame.K_<name>)
_COMBOS = {
    ("UP",): (FORWARD, OFF), ("DOWN",): (REVERSE, OFF),
    ("LEFT",): (OFF, LEFT), ("RIGHT",): (OFF, RIGHT),
    ("UP", "LEFT"): (FORWARD, LEFT), ("UP", "RIGHT"): (FORWARD, RIGHT),
    ("DOWN", "LEFT"): (REVERSE, LEFT), ("DOWN", "RIGHT"): (REVERSE, RIGHT),
}


class TeleopError(RuntimeError):
    """Keyboard teleoperation is not possible here (no display, no pygame); one line."""


def has_display() -> bool:
    """Whether a pygame window can be opened (not SDL's dummy driver; an X/Wayland display)."""
    if os.environ.get("SDL_VIDEODRIVER", "") in ("dummy", "offscreen"):
        return False
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def keys_to_action() -> dict[tuple[int, ...], np.ndarray]:
    """The arrow-key mapping in the form :func:`gymnasium.utils.play.play` takes: sorted tuples
    of pygame key codes -> ``[drive, steer]`` actions (``NOOP`` when nothing is pressed)."""
    try:
        import pygame
    except ImportError:
        raise TeleopError("keyboard teleop needs pygame (pip install 'mkv-sfm[render]')") from None
    return {tuple(sorted(getattr(pygame, f"K_{k}") for k in keys)): np.array(a, dtype=np.int64)
            for keys, a in _COMBOS.items()}


def action_for(pressed, mapping: dict) -> np.ndarray:
    """The action for a set of pressed key codes (unknown combinations: the closest subset of
    arrow keys that maps, else ``NOOP``)."""
    relevant = tuple(sorted(k for k in pressed if any(k in combo for combo in mapping)))
    if relevant in mapping:
        return mapping[relevant].copy()
    for k in relevant:  # e.g. up+down: take the first key alone
        if (k,) in mapping:
            return mapping[(k,)].copy()
    return NOOP.copy()


def drive_episodes(env, seeds: Sequence[int], recorder, read_keys: Callable[[], set | None],
                   show: Callable[[np.ndarray], None] | None = None,
                   mapping: dict | None = None) -> int:
    """Run one episode per seed, the action at each step from the keys ``read_keys()`` reports
    pressed (``None`` ends the run), recording every step into ``recorder``
    (:class:`~mkv_env.recorder.EpisodeRecorder`). Returns the number of finished episodes; an
    episode cut short by ``None`` is dropped."""
    mapping = keys_to_action() if mapping is None else mapping
    done_episodes = 0
    for seed in seeds:
        obs, reset_info = env.reset(seed=int(seed))
        steps = []
        while True:
            if show is not None:
                show(env.render())
            pressed = read_keys()
            if pressed is None:
                return done_episodes
            action = action_for(pressed, mapping)
            next_obs, reward, terminated, truncated, info = env.step(action)
            steps.append((obs, action, float(reward), bool(terminated), bool(truncated), info))
            obs = next_obs
            if terminated or truncated:
                break
        recorder.begin(seed, reset_info)
        for step in steps:
            recorder.add(*step)
        recorder.end(obs)
        done_episodes += 1
    return done_episodes


def record_keyboard(env_id: str, episodes: int, seed: int = 0, env_kwargs: dict | None = None,
                    fps: int = 10, zoom: float = 1.0):
    """Drive ``episodes`` episodes of ``env_id`` with the arrow keys in a window; returns the
    :class:`~mkv_env.dataset.Dataset` (episode ``i`` uses env seed ``seed + i``), with
    ``policy`` = ``"human:keyboard"`` in its metadata. Raises :class:`TeleopError` (one line)
    when there is no display or no pygame."""
    if not has_display():
        raise TeleopError("mkv teleop needs a display (none here: SDL_VIDEODRIVER is dummy or "
                          "DISPLAY is unset); drive headless with a command script "
                          "(--policy script:PATH) instead")
    mapping = keys_to_action()
    import pygame

    from mkv_env.recorder import EpisodeRecorder, make_env, recording_metadata

    env = make_env(env_id, env_kwargs, render_mode="rgb_array")
    pygame.display.init()
    try:
        env.reset(seed=int(seed))
        first = env.render()
        size = (int(first.shape[1] * zoom), int(first.shape[0] * zoom))
        screen = pygame.display.set_mode(size)
        pygame.display.set_caption(f"mkv teleop {env_id}: arrows drive and steer, Esc ends")
        clock = pygame.time.Clock()
        pressed: set[int] = set()

        def read_keys():
            for event in pygame.event.get():
                if event.type == pygame.QUIT or (event.type == pygame.KEYDOWN
                                                 and event.key == pygame.K_ESCAPE):
                    return None
                if event.type == pygame.KEYDOWN:
                    pressed.add(event.key)
                elif event.type == pygame.KEYUP:
                    pressed.discard(event.key)
            clock.tick(fps)
            return set(pressed)

        def show(rgb):
            surf = pygame.surfarray.make_surface(np.ascontiguousarray(rgb.transpose(1, 0, 2)))
            screen.blit(pygame.transform.scale(surf, size), (0, 0))
            pygame.display.flip()

        recorder = EpisodeRecorder(env.unwrapped.sensor_names)
        n = drive_episodes(env, [int(seed) + i for i in range(int(episodes))], recorder,
                           read_keys, show, mapping)
        if n == 0:
            raise TeleopError("no episode was finished; nothing recorded")
        return recorder.to_dataset(recording_metadata(env, env_id, env_kwargs,
                                                      "human:keyboard", seed))
    finally:
        env.close()
        pygame.display.quit()
