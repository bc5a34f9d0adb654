"""Surfaces: facet layouts, deflectometry IO, NURBS evaluation and fits."""

from __future__ import annotations

import json

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

from heliojax._errors import DataError
from heliojax.optics import (
    FacetLayout,
    NurbsFacets,
    bspline_basis,
    deflectometry_surface,
    fit_nurbs,
    ideal_surface,
    read_deflectometry,
    read_facet_layout,
    rms_normal_error_mrad,
    stack_deflectometry,
    write_deflectometry,
)

CANT = 0.0062  # rad, canting slope of the outer facets


def synthetic_facet(rng, n, centre, f=65.0, bump=1.5e-3):
    """Facet-local points/normals of a 1.6 x 1.25 m facet: canting tilt + focusing
    curvature about the heliostat centre + a Gaussian bump of max slope ~``bump``."""
    x = rng.uniform(-0.8, 0.8, n)
    y = rng.uniform(-0.625, 0.625, n)
    w = 0.25
    amp = bump * w * np.exp(0.5)  # max slope of a*exp(-r^2/(2 w^2)) is a / (w sqrt(e))
    bx, by = rng.uniform(-0.3, 0.3, 2)
    g = amp * np.exp(-((x - bx) ** 2 + (y - by) ** 2) / (2 * w**2))
    X, Y = x + centre[0], y + centre[1]
    z = (X**2 + Y**2) / (4 * f) - (centre[0] ** 2 + centre[1] ** 2) / (4 * f) + g
    zx = X / (2 * f) - g * (x - bx) / w**2
    zy = Y / (2 * f) - g * (y - by) / w**2
    nrm = np.stack([-zx, -zy, np.ones(n)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    return np.stack([x, y, z], -1), nrm


CENTRES = [(-0.8075, 0.6425), (0.8075, 0.6425), (-0.8075, -0.6425), (0.8075, -0.6425)]


@pytest.fixture
def deflectometry_file(tmp_path):
    rng = np.random.default_rng(0)
    facets = [synthetic_facet(rng, n, c) for n, c in zip((3000, 2500, 3300, 2800), CENTRES)]
    path = tmp_path / "AA39-deflectometry.h5"
    write_deflectometry(path, facets)
    return path, facets


def test_bspline_partition_of_unity_and_derivative():
    t = jnp.linspace(0, 1, 101)
    n, dn = bspline_basis(t, 7, 3)
    np.testing.assert_allclose(np.asarray(n).sum(-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(dn).sum(-1), 0.0, atol=1e-10)
    fd = (
        np.asarray(bspline_basis(t[1:-1] + 1e-6, 7, 3)[0]) - np.asarray(bspline_basis(t[1:-1] - 1e-6, 7, 3)[0])
    ) / 2e-6
    np.testing.assert_allclose(np.asarray(dn)[1:-1], fd, atol=1e-5)


def test_read_write_deflectometry_roundtrip(deflectometry_file):
    path, facets = deflectometry_file
    with h5py.File(path) as f:
        assert sorted(f.keys()) == ["facet1", "facet2", "facet3", "facet4"]
        assert f["facet1/surface_points"].dtype == np.float32
    d = read_deflectometry(path)
    assert d.points.shape == (4, 3300, 3)
    np.testing.assert_array_equal(np.asarray(d.counts()), [3000, 2500, 3300, 2800])
    np.testing.assert_allclose(np.asarray(d.points[1, :2500]), facets[1][0], atol=1e-6)
    assert not bool(d.mask[1, 2500])


def test_read_deflectometry_errors(tmp_path):
    bad = tmp_path / "bad.h5"
    with h5py.File(bad, "w") as f:
        f.create_group("facet1").create_dataset("surface_points", data=np.zeros((3, 3), np.float32))
    with pytest.raises(DataError, match="surface_normals"):
        read_deflectometry(bad)
    empty = tmp_path / "empty.h5"
    with h5py.File(empty, "w"):
        pass
    with pytest.raises(DataError, match="no facet groups"):
        read_deflectometry(empty)


def test_nurbs_fit_reproduces_normals_below_0p2_mrad(deflectometry_file):
    path, _ = deflectometry_file
    d = read_deflectometry(path)
    translations = jnp.asarray([[c[0], c[1], 0.0402] for c in CENTRES])
    facets = fit_nurbs(d, translations, n_ctrl=(8, 8))
    rms = float(rms_normal_error_mrad(facets, d))
    assert rms <= 0.2, rms
    # the ideal (flat canted) facets are far worse: the test measures something
    flat = fit_nurbs(d, translations, n_ctrl=(4, 4), degree=1)
    assert float(rms_normal_error_mrad(flat, d)) > 5 * rms
    # the evaluated patch carries the facet area
    surf = facets.evaluate((20, 20))
    assert float(surf.total_area()) == pytest.approx(4 * 1.6 * 1.25, rel=0.02)


def test_nurbs_fit_batched_over_heliostats_with_padding(deflectometry_file):
    path, facets = deflectometry_file
    d4 = read_deflectometry(path)
    from heliojax.optics import Deflectometry

    d2 = Deflectometry.from_facets(facets[:2])  # a heliostat with 2 facets, fewer points
    batch = stack_deflectometry([d4, d2])
    assert batch.points.shape == (2, 4, 3300, 3)
    t = jnp.asarray([[c[0], c[1], 0.0] for c in CENTRES])
    fb = fit_nurbs(batch, jnp.stack([t, t]))
    f2 = fit_nurbs(d2, t[:2])
    # float32 surfaces: agreement to ~1 ulp at the metre scale of the coordinates
    np.testing.assert_allclose(np.asarray(fb.control_points[1, :2]), np.asarray(f2.control_points), atol=1e-7)
    np.testing.assert_array_equal(np.asarray(fb.facet_mask), [[True] * 4, [True, True, False, False]])
    surf = fb.evaluate((8, 8))
    np.testing.assert_allclose(np.asarray(surf.total_area())[1], 2 * 1.6 * 1.25, rtol=0.02)


def test_ideal_nurbs_matches_ideal_surface(shared_paint):
    path = shared_paint / "flux-samples" / "AA39" / "Properties" / "AA39-heliostat-properties.json"
    lay = read_facet_layout(path)
    a = ideal_surface(lay, (10, 10))
    b = NurbsFacets.ideal(lay).evaluate((10, 10))
    np.testing.assert_allclose(np.asarray(a.points), np.asarray(b.points), atol=1e-9)
    np.testing.assert_allclose(np.asarray(a.normals), np.asarray(b.normals), atol=1e-9)
    np.testing.assert_allclose(np.asarray(a.areas), np.asarray(b.areas), rtol=1e-9)
    # PAINT AA39: 4 facets of 1.605 x 1.275 m, canted toward the centre
    assert float(a.total_area()) == pytest.approx(4 * 1.605 * 1.275, rel=1e-3)
    n = np.asarray(lay.normals())
    t = np.asarray(lay.translations)
    assert np.all(np.sign(n[:, 0]) == -np.sign(t[:, 0]))
    assert np.all(np.sign(n[:, 1]) == -np.sign(t[:, 1]))


def test_read_facet_layout_errors(tmp_path):
    p = tmp_path / "h.json"
    p.write_text(
        json.dumps(
            {
                "facet_properties": {
                    "facets": [{"translation_vector": [0, 0], "canting_e": [1, 0, 0], "canting_n": [0, 1, 0]}]
                }
            }
        )
    )
    with pytest.raises(DataError, match="translation_vector"):
        read_facet_layout(p)


def test_deflectometry_surface_areas(deflectometry_file):
    path, _ = deflectometry_file
    d = read_deflectometry(path)
    lay = FacetLayout.from_arrays([[c[0], c[1], 0.0] for c in CENTRES], [[0.8, 0, 0]] * 4, [[0, 0.625, 0]] * 4)
    s = deflectometry_surface(d, lay)
    assert s.points.shape == (4 * 3300, 3)
    assert float(s.total_area()) == pytest.approx(4 * 1.6 * 1.25, rel=1e-9)
    assert float(jnp.sum(s.areas > 0)) == 3000 + 2500 + 3300 + 2800
