"""Benchmark splits of calibration records, per heliostat (PAINT's algorithms).

PAINT (``paint.data.dataset_splits.DatasetSplitter``) defines four benchmark splits
of the calibration records of each heliostat; heliojax reproduces their algorithms
(not their code) and adds a chronological one:

``time``
    Chronological. Records sorted by time (ties: record index); the earliest
    ``n_train`` (or ``floor(train_fraction * n)``) train, the latest ``n_val``
    validate, the records in between test. Not a PAINT split.
``azimuth``
    Sorted by sun azimuth, then time (then record index); the ``n_train`` lowest
    azimuths train, the ``n_val`` highest validate, the rest test.
``solstice``
    Distance in seconds from the record's UTC timestamp to the nearest
    21 December 12:00 UTC (winter) and 21 June 12:00 UTC (summer) of the
    record's year, the previous or the next year (PAINT's measure: wall-clock
    time, not sun position). The ``n_train`` records closest to a winter
    solstice train (ties: time, index); of the *other* records, the ``n_val``
    closest to a summer solstice validate (ties: time, index); the rest test.
``balanced``
    KMeans (scikit-learn, ``random_state=seed``) with ``k = n_val`` clusters on
    (azimuth, elevation) in degrees. One random member of each cluster
    validates; one other random member of each cluster with at least two
    members tests; missing test records (singleton clusters) are drawn at
    random from the records not yet used. ``n_train`` random records of the
    rest train. Records not drawn are *unused* (PAINT drops them).
``high_variance``
    For each record, the mean Euclidean distance in (azimuth, elevation) to its
    3 nearest other records. Sorted by that distance, most isolated first
    (ties: record index): the first ``n_val`` validate, the next ``n_val`` test,
    the next ``n_train`` train; the remaining (most typical) records are
    *unused* (PAINT drops them).

Minimum size (PAINT's rule, plus at least one test record): a heliostat needs
``n_train + n_val + max(n_val, 1)`` valid records. A heliostat with fewer is not
dropped: its :class:`SplitResult` has ``ok=False`` and a ``reason``, all its
records in ``unused``, and :func:`split_fleet` lists it in
:attr:`FleetSplit.too_few`.

Differences from PAINT (deliberate, documented):

- *solstice*: PAINT picks validation among all records, so a record close to
  both solstices (spring/autumn data only) is first chosen for training and
  then relabelled validation, leaving fewer than ``n_train`` training records.
  heliojax picks validation among the records not chosen for training, so the
  sizes are exact. Where the two selections do not overlap the results agree.
- *balanced*: the random draws use ``numpy.random.default_rng(seed)`` instead
  of Python's ``random`` over pandas index/set order, so the drawn members are
  not bit-identical to PAINT's; the clustering (same features, same k, same
  ``random_state``) and the structure of the draw are the same.
- *high_variance*: ties in the distance are broken by record index (PAINT's
  sort is not stable); with fewer than 4 records, the mean runs over the
  ``n - 1`` others (PAINT raises).
- Records whose features are not finite (or masked by ``valid``) take no part
  and are listed in ``unused``.

All indices are positions in the heliostat's record arrays, sorted ascending.
Units: azimuth and elevation in radians (PAINT's azimuth convention: 0 = south,
positive toward east; only the order matters for *azimuth*), times in seconds
since the Unix epoch, UTC.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import typing
from collections.abc import Mapping, Sequence
from typing import Literal

import numpy as np
from jaxtyping import Bool, Float

from ._errors import ConfigError
from ._geometry import check_unit_vectors
from ._limits import count_problem, real_problem

__all__ = [
    "SPLIT_NAMES",
    "chronological_holdout",
    "days_since_fit",
    "days_from_fitted_mean",
    "utc_iso",
    "FleetSplit",
    "record_sky_gap_deg",
    "SplitResult",
    "knn_mean_distance",
    "minimum_records",
    "solstice_distance_s",
    "split_dict",
    "split_fleet",
    "split_masks",
    "split_records",
]


def utc_iso(unix_time: float) -> str | None:
    """``unix_time`` (s) as an ISO 8601 UTC date-time ``YYYY-MM-DDTHH:MM:SSZ``; None
    when it is not finite."""
    if not math.isfinite(unix_time):
        return None
    return datetime.datetime.fromtimestamp(float(unix_time), tz=datetime.UTC).isoformat().replace("+00:00", "Z")


SplitKind = Literal["time", "azimuth", "solstice", "balanced", "high_variance"]
SPLIT_NAMES: tuple[str, ...] = ("time", "azimuth", "solstice", "balanced", "high_variance")

_N_NEIGHBOURS = 3  # PAINT's high-variance metric: mean distance to the 3 nearest others.


@dataclasses.dataclass(frozen=True)
class SplitResult:
    """Split of one heliostat's records.

    Attributes:
        kind: the split's name (one of :data:`SPLIT_NAMES`).
        train, validation, test: int64 indices into the heliostat's records,
            sorted ascending, pairwise disjoint.
        unused: the remaining indices (records the algorithm leaves out, invalid
            records, or all records when ``ok`` is False). ``train``,
            ``validation``, ``test`` and ``unused`` partition ``range(n_records)``.
        n_records: number of records given (valid or not).
        ok: False when the heliostat has too few valid records for the split.
        reason: why ``ok`` is False (``None`` when ok).
    """

    kind: str
    train: np.ndarray
    validation: np.ndarray
    test: np.ndarray
    unused: np.ndarray
    n_records: int
    ok: bool = True
    reason: str | None = None

    def labels(self) -> np.ndarray:
        """Per-record label array of shape ``(n_records,)``: ``"train"``,
        ``"validation"``, ``"test"`` or ``"unused"``."""
        out = np.full(self.n_records, "unused", dtype=object)
        out[self.train] = "train"
        out[self.validation] = "validation"
        out[self.test] = "test"
        return out


@dataclasses.dataclass(frozen=True)
class FleetSplit:
    """Split of a padded fleet (see :func:`split_fleet`).

    Attributes:
        kind: the split's name.
        results: heliostat id -> :class:`SplitResult` (every heliostat, ok or not).
        train_mask, val_mask, test_mask: bool arrays of shape
            ``(n_heliostats, max_records)``; all False for a heliostat that is not ok.
        too_few: heliostat id -> reason, for every heliostat whose split is not ok.
    """

    kind: str
    results: dict[str, SplitResult]
    train_mask: np.ndarray
    val_mask: np.ndarray
    test_mask: np.ndarray
    too_few: dict[str, str]


def minimum_records(n_train: int, n_val: int) -> int:
    """Fewest valid records a split with ``n_train`` training and ``n_val``
    validation records accepts: ``n_train + n_val + max(n_val, 1)`` (PAINT's
    ``n_train + 2 n_val``, and at least one test record)."""
    return n_train + n_val + max(n_val, 1)


def solstice_distance_s(unix_time_s: np.ndarray, season: Literal["summer", "winter"]) -> np.ndarray:
    """Seconds from each time to the nearest solstice reference (PAINT's measure).

    The references are 21 June (summer) or 21 December (winter), 12:00 UTC, of the
    time's own year, the previous and the next year.

    Args:
        unix_time_s: float array, seconds since 1970-01-01T00:00:00 UTC.
        season: ``"summer"`` or ``"winter"``.

    Returns:
        float64 array of the same shape, non-negative seconds.
    """
    if season == "summer":
        month = 6
    elif season == "winter":
        month = 12
    else:
        raise ConfigError(f"season must be 'summer' or 'winter', got {season!r}")
    t = np.asarray(unix_time_s, dtype=np.float64)
    whole = np.floor(t)
    stamps = whole.astype("int64").astype("datetime64[s]")
    year = stamps.astype("datetime64[Y]")
    best = np.full(t.shape, np.inf)
    for dy in (-1, 0, 1):
        ref_month = (year + np.timedelta64(dy, "Y")).astype("datetime64[M]") + np.timedelta64(month - 1, "M")
        ref = (ref_month.astype("datetime64[D]") + np.timedelta64(20, "D")).astype("datetime64[s]") + np.timedelta64(
            12 * 3600, "s"
        )
        ref_s = ref.astype("int64").astype(np.float64)
        best = np.minimum(best, np.abs(t - ref_s))
    return best


def _sorted_idx(idx) -> np.ndarray:
    return np.sort(np.asarray(idx, dtype=np.int64))


def _result(kind, n, train, val, test) -> SplitResult:
    train, val, test = _sorted_idx(train), _sorted_idx(val), _sorted_idx(test)
    used = np.zeros(n, dtype=bool)
    used[train] = used[val] = used[test] = True
    unused = np.flatnonzero(~used).astype(np.int64)
    return SplitResult(kind, train, val, test, unused, n, True, None)


def _not_ok(kind: str, n: int, reason: str) -> SplitResult:
    empty = np.zeros(0, dtype=np.int64)
    return SplitResult(kind, empty, empty, empty, np.arange(n, dtype=np.int64), n, False, reason)


MAX_SEED = 2**32 - 1
"""Largest ``seed`` of the splits (scikit-learn's KMeans takes a ``random_state`` below 2**32)."""


def _whole(value: object, minimum: int) -> bool:
    """Whether ``value`` is a whole number (an int, or a float of one) at least ``minimum``."""
    return real_problem(value, minimum=minimum) is None and float(typing.cast(float, value)).is_integer()


def split_records(
    kind: SplitKind,
    azimuth_rad,
    elevation_rad,
    unix_time_s,
    *,
    n_train: int | None = None,
    n_val: int = 0,
    train_fraction: float | None = None,
    seed: int = 42,
    valid=None,
    unused_to_test: bool = False,
) -> SplitResult:
    """Split one heliostat's calibration records.

    Args:
        kind: one of :data:`SPLIT_NAMES` (see the module docstring).
        azimuth_rad: ``(n,)`` sun azimuth of each record, radians (PAINT convention).
        elevation_rad: ``(n,)`` sun elevation, radians.
        unix_time_s: ``(n,)`` record time, seconds since the Unix epoch (UTC).
        n_train: number of training records. Give exactly one of ``n_train`` and
            ``train_fraction``.
        n_val: number of validation records (>= 1 for *balanced* and *high_variance*,
            where it also fixes the number of test records).
        train_fraction: fraction of the valid records that train,
            ``n_train = floor(train_fraction * n_valid)``.
        seed: random state of the *balanced* split (KMeans and draws); PAINT uses 42.
        valid: optional ``(n,)`` bool mask; False records take no part (padding).
            Records with a non-finite feature that the split uses are invalid too.
        unused_to_test: put the records the algorithm leaves out (*balanced*,
            *high_variance*) into ``test`` instead of ``unused`` (not PAINT's rule).

    Returns:
        :class:`SplitResult`; ``ok=False`` with a ``reason`` when there are too few
        valid records (see :func:`minimum_records`).

    Raises:
        ConfigError: unknown ``kind`` or inconsistent sizes.
    """
    if kind not in SPLIT_NAMES:
        raise ConfigError(f"unknown split {kind!r}; choose one of {', '.join(SPLIT_NAMES)}")
    if (n_train is None) == (train_fraction is None):
        raise ConfigError("give exactly one of n_train and train_fraction")
    # NaN and inf had failed in int() (ValueError, OverflowError), a string fraction in a
    # comparison, an array of fractions as "truth value ... ambiguous", True had been 1
    if n_train is not None and not _whole(n_train, 1):
        raise ConfigError(f"n_train must be a positive integer, got {n_train!r}"[:200])
    if train_fraction is not None and not (real_problem(train_fraction) is None and 0.0 < train_fraction < 1.0):
        raise ConfigError(f"train_fraction must lie in (0, 1), got {train_fraction!r}"[:200])
    if not _whole(n_val, 0):
        raise ConfigError(f"n_val must be a non-negative integer, got {n_val!r}"[:200])
    # scikit-learn had named its random_state
    if seed is not None and count_problem(seed, MAX_SEED, minimum=0) is not None:
        raise ConfigError(f"seed must be a whole number in [0, {MAX_SEED}] (or None), got {seed!r}"[:200])
    if kind in ("balanced", "high_variance") and n_val < 1:
        raise ConfigError(f"the {kind} split needs n_val >= 1 (it also sets the number of test records)")
    n_val = int(n_val)

    az = np.asarray(azimuth_rad, dtype=np.float64).reshape(-1)
    el = np.asarray(elevation_rad, dtype=np.float64).reshape(-1)
    t = np.asarray(unix_time_s, dtype=np.float64).reshape(-1)
    n = az.shape[0]
    if el.shape[0] != n or t.shape[0] != n:
        raise ConfigError(f"azimuth ({n}), elevation ({el.shape[0]}) and time ({t.shape[0]}) differ in length")
    ok_mask = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool).reshape(-1).copy()
    if ok_mask.shape[0] != n:
        raise ConfigError(f"valid mask has {ok_mask.shape[0]} entries for {n} records")
    # Features each split needs finite (azimuth's time only breaks ties: a missing time sorts last).
    needs = {
        "time": (t,),
        "azimuth": (az,),
        "solstice": (t,),
        "balanced": (az, el),
        "high_variance": (az, el),
    }[kind]
    n_given = int(ok_mask.sum())
    for f in needs:
        ok_mask &= np.isfinite(f)
    vidx = np.flatnonzero(ok_mask).astype(np.int64)
    nv = vidx.size
    if nv < n_given:  # say which feature is missing, e.g. times without calibration-timestamps.json
        missing = "a time" if needs[0] is t else "a sun position"
        if nv == 0:
            return _not_ok(kind, n, f"none of the {n_given} records has {missing}, which the {kind} split needs")

    if train_fraction is not None:
        n_train = int(math.floor(train_fraction * nv))
        if n_train < 1:
            return _not_ok(kind, n, f"{nv} valid records: train_fraction={train_fraction} leaves no training record")
    need = minimum_records(int(n_train or 0), n_val)
    if nv < need:
        return _not_ok(
            kind,
            n,
            f"{nv} valid records; the {kind} split with n_train={n_train}, n_val={n_val} needs at least "
            f"{need} (n_train + n_val + max(n_val, 1))",
        )

    if kind == "time":
        order = vidx[np.lexsort((vidx, t[vidx]))]
        train = order[:n_train]
        val = order[nv - n_val :] if n_val else order[:0]
        test = order[n_train : nv - n_val]
        return _result(kind, n, train, val, test)

    if kind == "azimuth":
        order = vidx[np.lexsort((vidx, t[vidx], az[vidx]))]
        train = order[:n_train]
        val = order[nv - n_val :] if n_val else order[:0]
        test = order[n_train : nv - n_val]
        return _result(kind, n, train, val, test)

    if kind == "solstice":
        dw = solstice_distance_s(t[vidx], "winter")
        ds = solstice_distance_s(t[vidx], "summer")
        order_w = np.lexsort((vidx, t[vidx], dw))
        train_pos = order_w[:n_train]
        rest = np.setdiff1d(np.arange(nv), train_pos)
        order_s = rest[np.lexsort((vidx[rest], t[vidx][rest], ds[rest]))]
        val_pos = order_s[:n_val]
        test_pos = order_s[n_val:]
        return _result(kind, n, vidx[train_pos], vidx[val_pos], vidx[test_pos])

    if kind == "balanced":
        return _balanced(n, vidx, az, el, n_train, n_val, seed, unused_to_test)

    return _high_variance(n, vidx, az, el, n_train, n_val, unused_to_test)


def _balanced(n, vidx, az, el, n_train, n_val, seed, unused_to_test) -> SplitResult:
    from sklearn.cluster import KMeans

    features = np.stack([np.degrees(az[vidx]), np.degrees(el[vidx])], axis=1)
    labels = KMeans(n_clusters=n_val, random_state=seed, n_init="auto").fit_predict(features)
    rng = np.random.default_rng(seed)
    val: list[int] = []
    test: list[int] = []
    for label in np.unique(labels):  # ascending cluster labels, non-empty clusters only
        members = vidx[labels == label]  # ascending record indices
        v = int(rng.choice(members))
        val.append(v)
        if members.size >= 2:
            test.append(int(rng.choice(members[members != v])))
    missing = n_val - len(test)
    if missing > 0:
        pool = np.setdiff1d(vidx, np.array(val + test, dtype=np.int64))
        test.extend(int(i) for i in rng.permutation(pool)[:missing])
    pool = np.setdiff1d(vidx, np.array(val + test, dtype=np.int64))
    pool = rng.permutation(pool)
    train = pool[:n_train]
    if unused_to_test:
        test.extend(int(i) for i in pool[n_train:])
    return _result("balanced", n, train, val, test)


def knn_mean_distance(features: np.ndarray, k: int = _N_NEIGHBOURS) -> np.ndarray:
    """Mean Euclidean distance of each row of ``features`` ``(n, d)`` to its ``k``
    nearest *other* rows (``min(k, n - 1)`` when ``n <= k``). Returns ``(n,)``."""
    f = np.asarray(features, dtype=np.float64)
    m = f.shape[0]
    if m < 2:
        return np.zeros(m)
    d = np.sqrt(((f[:, None, :] - f[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    kk = min(k, m - 1)
    return np.sort(d, axis=1)[:, :kk].mean(axis=1)


def _high_variance(n, vidx, az, el, n_train, n_val, unused_to_test) -> SplitResult:
    score = knn_mean_distance(np.stack([az[vidx], el[vidx]], axis=1))
    order = vidx[np.argsort(-score, kind="stable")]
    val = order[:n_val]
    test = order[n_val : 2 * n_val]
    train = order[2 * n_val : 2 * n_val + n_train]
    if unused_to_test:
        test = np.concatenate([test, order[2 * n_val + n_train :]])
    return _result("high_variance", n, train, val, test)


def split_fleet(
    kind: SplitKind,
    azimuth_rad,
    elevation_rad,
    unix_time_s,
    ids: Sequence[str],
    *,
    valid=None,
    n_train: int | None = None,
    n_val: int = 0,
    train_fraction: float | None = None,
    seed: int = 42,
    unused_to_test: bool = False,
) -> FleetSplit:
    """Split every heliostat of a padded fleet.

    Args:
        kind: one of :data:`SPLIT_NAMES`.
        azimuth_rad, elevation_rad, unix_time_s: ``(h, m)`` arrays (radians,
            radians, seconds since the Unix epoch), padded to ``m`` records.
        ids: the ``h`` heliostat ids (distinct).
        valid: ``(h, m)`` bool mask of real records (default: all finite records).
        n_train, n_val, train_fraction, seed, unused_to_test: as in :func:`split_records`,
            the same for every heliostat.

    Returns:
        :class:`FleetSplit` with per-heliostat results, ``(h, m)`` masks, and the
        heliostats with too few records (never dropped silently).
    """
    az = np.asarray(azimuth_rad, dtype=np.float64)
    el = np.asarray(elevation_rad, dtype=np.float64)
    t = np.asarray(unix_time_s, dtype=np.float64)
    if az.ndim != 2 or el.shape != az.shape or t.shape != az.shape:
        raise ConfigError(f"fleet arrays must share one (h, m) shape, got {az.shape}, {el.shape}, {t.shape}")
    h, m = az.shape
    ids = [str(i) for i in ids]
    if len(ids) != h:
        raise ConfigError(f"{len(ids)} ids for {h} heliostats")
    if len(set(ids)) != h:
        raise ConfigError("heliostat ids must be distinct")
    vmask = np.ones((h, m), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if vmask.shape != (h, m):
        raise ConfigError(f"valid mask shape {vmask.shape} differs from {(h, m)}")
    masks = np.zeros((3, h, m), dtype=bool)
    results: dict[str, SplitResult] = {}
    too_few: dict[str, str] = {}
    for row, hid in enumerate(ids):
        r = split_records(
            kind,
            az[row],
            el[row],
            t[row],
            n_train=n_train,
            n_val=n_val,
            train_fraction=train_fraction,
            seed=seed,
            valid=vmask[row],
            unused_to_test=unused_to_test,
        )
        results[hid] = r
        if r.ok:
            masks[0, row, r.train] = True
            masks[1, row, r.validation] = True
            masks[2, row, r.test] = True
        else:
            too_few[hid] = r.reason or "too few records"
    return FleetSplit(kind, results, masks[0], masks[1], masks[2], too_few)


def split_masks(
    kind: SplitKind,
    azimuth_rad,
    elevation_rad,
    unix_time_s,
    *,
    valid=None,
    **kwargs,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(train_mask, val_mask, test_mask)``, each bool ``(h, m)``, for a padded fleet.

    Shorthand for :func:`split_fleet` without ids; heliostats with too few records
    get all-False rows (use :func:`split_fleet` to learn which and why).
    """
    az = np.asarray(azimuth_rad)
    ids = [str(i) for i in range(az.shape[0])] if az.ndim == 2 else []
    fs = split_fleet(kind, azimuth_rad, elevation_rad, unix_time_s, ids, valid=valid, **kwargs)
    return fs.train_mask, fs.val_mask, fs.test_mask


def split_dict(
    kind: SplitKind,
    records: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
    **kwargs,
) -> dict[str, SplitResult]:
    """Split ragged per-heliostat records: ``{id: (azimuth_rad, elevation_rad, unix_time_s)}``
    -> ``{id: SplitResult}`` (keyword arguments as in :func:`split_records`)."""
    return {hid: split_records(kind, *arrs, **kwargs) for hid, arrs in records.items()}


def chronological_holdout(
    fit_mask: np.ndarray, unix_time: np.ndarray, min_records: int, fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(early, late)`` ``(H, M)`` masks: for every heliostat with at least
    ``min_records`` records in ``fit_mask``, all with finite times, its latest
    ``round(fraction * n)`` (at least 2) records are ``late``; every other record of
    ``fit_mask`` is ``early`` (heliostats with fewer records keep all theirs there)."""
    fit_mask = np.asarray(fit_mask, bool)
    t = np.where(fit_mask, np.asarray(unix_time, float), np.inf)
    order = np.argsort(t, axis=1, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.arange(t.shape[1])[None, :], axis=1)
    n = fit_mask.sum(axis=1)
    timed = ~np.any(fit_mask & ~np.isfinite(np.asarray(unix_time, float)), axis=1)
    eligible = (n >= min_records) & timed
    n_late = np.maximum(2, np.floor(fraction * n + 0.5)).astype(int)
    late = fit_mask & eligible[:, None] & (rank >= (n - n_late)[:, None])
    return fit_mask & ~late, late


def days_since_fit(fit_mask: np.ndarray, record_time: np.ndarray, when: np.ndarray) -> np.ndarray:
    """Effective age (days) of each heliostat's fitted state at ``when`` (unix s,
    ``(H, N)`` or ``(N,)``), for a beam that drifts as a random walk: a fit to records
    at times ``t_i`` (``fit_mask`` ``(H, M)``, times ``record_time`` unix s) pins
    roughly their mean state, which lags the last record ``t_L`` by
    ``c = (1/n^2) sum_ij min(t_L - t_i, t_L - t_j)`` (``T/3`` for ``n`` records evenly
    spread over ``T`` days), so a record at ``t`` departs from it by a random walk of
    ``max(0, t - t_L) + c`` days. NaN for a heliostat without a timed fitted record."""
    fit_mask = np.asarray(fit_mask, bool)
    t = np.asarray(record_time, float) / 86400.0
    last = np.max(np.where(fit_mask, t, -np.inf), axis=1)
    last = np.where(np.isfinite(last), last, np.nan)
    lag = np.sort(np.where(fit_mask, last[:, None] - t, np.inf), axis=1)  # ascending, unused at the end
    n = fit_mask.sum(axis=1)
    k = np.arange(t.shape[1])[None, :]
    weight = np.where(k < n[:, None], 2.0 * (n[:, None] - k) - 1.0, 0.0)  # times each sorted lag is a pair's min
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.sum(np.where(weight > 0, lag * weight, 0.0), axis=1) / n.astype(float) ** 2
    when = np.asarray(when, float) / 86400.0
    when = np.broadcast_to(when, (last.shape[0], when.shape[-1]))
    return np.maximum(0.0, when - last[:, None]) + c[:, None]


def days_from_fitted_mean(fit_mask: np.ndarray, record_time: np.ndarray, when: np.ndarray) -> np.ndarray:
    """``(H, N)`` days from the mean time of each heliostat's fitted records
    (``fit_mask`` ``(H, M)``, times ``record_time`` unix s) to ``when`` (unix s,
    ``(H, N)`` or ``(N,)``), signed (negative before it): the age of the fitted state
    for a beam that *creeps* linearly in time. A least-squares fit of a zero to
    records at times ``t_i`` pins the zero at their mean time ``t_mean``, so a creep at
    rate ``rho`` (mrad per day) leaves ``rho (t - t_mean)`` at ``t``, the creep term of
    the predictive law (:mod:`heliojax._predictive`). NaN for a heliostat without a
    timed fitted record."""
    fit_mask = np.asarray(fit_mask, bool)
    t = np.asarray(record_time, float) / 86400.0
    use = fit_mask & np.isfinite(t)
    n = use.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, np.sum(np.where(use, t, 0.0), axis=1) / n, np.nan)
    when = np.asarray(when, float) / 86400.0
    when = np.broadcast_to(when, (mean.shape[0], when.shape[-1]))
    return when - mean[:, None]


_GAP_BLOCK = 256
"""Heliostats per block of :func:`record_sky_gap_deg` (memory ``O(block M^2)``)."""


def record_sky_gap_deg(
    fit_mask: Bool[np.ndarray, "H M"], record_sun: Float[np.ndarray, "H M 3"]
) -> Float[np.ndarray, "H M"]:
    """``(H, M)`` angle (deg) from each record's sun to the nearest sun of its
    heliostat's fitted records (``fit_mask`` ``(H, M)``; ``record_sun`` ``(H, M, 3)``
    unit ENU vectors to the sun): 0 for a fitted record, inf for every record of a
    heliostat without one, NaN for a record whose sun is not finite. The per-record
    counterpart of :func:`heliojax.sky_gap_deg` (instants shared by all heliostats),
    the sky gap of the predictive law (:mod:`heliojax._predictive`). Heliostats are
    taken in blocks, so memory stays ``O(block M^2)``.

    Raises:
        ValueError: shapes other than ``(H, M)`` and ``(H, M, 3)``, or a finite sun
            vector that is not a unit vector (one of length 2 had put every gap at 0
            deg, one of length 0.5 at ~75 deg).
    """
    fit_mask = np.asarray(fit_mask, bool)
    sun = np.asarray(record_sun, float)
    if fit_mask.ndim != 2 or sun.shape != (*fit_mask.shape, 3):
        raise ValueError(
            f"fit_mask has shape {fit_mask.shape} and record_sun {sun.shape}; expected (H, M) and (H, M, 3)"
        )
    known = np.all(np.isfinite(sun), axis=-1)
    check_unit_vectors(sun, known, "record_sun")
    use = fit_mask & known
    sun = np.where(known[..., None], sun, 0.0)
    out = np.empty(fit_mask.shape)
    for start in range(0, fit_mask.shape[0], _GAP_BLOCK):  # blocks of heliostats, not one each
        block = slice(start, start + _GAP_BLOCK)
        cosine = np.einsum("hmi,hni->hmn", sun[block], sun[block])
        best = np.max(np.where(use[block][:, None, :], cosine, -np.inf), axis=-1, initial=-np.inf)
        with np.errstate(invalid="ignore"):
            out[block] = np.where(np.isfinite(best), np.degrees(np.arccos(np.clip(best, -1.0, 1.0))), np.inf)
    return np.where(known, out, np.nan)
