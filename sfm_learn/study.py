"""Which features does the linear SfM policy need? The feature-set study (docs/sfm.md).

:func:`feature_study` fits the policy with each configuration of :data:`CONFIGS` on one or more
teacher recordings and measures, per fit, open-loop agreement on held-out teacher runs
(:func:`sfm_learn.compare.compare`) and the closed loop: escape rate on ``MKVJam-v0`` and stuck
fraction / distance on ``MKV-v0`` (:func:`sfm_learn.evaluation.evaluate`, same seeds for every
configuration). ``scripts/sfm_feature_study.py`` runs it on three training sets; ``mkv demo``
runs it on the demo's own training data.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from sfm_learn.compare import compare
from sfm_learn.evaluation import evaluate
from sfm_learn.features import FeatureSpec
from sfm_learn.policy import fit_policy

__all__ = ["CONFIGS", "feature_study", "study_markdown"]

_NO_CURRENTS = ("drive_ticks", "roller_ticks", "steer_angle", "compass", "bump_front_left",
                "bump_front_right", "bump_rear", "battery")
_NO_BUMPS = ("drive_ticks", "roller_ticks", "steer_angle", "compass", "drive_current",
             "steer_current", "battery")
_T = (0.5, 0.8)

#: (name, FeatureSpec keyword arguments, fit_policy keyword arguments)
CONFIGS = [
    ("sensors only (paper)", {}, {}),
    ("sensors, lstsq solver", {}, {"solver": "lstsq"}),
    ("sensors + prev command", {"prev_action": "signed"}, {}),
    ("sensors + traces", {"trace_decays": _T}, {}),
    ("sensors + traces + prev (default)", {"trace_decays": _T, "prev_action": "signed"}, {}),
    ("default, lstsq solver", {"trace_decays": _T, "prev_action": "signed"},
     {"solver": "lstsq"}),
    ("default, one-hot commands", {"trace_decays": _T, "prev_action": "signed"},
     {"encoding": "onehot"}),
    ("sensors + 2-step history + prev", {"history": 2, "prev_action": "signed"}, {}),
    ("default without currents", {"channels": _NO_CURRENTS, "trace_decays": _T,
                                  "prev_action": "signed"}, {}),
    ("default without bumps", {"channels": _NO_BUMPS, "trace_decays": _T,
                               "prev_action": "signed"}, {}),
]
COLUMNS = ("rank", "known", "drive", "steer_timing", "escape_rate", "stuck_fraction",
           "distance_m")


def feature_study(trains: Sequence, held, *, jam_episodes: int = 100, wander_episodes: int = 20,
                  seed: int = 1000, configs=CONFIGS,
                  on_config: Callable[[str], None] | None = None) -> list[tuple[str, np.ndarray]]:
    """Fit every configuration on every training set; returns ``(name, results)`` pairs with
    ``results`` of shape (len(trains), len(COLUMNS))."""
    names = tuple(trains[0].sensor_names)
    rows = []
    for name, fkw, kw in configs:
        res = []
        for tr in trains:
            pol = fit_policy(tr, FeatureSpec(obs_names=names, **fkw), **kw)
            m = compare(pol, held).metrics
            ej = evaluate("MKVJam-v0", pol, jam_episodes, seed).metrics
            ew = evaluate("MKV-v0", pol, wander_episodes, seed).metrics
            res.append((pol.n_components, pol.projector.n_known_, m["drive"], m["steer_timing"],
                        ej["escape_rate"], ew["stuck_fraction"], ew["distance_m"]))
        rows.append((name, np.array(res, dtype=float)))
        if on_config is not None:
            on_config(name)
    return rows


def study_markdown(rows) -> str:
    """The study as a Markdown table (means over training sets; escape-rate range if several)."""
    several = len(rows[0][1]) > 1
    head = ("| features / fit | rank n / known | drive agr. | steer timing | MKVJam escape"
            + (" [min..max]" if several else "") + " | MKV-v0 stuck | MKV-v0 distance [m] |")
    lines = [head, "|---|---|---|---|---|---|---|"]
    for name, r in rows:
        m = r.mean(axis=0)
        esc = f"{m[4]:.2f}" + (f" [{r[:, 4].min():.2f}..{r[:, 4].max():.2f}]" if several else "")
        lines.append(f"| {name} | {m[0]:.0f} / {m[1]:.0f} | {m[2]:.3f} | {m[3]:.3f} | {esc} | "
                     f"{m[5]:.3f} | {m[6]:.1f} |")
    return "\n".join(lines)
