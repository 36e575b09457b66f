"""The ``mkv demo`` report: ``DIR/report.md`` from the files and evaluations the demo produced.

Everything in the report is read from what the demo wrote (policy files and their metadata,
``compare.json``, the evaluations) or measured by it; the conclusions are computed from the
numbers with paired bootstrap intervals (:func:`sfm_learn.evaluation.paired_difference_ci`), so
they say what the run showed, including where a baseline beats the SfM policy.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import sys

import numpy as np

from sfm_common.files import atomic_write_text
from sfm_learn.evaluation.bootstrap import paired_difference_ci
from sfm_learn.reporting.tables import (
    METRIC_LABELS,
    format_cell,
    format_markdown,
    study_markdown,
)

__all__ = ["write_report", "conclusions", "HIGHER_IS_BETTER"]

#: Direction of "better" for each metric the conclusions compare.
HIGHER_IS_BETTER = {
    "escape_rate": True, "mean_escape_time_s": False, "distance_m": True,
    "stuck_fraction": False, "collisions_per_min": False, "mean_return": True,
}
#: (evaluation key, metric) pairs the conclusions compare.
COMPARED = [("jam", "escape_rate"), ("jam", "mean_escape_time_s"), ("wander", "distance_m"),
            ("wander", "stuck_fraction"), ("wander", "collisions_per_min"),
            ("wander", "mean_return")]
ENV_OF = {"jam": "MKVJam-v1", "wander": "MKV-v1"}
#: What the demo's PPO conclusions cannot claim.
PPO_CAVEAT = ("one PPO seed at the demo's reduced budget: not checked over seeds here; "
              "the claims section has PPO over 10 seeds to 500k steps")


def _by_name(evaluations):
    return {e.policy: e for e in evaluations}


def _fmt(v, digits=3):
    return "-" if v is None else f"{v:.{digits}f}"


def conclusions(evals: dict, learner: str = "SfM", others=("BC", "PPO"),
                notes: dict | None = None) -> list[str]:
    """One sentence per (baseline, metric): better, worse, or no clear difference (95% paired
    bootstrap interval of the difference excludes 0 or not). ``notes[other]`` is appended to
    every sentence about ``other`` (e.g. that a PPO result is one seed)."""
    lines = []
    notes = notes or {}
    for other in others:
        note = f" ({notes[other]})" if other in notes else ""
        wins, losses, ties = [], [], []
        for key, metric in COMPARED:
            ev = _by_name(evals[key])
            if learner not in ev or other not in ev:
                continue
            res = paired_difference_ci(ev[learner].records, ev[other].records, metric)
            if res is None:
                continue
            d, (lo, hi) = res
            text = (f"{METRIC_LABELS[metric]} on {ENV_OF[key]}: {learner} "
                    f"{_fmt(ev[learner].metrics[metric])} vs {other} "
                    f"{_fmt(ev[other].metrics[metric])} (difference {d:+.3f}, 95% CI "
                    f"[{lo:+.3f}, {hi:+.3f}])")
            if lo > 0 or hi < 0:
                better = (d > 0) == HIGHER_IS_BETTER[metric]
                (wins if better else losses).append(text)
            else:
                ties.append(text)
        if losses:
            lines.append(f"**{other} beats {learner}** on: " + "; ".join(losses) + note + ".")
        if wins:
            lines.append(f"**{learner} beats {other}** on: " + "; ".join(wins) + note + ".")
        if ties:
            lines.append(f"No clear difference between {learner} and {other} (interval "
                         f"includes 0) on: " + "; ".join(ties) + note + ".")
    return lines


def _arch(net_arch) -> str:
    """``{"pi": [64, 64], ...}`` or ``[64, 64]`` -> ``"64x64"``."""
    layers = net_arch.get("pi") if isinstance(net_arch, dict) else net_arch
    return "x".join(str(n) for n in layers) if layers else "linear"


def _read_json(path):
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def _cell(m: dict, key: str, digits: int = 3) -> str:
    """An agreement value with its bootstrap interval when the metric has one."""
    v = m.get(key)
    ci = (m.get("ci") or {}).get(key)
    return format_cell(v, ci, 2 if ci else digits)


def _over_sets(evs, key: str, digits: int = 2) -> str:
    vals = [e.metrics[key] for e in evs if e.metrics[key] is not None]
    if not vals:
        return "-"
    return f"{sum(vals) / len(vals):.{digits}f} [{min(vals):.{digits}f}..{max(vals):.{digits}f}]"


def write_report(out: str, budget, evals: dict, calib: dict | None, stages, total_wall_s: float,
                 quick: bool = False, studies: dict | None = None,
                 sweep: dict | None = None) -> str:
    """Write ``out/report.md`` (and ``out/learning_cost.png``); returns the report path.

    ``evals`` maps ``"jam"``/``"wander"`` to what the demo's evaluation returned (``table``,
    ``per_set``, ``pooled``, ``teacher``, ``random``, ``ppo``); ``studies`` holds the
    :class:`~sfm_learn.evaluation.study.StudyResult` of the feature and rank studies; ``sweep``
    the bundled claims sweeps (``about``, ``tables``, ``sentences``, ``plot``, ``specs``).
    """
    from sfm_learn import __version__
    from sfm_learn.baselines import bc, dagger, ppo
    from sfm_learn.eigenspace.policy import SfMPolicy
    from sfm_learn.evaluation.study import COLUMNS, study_by_key
    from sfm_learn.reporting.plots import plot_learning_cost

    def p(*parts):
        return os.path.join(out, *parts)

    n_sets = budget.train_sets
    sfm = SfMPolicy.load(p("policies", "sfm_0.npz"))
    paper = SfMPolicy.load(p("policies", "sfm_paper_0.npz"))
    bc_meta = bc.read_metadata(p("policies", "bc_0.zip"))
    dagger_meta = dagger.read_metadata(p("policies", "dagger_0.zip"))
    ppo_jam = ppo.read_metadata(p("policies", "ppo_jam.zip"))
    ppo_wander = ppo.read_metadata(p("policies", "ppo_wander.zip"))
    jenv, wenv = ENV_OF["jam"], ENV_OF["wander"]
    cmp = _read_json(p("compare.json"))
    cmp_paper = _read_json(p("compare_paper.json"))
    jam, wander = evals["jam"], evals["wander"]
    seeds = budget.train_seeds()

    L = ["# MK-V shape-from-motion demo report", ""]
    if quick:
        L += ["> **Quick run** (`mkv demo --quick`): tiny budgets, the numbers below are a smoke "
              "test and mean little. Run `mkv demo` for the real report.", ""]
    L += [f"Generated by `mkv demo` (mkv-sfm {__version__}) on "
          f"{_dt.date.today().isoformat()} in {total_wall_s / 60:.1f} min; "
          f"{environment_line()}.", ""]

    # ------------------------------------------------------------ set-up
    steps = budget.episode_steps or 600
    L += ["## Set-up: data, seeds and budgets", "",
          "| what | value |", "|---|---|",
          f"| teacher training sets | {n_sets} sets of {budget.train_episodes} {wenv} episodes "
          f"x {steps} steps ({sfm.training['rows']} steps each), env seeds "
          + ", ".join(f"{s}..{s + budget.train_episodes - 1}" for s in seeds) + " |",
          f"| held-out teacher runs (Figure 3) | {budget.held_episodes} episodes, env seeds "
          f"{budget.held_seed}..{budget.held_seed + budget.held_episodes - 1} "
          f"({cmp['modes']['free_running']['onsets']} teacher steer onsets) |",
          f"| SfM (default) | {sfm.feature_spec.n_features} features (sensors, traces "
          f"{'/'.join(f'{d:g}' for d in sfm.feature_spec.trace_decays)}, previous command), "
          f"rank by the largest singular-value ratio, {sfm.projector.solver} solver, learned "
          "thresholds |",
          f"| SfM paper preset | the paper's configuration: {paper.feature_spec.n_features} raw "
          "sensor channels, rank by the largest ratio, least-squares projection, fixed +-0.5 "
          "quantisation |",
          f"| BC | SB3 ActorCriticPolicy, {_arch(bc_meta.get('net_arch'))} MLP, "
          f"{bc_meta['epochs']} epochs, the SfM default features, one per training set |",
          f"| DAgger | the BC network and features; {dagger_meta['dagger']['rounds']} rounds, "
          f"{dagger_meta['teacher_steps']} teacher queries per training seed (the same budget as "
          "BC and SfM), round 0 the teacher driving, then the learner with the teacher labelling "
          "in shadow |",
          *[f"| PPO {k} | SB3 PPO on the {m['env_id']} reward, {m['timesteps']} env steps, "
            f"{m.get('n_envs')} envs, {m.get('observation', 'raw')} observation, packaged "
            f"hyperparameters, **one seed ({m.get('seed')}), reduced budget**: the claims sweep "
            "(`mkv sweep sweeps/claims_ppo.yml`) runs 10 seeds to 500k steps |"
            for k, m in (("jam", ppo_jam), ("wander", ppo_wander))],
          f"| evaluation | {jenv} {budget.jam_episodes} and {wenv} {budget.wander_episodes} "
          f"episodes per policy and training set, env seeds {budget.eval_seed}.. (never used "
          f"while developing); studies: {budget.study_jam_episodes} / "
          f"{budget.study_wander_episodes} episodes on the same seeds |", ""]

    # ------------------------------------------------------------ Figure 3
    fr, tf = cmp["modes"]["free_running"], cmp["modes"]["teacher_forced"]
    cp, co = cmp["baselines"]["copy_previous"], cmp["baselines"]["constant"]
    pf = cmp_paper["modes"]["free_running"]
    rows = [("drive", "drive"), ("steer timing (steer or not)", "steer_timing"),
            ("steer onsets hit within +-1 step", "onset_hit_w1"),
            ("steer onsets hit within +-2 steps", "onset_hit_w2"),
            ("... by chance, onsets placed at random at the policy's rate", "onset_hit_w2_chance"),
            ("... same side, among hits", "onset_side_given_hit_w2"),
            ("... of them the policy starts first (no leak)", "onset_hit_early_w2"),
            ("... by chance at the policy's rate", "onset_hit_early_w2_chance"),
            ("... same side, policy steers first", "onset_side_given_early_hit_w2"),
            ("escape-turn onsets hit within +-2", "onset_hit_w2_backoff")]
    L += ["## The paper's Figure 3, replayed honestly", "",
          "The policy (training set 0) replays the held-out teacher runs. **Free-running** (the "
          "figure): its own previous commands feed its features, as when it drives. "
          "**Teacher-forced** (the paper's replay): the teacher's previous command is fed "
          "instead, so a policy that echoes its input scores well; the **copy previous** "
          "baseline (the teacher's previous command, verbatim) shows how well. Onset metrics "
          "count the teacher's steer onsets; intervals are 95% bootstrap over onsets.", "",
          "![Figure 3](fig3.png)", "",
          "| agreement with the teacher | SfM free-running | SfM teacher-forced | copy previous "
          "| constant | paper preset |", "|---|---:|---:|---:|---:|---:|"]
    for label, key in rows:
        L.append(f"| {label} | {_cell(fr, key)} | {_cell(tf, key)} | {_cell(cp, key)} | "
                 f"{_cell(co, key)} | {_cell(pf, key)} |")
    L += [""]
    better_timing = fr["steer_timing"] > max(cp["steer_timing"], co["steer_timing"])
    L += [" ".join([
        f"Free-running, the default policy agrees on when to steer "
        f"{fr['steer_timing']:.3f} of the time against the constant guess "
        f"{co['steer_timing']:.3f} and copy-previous {cp['steer_timing']:.3f}: "
        + ("it beats both." if better_timing else
           "**it does not beat these baselines**; teacher-forced it scores "
           f"{tf['steer_timing']:.3f}, mostly by echoing the fed command."),
        f"It starts steering within +-2 steps of {fr['onset_hit_w2']:.0%} of the teacher's "
        f"onsets ({fr['onsets']} onsets, {fr['policy_onsets']} policy onsets; "
        f"{fr['onset_hit_w2_chance']:.0%} by chance at that rate), but it starts *first* at only "
        f"{fr['onset_hit_early_w2']:.0%} of them (chance {fr['onset_hit_early_w2_chance']:.0%}):"
        " when it starts after the teacher, the recorded steering angle and current already "
        "show the teacher's turn, side included, and the policy is reading it back.",
        f"The paper's configuration hits {pf['onset_hit_w2']:.0%} of onsets but starts "
        f"steering {pf['policy_onsets']} times (it dithers)."]), ""]

    # ------------------------------------------------------------ the paper's configuration
    pooled_w = wander["pooled"]
    t_rate = jam["teacher"].metrics["escape_rate"]
    L += ["## What the paper's own configuration achieves", "",
          f"Fitted on each of the {n_sets} training sets and driven in closed loop on the same "
          f"seeds, the paper's configuration escapes "
          f"{_over_sets(jam['per_set']['SfM paper'], 'escape_rate')} (mean [min..max] over "
          f"training sets) of {jenv} jams, against the teacher's {_fmt(t_rate, 2)}, and "
          f"travels {_over_sets(wander['per_set']['SfM paper'], 'distance_m', 1)} m per {wenv} "
          f"episode (teacher {wander['teacher'].metrics['distance_m']:.1f} m). Its rule keeps "
          f"n = {paper.n_components} eigenvectors of {paper.projector.n_features_in_} columns "
          f"({paper.projector.n_known_} sensors, 2 commands). With "
          "only the present sensor values a linear map cannot start a standing robot "
          "(the drive encoder reads zero, so the reconstructed drive command is near zero: "
          "stand still is a fixed point), and cannot hold a back-off.", ""]

    # ------------------------------------------------------------ studies
    if studies:
        feat = studies["features"]
        by = study_by_key(feat)
        esc = COLUMNS.index("escape_rate")
        L += ["## Which features, which solver: the feature study", "",
              f"Each configuration fitted on the same {n_sets} training sets; free-running "
              "agreement on the held-out runs; closed loop on the evaluation seeds. Means over "
              "training sets, [min..max] of the escape rate.", "",
              study_markdown(feat), ""]
        if {"default", "default_ols", "paper", "raw_ppca"} <= set(by):
            d, o = by["default"], by["default_ols"]
            L += [f"Ordinary least squares on the same features escapes {o[esc]:.2f} against "
                  f"the eigenspace policy's {d[esc]:.2f}: "
                  + ("the eigenspace projection adds nothing measurable over plain regression "
                     "here" if abs(o[esc] - d[esc]) < 0.03 else
                     ("the eigenspace projection does better" if d[esc] > o[esc] else
                      "plain regression does better"))
                  + f". The paper's configuration escapes {by['paper'][esc]:.2f}; the same raw "
                  f"sensors with the ppca solver and learned thresholds {by['raw_ppca'][esc]:.2f}"
                  ".", ""]
        rd, rp = studies["rank_default"], studies["rank_paper"]
        L += ["## The kept rank", "",
              "Closed-loop and free-running metrics against the kept rank n, for the default "
              "features and the paper's configuration (mean over training sets, range shaded; "
              "the star is the rank the largest-ratio rule picks):", "",
              "![rank study](rank_study.png)", ""]
        for name, res in (("default", rd), ("paper", rp)):
            e = res.column("escape_rate").mean(axis=1)
            ranks = res.column("rank")[:, 0].astype(int)
            rule = int(np.bincount(res.rule_rank.ravel()).argmax())
            at_rule = e[ranks == rule]
            L.append(f"- {name}: best escape rate {e.max():.2f} at n = {ranks[e.argmax()]}; "
                     f"the rule picks n = {rule}"
                     + (f" ({at_rule[0]:.2f})" if at_rule.size else "") + ".")
        L += [""]

    # ------------------------------------------------------------ closed loop
    L += ["## Closed loop: every policy on the same seeds", "",
          f"SfM, the paper preset, BC and DAgger pool their {n_sets} training sets ({n_sets} x "
          "the episodes; intervals resample (training set, episode) pairs); each PPO is one "
          "training run on its env's reward (jam or wander), evaluated on both envs. Stand "
          "still is the constant baseline (drive and steering off).", "",
          format_markdown(jam["table"]), "", f"![{jenv}](eval/jam.png)", "",
          format_markdown(wander["table"]), "", f"![{wenv}](eval/wander.png)", "",
          "Per training set (mean [min..max] over sets):", "",
          f"| learner | {jenv} escape rate | {wenv} distance [m] | {wenv} stuck fraction |",
          "|---|---:|---:|---:|"]
    for name in jam["per_set"]:
        L.append(f"| {name} | {_over_sets(jam['per_set'][name], 'escape_rate')} | "
                 f"{_over_sets(wander['per_set'][name], 'distance_m', 1)} | "
                 f"{_over_sets(wander['per_set'][name], 'stuck_fraction', 3)} |")
    L += [""]
    if t_rate:
        rates = [e.metrics["escape_rate"] for e in jam["per_set"]["SfM"]]
        mean, low = sum(rates) / len(rates), min(rates)
        ok = mean >= 0.9 * t_rate and low >= 0.85 * t_rate
        L += [f"SfM (default) escape rate: mean {mean:.3f} over {n_sets} training sets = "
              f"{mean / t_rate:.0%} of the teacher's {t_rate:.3f}; lowest set {low:.3f} = "
              f"{low / t_rate:.0%} (targets: mean >= 90%, every set >= 85%: "
              f"{'met' if ok else '**missed**'}).", ""]

    # ------------------------------------------------------------ learning cost
    teacher_return = wander["teacher"].metrics["mean_return"]
    points = [("SfM (teacher steps)", sfm.training["rows"],
               pooled_w["SfM"].metrics["mean_return"]),
              ("BC (teacher steps)", bc_meta["teacher_steps"],
               pooled_w["BC"].metrics["mean_return"]),
              ("DAgger (teacher queries)", dagger_meta["teacher_steps"],
               pooled_w["DAgger"].metrics["mean_return"])]
    plot_learning_cost(ppo_wander["learning_curve"], points, p("learning_cost.png"),
                       metric="mean_return", ylabel=f"mean return on {wenv}",
                       reference=("teacher", teacher_return),
                       title=f"What each learner needed: data vs score on {wenv}")
    L += ["## Learning cost", "",
          f"| learner | data used | training wall time | {jenv} escape rate | "
          f"{wenv} mean return |", "|---|---|---:|---:|---:|",
          f"| SfM | {sfm.training['rows']} teacher steps | {sfm.training['wall_s']:.2f} s | "
          f"{_over_sets(jam['per_set']['SfM'], 'escape_rate')} | "
          f"{_over_sets(wander['per_set']['SfM'], 'mean_return')} |",
          f"| BC | {bc_meta['teacher_steps']} teacher steps | {bc_meta['train_wall_s']:.1f} s | "
          f"{_over_sets(jam['per_set']['BC'], 'escape_rate')} | "
          f"{_over_sets(wander['per_set']['BC'], 'mean_return')} |",
          f"| DAgger | {dagger_meta['teacher_steps']} teacher queries | "
          f"{dagger_meta['train_wall_s']:.1f} s (last round's fit) | "
          f"{_over_sets(jam['per_set']['DAgger'], 'escape_rate')} | "
          f"{_over_sets(wander['per_set']['DAgger'], 'mean_return')} |",
          *[f"| PPO {k} | {m['timesteps']} env steps ({m['env_id']} reward) | "
            f"{m['train_wall_s']:.1f} s | {_fmt(jam['ppo'][f'PPO {k}'].metrics['escape_rate'])} | "
            f"{_fmt(wander['ppo'][f'PPO {k}'].metrics['mean_return'], 2)} |"
            for k, m in (("jam", ppo_jam), ("wander", ppo_wander))], "",
          "![learning cost](learning_cost.png)", "",
          f"The PPO curve is the {wenv}-reward run's periodic evaluation during training "
          f"({ppo_wander['eval']['episodes']} episodes on env seeds "
          f"{ppo_wander['eval']['seed']}.., deterministic actions); the SfM, BC and DAgger points "
          "and the teacher line are from the evaluation above. Teacher steps are a human's time "
          "on a real robot; env steps are simulated. Over 20 training sets per budget (and 10 "
          "PPO seeds): the next section.", ""]

    # ------------------------------------------------------------ sample efficiency
    if sweep is not None:
        L += ["## Over many training sets (the bundled claims sweeps, not rerun here)", "",
              "The demo trains each learner on 5 training sets at one budget. How they scale "
              "with data, how often a training set gives a failing policy, and which differences "
              "survive a paired test come from `mkv sweep sweeps/claims.yml` (20 training sets "
              "per teacher-step point) and `sweeps/claims_ppo.yml` (10 PPO seeds), whose rows "
              f"ship with the package: {sweep['about']} Curves: mean over sets [95% "
              "t-interval]; tables: mean [95% bootstrap over sets], median, 10th percentile, "
              "failure rate; paired differences over the same sets and evaluation seeds.", "",
              f"![sample efficiency]({sweep['plot']})", "", sweep["tables"], "",
              *[f"- {s}" for s in sweep["sentences"]], ""]

    # ------------------------------------------------------------ conclusions
    pooled_evals = {key: list(ev["pooled"].values()) for key, ev in evals.items()}
    names = {n: f"{n} ({n_sets} sets)" for n in ("SfM", "SfM paper", "BC", "DAgger")}
    L += ["## Conclusions (computed from the numbers above)", "",
          "Paired bootstrap over the same (training set, episode) pairs of the demo's 5 "
          "training sets; each PPO run is paired with each training set's episodes. These are "
          "differences on these sets; whether a ranking holds over new training sets is the "
          "claims section above (20 sets per budget).", ""]
    L += [f"- {line}" for line in conclusions(
        pooled_evals, learner=names["SfM"],
        others=(names["BC"], names["DAgger"], "PPO jam", "PPO wander", names["SfM paper"]),
        notes={"PPO jam": PPO_CAVEAT, "PPO wander": PPO_CAVEAT})]
    L += [""]

    # ------------------------------------------------------------ calib
    if calib is not None:
        L += ["## Force-sensor calibration: the paper's simulation trials", "",
              "Median mean-absolute offset error (units of the proof-mass weight) over "
              f"{budget.calib_seeds} seeds, shape from motion with bias (`centered` route) vs "
              "the value the paper reports:", "",
              "| trial | ours (median [IQR]) | paper | paper / ours |", "|---|---:|---:|---:|"]
        for t, s in calib.items():
            c = s["centered"]
            L.append(f"| {t} | {c['median']:.3g} [{c['q25']:.3g}, {c['q75']:.3g}] | "
                     f"{s['paper_reported']:.3g} | {c['ratio']:.1f}x |")
        L += ["", "Full tables, Table 1 and plots: [calib/trials.md](calib/trials.md).", ""]

    # ------------------------------------------------------------ reproduce
    L += ["## How this report was made", "",
          "| stage | command | wall time |", "|---|---|---:|"]
    for title, shown, wall in stages:
        L.append(f"| {title} | `{shown.replace(out + os.sep, '')}` | {wall:.1f} s |")
    L.append("")
    text = "\n".join(L)
    path = p("report.md")
    atomic_write_text(path, text)
    return path


def environment_line() -> str:
    """Python, platform, CPU count and the thread settings that decide training speed and (for
    torch) bit-reproducibility, for the report."""
    line = (f"Python {platform.python_version()} on {platform.system()} {platform.machine()} "
            f"({_cpu_model()}), {os.cpu_count()} CPUs; "
            f"{sys.executable}")
    try:
        import torch
    except ImportError:
        return line
    threads = ", ".join(f"{v}={os.environ[v]}" for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")
                        if v in os.environ) or "OMP/MKL_NUM_THREADS unset"
    return (f"{line}; torch {torch.__version__} ({torch.get_num_threads()} intra-op thread(s) "
            f"as the baselines set them, {threads})")


def _cpu_model() -> str:
    """The CPU model name (Linux /proc/cpuinfo), else what platform knows."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"
