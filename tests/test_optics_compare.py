"""Comparison of traced flux with PAINT's measured flux PNGs (real data)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax.optics import ImageGrid, pose_from_normal
from heliojax.optics._compare import (
    compare_record,
    flux_sample_records,
    kl_divergence,
    normalised_cross_correlation,
    point_at,
    remove_background,
    spot_widths,
)


def test_normalised_cross_correlation():
    rng = np.random.default_rng(0)
    a = rng.random((16, 16))
    assert normalised_cross_correlation(a, 3 * a + 1) == pytest.approx(1.0)
    assert normalised_cross_correlation(a, -a) == pytest.approx(-1.0)
    assert abs(normalised_cross_correlation(a, rng.random((16, 16)))) < 0.3


def test_remove_background():
    img = np.full((8, 8), 0.1)
    img[3:5, 3:5] = 0.9
    out = remove_background(img)
    assert out[0, 0] == 0.0 and out[4, 4] == pytest.approx(0.8)


def test_compare_real_flux_image(shared_paint):
    pairs = [p for p in flux_sample_records(shared_paint / "flux-samples") if p[0].name.startswith("271633")]
    if not pairs:
        pytest.skip("flux sample 271633 (AA39) not present")
    rec, props = pairs[0]
    c = compare_record(rec, props, shared_paint / "WRI1030197-tower-measurements.json", rays_per_point=32, steps=2)
    # the PNG extent assumption (whole target, 256 x 256) puts the measured centroid on
    # the record's own UTIS focal spot
    assert c.png_vs_record_m < 0.1
    # nominal kinematics: off by ~1 m, but the spot shape matches
    assert c.centroid_distance_m < 3.0
    assert c.ncc_centred > 0.9
    assert c.traced.shape == c.measured.shape == (256, 256)


def test_kl_divergence_ignores_brightness():
    rng = np.random.default_rng(1)
    a = rng.random((32, 32))
    assert kl_divergence(a, 5.0 * a) == pytest.approx(0.0, abs=1e-12)
    b = np.roll(a, 3, axis=0)
    assert kl_divergence(a, b) > 0.01


def test_spot_widths_of_a_gaussian():
    grid = ImageGrid.centred(0.5, -0.2, 6.0, 6.0, shape=(200, 240))
    u, v = (np.asarray(x) for x in grid.pixel_centres())
    img = np.exp(-0.5 * ((u[None, :] - 0.5) / 0.4) ** 2 - 0.5 * ((v[:, None] + 0.2) / 0.7) ** 2)
    np.testing.assert_allclose(spot_widths(img, grid), [0.4, 0.7], rtol=2e-3)


def test_point_at_reflects_the_central_ray_onto_the_spot():
    g = jnp.float64
    normal = jnp.asarray([0.1, -0.9, 0.4], g)
    pose = pose_from_normal(jnp.asarray([10.0, 40.0, 2.0], g), normal / jnp.linalg.norm(normal))
    sun = hj.sun_direction(jnp.asarray(0.3, g), jnp.asarray(0.6, g))
    spot = jnp.asarray([0.5, -3.0, 44.0], g)
    new = point_at(pose, sun, spot)
    out = np.asarray(hj.reflect(-sun, new.normal))
    want = np.asarray(spot - pose.centre)
    np.testing.assert_allclose(out, want / np.linalg.norm(want), atol=1e-12)
    r = np.asarray(new.rotation)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r[:, 2], np.asarray(new.normal), atol=1e-12)
