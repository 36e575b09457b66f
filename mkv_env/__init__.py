"""mkv_env: the MK-V robot as Gymnasium environments on a pymunk 2-D world.

Importing this package registers ``MKV-v0``, ``MKVJam-v0`` and their v1 rewards ``MKV-v1``,
``MKVJam-v1``::

    import gymnasium as gym
    import mkv_env  # noqa: F401  (or use the id "mkv_env:MKV-v0")

    env = gym.make("MKV-v0")
"""

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

for _id, _entry, _steps in (
    ("MKV-v0", "mkv_env.envs:MKVEnv", 600),
    ("MKVJam-v0", "mkv_env.envs:MKVJamEnv", 300),
    ("MKV-v1", "mkv_env.envs:MKVEnvV1", 600),
    ("MKVJam-v1", "mkv_env.envs:MKVJamEnvV1", 300),
):
    if _id not in registry:
        register(id=_id, entry_point=_entry, max_episode_steps=_steps)
