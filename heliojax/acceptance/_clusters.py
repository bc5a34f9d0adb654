"""Level 2, steps 1-2: cluster analysis of the sampled heliostats (DBSCAN on
scaled east, north and parameter value) and resampling advice.

Features: ``(east / L, north / L, value / s)``. ``L`` (metres) is the spatial
scale, by default 2.5 times the median nearest-neighbour spacing of the whole
field (so heliostats a couple of rows apart count as neighbours); ``s`` is the
value scale, by default ``value_factor`` (2.5) times the robust spread of the
values *between spatial neighbours* (:func:`local_std`), which is the spread
within a region even when the sample mixes a normal and an anomalous region.
DBSCAN (scikit-learn) runs with ``eps`` (default 1) and
``min_samples`` (default 4) on these features.

DBSCAN labels are then condensed into the labels the acceptance report uses:

* label ``0`` is the *main population*: DBSCAN noise plus every DBSCAN cluster
  whose values do not differ from the rest of the sample;
* labels ``1, 2, ...`` are *local anomalies*: DBSCAN clusters whose values differ
  from the other heliostats of the reference sample (the first random sample;
  default all) (two-sided Mann-Whitney U test at level
  ``alpha``, and a median at least ``min_shift`` (2) local stds,
  ``value_scale / value_factor``, from the median of the reference sample),
  numbered by decreasing size. Members of such
  a cluster whose value lies on the reference side of the midpoint between the
  reference median and the cluster median are border points that density
  chaining pulled in; they go back to the main population. Anomalous fragments
  that touch in space (members within ``L``) and deviate in the same direction
  are merged; merged clusters smaller than ``min_samples`` are dropped.

A randomly drawn sample is sparse in space, so an anomalous region shows up
first as isolated outliers. :func:`resampling_advice` therefore proposes to
measure the unmeasured neighbours of every outlier and of every anomalous
cluster; :func:`adaptive_survey` repeats measure -> cluster -> advise for a few
rounds.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from jaxtyping import Bool, Float, Int
from scipy import sparse, spatial, stats
from scipy.sparse import csgraph
from sklearn.cluster import DBSCAN

from .._limits import count_problem, real_problem
from ._sampling import select_sample

_MAD_TO_STD = 1.4826


def robust_std(values: Float[np.ndarray, " n"]) -> float:
    """1.4826 times the median absolute deviation (the std for normal data) of ``(n,)``
    finite values (same unit). Raises ValueError for no value or a NaN / infinite one
    (NumPy's median of none is NaN with a warning; one NaN made the spread NaN)."""
    x = np.asarray(values, dtype=float)
    if x.size == 0 or not np.isfinite(x).all():
        what = "no values" if x.size == 0 else f"{int((~np.isfinite(x)).sum())} NaN or infinite value(s)"
        raise ValueError(f"robust_std: needs finite values, got {what}; drop unmeasured values first")
    return float(_MAD_TO_STD * np.median(np.abs(x - np.median(x))))


def local_std(positions: Float[np.ndarray, "m 2"], values: Float[np.ndarray, " m"]) -> float:
    """Robust within-neighbourhood spread of a parameter.

    ``1.4826 * median |v_i - v_j| / sqrt(2)`` over the pairs (i, j = nearest
    measured neighbour of i in space). Differences between spatial neighbours
    cancel a step between regions, so a field with a block of different values
    still gives the spread *within* the regions (the global MAD would mix them).
    """
    xy = np.asarray(positions, dtype=float)[:, :2]
    v = np.asarray(values, dtype=float)
    if v.size < 3:
        return robust_std(v)
    _, j = spatial.cKDTree(xy).query(xy, k=2)  # pyright: ignore[reportAttributeAccessIssue]
    j = np.asarray(j)
    return float(_MAD_TO_STD * np.median(np.abs(v - v[j[:, 1]])) / np.sqrt(2.0))


def field_spacing(positions: Float[np.ndarray, "n 2"]) -> float:
    """Median nearest-neighbour distance of the field (m)."""
    xy = np.asarray(positions, dtype=float)[:, :2]
    if len(xy) < 2:
        return 1.0
    d, _ = spatial.cKDTree(xy).query(xy, k=2)  # pyright: ignore[reportAttributeAccessIssue]
    return float(np.median(d[:, 1]))


@dataclasses.dataclass(frozen=True)
class ClusterResult:
    """Clusters of the measured heliostats of one parameter.

    Attributes:
        labels: ``(m,)`` condensed labels (0 = main population, 1.. = anomalies),
            aligned with the ``values`` given to :func:`find_clusters`.
        dbscan_labels: ``(m,)`` raw DBSCAN labels (-1 = noise).
        length_scale_m: spatial scale ``L`` used (m).
        value_scale: value scale ``s`` used (parameter unit).
        p_values: Mann-Whitney p-value of each anomalous label ``1..K`` against the
            rest of the sample.
    """

    labels: Int[np.ndarray, " m"]
    dbscan_labels: Int[np.ndarray, " m"]
    length_scale_m: float
    value_scale: float
    p_values: dict[int, float]

    @property
    def n_anomalies(self) -> int:
        return int(self.labels.max(initial=0))


def find_clusters(
    positions: Float[np.ndarray, "m 2"],
    values: Float[np.ndarray, " m"],
    *,
    length_scale_m: float,
    value_scale: float | None = None,
    value_factor: float = 2.5,
    eps: float = 1.0,
    min_samples: int = 4,
    alpha: float = 0.05,
    reference: Bool[np.ndarray, " m"] | None = None,
    min_shift: float = 1.0,
) -> ClusterResult:
    """DBSCAN on scaled (east, north, value) of the measured heliostats.

    Args:
        positions: ``(m, 2)`` east, north (m) of the measured heliostats.
        values: ``(m,)`` their measured parameter values.
        length_scale_m: spatial scale ``L`` in m (see :func:`field_spacing`).
        value_scale: value scale ``s``; default ``value_factor * local_std``.
        value_factor: see ``value_scale``.
        eps, min_samples: DBSCAN settings on the scaled features.
        alpha: significance level for calling a cluster an anomaly.
        reference: ``(m,)`` mask of the heliostats that form the reference
            population, normally those of the first random sample (resampled
            heliostats were chosen *because* they are near anomalies, so they are
            not representative of the field). Default: all.
        min_shift: an anomaly's median must lie at least ``min_shift`` local
            stds from the reference median.

    Returns:
        A :class:`ClusterResult`.
    """
    # alpha = 5 (a percentage) had called every cluster an anomaly; a length scale of 0 or
    # NaN and min_samples of 0 failed inside scikit-learn
    if real_problem(alpha) is not None or not 0.0 < alpha < 1.0:
        raise ValueError(f"find_clusters: alpha must be a significance level in (0, 1), got {alpha!r}"[:200])
    if real_problem(length_scale_m) is not None or not length_scale_m > 0.0:
        raise ValueError(f"find_clusters: length_scale_m must be a finite length > 0 (m), got {length_scale_m!r}"[:200])
    problem = count_problem(min_samples, 1_000_000)
    if problem is not None:
        raise ValueError(f"find_clusters: min_samples {problem}")
    xy = np.asarray(positions, dtype=float)[:, :2]
    v = np.asarray(values, dtype=float)
    if xy.shape[0] != v.shape[0]:
        raise ValueError("positions and values differ in length")
    if not np.all(np.isfinite(v)):
        raise ValueError("values must be finite (pass only measured heliostats)")
    rs = local_std(xy, v) if v.size else 0.0
    if value_scale is None:
        value_scale = value_factor * rs
    if not value_scale > 0:
        value_scale = max(float(np.std(v)), 1e-12)
    feats = np.column_stack([xy / length_scale_m, v / value_scale])
    if v.size >= min_samples:
        raw = DBSCAN(eps=eps, min_samples=min_samples).fit(feats).labels_
    else:
        raw = -np.ones(v.size, dtype=int)
    threshold = min_shift * value_scale / value_factor
    anomalies: list[tuple[int, int, float]] = []
    ref = np.ones(v.size, dtype=bool) if reference is None else np.asarray(reference, dtype=bool)
    for k in np.unique(raw[raw >= 0]):  # loop over clusters, not heliostats
        inside = raw == k
        other = ref & ~inside
        if other.sum() < 2:
            continue
        p = float(stats.mannwhitneyu(v[inside], v[other], alternative="two-sided").pvalue)
        diff = abs(float(np.median(v[inside]) - np.median(v[ref])))
        if p < alpha and diff >= threshold:
            anomalies.append((int(inside.sum()), int(k), p))
    anomalies.sort(key=lambda t: -t[0])
    kept = np.zeros(v.size, dtype=int)  # +1 / -1: member of a high / low anomaly
    ref_median = float(np.median(v[ref])) if ref.any() else float(np.median(v))
    for _, k, _ in anomalies:
        inside = raw == k
        # members whose value lies nearer the reference median than the cluster
        # median are border points that density chaining pulled in: main population
        med = float(np.median(v[inside]))
        mid = 0.5 * (ref_median + med)
        kept[inside & (np.sign(v - mid) == np.sign(med - mid))] = int(np.sign(med - mid))
    # merge anomalous fragments that touch in space (within L) and deviate the same way
    labels = np.zeros(v.size, dtype=int)
    p_values = {}
    idx = np.flatnonzero(kept)
    if idx.size:
        pairs = spatial.cKDTree(xy[idx]).query_pairs(length_scale_m, output_type="ndarray")  # pyright: ignore[reportAttributeAccessIssue]
        pairs = pairs[kept[idx[pairs[:, 0]]] == kept[idx[pairs[:, 1]]]]
        graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(idx.size,) * 2)
        _, comp = csgraph.connected_components(graph, directed=False)
        sizes = np.bincount(comp)
        order = np.argsort(-sizes, kind="stable")
        new = 1
        for c in order:  # loop over clusters
            members = idx[comp == c]
            if members.size < min_samples:
                continue
            other = ref & (labels == 0)
            other[members] = False
            if other.sum() < 2:
                continue
            labels[members] = new
            p_values[new] = float(stats.mannwhitneyu(v[members], v[other], alternative="two-sided").pvalue)
            new += 1
    return ClusterResult(labels, raw, float(length_scale_m), float(value_scale), p_values)


def outliers(
    values: Float[np.ndarray, " m"],
    z_threshold: float = 2.5,
    side: str = "both",
    reference: Bool[np.ndarray, " m"] | None = None,
) -> Bool[np.ndarray, " m"]:
    """Robust outliers: ``(value - median) / robust_std`` beyond ``z_threshold``.

    Args:
        values: ``(m,)`` values.
        z_threshold: robust z-score threshold.
        side: ``"high"`` (only too large values: errors, where lower is better),
            ``"low"`` (only too small values), or ``"both"``.
        reference: mask of the values that define median and robust std
            (default all).
    """
    if real_problem(z_threshold, minimum=0.0) is not None:  # NaN had flagged nothing, -1 everything
        raise ValueError(f"outliers: z_threshold must be a finite number >= 0, got {z_threshold!r}"[:200])
    v = np.asarray(values, dtype=float)
    if reference is not None and np.shape(reference) != v.shape:  # an IndexError inside NumPy
        raise ValueError(f"outliers: reference has shape {np.shape(reference)}; expected {v.shape}, like values")
    ref = v if reference is None else v[np.asarray(reference, dtype=bool)]
    ref = ref[np.isfinite(ref)]  # an unmeasured (NaN) value is no outlier and sets no scale
    if ref.size == 0:
        return np.zeros(v.size, dtype=bool)
    rs = robust_std(ref)
    if rs == 0:
        return np.zeros(v.size, dtype=bool)
    z = (v - np.median(ref)) / rs
    if side == "high":
        return z > z_threshold
    if side == "low":
        return z < -z_threshold
    if side != "both":
        raise ValueError(f"side must be 'high', 'low' or 'both', got {side!r}")
    return np.abs(z) > z_threshold


def resampling_advice(
    field_positions: Float[np.ndarray, "n _"],
    measured: Int[np.ndarray, " m"],
    values: Float[np.ndarray, " m"],
    clusters: ClusterResult,
    *,
    k_neighbours: int = 8,
    z_threshold: float = 2.5,
    side: str = "both",
    reference: Bool[np.ndarray, " m"] | None = None,
) -> Int[np.ndarray, " k"]:
    """Heliostats to measure next, to confirm and delimit local anomalies.

    For every robust outlier among the measured values and every member of an
    anomalous cluster, the ``k_neighbours`` nearest heliostats of the field are
    proposed; those already measured are dropped.

    Args:
        field_positions: ``(n, 2)`` east, north (m) of all heliostats of the field.
        measured: ``(m,)`` indices into the field of the measured heliostats.
        values: ``(m,)`` their values.
        clusters: the :class:`ClusterResult` of these values.
        k_neighbours: neighbours proposed around each flagged heliostat.
        z_threshold: robust z-score above which a single value is an outlier.
        side: which outliers to follow up (see :func:`outliers`); ``"high"`` for
            errors (tracking, slope), ``"low"`` for reflectance and aperture.
        reference: mask of the measured heliostats of the first random sample,
            which define the median and spread for the outlier test.

    Returns:
        Sorted unique field indices (possibly empty).
    """
    xy = np.asarray(field_positions, dtype=float)[:, :2]
    measured = np.asarray(measured, dtype=int)
    flagged = outliers(values, z_threshold, side, reference) | (clusters.labels > 0)
    if not flagged.any():
        return np.zeros(0, dtype=int)
    k = min(k_neighbours + 1, len(xy))
    _, nb = spatial.cKDTree(xy).query(xy[measured[flagged]], k=k)  # pyright: ignore[reportAttributeAccessIssue]
    cand = np.unique(np.asarray(nb).ravel())
    return np.setdiff1d(cand, measured)


@dataclasses.dataclass(frozen=True)
class SurveyResult:
    """Outcome of :func:`adaptive_survey`.

    Attributes:
        measured: field indices measured, in order of measurement.
        values: their values.
        rounds: number of measured heliostats after each round.
        clusters: clusters of the final sample.
    """

    measured: Int[np.ndarray, " m"]
    values: Float[np.ndarray, " m"]
    rounds: list[int]
    clusters: ClusterResult


def adaptive_survey(
    field_positions: Float[np.ndarray, "n _"],
    measure: Callable[[np.ndarray], np.ndarray],
    n_initial: int,
    *,
    max_rounds: int = 3,
    max_extra: int | None = None,
    seed: int = 0,
    method: str = "stratified",
    length_scale_m: float | None = None,
    value_factor: float = 2.5,
    eps: float = 1.0,
    min_samples: int = 6,
    k_neighbours: int = 8,
    z_threshold: float = 2.0,
    side: str = "both",
) -> SurveyResult:
    """Random sample, then resampling rounds around anomalies (level 2, steps 1-2).

    Args:
        field_positions: ``(n, 2)`` east, north (m) of every heliostat.
        measure: callback taking field indices and returning their measured
            values (a measurement campaign; in tests, a lookup in a synthetic field).
        n_initial: size of the first random sample (from :func:`sample_size`).
        max_rounds: resampling rounds after the first sample.
        max_extra: cap on the number of heliostats added by resampling.
        seed, method: first-sample selection (:func:`select_sample`).
        length_scale_m: DBSCAN spatial scale, default 2.5 x field spacing.
        value_factor, eps, min_samples, k_neighbours, z_threshold, side: clustering /
            advice settings (:func:`find_clusters`, :func:`resampling_advice`).

    Returns:
        A :class:`SurveyResult`.
    """
    xy = np.asarray(field_positions, dtype=float)[:, :2]
    if length_scale_m is None:
        length_scale_m = 2.5 * field_spacing(xy)
    measured = select_sample(xy, n_initial, seed=seed, method=method)  # pyright: ignore[reportArgumentType]
    values = np.asarray(measure(measured), dtype=float)
    rounds = [int(measured.size)]

    n_first = measured.size

    def cluster(m, v):
        ref = np.arange(m.size) < n_first
        return find_clusters(
            xy[m],
            v,
            length_scale_m=length_scale_m,
            value_factor=value_factor,
            eps=eps,
            min_samples=min_samples,
            reference=ref,
        )

    res = cluster(measured, values)
    budget = np.inf if max_extra is None else max_extra
    for _ in range(max_rounds):
        new = resampling_advice(
            xy,
            measured,
            values,
            res,
            k_neighbours=k_neighbours,
            z_threshold=z_threshold,
            side=side,
            reference=np.arange(measured.size) < n_first,
        )
        if new.size == 0 or budget <= 0:
            break
        new = new[: int(min(new.size, budget))]
        budget -= new.size
        measured = np.concatenate([measured, new])
        values = np.concatenate([values, np.asarray(measure(new), dtype=float)])
        rounds.append(int(measured.size))
        res = cluster(measured, values)
    return SurveyResult(measured, values, rounds, res)
