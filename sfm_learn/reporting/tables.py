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


def study_markdown(rows) -> str:
    """The study as a Markdown table (means over training sets; escape-rate range if several)."""
    several = len(rows[0][1]) > 1
    head = ("| features / fit | rank n / known | drive agr. | steer timing | MKVJam escape"
            + (" [min..max]" if several else "") + " | MKV-v0 stuck | MKV-v0 distance [m] |")
    lines = [head, "|---|---|---|---|---|---|---|"]
    for config, r in rows:
        m = r.mean(axis=0)
        esc = f"{m[4]:.2f}" + (f" [{r[:, 4].min():.2f}..{r[:, 4].max():.2f}]" if several else "")
        lines.append(f"| {config.label} | {m[0]:.0f} / {m[1]:.0f} | {m[2]:.3f} | {m[3]:.3f} | "
                     f"{esc} | {m[5]:.3f} | {m[6]:.1f} |")
    return "\n".join(lines)
