"""The numpy baseline of benchmarks/calibration_speed.py equals heliojax's residual."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax._heliostat import RecordContext
from heliojax._simulate import random_stone_models, synthetic_geometry

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "calibration_speed.py"
STONE = hj.StoneModel.nominal(jnp.float64)
VIEW = hj.ParameterView.of(STONE)


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("calibration_speed", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _records(n_heliostats=3, n_records=7, seed=0):
    """Random (not necessarily physical) records: counts over the actuator range,
    suns above the horizon, spots near the tower; geometry with non-zero offsets."""
    rng = np.random.default_rng(seed)
    g = synthetic_geometry(jax.random.PRNGKey(seed), n_heliostats)
    g = g.__class__(
        position=g.position,
        joint_translation_1=jnp.asarray(rng.normal(0, 0.2, (n_heliostats, 3))),
        joint_translation_2=jnp.asarray(rng.normal(0, 0.2, (n_heliostats, 3))),
        concentrator_translation=g.concentrator_translation,
        actuators=g.actuators,
        linear_slope=g.linear_slope,
        linear_intercept=g.linear_intercept,
        ideal_axes=g.ideal_axes,
    )
    counts = rng.uniform(0, 69000, (n_heliostats, n_records, 2))
    az = rng.uniform(-1.5, 1.5, (n_heliostats, n_records))
    el = rng.uniform(0.2, 1.2, (n_heliostats, n_records))
    sun = np.stack([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)], -1)
    focal = np.stack(
        [
            rng.uniform(-3, 3, (n_heliostats, n_records)),
            np.full((n_heliostats, n_records), -3.2),
            rng.uniform(119, 127, (n_heliostats, n_records)),
        ],
        -1,
    )
    return g, counts, sun, focal


@pytest.mark.parametrize("nominal", [True, False])
def test_numpy_residual_matches_heliojax(bench, nominal):
    g, counts, sun, focal = _records()
    h = counts.shape[0]
    if nominal:
        y = np.zeros((h, 8))
    else:
        true = random_stone_models(jax.random.PRNGKey(5), h)
        p = np.asarray(VIEW.to_vector(true))
        y = (p - bench.STONE_NOMINAL) / bench.STONE_SCALE
    geoms = bench._geom_dicts(g)
    for i in range(h):
        model = VIEW.from_vector(STONE, jnp.asarray(bench.STONE_NOMINAL + bench.STONE_SCALE * y[i]))
        gi = jax.tree.map(lambda x: x[i], g)
        ctx = RecordContext.from_sun(jnp.asarray(sun[i]))
        ref = jax.vmap(lambda c, x, f: model.beam_components(gi, c, x, f))(
            jnp.asarray(counts[i]), ctx, jnp.asarray(focal[i])
        )
        ref = 1e3 * np.asarray(ref).reshape(-1)
        got = bench.stone_residual_np(y[i], geoms[i], counts[i], sun[i], focal[i])
        assert np.max(np.abs(ref)) > 1.0  # non-trivial residuals (mrad)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * 1e3)


def test_numpy_pose_reference_pose(bench):
    """Hand check: nominal model, theta = pi/2 and tau = 0 give the south-facing
    reference normal (0, -1, 0) and centre P + V2M (no other offsets)."""
    geom = dict(
        position=np.array([1.0, 2.0, 3.0]),
        joint_translation_1=np.zeros(3),
        joint_translation_2=np.zeros(3),
        concentrator_translation=np.array([0.0, 0.175, 0.0]),
        linear_slope=np.array([1e-5, 1e-5]),
        linear_intercept=np.array([np.pi / 2, 0.0]),
    )
    normal, centre = bench.stone_pose_np(bench.STONE_NOMINAL, geom, np.zeros((1, 2)))
    np.testing.assert_allclose(normal[0], [0.0, -1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(centre[0], [1.0, 2.175, 3.0], atol=1e-15)
    # theta = 0 faces up
    geom["linear_intercept"] = np.array([0.0, 0.0])
    normal, _ = bench.stone_pose_np(bench.STONE_NOMINAL, geom, np.zeros((1, 2)))
    np.testing.assert_allclose(normal[0], [0.0, 0.0, 1.0], atol=1e-15)


def test_scipy_fit_recovers_noise_free_parameters(bench):
    """The baseline fit itself works: noise-free simulated records -> true parameters."""
    from heliojax._simulate import calibration_target, simulate_records

    h, m = 2, 30
    g, _, sun, _ = _records(h, m, seed=3)
    g = synthetic_geometry(jax.random.PRNGKey(3), h)
    rng = np.random.default_rng(3)
    az = rng.uniform(-1.2, 1.2, (h, m))
    el = rng.uniform(0.3, 1.1, (h, m))
    sun = np.stack([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)], -1)
    true = random_stone_models(jax.random.PRNGKey(4), h)
    sim = simulate_records(
        jax.random.PRNGKey(5), true, g, RecordContext.from_sun(jnp.asarray(sun)), calibration_target()
    )
    params, nfev, _ = bench.scipy_fit_fleet(
        bench._geom_dicts(g), np.asarray(sim.counts), sun, np.asarray(sim.focal_spot), np.ones((h, m), bool)
    )
    expected = np.asarray(VIEW.to_vector(true))
    assert np.all(nfev > 0)
    np.testing.assert_allclose(params, expected, rtol=0, atol=1e-6)
