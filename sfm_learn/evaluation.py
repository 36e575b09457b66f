"""Policy evaluation on seeded episodes: per-episode records, aggregate metrics, bootstrap
confidence intervals, worker processes, and the reports (Markdown table, bar plot).

Every policy (teacher, random, command script, SfM, PPO, BC) is evaluated the same way: episode
``i`` resets the env with seed ``seed + i``; the episode is recorded with
:mod:`mkv_env.recorder` (so metrics come from the same ground-truth ``info`` a dataset stores);
each episode becomes an :class:`EpisodeRecord`; :func:`aggregate` turns a list of records into the
metrics below. Records are plain, picklable and independent of one another, so
:func:`evaluate_many` runs several policies on the same seeds, shares the seeds out to worker
processes, and bootstraps confidence intervals by resampling records.

Metrics (:data:`METRIC_KEYS`; ``None`` where undefined):

* ``escape_rate``: fraction of episodes that ended escaped (envs that report ``escaped``, e.g.
  ``MKVJam-v0``; ``None`` otherwise).
* ``mean_escape_time_s``: mean time to escape over escaped episodes [s] (``None`` if none escaped
  or the env has no escapes).
* ``distance_m``: mean distance travelled per episode [m].
* ``stuck_fraction``: stuck steps / all steps, pooled over episodes.
* ``collisions_per_min``: new collisions / simulated minutes, pooled over episodes.
* ``mean_return``: mean undiscounted episode return.

Same seeds, same numbers: each episode depends only on its env seed (the runners reset the env
with it and call ``policy.reset(seed=...)`` with a seed derived from it), each worker's unit of
work builds its own env and policy, and the bootstrap uses a fixed random stream. So the records,
the metrics and the confidence intervals are identical, byte for byte in the JSON, whatever the
number of workers and however the seeds are chunked. (A policy object without ``reset`` that
keeps state across episodes would break this; every spec policy has ``reset`` or no state.)
"""

from __future__ import annotations

import json
import math
import os
import pickle
import queue
import re
import signal
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from mkv_env.dataset import Dataset
from mkv_env.files import atomic_path
from mkv_env.policies import describe
from mkv_env.recorder import record

METRIC_KEYS = ("escape_rate", "mean_escape_time_s", "distance_m", "stuck_fraction",
               "collisions_per_min", "mean_return")

METRIC_LABELS = {
    "escape_rate": "escape rate",
    "mean_escape_time_s": "mean time to escape [s]",
    "distance_m": "distance per episode [m]",
    "stuck_fraction": "stuck fraction",
    "collisions_per_min": "collisions per minute",
    "mean_return": "mean return",
}

#: Decimals used for each metric in the tables.
METRIC_DECIMALS = {"escape_rate": 3, "mean_escape_time_s": 2, "distance_m": 2,
                   "stuck_fraction": 3, "collisions_per_min": 2, "mean_return": 2}

#: Default number of bootstrap resamples and confidence level.
N_BOOT = 2000
CI_LEVEL = 0.95

# Fixed entropy of the bootstrap stream (with the number of records): no clock, no OS entropy.
_BOOT_ENTROPY = 0x5EEDB007


@dataclass(frozen=True)
class EpisodeRecord:
    """What one episode did (ground truth), enough to aggregate every metric."""

    seed: int
    steps: int
    duration_s: float
    episode_return: float
    distance_m: float
    stuck_steps: int
    collisions: int
    jams: int
    escapes: int
    escaped: bool | None
    """Ended escaped; ``None`` when the env does not report escapes."""
    escape_time_s: float | None
    """Time of the first escaped step [s]; ``None`` if not escaped."""
    scenario: str | None = None


def episode_records(data: Dataset) -> list[EpisodeRecord]:
    """One :class:`EpisodeRecord` per episode of a recorded dataset."""
    dt = float(data.metadata["control_period_s"])
    scen = data.metadata.get("episode_scenarios") or [None] * data.n_episodes
    out = []
    for e, rows in enumerate(data.episode_slices()):
        last = rows.stop - 1
        escaped = escape_time = None
        if "escaped" in data:
            flags = data["escaped"][rows]
            escaped = bool(flags[-1])
            if flags.any():
                escape_time = (int(np.argmax(flags)) + 1) * dt
        n = rows.stop - rows.start
        out.append(EpisodeRecord(
            seed=int(data["episode_seeds"][e]),
            steps=int(n),
            duration_s=n * dt,
            episode_return=float(data["rewards"][rows].sum()),
            distance_m=float(data["distance_m"][last]),
            stuck_steps=int(data["stuck"][rows].sum()),
            collisions=int(data["collisions"][last]),
            jams=int(data["jams"][last]),
            escapes=int(data["escapes"][last]),
            escaped=escaped,
            escape_time_s=escape_time,
            scenario=scen[e],
        ))
    return out


def aggregate(records: Sequence[EpisodeRecord]) -> dict[str, float | None]:
    """The metrics of :data:`METRIC_KEYS` from episode records (see the module docstring)."""
    if not records:
        raise ValueError("no episode records to aggregate")
    steps = sum(r.steps for r in records)
    minutes = sum(r.duration_s for r in records) / 60.0
    has_escape = all(r.escaped is not None for r in records)
    escape_rate = mean_escape_time = None
    if has_escape:
        escape_rate = sum(bool(r.escaped) for r in records) / len(records)
        times = [r.escape_time_s for r in records if r.escape_time_s is not None]
        mean_escape_time = float(np.mean(times)) if times else None
    return {
        "escape_rate": escape_rate,
        "mean_escape_time_s": mean_escape_time,
        "distance_m": float(np.mean([r.distance_m for r in records])),
        "stuck_fraction": sum(r.stuck_steps for r in records) / steps if steps else None,
        "collisions_per_min": (sum(r.collisions for r in records) / minutes
                               if minutes > 0 else None),
        "mean_return": float(np.mean([r.episode_return for r in records])),
    }


# ---------------------------------------------------------------------- bootstrap
def bootstrap_indices(n: int, n_boot: int = N_BOOT) -> np.ndarray:
    """The resample indices used for ``n`` records: shape (n_boot, n), from a fixed stream.

    The stream depends only on ``n``, so policies evaluated on the same seeds are resampled with
    the same episodes (a paired bootstrap: differences between policies can be read off the same
    rows)."""
    if n < 1 or n_boot < 1:
        raise ValueError(f"need n >= 1 and n_boot >= 1, got n={n}, n_boot={n_boot}")
    rng = np.random.default_rng(np.random.SeedSequence([_BOOT_ENTROPY, int(n)]))
    return rng.integers(0, n, size=(int(n_boot), int(n)))


def resampled_metrics(records: Sequence[EpisodeRecord],
                      idx: np.ndarray) -> dict[str, np.ndarray]:
    """Every metric of :func:`aggregate` for each row of resample indices ``idx`` (k, n), at once.

    Row ``j`` equals ``aggregate([records[i] for i in idx[j]])`` (up to rounding), with NaN where
    that metric is undefined for the resample (e.g. mean escape time when it has no escape).
    """
    if not records:
        raise ValueError("no episode records to resample")
    idx = np.asarray(idx)
    steps = np.array([r.steps for r in records], dtype=np.float64)[idx]
    dur = np.array([r.duration_s for r in records], dtype=np.float64)[idx]
    out = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        if all(r.escaped is not None for r in records):
            esc = np.array([bool(r.escaped) for r in records], dtype=np.float64)[idx]
            out["escape_rate"] = esc.mean(axis=1)
            has_t = np.array([r.escape_time_s is not None for r in records])[idx]
            t = np.array([r.escape_time_s or 0.0 for r in records], dtype=np.float64)[idx]
            cnt = has_t.sum(axis=1)
            out["mean_escape_time_s"] = np.where(cnt > 0, t.sum(axis=1) / cnt, np.nan)
        else:
            out["escape_rate"] = out["mean_escape_time_s"] = np.full(len(idx), np.nan)
        out["distance_m"] = np.array([r.distance_m for r in records])[idx].mean(axis=1)
        tot_steps = steps.sum(axis=1)
        stuck = np.array([r.stuck_steps for r in records], dtype=np.float64)[idx].sum(axis=1)
        out["stuck_fraction"] = np.where(tot_steps > 0, stuck / tot_steps, np.nan)
        minutes = dur.sum(axis=1) / 60.0
        coll = np.array([r.collisions for r in records], dtype=np.float64)[idx].sum(axis=1)
        out["collisions_per_min"] = np.where(minutes > 0, coll / minutes, np.nan)
        out["mean_return"] = np.array([r.episode_return for r in records])[idx].mean(axis=1)
    return {k: out[k] for k in METRIC_KEYS}


def bootstrap_ci(records: Sequence[EpisodeRecord], level: float = CI_LEVEL,
                 n_boot: int = N_BOOT,
                 metrics: dict[str, float | None] | None = None) -> dict[str, list[float] | None]:
    """Percentile-bootstrap confidence intervals of every metric, over episodes.

    Resamples the records with replacement ``n_boot`` times (:func:`bootstrap_indices`, a fixed
    stream: the same records always give the same intervals), computes every metric of each
    resample (:func:`resampled_metrics`) and takes the ``(1 - level) / 2`` and
    ``(1 + level) / 2`` quantiles.

    Returns ``{key: [low, high]}`` with the keys of :data:`METRIC_KEYS`; ``None`` where the metric
    itself is ``None``. Resamples in which a metric is undefined (mean escape time of a resample
    without any escape) are dropped for that metric, so its interval is conditional on the metric
    existing. Each interval is widened, if need be, to contain the point estimate (this matters
    only for tiny samples and rounding). With one episode every interval is ``[m, m]``.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"confidence level must be in (0, 1), got {level!r}")
    if metrics is None:
        metrics = aggregate(records)
    n = len(records)
    # Blocks of resamples keep memory bounded (about 2 million indices at a time).
    block = max(1, 2_000_000 // n)
    idx = bootstrap_indices(n, n_boot)
    parts = [resampled_metrics(records, idx[i:i + block]) for i in range(0, n_boot, block)]
    q = [(1.0 - level) / 2.0, (1.0 + level) / 2.0]
    out: dict[str, list[float] | None] = {}
    for key in METRIC_KEYS:
        point = metrics[key]
        vals = np.concatenate([p[key] for p in parts])
        vals = vals[np.isfinite(vals)]
        if point is None or vals.size == 0:
            out[key] = None
            continue
        low, high = (float(v) for v in np.quantile(vals, q))
        out[key] = [min(low, float(point)), max(high, float(point))]
    return out


def paired_difference_ci(a: Sequence[EpisodeRecord], b: Sequence[EpisodeRecord], key: str,
                         level: float = CI_LEVEL,
                         n_boot: int = N_BOOT) -> tuple[float, list[float]] | None:
    """Metric ``key`` of ``a`` minus that of ``b`` with a paired percentile-bootstrap interval.

    ``a`` and ``b`` must be records of the same seeds (two policies evaluated on the same
    episodes); each resample draws the same episodes for both, so the interval reflects only how
    the policies differ, not how hard the drawn episodes were. An interval that excludes 0 is the
    usual reading of "a significant difference" at that level. Resamples where either metric is
    undefined are dropped; ``None`` if the difference itself is undefined.
    """
    if [r.seed for r in a] != [r.seed for r in b]:
        raise ValueError("a paired comparison needs records of the same seeds, in order")
    if key not in METRIC_KEYS:
        raise ValueError(f"unknown metric {key!r}; known: {', '.join(METRIC_KEYS)}")
    ma, mb = aggregate(a)[key], aggregate(b)[key]
    if ma is None or mb is None:
        return None
    n = len(a)
    block = max(1, 2_000_000 // n)
    idx = bootstrap_indices(n, n_boot)
    diffs = np.concatenate([resampled_metrics(a, idx[i:i + block])[key]
                            - resampled_metrics(b, idx[i:i + block])[key]
                            for i in range(0, n_boot, block)])
    diffs = diffs[np.isfinite(diffs)]
    d = float(ma - mb)
    if diffs.size == 0:
        return d, [d, d]
    low, high = (float(v) for v in np.quantile(diffs, [(1 - level) / 2, (1 + level) / 2]))
    return d, [min(low, d), max(high, d)]


# ---------------------------------------------------------------------- results
@dataclass
class Evaluation:
    """One policy on one env over seeds ``seed .. seed + episodes - 1``."""

    env: str
    policy: str
    episodes: int
    seed: int
    metrics: dict[str, float | None]
    records: list[EpisodeRecord] = field(default_factory=list, repr=False)
    env_kwargs: dict = field(default_factory=dict)
    metrics_ci: dict[str, list[float] | None] | None = None
    """Bootstrap interval per metric (:func:`bootstrap_ci`); ``None`` if not computed."""
    ci_level: float = CI_LEVEL
    n_boot: int = N_BOOT

    def to_dict(self) -> dict:
        """The ``mkv eval --json`` document: exactly env, policy, episodes, seed, metrics and
        metrics_ci (same keys as metrics, each ``[low, high]`` or ``None``)."""
        ci = self.metrics_ci or {}
        return {
            "env": self.env,
            "policy": self.policy,
            "episodes": self.episodes,
            "seed": self.seed,
            "metrics": {k: _json_number(self.metrics[k]) for k in METRIC_KEYS},
            "metrics_ci": {k: _json_interval(ci.get(k)) for k in METRIC_KEYS},
        }

    def to_json(self) -> str:
        return _dumps(self.to_dict())

    def records_as_dicts(self) -> list[dict]:
        return [asdict(r) for r in self.records]


def evaluations_json(evaluations: Sequence[Evaluation]) -> str:
    """The ``mkv eval --json`` file: one :meth:`Evaluation.to_dict` object for one evaluation,
    a list of them (in the given order) for several."""
    if not evaluations:
        raise ValueError("no evaluations")
    doc = (evaluations[0].to_dict() if len(evaluations) == 1
           else [e.to_dict() for e in evaluations])
    return _dumps(doc)


# ---------------------------------------------------------------------- running episodes
def run_episodes(env_id: str, policy, seeds: Sequence[int] | None = None, *, episodes: int = 0,
                 seed: int = 0, env_kwargs: dict | None = None,
                 on_episode: Callable[[int, int], None] | None = None) -> list[EpisodeRecord]:
    """Run ``policy`` (spec string or object with ``predict``) and return one record per episode.

    Give either consecutive seeds by ``episodes`` and ``seed`` (episode ``i`` uses ``seed + i``),
    or ``seeds`` as a list of consecutive integers (a worker's share of a larger evaluation).
    """
    if seeds is not None:
        seeds = [int(s) for s in seeds]
        if not seeds or seeds != list(range(seeds[0], seeds[0] + len(seeds))):
            raise ValueError("seeds must be a non-empty run of consecutive integers")
        seed, episodes = seeds[0], len(seeds)
    data = record(env_id, policy, episodes, seed, env_kwargs, on_episode=on_episode)
    return episode_records(data)


def _run_unit(env_id: str, env_kwargs: dict | None, policy, eval_seed: int, first: int,
              count: int, on_episode: Callable[[int, int], None] | None) -> list[EpisodeRecord]:
    """Episodes with env seeds ``first .. first + count - 1`` of an evaluation that starts at
    ``eval_seed``: builds its own env, and the policy (from a spec) with the evaluation's policy
    seed, so the records do not depend on how the seeds were chunked."""
    data = record(env_id, policy, count, first, env_kwargs, on_episode=on_episode,
                  first_seed=eval_seed)
    return episode_records(data)


def plan_units(n_policies: int, episodes: int, workers: int,
               min_chunk: int = 4) -> list[tuple[int, int, int]]:
    """Units of work ``(policy_index, first_episode, count)``, in the order they are handed out.

    One unit per policy with one worker. With several, guided chunking: each unit takes
    ``remaining / (2 * workers)`` episodes (at least ``min_chunk``; never across policies), so the
    first units are large (little start-up and IPC per episode) and the last ones small (workers
    finish together). The plan depends only on the arguments, never on timing.
    """
    if workers <= 1:
        return [(p, 0, episodes) for p in range(n_policies)]
    units = []
    remaining = n_policies * episodes
    for p in range(n_policies):
        start = 0
        while start < episodes:
            size = min(max(min_chunk, math.ceil(remaining / (2 * workers))), episodes - start)
            units.append((p, start, size))
            start += size
            remaining -= size
    return units


def default_start_method() -> str:
    """``forkserver`` where available (Linux, macOS), else ``spawn``.

    Workers start from a clean server process that has imported this module once, so they are
    cheap to start and never inherit threads (torch, OpenMP) or pymunk state of the caller, which
    ``fork`` would copy."""
    import multiprocessing as mp

    methods = mp.get_all_start_methods()
    return "forkserver" if "forkserver" in methods else "spawn"


def _portable_exception(e: BaseException) -> BaseException:
    """``e`` if it survives pickling, else a RuntimeError with its type and message; the worker's
    traceback is attached as a note where supported."""
    tb = "".join(traceback.format_exception(type(e), e, e.__traceback__))
    try:
        out = pickle.loads(pickle.dumps(e))
    except Exception:
        out = RuntimeError(f"{type(e).__name__}: {e}")
    if hasattr(out, "add_note"):
        out.add_note(f"in an evaluation worker process:\n{tb}")
    return out


_PROGRESS_INTERVAL_S = 0.1


def _worker_main(task_q, result_q) -> None:
    """A worker process: run units from ``task_q`` until a ``None`` arrives; post
    ``("episodes", uid, [(i, n_steps), ...])`` as episodes finish (batched, at most every
    0.1 s) and ``("done", uid, records)`` or ``("error", uid, exception)`` after every unit."""
    import multiprocessing as mp

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and stops us
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # one process per core; no thread oversubscription
    parent = mp.parent_process()
    while True:
        task = task_q.get()
        if task is None:
            return
        uid, env_id, env_kwargs, spec, eval_seed, first, count = task
        pending: list[tuple[int, int]] = []
        last = [time.monotonic()]

        def flush(uid=uid, pending=pending):
            if pending:
                result_q.put(("episodes", uid, pending[:]))
                pending.clear()

        def progress(i, n, pending=pending, last=last, flush=flush):
            pending.append((i, n))
            now = time.monotonic()
            if now - last[0] >= _PROGRESS_INTERVAL_S:
                last[0] = now
                flush()
                if parent is not None and not parent.is_alive():
                    os._exit(1)  # orphaned: nobody will read our results

        try:
            records = _run_unit(env_id, env_kwargs, spec, eval_seed, first, count, progress)
        except BaseException as e:  # noqa: BLE001  (sent to the parent, which raises it)
            result_q.put(("error", uid, _portable_exception(e)))
            return
        flush()
        result_q.put(("done", uid, records))


def _run_parallel(env_id, env_kwargs, specs, seed, units, workers, start_method, on_unit_episode):
    """Run ``units`` on ``workers`` processes; returns the records of each unit, by unit."""
    import multiprocessing as mp

    method = start_method or default_start_method()
    ctx = mp.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(["sfm_learn.evaluation"])
    task_q, result_q = ctx.Queue(), ctx.Queue()
    for uid, (p, first, count) in enumerate(units):
        task_q.put((uid, env_id, env_kwargs, specs[p], seed, seed + first, count))
    for _ in range(workers):
        task_q.put(None)
    procs = [ctx.Process(target=_worker_main, args=(task_q, result_q), daemon=True,
                         name=f"mkv-eval-{k}") for k in range(workers)]
    results: dict[int, list[EpisodeRecord]] = {}
    try:
        for proc in procs:
            proc.start()
        quiet_polls = 0
        while len(results) < len(units):
            try:
                msg = result_q.get(timeout=0.2)
            except queue.Empty:
                crashed = [q for q in procs if q.exitcode not in (None, 0)]
                if crashed:
                    raise RuntimeError(
                        f"an evaluation worker process died (exit code {crashed[0].exitcode}); "
                        "a script that starts workers must guard its main code with "
                        "if __name__ == '__main__':") from None
                quiet_polls = quiet_polls + 1 if all(q.exitcode == 0 for q in procs) else 0
                if quiet_polls > 10:
                    raise RuntimeError("evaluation workers exited with work left") from None
                continue
            kind, uid = msg[0], msg[1]
            if kind == "episodes":
                for i, n in msg[2]:
                    on_unit_episode(uid, i, n)
            elif kind == "done":
                results[uid] = msg[2]
            else:
                raise msg[2]
        for proc in procs:
            proc.join(timeout=5.0)
    finally:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
        for proc in procs:
            if proc.pid is not None:
                proc.join(timeout=5.0)
                if proc.is_alive():
                    proc.kill()
                    proc.join()
        task_q.cancel_join_thread()
        result_q.cancel_join_thread()
        task_q.close()
        result_q.close()
    return [results[uid] for uid in range(len(units))]


def evaluate_many(env_id: str, policies: Sequence, episodes: int, seed: int = 0,
                  env_kwargs: dict | None = None, *, workers: int = 1,
                  on_episode: Callable[[int, int, int], None] | None = None,
                  ci_level: float = CI_LEVEL, n_boot: int = N_BOOT,
                  start_method: str | None = None,
                  policy_names: Sequence[str] | None = None) -> list[Evaluation]:
    """Evaluate several policies on the same seeded episodes, optionally in worker processes.

    Args:
        env_id: registered Gymnasium id (``"MKV-v0"``, ``"MKVJam-v0"``).
        policies: spec strings (``"teacher"``, ``"teacher:backoff_s=2"``, ``"random"``,
            ``"script:PATH"``, ``"sfm:PATH"``, ``"ppo:PATH"``, ``"bc:PATH"``) or, with one worker
            only, objects with SB3 ``predict``. Names must be distinct.
        episodes: episodes per policy (>= 1); episode ``i`` uses env seed ``seed + i``.
        seed: first env seed.
        env_kwargs: extra ``gymnasium.make`` arguments.
        workers: processes to run episodes in. 1 runs everything in this process; more split
            the seeds into units (:func:`plan_units`) handed to worker processes (started with
            :func:`default_start_method` unless ``start_method`` is given). The results are
            identical for every worker count.
        on_episode: progress callback ``(policy_index, episode_index, n_steps)``, called in this
            process once per finished episode (in completion order with workers).
        ci_level, n_boot: bootstrap confidence intervals (:func:`bootstrap_ci`).
        policy_names: names for reports (default: the spec, or the object's ``spec`` attribute).

    Returns:
        One :class:`Evaluation` per policy, in the given order, with records, metrics and
        metrics_ci.

    Raises:
        ValueError: bad arguments (no policies, duplicate names, policy objects with workers > 1).
        PolicySpecError, ScriptError, ...: as raised while building a policy or env (in a worker
            too); KeyboardInterrupt stops and joins every worker first.
    """
    policies = list(policies)
    if not policies:
        raise ValueError("no policies to evaluate")
    if not (isinstance(episodes, (int, np.integer)) and episodes >= 1):
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    if not (isinstance(seed, (int, np.integer)) and 0 <= seed < 2**63 - episodes):
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if not (isinstance(workers, (int, np.integer)) and workers >= 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    names = list(policy_names) if policy_names is not None else [
        p if isinstance(p, str) else describe(p) for p in policies]
    if len(names) != len(policies):
        raise ValueError("policy_names must name every policy")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"policy {dup[0]!r} given more than once")
    units = plan_units(len(policies), int(episodes), int(workers))
    workers = min(int(workers), len(units))
    if workers > 1 and not all(isinstance(p, str) for p in policies):
        raise ValueError("policy objects can only be evaluated with workers=1; give spec "
                         "strings to use worker processes")
    env_kwargs = dict(env_kwargs or {})
    seed, episodes = int(seed), int(episodes)

    def unit_progress(uid, i, n):
        if on_episode is not None:
            p, first, _ = units[uid]
            on_episode(p, first + i, n)

    if workers == 1:
        unit_records = [_run_unit(env_id, env_kwargs, policies[p], seed, seed + first, count,
                                  lambda i, n, uid=uid: unit_progress(uid, i, n))
                        for uid, (p, first, count) in enumerate(units)]
    else:
        unit_records = _run_parallel(env_id, env_kwargs, policies, seed, units, workers,
                                     start_method, unit_progress)
    per_policy: list[list[EpisodeRecord]] = [[] for _ in policies]
    for (p, _, _), recs in zip(units, unit_records, strict=True):
        per_policy[p].extend(recs)
    out = []
    for name, recs in zip(names, per_policy, strict=True):
        metrics = aggregate(recs)
        out.append(Evaluation(env_id, name, episodes, seed, metrics, recs, dict(env_kwargs),
                              bootstrap_ci(recs, ci_level, n_boot, metrics), ci_level, n_boot))
    return out


def evaluate(env_id: str, policy, episodes: int, seed: int = 0, env_kwargs: dict | None = None,
             on_episode: Callable[[int, int], None] | None = None,
             policy_name: str | None = None, *, workers: int = 1, ci_level: float = CI_LEVEL,
             n_boot: int = N_BOOT) -> Evaluation:
    """Evaluate one policy on seeded episodes; returns records, metrics and their bootstrap CIs.

    Args:
        env_id: registered Gymnasium id (``"MKV-v0"``, ``"MKVJam-v0"``).
        policy: a spec string (``"teacher"``, ``"random"``, ``"script:PATH"``, plug-in specs) or an
            object with SB3 ``predict`` (then ``workers`` must be 1).
        episodes: number of episodes (>= 1); episode ``i`` uses env seed ``seed + i``.
        seed: first env seed.
        env_kwargs: extra ``gymnasium.make`` arguments.
        on_episode: progress callback ``(episode_index, n_steps)``.
        policy_name: name for reports (default: the spec, or the policy's ``spec`` attribute).
        workers, ci_level, n_boot: as for :func:`evaluate_many`.
    """
    cb = None if on_episode is None else (lambda p, i, n: on_episode(i, n))
    return evaluate_many(env_id, [policy], episodes, seed, env_kwargs, workers=workers,
                         on_episode=cb, ci_level=ci_level, n_boot=n_boot,
                         policy_names=None if policy_name is None else [policy_name])[0]


# ---------------------------------------------------------------------- reports
def format_table(evaluations: Sequence[Evaluation]) -> str:
    """A plain-text table: one row per metric, one column per evaluation (policy)."""
    if not evaluations:
        return ""
    heads = [e.policy for e in evaluations]
    label_w = max(len(v) for v in METRIC_LABELS.values())
    col_w = [max(10, len(h)) for h in heads]
    first = evaluations[0]
    lines = [f"{first.env}: {first.episodes} episodes, seeds {first.seed}.."
             f"{first.seed + first.episodes - 1}"]
    lines.append(f"{'metric':<{label_w}}  " + "  ".join(
        f"{h:>{w}}" for h, w in zip(heads, col_w, strict=True)))
    for key in METRIC_KEYS:
        cells = [_fmt(e.metrics[key]) for e in evaluations]
        lines.append(f"{METRIC_LABELS[key]:<{label_w}}  " + "  ".join(
            f"{c:>{w}}" for c, w in zip(cells, col_w, strict=True)))
    return "\n".join(lines)


def format_cell(value: float | None, interval: Sequence[float] | None = None,
                decimals: int = 3) -> str:
    """``0.980 [0.940, 1.000]``; just the value without an interval; ``-`` when undefined."""
    if value is None or not math.isfinite(value):
        return "-"
    text = f"{value:.{decimals}f}"
    if interval is not None:
        text += f" [{interval[0]:.{decimals}f}, {interval[1]:.{decimals}f}]"
    return text


def _seed_range(e: Evaluation) -> str:
    return f"{e.seed}..{e.seed + e.episodes - 1}"


def format_markdown(evaluations: Sequence[Evaluation]) -> str:
    """A Markdown comparison table: one row per policy, one column per metric.

    The first line names the env, the episodes and the seeds (when all evaluations share them;
    otherwise the table gets env and seeds columns) and the confidence level; cells read
    ``value [low, high]`` with the bootstrap interval, ``-`` where a metric is undefined.
    """
    if not evaluations:
        return ""
    first = evaluations[0]
    shared = all((e.env, e.episodes, e.seed) == (first.env, first.episodes, first.seed)
                 for e in evaluations)
    levels = {e.ci_level for e in evaluations if e.metrics_ci is not None}
    ci_text = (f"cells: value [{100 * levels.pop():g}% bootstrap confidence interval over "
               f"episodes]" if len(levels) == 1 else "cells: value [bootstrap interval]")
    if shared:
        head = (f"**{first.env}**, {first.episodes} episode{'s' * (first.episodes != 1)} per "
                f"policy on env seeds {_seed_range(first)}; {ci_text}.")
    else:
        head = f"Evaluations on different envs or seeds; {ci_text}."
    cols = ["policy"] + ([] if shared else ["env", "seeds"])
    cols += [METRIC_LABELS[k] for k in METRIC_KEYS]
    lines = [head, "", "| " + " | ".join(cols) + " |",
             "|" + "|".join([":---"] * (1 if shared else 3) + ["---:"] * len(METRIC_KEYS)) + "|"]
    for e in evaluations:
        ci = e.metrics_ci or {}
        cells = [_md_escape(e.policy)]
        if not shared:
            cells += [_md_escape(e.env), _seed_range(e)]
        cells += [format_cell(e.metrics[k], ci.get(k), METRIC_DECIMALS[k]) for k in METRIC_KEYS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _md_escape(text: str) -> str:
    return str(text).replace("|", "\\|")


def _short_name(name: str, width: int = 22) -> str:
    """A policy name for axis labels: paths reduced to their file name, then truncated."""
    prefix, sep, arg = name.partition(":")
    if sep and ("/" in arg or os.sep in arg):
        name = f"{prefix}:{os.path.basename(arg)}"
    return name if len(name) <= width else name[:width - 1] + "\u2026"


def plot_evaluations(evaluations: Sequence[Evaluation], path: str,
                     title: str | None = None, dpi: int = 120) -> None:
    """Bar plot of every metric: one panel per metric, one bar per policy, bootstrap CIs as error
    bars, written atomically to ``path`` (format from its extension, e.g. ``.png``, ``.pdf``).

    Needs matplotlib (``pip install 'mkv-sfm[plots]'``; ImportError otherwise). Uses the
    object-oriented API without pyplot, so no display or backend set-up is needed.
    """
    from matplotlib.figure import Figure

    if not evaluations:
        raise ValueError("no evaluations to plot")
    names = [_short_name(e.policy) for e in evaluations]
    colors = [f"C{i % 10}" for i in range(len(evaluations))]
    x = np.arange(len(evaluations))
    n_cols = 3
    n_rows = math.ceil(len(METRIC_KEYS) / n_cols)
    width = max(10.0, 1.1 * n_cols * max(2.0, 0.55 * len(evaluations)))
    fig = Figure(figsize=(width, 3.4 * n_rows + 0.9), dpi=dpi)
    axes = fig.subplots(n_rows, n_cols, squeeze=False).ravel()
    for ax, key in zip(axes, METRIC_KEYS, strict=False):
        vals = [e.metrics[key] for e in evaluations]
        cis = [(e.metrics_ci or {}).get(key) for e in evaluations]
        if all(v is None for v in vals):
            ax.text(0.5, 0.5, "undefined\n(the env reports no escapes,\nor none escaped)",
                    transform=ax.transAxes, ha="center", va="center", fontsize=9, color="0.4")
        for i, (v, ci) in enumerate(zip(vals, cis, strict=True)):
            if v is None:
                if not all(u is None for u in vals):
                    ax.text(x[i], 0.0, "n/a", ha="center", va="bottom", fontsize=9,
                            color="0.4")
                continue
            err = None
            if ci is not None:
                err = [[max(v - ci[0], 0.0)], [max(ci[1] - v, 0.0)]]
            ax.bar(x[i], v, width=0.7, color=colors[i], yerr=err, capsize=4,
                   error_kw={"elinewidth": 1.2, "ecolor": "0.15"})
        ax.set_title(METRIC_LABELS[key], fontsize=10)
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=25 if len(evaluations) > 2 else 0,
                           ha="right" if len(evaluations) > 2 else "center", fontsize=9)
        ax.set_xlim(-0.6, len(evaluations) - 0.4)
        ax.axhline(0.0, color="0.3", linewidth=0.8)
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
        ax.tick_params(axis="y", labelsize=9)
        if key in ("escape_rate", "stuck_fraction"):
            lo, hi = ax.get_ylim()
            ax.set_ylim(min(lo, 0.0), max(hi, 1.05) if key == "escape_rate" else hi)
        if all(v is None for v in vals):
            ax.set_yticks([])
    for ax in axes[len(METRIC_KEYS):]:
        ax.set_visible(False)
    if title is None:
        e = evaluations[0]
        level = f"{100 * e.ci_level:g}%" if e.metrics_ci is not None else ""
        title = (f"{e.env}: {e.episodes} episodes per policy, seeds {_seed_range(e)}"
                 + (f"; error bars: {level} bootstrap CI" if level else ""))
    fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    ext = os.path.splitext(path)[1].lstrip(".").lower() or "png"
    with atomic_path(path, f".{ext}") as tmp:
        fig.savefig(tmp, format=ext)


def _fmt(v) -> str:
    if v is None:
        return "-"
    return f"{v:.3f}"


_PAIR = re.compile(r"\[\n\s*(-?[0-9][0-9.eE+-]*),\n\s*(-?[0-9][0-9.eE+-]*)\n\s*\]")


def _dumps(doc) -> str:
    """Indented JSON with each ``[low, high]`` interval on one line (a JSON string never holds a
    raw newline, so only number pairs can match)."""
    return _PAIR.sub(r"[\1, \2]", json.dumps(doc, indent=2)) + "\n"


def _json_number(v):
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _json_interval(ci):
    if ci is None:
        return None
    low, high = _json_number(ci[0]), _json_number(ci[1])
    return None if low is None or high is None else [low, high]
