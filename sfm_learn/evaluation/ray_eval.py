"""Evaluation units as Ray tasks (``mkv eval --backend ray``), and the one place Ray is started.

The units are exactly the local backend's (:func:`~sfm_learn.evaluation.runner.plan_units`); each
builds its own env and policy from the spec with the evaluation's policy seed, so the records, and
the JSON written from them, are identical on either backend. Ray is imported only here and in
:mod:`sfm_learn.experiments.ray_backend`, never by the local backends or ``mkv --help``.

Ray core tasks, not Ray Tune: a unit (or a sweep job) is a plain function call with a result,
with no trials to schedule adaptively, and core tasks keep the code path the local backend runs.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Callable

INSTALL_HINT = "the ray backend needs the scale extra: pip install 'mkv-sfm[scale]'"


def import_ray():
    """``ray``, or ValueError with the install hint (one line)."""
    try:
        import ray
    except ImportError:
        raise ValueError(INSTALL_HINT) from None
    return ray


def init_ray(address: str | None, workers: int):
    """Connect to the cluster at ``address``, or start a private local Ray with ``workers`` CPUs
    (no dashboard, worker logs not forwarded). Reuses a running session. ValueError (one line)
    when the cluster cannot be reached.

    Without ``address`` the local Ray is always a new one (``ray.init(address="local")``): a bare
    ``ray.init`` would instead connect to ``RAY_ADDRESS`` or to the last ``ray start --head``
    recorded in ``<tmp>/ray/ray_current_cluster``, a file left behind when that head died without
    ``ray stop``, and then refuse ``num_cpus``. Ray shuts the local instance down when the process
    exits (its atexit handler), as before."""
    if address:
        use_cluster_token()  # before Ray is imported: it reads the mode then
    ray = import_ray()
    if ray.is_initialized():
        return ray
    if address and address != "auto":
        check_reachable(address)
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    kwargs = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
    try:
        if address:
            with _c_stderr_held():  # Ray's C++ client logs each failed try to fd 2
                ray.init(address=address, **kwargs)
        else:
            ray.init(address="local", num_cpus=int(workers), **kwargs)
    except Exception as e:  # noqa: BLE001  (ConnectionError, RuntimeError, ...: one line)
        text = (str(e).strip().splitlines() or [type(e).__name__])[0]
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        hint = ("; if the cluster uses token authentication (Ray's default for `ray start`), "
                "put its token in ~/.ray/auth_token or RAY_AUTH_TOKEN" if address else "")
        raise ValueError(f"cannot start or reach {where}: {text}{hint}") from None
    return ray


@contextlib.contextmanager
def _c_stderr_held():
    """The process's C-level standard error (file descriptor 2) into a temporary file while the
    block runs: written back to it when the block succeeds, dropped when it raises (then the
    command's one-line error is the only line it prints; Ray's C++ client writes a warning line
    per failed try to reach a cluster, about 20 before it gives up)."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        ok = False
        try:
            yield
            ok = True
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            if ok:
                held.seek(0)
                data = held.read()
                if data:
                    os.write(2, data)


def check_workers_fit(ray, workers: int) -> None:
    """ValueError (one line) when more than 4 tasks per CPU of the cluster would be in flight."""
    cpus = int(ray.cluster_resources().get("CPU", 0))
    if workers > max(1, 4 * cpus):
        raise ValueError(f"--workers {workers} is more than 4 per CPU of the Ray cluster "
                         f"({cpus} CPUs)")


def use_cluster_token() -> None:
    """Connect with token authentication when a token is at hand (``RAY_AUTH_TOKEN`` or the
    ``~/.ray/auth_token`` that ``ray start`` writes) and the user has not chosen a mode: clusters
    started by ``ray start --head`` (Ray >= 2.5x) refuse a driver without it."""
    if "RAY_AUTH_MODE" in os.environ:
        return
    token_file = os.path.join(os.path.expanduser("~"), ".ray", "auth_token")
    if os.environ.get("RAY_AUTH_TOKEN") or os.path.isfile(token_file):
        os.environ["RAY_AUTH_MODE"] = "token"


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """A TCP connection to ``host:port`` (``ray://`` stripped) within ``timeout_s``, else
    ValueError (one line): Ray itself retries an unreachable address for minutes."""
    import socket

    hostport = address.split("://", 1)[-1]
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"Ray address {address!r} is not host:port")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise ValueError(f"cannot reach the Ray cluster at {address}: "
                         f"{e.strerror or type(e).__name__}") from None


def _ray_unit(unit_fn, env_id, env_kwargs, spec, eval_seed, first, count):
    import mkv_env  # noqa: F401  (registers the ids in a fresh Ray worker)
    import sfm_learn  # noqa: F401  (and the policy specs)

    return unit_fn(env_id, env_kwargs, spec, eval_seed, first, count, None)


def run_units(unit_fn, env_id: str, env_kwargs: dict, specs, seed: int, units, workers: int,
              address: str | None,
              on_unit_episode: Callable[[int, int, int], None] | None = None) -> list:
    """Run every unit as a Ray task calling ``unit_fn`` (the runner's own unit function, passed
    in so this module does not import the runner); returns the records of each unit, by unit.
    Progress is reported per finished unit (one call per episode of it, in episode order)."""
    ray = init_ray(address, workers)
    task = ray.remote(num_cpus=1, max_retries=0)(_ray_unit)
    refs = {task.remote(unit_fn, env_id, env_kwargs, specs[p], seed, seed + first, count): uid
            for uid, (p, first, count) in enumerate(units)}
    results = {}
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=0.5)
            for ref in done:
                uid = refs[ref]
                try:
                    results[uid] = ray.get(ref)
                except ray.exceptions.RayTaskError as e:
                    raise e.as_instanceof_cause() from None
                if on_unit_episode is not None:
                    for i, rec in enumerate(results[uid]):
                        on_unit_episode(uid, i, rec.steps)
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    return [results[uid] for uid in range(len(units))]


__all__ = ["INSTALL_HINT", "check_reachable", "import_ray", "init_ray", "run_units"]
