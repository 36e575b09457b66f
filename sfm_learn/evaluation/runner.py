"""Policy evaluation on seeded episodes, in this process or in worker processes.

Every policy (teacher, random, command script, SfM, PPO, BC, any SB3 model) is evaluated the same
way: episode ``i`` resets the env with seed ``seed + i``; the episode is recorded with
:mod:`mkv_env.recorder` (so metrics come from the same ground-truth ``info`` a dataset stores);
each episode becomes an :class:`~sfm_learn.evaluation.records.EpisodeRecord`. Records are plain,
picklable and independent of one another, so :func:`evaluate_many` runs several policies on the
same seeds, shares the seeds out to worker processes (:mod:`concurrent.futures`, forkserver
start) and bootstraps confidence intervals by resampling records
(:mod:`sfm_learn.evaluation.bootstrap`).

Same seeds, same numbers: each episode depends only on its env seed (the runners reset the env
with it and call ``policy.reset(seed=...)`` with a seed derived from it), each worker's unit of
work builds its own env and policy, and the bootstrap uses a fixed random stream. So the records,
the metrics and the confidence intervals are identical, byte for byte in the JSON, whatever the
number of workers and however the seeds are chunked. (A policy object without ``reset`` that
keeps state across episodes would break this; every spec policy has ``reset`` or no state.)
"""

from __future__ import annotations

import math
import os
import pickle
import queue
import signal
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent import futures

import numpy as np

from mkv_env.policies import describe
from mkv_env.recorder import record
from sfm_learn.evaluation.bootstrap import bootstrap_ci
from sfm_learn.evaluation.records import (
    CI_LEVEL,
    N_BOOT,
    EpisodeRecord,
    Evaluation,
    aggregate,
    episode_records,
)

__all__ = ["run_episodes", "evaluate", "evaluate_many", "plan_units", "default_start_method",
           "pool"]


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
    traceback is attached as a note."""
    tb = "".join(traceback.format_exception(type(e), e, e.__traceback__))
    try:
        out = pickle.loads(pickle.dumps(e))
    except Exception:
        out = RuntimeError(f"{type(e).__name__}: {e}")
    if hasattr(out, "add_note"):  # Python >= 3.11
        out.add_note(f"in an evaluation worker process:\n{tb}")
    return out


_PROGRESS_INTERVAL_S = 0.1
_progress_queue = None  # set in each worker process by _init_worker


def _init_worker(progress_queue, main_pid: int | None = None) -> None:
    """Runs once in every worker process."""
    global _progress_queue
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and stops us
    if main_pid is not None:
        from sfm_common.workers import die_with

        die_with(main_pid)  # a kill -9 of the main process ends us too
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # one process per core; no thread oversubscription
    _progress_queue = progress_queue


def _worker_unit(uid: int, env_id: str, env_kwargs: dict, spec: str, eval_seed: int, first: int,
                 count: int) -> list[EpisodeRecord]:
    """One unit of work in a worker process; finished episodes are posted to the progress queue
    as ``(uid, [(i, n_steps), ...])``, batched at most every 0.1 s."""
    import multiprocessing as mp

    pending: list[tuple[int, int]] = []
    last = [time.monotonic()]
    parent = mp.parent_process()

    def flush():
        if pending and _progress_queue is not None:
            _progress_queue.put((uid, pending[:]))
            pending.clear()

    def on_episode(i, n):
        pending.append((i, n))
        now = time.monotonic()
        if now - last[0] >= _PROGRESS_INTERVAL_S:
            last[0] = now
            flush()
            if parent is not None and not parent.is_alive():
                os._exit(1)  # orphaned: nobody will read our results

    try:
        records = _run_unit(env_id, env_kwargs, spec, eval_seed, first, count, on_episode)
    except BaseException as e:  # noqa: BLE001  (raised again in the parent)
        raise _portable_exception(e) from None
    flush()
    return records


def _stop_workers(pool: futures.ProcessPoolExecutor) -> None:
    """Cancel pending units and end the worker processes now (Ctrl-C, or an error elsewhere)."""
    terminate = getattr(pool, "terminate_workers", None)  # Python >= 3.14
    if terminate is not None:
        terminate()
        return
    # the processes must be read before shutdown(), which forgets them
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    for proc in procs:
        proc.join(timeout=5.0)
        if proc.is_alive():
            proc.kill()
            proc.join()


def _run_parallel(env_id, env_kwargs, specs, seed, units, workers, start_method, on_unit_episode):
    """Run ``units`` on ``workers`` processes; returns the records of each unit, by unit."""
    import multiprocessing as mp

    method = start_method or default_start_method()
    ctx = mp.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(["sfm_learn.evaluation.runner"])
    progress_q = ctx.Queue()

    expected = sum(count for _, _, count in units)
    reported = [0]

    def drain(wait_s: float = 0.0):
        """Deliver the progress messages that have arrived; with ``wait_s``, wait up to that
        long for the rest (a worker's last message can still be in its queue's feeder thread
        when the unit's result is already here)."""
        deadline = time.monotonic() + wait_s
        while reported[0] < expected:
            try:
                left = deadline - time.monotonic()
                uid, done = (progress_q.get(timeout=left) if left > 0
                             else progress_q.get_nowait())
            except queue.Empty:
                return
            for i, n in done:
                on_unit_episode(uid, i, n)
            reported[0] += len(done)

    from sfm_common.workers import children_ignore_sigint

    pool = futures.ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                       initializer=_init_worker,
                                       initargs=(progress_q, os.getpid()))
    results: dict[int, list[EpisodeRecord]] = {}
    try:
        with children_ignore_sigint(ctx):  # the workers start at the submits
            pending = {pool.submit(_worker_unit, uid, env_id, env_kwargs, specs[p], seed,
                                   seed + first, count): uid
                       for uid, (p, first, count) in enumerate(units)}
        while pending:
            done, _ = futures.wait(pending, timeout=0.1, return_when=futures.FIRST_COMPLETED)
            drain()
            for fut in done:
                uid = pending.pop(fut)
                try:
                    results[uid] = fut.result()
                except futures.process.BrokenProcessPool:
                    raise RuntimeError(
                        "an evaluation worker process died unexpectedly (killed, or out of "
                        "memory); a script that starts workers must guard its main code with "
                        "if __name__ == '__main__':") from None
        drain(wait_s=10.0)
        pool.shutdown(wait=True)
    except BaseException:
        _stop_workers(pool)
        raise
    finally:
        progress_q.cancel_join_thread()
        progress_q.close()
    return [results[uid] for uid in range(len(units))]


def evaluate_many(env_id: str, policies: Sequence, episodes: int, seed: int = 0,
                  env_kwargs: dict | None = None, *, workers: int = 1,
                  on_episode: Callable[[int, int, int], None] | None = None,
                  ci_level: float = CI_LEVEL, n_boot: int = N_BOOT,
                  start_method: str | None = None,
                  policy_names: Sequence[str] | None = None,
                  backend: str = "local", address: str | None = None) -> list[Evaluation]:
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
        ci_level, n_boot: bootstrap confidence intervals (:func:`bootstrap_ci`); ``n_boot=0``
            skips them (``metrics_ci`` is None).
        policy_names: names for reports (default: the spec, or the object's ``spec`` attribute).
        backend: ``"local"`` (processes on this machine) or ``"ray"`` (the same units as Ray
            tasks, :mod:`sfm_learn.evaluation.ray_eval`; spec strings only): identical results.
        address: with ``backend="ray"``, a Ray cluster address (default: start Ray locally with
            ``workers`` CPUs).

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
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    if backend == "ray" and not all(isinstance(p, str) for p in policies):
        raise ValueError("the ray backend takes policy spec strings, not objects")
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

    if backend == "ray":
        from sfm_learn.evaluation.ray_eval import run_units

        unit_records = run_units(_run_unit, env_id, env_kwargs, policies, seed, units,
                                 int(workers), address, unit_progress)
    elif workers == 1:
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
        ci = bootstrap_ci(recs, ci_level, n_boot, metrics) if n_boot else None
        out.append(Evaluation(env_id, name, episodes, seed, metrics, recs, dict(env_kwargs),
                              ci, ci_level, n_boot))
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


def pool(evaluations: Sequence[Evaluation], name: str) -> Evaluation:
    """One evaluation from several copies of a learner (one per training set) evaluated on the
    same env seeds: records concatenated (copy 0's episodes, then copy 1's, ...), metrics over all
    of them (the mean over copies, for per-episode means), bootstrap intervals resampling
    (copy, episode) pairs. Two pooled evaluations in the same order pair up for
    :func:`~sfm_learn.evaluation.bootstrap.paired_difference_ci`."""
    evaluations = list(evaluations)
    if not evaluations:
        raise ValueError("nothing to pool")
    first = evaluations[0]
    for e in evaluations[1:]:
        if (e.env, e.episodes, e.seed, e.env_kwargs) != (first.env, first.episodes, first.seed,
                                                          first.env_kwargs):
            raise ValueError("pooled evaluations must share env, episodes and seeds")
    records = [r for e in evaluations for r in e.records]
    metrics = aggregate(records)
    ci = bootstrap_ci(records, first.ci_level, first.n_boot, metrics) if first.n_boot else None
    return Evaluation(first.env, name, first.episodes, first.seed, metrics, records,
                      dict(first.env_kwargs), ci, first.ci_level, first.n_boot,
                      sum(e.training_sets for e in evaluations))
