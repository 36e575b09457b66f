"""Is the env PPO's bottleneck? SB3 PPO training env steps/s on MKV-v0 against LunarLander-v3.

Same hyperparameters for both (the packaged MKVJam-v1 settings: 8 sync envs x 256 steps,
minibatch 256, 10 epochs, MLP 64x64, one torch thread), raw observations, alternating rounds,
medians; MKV-v0 also on its native vector env (``SB3VecEnv``) with 8 envs, and with 64 envs x 32
steps (the same 2048 samples per rollout, so the same training work per sample). The
target: MKV-v0 >= LunarLander-v3 in the same run.

    python benchmarks/ppo_env_speed.py [--steps 40960] [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import mkv_env  # noqa: F401  (registers the ids)


def ppo_rate(env_id: str, steps: int, seed: int = 0, native: bool = False,
             n_envs: int = 8) -> float:
    """PPO env steps/s; ``native``: MK-V's own vector env (mkv_env.sb3_vec.SB3VecEnv) instead of
    SB3's DummyVecEnv of single envs; ``n_envs`` envs x ``2048 / n_envs`` steps per rollout."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    torch.set_num_threads(1)
    if native:
        from mkv_env.sb3_vec import SB3VecEnv

        venv = SB3VecEnv(env_id, n_envs=n_envs, seed=seed)
    else:
        venv = make_vec_env(env_id, n_envs=n_envs, seed=seed)
    model = PPO("MlpPolicy", venv, n_steps=2048 // n_envs, batch_size=256, n_epochs=10,
                seed=seed,
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
    mkv, ll, nat, nat64 = [], [], [], []
    for r in range(args.rounds):
        ll.append(ppo_rate("LunarLander-v3", args.steps))
        mkv.append(ppo_rate("MKV-v0", args.steps))
        nat.append(ppo_rate("MKV-v0", args.steps, native=True))
        nat64.append(ppo_rate("MKV-v0", args.steps, native=True, n_envs=64))
        print(f"round {r}: LunarLander-v3 {ll[-1]:,.0f}, MKV-v0 {mkv[-1]:,.0f}, MKV-v0 native "
              f"vector x8 {nat[-1]:,.0f}, x64 {nat64[-1]:,.0f} env steps/s", flush=True)
    m, lm, nm = statistics.median(mkv), statistics.median(ll), statistics.median(nat)
    n64 = statistics.median(nat64)
    print(f"SB3 PPO env steps/s (medians): MKV-v0 {m:,.0f} (native vector env x8 {nm:,.0f}, "
          f"x64 {n64:,.0f}), LunarLander-v3 {lm:,.0f}: ratio {m / lm:.2f} (native x8 "
          f"{nm / lm:.2f}, x64 {n64 / lm:.2f}; target >= 1.0)")


if __name__ == "__main__":
    main()
