"""Plots (matplotlib, Agg). Each function takes ``ax=`` (or ``axes=``) and returns
the figure; ``save_figure`` writes atomically."""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np

from ._errors import ConfigError
from ._io import atomic_path
from ._predictive import PointingErrorLaw, prediction_region_d2, region_radius


def pyplot():
    """``matplotlib.pyplot``, imported on first use (matplotlib is the optional
    ``plot`` extra and costs ~0.5 s to import); switches to the headless Agg backend
    unless a notebook's inline backend is active. Raises ConfigError without it."""
    try:
        import matplotlib
    except ModuleNotFoundError as e:  # the 'plot' extra
        raise ConfigError("plots need matplotlib: pip install 'heliojax[plot]'") from e

    backend = matplotlib.get_backend().lower()
    if "inline" not in backend and backend != "agg" and not backend.startswith("module://"):
        matplotlib.use("Agg")  # headless default; notebooks keep their inline backend
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 120) -> None:
    """Save ``fig`` to ``path`` atomically (format from the suffix) and close it."""
    plt = pyplot()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png", bbox_inches="tight")
    plt.close(fig)


def plot_error_per_heliostat(ids, errors_mrad, *, ax=None, title=None, label="beam pointing error [mrad]"):
    """Box plot of per-record errors ``(H, M)`` (NaN = no record) per heliostat."""
    plt = pyplot()
    fig = ax.figure if ax is not None else plt.figure(figsize=(max(6, 0.35 * len(ids)), 4))
    ax = ax or fig.add_subplot(111)
    data = [e[np.isfinite(e)] for e in np.asarray(errors_mrad)[: len(ids)]]
    keep = [i for i, d in enumerate(data) if d.size]
    ax.boxplot([data[i] for i in keep], showfliers=True)
    ax.set_xticks(range(1, len(keep) + 1))
    ax.set_xticklabels([ids[i] for i in keep], rotation=90)
    ax.set_yscale("log")
    ax.set_ylabel(label)
    ax.set_xlabel("heliostat")
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    return fig


def _residual_panel(ax, pts, flagged, title, color, lim=None, errors=None):
    """Scatter of residual pairs (mrad) with flagged records marked; points outside
    the square ``lim`` are drawn on its edge (open triangles) and counted. The title's
    median and RMS are of ``errors`` (the same records' beam pointing errors, mrad, as
    summary.json counts them) where given, else of the pairs' lengths."""
    pts = pts[np.all(np.isfinite(pts), axis=1)] if pts.size else pts.reshape(0, 2)
    flagged = flagged[np.all(np.isfinite(flagged), axis=1)] if flagged.size else flagged.reshape(0, 2)
    if lim is None:
        lim = float(np.percentile(np.abs(pts), 95) * 1.5) if pts.size else 1.0
        lim = max(lim, 1e-3)
    inside = np.all(np.abs(pts) <= lim, axis=1)
    ax.scatter(pts[inside, 0], pts[inside, 1], s=6, alpha=0.6, color=color, label="records")
    if (~inside).any():
        edge = np.clip(pts[~inside], -lim, lim)
        ax.scatter(
            edge[:, 0],
            edge[:, 1],
            s=18,
            marker="^",
            facecolors="none",
            edgecolors=color,
            label=f"{int((~inside).sum())} beyond the axes (on the edge)",
        )
    if flagged.size:
        ax.scatter(
            *np.clip(flagged, -lim, lim).T,
            s=28,
            marker="x",
            color="tab:red",
            label=(
                f"{len(flagged)} training records flagged as outliers (robust fit)"
                if len(flagged) != 1
                else "1 training record flagged as an outlier (robust fit)"
            ),
        )
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.axhline(0, color="0.5", lw=0.5)
    ax.axvline(0, color="0.5", lw=0.5)
    ax.set_xlabel("horizontal miss [mrad]")
    ax.set_ylabel("vertical miss [mrad]")
    length = np.linalg.norm(pts, axis=1) if errors is None else np.asarray(errors, float)
    length = length[np.isfinite(length)]
    rms = np.sqrt(np.mean(length**2)) if length.size else np.nan
    med = np.median(length) if length.size else np.nan
    ax.set_title(f"{title}\n({length.size} records: median {med:.2f}, RMS {rms:.2f} mrad)")
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.18), frameon=False)


def plot_calibration(run, *, axes=None):
    """Per-heliostat held-out RMS before and after calibration (unfitted heliostats
    labelled with their status; change points, noise outliers, heliostats under
    the small-fleet prior and the worse-than-nominal flag marked), and the held-out residuals on the target
    (horizontal / vertical miss, mrad) before and after calibration, with the
    training records the robust fit flagged as outliers."""
    plt = pyplot()
    if axes is None:
        fig, axes = plt.subplots(1, 3, figsize=(18, 6), gridspec_kw={"width_ratios": [2.4, 1, 1]})
    else:
        fig = axes[0].figure
    summary = run.summary
    ids = list(summary["heliostats"])
    x = np.arange(len(ids))

    def col(key):
        return np.array(
            [np.nan if summary["heliostats"][h].get(key) is None else summary["heliostats"][h][key] for h in ids], float
        )

    ax = axes[0]
    ax.bar(x - 0.3, col("uncalibrated_test_rms_mrad"), 0.3, label="held-out, uncalibrated", color="0.7")
    ax.bar(x, col("train_rms_mrad"), 0.3, label="training, calibrated", color="tab:blue")
    ax.bar(x + 0.3, col("test_rms_mrad"), 0.3, label="held-out, calibrated", color="tab:orange")
    values = np.concatenate([col("uncalibrated_test_rms_mrad"), col("train_rms_mrad"), col("test_rms_mrad")])
    values = values[np.isfinite(values) & (values > 0)]
    top = float(values.max()) if values.size else 10.0
    bottom = float(values.min()) if values.size else 0.1
    ax.set_yscale("log")
    ax.set_ylim(bottom * 0.5, top * 90)
    marks = {  # key: marker, colour, legend, height above the tallest bar
        "change_point": ("v", "tab:purple", "change point: fitted since it", 1.4),
        "noise_outlier": ("D", "black", "noise outlier: left out of the fleet's statistics", 2.0),
        # never a noise outlier too (those are left out of it): the same height
        "small_fleet_prior": ("s", "tab:olive", "small-fleet prior: the fleet too small to learn one", 2.0),
        "worse_than_nominal": ("X", "tab:red", "worse than nominal (use the nominal model)", 2.9),
        "spots_off_target": ("P", "tab:brown", "spots mostly off target: not aimed with", 4.2),
    }
    for key, (marker, colour, label, height) in marks.items():
        flagged = [i for i, h in enumerate(ids) if summary["heliostats"][h].get(key)]
        if flagged:  # above the bars, below the status texts
            level = top * height
            ax.scatter(flagged, np.full(len(flagged), level), marker=marker, color=colour, s=40, label=label, zorder=3)
    for i, h in enumerate(ids):
        status = summary["heliostats"][h]["status"]
        if status != "converged":
            ax.text(
                i + 0.15,
                top * 4.5,
                status.replace("_", " "),
                rotation=90,
                ha="center",
                va="bottom",
                fontsize=7,
                color="tab:red",
            )
    ax.set_xticks(x)
    ax.set_xticklabels(ids, rotation=90)
    ax.set_xlim(-0.8, len(ids) - 0.2)
    ax.set_ylabel("RMS beam pointing error [mrad]")
    ax.set_xlabel("heliostat")
    ax.set_title(f"{summary['model']} model, {summary['split']} split (red: not calibrated, with the reason)")
    ax.legend(fontsize=8, loc="upper left", ncol=3)
    ax.grid(alpha=0.3, which="both")

    n = len(ids)
    test = np.asarray(run.test_mask)[:n] if np.any(run.test_mask) else np.asarray(run.fleet.mask)[:n]
    outlier = np.asarray(run.outlier)[:n] if run.outlier is not None else np.zeros_like(test)
    after = np.asarray(run.residuals_mrad)[:n]
    before = np.asarray(run.uncalibrated_residuals_mrad)[:n]
    # as summary.json's fleet figures: every heliostat before, the calibrated ones after
    calibrated = test & np.array([summary["heliostats"][h]["status"] == "converged" for h in ids])[:, None]
    _residual_panel(
        axes[1],
        before[test],
        before[outlier],
        "held-out records before calibration",
        "0.4",
        errors=np.asarray(run.uncalibrated_mrad)[:n][test],
    )
    _residual_panel(
        axes[2],
        after[calibrated],
        after[outlier & calibrated],
        "held-out records after calibration",
        "tab:orange",
        errors=np.asarray(run.errors_mrad)[:n][calibrated],
    )
    fig.tight_layout()
    return fig


def plot_aim(ids, pointing_cov_mrad2, ok, distance_m, hours=None, start=None, *, error_law=None, axes=None):
    """Error bars of aiming commands: 68 % prediction regions of the beam's landing
    point on the aim plane (cm; the beam's tangent plane scaled by each heliostat's
    distance) at the instant with most usable commands, and over the instants each
    heliostat's 68 % pointing radius (mrad, the region's semi-major axis). The
    predicted error law: scale ``pointing_cov_mrad2``, ``error_law`` a
    :class:`heliojax.PointingErrorLaw` (default Gaussian;
    :func:`heliojax.prediction_region_d2`). Flagged commands are left out."""
    plt = pyplot()
    from matplotlib.patches import Ellipse

    if axes is None:
        fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1, 1.5]})
    else:
        fig = axes[0].figure
    error_law = PointingErrorLaw() if error_law is None else error_law
    cov = np.asarray(pointing_cov_mrad2, float)
    ok = np.asarray(ok, bool)
    d2 = prediction_region_d2(0.68, error_law)
    radius = region_radius(np.linalg.eigvalsh(np.where(np.isfinite(cov), cov, 0.0))[..., -1], 0.68, error_law)
    radius = np.where(np.all(np.isfinite(cov), axis=(-2, -1)), radius, np.nan)
    j = int(np.argmax(ok.sum(axis=0)))
    ax = axes[0]
    colours = plt.get_cmap("viridis")(np.linspace(0, 1, max(len(ids), 2)))
    extent = 0.0
    for i in np.flatnonzero(ok[:, j] & np.all(np.isfinite(cov[:, j]), axis=(-2, -1))):
        vals, vecs = np.linalg.eigh(d2 * cov[i, j] * (distance_m[i] * 1e-3 * 100.0) ** 2)  # mrad^2 -> cm^2
        w, h = 2.0 * np.sqrt(np.clip(vals, 0.0, None))
        angle = float(np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1])))
        ax.add_patch(Ellipse((0.0, 0.0), float(h), float(w), angle=angle, fill=False, color=colours[i], lw=1))
        extent = max(extent, float(max(w, h)) / 2)
    extent = 1.15 * (extent or 1.0)
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    ax.axhline(0, color="0.6", lw=0.5)
    ax.axvline(0, color="0.6", lw=0.5)
    ax.set_xlabel("horizontal offset on the aim plane [cm]")
    ax.set_ylabel("vertical offset on the aim plane [cm]")
    if hours is None or start is None:
        when = f"instant {j}"
    else:
        when = f"{start + datetime.timedelta(hours=float(hours[j])):%Y-%m-%d %H:%M} UTC"
    flagged = int((~ok.any(axis=1)).sum())  # left out without a word, they looked forgotten
    ax.set_title(
        f"68 % landing regions of {int(ok[:, j].sum())} heliostats"
        + (f"\n({flagged} more with every command flagged: see the CSV's flags)" if flagged else "")
        + f"\n{when}; colours as in the right panel's legend",
        fontsize=10,
    )
    ax = axes[1]
    x = np.arange(radius.shape[1]) if hours is None or start is None else hours
    for i, hid in enumerate(ids):
        y = np.where(ok[i], radius[i], np.nan)
        if np.isfinite(y).any():
            ax.plot(x, y, marker="o", ms=3, lw=1, color=colours[i], label=hid)
    ax.set_xlabel("instant" if hours is None or start is None else f"hours after {start:%Y-%m-%d %H:%M} UTC")
    ax.set_ylabel("radius holding the beam with 68 % [mrad]")
    ax.set_title(f"predicted pointing uncertainty of the usable commands ({error_law.describe()})", fontsize=10)
    ax.grid(alpha=0.3)
    if not ok.any():  # empty axes and an empty legend said nothing
        for a in axes:
            a.text(
                0.5,
                0.5,
                "no usable command:\nevery one is flagged\n(see the CSV's flags column)",
                transform=a.transAxes,
                ha="center",
                va="center",
                fontsize=11,
                color="tab:red",
            )
    elif len(ids) <= 30:
        ax.legend(fontsize=7, ncol=2, loc="upper left", bbox_to_anchor=(1.01, 1.0), title="heliostat")
    fig.tight_layout()
    return fig


def plot_plan(ids, before_mrad, after_mrad, chosen, changed=None, *, max_bars: int = 40, discrepancy: bool = False):
    """A calibration plan: each heliostat's predicted pointing uncertainty over the
    operating envelope before and after its planned measurements (the ``max_bars``
    heliostats most in need, change points marked), and the fleet's uncertainty
    against the number of planned measurements (median and 10-90 % band).
    ``discrepancy``: the plan counted a model discrepancy (named in the title)."""
    plt = pyplot()
    before = np.asarray(before_mrad, float)
    after = np.asarray(after_mrad, float)
    chosen = np.asarray(chosen)
    h, k = after.shape
    changed = np.zeros(h, bool) if changed is None else np.asarray(changed, bool)
    curve = np.concatenate([before[:, None], np.where(chosen >= 0, after, np.nan)], axis=1)
    curve = np.fmin.accumulate(np.where(np.isnan(curve), np.inf, curve), axis=1)
    final = curve[:, -1]
    order = np.argsort(-before)[:max_bars]
    nb = order.size
    fig, axes = plt.subplots(
        1, 2, figsize=(max(10.0, 4.0 + 0.32 * nb), 5.0), gridspec_kw={"width_ratios": [max(2.0, nb / 8), 1]}
    )
    ax = axes[0]
    x = np.arange(nb)
    ax.bar(x - 0.2, before[order], 0.4, color="0.65", label="before (current knowledge)")
    ax.bar(x + 0.2, final[order], 0.4, color="tab:blue", label="after the planned measurements")
    if changed[order].any():
        top = float(np.max(before)) * 1.05
        ax.plot(
            x[changed[order]], np.full(int(changed[order].sum()), top), "v", color="tab:red", label="change point found"
        )
    ax.set_xticks(x, [ids[i] for i in order], rotation=90, fontsize=8)
    ax.set_xlabel(
        "heliostat (largest predicted uncertainty first)"
        if nb == h
        else f"the {nb} of {h} heliostats with the largest predicted uncertainty"
    )
    ax.set_ylabel("predicted pointing uncertainty over the envelope [mrad]")
    source = "parameter uncertainty and model discrepancy" if discrepancy else "parameter uncertainty"
    ax.set_title(f"predicted RMS pointing error from {source}", fontsize=10)
    ax.set_ylim(0.0, 1.45 * float(np.max(before[order])))  # room above the bars and markers for the legend
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(axis="y", alpha=0.3)
    ax = axes[1]
    n = np.arange(k + 1)
    ax.fill_between(
        n, np.percentile(curve, 10, axis=0), np.percentile(curve, 90, axis=0), color="tab:blue", alpha=0.2,
        label="10-90 % of heliostats",
    )  # fmt: skip
    ax.plot(n, np.median(curve, axis=0), "o-", color="tab:blue", label="median heliostat")
    ax.set_xlabel("planned measurements per heliostat")
    ax.set_ylabel("predicted pointing uncertainty [mrad]")
    ax.set_title("fleet, by number of measurements", fontsize=10)
    ax.set_xticks(n)
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


__all__ = ["plot_aim", "plot_calibration", "plot_error_per_heliostat", "plot_plan", "pyplot", "save_figure"]
