"""Plots (matplotlib, Agg). Each function takes ``ax=`` (or ``axes=``) and returns
the figure; ``save_figure`` writes atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._io import atomic_path


def _plt():
    try:
        import matplotlib
    except ModuleNotFoundError as e:  # the 'plot' extra
        from ._errors import ConfigError

        raise ConfigError("plots need matplotlib: pip install 'heliojax[plot]'") from e

    backend = matplotlib.get_backend().lower()
    if "inline" not in backend and backend != "agg" and not backend.startswith("module://"):
        matplotlib.use("Agg")  # headless default; notebooks keep their inline backend
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 120) -> None:
    """Save ``fig`` to ``path`` atomically (format from the suffix) and close it."""
    plt = _plt()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png", bbox_inches="tight")
    plt.close(fig)


def plot_error_per_heliostat(ids, errors_mrad, *, ax=None, title=None, label="beam pointing error [mrad]"):
    """Box plot of per-record errors ``(H, M)`` (NaN = no record) per heliostat."""
    plt = _plt()
    fig = ax.figure if ax is not None else plt.figure(figsize=(max(6, 0.35 * len(ids)), 4))
    ax = ax or fig.add_subplot(111)
    data = [e[np.isfinite(e)] for e in np.asarray(errors_mrad)[: len(ids)]]
    keep = [i for i, d in enumerate(data) if d.size]
    ax.boxplot([data[i] for i in keep], showfliers=True)
    ax.set_xticks(range(1, len(keep) + 1))
    ax.set_xticklabels([ids[i] for i in keep], rotation=90)
    ax.set_yscale("log")
    ax.set_ylabel(label)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    return fig


def plot_calibration(run, *, axes=None):
    """Per-heliostat train / test RMS before and after calibration, and the
    residuals on the target (horizontal / vertical miss, mrad) of the test records
    before and after calibration."""
    plt = _plt()
    if axes is None:
        fig, axes = plt.subplots(1, 3, figsize=(17, 4.8), gridspec_kw={"width_ratios": [2.2, 1, 1]})
    else:
        fig = axes[0].figure
    summary = run.summary
    ids = list(summary["heliostats"])
    x = np.arange(len(ids))

    def col(key):
        return np.array([np.nan if summary["heliostats"][h][key] is None else summary["heliostats"][h][key] for h in ids])

    ax = axes[0]
    ax.bar(x - 0.3, col("uncalibrated_test_rms_mrad"), 0.3, label="test, uncalibrated", color="0.7")
    ax.bar(x, col("train_rms_mrad"), 0.3, label="train, calibrated", color="tab:blue")
    ax.bar(x + 0.3, col("test_rms_mrad"), 0.3, label="test, calibrated", color="tab:orange")
    ax.set_xticks(x)
    ax.set_xticklabels(ids, rotation=90)
    ax.set_yscale("log")
    ax.set_ylabel("RMS beam pointing error [mrad]")
    ax.set_title(f"{summary['model']} model, {summary['split']} split")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")

    n = len(ids)
    test = np.asarray(run.test_mask)[:n] if np.any(run.test_mask) else np.asarray(run.fleet.mask)[:n]
    for ax, res, title, color in (
        (axes[1], np.asarray(run.uncalibrated_residuals_mrad)[:n], "before calibration", "0.4"),
        (axes[2], np.asarray(run.residuals_mrad)[:n], "after calibration", "tab:orange"),
    ):
        pts = res[test]
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        ax.scatter(pts[:, 0], pts[:, 1], s=6, alpha=0.6, color=color)
        lim = np.percentile(np.abs(pts), 98) * 1.3 if pts.size else 1.0
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.axhline(0, color="0.5", lw=0.5)
        ax.axvline(0, color="0.5", lw=0.5)
        ax.set_xlabel("horizontal miss [mrad]")
        ax.set_ylabel("vertical miss [mrad]")
        rms = np.sqrt(np.mean(np.sum(pts**2, axis=1))) if pts.size else np.nan
        ax.set_title(f"test-record residuals {title}\n(RMS {rms:.2f} mrad)")
        ax.set_aspect("equal")
    fig.tight_layout()
    return fig


__all__ = ["plot_calibration", "plot_error_per_heliostat", "save_figure"]
