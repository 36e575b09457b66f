"""``mkv train-bc`` and ``bc:PATH``: accuracy against the majority class, online == batch,
file format, one-line errors, no partial output."""

import io
import json
import os
import zipfile

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

pytest.importorskip("stable_baselines3")

from mkv_env import dataset as ds  # noqa: E402
from mkv_env.policies import make_policy  # noqa: E402
from mkv_env.recorder import make_env, record  # noqa: E402
from sfm_learn.baselines import bc  # noqa: E402
from sfm_learn.cli import main  # noqa: E402

ENV_KW = {"max_episode_steps": 150}


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def teacher_data(tmp_path_factory):
    path = tmp_path_factory.mktemp("bcdata") / "teacher.npz"
    ds.save(record("MKV-v0", "teacher", episodes=10, seed=0, env_kwargs=ENV_KW), path)
    return path


@pytest.fixture(scope="module")
def trained(teacher_data, tmp_path_factory):
    out = tmp_path_factory.mktemp("bc") / "bc.zip"
    code = main(["train-bc", str(teacher_data), "--out", str(out), "--epochs", "15",
                 "--min-updates", "0", "--quiet"])
    assert code == 0
    return out


def test_held_out_accuracy_beats_the_majority_class(teacher_data, trained):
    data = ds.load(teacher_data)
    train, held = data.split(0.2, seed=0)
    meta = bc.read_metadata(trained)
    # the held-out metrics come from a network trained on the other episodes; the saved policy
    # was refitted on every step (validation never costs the policy data)
    assert meta["validation_trained_steps"] == train.n_steps
    assert meta["held_out_steps"] == held.n_steps
    assert meta["teacher_steps"] == data.n_steps and meta["refit_on_all"] is True
    for j, name in enumerate(bc.ACTION_NAMES):
        majority = np.bincount(train["actions"][:, j], minlength=3).argmax()
        baseline = float(np.mean(held["actions"][:, j] == majority))
        acc = meta["held_out"]["accuracy"][name]
        assert meta["held_out"]["majority_accuracy"][name] == pytest.approx(baseline)
        # at least half of the majority-class errors removed
        assert 1 - acc <= 0.5 * (1 - baseline), (name, acc, baseline)


def test_metadata_contents(teacher_data, trained):
    data = ds.load(teacher_data)
    meta = bc.read_metadata(trained)
    assert meta["format"] == "mkv-bc" and meta["env_id"] == "MKV-v0"
    assert meta["sensor_names"] == data.sensor_names and meta["action_nvec"] == [3, 3]
    assert meta["features"] == "default" and meta["epochs"] == 15
    assert meta["dataset"]["content_sha256"] == data.metadata["content_sha256"]
    assert meta["dataset"]["file"] == "teacher.npz"
    assert len(meta["input_mean"]) == len(meta["input_std"]) > len(data.sensor_names)
    assert meta["train_wall_s"] > 0 and len(meta["history"]) == 15
    assert meta["epochs_requested"] == 15 and meta["min_updates"] == 0
    assert meta["updates"] == 15 * -(-data.n_steps // meta["batch_size"])
    assert set(meta["held_out"]["recall"]) == {"drive", "steer"}
    json.dumps(meta, allow_nan=False)
    with zipfile.ZipFile(trained) as zf:  # an SB3 PPO model zip plus mkv_meta.json
        assert {"data", "policy.pth", "mkv_meta.json"} <= set(zf.namelist())
    assert meta["format_version"] == 2
    assert meta["make_kwargs"] == {**data.metadata.get("env_kwargs", {}),
                                   "observation": "features"}


def test_saved_policy_is_trained_on_every_episode(teacher_data):
    # with a held-out split the returned network is the one held_out=0 trains (same seed, same
    # rows): identical weights; refit=False returns the validation network, which differs
    data = ds.load(teacher_data)
    kw = {"epochs": 3, "seed": 4, "min_updates": 40}  # the minimum raises the epochs (7 / 5)
    refit, meta = bc.train(data, held_out=0.3, **kw)
    full, _ = bc.train(data, held_out=0.0, **kw)
    val, vmeta = bc.train(data, held_out=0.3, refit=False, **kw)
    a, b, c = (p.state_dict() for p in (refit, full, val))
    assert all(np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)
    assert not all(np.array_equal(a[k].numpy(), c[k].numpy()) for k in a)
    assert meta["held_out"] == vmeta["held_out"] and vmeta["teacher_steps"] < data.n_steps


def test_online_predict_equals_batch_path(trained):
    env = make_env("MKV-v0", ENV_KW)
    policy = make_policy(f"bc:{trained}", env, seed=0)
    env.close()
    # record episodes with the BC policy itself: its actions are the previous commands it sees
    data = record("MKV-v0", policy, episodes=2, seed=50, env_kwargs={"max_episode_steps": 60})
    batch = policy.batch_actions(data["observations"], data["actions"], data["step"] == 0)
    assert np.array_equal(batch, data["actions"])
    # a single observation in, shape (2,) out; a (1, n_obs) batch gives (1, 2)
    policy.reset(seed=0)
    a, state = policy.predict(data["observations"][0])
    assert a.shape == (2,) and state is None
    a2, _ = policy.predict(data["observations"][:1], episode_start=np.array([True]))
    assert a2.shape == (1, 2) and np.array_equal(a2[0], a)
    # a batch of three envs: each row as if that env ran alone from its episode start
    rows = data["observations"][:3]
    batch, _ = policy.predict(rows, episode_start=np.ones(3, dtype=bool))
    assert batch.shape == (3, 2)
    for i in range(3):
        policy.reset(seed=0)
        np.testing.assert_array_equal(batch[i], policy.predict(rows[i])[0])
    with pytest.raises(ValueError, match="n_envs"):
        policy.predict(np.zeros((3, 4)))


def test_mkv_eval_runs_a_bc_policy(trained, capsys):
    code, text, err = run(
        capsys,
        "eval",
        "--env",
        "MKV-v0",
        "--env-kwargs",
        '{"max_episode_steps": 30}',
        "--policy",
        f"bc:{trained}",
        "--episodes",
        "2",
        "--quiet",
    )
    assert code == 0, err
    assert f"bc:{trained}" in text


def test_raw_features_and_same_seed_same_weights(teacher_data, tmp_path, capsys):
    import torch

    outs = []
    for name in ("a.zip", "b.zip"):
        out = tmp_path / name
        code, text, err = run(
            capsys,
            "train-bc",
            str(teacher_data),
            "--out",
            str(out),
            "--features",
            "raw",
            "--epochs",
            "2",
            "--held-out",
            "0.3",
        )
        assert code == 0, err
        assert "held-out" in text and "majority-class baseline" in text and "recall" in text
        outs.append(out)
    metas = [bc.read_metadata(o) for o in outs]
    assert metas[0]["features"] == "raw" and len(metas[0]["input_mean"]) == 10
    assert metas[0]["held_out"] == metas[1]["held_out"]
    weights = []
    for o in outs:
        with zipfile.ZipFile(o) as zf:
            weights.append(zf.read("policy.pth"))
    sd = [torch.load(io.BytesIO(w), weights_only=True) for w in weights]
    assert all(torch.equal(sd[0][k], sd[1][k]) for k in sd[0])


def test_sensor_layout_mismatch(teacher_data, tmp_path, capsys):
    data = ds.load(teacher_data)
    renamed = [f"{n}_v2" if n == "battery" else n for n in data.sensor_names]
    other = ds.build(dict(data.arrays), dict(data.metadata, sensor_names=renamed))
    ds.save(other, tmp_path / "other.npz")
    out = tmp_path / "other.zip"
    assert (
        run(
            capsys,
            "train-bc",
            str(tmp_path / "other.npz"),
            "--out",
            str(out),
            "--epochs",
            "1",
            "--quiet",
        )[0]
        == 0
    )
    code, _, err = run(
        capsys, "eval", "--env", "MKV-v0", "--policy", f"bc:{out}", "--episodes", "1"
    )
    assert code == 2 and err.count("\n") == 1
    assert "other.zip was trained on sensors [" in err and "battery_v2" in err
    assert "but env has [" in err


def test_bc_zip_as_ppo_is_refused(trained, capsys):
    code, _, err = run(
        capsys, "eval", "--env", "MKV-v0", "--policy", f"ppo:{trained}", "--episodes", "1"
    )
    assert code == 2 and err.count("\n") == 1
    assert "is a behaviour-cloning policy, not a PPO model; use bc:" in err


@pytest.mark.parametrize(
    "case, message",
    [
        ("missing", "does not exist"),
        ("text", "not a readable dataset"),
        ("directory", "is a directory"),
        ("outdir", "does not exist"),
        ("held_out", "fraction in [0, 1)"),
        ("epochs", "positive integer"),
        ("min_updates", "integer in [0, 10_000_000]"),
        ("lr", "positive number"),
        ("features", "invalid choice"),
    ],
)
def test_train_bc_bad_input_is_one_line_exit_2(teacher_data, tmp_path, capsys, case, message):
    (tmp_path / "notes.npz").write_text("not a zip\n")
    (tmp_path / "d").mkdir()
    data, out, extra = str(teacher_data), str(tmp_path / "bc.zip"), []
    if case == "missing":
        data = str(tmp_path / "nothing.npz")
    elif case == "text":
        data = str(tmp_path / "notes.npz")
    elif case == "directory":
        data = str(tmp_path / "d")
    elif case == "outdir":
        out = str(tmp_path / "no" / "bc.zip")
    elif case == "held_out":
        extra = ["--held-out", "1.5"]
    elif case == "epochs":
        extra = ["--epochs", "-1"]
    elif case == "min_updates":
        extra = ["--min-updates", "-5"]
    elif case == "lr":
        extra = ["--lr", "nan"]
    elif case == "features":
        extra = ["--features", "fancy"]
    code, _, err = run(capsys, "train-bc", data, "--out", out, *extra)
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert err.startswith("mkv train-bc: error:") and "Traceback" not in err
    assert sorted(os.listdir(tmp_path)) == ["d", "notes.npz"]


def test_interrupt_leaves_no_output(teacher_data, tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(bc, "action_metrics", interrupted)
    code, _, err = run(
        capsys,
        "train-bc",
        str(teacher_data),
        "--out",
        str(tmp_path / "b.zip"),
        "--epochs",
        "2",
        "--quiet",
    )
    assert code == 130 and "interrupted" in err
    assert os.listdir(tmp_path) == []


def test_corrupt_bc_zip_is_one_line(trained, tmp_path, capsys):
    bad = tmp_path / "bad.zip"
    with zipfile.ZipFile(trained) as src, zipfile.ZipFile(bad, "w") as dst:
        dst.writestr("mkv_meta.json", src.read("mkv_meta.json"))
        dst.writestr("policy.pth", b"garbage")
    code, _, err = run(
        capsys, "eval", "--env", "MKV-v0", "--policy", f"bc:{bad}", "--episodes", "1"
    )
    assert code == 2 and err.count("\n") == 1 and "cannot rebuild a behaviour-cloning policy" in err
    truncated = tmp_path / "trunc.zip"
    truncated.write_bytes(trained.read_bytes()[:200])
    code, _, err = run(
        capsys, "eval", "--env", "MKV-v0", "--policy", f"bc:{truncated}", "--episodes", "1"
    )
    assert code == 2 and err.count("\n") == 1 and "not a readable bc policy zip" in err


@pytest.mark.parametrize("features", ["default", "raw"])
def test_plain_sb3_runs_a_bc_zip_with_no_project_code(teacher_data, tmp_path, features):
    """A BC zip is a PPO model zip whose network takes the env's own observation
    (gym.make(env_id, **make_kwargs)); plain PPO.load acts exactly as bc: does, and as the
    in-memory network before folding on all but rounding ties."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    data = ds.load(teacher_data)
    policy, meta = bc.train(data, epochs=3, seed=1, held_out=0.0, features=features)
    path = tmp_path / "bc.zip"
    bc.save(policy, meta, path)
    saved = bc.read_metadata(path)
    model = PPO.load(path, device="cpu")
    mine = make_policy(f"bc:{path}", make_env("MKV-v0", ENV_KW), seed=0)
    unfolded = bc.BCPolicy(policy, meta)  # the network as trained (standardised raw features)
    plain_env = gym.make(saved["env_id"], **{**saved["make_kwargs"], **ENV_KW})
    raw_env = make_env("MKV-v0", ENV_KW)
    same = total = agree = 0
    for s in (400, 401):
        obs, _ = plain_env.reset(seed=s)
        raw, _ = raw_env.reset(seed=s)
        mine.reset(s)
        unfolded.reset(s)
        done = False
        while not done:
            a_plain, _ = model.predict(obs, deterministic=True)
            a_mine, _ = mine.predict(raw, deterministic=True)
            a_raw, _ = unfolded.predict(raw, deterministic=True)
            same += np.array_equal(a_plain, a_mine)
            agree += np.array_equal(a_plain, a_raw)
            total += 1
            obs, _, term, trunc, _ = plain_env.step(a_plain)
            raw, *_ = raw_env.step(a_plain)
            done = term or trunc
    assert same == total and agree >= 0.99 * total, (same, agree, total)


@given(n=st.integers(1, 100_000), epochs=st.integers(1, 500), batch=st.integers(1, 4096),
       min_updates=st.integers(0, 20_000))
def test_planned_epochs_is_the_least_that_reaches_the_minimum(n, epochs, batch, min_updates):
    e = bc.planned_epochs(n, epochs, batch, min_updates)
    batches = -(-n // batch)
    assert e >= epochs and e * batches >= min_updates
    if e > epochs:  # one epoch fewer would not reach the minimum
        assert (e - 1) * batches < min_updates


def test_small_data_gets_the_minimum_number_of_updates(teacher_data, tmp_path, capsys):
    # at 1,200 teacher steps 30 epochs were 150 updates and BC underfitted; the default
    # runs at least bc.MIN_UPDATES minibatch updates, and says so
    data = ds.load(teacher_data)  # 1,500 rows: 6 minibatches, so 30 epochs are 180 updates
    out = tmp_path / "bc.zip"
    code, stdout, _ = run(capsys, "train-bc", str(teacher_data), "--out", str(out), "--held-out",
                          "0", "--quiet")
    assert code == 0
    meta = bc.read_metadata(out)
    batches = -(-data.n_steps // meta["batch_size"])
    assert meta["min_updates"] == bc.MIN_UPDATES == 1000 and meta["epochs_requested"] == 30
    assert meta["updates"] == meta["epochs"] * batches >= 1000
    assert (meta["epochs"] - 1) * batches < 1000 and meta["epochs"] > 30
    assert f"{meta['epochs']} epochs ({meta['updates']} updates)" in stdout


def test_the_refit_says_it_is_the_saved_policy_and_where_its_epochs_come_from(teacher_data,
                                                                             tmp_path, capsys):
    # each fit plans its epochs from its own rows: with --min-updates raising them, the refit on
    # every row (more minibatches per epoch) runs fewer epochs than the held-out fit printed
    data = ds.load(teacher_data)  # 1,500 rows: 6 minibatches of 256; the held-out fit's 1,200: 5
    out = tmp_path / "bc.zip"
    code, stdout, _ = run(capsys, "train-bc", str(teacher_data), "--out", str(out), "--epochs",
                          "3", "--min-updates", "100")
    assert code == 0
    meta = bc.read_metadata(out)
    held_epochs = bc.planned_epochs(meta["validation_trained_steps"], 3, 256, 100)
    assert meta["epochs"] == bc.planned_epochs(data.n_steps, 3, 256, 100) == 17 < held_epochs == 20
    lines = stdout.splitlines()
    refit = next(i for i, line in enumerate(lines) if line.startswith("refit"))
    assert lines[refit - 1].startswith(f"epoch {held_epochs}/{held_epochs}:")
    assert lines[refit] == (
        f"refit of the saved policy on all {data.n_steps} rows: 17 epochs (--epochs 3 raised to "
        "reach --min-updates 100 at 6 minibatches per epoch; the held-out fit above ran 20 on "
        "its fewer rows)")
    assert "saved policy: 1500 training rows (10 episodes), 17 epochs (102 updates)" in stdout


@pytest.mark.parametrize("steps, episodes, options, message", [
    (2, 1, [], "has 2 rows; behaviour cloning on 32 default features needs at least 33"),
    (32, 1, [], "has 32 rows; behaviour cloning on 32 default features needs at least 33"),
    (10, 1, ["--features", "raw"], "has 10 rows; behaviour cloning on 10 raw features needs "
                                   "at least 11"),
    # 40 rows, but the held-out split leaves the validation network 20
    (20, 2, [], "holding out 1 of 2 episodes (fraction 0.2) leaves 20 training rows; behaviour "
                "cloning on 32 default features needs at least 33: hold out less"),
])
def test_too_few_rows_are_refused_before_training(tiny_data, tmp_path, capsys, steps, episodes,
                                                  options, message):
    data = tiny_data(steps, episodes)
    out = tmp_path / "bc.zip"
    code, text, err = run(capsys, "train-bc", str(data), "--out", str(out), *options)
    assert code == 2 and text == ""
    assert err.count("\n") == 1 and err.startswith(f"mkv train-bc: error: dataset {data}")
    assert message in err
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="behaviour cloning on"):   # the library says it too
        bc.train(ds.load(data), epochs=1, features=options[-1] if options else "default")


@pytest.mark.parametrize("steps, episodes, options", [
    (33, 1, []),                                  # features + 1
    (11, 1, ["--features", "raw"]),
    (20, 2, ["--held-out", "0"]),                 # nothing held out: all 40 rows train
])
def test_the_smallest_accepted_dataset_trains(tiny_data, tmp_path, capsys, steps, episodes,
                                              options):
    out = tmp_path / "bc.zip"
    code, text, err = run(capsys, "train-bc", str(tiny_data(steps, episodes)), "--out", str(out),
                          "--epochs", "1", "--min-updates", "0", "--quiet", *options)
    assert code == 0, err
    assert bc.read_metadata(out)["teacher_steps"] == steps * episodes


def test_min_rows_is_one_more_than_the_features():
    assert bc.min_rows(32) == 33 and bc.min_rows(10) == 11
