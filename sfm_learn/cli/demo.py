"""``mkv demo``: the main job end to end, on defaults (about 3-4 minutes on two cores).

It runs, in order, the same commands a user would (each printed, so every number in the report
can be reproduced by hand):

1. ``mkv record`` the scripted teacher: training runs and held-out runs on ``MKV-v0``;
2. ``mkv fit`` the shape-from-motion policy; ``mkv compare`` on the held-out runs (Figure 3);
   the feature-set study (:mod:`sfm_learn.evaluation.study`) on the same data;
3. ``mkv train-bc`` on the same training runs; ``mkv train-ppo`` on the ``MKV-v0`` reward;
4. ``mkv eval`` teacher, random, SfM, BC and PPO on the same seeds of ``MKVJam-v0`` and ``MKV-v0``
   (worker processes, bootstrap confidence intervals, bar plots);
5. ``calib trials`` (the paper's force-sensor simulation trials);

and writes ``DIR/report.md`` with the tables, the plots (PNG, beside it) and conclusions drawn
from the numbers (including where a baseline beats the SfM policy, with the paired difference
and its interval). ``--quick`` shrinks every budget (seconds instead of minutes; for tests and a
first look; its numbers mean little).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import tempfile
import time
from dataclasses import dataclass

from sfm_common.files import atomic_write_text
from sfm_common.progress import progress
from sfm_learn.cli.common import CliError, episodes_type, positive_int, seed, timesteps_type

__all__ = ["add_arguments", "run", "Budget"]


@dataclass(frozen=True)
class Budget:
    """Seeds and sizes of one demo run."""

    train_episodes: int = 20
    train_seed: int = 0
    held_episodes: int = 5
    held_seed: int = 500
    episode_steps: int | None = None  # None: the env's default (600 steps = 60 s)
    bc_epochs: int = 30
    ppo_timesteps: int = 200_000
    ppo_eval_episodes: int = 10
    jam_episodes: int = 100
    wander_episodes: int = 20
    eval_seed: int = 1000
    calib_seeds: int = 200
    workers: int = 2


QUICK = Budget(train_episodes=3, held_episodes=1, episode_steps=120, bc_epochs=2,
               ppo_timesteps=1024, ppo_eval_episodes=2, jam_episodes=6, wander_episodes=2,
               calib_seeds=2, workers=2)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", metavar="DIR",
                   help="output directory (default demo_out; created if missing)")
    p.add_argument("--quick", action="store_true",
                   help="tiny budgets: a smoke run in well under a minute")
    p.add_argument("--ppo-timesteps", type=timesteps_type, default=None, metavar="T",
                   help=f"PPO budget in env steps (default {Budget.ppo_timesteps})")
    p.add_argument("--train-episodes", type=episodes_type, default=None, metavar="N",
                   help=f"teacher training episodes (default {Budget.train_episodes})")
    p.add_argument("--workers", type=positive_int, default=None, metavar="N",
                   help="evaluation worker processes (default 2)")
    p.add_argument("--seed", type=seed, default=0, metavar="S",
                   help="seed of the training runs, BC and PPO (default 0)")
    p.add_argument("--skip-calib", action="store_true", help="do not run calib trials")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _budget(args) -> Budget:
    from dataclasses import replace

    b = QUICK if args.quick else Budget()
    over = {"train_seed": args.seed}
    if args.ppo_timesteps is not None:
        over["ppo_timesteps"] = args.ppo_timesteps
    if args.train_episodes is not None:
        over["train_episodes"] = args.train_episodes
    if args.workers is not None:
        over["workers"] = args.workers
    else:
        over["workers"] = max(1, min(b.workers, os.cpu_count() or 1))
    return replace(b, **over)


class _Stages:
    """Runs the demo's commands, printing each and timing it."""

    def __init__(self, total: int, quiet: bool):
        self.total, self.quiet, self.i = total, quiet, 0
        self.log: list[tuple[str, str, float]] = []

    def mkv(self, title: str, argv: list[str]) -> float:
        from sfm_learn.cli.app import main

        argv = [str(a) for a in argv]
        if self.quiet and "--quiet" not in argv and argv[0] in ("record", "train-ppo",
                                                                 "train-bc"):
            argv.append("--quiet")
        return self._run(title, "mkv " + shlex.join(argv), lambda: main(argv))

    def call(self, title: str, shown: str, fn) -> float:
        return self._run(title, shown, lambda: (fn(), 0)[1])

    def _run(self, title, shown, fn) -> float:
        self.i += 1
        print(f"\n[{self.i}/{self.total}] {title}\n$ {shown}", flush=True)
        t0 = time.perf_counter()
        code = fn()
        wall = time.perf_counter() - t0
        if code:
            raise CliError(f"stage {self.i} ({title}) failed with exit status {code}")
        self.log.append((title, shown, wall))
        print(f"    done in {wall:.1f} s", flush=True)
        return wall


def run(args) -> int:
    """Build the whole output in a temporary sibling folder and swap it in only when complete:
    an interrupt or a failure leaves the previous output untouched and nothing partial."""
    final = os.path.realpath(args.out)
    if os.path.exists(final) and not os.path.isdir(final):
        raise CliError(f"--out {args.out} exists and is not a directory")
    parent = os.path.dirname(final)
    if not os.path.isdir(parent):
        raise CliError(f"--out {args.out}: directory {parent} does not exist")
    _check_extras()
    work = tempfile.mkdtemp(prefix=f".{os.path.basename(final)}.tmp-", dir=parent)
    try:
        _run(args, work, final)
        _swap_in(work, final)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    print(f"\nwrote {os.path.join(args.out, 'report.md')}")
    return 0


def _swap_in(work: str, final: str) -> None:
    """Replace ``final`` by the finished ``work`` folder (the old one is removed afterwards)."""
    old = None
    if os.path.exists(final):
        old = tempfile.mkdtemp(prefix=f".{os.path.basename(final)}.old-",
                               dir=os.path.dirname(final))
        os.rmdir(old)
        os.rename(final, old)
    try:
        os.rename(work, final)
    except BaseException:
        if old is not None:
            os.rename(old, final)
        raise
    os.chmod(final, 0o777 & ~_umask())
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _check_extras() -> None:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise CliError("mkv demo draws plots: it needs matplotlib "
                       "(pip install 'mkv-sfm[plots]')") from None
    try:
        import stable_baselines3  # noqa: F401
        import torch  # noqa: F401
    except ImportError:
        raise CliError("mkv demo trains the SB3 baselines: it needs torch and "
                       "stable-baselines3 (pip install 'mkv-sfm[baselines]')") from None


def _run(args, out: str, final: str) -> None:
    """Every stage, writing into ``out`` (the temporary folder); ``final`` is where it goes."""
    b = _budget(args)
    for sub in ("", "data", "policies", "eval"):
        os.makedirs(os.path.join(out, sub), exist_ok=True)

    def p(*parts):
        return os.path.join(out, *parts)

    t_start = time.perf_counter()
    st = _Stages(total=11 - bool(args.skip_calib), quiet=args.quiet)
    env_kwargs = [] if b.episode_steps is None else [
        "--env-kwargs", json.dumps({"max_episode_steps": b.episode_steps})]
    train, held = p("data", "teacher_train.npz"), p("data", "teacher_held_out.npz")
    sfm, bc, ppo = p("policies", "sfm.npz"), p("policies", "bc.zip"), p("policies", "ppo.zip")

    st.mkv("record the teacher's training runs", [
        "record", "--env", "MKV-v0", *env_kwargs, "--policy", "teacher",
        "--episodes", b.train_episodes, "--seed", b.train_seed, "--out", train])
    st.mkv("record held-out teacher runs", [
        "record", "--env", "MKV-v0", *env_kwargs, "--policy", "teacher",
        "--episodes", b.held_episodes, "--seed", b.held_seed, "--out", held])
    st.mkv("fit the shape-from-motion policy", [
        "fit", train, "--out", sfm, "--spectrum", p("sfm_spectrum.png")])
    st.mkv("Figure 3: teacher vs SfM on the held-out runs", [
        "compare", held, sfm, "--plot", p("fig3.png"), "--spectrum", p("sfm_spectrum.png"),
        "--json", p("compare.json")])
    study = []

    def run_study():
        from mkv_env.dataset import load
        from sfm_learn.evaluation.study import feature_study
        from sfm_learn.reporting.tables import study_markdown

        rows = feature_study([load(train)], load(held), jam_episodes=b.jam_episodes,
                             wander_episodes=b.wander_episodes, seed=b.eval_seed)
        study.extend(rows)
        text = study_markdown(rows)
        atomic_write_text(p("feature_study.md"), text + "\n")
        print(text)

    st.call("which features the SfM policy needs (feature-set study)",
            "sfm_learn.evaluation.study.feature_study on the data above "
            "(standalone: python scripts/sfm_feature_study.py)",
            run_study)
    st.mkv("behaviour cloning on the same demonstrations", [
        "train-bc", train, "--out", bc, "--epochs", b.bc_epochs, "--seed", b.train_seed,
        "--held-out", "0"])
    st.mkv("PPO on the MKV-v0 reward", [
        "train-ppo", "--env", "MKV-v0", "--timesteps", b.ppo_timesteps, "--out", ppo,
        "--seed", b.train_seed, "--eval-episodes", b.ppo_eval_episodes])

    policies = ["teacher", "random", f"sfm:{sfm}", f"bc:{bc}", f"ppo:{ppo}"]
    names = ["teacher", "random", "SfM", "BC", "PPO"]
    evals = {}
    for env_id, episodes, key in (("MKVJam-v0", b.jam_episodes, "jam"),
                                  ("MKV-v0", b.wander_episodes, "wander")):
        shown = ("mkv eval --env " + env_id + "".join(f" --policy {s}" for s in policies)
                 + f" --episodes {episodes} --seed {b.eval_seed} --workers {b.workers}"
                 + f" --json eval/{key}.json --plot eval/{key}.png")
        st.call(f"evaluate all policies on {env_id}", shown,
                lambda env_id=env_id, episodes=episodes, key=key: evals.__setitem__(
                    key, _evaluate(env_id, policies, names, episodes, b, p("eval", key),
                                   args.quiet)))
    if not args.skip_calib:
        calib = {}
        st.call("calibration: the paper's simulation trials",
                f"calib trials --out calib --seeds {b.calib_seeds}",
                lambda: calib.update(_calib(p("calib"), b.calib_seeds, args.quiet)))
    else:
        calib = None

    def write():
        from sfm_learn.reporting.report import write_report

        write_report(out, b, evals, calib, st.log, time.perf_counter() - t_start,
                     quick=args.quick, study=study)

    st.call("learning-cost plot and report", "(mkv demo) report.md", write)
    print(f"\nfinished in {time.perf_counter() - t_start:.0f} s")


def _evaluate(env_id, policies, names, episodes, b: Budget, stem: str, quiet: bool):
    from sfm_learn.evaluation import evaluate_many, evaluations_json
    from sfm_learn.reporting.plots import plot_evaluations
    from sfm_learn.reporting.tables import format_markdown

    total = episodes * len(policies)
    with progress(total, f"eval {env_id}", unit="ep", enabled=False if quiet else None) as bar:
        result = evaluate_many(env_id, policies, episodes, b.eval_seed, workers=b.workers,
                               on_episode=lambda *a: bar.update(1), policy_names=names)
    atomic_write_text(stem + ".json", evaluations_json(result))
    plot_evaluations(result, stem + ".png",
                     title=f"{env_id}: {episodes} episodes per policy, "
                           f"seeds {b.eval_seed}..{b.eval_seed + episodes - 1}")
    print(format_markdown(result))
    return result


def _calib(out: str, seeds: int, quiet: bool) -> dict:
    """``calib trials``: the paper's Trials 1-4; returns the offset-error summary per trial."""
    from calib.trials import trial_summary, write_report

    res = write_report(out, seeds=seeds, plots=True, progress=not quiet)
    summary = {t: trial_summary(res["trials"][t], t) for t in (2, 3, 4)}
    for t, s in summary.items():
        print(f"Trial {t}: median mean-abs offset error {s['centered']['median']:.3g} "
              f"(paper {s['paper_reported']:.3g})")
    return summary
