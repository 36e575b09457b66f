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
once; opposite arrows cancel (up + down = drive off); no key = both motors off (:data:`NOOP`,
the ``noop`` to give :func:`gymnasium.utils.play.play`, whose own default 0 is no MK-V action).
Escape (or closing the window) ends the run. Needs a display that a server answers for (SDL's
headless fallback is refused, not recorded as keyboard steps); headless machines drive the robot
with command scripts (``script:PATH``) instead.

The only modules that import pygame are this one and :mod:`mkv_env.render` (both draw).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from itertools import combinations

import numpy as np

from mkv_env.actions import FORWARD, LEFT, NOOP_ACTION, OFF, REVERSE, RIGHT

__all__ = ["NOOP", "TeleopError", "action_for", "drive_episodes", "has_display",
           "keys_to_action", "record_keyboard"]

#: The action when no key is pressed: both motors off, shape (2,).
NOOP = np.array(NOOP_ACTION, dtype=np.int64)

_ARROWS = ("UP", "DOWN", "LEFT", "RIGHT")


def _arrow_action(keys: frozenset[str]) -> tuple[int, int]:
    """(drive, steer) for a set of held arrow names; opposite arrows cancel."""
    def axis(plus: str, minus: str, plus_value: int, minus_value: int) -> int:
        if (plus in keys) == (minus in keys):
            return OFF
        return plus_value if plus in keys else minus_value
    return (axis("UP", "DOWN", FORWARD, REVERSE), axis("LEFT", "RIGHT", LEFT, RIGHT))


# (drive, steer) for every non-empty combination of arrow keys, by key name (pygame.K_<name>):
# every combination a player can hold maps, so play()'s noop is used only with no key held.
_COMBOS = {combo: _arrow_action(frozenset(combo))
           for n in range(1, len(_ARROWS) + 1) for combo in combinations(_ARROWS, n)}


class TeleopError(RuntimeError):
    """Keyboard teleoperation is not possible here (no display, no pygame); one line."""


def _no_display_reason() -> str | None:
    """Why no pygame window can be opened here, or None when one can."""
    driver = os.environ.get("SDL_VIDEODRIVER", "")
    if driver in ("dummy", "offscreen"):
        return f"SDL_VIDEODRIVER is {driver}"
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                 or os.environ.get("WAYLAND_DISPLAY")):
        return "neither DISPLAY nor WAYLAND_DISPLAY is set"
    return None


#: SDL video drivers that draw into memory only: no window a person could see or type into.
_HEADLESS_DRIVERS = ("dummy", "offscreen")


def _display_name() -> str:
    """The display variables as set, for a message: ``DISPLAY=:1``, ``WAYLAND_DISPLAY=w-0``."""
    shown = [f"{k}={os.environ[k]}" for k in ("DISPLAY", "WAYLAND_DISPLAY") if os.environ.get(k)]
    return " ".join(shown) or "the default display"


@contextmanager
def _quiet_stderr():
    """Silence file descriptor 2 for the duration: SDL and libwayland print their own
    multi-line complaints while probing video drivers (the refusal says what matters)."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _init_display(pygame) -> None:
    """``pygame.display.init()``, refused in one line (:class:`TeleopError`) unless SDL opened a
    real video driver. With DISPLAY or WAYLAND_DISPLAY naming a display that has no server, SDL
    falls back to its ``offscreen`` driver: a window nobody sees and a keyboard nobody can press,
    which would record no-op steps labelled ``human:keyboard``. A headless driver is accepted only
    when SDL_VIDEODRIVER names it (the scripted path of the tests; :func:`record_keyboard` itself
    refuses that variable before getting here)."""
    with _quiet_stderr():
        try:
            pygame.display.init()
        except pygame.error as e:
            reason = str(e).splitlines()[0] if str(e) else "SDL error"
            raise TeleopError(f"mkv teleop cannot open {_display_name()} ({reason}); use a "
                              "command script (script:PATH) for keyboard-less teleop") from None
    driver = pygame.display.get_driver()
    if driver in _HEADLESS_DRIVERS and driver != os.environ.get("SDL_VIDEODRIVER", ""):
        pygame.display.quit()
        raise TeleopError(f"mkv teleop cannot open {_display_name()}: no display server answers "
                          f"(SDL fell back to its {driver} driver); use a command script "
                          "(script:PATH) for keyboard-less teleop")


def has_display() -> bool:
    """Whether a pygame window can be opened: False under SDL's ``dummy``/``offscreen`` video
    drivers and, on Linux, when neither ``DISPLAY`` nor ``WAYLAND_DISPLAY`` is set."""
    return _no_display_reason() is None


def keys_to_action() -> dict[tuple[int, ...], np.ndarray]:
    """The arrow-key mapping in the form :func:`gymnasium.utils.play.play` takes.

    Returns:
        dict from a sorted tuple of pygame key codes (every non-empty combination of the four
        arrows, 15 in all) to an int64 ``[drive, steer]`` action of shape (2,). No key held is
        not in the dict (play() refuses an empty tuple): it is :data:`NOOP`.

    Raises:
        TeleopError: pygame is not installed.
    """
    try:
        import pygame
    except ImportError:
        raise TeleopError("keyboard teleop needs pygame (pip install 'mkv-sfm[render]')") from None
    return {tuple(sorted(getattr(pygame, f"K_{k}") for k in keys)): np.array(a, dtype=np.int64)
            for keys, a in _COMBOS.items()}


def action_for(pressed, mapping: dict) -> np.ndarray:
    """The action, shape (2,), for a set of held key codes, as play() picks it: keys that appear
    in no combination of ``mapping`` are ignored; a combination not in ``mapping`` (or none held)
    is ``NOOP``."""
    keys = {k for combo in mapping for k in combo}
    relevant = tuple(sorted(k for k in pressed if k in keys))
    return np.array(mapping.get(relevant, NOOP), dtype=np.int64)


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
    """Drive ``episodes`` episodes of ``env_id`` with the arrow keys in a window.

    Args:
        env_id: a registered env id (``"MKV-v0"``); ``env_kwargs`` go to ``gymnasium.make``.
        episodes: episodes to drive; episode ``i`` resets the env with seed ``seed + i``.
        fps: control steps per second of wall time (10 = real time for ``MKV-v0``).
        zoom: window scale.

    Returns:
        the :class:`~mkv_env.dataset.Dataset` of the finished episodes, exactly as
        :func:`mkv_env.recorder.record` would store the same actions, with ``policy`` =
        ``"human:keyboard"`` in its metadata. Escape or closing the window ends the run (an
        unfinished episode is dropped).

    Raises:
        TeleopError: (one line) no display, no pygame, or no episode finished.
        ValueError: a bad argument or env id.
    """
    if not (_integer(episodes) and episodes >= 1):
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    if not (_integer(seed) and 0 <= seed < 2**63 - episodes):
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    for name, v in (("fps", fps), ("zoom", zoom)):
        if not (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                and 0 < v < float("inf")):
            raise ValueError(f"{name} must be a positive number, got {v!r}")
    reason = _no_display_reason()
    if reason is not None:
        raise TeleopError(f"mkv teleop needs a display ({reason}); use a command script "
                          "(script:PATH) for keyboard-less teleop")
    mapping = keys_to_action()
    import pygame

    from mkv_env.recorder import EpisodeRecorder, make_env, recording_metadata

    env = make_env(env_id, env_kwargs, render_mode="rgb_array")
    try:
        _init_display(pygame)
    except BaseException:
        env.close()
        raise
    try:
        env.reset(seed=int(seed))
        first = env.render()
        size = (int(first.shape[1] * zoom), int(first.shape[0] * zoom))
        try:
            screen = pygame.display.set_mode(size)
        except pygame.error as e:
            reason = str(e).splitlines()[0] if str(e) else "SDL error"
            raise TeleopError(f"mkv teleop cannot open a window on {_display_name()} "
                              f"({reason})") from None
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


def _integer(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)
