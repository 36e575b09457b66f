"""Shared recordings for the sfm_learn tests (recorded once per session; a few seconds)."""

import os
import tempfile

import pytest

from mkv_env.dataset import save
from mkv_env.recorder import record

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("MPLBACKEND", "Agg")
# plain-SB3 models in the tests log nowhere useful; keep their folders out of /tmp
os.environ.setdefault("SB3_LOGDIR", os.path.join(tempfile.gettempdir(), "mkv-tests-sb3-logs"))


@pytest.fixture(scope="session")
def wander_train():
    """20 teacher episodes of MKV-v0 (env seeds 0..19, 12,000 steps): the issue's budget."""
    return record("MKV-v0", "teacher", 20, 0)


@pytest.fixture(scope="session")
def wander_held():
    """Held-out teacher runs of MKV-v0 (env seeds 500..502)."""
    return record("MKV-v0", "teacher", 3, 500)


@pytest.fixture(scope="session")
def small_train():
    """A short recording for CLI and file tests (3 x 100 steps)."""
    return record("MKV-v0", "teacher", 3, 0, {"max_episode_steps": 100})


@pytest.fixture(scope="session")
def data_files(tmp_path_factory, small_train, wander_held):
    d = tmp_path_factory.mktemp("sfm_data")
    train, held = d / "train.npz", d / "held.npz"
    save(small_train, train)
    save(wander_held, held)
    return train, held


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    """``tiny_data(steps, episodes=1)``: the path of a teacher recording of ``episodes`` MKV-v0
    episodes cut at ``steps`` steps each (made once per size; well under a second)."""
    d = tmp_path_factory.mktemp("tiny_data")
    made = {}

    def make(steps: int, episodes: int = 1):
        if (steps, episodes) not in made:
            path = d / f"teacher_{episodes}x{steps}.npz"
            save(record("MKV-v0", "teacher", episodes, 0, max_steps=steps), path)
            made[steps, episodes] = path
        return made[steps, episodes]

    return make
