"""Hostile-input round 15: the two problems left by round 14, the public optics API, and
the effects, discovery and simulation helpers, as a Python user calls them.

Left by round 14: ``aim_fleet`` / ``aim_results`` of an aim point below ground (ENU up
< 0 and below the heliostat: a sign or frame mistake) returned commands like any
other; it is now a ValueError naming ``aim_points`` (refused, not flagged: no plant
sends a beam into the ground). A :class:`~heliojax.optics.FacetLayout` of a facet of
zero width or height, NaN or parallel canting vectors (or fields of different shapes)
was built, and its facet traced a NaN normal and no light; it now names the facet and
the field, with the properties reader's thresholds; the ARTIST scenario reader, which
had checked a facet's half-diagonal alone, now checks each half-edge and their angle by
the same thresholds, so that such a facet is a ``DataError`` naming the file and field
and ``skip_bad`` leaves out that heliostat only.

Optics: ``flux_images`` of a zero, NaN or inf sun, or of a pose of NaN, traced an image
of zeros; its ``dni`` / ``reflectivity`` check let every array through (a NaN or
negative flux: the check ran under its own ``jit``); an integer ``dtype`` traced zeros;
surfaces of no points an empty image. ``aim_pose`` aimed at its own centre, straight
away from the sun or with a zero sun, and ``pose_from_normal`` of a zero or NaN normal,
gave a pose of NaN; a ``(2,)`` centre failed inside JAX. ``SurfacePoints`` took negative
or NaN areas and NaN or zero normals; ``stack_surfaces`` / ``stack_layouts`` /
``stack_deflectometry`` / ``Deflectometry.from_facets`` of an empty list failed in
``max()``; ``ideal_surface`` of a resolution 0 or -1 gave a mirror of no points, 2.5 was
cut to 2 (so was an ``ImageGrid`` shape); ``ray_count`` counted -96 rays; ``BuieSun`` of
``n=0`` built a table of one entry, of a csr array or string failed in a comparison,
and ``buie_profile(csr=0)`` divided by zero; ``plane_power`` of a zero sun or a NaN or
negative ``dni`` returned 0, NaN or a negative power.

Effects, discovery, simulation: ``make_effect`` took NaN and inf magnitudes (every
prediction NaN) and named no value for a string; ``effect_class`` of a list failed as
"unhashable"; ``simulate_fleet(base="bogus")`` simulated actuator models, effects given
by name failed in JAX's ``asarray`` and a per-heliostat effect not batched over the
heliostats was taken; ``random_actuator_models`` made models of 0 heliostats and NaN
models for a NaN sigma (so did ``random_stone_models``, also for a negative one);
``holm`` at ``alpha=5`` rejected every hypothesis and sorted a NaN p-value anywhere.
``DiscoveryConfig(effects="thermal")`` read the string as its letters ("unknown effects
['a', 'e', ...]"), ``n_folds=2.5`` passed its ``< 2`` check, and ``max_named``,
``max_refits``, ``max_iterations`` and ``max_steps`` were not checked at all; each is now
a whole number in a stated range (``n_folds`` up to the command's ``--folds`` limit).
A ``GaussianSun`` or ``PillboxSun`` of an array of widths was taken for one sun, and
``with_effects(None, ...)`` failed in a concatenation; both now say what is wrong, as do
``centroid`` / ``total_power`` of an image that does not end in the grid's shape and
``uniforms`` / ``sample`` of a negative size (each had failed inside JAX).

Ill-typed values are given under the ``unchecked`` fixture."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax import discovery, effects, optics
from heliojax._errors import DataError

SUN = jnp.asarray([0.0, -0.6, 0.8])
TARGET = hj.TargetPlane.from_corners(
    *(jnp.asarray(c) for c in ([-2.0, 0.0, 52.0], [2.0, 0.0, 52.0], [-2.0, 0.0, 48.0], [2.0, 0.0, 48.0]))
)
GRID = optics.ImageGrid.for_target(TARGET, (8, 8))
KEY = jax.random.key(0)


def _layout(**kw):
    arrays = {
        "translations": np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
        "canting_e": np.array([[0.4, 0.0, 0.0]] * 2),
        "canting_n": np.array([[0.0, 0.4, 0.0]] * 2),
    }
    for name, row in kw.items():
        arrays[name][1] = row
    return optics.FacetLayout.from_arrays(arrays["translations"], arrays["canting_e"], arrays["canting_n"])


@pytest.fixture(scope="module")
def surface():
    return optics.ideal_surface(_layout(), (2, 2))


@pytest.fixture(scope="module")
def pose():
    return optics.aim_pose(jnp.asarray([0.0, -50.0, 1.0]), SUN, TARGET.centre)


# --------------------------------------------------------------------------------------
# Left by round 14
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_fleet():
    return hj.random_stone_models(jax.random.PRNGKey(1), 2), hj.synthetic_geometry(jax.random.PRNGKey(0), 2)


@pytest.mark.parametrize(
    "points",
    [[0.0, 0.0, -60.0], [[0.0, 0.0, 50.0], [0.0, 0.0, -60.0]], [[[0.0, 0.0, 50.0]], [[3.0, 4.0, -5.0]]]],
    ids=["one", "per-heliostat", "per-instant"],
)
def test_aim_fleet_refuses_an_aim_point_below_ground(small_fleet, points):
    models, geometry = small_fleet
    with pytest.raises(ValueError, match=r"aim_points: \d aim point\(s\) below ground.*into the ground"):
        hj.aim_fleet(models, geometry, SUN[None], jnp.asarray(points))


@pytest.mark.parametrize(
    ("row", "said"),
    [
        ({"canting_e": [0.0, 0.0, 0.0]}, r"facet 1: canting_e is \[0.0, 0.0, 0.0\].*half-width"),
        ({"canting_n": [0.0, 1e-6, 0.0]}, r"facet 1: canting_n .*half-height"),
        ({"canting_e": [np.nan, 0.0, 0.0]}, r"facet 1: canting_e is \[nan"),
        ({"canting_n": [0.4, 0.0, 0.0]}, r"facet 1: canting_n .*parallel"),
        ({"translations": [np.inf, 0.0, 0.0]}, r"facet 1: translations"),
    ],
)
def test_facet_layout_names_a_facet_of_no_area(row, said, unchecked):
    with pytest.raises(ValueError, match=f"FacetLayout: {said}"):
        _layout(**row)
    with pytest.raises(ValueError, match=r"FacetLayout: translations \(2, 3\), canting_e \(1, 3\)"):
        optics.FacetLayout.from_arrays(np.zeros((2, 3)), np.ones((1, 3)), np.ones((1, 3)))
    one = optics.FacetLayout.from_arrays(np.zeros((1, 3)), np.array([[0.4, 0.0, 0.0]]), np.array([[0.0, 0.4, 0.0]]))
    padded = optics.stack_layouts([_layout(), one])
    assert padded.mask.tolist() == [[True, True], [True, False]]  # padding facets are not checked


# --------------------------------------------------------------------------------------
# Optics
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("sun", [[0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [np.inf, 0.0, 1.0]])
def test_flux_images_refuses_a_sun_that_is_no_direction(surface, pose, sun):
    with pytest.raises(ValueError, match=r"flux_images: sun is \[.*no direction"):
        optics.flux_image(KEY, surface, pose, jnp.asarray(sun), TARGET, GRID, optics.GaussianSun())


@pytest.mark.parametrize(("name", "value"), [("dni", np.nan), ("dni", -1.0), ("reflectivity", 2.0)])
def test_flux_images_checks_dni_and_reflectivity_given_as_arrays(surface, pose, name, value):
    with pytest.raises(ValueError, match=f"flux_images: {name} must be"):
        optics.flux_image(KEY, surface, pose, SUN, TARGET, GRID, optics.GaussianSun(), **{name: jnp.asarray(value)})


def test_flux_images_refuses_a_nan_pose_an_integer_dtype_and_no_points(surface, pose):
    nan_pose = hj.Pose(normal=pose.normal, centre=pose.centre.at[0].set(jnp.nan), rotation=pose.rotation)
    with pytest.raises(ValueError, match=r"flux_images: poses.centre is not finite"):
        optics.flux_image(KEY, surface, nan_pose, SUN, TARGET, GRID, optics.GaussianSun())
    with pytest.raises(TypeError, match=r"flux_images: dtype must be a float type"):
        optics.flux_image(KEY, surface, pose, SUN, TARGET, GRID, optics.GaussianSun(), dtype=jnp.int32)
    empty = optics.SurfacePoints(jnp.zeros((0, 3)), jnp.zeros((0, 3)), jnp.zeros((0,)))
    with pytest.raises(ValueError, match=r"flux_images: surfaces hold no points"):
        optics.flux_image(KEY, empty, pose, SUN, TARGET, GRID, optics.GaussianSun())


def test_poses_of_no_direction_are_refused(unchecked):
    centre = jnp.asarray([0.0, -50.0, 1.0])
    with pytest.raises(ValueError, match=r"aim_pose: aim_point - centre is \[0.0, 0.0, 0.0\], no direction"):
        optics.aim_pose(centre, SUN, centre)
    with pytest.raises(ValueError, match=r"aim_pose: sun is \[0.0, 0.0, 0.0\], no direction"):
        optics.aim_pose(centre, jnp.zeros(3), TARGET.centre)
    with pytest.raises(ValueError, match=r"aim_pose: aim_point lies straight away from the sun"):
        optics.aim_pose(centre, SUN, centre - 10.0 * SUN)
    with pytest.raises(ValueError, match=r"aim_pose: centre has shape \(2,\)"):
        optics.aim_pose(centre[:2], SUN, TARGET.centre)
    with pytest.raises(ValueError, match=r"aim_pose: centre is \[nan"):
        optics.aim_pose(centre.at[0].set(jnp.nan), SUN, TARGET.centre)
    for normal in ([0.0, 0.0, 0.0], [np.nan, 0.0, 1.0]):
        with pytest.raises(ValueError, match=r"pose_from_normal: normal is .*no direction"):
            optics.pose_from_normal(centre, jnp.asarray(normal))


def test_surface_points_refuse_negative_or_nan_areas_and_normals(surface):
    with pytest.raises(ValueError, match=r"SurfacePoints: areas\[0\] is -"):
        optics.SurfacePoints(surface.points, surface.normals, -surface.areas)
    with pytest.raises(ValueError, match=r"SurfacePoints: areas\[1\] is nan"):
        optics.SurfacePoints(surface.points, surface.normals, surface.areas.at[1].set(jnp.nan))
    for bad in (0.0, jnp.nan):
        with pytest.raises(ValueError, match=r"SurfacePoints: normals\[2\] is .*non-zero normals"):
            optics.SurfacePoints(surface.points, surface.normals.at[2].set(bad), surface.areas)
    padded = surface.pad_to(surface.n_points + 3)  # padding (area 0) keeps its normal unread
    assert padded.n_points == surface.n_points + 3


def test_stacks_of_nothing_name_their_argument(unchecked):
    for function, name in (
        (optics.stack_surfaces, "surfaces"),
        (optics.stack_layouts, "layouts"),
        (optics.stack_deflectometry, "items"),
        (optics.Deflectometry.from_facets, "facets"),
    ):
        with pytest.raises(ValueError, match=rf"{function.__name__.split('.')[-1]}: {name} is empty"):
            function([])
    with pytest.raises(TypeError, match=r"stack_surfaces: surfaces must be a sequence of SurfacePoints, got str"):
        optics.stack_surfaces("surface")


@pytest.mark.parametrize(("resolution", "said"), [((0, 4), "at least 1"), ((-1, 4), "at least 1"), ((2.5, 4), "whole")])
def test_ideal_surface_refuses_a_resolution_of_no_points(resolution, said, unchecked):
    with pytest.raises(ValueError, match=f"ideal_surface: resolution n_e must be .*{said}"):
        optics.ideal_surface(_layout(), resolution)


def test_image_grid_and_ray_count_refuse_fractional_or_negative_counts(surface, unchecked):
    with pytest.raises(ValueError, match=r"ImageGrid shape must be \(ny, nx\) >= 1, whole numbers, got \(2.5, 4\)"):
        optics.ImageGrid.for_target(TARGET, (2.5, 4))
    assert optics.ImageGrid.for_target(TARGET, (np.int64(3), 4)).shape == (3, 4)
    with pytest.raises(ValueError, match=r"ray_count: rays_per_point must be at least 1, got -3"):
        optics.ray_count(surface, -3)


@pytest.mark.parametrize(
    ("make", "said"),
    [
        (lambda: optics.BuieSun(0.05, n=0), r"BuieSun: n must be at least 1"),
        (lambda: optics.BuieSun(0.05, n=-1), r"BuieSun: n must be at least 1"),
        (lambda: optics.BuieSun("a"), r"BuieSun: csr must be a circumsolar ratio in \(0, 1\), got 'a'"),
        (lambda: optics.BuieSun(np.array([0.1, 0.2])), r"BuieSun: csr must be"),
        (lambda: optics.BuieSun(np.nan), r"BuieSun: csr must be"),
        (lambda: optics.buie_profile(np.array([1.0]), 0.0), r"buie_profile: csr must be .*got 0.0"),
    ],
)
def test_buie_sun_refuses_a_table_of_no_entries_and_a_csr_that_is_no_ratio(make, said, unchecked):
    with pytest.raises(ValueError, match=said):
        make()


def test_plane_power_refuses_a_sun_of_no_direction_and_a_bad_dni(surface, pose):
    with pytest.raises(ValueError, match=r"plane_power: sun is \[0.0, 0.0, 0.0\], no direction"):
        optics.plane_power(surface, pose, jnp.zeros(3), TARGET)
    for dni in (float("nan"), -5.0):
        with pytest.raises(ValueError, match=r"plane_power: dni must be finite and >= 0"):
            optics.plane_power(surface, pose, SUN, TARGET, dni=dni)


# --------------------------------------------------------------------------------------
# Effects, discovery, simulation
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", [float("nan"), float("inf"), "a", [1e-3, 2e-3]])
def test_make_effect_refuses_a_magnitude_that_is_no_finite_number(value, unchecked):
    with pytest.raises(ValueError, match=r"make_effect\('backlash'\): backlash_1 must be a finite real number"):
        effects.make_effect("backlash", backlash_1=value)


def test_effect_class_of_a_list_names_the_name(unchecked):
    with pytest.raises(TypeError, match=r"effect name must be a string .*got list \['thermal'\]"):
        effects.effect_class(["thermal"])


@pytest.mark.parametrize(
    ("kwargs", "said"),
    [
        ({"base": "bogus"}, r"base must be 'stone8' or 'actuator', got 'bogus'"),
        ({"effects": "thermal"}, r"effects must be a sequence of effect instances .*got str"),
        ({"effects": ("thermal",)}, r"effects must be a sequence of effect instances .*got 'thermal'"),
        (
            {"per_heliostat_effects": [effects.make_effect("backlash", backlash_1=1e-3)]},
            r"per_heliostat_effects: Backlash has arrays of leading shape \[\(2,\)\]; expected \(3,\)",
        ),
    ],
)
def test_simulate_fleet_refuses_an_unknown_base_and_effects_it_cannot_use(kwargs, said, unchecked):
    with pytest.raises(ValueError, match=f"simulate_fleet: {said}"):
        discovery.simulate_fleet(0, 3, 4, **kwargs)


@pytest.mark.parametrize(
    ("make", "said"),
    [
        (lambda: discovery.random_actuator_models(jax.random.PRNGKey(0), 0), r"n must be at least 1, got 0"),
        (
            lambda: discovery.random_actuator_models(jax.random.PRNGKey(0), 2, angle_sigma=float("nan")),
            r"angle_sigma must be a finite number >= 0, got nan",
        ),
        (
            lambda: hj.random_stone_models(jax.random.PRNGKey(0), 2, angle_sigma=-1.0),
            r"angle_sigma must be a finite number >= 0, got -1.0",
        ),
        (
            lambda: hj.random_stone_models(jax.random.PRNGKey(0), 2, gear_sigma=float("nan")),
            r"gear_sigma must be a finite number >= 0, got nan",
        ),
    ],
)
def test_random_models_refuse_no_heliostats_and_nan_or_negative_spreads(make, said):
    with pytest.raises(ValueError, match=said):
        make()


def test_holm_refuses_a_level_outside_0_1_and_p_values_that_are_none():
    p = {"a": 0.001, "b": 0.2}
    assert discovery.holm(p, 0.01)[1] == {"a"}
    for alpha in (5.0, 0.0, float("nan")):
        with pytest.raises(ValueError, match=r"holm: alpha must be a family-wise error rate in \(0, 1\)"):
            discovery.holm(p, alpha)
    for bad in (float("nan"), -0.1, 1.5):
        with pytest.raises(ValueError, match=r"holm: pvalues\['b'\] is .*expected p-values in \[0, 1\]"):
            discovery.holm({"a": 0.001, "b": bad}, 0.01)


@pytest.mark.parametrize(
    "canting",
    [[[0.8, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]], [[0.8, 0.0, 0.0, 0.0], [0.6, 0.001, 0.0, 0.0]]],
    ids=["zero-edge", "parallel-edges"],
)
def test_an_artist_facet_of_no_area_is_named_by_file_and_field_and_skipped_alone(canting, tmp_path, shared_paint):
    import shutil

    import h5py

    from heliojax.paint import read_artist_scenario

    source = shared_paint.parent / "artist-scenarios" / "paint_four_heliostats_deflectometry.h5"
    path = tmp_path / "scenario.h5"
    shutil.copy(source, path)
    field = "heliostats/AA39/surface/facets/facet_1/canting"
    with h5py.File(path, "r+") as f:
        del f[field]
        f[field] = np.asarray(canting, np.float32)
    with pytest.raises(DataError, match="no facet") as e:
        read_artist_scenario(path)
    assert e.value.file == str(path) and e.value.field is not None and field in e.value.field, str(e.value)
    assert optics.scene_from_artist(path, skip_bad=True).heliostat_ids == ("AA28", "AA31", "AC43")


@pytest.mark.parametrize(
    ("options", "said"),
    [
        ({"effects": "thermal"}, "effects must be a sequence of effect names"),
        ({"n_folds": 2.5}, "n_folds must be a whole number"),
        ({"n_folds": 101}, "n_folds must be at most 100"),
        ({"max_named": 0}, "max_named must be at least 1"),
        ({"max_refits": True}, "max_refits must be a whole number"),
        ({"max_iterations": -1}, "max_iterations must be at least 1"),
        ({"max_steps": 64.0}, "max_steps must be a whole number"),
        ({"alpha": "0.01"}, "alpha must be in"),
    ],
    ids=[
        "effects-str",
        "folds-float",
        "folds-huge",
        "named-0",
        "refits-bool",
        "iterations-neg",
        "steps-float",
        "alpha-str",
    ],
)
def test_discovery_config_names_an_option_that_is_no_count_in_range(options, said, unchecked):
    with pytest.raises(ValueError, match=said):
        discovery.DiscoveryConfig(**options)


def test_a_sun_of_several_widths_and_effects_on_no_model_are_named(unchecked):
    """``GaussianSun`` of an array of two widths was taken for one sun (its ``sigma`` an
    array that the tracer's scalar code read in part), and ``with_effects(None, ...)``
    failed in a concatenation that named nothing."""
    with pytest.raises(ValueError, match=r"GaussianSun: sigma must be one number .* shape \(2,\)"):
        optics.GaussianSun(np.array([1e-3, 2e-3]))
    with pytest.raises(ValueError, match=r"PillboxSun: half_angle must be one number"):
        optics.PillboxSun(np.array([4.65e-3]))
    assert float(optics.GaussianSun(np.float64(2e-3)).sigma) == 2e-3
    with pytest.raises(TypeError, match="with_effects: model must be a kinematic model, got NoneType"):
        effects.with_effects(None, ["thermal"])


def test_images_of_another_shape_and_negative_sample_sizes_are_named(unchecked):
    """``centroid`` / ``total_power`` of a 1-D image failed in JAX's axis handling and
    ``uniforms`` / ``sample`` of a negative size in JAX's ``iota``, naming neither the
    function nor the shape."""
    with pytest.raises(ValueError, match=r"centroid: image has shape \(8,\); expected \(\.\.\., ny, nx\)"):
        optics.centroid(jnp.ones(8), GRID)
    with pytest.raises(ValueError, match=r"total_power: image has shape \(8, 4\)"):
        optics.total_power(jnp.ones((8, 4)), GRID)
    np.testing.assert_allclose(float(optics.total_power(jnp.ones((8, 8)), GRID)), 16.0 * 1.0, rtol=1e-12)
    with pytest.raises(ValueError, match=r"uniforms: shape must be whole numbers >= 0, got \(-3, 2\)"):
        optics.GaussianSun().sample(KEY, (-3,))
