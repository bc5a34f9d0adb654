"""Acceptance figures (matplotlib; each function takes ``ax=None`` and returns the figure)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import spatial

from .._io import atomic_path
from .._plotting import pyplot
from ._extrapolate import Extrapolation
from ._yield import YieldResult


def _axes(ax, figsize=(6.5, 5.0)):
    if ax is None:
        fig, ax = pyplot().subplots(figsize=figsize)
        return fig, ax
    return ax.figure, ax


AXIS_LABELS = {
    "tracking_mrad": "tracking error, radial RMS [mrad]",
    "slope_mrad": "slope error, radial RMS [mrad]",
    "reflectance": "solar-weighted specular reflectance [-]",
    "aperture_m2": "net reflective aperture [m$^2$]",
}
"""Axis labels (with units) of the acceptance parameters."""
AXIS_UNITS = {"tracking_mrad": "mrad", "slope_mrad": "mrad", "reflectance": "-", "aperture_m2": "m$^2$"}


def plot_field_map(
    positions: np.ndarray,
    tracking_mrad: np.ndarray,
    measured: np.ndarray,
    labels: np.ndarray | None = None,
    *,
    ax=None,
):
    """Field map: heliostats sized by tracking error (measured: filled, extrapolated:
    open), coloured by cluster label, with the outline (convex hull) of every
    anomalous cluster.

    Args:
        positions: ``(n, 2|3)`` ENU m.
        tracking_mrad: ``(n,)`` tracking errors (measured or extrapolated).
        measured: ``(n,)`` mask of measured heliostats.
        labels: ``(n,)`` cluster label per heliostat (0 = main population).
    """
    fig, ax = _axes(ax)
    xy = np.asarray(positions)[:, :2]
    t = np.asarray(tracking_mrad, dtype=float)
    meas = np.asarray(measured, dtype=bool)
    lab = np.zeros(len(xy), dtype=int) if labels is None else np.asarray(labels)
    size = 6.0 + 60.0 * (t / np.nanmax(t)) ** 2
    colours = np.array(["tab:blue", "tab:red", "tab:orange", "tab:purple", "tab:green", "tab:brown"])
    col = colours[np.minimum(lab, len(colours) - 1)]
    if (~meas).any():  # an empty scatter had left a legend entry without a symbol
        ax.scatter(
            xy[~meas, 0],
            xy[~meas, 1],
            s=size[~meas],
            facecolors="none",
            edgecolors=col[~meas],  # pyright: ignore[reportArgumentType]
            linewidths=0.5,
            alpha=0.6,
            label="extrapolated",
        )
    ax.scatter(xy[meas, 0], xy[meas, 1], s=size[meas], c=col[meas], edgecolors="k", linewidths=0.4, label="measured")
    for k in range(1, int(lab.max(initial=0)) + 1):  # loop over clusters
        pts = xy[(lab == k) & meas]
        if len(pts) >= 3:
            try:
                hull = spatial.ConvexHull(pts)
            except spatial.QhullError:
                continue
            ring = pts[np.r_[hull.vertices, hull.vertices[0]]]
            ax.plot(ring[:, 0], ring[:, 1], "-", color=colours[min(k, len(colours) - 1)], lw=1.5, label=f"cluster {k}")
    ax.plot([0], [0], "k^", ms=8, label="tower")
    finite = t[np.isfinite(t)]
    if finite.size:  # the marker-size scale
        for ref in np.unique(np.round(np.nanpercentile(finite, [10, 50, 100]), 1)):
            s_ref = 6.0 + 60.0 * (ref / np.nanmax(t)) ** 2
            ax.scatter([], [], s=s_ref, facecolors="none", edgecolors="0.3", label=f"{ref:g} mrad")
    ax.set_aspect("equal")
    ax.set_xlabel("east of the tower [m]")
    ax.set_ylabel("north of the tower [m]")
    anomalous = int(lab.max(initial=0))
    ax.set_title(
        "tracking error (marker size), "
        + (f"{anomalous} anomalous cluster(s) outlined" if anomalous else "no anomalous cluster (one population)")
    )
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    return fig


def plot_cluster_distributions(
    values: np.ndarray,
    labels: np.ndarray,
    extrapolation: Extrapolation | None = None,
    *,
    name: str = "tracking_mrad",
    ax=None,
):
    """Histogram of the measured values per cluster, with the cluster KDE curves.

    Args:
        values: ``(m,)`` measured values.
        labels: ``(m,)`` their cluster labels.
        extrapolation: optional, supplies the KDE of each cluster.
        name: parameter name for the axis label.
    """
    fig, ax = _axes(ax)
    v = np.asarray(values, dtype=float)
    lab = np.asarray(labels)
    # every acceptance parameter is non-negative: no density drawn below zero
    grid = np.linspace(max(0.0, v.min() - 0.2 * np.ptp(v)), v.max() + 0.2 * np.ptp(v) + 1e-9, 400)
    colours = ["tab:blue", "tab:red", "tab:orange", "tab:purple", "tab:green", "tab:brown"]
    for k in np.unique(lab):
        c = colours[min(int(k), len(colours) - 1)]
        sel = v[lab == k]
        ax.hist(
            sel,
            bins=max(5, int(np.sqrt(sel.size)) + 2),
            density=True,
            alpha=0.35,
            color=c,
            label=f"cluster {k} (n={sel.size})",
        )
        if extrapolation is not None and int(k) in extrapolation.kdes:
            ax.plot(grid, extrapolation.kdes[int(k)].pdf(np.maximum(grid, 1e-12)), color=c, lw=1.5)
    ax.set_xlabel(AXIS_LABELS.get(name, name))
    ax.set_ylabel(f"probability density [1/{AXIS_UNITS.get(name, 'unit')}]")
    ax.set_title("distribution per cluster (histogram: measured; line: KDE)")
    ax.legend(fontsize=7)
    return fig


def plot_monthly_efficiency(contract: YieldResult, measured: YieldResult | None, *, ax=None):
    """Monthly DNI-weighted field efficiency, contract against measured values
    (``measured`` None: level 2 not assessed, nothing measured; the contract alone)."""
    fig, ax = _axes(ax, figsize=(6.5, 4.0))
    months = np.arange(1, 13)
    ax.plot(months, contract.monthly, "o-", label=f"contract (annual {contract.annual:.4f})")
    if measured is not None:
        ax.plot(months, measured.monthly, "s--", label=f"measured (annual {measured.annual:.4f})")
    else:
        ax.plot([], [], " ", label="measured: not assessed (nothing measured on >= 2 heliostats)")
    ax.set_xticks(months)
    ax.set_xticklabels(list("JFMAMJJASOND"))
    ax.set_xlabel("month")
    ax.set_ylabel("field efficiency")
    ax.set_title("monthly field efficiency")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.15))  # below the axes: never on a curve
    return fig


def plot_all(result, directory) -> list:
    """Write the three acceptance figures of an :class:`AcceptanceResult` as PNGs
    (atomically) into ``directory``; returns the paths."""
    plt = pyplot()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    out = []
    ex = result.extrapolations.get("tracking_mrad")
    cr = result.clusters.get("tracking_mrad")
    figs = {}
    if ex is not None and cr is not None:
        figs["field_map.png"] = plot_field_map(result.field.positions, ex.values, ex.measured, ex.labels)
        meas = np.isfinite(np.asarray(result.field.values["tracking_mrad"]))
        figs["cluster_distributions.png"] = plot_cluster_distributions(
            np.asarray(result.field.values["tracking_mrad"])[meas], cr.labels, ex
        )
    figs["monthly_efficiency.png"] = plot_monthly_efficiency(result.yield_contract, result.yield_measured)
    for fname, fig in figs.items():
        with atomic_path(directory / fname) as tmp:
            fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
        plt.close(fig)
        out.append(directory / fname)
    return out
