"""Generic competitors (heliojax.discovery._competitors): the design, the evidence
against second formulas, and what they find in residuals of known structure."""

from __future__ import annotations

import types

import numpy as np
import pytest
from _evidence import scale_and_penalty

from heliojax.discovery._competitors import (
    GENERIC_TYPICAL_MRAD,
    CompetitorScore,
    _fleet,
    _per_heliostat,
    competitor_design,
    competitor_features,
    score_competitors,
    unexplained_entry,
)
from heliojax.discovery._screen import prepare_bases

DAY = 86400.0


def _fake_fleet(h, m, rng):
    t = 1.7e9 + np.sort(rng.uniform(0, 200 * DAY, size=(h, m)), axis=1)
    ctx = types.SimpleNamespace(
        unix_time=t,
        wind_speed=rng.uniform(0, 12, size=(h, m)),
        wind_direction=rng.uniform(0, 2 * np.pi, size=(h, m)),
    )
    return types.SimpleNamespace(context=ctx)


def _residuals(h, m, p, rng, structure=None, sigma=0.25):
    """Residuals of a linear model's least-squares fit: noise (plus ``structure``,
    (H, 2M)) with ``p`` random columns per heliostat projected out."""
    jac = rng.normal(size=(h, 2 * m, p))
    y = sigma * rng.normal(size=(h, 2 * m)) + (0.0 if structure is None else structure)
    r = np.stack([y[i] - jac[i] @ np.linalg.lstsq(jac[i], y[i], rcond=None)[0] for i in range(h)])
    return r, jac


def test_the_design_puts_each_function_on_its_component():
    f = np.arange(2 * 3 * 2, dtype=float).reshape(2, 3, 2)
    f[1, 2, 0] = np.nan
    d = competitor_design(f)
    assert d.shape == (2, 6, 4)
    # record j, component c at row 2j + c; coefficients (c, function) at column 2c + k
    np.testing.assert_array_equal(d[0, 2], [f[0, 1, 0], f[0, 1, 1], 0, 0])
    np.testing.assert_array_equal(d[0, 3], [0, 0, f[0, 1, 0], f[0, 1, 1]])
    assert d[1, 4, 0] == 0.0  # a record without the variable carries nothing


def test_the_features_are_the_day_phase_and_the_wind_vector():
    rng = np.random.default_rng(0)
    fleet = _fake_fleet(2, 5, rng)
    tod = competitor_features(fleet, "time_of_day")
    phase = 2 * np.pi * (fleet.context.unix_time % DAY) / DAY
    np.testing.assert_allclose(tod[..., 0], np.sin(phase))
    wind = competitor_features(fleet, "wind_direction")
    # from the north at 10 m/s: (0, 1); from the east: (1, 0)
    v, d = fleet.context.wind_speed / 10, fleet.context.wind_direction
    np.testing.assert_allclose(wind, np.stack([v * np.sin(d), v * np.cos(d)], -1))
    with pytest.raises(ValueError, match="no generic competitor"):
        competitor_features(fleet, "temperature")


def test_the_per_heliostat_evidence_against_second_formulas():
    """Delta = sum_h n_h log(RSS_h / RSS'_h) - log det(I + T F_h) - beta^T T^-1 beta, with
    the MAP from the augmented least-squares system and the log det by the matrix
    determinant lemma (``log det(s^2 I + X T X^T) - n log s^2``), ``T`` at the
    hyperprior's scale and less its ``-2 log`` average over the scales (both from the
    marginal likelihood of the rows, ``tests/_evidence.py``)."""
    rng = np.random.default_rng(3)
    h, m, p = 4, 30, 5
    fleet = _fake_fleet(h, m, rng)
    design = competitor_design(competitor_features(fleet, "time_of_day"))
    structure = np.einsum("hrk,hk->hr", design, rng.normal(scale=0.4, size=(h, 4)))
    r, jac = _residuals(h, m, p, rng, structure)
    used = np.ones((h, 2 * m), bool)
    bases = prepare_bases(r, jac, used, range(p), range(h))
    noise = np.full(h, 0.3)
    delta, pval, size, p_h = _per_heliostat(bases, design, noise, h)
    blocks = []
    for i in range(h):
        q, _ = np.linalg.qr(jac[i])
        blocks.append(
            (
                design[i] - q @ (q.T @ design[i]),
                r[i] - q @ (q.T @ r[i]),
                noise[i] ** 2,
                np.full(4, GENERIC_TYPICAL_MRAD),
            )
        )
    scale, penalty = scale_and_penalty(blocks)
    t2 = (scale * GENERIC_TYPICAL_MRAD) ** 2
    expected = -penalty
    for i in range(h):
        q, _ = np.linalg.qr(jac[i])
        xt = design[i] - q @ (q.T @ design[i])
        s2 = noise[i] ** 2
        aug = np.vstack([xt / noise[i], np.eye(4) / np.sqrt(t2)])
        beta = np.linalg.lstsq(aug, np.concatenate([r[i] / noise[i], np.zeros(4)]), rcond=None)[0]
        rss, rss_new = r[i] @ r[i], np.sum((r[i] - xt @ beta) ** 2)
        logdet = np.linalg.slogdet(s2 * np.eye(2 * m) + t2 * xt @ xt.T)[1] - 2 * m * np.log(s2)
        expected += 2 * m * np.log(rss / rss_new) - logdet - beta @ beta / t2
    np.testing.assert_allclose(delta, expected, rtol=1e-8)
    assert delta > 10 and pval < 1e-6 and np.all(p_h < 0.05)
    assert 0.2 < size < 1.0  # RMS of the planted function, ~0.4 mrad per coefficient


def test_competitors_on_noise_lose_and_on_their_structure_win():
    """Pure noise: every competitor's evidence is negative and its test not
    significant. A fleet-wide wind load linear in the wind vector: the wind
    competitor wins in its fleet form, and its entry names it."""
    rng = np.random.default_rng(11)
    h, m, p = 12, 40, 6
    fleet = _fake_fleet(h, m, rng)
    r, jac = _residuals(h, m, p, rng)
    bases = prepare_bases(r, jac, np.ones((h, 2 * m), bool), range(p), range(h))
    scores = score_competitors(fleet, bases, np.full(h, 0.25), h)
    assert [s.variable for s in scores] and all(s.delta_bic < 0 and s.p > 0.01 for s in scores)

    wind = competitor_design(competitor_features(fleet, "wind_direction"))
    load = np.einsum("hrk,k->hr", wind, np.array([0.3, -0.2, 0.1, 0.4]))
    r, jac = _residuals(h, m, p, rng, load)
    bases = prepare_bases(r, jac, np.ones((h, 2 * m), bool), range(p), range(h))
    scores = score_competitors(fleet, bases, np.full(h, 0.25), h)
    top = scores[0]
    assert top.variable == "wind_direction" and top.form == "fleet" and top.delta_bic > 50
    d_f, p_f, _ = _fleet(bases, wind, np.full(h, 0.25))
    assert d_f == top.delta_bic and p_f < 1e-10
    ids = [f"H{i}" for i in range(h)]
    entry = unexplained_entry(top, len(scores), 0.01, ids, {"effect": "wind", "mode": "shared", "delta_bic": 1.0})
    assert entry["variable"] == "wind_direction" and entry["source"] == "generic competitor"
    assert entry["p_holm"] == min(1.0, 2 * top.p) and set(entry["heliostats"]) <= set(ids)


def test_a_significant_competitor_close_below_the_named_effect_makes_the_name_ambiguous():
    """``generic_rivals``: a generic competitor within ``ambiguity_bic`` below the named
    effect's criterion and significant over the competitors (``n p <= alpha``, as for
    one that wins) is reported with the name as an ambiguity; one further below, or
    not significant, is not. The Markdown says which alternative is no library effect."""
    from heliojax.discovery._competitors import generic_rivals

    def score(variable, delta, p):
        return CompetitorScore(variable, "per_heliostat", delta, p, 0.3, np.array([p]))

    comps = [score("time_of_day", 52.0, 2e-11), score("wind_direction", 50.0, 0.2), score("x", 40.0, 1e-9)]
    rivals = generic_rivals(55.0, comps, alpha=0.01, ambiguity_bic=10.0)
    assert [r["variable"] for r in rivals] == ["time_of_day"]
    (r,) = rivals
    assert r["effect"] is None and r["source"] == "generic competitor" and r["delta_bic"] == 52.0
    assert generic_rivals(62.5, comps, alpha=0.01, ambiguity_bic=10.0) == ()
    assert generic_rivals(55.0, comps[:2], alpha=0.01, ambiguity_bic=10.0)[0]["p"] == 2e-11
    # two competitors: 2 x 2e-11 still significant; at p = 0.01 / 3 < p it would not be
    assert generic_rivals(55.0, [score("time_of_day", 52.0, 0.004)] * 3, alpha=0.01, ambiguity_bic=10.0) == ()

    from heliojax.discovery import markdown_summary

    report = {  # what the Markdown reads of a report without steps
        "data": {"n_heliostats": 2, "n_records": 40},
        "base_model": "actuator",
        "config": {"n_folds": 5, "ambiguity_bic": 10.0, "absorbed_limit": 0.999},
        "steps": [],
        "named_effects": [],
        "screens": [],
        "absorbed_fraction": {},
        "change_points": [],
        "outliers": [],
        "unexplained": [],
        "not_identifiable": [],
        "untestable": [],
        "not_tested_reason": None,
        **{f"{k}_mrad": 1.0 for k in ("heldout_rms_base", "heldout_rms_final", "heldout_median_base")},
        **{f"{k}_mrad": 1.0 for k in ("heldout_median_final", "train_rms_base", "train_rms_final")},
        "noise_estimate_mrad": 0.3,
    }
    report["ambiguities"] = [
        {
            "step": 1,
            "named": "encoder_wobble",
            "alternatives": [
                {"effect": "backlash", "mode": "shared", "delta_bic": 50.0, "source": "library"},
                {
                    "effect": None,
                    "mode": "per_heliostat",
                    "delta_bic": 52.0,
                    "source": "generic competitor",
                    "variable": "time_of_day",
                    "p": 2e-11,
                },
            ],
        }
    ]
    text = markdown_summary(report)
    assert "`encoder_wobble` (mode unknown) and `backlash` (shared, delta BIC 50.0), a smooth function of " in text
    assert "a smooth function of `time_of_day` (generic" in text
    # the same effect in its two forms is told apart by its mode (it read "`thermal` and `thermal`")
    report["ambiguities"] = [
        {
            "step": 1,
            "named": "thermal",
            "named_mode": "shared",
            "alternatives": [{"effect": "thermal", "mode": "per_heliostat", "delta_bic": 41.0, "source": "library"}],
        }
    ]
    assert "`thermal` (shared) and `thermal` (per heliostat, delta BIC 41.0) explain" in markdown_summary(report)
    # the withdrawn change points of report.json are in the Markdown too (they were not)
    report["change_points_withdrawn"] = [{"heliostat": "BF56", "time": "2023-03-01T10:00:00Z", "p": 1.4e-52}]
    assert "withdrawn, not named): BF56 (2023-03-01T10:00:00Z, p 1.4e-52)" in markdown_summary(report)


def _absorbing_fit(design, n_free, rng, y):
    """The least-squares residuals of ``y`` ``(H, R)`` under a base of ``n_free`` random
    columns and random mixtures of ``design``'s columns (``(H, R, j)``: inside every
    heliostat's span of the base), with the bases of that base."""
    h, rows, j = design.shape
    mix = design @ rng.normal(size=(h, j, j))
    jac = np.concatenate([rng.normal(size=(h, rows, n_free)), mix], axis=2)
    r = np.stack([y[i] - jac[i] @ np.linalg.lstsq(jac[i], y[i], rcond=None)[0] for i in range(h)])
    return prepare_bases(r, jac, np.ones((h, rows), bool), range(n_free + j), range(h))


def test_a_competitor_the_base_absorbs_is_untested_and_a_free_one_tested_as_before():
    """A competitor whose functions lie inside every heliostat's span of the base's
    columns holds rounding only after the projection: neither form tests it (``p``
    ``None``, no per-heliostat p; the screens' rule, :func:`._screen.heliostat_directions`
    and :func:`._screen.shared_score`), so it is never significant, never a rival, and
    it is out of the Bonferroni family. A relative cut alone gave it a p from rounding.
    A free competitor is tested as before (the fleet's ``g^T G^-1 g`` on its four
    directions, chi-square); half absorbed, both forms test the free half alone."""
    from scipy import stats

    from heliojax.discovery._competitors import generic_rivals, n_tested, significant

    rng = np.random.default_rng(21)
    h, m, p = 8, 40, 5
    fleet = _fake_fleet(h, m, rng)
    tod = competitor_design(competitor_features(fleet, "time_of_day"))
    wind = competitor_design(competitor_features(fleet, "wind_direction"))
    noise = np.full(h, 0.25)
    load = np.einsum("hrk,k->hr", wind, np.array([0.03, -0.02, 0.01, 0.04]))
    y = 0.25 * rng.normal(size=(h, 2 * m)) + load + np.einsum("hrk,k->hr", tod, np.array([0.5, 0.3, -0.4, 0.2]))
    bases = _absorbing_fit(tod, p, rng, y)

    d_h, p_h, _, p_each = _per_heliostat(bases, tod, noise, h)
    d_f, p_f, _ = _fleet(bases, tod, noise)
    assert p_h is None and p_f is None and np.all(np.isnan(p_each))
    assert abs(d_h) < 1e-6 and abs(d_f) < 1e-6  # the evidence of rounding: none
    scores = score_competitors(fleet, bases, noise, h)
    by = {s.variable: s for s in scores}
    assert by["time_of_day"].p is None and n_tested(scores) == 1
    assert not significant(by["time_of_day"], n_tested(scores), 0.01)
    assert all(r["variable"] != "time_of_day" for r in generic_rivals(d_f + 1.0, scores, 0.01, 10.0))

    # the free competitor: the fleet's chi-square statistic on its four directions
    w = 1.0 / noise[bases.index] ** 2
    xt = bases.project(bases.rows(wind))
    g = np.einsum("s,srk,sr->k", w, xt, bases.r_res)
    gmat = np.einsum("s,srk,srj->kj", w, xt, xt)
    expected = stats.chi2.sf(g @ np.linalg.solve(gmat, g), 4)
    assert 1e-12 < expected < 1e-2  # the planted load is found, not to rounding
    np.testing.assert_allclose(_fleet(bases, wind, noise)[1], expected, rtol=1e-8)
    assert by["wind_direction"].p is not None and np.all(np.isfinite(by["wind_direction"].p_heliostats))

    # half absorbed (the first component's functions): the second component's alone
    bases = _absorbing_fit(tod[..., :2], p, rng, y)
    free = tod * np.array([0.0, 0.0, 1.0, 1.0])
    for form in (_fleet, lambda *a: _per_heliostat(*a, h)):
        half, alone = form(bases, tod, noise), form(bases, free, noise)
        assert half[1] is not None and alone[1] is not None and half[1] < 1e-6
        np.testing.assert_allclose(half[1], alone[1], rtol=1e-8)
        np.testing.assert_allclose(half[0], alone[0], rtol=1e-6)
    np.testing.assert_allclose(_per_heliostat(bases, tod, noise, h)[3], _per_heliostat(bases, free, noise, h)[3])
