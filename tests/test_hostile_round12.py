"""Hostile-input round 12, the public library API as a Python user calls it: geodesy
of a point that is no ``(..., 3)`` triple (JAX clamps the index: a ``(lat, lon)`` pair
had read the longitude as the altitude) or of a latitude past the pole; integer
positions that truncated the other vectors to integers (a geometry without its mirror
offset, a NaN pose); ``forward`` of counts or of a batch that it broadcast or failed on
deep inside; a level-1 test at ``confidence=95`` or a NaN contract value that failed
without a reason; ``flux_images`` of no rays (an image of zeros) or of sizes past its
32-bit indices; ``fit`` of a mask, start model or free set made for another fleet or
model; ``with_effects`` of one name read as its letters; a NaN prior sigma read as no
prior; sun shapes of a width given in mrad, negative or NaN; a target of coincident
corners (a NaN plane); ``select_sample`` of positions that are not finite or not
``(N, 2)``; ``solar_position`` of a datetime called "text".

Ill-typed values are given under the ``unchecked`` fixture (the test run's jaxtyping
checker would refuse them first; a user has none)."""

from __future__ import annotations

import dataclasses
import datetime as dt

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHARED_PAINT

import heliojax as hj
from heliojax import acceptance, optics, paint
from heliojax._heliostat import Pose
from heliojax._simulate import typical_actuators

ORIGIN = jnp.array([50.913421, 6.387825, 87.0])


def test_geodesy_names_a_point_that_is_no_triple_or_a_latitude_past_the_pole(unchecked):
    """``lla[..., 2]`` of a pair is JAX's clamped ``lla[..., 1]``: an origin of
    ``(lat, lon)`` had been taken at an altitude of 6.39 m, a point of two numbers
    converted without an error; a latitude of 200 deg gave a point 12,000 km away."""
    point = jnp.array([50.914, 6.388, 90.0])
    with pytest.raises(ValueError, match=r"wgs84_to_enu: origin_lla has shape \(2,\); expected one \(3,\) vector"):
        hj.wgs84_to_enu(point, ORIGIN[:2])
    with pytest.raises(ValueError, match=r"wgs84_to_enu: lla has shape \(2,\)"):
        hj.wgs84_to_enu(point[:2], ORIGIN)
    with pytest.raises(ValueError, match=r"wgs84_to_ecef: lla has shape \(4,\)"):
        hj.wgs84_to_ecef(jnp.zeros(4))
    with pytest.raises(ValueError, match=r"ecef_to_wgs84: xyz has shape \(2,\)"):
        hj.ecef_to_wgs84(jnp.array([6.4e6, 0.0]))
    with pytest.raises(ValueError, match=r"enu_to_wgs84: origin_lla has shape \(2,\)"):
        hj.enu_to_wgs84(jnp.zeros(3), ORIGIN[:2])
    with pytest.raises(ValueError, match=r"latitude of 200 deg, outside \[-90, 90\]"):
        hj.wgs84_to_enu(jnp.array([200.0, 6.388, 90.0]), ORIGIN)
    with pytest.raises(ValueError, match=r"enu_to_wgs84: origin_lla holds a latitude of -91 deg"):
        hj.enu_to_wgs84(jnp.zeros(3), jnp.array([-91.0, 6.4, 87.0]))
    # the shape is checked under jit too; a batch of points and a NaN still convert
    with pytest.raises(ValueError, match="origin_lla has shape"):
        jax.jit(hj.wgs84_to_enu)(point, ORIGIN[:2])
    enu = hj.wgs84_to_enu(jnp.stack([point, point.at[0].set(jnp.nan)]), ORIGIN)
    assert enu.shape == (2, 3) and np.isfinite(np.asarray(enu[0])).all() and np.isnan(np.asarray(enu[1])).all()


def test_integer_positions_no_longer_truncate_the_other_vectors(unchecked):
    """A position of whole metres had cast the mirror offset ``(0, 0.175, 0)`` to zeros
    (``HeliostatGeometry.build``) and the sun to integers, a NaN normal (``aim_pose``,
    ``pose_from_normal``)."""
    g = hj.HeliostatGeometry.build(jnp.array([10, 50, 1]), typical_actuators(), concentrator_translation=(0, 0.175, 0))
    assert jnp.issubdtype(g.position.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(g.concentrator_translation), [0.0, 0.175, 0.0])
    sun = jnp.array([0.3, -0.5, 0.8])
    pose = optics.aim_pose(jnp.array([0, 50, 2]), sun, jnp.array([0.0, 0.0, 100.0]))
    expected = optics.aim_pose(jnp.array([0.0, 50.0, 2.0]), sun, jnp.array([0.0, 0.0, 100.0]))
    np.testing.assert_allclose(np.asarray(pose.normal), np.asarray(expected.normal))
    normal = optics.pose_from_normal(jnp.array([0, 50, 2]), sun).normal
    np.testing.assert_allclose(np.asarray(normal), np.asarray(sun / jnp.linalg.norm(sun)))


def test_forward_names_counts_or_a_heliostat_batch_it_would_misread(unchecked):
    """Counts of shape (1,) had been used for both axes (a plausible pose), counts of
    (3,) or a batched model had failed with a broadcasting or ``dot_general`` error."""
    g = hj.HeliostatGeometry.build(jnp.array([10.0, 50.0, 1.5]), typical_actuators())
    model = hj.StoneModel.nominal()
    for counts in (jnp.array([3e4]), jnp.array([3e4, 3e4, 1.0]), jnp.full((4, 2), 3e4)):
        with pytest.raises(ValueError, match=rf"forward: counts has shape \({counts.shape[0]},.*expected \(2,\)"):
            hj.forward(model, g, counts)
    with pytest.raises(ValueError, match="forward: model is batched over heliostats"):
        hj.forward(hj.broadcast_model(model, 2), g, jnp.array([3e4, 3e4]))
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), g)
    with pytest.raises(ValueError, match=r"forward: geometry.position has shape \(2, 3\)"):
        hj.forward(model, batch, jnp.array([3e4, 3e4]))
    with pytest.raises(ValueError, match=r"inverse_normal: normal has shape \(2,\)"):
        hj.inverse_normal(model, g, jnp.array([0.0, 1.0]))
    # vmap over heliostats and records, as documented, still works
    normals = jax.vmap(lambda gg: hj.forward(model, gg, jnp.array([3e4, 3e4])).normal)(batch)
    assert normals.shape == (2, 3)


def test_a_level1_test_refuses_a_percent_confidence_or_a_nan_contract_instead_of_failing():
    """``confidence=95`` had given NaN intervals and a failed test (``passed=False``),
    a NaN contract mean a failed mean, a negative contract std a failed spread: no
    reason given."""
    x = np.random.default_rng(0).normal(2.0, 0.3, 30)
    with pytest.raises(ValueError, match=r"confidence must lie in \(0, 1\), got 95 \(for 95 %, give 0.95\)"):
        acceptance.level1_test(x, 2.2, 0.5, confidence=95)
    with pytest.raises(ValueError, match=r"confidence_intervals: confidence must lie in \(0, 1\), got 1.5"):
        acceptance.confidence_intervals(x, 1.5)
    with pytest.raises(ValueError, match="contract_mean must be finite, got nan"):
        acceptance.level1_test(x, float("nan"), 0.5)
    with pytest.raises(ValueError, match="contract_std must be finite and >= 0, got -0.5"):
        acceptance.level1_test(x, 2.2, -0.5)
    with pytest.raises(ValueError, match="n_resamples must be an integer >= 1, got 0"):
        acceptance.level1_test(np.abs(x), 2.2, 0.5, distribution="radial", n_resamples=0)
    assert acceptance.level1_test(x, 2.2, 0.5).passed


def _mirror():
    c = (np.arange(2) + 0.5) / 2 - 0.5
    x, y = np.meshgrid(c, c, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), np.zeros(4)], -1)
    return optics.SurfacePoints(jnp.asarray(points), jnp.tile(jnp.array([0.0, 0.0, 1.0]), (4, 1)), jnp.full(4, 0.25))


def test_flux_images_refuses_no_rays_and_sizes_past_its_indices(unchecked):
    """``rays_per_point=0`` or ``steps=0`` had returned an image of zeros (no power on
    the target, as if the mirror missed it); -1 or 4.5 a JAX shape error; a 10^6 x 10^6
    grid an OverflowError of int32; 10^9 rays per point a 512 GB allocation attempt."""
    up = Pose(normal=jnp.array([0.0, 0.0, 1.0]), centre=jnp.zeros(3), rotation=jnp.eye(3))
    target = hj.TargetPlane.from_corners(
        jnp.array([-2.0, 2.0, 10.0]),
        jnp.array([2.0, 2.0, 10.0]),
        jnp.array([-2.0, -2.0, 10.0]),
        jnp.array([2.0, -2.0, 10.0]),
    )
    grid = optics.ImageGrid.for_target(target, (8, 8))
    args = (jax.random.key(0), _mirror(), up, jnp.array([0.0, 0.0, 1.0]), target, grid, optics.GaussianSun(2e-3))
    for kwargs, said in [
        (dict(rays_per_point=0), "rays_per_point must be an integer >= 1, got 0"),
        (dict(rays_per_point=4.5), "rays_per_point must be an integer >= 1, got 4.5"),
        (dict(rays_per_point=2, steps=0), "steps must be an integer >= 1, got 0"),
        (
            dict(rays_per_point=10**9),
            r"1 heliostat\(s\) x 4 points x 1000000000 rays_per_point need 8e\+09 random numbers",
        ),
        (dict(rays_per_point=2, dni=float("nan")), "dni must be finite and >= 0"),
        (dict(rays_per_point=2, reflectivity=1.5), r"reflectivity must be in \[0, 1\]"),
    ]:
        with pytest.raises(ValueError, match=f"flux_images: {said}"):
            optics.flux_image(*args, **kwargs)
    huge = optics.ImageGrid.centred(0.0, 0.0, 1.0, 1.0, (10**6, 10**6))
    with pytest.raises(ValueError, match=r"flux_images: grid.shape \(1000000, 1000000\) .* \(32-bit pixel indices\)"):
        optics.flux_image(*args[:5], huge, args[6], rays_per_point=1)
    with pytest.raises(ValueError, match=r"flux_images: sun has shape \(2,\)"):
        optics.flux_image(args[0], args[1], up, jnp.array([0.0, 1.0]), *args[4:], rays_per_point=1)


@pytest.fixture(scope="module")
def two_heliostats():
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    geometry = hj.synthetic_geometry(k[0], 2)
    context = hj.synthetic_contexts(k[1], 2, 4)
    counts = jnp.full((2, 4, 2), 3e4)
    return hj.fleet_from_arrays(geometry, counts, context, jnp.zeros((2, 4, 3)))


def test_fit_names_a_mask_start_model_or_free_set_of_another_shape(two_heliostats, unchecked):
    """A mask of another shape had met NumPy's broadcasting error, a float mask a dtype
    error of ``&``, an integer mask of 2s fitted nothing (``2 & True`` is 0); a start
    model batched for 3 heliostats a ``scan`` error; a free set of another model or a
    dict an AttributeError. All before anything compiles."""
    fleet, model = two_heliostats, hj.StoneModel.nominal()
    for mask, said in [
        (np.ones((2, 3), bool), r"fit: mask has shape \(2, 3\); expected \(2, 4\)"),
        (np.ones((2, 4)), "fit: mask has dtype float64; expected booleans"),
        (np.full((2, 4), 2), "fit: mask has dtype int64 with values other than 0 and 1"),
    ]:
        with pytest.raises(ValueError, match=said):
            hj.fit(model, fleet, mask=mask)
    with pytest.raises(ValueError, match="fit: model0 is batched over 3 heliostats and the fleet has 2"):
        hj.fit(hj.broadcast_model(model, 3), fleet)
    with pytest.raises(TypeError, match=r"free set: no entry for alpha of the model \(StoneModel\), got a dict"):
        hj.fit(model, fleet, free={"alpha": True})
    with pytest.raises(TypeError, match=r"free set: no entry for theta_k .* got a ActuatorModel"):
        hj.fit(model, fleet, free=hj.default_free(hj.ActuatorModel.nominal()))


def test_with_effects_takes_one_name_as_one_effect(unchecked):
    """``with_effects(model, "thermal")`` had said "unknown effect 't'"."""
    model = hj.with_effects(hj.StoneModel.nominal(), "thermal")
    assert "thermal_1" in hj.ParameterView.of(model).names
    with pytest.raises(TypeError, match="with_effects: effects must be effect names"):
        hj.with_effects(hj.StoneModel.nominal(), [3])


def test_a_nan_prior_sigma_is_refused_not_read_as_no_prior():
    """``{"gamma": nan}`` passed the ``<= 0`` check, and a NaN sigma weighs its row by 0:
    no prior on gamma, without a word."""
    model = hj.StoneModel.nominal()
    with pytest.raises(ValueError, match=r"prior sigmas must be > 0 \(inf: no prior\), got \{'gamma': nan\}"):
        hj.gaussian_prior(model, {"gamma": float("nan")})
    with pytest.raises(ValueError, match="gaussian_prior: noise_mrad must be finite and > 0"):
        hj.gaussian_prior(model, {"gamma": 5e-3}, noise_mrad=0.0)
    hj.gaussian_prior(model, {"gamma": 5e-3, "delta": float("inf")})


def test_sun_shapes_refuse_a_width_in_mrad_negative_or_nan():
    """``GaussianSun(2.51)`` (mrad meant) traced a 2.5 rad sun, a flux image of nothing;
    NaN a NaN image; negative widths were taken. ``BuieSun`` checked its csr already."""
    for make, name in [
        (optics.GaussianSun, "GaussianSun: sigma"),
        (optics.PillboxSun, "PillboxSun: half_angle"),
        (lambda w: optics.EffectiveSun(optics.PillboxSun(), w), "EffectiveSun: slope_error"),
    ]:
        with pytest.raises(ValueError, match=rf"{name} must be finite and in \[0, 0.1\] rad, got 2.51; mrad\?"):
            make(2.51)
        for bad in (-1e-3, float("nan")):
            with pytest.raises(ValueError, match=rf"{name} must be finite"):
                make(bad)
    # traced widths are not checked (EffectiveSun draws its slope errors with a traced sigma)
    offsets = jax.jit(lambda s: optics.GaussianSun(s).sample(jax.random.key(0), (8,)))(2e-3)
    assert offsets.shape == (8, 2)
    # an ARTIST scenario's sun of a negative variance (a NaN sun) names the file's field
    path = SHARED_PAINT.parent / "artist-scenarios" / "paint_four_heliostats_ideal.h5"
    if path.exists():
        scenario = paint.read_artist_scenario(path)
        name, sun = next(iter(scenario.light_sources.items()))
        bad = dataclasses.replace(scenario, light_sources={name: dataclasses.replace(sun, covariance=-1e-6)})
        with pytest.raises(hj.DataError, match=rf"lightsources/{name}/distribution_parameters/covariance.*-1e-06"):
            optics.scene_from_artist(bad)


def test_a_target_of_corners_that_span_no_rectangle_is_refused(unchecked):
    """Four equal corners or a corner repeated had given a plane of NaN axes (every ray
    missed it); corners of two numbers a plane of garbage."""
    a, b = jnp.array([0.0, 0.0, 1.0]), jnp.array([1.0, 0.0, 1.0])
    with pytest.raises(ValueError, match=r"the corners span no rectangle \(width 0 m"):
        hj.TargetPlane.from_corners(a, a, a, a)
    with pytest.raises(ValueError, match=r"the corners span no rectangle \(width 1 m, height 0 m\)"):
        hj.TargetPlane.from_corners(a, b, a, b)
    with pytest.raises(ValueError, match=r"upper_left has shape \(2,\); expected \(3,\)"):
        hj.TargetPlane.from_corners(a[:2], b[:2], a[:2], b[:2])


def test_select_sample_names_positions_that_are_not_finite_or_not_pairs(unchecked):
    """NaN positions had failed with "cannot convert float NaN to integer", a 1-D array
    with an IndexError, ``n=3.0`` with a slice error."""
    xy = np.random.default_rng(0).random((20, 2))
    with pytest.raises(
        ValueError, match=r"select_sample: positions of 1 heliostat\(s\) are not finite \(first: row 4\)"
    ):
        acceptance.select_sample(np.where(np.arange(20)[:, None] == 4, np.nan, xy), 3)
    with pytest.raises(ValueError, match=r"select_sample: positions has shape \(20,\)"):
        acceptance.select_sample(xy[:, 0], 3)
    with pytest.raises(ValueError, match="select_sample: n must be an integer, got 3.0"):
        acceptance.select_sample(xy, 3.0)  # pyright: ignore[reportArgumentType]


def test_solar_position_of_a_datetime_does_not_call_it_text(unchecked):
    """A ``datetime`` had been refused as "not text datetime.datetime(...)"."""
    with pytest.raises(
        TypeError,
        match=r"not datetime datetime.datetime\(2024, 6, 1, 12, 0\) \(heliojax.datetime_to_unix converts a datetime",
    ):
        hj.solar_position(dt.datetime(2024, 6, 1, 12), 50.9, 6.4)  # pyright: ignore[reportArgumentType]
