"""Discovery's lanes engine (the compiled fits over heliostat x fold lanes) against
second computations: grouping by record width against one group, and the refits'
effect prior against the fit core's Gaussian prior. Small fleets of their own
shapes, so the programs compile unoptimised (see tests/conftest.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from heliojax.discovery import DiscoveryConfig, simulate_fleet
from heliojax.discovery._screen import PRIOR_SCALES
from heliojax.effects import make_effect

M, NOISE = 40, 0.25


def test_lane_groups_by_record_width_change_no_lane_result(monkeypatch):
    """Lanes grouped by their heliostat's record width (each group its own compiled
    programs, cut to its width) against all lanes in one group at the fleet's width:
    the same fits and the same residuals and Jacobians, with heliostats of 12 and 70
    records and a masked record in the middle of one (two groups: each compile is
    seconds)."""
    import equinox as eqx
    import jax.numpy as jnp

    import heliojax as hj
    from heliojax.discovery import _lanes

    fleet, _ = simulate_fleet(2, 6, 70, effects=(make_effect("backlash"),), noise_mrad=NOISE)
    mask = np.asarray(fleet.mask).copy()
    mask[0, 12:] = False
    mask[1, 5] = False
    fleet = eqx.tree_at(lambda f: f.mask, fleet, jnp.asarray(mask))
    layout, template = _lanes.make_layout(hj.nominal_model("stone8"), ("backlash", "thermal"), fleet)
    lanes = _lanes.make_lanes(fleet, 3)
    one_block = hj.LaxMap()  # width groups alone (Threaded cuts them into blocks: tests/test_threaded.py)
    engine = _lanes.Engine.create(layout, template, lanes, batching=one_block)
    assert sorted(g.width for g in engine.groups) == [16, 70]
    p0 = np.broadcast_to(np.asarray(layout.view.to_vector(template)), (lanes.fold.shape[0], layout.view.n_parameters))
    cols = [0, 1]

    def run(e):
        out = e.fit(p0, cols, p0, e.expand(p0))
        p = out["params"] if reference is None else reference
        return out, e.jacobian(p), e.jacobian(p, evaluate=True)

    reference = None
    grouped = run(engine)
    reference = grouped[0]["params"]  # Jacobians of both at the same point
    one = lambda ln: (_lanes.LaneGroup(np.arange(ln.fold.size), ln.fold.size, 70),)  # noqa: E731
    monkeypatch.setattr(_lanes, "lane_groups", one)
    single = run(_lanes.Engine.create(layout, template, lanes, batching=one_block))
    # fits: equal to the solver's path tolerance (10 x its step tolerance, per parameter scale)
    path_atol = 10 * hj.fitting.DEFAULT_ATOL * np.asarray(layout.view.scales)
    assert np.all(np.abs(grouped[0]["params"] - single[0]["params"]) <= path_atol)
    np.testing.assert_array_equal(grouped[0]["ok"], single[0]["ok"])
    np.testing.assert_array_equal(grouped[0]["n_used"], single[0]["n_used"])
    for a, b in zip(grouped[1] + grouped[2], single[1] + single[2], strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)


def test_effect_prior_is_the_fit_cores_gaussian_prior_and_spares_well_sampled_heliostats():
    """The refits' effect prior (``DiscoveryConfig.effect_prior``) against a second
    implementation: :func:`heliojax.fit` of the same model with
    :func:`heliojax.gaussian_prior` (typical sizes as standard deviations, the lane's
    noise as scale) reaches the same posterior mode, to the solvers' path tolerance.
    A heliostat whose 8 records span four weeks is held near no drift; the
    well-sampled ones (40 records) keep their rates (within 2 % of the fit without the
    prior; measured 1.1-1.3 %),
    and the effective number of parameters counts the held one as less than free."""
    import equinox as eqx
    import jax.numpy as jnp

    import heliojax as hj
    from heliojax.discovery import _lanes, _select

    drift = [make_effect("offset_drift", offset_drift_1=1.5e-3, offset_drift_2=-1.5e-3)]
    fleet, _ = simulate_fleet(107, 6, M, effects=drift, noise_mrad=NOISE)
    mask = np.asarray(fleet.mask).copy()
    mask[0, 8:] = False
    fleet = eqx.tree_at(lambda f: f.mask, fleet, jnp.asarray(mask))
    layout, template = _lanes.make_layout(hj.nominal_model("stone8"), ("offset_drift",), fleet)
    lanes = _lanes.make_lanes(fleet, 2)
    p_none = np.broadcast_to(np.asarray(layout.view.to_vector(template)), (lanes.fold.size, layout.view.n_parameters))
    noise = np.full(lanes.fold.size, NOISE)

    def solve(engine):  # expand and fit until the first-order expansion is exact
        p = p_none
        for _ in range(6):
            p = engine.fit(p, [0, 1], p, engine.expand(p), noise)["params"]
        return p

    with_prior = solve(_lanes.Engine.create(layout, template, lanes))
    without = solve(_lanes.Engine.create(layout, template, lanes, effect_prior=False))
    typical = {n: float(t) for n, t in zip(layout.view.names, layout.view.typical, strict=True) if "drift" in n}
    reference = hj.fit(template, fleet, prior=hj.gaussian_prior(template, typical, noise_mrad=NOISE))
    assert np.all(np.asarray(reference.status) == hj.FitStatus.CONVERGED)
    fold0 = np.flatnonzero(lanes.fold == 0)
    path_atol = 10 * hj.fitting.DEFAULT_ATOL * np.asarray(layout.view.scales)
    free = np.asarray(layout.free_index)
    assert np.all(np.abs(with_prior[fold0][:, free] - np.asarray(reference.parameters())[:, free]) <= path_atol[free])
    rates = [layout.view.names.index(n) for n in typical]
    held, kept = with_prior[fold0][:, rates], without[fold0][:, rates]
    assert np.all(np.abs(held[0]) < 0.5 * np.abs(kept[0]))  # measured: 0.54 / 5.0 and 0.10 / 0.69 mrad/year
    np.testing.assert_allclose(held[1:], kept[1:], rtol=0.02)
    wf = _select._Workflow(_lanes.Engine.create(layout, template, lanes), DiscoveryConfig(base="stone8"))
    wf.noise = noise
    r, jac = wf.engine.jacobian(with_prior)
    state = _select.ModelState(
        (("offset_drift", "per_heliostat"),),
        with_prior,
        np.ones(len(noise), bool),
        r,
        jac,
        np.sum(r**2, axis=1),
        2 * lanes.train_mask.sum(axis=1),
        np.zeros_like(mask, float),
        None,
        0.0,
    )
    df = wf.effective_parameters(state, fold0)
    n_active = len(wf.active_cols(state.effects))
    assert df[0] < n_active - 0.5 and np.all(df[1:] > n_active - 0.1) and np.all(df <= n_active + 1e-9)

    # The Laplace Occam term of the refits' criterion against a second formula: per
    # lane, log det of the whole posterior precision (base and effect columns, no Schur
    # complement) over the base's and the prior's, plus the prior's exponent; at the
    # prior's scale the state was fitted with (1 here; then 4, as a screen may choose).
    act = wf.active_cols(state.effects)
    n_base = len(layout.base_cols)
    typical_inv = layout.inverse_typical[np.asarray(act[n_base:]) - n_base]
    assert np.all(typical_inv > 0)
    used = np.repeat(lanes.train_mask, 2, axis=1)
    nominal = np.asarray(layout.view.nominal)

    def reference(st, lane):
        inv_typ = typical_inv / st.prior_scales[0]
        j = st.jac[lane][used[lane]][:, act]
        a = j.T @ j / noise[lane] ** 2
        precision = a + np.diag(np.r_[np.zeros(n_base), inv_typ**2])
        idx = np.asarray(layout.free_index)[act[n_base:]]
        q = (st.params[lane, idx] - nominal[idx]) / layout.scales[act[n_base:]]
        ref = (
            np.linalg.slogdet(precision)[1]
            - np.linalg.slogdet(a[:n_base, :n_base])[1]
            - np.sum(np.log(inv_typ**2))
            + np.sum((q * inv_typ) ** 2)
        )
        # The hyperprior on the prior's scale: the evidence of the linearised lane at
        # each scale s, by stacked least squares (the effect's prior rows at 1 / (s
        # typical)) and whole log-determinants, against no effect.
        jw, rw = j / noise[lane], st.r[lane][used[lane]] / noise[lane]
        n_eff = len(inv_typ)

        def minus_two_log_bayes_factor(s):
            prior = typical_inv / s
            rows = np.vstack([jw, np.hstack([np.zeros((n_eff, n_base)), np.diag(prior)])])
            rhs = -np.concatenate([rw, prior * q])
            step = np.linalg.lstsq(rows, rhs, rcond=None)[0]
            with_effect = np.sum((rows @ step - rhs) ** 2)
            base_step = np.linalg.lstsq(jw[:, :n_base], -(rw - jw[:, n_base:] @ q), rcond=None)[0]
            without = np.sum((rw - jw[:, n_base:] @ q + jw[:, :n_base] @ base_step) ** 2)
            logdets = (
                np.linalg.slogdet(jw.T @ jw + np.diag(np.r_[np.zeros(n_base), prior**2]))[1]
                - np.linalg.slogdet(jw[:, :n_base].T @ jw[:, :n_base])[1]
                - np.sum(np.log(prior**2))
            )
            return logdets + with_effect - without

        e = np.array([minus_two_log_bayes_factor(s) for s in PRIOR_SCALES])
        e_own = minus_two_log_bayes_factor(st.prior_scales[0])
        return ref - 2.0 * np.log(np.mean(np.exp(-0.5 * (e - e_own))))

    # occam_terms' ridge (1e-12 of the trace of the base's normal matrix) moves the
    # log-determinant by ~1e-12 times that matrix's condition number (~1e5 here); the
    # hyperprior term takes the score at no effect from the posterior mode, which the
    # fit reaches to its path tolerance (measured: 2.4e-6 of 0.89 on the held lane)
    per_lane = [wf.occam_terms(state, np.array([lane])) for lane in fold0]
    np.testing.assert_allclose(per_lane, [reference(state, lane) for lane in fold0], rtol=1e-6, atol=1e-5)
    # the held heliostat's two rates, which its records barely determine, cost less
    # than one unit together (measured 0.89, 0.28 of it the hyperprior's term); the
    # well-sampled ones' cost their information and their size (planted at several
    # typical sizes; measured 14.7-16.0)
    assert per_lane[0] < 1.0 and min(per_lane[1:]) > 10.0
    # A state fitted at four times the typical sizes carries that scale into its
    # criterion (the held heliostat's rates, held less, move: a different term)
    wide = wf.fit_state(state.effects, with_prior, prior_scales=(4.0,))
    assert wide.prior_scales == (4.0,) and np.all(wide.ok[fold0])
    wide_terms = [wf.occam_terms(wide, np.array([lane])) for lane in fold0]
    np.testing.assert_allclose(wide_terms, [reference(wide, lane) for lane in fold0], rtol=1e-6, atol=1e-5)
    assert abs(wide_terms[0] - per_lane[0]) > 0.1
    with pytest.raises(ValueError, match="2 prior scales for 1 effects"):
        dataclasses.replace(state, prior_scales=(1.0, 4.0))


def _thermal_backlash_engine():
    """The small fleet of the two tests below (2 heliostats x 40 records, thermal and
    backlash planted, 3 folds): layout, template, lanes, engine and the nominal start
    ``(L, P)``."""
    import heliojax as hj
    from heliojax.discovery import _lanes

    effects = (make_effect("thermal", thermal_1=4e-5, thermal_2=-3e-5), make_effect("backlash"))
    fleet, _ = simulate_fleet(3, 2, M, effects=effects, noise_mrad=NOISE)
    layout, template = _lanes.make_layout(hj.nominal_model("stone8"), ("thermal", "backlash"), fleet)
    lanes = _lanes.make_lanes(fleet, 3)
    engine = _lanes.Engine.create(layout, template, lanes)
    n_lanes = lanes.fold.shape[0]
    p0 = np.broadcast_to(np.asarray(layout.view.to_vector(template)), (n_lanes, layout.view.n_parameters)).copy()
    return layout, template, lanes, engine, p0


def test_expansions_residuals_and_refits_against_second_computations():
    """The refits' cheaper paths against second computations on one small fleet
    (2 heliostats x 40 records, 3 folds; thermal and backlash planted):

    * the effect graph's derivative ``D`` (reverse mode) equals forward mode's;
    * an expansion that keeps an earlier ``D`` evaluates ``c0`` at the new point as a
      full expansion does, and carries the earlier ``D`` unchanged;
    * the residual-only program gives the Jacobian program's residuals;
    * ``fit_state`` (iterations with a kept ``D``, then a fresh one) ends where
      iterating "expand afresh, fit" to convergence ends, to the solver's path
      tolerance, for a per-heliostat thermal and backlash refit."""
    import jax
    import jax.numpy as jnp

    import heliojax as hj
    from heliojax.discovery import _lanes, _select

    layout, template, lanes, engine, p0 = _thermal_backlash_engine()
    n_lanes = lanes.fold.shape[0]
    rng = np.random.default_rng(5)
    free = np.asarray(layout.free_index)
    p1 = p0.copy()
    p1[:, free] += 0.3 * rng.normal(size=(n_lanes, free.size)) * np.asarray(layout.scales)

    # reverse-mode D against forward mode, lane 0
    (group,) = engine.groups
    geometry, counts, context, focal, mask = group.take(lanes.data)
    lane0 = jax.tree.map(lambda x: x[0], (geometry, counts, context, focal, mask))
    c0, d_rev = _lanes._corrections_lane(layout, template, jnp.asarray(p1[0]), *lane0)
    counts0, context0, focal0, _, _ = _lanes.sanitise(*lane0)
    eidx = jnp.asarray(layout.effect_index, dtype=jnp.int32)
    p1_0 = jnp.asarray(p1[0])

    def corr(q, c, x, f):
        return _lanes._corrections(layout.model(template, p1_0.at[eidx].set(q)), lane0[0], c, x, f)

    d_fwd = jax.vmap(lambda c, x, f: jax.jacfwd(corr)(p1_0[eidx], c, x, f))(counts0, context0, focal0)
    np.testing.assert_allclose(np.asarray(d_rev), np.asarray(d_fwd), rtol=0, atol=1e-12 * float(np.abs(d_fwd).max()))
    assert float(np.abs(d_fwd).max()) > 0

    # an expansion that keeps D: c0 at the new point, D of the old one
    ((c_old, d_old),) = engine.expand(p0)
    ((c_new, d_new),) = engine.expand(p1)
    ((c_kept, d_kept),) = engine.expand(p1, derivative_from=((c_old, d_old),))
    np.testing.assert_allclose(np.asarray(c_kept), np.asarray(c_new), rtol=0, atol=1e-12)
    assert d_kept is d_old and float(np.abs(np.asarray(d_new) - np.asarray(d_old)).max()) > 0

    # the residual-only program
    for evaluate in (False, True):
        r_jac, _ = engine.jacobian(p1, evaluate=evaluate)
        np.testing.assert_allclose(engine.residuals(p1, evaluate=evaluate), r_jac, rtol=0, atol=1e-10)

    # a refit ends where "expand afresh, fit" iterated to convergence ends (measured: 4e-8
    # of a solver scale; iterations that stopped at the cost test, without the fresh
    # derivative's last fit, were 1.3e-4 away): within the solver's path tolerance
    wf = _select._Workflow(engine, DiscoveryConfig(base="stone8"))
    base = wf.fit_state((), p0)
    wf.noise = _select._lane_noise(base, len(layout.base_cols))
    n_base = len(layout.base_cols)
    path_atol = 10 * hj.fitting.DEFAULT_ATOL
    for effect in ("thermal", "backlash"):
        state = wf.fit_state(((effect, "per_heliostat"),), base.params)
        cols = [c - n_base for c in wf.active_cols(state.effects) if c >= n_base]
        p = base.params
        for _ in range(12):
            p = engine.fit(p, cols, p, engine.expand(p), wf.noise)["params"]
        assert state.ok.all() and np.all(state.rss < base.rss)
        assert np.max(np.abs(state.params - p)[:, free] / np.asarray(layout.scales)) <= path_atol


def test_a_refit_on_the_fold_0_lanes_alone_is_the_full_refits_fold_0():
    """A refit is first fitted on its fold-0 lanes alone (``active``), for the BIC that
    decides whether the cross-validation folds are fitted at all. Against the refit of
    every lane (the same small fleet as above, per-heliostat and shared forms): the
    fold-0 lanes end at the same parameters to the solver's path tolerance and give the
    same delta BIC; the skipped lanes are not ``ok``, stay at their start and have no
    residuals; the engine's programs give the active lanes' values unchanged. (Shared
    parameters are stepped until no fold's step exceeds 1e-3 of a scale; with other
    folds' steps in that test the full refit may take one step more, so the shared form
    agrees to that tolerance: measured 9.6e-4.)"""
    import heliojax as hj
    from heliojax.discovery import _lanes, _select

    layout, template, lanes, engine, p0 = _thermal_backlash_engine()
    n_lanes = lanes.fold.shape[0]
    fold0 = lanes.fold == 0
    assert 0 < fold0.sum() < n_lanes

    r_all, jac_all = engine.jacobian(p0)
    r_some, jac_some = engine.jacobian(p0, active=fold0)
    np.testing.assert_allclose(r_some[fold0], r_all[fold0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(jac_some[fold0], jac_all[fold0], rtol=0, atol=1e-12)
    assert np.all(r_some[~fold0] == 0) and np.all(jac_some[~fold0] == 0) and np.any(r_all[~fold0] != 0)
    # vmapped lanes compute every lane and select: the same values, but nothing saved
    vmapped = _lanes.Engine.create(layout, template, lanes, batching=hj.Vmap())
    assert engine.skips_inactive_lanes and not vmapped.skips_inactive_lanes
    r_vm, jac_vm = vmapped.jacobian(p0, active=fold0)
    np.testing.assert_allclose(r_vm, r_some, rtol=0, atol=1e-10)
    np.testing.assert_allclose(jac_vm, jac_some, rtol=0, atol=1e-10)

    wf = _select._Workflow(engine, DiscoveryConfig(base="stone8"))
    base = wf.fit_state((), p0)
    wf.noise = _select._lane_noise(base, len(layout.base_cols))
    free = np.asarray(layout.free_index)
    path_atol = 10 * hj.fitting.DEFAULT_ATOL
    for model, atol in (((("thermal", "per_heliostat"),), path_atol), ((("backlash", "shared"),), 1e-3)):
        full = wf.fit_state(model, base.params)
        first = wf.fit_state(model, base.params, active=fold0)
        np.testing.assert_array_equal(first.ok, full.ok & fold0)
        assert full.ok.all()
        gap = np.abs(first.params[fold0] - full.params[fold0])[:, free] / np.asarray(layout.scales)
        assert np.max(gap) <= atol, (model, np.max(gap))
        np.testing.assert_array_equal(first.params[~fold0], base.params[~fold0])
        assert np.all(first.r[~fold0] == 0)
        b0, b1, n = wf.bic_pair(base, first)
        c0, c1, m = wf.bic_pair(base, full)
        assert n == m == fold0.sum()
        # the BIC is stationary at the optimum, so the parameters' tolerance moves it by
        # its square only (measured: 4e-3 for the shared form, 0 for the per-heliostat one)
        assert b0 == c0 and abs((b0 - b1) - (c0 - c1)) <= 0.02, (b0 - b1, c0 - c1)


def test_a_cross_validation_lane_with_fewer_training_records_than_free_parameters_is_not_fitted():
    """``make_lanes(..., min_training_records=n)`` (discovery: ``n`` = the base model's
    free parameters): a cross-validation lane that would train on fewer than ``n``
    records trains on nothing and holds nothing out; every other lane (the heliostat's
    fold-0 lane among them) is the lane without the rule, and its fit of the base
    model (``_Workflow.fit_state``) is the same; the lanes left out are not fitted
    (not ``ok``, no held-out error)."""
    import equinox as eqx
    import jax.numpy as jnp

    from heliojax.discovery import _lanes, _select

    fleet, _ = simulate_fleet(61, 4, M, noise_mrad=NOISE)
    mask = np.asarray(fleet.mask).copy()
    mask[0, np.flatnonzero(mask[0])[9:]] = False  # heliostat 0 keeps 9 records
    fleet = eqx.tree_at(lambda f: f.mask, fleet, jnp.asarray(mask))
    config = DiscoveryConfig(base="stone8")
    base = _select.nominal_model(config.base, fleet.counts.dtype)
    # one candidate: the rule is about the base's parameters, and the full library's
    # effect graph only made the two compiles slower
    layout, template = _lanes.make_layout(base, ("thermal",), fleet, change_points=False)
    n_base = len(layout.base_cols)
    plain = _lanes.make_lanes(fleet, config.n_folds)
    ruled = _lanes.make_lanes(fleet, config.n_folds, min_training_records=n_base)
    short = (plain.fold > 0) & (plain.train_mask.sum(axis=1) < n_base)
    assert short.any() and np.all(plain.heliostat[short] == 0)
    np.testing.assert_array_equal(ruled.cross_validated, ~short)
    np.testing.assert_array_equal(ruled.train_mask[~short], plain.train_mask[~short])
    assert not ruled.train_mask[short].any() and not ruled.heldout_mask()[short].any()
    np.testing.assert_array_equal(ruled.heldout_mask()[~short], plain.heldout_mask()[~short])
    assert plain.heldout_mask()[short].any()  # the rule is what removes them
    states = []
    for lanes in (plain, ruled):
        engine = _lanes.Engine.create(
            layout, template, lanes, config.solver, config.max_steps, config.batching, config.effect_prior
        )
        wf = _select._Workflow(engine, config)
        p0 = np.broadcast_to(np.asarray(layout.view.to_vector(template)), (lanes.fold.size, layout.view.n_parameters))
        states.append(wf.fit_state((), np.array(p0)))
    before, after = states
    assert before.ok[short].all() and not after.ok[short].any()
    assert np.isnan(after.heldout_sq[short]).all()
    keep = ~short
    np.testing.assert_array_equal(after.ok[keep], before.ok[keep])
    # lanes are fitted independently: the same arithmetic, lane by lane
    np.testing.assert_allclose(after.params[keep], before.params[keep], rtol=0, atol=1e-12)
    np.testing.assert_allclose(after.heldout_sq[keep], before.heldout_sq[keep], rtol=1e-12, atol=1e-14)
