"""``mkv sweep``: run a sweep spec (learners x seeds x budgets), resumable; or summarise one.

::

    mkv sweep SPEC --out DIR [--backend local|ray] [--workers N] [--address ADDR] [--quiet]
    mkv sweep --summary DIR [--plot curves.png]

Every job writes its row(s) into ``DIR/rows`` when it finishes; rerunning the same command skips
finished jobs (a killed sweep loses only the jobs that were running) and retries failed ones. A
failing job is reported with its error and does not stop the others (exit status 1 at the end).
See :mod:`sfm_learn.experiments.sweep` for the spec and ``sweeps/sample_efficiency.yml`` for the
sweep behind the README's curves.
"""

from __future__ import annotations

import argparse
import json
import os

from sfm_learn.cli.common import (
    CliError,
    add_quiet_argument,
    check_outputs,
    check_png_path,
    int_in_range,
    one_line,
)

workers_type = int_in_range(1, 256)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", nargs="?", metavar="SPEC", help="sweep spec (.json, .yml/.yaml)")
    p.add_argument("--out", metavar="DIR", help="sweep directory (rows/, data/, policies/)")
    p.add_argument("--backend", choices=("local", "ray"), default="local",
                   help="local: this machine (default); ray: Ray tasks")
    p.add_argument("--workers", type=workers_type, default=1, metavar="N",
                   help="jobs at once (local: processes; ray: tasks in flight); default 1")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="Ray cluster address (default: start Ray locally)")
    p.add_argument("--summary", metavar="DIR", default=None,
                   help="print the tables of a sweep directory and draw its curves")
    p.add_argument("--plot", metavar="PNG", default=None,
                   help="with --summary: where to draw the curves (default DIR/curves.png)")
    add_quiet_argument(p)


def _summary(d: str, plot: str | None) -> int:
    from sfm_learn.experiments.summary import aggregate, markdown_table, plot_curves
    from sfm_learn.experiments.sweep import read_rows

    spec_path = os.path.join(d, "spec.json")
    if not os.path.isfile(spec_path):
        raise CliError(f"{d} is not a sweep directory (no spec.json)")
    try:
        with open(spec_path, encoding="utf-8") as f:
            spec = json.load(f)
        units = {n: ("env steps" if lr["kind"] == "ppo" else "teacher steps")
                 for n, lr in spec["learners"].items()}
        envs = list(spec["env"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CliError(f"{spec_path} is damaged: {one_line(e)}") from None
    if plot is not None:  # never onto the sweep's own files or the user's spec
        check_png_path(plot, "--plot")
        inputs = [spec_path] + [os.path.join(d, sub, n) for sub in ("rows", "data", "policies")
                                if os.path.isdir(os.path.join(d, sub))
                                for n in os.listdir(os.path.join(d, sub))]
        check_outputs(inputs, [plot])
    damaged: list = []
    rows = read_rows(d, damaged)
    agg = aggregate(rows)
    for name, why in damaged:
        print(f"damaged row {name}: {why} (left out; a resumed sweep runs its job again)")
    metrics = [("escape_rate", "MKVJam"), ("distance_m", "MKV-"), ("stuck_fraction", "MKV-"),
               ("mean_return", "")]
    panels = []
    for env_id in envs:
        for metric, prefix in metrics:
            if env_id.startswith(prefix) and any(k[1] == env_id and k[2] == metric
                                                 for k in agg["curves"]):
                print(markdown_table(agg, env_id, metric, units))
                if metric != "mean_return":
                    panels.append((env_id, metric))
    for r in agg["errors"]:
        print(f"error: {r.get('learner')} seed {r.get('seed')} budget {r.get('budget')}: "
              f"{r.get('error')}")
    if panels:
        path = plot or os.path.join(d, "curves.png")
        try:
            plot_curves(agg, panels, path, units, spec.get("name", ""), rows=rows)
        except ImportError:
            print("(matplotlib not installed: no plot)")
        else:
            print(f"wrote {path}")
    return 0


def run(args) -> int:
    if args.summary:
        if args.spec or args.out:
            raise CliError("--summary DIR takes no SPEC or --out")
        return _summary(args.summary, args.plot)
    if not args.spec or not args.out:
        raise CliError("give SPEC and --out DIR (or --summary DIR)")
    if args.address is not None and args.backend != "ray":
        raise CliError("--address needs --backend ray")
    if args.address is not None and not args.address.strip():
        raise CliError("--address is empty; give HOST:PORT of a Ray cluster or leave it out")
    from sfm_learn.experiments.sweep import (
        check_budgets,
        check_envs,
        load_spec,
        pending,
        plan,
        read_rows,
        run_sweep,
    )

    try:
        spec = load_spec(args.spec)
        check_envs(spec)
        check_budgets(spec)  # every budget leaves its learner the rows it needs
    except ValueError as e:
        raise CliError(one_line(e)) from None
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise CliError(f"--out {args.out} exists and is not a directory")
    if args.backend == "ray":  # reach the cluster before anything is written into --out
        from sfm_learn.evaluation.ray_eval import check_workers_fit, init_ray

        try:
            check_workers_fit(init_ray(args.address, args.workers), args.workers)
        except ValueError as e:
            raise CliError(one_line(e)) from None
    old = os.path.join(args.out, "spec.json")
    if os.path.isfile(old):
        try:
            with open(old, encoding="utf-8") as f:
                same = json.load(f) == json.loads(json.dumps(spec))
        except (OSError, ValueError):
            same = False
        if not same:
            raise CliError(f"{args.out} holds a sweep of another spec; use a new --out")
    from sfm_learn.cli.common import progress_for

    damaged: list = []
    read_rows(args.out, damaged)
    for name, why in damaged:
        print(f"damaged row {name}: {why} (its job runs again)")
    n_jobs = len(plan(spec))
    with progress_for(args, n_jobs, f"sweep {spec['name']}", unit="job") as bar:
        bar.update(n_jobs - len(pending(spec, args.out)))   # finished in an earlier run
        def on_job(job, rows):
            bar.update(1)
            for r in rows:
                if r.get("status") != "ok":
                    bar.write(f"job {job.learner} seed {job.seed} budget {r['budget']} failed: "
                              f"{r['error']}")
        try:
            counts = run_sweep(spec, args.out, backend=args.backend, workers=args.workers,
                               address=args.address, on_job=on_job)
        except ValueError as e:
            raise CliError(one_line(e)) from None
    print(f"{counts['jobs']} jobs: {counts['skipped']} already done, {counts['ok']} ran, "
          f"{counts['error']} failed; rows in {os.path.join(args.out, 'rows')}")
    print(f"summary: mkv sweep --summary {args.out}")
    return 1 if counts["error"] else 0
