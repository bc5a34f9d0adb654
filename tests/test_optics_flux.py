"""Flux tracing: energy, analytic spots, orientation, batching, gradients."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heliojax._geometry import TargetPlane, intersect_plane, reflect
from heliojax._heliostat import Pose
from heliojax.optics import (
    FacetLayout,
    GaussianSun,
    ImageGrid,
    NurbsFacets,
    PillboxSun,
    SurfacePoints,
    aim_pose,
    centroid,
    flux_image,
    flux_images,
    ideal_surface,
    plane_power,
    stack_surfaces,
    total_power,
)

UP = Pose(normal=jnp.asarray([0.0, 0.0, 1.0]), centre=jnp.zeros(3), rotation=jnp.eye(3))


def ceiling(height, half):
    """Horizontal target at ``height`` facing down (u east, v south)."""
    return TargetPlane(
        centre=jnp.asarray([0.0, 0.0, height]),
        normal=jnp.asarray([0.0, 0.0, -1.0]),
        u_axis=jnp.asarray([1.0, 0.0, 0.0]),
        v_axis=jnp.asarray([0.0, -1.0, 0.0]),
        half_width=jnp.asarray(half),
        half_height=jnp.asarray(half),
    )


def square_mirror(side, n):
    c = (np.arange(n) + 0.5) / n * side - side / 2
    x, y = np.meshgrid(c, c, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], -1)
    nrm = np.tile([0.0, 0.0, 1.0], (n * n, 1))
    return SurfacePoints(jnp.asarray(pts), jnp.asarray(nrm), jnp.full(n * n, side**2 / n**2))


def moments(img, grid):
    img = np.asarray(img, np.float64)
    u, v = (np.asarray(a, np.float64) for a in grid.pixel_centres())
    w = img / img.sum()
    cu = (w * u[None, :]).sum()
    cv = (w * v[:, None]).sum()
    return cu, cv, (w * (u[None, :] - cu) ** 2).sum(), (w * (v[:, None] - cv) ** 2).sum()


def test_energy_on_oversized_target_within_monte_carlo_error():
    # Canted 4-facet heliostat, oblique sun: total power = DNI rho sum_i A_i <cos_i>.
    lay = FacetLayout.from_arrays(
        [[-0.8, 0.64, 0.04], [0.8, 0.64, 0.04], [-0.8, -0.64, 0.04], [0.8, -0.64, 0.04]],
        [[0.8, 0, -0.005], [0.8, 0, 0.005], [0.8, 0, -0.005], [0.8, 0, 0.005]],
        [[0, 0.64, 0.003], [0, 0.64, 0.003], [0, 0.64, -0.003], [0, 0.64, -0.003]],
    )
    surf = ideal_surface(lay, (16, 16))
    sun = jnp.asarray([0.6, 0.3, 0.5]) / np.linalg.norm([0.6, 0.3, 0.5])
    pose = aim_pose(jnp.asarray([10.0, 60.0, 2.0]), sun, jnp.asarray([0.0, 0.0, 40.0]))
    target = TargetPlane.from_corners(
        np.array([15.0, 0, 55]),
        np.array([-15.0, 0, 55]),
        np.array([15.0, 0, 25]),
        np.array([-15.0, 0, 25]),
    )
    grid = ImageGrid.for_target(target, (128, 128))
    sunshape = PillboxSun()
    dni, rho, K = 850.0, 0.93, 64 * 4
    img = flux_images(
        jax.random.key(0),
        surf,
        pose,
        sun,
        target,
        grid,
        sunshape,
        rays_per_point=64,
        steps=4,
        dni=dni,
        reflectivity=rho,
    )
    assert img.dtype == jnp.float32
    power = float(total_power(img.astype(jnp.float64), grid))
    # Expected value: E[d . n] = E[cos r] (s . n) for a symmetric sun shape;
    # pillbox: E[cos r] = E[1 - r^2/2 + r^4/24] = 1 - a^2/4 + a^4/72.
    a = 4.65e-3
    n = np.asarray(surf.normals) @ np.asarray(pose.rotation).T
    sn = n @ np.asarray(sun)
    areas = np.asarray(surf.areas)
    ecos = 1 - a**2 / 4 + a**4 / 72
    expected = dni * rho * np.sum(areas * sn * ecos)
    # Monte Carlo sd: per ray Var(d . n) ~ E[r^2]/2 (1 - (s.n)^2) (tangential part)
    var_ray = a**2 / 4 * (1 - sn**2)
    sd = np.sqrt(np.sum((dni * rho * areas / K) ** 2 * K * var_ray))
    # float32 accumulation: ~1e3 adds per pixel, relative rounding ~ 1e-7 * sqrt(1e3)
    tol = 3 * sd + 4e-6 * expected
    assert abs(power - expected) < tol, (power, expected, sd)
    # and the naive formula of the issue (area x cos of the central ray) agrees to MC precision
    assert power == pytest.approx(dni * rho * float(surf.total_area()) * float(sun @ pose.normal), rel=2e-3)
    # the plane catches everything: plane_power is the expectation at the sun's centre
    on_plane = float(plane_power(surf, pose, sun, target, dni=dni, reflectivity=rho))
    assert on_plane == pytest.approx(expected / ecos, rel=1e-9)
    assert abs(power - on_plane) < tol + expected * (1 - ecos)


def test_plane_power_counts_the_points_whose_beam_reaches_the_front_of_the_plane():
    """``plane_power`` (W): DNI x reflectivity x area x cos for the mirror points in
    front of the plane whose reflected central ray travels toward it; none from behind
    it or for a sun behind the mirror."""
    mirror = square_mirror(2.0, 8)  # 4 m^2 facing up at the origin, points x, y in (-1, 1)
    overhead = jnp.asarray([0.0, 0.0, 1.0])
    tilted = jnp.asarray([np.sin(0.5), 0.0, np.cos(0.5)])
    assert float(plane_power(mirror, UP, overhead, ceiling(5.0, 1.0), dni=900.0, reflectivity=0.9)) == pytest.approx(
        900.0 * 0.9 * 4.0, rel=1e-12
    )
    assert float(plane_power(mirror, UP, tilted, ceiling(5.0, 1.0))) == pytest.approx(1000.0 * 4.0 * np.cos(0.5))
    assert float(plane_power(mirror, UP, overhead, ceiling(-5.0, 1.0))) == 0.0  # the mirror is behind it
    assert float(plane_power(mirror, UP, -overhead, ceiling(5.0, 1.0))) == 0.0  # the sun below the mirror
    # a wall through the mirror, facing +x: only the half at x > 0 is in front of it; the
    # beams (sun tilted toward +x: reflected toward -x) travel to its front
    wall = TargetPlane(
        centre=jnp.zeros(3),
        normal=jnp.asarray([1.0, 0.0, 0.0]),
        u_axis=jnp.asarray([0.0, -1.0, 0.0]),
        v_axis=jnp.asarray([0.0, 0.0, 1.0]),
        half_width=jnp.asarray(1.0),
        half_height=jnp.asarray(1.0),
    )
    assert float(plane_power(mirror, UP, tilted, wall)) == pytest.approx(1000.0 * 2.0 * np.cos(0.5))
    away = jnp.asarray([-np.sin(0.5), 0.0, np.cos(0.5)])  # reflected toward +x: away from the wall's front
    assert float(plane_power(mirror, UP, away, wall)) == 0.0


def _overhead_sun_image(surf, target, pixels, sunshape, rays_per_point, seed):
    """Flux image of ``surf`` (facing up) for the sun overhead: ``(grid, image, moments)``."""
    grid = ImageGrid.for_target(target, (pixels, pixels))
    sun = jnp.asarray([0.0, 0.0, 1.0])
    img = flux_image(
        jax.random.key(seed), surf, UP, sun, target, grid, sunshape, rays_per_point=rays_per_point, steps=4
    )
    return grid, img, moments(img, grid)


def test_flat_mirror_pillbox_spot_is_analytic_disk():
    # Sun overhead, small flat mirror facing up, target ceiling at D: the spot is the
    # sun disk of radius D tan(a) (mirror 0.1 m wide convolves it slightly).
    D, a, side = 100.0, 4.65e-3, 0.1
    surf = square_mirror(side, 8)
    target = ceiling(D, 1.0)
    grid, img, (cu, cv, vu, vv) = _overhead_sun_image(surf, target, 200, PillboxSun(a), 4096, seed=1)
    R = D * np.tan(a)
    # per axis: disk R^2/4 (cos-weighting changes it by O(a^2)), mirror side^2/12,
    # bilinear splat du^2/6
    du = 2.0 / 200
    expected = R**2 / 4 + side**2 / 12 + du**2 / 6
    n_rays = 64 * 4096 * 4
    sd = R**2 / np.sqrt(12 * n_rays)  # Var(r^2) of a uniform disk is R^4 / 12
    assert abs(vu + vv - 2 * expected) < 3 * sd + 1e-5 * expected
    assert abs(cu) < 1e-3 and abs(cv) < 1e-3
    # no flux beyond the disk edge + half mirror diagonal + one pixel
    u, v = (np.asarray(x) for x in grid.pixel_centres())
    rr = np.hypot(u[None, :], v[:, None])
    outside = np.asarray(img)[rr > R + side / np.sqrt(2) + 1.5 * du].sum()
    assert outside == 0.0
    # uniform disk: mean flux inside 0.8 R equals P / (pi R^2) within 1.5 %
    inner = np.asarray(img, np.float64)[rr < 0.8 * R].mean()
    P = float(total_power(img, grid))
    assert inner == pytest.approx(P / (np.pi * R**2), rel=0.015)


def test_gaussian_sun_parabolic_facet_gives_gaussian_spot():
    # On-axis paraboloid z = rho^2 / (4 f), sun on axis, target in the focal plane:
    # a ray from the point at distance L = f + z from the focus, deviated by the small
    # angle delta, lands L delta / cos(psi) (radially) from the focus. With rim angle
    # psi <= 0.02 rad and L - f <= 5 mm the spot is Gaussian with per-axis variance
    # sigma^2 <L^2 (1 + tan^2(psi)/2)> (relative corrections 1e-4), plus du^2/6.
    f, sigma = 50.0, 2e-3
    n = 48
    cx = (np.arange(n) + 0.5) / n * 1.6 - 0.8
    cy = (np.arange(n) + 0.5) / n * 1.25 - 0.625
    x, y = (g.ravel() for g in np.meshgrid(cx, cy, indexing="ij"))
    z = (x**2 + y**2) / (4 * f)
    nrm = np.stack([-x / (2 * f), -y / (2 * f), np.ones_like(x)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    surf = SurfacePoints(jnp.asarray(np.stack([x, y, z], -1)), jnp.asarray(nrm), jnp.full(x.shape, 2.0 / n**2))
    target = ceiling(f, 0.6)
    grid, img, (cu, cv, vu, vv) = _overhead_sun_image(surf, target, 160, GaussianSun(sigma), 256, seed=2)
    L = f + z
    tan2 = (x**2 + y**2) / (f - z) ** 2
    du = 1.2 / 160
    expected = sigma**2 * np.mean(L**2 * (1 + tan2 / 2)) + du**2 / 6
    n_rays = x.size * 256 * 4
    sd = expected * np.sqrt(2 / n_rays)  # Var of a squared Gaussian: 2 s^4
    assert abs(vu - expected) < 3 * sd and abs(vv - expected) < 3 * sd
    assert abs(cu) < 3 * np.sqrt(expected / n_rays) + 1e-5
    # Gaussian shape: energy within radius s is 1 - exp(-1/2) of the total
    s = np.sqrt(expected)
    u, v = (np.asarray(q) for q in grid.pixel_centres())
    rr = np.hypot(u[None, :], v[:, None])
    frac = np.asarray(img, np.float64)[rr < s].sum() / np.asarray(img, np.float64).sum()
    # discretisation of the disk into pixels: ~ perimeter * du / area ~ 1 % before averaging; allow 1.5 %
    assert frac == pytest.approx(1 - np.exp(-0.5), rel=0.015)


def test_centroid_follows_the_central_ray_and_orientation():
    # Tilted flat mirror: the spot centre is where the reflected central ray meets
    # the target; the image is PNG-oriented (column -> +u, row -> -v).
    sun = jnp.asarray([0.2, -0.4, 0.9]) / np.linalg.norm([0.2, -0.4, 0.9])
    target = TargetPlane.from_corners(
        np.array([5.0, -1, 35]),
        np.array([-5.0, -1, 35]),
        np.array([5.0, -1, 25]),
        np.array([-5.0, -1, 25]),
    )
    aim = jnp.asarray([1.5, -1.0, 28.0])  # right (west, +u) of and below (-v) the centre
    pose = aim_pose(jnp.asarray([2.0, 50.0, 1.5]), sun, aim)
    surf = square_mirror(1.0, 16)
    grid = ImageGrid.for_target(target, (100, 100))
    img = flux_image(jax.random.key(3), surf, pose, sun, target, grid, GaussianSun(1e-3), rays_per_point=64)
    c = np.asarray(centroid(img, grid))
    hit = intersect_plane(pose.centre, reflect(-sun, pose.normal), target)
    np.testing.assert_allclose(c, np.asarray(hit.uv), atol=0.01)
    np.testing.assert_allclose(c, [-1.5, -2.0], atol=0.02)  # u points west: aim is 1.5 m west
    r, col = np.unravel_index(np.argmax(np.asarray(img)), img.shape)
    assert col < 50 and r > 50  # left of centre (u < 0), below centre (row > half)


def test_batched_padded_heliostats_match_individual_and_combine():
    s1 = square_mirror(1.0, 8)
    s2 = square_mirror(0.5, 5)
    sun = jnp.asarray([0.0, 0.0, 1.0])
    target = ceiling(30.0, 1.5)
    grid = ImageGrid.for_target(target, (64, 64))
    poses = jax.tree_util.tree_map(
        lambda *x: jnp.stack(x), UP, eqx.tree_at(lambda p: p.centre, UP, jnp.asarray([0.3, 0.0, 0.0]))
    )
    batch = stack_surfaces([s1, s2])
    assert batch.points.shape == (2, 64, 3) and float(batch.areas[1, 25:].sum()) == 0.0
    imgs = flux_images(jax.random.key(4), batch, poses, sun, target, grid, PillboxSun(), rays_per_point=32)
    total = flux_images(
        jax.random.key(4), batch, poses, sun, target, grid, PillboxSun(), rays_per_point=32, combine=True
    )
    np.testing.assert_allclose(np.asarray(total), np.asarray(imgs).sum(0), rtol=1e-5, atol=1e-3)
    p = np.asarray(total_power(imgs.astype(jnp.float64), grid))
    np.testing.assert_allclose(p, [1000.0, 250.0], rtol=1e-4)
    # the padded heliostat's spot sits 0.3 m east of the first
    c = np.asarray(centroid(imgs, grid))
    assert c[1, 0] - c[0, 0] == pytest.approx(0.3, abs=0.01)


def test_reproducible_keys_and_fresh_steps():
    surf = square_mirror(1.0, 8)
    target = ceiling(30.0, 1.5)
    grid = ImageGrid.for_target(target, (32, 32))
    args = (surf, UP, jnp.asarray([0.0, 0.0, 1.0]), target, grid, GaussianSun(3e-3))
    a = flux_image(jax.random.key(7), *args, rays_per_point=8, steps=2)
    b = flux_image(jax.random.key(7), *args, rays_per_point=8, steps=2)
    c = flux_image(jax.random.key(8), *args, rays_per_point=8, steps=2)
    np.testing.assert_array_equal(a, b)
    assert float(jnp.abs(a - c).max()) > 0
    # step j uses fold_in(key, first_step + j): the second step draws fresh rays, and
    # two one-step calls (first_step 0 and 1) average to the two-step image
    s0, s1 = (
        flux_image(jax.random.key(7), *args, rays_per_point=8, first_step=jnp.asarray(j, jnp.int32)) for j in (0, 1)
    )
    assert float(jnp.abs(s0 - s1).max()) > 0
    np.testing.assert_allclose(
        np.asarray(a), (np.asarray(s0) + np.asarray(s1)) / 2, rtol=1e-5, atol=1e-6 * float(a.max())
    )


def _nurbs_flux_loss(dz, facets, key, dtype):
    f = eqx.tree_at(lambda x: x.control_points, facets, facets.control_points.at[..., 2].add(dz))
    surf = f.evaluate((12, 12))
    sun = jnp.asarray([0.0, 0.0, 1.0], dtype)
    target = ceiling(40.0, 1.2)
    grid = ImageGrid.for_target(target, (48, 48))
    img = flux_image(key, surf, UP, sun, target, grid, GaussianSun(2e-3), rays_per_point=64, dtype=dtype)
    u, v = grid.pixel_centres()
    weight = jnp.exp(-((u[None, :] - 0.2) ** 2 + (v[:, None] + 0.1) ** 2) / 0.3)
    return jnp.sum(img * weight.astype(dtype)) * 1e-3


def _facets():
    lay = FacetLayout.from_arrays([[0.0, 0.0, 0.0]], [[0.6, 0.0, 0.0]], [[0.0, 0.5, 0.0]])
    return NurbsFacets.ideal(lay, n_ctrl=(4, 4), degree=2)


def test_gradient_wrt_control_points_matches_finite_differences():
    facets = _facets()
    key = jax.random.key(11)
    rng = np.random.default_rng(0)
    dz0 = jnp.asarray(rng.normal(0, 2e-3, (1, 4, 4)))
    loss = jax.jit(lambda dz: _nurbs_flux_loss(dz, facets, key, jnp.float64))
    g = np.asarray(jax.grad(loss)(dz0))
    assert np.abs(g).max() > 0
    h = 1e-6
    for idx in [(0, 0, 0), (0, 1, 2), (0, 3, 1), (0, 2, 2)]:
        e = jnp.zeros_like(dz0).at[idx].set(h)
        fd = (float(loss(dz0 + e)) - float(loss(dz0 - e))) / (2 * h)
        assert g[idx] == pytest.approx(fd, rel=2e-3, abs=1e-3 * np.abs(g).max())
    # the float32 tracer gives the same gradient to float32 Monte Carlo precision
    g32 = np.asarray(jax.jit(jax.grad(lambda dz: _nurbs_flux_loss(dz, facets, key, jnp.float32)))(dz0))
    np.testing.assert_allclose(g32, g, rtol=0.02, atol=0.01 * np.abs(g).max())


def test_gradient_wrt_kinematic_parameters():
    from heliojax._heliostat import HeliostatGeometry
    from heliojax._kinematics import StoneModel, forward, inverse_aim
    from heliojax._simulate import calibration_target, typical_actuators

    geometry = HeliostatGeometry.build(
        jnp.asarray([5.0, 80.0, 1.5]), typical_actuators(), concentrator_translation=(0.0, 0.175, 0.0)
    )
    target = calibration_target()
    sun = jnp.asarray([0.3, -0.6, 0.7]) / np.linalg.norm([0.3, -0.6, 0.7])
    counts = inverse_aim(StoneModel.nominal(), geometry, target.centre, sun)
    surf = square_mirror(2.0, 12)
    grid = ImageGrid.for_target(target, (64, 64))
    key = jax.random.key(5)

    @jax.jit
    def spot(alpha):
        model = eqx.tree_at(lambda m: m.alpha, StoneModel.nominal(), alpha)
        pose = forward(model, geometry, counts)
        img = flux_image(key, surf, pose, sun, target, grid, GaussianSun(2e-3), rays_per_point=32, dtype=jnp.float64)
        return centroid(img, grid)

    jac = np.asarray(jax.jacfwd(spot)(jnp.asarray(0.0)))
    h = 1e-6
    fd = (np.asarray(spot(jnp.asarray(h))) - np.asarray(spot(jnp.asarray(-h)))) / (2 * h)
    np.testing.assert_allclose(jac, fd, rtol=1e-3, atol=1e-3)
    assert np.abs(jac).max() > 10.0  # ~ 2 x distance (m/rad)


def test_image_grid_helpers():
    g = ImageGrid.centred(1.0, -2.0, 6.0, 4.0, (40, 60))
    u, v = g.pixel_centres()
    assert float(g.du) == pytest.approx(0.1) and float(g.dv) == pytest.approx(0.1)
    assert float(u[0]) == pytest.approx(-1.95) and float(v[0]) == pytest.approx(-0.05)
    with pytest.raises(ValueError):
        ImageGrid.centred(0.0, 0.0, 1.0, 1.0, (0, 3))
