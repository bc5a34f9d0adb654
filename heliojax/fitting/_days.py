"""Records that share an error by day: day labels and the intra-day correlation.

A camera-target record's error is not always its own: records of one heliostat on
one day can share the target's or the camera's state that day, a daily homing of the
drives, or a drift slower than a day. Discovery whitens its criterion under such a
random day effect and the planner spreads its measurements over days by it.

A *day* is a local mean solar day at the plant (``longitude_deg`` east; UTC days
where it is 0): its boundary, local mean midnight, falls at night wherever the
plant is, so no day's records are split between two labels.
"""

from __future__ import annotations

import dataclasses
import typing

import numpy as np
from scipy import optimize, stats


def heliostat_noise(r: np.ndarray, use: np.ndarray, n_params: int) -> np.ndarray:
    """``(H,)`` noise per residual component, ``sqrt(RSS_h / (2 n_h - p))`` (NaN where
    the heliostat has no residual degrees of freedom)."""
    n = use.sum(axis=1)
    rss = np.sum(np.where(use[..., None], r, 0.0) ** 2, axis=(1, 2))
    dof = 2 * n - n_params
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(dof > 0, np.sqrt(rss / np.maximum(dof, 1)), np.nan)


DAY_S = 86400.0
SECONDS_PER_DEGREE_LONGITUDE = DAY_S / 360.0
"""Mean solar time advances 240 s per degree of longitude eastwards."""
CLUSTERING_ALPHA = 0.01
"""Level of the F test that the records of one heliostat on one day share an error
(:func:`day_clustering`): below it the design effect is used, otherwise it is 1 (the
records are taken as independent, as every test assumes)."""


@dataclasses.dataclass(frozen=True)
class DayClustering:
    """How much the records of one heliostat on one day share their error.

    Attributes:
        correlation: the intra-day correlation of the residual components (one-way
            random-effects analysis of variance, clusters (heliostat, day,
            component); 0 where the F test does not reject independence).
        p: the F test's p-value (NaN where it cannot be made).
        design_effect: ``(H,)`` ``1 + (m_h - 1) correlation`` per heliostat, ``m_h``
            its size-weighted mean records per day (``sum n_c^2 / sum n_c``): the
            factor by which records clustered by day overstate a test statistic
            (Kish's design effect); 1 where the heliostat has no record.
        records_per_day: ``(H,)`` ``m_h``.
    """

    correlation: float
    p: float
    design_effect: np.ndarray
    records_per_day: np.ndarray

    def as_dict(self) -> dict:
        """The report's entry (JSON types)."""
        return {
            "intra_day_correlation": round(float(self.correlation), 4),
            "p": None if not np.isfinite(self.p) else float(self.p),
            "design_effect_median": round(float(np.median(self.design_effect)), 4),
            "records_per_day_median": round(float(np.median(self.records_per_day)), 3),
        }


def day_clustering(
    r: np.ndarray,
    use: np.ndarray,
    unix_time: np.ndarray,
    n_params: int,
    longitude_deg: float = 0.0,
    basis: np.ndarray | None = None,
) -> DayClustering:
    """Whether residuals of one heliostat's records on one day share an error, and
    the design effect that follows (:class:`DayClustering`).

    Every test of discovery takes the records as independent given the model. Records
    of one day can share an error the model does not have (the target's or camera's
    state that day, a daily homing of the drives, a drift slower than a day): then a
    statistic made of ``n`` records carries the information of about ``n / deff``, and
    taking them as independent names effects that are only such shared errors.

    Estimate: each heliostat's components are standardised by its own noise level
    (:func:`heliostat_noise`); clusters are (heliostat, day, component). The one-way
    analysis of variance gives ``MSB`` over ``K - 2 H'`` degrees of freedom (cluster
    means about their heliostat's component mean, ``H'`` heliostats with records) and
    ``MSW`` over ``N - K``; the between-cluster variance is ``(MSB - MSW) / n0`` with
    ``n0 = (N - sum n_c^2 / N) / (K - 1)``, and the intra-day correlation its share of
    the total. It is used only where ``MSB / MSW`` rejects independence at
    :data:`CLUSTERING_ALPHA` (so records without a shared error leave every test as it
    was, up to that level's false alarms); records alone on their day take no part
    in the test.

    With ``basis`` (the fitted model's columns), the correlation is the
    method-of-moments estimate that allows for what the fit absorbed
    (:func:`_absorbed_correlation`): the model's parameters take up part of each
    day's shared error (a day's mean is partly an offset, partly any parameter whose
    column varies from day to day), so the analysis of variance of the residuals
    alone, which allows for each heliostat's mean only, finds the correlation too
    small (independent simulator, half of the variance shared by day: ~0.42 for
    0.5 with the actuator model's 8 parameters per heliostat and ~4 records per day).

    Args:
        r: ``(H, M, 2)`` residual components (mrad).
        use: ``(H, M)`` the records fitted.
        unix_time: ``(H, M)`` seconds (UTC); non-finite times take no part.
        n_params: fitted parameters per heliostat (for the noise level).
        longitude_deg: the plant's longitude (deg east) for its local days
            (:func:`day_labels`).
        basis: ``(H, M, 2, c)`` an orthonormal basis, per heliostat, of the span of
            its fitted model's Jacobian columns on its used residual components
            (record ``j``'s two components at ``[:, j]``; zero on unused records and
            beyond the rank), or None (only each heliostat's mean allowed for).
    """
    h = r.shape[0]
    use = np.asarray(use, bool) & np.isfinite(unix_time) & np.all(np.isfinite(r), axis=-1)
    ones = np.ones(h)
    sigma = heliostat_noise(r, use, n_params)
    use &= (np.isfinite(sigma) & (sigma > 0))[:, None]
    hi, mi = np.nonzero(use)
    if hi.size == 0:
        return DayClustering(0.0, float("nan"), ones, ones)
    day = day_labels(unix_time[hi, mi], longitude_deg)
    _, cluster = np.unique(np.stack([hi, day]), axis=1, return_inverse=True)
    cluster = cluster.reshape(-1)
    n_c = np.bincount(cluster).astype(float)
    helio_of = np.zeros(n_c.size, np.int64)
    helio_of[cluster] = hi
    per_helio_n = np.bincount(hi, minlength=h).astype(float)
    m_h = np.bincount(helio_of, weights=n_c * n_c, minlength=h) / np.maximum(per_helio_n, 1.0)
    z = r[hi, mi] / sigma[hi, None]  # (N, 2)
    n_total = 2.0 * z.shape[0]
    k_clusters = 2.0 * n_c.size
    n_helio = float(np.count_nonzero(per_helio_n))
    ss_within = ss_between = 0.0
    for c in range(2):  # the two components: a fixed 2, not heliostats
        s_c = np.bincount(cluster, weights=z[:, c])
        s_h = np.bincount(hi, weights=z[:, c], minlength=h)
        ss_within += float(np.sum(z[:, c] ** 2) - np.sum(s_c * s_c / n_c))
        ss_between += float(np.sum(s_c * s_c / n_c) - np.sum(s_h[per_helio_n > 0] ** 2 / per_helio_n[per_helio_n > 0]))
    d1, d2 = k_clusters - 2.0 * n_helio, n_total - k_clusters
    if d1 <= 0 or d2 <= 0:
        return DayClustering(0.0, float("nan"), ones, np.where(per_helio_n > 0, m_h, 1.0))
    msb, msw = ss_between / d1, ss_within / d2
    p = float(stats.f.sf(msb / max(msw, 1e-300), d1, d2))
    n0 = (n_total - 2.0 * np.sum(n_c * n_c) / n_total) / (k_clusters - 1.0)
    between = max((msb - msw) / max(n0, 1e-300), 0.0)
    rho = between / (between + msw) if p < CLUSTERING_ALPHA and between > 0 else 0.0
    if rho > 0.0 and basis is not None:
        rho = _absorbed_correlation(z, hi, mi, cluster, n_c, helio_of, np.asarray(basis, float), h)
    m_h = np.where(per_helio_n > 0, m_h, 1.0)
    return DayClustering(float(rho), p, 1.0 + (m_h - 1.0) * rho, m_h)


MAX_CORRELATION = 0.99
"""Largest intra-day correlation :func:`_absorbed_correlation` returns (at 1 a day's
records would carry one record's information)."""


def _absorbed_correlation(
    z: np.ndarray,
    hi: np.ndarray,
    mi: np.ndarray,
    cluster: np.ndarray,
    n_c: np.ndarray,
    helio_of: np.ndarray,
    basis: np.ndarray,
    h: int,
) -> float:
    """The intra-day correlation ``rho`` whose expected within-day share of the
    residuals' sum of squares is the observed one, the fit's absorption allowed for.

    Per heliostat, with ``M = I - U U^T`` (``U`` its model's orthonormal basis on its
    used components), ``Z`` the (day, component) cluster indicators and ``B`` the
    projector on the variation within the clusters, residuals of an error
    ``s^2 ((1 - rho) I + rho Z Z^T)`` have ``E|r|^2 = s^2 ((1 - rho) tr M + rho |M Z|^2)``
    and ``E|B r|^2 = s^2 ((1 - rho) tr(B M) + rho |B M Z|^2)`` (the traces from the
    clusters' sums of ``U``'s rows, ``S_c``: ``tr M = n - |U|^2``, ``|M Z|^2 = n - sum_c
    |S_c|^2``, ``tr(B M) = tr M - K + sum_c |S_c|^2 / n_c``, ``|B M Z|^2 = |M Z|^2 - |A M Z|^2``
    with ``|A M Z|^2 = n - 2 sum_c |S_c|^2 + sum_c S_c^T C S_c / n_c``, ``C = sum_c S_c S_c^T``).
    Each heliostat's residuals are standardised by its own noise, so the pooled
    equation is ``sum_h |B z_h|^2 = sum_h |z_h|^2 E|B r_h|^2 / E|r_h|^2``, solved for
    ``rho`` in ``[0, MAX_CORRELATION]`` (the right side falls as ``rho`` grows);
    ``rho = 0`` and no absorption give back the analysis of variance's within share.

    Args:
        z: ``(N, 2)`` the standardised residuals of the used records.
        hi, mi: ``(N,)`` their heliostat and record index.
        cluster: ``(N,)`` their (heliostat, day) cluster; ``n_c`` ``(K,)`` its size,
            ``helio_of`` ``(K,)`` its heliostat.
        basis: ``(H, M, 2, c)`` (:func:`day_clustering`).
        h: ``H``.
    """
    u = basis[hi, mi]  # (N, 2, c)
    k, width = n_c.size, u.shape[-1]
    n_h = np.bincount(hi, minlength=h).astype(float)
    k_h = np.bincount(helio_of, minlength=h).astype(float)
    s_u = np.zeros((2, k, width))  # each cluster's sum of U's rows; clusters (heliostat, day, component)
    for comp in range(2):  # the two components: a fixed 2, not heliostats
        np.add.at(s_u[comp], cluster, u[:, comp])
    c_h = np.zeros((h, width, width))  # C = sum_c S_c S_c^T over a heliostat's clusters of both components
    np.add.at(c_h, helio_of, np.einsum("xki,xkj->kij", s_u, s_u))
    su2 = np.sum(s_u * s_u, axis=2)  # (2, K) |S_c|^2
    quad = np.einsum("xki,kij,xkj->xk", s_u, c_h[helio_of], s_u)  # (2, K) S_c^T C S_c
    qt = np.bincount(hi, weights=np.sum(z * z, axis=1), minlength=h)
    s_z = np.stack([np.bincount(cluster, weights=z[:, comp], minlength=k) for comp in range(2)])
    qw = qt - np.bincount(helio_of, weights=np.sum(s_z * s_z, axis=0) / n_c, minlength=h)
    per_h = lambda x: np.bincount(helio_of, weights=np.sum(x, axis=0), minlength=h)  # noqa: E731
    t1 = 2.0 * n_h - np.bincount(hi, weights=np.sum(u * u, axis=(1, 2)), minlength=h)  # tr M
    t2 = 2.0 * n_h - per_h(su2)  # |M Z|^2
    w1 = t1 - 2.0 * k_h + per_h(su2 / n_c)  # tr(B M)
    w2 = t2 - (2.0 * n_h - 2.0 * per_h(su2) + per_h(quad / n_c))  # |B M Z|^2 = |M Z|^2 - |A M Z|^2
    ok = (t1 > 0) & (qt > 0)
    if not ok.any():
        return 0.0
    qt, qw, t1, t2, w1, w2 = (a[ok] for a in (qt, qw, t1, t2, w1, w2))

    def excess(rho: float) -> float:  # expected minus observed within-day sum of squares
        expected = (1.0 - rho) * t1 + rho * t2
        return float(np.sum(qt * ((1.0 - rho) * w1 + rho * w2) / np.maximum(expected, 1e-300)) - np.sum(qw))

    if excess(0.0) <= 0.0:
        return 0.0
    if excess(MAX_CORRELATION) >= 0.0:
        return MAX_CORRELATION
    root = optimize.brentq(excess, 0.0, MAX_CORRELATION, xtol=1e-6)
    return float(typing.cast(float, root))


def day_labels(unix_time: np.ndarray, longitude_deg: float = 0.0) -> np.ndarray:
    """``(..., M)`` integer local mean solar day of each record, ``floor((t + 240 s *
    longitude_deg) / 1 day)`` (the UTC day at longitude 0); a record without a finite
    time is a day of its own (a negative label of its own).

    Args:
        unix_time: ``(..., M)`` s since 1970-01-01 UTC.
        longitude_deg: the plant's longitude, deg east (-180..180).
    """
    if not (np.isfinite(longitude_deg) and -180.0 <= longitude_deg <= 180.0):
        raise ValueError(f"longitude_deg must be in [-180, 180], not {longitude_deg!r}")
    t = np.asarray(unix_time, float) + SECONDS_PER_DEGREE_LONGITUDE * float(longitude_deg)
    own = -1 - np.arange(t.size, dtype=np.int64).reshape(t.shape)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(t), np.floor(np.where(np.isfinite(t), t, 0.0) / DAY_S), own).astype(np.int64)


__all__ = ["CLUSTERING_ALPHA", "DAY_S", "DayClustering", "day_clustering", "day_labels", "heliostat_noise"]
