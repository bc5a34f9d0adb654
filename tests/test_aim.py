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


def _true_miss_mrad(truth, geometry, counts, sun, aim) -> np.ndarray:
    """``(H, T)`` angle [mrad] between the true models' reflected ray at the
    commanded ``counts`` ``(H, T, 2)`` and the direction to ``aim`` (ENU, m); the
    sun ``(T, 3)``. Forward kinematics only (no inverse)."""

    def one(model, geom, c, s):
        pose = hj.forward(model, geom, c)
        return hj.angle_between(hj.reflected_ray(pose, s), aim - pose.centre) * 1e3

    per_instant = jax.vmap(one, in_axes=(None, None, 0, 0))
    return np.asarray(jax.jit(jax.vmap(per_instant, in_axes=(0, 0, 0, None)))(truth, geometry, counts, sun))


def test_true_models_put_the_beam_on_the_aim_point():
    fleet, truth = simulate_fleet(3, 6, 8, base="actuator", noise_mrad=0.0)
    sun = _sun([2.0, 8.0, 10.0, 12.0, 14.0])  # 02 UTC: night
    aim = jnp.array([0.0, 0.0, 60.0])
    r = hj.aim_fleet(truth, fleet.geometry, sun, aim)
    ok = np.asarray(r.ok)
    assert bool(np.asarray(r.sun_low)[0]) and not np.asarray(r.sun_low)[1:].any()
    assert ok[:, 1:].mean() > 0.5
    # independent check: the true pose reflects the sun onto the aim point
    miss = _true_miss_mrad(truth, fleet.geometry, r.counts, sun, aim)
    assert np.all(miss[ok] < 1e-6)
    # counts flagged out of range really are outside the actuator range
    oor = np.asarray(r.counts_out_of_range)
    lo = np.asarray(fleet.geometry.actuators.min_counts)[:, None, :]
    hi = np.asarray(fleet.geometry.actuators.max_counts)[:, None, :]
    c = np.asarray(r.counts)
    np.testing.assert_array_equal(oor, np.any((c < lo) | (c > hi), axis=-1))


def test_unfitted_heliostats_are_flagged_and_shapes_broadcast():
    fleet, truth = simulate_fleet(3, 6, 8, base="actuator", noise_mrad=0.0)  # the shapes of the test above
    sun = _sun([9.0, 11.0])
    points = jnp.stack([jnp.array([0.0, 0.0, 55.0 + k]) for k in range(6)])
    fitted = np.array([True, False, True, True, False, True])
    r = hj.aim_fleet(truth, fleet.geometry, sun, points, fitted=jnp.asarray(fitted))
    assert r.counts.shape == (6, 2, 2)
    np.testing.assert_array_equal(np.asarray(r.unreliable), ~fitted)
    assert not np.asarray(r.ok)[~fitted].any()
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
    miss2 = _true_miss_mrad(truth, fleet.geometry, r.counts, sun, aim)[ok] ** 2
    var = np.trace(np.asarray(r.pointing_cov_mrad2), axis1=-2, axis2=-1)[ok]
    assert len(miss2) > 150
    ratio = np.mean(miss2) / np.mean(var)
    assert 0.5 < ratio < 2.0, ratio
    assert np.all(np.isfinite(np.asarray(r.pointing_std_mrad)[ok]))
    without = hj.aim_fleet(solution.model, fleet.geometry, sun, aim)
    assert np.isnan(np.asarray(without.pointing_std_mrad)).all()
