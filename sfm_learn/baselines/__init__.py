"""Stable-Baselines3 baselines the eigenspace policy is compared with.

* :mod:`~sfm_learn.baselines.sb3`: the policy-file container, the SB3 ``predict`` view of an
  ``ActorCriticPolicy``, observation rescaling, env factories;
* :mod:`~sfm_learn.baselines.bc`: behaviour cloning on the teacher's demonstrations (``bc:PATH``);
* :mod:`~sfm_learn.baselines.ppo`: PPO on the env reward (``ppo:PATH``).

torch and stable-baselines3 (the ``baselines`` extra) are imported inside functions.
"""
