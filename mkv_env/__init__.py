"""mkv_env: the MK-V robot as Gymnasium environments on a pymunk 2-D world.

Importing this package registers ``MKV-v0``, ``MKVJam-v0`` and their v1 rewards ``MKV-v1``,
``MKVJam-v1``::

    import gymnasium as gym
    import mkv_env  # noqa: F401  (or use the id "mkv_env:MKV-v0")

    env = gym.make("MKV-v0")
    envs = gym.make_vec("MKV-v0", num_envs=16, vectorization_mode="vector_entry_point")

The vector entry point (:class:`mkv_env.vector.MKVVectorEnv`) steps all robots in one process with
their physics batched; it is also what ``gym.make_vec(id, num_envs)`` picks by default.
"""

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

for _id, _entry, _vector, _steps in (
    ("MKV-v0", "mkv_env.envs:MKVEnv", "mkv_env.vector:wander_v0", 600),
    ("MKVJam-v0", "mkv_env.envs:MKVJamEnv", "mkv_env.vector:jam_v0", 300),
    ("MKV-v1", "mkv_env.envs:MKVEnvV1", "mkv_env.vector:wander_v1", 600),
    ("MKVJam-v1", "mkv_env.envs:MKVJamEnvV1", "mkv_env.vector:jam_v1", 300),
):
    if _id not in registry:
        register(id=_id, entry_point=_entry, vector_entry_point=_vector,
                 max_episode_steps=_steps)
