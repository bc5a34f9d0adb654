"""Discovery on data with gross errors, steps and effects outside the library (issue 13):
the change-point statistics, the open-world residual diagnostics, and the whole
workflow on suites of the independent simulator (which shares no code with heliojax)."""

from __future__ import annotations

import dataclasses
import datetime
import json
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from heliojax import load_paint_directory
from heliojax.discovery import (
    Cleaning,
    Variable,
    change_point_pvalues,
    discover,
    markdown_summary,
    plot_unexplained,
    unexplained_structure,
    write_figures,
    write_report,
)
from heliojax.discovery._cleaning import confirm_change_points, recheck_outliers
from heliojax.discovery._diagnostics import anova, bin_index, predicted_spot

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from independent_sim import generate  # noqa: E402 (after the sys.path line)

# --------------------------------------------------------------------------------------
# Change-point statistics
# --------------------------------------------------------------------------------------


def test_change_point_pvalue_hand_values():
    # chi-square(2) tail exp(-d/2), Bonferroni over n dates, capped at 1, NaN without a scan
    p = change_point_pvalues(np.array([20.0, 0.0, np.nan, 40.0]), np.array([10, 10, 10, 0]))
    np.testing.assert_allclose(p[0], 10 * np.exp(-10.0), rtol=1e-12)
    assert p[1] == 1.0 and np.isnan(p[2])
    np.testing.assert_allclose(p[3], np.exp(-20.0), rtol=1e-12)  # at least one date


def _cleaning_with_change(h, m, t_change):
    valid = np.ones((h, m), bool)
    base = Cleaning.none(valid)
    return Cleaning(
        valid=valid,
        outlier=np.zeros_like(valid),
        superseded=np.zeros_like(valid),
        change_found=np.ones(h, bool),
        change_time_s=np.full(h, t_change),
        change_previous_s=np.full(h, t_change - 1.0),
        change_jump_mrad=np.zeros((h, 2)),
        change_p=np.full(h, 1e-9),
        change_p_holm=np.full(h, 1e-9),
        offsets=("angle_offset_1", "angle_offset_2"),
        noise_mrad=base.noise_mrad,
    )


def _linear_model(h, m):
    """Record times ``(H, M)`` (0, 1, ...) and the Jacobian ``(H, 2M, 3)`` of a linear
    model per heliostat: 2 offset columns (one per component) and a slope in time."""
    t = np.tile(np.arange(m, dtype=float), (h, 1))
    jac = np.zeros((h, 2 * m, 3))
    jac[:, 0::2, 0] = 1.0
    jac[:, 1::2, 1] = 1.0
    jac[:, :, 2] = np.repeat(np.linspace(-1, 1, m), 2)[None]
    return t, jac


def test_confirm_keeps_a_real_step_and_withdraws_a_spurious_one():
    # A linear model per heliostat: 2 offset columns (one per component) and a slope.
    rng = np.random.default_rng(0)
    h, m = 2, 40
    t, jac = _linear_model(h, m)
    noise = 0.25 * rng.standard_normal((h, 2 * m))
    step = np.where(np.repeat(t[0] < 20, 2), 1.0, 0.0)  # 1 mrad before the change in both components
    r = noise.copy()
    r[0] += step  # heliostat 0 jumped; heliostat 1 did not
    out, withdrawn = confirm_change_points(_cleaning_with_change(h, m, 20.0), r, jac, [0, 1, 2], [0, 1], t, 0.01)
    assert withdrawn == [1]
    assert out.change_found.tolist() == [True, False]
    assert out.withdrawn is not None and out.withdrawn.tolist() == [False, True]
    assert out.change_p[0] < 1e-6 and out.change_p[1] > 1e-3
    # Records the final model cannot evaluate (non-finite residual or Jacobian rows, e.g.
    # a left-out record outside an actuator's range) take no part: the same outcome as
    # with those records left out, and no exception.
    bad_r, bad_jac = r.copy(), jac.copy()
    bad_r[0, 2 * 5] = np.nan
    bad_jac[0, 2 * 7 + 1, 2] = np.inf
    bad_jac[1, 2 * 30, 0] = np.nan
    cleaning = _cleaning_with_change(h, m, 20.0)
    nan_out, nan_withdrawn = confirm_change_points(cleaning, bad_r, bad_jac, [0, 1, 2], [0, 1], t, 0.01)
    valid = cleaning.valid.copy()
    valid[0, [5, 7]] = False
    valid[1, 30] = False
    left_out = dataclasses.replace(cleaning, valid=valid)
    ref, ref_withdrawn = confirm_change_points(left_out, r, jac, [0, 1, 2], [0, 1], t, 0.01)
    assert nan_withdrawn == ref_withdrawn == [1]
    np.testing.assert_allclose(nan_out.change_p, ref.change_p, rtol=1e-10)
    # A heliostat whose records the final model cannot evaluate at all has no evidence
    # for its change point: withdrawn (p = 1), without a warning (seen on the real records)
    none_r = r.copy()
    none_r[0] = np.nan
    none_out, none_withdrawn = confirm_change_points(cleaning, none_r, jac, [0, 1, 2], [0, 1], t, 0.01)
    assert none_withdrawn == [0, 1] and none_out.change_p[0] == 1.0


def test_errors_shared_by_day_make_no_step_when_the_design_effect_is_given():
    """Records of one day sharing an error (a day's own offset) move runs of records
    together, as a step does: confirmed as independent records, a clean heliostat
    kept a change point at the date where its day errors happen to divide best
    (independent simulator, day-clustered noise, null suite seed 11720). With each
    heliostat's design effect its evidence is that of ``n / deff`` records: the
    likelihood ratio is divided by it (checked against the p-value written by hand),
    the clean heliostat's step is withdrawn, and a real 2 mrad jump (five days before it,
    five after, 0.4 mrad day errors) stays."""
    rng = np.random.default_rng(5)
    h, m, per_day = 2, 80, 8
    t, jac = _linear_model(h, m)
    day = np.repeat(np.arange(m // per_day), per_day)
    shared = 0.4 * rng.standard_normal((h, m // per_day, 2))[:, day].reshape(h, 2 * m)
    r = 0.15 * rng.standard_normal((h, 2 * m)) + shared
    r[0] += 2.0 * np.repeat((t[0] < 40).astype(float), 2)  # heliostat 0 jumped by 2 mrad; heliostat 1 is clean

    def confirmed(change_1, **kw):
        cleaning = dataclasses.replace(_cleaning_with_change(h, m, 40.0), change_time_s=np.array([40.0, change_1]))
        return confirm_change_points(cleaning, r, jac, [0, 1, 2], [0, 1], t, 0.01, **kw)

    # the clean heliostat's "change": the day boundary where its day errors divide best, as a scan finds it
    change_1 = min(range(per_day, m, per_day), key=lambda c: confirmed(float(c))[0].change_p[1])
    plain, withdrawn_plain = confirmed(float(change_1))
    assert withdrawn_plain == []  # taken as independent records, both are steps
    deff = np.full(h, 1 + (per_day - 1) * 0.4**2 / (0.4**2 + 0.15**2))  # Kish's, 8 records a day
    out, withdrawn = confirmed(float(change_1), design_effect=deff)
    assert withdrawn == [1] and out.change_found.tolist() == [True, False]
    # the evidence of heliostat 0 by hand: 2m rows, RSS with and without the jump columns
    a = jac[0][:, [0, 1, 2]]
    step = np.where(np.repeat(t[0] < 40, 2)[:, None], jac[0][:, [0, 1]], 0.0)

    def rss(x):
        return float(np.sum((r[0] - x @ np.linalg.lstsq(x, r[0], rcond=None)[0]) ** 2))

    d = (2 * m / deff[0]) * np.log(rss(a) / rss(np.concatenate([a, step], axis=1)))
    np.testing.assert_allclose(out.change_p[0], min(1.0, m * np.exp(-d / 2)), rtol=1e-9)
    # a design effect of 1 (no clustering found) changes nothing
    same, _ = confirmed(float(change_1), design_effect=np.ones(h))
    np.testing.assert_array_equal(same.change_p, plain.change_p)


def test_structure_reported_unexplained_is_no_step_when_change_points_are_confirmed():
    """A recorded variable that runs higher before a date than after it (the wind of a
    season) drives residual structure the model lacks: the pre-pass's scan dates it as
    a step. Confirmed with that variable's generic functions fitted beside the model
    (``extra_columns``: discovery passes those of the competitors it reports as
    unexplained) the change point is withdrawn; a real jump in another heliostat,
    whose variable carries no such structure, stays. (Independent simulator, wind
    direction, 26 x 80 records, seed 11712: BE61 got a change point of 0.16 mrad while
    the wind-vector load was reported unexplained.)"""
    rng = np.random.default_rng(3)
    h, m = 2, 40
    t, jac = _linear_model(h, m)
    before = (t < 20).astype(float)
    x = before + 0.5 * rng.standard_normal((h, m))  # the variable: higher before the date
    extra = np.zeros((h, 2 * m, 2))
    extra[:, 0::2, 0] = x
    extra[:, 1::2, 1] = x
    r = 0.25 * rng.standard_normal((h, 2 * m))
    r[0] += np.repeat(before[0], 2)  # heliostat 0 jumped by 1 mrad (its variable drives nothing)
    r[1] += 0.8 * np.repeat(x[1], 2)  # heliostat 1: structure in its variable, no jump
    cleaning = _cleaning_with_change(h, m, 20.0)
    without, withdrawn_without = confirm_change_points(cleaning, r, jac, [0, 1, 2], [0, 1], t, 0.01)
    assert withdrawn_without == []  # the structure passes for a step when nothing else can take it
    out, withdrawn = confirm_change_points(cleaning, r, jac, [0, 1, 2], [0, 1], t, 0.01, extra_columns=extra)
    assert withdrawn == [1] and out.change_found.tolist() == [True, False]
    assert out.change_p[0] < 1e-6


# --------------------------------------------------------------------------------------
# Residual diagnostics
# --------------------------------------------------------------------------------------


def test_binned_anova_is_calibrated_under_the_null():
    # p-values of structureless residuals are uniform: the fraction below 0.05 stays near 0.05
    rng = np.random.default_rng(1)
    h, m = 10, 40
    x = rng.uniform(0, 1, (h, m))
    use = np.ones((h, m), bool)
    idx = bin_index(x, use, "continuous")
    p = np.array([anova(rng.standard_normal((h, m, 2)), idx)[0] for _ in range(400)])
    assert 0.02 <= np.mean(p < 0.05) <= 0.09
    assert idx.max() + 1 == 8 and np.all(np.bincount(idx.ravel()) >= 5)


def test_anova_matches_scipy_for_one_component():
    # with the second component constant, the F statistic's between part is the first
    # component's; compare the bin means with a direct computation and p with f_oneway's ordering
    rng = np.random.default_rng(2)
    z = rng.standard_normal((4, 30, 2))
    z[..., 0] += np.repeat([0.0, 1.0], 60).reshape(4, 30)
    idx = np.repeat([0, 1], 60).reshape(4, 30)
    p, means = anova(z, idx)
    np.testing.assert_allclose(means[:, 0], [z[..., 0][idx == 0].mean(), z[..., 0][idx == 1].mean()])
    assert p < 1e-3


def _variables(rng, h, m):
    x = rng.uniform(-1, 1, (h, m))
    echo = x + 0.3 * rng.standard_normal((h, m))  # a variable correlated with x
    other = rng.uniform(0, 10, (h, m))
    cat = rng.integers(0, 3, (h, m)).astype(float)
    return [
        Variable("x", "x [1]", x),
        Variable("echo", "echo [1]", echo),
        Variable("other", "other [1]", other),
        Variable("cat", "category", cat, "categorical"),
    ]


def test_unexplained_structure_names_the_driving_variable_only():
    rng = np.random.default_rng(3)
    h, m = 12, 60
    variables = _variables(rng, h, m)
    x = variables[0].values
    signal = 0.3 * np.sin(np.pi * x)  # mrad, horizontal component
    r = 0.25 * rng.standard_normal((h, m, 2))
    r[..., 0] += signal
    entries, first = unexplained_structure(variables, r, np.ones((h, m), bool), 4, 0.01, [f"H{i}" for i in range(h)])
    assert [e["variable"] for e in entries] == ["x"]  # the echo is not reported once x is taken out
    assert first["echo"] < 0.01  # ...although on its own it is significant
    true_size = float(np.sqrt(np.mean(signal**2)))
    assert abs(entries[0]["effect_size_mrad"] - true_size) < 0.25 * true_size
    assert entries[0]["p_holm"] <= 0.01


def test_unexplained_structure_per_heliostat_finds_a_shape_that_differs_between_heliostats():
    """Each heliostat's residual follows x with its own phase (a daily tilt of each
    pylon): the fleet's binned means average it out, the per-heliostat form finds it,
    with its size, and the heliostats carrying it."""
    rng = np.random.default_rng(4)
    h, m = 16, 60
    variables = _variables(rng, h, m)
    x = variables[0].values
    phase = rng.uniform(0.0, 2.0 * np.pi, h)
    signal = 0.3 * np.sin(np.pi * x + phase[:, None])  # mrad, vertical component
    r = 0.25 * rng.standard_normal((h, m, 2))
    r[..., 1] += signal
    entries, first = unexplained_structure(variables, r, np.ones((h, m), bool), 4, 0.01, [f"H{i}" for i in range(h)])
    assert [(e["variable"], e["form"]) for e in entries][:1] == [("x", "per_heliostat")]
    assert first["x (per heliostat)"] < first["x"]
    true_size = float(np.sqrt(np.mean((signal - signal.mean(axis=1, keepdims=True)) ** 2)))
    assert abs(entries[0]["effect_size_mrad"] - true_size) < 0.3 * true_size
    # the echo of x is not reported once x is taken out
    assert "echo" not in [e["variable"] for e in entries]


def test_unexplained_structure_reports_nothing_without_structure():
    hits = 0
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        h, m = 10, 50
        r = 0.25 * rng.standard_normal((h, m, 2))
        entries, _ = unexplained_structure(_variables(rng, h, m), r, np.ones((h, m), bool), 4, 0.01, ["a"] * h)
        hits += bool(entries)
    assert hits <= 1  # family-wise level 1 % per data set


def test_predicted_spot_removes_the_residual_along_the_tangent_basis():
    # heliostat 10 m up, a vertical target 100 m north facing south; the measured spot lies
    # 0.1 m east and 0.2 m up of the model's, i.e. residual components (-1, +2) mrad
    class _T:
        centre = np.array([[0.0, 100.0, 10.0]])
        normal = np.array([[0.0, -1.0, 0.0]])

    class _G:
        position = np.array([[0.0, 0.0, 10.0]])

    class _F:
        focal_spot = np.array([[[0.1, 100.0, 10.2]]])
        target_index = np.zeros((1, 1), int)
        targets = _T
        geometry = _G

    spot = predicted_spot(_F, np.array([[[-1.0, 2.0]]]))
    # e1 = up x d points west for a ray to the north: d . e1 = -1 mrad means 0.1 m east
    np.testing.assert_allclose(spot[0, 0], [0.0, 100.0, 10.0], atol=2e-4)
    np.testing.assert_allclose(predicted_spot(_F, None), _F.focal_spot)


# --------------------------------------------------------------------------------------
# The workflow on the independent simulator
# --------------------------------------------------------------------------------------

SUITE = {"n_heliostats": 6, "n_records": 40}  # one padded shape: the compiled programs are shared
CANDIDATES = ("backlash", "thermal", "survey_target")


def _ts(s):
    return datetime.datetime.fromisoformat(s.replace("Z", "+00:00")).timestamp()


def test_planted_steps_are_change_points_and_gross_errors_are_left_out(shared_paint, tmp_path):
    truth = generate("step", tmp_path / "s", seed=11, outliers=0.05, source=shared_paint, **SUITE)
    fleet = load_paint_directory(tmp_path / "s")
    res = discover(fleet, base="actuator", effects=CANDIDATES)
    rep = res.report
    assert rep["named_effects"][0] == "change_point"
    assert not [n for n in rep["named_effects"] if n != "change_point"]  # the steps named nothing else
    cps = {c["heliostat"]: c for c in rep["change_points"]}
    dated = 0
    for st in truth["steps"]:
        c = cps.get(st["heliostat"])
        if c is not None and _ts(c["previous_record_time"]) <= _ts(st["time"]) <= _ts(c["time"]):
            dated += 1
    assert dated >= 5  # of 6 heliostats
    # the records before a change stay in the fit (the step is a jump of both joint zeros),
    # and the fitted jumps are the planted ones: the independent simulator's joint-zero
    # jumps of ~1 mrad, to ~3.5 standard errors of a jump fitted from 12-28 records a side
    cl = res.cleaning
    assert cl is not None
    h = cl.valid.shape[0]
    earlier = cl.superseded & ~cl.outlier
    assert earlier.any() and np.all(res.lanes.train_mask[:h][earlier])
    ids = list(res.fleet.ids)
    for st in truth["steps"]:
        c = cps.get(st["heliostat"])
        if c is not None:
            fitted = np.array([c["jump"]["angle_offset_1"], c["jump"]["angle_offset_2"]]) * 1e3
            np.testing.assert_allclose(fitted, [st["jump_mrad"]["axis_1"], st["jump_mrad"]["axis_2"]], atol=0.3)
            assert c["n_records_before"] == int(cl.superseded[ids.index(st["heliostat"])].sum())
    planted = {(o["heliostat"], int(o["record_id"])) for o in truth["outliers"]}
    found = {(o["heliostat"], o["record_id"]) for o in rep["outliers"]}
    assert planted and len(planted & found) >= 0.8 * len(planted)
    assert rep["noise_estimate_mrad"] < 1.4 * truth["noise_mrad"]  # the inliers' noise, not the gross errors'
    json.dumps(rep, allow_nan=False)
    # the change-point figure shows the records before the change off by the jump (the
    # final model without it), the rest around zero
    assert cl.final_residuals is not None
    h = int(np.argmax(np.abs(np.nan_to_num(cl.change_jump_mrad)).max(axis=1)))
    keep = cl.valid[h] & ~cl.outlier[h]
    before = keep & cl.superseded[h]
    since = keep & ~cl.superseded[h]
    assert before.any() and since.any()
    offset = np.linalg.norm(cl.final_residuals[h][before].mean(axis=0))
    assert offset > 0.5 * np.linalg.norm(cl.change_jump_mrad[h])
    assert np.linalg.norm(cl.final_residuals[h][since].mean(axis=0)) < 0.2 * offset
    assert (tmp_path / "fig" / "change_points.png") in write_figures(res, tmp_path / "fig")


def test_effect_outside_the_library_is_unexplained_not_misnamed(shared_paint, tmp_path):
    generate("lens_distortion", tmp_path / "l", seed=12, source=shared_paint, **SUITE)
    fleet = load_paint_directory(tmp_path / "l")
    res = discover(fleet, base="actuator", effects=CANDIDATES)
    rep = res.report
    assert rep["named_effects"] == []
    assert rep["unexplained"] and rep["unexplained"][0]["variable"] in ("spot_u", "spot_v")
    assert rep["unexplained"][0]["effect_size_mrad"] > 0.05
    # both forms of the figure render (labels, legend, nothing cut off: the save checks them)
    for form in ("fleet", "per_heliostat"):
        as_form = dataclasses.replace(res, unexplained=(dict(res.unexplained[0], form=form),))
        fig = plot_unexplained(as_form, 0)
        fig.savefig(tmp_path / f"unexplained_{form}.png")
        assert fig.axes[0].get_legend() is not None and fig.axes[0].get_xlabel()


@pytest.fixture(scope="module")
def null_suite(shared_paint, tmp_path_factory):
    out = tmp_path_factory.mktemp("null") / "none"
    generate("none", out, seed=13, source=shared_paint, **SUITE)
    return out


def test_null_suite_names_nothing_and_finds_no_structure(null_suite, tmp_path):
    res = discover(load_paint_directory(null_suite), base="actuator", effects=CANDIDATES)
    rep = res.report
    assert rep["named_effects"] == [] and rep["unexplained"] == [] and rep["change_points"] == []
    # 0.1 % tail of 240 clean records: P(Poisson(0.24) > 2) = 0.2 %
    assert len(rep["outliers"]) <= 2
    assert all(v is None or v > 1e-3 for v in rep["variable_p_values"].values())
    assert write_figures(res, tmp_path)  # no unexplained figure, the others render


def test_recheck_restores_records_the_final_model_fits():
    # Two records were flagged under the base model; the final model fits one of them
    # (an effect's tail) and still misses the other (a real gross error).
    rng = np.random.default_rng(7)
    h, m = 1, 60
    r = rng.standard_normal((h, m, 2)) * np.array([0.2, 0.3])
    r[0, 5] = [6.0, -4.0]  # still a gross error under the final model
    cl = Cleaning.none(np.ones((h, m), bool))
    flagged = np.zeros((h, m), bool)
    flagged[0, [5, 9]] = True
    out = recheck_outliers(dataclasses.replace(cl, outlier=flagged), r, 6)
    assert out.outlier[0].nonzero()[0].tolist() == [5]
    assert out.restored is not None and out.restored[0].nonzero()[0].tolist() == [9]


def test_a_generic_competitor_that_beats_the_library_is_reported_and_the_report_writes(shared_paint, tmp_path):
    """A wind load from one direction (outside the library; its ``wind`` drag grows with
    the speed from any direction): the time-of-day and wind-direction competitors are
    scored, the wind-direction one beats ``wind`` and is reported unexplained instead of
    it, with whether it won by less than the ambiguity margin; the whole report is JSON
    (a numpy boolean in that entry once stopped ``heliojax discover`` writing it).

    Refits in batches of one (``max_refits=1``): the first batch (``wind``) passes, the
    competitor beats it, and before the competitor is reported every other eligible
    candidate (Holm-significant in the step's screen) is refitted too: a batch that
    passed once ended the step, and the true effect of a suite, ranked behind by the
    linearisation, was never tried (independent simulator, encoder wobble 11706).

    Seed 15: at seed 14 (until the per-heliostat priors learnt their scale) the
    per-heliostat ``wind`` at four times its typical size explains this load as well
    as the competitor (467.8 against 464.3) and is named, flagged ambiguous."""
    generate("wind_direction", tmp_path / "w", seed=15, source=shared_paint, amplitude=1.5, **SUITE)
    fleet = load_paint_directory(tmp_path / "w")
    rep = discover(fleet, base="actuator", effects=("wind", "thermal"), max_refits=1).report
    first = rep["unexplained"][0]
    assert first["source"] == "generic competitor" and first["variable"] == "wind_direction"
    assert first["instead_of"]["effect"] == "wind" and isinstance(first["instead_of"]["ambiguous"], bool)
    assert "wind" not in rep["named_effects"]
    # its size is that of the residual structure it explains, never more than the residuals
    # (before, the function's amplitude with the share the model absorbs: 3.1 mrad on the
    # real records against a training RMS of 0.83)
    assert 0.0 < first["effect_size_mrad"] <= rep["train_rms_final_mrad"]
    eligible = {c for c, s in rep["screens"][0].items() if s["tested"] and s["p_holm"] < 0.01}
    assert len(eligible) == 2  # wind and thermal: a second batch to refit
    assert eligible <= {x["effect"] for x in rep["refits"][0]}
    # each name carries the p of its held-out gain over days; those at or above alpha are flagged
    assert all(0.0 <= s["cv_p"] <= 1.0 for s in rep["steps"])
    flagged = [(i + 1, s["effect"]) for i, s in enumerate(rep["steps"]) if s["cv_p"] >= 0.01]
    assert [(u["step"], u["named"]) for u in rep["held_out_not_significant"]] == flagged
    write_report(tmp_path / "report.json", rep)
    assert json.loads((tmp_path / "report.json").read_text())["unexplained"][0]["instead_of"] == first["instead_of"]


def _garbage(fleet, heliostats, seed=0, swap_first=True):
    """``fleet`` with the records of ``heliostats`` made garbage: motor axes swapped in
    the first (``swap_first``), the others' counts shuffled among their records."""
    import equinox as eqx

    rng = np.random.default_rng(seed)
    counts = np.asarray(fleet.counts).copy()
    for k, h in enumerate(heliostats):
        counts[h] = counts[h, :, ::-1] if k == 0 and swap_first else counts[h, rng.permutation(counts.shape[1])]
    return eqx.tree_at(lambda f: f.counts, fleet, jnp.asarray(counts))


def test_garbage_heliostats_are_left_out_and_spoil_nothing():
    """Heliostats of garbage records (motor axes swapped, counts shuffled) changed the
    fleet's noise estimate and every p-value of ``discover`` without a word (hostile-input
    trials, rounds 5 and 6; with two of them, leaving them out after the pre-pass still
    let them move the start geometries and the pre-pass of the others). Now they are
    named in the report and a warning and left out of everything after a first pre-pass:
    the noise estimate, held-out errors and every variable's p are those of the fleet
    without them; with ``keep_noisy`` they are kept and these move."""
    from helpers import zoo

    from heliojax._fleet import fleet_subset

    fleet = zoo("actuator").fleet
    assert np.asarray(fleet.mask).all()
    garbage = _garbage(fleet, (0, 1))
    settings = dict(base="actuator", effects=("backlash",), max_refits=1)
    rep = discover(garbage, **settings).report
    bad = list(fleet.ids[:2])
    assert [n["heliostat"] for n in rep["noisy_heliostats"]] == bad
    assert all(n["left_out"] is True for n in rep["noisy_heliostats"])
    assert min(n["noise_mrad"] for n in rep["noisy_heliostats"]) > 10 * rep["data"]["robust_noise_median_mrad"]
    assert any(all(i in w for i in bad) and "left out" in w for w in rep["warnings"])
    # shuffled counts leave a noise above the spots' scatter about the target centres; the
    # swapped axes, which the robust fit partly absorbs (4 mrad), do not
    assert [n["heliostat"] for n in rep["spots_unexplained"]] == [fleet.ids[1]]
    n_bad = int(np.asarray(fleet.mask[:2]).sum())
    others_flagged = sum(o["heliostat"] not in bad for o in rep["outliers"])
    assert rep["data"]["n_records_used"] == int(np.asarray(fleet.mask).sum()) - n_bad - others_flagged
    assert "(2 left out after the pre-pass as noise outliers: " in markdown_summary(rep)

    rest = discover(fleet_subset(fleet, list(fleet.ids[2:])), **settings).report
    assert sorted(o["record_id"] for o in rest["outliers"]) == sorted(
        o["record_id"] for o in rep["outliers"] if o["heliostat"] not in bad
    )
    for key in ("noise_estimate_mrad", "heldout_rms_base_mrad", "heldout_rms_final_mrad"):
        np.testing.assert_allclose(rep[key], rest[key], rtol=1e-6, err_msg=key)
    assert rep["variable_p_values"].keys() == rest["variable_p_values"].keys()
    tested = [v for v, p in rest["variable_p_values"].items() if p is not None]
    assert tested
    np.testing.assert_allclose(
        [rep["variable_p_values"][v] for v in tested], [rest["variable_p_values"][v] for v in tested], rtol=1e-6
    )
    assert rep["named_effects"] == rest["named_effects"]
    assert rest["noisy_heliostats"] == [] and rest["spots_unexplained"] == []  # the clean heliostats

    kept = discover(garbage, keep_noisy=True, **settings).report
    assert [n["left_out"] for n in kept["noisy_heliostats"]] == [False, False]
    assert kept["noise_estimate_mrad"] > 1.2 * rest["noise_estimate_mrad"]


def test_a_majority_of_garbage_heliostats_is_warned_of():
    """Five of eight heliostats garbage: no minority stands out, so none is a noise
    outlier, and ``discover`` said nothing (hostile-input trial, round 6: 3 of 5, a noise
    estimate of 404 mrad, no warning). Their models predict their spots worse than a beam
    on the target centre would: the report names them and warns."""
    from helpers import zoo

    fleet = zoo("actuator").fleet
    rep = discover(_garbage(fleet, range(5), swap_first=False), base="actuator", effects=("backlash",), max_refits=1)
    rep = rep.report
    # (with a garbage majority the pre-pass's joint fit of the change points fails for some
    # good heliostats too: here two at 157 mrad, named as well)
    assert set(fleet.ids[:5]) <= {n["heliostat"] for n in rep["spots_unexplained"]}
    assert all(n["noise_mrad"] > 2 * n["spot_scatter_mrad"] for n in rep["spots_unexplained"])
    assert any("worse than a beam on the target's centre" in w and fleet.ids[4] in w for w in rep["warnings"])


@pytest.mark.parametrize("field", ["keep_noisy", "robust", "changes", "effect_prior", "generic_competitors"])
@pytest.mark.parametrize("value", ["no", np.array([True, False]), 1])
def test_switches_of_the_discovery_config_take_booleans_only(field, value):
    """``discover(fleet, keep_noisy="no")`` kept the garbage heliostat (a truthy string)
    and an array raised numpy's "truth value ... ambiguous" from deep inside (round 6)."""
    from helpers import unchecked_config

    with pytest.raises(ValueError, match=f"{field} must be True or False"):
        unchecked_config(**{field: value})
