"""ARTIST scenario interop: the reader/writer round trip, the conventions (against a
second implementation of ARTIST's rigid-body chain written from its published
equations), and tracing the imported scene against the same scene built from
PAINT files."""

from __future__ import annotations

import shutil

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHARED_PAINT

import heliojax as hj
from heliojax import DataError
from heliojax.optics import (
    ImageGrid,
    NurbsFacets,
    centroid,
    flux_images,
    geometry_from_properties,
    layout_from_properties,
    low_order_shape,
    normal_deviation_mrad,
    scene_from_artist,
    scene_to_artist,
    total_power,
)
from heliojax.paint import read_artist_scenario, read_heliostat_properties, read_tower, write_artist_scenario

SCENARIOS = SHARED_PAINT.parent / "artist-scenarios"
needs_scenarios = pytest.mark.skipif(
    not (SCENARIOS / "paint_four_heliostats_ideal.h5").exists() or not SHARED_PAINT.exists(),
    reason="needs ../shared/data/artist-scenarios",
)
KINDS = ("ideal", "deflectometry")


def _path(kind):
    return SCENARIOS / f"paint_four_heliostats_{kind}.h5"


def _leaves(scenario):
    """Every number of a scenario's heliostats, targets and sun, by name."""
    out = {"plant": scenario.plant_position_lla}
    for h in scenario.heliostats:
        out[f"{h.name}/position"] = h.position
        for k, v in h.deviations.items():
            out[f"{h.name}/{k}"] = np.asarray(v)
        for i, a in enumerate(h.actuators):
            out[f"{h.name}/a{i}/minmax"] = np.asarray(a.min_max_motor_positions)
            out[f"{h.name}/a{i}/cw"] = np.asarray(a.clockwise_axis_movement)
            for k, v in a.parameters.items():
                out[f"{h.name}/a{i}/{k}"] = np.asarray(v)
        for k, f in enumerate(h.facets):
            for name in ("position", "canting", "control_points"):
                out[f"{h.name}/f{k}/{name}"] = getattr(f, name)
    for name, t in scenario.planar_targets.items():
        for k in ("centre", "normal", "width", "height"):
            out[f"{name}/{k}"] = np.asarray(getattr(t, k))
    for name, s in scenario.light_sources.items():
        out[f"{name}/covariance"] = np.asarray(s.covariance)
    return out


@needs_scenarios
@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_artist_heliojax_artist(kind, tmp_path):
    """File -> Scene -> ArtistScenario -> file: every array equal to float32 precision."""
    original = read_artist_scenario(_path(kind))
    scene = scene_from_artist(original)
    out = tmp_path / "scenario.h5"
    write_artist_scenario(out, scene_to_artist(scene))
    back = read_artist_scenario(out)
    a, b = _leaves(original), _leaves(back)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_allclose(b[k], a[k], rtol=2e-7, atol=1e-9, err_msg=k)
    # the flat (ideal) facets are written back flat (ARTIST cants them), measured ones translated
    flat = all(np.all(f.control_points[..., 2] == 0) for h in back.heliostats for f in h.facets)
    assert flat == (kind == "ideal")
    assert [a.type for a in back.heliostats[3].actuators] == ["ideal", "ideal"]  # AC43
    assert back.prototype is not None and back.cylindrical_targets.keys() == original.cylindrical_targets.keys()


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _artist_rn(a):  # ARTIST's rotate_n: a rotation about north by -a in the right-handed sense
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _homogeneous(r=None, t=None):
    m = np.eye(4)
    if r is not None:
        m[:3, :3] = r
    if t is not None:
        m[:3, 3] = t
    return m


def _artist_pose(h, counts):
    """ARTIST's rigid body with linear actuators, from its equations (numpy)."""
    angles = []
    for i, a in enumerate(h.actuators):
        p = a.parameters

        def absolute(c, p=p):
            stroke = c / p["increment"] + p["initial_stroke_length"]
            return np.arccos(
                (p["offset"] ** 2 + p["pivot_radius"] ** 2 - stroke**2) / (2 * p["offset"] * p["pivot_radius"])
            )

        delta = absolute(0.0) - absolute(counts[i])
        angle = p["initial_angle"] + (delta if a.clockwise_axis_movement else -delta)
        angles.append(angle - np.pi / 2 if i == 0 else angle)  # ARTIST's load-time shift of axis 1
    d = h.deviations
    vec = lambda pre: np.array([d[f"{pre}_{c}"] for c in "enu"])  # noqa: E731
    m = (
        _homogeneous(t=h.position)
        @ _homogeneous(_artist_rn(d["first_joint_tilt_n"]) @ _rz(d["first_joint_tilt_u"]))
        @ _homogeneous(t=vec("first_joint_translation"))
        @ _homogeneous(_rx(angles[0]))
        @ _homogeneous(_rx(d["second_joint_tilt_e"]) @ _artist_rn(d["second_joint_tilt_n"]))
        @ _homogeneous(t=vec("second_joint_translation"))
        @ _homogeneous(_rz(angles[1]))
        @ _homogeneous(t=vec("concentrator_translation"))
    )
    return m[:3, :3] @ np.array([0.0, -1.0, 0.0]), m[:3, 3]


@needs_scenarios
def test_chain_conventions_against_artist_equations():
    """Random joint tilts written into the scenario: heliojax's forward model of the
    imported scene equals ARTIST's chain (second implementation) to 1e-12."""
    original = read_artist_scenario(_path("deflectometry"))
    rng = np.random.default_rng(3)
    heliostats = []
    for h in original.heliostats[1:3]:  # AA31, AA39: linear actuators
        dev = dict(h.deviations)
        for k in ("first_joint_tilt_n", "first_joint_tilt_u", "second_joint_tilt_e", "second_joint_tilt_n"):
            dev[k] = float(rng.normal(0, 3e-3))
        heliostats.append(type(h)(**{**h.__dict__, "deviations": dev}))
    scenario = type(original)(**{**original.__dict__, "heliostats": tuple(heliostats)})
    scene = scene_from_artist(scenario)
    counts = rng.uniform(5000, 60000, (len(heliostats), 5, 2))
    poses = jax.jit(jax.vmap(jax.vmap(hj.forward, in_axes=(None, None, 0))))(scene.model, scene.geometry, counts)
    for i, h in enumerate(heliostats):
        for j, c in enumerate(counts[i]):
            normal, centre = _artist_pose(h, c)
            np.testing.assert_allclose(np.asarray(poses.normal[i, j]), normal, atol=1e-12)
            np.testing.assert_allclose(np.asarray(poses.centre[i, j]), centre, atol=1e-12)


@needs_scenarios
def test_fitted_model_written_to_artist_and_read_back(tmp_path):
    """A calibrated actuator model (tilts, angle offsets, increment scales, stroke
    offsets) exported to ARTIST's layout and imported again points the same way."""
    scene = scene_from_artist(_path("deflectometry"))
    h = len(scene.heliostat_ids)
    rng = np.random.default_rng(5)
    small = lambda *s: jnp.asarray(rng.normal(0, 2e-3, s))  # noqa: E731
    model = hj.ActuatorModel(
        alpha=small(h),
        beta=small(h),
        gamma=small(h),
        delta=jnp.zeros(h),
        angle_offset=small(h, 2),
        increment_scale=small(h, 2),
        stroke_offset=small(h, 2) * 0.1,
    )
    out = tmp_path / "fitted.h5"
    write_artist_scenario(out, scene_to_artist(scene, model))
    again = scene_from_artist(out)
    counts = jnp.asarray(rng.uniform(5000, 60000, (h, 2)))
    before = jax.vmap(hj.forward)(model, scene.geometry, counts)
    after = jax.vmap(hj.forward)(again.model, again.geometry, counts)
    miss = (
        np.degrees(np.arccos(np.clip(np.sum(np.asarray(before.normal * after.normal), -1), -1, 1))) * np.pi / 180 * 1e3
    )
    linear = ~np.asarray(scene.geometry.ideal_axes).any(-1)
    assert np.all(miss[linear] < 1e-3), miss  # float32 file precision: < 1 urad
    assert np.all(miss[~linear] < 0.05), miss  # ideal axes: re-linearised actuator law
    with pytest.raises(ValueError, match="delta"):
        scene_to_artist(scene, eqx_replace_delta(model, 1e-3))


def eqx_replace_delta(model, value):
    import equinox as eqx

    return eqx.tree_at(lambda m: m.delta, model, jnp.full_like(model.delta, value))


@needs_scenarios
def test_imported_scene_traces_like_the_scene_from_paint_files():
    """The ideal scenario's four heliostats, aimed by the same motor counts, against the
    same heliostats built from PAINT's properties and tower files: same power (1e-5)
    and centroid (< 5 mm; ARTIST's positions differ from heliojax's WGS84 -> ENU by
    < 0.6 mm)."""
    scene = scene_from_artist(_path("ideal"))
    tower = read_tower(next(SHARED_PAINT.glob("*-tower-measurements.json")))
    props = [
        read_heliostat_properties(SHARED_PAINT / "flux-samples" / h / "Properties" / f"{h}-heliostat-properties.json")
        for h in scene.heliostat_ids
    ]
    stack = lambda xs: jax.tree.map(lambda *x: jnp.stack(x), *xs)  # noqa: E731
    geometry = stack([geometry_from_properties(p, tower.origin_lla) for p in props])
    layout = stack([layout_from_properties(p) for p in props])
    np.testing.assert_array_equal(np.asarray(geometry.ideal_axes), np.asarray(scene.geometry.ideal_axes))
    target = scene.targets["solar_tower_juelich_upper"]
    sun = hj.sun_direction(jnp.deg2rad(30.0), jnp.deg2rad(40.0))
    nominal = hj.ActuatorModel.nominal(jnp.float64)
    counts = jax.jit(jax.vmap(lambda g: hj.inverse_aim(nominal, g, target.centre, sun)))(geometry)
    both = jax.jit(jax.vmap(hj.forward, in_axes=(0, 0, 0)))
    pose_paint = both(jax.tree.map(lambda x: jnp.broadcast_to(x, (4,) + x.shape), nominal), geometry, counts)
    pose_artist = both(scene.model, scene.geometry, counts)
    grid = ImageGrid.for_target(target, (64, 64))
    key = jax.random.key(0)
    trace = jax.jit(  # one compiled program for both scenes
        lambda s, p: flux_images(key, s, p, sun, target, grid, scene.sunshape, rays_per_point=8).astype(jnp.float64)
    )
    img_paint = trace(NurbsFacets.ideal(layout).evaluate((12, 12)), pose_paint)
    img_artist = trace(scene.facets.evaluate((12, 12)), pose_artist)
    p0, p1 = np.asarray(total_power(img_paint, grid)), np.asarray(total_power(img_artist, grid))
    assert np.all(p0 > 5000.0)  # the spots are on the target
    np.testing.assert_allclose(p1, p0, rtol=1e-5)
    shift = np.linalg.norm(np.asarray(centroid(img_artist, grid) - centroid(img_paint, grid)), axis=-1)
    assert np.all(shift < 5e-3), shift  # the two surfaces are sampled at different points


@needs_scenarios
def test_artist_flat_facets_have_their_exact_area():
    """ARTIST's flat facets (uniform, non-Greville control points): the sampled areas
    add up to the facets' area even on a coarse grid."""
    scene = scene_from_artist(_path("ideal"))
    exact = np.asarray(scene.layout.areas().sum(-1))
    got = np.asarray(scene.facets.evaluate((6, 6)).areas.sum(-1))
    np.testing.assert_allclose(got, exact, rtol=1e-6)


@needs_scenarios
def test_bad_scenario_names_the_field(tmp_path):
    broken = tmp_path / "broken.h5"
    shutil.copy(_path("ideal"), broken)
    broken.chmod(0o644)
    with h5py.File(broken, "a") as f:
        del f["heliostats/AA39/actuator/actuator_1/parameters/pivot_radius"]
        f["heliostats/AA31/position"][0] = np.nan
    with pytest.raises(DataError, match="AA31/position"):
        read_artist_scenario(broken)
    with h5py.File(broken, "a") as f:
        f["heliostats/AA31/position"][0] = 1.0
    with pytest.raises(DataError, match="AA39/actuator/actuator_1/parameters/pivot_radius"):
        read_artist_scenario(broken)
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(DataError, match="junk.h5"):
        read_artist_scenario(tmp_path / "junk.h5")


@needs_scenarios
def test_surface_comparison_across_parameterisations():
    """heliojax's ideal facets (Greville control points) against ARTIST's flat facets of
    the same heliostat (uniform control points): the normals agree (< 0.05 mrad, the
    canting vectors are not exactly orthogonal), the deflectometry surface does not;
    the fitted low-order shape of a flat canted facet is flat with the canting slope."""
    ideal_scene = scene_from_artist(_path("ideal"))
    measured_scene = scene_from_artist(_path("deflectometry"))
    i = ideal_scene.index("AA31")
    take = lambda t: jax.tree.map(lambda x: x[i], t)  # noqa: E731
    ours = NurbsFacets.ideal(take(ideal_scene.layout))
    assert normal_deviation_mrad(ours, take(ideal_scene.facets)) < 0.05
    assert normal_deviation_mrad(ours, take(measured_scene.facets)) > 1.0
    shape = low_order_shape(ours)
    ce = np.asarray(take(ideal_scene.layout).canting_e)
    for facet, c in zip(shape, ce, strict=True):
        assert abs(facet["focal_length_m"]) > 1e6
        assert facet["tilt_mrad"][0] == pytest.approx(c[2] / c[0] * 1e3, rel=1e-3)
