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

import numpy as np
from scipy import stats


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
    r: np.ndarray, use: np.ndarray, unix_time: np.ndarray, n_params: int, longitude_deg: float = 0.0
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

    Args:
        r: ``(H, M, 2)`` residual components (mrad).
        use: ``(H, M)`` the records fitted.
        unix_time: ``(H, M)`` seconds (UTC); non-finite times take no part.
        n_params: fitted parameters per heliostat (for the noise level).
        longitude_deg: the plant's longitude (deg east) for its local days
            (:func:`day_labels`).
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
    m_h = np.where(per_helio_n > 0, m_h, 1.0)
    return DayClustering(float(rho), p, 1.0 + (m_h - 1.0) * rho, m_h)


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
