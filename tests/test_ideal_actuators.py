"""Ideal actuators (PAINT ``type_axis == "ideal"``, e.g. AC43): they load, the
actuator model uses the linear counts-to-angle map on them, and a fleet that mixes
both kinds is fitted in one program."""

from __future__ import annotations

import shutil

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from helpers import zoo

import heliojax as hj


def _flux_sample_dir(shared_paint, tmp_path):
    root = tmp_path / "paint"
    root.mkdir()
    shutil.copy(shared_paint / "WRI1030197-tower-measurements.json", root)
    for h in ("AA39", "AC43"):
        shutil.copytree(shared_paint / "flux-samples" / h, root / h)
    return root


def test_ac43_loads_with_ideal_axes(shared_paint, tmp_path):
    fleet = hj.load_paint_directory(_flux_sample_dir(shared_paint, tmp_path))
    assert fleet.ids == ("AA39", "AC43")
    np.testing.assert_array_equal(np.asarray(fleet.geometry.ideal_axes), [[False, False], [True, True]])
    # on ideal axes the actuator model's nominal map is the Stone model's (linear) one
    act = hj.fleet_beam_errors_mrad(hj.ActuatorModel.nominal(jnp.float64), fleet)
    stone = hj.fleet_beam_errors_mrad(hj.StoneModel.nominal(jnp.float64), fleet)
    ok = np.isfinite(np.asarray(act[1]))
    assert ok.sum() == 2
    np.testing.assert_allclose(np.asarray(act[1])[ok], np.asarray(stone[1])[ok], rtol=1e-12)
    assert not np.allclose(np.asarray(act[0])[:3], np.asarray(stone[0])[:3])


def test_mixed_fleet_fits_in_one_program():
    """Half the heliostats declare ideal actuators: data simulated by the Stone model
    there and by the actuator model elsewhere are fitted by one actuator model."""
    case = zoo("stone")
    fleet = case.fleet
    h = fleet.n_heliostats
    ideal = jnp.broadcast_to((jnp.arange(h) % 2 == 0)[:, None], (h, 2))
    geometry = eqx.tree_at(lambda g: g.ideal_axes, fleet.geometry, ideal)
    mixed = eqx.tree_at(lambda f: f.geometry, fleet, geometry)
    sol = hj.fit(hj.ActuatorModel.nominal(jnp.float64), mixed)
    labels = sol.status_labels()
    # the Stone truth is representable exactly on the ideal heliostats only
    rms = np.asarray(sol.rms_mrad)
    even = np.arange(h) % 2 == 0
    assert all(lab == "converged" for lab, e in zip(labels, even) if e)
    assert np.all(rms[even] < 0.4)  # 0.2 mrad per component noise -> ~0.28 mrad RMS
    assert np.median(rms[~even]) > 1.0  # a linear truth through the law of cosines: misfit
