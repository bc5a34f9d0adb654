"""Sun shapes: sampled moments against closed forms, reproducibility, helpers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heliojax.optics import (
    BuieSun,
    EffectiveSun,
    GaussianSun,
    PillboxSun,
    buie_profile,
    offsets_to_directions,
    tangent_basis,
    uniforms,
)
from heliojax.optics._sunshape import _disk

N = 400_000


def _radii(shape, key=0):
    x = np.asarray(shape.sample(jax.random.key(key), (N,)), np.float64)
    return x, np.hypot(x[:, 0], x[:, 1])


@pytest.mark.parametrize("method", ["hash", "jax"])
def test_uniforms_moments_and_range(method):
    u = np.asarray(uniforms(jax.random.key(3), (N,), jnp.float32, method), np.float64)
    assert u.min() > 0.0 and u.max() < 1.0
    # mean 1/2 (sd 1/sqrt(12 N)), variance 1/12 (sd ~ 1/(sqrt(180 N)))
    assert abs(u.mean() - 0.5) < 4 / np.sqrt(12 * N)
    assert abs(u.var() - 1 / 12) < 4 / np.sqrt(180 * N)
    # neighbouring counters must not be correlated (lag-1 autocorrelation ~ N(0, 1/N))
    c = np.corrcoef(u[:-1], u[1:])[0, 1]
    assert abs(c) < 4 / np.sqrt(N)


def test_uniforms_reproducible_and_fresh():
    a = uniforms(jax.random.key(1), (1000,))
    b = uniforms(jax.random.key(1), (1000,))
    c = uniforms(jax.random.fold_in(jax.random.key(1), 1), (1000,))
    np.testing.assert_array_equal(a, b)
    assert np.mean(np.asarray(a) == np.asarray(c)) < 0.01


def test_disk_polynomials_are_unit_circle():
    u = jnp.linspace(1e-6, 1 - 1e-6, 10001)
    xy = np.asarray(_disk(jnp.ones_like(u), u), np.float64)
    np.testing.assert_allclose(np.hypot(xy[:, 0], xy[:, 1]), 1.0, atol=1e-8)
    ang = np.arctan2(xy[:, 1], xy[:, 0])
    np.testing.assert_allclose(np.unwrap(ang), 2 * np.pi * (np.asarray(u) - 0.5), atol=1e-8)


def test_gaussian_sun_moments():
    s = 2.5e-3
    x, r = _radii(GaussianSun(s))
    # per-axis variance sigma^2: sd of the estimate sigma^2 sqrt(2/N)
    np.testing.assert_allclose((x**2).mean(0), s**2, atol=4 * s**2 * np.sqrt(2 / N))
    # Rayleigh: P(r < sigma) = 1 - exp(-1/2)
    p = 1 - np.exp(-0.5)
    assert abs((r < s).mean() - p) < 4 * np.sqrt(p * (1 - p) / N)


def test_pillbox_sun_uniform_disk():
    a = 4.65e-3
    x, r = _radii(PillboxSun())
    assert r.max() <= a * (1 + 1e-6)
    np.testing.assert_allclose((x**2).mean(0), a**2 / 4, atol=4 * a**2 / 4 * np.sqrt(1.0 / N) * 1.5)
    # uniform in area: P(r < a/2) = 1/4
    assert abs((r < a / 2).mean() - 0.25) < 4 * np.sqrt(0.25 * 0.75 / N)
    assert PillboxSun().second_moment() == pytest.approx(a**2 / 4)


@pytest.mark.parametrize("csr", [0.05, 0.1, 0.3])
def test_buie_sun_inverse_cdf(csr):
    sun = BuieSun(csr)
    x, r = _radii(sun)
    p = sun.realized_csr
    assert abs((r > 4.65e-3).mean() - p) < 4 * np.sqrt(p * (1 - p) / N) + 1e-4
    assert r.max() <= 43.6e-3 * (1 + 1e-6)
    np.testing.assert_allclose((x**2).mean(0), sun.second_moment(), rtol=0.03)
    # independent check of the disk part: on the disk, the radial density is
    # proportional to phi(t) t; compare the sampled histogram over [0, 4.65] mrad
    edges = np.linspace(0, 4.65e-3, 11)
    hist, _ = np.histogram(r, edges)
    t = np.linspace(0, 4.65, 2001)
    dens = buie_profile(t, csr) * t
    cum = np.concatenate([[0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(t))])
    expected = np.diff(np.interp(edges * 1e3, t, cum))
    expected = expected / expected.sum() * hist.sum()
    # Poisson counts: 4 sigma per bin
    assert np.all(np.abs(hist - expected) < 4 * np.sqrt(expected) + 0.005 * expected)


def test_buie_realized_csr_grows_with_parameter():
    vals = [BuieSun(c).realized_csr for c in (0.02, 0.05, 0.1, 0.2, 0.4)]
    assert np.all(np.diff(vals) > 0)
    assert 0.05 < BuieSun(0.1).realized_csr < 0.15


def test_buie_rejects_bad_csr():
    with pytest.raises(ValueError):
        BuieSun(0.0)


def test_effective_sun_adds_doubled_slope_error():
    base = PillboxSun()
    eff = EffectiveSun(base, 1e-3)
    x, _ = _radii(eff)
    expected = base.second_moment() + 4e-6
    assert eff.second_moment() == pytest.approx(expected)
    np.testing.assert_allclose((x**2).mean(0), expected, rtol=0.02)


@pytest.mark.parametrize("s", [[0.3, -0.5, 0.8], [0.0, 0.0, 1.0], [0.0, 1e-9, -1.0]])
def test_tangent_basis_orthonormal(s):
    s = jnp.asarray(s) / jnp.linalg.norm(jnp.asarray(s))
    e1, e2 = tangent_basis(s)
    m = np.stack([e1, e2, s])
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.cross(e1, e2), s, atol=1e-12)


def test_offsets_to_directions_angle():
    s = jnp.asarray([0.0, -0.6, 0.8])
    off = jnp.asarray([[3e-3, 4e-3], [0.0, 0.0]])
    d = offsets_to_directions(off, s)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    ang = np.arccos(np.clip(np.asarray(d) @ np.asarray(s), -1, 1))
    np.testing.assert_allclose(ang, [5e-3, 0.0], atol=1e-7)
