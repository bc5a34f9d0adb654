"""Open-world diagnostics: residual structure against every recorded variable.

The effect library cannot know every effect a plant has. After the library
effects are named, the final model's training residuals are tested against
every variable a record carries (:func:`record_variables`): time, UTC time of
day, sun azimuth and elevation, each axis's motor counts and approach
direction, the target, the spot position on the target, temperature, wind
speed and direction, and the heliostat's position in the field.

Test (per variable): each heliostat's residual components are standardised by
its own noise level (``sqrt(RSS_h / dof_h)``), the records are grouped into
bins of the variable (:data:`N_BINS` quantile bins pooled over the fleet; the
categories of a categorical variable), and a one-way analysis of variance of
both components together gives ``F = (SS_between / (2 (B - 1))) / (SS_within /
(2 (N - B)))``, referred to ``F(2 (B - 1), 2 (N - B))``. A bin needs
:data:`MIN_PER_BIN` records. The variables are selected forward: the most
significant variable is reported when its p-value passes Holm's threshold
``alpha / (number of variables still in the family)``; its binned means are
then removed from the residuals and the remaining variables are tested again,
so that a variable that only echoes a reported one (time of day and sun
azimuth) is not reported as well. The effect size is the RMS over records of
the binned-mean curve (mrad, both components).

Each variable is tested in two forms. The *fleet* form above finds a dependence
that the heliostats share. The *per-heliostat* form finds one whose shape differs
from heliostat to heliostat (a daily tilt of each pylon with its own phase: the
fleet's binned means of such a structure average out): cells are (heliostat, bin)
with at least 2 records, each heliostat's own mean is taken out, and the analysis
of variance of both components gives ``F = (SS_cells / (2 (C - H'))) /
(SS_within / (2 (N - C)))`` over ``C`` cells of ``H'`` heliostats, referred to
``F(2 (C - H'), 2 (N - C))`` (bins of one variable are fixed by the variable, not
by the residuals, so the test is exact under Gaussian noise; the fit's residuals
make it conservative). Both forms of every variable are one Holm family, and the
forward selection removes the chosen form's means (per cell for the per-heliostat
form). An entry says which form it is (``"form"``: ``"fleet"`` or
``"per_heliostat"``).

The residuals of the final model include whatever the library effects named
before explained, so a significant variable is structure *no named effect
explains*: it is reported under ``"unexplained"``, never given a library name.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import stats

from ..fitting import (
    DayClustering as DayClustering,
    day_clustering as day_clustering,
    day_labels as day_labels,
    heliostat_noise as heliostat_noise,
)

N_BINS = 8
"""Quantile bins of a continuous variable (a design choice, not tuned on data)."""

MIN_PER_BIN = 5
"""Records a bin needs to take part in the test."""

CONTINUOUS, CATEGORICAL = "continuous", "categorical"


@dataclasses.dataclass(frozen=True)
class Variable:
    """A recorded variable per record ``(H, M)`` (NaN where unknown).

    Attributes:
        name: machine name (report key).
        label: axis label with unit.
        values: ``(H, M)``.
        kind: ``"continuous"`` or ``"categorical"``.
    """

    name: str
    label: str
    values: np.ndarray
    kind: str = CONTINUOUS


def predicted_spot(fleet, residuals_mrad: np.ndarray | None) -> np.ndarray:
    """``(H, M, 3)`` ENU m: where the model puts each record's spot on its target.

    A residual structure must not be tested against the *measured* spot: the
    measurement noise is in both, and binning by a noisy copy of the response
    shows structure where there is none (regression dilution). The model's
    spot is the measured direction from the heliostat with the residual
    components (``d . e1``, ``d . e2``, :func:`heliojax.beam_error_components`)
    taken out, intersected with the target plane (first order in the residual).
    Without residuals the measured spot is returned.
    """
    focal = np.asarray(fleet.focal_spot, float)
    if residuals_mrad is None:
        return focal
    pos = np.asarray(fleet.geometry.position, float)[:, None, :]
    d = focal - pos
    d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    up = np.array([0.0, 0.0, 1.0])
    e1 = np.cross(up, d)
    e1 /= np.maximum(np.linalg.norm(e1, axis=-1, keepdims=True), 1e-12)
    e2 = np.cross(d, e1)
    c = np.nan_to_num(np.asarray(residuals_mrad, float)) * 1e-3
    ray = d - c[..., :1] * e1 - c[..., 1:] * e2
    ti = np.clip(np.asarray(fleet.target_index), 0, None)
    centre = np.asarray(fleet.targets.centre, float)[ti]
    normal = np.asarray(fleet.targets.normal, float)[ti]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sum((centre - pos) * normal, axis=-1) / np.sum(ray * normal, axis=-1)
    return pos + s[..., None] * ray


def record_variables(fleet, residuals_mrad: np.ndarray | None = None) -> list[Variable]:
    """Every variable the records carry (:class:`Variable` list) from a padded fleet;
    the spot position is the model's (:func:`predicted_spot`, from the residuals
    ``(H, M, 2)`` mrad when given)."""
    ctx = fleet.context
    h, m = np.asarray(fleet.mask).shape
    sun = np.asarray(ctx.sun, float)
    t = np.asarray(ctx.unix_time, float)
    counts = np.asarray(fleet.counts, float)
    approach = np.asarray(ctx.approach, float)
    approach = np.where(approach == 0.0, np.nan, np.sign(approach))
    focal = predicted_spot(fleet, residuals_mrad)
    ti = np.clip(np.asarray(fleet.target_index), 0, None)
    centre = np.asarray(fleet.targets.centre, float)[ti]
    u_axis = np.asarray(fleet.targets.u_axis, float)[ti]
    v_axis = np.asarray(fleet.targets.v_axis, float)[ti]
    offset = focal - centre
    pos = np.broadcast_to(np.asarray(fleet.geometry.position, float)[:, None, :], (h, m, 3))
    t0 = np.nanmin(t) if np.isfinite(t).any() else 0.0
    azimuth = np.degrees(np.arctan2(sun[..., 0], sun[..., 1]))
    wind_from = np.degrees(np.asarray(ctx.wind_direction, float))
    return [
        Variable("time", "days since the first record", (t - t0) / 86400.0),
        Variable("time_of_day", "UTC time of day [h]", np.mod(t, 86400.0) / 3600.0),
        Variable("sun_azimuth", "sun azimuth [deg, north = 0, east = 90]", azimuth),
        Variable("sun_elevation", "sun elevation [deg]", np.degrees(np.arcsin(np.clip(sun[..., 2], -1.0, 1.0)))),
        Variable("counts_1", "axis-1 motor counts", counts[..., 0]),
        Variable("counts_2", "axis-2 motor counts", counts[..., 1]),
        Variable("approach_1", "axis-1 approach direction (-1 / +1)", approach[..., 0], CATEGORICAL),
        Variable("approach_2", "axis-2 approach direction (-1 / +1)", approach[..., 1], CATEGORICAL),
        Variable("target", "target (index in the tower file)", np.asarray(fleet.target_index, float), CATEGORICAL),
        Variable("spot_u", "model spot position on the target, horizontal [m]", np.sum(offset * u_axis, axis=-1)),
        Variable("spot_v", "model spot position on the target, vertical [m]", np.sum(offset * v_axis, axis=-1)),
        Variable("temperature", "ambient temperature [deg C]", np.asarray(ctx.temperature, float)),
        Variable("wind_speed", "wind speed [m/s]", np.asarray(ctx.wind_speed, float)),
        Variable("wind_direction", "wind direction [deg from north]", wind_from),
        Variable("field_east", "heliostat position, east [m]", pos[..., 0]),
        Variable("field_north", "heliostat position, north [m]", pos[..., 1]),
    ]


def bin_index(values: np.ndarray, use: np.ndarray, kind: str) -> np.ndarray:
    """Bin of every record ``(H, M)`` (-1 where unused, unknown or in a bin with fewer
    than :data:`MIN_PER_BIN` records)."""
    x = np.where(use, values, np.nan)
    ok = np.isfinite(x)
    idx = np.full(x.shape, -1, int)
    if ok.sum() < 2 * MIN_PER_BIN:
        return idx
    if kind == CATEGORICAL:
        cats, inv = np.unique(x[ok], return_inverse=True)
        del cats
        idx[ok] = inv
    else:
        edges = np.unique(np.quantile(x[ok], np.linspace(0.0, 1.0, N_BINS + 1)))
        if edges.size < 2:
            return idx
        idx[ok] = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, edges.size - 2)
    counts = np.bincount(idx[ok], minlength=int(idx.max()) + 1)
    small = counts < MIN_PER_BIN
    idx[(idx >= 0) & small[np.clip(idx, 0, None)]] = -1
    # renumber the remaining bins 0..B-1
    kept = np.unique(idx[idx >= 0])
    remap = np.full(int(idx.max()) + 2, -1)
    remap[kept] = np.arange(kept.size)
    return np.where(idx >= 0, remap[np.clip(idx, 0, None)], -1)


def anova(z: np.ndarray, idx: np.ndarray, design_effect: float = 1.0) -> tuple[float, np.ndarray]:
    """p-value of binned structure in ``z`` ``(H, M, 2)`` (bins ``idx``), and the bin
    means ``(B, 2)`` (see the module docstring); ``F`` divided by ``design_effect``
    (:func:`day_clustering`)."""
    ok = idx >= 0
    n_bins = int(idx.max()) + 1 if ok.any() else 0
    if n_bins < 2:
        return float("nan"), np.zeros((0, 2))
    zz = z[ok]
    b = idx[ok]
    n = np.bincount(b, minlength=n_bins).astype(float)
    means = np.stack([np.bincount(b, weights=zz[:, j], minlength=n_bins) / n for j in range(2)], axis=1)
    grand = zz.mean(axis=0)
    ss_between = float(np.sum(n[:, None] * (means - grand) ** 2))
    ss_within = float(np.sum((zz - means[b]) ** 2))
    d1, d2 = 2 * (n_bins - 1), 2 * (zz.shape[0] - n_bins)
    if d2 <= 0 or ss_within <= 0:
        return float("nan"), means
    f = (ss_between / d1) / (ss_within / d2) / design_effect
    return float(stats.f.sf(f, d1, d2)), means


MIN_PER_CELL = 2
"""Records a (heliostat, bin) cell needs in the per-heliostat form."""

FLEET, PER_HELIOSTAT = "fleet", "per_heliostat"


def per_heliostat_cells(idx: np.ndarray) -> np.ndarray:
    """``(H, M)`` the (heliostat, bin) cell of each record for the per-heliostat form
    (-1 outside a bin or in a cell with fewer than :data:`MIN_PER_CELL` records)."""
    h = idx.shape[0]
    n_bins = int(idx.max()) + 1 if (idx >= 0).any() else 0
    cell = np.where(idx >= 0, np.arange(h)[:, None] * max(n_bins, 1) + idx, -1)
    if n_bins > 0:
        sizes = np.bincount(cell[cell >= 0], minlength=h * n_bins)
        cell = np.where((cell >= 0) & (sizes[np.clip(cell, 0, None)] >= MIN_PER_CELL), cell, -1)
    return cell


def anova_per_heliostat(z: np.ndarray, idx: np.ndarray, design_effect: float = 1.0) -> tuple[float, np.ndarray]:
    """p-value of binned structure in ``z`` ``(H, M, 2)`` whose shape may differ
    between heliostats (cells = (heliostat, bin) of ``idx`` with at least
    :data:`MIN_PER_CELL` records, each heliostat's mean taken out; see the module
    docstring), and each record's cell mean minus its heliostat's mean ``(H, M, 2)``
    (0 outside the cells); ``F`` divided by ``design_effect`` (:func:`day_clustering`)."""
    h = idx.shape[0]
    cell = per_heliostat_cells(idx)
    ok = cell >= 0
    deviation = np.zeros(z.shape)
    if not ok.any():
        return float("nan"), deviation
    _, c = np.unique(cell[ok], return_inverse=True)
    _, k = np.unique(np.broadcast_to(np.arange(h)[:, None], idx.shape)[ok], return_inverse=True)
    zz = z[ok]
    n_c, n_k = np.bincount(c).astype(float), np.bincount(k).astype(float)
    mean_c = np.stack([np.bincount(c, weights=zz[:, j]) / n_c for j in range(2)], axis=1)
    mean_k = np.stack([np.bincount(k, weights=zz[:, j]) / n_k for j in range(2)], axis=1)
    dev = mean_c[c] - mean_k[k]
    deviation[ok] = dev
    ss_between = float(np.sum(dev**2))
    ss_within = float(np.sum((zz - mean_c[c]) ** 2))
    d1, d2 = 2 * (n_c.size - n_k.size), 2 * (zz.shape[0] - n_c.size)
    if d1 <= 0 or d2 <= 0 or ss_within <= 0:
        return float("nan"), deviation
    f = (ss_between / d1) / (ss_within / d2) / design_effect
    return float(stats.f.sf(f, d1, d2)), deviation


def anova_each_heliostat(z: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``(H,)`` per heliostat, the p-value of :func:`anova` of its own records alone
    (``z`` ``(H, M, 2)``, bins ``idx`` ``(H, M)``; the bins it has records in, each
    with at least one), all heliostats at once; NaN where the heliostat has fewer
    than ``2 MIN_PER_BIN`` records in bins or the test does not exist (fewer than two
    bins, no within-bin degrees of freedom or scatter)."""
    h = idx.shape[0]
    p = np.full(h, np.nan)
    ok = idx >= 0
    n_bins = int(idx.max()) + 1 if ok.any() else 0
    if n_bins < 2:
        return p
    heliostat = np.broadcast_to(np.arange(h)[:, None], idx.shape)[ok]
    cell = heliostat * n_bins + idx[ok]  # (heliostat, bin)
    zz = z[ok]
    count = np.bincount(cell, minlength=h * n_bins).reshape(h, n_bins)
    sums = np.stack([np.bincount(cell, weights=zz[:, j], minlength=h * n_bins) for j in range(2)], axis=-1)
    sums = sums.reshape(h, n_bins, 2)
    n = count.sum(axis=1)
    bins = (count > 0).sum(axis=1)
    means = sums / np.maximum(count, 1)[..., None]  # (H, B, 2)
    grand = sums.sum(axis=1) / np.maximum(n, 1)[:, None]
    ss_between = np.sum(count[..., None] * (means - grand[:, None, :]) ** 2, axis=(1, 2))
    within = np.sum((zz - means.reshape(-1, 2)[cell]) ** 2, axis=1)
    ss_within = np.bincount(heliostat, weights=within, minlength=h)
    d1, d2 = 2 * (bins - 1), 2 * (n - bins)
    valid = (n >= 2 * MIN_PER_BIN) & (bins >= 2) & (d2 > 0) & (ss_within > 0)
    f = (ss_between[valid] / d1[valid]) / (ss_within[valid] / d2[valid])
    p[valid] = stats.f.sf(f, d1[valid], d2[valid])
    return p


def unexplained_structure(
    variables: list[Variable],
    r: np.ndarray,
    use: np.ndarray,
    n_params: int,
    alpha: float,
    ids: list[str],
    design_effect: float = 1.0,
) -> tuple[list[dict], dict[str, float]]:
    """Forward selection of the variables residual structure depends on.

    Args:
        variables: from :func:`record_variables`.
        r: ``(H, M, 2)`` residual components (mrad) of the final model.
        use: ``(H, M)`` the records the model was fitted to.
        n_params: fitted parameters per heliostat.
        alpha: family-wise level (Holm over the variables).
        ids: heliostat ids.
        design_effect: the records' day-clustering design effect (:func:`day_clustering`;
            1: independent records), by which every ``F`` is divided.

    Returns:
        ``(entries, first_p)``: the reported variables in the order selected, each
        ``{"variable", "form", "label", "p", "p_holm", "effect_size_mrad",
        "heliostats"}`` (``form`` ``"fleet"`` or ``"per_heliostat"``; heliostats
        whose own test has p < ``alpha``), and every variable's p-value before any
        selection (the per-heliostat form under ``"<variable> (per heliostat)"``).
    """
    sigma = heliostat_noise(r, use, n_params)
    use = use & np.isfinite(sigma)[:, None] & np.all(np.isfinite(r), axis=-1)
    z = np.where(use[..., None], r / np.where(np.isfinite(sigma) & (sigma > 0), sigma, 1.0)[:, None, None], 0.0)
    raw = np.where(use[..., None], r, 0.0)
    bins = {v.name: bin_index(v.values, use, v.kind) for v in variables}

    def test(z_now: np.ndarray, name: str, form: str) -> float:
        idx = bins[name]
        if form == FLEET:
            return anova(z_now, idx, design_effect)[0]
        return anova_per_heliostat(z_now, idx, design_effect)[0]

    def key(name: str, form: str) -> str:
        return name if form == FLEET else f"{name} (per heliostat)"

    by_name = {v.name: v for v in variables}
    first = {key(v.name, f): test(z, v.name, f) for v in variables for f in (FLEET, PER_HELIOSTAT)}
    remaining = [(v.name, f) for v in variables for f in (FLEET, PER_HELIOSTAT) if np.isfinite(first[key(v.name, f)])]
    entries: list[dict] = []
    running = 0.0
    while remaining:
        ps = {c: test(z, *c) for c in remaining}
        best = min(remaining, key=lambda c: (np.nan_to_num(ps[c], nan=1.0), c[1] != FLEET, c[0]))
        p = ps[best]
        running = max(running, min(1.0, len(remaining) * p))
        if not (np.isfinite(p) and running <= alpha):
            break
        name, form = best
        idx = bins[name]
        ok = idx >= 0
        if form == FLEET:
            _, means_z = anova(z, idx)
            _, means_r = anova(raw, idx)
            shift_z = np.where(ok[..., None], means_z[np.clip(idx, 0, None)], 0.0)
            effect = float(np.sqrt(np.sum(means_r[idx[ok]] ** 2) / max(int(ok.sum()), 1)))
        else:
            _, shift_z = anova_per_heliostat(z, idx)
            _, shift_r = anova_per_heliostat(raw, idx)
            inside = per_heliostat_cells(idx) >= 0
            effect = float(np.sqrt(np.sum(shift_r**2) / max(int(inside.sum()), 1)))
        p_each = anova_each_heliostat(z, idx)
        heliostats = [ids[h] for h in np.flatnonzero(np.isfinite(p_each) & (p_each < alpha)) if ids[h]]
        entries.append(
            {
                "variable": name,
                "form": form,
                "label": by_name[name].label,
                "p": float(p),
                "p_holm": float(running),
                "effect_size_mrad": effect,
                "heliostats": heliostats,
            }
        )
        # remove the structure found before testing the others
        z = z - shift_z
        remaining = [c for c in remaining if c != best]
    return entries, {k: float(v) for k, v in first.items()}


def day_whitened_rss(rows: np.ndarray, used: np.ndarray, day: np.ndarray, correlation: float) -> np.ndarray:
    """``(S,)`` ``r^T R^-1 r`` of each row set: the residual sum of squares of
    generalised least squares under a random day effect.

    The residual components of one row set (a heliostat's lane), day and component
    are taken as correlated by ``correlation`` (``rho``, :func:`day_clustering`), those
    of different days or components as independent: per cluster of ``n_c`` rows,
    ``R_c = (1 - rho) I + rho 1 1^T``, so ``r_c^T R_c^-1 r_c = (SSW_c + n_c mean_c^2
    (1 - rho) / (1 - rho + n_c rho)) / (1 - rho)``, ``SSW_c`` the sum of squares
    about the cluster's mean. The structure a day shares counts with the weight of
    ``(1 - rho) / (1 - rho + n_c rho)``, the variation within a day in full; at
    ``rho = 0`` this is the plain sum of squares. Two models compared on the same rows
    under the same ``rho`` have the same ``log det R``, so the difference of their
    ``n log(r^T R^-1 r / n)`` is ``2 log`` of their likelihood ratio (each row set's
    noise profiled out).

    Args:
        rows: ``(S, R)`` residual components (mrad), record ``j``'s at rows ``2j``,
            ``2j + 1``.
        used: ``(S, R)`` the rows that count.
        day: ``(S, >= R / 2)`` each record's day (:func:`day_labels`).
        correlation: ``rho`` in ``[0, 1)``.
    """
    rows = np.where(used, rows, 0.0)
    plain = np.sum(rows * rows, axis=1)
    if correlation <= 0.0:
        return plain
    if not correlation < 1.0:
        raise ValueError(f"day_whitened_rss: correlation must be below 1, got {correlation}")
    s, r = rows.shape
    si, ri = np.nonzero(used)
    keys = np.stack([si, np.asarray(day)[si, ri // 2], ri % 2])
    _, cluster = np.unique(keys, axis=1, return_inverse=True)
    cluster = cluster.reshape(-1)
    x = rows[si, ri]
    n_c = np.bincount(cluster).astype(float)
    between = np.bincount(cluster, weights=x) ** 2 / n_c  # n_c mean_c^2
    set_of = np.zeros(n_c.size, np.int64)
    set_of[cluster] = si
    rho = float(correlation)
    kept = between * (1.0 - rho) / (1.0 - rho + n_c * rho)
    return (plain - np.bincount(set_of, weights=between - kept, minlength=s)) / (1.0 - rho)
