"""``mkv sweep --backend ray``: every sweep job as one Ray core task.

A job is one plain call (record, fit or train, evaluate, write its rows), so Ray core tasks fit
it directly: no trials to schedule adaptively (Ray Tune's job), and the task runs exactly the code
the local backend runs, which is why the rows are the same on either backend. A job's own failure
is already an error row (written by the job). A task whose worker or node dies (a node lost from
the cluster, out of memory) is run again by Ray, up to ``TASK_RETRIES`` times, elsewhere in the
cluster: a job is idempotent (its rows and cached data are written atomically, whole), so the
sweep still ends with every row once and the same rows as a local run; a task that dies every
time is written as an error row here, so the sweep goes on and a rerun retries it. Ctrl-C
cancels the tasks still running; rows of finished jobs stay.
"""

from __future__ import annotations

#: How often Ray reruns a job whose worker or node died (not a job's own exception).
TASK_RETRIES = 3


def run(job_fn, spec: dict, jobs, out_dir: str, *, workers: int = 1,
        address: str | None = None, on_done=None, on_lost=None) -> None:
    """Run ``job_fn(spec, job, out_dir)`` for every job as a Ray task (1 CPU each);
    ``on_done(job, rows)`` as each finishes; a task that died is handed to
    ``on_lost(job, error_text) -> rows`` (the sweep writes error rows)."""
    from sfm_learn.evaluation.ray_eval import init_ray

    ray = init_ray(address, workers)
    task = ray.remote(num_cpus=1, max_retries=TASK_RETRIES, retry_exceptions=False)(job_fn)
    refs = {task.remote(spec, job, out_dir): job for job in jobs}
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=0.5)
            for ref in done:
                job = refs[ref]
                try:
                    rows = ray.get(ref)
                except (ray.exceptions.RayError, OSError) as e:
                    text = (str(e).strip().splitlines() or [type(e).__name__])[0]
                    rows = on_lost(job, f"{type(e).__name__}: {text}") if on_lost else []
                if on_done is not None:
                    on_done(job, rows)
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise


__all__ = ["run"]
