"""Against a real head started by ``ray start --head`` (the pinned Ray's default auth: a token in
~/.ray/auth_token), ``mkv eval`` and ``mkv sweep`` reach it with ``--address`` and write what a
local run writes; a refused command leaves nothing behind."""

import json
import os
import shutil
import socket
import subprocess
import sys
import time

import pytest

pytest.importorskip("ray")
# Ray instances share machine-wide state (ports, /tmp/ray), and a head started from an xdist
# worker does not answer (measured): `make test` runs these after the others, in one process
pytestmark = pytest.mark.ray

SPEC = {"name": "head", "teacher_env": "MKV-v1", "env": ["MKVJam-v1"],
        "eval": {"episodes": 2, "seed": 4_500_000}, "seeds": [0, 1],
        "learners": {"sfm": {}}, "budgets": {"sfm": [300]}}
VOLATILE = ("wall_s", "train_s", "policy", "_file")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _mkv(*args, env=None):
    code = f"import sys; from sfm_learn.cli import main; sys.exit(main({list(args)!r}))"
    e = dict(os.environ, SDL_VIDEODRIVER="dummy")
    e.pop("RAY_ADDRESS", None)
    e.update(env or {})
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e,
                          timeout=600, stdin=subprocess.DEVNULL)


@pytest.fixture(scope="module")
def head():
    ray_cli = shutil.which("ray", path=os.path.dirname(sys.executable))
    if ray_cli is None:
        pytest.skip("no ray command")
    port = _free_port()
    r = subprocess.run([ray_cli, "start", "--head", f"--port={port}", "--num-cpus=2",
                        "--include-dashboard=false", "--disable-usage-stats"],
                       capture_output=True, text=True, timeout=180,
                       stdin=subprocess.DEVNULL)
    if r.returncode != 0:
        pytest.skip(f"ray start failed here: {r.stderr.strip().splitlines()[-1:]}")
    # `ray start` returns before the head's node is registered; on a loaded machine (the suite
    # runs on 2 xdist workers) a driver connecting at once can time out: wait until it answers
    deadline = time.monotonic() + 180
    while subprocess.run([ray_cli, "status", f"--address=127.0.0.1:{port}"], capture_output=True,
                         timeout=120, stdin=subprocess.DEVNULL).returncode != 0 \
            and time.monotonic() < deadline:
        time.sleep(1.0)
    try:
        yield f"127.0.0.1:{port}"
    finally:
        subprocess.run([ray_cli, "stop", "--force"], capture_output=True, timeout=120)


def _stable(rows_dir):
    rows = []
    for name in sorted(os.listdir(rows_dir)):
        with open(os.path.join(rows_dir, name)) as f:
            r = json.load(f)
        rows.append(json.dumps({k: v for k, v in r.items() if k not in VOLATILE}, sort_keys=True))
    return rows


def test_eval_and_sweep_on_a_ray_start_head_equal_local_runs(head, tmp_path):
    args = ["eval", "--env", "MKVJam-v1", "--policy", "teacher", "--episodes", "3", "--seed", "7",
            "--workers", "2", "--quiet"]
    r_local = _mkv(*args, "--json", str(tmp_path / "local.json"))
    assert r_local.returncode == 0, r_local.stderr
    r_ray = _mkv(*args, "--backend", "ray", "--address", head, "--json",
                 str(tmp_path / "ray.json"))
    assert r_ray.returncode == 0, r_ray.stderr[-500:]
    assert (tmp_path / "ray.json").read_bytes() == (tmp_path / "local.json").read_bytes()

    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SPEC))
    assert _mkv("sweep", str(spec), "--out", str(tmp_path / "sl"), "--quiet").returncode == 0
    r = _mkv("sweep", str(spec), "--out", str(tmp_path / "sr"), "--backend", "ray", "--address",
             head, "--workers", "2", "--quiet")
    assert r.returncode == 0, r.stderr[-500:]
    assert _stable(tmp_path / "sr" / "rows") == _stable(tmp_path / "sl" / "rows")


def test_more_workers_than_the_cluster_takes_are_refused_leaving_nothing(head, tmp_path):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SPEC))
    r = _mkv("sweep", str(spec), "--out", str(tmp_path / "o"), "--backend", "ray", "--address",
             head, "--workers", "64")
    assert r.returncode == 2 and "4 per CPU of the Ray cluster" in r.stderr
    assert not (tmp_path / "o").exists()
    r = _mkv("eval", "--env", "MKVJam-v1", "--policy", "teacher", "--episodes", "1",
             "--backend", "ray", "--address", head, "--workers", "64")
    assert r.returncode == 2 and "4 per CPU of the Ray cluster" in r.stderr
