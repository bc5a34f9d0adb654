"""Comparison of traced flux with PAINT's measured flux PNGs (real data)."""

from __future__ import annotations

import numpy as np
import pytest

from heliojax.optics._compare import (
    compare_record,
    flux_sample_records,
    normalised_cross_correlation,
    remove_background,
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
