"""The Ray backend (``--backend ray``): same evaluation JSON and sweep rows as the local one."""

import json

import pytest

ray = pytest.importorskip("ray")
# Ray instances share machine-wide state (ports, /tmp/ray), and a head started from an xdist
# worker does not answer (measured): `make test` runs these after the others, in one process
pytestmark = pytest.mark.ray

from sfm_learn.cli import main  # noqa: E402
from sfm_learn.evaluation import evaluate_many, evaluations_json  # noqa: E402
from sfm_learn.experiments import sweep  # noqa: E402

SPEC = {
    "name": "tiny-ray",
    "teacher_env": "MKV-v1",
    "env": ["MKVJam-v1"],
    "eval": {"episodes": 2, "seed": 4_200_000},
    "seeds": [0, 1],
    "learners": {"sfm": {}, "dagger-bad": {"rounds": 50}},
    "budgets": {"sfm": [200, 300], "dagger-bad": [50]},
}
VOLATILE = ("wall_s", "train_s", "policy", "_file")


def stable(rows):
    return sorted(json.dumps({k: v for k, v in r.items() if k not in VOLATILE}, sort_keys=True)
                  for r in rows)


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
             configure_logging=False)
    yield
    ray.shutdown()


def test_eval_json_is_identical_on_both_backends():
    specs = ["teacher", "random"]
    local = evaluations_json(evaluate_many("MKVJam-v1", specs, 6, 11, workers=2))
    on_ray = evaluations_json(evaluate_many("MKVJam-v1", specs, 6, 11, workers=2,
                                            backend="ray"))
    assert on_ray == local


def test_mkv_eval_backend_ray_writes_the_same_file(tmp_path, capsys):
    out = {b: tmp_path / f"{b}.json" for b in ("local", "ray")}
    for b, path in out.items():
        assert main(["eval", "--env", "MKVJam-v1", "--policy", "teacher", "--episodes", "3",
                     "--seed", "5", "--workers", "2", "--backend", b, "--json", str(path),
                     "--quiet"]) == 0
    assert out["ray"].read_bytes() == out["local"].read_bytes()


def test_sweep_on_ray_gives_the_local_rows_and_reports_the_failing_job(tmp_path):
    spec = sweep.check_spec(SPEC)
    local, on_ray = tmp_path / "local", tmp_path / "ray"
    c1 = sweep.run_sweep(spec, str(local))
    c2 = sweep.run_sweep(spec, str(on_ray), backend="ray", workers=2)
    assert c1 == c2 == {"jobs": 6, "skipped": 0, "ok": 4, "error": 2}
    rows = sweep.read_rows(str(on_ray))
    assert stable(rows) == stable(sweep.read_rows(str(local)))
    bad = [r for r in rows if r["status"] == "error"]
    assert len(bad) == 2 and all("per round" in r["error"] for r in bad)


def test_interrupted_ray_sweep_resumes_to_the_same_rows(tmp_path):
    spec = sweep.check_spec(dict(SPEC, learners={"sfm": {}}, budgets={"sfm": [200, 300]}))
    full, resumed = tmp_path / "full", tmp_path / "resumed"
    sweep.run_sweep(spec, str(full), backend="ray", workers=2)
    seen = []

    def stop_after_one(job, rows):
        seen.append(job)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sweep.run_sweep(spec, str(resumed), backend="ray", workers=1, on_job=stop_after_one)
    assert 1 <= len(sweep.read_rows(str(resumed))) < 4
    counts = sweep.run_sweep(spec, str(resumed), backend="ray", workers=2)
    assert counts["skipped"] >= 1 and counts["error"] == 0
    assert stable(sweep.read_rows(str(resumed))) == stable(sweep.read_rows(str(full)))


def test_address_without_ray_backend_is_refused(capsys):
    assert main(["eval", "--env", "MKVJam-v1", "--policy", "teacher", "--episodes", "1",
                 "--address", "127.0.0.1:1"]) == 2
    assert "--address is for --backend ray" in capsys.readouterr().err


@pytest.mark.parametrize("address, message", [("127.0.0.1:1", "cannot reach the Ray cluster"),
                                              ("nonsense", "is not host:port")])
def test_unreachable_address_is_one_line(address, message):
    from sfm_learn.evaluation.ray_eval import check_reachable

    with pytest.raises(ValueError, match=message) as e:
        check_reachable(address, timeout_s=1.0)
    assert "\n" not in str(e.value)
