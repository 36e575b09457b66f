"""No code runs from a file a user was handed (docs/trust.md): ``sb3:`` zips and the
``vecnormalize.pkl`` beside them are read without unpickling anything unless the user passes
``--trust-pickle``. Each payload below would create a marker file if it were unpickled."""

import base64
import json
import os
import pickle
import subprocess
import sys
import zipfile

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize  # noqa: E402

import mkv_env  # noqa: E402, F401
import sfm_learn  # noqa: E402, F401
from mkv_env.policies import PolicySpecError, make_policy  # noqa: E402
from sfm_learn.baselines.sb3_models import TRUST_ENV  # noqa: E402


class Payload:
    """Unpickling this creates ``path`` (stands for any code an attacker would run)."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _payload_b64(marker) -> str:
    return base64.b64encode(pickle.dumps(Payload(marker))).decode()


@pytest.fixture(scope="module")
def model_zip(tmp_path_factory):
    d = tmp_path_factory.mktemp("sb3")
    model = PPO("MlpPolicy", gym.make("MKV-v0"), n_steps=32, batch_size=32, device="cpu",
                policy_kwargs={"net_arch": [16, 16]}, seed=0)
    model.save(d / "ppo.zip")
    return d / "ppo.zip"


@pytest.fixture(autouse=True)
def untrusted(monkeypatch):
    monkeypatch.delenv(TRUST_ENV, raising=False)


def _rewrite(src, dst, edit):
    """A copy of zip ``src`` at ``dst`` with its data JSON changed by ``edit(data)``."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            raw = zin.read(item.filename)
            if item.filename == "data":
                data = json.loads(raw)
                edit(data)
                raw = json.dumps(data).encode()
            zout.writestr(item, raw)
    return dst


def _actions(spec):
    env = gym.make("MKV-v0")
    policy = make_policy(spec, env, seed=0)
    obs = np.random.default_rng(0).standard_normal((20, 10)).astype(np.float32)
    return policy.predict(obs)[0]


@pytest.mark.parametrize("key", ["evil_extra_key", "policy_class", "observation_space",
                                 "action_space", "lr_schedule", "policy_kwargs"])
def test_serialized_payloads_in_the_zip_never_run(model_zip, tmp_path, key):
    marker = tmp_path / "PWNED"

    def edit(data):
        item = data.get(key, {":type:": "<class 'object'>"})
        item = dict(item) if isinstance(item, dict) else {":type:": "<class 'object'>"}
        item[":serialized:"] = _payload_b64(marker)
        data[key] = item

    evil = _rewrite(model_zip, tmp_path / "evil.zip", edit)
    try:
        got = _actions(f"sb3:PPO:{evil}")
    except PolicySpecError as e:  # refused in one line is fine too, running it is not
        assert "\n" not in str(e)
    else:
        np.testing.assert_array_equal(got, _actions(f"sb3:PPO:{model_zip}"))
    assert not marker.exists()


def _evil_pkl(path, marker):
    with open(path, "wb") as f:
        pickle.dump(Payload(marker), f)


@pytest.mark.parametrize("where", ["beside", "rl-zoo3 layout"])
def test_vecnormalize_payloads_are_refused_not_run(model_zip, tmp_path, where):
    marker = tmp_path / "PWNED"
    run = tmp_path / "run"
    (run / "ppo").mkdir(parents=True)
    zip_path = run / "ppo.zip"
    zip_path.write_bytes(model_zip.read_bytes())
    _evil_pkl(run / "vecnormalize.pkl" if where == "beside" else run / "ppo" / "vecnormalize.pkl",
              marker)
    with pytest.raises(PolicySpecError, match="refused: it names io.open"):
        _actions(f"sb3:PPO:{zip_path}")
    assert not marker.exists()


def test_a_vecnormalize_in_any_other_subfolder_is_not_read(model_zip, tmp_path):
    marker = tmp_path / "PWNED"
    (tmp_path / "run" / "other").mkdir(parents=True)
    zip_path = tmp_path / "run" / "ppo.zip"
    zip_path.write_bytes(model_zip.read_bytes())
    _evil_pkl(tmp_path / "run" / "other" / "vecnormalize.pkl", marker)
    _actions(f"sb3:PPO:{zip_path}")
    assert not marker.exists()


def test_genuine_vecnormalize_statistics_still_apply(model_zip, tmp_path):
    venv = VecNormalize(DummyVecEnv([lambda: gym.make("MKV-v0")]))
    venv.obs_rms.mean = np.linspace(-1, 1, 10)
    venv.obs_rms.var = np.linspace(0.5, 2, 10)
    (tmp_path / "ppo").mkdir()
    venv.save(str(tmp_path / "ppo" / "vecnormalize.pkl"))
    zip_path = tmp_path / "ppo.zip"
    zip_path.write_bytes(model_zip.read_bytes())
    obs = np.random.default_rng(0).standard_normal((20, 10)).astype(np.float32)
    policy = make_policy(f"sb3:PPO:{zip_path}", gym.make("MKV-v0"), seed=0)
    model = PPO.load(model_zip, device="cpu")
    np.testing.assert_array_equal(policy.predict(obs)[0],
                                  model.predict(venv.normalize_obs(obs), deterministic=True)[0])


def test_a_vecnormalize_holding_something_else_is_refused(model_zip, tmp_path):
    with open(tmp_path / "vecnormalize.pkl", "wb") as f:
        pickle.dump({"obs_rms": None}, f)
    zip_path = tmp_path / "ppo.zip"
    zip_path.write_bytes(model_zip.read_bytes())
    with pytest.raises(PolicySpecError, match="holds a dict, not SB3's VecNormalize"):
        _actions(f"sb3:PPO:{zip_path}")


@pytest.mark.parametrize("algo", ["A2C", "TRPO", "RecurrentPPO"])
def test_the_zip_must_have_been_saved_by_the_named_algorithm(model_zip, algo):
    try:
        _actions(f"sb3:{algo}:{model_zip}")
    except PolicySpecError as e:
        assert "saved by PPO" in str(e) or "needs sb3-contrib" in str(e)
    else:
        pytest.fail(f"sb3:{algo} loaded a PPO zip")


def _mkv(*args, env=None):
    e = dict(os.environ, SDL_VIDEODRIVER="dummy")
    e.pop(TRUST_ENV, None)
    e.update(env or {})
    code = f"import sys; from sfm_learn.cli import main; sys.exit(main({list(args)!r}))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e,
                          timeout=300)


def test_cli_checks_every_spec_before_loading_any_and_trust_is_explicit(model_zip, tmp_path):
    marker = tmp_path / "PWNED"
    run = tmp_path / "run"
    run.mkdir()
    zip_path = run / "ppo.zip"
    zip_path.write_bytes(model_zip.read_bytes())
    _evil_pkl(run / "vecnormalize.pkl", marker)
    r = _mkv("eval", "--env", "MKV-v0", "--policy", f"sb3:PPO:{zip_path}", "--policy", "bogus",
             "--episodes", "1")
    assert r.returncode == 2 and "bogus" in r.stderr and r.stderr.count("\n") == 1
    assert not marker.exists()
    r = _mkv("eval", "--env", "MKV-v0", "--policy", f"sb3:PPO:{zip_path}", "--episodes", "1")
    assert r.returncode == 2 and "refused" in r.stderr and not marker.exists()
    r = _mkv("eval", "--env", "MKV-v0", "--policy", f"sb3:PPO:{zip_path}", "--episodes", "1",
             "--trust-pickle")
    assert "--trust-pickle" in r.stderr and "warning" in r.stderr
    assert marker.exists()  # the user said so: the file was unpickled (and failed: not stats)


def test_cli_help_lists_sb3_with_its_trust_rule():
    r = _mkv("eval", "--help")
    assert "sb3:ALGO:PATH" in r.stdout and "--trust-pickle" in r.stdout


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_as_model_is_refused_at_once(tmp_path):
    fifo = tmp_path / "model.zip"
    os.mkfifo(fifo)
    r = _mkv("eval", "--env", "MKV-v0", "--policy", f"sb3:PPO:{fifo}", "--episodes", "1")
    assert r.returncode == 2 and "not a regular file" in r.stderr


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
@pytest.mark.parametrize("prefix", ["script", "sfm", "ppo", "bc"])
def test_a_fifo_as_any_policy_file_is_refused_at_once(tmp_path, prefix):
    fifo = tmp_path / "policy.file"
    os.mkfifo(fifo)
    r = _mkv("eval", "--env", "MKV-v0", "--policy", f"{prefix}:{fifo}", "--episodes", "1")
    assert r.returncode == 2 and "not a regular file" in r.stderr
    assert r.stderr.count("\n") == 1


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_fifos_as_hyperparameters_or_calibration_are_refused_at_once(tmp_path):
    from calib.data.io import load_calibration
    from calib.data.result import CalibrationError
    from sfm_learn.baselines.ppo import load_hyperparameters

    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="not a regular file"):
        load_hyperparameters("MKV-v1", str(fifo))
    with pytest.raises(CalibrationError, match="not a regular file"):
        load_calibration(str(fifo))
    r = _mkv("train-ppo", "--env", "MKV-v1", "--hyperparams", str(fifo), "--timesteps", "64",
             "--out", str(tmp_path / "p.zip"))
    assert r.returncode == 2 and "not a regular file" in r.stderr
