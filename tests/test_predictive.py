"""The predicted pointing-error law (heliojax._predictive): prediction regions of the
bivariate Student t against scipy's F and chi-square quantiles and against sampling,
and the maximum-likelihood drift and tails recovered from residuals drawn with known
values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

import heliojax as hj


@pytest.mark.parametrize("probability", [0.5, 0.68, 0.95, 0.999])
@pytest.mark.parametrize("dof", [0.7, 1.0, 2.5, 10.0, 1e4, math.inf])
def test_prediction_region_matches_scipy(probability, dof):
    # d^2 / 2 of a bivariate t with nu degrees of freedom is F(2, nu); chi-square(2) when Gaussian
    expected = stats.chi2.ppf(probability, 2) if math.isinf(dof) else 2.0 * stats.f.ppf(probability, 2, dof)
    assert hj.prediction_region_d2(probability, dof) == pytest.approx(expected, rel=1e-9)


def _t_residuals(rng, scale, dof, n):
    """``(n, 2)`` bivariate t draws with scale matrices ``scale`` ``(n, 2, 2)``."""
    z = np.einsum("nij,nj->ni", np.linalg.cholesky(scale), rng.normal(size=(n, 2)))
    return z if math.isinf(dof) else z / np.sqrt(rng.chisquare(dof, size=n) / dof)[:, None]


def test_prediction_region_holds_its_probability_by_sampling():
    rng = np.random.default_rng(0)
    n = 40_000
    scale = np.broadcast_to(np.array([[2.0, 0.6], [0.6, 0.5]]), (n, 2, 2))
    for dof in (1.2, 4.0, math.inf):
        r = _t_residuals(rng, scale, dof, n)
        d2 = np.einsum("ni,nij,nj->n", r, np.linalg.inv(scale), r)
        for p in (0.68, 0.95):
            # binomial standard error at n = 40,000: <= 0.0025
            assert np.mean(d2 <= hj.prediction_region_d2(p, dof)) == pytest.approx(p, abs=0.01)


def test_prediction_region_rejects_bad_input():
    with pytest.raises(ValueError, match="probability"):
        hj.prediction_region_d2(1.0)
    with pytest.raises(ValueError, match="tail_dof"):
        hj.prediction_region_d2(0.5, 0.0)


def _validation(rng, n, q, dof):
    """Residuals of ``n`` records with random scales (noise 0.3-1 mrad per component,
    correlated) at 1-200 days after the fit, drifting at ``q`` with ``dof`` tails."""
    a = rng.uniform(0.3, 1.0, size=(n, 2, 2)) * np.array([[1.0, 0.3], [0.0, 1.0]])
    scale = np.einsum("nij,nkj->nik", a, a) + 0.05 * np.eye(2)
    days = rng.uniform(1.0, 200.0, size=n)
    total = scale + (q * days)[:, None, None] * np.eye(2)
    return _t_residuals(rng, total, dof, n), scale, days


def test_maximum_likelihood_recovers_drift_and_tails():
    rng = np.random.default_rng(1)
    # Gaussian, no drift: q ~ 0 (far below the noise variance over 200 days) and light tails
    r, s, days = _validation(rng, 3000, 0.0, math.inf)
    q, dof = hj.fit_drift_and_tails(r, s, days)
    assert q * 200.0 < 0.05 and dof >= 50.0
    # a random walk at 0.01 mrad^2/day (2 mrad^2 after 200 days), Gaussian
    r, s, days = _validation(rng, 3000, 0.01, math.inf)
    q, dof = hj.fit_drift_and_tails(r, s, days)
    assert q == pytest.approx(0.01, rel=0.25) and dof >= 50.0
    # heavy tails (nu = 1.5, gross errors and episodes) with a drift: both recovered
    r, s, days = _validation(rng, 3000, 0.01, 1.5)
    q, dof = hj.fit_drift_and_tails(r, s, days)
    assert q == pytest.approx(0.01, rel=0.35) and dof == pytest.approx(1.5, rel=0.2)
