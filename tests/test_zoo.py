"""The shared test zoo itself, and the fit core on every zoo fleet: converged
where there are records, NO_RECORDS where there are none, padding changes nothing."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import NOISE_MRAD, ZOO_NAMES, zoo

import heliojax as hj


@pytest.mark.parametrize("name", ZOO_NAMES)
def test_zoo_fleets_are_fleets(name):
    case = zoo(name)
    assert isinstance(case.fleet, hj.Fleet)
    h, m = case.fleet.mask.shape
    assert case.fleet.counts.shape == (h, m, 2)


def test_fit_on_the_zoo():
    model = hj.StoneModel.nominal(jnp.float64)
    plain = hj.fit(model, zoo("stone").fleet)
    assert plain.status_labels() == ["converged"] * 8
    # the noise estimate matches the simulated noise (2 * 24 residuals, 8 parameters: ~13 % scatter)
    assert np.all(np.abs(np.asarray(plain.noise_mrad) / NOISE_MRAD - 1.0) < 0.5)
    padded = hj.fit(model, zoo("padded").fleet)
    labels = padded.status_labels()
    assert labels[:8] == ["converged"] * 8 and set(labels[8:]) == {"no_records"}
    np.testing.assert_allclose(np.asarray(padded.parameters())[:8], np.asarray(plain.parameters()), atol=1e-12)
    empty = hj.fit(model, zoo("all_masked").fleet)
    assert set(empty.status_labels()) == {"no_records"}
