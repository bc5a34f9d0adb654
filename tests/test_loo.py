"""Leave-one-out errors of the fit core (FitSolution.loo_mrad) and the
calibration's "worse than nominal" flag built on them.

Independent reference: refitting without the record (the definition) for every
record of a small fleet."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import heliojax as hj
from heliojax._simulate import (
    calibration_target,
    random_stone_models,
    simulate_records,
    synthetic_contexts,
    synthetic_geometry,
)
from heliojax.discovery import simulate_fleet


def test_linearised_leave_one_out_equals_refits_without_the_record():
    fleet, _ = simulate_fleet(1, 2, 16, base="actuator", noise_mrad=0.5)
    model0 = hj.ActuatorModel.nominal()
    solution = hj.fit(model0, fleet)
    assert set(solution.status_labels()) == {"converged"}
    m = fleet.mask.shape[1]
    # One refit per left-out record, all in one batched fit: heliostat h, record k.
    drop = ~np.eye(m, dtype=bool)  # (K, M): row k leaves record k out
    per_heliostat = lambda f: (f.geometry, f.counts, f.context, f.focal_spot, f.record_id, f.mask)  # noqa: E731
    rep = eqx.tree_at(per_heliostat, fleet, jax.tree.map(lambda x: jnp.repeat(x, m, axis=0), per_heliostat(fleet)))
    rep = dataclasses.replace(rep, ids=tuple(f"{i}-{k}" for i in fleet.ids for k in range(m)))
    mask = jnp.asarray(np.tile(drop, (2, 1)) & np.repeat(np.asarray(fleet.mask), m, axis=0))
    refits = hj.fit(model0, rep, mask=mask)
    err = np.asarray(hj.fleet_residuals_mrad(refits.model, rep))  # (2 M, M, 2)
    left_out = np.linalg.norm(err[np.arange(2 * m), np.tile(np.arange(m), 2)], axis=-1).reshape(2, m)
    # The linearisation's error is second order in the parameter change (~1e-4 here).
    np.testing.assert_allclose(np.asarray(solution.loo_mrad), left_out, rtol=2e-3, atol=1e-4)
    # and it is an out-of-sample error: larger than the in-sample residual
    inside = np.linalg.norm(np.asarray(hj.fleet_residuals_mrad(solution.model, fleet)), axis=-1)
    assert np.all(np.asarray(solution.loo_mrad) >= inside - 1e-12)


def test_heliostats_that_are_already_nominal_are_flagged_worse_than_nominal(tmp_path):
    """Half the fleet truly follows the nominal model (its uncalibrated error is
    the noise), half has 1-3 mrad errors: only the first half may be flagged, and
    most of it is. (A calibrated nominal heliostat only adds the fitted noise: the
    expected PRESS excess is ~p/n of the noise power, ~10 % here, which the flag
    sees reliably from ~40 training records.)"""
    h, m = 16, 60
    k = jax.random.split(jax.random.PRNGKey(5), 4)
    geometry = synthetic_geometry(k[0], h)
    nominal = hj.broadcast_model(hj.StoneModel.nominal(), h)
    is_nominal = np.arange(h) < h // 2
    true = jax.tree.map(
        lambda a, b: jnp.where(jnp.asarray(is_nominal).reshape((h,) + (1,) * (a.ndim - 1)), a, b),
        nominal,
        random_stone_models(k[1], h, angle_sigma=1e-3),  # 1-3 mrad: every spot on the target
    )
    contexts = synthetic_contexts(k[2], h, m)
    fleet = simulate_records(k[3], true, geometry, contexts, calibration_target(), noise_mrad=0.3)
    run = hj.calibrate(fleet, model="stone8", split="time")
    flagged = np.array([run.summary["heliostats"][i]["worse_than_nominal"] for i in fleet.ids])
    assert all(run.summary["heliostats"][i]["status"] == "converged" for i in fleet.ids)
    assert not flagged[~is_nominal].any()
    assert flagged[is_nominal].mean() >= 0.75, flagged
    assert run.summary["fleet"]["worse_than_nominal"] == [i for i, f in zip(fleet.ids, flagged) if f]
    # the held-out flag: none of the heliostats with 1-3 mrad to correct; a nominal one
    # only by the sign test's chance (the calibrated and uncalibrated errors are alike)
    held_out = np.array([run.summary["heliostats"][i]["worse_than_nominal_held_out"] for i in fleet.ids])
    assert not held_out[~is_nominal].any() and held_out[is_nominal].sum() <= 1, held_out
    # results.h5 carries the flag; aiming does not use the flagged fits
    hj.write_results_h5(tmp_path / "results.h5", run)
    results = hj.load_results(tmp_path / "results.h5")
    np.testing.assert_array_equal(results.worse_than_nominal, flagged)
    np.testing.assert_array_equal(results.fitted, ~flagged)
    # every training record the fit used has its leave-one-out error; records before a
    # change point (a false alarm is allowed at the detector's rate) are not used
    used = run.train_mask & np.asarray(run.fleet.mask) & ~results.records["superseded"].astype(bool)
    np.testing.assert_array_equal(np.isfinite(results.records["loo_mrad"]), used)


def test_the_held_out_flag_is_a_one_sided_sign_test():
    """``worse_than_nominal_held_out``: the calibrated model misses by more than the
    uncalibrated one on significantly more than half of the held-out records (the
    binomial tail by hand); ties and records not held out take no part; never for a
    heliostat that did not converge."""
    from heliojax._workflow import HELD_OUT_WORSE_ALPHA, _worse_on_held_out
    from heliojax.fitting import FitStatus

    unc = np.full(20, 2.0)
    cal = np.where(np.arange(20) < 16, 3.0, 1.0)  # worse on 16 of 20: P(X >= 16) = 6196 / 2^20
    assert 6196 / 2**20 < HELD_OUT_WORSE_ALPHA
    note = _worse_on_held_out(FitStatus.CONVERGED, cal, unc)
    assert note is not None and "on 16 of 20 (sign test p = 0.0059" in note and "median 3 mrad against 2" in note
    cal_15 = np.where(np.arange(20) < 15, 3.0, 1.0)  # P(X >= 15) = 21700 / 2^20 = 0.0207
    assert _worse_on_held_out(FitStatus.CONVERGED, cal_15, unc) is None
    # ties and records without both errors leave the test: 16 of 20 again
    tied = np.concatenate([cal, [2.0, 2.0, np.nan]])
    assert "on 16 of 20" in _worse_on_held_out(FitStatus.CONVERGED, tied, np.concatenate([unc, [2.0, 2.0, 1.0]]))
    assert _worse_on_held_out(FitStatus.MAX_STEPS, cal, unc) is None
    assert _worse_on_held_out(FitStatus.CONVERGED, np.full(3, np.nan), unc[:3]) is None
