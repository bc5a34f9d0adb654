"""Change points (heliojax.fitting.find_change_points) on simulated fleets with
planted jumps of the axis offsets at a random date, beside clean heliostats.

Independent of the detector: the truth is two simulations of the same records
(before / after the planted date) spliced by time."""

from __future__ import annotations

import datetime

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax._simulate import calibration_target, simulate_records, synthetic_contexts, synthetic_geometry
from heliojax.discovery._suites import random_actuator_models

DAY = 86400.0


def _stepped_fleet(seed: int, h: int = 40, m: int = 40, noise_mrad: float = 0.25, drift: bool = False):
    """Half the heliostats get a jump of both angle offsets (norm 1.5-3 mrad) at a
    random record time (between the 25 % and 75 % points of their records). With
    ``drift`` they get no jump but a linear drift of the offsets by that much from
    their first record to their last (the spots interpolated in time between the
    two simulations: linear in the offsets to second order, ~1e-6 mrad)."""
    k = jax.random.split(jax.random.PRNGKey(seed), 4)
    rng = np.random.default_rng(seed)
    geometry = synthetic_geometry(k[0], h)
    before = random_actuator_models(k[1], h, angle_sigma=1e-3)
    stepped = np.arange(h) < h // 2
    direction = rng.normal(size=(h, 2))
    jump = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(1.5e-3, 3e-3, (h, 1))
    jump[~stepped] = 0.0
    after = eqx.tree_at(lambda mm: mm.angle_offset, before, before.angle_offset + jnp.asarray(jump))
    contexts = synthetic_contexts(k[2], h, m)
    target = calibration_target()
    # The plant aims with the pre-change state throughout (same counts in both).
    a = simulate_records(k[3], before, geometry, contexts, target, controller_models=before, noise_mrad=noise_mrad)
    b = simulate_records(k[3], after, geometry, contexts, target, controller_models=before, noise_mrad=noise_mrad)
    t = np.asarray(contexts.unix_time)
    change = np.array([rng.choice(np.sort(t[i])[m // 4 : 3 * m // 4]) for i in range(h)])
    later = t >= change[:, None]
    spot = np.where(later[..., None], np.asarray(b.focal_spot), np.asarray(a.focal_spot))
    if drift:
        frac = (t - t.min(axis=1, keepdims=True)) / np.ptp(t, axis=1, keepdims=True)
        spot = np.asarray(a.focal_spot) + frac[..., None] * (np.asarray(b.focal_spot) - np.asarray(a.focal_spot))
    fleet = eqx.tree_at(lambda f: (f.focal_spot, f.mask), a, (jnp.asarray(spot), a.mask & b.mask))
    return fleet, stepped, change, jump * 1e3


def test_planted_jumps_are_found_and_dated_and_clean_heliostats_are_left_alone():
    found, dated, clean_flags, jump_err, steps = [], [], [], [], []
    for seed in (1, 2):
        fleet, stepped, change, jump = _stepped_fleet(seed)
        robust = hj.fitting.fit_robust(hj.ActuatorModel.nominal(), fleet)
        cp = hj.fitting.find_change_points(robust.solution, fleet, fleet.mask, robust.weights)
        f = np.asarray(cp.found)
        found += list(f[stepped])
        clean_flags += list(f[~stepped])
        t0, t1 = np.asarray(cp.previous_time_s), np.asarray(cp.time_s)
        ok = (t0 < change) & (change <= t1) | (np.abs(t1 - change) <= 10 * DAY)
        dated += list(ok[stepped & f])
        jump_err += list(np.linalg.norm(np.asarray(cp.jump_mrad) - jump, axis=1)[stepped & f])
        steps += list(np.asarray(cp.is_step)[stepped & f])  # labelled steps, not drifts
    assert np.mean(found) >= 0.9, np.mean(found)
    assert np.mean(dated) >= 0.9, np.mean(dated)
    assert np.mean(clean_flags) <= 0.05, np.mean(clean_flags)
    assert np.median(jump_err) < 0.3, np.median(jump_err)
    assert np.mean(steps) >= 0.9, np.mean(steps)


def test_a_linear_drift_of_the_offsets_is_a_change_labelled_drift():
    """Offsets that creep by 1.5-3 mrad over the records (a drift, not a jump): found as
    changes of state, but labelled drifts (``is_step`` false: a linear drift of the
    offsets fits as well, by BIC), so discovery does not split them; clean heliostats
    get neither."""
    fleet, drifting, _, _ = _stepped_fleet(3, drift=True)
    robust = hj.fitting.fit_robust(hj.ActuatorModel.nominal(), fleet)
    cp = hj.fitting.find_change_points(robust.solution, fleet, fleet.mask, robust.weights)
    f, step = np.asarray(cp.found), np.asarray(cp.is_step)
    assert np.mean(f[drifting]) >= 0.9, np.mean(f[drifting])
    assert np.mean(f[~drifting]) <= 0.05, np.mean(f[~drifting])
    assert np.mean(step[drifting]) <= 0.1, np.mean(step[drifting])
    assert np.all(np.asarray(cp.drift_delta_chi2)[drifting] > np.asarray(cp.threshold)[drifting])


@pytest.mark.parametrize(("jump_is_base", "undated"), [(False, 2), (True, 0), (True, 2)])
def test_jump_scan_matches_a_least_squares_solve_per_candidate(jump_is_base, undated):
    """The suffix-sum scan against the definition: per candidate date, numpy's lstsq of
    the base design with the two jump columns on the records at or after that date
    (records with tied times, unused records, used records without a time, and a
    rank-deficient base column). With
    ``jump_is_base`` the jump columns are two of the base columns, as in the detector:
    with every record dated, a step at the first date duplicates them and lowers
    nothing. ``undated`` used records have no time (NaN)."""
    from heliojax.fitting._changes import jump_scan

    rng = np.random.default_rng(3)
    m, f = 30, 6
    base = rng.normal(size=(m, 2, f))
    base[..., 5] = base[..., 4]  # rank-deficient base design
    jump = base[..., :2].copy() if jump_is_base else rng.normal(size=(m, 2, 2))
    residual = rng.normal(size=(m, 2))
    time = rng.integers(0, 12, m).astype(float)  # ties
    use = rng.random(m) > 0.15
    time = np.where(use, time, np.inf)
    time[np.flatnonzero(use)[:undated]] = np.nan  # used records without a time: never after a date
    rss0, (coef, drop), n_after = jax.jit(jump_scan)(base, jump, residual, time, use)

    w = use[:, None, None]
    design0 = (base * w).reshape(2 * m, f)
    rr = (residual * use[:, None]).reshape(-1)
    x0, *_ = np.linalg.lstsq(design0, rr, rcond=None)
    want_rss0 = np.sum((rr - design0 @ x0) ** 2)
    np.testing.assert_allclose(float(rss0), want_rss0, rtol=1e-10)
    compared = 0
    for c in range(m):
        after = use & (time >= time[c])
        assert int(n_after[c]) == after.sum()
        design = np.concatenate([design0, (jump * after[:, None, None]).reshape(2 * m, 2)], axis=1)
        x, *_ = np.linalg.lstsq(design, rr, rcond=None)
        want_drop = want_rss0 - np.sum((rr - design @ x) ** 2)
        if after.sum() == 0 or (jump_is_base and not undated and after.sum() == use.sum()):
            assert float(drop[c]) == 0.0 and np.all(np.asarray(coef[c]) == 0.0)
            assert abs(want_drop) < 1e-9 * want_rss0
            continue
        np.testing.assert_allclose(float(drop[c]), want_drop, rtol=1e-8, atol=1e-10 * want_rss0)
        np.testing.assert_allclose(np.asarray(coef[c]), x[-2:], rtol=1e-7, atol=1e-9)
        compared += 1
    assert compared >= m // 2


def test_a_run_of_gross_errors_at_the_end_is_warned_about():
    """Heliostat 0's latest 3 training records all sit 15 mrad off in one direction (a
    change that has just started: too few records after it for a change point). The
    robust fit flags them; summary.json warns about heliostat 0 alone, with the run's
    length, start and size; the clean fleet gets no warning."""
    h, m = 6, 40
    k = jax.random.split(jax.random.PRNGKey(8), 3)
    geometry = synthetic_geometry(k[0], h)
    contexts = synthetic_contexts(k[1], h, m)
    fleet = simulate_records(k[2], hj.broadcast_model(hj.StoneModel.nominal(), h), geometry, contexts,
                             calibration_target(), noise_mrad=0.3)  # fmt: skip
    clean = hj.calibrate(fleet, model="stone8", split="time")
    assert all(e["warning"] is None for e in clean.summary["heliostats"].values())
    t = np.asarray(fleet.context.unix_time)
    latest = np.argsort(np.where(clean.train_mask[0, :m], t[0], -np.inf))[::-1][:3]  # the run's fleet is padded
    spot = np.array(fleet.focal_spot)
    d = spot[0, latest] - np.asarray(geometry.position)[0]
    side = np.cross(d, [0.0, 0.0, 1.0])
    spot[0, latest] += side / np.linalg.norm(side, axis=-1, keepdims=True) * np.linalg.norm(d, axis=-1)[:, None] * 15e-3
    moved = eqx.tree_at(lambda f: f.focal_spot, fleet, jnp.asarray(spot))
    s = hj.calibrate(moved, model="stone8", split="time").summary["heliostats"]
    first = s[fleet.ids[0]]
    assert first["recent_outliers"] == 3 and "measure it again" in first["warning"]
    assert abs(first["recent_outliers_median_mrad"] - 15.0) < 1.5
    since = datetime.datetime.fromtimestamp(t[0, latest[-1]], tz=datetime.UTC)
    assert first["recent_outliers_since"] == since.strftime("%Y-%m-%dT%H:%M:%S") + "Z"
    assert all(s[i]["warning"] is None and s[i]["recent_outliers"] <= 1 for i in fleet.ids[1:])


def test_a_change_between_two_campaigns_is_undecided_and_rivals_a_per_heliostat_name():
    """Each heliostat's records in two campaigns ten years apart, half the fleet's planted
    jump in the gap: a step and a linear drift of the offsets fit such records alike,
    so discovery's pre-pass keeps the change as a change point where the step's fit is
    better by the BIC and marks it undecided where neither fits better by the BIC's
    margin (the noise decides: the two fits' evidence differed by -4 to +6 here);
    clean heliostats get neither, and offsets that drift through continuous records
    are not undecided. A per-heliostat effect significant only in
    undecided heliostats has the change point as its rival (``change_point_rival``)."""
    from heliojax.discovery._cleaning import change_point_rival, clean
    from heliojax.discovery._report import _alternative_words

    fleet, stepped, change, _ = _stepped_fleet(1)
    t = np.asarray(fleet.context.unix_time)
    campaigns = eqx.tree_at(
        lambda f: f.context.unix_time, fleet, jnp.asarray(np.where(t >= change[:, None], t + 3650 * DAY, t))
    )
    out = clean(hj.ActuatorModel.nominal(), campaigns, 0.01)
    assert out.undecided is not None
    changed = out.change_found | out.undecided
    assert np.mean(changed[stepped]) >= 0.9, np.mean(changed[stepped])
    assert np.mean(changed[~stepped]) <= 0.05, np.mean(changed[~stepped])
    assert not np.any(out.change_found & out.undecided)
    drifting_fleet, drifting, _, _ = _stepped_fleet(3, drift=True)
    drifting_out = clean(hj.ActuatorModel.nominal(), drifting_fleet, 0.01)
    assert drifting_out.undecided is not None and np.mean(drifting_out.undecided[drifting]) <= 0.1

    ids = list(campaigns.ids)
    undecided = [ids[i] for i in np.flatnonzero(out.undecided)]
    assert undecided, "no undecided change to test the rival with"
    rival = change_point_rival(out, undecided[:1], ids)
    assert rival is not None and rival["effect"] == "change_point" and rival["heliostats"] == undecided[:1]
    assert rival["p"] == out.change_p_holm[ids.index(undecided[0])]
    decided = [ids[i] for i in np.flatnonzero(~out.undecided)]
    assert change_point_rival(out, undecided[:1] + decided[:1], ids) is None  # one significant elsewhere
    assert change_point_rival(out, [], ids) is None
    words = _alternative_words(rival)  # the Markdown report's wording of the rival
    assert f"a change of state of {undecided[0]}" in words and "a step and a drift" in words
