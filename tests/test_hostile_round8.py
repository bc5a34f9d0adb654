"""Hostile-input round 8, public API: aim_fleet / aim_results argument checks (NaN or
negative covariance and drift, NaN thresholds, mis-shaped fitted / covariance,
mismatched models and geometry, options aim_results sets itself, jit), fleet_subset
indices, CalibrationResults.drift_variance_mrad2 times, inverse_aim with a zero sun."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj

AIM = jnp.array([0.0, 0.0, 50.0])


@pytest.fixture(scope="module")
def results(fitted_h5):
    return hj.load_results(fitted_h5)


def _sun(elevation_deg=40.0):
    return hj.sun_direction(np.array([0.3]), np.radians(np.array([elevation_deg])))


def test_aim_fleet_refuses_a_nan_or_negative_covariance_or_drift_and_never_trusts_a_nan_uncertainty(results, unchecked):
    """Case 4: a NaN / negative covariance or drift variance had given ok commands
    beside a NaN pointing radius."""
    r, sun = results, _sun()
    args = (r.model, r.geometry, sun, AIM)
    fitted = np.asarray(r.fitted)
    assert fitted.any()
    cases = [
        (dict(covariance=np.full_like(r.covariance, np.nan)), "covariance: not finite"),
        (dict(covariance=-r.covariance), "covariance: not positive semi-definite"),
        (dict(covariance=r.covariance, drift_variance_mrad2=-100.0), "drift_variance_mrad2: .* negative or not finite"),
        (dict(covariance=r.covariance, drift_variance_mrad2=np.nan), "drift_variance_mrad2: .* negative or not finite"),
    ]
    for kwargs, message in cases:
        with pytest.raises(ValueError, match=message):
            hj.aim_fleet(*args, fitted=fitted, view=r.view, **{"covariance": r.covariance, **kwargs})
    # a heliostat that is not used (fitted False) may hold a NaN covariance
    cov = np.array(r.covariance)
    cov[~fitted] = np.nan
    good = hj.aim_fleet(*args, fitted=fitted, covariance=cov, view=r.view)
    assert np.isfinite(np.asarray(good.pointing_radius_mrad())[fitted]).all()
    # under jit the value checks are skipped: the NaN uncertainty still makes no command ok
    ok = jax.jit(lambda c: hj.aim_fleet(*args, covariance=c, view=r.view).ok)(np.full_like(r.covariance, np.nan))
    assert not np.asarray(ok).any()


def test_aim_thresholds_must_be_finite_and_in_range(results):
    """Case 5: min_sun_elevation_deg=nan had unflagged a 2-degree sun,
    reach_tolerance_mrad=nan flagged every command unreachable."""
    with pytest.raises(ValueError, match=r"min_sun_elevation_deg is nan; expected a finite value in \[-90, 90\] deg"):
        hj.aim_results(results, _sun(2.0), AIM, min_sun_elevation_deg=float("nan"))
    with pytest.raises(ValueError, match=r"reach_tolerance_mrad is nan; expected a finite value >= 0 mrad"):
        hj.aim_results(results, _sun(), AIM, reach_tolerance_mrad=float("nan"))
    with pytest.raises(ValueError, match=r"max_sky_gap_deg is -5.0; expected a finite value in \[0, 180\] deg"):
        hj.aim_results(results, _sun(), AIM, max_sky_gap_deg=-5.0)
    assert np.asarray(hj.aim_results(results, _sun(2.0), AIM).sun_low).all()


def test_aim_fleet_names_a_mis_shaped_or_mis_typed_argument(results, unchecked):
    """Case 6: fitted broadcast / taken as True / a raw broadcasting error, a
    covariance of the wrong shape, models and geometry of different fleets, and
    aim_results given an option it takes from the file."""
    r, sun = results, _sun()
    args = (r.model, r.geometry, sun, AIM)
    h, f = len(r.ids), r.view.n_free
    with pytest.raises(ValueError, match=rf"fitted has shape \(1,\); expected \({h},\)"):
        hj.aim_fleet(*args, fitted=np.zeros(1, bool))
    with pytest.raises(TypeError, match=rf"fitted has dtype float64; expected a boolean \({h},\) array"):
        hj.aim_fleet(*args, fitted=np.array([2.5] * h))
    with pytest.raises(ValueError, match=rf"fitted has shape \(3,\); expected \({h},\)"):
        hj.aim_fleet(*args, fitted=np.ones(3, bool))
    with pytest.raises(ValueError, match=rf"covariance has shape \({h}, 3, 3\); expected \({h}, {f}, {f}\)"):
        hj.aim_fleet(*args, covariance=np.eye(3)[None].repeat(h, 0), view=r.view)
    with pytest.raises(ValueError, match="give both covariance and view"):
        hj.aim_fleet(*args, covariance=r.covariance)
    three = jax.tree.map(lambda x: x[:3], r.geometry)
    with pytest.raises(ValueError, match=rf"models: arrays batched over {h} heliostat\(s\), expected 3"):
        hj.aim_fleet(r.model, three, sun, AIM)
    with pytest.raises(TypeError, match="aim_results: drift_variance_mrad2 is taken from the calibration file"):
        hj.aim_results(r, sun, AIM, drift_variance_mrad2=1.0)


def test_fleet_subset_refuses_bools_floats_and_an_empty_selection(unchecked):
    """Case 7: True and 1.5 had been taken as heliostat 1; an empty subset failed later
    in calibrate with a shape message."""
    fleet = hj.load_paint_directory(hj.default_data_dir())
    for bad in (True, [1.5], 1.5, [np.True_]):
        with pytest.raises(TypeError, match="expected an integer position or a heliostat id"):
            hj.fleet_subset(fleet, bad)
    with pytest.raises(TypeError, match="a boolean mask: np.flatnonzero"):
        hj.fleet_subset(fleet, np.ones(fleet.n_heliostats, bool))
    with pytest.raises(ValueError, match="no heliostat selected"):
        hj.fleet_subset(fleet, [])
    with pytest.raises(IndexError, match="out of range"):
        hj.fleet_subset(fleet, [fleet.n_heliostats])
    last = fleet.ids[-1]
    assert hj.fleet_subset(fleet, np.array([-1])).ids == (last,)
    assert hj.fleet_subset(fleet, [np.int64(0), last]).ids == (fleet.ids[0], last)


def test_drift_variance_refuses_times_not_in_seconds(results):
    """Case 8: milliseconds (1.7e12) or NaN had been extrapolated silently."""
    for bad in (np.array([1.7e12]), np.array([np.nan])):
        with pytest.raises(ValueError, match=r"unix_time must be seconds since 1970-01-01 UTC .*\(not ms or ns\)"):
            results.drift_variance_mrad2(bad)
    assert results.drift_variance_mrad2(np.array([1.7e9, 1.71e9])).shape == (len(results.ids), 2)


def test_inverse_aim_of_a_zero_or_non_finite_sun_is_nan(results):
    """Case 9: a zero sun vector had given plausible finite counts."""
    model, geometry = results.heliostat(results.ids[0])
    sun = _sun()[0]
    assert np.isfinite(np.asarray(hj.inverse_aim(model, geometry, AIM, sun))).all()
    for bad in (np.zeros(3), np.full(3, np.inf)):
        assert np.isnan(np.asarray(hj.inverse_aim(model, geometry, AIM, bad))).all()
    batch = jax.vmap(lambda s: hj.inverse_aim(model, geometry, AIM, s))(np.stack([sun, np.zeros(3)]))
    assert np.isfinite(np.asarray(batch[0])).all() and np.isnan(np.asarray(batch[1])).all()


def test_inverse_aim_takes_the_direction_of_a_non_unit_sun(results):
    """Only the sun's direction counts: a sun vector of length 0.5 or 1e3 had given
    other counts than the unit vector (the bisector of a non-unit sun and the unit aim
    direction is not the mirror normal)."""
    model, geometry = results.heliostat(results.ids[0])
    sun = _sun()[0]
    unit = np.asarray(hj.inverse_aim(model, geometry, AIM, sun))
    for scale in (0.5, 1e3):
        np.testing.assert_allclose(
            np.asarray(hj.inverse_aim(model, geometry, AIM, scale * sun)), unit, rtol=0, atol=1e-9
        )


def test_inverse_aim_names_a_mis_shaped_sun_or_aim_point(results, unchecked):
    """A sun of shape (1, 3) or (2,), or an aim point of shape (3, 1), had given JAX's
    broadcasting error naming neither argument (hostile-input round 9)."""
    model, geometry = results.heliostat(results.ids[0])
    sun = _sun()[0]
    aim = np.asarray(AIM, float)
    for name, args in (("sun", (aim, sun[None])), ("sun", (aim, sun[:2])), ("aim_point", (aim[:, None], sun))):
        with pytest.raises(ValueError, match=rf"inverse_aim: {name} must have shape \(3,\)"):
            hj.inverse_aim(model, geometry, *args)


def test_jit_of_aim_results_says_it_is_host_side(results):
    """Case 13: a TracerArrayConversionError had not said why."""
    message = "aim_results is a host-side function .* call it outside jit; heliojax.aim_fleet is the jittable core"
    with pytest.raises(TypeError, match=message):
        jax.jit(lambda s: hj.aim_results(results, s, AIM))(_sun())
