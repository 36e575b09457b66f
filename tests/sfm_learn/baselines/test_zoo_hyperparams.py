"""`mkv train-ppo --hyperparams` reads rl-zoo3 ymls: policy, normalize, n_envs, policy_kwargs (as
data, never evaluated) are understood; what the trainer cannot honour is a one-line refusal."""

import subprocess
import sys

import pytest

from sfm_learn.baselines.ppo import load_hyperparameters

ZOO = """
MKV-v1:
  n_envs: 4
  n_timesteps: !!float 1e6
  policy: 'MlpPolicy'
  normalize: false
  n_steps: 64
  batch_size: 64
  gae_lambda: 0.95
  gamma: 0.99
  n_epochs: 2
  ent_coef: 0.0
  learning_rate: !!float 3e-4
  clip_range: 0.2
  policy_kwargs: "dict(net_arch=[32, 32], activation_fn=nn.Tanh, ortho_init=True)"
"""


def test_an_rl_zoo3_entry_is_read(tmp_path):
    p = tmp_path / "ppo.yml"
    p.write_text(ZOO)
    hp = load_hyperparameters("MKV-v1", str(p))
    assert hp["n_envs"] == 4 and hp["n_steps"] == 64 and hp["net_arch"] == [32, 32]
    assert hp["n_timesteps"] == 1_000_000 and hp["observation"] == "raw"


@pytest.mark.parametrize("line, match", [
    ("  normalize: true", "VecNormalize is not supported"),
    ("  policy: 'CnnPolicy'", "only MlpPolicy"),
    ('  policy_kwargs: "dict(net_arch=[8], activation_fn=nn.ReLU)"', "activation_fn"),
    ('  policy_kwargs: "__import__(\'os\').system(\'touch PWNED\')"', "must be dict"),
    ("  env_wrapper: sb3_contrib.common.wrappers.TimeFeatureWrapper", "env wrappers"),
    ("  learning_rate: lin_3e-4", "schedules"),
])
def test_what_cannot_be_honoured_is_refused_in_one_line(tmp_path, line, match):
    p = tmp_path / "ppo.yml"
    key = line.split(":")[0].strip()
    text = "\n".join(x for x in ZOO.splitlines() if not x.strip().startswith(key + ":"))
    p.write_text(text + "\n" + line + "\n")
    with pytest.raises(ValueError, match=match) as e:
        load_hyperparameters("MKV-v1", str(p))
    assert "\n" not in str(e.value)
    assert not (tmp_path / "PWNED").exists()


def test_mkv_train_ppo_trains_on_an_rl_zoo3_yml(tmp_path):
    pytest.importorskip("stable_baselines3")
    p = tmp_path / "ppo.yml"
    p.write_text(ZOO)
    out = tmp_path / "ppo.zip"
    code = ("import sys; from sfm_learn.cli import main; sys.exit(main(['train-ppo', '--env', "
            f"'MKV-v1', '--hyperparams', {str(p)!r}, '--timesteps', '2048', '--out', "
            f"{str(out)!r}, '--quiet']))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-400:]
    assert out.exists()


def test_env_kwargs_name_the_observation_and_nothing_else(tmp_path):
    p = tmp_path / "ppo.yml"
    p.write_text(ZOO.replace("  normalize: false", "  normalize: false\n  env_kwargs:\n"
                             "    observation: features"))
    assert load_hyperparameters("MKV-v1", str(p))["observation"] == "features"
    for extra, match in (("    observation: raw", "must be rescaled or features"),
                         ("    n_clutter: 3", "only {observation")):
        p.write_text(ZOO.replace("  normalize: false", f"  normalize: false\n  env_kwargs:\n"
                                 f"{extra}"))
        with pytest.raises(ValueError, match=match):
            load_hyperparameters("MKV-v1", str(p))


def test_the_packaged_file_trains_under_rl_zoo3_and_its_zip_runs_in_mkv(tmp_path):
    """The packaged hyperparameters are a valid rl-zoo3 yml (2,048 steps of
    ``python -m rl_zoo3.train ... --gym-packages mkv_env``), and the run's zip, trained on
    gym.make(id, observation="features"), runs through ``sb3:PPO:`` on a plain env exactly as
    plain SB3 runs it on the features env."""
    pytest.importorskip("rl_zoo3")
    import gymnasium as gym
    import numpy as np
    from stable_baselines3 import PPO

    import mkv_env  # noqa: F401
    from mkv_env.recorder import record
    from sfm_learn.baselines.ppo import HYPERPARAMS_FILE

    r = subprocess.run([sys.executable, "-m", "rl_zoo3.train", "--algo", "ppo", "--env",
                        "MKVJam-v1", "--gym-packages", "mkv_env", "--conf-file",
                        HYPERPARAMS_FILE, "-n", "2048", "--log-folder", str(tmp_path),
                        "--seed", "0", "--eval-freq", "-1", "--vec-env", "dummy"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    zips = list(tmp_path.glob("ppo/MKVJam-v1_*/MKVJam-v1.zip"))
    assert len(zips) == 1
    model = PPO.load(zips[0], device="cpu")
    kw = {"max_episode_steps": 40}
    seeds = [5, 6]
    plain = []
    for s in seeds:
        env = gym.make("MKVJam-v1", observation="features", **kw)
        obs, _ = env.reset(seed=s)
        done = False
        while not done:
            a, _ = model.predict(obs, deterministic=True)
            plain.append(a)
            obs, _, term, trunc, _ = env.step(a)
            done = term or trunc
    mkv = record("MKVJam-v1", f"sb3:PPO:{zips[0]}", len(seeds), seeds[0], kw)["actions"]
    np.testing.assert_array_equal(mkv, np.stack(plain))
