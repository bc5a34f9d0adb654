"""Aiming: counts from the fitted (here: true) models put the beam on the aim point;
flags for out-of-range counts, low sun and unusable fits; vmap equals a loop."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

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
    assert not np.asarray(r.uncertainty_above_nominal).any()  # no uncalibrated error given: no flag
    # uncertainty_above_nominal: the predicted std against a per-heliostat bound (NaN: unknown, no flag)
    std = np.asarray(r.pointing_std_mrad)
    nominal = np.median(std, axis=1)
    nominal[0] = np.nan
    flagged = hj.aim_fleet(
        solution.model,
        fleet.geometry,
        sun,
        aim,
        covariance=solution.covariance,
        view=solution.view,
        nominal_rms_mrad=jnp.asarray(nominal),
    )
    above = np.asarray(flagged.uncertainty_above_nominal)
    np.testing.assert_array_equal(above[1:], std[1:] > nominal[1:, None])
    assert not above[0].any() and above[1:].any()
    np.testing.assert_array_equal(np.asarray(flagged.ok), ok & ~above)


def test_sky_gap_is_the_angle_to_the_nearest_fitted_sun_and_flags_extrapolation():
    """``sky_gap_deg`` equals a loop over heliostats and records (arccos of the largest
    cosine; inf without a fitted record). A heliostat whose fitted records all share
    one sun position is aimed without a flag at that position only: elsewhere its
    commands are ``beyond_calibrated_sky`` and not ``ok``."""
    rng = np.random.default_rng(0)
    h, m, n = 3, 7, 5
    sun = _sun([8.0, 10.0, 12.0, 14.0, 16.0])
    fitted_sun = rng.normal(size=(h, m, 3))
    fitted_sun[..., 2] = np.abs(fitted_sun[..., 2])
    fitted_sun /= np.linalg.norm(fitted_sun, axis=-1, keepdims=True)
    fitted_sun[1, :] = np.asarray(sun)[2]  # heliostat 1: every record at the noon sun
    use = rng.random((h, m)) > 0.3
    use[1] = True
    use[2] = False  # heliostat 2: no fitted record
    gap = np.asarray(hj.sky_gap_deg(sun, jnp.asarray(fitted_sun), jnp.asarray(use)))
    want = np.full((h, n), np.inf)
    for i in range(h):
        for j in range(n):
            for k in range(m):
                if use[i, k]:
                    cosine = np.clip(np.dot(np.asarray(sun)[j], fitted_sun[i, k]), -1.0, 1.0)
                    want[i, j] = min(want[i, j], np.degrees(np.arccos(cosine)))
    np.testing.assert_allclose(gap, want, rtol=0, atol=1e-6)  # arccos near 1: ~1e-8 rad of rounding
    assert gap[1, 2] < 1e-6 and np.all(gap[1, [0, 1, 3, 4]] > 20.0)  # the sun moves ~15 deg/h
    fleet, truth = simulate_fleet(3, h, 8, base="actuator", noise_mrad=0.0)
    aim = jnp.array([0.0, 0.0, 60.0])
    sky = {"fitted_sun": jnp.asarray(fitted_sun), "fitted_record": jnp.asarray(use)}
    r = hj.aim_fleet(truth, fleet.geometry, sun, aim, **sky)
    np.testing.assert_array_equal(np.asarray(r.beyond_calibrated_sky), gap > hj.MAX_SKY_GAP_DEG)
    ok = np.asarray(r.ok)
    assert ok[1, 2] and not ok[1, [0, 1, 3, 4]].any() and not ok[2].any()
    plain = hj.aim_fleet(truth, fleet.geometry, sun, aim)  # no records given: no flag, no gap
    assert not np.asarray(plain.beyond_calibrated_sky).any() and np.isnan(np.asarray(plain.sky_gap_deg)).all()
    np.testing.assert_array_equal(np.asarray(plain.counts), np.asarray(r.counts))


def test_cli_sky_gap_default_is_the_librarys():
    from heliojax.cli._main import build_parser

    args = build_parser()[0].parse_args(["aim", "results.h5"])
    assert args.max_sky_gap == hj.MAX_SKY_GAP_DEG


def test_sky_gap_variance_refuses_suns_it_would_misread_and_flags_a_heliostat_without_one(unchecked):
    """With ``sky_gap_mrad2_per_deg`` > 0, a heliostat without a fitted record (sky gap
    inf) had its sky-gap variance dropped (the radial scale of one with a gap of 0)
    and was not flagged ``unreliable``, though the code said it was: now it is. Fitted
    suns of length 2 had put every gap at 0 deg (no flag, no sky-gap variance), and
    ``fitted_sun`` of another heliostat count failed deep in JAX: both are refused,
    naming the argument; so is a rate that is not a number."""
    h, m = 3, 4
    sun = _sun([10.0, 12.0])
    fleet, truth = simulate_fleet(3, h, 8, base="actuator", noise_mrad=0.0)
    fitted_sun = np.broadcast_to(np.asarray(_sun([9.0, 11.0, 13.0, 15.0])), (h, m, 3)).copy()
    use = np.ones((h, m), bool)
    use[2] = False  # heliostat 2: no fitted record
    aim = jnp.array([0.0, 0.0, 60.0])
    fs, fr = jnp.asarray(fitted_sun), jnp.asarray(use)
    r = hj.aim_fleet(truth, fleet.geometry, sun, aim, sky_gap_mrad2_per_deg=0.02, fitted_sun=fs, fitted_record=fr)
    np.testing.assert_array_equal(np.asarray(r.unreliable), [False, False, True])
    assert np.isinf(np.asarray(r.sky_gap_deg)[2]).all() and not np.asarray(r.ok)[2].any()
    plain = hj.aim_fleet(truth, fleet.geometry, sun, aim, fitted_sun=fs, fitted_record=fr)  # no sky-gap term
    assert not np.asarray(plain.unreliable).any()
    with pytest.raises(ValueError, match="fitted_sun: .* not finite unit vectors"):
        hj.aim_fleet(truth, fleet.geometry, sun, aim, sky_gap_mrad2_per_deg=0.02, fitted_sun=2 * fs, fitted_record=fr)
    with pytest.raises(
        ValueError, match=r"fitted_sun has shape \(2, 4, 3\) and fitted_record \(2, 4\); expected \(3, M, 3\)"
    ):
        hj.aim_fleet(truth, fleet.geometry, sun, aim, fitted_sun=fitted_sun[:2], fitted_record=use[:2])
    with pytest.raises(ValueError, match="sky_gap_mrad2_per_deg is \\[0.02\\]; expected a number"):
        hj.aim_fleet(truth, fleet.geometry, sun, aim, sky_gap_mrad2_per_deg=[0.02], fitted_sun=fs, fitted_record=fr)  # type: ignore[arg-type]
