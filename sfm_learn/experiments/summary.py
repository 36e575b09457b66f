"""A sweep's rows as curves: mean over training seeds with 95% intervals, a table and a plot.

For each (learner, budget, eval env, metric) the rows of the different training seeds give one
value each; the point is their mean and the band a 95% Student-t interval over seeds
(``mean +- t_{0.975, n-1} * sd / sqrt(n)``, clipped to a rate's [0, 1]; with a handful of
seeds, t rather than a bootstrap, whose intervals are too narrow at n = 5). Error rows are
counted and listed, never averaged.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

METRIC_LABELS = {
    "escape_rate": "escape rate",
    "distance_m": "distance per episode [m]",
    "stuck_fraction": "stuck fraction",
    "mean_return": "mean return",
}


def t_interval(values, level: float = 0.95) -> tuple[float, float, float]:
    """``(mean, lo, hi)``; lo = hi = mean for one value."""
    from scipy import stats

    v = np.asarray(values, dtype=float)
    m = float(v.mean())
    if len(v) < 2:
        return m, m, m
    sem = float(v.std(ddof=1) / math.sqrt(len(v)))
    if sem == 0.0:
        return m, m, m
    lo, hi = stats.t.interval(level, len(v) - 1, loc=m, scale=sem)
    return m, float(lo), float(hi)


BOUNDS = {"escape_rate": (0.0, 1.0), "stuck_fraction": (0.0, 1.0), "distance_m": (0.0, math.inf)}
"""Ranges of bounded metrics: their t-intervals are clipped to them."""


def aggregate(rows: list[dict]) -> dict:
    """``{(learner, env, metric): [(budget, steps_mean, mean, lo, hi, n), ...]}`` sorted by budget,
    from the ok rows; plus ``errors``: the error rows."""
    groups: dict = defaultdict(lambda: defaultdict(list))
    steps: dict = defaultdict(list)
    errors = []
    for r in rows:
        if r.get("status") != "ok":
            errors.append(r)
            continue
        steps[(r["learner"], r["budget"])].append(r.get("steps", r["budget"]))
        for env_id, metrics in r["metrics"].items():
            for k, v in metrics.items():
                if v is not None:
                    groups[(r["learner"], env_id, k)][r["budget"]].append(v)
    out = {}
    for key, by_budget in groups.items():
        pts = []
        for b in sorted(by_budget):
            m, lo, hi = t_interval(by_budget[b])
            lo_b, hi_b = BOUNDS.get(key[2], (-math.inf, math.inf))
            lo, hi = max(lo, lo_b), min(hi, hi_b)
            pts.append((b, float(np.mean(steps[(key[0], b)])), m, lo, hi, len(by_budget[b])))
        out[key] = pts
    return {"curves": out, "errors": errors}


def markdown_table(agg: dict, env_id: str, metric: str, units: dict[str, str]) -> str:
    """One Markdown table: a row per (learner, budget) for ``metric`` on ``env_id``."""
    lines = [f"{METRIC_LABELS.get(metric, metric)} on **{env_id}**, mean over training seeds "
             "[95% t-interval]", "",
             "| learner | budget | steps used | unit | value | seeds |",
             "|:---|---:|---:|:---|---:|---:|"]
    for (learner, env, m), pts in sorted(agg["curves"].items()):
        if env != env_id or m != metric:
            continue
        for b, steps, mean, lo, hi, n in pts:
            lines.append(f"| {learner} | {b:,} | {steps:,.0f} | {units.get(learner, 'steps')} | "
                         f"{mean:.3f} [{lo:.3f}, {hi:.3f}] | {n} |")
    return "\n".join(lines) + "\n"


def plot_curves(agg: dict, panels: list[tuple[str, str]], path: str,
                units: dict[str, str], title: str = "", rows: list[dict] | None = None) -> str:
    """Draw :func:`aggregate`'s curves (:func:`sfm_learn.reporting.plots.plot_sweep_curves`);
    with ``rows``, every training seed's value as a dot beside its learner's curve."""
    from sfm_learn.reporting.plots import plot_sweep_curves

    labels = {m: METRIC_LABELS.get(m, m) for _, m in panels}
    points: dict = defaultdict(list)
    for r in rows or ():
        if r.get("status") != "ok":
            continue
        for env_id, metric in panels:
            v = r["metrics"].get(env_id, {}).get(metric)
            if v is not None:
                points[(r["learner"], env_id, metric)].append((r.get("steps", r["budget"]), v))
    return plot_sweep_curves(agg["curves"], panels, path, units, labels, title, dict(points))


def combined_table(agg: dict, units: dict[str, str], columns) -> str:
    """One Markdown row per (learner, budget): ``columns`` are ``(env, metric, header)``;
    each cell is the mean over seeds [95% t-interval] ("-" where the learner was not
    evaluated on that env)."""
    lines = ["| learner | budget | " + " | ".join(h for *_, h in columns) + " | seeds |",
             "|:---|---:|" + "---:|" * len(columns) + "---:|"]
    learners = sorted({k[0] for k in agg["curves"]})
    for learner in learners:
        budgets = sorted({p[0] for k, pts in agg["curves"].items() if k[0] == learner
                          for p in pts})
        for b in budgets:
            cells, n = [], 0
            for env_id, metric, _ in columns:
                pt = next((p for p in agg["curves"].get((learner, env_id, metric), [])
                           if p[0] == b), None)
                if pt is None:
                    cells.append("-")
                    continue
                digits = 1 if metric == "distance_m" else 3
                cells.append(f"{pt[2]:.{digits}f} [{pt[3]:.{digits}f}, {pt[4]:.{digits}f}]")
                n = max(n, pt[5])
            unit = units.get(learner, "steps")
            lines.append(f"| {learner} | {b:,} {unit} | " + " | ".join(cells) + f" | {n} |")
    return "\n".join(lines) + "\n"


__all__ = ["aggregate", "combined_table", "markdown_table",
           "plot_curves", "t_interval"]
