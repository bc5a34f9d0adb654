"""Geometry: geodesy against hand values and round trips, sun vectors, reflection,
ray-plane intersection on tilted targets."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax._geometry import (
    WGS84_A,
    WGS84_F,
    TargetPlane,
    angle_between,
    direction_to_azimuth_elevation,
    ecef_to_wgs84,
    enu_to_wgs84,
    intersect_plane,
    reflect,
    rotation_about_axis,
    rotation_x,
    rotation_y,
    rotation_z,
    sun_direction,
    wgs84_to_ecef,
    wgs84_to_enu,
)

JUELICH = np.array([50.913421122592574, 6.387824755874856, 87.0])


def test_ecef_hand_values():
    b = WGS84_A * (1 - WGS84_F)
    np.testing.assert_allclose(wgs84_to_ecef(jnp.array([0.0, 0.0, 0.0])), [WGS84_A, 0, 0], atol=1e-9)
    np.testing.assert_allclose(wgs84_to_ecef(jnp.array([0.0, 90.0, 10.0])), [0, WGS84_A + 10, 0], atol=1e-8)
    np.testing.assert_allclose(wgs84_to_ecef(jnp.array([90.0, 0.0, 0.0])), [0, 0, b], atol=1e-8)
    # 45 deg latitude, hand formula: N = a / sqrt(1 - e2/2)
    e2 = WGS84_F * (2 - WGS84_F)
    n = WGS84_A / np.sqrt(1 - e2 / 2)
    x = n * np.sqrt(0.5)
    z = n * (1 - e2) * np.sqrt(0.5)
    np.testing.assert_allclose(wgs84_to_ecef(jnp.array([45.0, 0.0, 0.0])), [x, 0, z], rtol=1e-14)


def test_enu_hand_values():
    # A point 1e-3 deg of latitude north at the same height is ~111.26 m north
    # (meridian radius of curvature M = a (1 - e2) / (1 - e2 sin^2 lat)^1.5).
    e2 = WGS84_F * (2 - WGS84_F)
    lat = np.deg2rad(JUELICH[0])
    m = WGS84_A * (1 - e2) / (1 - e2 * np.sin(lat) ** 2) ** 1.5
    p = JUELICH + np.array([1e-3, 0.0, 0.0])
    enu = np.asarray(wgs84_to_enu(jnp.asarray(p), jnp.asarray(JUELICH)))
    assert abs(enu[0]) < 1e-6
    np.testing.assert_allclose(enu[1], (m + JUELICH[2]) * np.deg2rad(1e-3), rtol=1e-7)
    assert -1e-3 < enu[2] < 0  # the surface curves away below the tangent plane
    # Up is up.
    up = np.asarray(wgs84_to_enu(jnp.asarray(JUELICH + [0, 0, 50.0]), jnp.asarray(JUELICH)))
    np.testing.assert_allclose(up, [0, 0, 50.0], atol=1e-8)


def test_enu_round_trip():
    rng = np.random.default_rng(0)
    enu = rng.uniform([-500, -500, -20], [500, 500, 200], size=(200, 3))
    lla = enu_to_wgs84(jnp.asarray(enu), jnp.asarray(JUELICH))
    back = wgs84_to_enu(lla, jnp.asarray(JUELICH))
    np.testing.assert_allclose(back, enu, atol=1e-6)
    # And geodetic -> ECEF -> geodetic far from the origin too.
    lla2 = np.stack([rng.uniform(-89, 89, 50), rng.uniform(-180, 180, 50), rng.uniform(-100, 9000, 50)], 1)
    np.testing.assert_allclose(ecef_to_wgs84(wgs84_to_ecef(jnp.asarray(lla2))), lla2, atol=1e-9)


def test_sun_direction_convention():
    # az = 0 -> south; az = +90 deg -> east; el = 90 deg -> up.
    np.testing.assert_allclose(sun_direction(0.0, 0.0), [0, -1, 0], atol=1e-15)
    np.testing.assert_allclose(sun_direction(np.pi / 2, 0.0), [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(sun_direction(-np.pi / 2, 0.0), [-1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(sun_direction(0.3, np.pi / 2), [0, 0, 1], atol=1e-15)
    az, el = direction_to_azimuth_elevation(sun_direction(0.7, 0.4))
    np.testing.assert_allclose([az, el], [0.7, 0.4], atol=1e-15)


def test_reflection_and_angles():
    d = jnp.array([0.0, 0.0, -1.0])
    n = jnp.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(reflect(d, n), [0, 0, 1])
    n45 = jnp.array([0.0, np.sqrt(0.5), np.sqrt(0.5)])
    np.testing.assert_allclose(reflect(d, n45), [0, 1, 0], atol=1e-15)
    assert float(angle_between(jnp.array([1.0, 0, 0]), jnp.array([1.0, 1e-9, 0]))) == pytest.approx(1e-9, rel=1e-9)


def test_rotations_agree_with_rodrigues():
    for ang in (0.3, -1.2):
        np.testing.assert_allclose(rotation_x(ang), rotation_about_axis(jnp.array([1.0, 0, 0]), ang), atol=1e-15)
        np.testing.assert_allclose(rotation_y(ang), rotation_about_axis(jnp.array([0, 1.0, 0]), ang), atol=1e-15)
        np.testing.assert_allclose(rotation_z(ang), rotation_about_axis(jnp.array([0, 0, 1.0]), ang), atol=1e-15)
    # Right-handed: x rotated about z by +90 deg is y.
    np.testing.assert_allclose(rotation_z(np.pi / 2) @ jnp.array([1.0, 0, 0]), [0, 1, 0], atol=1e-15)


def _tilted_target():
    # A 4 x 2 m target, centre (1, -2, 10), facing north but tilted 30 deg back
    # (its normal points north and 30 deg up), rotated 10 deg about up.
    tilt = np.deg2rad(30.0)
    yaw = np.deg2rad(10.0)
    rz = np.array(rotation_z(yaw))
    u = rz @ np.array([-1.0, 0, 0])  # left (east) to right (west) as seen from the north
    v = rz @ np.array([0.0, -np.sin(tilt), np.cos(tilt)])
    c = np.array([1.0, -2.0, 10.0])
    corners = dict(
        upper_left=c - 2 * u + 1 * v,
        upper_right=c + 2 * u + 1 * v,
        lower_left=c - 2 * u - 1 * v,
        lower_right=c + 2 * u - 1 * v,
    )
    return TargetPlane.from_corners(**{k: jnp.asarray(p) for k, p in corners.items()}), c, u, v


def test_target_from_corners_tilted():
    target, c, u, v = _tilted_target()
    np.testing.assert_allclose(target.centre, c, atol=1e-12)
    np.testing.assert_allclose(target.u_axis, u, atol=1e-12)
    np.testing.assert_allclose(target.v_axis, v, atol=1e-12)
    np.testing.assert_allclose(target.normal, np.cross(u, v), atol=1e-12)
    assert target.normal[1] > 0.8 and target.normal[2] > 0.4  # faces the field (north), tilted up
    assert float(target.half_width) == pytest.approx(2.0)
    assert float(target.half_height) == pytest.approx(1.0)


def test_intersect_tilted_target_by_hand():
    target, c, u, v = _tilted_target()
    # A ray aimed at the in-plane point (0.5, -0.25) from 50 m in front of it.
    p = c + 0.5 * u - 0.25 * v
    origin = p + 50.0 * np.asarray(target.normal) + np.array([3.0, 0.0, 1.0])
    direction = (p - origin) / np.linalg.norm(p - origin)
    hit = intersect_plane(jnp.asarray(origin), jnp.asarray(direction), target)
    np.testing.assert_allclose(hit.point, p, atol=1e-10)
    np.testing.assert_allclose(hit.uv, [0.5, -0.25], atol=1e-10)
    assert bool(hit.hit)
    np.testing.assert_allclose(hit.distance, np.linalg.norm(p - origin), rtol=1e-12)
    # Outside the rectangle, behind, and from the back: no hit.
    p_out = c + 2.5 * u
    d_out = (p_out - origin) / np.linalg.norm(p_out - origin)
    assert not bool(intersect_plane(jnp.asarray(origin), jnp.asarray(d_out), target).hit)
    assert not bool(intersect_plane(jnp.asarray(origin), -jnp.asarray(direction), target).hit)
    back = p - 10 * np.asarray(target.normal)
    assert not bool(intersect_plane(jnp.asarray(back), jnp.asarray(target.normal), target).hit)


def test_intersect_vmapped_over_targets_and_rays():
    t1, *_ = _tilted_target()
    t2 = TargetPlane.from_corners(
        jnp.array([3.0, -3.0, 126.0]),
        jnp.array([-3.0, -3.0, 126.0]),
        jnp.array([3.0, -3.0, 120.0]),
        jnp.array([-3.0, -3.0, 120.0]),
    )
    targets = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), t1, t2)
    origins = jnp.array([[0.0, 100.0, 2.0], [5.0, 200.0, 2.0]])
    dirs = jnp.array([[0.0, -0.9, 0.6], [-0.02, -0.8, 0.5]])
    vm = jax.vmap(lambda t: intersect_plane(origins, dirs, t))(targets)
    for k, t in enumerate((t1, t2)):
        loop = intersect_plane(origins, dirs, t)
        np.testing.assert_allclose(vm.point[k], loop.point, rtol=1e-14)
        np.testing.assert_array_equal(vm.hit[k], loop.hit)


def test_geodesy_below_float64_warns_and_float64_does_not():
    """Earth-centred coordinates resolve ~0.5 m in float32: without ``jax_enable_x64``
    the conversions came out ~0.1 m off per axis without a word (a probe of the
    library in its default configuration); each public conversion now warns, naming the
    flag, and in float64 none does."""
    origin = np.array([50.91342, 6.38763, 87.0])
    point = origin + np.array([1e-4, 1e-4, 10.0])
    calls = {
        "wgs84_to_ecef": lambda: hj.wgs84_to_ecef(point),
        "ecef_to_wgs84": lambda: hj.ecef_to_wgs84(np.array([4.0e6, 4.5e5, 4.9e6])),
        "wgs84_to_enu": lambda: hj.wgs84_to_enu(point, origin),
        "enu_to_wgs84": lambda: hj.enu_to_wgs84(np.array([7.0, 11.0, 10.0]), origin),
    }
    with jax.enable_x64(False):
        for name, call in calls.items():
            with pytest.warns(UserWarning, match=rf"{name}: geodesy in float32 .*jax_enable_x64"):
                call()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        enu = hj.wgs84_to_enu(point, origin)
        np.testing.assert_allclose(hj.enu_to_wgs84(enu, origin), point, rtol=0, atol=1e-9)
