"""Level 2, step 3: extrapolation to the unmeasured heliostats by kernel density
estimation per cluster.

The KDE (``scipy.stats.gaussian_kde``) is fitted in a transformed space chosen by
the parameter's support, so that it keeps skew and never produces impossible
values: ``log`` for positive parameters (tracking and slope errors, aperture:
no negative errors, a right-skewed Rayleigh/Weibull-like shape stays skewed),
``logit`` for fractions (reflectance), identity otherwise. Density and samples
are mapped back with the inverse transform (and the Jacobian for the density).

The bandwidth defaults to leave-one-out maximum-likelihood cross-validation
(``"cv"``), which follows several peaks far better than the normal-reference
rules (``"scott"``, ``"silverman"``, which over-smooth a bimodal sample).

Every unmeasured heliostat takes the cluster label of its nearest measured
heliostat (DBSCAN noise and non-anomalous clusters are the main population,
label 0) and a value drawn from that cluster's KDE; measured heliostats keep
their measured value.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np
from jaxtyping import Float, Int
from scipy import spatial, stats
from scipy.special import expit, logit

from .._limits import count_problem
from ._field import field_indices

Support = Literal["positive", "unit", "real"]
Bandwidth = Literal["cv", "scott", "silverman"] | float


def _forward(x: np.ndarray, support: Support) -> np.ndarray:
    if support == "positive":
        return np.log(x)
    if support == "unit":
        return logit(x)
    if support == "real":
        return x
    raise ValueError(f"support must be 'positive', 'unit' or 'real', got {support!r}")


def _inverse(y: np.ndarray, support: Support) -> np.ndarray:
    if support == "positive":
        return np.exp(y)
    if support == "unit":
        return expit(y)
    return y


def _log_jacobian(x: np.ndarray, support: Support) -> np.ndarray:
    if support == "positive":
        return -np.log(x)
    if support == "unit":
        return -np.log(x) - np.log1p(-x)
    return np.zeros_like(x)


MAX_CV_VALUES = 2000
"""Most values the leave-one-out bandwidth search uses; a larger sample's factor is that
of a fixed random subsample of this size, scaled from its Scott factor to the sample's
(both ``n^(-1/5)``), so that time and memory stay bounded."""


def cv_bandwidth_factor(y: Float[np.ndarray, " n"], n_grid: int = 60) -> float:
    """Leave-one-out likelihood cross-validated bandwidth factor (multiplies the
    sample std, as ``gaussian_kde``'s ``bw_method`` scalar does) for 1-D data
    (beyond :data:`MAX_CV_VALUES` values, from a subsample). ``n_grid``: factors tried,
    a whole number in [1, 10,000] (0 had divided by zero)."""
    problem = count_problem(n_grid, 10_000)
    if problem is not None:
        raise ValueError(f"cv_bandwidth_factor: n_grid {problem}")
    y = np.asarray(y, dtype=float)
    n = y.size
    if n > MAX_CV_VALUES:
        sub = np.random.default_rng(0).choice(y, MAX_CV_VALUES, replace=False)
        return cv_bandwidth_factor(sub, n_grid) * (n / MAX_CV_VALUES) ** (-0.2)
    sd = y.std(ddof=1)
    if n < 3 or sd == 0:
        return float(n ** (-0.2)) if n > 0 else 1.0
    scott = n ** (-0.2)
    factors = scott * np.logspace(np.log10(0.05), np.log10(2.0), n_grid)
    h = factors * sd  # (g,)
    ll = np.zeros(n_grid)
    rows = max(1, 2_000_000 // (n_grid * n))  # (g, rows, n) at a time: <= ~16 MB
    for start in range(0, n, rows):
        d2 = (y[start : start + rows, None] - y[None, :]) ** 2  # (rows, n)
        d2[np.arange(d2.shape[0]), np.arange(start, start + d2.shape[0])] = np.inf  # leave each point out
        # log LOO density per point and factor, with a log-sum-exp over j
        a = -0.5 * d2[None, :, :] / h[:, None, None] ** 2  # (g, rows, n)
        amax = a.max(axis=2, keepdims=True)
        lse = amax[..., 0] + np.log(np.exp(a - amax).sum(axis=2))
        ll += (lse - np.log((n - 1) * h[:, None] * np.sqrt(2 * np.pi))).sum(axis=1)
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    return float(factors[int(np.argmax(ll))])


@dataclasses.dataclass(frozen=True)
class TransformedKDE:
    """A 1-D Gaussian KDE fitted in a transformed space (see the module docstring).

    Attributes:
        kde: the fitted ``scipy.stats.gaussian_kde`` (transformed space).
        support: ``"positive"``, ``"unit"`` or ``"real"``.
        bandwidth_factor: the factor used (times the transformed sample std).
    """

    kde: stats.gaussian_kde
    support: Support
    bandwidth_factor: float

    def pdf(self, x: Float[np.ndarray, " k"]) -> Float[np.ndarray, " k"]:
        """Density in the parameter's own unit (0 outside the support)."""
        x = np.asarray(x, dtype=float)
        out = np.zeros_like(x)
        if self.support == "positive":
            ok = x > 0
        elif self.support == "unit":
            ok = (x > 0) & (x < 1)
        else:
            ok = np.ones_like(x, dtype=bool)
        y = _forward(x[ok], self.support)
        out[ok] = self.kde(y) * np.exp(_log_jacobian(x[ok], self.support))
        return out

    def sample(self, n: int, seed: int | np.random.Generator = 0) -> Float[np.ndarray, " n"]:
        """``n`` independent draws, in the parameter's unit."""
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        return _inverse(self.kde.resample(n, seed=rng)[0], self.support)


def fit_kde(
    values: Float[np.ndarray, " n"],
    support: Support = "positive",
    bandwidth: Bandwidth = "cv",
) -> TransformedKDE:
    """Fit a :class:`TransformedKDE` to measured values (at least 2, not all equal).

    Args:
        values: ``(n,)`` values inside the support.
        support: ``"positive"`` (log), ``"unit"`` (logit) or ``"real"``.
        bandwidth: ``"cv"`` (leave-one-out likelihood), ``"scott"``,
            ``"silverman"`` or a scalar factor (finite, > 0).

    Raises:
        ValueError: fewer than 2 finite values, values outside the support, an
            unknown bandwidth rule or a factor that is not finite and positive (a
            negative or NaN one had made a KDE of NaN densities).
    """
    if isinstance(bandwidth, str):
        if bandwidth not in ("cv", "scott", "silverman"):
            raise ValueError(f"bandwidth must be 'cv', 'scott', 'silverman' or a factor > 0, got {bandwidth!r}")
    elif isinstance(bandwidth, bool) or not isinstance(bandwidth, int | float) or not 0 < bandwidth < math.inf:
        raise ValueError(f"bandwidth must be 'cv', 'scott', 'silverman' or a finite factor > 0, got {bandwidth!r}")
    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    if x.size < 2:
        raise ValueError(f"a KDE needs at least 2 values, got {x.size}")
    with np.errstate(invalid="ignore", divide="ignore"):
        y = _forward(x, support)
    if not np.all(np.isfinite(y)):
        raise ValueError(f"values outside the {support!r} support")
    if np.ptp(y) == 0:  # all equal: widen by a tiny relative jitter
        y = y + np.linspace(-1e-6, 1e-6, y.size) * max(1.0, abs(float(y[0])))
    if bandwidth == "cv":
        factor = cv_bandwidth_factor(y)
    elif isinstance(bandwidth, str):
        factor = float(stats.gaussian_kde(y, bw_method=bandwidth).factor)  # pyright: ignore[reportArgumentType]
    else:
        factor = float(bandwidth)
    return TransformedKDE(stats.gaussian_kde(y, bw_method=factor), support, factor)


@dataclasses.dataclass(frozen=True)
class Extrapolation:
    """A value for every heliostat of the field.

    Attributes:
        values: ``(n,)`` measured values where measured, KDE draws elsewhere.
        labels: ``(n,)`` cluster label of every heliostat (0 = main population).
        measured: ``(n,)`` mask of measured heliostats.
        kdes: label -> its :class:`TransformedKDE`.
    """

    values: Float[np.ndarray, " n"]
    labels: Int[np.ndarray, " n"]
    measured: np.ndarray
    kdes: dict[int, TransformedKDE]


def extrapolate_field(
    field_positions: Float[np.ndarray, "n 2"],
    measured: Int[np.ndarray, " m"],
    values: Float[np.ndarray, " m"],
    labels: Int[np.ndarray, " m"] | None = None,
    *,
    support: Support = "positive",
    bandwidth: Bandwidth = "cv",
    seed: int = 0,
) -> Extrapolation:
    """Assign a value to every heliostat (measured: measured; others: KDE draw).

    Args:
        field_positions: ``(n, 2)`` east, north (m) of every heliostat.
        measured: ``(m,)`` field indices of the measured heliostats.
        values: ``(m,)`` their values.
        labels: ``(m,)`` their condensed cluster labels (default: all 0).
        support, bandwidth: KDE settings (:func:`fit_kde`).
        seed: random seed of the draws.

    Returns:
        An :class:`Extrapolation`.

    Raises:
        ValueError: ``measured`` of indices outside the field, not whole, or given
            twice (:func:`~heliojax.acceptance._field.field_indices`: -1 was read as the
            last heliostat), none measured, ``values`` not finite (a NaN had been
            "measured" and drawn from), lengths that differ.
    """
    xy = np.asarray(field_positions, dtype=float)[:, :2]
    n = len(xy)
    measured = field_indices("measured", measured, n)
    v = np.asarray(values, dtype=float)
    lab = np.zeros(v.size, dtype=int) if labels is None else np.asarray(labels, dtype=int)
    if not (measured.shape == v.shape == lab.shape):
        raise ValueError("measured, values and labels must have the same length")
    if measured.size == 0:
        raise ValueError("measured: no heliostat measured; nothing to extrapolate from")
    if not np.isfinite(v).all():
        raise ValueError(f"values: not finite for heliostat index {int(measured[~np.isfinite(v)][0])} (measured)")
    is_meas = np.zeros(n, dtype=bool)
    is_meas[measured] = True
    # label of the nearest measured heliostat
    _, j = spatial.cKDTree(xy[measured]).query(xy, k=1)  # pyright: ignore[reportAttributeAccessIssue]
    field_labels = lab[j]
    field_labels[measured] = lab
    out = np.full(n, np.nan)
    out[measured] = v
    rng = np.random.default_rng(seed)
    kdes = {}
    for k in np.unique(field_labels):  # loop over clusters
        members = v[lab == k]
        if members.size < 2:  # too few to fit: use the main population
            members = v[lab == 0] if (lab == 0).sum() >= 2 else v
        kdes[int(k)] = fit_kde(members, support, bandwidth)
        todo = (field_labels == k) & ~is_meas
        out[todo] = kdes[int(k)].sample(int(todo.sum()), rng)
    return Extrapolation(out, field_labels, is_meas, kdes)
