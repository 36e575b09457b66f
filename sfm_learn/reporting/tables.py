"""Evaluations as text: a plain table, a Markdown table, and cells with intervals."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from sfm_learn.evaluation.records import METRIC_KEYS, Evaluation

__all__ = ["METRIC_LABELS", "METRIC_DECIMALS", "format_table", "format_markdown", "format_cell",
           "seed_range", "short_name", "spectrum_lines", "study_markdown"]

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


def seed_range(e: Evaluation) -> str:
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
                f"policy on env seeds {seed_range(first)}; {ci_text}.")
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
            cells += [_md_escape(e.env), seed_range(e)]
        cells += [format_cell(e.metrics[k], ci.get(k), METRIC_DECIMALS[k]) for k in METRIC_KEYS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _md_escape(text: str) -> str:
    return str(text).replace("|", "\\|")


def short_name(name: str, width: int = 22) -> str:
    """A policy name for axis labels: paths reduced to their file name, then truncated."""
    prefix, sep, arg = name.partition(":")
    if sep and ("/" in arg or os.sep in arg):
        name = f"{prefix}:{os.path.basename(arg)}"
    return name if len(name) <= width else name[:width - 1] + "\u2026"



def _fmt(v) -> str:
    if v is None:
        return "-"
    return f"{v:.3f}"


def spectrum_lines(singular_values, rank: int, floor: float, limit: int = 60) -> list[str]:
    """The spectrum as text: index, singular value, adjacent ratio, the chosen rank marked."""
    s = np.asarray(singular_values, dtype=float)
    lines = ["   i   s_i          s_i/s_(i+1)"]
    for i in range(min(s.size, limit)):
        ratio = s[i] / s[i + 1] if i + 1 < s.size and s[i + 1] > 0 else float("nan")
        mark = "  <- n (largest ratio above the floor)" if i + 1 == rank else ""
        below = "  (below floor)" if s[i] <= floor else ""
        lines.append(f"  {i + 1:2d}   {s[i]:11.4g}  {ratio:10.3f}{mark}{below}")
    if s.size > limit:
        lines.append(f"  ... {s.size - limit} more")
    return lines


def _mean_range(values, digits: int) -> str:
    v = np.asarray(values, dtype=float)
    if v.size == 1:
        return f"{v[0]:.{digits}f}"
    return f"{v.mean():.{digits}f} [{v.min():.{digits}f}..{v.max():.{digits}f}]"


def study_markdown(result) -> str:
    """A :class:`~sfm_learn.evaluation.study.StudyResult` as a Markdown table: per
    configuration the mean over training sets, [min..max] where there are several."""
    from sfm_learn.evaluation.study import COLUMNS

    n_sets = result.values.shape[1]
    rng = " [min..max]" if n_sets > 1 else ""
    head = ("| configuration | rank n / known | free-running drive | free-running steer timing"
            " | onsets hit +-2 | MKVJam escape" + rng + " | MKV stuck | MKV distance [m] |")
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    for c, config in enumerate(result.configs):
        r = result.values[c]
        col = {name: r[:, k] for k, name in enumerate(COLUMNS)}
        ranks = col["rank"]
        rank = (f"{ranks[0]:.0f}" if np.all(ranks == ranks[0])
                else f"{ranks.min():.0f}..{ranks.max():.0f}")
        lines.append(
            f"| {config.label} | {rank} / {col['known'][0]:.0f} | {col['drive'].mean():.3f} | "
            f"{col['steer_timing'].mean():.3f} | {col['onset_hit_w2'].mean():.2f} | "
            f"{_mean_range(col['escape_rate'], 2)} | {col['stuck_fraction'].mean():.3f} | "
            f"{col['distance_m'].mean():.1f} |")
    return "\n".join(lines)


#: Rows of :func:`comparison_table`: (label, agreement key, with interval).
COMPARISON_ROWS = (
    ("drive", "drive", False),
    ("steer timing (steer or not)", "steer_timing", False),
    ("steer direction (both steer)", "steer_direction", False),
    ("steer onset hit, +-1 step", "onset_hit_w1", True),
    ("steer onset hit, +-2 steps", "onset_hit_w2", True),
    ("  ... by chance at that rate", "onset_hit_w2_chance", False),
    ("  ... and same side", "onset_same_side_w2", True),
    ("  side, among hits", "onset_side_given_hit_w2", True),
    ("  policy starts first (no leak)", "onset_hit_early_w2", True),
    ("  ... by chance at that rate", "onset_hit_early_w2_chance", False),
    ("  side, policy first", "onset_side_given_early_hit_w2", True),
    ("escape-turn onset hit, +-2", "onset_hit_w2_backoff", True),
    ("  side, among hits", "onset_side_given_hit_w2_backoff", True),
)


def comparison_table(cmp) -> str:
    """A :class:`~sfm_learn.evaluation.compare.Comparison` as a text table: one column per replay
    mode and baseline, one row per agreement metric (onset rows with 95% bootstrap intervals)."""
    cols = [("free-running", cmp.modes.get("free_running")),
            ("teacher-forced", cmp.modes.get("teacher_forced")),
            ("copy previous", cmp.baselines["copy_previous"]),
            ("constant", cmp.baselines["constant"])]
    cols = [(name, m) for name, m in cols if m is not None]
    width = 31
    lines = [f"{'agreement with the teacher':<{width}}" + "".join(f"{n:>22}" for n, _ in cols)]
    for label, key, with_ci in COMPARISON_ROWS:
        cells = []
        for _, m in cols:
            v = m.get(key)
            ci = m["ci"].get(key) if with_ci else None
            cells.append(format_cell(v, ci, 2 if ci else 3))
        lines.append(f"{label:<{width}}" + "".join(f"{c:>22}" for c in cells))
    first = cols[0][1]
    lines.append(f"{first['onsets']} teacher steer onsets ({first['backoff_onsets']} while "
                 "reversing: escape turns, side drawn at random); policy onsets: "
                 + ", ".join(f"{n} {m['policy_onsets']}" for n, m in cols[:2]))
    return "\n".join(lines)
