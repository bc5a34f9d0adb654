"""KDE extrapolation keeps skew and several peaks."""

import numpy as np
import pytest
from scipy import integrate, stats

from heliojax.acceptance import extrapolate_field, fit_kde, synthetic_field


def _bimodal(rng, n):
    comp = rng.random(n) < 0.5
    return np.where(comp, rng.gamma(100, 1.5 / 100, n), rng.gamma(100, 2.5 / 100, n))


def test_bimodal_field_preserved_in_90_percent_of_seeds():
    field, _ = synthetic_field()
    xy = field.positions[:, :2]
    n, n_meas = len(xy), 60
    kde_ok = normal_rejected = 0
    seeds = range(30)
    for seed in seeds:
        rng = np.random.default_rng(seed)
        truth = _bimodal(rng, n)
        meas = np.sort(rng.choice(n, n_meas, replace=False))
        ex = extrapolate_field(xy, meas, truth[meas], seed=seed)
        un = ~ex.measured
        assert np.array_equal(ex.values[meas], truth[meas])
        # two-sample KS, extrapolated vs true values of the unmeasured heliostats.
        # The extrapolation carries the information of n_meas values only, so the
        # null distribution is that of KS(n_meas, m) (effective size n_meas m / (n_meas + m)).
        d = stats.ks_2samp(ex.values[un], truth[un]).statistic
        m = int(un.sum())
        p = stats.kstwo.sf(d, round(n_meas * m / (n_meas + m)))
        kde_ok += p >= 0.05
        # and the extrapolated field against the measured sample (plain KS)
        assert stats.ks_2samp(ex.values[un], truth[meas]).pvalue >= 0.01 or p < 0.05
        # power check: a normal (mean/sd) extrapolation is rejected
        s = truth[meas]
        normal = rng.normal(s.mean(), s.std(ddof=1), m)
        normal_rejected += stats.ks_2samp(normal, truth[meas]).pvalue < 0.05
    assert kde_ok >= 0.9 * len(seeds)
    assert normal_rejected >= 0.5 * len(seeds)


def test_kde_density_has_two_peaks_and_integrates_to_one():
    rng = np.random.default_rng(3)
    kde = fit_kde(_bimodal(rng, 80), "positive")
    x = np.linspace(0.8, 3.5, 2000)
    f = kde.pdf(x)
    peaks = np.flatnonzero((f[1:-1] > f[:-2]) & (f[1:-1] > f[2:])) + 1
    big = peaks[f[peaks] > 0.3 * f.max()]
    assert len(big) == 2
    assert 1.3 < x[big[0]] < 1.7 and 2.3 < x[big[1]] < 2.7
    total, _ = integrate.quad(lambda t: kde.pdf(np.array([t]))[0], 1e-9, 20, limit=200)
    assert total == pytest.approx(1.0, abs=1e-3)


def test_positive_support_keeps_skew_and_sign():
    x = stats.rayleigh.rvs(scale=0.8, size=60, random_state=0)
    kde = fit_kde(x, "positive")
    draws = kde.sample(20000, 1)
    assert draws.min() > 0
    assert stats.skew(draws) > 0.3  # Rayleigh skewness 0.63
    assert kde.pdf(np.array([-0.1, 0.0]))[:].tolist() == [0.0, 0.0]


def test_unit_support_and_bandwidth_options():
    rng = np.random.default_rng(2)
    r = rng.normal(0.94, 0.002, 30)
    for bw in ("cv", "scott", "silverman", 0.3):
        d = fit_kde(r, "unit", bw).sample(5000, 0)
        assert 0 < d.min() and d.max() < 1
        assert abs(d.mean() - r.mean()) < 0.001
    with pytest.raises(ValueError):
        fit_kde(np.array([-1.0, 1.0]), "positive")


def test_cluster_labels_propagate_to_nearest():
    xy = np.column_stack([np.arange(20.0), np.zeros(20)])
    meas = np.array([0, 2, 4, 6, 13, 15, 17, 19])
    vals = np.array([1.0, 1.1, 0.9, 1.05, 3.0, 3.1, 2.9, 3.05])
    lab = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    ex = extrapolate_field(xy, meas, vals, lab)
    assert ex.labels.tolist() == [0] * 10 + [1] * 10
    assert np.all(ex.values[10:] > 2.0) and np.all(ex.values[:10] < 2.0)


def test_cv_bandwidth_is_the_direct_leave_one_out_search_and_bounded_beyond_its_cap():
    """The row-chunked search equals the direct (grid, n, n) leave-one-out likelihood;
    beyond MAX_CV_VALUES it uses a fixed subsample (100,000 values used to ask 75 GiB)."""
    from heliojax.acceptance._extrapolate import MAX_CV_VALUES, cv_bandwidth_factor

    rng = np.random.default_rng(3)
    y = rng.gamma(3.0, 1.0, 300)
    n, sd = y.size, y.std(ddof=1)
    factors = n ** (-0.2) * np.logspace(np.log10(0.05), np.log10(2.0), 60)
    d2 = (y[:, None] - y[None, :]) ** 2
    np.fill_diagonal(d2, np.inf)
    h = factors * sd
    dens = np.exp(-0.5 * d2[None] / h[:, None, None] ** 2).sum(axis=2) / ((n - 1) * h[:, None] * np.sqrt(2 * np.pi))
    with np.errstate(divide="ignore"):  # the smallest factors underflow (never the best)
        loo = np.log(dens).sum(axis=1)
    assert cv_bandwidth_factor(y) == factors[int(np.argmax(loo))]
    big = rng.gamma(3.0, 1.0, 4 * MAX_CV_VALUES)
    sub = np.random.default_rng(0).choice(big, MAX_CV_VALUES, replace=False)
    assert cv_bandwidth_factor(big) == cv_bandwidth_factor(sub) * 4 ** (-0.2)
