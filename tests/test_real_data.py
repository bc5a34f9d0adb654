"""Acceptance on the real shared PAINT records (../shared/data/paint)."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np
import pytest

import heliojax as hj


@pytest.fixture(scope="module")
def shared_fleet(shared_paint):
    return hj.load_paint_directory(shared_paint)


def _flagged_properties(fleet):
    return {Path(f.file).parts[-3] for f in fleet.report.flags if Path(f.file).parts[-2:-1] == ("Properties",)}


def test_uncalibrated_actuator_normals_point_up_and_south(shared_fleet):
    fleet = shared_fleet
    n_h = len([i for i in fleet.ids if i])
    models = hj.broadcast_model(hj.ActuatorModel.nominal(fleet.counts.dtype), fleet.n_heliostats)
    normals = jax.vmap(lambda m, g, c: jax.vmap(lambda ci: hj.forward(m, g, ci).normal)(c))(
        models, fleet.geometry, fleet.counts
    )
    mask = np.asarray(fleet.mask)
    bad = _flagged_properties(fleet)
    assert "BF41" in bad  # its anomalous actuator file is flagged in the load report
    checked = 0
    for i in range(n_h):
        if fleet.ids[i] == "BF41":
            continue
        n = np.asarray(normals[i])[mask[i]]
        assert np.all(n[:, 2] > 0.1), fleet.ids[i]  # up
        assert np.all(n[:, 1] < -0.3), fleet.ids[i]  # south, toward the tower
        checked += n.shape[0]
    assert checked > 1400


def _uncalibrated_errors(fleet):
    models = hj.broadcast_model(hj.ActuatorModel.nominal(fleet.counts.dtype), fleet.n_heliostats)
    return np.asarray(hj.fleet_beam_errors_mrad(models, fleet))


def test_uncalibrated_beam_errors_are_bounded(shared_fleet):
    err = _uncalibrated_errors(shared_fleet)
    ids = shared_fleet.ids
    meds = {ids[i]: float(np.nanmedian(err[i])) for i in range(len(ids)) if ids[i] and np.isfinite(err[i]).any()}
    assert meds["BF41"] > 1000  # the anomalous properties file (README: ~1.5 rad)
    rest = [v for k, v in meds.items() if k != "BF41"]
    assert np.median(rest) < 100.0


@pytest.mark.xfail(
    strict=True,
    reason=(
        "Issue 2 expects < 100 mrad for every record; measured: 9 of 26 heliostats (e.g. BF09 169, BK20 171, "
        "BG14 147 mrad median) exceed it because their PAINT axis-2 initial_angle is 2-5 deg off the value "
        "the records imply (constant per heliostat, scatter < 0.5 deg); see README 'Uncalibrated errors'."
    ),
)
def test_issue_bound_of_100_mrad_for_every_record(shared_fleet):
    err = _uncalibrated_errors(shared_fleet)
    ids = shared_fleet.ids
    keep = np.array([bool(h) and h != "BF41" for h in ids])
    assert np.nanmax(err[keep]) < 100.0


def test_calibration_recovers_bf41_from_fleet_typical_start(shared_fleet):
    fleet = hj.fleet_subset(shared_fleet, ["BF41", "BE36", "BF56", "BF57", "BH35"])
    run = hj.calibrate(fleet, model="actuator", split="time")
    s = run.summary["heliostats"]["BF41"]
    assert s["start_geometry"] == "fleet_typical"
    assert s["status"] == "converged"
    assert s["test_median_mrad"] < 5.0
    for h in ("BE36", "BF56", "BF57", "BH35"):
        assert run.summary["heliostats"][h]["test_median_mrad"] < 5.0


def test_only_broken_properties_give_way_to_the_fleet_typical_actuators(shared_fleet):
    """BF41's properties are broken (~1.5 rad off): its own robust fit's noise is
    hundreds of times the fit's from the fleet-typical actuators, and it starts from
    those. Proposed heliostats whose fit from the typical actuators is better by a few
    per cent only keep their own properties (``fitted_start_geometry``)."""
    import equinox as eqx

    fleet = shared_fleet
    model = hj.nominal_model("actuator")
    proposed, suggested, _ = hj.choose_start_geometry(fleet, model)
    own = np.asarray(hj.fitting.fit_robust(model, fleet).noise_mrad)
    alt_fleet = eqx.tree_at(lambda f: f.geometry, fleet, proposed)
    alt = np.asarray(hj.fitting.fit_robust(model, alt_fleet).noise_mrad)
    ids = np.array(fleet.ids)
    bf41 = list(ids).index("BF41")
    assert own[bf41] > 100 * alt[bf41]
    slightly_better = np.asarray(suggested) & (alt < own) & (own < 1.2 * alt)
    assert slightly_better.sum() >= 3  # the case this test is about occurs in these records
    _, replaced, _ = hj.fitted_start_geometry(model, fleet)
    assert list(ids[np.asarray(replaced)]) == ["BF41"]
