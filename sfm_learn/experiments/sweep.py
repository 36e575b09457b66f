"""Sweeps: many (learner, seed, budget) training runs, each evaluated, one JSON row per job.

A spec (JSON, or YAML with PyYAML installed) names what to run::

    name: sample-efficiency
    teacher_env: MKV-v1            # where the teacher's demonstrations are recorded
    env: [MKVJam-v1, MKV-v1]       # evaluation env(s)
    eval: {episodes: 50, seed: 5000000}   # optional banks: 3 (below)
    seeds: [0, 1, 2, 3, 4]
    learners:
      sfm: {}                      # kind = the name before the first "-" unless given
      sfm-paper: {preset: paper}
      bc: {epochs: 30}
      dagger: {rounds: 4}
      ppo-jam: {kind: ppo, env: MKVJam-v1, eval_env: [MKVJam-v1]}
      ppo-raw: {kind: ppo, env: MKVJam-v1, hyperparams: ppo_raw.yml}   # relative to SPEC
    budgets:                       # teacher steps (sfm, bc, dagger) or env steps (ppo)
      sfm: [1200, 3000, 12000]
      ppo-jam: [50000, 200000]

Jobs. For a teacher-step learner one job is (learner, seed, budget): record the teacher for
``budget`` steps (cached per (seed, budget) in ``DIR/data``; episodes of at most 600 steps on seeds
``10_000_000 + 10_000 * seed + i``, disjoint from every evaluation seed), fit or train, evaluate.
For PPO one job is (learner, seed): one training run with a checkpoint at each budget (PPO's
constant schedules make the checkpoint at ``b`` steps the same network a run of budget ``b``
would end with), each checkpoint evaluated; it writes one row per budget. A teacher-step budget
must leave its learner the rows its fit can identify (:func:`min_budget`: 35 for ``sfm``, 13
for ``sfm`` with ``preset: paper``, 33 for ``bc``, 32 * rounds + 1 for ``dagger``, on the MK-V
envs' 10 sensors); :func:`check_budgets` (``mkv sweep`` runs it before anything starts) refuses
a smaller one in one line.

Banks. ``eval: {..., banks: N}`` (1-20) evaluates every policy on N disjoint seed banks of
``episodes`` episodes each (bank k from ``seed + 100_000 * k``), and the rows then keep every
episode's outcome (``"episodes": {env: {"bank", "escaped", "distance_m"}}``), so the claims'
intervals cover training sets *and* evaluation episodes (:mod:`sfm_learn.experiments.crossed`).
Without ``banks``: one bank, and the rows keep only the metrics.

Rows. Each job writes ``DIR/rows/<learner>__s<seed>__b<budget>.json`` atomically when it has
finished (PPO: all its budgets at the end), so a killed sweep loses no finished job and a rerun
skips every job whose rows exist with ``"status": "ok"``. A job that raises writes a row with
``"status": "error"`` and the one-line error; the other jobs go on, and a rerun retries it.

Backends. ``local`` runs jobs in this process (``workers=1``) or in a ``ProcessPoolExecutor``;
``ray`` submits each job as a Ray task (:mod:`sfm_learn.experiments.ray_backend`). Jobs are
deterministic given the spec, so the backend changes only the wall time.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent import futures
from dataclasses import dataclass

from sfm_common.cli import caused_by_interrupt
from sfm_common.files import atomic_write_text

KINDS = ("sfm", "bc", "dagger", "ppo")
TEACHER_KINDS = ("sfm", "bc", "dagger")
TRAIN_SEED_BASE = 10_000_000
"""Demonstrations of training seed ``s`` use env seeds ``TRAIN_SEED_BASE + 10_000 s + i``."""
MAX_EPISODE_STEPS = 600
METRICS = ("escape_rate", "distance_m", "stuck_fraction", "mean_return")
MAX_BANKS = 20
"""Most evaluation banks a spec may name (``eval.banks``)."""
BANK_STRIDE = 100_000
"""Evaluation bank k of a spec starts ``BANK_STRIDE * k`` seeds after ``eval.seed`` (the most
episodes a bank may have, so banks never share a seed)."""


class SpecError(ValueError):
    """A sweep spec that cannot be run (one line)."""


@dataclass(frozen=True)
class Job:
    """One unit of work: a learner on one training seed and one budget (PPO: all budgets)."""

    learner: str
    seed: int
    budgets: tuple[int, ...]

    @property
    def names(self) -> list[str]:
        """Row file names this job writes (one per budget)."""
        return [row_name(self.learner, self.seed, b) for b in self.budgets]


def row_name(learner: str, seed: int, budget: int) -> str:
    return f"{learner}__s{seed}__b{budget}.json"


# ---------------------------------------------------------------------- spec
MAX_SPEC_BYTES = 1_000_000
"""A sweep spec is a page of settings: larger files are refused before they are parsed."""


def load_spec(path: str) -> dict:
    """Read and check a spec file (JSON, or YAML when the name ends in .yml/.yaml)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise SpecError(f"cannot read sweep spec {path}: no such file")
    if not os.path.isfile(path):  # a FIFO or a device would block or never end
        raise SpecError(f"sweep spec {path} is not a regular file")
    if os.path.getsize(path) > MAX_SPEC_BYTES:
        raise SpecError(f"sweep spec {path} is larger than {MAX_SPEC_BYTES:,} bytes")
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except OSError as e:
        raise SpecError(f"cannot read sweep spec {path}: {e.strerror}") from None
    except UnicodeDecodeError:
        raise SpecError(f"sweep spec {path} is not UTF-8 text") from None
    try:
        if path.endswith((".yml", ".yaml")):
            try:
                import yaml
            except ImportError:
                raise SpecError("a YAML sweep spec needs PyYAML: pip install pyyaml") from None
            try:
                doc = yaml.safe_load(text)
            except yaml.YAMLError as e:
                raise SpecError(f"sweep spec {path} is not valid YAML: "
                                f"{str(e).splitlines()[0]}") from None
        else:
            try:
                doc = json.loads(text)
            except json.JSONDecodeError as e:
                raise SpecError(f"sweep spec {path} is not valid JSON: {e}") from None
    except RecursionError:
        raise SpecError(f"sweep spec {path} is nested too deeply") from None
    spec = check_spec(doc)
    # a PPO learner's hyperparameter file is named relative to the spec file
    for lr in spec["learners"].values():
        hp = lr["options"].get("hyperparams")
        if isinstance(hp, str) and not os.path.isabs(hp):
            lr["options"]["hyperparams"] = os.path.normpath(
                os.path.join(os.path.dirname(os.path.abspath(path)), hp))
    return spec


#: Learner names: rows are named after them (no path parts, no hidden files, no "__").
LEARNER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")
MKV_IDS = ("MKV-v0", "MKVJam-v0", "MKV-v1", "MKVJam-v1")


def _is_int(v) -> bool:
    """A whole finite number (JSON/YAML may give 3.0; never inf, nan or a bool)."""
    return (not isinstance(v, bool) and isinstance(v, (int, float))
            and (isinstance(v, int) or (math.isfinite(v) and v == int(v))))


def _int_list(value, what, lo=0, hi=10**12) -> list[int]:
    if not isinstance(value, list) or not value:
        raise SpecError(f"{what} must be a non-empty list of integers")
    out = []
    for v in value:
        if not _is_int(v) or not lo <= int(v) <= hi:
            raise SpecError(f"{what} must hold integers in [{lo}, {hi}], got {v!r}")
        out.append(int(v))
    if len(set(out)) != len(out):
        raise SpecError(f"{what} has repeated values")
    return out


def _env_list(value, what) -> list[str]:
    envs = [value] if isinstance(value, str) else value
    if not isinstance(envs, list) or not envs or not all(isinstance(e, str) and e for e in envs):
        raise SpecError(f"{what} must be an env id or a non-empty list of env ids")
    for e in envs:
        if e not in MKV_IDS:
            raise SpecError(f"{what}: {e!r} is not an MK-V env id ({', '.join(MKV_IDS)})")
    return list(envs)


def check_spec(doc) -> dict:
    """Normalise a spec (a dict) and check every field; SpecError (one line) otherwise."""
    if not isinstance(doc, dict):
        raise SpecError("a sweep spec must be a mapping")
    known = {"name", "env", "teacher_env", "eval", "seeds", "learners", "budgets"}
    unknown = set(doc) - known
    if unknown:
        raise SpecError(f"unknown sweep spec key(s) {sorted(unknown)}; known: {sorted(known)}")
    for key in ("env", "learners", "seeds", "budgets"):
        if key not in doc:
            raise SpecError(f"sweep spec lacks {key!r}")
    name = doc.get("name", "sweep")
    if not isinstance(name, (str, int)) or isinstance(name, bool) or len(str(name)) > 200:
        raise SpecError("name must be a short string")
    spec = {"name": str(name), "env": _env_list(doc["env"], "env")}
    spec["teacher_env"] = _env_list(doc.get("teacher_env", spec["env"][0]), "teacher_env")[0]
    if not isinstance(doc.get("teacher_env", ""), str):
        raise SpecError("teacher_env must be an env id")
    ev = doc.get("eval", {})
    if not isinstance(ev, dict) or set(ev) - {"episodes", "seed", "banks"}:
        raise SpecError("eval must be a mapping with 'episodes', 'seed' and optionally 'banks'")
    spec["eval"] = {"episodes": _int_list([ev.get("episodes", 50)], "eval.episodes", 1,
                                          100_000)[0],
                    "seed": _int_list([ev.get("seed", 5_000_000)], "eval.seed", 0,
                                      2**62)[0]}
    if "banks" in ev:  # absent: one bank, rows as before
        spec["eval"]["banks"] = _int_list([ev["banks"]], "eval.banks", 1, MAX_BANKS)[0]
    spec["seeds"] = _int_list(doc["seeds"], "seeds", 0, 99_999)
    if not isinstance(doc["learners"], dict) or not doc["learners"]:
        raise SpecError("learners must map names to options")
    if not isinstance(doc["budgets"], dict):
        raise SpecError("budgets must map learner names to lists of steps")
    learners = {}
    for name, opts in doc["learners"].items():
        opts = dict(opts or {}) if isinstance(opts, dict) or opts is None else None
        if not isinstance(name, str) or not LEARNER_NAME.fullmatch(name) or "__" in name:
            raise SpecError(f"learner {name!r}: names are letters, digits, '-' and '_' "
                            "(starting with a letter or digit, no '__')")
        if opts is None:
            raise SpecError(f"learner {name!r}: options must be a mapping")
        kind = opts.pop("kind", name.split("-")[0])
        if kind not in KINDS:
            raise SpecError(f"learner {name!r}: unknown kind {kind!r}; known: {', '.join(KINDS)}")
        allowed = {"sfm": {"preset", "min_support"}, "bc": {"epochs", "min_updates"},
                   "dagger": {"rounds", "epochs", "min_updates"},
                   "ppo": {"env", "hyperparams", "eval_env"}}[kind] | {"eval_env"}
        if set(opts) - allowed:
            raise SpecError(f"learner {name!r} ({kind}): unknown option(s) "
                            f"{sorted(set(opts) - allowed)}; known: {sorted(allowed)}")
        if "hyperparams" in opts and not (isinstance(opts["hyperparams"], str)
                                          and opts["hyperparams"]):
            raise SpecError(f"learner {name!r}: hyperparams must be a file name")
        for key, lo, hi in (("epochs", 1, 100_000), ("rounds", 1, 1_000),
                            ("min_updates", 0, 10_000_000), ("min_support", 0, 10_000_000)):
            if key in opts and not (_is_int(opts[key]) and lo <= opts[key] <= hi):
                raise SpecError(f"learner {name!r}: {key} must be an integer in [{lo}, {hi}], "
                                f"got {opts[key]!r}")
            if key in opts:
                opts[key] = int(opts[key])
        if "preset" in opts and opts["preset"] not in ("default", "paper", "ols"):
            raise SpecError(f"learner {name!r}: preset must be 'default', 'paper' or 'ols', "
                            f"got {opts['preset']!r}")
        if "env" in opts:
            if not isinstance(opts["env"], str):
                raise SpecError(f"learner {name!r}: env must be one env id")
            opts["env"] = _env_list(opts["env"], f"{name}.env")[0]
        if "eval_env" in opts:
            opts["eval_env"] = _env_list(opts["eval_env"], f"{name}.eval_env")
        if kind == "ppo":
            opts.setdefault("env", spec["env"][0])
        if name not in doc["budgets"]:
            raise SpecError(f"budgets lacks learner {name!r}")
        hi = 10**10 if kind == "ppo" else 10_000_000
        budgets = _int_list(doc["budgets"][name], f"budgets.{name}", 2, hi)
        learners[name] = {"kind": kind, "options": opts, "budgets": sorted(budgets)}
    extra = set(doc["budgets"]) - set(learners)
    if extra:
        raise SpecError(f"budgets names unknown learner(s) {sorted(extra)}")
    spec["learners"] = learners
    return spec


def plan(spec: dict) -> list[Job]:
    """Every job of the spec, in a fixed order (learner, seed, budget)."""
    jobs = []
    for name, lr in spec["learners"].items():
        for s in spec["seeds"]:
            if lr["kind"] == "ppo":
                jobs.append(Job(name, s, tuple(lr["budgets"])))
            else:
                jobs.extend(Job(name, s, (b,)) for b in lr["budgets"])
    return jobs


def check_envs(spec: dict) -> None:
    """Make every env of the spec once (fail fast, one line), before any job runs."""
    from mkv_env.recorder import make_env

    envs = {spec["teacher_env"], *spec["env"]}
    for lr in spec["learners"].values():
        envs |= set(lr["options"].get("eval_env", []))
        if lr["kind"] == "ppo":
            envs.add(lr["options"]["env"])
    for env_id in sorted(envs):
        try:
            make_env(env_id).close()
        except ValueError as e:
            raise SpecError(str(e)) from None


def teacher_rows(budget: int) -> int:
    """Rows :func:`teacher_data` records for ``budget`` teacher steps: ``ceil(budget / 600)``
    episodes of ``budget // episodes`` steps, topped up with further episodes where an episode
    ended early (:func:`mkv_env.recorder.record`'s ``min_steps``)."""
    episodes = _teacher_episodes(budget)
    return episodes * (budget // episodes)


def _teacher_episodes(budget: int) -> int:
    return max(1, math.ceil(budget / MAX_EPISODE_STEPS))


def min_budget(spec: dict, name: str, sensor_names) -> tuple[int, str]:
    """``(smallest budget, why)`` of teacher-step learner ``name``: the fewest teacher steps
    whose training rows its fit can identify (``sfm``:
    :func:`~sfm_learn.eigenspace.policy.min_fit_rows`, ``bc``:
    :func:`~sfm_learn.baselines.bc.min_rows`, ``dagger``:
    :func:`~sfm_learn.baselines.dagger.min_steps`)."""
    lr = spec["learners"][name]
    kind, opts = lr["kind"], lr["options"]
    if kind == "dagger":
        from sfm_learn.baselines import bc, dagger

        n_features = bc.feature_spec(sensor_names, "default").n_features
        rounds = opts.get("rounds", 4)
        return dagger.min_steps(n_features, rounds), (
            f"{rounds} DAgger round{'s' if rounds != 1 else ''}: round 0's fit on {n_features} "
            f"features needs {bc.min_rows(n_features)} rows")
    if kind == "sfm":
        from sfm_learn.eigenspace.policy import min_fit_rows, preset

        fspec, _ = preset(opts.get("preset", "default"), sensor_names)
        rows = min_fit_rows(fspec)
        why = (f"SfM preset {opts.get('preset', 'default')}: {fspec.n_features} features + "
               f"{rows - 1 - fspec.n_features} command columns need {rows} rows")
    elif kind == "bc":
        from sfm_learn.baselines import bc

        n_features = bc.feature_spec(sensor_names, "default").n_features
        rows = bc.min_rows(n_features)
        why = f"behaviour cloning on {n_features} features needs {rows} rows"
    else:
        raise ValueError(f"{kind} budgets are env steps, not teacher steps")
    budget = rows
    while teacher_rows(budget) < rows:
        budget += 1
    return budget, why


def check_budgets(spec: dict) -> None:
    """Every teacher-step budget of the spec leaves its learner the rows it needs
    (:func:`min_budget`): SpecError (one line naming the budget and the minimum) before any
    job runs, instead of an error row per job midway through the sweep. The teacher env is made
    once to read its sensors. PPO budgets (env steps) are not checked here."""
    names = [n for n, lr in spec["learners"].items() if lr["kind"] in TEACHER_KINDS]
    if not names:
        return
    from mkv_env.recorder import make_env

    try:
        env = make_env(spec["teacher_env"])
    except ValueError as e:
        raise SpecError(str(e)) from None
    try:
        sensor_names = list(env.unwrapped.sensor_names)
    finally:
        env.close()
    for name in names:
        least, why = min_budget(spec, name, sensor_names)
        small = [b for b in spec["learners"][name]["budgets"] if b < least]
        if small:
            raise SpecError(f"budgets.{name}: {small[0]} teacher steps is too small; the "
                            f"smallest budget is {least} ({why})")


# ---------------------------------------------------------------------- one job
def teacher_data(spec: dict, seed: int, budget: int, out_dir: str):
    """The teacher's recording for (seed, budget), cached in ``out_dir/data``."""
    from mkv_env import dataset as ds
    from mkv_env.recorder import record

    path = os.path.join(out_dir, "data", f"teacher_s{seed}_b{budget}.npz")
    if os.path.exists(path):
        try:
            return ds.load(path)
        except ValueError:
            pass  # damaged (a crash outside our atomic writes): record again
    episodes = _teacher_episodes(budget)
    # min_steps: a teacher env whose episodes end early (a jam env's escape) is recorded on
    # further seeds of this training seed's range until the budget's rows are there, as
    # check_budgets promised (a wander env's episodes never end early: its data are unchanged)
    data = record(spec["teacher_env"], "teacher", episodes,
                  TRAIN_SEED_BASE + 10_000 * seed, max_steps=budget // episodes,
                  min_steps=teacher_rows(budget),
                  max_extra_episodes=max(0, 10_000 - episodes))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    ds.save(data, path)
    return data


def bank_seeds(ev: dict) -> list[int]:
    """The first evaluation seed of every bank of a spec's ``eval`` (bank k starts
    :data:`BANK_STRIDE` x k after ``seed``: disjoint for any allowed episode count)."""
    return [ev["seed"] + BANK_STRIDE * k for k in range(ev.get("banks", 1))]


def _evaluate(spec: dict, policy_spec: str, env_ids: Sequence[str]) -> tuple[dict, dict | None]:
    """(metrics per env over every bank's episodes, per-episode outcomes per env or None).
    The outcomes (``{"bank": [...], "escaped": [...] | None, "distance_m": [...]}``) are kept
    when the spec names ``banks``: claims then bootstrap over training sets and episodes."""
    from sfm_learn.evaluation import evaluate
    from sfm_learn.evaluation.records import aggregate

    out, episodes = {}, {}
    for env_id in env_ids:
        records, bank = [], []
        for k, first in enumerate(bank_seeds(spec["eval"])):
            got = evaluate(env_id, policy_spec, spec["eval"]["episodes"], first).records
            records += got
            bank += [k] * len(got)
        m = aggregate(records)
        out[env_id] = {k: m.get(k) for k in METRICS}
        esc = [r.escaped for r in records]
        episodes[env_id] = {"bank": bank,
                            "escaped": None if any(e is None for e in esc) else
                            [int(bool(e)) for e in esc],
                            "distance_m": [float(r.distance_m) for r in records]}
    return out, (episodes if "banks" in spec["eval"] else None)


def _min_updates(opts) -> dict:
    """``min_updates`` when the spec sets it; else the learners' own default (bc.MIN_UPDATES)."""
    return {"min_updates": opts["min_updates"]} if "min_updates" in opts else {}


def _train_teacher_learner(spec, job, kind, opts, budget, pol_dir) -> tuple[str, int]:
    """Train one teacher-step learner; returns (policy spec, teacher steps used)."""
    base = os.path.join(pol_dir, f"{job.learner}_s{job.seed}_b{budget}")
    if kind == "dagger":
        from sfm_learn.baselines import dagger

        policy, meta = dagger.train(spec["teacher_env"], budget, rounds=opts.get("rounds", 4),
                                    seed=TRAIN_SEED_BASE + 10_000 * job.seed,
                                    epochs=opts.get("epochs", 30), **_min_updates(opts))
        dagger.save(policy, meta, base + ".zip")
        return f"dagger:{base}.zip", meta["teacher_steps"]
    data = teacher_data(spec, job.seed, budget, os.path.dirname(pol_dir))
    if kind == "sfm":
        from sfm_learn.eigenspace.policy import fit_policy, preset

        fspec, kw = preset(opts.get("preset", "default"), data.metadata["sensor_names"])
        if "min_support" in opts:
            kw["min_support"] = opts["min_support"]
        fit_policy(data, fspec, **kw).save(base + ".npz")
        return f"sfm:{base}.npz", data.n_steps
    from sfm_learn.baselines import bc

    policy, meta = bc.train(data, epochs=opts.get("epochs", 30), seed=job.seed, held_out=0.0,
                            **_min_updates(opts))
    bc.save(policy, meta, base + ".zip")
    return f"bc:{base}.zip", data.n_steps


def run_job(spec: dict, job: Job, out_dir: str) -> list[dict]:
    """Run one job and write its rows; returns them. Exceptions become an error row."""
    lr = spec["learners"][job.learner]
    kind, opts = lr["kind"], lr["options"]
    eval_envs = opts.get("eval_env", spec["env"])
    pol_dir = os.path.join(out_dir, "policies")
    os.makedirs(pol_dir, exist_ok=True)
    t0 = time.perf_counter()
    base_row = {"learner": job.learner, "kind": kind, "seed": job.seed,
                "budget_unit": "env_steps" if kind == "ppo" else "teacher_steps"}
    rows = []
    try:
        if kind == "ppo":
            rows = _run_ppo(spec, job, opts, eval_envs, pol_dir, base_row, t0)
        else:
            budget = job.budgets[0]
            policy_spec, used = _train_teacher_learner(spec, job, kind, opts, budget, pol_dir)
            train_s = time.perf_counter() - t0
            metrics, episodes = _evaluate(spec, policy_spec, eval_envs)
            rows = [{**base_row, "budget": budget, "steps": int(used), "status": "ok",
                     "policy": policy_spec, "metrics": metrics, "train_s": round(train_s, 3),
                     "wall_s": round(time.perf_counter() - t0, 3)}]
            if episodes is not None:
                rows[0]["episodes"] = episodes
    except KeyboardInterrupt:
        raise
    except Exception as e:  # noqa: BLE001 - a job's failure is data, not a crash of the sweep
        if caused_by_interrupt(e):  # a Ctrl-C Python wrapped (an extension's import): no row
            raise KeyboardInterrupt from e
        msg = (str(e).strip().splitlines() or [type(e).__name__])[0]
        rows = [{**base_row, "budget": b, "status": "error",
                 "error": f"{type(e).__name__}: {msg}",
                 "where": traceback.format_exc(limit=-1).strip().splitlines()[-3:],
                 "wall_s": round(time.perf_counter() - t0, 3)} for b in job.budgets]
    for row, name in zip(rows, job.names, strict=True):
        write_row(out_dir, name, row)
    return rows


def _run_ppo(spec, job, opts, eval_envs, pol_dir, base_row, t0) -> list[dict]:
    from sfm_learn.baselines import ppo

    hp = ppo.load_hyperparameters(opts["env"], opts.get("hyperparams"))
    n_envs, observation = hp.pop("n_envs"), hp.pop("observation")
    hp.pop("n_timesteps")
    ckpt = os.path.join(pol_dir, f"{job.learner}_s{job.seed}")
    os.makedirs(ckpt, exist_ok=True)
    _, meta = ppo.train(opts["env"], max(job.budgets), seed=job.seed, n_envs=n_envs,
                        hyperparameters=hp, observation=observation, eval_at=job.budgets,
                        eval_episodes=1, eval_seed=spec["eval"]["seed"], checkpoint_dir=ckpt)
    train_s = time.perf_counter() - t0
    rows = []
    for b in job.budgets:
        # the first checkpoint at or after b env steps (SB3 finishes whole rollouts)
        point = next(p for p in meta["learning_curve"] if p["env_steps"] >= b)
        path = os.path.join(ckpt, f"ppo_{point['env_steps']:08d}.zip")
        metrics, episodes = _evaluate(spec, f"ppo:{path}", eval_envs)
        rows.append({**base_row, "budget": b, "steps": point["env_steps"], "status": "ok",
                     "policy": f"ppo:{path}", "metrics": metrics,
                     "train_s": round(train_s, 3), "ppo_train_wall_s": point["wall_s"],
                     "wall_s": round(time.perf_counter() - t0, 3)})
        if episodes is not None:
            rows[-1]["episodes"] = episodes
    return rows


def write_row(out_dir: str, name: str, row: dict) -> None:
    os.makedirs(os.path.join(out_dir, "rows"), exist_ok=True)
    atomic_write_text(os.path.join(out_dir, "rows", name),
                      json.dumps(row, indent=1, sort_keys=True, allow_nan=False) + "\n")


def _episodes_ok(episodes, metrics) -> bool:
    """A row's per-episode outcomes (:func:`_evaluate`): for each evaluated env, equally long
    lists of bank numbers, escapes (0/1, or None for an env without escapes) and distances."""
    if not isinstance(episodes, dict) or set(episodes) - set(metrics):
        return False
    for e in episodes.values():
        if not isinstance(e, dict) or set(e) != {"bank", "escaped", "distance_m"}:
            return False
        bank, esc, dist = e["bank"], e["escaped"], e["distance_m"]
        if not (isinstance(bank, list) and bank and isinstance(dist, list)
                and len(dist) == len(bank) and (esc is None or (isinstance(esc, list)
                                                                 and len(esc) == len(bank)))):
            return False
        if not all(_is_int(b) and 0 <= b < MAX_BANKS for b in bank):
            return False
        if esc is not None and not all(_is_int(x) and x in (0, 1) for x in esc):
            return False
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                   for x in dist):
            return False
    return True


def row_problem(row) -> str | None:
    """Why a row cannot be used (None for a good one): the fields the summary and resume read."""
    if not isinstance(row, dict):
        return "not a JSON object"
    if not isinstance(row.get("learner"), str) or not _is_int(row.get("seed")) \
            or not _is_int(row.get("budget")):
        return "no learner, seed or budget"
    if row.get("status") == "ok":
        m = row.get("metrics")
        if not isinstance(m, dict) or not all(
                isinstance(v, dict) and all(x is None or (isinstance(x, (int, float))
                                                         and not isinstance(x, bool)
                                                         and math.isfinite(x))
                                            for x in v.values())
                for v in m.values()):
            return "status ok without a mapping of finite metrics"
        if "steps" in row and not _is_int(row["steps"]):
            return "steps is not an integer"
        if "episodes" in row and not _episodes_ok(row["episodes"], m):
            return "episodes is not per-env lists of banks, escapes (0/1) and finite distances"
    elif row.get("status") != "error":
        return f"status {row.get('status')!r} is neither 'ok' nor 'error'"
    return None


def read_rows(out_dir: str, damaged: list | None = None) -> list[dict]:
    """Every usable row in ``out_dir/rows``. Rows that cannot be read or used are left out and,
    when ``damaged`` is a list, reported in it as ``(file name, reason)``; the hidden temporary
    files of a write that a kill interrupted are skipped silently."""
    d = os.path.join(out_dir, "rows")
    rows = []
    for name in sorted(os.listdir(d)) if os.path.isdir(d) else []:
        if not name.endswith(".json") or name.startswith("."):
            continue
        path = os.path.join(d, name)
        why = None
        if not os.path.isfile(path):
            why = "not a regular file"
        else:
            try:
                with open(path, encoding="utf-8") as f:
                    row = json.load(f)
            except (OSError, ValueError, RecursionError) as e:
                why = f"unreadable ({type(e).__name__})"
            else:
                why = row_problem(row)
        if why is not None:
            if damaged is not None:
                damaged.append((name, why))
            continue
        row["_file"] = name
        rows.append(row)
    return rows


def pending(spec: dict, out_dir: str) -> list[Job]:
    """Jobs whose rows are not all present with status ok."""
    done = {r["_file"] for r in read_rows(out_dir) if r.get("status") == "ok"}
    return [j for j in plan(spec) if not all(n in done for n in j.names)]


# ---------------------------------------------------------------------- the sweep
def _job_entry(spec, job, out_dir):
    import mkv_env  # noqa: F401  (a fresh worker registers the ids)
    import sfm_learn  # noqa: F401  (and the policy specs)

    return run_job(spec, job, out_dir)


def run_sweep(spec: dict, out_dir: str, *, backend: str = "local", workers: int = 1,
              address: str | None = None,
              on_job: Callable[[Job, list[dict]], None] | None = None) -> dict:
    """Run every pending job of ``spec`` into ``out_dir``; returns counts
    ``{"jobs", "skipped", "ok", "error"}``. ``on_job(job, rows)`` after each finished job."""
    os.makedirs(out_dir, exist_ok=True)
    rows_dir = os.path.join(out_dir, "rows")
    for name in os.listdir(rows_dir) if os.path.isdir(rows_dir) else []:
        if name.startswith(".tmp-"):   # a write a kill interrupted in an earlier run
            os.unlink(os.path.join(rows_dir, name))
    atomic_write_text(os.path.join(out_dir, "spec.json"),
                      json.dumps(spec, indent=1, sort_keys=True) + "\n")
    # longest first (PPO runs), so no long job starts last while the other workers idle
    todo = sorted(pending(spec, out_dir),
                  key=lambda j: spec["learners"][j.learner]["kind"] != "ppo")
    counts = {"jobs": len(plan(spec)), "skipped": len(plan(spec)) - len(todo), "ok": 0,
              "error": 0}

    def done(job, rows):
        bad = any(r.get("status") != "ok" for r in rows)
        counts["error" if bad else "ok"] += 1
        if on_job is not None:
            on_job(job, rows)

    if backend == "ray":
        from sfm_learn.experiments import ray_backend

        def lost(job, error):
            rows = [{"learner": job.learner, "kind": spec["learners"][job.learner]["kind"],
                     "seed": job.seed, "budget": b, "status": "error", "error": error}
                    for b in job.budgets]
            for row, name in zip(rows, job.names, strict=True):
                write_row(out_dir, name, row)
            return rows

        ray_backend.run(_job_entry, spec, todo, out_dir, workers=workers, address=address,
                        on_done=done, on_lost=lost)
    elif backend != "local":
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    elif workers <= 1:
        for job in todo:
            done(job, _job_entry(spec, job, out_dir))
    else:
        import multiprocessing as mp

        from sfm_common.workers import children_ignore_sigint, die_with
        from sfm_learn.evaluation.runner import default_start_method

        ctx = mp.get_context(default_start_method())
        with futures.ProcessPoolExecutor(workers, mp_context=ctx, initializer=die_with,
                                         initargs=(os.getpid(),)) as pool:
            with children_ignore_sigint(ctx):  # the workers start at the submits
                futs = {pool.submit(_job_entry, spec, job, out_dir): job for job in todo}
            try:
                for fut in futures.as_completed(futs):
                    done(futs[fut], fut.result())
            except BaseException:
                for f in futs:
                    f.cancel()
                raise
    return counts


__all__ = ["Job", "SpecError", "check_budgets", "check_envs", "check_spec", "load_spec",
           "min_budget", "pending", "plan", "read_rows", "row_name", "run_job", "run_sweep",
           "teacher_data", "teacher_rows"]
