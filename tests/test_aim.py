"""Aiming: counts from the fitted (here: true) models put the beam on the aim point;
flags for out-of-range counts, low sun and unusable fits; vmap equals a loop."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import heliojax as hj
from heliojax.discovery import simulate_fleet

LAT, LON, ALT = 50.913421122592574, 6.387824755874856, 87.0


def _sun(hours):
    t = 1660348800.0 + np.asarray(hours, float) * 3600.0  # 2022-08-13 00:00 UTC + hours
    return hj.solar_position(t, LAT, LON, ALT).direction_enu()


def test_true_models_put_the_beam_on_the_aim_point():
    fleet, truth = simulate_fleet(3, 6, 8, base="actuator", noise_mrad=0.0)
    sun = _sun([2.0, 8.0, 10.0, 12.0, 14.0])  # 02 UTC: night
    aim = jnp.array([0.0, 0.0, 60.0])
    r = hj.aim_fleet(truth, fleet.geometry, sun, aim)
    ok = np.asarray(r.ok)
    assert bool(np.asarray(r.sun_low)[0]) and not np.asarray(r.sun_low)[1:].any()
    assert ok[:, 1:].mean() > 0.5
    # independent check: the true pose reflects the sun onto the aim point
    for i, j in zip(*np.nonzero(ok)):
        model = jax.tree.map(lambda x: x[i], truth)
        geometry = jax.tree.map(lambda x: x[i], fleet.geometry)
        pose = hj.forward(model, geometry, r.counts[i, j])
        ray = hj.reflected_ray(pose, sun[j])
        to_aim = aim - pose.centre
        assert float(hj.angle_between(ray, to_aim)) * 1e3 < 1e-6
    # counts flagged out of range really are outside the actuator range
    oor = np.asarray(r.counts_out_of_range)
    lo = np.asarray(fleet.geometry.actuators.min_counts)[:, None, :]
    hi = np.asarray(fleet.geometry.actuators.max_counts)[:, None, :]
    c = np.asarray(r.counts)
    np.testing.assert_array_equal(oor, np.any((c < lo) | (c > hi), axis=-1))


def test_unfitted_heliostats_are_flagged_and_shapes_broadcast():
    fleet, truth = simulate_fleet(4, 3, 8, base="stone8", noise_mrad=0.0)
    sun = _sun([9.0, 11.0])
    points = jnp.stack([jnp.array([0.0, 0.0, 55.0 + k]) for k in range(3)])
    r = hj.aim_fleet(truth, fleet.geometry, sun, points, fitted=jnp.array([True, False, True]))
    assert r.counts.shape == (3, 2, 2)
    np.testing.assert_array_equal(np.asarray(r.unreliable), [False, True, False])
    assert not np.asarray(r.ok)[1].any()
    np.testing.assert_allclose(np.asarray(r.aim_point)[2, 1], [0.0, 0.0, 57.0])


def test_predicted_pointing_uncertainty_matches_the_true_miss():
    """Independent check of the error bars: fit a simulated fleet with known noise,
    aim with the fitted models, and compare the true models' beam miss of the
    commanded counts with the predicted pointing covariance. The mean squared miss
    over heliostats and instants matches the mean predicted variance (ratio ~1;
    bounds for 60 heliostats whose errors are correlated over the day)."""
    fleet, truth = simulate_fleet(5, 60, 24, base="actuator", noise_mrad=0.5)
    solution = hj.fit(hj.ActuatorModel.nominal(), fleet)
    assert set(solution.status_labels()) == {"converged"}
    sun = _sun([8.0, 10.0, 12.0, 14.0, 16.0])
    aim = jnp.array([0.0, 0.0, 60.0])
    r = hj.aim_fleet(solution.model, fleet.geometry, sun, aim, covariance=solution.covariance, view=solution.view)
    ok = np.asarray(r.ok)
    miss2, var = [], []
    for i, j in zip(*np.nonzero(ok)):
        model = jax.tree.map(lambda x: x[i], truth)
        geometry = jax.tree.map(lambda x: x[i], fleet.geometry)
        pose = hj.forward(model, geometry, r.counts[i, j])
        miss2.append((float(hj.beam_pointing_error(pose, sun[j], aim)) * 1e3) ** 2)
        var.append(float(np.trace(np.asarray(r.pointing_cov_mrad2)[i, j])))
    assert len(miss2) > 150
    ratio = np.mean(miss2) / np.mean(var)
    assert 0.5 < ratio < 2.0, ratio
    assert np.all(np.isfinite(np.asarray(r.pointing_std_mrad)[ok]))
    without = hj.aim_fleet(solution.model, fleet.geometry, sun, aim)
    assert np.isnan(np.asarray(without.pointing_std_mrad)).all()
