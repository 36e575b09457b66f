"""Figures for ``calib trials``. The only module that imports matplotlib (Agg backend)."""

from __future__ import annotations

import numpy as np

from sfm_common.files import atomic_path


def _save(fig, path: str) -> str:
    """Write ``fig`` to ``path`` atomically (no half-written PNG on an error or Ctrl-C)."""
    plt = _plt()
    try:
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    finally:
        plt.close(fig)
    return path


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_spectra(spec: dict, path: str) -> str:
    """Singular values of raw Z (with offsets) for each trial; the proper rank is 4 (r+1)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for t, s in spec.items():
        ax.semilogy(np.arange(1, len(s) + 1), np.maximum(s, 1e-16), "o-", label=f"Trial {t}")
    ax.axvline(4.5, color="grey", ls="--", lw=1)
    ax.text(0.58, 0.55, "proper rank r+1 = 4", color="grey", transform=ax.transAxes)
    ax.set_xlabel("index")
    ax.set_ylabel("singular value of Z (counts)")
    ax.set_title("Singular-value spectrum of the raw data (one seed)")
    ax.legend()
    fig.tight_layout()
    return _save(fig, path)


def plot_noise_sweep(noise: dict, paper_points: dict, path: str) -> str:
    """Median mean-absolute offset error vs peak noise, both methods, IQR bands, paper's points."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    x = np.asarray(noise["peak_noise"])
    for m, c in (("centered", "C0"), ("paper", "C1")):
        d = noise[m]
        ax.plot(x, d["median"], "o-", color=c, label=f"{m} route (median, IQR band)")
        ax.fill_between(x, d["q25"], d["q75"], color=c, alpha=0.2)
    # Trial 4 mixes 15 and 25: plotted at its rms-equivalent peak noise
    px = {2: 3, 3: 15, 4: float(np.sqrt((6 * 15**2 + 2 * 25**2) / 8))}
    for t, v in paper_points.items():
        ax.plot(px[t], v, "k^", ms=8)
        ax.annotate(f"paper's Trial {t}", (px[t], v), textcoords="offset points", xytext=(5, -3))
    ax.set_xlabel("peak uniform noise (counts; signal peak 150)")
    ax.set_ylabel("mean |offset error| (counts)")
    ax.set_title("Offset error vs noise (Trial 3 offsets)")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.legend(loc="upper left")
    fig.tight_layout()
    return _save(fig, path)


def plot_cap_sweep(caps: dict, path: str) -> str:
    """Median (IQR band, max dotted) offset error vs the cap half-angle of force directions."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    x = np.asarray(caps["cap_deg"])
    for m, c in (("centered", "C0"), ("paper", "C1")):
        d = caps[m]
        ax.plot(x, d["median"], "o-", color=c, label=f"{m} route (median, IQR band)")
        ax.fill_between(x, d["q25"], d["q75"], color=c, alpha=0.2)
        ax.plot(x, d["max"], ":", color=c, label=f"{m} route (max)")
    ax.set_yscale("log")
    ax.set_xlabel("cap half-angle of force directions (deg; 180 = whole sphere)")
    ax.set_ylabel("mean |offset error| (counts)")
    ax.set_title(f"Offset error vs coverage (Trial {caps['trial']} noise)")
    ax.legend()
    fig.tight_layout()
    return _save(fig, path)
