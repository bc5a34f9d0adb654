"""Simulator: records consistent with the true model, PAINT round trip, injection point."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax._simulate import (
    approach_directions,
    calibration_target,
    calibration_times,
    random_stone_models,
    simulate_records,
    synthetic_contexts,
    synthetic_geometry,
    write_simulation,
)


@pytest.fixture(scope="module")
def small_sim():
    h, m = 4, 30
    g = synthetic_geometry(jax.random.PRNGKey(0), h)
    true = random_stone_models(jax.random.PRNGKey(1), h, angle_sigma=1e-3)
    ctx = synthetic_contexts(jax.random.PRNGKey(2), h, m)
    target = calibration_target()
    # The plant aims with a calibrated controller (here: the truth), so spots land near the aim point.
    sim = simulate_records(jax.random.PRNGKey(3), true, g, ctx, target, controller_models=true, noise_mrad=0.0)
    return g, true, ctx, target, sim


def test_noise_free_records_fit_the_true_model_exactly(small_sim):
    g, true, ctx, target, sim = small_sim
    # Records whose true spot misses the target are not recorded (hit = False).
    assert float(jnp.mean(sim.mask)) > 0.9
    err = hj.beam_errors_mrad(true, g, sim.counts, ctx, sim.focal_spot, sim.mask)
    assert float(jnp.nanmax(err)) < 1e-7
    # Counts are whole numbers inside the actuator range.
    c = np.asarray(sim.counts)
    np.testing.assert_array_equal(c, np.round(c))
    assert np.all(c >= 0) and np.all(c <= np.asarray(g.actuators.max_counts)[:, None, :])
    # The nominal (controller) model misses by the true parameters' mrad-level error.
    nominal = hj.broadcast_model(hj.StoneModel.nominal(jnp.float64), 4)
    e_nom = hj.beam_errors_mrad(nominal, g, sim.counts, ctx, sim.focal_spot, sim.mask)
    assert 0.5 < float(jnp.nanmedian(e_nom)) < 50.0


def test_noise_level(small_sim):
    g, true, ctx, target, _ = small_sim
    sim = simulate_records(jax.random.PRNGKey(7), true, g, ctx, target, controller_models=true, noise_mrad=0.3)
    comps = jax.vmap(lambda m, gg, c, x, f: jax.vmap(lambda ci, xi, fi: m.beam_components(gg, ci, xi, fi))(c, x, f))(
        true, g, sim.counts, ctx, sim.focal_spot
    )
    std = float(jnp.std(comps[sim.mask])) * 1e3
    assert std == pytest.approx(0.3, rel=0.15)


def test_injection_point_perturbs_the_truth(small_sim):
    g, true, ctx, target, sim0 = small_sim

    def tilt_up(pose, context):
        # An unmodelled 2 mrad rotation of the normal about east.
        rot = hj._geometry.rotation_x(jnp.asarray(2e-3))
        return hj.Pose(normal=rot @ pose.normal, centre=pose.centre, rotation=rot @ pose.rotation)

    sim = simulate_records(jax.random.PRNGKey(3), true, g, ctx, target, controller_models=true, perturb_pose=tilt_up)
    np.testing.assert_array_equal(sim.counts, sim0.counts)
    err = hj.beam_errors_mrad(true, g, sim.counts, ctx, sim.focal_spot, sim.mask)
    assert 1.0 < float(jnp.nanmedian(err)) < 4.5  # ~2x the normal's rotation, projected


def test_approach_directions_by_hand():
    counts = jnp.array([[[10.0, 5.0], [20.0, 5.0], [15.0, 7.0], [15.0, 7.0]]])
    mask = jnp.array([[True, True, True, True]])
    d = np.asarray(approach_directions(counts, mask))[0]
    np.testing.assert_array_equal(d, [[0, 0], [1, 0], [-1, 1], [0, 0]])
    # A masked record is skipped: the previous valid one counts.
    d2 = np.asarray(approach_directions(counts, jnp.array([[True, False, True, True]])))[0]
    np.testing.assert_array_equal(d2[2], [1, 1])


def test_simulator_paint_round_trip_is_bit_identical(small_sim, tmp_path):
    g, true, ctx, target, sim = small_sim
    mask = np.asarray(sim.mask)
    path, tower, props, records = write_simulation(tmp_path / "sim", sim, g, target)
    in_memory = hj.records_to_fleet(tower, props, records)
    loaded = hj.load_paint_directory(path)
    assert loaded.ids[: len(props)] == in_memory.ids[: len(props)]
    for name in ("counts", "focal_spot", "mask", "record_id", "target_index"):
        np.testing.assert_array_equal(
            np.asarray(getattr(loaded, name)), np.asarray(getattr(in_memory, name)), err_msg=name
        )
    for name in ("sun", "unix_time", "temperature", "wind_speed", "wind_direction"):
        a = np.asarray(getattr(loaded.context, name))
        b = np.asarray(getattr(in_memory.context, name))
        np.testing.assert_array_equal(a, b, err_msg=name)
    np.testing.assert_array_equal(np.asarray(loaded.geometry.position), np.asarray(in_memory.geometry.position))
    # And the loaded arrays are the simulated ones (through WGS84 and degrees at the boundary).
    for i in range(4):
        n = int(mask[i].sum())  # simulated contexts are already chronological
        np.testing.assert_array_equal(np.asarray(loaded.counts)[i, :n], np.asarray(sim.counts)[i][mask[i]])
        np.testing.assert_allclose(
            np.asarray(loaded.focal_spot)[i, :n], np.asarray(sim.focal_spot)[i][mask[i]], atol=1e-6
        )
    np.testing.assert_allclose(np.asarray(loaded.geometry.position)[:4], np.asarray(g.position), atol=1e-6)
    # Fitting the loaded data recovers the simulated (noise-free) truth.
    res = hj.fit(hj.StoneModel.nominal(jnp.float64), loaded)
    err = np.asarray(hj.fleet_beam_errors_mrad(res.model, loaded))
    assert np.nanmax(err[:4]) < 1e-3


def test_calibration_times_are_daytime_even_on_short_winter_days():
    """In a high-latitude December no hour sees the sun above 15 deg; the fallback must
    still be daylight (it had been the last random hour, often at night, which the
    loader rightly refuses), and with local solar noon among the candidates the sun is
    about as high as it gets that day: 90 - 58 - 23.4 = 8.6 deg on 21 December,
    9.7 deg on 8 January (declination -22.3 deg)."""
    lat, lon = 58.0, 6.36
    start = 1.7030e9  # 2023-12-19
    t, sun = calibration_times(
        jax.random.key(3), (400,), start_unix=start, days=20.0, latitude_deg=lat, longitude_deg=lon
    )
    elevation = np.rad2deg(np.arcsin(np.asarray(sun)[:, 2]))
    assert elevation.min() > 7.5 and elevation.max() < 10.5
    assert np.all((np.asarray(t) >= start - 86400.0) & (np.asarray(t) < start + 21 * 86400.0))
