"""PPO on the feature observation (``--observation features``) and the hyperparameter file."""

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("yaml")

from mkv_env.policies import make_policy  # noqa: E402
from mkv_env.recorder import make_env  # noqa: E402
from sfm_learn.baselines import ppo, sb3  # noqa: E402
from sfm_learn.cli import main  # noqa: E402

SHORT = '{"max_episode_steps": 40}'


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("ppof") / "ppo.zip"
    code = main(["train-ppo", "--env", "MKVJam-v1", "--env-kwargs", SHORT, "--timesteps", "128",
                 "--n-envs", "2", "--n-steps", "64", "--observation", "features",
                 "--eval-episodes", "1", "--out", str(out), "--quiet"])
    assert code == 0
    return out


def test_features_are_recorded_and_hyperparameters_come_from_the_file(trained):
    meta = ppo.read_metadata(trained)
    assert meta["observation"] == "features" and meta["format_version"] == 3
    assert meta["feature_spec"]["prev_action"] == "signed"
    file_hp = ppo.load_hyperparameters("MKVJam-v1")
    # flags override the file; everything else is the file's entry for MKVJam-v1
    assert meta["hyperparameters"]["n_steps"] == 64 and meta["n_envs"] == 2
    for k in ("batch_size", "n_epochs", "learning_rate", "gamma", "ent_coef"):
        want = file_hp[k] if k != "batch_size" else min(file_hp[k], 128)
        assert meta["hyperparameters"][k] == want, k


def test_ppo_spec_replays_the_training_wrapper_action_for_action(trained):
    """ppo:PATH (online features) and SB3's PPO.load on the documented wrapper stack
    (RescaleObservation -> FeatureObservation) choose the same actions."""
    from stable_baselines3 import PPO

    meta = ppo.read_metadata(trained)
    model = PPO.load(trained, device="cpu")
    env = make_env("MKVJam-v1", {"max_episode_steps": 40})
    wrapped = sb3.make_rescaled_env("MKVJam-v1", {"max_episode_steps": 40}, monitor=False,
                                    feature_spec=meta["feature_spec"])
    policy = make_policy(f"ppo:{trained}", env, seed=0)
    policy.reset(3)
    obs, _ = env.reset(seed=3)
    fobs, _ = wrapped.reset(seed=3)
    for _ in range(40):
        a, _ = policy.predict(obs)
        b, _ = model.predict(fobs, deterministic=True)
        assert np.array_equal(a, b)
        obs, _, term, trunc, _ = env.step(a)
        fobs, *_ = wrapped.step(b)
        if term or trunc:
            break
    env.close()
    wrapped.close()


def test_feature_policy_keeps_state_per_env(trained):
    """A batch of 2 envs gives each env the actions it would get alone."""
    env = make_env("MKVJam-v1", {"max_episode_steps": 40})
    single = [make_policy(f"ppo:{trained}", env, seed=0) for _ in range(2)]
    batch = make_policy(f"ppo:{trained}", env, seed=0)
    envs = [make_env("MKVJam-v1", {"max_episode_steps": 40}) for _ in range(2)]
    obs = [e.reset(seed=10 + i)[0] for i, e in enumerate(envs)]
    for t in range(15):
        ab, _ = batch.predict(np.stack(obs), episode_start=np.array([t == 0] * 2))
        for i in range(2):
            a, _ = single[i].predict(obs[i], episode_start=t == 0)
            assert np.array_equal(a, ab[i])
        obs = [e.step(ab[i])[0] for i, e in enumerate(envs)]


@pytest.mark.parametrize("text, message", [
    ("MKVJam-v1: [1, 2]", "is not a mapping"),
    ("MKVJam-v1: {n_envs: 0}", "n_envs of MKVJam-v1"),
    ("MKVJam-v1: {learning_rate: .nan}", "learning_rate of MKVJam-v1"),
    ("MKVJam-v1: {net_arch: [64, -1]}", "net_arch of MKVJam-v1"),
    ("MKVJam-v1: {observation: pixels}", "observation of MKVJam-v1"),
    ("MKVJam-v1: {n_stepz: 3}", "unknown hyperparameter"),
    ("MKVJam-v1: [", "not valid YAML"),
    ("- 1", "must map env ids"),
])
def test_bad_hyperparameter_files_are_one_line_errors(tmp_path, capsys, text, message):
    f = tmp_path / "hp.yml"
    f.write_text(text)
    with pytest.raises(ValueError, match=message) as e:
        ppo.load_hyperparameters("MKVJam-v1", f)
    assert "\n" not in str(e.value)
    code = main(["train-ppo", "--env", "MKVJam-v1", "--hyperparams", str(f),
                 "--out", str(tmp_path / "o.zip"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and message.split()[0] in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o.zip").exists()


def test_missing_hyperparameter_file_and_default_entry(tmp_path):
    with pytest.raises(ValueError, match="cannot read hyperparameter file"):
        ppo.load_hyperparameters("MKV-v1", tmp_path / "none.yml")
    f = tmp_path / "hp.yml"
    f.write_text("default: {n_envs: 3, observation: features}\n")
    hp = ppo.load_hyperparameters("MKV-v1", f)
    assert hp["n_envs"] == 3 and hp["observation"] == "features"
    assert hp["n_steps"] == ppo.DEFAULTS["n_steps"]


def test_hyperparameter_file_cannot_be_the_output(tmp_path, capsys):
    f = tmp_path / "hp.yml"
    f.write_text("default: {n_envs: 2}\n")
    assert main(["train-ppo", "--env", "MKVJam-v1", "--hyperparams", str(f), "--out", str(f),
                 "--quiet"]) == 2
    assert f.read_text() == "default: {n_envs: 2}\n"


def test_same_seed_same_weights_with_features_on_v1():
    def params(seed):
        model, _ = ppo.train("MKVJam-v1", 128, seed=seed, n_envs=2, eval_episodes=1,
                             env_kwargs={"max_episode_steps": 20}, observation="features",
                             hyperparameters={"n_steps": 32, "batch_size": 32})
        return {k: v.detach().clone().numpy() for k, v in model.policy.state_dict().items()}

    a, b, c = params(3), params(3), params(4)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not all(np.array_equal(a[k], c[k]) for k in a)


def test_eval_at_checkpoints_at_the_first_rollout_boundary_after_each_budget(tmp_path):
    _, meta = ppo.train("MKVJam-v1", 256, n_envs=2, eval_episodes=1, eval_at=[60, 130, 256],
                        env_kwargs={"max_episode_steps": 20}, checkpoint_dir=str(tmp_path),
                        hyperparameters={"n_steps": 32, "batch_size": 32})
    # rollouts of 2 x 32 = 64 steps: 0, then the first boundary >= 60, >= 130, and the end
    assert [p["env_steps"] for p in meta["learning_curve"]] == [0, 64, 192, 256]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        f"ppo_{s:08d}.zip" for s in (0, 64, 192, 256)]
