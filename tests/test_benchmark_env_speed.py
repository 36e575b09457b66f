"""benchmarks/env_speed.py runs end to end (tiny sizes) and prints every section it promises: the
benchmark reaches into private parts of the vector env (``_move``) to split its time, so a
refactor that breaks it must fail here rather than at ``make bench``."""

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def env_speed():
    spec = importlib.util.spec_from_file_location("env_speed", ROOT / "benchmarks/env_speed.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_env_speed_prints_ratios_splits_and_ceiling(env_speed, capsys):
    env_speed.main(["--steps", "600", "--rounds", "1", "--num-envs", "2"])
    out = capsys.readouterr().out
    for section in ("MKV-v0 / LunarLander-v3", "native vector x2 / MKV-v0 single",
                    "where an MKV-v0 step's time goes", "native vector x2, us per robot-step",
                    "one space holding all 2 arenas", "ceiling of native vector x2"):
        assert section in out


def test_vector_split_times_every_part(env_speed):
    """700 steps per robot outlast one 600-step MKV-v0 episode: physics, resets and the rest all
    got time (the timing hooks are attached to what the vector env really calls)."""
    parts = env_speed.vector_split(2, 1400)
    assert parts["physics"] > 0 and parts["reset"] > 0 and parts["rest"] > 0
