"""Is the env PPO's bottleneck? SB3 PPO training env steps/s on MKV-v0 against LunarLander-v3.

Same hyperparameters for both (the packaged MKVJam-v1 settings: 8 sync envs x 256 steps,
minibatch 256, 10 epochs, MLP 64x64, one torch thread), raw observations, alternating rounds,
medians; MKV-v0 also on its native vector env (``SB3VecEnv``). Issue 15's target: MKV-v0 >=
LunarLander-v3 in the same run.

    python benchmarks/ppo_env_speed.py [--steps 40960] [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import mkv_env  # noqa: F401  (registers the ids)


def ppo_rate(env_id: str, steps: int, seed: int = 0, native: bool = False) -> float:
    """PPO env steps/s; ``native``: MK-V's own vector env (mkv_env.sb3_vec.SB3VecEnv) instead of
    SB3's DummyVecEnv of single envs."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    torch.set_num_threads(1)
    if native:
        from mkv_env.sb3_vec import SB3VecEnv

        venv = SB3VecEnv(env_id, n_envs=8, seed=seed)
    else:
        venv = make_vec_env(env_id, n_envs=8, seed=seed)
    model = PPO("MlpPolicy", venv, n_steps=256, batch_size=256, n_epochs=10, seed=seed,
                device="cpu", verbose=0,
                policy_kwargs={"net_arch": [64, 64], "activation_fn": torch.nn.Tanh})
    t0 = time.perf_counter()
    model.learn(total_timesteps=steps)
    dt = time.perf_counter() - t0
    venv.close()
    return model.num_timesteps / dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40_960)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    mkv, ll, nat = [], [], []
    for r in range(args.rounds):
        ll.append(ppo_rate("LunarLander-v3", args.steps))
        mkv.append(ppo_rate("MKV-v0", args.steps))
        nat.append(ppo_rate("MKV-v0", args.steps, native=True))
        print(f"round {r}: LunarLander-v3 {ll[-1]:,.0f}, MKV-v0 {mkv[-1]:,.0f}, MKV-v0 native "
              f"vector {nat[-1]:,.0f} env steps/s", flush=True)
    m, lm, nm = statistics.median(mkv), statistics.median(ll), statistics.median(nat)
    print(f"SB3 PPO env steps/s (medians): MKV-v0 {m:,.0f} (native vector env {nm:,.0f}), "
          f"LunarLander-v3 {lm:,.0f}: ratio {m / lm:.2f} (native {nm / lm:.2f}; target >= 1.0)")


if __name__ == "__main__":
    main()
