"""Stable-Baselines3 interop: every policy spec works in SB3's ``evaluate_policy`` on a vector env,
mkv's PPO zips run under plain SB3, and zips saved by plain SB3 (also recurrent ones) run in mkv."""

import os

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.common.monitor import Monitor  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize  # noqa: E402

import mkv_env  # noqa: E402,F401
from mkv_env.dataset import save  # noqa: E402
from mkv_env.policies import make_policy  # noqa: E402
from mkv_env.recorder import make_env, record  # noqa: E402
from sfm_learn.baselines import bc  # noqa: E402
from sfm_learn.baselines import ppo as mkv_ppo  # noqa: E402
from sfm_learn.cli import main  # noqa: E402
from sfm_learn.eigenspace.policy import fit_policy  # noqa: E402

SHORT = {"max_episode_steps": 40}


@pytest.fixture(scope="module")
def files(tmp_path_factory, small_train):
    """An SfM policy, a BC zip, an mkv PPO zip and a plain-SB3 PPO zip, all tiny."""
    d = tmp_path_factory.mktemp("interop")
    sfm = fit_policy(small_train).save(d / "sfm.npz")
    policy, meta = bc.train(small_train, epochs=2, held_out=0.0)
    bc.save(policy, meta, d / "bc.zip")
    model, meta = mkv_ppo.train("MKVJam-v0", 128, n_envs=1, env_kwargs=SHORT,
                                eval_episodes=1, hyperparameters={"n_steps": 64})
    mkv_ppo.save(model, meta, d / "ppo.zip")
    plain = PPO("MlpPolicy", gym.make("MKVJam-v0", **SHORT), n_steps=64, batch_size=32,
                seed=0, device="cpu")
    plain.learn(128)
    plain.save(d / "plain.zip")
    save(small_train, d / "train.npz")
    return {"sfm": f"sfm:{sfm}", "bc": f"bc:{d / 'bc.zip'}", "ppo": f"ppo:{d / 'ppo.zip'}",
            "sb3": f"sb3:PPO:{d / 'plain.zip'}", "dir": d}


@pytest.mark.parametrize("name", ["teacher", "random", "sfm", "bc", "ppo", "sb3"])
def test_evaluate_policy_on_a_vector_env_of_two(files, name):
    spec = files.get(name, name)
    venv = DummyVecEnv([lambda: Monitor(gym.make("MKVJam-v0", **SHORT))] * 2)
    venv.seed(7)
    policy = make_policy(spec, venv.envs[0], seed=0)
    rewards, lengths = evaluate_policy(policy, venv, n_eval_episodes=4, return_episode_rewards=True)
    assert len(rewards) == 4 and all(0 < n <= 40 for n in lengths)
    assert all(np.isfinite(rewards))


def actions_plain(model, env_id, seeds, wrap=lambda e: e, state_kept=True, make_kwargs=None):
    """What a plain SB3 user would do: PPO.load + gymnasium.make (``make_kwargs``, default
    SHORT) + public wrappers, one episode per seed, deterministic actions (recurrent state
    threaded unless ``state_kept`` is False). Returns the actions of all episodes, stacked."""
    out = []
    for s in seeds:
        env = wrap(gym.make(env_id, **(SHORT if make_kwargs is None else make_kwargs)))
        obs, _ = env.reset(seed=s)
        state, start, done = None, True, False
        while not done:
            action, new_state = model.predict(obs, state=state, episode_start=np.array([start]),
                                              deterministic=True)
            state = new_state if state_kept else None
            start = False
            out.append(action)
            obs, _, term, trunc, _ = env.step(action)
            done = term or trunc
    return np.stack(out)


def actions_mkv(spec, seeds):
    """The same episodes through mkv's episode runner (what ``mkv eval``/``mkv record`` run)."""
    return record("MKVJam-v0", spec, len(seeds), seeds[0], SHORT)["actions"]


def test_mkv_ppo_zip_under_plain_sb3_equals_mkv_eval(files):
    """``mkv train-ppo``'s zip + plain ``PPO.load`` + the documented public wrapper
    (gymnasium's RescaleObservation to [-1, 1]) gives what ``mkv eval ppo:`` gives."""
    from gymnasium.wrappers import RescaleObservation

    model = PPO.load(files["ppo"][4:], device="cpu")
    seeds = list(range(300, 305))
    plain = actions_plain(
        model, "MKVJam-v0", seeds,
        wrap=lambda e: RescaleObservation(e, np.float32(-1.0), np.float32(1.0)))
    np.testing.assert_array_equal(actions_mkv(files["ppo"], seeds), plain)
    # and the sb3: spec on the same zip applies the same rescaling
    np.testing.assert_array_equal(actions_mkv(f"sb3:PPO:{files['ppo'][4:]}", seeds), plain)


def test_sb3_spec_runs_a_zip_saved_by_plain_sb3(files, capsys, tmp_path):
    model = PPO.load(files["sb3"].split(":", 2)[2], device="cpu")
    seeds = list(range(300, 305))
    np.testing.assert_array_equal(actions_mkv(files["sb3"], seeds),
                                  actions_plain(model, "MKVJam-v0", seeds))
    out = tmp_path / "e.json"
    code = main(["eval", "--env", "MKVJam-v0", "--env-kwargs", '{"max_episode_steps": 40}',
                 "--policy", files["sb3"], "--episodes", "2", "--json", str(out), "--quiet"])
    assert code == 0 and out.exists()


def test_sb3_spec_applies_rl_zoo3_observation_normalisation(files, tmp_path):
    """rl-zoo3 layout: <run>/<env>.zip with <run>/<env>/vecnormalize.pkl."""
    run = tmp_path / "MKVJam-v0_1"
    (run / "MKVJam-v0").mkdir(parents=True)
    venv = VecNormalize(DummyVecEnv([lambda: gym.make("MKVJam-v0", **SHORT)]), norm_reward=False)
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=32, seed=1, device="cpu")
    model.learn(128)
    model.save(run / "MKVJam-v0.zip")
    venv.save(run / "MKVJam-v0" / "vecnormalize.pkl")
    stats = VecNormalize.load(run / "MKVJam-v0" / "vecnormalize.pkl",
                              DummyVecEnv([lambda: gym.make("MKVJam-v0", **SHORT)]))
    stats.training = False

    class Normalise(gym.ObservationWrapper):
        def observation(self, obs):
            return stats.normalize_obs(obs)

    seeds = list(range(310, 313))
    plain = actions_plain(PPO.load(run / "MKVJam-v0.zip", device="cpu"), "MKVJam-v0", seeds,
                          wrap=Normalise)
    np.testing.assert_array_equal(actions_mkv(f"sb3:PPO:{run / 'MKVJam-v0.zip'}", seeds), plain)
    raw = actions_plain(PPO.load(run / "MKVJam-v0.zip", device="cpu"), "MKVJam-v0", seeds)
    assert not np.array_equal(raw, plain), "normalisation changes nothing: test proves nothing"


def test_recurrent_ppo_keeps_its_memory_in_mkv_eval(tmp_path):
    """RecurrentPPO through ``sb3:`` scores what a plain loop threading the LSTM state scores;
    the same loop dropping the state scores differently (so the state really is carried)."""
    sb3_contrib = pytest.importorskip("sb3_contrib")
    model = sb3_contrib.RecurrentPPO("MlpLstmPolicy", gym.make("MKVJam-v0", **SHORT), n_steps=64,
                                     batch_size=32, seed=0, device="cpu")
    # random weights large enough that the LSTM's memory decides the actions (a freshly built
    # or briefly trained model picks the same action whatever its state)
    import torch

    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name, p in model.policy.named_parameters():
            if "lstm_actor" in name:
                p.copy_(torch.randn(p.shape, generator=g))
        model.policy.action_net.weight.copy_(
            3.0 * torch.randn(model.policy.action_net.weight.shape, generator=g))
        model.policy.action_net.bias.zero_()
    path = tmp_path / "rppo.zip"
    model.save(path)
    model = sb3_contrib.RecurrentPPO.load(path, device="cpu")
    seeds = list(range(300, 306))
    kept = actions_plain(model, "MKVJam-v0", seeds)
    dropped = actions_plain(model, "MKVJam-v0", seeds, state_kept=False)
    assert kept.shape != dropped.shape or not np.array_equal(kept, dropped), \
        "this model ignores its state: the test would prove nothing"
    np.testing.assert_array_equal(actions_mkv(f"sb3:RecurrentPPO:{path}", seeds), kept)


@pytest.mark.parametrize("spec, message", [
    ("sb3:PPO", "sb3:ALGO:PATH"),
    ("sb3:FOO:x.zip", "unknown SB3 algorithm"),
    ("sb3:PPO:{missing}", "no such file"),
    ("sb3:PPO:{dir}", "is a directory"),
    ("sb3:PPO:{text}", "cannot load it as a PPO zip"),
])
def test_bad_sb3_specs_are_one_line(files, tmp_path, capsys, spec, message):
    text = tmp_path / "notes.zip"
    text.write_text("not a zip")
    spec = spec.format(missing=tmp_path / "none.zip", dir=tmp_path, text=text)
    code = main(["eval", "--env", "MKVJam-v0", "--policy", spec, "--episodes", "1"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and message in err, err


def test_sb3_spec_refuses_a_model_of_other_spaces(tmp_path, capsys):
    other = PPO("MlpPolicy", gym.make("CartPole-v1"), n_steps=32, batch_size=16, device="cpu")
    other.save(tmp_path / "cartpole.zip")
    env = make_env("MKVJam-v0")
    with pytest.raises(ValueError, match="action space"):
        make_policy(f"sb3:PPO:{tmp_path / 'cartpole.zip'}", env, seed=0)
    env.close()
    assert os.path.exists(tmp_path / "cartpole.zip")


@pytest.mark.parametrize("observation", ["raw", "features"])
def test_plain_sb3_recipe_runs_every_ppo_zip_with_no_wrapper(tmp_path, observation):
    """The README's three lines (PPO.load, then gymnasium.make with the kwargs the zip
    records) run a ``mkv train-ppo`` zip of either observation mode with no project wrapper,
    and act as ``mkv eval ppo:`` and ``sb3:PPO:`` do."""
    import json
    import zipfile

    model, meta = mkv_ppo.train("MKVJam-v0", 128, n_envs=1, env_kwargs=SHORT, eval_episodes=1,
                                hyperparameters={"n_steps": 64}, observation=observation)
    path = tmp_path / "ppo.zip"
    mkv_ppo.save(model, meta, path)
    with zipfile.ZipFile(path) as zf:
        kwargs = json.loads(zf.read("mkv_meta.json"))["make_kwargs"]
    assert kwargs["observation"] == ("features" if observation == "features" else "rescaled")
    seeds = list(range(310, 314))
    # SHORT is in the recorded kwargs too
    plain = actions_plain(PPO.load(path, device="cpu"), "MKVJam-v0", seeds, make_kwargs=kwargs)
    np.testing.assert_array_equal(actions_mkv(f"ppo:{path}", seeds), plain)
    np.testing.assert_array_equal(actions_mkv(f"sb3:PPO:{path}", seeds), plain)


def test_sb3_spec_accepts_every_zip_the_project_writes(files, capsys):
    seeds = list(range(320, 323))
    bc_zip = files["bc"][3:]
    np.testing.assert_array_equal(actions_mkv(f"sb3:PPO:{bc_zip}", seeds),
                                  actions_mkv(files["bc"], seeds))
    code = main(["eval", "--env", "MKVJam-v0", "--policy", f"sb3:A2C:{bc_zip}", "--episodes",
                 "1"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "was written by mkv train-bc" in err
