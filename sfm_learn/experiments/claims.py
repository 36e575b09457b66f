"""Claims over many training sets: per-point spread, failure rates, paired verdicts.

A sweep's rows give one value per (learner, budget, training seed), and, when the sweep's spec
names evaluation ``banks``, every episode's outcome. For every point this module reports the
mean with a percentile-bootstrap interval, the median, the 10th percentile and the *failure
rate*: the share of training sets whose policy escapes fewer than :data:`ESCAPE_FAIL` of
MKVJam-v1 jams or wanders less than :data:`DISTANCE_FAIL` m per MKV-v1 episode (each test only
where that env was evaluated).

What an interval covers (:func:`design`): with per-episode outcomes, training sets *and*
evaluation episodes (and banks, with three or more), resampled independently
(:mod:`sfm_learn.experiments.crossed`): the interval is about the learner, not about the
episodes that happened to be drawn. Rows without them (sweeps before banks) give intervals over
training sets only, the episodes held fixed, and say so. Beside each level's confidence interval
the claims state where a *rerun* lands (as many new training sets on a new bank of one bank's
episodes; :func:`crossed.replication_interval`), jointly over every level stated: the interval a
replication checks (:func:`check` compares a check sweep with it; :func:`held_out_banks` holds
each bank out in turn).

Two learners are ranked only by a *paired* comparison (same training seeds, same episodes), and
only when Holm's family-wise adjustment over the comparisons of the budget's table rejects "no
difference" (each comparison's interval is shown at its Holm step's level, so it excludes 0
exactly then) over at least :data:`MIN_PAIRED` sets; otherwise "no clear difference". Each table
also states the smallest difference its design detects (:func:`crossed.min_detectable_effect`).
Every ranking sentence the README and ``mkv demo`` print comes from :func:`claim_sentences`.

Bootstraps are seeded, so the same rows give the same text.
"""

from __future__ import annotations

import json
import os
import re
import sys
import textwrap
from collections import defaultdict

import numpy as np

from sfm_learn.experiments import crossed

JAM, WANDER = "MKVJam-v1", "MKV-v1"
ESCAPE_FAIL = 0.8
DISTANCE_FAIL = 10.0
RESAMPLES = 2000
MIN_PAIRED = 10
"""Fewer common training sets than this give no verdict ("too few sets"), whatever the interval."""
PAIRS = (("sfm", "bc"), ("sfm", "dagger"), ("bc", "dagger"), ("sfm", "sfm-ols"),
         ("sfm", "sfm-paper"))
NAMES = {"sfm": "SfM", "sfm-ols": "SfM with the OLS solver", "sfm-paper": "the paper's SfM",
         "bc": "BC", "dagger": "DAgger", "ppo-jam": "PPO (jam reward)",
         "ppo-wander": "PPO (wander reward)"}


def by_point(rows) -> dict:
    """``{(learner, budget): {seed: {"escape": x|None, "distance": d|None}}}`` from ok rows."""
    out: dict = defaultdict(dict)
    for r in rows:
        if r.get("status") != "ok":
            continue
        m = r["metrics"]
        out[(r["learner"], int(r["budget"]))][int(r["seed"])] = {
            "escape": m.get(JAM, {}).get("escape_rate"),
            "distance": m.get(WANDER, {}).get("distance_m"),
            "episodes": (r.get("episodes") or {}).get(JAM),
            "wander_episodes": (r.get("episodes") or {}).get(WANDER),
        }
    return dict(out)


#: Per metric of a point: the ``by_point`` field of its per-set value, the field of its
#: per-episode outcomes, and the outcome's key in them.
METRIC_FIELDS = {"escape": ("escape", "episodes", "escaped"),
                 "distance": ("distance", "wander_episodes", "distance_m")}


def outcomes(sets: dict, metric: str = "escape") -> crossed.Outcomes | None:
    """The outcomes of one point (``by_point`` value) in ``metric`` ("escape": 0/1 per MKVJam-v1
    episode; "distance": metres per MKV-v1 episode) for the bootstrap: per episode when every
    set has them on the same episodes (``design`` "sets x episodes"), else each set's mean as its
    one value (the episodes held fixed); None without that metric."""
    value, field, key = METRIC_FIELDS[metric]
    seeds = sorted(s for s in sets if sets[s][value] is not None)
    if not seeds:
        return None
    eps = [sets[s].get(field) for s in seeds]
    if all(e and e.get(key) is not None for e in eps) and all(
            e["bank"] == eps[0]["bank"] for e in eps):
        return crossed.Outcomes(tuple(seeds), np.array([e[key] for e in eps], float),
                                np.array(eps[0]["bank"]))
    return crossed.Outcomes(tuple(seeds), np.array([[sets[s][value]] for s in seeds]),
                            np.zeros(1, int))


def design(out: crossed.Outcomes | None) -> str:
    """What an interval over ``out`` covers, in words."""
    if out is None or out.values.shape[1] == 1:
        return "training sets (the evaluation episodes held fixed)"
    banks = len(np.unique(out.banks))
    level = ", banks resampled" if banks >= crossed.MIN_BANKS_AS_LEVEL else ""
    return (f"training sets and evaluation episodes ({out.values.shape[1]} in {banks} "
            f"bank{'s' if banks > 1 else ''}{level})")


def _rerun(oc: crossed.Outcomes) -> dict:
    """The design of the rerun a replication interval is about: as many new training sets, and a
    new bank of one bank's episodes (None: rows without episodes, the episodes held fixed)."""
    if oc.values.shape[1] == 1:
        return {"rerun": (oc.values.shape[0], None)}
    sizes = np.unique(oc.banks, return_counts=True)[1]
    return {"rerun": (oc.values.shape[0], int(sizes.min()))}


def rerun_words(p: dict, family: int, unit: str = "training sets",
                generic: bool = False) -> str:
    """What a point's replication interval (``point_summary``) is, in words (``generic``: for
    any point of the same design, without its counts)."""
    n, e = p["rerun"]
    if generic:
        n, e = "as many", ("one bank's" if e else None)
    bank = f" on a new bank of {e} episodes per env" if e else " (the episodes held fixed)"
    joint = f", 95 % jointly over the {family} levels stated" if family > 1 else ", 95 %"
    return f"{n} new {unit}{bank}{joint}"


def point_summary(sets: dict, seed: int = 0, family: int = 1) -> dict:
    """Summary of one point (``by_point`` value): n, escape mean/CI/replication
    interval/median/p10, distance mean/CI/replication interval, what each interval covers,
    failures (count of sets failing either test that was measured). The replication intervals
    are simultaneous over ``family`` levels (:func:`crossed.level`)."""
    seeds = sorted(sets)
    esc = np.array([sets[s]["escape"] for s in seeds if sets[s]["escape"] is not None], float)
    dist = np.array([sets[s]["distance"] for s in seeds if sets[s]["distance"] is not None], float)
    fail = [((sets[s]["escape"] is not None and sets[s]["escape"] < ESCAPE_FAIL)
             or (sets[s]["distance"] is not None and sets[s]["distance"] < DISTANCE_FAIL))
            for s in seeds]
    out = {"n": len(seeds), "failures": int(sum(fail))}
    if len(esc):
        oc = outcomes(sets)
        lv = crossed.level(oc, seed=seed, resamples=RESAMPLES, family=family)
        out.update(_rerun(oc))
        out.update(escape_mean=float(esc.mean()), escape_ci=lv["ci"],
                   escape_rep=lv["replication"],
                   escape_median=float(np.median(esc)), escape_p10=float(np.percentile(esc, 10)),
                   covers=design(oc))
    if len(dist):
        oc = outcomes(sets, "distance")
        lv = crossed.level(oc, seed=seed, resamples=RESAMPLES, family=family)
        out.setdefault("rerun", _rerun(oc)["rerun"])
        out.update(distance_mean=float(dist.mean()), distance_ci=lv["ci"],
                   distance_rep=lv["replication"],
                   distance_covers=design(oc))
    return out


def budget_table(points: dict, budget: int, seed: int = 0, pairs=PAIRS) -> dict:
    """The paired comparisons ``pairs`` (default :data:`PAIRS`) at ``budget`` as one Holm family:
    ``{(a, b): {"n", "mean", "ci", "confidence", "p_adjusted", "verdict", "mde", "covers"}}``
    (``verdict`` a learner name or None; None also below :data:`MIN_PAIRED` common sets)."""
    family = {}
    for a, b in pairs:
        oa, ob = outcomes(points.get((a, budget), {})), outcomes(points.get((b, budget), {}))
        if oa is None or ob is None:
            continue
        if oa.values.shape[1] != ob.values.shape[1] or not np.array_equal(oa.banks, ob.banks):
            # one of them without per-episode outcomes: compare the per-set rates
            oa, ob = (crossed.Outcomes(o.sets, o.values.mean(axis=1, keepdims=True),
                                       np.zeros(1, int)) for o in (oa, ob))
        family[(a, b)] = (oa, ob)
    got = crossed.table(family, seed=seed, resamples=RESAMPLES)
    out = {}
    for (a, b), r in got.items():
        verdict = {"a": a, "b": b}.get(r["verdict"]) if r["n"] >= MIN_PAIRED else None
        out[(a, b)] = {**r, "verdict": verdict, "covers": design(family[(a, b)][0])}
    return out


def paired(points: dict, a: str, b: str, budget: int, seed: int = 0) -> dict | None:
    """Paired escape-rate difference ``a - b`` at ``budget``: its row of :func:`budget_table`
    (Holm-adjusted over the budget's :data:`PAIRS`), or, for a pair outside them, a family of
    one; None when they share no seed."""
    if (a, b) in PAIRS:
        return budget_table(points, budget, seed).get((a, b))
    if (b, a) in PAIRS:
        r = budget_table(points, budget, seed).get((b, a))
        return None if r is None else {**r, "mean": -r["mean"],
                                       "ci": (-r["ci"][1], -r["ci"][0])}
    return budget_table(points, budget, seed, pairs=((a, b),)).get((a, b))


def _name(learner: str) -> str:
    return NAMES.get(learner, learner)


def _budget(learner: str, budget: int) -> str:
    return f"{budget // 1000}k env steps" if learner.startswith("ppo") else \
        f"{budget:,} teacher steps"


def tables(rows) -> str:
    """Markdown: the per-point table, then the paired table."""
    points = by_point(rows)
    fam = len(points)
    lines = ["| learner | budget | sets | escape mean [95 % CI] | a rerun lands in | median | p10 "
             "| distance m mean [95 % CI] | a rerun lands in | failure rate (escape < "
             f"{ESCAPE_FAIL} or distance < {DISTANCE_FAIL:g} m) |",
             "|---|---|---:|---|---|---:|---:|---|---|---|"]
    for (learner, budget) in sorted(points):
        p = point_summary(points[(learner, budget)], family=fam)
        esc = (f"{p['escape_mean']:.3f} [{p['escape_ci'][0]:.3f}, {p['escape_ci'][1]:.3f}] | "
               f"[{p['escape_rep'][0]:.3f}, {p['escape_rep'][1]:.3f}] | "
               f"{p['escape_median']:.3f} | {p['escape_p10']:.3f}"
               if "escape_mean" in p else "- | - | - | -")
        dist = (f"{p['distance_mean']:.2f} [{p['distance_ci'][0]:.2f}, "
                f"{p['distance_ci'][1]:.2f}] | [{p['distance_rep'][0]:.2f}, "
                f"{p['distance_rep'][1]:.2f}]" if "distance_mean" in p else "- | -")
        lines.append(f"| {learner} | {budget:,} | {p['n']} | {esc} | {dist} | "
                     f"{p['failures'] / p['n']:.2f} ({p['failures']}/{p['n']}) |")
    if points:
        some = _rerun(next(oc for v in points.values() for oc in (outcomes(v),
                                                                   outcomes(v, "distance"))
                           if oc is not None))
        lines += ["", f"A rerun lands in: the mean of {rerun_words(some, fam, generic=True)} "
                  "(Bonferroni; "
                  "one level per point is stated: escape, or distance for PPO with the wander "
                  "reward); the 95 % CI is about the level itself."]
    covered = {design(oc) for oc in map(outcomes, points.values()) if oc is not None}
    lines += ["", "Intervals of a level cover " + "; ".join(sorted(covered)) + ".",
        "", "| pair | budget | paired mean difference in escape [bootstrap, Holm step level] "
        "| Holm-adjusted p | verdict | detectable difference (80 % power) |",
        "|---|---:|---|---:|---|---:|"]
    for b in sorted({b for _, b in points}):
        for (a, c), r in budget_table(points, b).items():
            verdict = (f"{r['verdict']} higher" if r["verdict"] else "no clear difference"
                       if r["n"] >= MIN_PAIRED else f"too few sets (< {MIN_PAIRED})")
            lines.append(f"| {a} - {c} | {b:,} | {r['mean']:+.3f} [{r['ci'][0]:+.3f}, "
                         f"{r['ci'][1]:+.3f}] ({100 * r['confidence']:.1f} %, n={r['n']}) | "
                         f"{r['p_adjusted']:.3f} | {verdict} | {r['mde']:.3f} |")
    held = held_out_banks(rows)
    if held:
        by = defaultdict(list)
        for q in held:
            by[q["metric"]].append((q["covered"], q["in_replication"]))
        lines += ["", "Each bank held out in turn (intervals from the other banks' episodes, the "
                  "same policies; the held-out bank's mean): " + "; ".join(
                      f"{m} levels in the 95 % CI {sum(c for c, _ in v)} of {len(v)}, in a "
                      f"rerun's 95 % interval {sum(r for _, r in v)} of {len(v)}"
                      for m, v in sorted(by.items())) + ". A confidence interval is about the "
                  "mean and misses a new bank's value more often than 5 %; the rerun's "
                  "interval adds that bank's own sampling (and new training sets', so it is "
                  "conservative here)."]
    return "\n".join(lines) + "\n"


def claim_sentences(rows) -> list[str]:
    """One sentence per budget for the teacher-step learners (escape rates, failure rates, every
    paired verdict), and one per PPO learner: the text the README and the demo print."""
    points = by_point(rows)
    fam = len(points)  # one level stated per point: the family of the replication intervals
    out = []
    budgets = sorted({b for (lr, b) in points if not lr.startswith("ppo")})
    for b in budgets:
        parts = []
        for learner in ("sfm", "bc", "dagger", "sfm-ols", "sfm-paper"):
            if (learner, b) not in points:
                continue
            p = point_summary(points[(learner, b)], family=fam)
            parts.append(f"{_name(learner)} {p['escape_mean']:.3f} [{p['escape_ci'][0]:.3f}, "
                         f"{p['escape_ci'][1]:.3f}] (a rerun: {p['escape_rep'][0]:.2f}-"
                         f"{p['escape_rep'][1]:.2f}), failing on {p['failures']} of {p['n']}")
        if not parts:
            continue
        verdicts, table = [], budget_table(points, b)
        for (a, c), r in table.items():
            ci = f"{r['mean']:+.3f} [{r['ci'][0]:+.3f}, {r['ci'][1]:+.3f}]"
            if r["n"] < MIN_PAIRED:
                verdicts.append(f"{_name(a)} and {_name(c)}: too few common sets ({r['n']}) "
                                "to rank")
            elif r["verdict"]:
                lo_name = _name(c if r["verdict"] == a else a)
                verdicts.append(f"{_name(r['verdict'])} above {lo_name} ({_name(a)} minus "
                                f"{_name(c)} {ci})")
            else:
                verdicts.append(f"{_name(a)} and {_name(c)}: no clear difference ({ci})")
        first = next(lr for lr in ("sfm", "bc", "dagger", "sfm-ols", "sfm-paper")
                     if (lr, b) in points)
        covers = design(outcomes(points[(first, b)]))
        rerun = rerun_words(_rerun(outcomes(points[(first, b)])), fam)
        mde = (f" The design detects paired differences of about "
               f"{float(np.median([r['mde'] for r in table.values()])):.3f} (80 % power)."
               if table else "")
        out.append(f"At {b:,} teacher steps the escape rates (mean [95 % bootstrap interval "
                   f"over {covers}] (where a rerun lands: {rerun})) are {'; '.join(parts)}. "
                   "Paired over the same sets and episodes, ranked only where Holm's adjustment "
                   f"over these {len(table)} comparisons excludes 0 (intervals at its step "
                   f"levels): {'; '.join(verdicts)}.{mde}")
    for learner in sorted({lr for lr, _ in points if lr.startswith("ppo")}):
        parts, covers, reruns = [], set(), set()
        for b in sorted(b for lr, b in points if lr == learner):
            p = point_summary(points[(learner, b)], family=fam)
            covers.add(p.get("covers", p.get("distance_covers")))
            reruns.add(rerun_words(p, fam, "PPO seeds"))
            if "escape_mean" in p:
                val = (f"escapes {p['escape_mean']:.3f} [{p['escape_ci'][0]:.3f}, "
                       f"{p['escape_ci'][1]:.3f}] (a rerun: {p['escape_rep'][0]:.2f}-"
                       f"{p['escape_rep'][1]:.2f}; median {p['escape_median']:.2f}, 10th "
                       f"percentile {p['escape_p10']:.2f})")
            else:
                val = (f"wanders {p['distance_mean']:.1f} m [{p['distance_ci'][0]:.1f}, "
                       f"{p['distance_ci'][1]:.1f}] (a rerun: {p['distance_rep'][0]:.1f}-"
                       f"{p['distance_rep'][1]:.1f} m)")
            parts.append(f"at {_budget(learner, b)} it {val}, failing on {p['failures']} of "
                         f"{p['n']} seeds")
        over = "; ".join(sorted(c for c in covers if c)).replace("training sets", "PPO seeds")
        out.append(f"{_name(learner)} (mean [95 % bootstrap interval over {over}] (where a "
                   "rerun lands: "
                   f"{'; '.join(sorted(reruns))})): {'; '.join(parts)}.")
    return out


def check(published_rows, check_rows) -> dict:
    """How the claims of ``published_rows`` fare on a check sweep (new training sets and a new
    evaluation bank, the acceptance test of a claim): ``{"levels": [...], "pairs": [...]}``.

    A level (learner, budget, metric) is *covered* when the published replication interval
    (simultaneous over the published points) contains the check's mean; ``in_ci`` says whether
    the level's 95 % confidence interval does (it is about the mean alone, and misses a rerun's
    value more often than 5 %). A published comparison *held* when the check's own verdict
    (Holm over its table) is the same, *reversed* when the check ranks the other learner above,
    and *flipped* when the check's mean difference has the other sign (a reversal in the making)."""
    pub, new = by_point(published_rows), by_point(check_rows)
    levels = []
    for key in sorted(set(pub) & set(new)):
        p, c = point_summary(pub[key], family=len(pub)), point_summary(new[key])
        for metric in ("escape", "distance"):
            if f"{metric}_mean" in p and f"{metric}_mean" in c:
                lo, hi = p[f"{metric}_rep"]
                value = c[f"{metric}_mean"]
                levels.append({"learner": key[0], "budget": key[1], "metric": metric,
                               "published": p[f"{metric}_mean"], "replication": (lo, hi),
                               "ci": p[f"{metric}_ci"], "check": value,
                               "covered": bool(lo <= value <= hi),
                               "in_ci": bool(p[f"{metric}_ci"][0] <= value
                                             <= p[f"{metric}_ci"][1])})
    pairs = []
    for b in sorted({b for _, b in pub} & {b for _, b in new}):
        tp, tc = budget_table(pub, b), budget_table(new, b)
        for key in tp.keys() & tc.keys():
            r, c = tp[key], tc[key]
            pairs.append({"pair": key, "budget": b, "published": r["mean"], "ci": r["ci"],
                          "verdict": r["verdict"], "check": c["mean"], "check_ci": c["ci"],
                          "check_verdict": c["verdict"], "held": c["verdict"] == r["verdict"],
                          "reversed": bool(r["verdict"] and c["verdict"]
                                           and c["verdict"] != r["verdict"]),
                          "flipped": bool(r["verdict"] and np.sign(c["mean"])
                                          != np.sign(r["mean"]))})
    pairs.sort(key=lambda q: (q["budget"], PAIRS.index(q["pair"]) if q["pair"] in PAIRS else 99))
    return {"levels": levels, "pairs": pairs}


def held_out_banks(rows, seed: int = 0) -> list[dict]:
    """Each evaluation bank held out in turn: for every point and metric with per-episode
    outcomes on at least 2 banks, the 95 % interval from the other banks' episodes (training
    sets and episodes resampled as everywhere), a rerun's 95 % interval from them (one level:
    no family adjustment) and the held-out bank's mean, with ``covered`` (in the CI) and
    ``in_replication``. The real-data counterpart of a fresh bank's check (the same policies,
    new episodes; the rerun's interval also allows for new training sets, so it is conservative
    here)."""
    out = []
    for key, sets in sorted(by_point(rows).items()):
        for metric in ("escape", "distance"):
            oc = outcomes(sets, metric)
            if oc is None or len(np.unique(oc.banks)) < 2:
                continue
            for b in np.unique(oc.banks):
                rest = oc.banks != b
                lv = crossed.level(crossed.Outcomes(oc.sets, oc.values[:, rest], oc.banks[rest]),
                                   seed=seed, resamples=RESAMPLES)
                value = float(oc.values[:, ~rest].mean())
                lo, hi = lv["replication"]
                out.append({"learner": key[0], "budget": key[1], "metric": metric,
                            "bank": int(b), "ci": lv["ci"], "replication": (lo, hi),
                            "value": value,
                            "covered": bool(lv["ci"][0] <= value <= lv["ci"][1]),
                            "in_replication": bool(lo <= value <= hi)})
    return out


def check_report(result: dict) -> str:
    """Markdown of :func:`check`: the levels, the comparisons, and a one-line tally."""
    lv, pr = result["levels"], result["pairs"]
    lines = ["| learner | budget | metric | published [a rerun lands in] | 95 % CI | check | "
             "covered | in the CI |", "|---|---:|---|---|---|---:|---|---|"]
    for q in lv:
        lines.append(f"| {q['learner']} | {q['budget']:,} | {q['metric']} | {q['published']:.3f} "
                     f"[{q['replication'][0]:.3f}, {q['replication'][1]:.3f}] | "
                     f"[{q['ci'][0]:.3f}, {q['ci'][1]:.3f}] | {q['check']:.3f} | "
                     f"{'yes' if q['covered'] else '**no**'} | "
                     f"{'yes' if q['in_ci'] else 'no'} |")
    lines += ["", "| pair | budget | published | verdict | check | check's verdict | held |",
              "|---|---:|---|---|---|---|---|"]
    for q in pr:
        a, b = q["pair"]
        lines.append(f"| {a} - {b} | {q['budget']:,} | {q['published']:+.3f} [{q['ci'][0]:+.3f}, "
                     f"{q['ci'][1]:+.3f}] | {q['verdict'] or 'no clear difference'} | "
                     f"{q['check']:+.3f} [{q['check_ci'][0]:+.3f}, {q['check_ci'][1]:+.3f}] | "
                     f"{q['check_verdict'] or 'no clear difference'} | "
                     + ("**reversed**" if q["reversed"] else "yes" if q["held"] else
                        "sign flipped" if q["flipped"] else "verdict differs") + " |")
    ranked = [q for q in pr if q["verdict"]]
    lines += ["", f"Levels covered: {sum(q['covered'] for q in lv)} of {len(lv)} (in the 95 % "
              f"CI: {sum(q['in_ci'] for q in lv)}). Published "
              f"rankings: {len(ranked)}; reversed {sum(q['reversed'] for q in ranked)}, sign "
              f"flipped {sum(q['flipped'] for q in ranked)}, held "
              f"{sum(q['held'] for q in ranked)}. Comparisons without a published ranking that "
              f"the check ranks: {sum(1 for q in pr if not q['verdict'] and q['check_verdict'])}."]
    return "\n".join(lines) + "\n"


REFERENCE = os.path.join(os.path.dirname(__file__), "reference", "claims.json")
"""The rows behind the README's claims (``scripts/claims_summary.py --bundle``)."""


def load_reference(path: str = REFERENCE) -> dict:
    """``{"about", "specs", "rows"}`` of the bundled claims sweeps."""
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    if not isinstance(doc, dict) or not {"specs", "rows"} <= set(doc):
        raise ValueError(f"{path} is not a bundled claims file")
    return doc


def _evaluation(ev: dict) -> str:
    """A sweep spec's ``eval`` in words (its banks' first seeds)."""
    from sfm_learn.experiments.sweep import bank_seeds

    firsts = bank_seeds(ev)
    if len(firsts) == 1:
        return f"evaluation seeds {firsts[0]:,}.., {ev['episodes']} episodes per env"
    return (f"{len(firsts)} evaluation banks of {ev['episodes']} episodes per env (seeds "
            f"{' / '.join(f'{s:,}..' for s in firsts)})")


def readme_block(doc: dict, width: int = 100) -> str:
    """The README's claims paragraphs, generated from ``doc`` (:func:`load_reference`)."""
    ev = {json.dumps(s["eval"], sort_keys=True) for s in doc["specs"]}
    evals = "; ".join(_evaluation(e) for e in map(json.loads, sorted(ev)))
    points = by_point(doc["rows"])
    sets = sorted({len(v) for v in points.values()})
    t = doc.get("teacher", {})
    where = ("the same seeds" if len(ev) == 1 else
             f"the {_evaluation(doc.get('teacher_eval', doc['specs'][0]['eval']))}")
    teacher = (f"; the teacher on {where} escapes {t[JAM]['escape_rate']:.2f} of jams and "
               f"wanders {t[WANDER]['distance_m']:.1f} m" if JAM in t and WANDER in t else "")
    names = ['`' + s.get('file', s.get('name', '?')) + '`' for s in doc['specs']]
    runs = (f"{', '.join(names)}; {evals}" if len(ev) == 1 else "; ".join(
        f"{n} on {_evaluation(s['eval'])}" for n, s in zip(names, doc['specs'], strict=True)))
    head = (f"Over {' or '.join(map(str, sets))} training sets per point "
            f"({runs}; a set *fails* when its policy escapes fewer than {ESCAPE_FAIL:g} of jams "
            f"or wanders less than {DISTANCE_FAIL:g} m{teacher}; generated by "
            "`python -m sfm_learn.experiments.claims` from the bundled rows):")
    paras = [head] + claim_sentences(doc["rows"])
    return "\n\n".join(textwrap.fill(p, width, break_on_hyphens=False, break_long_words=False)
                        for p in paras)


BLOCK = re.compile(r"(<!-- claims:begin -->\n)(.*?)(<!-- claims:end -->)", re.S)


def replace_block(text: str, block: str) -> str:
    """``text`` with the part between ``<!-- claims:begin -->`` and ``<!-- claims:end -->``
    replaced by ``block``; ValueError when the markers are missing."""
    if not BLOCK.search(text):
        raise ValueError("no <!-- claims:begin --> ... <!-- claims:end --> block")
    return BLOCK.sub(lambda m: m.group(1) + block.strip() + "\n" + m.group(3), text, count=1)


def main(argv=None) -> int:
    """Print the claims block from the bundled rows; ``--write FILE ...`` puts it into each file
    between its markers (README.md, docs/baselines.md)."""
    argv = sys.argv[1:] if argv is None else argv
    block = readme_block(load_reference())
    if not argv:
        print(block)
        return 0
    if argv[0] != "--write" or len(argv) < 2:
        print("usage: python -m sfm_learn.experiments.claims [--write FILE ...]", file=sys.stderr)
        return 2
    from sfm_common.files import atomic_write_text

    for path in argv[1:]:
        with open(path, encoding="utf-8") as f:
            text = f.read()
        try:
            atomic_write_text(path, replace_block(text, block))
        except ValueError as e:
            print(f"{path}: {e}", file=sys.stderr)
            return 1
        print(f"updated {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
