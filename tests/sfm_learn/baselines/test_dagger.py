"""``mkv train-dagger`` and ``dagger:PATH``."""

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from mkv_env.policies import PolicySpecError, make_policy  # noqa: E402
from mkv_env.recorder import make_env  # noqa: E402
from sfm_learn.baselines import dagger  # noqa: E402
from sfm_learn.cli import main  # noqa: E402


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("dagger") / "d.zip"
    assert main(["train-dagger", "--env", "MKV-v1", "--steps", "601", "--rounds", "3",
                 "--epochs", "2", "--out", str(out), "--quiet"]) == 0
    return out


def test_teacher_is_queried_exactly_the_budget(trained):
    meta = dagger.read_metadata(trained)
    log = meta["dagger"]["log"]
    assert meta["teacher_steps"] == 601 == sum(r["rows"] for r in log)
    assert [r["rows"] for r in log] == [201, 200, 200]
    assert [r["driver"] for r in log] == ["teacher", "learner", "learner"]
    assert log[0]["agreement"] == 1.0            # round 0 is the teacher driving
    assert [r["total_rows"] for r in log] == [201, 401, 601]
    assert meta["format"] == "mkv-dagger" and meta["env_id"] == "MKV-v1"


def test_dagger_spec_drives_and_keeps_per_env_state(trained):
    env = make_env("MKVJam-v1", {"max_episode_steps": 30})
    p = make_policy(f"dagger:{trained}", env, seed=0)
    q = make_policy(f"dagger:{trained}", env, seed=0)
    obs, _ = env.reset(seed=5)
    for t in range(30):
        a, _ = p.predict(obs, episode_start=t == 0)
        b, _ = q.predict(np.stack([obs, obs]), episode_start=t == 0)
        assert a.shape == (2,) and np.array_equal(b[0], a) and np.array_equal(b[1], a)
        obs, _, term, trunc, _ = env.step(a)
        if term or trunc:
            break
    env.close()


def test_same_seed_same_weights(tmp_path):
    outs = [tmp_path / f"{i}.zip" for i in range(2)]
    for o in outs:
        assert main(["train-dagger", "--env", "MKV-v1", "--steps", "200", "--rounds", "2",
                     "--epochs", "1", "--out", str(o), "--quiet"]) == 0
    import zipfile

    weights = [zipfile.ZipFile(o).read("policy.pth") for o in outs]
    assert len(weights[0]) > 1000 and weights[0] == weights[1]   # meta differs only in wall time


def test_wrong_prefix_names_the_right_one(trained):
    with pytest.raises(PolicySpecError, match="use dagger:"):
        make_policy(f"bc:{trained}", make_env("MKV-v1"))


@pytest.mark.parametrize("argv, message", [
    (["--steps", "3", "--rounds", "2"], "too small for 2 rounds"),
    (["--steps", "128"], "--steps 128 is too small for 4 rounds (at least 129): round 0 gets 32 "
                         "teacher steps and its fit on 32 features needs at least 33 rows"),
    (["--steps", "2", "--rounds", "1"], "--steps 2 is too small for 1 round (at least 33)"),
    (["--steps", "64", "--rounds", "2"], "round 0 gets 32 teacher steps"),
    (["--rounds", "0"], "--rounds"),
    (["--env", "Nope-v0"], "Nope-v0"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, argv, message):
    out = tmp_path / "o.zip"
    base = ["train-dagger", "--env", "MKV-v1", "--out", str(out), "--quiet"]
    assert main(base + argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_budget_is_met_exactly_when_episodes_end_early(tmp_path):
    """Episodes shorter than a round's share (time limit 50) do not shrink the budget."""
    policy, meta = dagger.train("MKV-v1", 330, rounds=2, env_kwargs={"max_episode_steps": 50},
                                epochs=1)
    log = meta["dagger"]["log"]
    assert [r["rows"] for r in log] == [165, 165] and [r["episodes"] for r in log] == [4, 4]
    assert meta["teacher_steps"] == 330


def test_the_smallest_accepted_budget_trains(tmp_path, capsys):
    out = tmp_path / "d.zip"
    assert main(["train-dagger", "--env", "MKV-v1", "--steps", "33", "--rounds", "1",
                 "--epochs", "1", "--min-updates", "0", "--out", str(out), "--quiet"]) == 0
    assert dagger.read_metadata(out)["teacher_steps"] == 33


def test_min_steps_gives_round_0_the_rows_its_fit_needs():
    for rounds in (1, 2, 3, 4, 7):
        need = dagger.min_steps(32, rounds)
        assert dagger.round_steps(need, rounds)[0] == 33
        assert dagger.round_steps(need - 1, rounds)[0] == 32
        assert sum(dagger.round_steps(need, rounds)) == need
    with pytest.raises(ValueError, match=r"steps 128 is too small for 4 rounds \(at least 129\)"):
        dagger.train("MKV-v1", 128, rounds=4)
