"""Without ``--address`` the Ray backend runs on a private local Ray: a ``ray start --head`` that
died without ``ray stop`` leaves ``<tmp>/ray/ray_current_cluster`` behind, and neither that file
nor ``RAY_ADDRESS`` may send ``mkv eval`` / ``mkv sweep`` to the dead head. Each command runs in
its own process with ``RAY_TMPDIR`` pointing at a private directory, so the machine's /tmp/ray is
never read or written."""

import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time

import pytest

pytest.importorskip("ray")
# Ray instances share machine-wide state (ports, /tmp/ray), and a head started from an xdist
# worker does not answer (measured): `make test` runs these after the others, in one process
pytestmark = pytest.mark.ray

SPEC = {"name": "stale", "teacher_env": "MKV-v1", "env": ["MKVJam-v1"],
        "eval": {"episodes": 2, "seed": 4_600_000}, "seeds": [0],
        "learners": {"sfm": {}}, "budgets": {"sfm": [300]}}


def _closed_port() -> int:
    """A port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def stale_tmp():
    """A private RAY_TMPDIR (short: Ray's socket paths live under it) holding the file a dead
    ``ray start --head`` leaves behind; yields (tmpdir, the dead address)."""
    tmp = tempfile.mkdtemp(prefix="mkvray", dir="/tmp")
    dead = f"127.0.0.1:{_closed_port()}"
    os.makedirs(os.path.join(tmp, "ray"))
    with open(os.path.join(tmp, "ray", "ray_current_cluster"), "w") as f:
        f.write(dead)
    try:
        yield tmp, dead
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _mkv(tmp, *args, ray_address=None):
    code = f"import sys; from sfm_learn.cli import main; sys.exit(main({list(args)!r}))"
    env = dict(os.environ, SDL_VIDEODRIVER="dummy", RAY_TMPDIR=tmp)
    env.pop("RAY_ADDRESS", None)
    if ray_address is not None:
        env["RAY_ADDRESS"] = ray_address
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=600)


def _ray_processes_under(tmp) -> list[str]:
    """Command lines of live processes mentioning ``tmp`` (Ray's raylet, GCS and workers carry
    their session directory, which is under RAY_TMPDIR)."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if tmp in cmd:
            found.append(f"{pid}: {cmd[:200]}")
    return found


def _assert_ray_gone(tmp, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    while (left := _ray_processes_under(tmp)) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not left, left


def _assert_stale_file_untouched(tmp, dead):
    with open(os.path.join(tmp, "ray", "ray_current_cluster")) as f:
        assert f.read() == dead


def test_eval_without_address_ignores_a_dead_heads_cluster_file(stale_tmp, tmp_path):
    tmp, dead = stale_tmp
    out = tmp_path / "ray.json"
    r = _mkv(tmp, "eval", "--env", "MKVJam-v1", "--policy", "teacher", "--episodes", "2",
             "--seed", "7", "--workers", "1", "--backend", "ray", "--json", str(out), "--quiet")
    assert r.returncode == 0, r.stderr[-800:]
    assert json.loads(out.read_text())
    _assert_stale_file_untouched(tmp, dead)
    _assert_ray_gone(tmp)


def test_sweep_without_address_ignores_the_file_and_ray_address(stale_tmp, tmp_path):
    # RAY_ADDRESS names the dead head too: without --address it is not used either
    tmp, dead = stale_tmp
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SPEC))
    r = _mkv(tmp, "sweep", str(spec), "--out", str(tmp_path / "o"), "--backend", "ray",
             "--workers", "1", "--quiet", ray_address=dead)
    assert r.returncode == 0, r.stderr[-800:]
    rows = list((tmp_path / "o" / "rows").glob("*.json"))
    assert rows and all(json.loads(p.read_text())["status"] == "ok" for p in rows)
    _assert_stale_file_untouched(tmp, dead)
    _assert_ray_gone(tmp)


def test_an_unreachable_address_is_still_refused_in_one_line(stale_tmp):
    tmp, dead = stale_tmp  # nothing listens there: refused before Ray starts
    r = _mkv(tmp, "eval", "--env", "MKVJam-v1", "--policy", "teacher", "--episodes", "1",
             "--backend", "ray", "--address", dead)
    err = r.stderr.strip()
    assert r.returncode == 2 and f"cannot reach the Ray cluster at {dead}" in err, err[-800:]
    assert "\n" not in err
    assert not _ray_processes_under(tmp)
