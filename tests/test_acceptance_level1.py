"""Level-1 test: confidence intervals and pass rules."""

import math

import numpy as np
import pytest
from scipy import stats

from heliojax.acceptance import confidence_intervals, level1_test


def test_normal_ci_by_hand():
    x = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    (ml, mh), (sl, sh) = confidence_intervals(x, 0.95, "normal")
    s = math.sqrt(2.5)
    t = 2.7764451051977987  # t_{0.975, 4}
    assert ml == pytest.approx(3 - t * s / math.sqrt(5), rel=1e-12)
    assert mh == pytest.approx(3 + t * s / math.sqrt(5), rel=1e-12)
    # chi2_{0.975,4} = 11.143286781877796, chi2_{0.025,4} = 0.4844185570879305
    assert sl == pytest.approx(math.sqrt(4 * 2.5 / 11.143286781877796), rel=1e-9)
    assert sh == pytest.approx(math.sqrt(4 * 2.5 / 0.4844185570879305), rel=1e-9)


def test_bootstrap_ci_covers_rayleigh_mean():
    # Rayleigh radial errors, true mean sigma*sqrt(pi/2)
    sigma = 1.3
    true_mean = sigma * math.sqrt(math.pi / 2)
    hits = 0
    for seed in range(40):
        x = stats.rayleigh.rvs(scale=sigma, size=30, random_state=seed)
        (lo, hi), _ = confidence_intervals(x, 0.95, "bootstrap", n_resamples=1000, seed=seed)
        hits += lo <= true_mean <= hi
    assert hits >= 34  # nominal 38 of 40


def test_rayleigh_weibull_fit_and_skew_visible():
    x = stats.rayleigh.rvs(scale=1.0, size=400, random_state=1)
    r = level1_test(x, 1.25, 0.66, distribution="radial")
    assert r.method == "bootstrap-bca"
    assert r.weibull_shape == pytest.approx(2.0, abs=0.25)
    assert r.weibull_scale == pytest.approx(math.sqrt(2.0), rel=0.08)
    assert r.normality_p < 0.01  # skewed: not normal


def test_pass_rules_lower_is_better():
    rng = np.random.default_rng(0)
    good = rng.normal(1.7, 0.2, 40)
    bad = rng.normal(2.3, 0.2, 40)
    assert level1_test(good, 1.8, 0.25).passed
    r = level1_test(bad, 1.8, 0.25)
    assert not r.pass_mean and not r.passed and r.pass_std
    wide = rng.normal(1.7, 0.6, 40)
    r = level1_test(wide, 1.8, 0.25)
    assert r.pass_mean and not r.pass_std and not r.passed


def test_pass_rules_higher_and_two_sided_and_sample_size():
    rng = np.random.default_rng(1)
    refl = rng.normal(0.935, 0.001, 20)
    assert not level1_test(refl, 0.94, sense="higher").pass_mean
    assert level1_test(refl, 0.93, sense="higher").pass_mean
    assert not level1_test(refl, 0.93, sense="two-sided").pass_mean
    r = level1_test(refl, 0.93, sense="higher", n_required=25)
    assert r.pass_mean and not r.sufficient_sample and not r.passed


def test_to_json_and_nan_handling():
    r = level1_test(np.array([1.0, np.nan, 2.0, 3.0]), 2.0, None)
    assert r.n == 3 and r.pass_std
    d = r.to_json()
    assert d["pass"] is True and d["weibull_shape"] is None and d["contract_std"] is None
    with pytest.raises(ValueError):
        level1_test(np.array([1.0]), 1.0)


def test_a_large_radial_sample_gets_the_percentile_interval_in_bounded_memory():
    """BCa's jackknife needs memory growing as n^2 (100,000 heliostats asked for 75 GiB):
    beyond BCA_MAX_VALUES the percentile interval is used and named; it covers the true
    mean of the Rayleigh sample like the normal-theory interval does."""
    from heliojax.acceptance._level1 import BCA_MAX_VALUES

    rng = np.random.default_rng(7)
    x = rng.rayleigh(1.0, BCA_MAX_VALUES + 1)
    r = level1_test(x, 1.3, 0.7, distribution="radial", n_resamples=200)
    assert r.method == "bootstrap-percentile"
    (lo, hi), (slo, shi) = confidence_intervals(x, 0.95, "bootstrap", n_resamples=200)
    true_mean, true_std = math.sqrt(math.pi / 2), math.sqrt((4 - math.pi) / 2)
    assert lo < true_mean < hi and slo < true_std < shi
    (nlo, nhi), _ = confidence_intervals(x, 0.95, "normal")
    assert abs((hi - lo) - (nhi - nlo)) < 0.2 * (nhi - nlo)
    assert level1_test(x[:50], 1.3, 0.7, distribution="radial", n_resamples=200).method == "bootstrap-bca"
