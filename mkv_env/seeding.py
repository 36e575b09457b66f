"""Episodes seeded as ``mkv eval`` seeds them, for evaluation loops that are not mkv's own.

``mkv eval --seed S`` starts episode ``i`` from env seed ``S + i``. Stable-Baselines3's
``evaluate_policy`` instead resets its vector env once and lets later episodes follow on from the
env's generator, so the same policy meets other arenas and jams and gets other numbers. Wrapping
the env in :class:`EpisodeSeeds` makes every reset (SB3's automatic ones included) use the next
seed of ``S, S + 1, ...``, so ``evaluate_policy`` gives ``mkv eval``'s episodes::

    import gymnasium as gym
    import mkv_env
    from mkv_env.seeding import EpisodeSeeds
    from stable_baselines3 import PPO
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.vec_env import DummyVecEnv

    venv = DummyVecEnv([lambda: EpisodeSeeds(gym.make("MKVJam-v1"), seed=S)])
    rewards, lengths = evaluate_policy(PPO.load("ppo.zip"), venv, n_eval_episodes=N,
                                       return_episode_rewards=True)
    # the per-episode returns of `mkv eval --env MKVJam-v1 --policy sb3:PPO:ppo.zip --seed S
    # --episodes N` (one env: with several, SB3 spreads the episodes over them)

``tests/mkv_env/test_seeding.py`` checks the equality.
"""

from __future__ import annotations

import gymnasium as gym


class EpisodeSeeds(gym.Wrapper):
    """Reset ``env`` with seeds ``seed, seed + 1, ...``, one per episode, whatever seed the caller
    passes (an explicit ``reset(seed=s)`` restarts the count at ``s``)."""

    def __init__(self, env: gym.Env, seed: int):
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        super().__init__(env)
        self._next = int(seed)
        self._started = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None and not self._started:
            pass  # the vector env's own first seeding: the episode seeds decide
        elif seed is not None:
            self._next = int(seed)
        self._started = True
        s, self._next = self._next, self._next + 1
        return self.env.reset(seed=s, options=options)
