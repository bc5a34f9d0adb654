"""Fleet calibration on simulated fleets with known parameters."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax._calibration import STONE8, FitStatus
from heliojax._simulate import (
    calibration_target,
    random_stone_models,
    simulate_records,
    synthetic_contexts,
    synthetic_geometry,
)


def _fleet(h, m, noise=0.2, seed=0, angle_sigma=3e-3):
    k = jax.random.split(jax.random.PRNGKey(seed), 5)
    g = synthetic_geometry(k[0], h)
    true = random_stone_models(k[1], h, angle_sigma=angle_sigma)
    # The plant aims with an older calibration: the truth plus ~1 mrad errors.
    old = random_stone_models(k[4], h, angle_sigma=0.3e-3, gear_sigma=2e-4)
    controller = jax.tree_util.tree_map(lambda t, o, n: t + o - n, true, old, hj.StoneModel.nominal())
    ctx = synthetic_contexts(k[2], h, m)
    sim = simulate_records(k[3], true, g, ctx, calibration_target(), controller_models=controller, noise_mrad=noise)
    return g, true, ctx, sim


@pytest.fixture(scope="module")
def fleet100():
    h, m = 100, 100
    g, true, ctx, sim = _fleet(h, m)
    # Held-out records drawn at random (70 % train): same distribution as training.
    is_train = jax.random.uniform(jax.random.PRNGKey(99), (h, m)) < 0.7
    train = is_train & sim.hit
    test = ~is_train & sim.hit
    data = hj.CalibrationData(geometry=g, counts=sim.counts, context=ctx, focal_spot=sim.focal_spot, mask=train)
    res = hj.fit_fleet(data, "stone8", hj.FitConfig())
    return g, true, ctx, sim, train, test, data, res


def test_simulated_fleet_recovers_parameters_and_reaches_the_noise_floor(fleet100):
    g, true, ctx, sim, train, test, data, res = fleet100
    assert all(s == "converged" for s in res.status_labels())
    tp = np.stack([np.asarray(getattr(true, n)) for n in STONE8.names], 1)
    err = np.asarray(res.params) - tp
    rms = np.sqrt(np.mean(err**2, axis=0))
    named = dict(zip(STONE8.names, rms))
    assert named["alpha"] < 0.3e-3 and named["beta"] < 0.3e-3 and named["tau_k"] < 0.3e-3
    assert named["gr1"] < 2e-4 and named["gr2"] < 2e-4
    # Held-out beam error vs the noise-only floor (the true model on the same records).
    e_fit = np.asarray(hj.beam_errors_mrad(res.models(), g, sim.counts, ctx, sim.focal_spot, test))
    e_true = np.asarray(hj.beam_errors_mrad(true, g, sim.counts, ctx, sim.focal_spot, test))
    ratio = np.sqrt(np.nanmean(e_fit**2, 1)) / np.sqrt(np.nanmean(e_true**2, 1))
    assert np.mean(ratio <= 1.1) >= 0.99, np.sort(ratio)[-5:]
    # The Gauss-Newton standard errors describe the actual errors (z-scores ~ N(0, 1)).
    z = err / np.asarray(res.std)
    assert 0.75 < np.sqrt(np.mean(z**2)) < 1.3


@pytest.mark.slow
def test_strategies_agree(fleet100):
    *_, data, res = fleet100
    sub = jax.tree_util.tree_map(lambda x: x[:8], data)
    ref = hj.fit_fleet(sub, "stone8", hj.FitConfig(strategy="map"))
    for strategy in ("vmap", "chunked"):
        other = hj.fit_fleet(sub, "stone8", hj.FitConfig(strategy=strategy, chunk_size=3))
        np.testing.assert_allclose(other.params, ref.params, rtol=0, atol=1e-10)
        np.testing.assert_array_equal(other.status, ref.status)
    np.testing.assert_allclose(ref.params, res.params[:8], atol=1e-12)


def test_padding_records_and_heliostats_change_nothing(fleet100):
    *_, data, res = fleet100
    sub = jax.tree_util.tree_map(lambda x: x[:6], data)
    ref = hj.fit_fleet(sub, "stone8")
    # Append 20 garbage records (masked) and 2 empty heliostats.
    def pad_records(x):
        if x.ndim >= 2 and x.shape[1] == 100:
            junk = jnp.full((x.shape[0], 20) + x.shape[2:], 7.0e3 if x.dtype != bool else False, x.dtype)
            return jnp.concatenate([x, junk], axis=1)
        return x

    padded = jax.tree_util.tree_map(pad_records, sub)
    padded = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, x[:2]], axis=0), padded)
    padded = hj.CalibrationData(
        geometry=padded.geometry, counts=padded.counts, context=padded.context,
        focal_spot=padded.focal_spot, mask=padded.mask.at[6:].set(False),
    )
    out = hj.fit_fleet(padded, "stone8")
    np.testing.assert_allclose(out.params[:6], ref.params, rtol=0, atol=1e-12)
    assert [FitStatus(int(s)) for s in out.status[6:]] == [FitStatus.PADDING] * 2


def test_bad_heliostats_do_not_spoil_a_fleet_of_1000():
    h, m = 1000, 24
    g, true, ctx, sim = _fleet(h, m, seed=5)
    mask = sim.hit
    good = hj.CalibrationData(geometry=g, counts=sim.counts, context=ctx, focal_spot=sim.focal_spot, mask=mask)
    # Three problem heliostats replace heliostats 10, 20, 30 in a second run.
    counts = sim.counts
    spots = sim.focal_spot
    m2 = mask
    spots = spots.at[10, 3].set(jnp.nan)                      # NaN record
    m2 = m2.at[20].set(jnp.arange(m) < 3)                      # 3 records
    rng = np.random.default_rng(0)                             # garbage that cannot converge
    spots = spots.at[30].set(jnp.asarray(rng.uniform(-80, 80, (m, 3)) + np.array([0, -3, 120])))
    counts = counts.at[30].set(jnp.asarray(rng.uniform(1000, 60000, (m, 2))))
    bad = hj.CalibrationData(geometry=g, counts=counts, context=ctx, focal_spot=spots, mask=m2)
    cfg = hj.FitConfig()
    r_good = hj.fit_fleet(good, "stone8", cfg)
    r_bad = hj.fit_fleet(bad, "stone8", cfg)
    others = np.setdiff1d(np.arange(h), [10, 20, 30])
    np.testing.assert_array_equal(np.asarray(r_bad.params)[others], np.asarray(r_good.params)[others])
    np.testing.assert_array_equal(np.asarray(r_bad.status)[others], np.asarray(r_good.status)[others])
    labels = r_bad.status_labels()
    assert labels[10] == "non_finite_input"
    assert labels[20] == "too_few_records"
    np.testing.assert_array_equal(np.asarray(r_bad.params)[20], STONE8.nominal)  # never an unconstrained fit
    assert labels[30] in ("max_steps", "diverged")
    assert np.mean(np.asarray(r_good.status)[others] == FitStatus.CONVERGED) > 0.99


def test_prior_pulls_weak_parameters_toward_nominal(fleet100):
    *_, data, res = fleet100
    sub = jax.tree_util.tree_map(lambda x: x[:4], data)
    strong = hj.FitConfig(prior_sigma={"gamma": 1e-6, "delta": 1e-6})
    out = hj.fit_fleet(sub, "stone8", strong)
    gi = STONE8.names.index("gamma")
    di = STONE8.names.index("delta")
    assert np.max(np.abs(np.asarray(out.params)[:, [gi, di]])) < 1e-5
    assert np.max(np.abs(np.asarray(res.params)[:4, [gi, di]])) > 1e-4
    # The other parameters still fit (partly absorbing the pinned pair's signature).
    assert all(lab == "converged" for lab in out.status_labels())
    assert np.all(np.asarray(out.rms_mrad) < 3.0)


def test_actuator_model_fits_actuator_truth():
    h, m = 6, 60
    k = jax.random.split(jax.random.PRNGKey(11), 4)
    g = synthetic_geometry(k[0], h)
    vec = np.zeros((h, 10))
    rng = np.random.default_rng(3)
    vec[:, :4] = rng.normal(0, 2e-3, (h, 4))
    vec[:, 4:6] = rng.normal(0, 5e-3, (h, 2))
    vec[:, 6:8] = rng.normal(0, 2e-3, (h, 2))
    true = jax.vmap(hj.ACTUATOR.builder)(jnp.asarray(vec))
    ctx = synthetic_contexts(k[1], h, m)
    sim = simulate_records(k[2], true, g, ctx, calibration_target(), controller_models=true, noise_mrad=0.1)
    data = hj.CalibrationData(geometry=g, counts=sim.counts, context=ctx, focal_spot=sim.focal_spot, mask=sim.hit)
    res = hj.fit_fleet(data, "actuator")
    assert all(s == "converged" for s in res.status_labels())
    assert np.all(np.asarray(res.rms_mrad) < 0.2)
    np.testing.assert_allclose(np.asarray(res.params)[:, 4:6], vec[:, 4:6], atol=1e-3)
