"""Calibration planning: the greedy I-optimal choice against brute force, the
operating envelope and its clear-sky weights against hand values, candidates that
aim at the targets, slots that exclude each other, and record roles for
``calibrate``."""

from __future__ import annotations

import logging
import typing

import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest

import heliojax as hj
from heliojax._workflow import roles_to_masks

LAT, LON, ALT = 50.913421122592574, 6.387824755874856, 87.0


def _integrated_variance(cov, m):
    return float(np.trace(cov @ m))


@pytest.mark.parametrize("per_candidate", [False, True], ids=["one_noise", "noise_per_candidate"])
def test_greedy_choice_matches_brute_force_in_information_form(per_candidate):
    rng = np.random.default_rng(3)
    f, k = 5, 12
    a = rng.normal(size=(f, f))
    cov = a @ a.T + 0.5 * np.eye(f)
    jac = rng.normal(size=(1, k, 2, f))
    b = rng.normal(size=(3 * f, f))
    m = b.T @ b / (3 * f)
    sigma = rng.uniform(0.3, 2.0, k) if per_candidate else np.full(k, 0.7)
    plan = hj.plan_measurements(
        jnp.asarray(cov[None]),
        jnp.asarray(jac),
        jnp.ones((1, k), bool),
        jnp.asarray(m[None]),
        jnp.asarray(sigma[None]) if per_candidate else 0.7,
        3,
    )
    chosen = np.asarray(plan.chosen)[0]
    info = np.linalg.inv(cov)
    expected_u = []
    for _ in range(3):  # brute force: every remaining candidate's posterior, information form
        left = [c for c in range(k) if c not in chosen[: len(expected_u)]]
        u = {c: _integrated_variance(np.linalg.inv(info + jac[0, c].T @ jac[0, c] / sigma[c] ** 2), m) for c in left}
        best = min(u, key=lambda c: u[c])
        assert best == chosen[len(expected_u)]
        info = info + jac[0, best].T @ jac[0, best] / sigma[best] ** 2
        expected_u.append(np.sqrt(u[best]))
    np.testing.assert_allclose(np.asarray(plan.uncertainty_after_mrad)[0], expected_u, rtol=1e-9)
    np.testing.assert_allclose(float(plan.uncertainty_before_mrad[0]), np.sqrt(np.trace(cov @ m)), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(plan.covariance_after)[0], np.linalg.inv(info), rtol=1e-8, atol=1e-12)


def _gls_posterior(cov, jac, sigma, day, rho, chosen):
    """The parameters' posterior covariance after records ``chosen`` whose residual
    components share a day effect: ``R = diag((1 - rho) sigma^2) + rho sigma sigma^T``
    between components of one index of records of one day (a dense solve)."""
    if not chosen:
        return cov
    rows = np.concatenate([jac[c] for c in chosen])  # (2n, F)
    rec = np.repeat(np.asarray(chosen), 2)
    comp = np.tile([0, 1], len(chosen))
    s = sigma[rec]
    same = (day[rec][:, None] == day[rec][None, :]) & (comp[:, None] == comp[None, :])
    r = np.diag((1.0 - rho) * s**2) + rho * np.outer(s, s) * same
    return np.linalg.inv(np.linalg.inv(cov) + rows.T @ np.linalg.solve(r, rows))


@pytest.mark.parametrize("rho", [0.0, 0.45, 0.9])
def test_greedy_choice_with_day_effects_matches_brute_force_generalised_least_squares(rho):
    """Records of one day share an error (variance ``rho sigma^2``): each step's choice
    and the covariance after it against the dense GLS posterior of every remaining
    candidate (4 days, noise per candidate)."""
    rng = np.random.default_rng(5)
    f, k, budget = 5, 14, 7
    a = rng.normal(size=(f, f))
    cov = a @ a.T + 0.5 * np.eye(f)
    jac = rng.normal(size=(k, 2, f))
    b = rng.normal(size=(3 * f, f))
    m = b.T @ b / (3 * f)
    sigma = rng.uniform(0.4, 1.2, k)
    day = rng.integers(0, 4, k) * 86400 + 20000  # any integer labels
    plan = hj.plan_measurements(
        jnp.asarray(cov[None]),
        jnp.asarray(jac[None]),
        jnp.ones((1, k), bool),
        jnp.asarray(m[None]),
        jnp.asarray(sigma[None]),
        budget,
        day=day[None],
        day_correlation=rho,
    )
    chosen = [int(c) for c in np.asarray(plan.chosen)[0]]
    expected_u = []
    for step in range(budget):
        left = [c for c in range(k) if c not in chosen[:step]]
        u = {c: _integrated_variance(_gls_posterior(cov, jac, sigma, day, rho, [*chosen[:step], c]), m) for c in left}
        assert min(u, key=lambda c: u[c]) == chosen[step]
        expected_u.append(np.sqrt(u[chosen[step]]))
    np.testing.assert_allclose(np.asarray(plan.uncertainty_after_mrad)[0], expected_u, rtol=1e-9)
    posterior = _gls_posterior(cov, jac, sigma, day, rho, chosen)
    np.testing.assert_allclose(np.asarray(plan.covariance_after)[0], posterior, rtol=1e-8, atol=1e-12)


def test_a_shared_day_error_spreads_the_plan_over_days():
    """Six copies of one informative pose on day 0, six slightly weaker ones on day 1:
    taking records as independent, the plan stays on day 0; with a day effect, its
    second record is on the other day."""
    rng = np.random.default_rng(6)
    f, k = 3, 12
    base = rng.normal(size=(2, f))
    jac = np.stack([base * (1.0 if c < 6 else 0.9) + 0.01 * rng.normal(size=(2, f)) for c in range(k)])
    day = np.repeat([0, 1], 6)
    args = (jnp.eye(f)[None], jnp.asarray(jac[None]), jnp.ones((1, k), bool), jnp.eye(f)[None], 0.5, 4)
    independent = np.asarray(hj.plan_measurements(*args, day=day[None], day_correlation=0.0).chosen)[0]
    shared = np.asarray(hj.plan_measurements(*args, day=day[None], day_correlation=0.8).chosen)[0]
    assert (day[independent[:2]] == 0).all()
    assert set(day[shared[:2]]) == {0, 1}
    plain = np.asarray(hj.plan_measurements(*args).chosen)[0]
    np.testing.assert_array_equal(independent, plain)  # rho = 0 is the plan without days
    with pytest.raises(ValueError, match=r"day_correlation must be in \[0, 1\)"):
        hj.plan_measurements(*args, day=day[None], day_correlation=1.0)


def test_slots_exclude_each_other_and_invalid_candidates_are_never_chosen():
    rng = np.random.default_rng(4)
    f, k = 4, 10
    jac = jnp.asarray(rng.normal(size=(2, k, 2, f)))
    cov = jnp.broadcast_to(jnp.eye(f), (2, f, f))
    m = jnp.broadcast_to(jnp.eye(f), (2, f, f))
    slot = jnp.asarray(np.broadcast_to(np.arange(k) // 2, (2, k)).astype(np.int32))
    valid = jnp.asarray(np.array([[True] * k, [True, False] * 5]))
    plan = hj.plan_measurements(cov, jac, valid, m, jnp.array([0.5, 0.5]), 6, slot=slot)
    chosen = np.asarray(plan.chosen)
    for i in range(2):
        picked = chosen[i][chosen[i] >= 0]
        assert len(set(np.asarray(slot)[i][picked])) == len(picked)  # one candidate per slot
        assert np.asarray(valid)[i][picked].all()
    assert (chosen[0] >= 0).sum() == 5  # 5 slots
    assert (chosen[1] >= 0).sum() == 5 and (chosen[1][5:] == -1).all()
    u = np.asarray(plan.uncertainty_after_mrad)
    assert np.all(np.diff(u, axis=1) <= 1e-12)


def test_aged_noise_grows_with_the_age_at_the_use_time():
    day = 86400.0
    times = np.array([[0.0, 10 * day, 20 * day, np.nan], [5 * day, 0.0, 30 * day, 1 * day]])
    valid = np.array([[True, True, True, True], [True, True, False, True]])
    got = hj.aged_noise_mrad(np.array([0.5, 0.2]), 0.01, times, valid)
    # the use time defaults to each heliostat's latest valid candidate: day 20 and day 5
    # (the invalid candidate at day 30 neither sets it nor is aged)
    expected = np.sqrt(np.array([[0.25 + 0.2, 0.25 + 0.1, 0.25, 0.25], [0.04, 0.04 + 0.05, 0.04, 0.04 + 0.04]]))
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    np.testing.assert_allclose(hj.aged_noise_mrad(0.3, 0.0, times, valid), 0.3, rtol=0)
    later = hj.aged_noise_mrad(0.5, 0.01, times[:1], valid[:1], use_unix_time=30 * day)
    np.testing.assert_allclose(later[0, :3] ** 2, 0.25 + 0.01 * np.array([30.0, 20.0, 10.0]), rtol=1e-12)
    with pytest.raises(ValueError, match="drift_mrad2_per_day"):
        hj.aged_noise_mrad(0.5, -1.0, times, valid)
    # the creep (variance c a^2 at age a days) beside the walk
    crept = hj.aged_noise_mrad(0.5, 0.01, times[:1], valid[:1], use_unix_time=30 * day, creep_mrad2_per_day2=1e-3)
    age = np.array([30.0, 20.0, 10.0])
    np.testing.assert_allclose(crept[0, :3] ** 2, 0.25 + 0.01 * age + 1e-3 * age**2, rtol=1e-12)
    np.testing.assert_allclose(crept[0, 3], 0.5, rtol=0)  # unknown time: age 0
    with pytest.raises(ValueError, match="creep_mrad2_per_day2"):
        hj.aged_noise_mrad(0.5, 0.0, times, valid, creep_mrad2_per_day2=float("nan"))


def test_clear_sky_dni_hand_values():
    # Meinel with Kasten-Young air mass: zenith sun AM = 1/(1 + 0.50572 * 96.07995^-1.6364) = 0.99972
    am_zenith = 1.0 / (1.0 + 0.50572 * 96.07995**-1.6364)
    np.testing.assert_allclose(hj.clear_sky_dni(np.pi / 2), 1361.0 * 0.7 ** (am_zenith**0.678), rtol=1e-12)
    assert abs(float(hj.clear_sky_dni(np.pi / 2)) - 952.8) < 0.5  # ~ 1361 * 0.7
    # 30 deg elevation: AM ~ 1.994 -> 0.7^(1.994^0.678) = 0.7^1.596 = 0.566
    assert 765.0 < float(hj.clear_sky_dni(np.radians(30.0))) < 775.0
    assert float(hj.clear_sky_dni(np.radians(-1.0))) == 0.0


def test_operating_envelope_is_above_the_limit_and_weighted_by_dni():
    sun, weight = hj.operating_envelope(np.array([LAT, LON, ALT]), day_step=30, min_elevation_deg=15.0)
    el = np.degrees(np.arcsin(np.asarray(sun)[:, 2]))
    assert el.min() > 15.0 and el.max() < 90.0 - LAT + 23.5 + 0.5  # noon sun at the summer solstice
    np.testing.assert_allclose(np.linalg.norm(np.asarray(sun), axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(weight), hj.clear_sky_dni(np.radians(el)), rtol=1e-10)
    assert 13 * 6 < sun.shape[0] < 13 * 16  # 13 days, 6-16 hours above 15 deg at 51 N


def _fleet_of_four():
    """Four Jülich-like heliostats with true actuator models off nominal by ~2 solver scales."""
    geometry = hj.synthetic_geometry(jax.random.key(5), 4)
    base = hj.broadcast_model(hj.nominal_model("actuator"), 4)
    view = hj.ParameterView.of(base)
    p = np.asarray(jax.vmap(view.to_vector)(base))
    step = np.zeros_like(p)
    step[:, list(view.free_index)] = (
        2.0 * np.asarray(view.free_scales(jnp.float64)) * np.random.default_rng(5).normal(size=(4, view.n_free))
    )
    return jax.vmap(view.from_vector)(base, jnp.asarray(p + step)), geometry, view


def test_candidates_aim_at_the_targets_and_plans_reduce_uncertainty():
    truth, geometry, view = _fleet_of_four()
    target = hj.calibration_target()
    unix = 1687330800.0 + np.arange(0.0, 12 * 3600.0, 3600.0)  # 2023-06-21 07:00 UTC on
    sun = hj.solar_position(jnp.asarray(unix), LAT, LON, ALT).direction_enu()
    centres = jnp.stack([target.centre, target.centre + jnp.array([0.0, 0.0, 8.0])])
    cand = hj.candidates_at_targets(truth, geometry, sun, centres, unix_time=unix)
    assert cand.counts.shape == (4, 24, 2)
    valid = np.asarray(cand.valid)
    assert valid.mean() > 0.5
    np.testing.assert_array_equal(np.asarray(cand.slot)[0], np.repeat(np.arange(12), 2))
    # each candidate carries its target (the fleet's index, for target-dependent effects)
    np.testing.assert_array_equal(np.asarray(cand.context.target), -1)  # unknown unless given
    named = hj.candidates_at_targets(truth, geometry, sun, centres, unix_time=unix, target_index=np.array([1, -1]))
    np.testing.assert_array_equal(np.asarray(named.context.target), np.tile([1, -1], (4, 12)))
    np.testing.assert_array_equal(np.asarray(named.counts), np.asarray(cand.counts))
    with pytest.raises((ValueError, jaxtyping.TypeCheckError), match="one per target centre|target_index"):
        hj.candidates_at_targets(truth, geometry, sun, centres, target_index=np.array([0]))

    # the candidate counts point the true beam at the target centre
    @jax.jit
    def miss(truth, geometry, counts, context, spots):
        def one(model, g, c, x, f):
            return jax.vmap(lambda ci, xi, fi: model.beam_error(g, ci, xi, fi))(c, x, f) * 1e3

        return jax.vmap(one)(truth, geometry, counts, context, spots)

    err = np.asarray(miss(truth, geometry, cand.counts, cand.context, cand.spots))
    assert np.all(err[valid] < 1e-6)

    # the envelope matrix equals the weighted sum of the Jacobians at the counts that aim
    # there (candidates of the same shapes aimed at the aim point, so no new program)
    aim = target.centre + jnp.array([0.0, 0.0, 8.0])
    sun_e = jnp.repeat(sun, 2, axis=0)
    w_e = jnp.asarray(np.linspace(1.0, 2.0, 24))
    m = hj.envelope_matrices(truth, view, geometry, sun_e, w_e, aim, batch_size=3)
    at_aim = hj.candidates_at_targets(truth, geometry, sun, jnp.stack([aim, aim]))
    all_on = jnp.ones((4, 24), bool)
    jac_e = hj.residual_jacobians(truth, view, geometry, at_aim.counts, at_aim.context, at_aim.spots, all_on)
    np.testing.assert_allclose(np.asarray(m), np.asarray(hj.envelope_matrix(jac_e, w_e)), rtol=1e-9, atol=1e-12)

    cov = jnp.broadcast_to(jnp.diag(view.free_scales(jnp.float64) ** 2), (4, view.n_free, view.n_free))
    jac = hj.residual_jacobians(truth, view, geometry, cand.counts, cand.context, cand.spots, cand.valid)
    plan = hj.plan_measurements(cov, jac, cand.valid, m, 0.5, 4, slot=cand.slot)
    before = np.asarray(plan.uncertainty_before_mrad)
    after = np.asarray(plan.uncertainty_after_mrad)
    assert np.all(after[:, -1] < 0.5 * before)
    np.testing.assert_allclose(before, np.asarray(hj.predicted_uncertainty_mrad(cov, m)), rtol=1e-12)

    # planning for a model that is not exact: with a discrepancy of amplitude 0 the plan is
    # the exact-model plan; with one, the parameters' block of the envelope matrix is still M
    # and the predicted uncertainty adds the discrepancy's
    f = view.n_free
    for amplitude in (0.0, 0.5):
        process = hj.ModelDiscrepancy(amplitude_mrad=amplitude, length=0.2)
        design = hj.discrepancy_design(process, geometry, cov, jac, cand, sun_e, aim, inducing=8)
        assert design.covariance.shape == (4, f + 16, f + 16)
        assert design.candidate_jacobians.shape == (4, 24, 2, f + 16)
        m_d = hj.envelope_matrices(
            truth, view, geometry, sun_e, w_e, aim, discrepancy=process, inducing=design.inducing, batch_size=3
        )
        np.testing.assert_allclose(np.asarray(m_d)[:, :f, :f], np.asarray(m), rtol=1e-9, atol=1e-12)
        plan_d = hj.plan_measurements(
            design.covariance, design.candidate_jacobians, cand.valid, m_d, 0.5, 4, slot=cand.slot
        )
        if amplitude == 0.0:
            np.testing.assert_array_equal(np.asarray(plan_d.chosen), np.asarray(plan.chosen))
            np.testing.assert_allclose(np.asarray(plan_d.uncertainty_after_mrad), after, rtol=1e-9)
        else:
            assert np.all(np.asarray(plan_d.uncertainty_before_mrad) > before)
            assert np.all(np.asarray(plan_d.uncertainty_before_mrad) ** 2 <= before**2 + 0.5**2 * 2 * (1 + 1e-6))


def test_record_roles_choose_the_training_and_held_out_records(caplog):
    fleet = hj.load_paint_directory(hj.default_data_dir())
    rid = np.asarray(fleet.record_id)
    mask = np.asarray(fleet.mask)
    hid = fleet.ids[0]
    chosen = [int(r) for r in rid[0][mask[0]][:5]]
    train, test = roles_to_masks(fleet, {hid: {r: "train" for r in chosen}})
    assert train.sum() == 5 and set(rid[0][train[0]]) == set(chosen)
    np.testing.assert_array_equal(test, mask & ~train)  # no test role: everything else is held out
    train, test = roles_to_masks(fleet, {hid: {chosen[0]: "train", chosen[1]: "test"}})
    assert train.sum() == 1 and test.sum() == 1
    # another heliostat trained without a held-out record while this one has one: named
    other = [int(r) for r in rid[1][mask[1]][:3]]
    with caplog.at_level(logging.WARNING, logger="heliojax._workflow"):
        train, test = roles_to_masks(fleet, {hid: {chosen[1]: "test"}, fleet.ids[1]: {other[0]: "train"}})
    assert not test[1].any() and f"{fleet.ids[1]} ({int(mask[1].sum()) - 1})" in caplog.text
    caplog.clear()
    every = {int(r): "train" for r in rid[1][mask[1]]}  # all of its records train: none left out, none held out
    with caplog.at_level(logging.WARNING, logger="heliojax._workflow"):
        roles_to_masks(fleet, {hid: {chosen[1]: "test"}, fleet.ids[1]: every})
    assert f"{fleet.ids[1]} (0)" in caplog.text
    with pytest.raises(hj.ConfigError, match="BX99"):
        roles_to_masks(fleet, {"BX99": {1: "train"}})
    with pytest.raises(hj.ConfigError, match="record 1 of"):
        roles_to_masks(fleet, {hid: {1: "train"}})
    with pytest.raises(hj.ConfigError, match="role 'fit'"):
        roles_to_masks(fleet, {hid: {chosen[0]: "fit"}})
    with pytest.raises(hj.ConfigError, match="no record has the role train"):
        roles_to_masks(fleet, {})
    with pytest.raises(hj.ConfigError, match="start must be one of auto, nominal, not 'fleet_typical'"):
        hj.calibrate(fleet, start="fleet_typical")  # was taken for "nominal"


def test_ill_typed_record_roles_are_named_not_truncated(unchecked):
    """Without run-time type checks (as a user runs): a list for a heliostat's roles, a
    record id that is not whole (118671.9 was truncated to 118671), a list for all roles."""
    fleet = hj.load_paint_directory(hj.default_data_dir())
    hid = fleet.ids[0]
    chosen = [int(r) for r in np.asarray(fleet.record_id)[0][np.asarray(fleet.mask)[0]][:2]]
    roles: typing.Any = {hid: chosen}
    with pytest.raises(hj.ConfigError, match="not a list"):
        roles_to_masks(fleet, roles)
    roles = {hid: {chosen[0] + 0.9: "train"}}
    with pytest.raises(hj.ConfigError, match="not a whole number"):
        roles_to_masks(fleet, roles)
    with pytest.raises(hj.ConfigError, match="record_roles must map"):
        hj.calibrate(fleet, record_roles=typing.cast(typing.Any, [hid]))
