"""benchmarks/env_speed.py runs end to end (tiny sizes) and prints every section it promises: the
benchmark reaches into private parts of the envs (the step kernel's batch) to split their time,
so a refactor that breaks it must fail here rather than at ``make bench``."""

import importlib.util
from pathlib import Path

import pytest

from mkv_env import kernel as kernel_mod

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not kernel_mod.AVAILABLE, reason="compiled kernel not built")


@pytest.fixture(scope="module")
def env_speed():
    spec = importlib.util.spec_from_file_location("env_speed", ROOT / "benchmarks/env_speed.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_env_speed_prints_every_ratio_and_split(env_speed, capsys):
    env_speed.main(["--steps", "600", "--rounds", "1", "--num-envs", "2"])
    out = capsys.readouterr().out
    for section in ("MKV-v0 / LunarLander-v3", "native vector x2 / LunarLander-v3",
                    "time per robot-step / physics alone", "2 threads / 1 thread",
                    "stepping alone, 2 threads", "the step's kernel call (Batch.vstep",
                    "MKVJam-v0 time per step / MKV-v0's", "compiled kernel / Python reference",
                    "native vector x2, one thread, us per robot-step",
                    "where an MKV-v0 step's time goes"):
        assert section in out
    assert "target >= 3.5" in out and ("met" in out or "MISSED" in out)


def test_vector_split_times_every_part(env_speed):
    """700 steps per robot outlast one 600-step MKV-v0 episode: the step's kernel call (its
    autoresets inside) and the Python around it got time, Python reset nothing (the timing hooks
    are attached to what the vector env really calls); a jam id's resets are Python's."""
    parts = env_speed.vector_split(2, 1400)
    assert parts["call"] > 0 and parts["rest"] > 0 and parts["reset"] == 0
    assert parts["total"] > parts["call"]
    jam = env_speed.vector_split(2, 1400, "MKVJam-v0")
    assert jam["call"] == 0 and jam["reset"] > 0  # (no one-call step for the jam ids)


def test_single_split_times_every_part(env_speed):
    parts = dict(env_speed.where_the_single_step_goes(700))
    assert all(v > 0 for k, v in parts.items() if k != "Gymnasium's wrappers")
