"""``mkv demo``: the main job end to end, on defaults (about 8-9 minutes on two cores).

It runs, in order, the same commands a user would (each printed, so every number in the report
can be reproduced by hand):

1. ``mkv record`` the scripted teacher: training runs and held-out runs on ``MKV-v1``;
2. ``mkv fit`` the shape-from-motion policy; ``mkv compare`` on the held-out runs (Figure 3);
   the feature-set and rank studies (:mod:`sfm_learn.evaluation.study`) on the same data;
3. ``mkv train-bc`` and ``mkv train-dagger`` with the same teacher budget; ``mkv train-ppo`` on
   the ``MKVJam-v1`` and ``MKV-v1`` rewards (one seed each, a reduced budget: the report says so
   and points to the sweep, ``sweeps/sample_efficiency.yml``, for 5 seeds and 1M steps);
4. ``mkv eval`` teacher, random, stand-still, SfM, BC, DAgger and PPO on the same seeds of
   ``MKVJam-v1`` and ``MKV-v1`` (worker processes, bootstrap confidence intervals, bar plots);
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

from sfm_common.cli import int_in_range
from sfm_common.files import atomic_write_text
from sfm_common.progress import progress
from sfm_learn.cli.common import CliError, episodes_type, positive_int, seed, timesteps_type

__all__ = ["add_arguments", "run", "Budget"]

TEACHER_ENV, JAM_ENV, WANDER_ENV = "MKV-v1", "MKVJam-v1", "MKV-v1"


@dataclass(frozen=True)
class Budget:
    """Seeds and sizes of one demo run."""

    train_sets: int = 5
    """Teacher training sets (different teacher seeds): every closed-loop SfM/BC number is a
    mean over them, with the range."""
    train_episodes: int = 20
    train_seed: int = 0
    train_seed_step: int = 100
    held_episodes: int = 5
    held_seed: int = 500
    episode_steps: int | None = None  # None: the env's default (600 steps = 60 s)
    bc_epochs: int = 30
    min_updates: int | None = None
    """At least this many minibatch updates per BC and DAgger fit (None: the commands' default,
    1,000: more epochs on small data)."""
    dagger_rounds: int = 4
    ppo_timesteps: int = 150_000
    """Per PPO run (one on each v1 reward); the sweep uses up to 1,000,000 and 5 seeds."""
    ppo_eval_episodes: int = 10
    jam_episodes: int = 100
    wander_episodes: int = 20
    eval_seed: int = 2_000_000
    """Evaluation env seeds: never used while developing the package (development used
    1000.., 10000.., 777000.. and the training/held-out seeds below 1000)."""
    study_jam_episodes: int = 50
    study_wander_episodes: int = 10
    rank_study_ranks: tuple = (1, 2, 4, 8, 16, 32)
    calib_seeds: int = 200
    workers: int = 2

    def train_seeds(self) -> list[int]:
        return [self.train_seed + k * self.train_seed_step for k in range(self.train_sets)]


QUICK = Budget(train_sets=2, train_episodes=3, held_episodes=1, episode_steps=120, bc_epochs=2,
               min_updates=50, dagger_rounds=2,
               ppo_timesteps=1024, ppo_eval_episodes=2, jam_episodes=6, wander_episodes=2,
               study_jam_episodes=4, study_wander_episodes=1, rank_study_ranks=(1, 8, 32),
               calib_seeds=2, workers=2)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", metavar="DIR",
                   help="output directory (default demo_out; created if missing)")
    p.add_argument("--quick", action="store_true",
                   help="tiny budgets: a smoke run in well under a minute")
    p.add_argument("--ppo-timesteps", type=timesteps_type, default=None, metavar="T",
                   help=f"budget of each PPO run in env steps (default {Budget.ppo_timesteps})")
    p.add_argument("--train-episodes", type=episodes_type, default=None, metavar="N",
                   help=f"teacher episodes per training set (default {Budget.train_episodes})")
    p.add_argument("--train-sets", type=int_in_range(1, 100), default=None, metavar="K",
                   help=f"teacher training sets, seeds S, S+100, ... (default "
                        f"{Budget.train_sets}); every learned-policy number is over all of them")
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
    if args.train_sets is not None:
        over["train_sets"] = args.train_sets
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
        return self._run(title, "mkv " + shlex.join(argv), lambda: main(argv, nested=True))

    def call(self, title: str, shown: str, fn) -> float:
        return self._run(title, shown, lambda: (fn(), 0)[1])

    def _run(self, title, shown, fn) -> float:
        self.i += 1
        print(f"\n[{self.i}/{self.total}] {title}\n$ {shown}", flush=True)
        t0 = time.perf_counter()
        code = fn()
        wall = time.perf_counter() - t0
        if code == 130:  # an mkv stage was interrupted (it printed nothing partial)
            raise KeyboardInterrupt
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
    st = _Stages(total=14 - bool(args.skip_calib), quiet=args.quiet)
    env_kwargs = [] if b.episode_steps is None else [
        "--env-kwargs", json.dumps({"max_episode_steps": b.episode_steps})]
    sets = range(b.train_sets)
    trains = [p("data", f"teacher_train_{k}.npz") for k in sets]
    held = p("data", "teacher_held_out.npz")
    sfm = [p("policies", f"sfm_{k}.npz") for k in sets]
    paper = [p("policies", f"sfm_paper_{k}.npz") for k in sets]
    bc = [p("policies", f"bc_{k}.zip") for k in sets]
    dagger = [p("policies", f"dagger_{k}.zip") for k in sets]
    ppo = {JAM_ENV: p("policies", "ppo_jam.zip"), WANDER_ENV: p("policies", "ppo_wander.zip")}

    def mkv(argv):
        from sfm_learn.cli.app import main

        return main(argv, nested=True)

    def each(fn):
        for k in sets:
            code = fn(k)
            if code == 130:  # the stage was interrupted (Ctrl-C): not a failure
                raise KeyboardInterrupt
            if code:
                raise CliError(f"stage failed for training set {k}")

    def record_sets():

        each(lambda k: mkv(["record", "--env", TEACHER_ENV, *env_kwargs, "--policy", "teacher",
                             "--episodes", str(b.train_episodes), "--seed",
                             str(b.train_seeds()[k]), "--out", trains[k], "--quiet"]))

    st.call(f"record {b.train_sets} teacher training sets",
            f"for S in {' '.join(map(str, b.train_seeds()))}: mkv record --env {TEACHER_ENV} "
            f"--policy teacher --episodes {b.train_episodes} --seed S "
            "--out data/teacher_train_K.npz", record_sets)
    st.mkv("record held-out teacher runs", [
        "record", "--env", TEACHER_ENV, *env_kwargs, "--policy", "teacher",
        "--episodes", b.held_episodes, "--seed", b.held_seed, "--out", held])

    def fit_sets():

        each(lambda k: mkv(["fit", trains[k], "--out", sfm[k]]
                            + (["--spectrum", p("sfm_spectrum.png")] if k == 0 else [])))
        each(lambda k: mkv(["fit", trains[k], "--preset", "paper", "--out", paper[k]]
                            + (["--spectrum", p("sfm_paper_spectrum.png")] if k == 0 else [])))

    st.call("fit the SfM policy (default and the paper's preset) on every training set",
            "mkv fit data/teacher_train_K.npz --out policies/sfm_K.npz; "
            "mkv fit data/teacher_train_K.npz --preset paper --out policies/sfm_paper_K.npz",
            fit_sets)
    st.mkv("Figure 3: teacher vs SfM on the held-out runs (free-running)", [
        "compare", held, sfm[0], "--plot", p("fig3.png"), "--json", p("compare.json")])
    st.mkv("the same for the paper's configuration", [
        "compare", held, paper[0], "--json", p("compare_paper.json")])
    studies = {}

    def run_studies():
        from mkv_env.dataset import load
        from sfm_learn.evaluation.study import FEATURE_CONFIGS, rank_configs, run_study
        from sfm_learn.reporting.plots import plot_rank_study
        from sfm_learn.reporting.tables import study_markdown

        data = [load(t) for t in trains]
        held_data = load(held)
        names = data[0].sensor_names
        jobs = {"features": list(FEATURE_CONFIGS),
                "rank_default": rank_configs(names, "default", b.rank_study_ranks),
                "rank_paper": rank_configs(names, "paper")}
        total = sum(len(c) for c in jobs.values()) * b.train_sets * (
            b.study_jam_episodes + b.study_wander_episodes)
        with progress(total, "studies", unit="ep",
                      enabled=False if args.quiet else None) as bar:
            for key, configs in jobs.items():
                studies[key] = run_study(data, held_data, configs,
                                         jam_episodes=b.study_jam_episodes,
                                         wander_episodes=b.study_wander_episodes,
                                         seed=b.eval_seed, workers=b.workers,
                                         on_episode=lambda: bar.update(1))
        for key in jobs:
            text = study_markdown(studies[key])
            atomic_write_text(p(f"{key}_study.md"), text + "\n")
            print(text)
        plot_rank_study({"default": studies["rank_default"], "paper": studies["rank_paper"]},
                        p("rank_study.png"),
                        title=f"Kept rank n: mean over {b.train_sets} training sets, "
                              f"[min, max] shaded; env seeds {b.eval_seed}..")

    st.call("studies: which features, the paper's configuration, the kept rank",
            "sfm_learn.evaluation.study.run_study (standalone: python scripts/sfm_study.py)",
            run_studies)

    updates = [] if b.min_updates is None else ["--min-updates", str(b.min_updates)]
    shown_updates = "".join(f" {a}" for a in updates)

    def bc_sets():

        each(lambda k: mkv(["train-bc", trains[k], "--out", bc[k], "--epochs",
                             str(b.bc_epochs), *updates, "--seed", str(b.train_seed),
                             "--held-out", "0", "--quiet"]))

    st.call("behaviour cloning on every training set",
            f"mkv train-bc data/teacher_train_K.npz --out policies/bc_K.zip --epochs "
            f"{b.bc_epochs}{shown_updates} --held-out 0", bc_sets)
    steps_per_set = b.train_episodes * (b.episode_steps or 600)

    def dagger_sets():

        each(lambda k: mkv(["train-dagger", "--env", TEACHER_ENV, *env_kwargs, "--steps",
                             str(steps_per_set), "--rounds", str(b.dagger_rounds), "--seed",
                             str(b.train_seeds()[k]), "--epochs", str(b.bc_epochs), *updates,
                             "--out", dagger[k], "--quiet"]))

    st.call("DAgger with the same teacher budget on every training seed",
            f"mkv train-dagger --env {TEACHER_ENV} --steps {steps_per_set} --rounds "
            f"{b.dagger_rounds} --seed S --epochs {b.bc_epochs}{shown_updates} "
            "--out policies/dagger_K.zip", dagger_sets)
    for env_id in (JAM_ENV, WANDER_ENV):
        st.mkv(f"PPO on the {env_id} reward (one seed, reduced budget)", [
            "train-ppo", "--env", env_id, "--timesteps", b.ppo_timesteps, "--out", ppo[env_id],
            "--seed", b.train_seed, "--eval-episodes", b.ppo_eval_episodes])

    learners = {"SfM": [f"sfm:{x}" for x in sfm], "SfM paper": [f"sfm:{x}" for x in paper],
                "BC": [f"bc:{x}" for x in bc], "DAgger": [f"dagger:{x}" for x in dagger]}
    ppo_specs = {"PPO jam": f"ppo:{ppo[JAM_ENV]}", "PPO wander": f"ppo:{ppo[WANDER_ENV]}"}
    evals = {}
    for env_id, episodes, key in ((JAM_ENV, b.jam_episodes, "jam"),
                                  (WANDER_ENV, b.wander_episodes, "wander")):
        shown = (f"mkv eval --env {env_id} --policy teacher --policy random --policy const:still "
                 "--policy sfm:policies/sfm_K.npz --policy sfm:policies/sfm_paper_K.npz --policy "
                 "bc:policies/bc_K.zip --policy dagger:policies/dagger_K.zip --policy "
                 "ppo:policies/ppo_jam.zip --policy ppo:policies/ppo_wander.zip --episodes "
                 f"{episodes} --seed {b.eval_seed} --workers {b.workers} (each K; pooled over K)")
        st.call(f"evaluate every policy on {env_id}", shown,
                lambda env_id=env_id, episodes=episodes, key=key: evals.__setitem__(
                    key, _evaluate(env_id, learners, ppo_specs, episodes, b,
                                   p("eval", key), args.quiet)))
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
                     quick=args.quick, studies=studies,
                     sweep=_reference_sweep(p("sample_efficiency.png")))

    st.call("learning-cost plot and report", "(mkv demo) report.md", write)
    print(f"\nfinished in {time.perf_counter() - t_start:.0f} s")


def _evaluate(env_id, learners: dict, ppo_specs: dict, episodes, b: Budget, stem: str,
              quiet: bool) -> dict:
    """Every policy on the same seeds; each learner's training sets pooled into one evaluation
    (records of set 0, then set 1, ...; each PPO run repeated per set so records pair up).

    Returns ``{"table": [Evaluation, ...], "per_set": {learner: [Evaluation per set]},
    "pooled": {name: Evaluation}, "teacher", "random", "still", "ppo": {name: Evaluation}}``."""
    from sfm_learn.evaluation import evaluate_many, evaluations_json
    from sfm_learn.evaluation.runner import pool
    from sfm_learn.reporting.plots import plot_evaluations
    from sfm_learn.reporting.tables import format_markdown

    specs = ["teacher", "random", "const:still", *[s for v in learners.values() for s in v],
             *ppo_specs.values()]
    names = ["teacher", "random", "stand still", *[f"{n} set {k}" for n, v in learners.items()
                                                   for k in range(len(v))], *ppo_specs]
    with progress(episodes * len(specs), f"eval {env_id}", unit="ep",
                  enabled=False if quiet else None) as bar:
        result = evaluate_many(env_id, specs, episodes, b.eval_seed, workers=b.workers,
                               on_episode=lambda *a: bar.update(1), policy_names=names)
    by = {e.policy: e for e in result}
    per_set = {n: [by[f"{n} set {k}"] for k in range(len(v))] for n, v in learners.items()}
    n_sets = b.train_sets
    pooled = {n: pool(evs, f"{n} ({n_sets} sets)") for n, evs in per_set.items()}
    for n in ppo_specs:
        pooled[n] = pool([by[n]] * n_sets, n)
    table = [by["teacher"], by["random"], by["stand still"], *[pooled[n] for n in learners],
             *[by[n] for n in ppo_specs]]
    atomic_write_text(stem + ".json", evaluations_json(table + [e for evs in per_set.values()
                                                                for e in evs]))
    plot_evaluations(table, stem + ".png",
                     title=f"{env_id}: {episodes} episodes per policy and training set, "
                           f"seeds {b.eval_seed}..{b.eval_seed + episodes - 1}")
    print(format_markdown(table))
    return {"table": table, "per_set": per_set, "pooled": pooled,
            "teacher": by["teacher"], "random": by["random"], "still": by["stand still"],
            "ppo": {n: by[n] for n in ppo_specs}}


def _reference_sweep(png: str) -> dict | None:
    """The bundled claims sweeps (20 training sets per teacher-step point, 10 PPO seeds; too long
    for the demo to rerun): their tables, paired verdicts (:mod:`sfm_learn.experiments.claims`)
    and curves drawn into ``png``. None when the bundle is missing."""
    from sfm_learn.experiments import claims
    from sfm_learn.experiments.summary import aggregate, plot_curves

    try:
        doc = claims.load_reference()
    except (OSError, ValueError):
        return None
    units = {n: ("env steps" if lr["kind"] == "ppo" else "teacher steps")
             for spec in doc["specs"] for n, lr in spec["learners"].items()}
    panels = [("MKVJam-v1", "escape_rate"), ("MKV-v1", "distance_m"),
              ("MKV-v1", "stuck_fraction")]
    plot_curves(aggregate(doc["rows"]), panels, png, units,
                "over many training sets (dots: each training set or PPO seed)", rows=doc["rows"])
    return {"about": doc.get("about", ""), "tables": claims.tables(doc["rows"]),
            "sentences": claims.claim_sentences(doc["rows"]), "plot": os.path.basename(png),
            "specs": [s.get("name", "") for s in doc["specs"]]}


def _calib(out: str, seeds: int, quiet: bool) -> dict:
    """``calib trials``: the paper's Trials 1-4; returns the offset-error summary per trial."""
    from calib.simulation.trials import trial_summary, write_report

    res = write_report(out, seeds=seeds, plots=True, progress=not quiet)
    summary = {t: trial_summary(res["trials"][t], t) for t in (2, 3, 4)}
    for t, s in summary.items():
        print(f"Trial {t}: median mean-abs offset error {s['centered']['median']:.3g} "
              f"(paper {s['paper_reported']:.3g})")
    return summary
