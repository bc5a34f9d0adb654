"""Benchmark splits: small tables whose expected splits were worked out by hand."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest

from heliojax._errors import ConfigError
from heliojax._splits import (
    SPLIT_NAMES,
    knn_mean_distance,
    minimum_records,
    solstice_distance_s,
    split_fleet,
    split_masks,
    split_records,
)

DAY = 86400.0


def utc(*args) -> float:
    return dt.datetime(*args, tzinfo=dt.UTC).timestamp()


def as_set(a) -> set[int]:
    return {int(i) for i in a}


def check_partition(r, n):
    parts = [as_set(r.train), as_set(r.validation), as_set(r.test), as_set(r.unused)]
    assert sum(len(p) for p in parts) == n, "overlapping parts"
    assert set().union(*parts) == set(range(n)), "parts do not cover all records"
    for a in (r.train, r.validation, r.test, r.unused):
        assert a.dtype == np.int64 and np.all(np.diff(a) > 0)


# --------------------------------------------------------------------- time
def test_time_split_by_hand():
    # times:        idx 0   1   2   3   4   5   6
    t = np.array([50, 10, 40, 20, 70, 30, 60], dtype=float)
    z = np.zeros(7)
    # chronological order: 1(10) 3(20) 5(30) 2(40) 0(50) 6(60) 4(70)
    r = split_records("time", z, z, t, n_train=3, n_val=1)
    assert r.ok and r.reason is None
    assert as_set(r.train) == {1, 3, 5}
    assert as_set(r.validation) == {4}
    assert as_set(r.test) == {0, 2, 6}
    check_partition(r, 7)
    # fraction: floor(0.5 * 7) = 3 earliest train, no validation, rest test
    r = split_records("time", z, z, t, train_fraction=0.5)
    assert as_set(r.train) == {1, 3, 5} and as_set(r.validation) == set()
    assert as_set(r.test) == {0, 2, 4, 6}
    # fraction 0.6 of 7 = 4.2 -> 4 train
    r = split_records("time", z, z, t, train_fraction=0.6)
    assert as_set(r.train) == {1, 2, 3, 5}


# ------------------------------------------------------------------ azimuth
def test_azimuth_split_by_hand():
    az_deg = np.array([10, -50, 30, -50, 70, 0, 90, 20], dtype=float)
    el = np.radians(np.full(8, 30.0))
    t = np.array([5, 200, 5, 100, 5, 5, 5, 5], dtype=float)
    # sorted by (azimuth, time): 3(-50,t100) 1(-50,t200) 5(0) 0(10) 7(20) 2(30) 4(70) 6(90)
    r = split_records("azimuth", np.radians(az_deg), el, t, n_train=3, n_val=2)
    assert as_set(r.train) == {1, 3, 5}
    assert as_set(r.validation) == {4, 6}
    assert as_set(r.test) == {0, 2, 7}
    check_partition(r, 8)
    # the time breaks the azimuth tie: with n_train=1 the earlier of 1 and 3 trains
    r = split_records("azimuth", np.radians(az_deg), el, t, n_train=1, n_val=1)
    assert as_set(r.train) == {3} and as_set(r.validation) == {6}
    assert as_set(r.test) == {0, 1, 2, 4, 5, 7}


# ----------------------------------------------------------------- solstice
def test_solstice_distance_by_hand(unchecked):
    t = np.array(
        [
            utc(2022, 12, 20, 12),  # 1 day before the 2022 winter solstice
            utc(2023, 1, 10, 12),  # 20 days after the *previous year's* one
            utc(2023, 12, 1, 12),  # 20 days before the same year's one
            utc(2023, 3, 22, 12),  # halfway Dec 21 -> Jun 21 (182 d): 91 d to both
        ]
    )
    np.testing.assert_allclose(solstice_distance_s(t, "winter") / DAY, [1, 20, 20, 91])
    np.testing.assert_allclose(solstice_distance_s(t, "summer") / DAY, [182, 162, 163, 91])
    with pytest.raises(ConfigError):
        solstice_distance_s(t, "spring")


def test_solstice_split_by_hand():
    t = np.array(
        [
            utc(2022, 12, 20, 12),  # 0: winter 1 d
            utc(2023, 6, 22, 12),  # 1: summer 1 d
            utc(2023, 1, 10, 12),  # 2: winter 20 d (previous year's solstice)
            utc(2022, 7, 1, 12),  # 3: summer 10 d
            utc(2023, 3, 20, 12),  # 4: winter 89 d, summer 93 d
            utc(2022, 5, 22, 12),  # 5: summer 30 d
            utc(2023, 12, 1, 12),  # 6: winter 20 d: ties with 2, later in time
        ]
    )
    z = np.zeros(7)
    r = split_records("solstice", z, z, t, n_train=2, n_val=2)
    # winter order: 0 (1 d), 2 (20 d, earlier), 6 (20 d) ...
    assert as_set(r.train) == {0, 2}
    # summer order among the rest: 1 (1 d), 3 (10 d), 5 (30 d), 4 (93 d), 6 (163 d)
    assert as_set(r.validation) == {1, 3}
    assert as_set(r.test) == {4, 5, 6}
    check_partition(r, 7)


def test_solstice_validation_never_takes_a_training_record():
    # A (2023-03-22 12:00) lies 91 d from both solstices; C and D (21 Sep 00:00)
    # lie 91.5 d from both. A is closest to the winter solstice *and* to the
    # summer solstice. PAINT would relabel A as validation and train on nothing;
    # heliojax keeps A for training and validates on the closest of the others.
    t = np.array([utc(2023, 3, 22, 12), utc(2023, 9, 21), utc(2024, 9, 21)])
    np.testing.assert_allclose(solstice_distance_s(t, "winter") / DAY, [91, 91.5, 91.5])
    np.testing.assert_allclose(solstice_distance_s(t, "summer") / DAY, [91, 91.5, 91.5])
    z = np.zeros(3)
    r = split_records("solstice", z, z, t, n_train=1, n_val=1)
    assert as_set(r.train) == {0}
    assert as_set(r.validation) == {1}  # tie with 2 broken by time
    assert as_set(r.test) == {2}


# ----------------------------------------------------------------- balanced
def _deg(az, el):
    return np.radians(np.asarray(az, float)), np.radians(np.asarray(el, float))


def test_balanced_split_by_hand():
    # Three obvious clusters: A = {0, 1}, B = {2, 3}, C = {4, 5, 6}; k = n_val = 3.
    az, el = _deg([-60, -61, 0, 1, 60, 61, 60], [30, 31, 60, 61, 30, 31, 32])
    t = np.arange(7.0)
    r = split_records("balanced", az, el, t, n_train=1, n_val=3, seed=42)
    check_partition(r, 7)
    val, test = as_set(r.validation), as_set(r.test)
    # one validation and one test record per cluster ...
    for cluster in ({0, 1}, {2, 3}, {4, 5, 6}):
        assert len(val & cluster) == 1 and len(test & cluster) == 1
    # ... so A and B are used up, and the single training record comes from C.
    assert {0, 1, 2, 3} <= val | test
    assert len(r.train) == 1 and as_set(r.train) <= {4, 5, 6}
    assert as_set(r.unused) == set()


def test_balanced_singleton_cluster_fills_test_from_pool():
    # Record 0 is alone; 1..5 form one tight cluster; k = 2.
    az, el = _deg([-80, 40, 41, 42, 40, 41], [10, 50, 51, 50, 52, 50])
    r = split_records("balanced", az, el, np.arange(6.0), n_train=1, n_val=2, seed=0)
    check_partition(r, 6)
    assert 0 in as_set(r.validation)  # the singleton's only member validates
    assert 0 not in as_set(r.test)
    assert len(r.validation) == 2 and len(r.test) == 2  # one test drawn from the pool
    assert as_set(r.test) <= {1, 2, 3, 4, 5}
    assert len(r.train) == 1 and len(r.unused) == 1  # PAINT drops the record not drawn
    r2 = split_records("balanced", az, el, np.arange(6.0), n_train=1, n_val=2, seed=0, unused_to_test=True)
    assert len(r2.unused) == 0 and len(r2.test) == 3


def test_balanced_is_deterministic_under_seed_and_depends_on_it():
    rng = np.random.default_rng(1)
    az, el = rng.uniform(-1.5, 1.5, 40), rng.uniform(0.1, 1.2, 40)
    t = np.arange(40.0)
    runs = [split_records("balanced", az, el, t, n_train=10, n_val=5, seed=7) for _ in range(2)]
    for a in ("train", "validation", "test", "unused"):
        np.testing.assert_array_equal(getattr(runs[0], a), getattr(runs[1], a))
    others = [split_records("balanced", az, el, t, n_train=10, n_val=5, seed=s) for s in range(8, 14)]
    assert any(not np.array_equal(o.train, runs[0].train) for o in others)
    check_partition(runs[0], 40)
    assert len(runs[0].train) == 10 and len(runs[0].validation) == 5 and len(runs[0].test) == 5


# ------------------------------------------------------------ high variance
def test_high_variance_split_by_hand():
    # Points on a line (elevation constant), azimuth x / 64 rad (exact in binary).
    x = np.array([0, 1, 2, 3, 4, 10, 30], dtype=float)
    az, el = x / 64, np.full(7, 0.5)
    # mean distance to the 3 nearest others (in units of 1/64):
    #   0: (1+2+3)/3 = 2      1: (1+1+2)/3 = 4/3   2: (1+1+2)/3 = 4/3
    #   3: (1+1+2)/3 = 4/3    4: (1+2+3)/3 = 2     5: (6+7+8)/3 = 7
    #   6: (20+26+27)/3 = 73/3
    np.testing.assert_allclose(knn_mean_distance(np.stack([az, el], 1)) * 64, [2, 4 / 3, 4 / 3, 4 / 3, 2, 7, 73 / 3])
    # most isolated first, ties by index: 6, 5, 0, 4, 1, 2, 3
    r = split_records("high_variance", az, el, np.zeros(7), n_train=2, n_val=1)
    assert as_set(r.validation) == {6} and as_set(r.test) == {5}
    assert as_set(r.train) == {0, 4} and as_set(r.unused) == {1, 2, 3}
    r = split_records("high_variance", az, el, np.zeros(7), n_train=2, n_val=2)
    assert as_set(r.validation) == {5, 6} and as_set(r.test) == {0, 4}
    assert as_set(r.train) == {1, 2} and as_set(r.unused) == {3}
    check_partition(r, 7)


def test_knn_metric_matches_sklearn():
    from sklearn.neighbors import NearestNeighbors

    f = np.random.default_rng(3).normal(size=(30, 2))
    d, _ = NearestNeighbors(n_neighbors=4).fit(f).kneighbors(f)
    np.testing.assert_allclose(knn_mean_distance(f), d[:, 1:].mean(1), rtol=1e-12)


# ------------------------------------------------------------- too few etc.
@pytest.mark.parametrize("kind", SPLIT_NAMES)
def test_too_few_records_reported_not_dropped(kind):
    n = 6
    az, el, t = np.linspace(-1, 1, n), np.linspace(0.2, 0.8, n), np.arange(n, dtype=float)
    assert minimum_records(3, 2) == 7
    r = split_records(kind, az, el, t, n_train=3, n_val=2)
    assert not r.ok and "needs at least 7" in r.reason and "6 valid records" in r.reason
    assert r.train.size == r.validation.size == r.test.size == 0
    assert as_set(r.unused) == set(range(n))
    # exactly the minimum works, and every split gives the requested sizes
    r = split_records(kind, np.linspace(-1, 1, 7), np.linspace(0.2, 0.8, 7), np.arange(7.0), n_train=3, n_val=2)
    assert r.ok and len(r.train) == 3 and len(r.validation) == 2 and len(r.test) == 2
    check_partition(r, 7)


def test_invalid_records_take_no_part():
    t = np.array([50, 10, np.nan, 20, 70, 30, 60], dtype=float)
    z = np.zeros(7)
    valid = np.array([True, True, True, True, True, False, True])
    r = split_records("time", z, z, t, n_train=2, n_val=1, valid=valid)
    # valid and finite: 0(50) 1(10) 3(20) 4(70) 6(60)
    assert as_set(r.train) == {1, 3} and as_set(r.validation) == {4}
    assert as_set(r.test) == {0, 6} and as_set(r.unused) == {2, 5}
    # azimuth needs no time (it only breaks ties, a missing one sorting last)
    az = np.radians([10.0, 20, 20, 30, np.nan, 40, 50])
    r = split_records("azimuth", az, z, t, n_train=2, n_val=1)
    # finite azimuths: 0(10) 1(20,t10) 2(20,t=nan) 3(30) 5(40) 6(50); 4 invalid
    assert as_set(r.train) == {0, 1} and as_set(r.validation) == {6}
    assert as_set(r.test) == {2, 3, 5} and as_set(r.unused) == {4}


def test_bad_arguments(unchecked):
    z = np.zeros(8)
    with pytest.raises(ConfigError, match="unknown split"):
        split_records("random", z, z, z, n_train=2)
    with pytest.raises(ConfigError, match="exactly one"):
        split_records("time", z, z, z)
    with pytest.raises(ConfigError, match="n_val >= 1"):
        split_records("balanced", z, z, z, n_train=2, n_val=0)
    with pytest.raises(ConfigError, match="differ in length"):
        split_records("time", z, z[:3], z, n_train=2)


# -------------------------------------------------------------------- fleet
@pytest.mark.parametrize("kind", SPLIT_NAMES)
def test_fleet_masks(kind):
    rng = np.random.default_rng(5)
    h, m = 3, 12
    az = rng.uniform(-1.5, 1.5, (h, m))
    el = rng.uniform(0.1, 1.2, (h, m))
    t = rng.uniform(1.65e9, 1.72e9, (h, m))
    valid = np.ones((h, m), bool)
    valid[1, 3:] = False  # BB has only 3 real records (padding)
    valid[2, 10:] = False
    fs = split_fleet(kind, az, el, t, ["AA", "BB", "CC"], valid=valid, n_train=4, n_val=2)
    assert set(fs.too_few) == {"BB"} and "3 valid records" in fs.too_few["BB"]
    assert not fs.results["BB"].ok and fs.results["AA"].ok and fs.results["CC"].ok
    assert not (fs.train_mask[1] | fs.val_mask[1] | fs.test_mask[1]).any()
    total = fs.train_mask.astype(int) + fs.val_mask + fs.test_mask
    assert total.max() <= 1  # no record in two splits
    assert not (total.astype(bool) & ~valid).any()  # padding never used
    for row, hid in enumerate(["AA", "CC"]):
        r = fs.results[hid]
        row = [0, 2][row]
        np.testing.assert_array_equal(np.flatnonzero(fs.train_mask[row]), r.train)
        np.testing.assert_array_equal(np.flatnonzero(fs.test_mask[row]), r.test)
        assert len(r.train) == 4 and len(r.validation) == 2
    tr, va, te = split_masks(kind, az, el, t, valid=valid, n_train=4, n_val=2)
    np.testing.assert_array_equal(tr, fs.train_mask)
    np.testing.assert_array_equal(va, fs.val_mask)
    np.testing.assert_array_equal(te, fs.test_mask)


def test_labels():
    z = np.zeros(4)
    r = split_records("time", z, z, np.array([3.0, 2, 1, 0]), n_train=1, n_val=1)
    assert list(r.labels()) == ["validation", "test", "test", "train"]
