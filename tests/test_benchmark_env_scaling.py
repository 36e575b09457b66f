"""benchmarks/env_scaling.py runs end to end (tiny sizes) and prints what it promises: a rate and
a memory figure for every size and env, both targets with a verdict, and the plot."""

import importlib.util
from pathlib import Path

import pytest

from mkv_env import kernel as kernel_mod

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not kernel_mod.AVAILABLE, reason="compiled kernel not built")


@pytest.fixture(scope="module")
def env_scaling():
    spec = importlib.util.spec_from_file_location("env_scaling",
                                                  ROOT / "benchmarks/env_scaling.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_env_scaling_prints_every_size_target_and_plot(env_scaling, capsys, tmp_path,
                                                       monkeypatch):
    pytest.importorskip("matplotlib")
    monkeypatch.setattr(env_scaling, "SIZES", (1, 2))
    png = tmp_path / "curve.png"
    env_scaling.main(["--robot-steps", "8", "--rounds", "1", "--png", str(png),
                      "--target-size", "2"])
    out = capsys.readouterr().out
    rows = [r for r in map(str.split, out.splitlines())
            if len(r) > 4 and r[0] in env_scaling.ENVS and r[1].isdigit()]
    assert sorted((r[0], r[1]) for r in rows) == sorted(
        (e, str(n)) for e in env_scaling.ENVS for n in (1, 2))
    for r in rows:  # a positive rate and a positive memory figure on every row
        assert float(r[2].replace(",", "")) > 0 and float(r[4]) > 0
    for env_id in ("MKV-v1", "MKVJam-v1"):
        assert f"{env_id}: 2-robot rate / 1-robot rate" in out
        assert f"{env_id}: memory per robot at 2" in out
    assert out.count("met") + out.count("MISSED") >= 4
    assert png.is_file() and png.stat().st_size > 10_000


def test_env_scaling_refuses_bad_options(env_scaling):
    with pytest.raises(SystemExit):
        env_scaling.main(["--rounds", "0"])
