"""Level-2 optics: intercept against brute-force integration, monotonicity, year."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from heliojax._geometry import intersect_plane
from heliojax.acceptance import (
    JUELICH_COORDINATES,
    atmospheric_attenuation,
    beam_sigma,
    clear_sky_dni,
    cosine_efficiency,
    field_efficiency,
    intercept_efficiency,
    juelich_receiver,
    load_receiver,
    typical_year,
)

POSITIONS = np.array([[0.0, 30, 1], [60, 30, 1], [-100, 150, 2], [150, 250, 0], [0, 400, 0], [-20, 20, 0]])


def _brute_force(p, aperture, sigma, k=901):
    """Grid over the beam's tangent-plane angles, rays intersected with the aperture."""
    w = np.asarray(aperture.centre) - p
    u = w / np.linalg.norm(w)
    e1 = np.cross([0, 0, 1.0], u)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    x = np.linspace(-7 * sigma, 7 * sigma, k)
    dx = x[1] - x[0]
    gx, gy = np.meshgrid(x, x, indexing="ij")
    dens = np.exp(-(gx**2 + gy**2) / (2 * sigma**2)) / (2 * np.pi * sigma**2) * dx * dx
    d = u + gx[..., None] * e1 + gy[..., None] * e2
    hit = np.asarray(intersect_plane(jnp.asarray(p), jnp.asarray(d), aperture).hit)
    return float((dens * hit).sum())


@pytest.mark.parametrize("sigma", [3e-3, 6e-3, 10e-3])
def test_intercept_matches_brute_force(sigma):
    ap = juelich_receiver()
    ana = np.asarray(intercept_efficiency(POSITIONS, ap, np.full(len(POSITIONS), sigma)))
    bf = np.array([_brute_force(p, ap, sigma) for p in POSITIONS])
    assert np.abs(ana - bf).max() < 1e-3
    assert ana.min() < 0.95  # the comparison includes real spillage


def test_intercept_off_centre_aim_and_tiny_target():
    # tiny aperture: intercept -> Gaussian density * area / projection
    from heliojax._geometry import TargetPlane

    c = np.array([0.0, 0.0, 50.0])
    tp = TargetPlane(
        centre=jnp.asarray(c),
        normal=jnp.array([0.0, 1, 0]),
        u_axis=jnp.array([-1.0, 0, 0]),
        v_axis=jnp.array([0.0, 0, 1]),
        half_width=jnp.asarray(0.05),
        half_height=jnp.asarray(0.05),
    )
    p = np.array([[0.0, 100.0, 50.0]])  # normal incidence, d = 100 m
    sigma = 5e-3
    got = float(intercept_efficiency(p, tp, np.array([sigma]))[0])
    spot = 100 * sigma
    expect = math.erf(0.05 / (spot * math.sqrt(2))) ** 2
    assert got == pytest.approx(expect, rel=1e-6)


def test_intercept_monotone_in_tracking_error():
    ap = juelich_receiver()
    track = np.linspace(0.0, 8.0, 41)
    for p in POSITIONS[2:5]:
        eta = np.asarray(intercept_efficiency(np.repeat(p[None], 41, 0), ap, beam_sigma(track, 1.5)))
        assert np.all(np.diff(eta) < 0)


def test_beam_sigma_factors():
    # per-axis variance: sun^2 + 2 slope^2 + tracking^2 / 2 (radial RMS inputs)
    assert float(beam_sigma(0.0, 0.0, 2.51)) == pytest.approx(2.51e-3)
    assert float(beam_sigma(2.0, 0.0, 0.0)) == pytest.approx(2.0e-3 / math.sqrt(2))
    assert float(beam_sigma(0.0, 1.0, 0.0)) == pytest.approx(math.sqrt(2) * 1e-3)
    # radial RMS of a 2-D isotropic Gaussian with per-axis s is s*sqrt(2)
    rng = np.random.default_rng(0)
    s = float(beam_sigma(2.0, 0.0, 0.0))
    xy = rng.normal(0, s, (200000, 2))
    assert math.sqrt((xy**2).sum(1).mean()) == pytest.approx(2.0e-3, rel=0.01)


def test_cosine_and_attenuation_and_dni_by_hand():
    # heliostat due north of the aim point at the same height, sun in the south at 30 deg
    pos = np.array([[0.0, 100.0, 0.0]])
    aim = np.array([0.0, 0.0, 0.0])
    el = math.radians(30)
    sun = np.array([[0.0, -math.cos(el), math.sin(el)]])
    # angle between sun and receiver direction = 30 deg -> cos(15 deg)
    assert float(cosine_efficiency(pos, aim, sun)[0, 0]) == pytest.approx(math.cos(math.radians(15)))
    assert float(atmospheric_attenuation(0.0)) == pytest.approx(0.99321)
    assert float(atmospheric_attenuation(1000.0)) == pytest.approx(0.99321 - 0.1176 + 0.0197)
    # Meinel at zenith: AM ~ 1 -> 1353 * 0.7 = 947 W/m2
    assert float(clear_sky_dni(math.pi / 2)) == pytest.approx(1353 * 0.7 ** (0.99972**0.678), rel=1e-3)
    assert float(clear_sky_dni(-0.1)) == 0.0


def test_receiver_from_tower_file(shared_paint):
    ap, plant = load_receiver(shared_paint / "WRI1030197-tower-measurements.json")
    ref = juelich_receiver()
    assert plant == pytest.approx(JUELICH_COORDINATES)
    for a, b in [(ap.centre, ref.centre), (ap.normal, ref.normal), (ap.u_axis, ref.u_axis)]:
        assert np.allclose(np.asarray(a), np.asarray(b), atol=1e-3)
    assert float(ap.half_width) * 2 == pytest.approx(4.53, abs=0.01)
    # the file's normal_vector [0, 0.906, -0.423]
    assert np.allclose(np.asarray(ap.normal), [0, 0.906, -0.423], atol=0.01)


def test_typical_year_and_field_efficiency():
    sun = typical_year(*JUELICH_COORDINATES, step_minutes=60)
    el = np.degrees(np.arcsin(sun.direction[:, 2]))
    # Jülich 50.9 N: noon elevation about 62.5 deg at the June solstice, 15.6 in December
    assert 61.5 < el[sun.month == 6].max() < 63.0
    assert 15.0 < el[sun.month == 12].max() < 18.0  # 1 Dec: declination -21.7 deg
    pos = np.array([[0.0, 50.0, 0.0], [30.0, 120.0, 0.0], [-80.0, 150.0, 0.0]])
    ap = juelich_receiver()
    good = field_efficiency(pos, ap, sun, tracking_mrad=np.full(3, 1.0), slope_mrad=1.5)
    bad = field_efficiency(pos, ap, sun, tracking_mrad=np.full(3, 6.0), slope_mrad=1.5)
    assert 0.6 < good.annual < 1.0 and bad.annual < good.annual
    assert np.all(bad.monthly < good.monthly)
    # north field: winter (low sun in the south) has the better cosine
    assert good.monthly[11] > good.monthly[5]
    # annual = DNI-weighted mean of the months
    w = good.dni_kwh_m2
    assert good.annual == pytest.approx(float((good.monthly * w).sum() / w.sum()), rel=1e-9)
    # reflectance and aperture scale linearly
    half = field_efficiency(
        pos,
        ap,
        sun,
        tracking_mrad=np.full(3, 1.0),
        slope_mrad=1.5,
        reflectance=0.5,
        aperture_m2=np.full(3, 4.0),
        reference_aperture_m2=8.0,
    )
    assert half.annual == pytest.approx(good.annual / 4, rel=1e-9)
