"""``mkv train-ppo`` and ``ppo:PATH``: tiny budgets, file format, determinism, one-line errors."""

import io
import json
import os
import zipfile

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from mkv_env.policies import PolicySpecError, make_policy  # noqa: E402
from mkv_env.recorder import make_env  # noqa: E402
from sfm_learn.baselines import ppo  # noqa: E402
from sfm_learn.cli import main  # noqa: E402

SHORT = '{"max_episode_steps": 40}'  # keeps evaluation episodes short


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """One tiny PPO run through the CLI: 256 steps, 2 envs, rollouts of 2 x 64 steps."""
    d = tmp_path_factory.mktemp("ppo")
    out, ckpt = d / "ppo.zip", d / "ckpt"
    code = main(
        [
            "train-ppo",
            "--env",
            "MKVJam-v0",
            "--env-kwargs",
            SHORT,
            "--timesteps",
            "256",
            "--n-envs",
            "2",
            "--n-steps",
            "64",
            "--eval-every",
            "128",
            "--eval-episodes",
            "2",
            "--checkpoint-dir",
            str(ckpt),
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert code == 0
    return out, ckpt


def test_train_ppo_writes_sb3_zip_with_metadata(trained):
    out, ckpt = trained
    meta = ppo.read_metadata(out)
    assert meta["format"] == "mkv-ppo" and meta["env_id"] == "MKVJam-v0"
    assert meta["env_kwargs"] == {"max_episode_steps": 40}
    env = make_env("MKVJam-v0")
    assert meta["sensor_names"] == env.unwrapped.sensor_names and meta["action_nvec"] == [3, 3]
    env.close()
    assert meta["timesteps"] == 256 and meta["timesteps_requested"] == 256
    assert meta["seed"] == 0 and meta["n_envs"] == 2 and meta["train_wall_s"] > 0
    assert meta["hyperparameters"]["n_steps"] == 64
    curve = meta["learning_curve"]
    assert [p["env_steps"] for p in curve] == [0, 128, 256]
    for p in curve:
        assert set(p) == {"env_steps", "wall_s", "mean_return", "escape_rate", "distance_m",
                          "stuck_fraction"}
        assert 0 <= p["escape_rate"] <= 1 and p["distance_m"] >= 0
    assert [p["wall_s"] for p in curve] == sorted(p["wall_s"] for p in curve)
    assert meta["final_eval"] == curve[-1]
    json.dumps(meta, allow_nan=False)  # strict JSON
    assert sorted(os.listdir(ckpt)) == [f"ppo_{s:08d}.zip" for s in (0, 128, 256)]
    assert ppo.read_metadata(ckpt / "ppo_00000128.zip")["learning_curve"] == curve[:2]


def test_sb3_ppo_load_reads_the_file_and_agrees_with_ppo_spec(trained):
    from gymnasium.wrappers import RescaleObservation
    from stable_baselines3 import PPO

    out, _ = trained
    model = PPO.load(out, device="cpu")
    env = make_env("MKVJam-v0", {"max_episode_steps": 40})
    policy = make_policy(f"ppo:{out}", env, seed=0)
    # the documented public wrapper, nothing private
    scaled = RescaleObservation(make_env("MKVJam-v0", {"max_episode_steps": 40}),
                                np.float32(-1.0), np.float32(1.0))
    obs, _ = env.reset(seed=3)
    sobs, _ = scaled.reset(seed=3)
    for _ in range(20):
        a, _ = policy.predict(obs, episode_start=False)
        b, _ = model.predict(sobs, deterministic=True)
        assert a.shape == (2,) and np.array_equal(a, b)
        obs, *_ = env.step(a)
        sobs, *_ = scaled.step(b)
    env.close()
    scaled.close()


def test_mkv_eval_runs_a_ppo_policy(trained, capsys):
    out, _ = trained
    code, text, err = run(
        capsys,
        "eval",
        "--env",
        "MKVJam-v0",
        "--env-kwargs",
        SHORT,
        "--policy",
        f"ppo:{out}",
        "--episodes",
        "2",
        "--seed",
        "1000",
        "--quiet",
    )
    assert code == 0, err
    assert f"ppo:{out}" in text


def test_same_seed_same_parameters():
    def params(seed):
        model, meta = ppo.train(
            "MKV-v0",
            128,
            seed=seed,
            n_envs=1,
            eval_episodes=1,
            env_kwargs={"max_episode_steps": 10},
            hyperparameters={"n_steps": 64, "batch_size": 32},
        )
        return {k: v.detach().clone() for k, v in model.policy.state_dict().items()}

    a, b, c = params(1), params(1), params(2)
    assert all(np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)
    assert not all(np.array_equal(a[k].numpy(), c[k].numpy()) for k in a)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--timesteps", "-5"], "positive integer"),
        (["--timesteps", "0"], "positive integer"),
        (["--n-envs", "0"], "positive integer"),
        (["--env", "NoSuchEnv-v9"], "NoSuchEnv-v9"),
        (["--env-kwargs", '{"n_clutter": -1}'], "n_clutter"),
        (["--out", "/no/such/dir/ppo.zip"], "does not exist"),
        (["--vec", "threads"], "invalid choice"),
    ],
)
def test_train_ppo_bad_input_is_one_line_exit_2(capsys, tmp_path, argv, message):
    base = {
        "--env": "MKVJam-v0",
        "--timesteps": "64",
        "--out": str(tmp_path / "p.zip"),
        "--checkpoint-dir": str(tmp_path / "ckpt"),  # not created on bad input
    }
    extra = dict(zip(argv[::2], argv[1::2], strict=True))
    args = ["train-ppo"] + [x for k, v in {**base, **extra}.items() for x in (k, v)]
    code, out, err = run(capsys, *args)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("mkv train-ppo: error:") and message in err
    assert "Traceback" not in err
    assert os.listdir(tmp_path) == []


def _rewrite_meta(src, dst, **changes):
    with zipfile.ZipFile(src) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    meta = json.loads(members["mkv_meta.json"])
    meta.update(changes)
    members["mkv_meta.json"] = json.dumps(meta).encode()
    with zipfile.ZipFile(dst, "w") as zf:
        for n, data in members.items():
            zf.writestr(n, data)


def test_ppo_spec_errors_are_one_line(trained, capsys, tmp_path):
    out, _ = trained
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    other = tmp_path / "other_sensors.zip"
    _rewrite_meta(out, other, sensor_names=["a", "b"])
    bc_like = tmp_path / "bc_like.zip"
    _rewrite_meta(out, bc_like, format="mkv-bc")
    cases = [
        (f"ppo:{tmp_path / 'missing.zip'}", "no such file"),
        (f"ppo:{text}", "not a readable ppo policy zip"),
        (f"ppo:{other}", "was trained on sensors ['a', 'b'] but env has"),
        (f"ppo:{bc_like}", "use bc:"),
        (f"bc:{out}", f"is a PPO model, not a behaviour-cloning policy; use ppo:{out}"),
        ("ppo:", "needs a file"),
    ]
    for spec, message in cases:
        code, _, err = run(
            capsys, "eval", "--env", "MKVJam-v0", "--policy", spec, "--episodes", "1"
        )
        assert code == 2, spec
        assert err.count("\n") == 1 and message in err, (spec, err)


def test_sb3_zip_without_metadata_is_refused(trained, tmp_path):
    out, _ = trained
    plain = tmp_path / "plain.zip"
    with zipfile.ZipFile(out) as src, zipfile.ZipFile(plain, "w") as dst:
        for n in src.namelist():
            if n != "mkv_meta.json":
                dst.writestr(n, src.read(n))
    with pytest.raises(PolicySpecError, match="not written by mkv train-ppo"):
        ppo.load_spec(str(plain), None, 0)


def test_interrupt_leaves_no_output(capsys, tmp_path, monkeypatch):
    calls = []

    def interrupted(*args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return {"mean_return": 0.0, "escape_rate": None, "distance_m": 0.0}

    monkeypatch.setattr(ppo, "_evaluate", interrupted)
    out = tmp_path / "p.zip"
    code, _, err = run(
        capsys,
        "train-ppo",
        "--env",
        "MKV-v0",
        "--env-kwargs",
        '{"max_episode_steps": 10}',
        "--timesteps",
        "128",
        "--n-envs",
        "1",
        "--n-steps",
        "32",
        "--eval-every",
        "32",
        "--out",
        str(out),
        "--quiet",
    )
    assert code == 130 and "interrupted" in err
    assert os.listdir(tmp_path) == []


def test_checkpoint_dir_that_is_a_file_is_refused(capsys, tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    code, _, err = run(
        capsys,
        "train-ppo",
        "--env",
        "MKV-v0",
        "--timesteps",
        "64",
        "--out",
        str(tmp_path / "p.zip"),
        "--checkpoint-dir",
        str(f),
    )
    assert code == 2 and "not a directory" in err


def test_metadata_reader_roundtrip_through_bytes(trained):
    out, _ = trained
    with zipfile.ZipFile(io.BytesIO(out.read_bytes())) as zf:
        assert json.loads(zf.read("mkv_meta.json")) == ppo.read_metadata(out)


def test_tensorboard_logs_training_and_evaluations(tmp_path, capsys):
    """``mkv train-ppo --tensorboard DIR`` writes SB3's TensorBoard events with the
    evaluation points; a DIR that is a file is refused in one line before anything runs."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from sfm_learn.cli import main

    tb = tmp_path / "tb"
    code = main(["train-ppo", "--env", "MKV-v1", "--timesteps", "512", "--n-envs", "2",
                 "--n-steps", "128", "--eval-episodes", "1", "--out", str(tmp_path / "p.zip"),
                 "--tensorboard", str(tb), "--quiet"])
    assert code == 0
    runs = list(tb.iterdir())
    assert [r.name for r in runs] == ["PPO_0_1"]
    ea = EventAccumulator(str(runs[0]))
    ea.Reload()
    tags = set(ea.Tags()["scalars"])
    assert {"eval/mean_return", "train/loss"} <= tags
    assert len(ea.Scalars("eval/mean_return")) >= 2  # before and after training
    (tmp_path / "afile").write_text("x")
    capsys.readouterr()
    code = main(["train-ppo", "--env", "MKV-v1", "--timesteps", "512", "--out",
                 str(tmp_path / "q.zip"), "--tensorboard", str(tmp_path / "afile")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "is not a directory" in err
    assert not (tmp_path / "q.zip").exists()
