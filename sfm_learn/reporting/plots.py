"""Plots of the learning side: Figure 3, the singular-value spectrum, learning cost, and the
evaluation bar plot.

The only module of the SfM side that draws with matplotlib (imported inside each function, so the
package works without the ``plots`` extra until a plot is asked for). Every function writes a PNG
atomically and returns its path.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from mkv_env.actions import VALUE_NAMES
from sfm_common.files import atomic_path
from sfm_learn.evaluation.records import METRIC_KEYS, Evaluation
from sfm_learn.reporting.tables import METRIC_LABELS, seed_range, short_name

__all__ = ["plot_figure3", "plot_spectrum", "plot_learning_cost", "plot_evaluations",
           "plot_rank_study", "plot_sweep_curves",
           "MatplotlibMissing"]

_COMMAND_TICKS = VALUE_NAMES  # axis labels of each command's three values


class MatplotlibMissing(ImportError):
    """Plotting was asked for but matplotlib is not installed."""


def _pyplot():
    try:
        import matplotlib

        if not os.environ.get("MPLBACKEND"):
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise MatplotlibMissing("plots need matplotlib (pip install 'mkv-sfm[plots]')") from None
    return plt


def _save(fig, path) -> str:
    plt = _pyplot()
    path = os.fspath(path)
    try:
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    finally:
        plt.close(fig)
    return path


def plot_figure3(time_s, teacher, policy, path, *, title=None, metrics=None, bumps=None,
                 policy_label="SfM policy") -> str:
    """The paper's Figure 3: teacher vs SfM commands over time, one panel per command.

    Args:
        time_s: (n,) times [s].
        teacher, policy: (n, 2) action indices [drive, steer] (0 = reverse/left, 1 = off,
            2 = forward/right).
        path: output PNG.
        title: figure title.
        metrics: optional agreement dict (:func:`~sfm_learn.evaluation.compare.agreement`) for
            the panel
            titles.
        bumps: optional (n,) booleans, marked as ticks on the drive panel (context).
    """
    plt = _pyplot()
    t = np.asarray(time_s, dtype=float)
    teacher = np.asarray(teacher)
    policy = np.asarray(policy)
    fig, axes = plt.subplots(2, 1, figsize=(11, 5.2), sharex=True)
    for j, (ax, name) in enumerate(zip(axes, ("drive", "steer"), strict=True)):
        ta, pa = teacher[:, j] - 1, policy[:, j] - 1
        ax.step(t, ta + 0.06, where="post", color="0.2", lw=2.2, label="teacher")
        ax.step(t, pa - 0.06, where="post", color="tab:orange", lw=1.4, label=policy_label)
        if name == "drive":
            differ = ta != pa
        else:
            differ = (ta != 0) != (pa != 0)  # timing: steer vs no steer
        ax.fill_between(t, -1.35, 1.35, where=differ, step="post", color="tab:red", alpha=0.12,
                        lw=0, label="disagree" if name == "drive" else "disagree (timing)")
        ax.set_yticks([-1, 0, 1], _COMMAND_TICKS[name])
        ax.set_ylim(-1.4, 1.4)
        label = f"{name} command"
        if metrics is not None:
            if name == "drive":
                label += f"  (agreement {metrics['drive']:.0%})"
            else:
                d = metrics.get("steer_direction")
                label += (f"  (timing agreement {metrics['steer_timing']:.0%}, direction "
                          + ("n/a" if d is None else f"{d:.0%}") + ")")
        ax.set_title(label, loc="left", fontsize=10)
        ax.grid(axis="x", alpha=0.3)
        if name == "drive" and bumps is not None and np.any(bumps):
            bt = t[np.asarray(bumps, dtype=bool)]
            ax.plot(bt, np.full(bt.shape, 1.28), "|", color="tab:blue", ms=7, label="bump")
    axes[0].legend(loc="lower right", fontsize=8, ncol=4, framealpha=0.9)
    axes[1].set_xlabel("time [s]")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


def plot_spectrum(singular_values, rank, path, *, floor=None, title=None) -> str:
    """Singular values (log scale) with the chosen rank and the rank floor marked, and the
    adjacent ratios ``s_i / s_{i+1}`` the rank rule compares."""
    plt = _pyplot()
    s = np.asarray(singular_values, dtype=float)
    idx = np.arange(1, s.size + 1)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    ax.semilogy(idx, np.maximum(s, 1e-300), "o-", ms=4, color="tab:blue")
    ax.semilogy(idx[:rank], np.maximum(s[:rank], 1e-300), "o", ms=6, color="tab:orange",
                label=f"kept: n = {rank}")
    ax.axvline(rank + 0.5, color="tab:orange", ls="--", lw=1)
    if floor is not None and floor > 0:
        ax.axhline(floor, color="0.5", ls=":", lw=1, label=f"floor {floor:.3g}")
    ax.set_xlabel("index i")
    ax.set_ylabel("singular value s_i (standardised data)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    if s.size > 1:
        ratios = s[:-1] / np.maximum(s[1:], 1e-300)
        ok = np.isfinite(ratios) & (s[1:] > (floor or 0))
        ax2.bar(idx[:-1][ok], ratios[ok], color="tab:blue", width=0.7)
        if 1 <= rank < s.size:
            ax2.bar([rank], [ratios[rank - 1]], color="tab:orange", width=0.7,
                    label=f"s_{rank} / s_{rank + 1}")
            ax2.legend(fontsize=8)
        ax2.set_xlabel("i")
        ax2.set_ylabel("adjacent ratio s_i / s_(i+1) (above the floor)")
        ax2.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


def plot_learning_cost(curve, points, path, *, metric="escape_rate", ylabel=None,
                       title=None, reference=None) -> str:
    """PPO's learning curve (score vs env steps) with other learners as points.

    Args:
        curve: list of dicts with ``env_steps`` and ``metric`` (PPO's periodic evaluations).
        points: list of ``(label, steps, score)``, e.g. ``("SfM (teacher steps)", 12000, 0.96)``.
        reference: optional ``(label, score)`` drawn as a horizontal line (the teacher).
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    xs = [c["env_steps"] for c in curve if c.get(metric) is not None]
    ys = [c[metric] for c in curve if c.get(metric) is not None]
    if xs:
        ax.plot(xs, ys, "o-", ms=3, color="tab:blue", label="PPO (env steps)")
    markers = iter(["s", "D", "^", "v", "P"])
    colours = iter(["tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink"])
    for label, steps, score in points:
        if score is None:
            continue
        ax.plot([steps], [score], next(markers), ms=9, color=next(colours), label=label)
    if reference is not None and reference[1] is not None:
        ax.axhline(reference[1], color="0.4", ls="--", lw=1, label=reference[0])
    ax.set_xlim(left=0)
    ax.set_xlabel("training data: steps (teacher steps for SfM/BC, env steps for PPO)")
    ax.set_ylabel(ylabel or metric.replace("_", " "))
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def plot_evaluations(evaluations: Sequence[Evaluation], path: str,
                     title: str | None = None, dpi: int = 120) -> None:
    """Bar plot of every metric: one panel per metric, one bar per policy, bootstrap CIs as error
    bars, written atomically to ``path`` (format from its extension, e.g. ``.png``, ``.pdf``).

    Needs matplotlib (``pip install 'mkv-sfm[plots]'``; ImportError otherwise). Uses the
    object-oriented API without pyplot, so no display or backend set-up is needed.
    """
    from matplotlib.figure import Figure

    if not evaluations:
        raise ValueError("no evaluations to plot")
    names = [short_name(e.policy) for e in evaluations]
    colors = [f"C{i % 10}" for i in range(len(evaluations))]
    x = np.arange(len(evaluations))
    n_cols = 3
    n_rows = math.ceil(len(METRIC_KEYS) / n_cols)
    width = max(10.0, 1.1 * n_cols * max(2.0, 0.55 * len(evaluations)))
    fig = Figure(figsize=(width, 3.4 * n_rows + 0.9), dpi=dpi)
    axes = fig.subplots(n_rows, n_cols, squeeze=False).ravel()
    for ax, key in zip(axes, METRIC_KEYS, strict=False):
        vals = [e.metrics[key] for e in evaluations]
        cis = [(e.metrics_ci or {}).get(key) for e in evaluations]
        if all(v is None for v in vals):
            ax.text(0.5, 0.5, "undefined\n(the env reports no escapes,\nor none escaped)",
                    transform=ax.transAxes, ha="center", va="center", fontsize=9, color="0.4")
        for i, (v, ci) in enumerate(zip(vals, cis, strict=True)):
            if v is None:
                if not all(u is None for u in vals):
                    ax.text(x[i], 0.0, "n/a", ha="center", va="bottom", fontsize=9,
                            color="0.4")
                continue
            err = None
            if ci is not None:
                err = [[max(v - ci[0], 0.0)], [max(ci[1] - v, 0.0)]]
            ax.bar(x[i], v, width=0.7, color=colors[i], yerr=err, capsize=4,
                   error_kw={"elinewidth": 1.2, "ecolor": "0.15"})
        ax.set_title(METRIC_LABELS[key], fontsize=10)
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=25 if len(evaluations) > 2 else 0,
                           ha="right" if len(evaluations) > 2 else "center", fontsize=9)
        ax.set_xlim(-0.6, len(evaluations) - 0.4)
        ax.axhline(0.0, color="0.3", linewidth=0.8)
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
        ax.tick_params(axis="y", labelsize=9)
        if key in ("escape_rate", "stuck_fraction"):
            lo, hi = ax.get_ylim()
            ax.set_ylim(min(lo, 0.0), max(hi, 1.05) if key == "escape_rate" else hi)
        if all(v is None for v in vals):
            ax.set_yticks([])
    for ax in axes[len(METRIC_KEYS):]:
        ax.set_visible(False)
    if title is None:
        e = evaluations[0]
        level = f"{100 * e.ci_level:g}%" if e.metrics_ci is not None else ""
        title = (f"{e.env}: {e.episodes} episodes per policy, seeds {seed_range(e)}"
                 + (f"; error bars: {level} bootstrap CI" if level else ""))
    fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    ext = os.path.splitext(path)[1].lstrip(".").lower() or "png"
    with atomic_path(path, f".{ext}") as tmp:
        fig.savefig(tmp, format=ext)


def plot_rank_study(results: dict, path, *, teacher: dict | None = None, title=None) -> str:
    """Closed-loop and free-running metrics against the kept rank n, one line per preset
    (``{"default": StudyResult, "paper": StudyResult}``), mean over training sets with the
    [min, max] band, the rank the largest-ratio rule picks marked. ``teacher`` may hold the
    teacher's ``escape_rate`` / ``distance_m`` on the same seeds (dashed reference lines)."""
    plt = _pyplot()
    panels = (("escape_rate", "MKVJam-v1 escape rate"),
              ("steer_timing", "free-running steer timing agreement"),
              ("onset_hit_w2", "teacher steer onsets hit within +-2 steps"),
              ("distance_m", "MKV-v1 distance per episode [m]"))
    fig, axes = plt.subplots(1, len(panels), figsize=(16, 4))
    for color, (preset, res) in zip(("tab:orange", "tab:blue", "tab:green"), results.items(),
                                    strict=False):
        n = res.column("rank")[:, 0]
        rule = int(np.bincount(res.rule_rank.ravel()).argmax())
        for ax, (key, label) in zip(axes, panels, strict=True):
            v = res.column(key)
            ax.plot(n, v.mean(axis=1), "o-", ms=3, color=color, label=preset)
            ax.fill_between(n, v.min(axis=1), v.max(axis=1), color=color, alpha=0.18, lw=0)
            if rule in n:
                i = int(np.flatnonzero(n == rule)[0])
                ax.plot([rule], [v[i].mean()], "*", ms=13, color=color, mec="k",
                        label=f"{preset}: rule's pick n = {rule}")
            ax.set_title(label, fontsize=10)
            ax.set_xlabel("kept rank n")
            ax.grid(alpha=0.3)
    if teacher:
        for ax, (key, _) in zip(axes, panels, strict=True):
            if teacher.get(key) is not None:
                ax.axhline(teacher[key], color="0.3", ls="--", lw=1, label="teacher")
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


def plot_sweep_curves(curves: dict, panels, path, units: dict, labels: dict,
                      title: str = "", points: dict | None = None) -> str:
    """A sweep's curves, one panel per ``(env, metric)``: a line per learner (mean over training
    seeds) with its 95% band, against steps on a log axis (teacher steps solid, env steps
    dashed). ``curves[(learner, env, metric)]`` holds ``(budget, steps, mean, lo, hi, n)``;
    ``points[(learner, env, metric)]``, if given, ``(steps, value)`` of every training seed,
    drawn as faint dots (nudged sideways per learner) so the spread over seeds shows."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.2), squeeze=False)
    learners = sorted({k[0] for k in curves})
    colours = {name: plt.cm.tab10(i % 10) for i, name in enumerate(learners)}
    kinds = {units.get(n, "steps") for n in learners}
    xlabel = ("teacher steps (solid) / PPO env steps (dashed)" if len(kinds) > 1
              else next(iter(kinds), "steps"))
    for ax, (env_id, metric) in zip(axes[0], panels, strict=True):
        for k, learner in enumerate(learners):
            for steps, value in (points or {}).get((learner, env_id, metric), ()):
                ax.plot(steps * 1.04 ** (k - len(learners) / 2), value, ".", ms=3, alpha=0.35,
                        color=colours[learner])
            pts = curves.get((learner, env_id, metric))
            if not pts:
                continue
            x = [p[1] for p in pts]
            mean, lo, hi = ([p[i] for p in pts] for i in (2, 3, 4))
            dashed = units.get(learner) == "env steps"
            ax.plot(x, mean, "--" if dashed else "-", marker="o", ms=3, color=colours[learner],
                    label=f"{learner} ({units.get(learner, 'steps')})")
            ax.fill_between(x, lo, hi, color=colours[learner], alpha=0.15, lw=0)
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(labels.get(metric, metric))
        ax.set_title(env_id)
        ax.grid(alpha=0.3)
    handles = {}
    for ax in axes[0]:          # every learner once, whichever panel drew it
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, h)
    fig.legend(list(handles.values()), list(handles), fontsize=8, loc="lower center",
               ncol=min(len(handles), 6), frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    return _save(fig, path)
