"""The batched screens (one padded stack of heliostats) against a straightforward
per-heliostat computation, on a small random problem with unequal record counts:
a heliostat without used rows, one without residual degrees of freedom and one
without degrees of freedom left for its F test. The rows a heliostat does not use
hold large values in the residuals and the Jacobian, so a padded row that leaked
into a projection or a sum would change the results."""

from __future__ import annotations

import numpy as np
import pytest
from _evidence import scale_and_penalty
from scipy import stats

from heliojax.discovery import ABSORBED_LIMIT
from heliojax.discovery._competitors import GENERIC_TYPICAL_MRAD, _fleet, _per_heliostat
from heliojax.discovery._identifiability import RANK_RTOL, column_basis
from heliojax.discovery._screen import prepare_bases, screen_candidate

N_ROWS = 40  # residual rows of the padded fleet
N_BASE = 5  # current model's columns
CAND = (5, 6)  # the candidate's columns
# used rows per heliostat: none, fewer than the base's columns (dof <= 0), dof 3 with a
# second candidate column absorbed (one direction tested, dof - k = 2), dof 2 with two
# candidate columns (dof - k = 0: in the shared sums, not tested per heliostat), full ...
USED = (0, 4, 8, 7, 40, 23, 31, 12)
ABSORBED_HELIOSTAT = 2


def _problem(seed: int = 7):
    rng = np.random.default_rng(seed)
    h = len(USED)
    jac = rng.normal(size=(h, N_ROWS, N_BASE + 2))
    jac[ABSORBED_HELIOSTAT, :, 6] = jac[ABSORBED_HELIOSTAT, :, :N_BASE] @ rng.normal(size=N_BASE)
    noise = rng.normal(scale=rng.uniform(0.5, 2.0, (h, 1)), size=(h, N_ROWS))
    r = jac[:, :, 5] * rng.normal(scale=0.3, size=(h, 1)) + noise
    used = np.zeros((h, N_ROWS), bool)
    for i, n in enumerate(USED):
        used[i, rng.permutation(N_ROWS)[:n]] = True
    # what a leaked padded row would bring in
    r = np.where(used, r, 1e3)
    jac = np.where(used[..., None], jac, -1e3)
    return r, jac, used


def _reference(r, jac, used, typical):
    """The screens one heliostat at a time, on its used rows only."""
    h, k = r.shape[0], len(CAND)
    out = dict(p_h=np.full(h, np.nan), theta_h=np.full((h, k), np.nan), q=0.0, k_sum=0, dll_ph=0.0, n_total=0)
    full, res, info, g, gmat, dof_total, per = np.zeros((k, k)), np.zeros((k, k)), np.zeros((k, k)), 0, 0, 0, []
    tested = []
    for i in range(h):
        rows = np.flatnonzero(used[i])
        if rows.size == 0:
            continue
        u = column_basis(jac[i][rows][:, :N_BASE])
        rr = r[i][rows]
        dof = rows.size - u.shape[1]
        if dof <= 0:
            continue
        b = jac[i][rows][:, list(CAND)]
        bt = b - u @ (u.T @ b)
        rt = rr - u @ (u.T @ rr)
        w = dof / (rr @ rr)
        full, res = full + b.T @ b, res + bt.T @ bt
        info = info + w * (bt * typical).T @ (bt * typical)
        g, gmat, dof_total = g + w * bt.T @ rt, gmat + w * bt.T @ bt, dof_total + dof
        out["n_total"] += rows.size
        per.append((rows.size, bt, rt))
        v, s, _ = np.linalg.svd(bt / np.sqrt(np.sum(b * b, axis=0)), full_matrices=False)
        v = v[:, s > 1e-6]
        kh = v.shape[1]
        if kh == 0 or dof - kh <= 0:
            continue
        explained = np.sum((v.T @ rt) ** 2)
        sigma2 = (rt @ rt - explained) / (dof - kh)
        out["p_h"][i] = stats.f.sf(explained / kh / sigma2, kh, dof - kh)
        out["q"] += stats.chi2.isf(out["p_h"][i], kh)
        out["k_sum"] += kh
        tested.append((i, bt, rt, sigma2))
        out["dll_ph"] += rows.size * np.log(rt @ rt / (rt @ rt - explained))
    # the starts under the prior at the hyperprior's scale, chosen on the tested heliostats
    out["scale"], _ = scale_and_penalty([(bt, rt, sigma2, typical) for _, bt, rt, sigma2 in tested])
    for i, bt, rt, sigma2 in tested:
        ridge = bt.T @ bt + sigma2 * np.diag(1.0 / (out["scale"] * typical) ** 2)
        out["theta_h"][i] = -np.linalg.lstsq(ridge, bt.T @ rt, rcond=None)[0]
    ev, vec = np.linalg.eigh(full)
    wf = vec / np.sqrt(ev)
    out["fractions"] = np.sort(1.0 - np.linalg.eigvalsh(wf.T @ res @ wf))
    out["information"] = np.linalg.eigvalsh(info).max()
    out["theta_shared"] = -np.linalg.solve(gmat, g)
    out["stat_shared"] = g @ np.linalg.solve(gmat, g)
    out["p_shared"] = stats.f.sf(out["stat_shared"] / k, k, dof_total - k)
    out["start_shared"] = -np.linalg.solve(gmat + np.diag(1.0 / typical**2), g)
    out["dll_sh"] = sum(n * np.log(rt @ rt / np.sum((rt + bt @ out["theta_shared"]) ** 2)) for n, bt, rt in per)
    return out


def test_batched_screen_equals_the_per_heliostat_computation():
    r, jac, used = _problem()
    typical = np.array([0.4, 1.5])
    bases = prepare_bases(r, jac, used, range(N_BASE), range(len(USED)))
    assert bases.index.tolist() == [2, 3, 4, 5, 6, 7]  # no rows, dof <= 0: left out
    assert np.all(bases.r_res[~bases.used] == 0) and np.all(bases.u[~bases.used] == 0)
    s = screen_candidate("x", bases, jac, CAND, len(USED), ABSORBED_LIMIT, typical=typical)
    ref = _reference(r, jac, used, typical)
    # not tested per heliostat: no rows, dof <= 0, dof - k <= 0
    assert np.flatnonzero(np.isnan(s.p_heliostats)).tolist() == [0, 1, 3]
    assert np.all(np.isnan(s.theta_per_heliostat[[0, 1, 3]]))
    assert s.k_per_heliostat == ref["k_sum"] == 1 + 2 * 4  # the absorbed heliostat tests one direction
    assert s.k_shared == 2
    close = dict(rtol=1e-9, atol=0)
    np.testing.assert_allclose(s.p_heliostats, ref["p_h"], **close)
    # the absorbed column's estimate is 0 to rounding
    assert s.prior_scale == {"shared": 1.0, "per_heliostat": ref["scale"]}
    np.testing.assert_allclose(s.theta_per_heliostat, ref["theta_h"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s.stat_per_heliostat, ref["q"], **close)
    np.testing.assert_allclose(s.p_per_heliostat, stats.chi2.sf(ref["q"], ref["k_sum"]), **close)
    np.testing.assert_allclose(s.fractions, ref["fractions"], rtol=1e-9, atol=1e-12)
    for name in ("information", "theta_shared", "stat_shared", "p_shared", "start_shared"):
        np.testing.assert_allclose(getattr(s, name), ref[name], err_msg=name, **close)
    log_n = np.log(ref["n_total"])
    assert s.approx_delta_bic is not None
    np.testing.assert_allclose(s.approx_delta_bic["per_heliostat"], ref["dll_ph"] - ref["k_sum"] * log_n, **close)
    np.testing.assert_allclose(s.approx_delta_bic["shared"], ref["dll_sh"] - 2 * log_n, **close)
    assert RANK_RTOL < 1e-6  # the absorbed column is cut by the per-heliostat test, not the basis


def test_batched_competitor_forms_equal_the_per_heliostat_computation():
    r, jac, used = _problem(11)
    rng = np.random.default_rng(3)
    design = rng.normal(size=(len(USED), N_ROWS, 4))
    design[5] = 0.0  # a heliostat whose records lack the variable
    noise = rng.uniform(0.5, 2.0, len(USED))
    bases = prepare_bases(r, jac, used, range(N_BASE), range(len(USED)))
    delta, p, size, p_h = _per_heliostat(bases, design, noise, len(USED))
    d_fleet, _, size_fleet = _fleet(bases, design, noise)
    t2 = GENERIC_TYPICAL_MRAD**2
    ref_delta, ref_p, sq, n_sq = 0.0, np.full(len(USED), np.nan), 0.0, 0
    g, gmat, parts = np.zeros(4), np.zeros((4, 4)), []
    # the per-heliostat form's prior at the hyperprior's scale, its choice paid for
    blocks = []
    for i in bases.index:
        rows = np.flatnonzero(used[i])
        u = column_basis(jac[i][rows][:, :N_BASE])
        x = design[i][rows]
        if np.any(x):
            rt = r[i][rows] - u @ (u.T @ r[i][rows])
            blocks.append((x - u @ (u.T @ x), rt, noise[i] ** 2, np.full(4, GENERIC_TYPICAL_MRAD)))
    scale, penalty = scale_and_penalty(blocks)
    t2_scaled = (scale * GENERIC_TYPICAL_MRAD) ** 2
    ref_delta -= penalty
    for i in bases.index:
        rows = np.flatnonzero(used[i])
        u = column_basis(jac[i][rows][:, :N_BASE])
        x = design[i][rows]
        xt, rt, rr = x - u @ (u.T @ x), r[i][rows] - u @ (u.T @ r[i][rows]), r[i][rows]
        s2 = noise[i] ** 2
        g, gmat = g + xt.T @ rt / s2, gmat + xt.T @ xt / s2
        parts.append((rows.size, x, xt, rt, rr))
        if not np.any(x):
            continue
        beta = np.linalg.solve(xt.T @ xt / s2 + np.eye(4) / t2_scaled, xt.T @ rt / s2)
        rss_new = rr @ rr - (rt @ rt - np.sum((rt - xt @ beta) ** 2))
        logdet = np.linalg.slogdet(np.eye(4) + t2_scaled * xt.T @ xt / s2)[1]
        ref_delta += rows.size * np.log(rr @ rr / rss_new) - logdet - beta @ beta / t2_scaled
        sq, n_sq = sq + np.sum((xt @ beta) ** 2), n_sq + rows.size // 2  # the structure it explains
        dof = rows.size - u.shape[1]
        if dof - 4 > 0:
            v = np.linalg.svd(xt, full_matrices=False)[0]
            explained = np.sum((v.T @ rt) ** 2)
            ref_p[i] = stats.f.sf(explained / 4 / ((rt @ rt - explained) / (dof - 4)), 4, dof - 4)
    np.testing.assert_allclose(delta, ref_delta, rtol=1e-9)
    np.testing.assert_allclose(size, np.sqrt(sq / n_sq), rtol=1e-9)
    np.testing.assert_allclose(p_h, ref_p, rtol=1e-9)
    assert np.isnan(p_h[5]) and np.isnan(p_h[3])  # no variable; dof - k <= 0
    assert 0.0 <= p <= 1.0
    beta = np.linalg.solve(gmat + np.eye(4) / t2, g)
    ref_fleet = sum(
        n * np.log(rr @ rr / (rr @ rr - (rt @ rt - np.sum((rt - xt @ beta) ** 2)))) for n, _, xt, rt, rr in parts
    )
    ref_fleet -= np.linalg.slogdet(np.eye(4) + t2 * gmat)[1] + beta @ beta / t2
    np.testing.assert_allclose(d_fleet, ref_fleet, rtol=1e-9)
    ref_size = np.sqrt(sum(np.sum((xt @ beta) ** 2) for _, _, xt, _, _ in parts) / sum(n // 2 for n, *_ in parts))
    np.testing.assert_allclose(size_fleet, ref_size, rtol=1e-9)


def test_each_heliostats_anova_equals_the_anova_of_its_own_records():
    """:func:`anova_each_heliostat` against :func:`anova` of one heliostat's records at a
    time (its bins renumbered), with heliostats below ``2 MIN_PER_BIN`` records in bins,
    with one bin only, and without records."""
    from heliojax.discovery._diagnostics import MIN_PER_BIN, anova, anova_each_heliostat

    rng = np.random.default_rng(5)
    h, m = 7, 30
    idx = rng.integers(0, 6, (h, m))
    idx[rng.random((h, m)) < 0.2] = -1
    idx[1, 2 * MIN_PER_BIN - 1 :] = -1  # too few records
    idx[2] = np.where(idx[2] >= 0, 3, -1)  # one bin
    idx[3] = -1  # none
    idx[4] = np.where(idx[4] >= 0, idx[4] % 2 + 4, -1)  # bins 4 and 5 only
    z = rng.normal(size=(h, m, 2)) + 0.5 * (idx == 1)[..., None]
    p = anova_each_heliostat(z, idx)
    for i in range(h):
        ok = idx[i] >= 0
        expected = np.nan
        if ok.sum() >= 2 * MIN_PER_BIN:
            _, own = np.unique(idx[i][ok], return_inverse=True)
            expected = anova(z[i][ok][None], own[None])[0]
        np.testing.assert_allclose(p[i], expected, rtol=1e-12, err_msg=str(i))
    assert np.flatnonzero(np.isnan(p)).tolist() == [1, 2, 3]


def test_a_direction_the_base_absorbs_is_tested_in_neither_form():
    """A candidate column inside every heliostat's base span holds rounding only after
    the projection: with both columns absorbed nothing is tested (no p from rounding),
    with one absorbed the shared form tests the other alone, as the one-column
    candidate's screen does."""
    rng = np.random.default_rng(4)
    h = 6
    jac = rng.normal(size=(h, N_ROWS, N_BASE + 2))
    for i in range(h):
        jac[i, :, 6] = jac[i, :, :N_BASE] @ rng.normal(size=N_BASE)
    r = jac[:, :, 5] * 0.6 + rng.normal(size=(h, N_ROWS))
    bases = prepare_bases(r, jac, np.ones((h, N_ROWS), bool), range(N_BASE), range(h))
    both = screen_candidate("x", bases, jac, (6,), h, ABSORBED_LIMIT)
    assert not both.tested and both.k_shared == 0 and both.k_per_heliostat == 0 and both.p == 1.0
    np.testing.assert_allclose(both.fractions, [1.0], atol=1e-9)
    pair = screen_candidate("x", bases, jac, (5, 6), h, ABSORBED_LIMIT)
    alone = screen_candidate("x", bases, jac, (5,), h, ABSORBED_LIMIT)
    assert pair.k_shared == 1 and pair.k_per_heliostat == h
    np.testing.assert_allclose(pair.stat_shared, alone.stat_shared, rtol=1e-8)
    np.testing.assert_allclose(pair.p_shared, alone.p_shared, rtol=1e-8)
    assert pair.theta_shared is not None and alone.theta_shared is not None
    # the absorbed column gets no share of the estimate
    np.testing.assert_allclose(pair.theta_shared, [alone.theta_shared[0], 0.0], rtol=1e-6, atol=1e-9)
    assert pair.p_shared < 1e-6  # the free column's 0.6 is found


def _clustered_residuals(rng, h, days, per_day, rho, sigma):
    """``(H, M, 2)`` residuals of ``h`` heliostats with ``per_day`` records on each of
    ``days`` UTC days, a share ``rho`` of the variance common to one heliostat's day."""
    m = days * per_day
    day = np.repeat(np.arange(days), per_day)
    t = (100 + day)[None, :] * 86400.0 + rng.uniform(6, 18, (h, m)) * 3600.0
    shared = rng.normal(size=(h, days, 2))[:, day]
    r = sigma[:, None, None] * (np.sqrt(1 - rho) * rng.normal(size=(h, m, 2)) + np.sqrt(rho) * shared)
    return r, t


def test_day_clustering_is_the_one_way_anova_estimate_and_stays_off_for_independent_records():
    """:func:`day_clustering` against the balanced one-way random-effects estimate written
    out with loops (each heliostat's components standardised by its noise, cluster
    means about the heliostat's mean), its recovery of a planted intra-day correlation,
    and no design effect for independent records (the F test's gate)."""
    from heliojax.fitting import CLUSTERING_ALPHA, day_clustering

    rng = np.random.default_rng(3)
    h, days, per_day, n_params = 6, 12, 3, 4
    sigma = rng.uniform(0.2, 0.6, h)
    r, t = _clustered_residuals(rng, h, days, per_day, 0.4, sigma)
    use = np.ones(t.shape, bool)
    use[0, :per_day] = False  # one heliostat's first day unused
    got = day_clustering(r, use, t, n_params)
    ssb = ssw = 0.0
    n_total = k = 0
    for i in range(h):
        keep = use[i]
        s = np.sqrt(np.sum(r[i][keep] ** 2) / (2 * keep.sum() - n_params))
        z = r[i][keep] / s
        d = np.floor(t[i][keep] / 86400.0)
        for c in range(2):
            mean_h = z[:, c].mean()
            for u in np.unique(d):
                g = z[d == u, c]
                ssb += g.size * (g.mean() - mean_h) ** 2
                ssw += np.sum((g - g.mean()) ** 2)
                k += 1
            n_total += z.shape[0]
    msb, msw = ssb / (k - 2 * h), ssw / (n_total - k)
    # every cluster has per_day records: n0 = per_day, the balanced estimate
    expected = (msb - msw) / (msb + (per_day - 1) * msw)
    assert got.p < CLUSTERING_ALPHA
    np.testing.assert_allclose(got.correlation, expected, rtol=1e-10)
    np.testing.assert_allclose(got.records_per_day, per_day)
    np.testing.assert_allclose(got.design_effect, 1 + (per_day - 1) * expected)
    # many clusters: the planted correlation, to its sampling error
    big = _clustered_residuals(rng, 40, 30, 3, 0.5, np.full(40, 0.3))
    assert abs(day_clustering(*big[:1], np.ones(big[1].shape, bool), big[1], n_params).correlation - 0.5) < 0.06
    # independent records: no design effect (this draw's F test is far from the gate)
    iid = _clustered_residuals(rng, 40, 30, 3, 0.0, np.full(40, 0.3))
    off = day_clustering(iid[0], np.ones(iid[1].shape, bool), iid[1], n_params)
    assert off.p > 0.05 and off.correlation == 0.0
    np.testing.assert_array_equal(off.design_effect, np.ones(40))


def _fitted_clustered_residuals(rng, h, days, per_day, rho, n_cols, use=None):
    """Residuals ``(H, M, 2)`` of a least-squares fit of ``n_cols`` smooth columns per
    component (a constant, slow trends over the days, the hour) to the records ``use``
    (all by default) whose error shares ``rho`` of its variance by day; their times and
    the fit's orthonormal basis ``(H, M, 2, 2 n_cols)`` (zero on unused records)."""
    r, t = _clustered_residuals(rng, h, days, per_day, rho, np.ones(h))
    m = days * per_day
    use = np.ones((h, m), bool) if use is None else use
    season = (t - t.min()) / (t.max() - t.min())
    hour = np.mod(t, 86400.0) / 86400.0
    cols = np.stack([np.ones_like(t), season, season**2, np.sin(6 * season), hour, season * hour], -1)[..., :n_cols]
    x = np.zeros((h, m, 2, 2 * n_cols))
    x[:, :, 0, :n_cols], x[:, :, 1, n_cols:] = cols, cols
    x *= use[..., None, None]
    u = np.linalg.svd(x.reshape(h, 2 * m, -1), full_matrices=False)[0]
    y = r.reshape(h, 2 * m)
    fitted = np.einsum("hrc,hc->hr", u, np.einsum("hrc,hr->hc", u, y))
    return (y - fitted).reshape(h, m, 2), t, u.reshape(h, m, 2, -1)


def test_day_clustering_allows_for_what_the_fit_absorbed():
    """The residuals' analysis of variance finds the intra-day correlation too small
    when the fitted parameters take up part of each day's shared error (a trend over
    the days absorbs day means); with the fit's basis the method-of-moments estimate
    recovers the planted one, and equals a second computation with every projector
    written out densely (heliostat by heliostat)."""
    from scipy import optimize

    from heliojax.fitting import day_clustering, day_labels

    rng = np.random.default_rng(11)
    for rho in (0.2, 0.5):
        plain, moments = [], []
        for _ in range(4):
            r, t, u = _fitted_clustered_residuals(rng, 30, 10, 4, rho, 6)
            use = np.ones(t.shape, bool)
            plain.append(day_clustering(r, use, t, 12).correlation)
            moments.append(day_clustering(r, use, t, 12, basis=u).correlation)
        assert np.mean(plain) < rho - 0.08  # what the fit absorbed, taken for independence
        assert abs(np.mean(moments) - rho) < 0.04, (rho, moments)
    # the second computation: M = I - U U^T, Z the (day, component) indicators, A the
    # projector on the cluster means, B = I - A, on a heliostat's used rows
    use = np.ones((6, 24), bool)
    use[1, :2] = False
    r, t, u = _fitted_clustered_residuals(rng, 6, 8, 3, 0.5, 3, use)
    h, m = use.shape
    sums = np.zeros((6, h))  # |z|^2, |B z|^2, tr M, |M Z|^2, tr(B M), |B M Z|^2
    for i in range(h):
        keep = np.repeat(use[i], 2)
        ui = u[i].reshape(2 * m, -1)[keep] * 1.0
        ui = ui[:, np.linalg.norm(ui, axis=0) > 0]
        ri = r[i].reshape(-1)[keep]
        z = ri / np.sqrt(ri @ ri / (keep.sum() - 6))
        label = day_labels(np.repeat(t[i], 2))[keep] * 2 + np.tile([0, 1], m)[keep]
        zmat = (label[:, None] == np.unique(label)[None, :]).astype(float)
        a = zmat @ np.linalg.inv(zmat.T @ zmat) @ zmat.T
        b = np.eye(keep.sum()) - a
        mm = np.eye(keep.sum()) - ui @ ui.T
        mz = mm @ zmat
        sums[:, i] = [z @ z, z @ b @ z, np.trace(mm), np.sum(mz**2), np.trace(b @ mm), np.sum((b @ mz) ** 2)]
    qt, qw, t1, t2, w1, w2 = sums

    def excess(c):
        return np.sum(qt * ((1 - c) * w1 + c * w2) / ((1 - c) * t1 + c * t2)) - np.sum(qw)

    expected = optimize.brentq(excess, 0.0, 0.99, xtol=1e-12) if excess(0.0) > 0 else 0.0
    got = day_clustering(r, use, t, 6, basis=u)
    assert got.p < 0.01 and expected > 0.2  # this draw's test rejects independence
    np.testing.assert_allclose(got.correlation, expected, rtol=1e-6)


def test_day_whitened_rss_is_the_quadratic_form_of_the_random_day_effect_covariance():
    """:func:`day_whitened_rss` against ``r^T R^-1 r`` with ``R`` written out densely and
    solved (clusters: row set, UTC day, component; a record without a time alone), the
    plain sum of squares at ``rho = 0``, and unused rows counting nothing."""
    from heliojax.discovery._diagnostics import day_whitened_rss
    from heliojax.fitting import day_labels

    rng = np.random.default_rng(5)
    s, m, rho = 3, 9, 0.35
    t = (200 + rng.integers(0, 3, (s, m))) * 86400.0 + rng.uniform(0, 86000, (s, m))
    t[1, 4] = np.nan
    day = day_labels(t)
    rows = rng.normal(size=(s, 2 * m))
    used = np.ones((s, 2 * m), bool)
    used[2, 6:10] = False  # records 3 and 4 of the third row set
    got = day_whitened_rss(rows, used, day, rho)
    for i in range(s):
        keep = np.flatnonzero(used[i])
        key = [(day[i, j // 2] if np.isfinite(t[i, j // 2]) else -1000 - j // 2, j % 2) for j in keep]
        same = np.array([[a == b for b in key] for a in key], float)
        cov = (1 - rho) * np.eye(keep.size) + rho * same
        x = rows[i, keep]
        np.testing.assert_allclose(got[i], x @ np.linalg.solve(cov, x), rtol=1e-12)
    np.testing.assert_allclose(day_whitened_rss(rows, used, day, 0.0), np.sum(np.where(used, rows, 0) ** 2, axis=1))
    with pytest.raises(ValueError, match="below 1"):
        day_whitened_rss(rows, used, day, 1.0)


def test_whitened_evidence_of_a_day_constant_regressor_is_calibrated_under_day_clustered_noise():
    """Under noise of which a share ``rho`` is common to a day's records, the likelihood
    ratio of a regressor that is constant within each day (a slow drift) is inflated by
    ordinary least squares (about Kish's design effect) and chi-square with 1 degree of
    freedom (mean 1) after :func:`day_whitened_rss`; a regressor that varies within
    the day keeps nearly all of its evidence: the reason the criterion whitens instead
    of dividing every record by the design effect."""
    from heliojax.discovery._diagnostics import day_whitened_rss

    rng = np.random.default_rng(11)
    reps, days, per_day, rho = 2000, 20, 4, 0.5
    m = days * per_day
    day_of = np.repeat(np.arange(days), per_day)
    day = np.broadcast_to(day_of, (reps, m))
    shared = rng.normal(size=(reps, days, 2))[:, day_of]
    noise = np.sqrt(1 - rho) * rng.normal(size=(reps, m, 2)) + np.sqrt(rho) * shared
    rows = noise.reshape(reps, 2 * m)
    used = np.ones(rows.shape, bool)

    def likelihood_ratios(x):
        """``n log(Q0 / Q1)`` for the one-column fit ``x`` ``(2M,)`` by least squares,
        plain and whitened (the fit itself by generalised least squares for the latter:
        the whitened sum of squares is a quadratic form, minimised in closed form)."""
        n = 2 * m
        plain0 = np.sum(rows**2, axis=1)
        beta = rows @ x / (x @ x)
        plain1 = np.sum((rows - beta[:, None] * x) ** 2, axis=1)
        q = lambda v: day_whitened_rss(v, used, day, rho)  # noqa: E731
        qx = q(np.broadcast_to(x, rows.shape))
        cross = (q(rows + x) - q(rows - x)) / 4.0  # the bilinear form r^T R^-1 x
        white0 = q(rows)
        white1 = white0 - cross**2 / qx
        return n * np.log(plain0 / plain1), n * np.log(white0 / white1)

    drift = np.repeat((day_of - days / 2) / days, 2)  # constant within a day
    plain, white = likelihood_ratios(drift)
    deff = 1 + (per_day - 1) * rho
    assert abs(plain.mean() / deff - 1) < 0.15  # inflated by the design effect
    assert abs(white.mean() - 1) < 0.1 and abs(np.mean(white > 3.841) - 0.05) < 0.015
    # a regressor varying within the day: its noise-only ratio is calibrated as well,
    # and a real effect of it keeps its evidence (far from being divided by deff)
    wobble = np.sin(np.arange(2 * m) * 1.7)
    _, white_null = likelihood_ratios(wobble)
    assert abs(white_null.mean() - 1) < 0.1


def test_held_out_improvement_is_tested_over_days_and_keeps_its_level_under_day_clustered_noise():
    """:func:`cv_improvement_p` under held-out noise of which half is common to a day's
    records, for a refit whose extra column is constant within a day (a temperature)
    and whose coefficient was fitted to noise only: rejection at 5 % stays at or below
    5 % (a t test over records instead rejects far more often: the shared error made
    evidence), and a real effect of that column is found (p < 0.01 in most draws)."""
    from types import SimpleNamespace

    from heliojax.discovery._report import cv_improvement_p

    rng = np.random.default_rng(21)
    reps, heliostats, days, per_day, rho = 400, 8, 10, 8, 0.5
    m = days * per_day
    day = np.broadcast_to(np.repeat(np.arange(days), per_day), (heliostats, m))
    lane = np.arange(heliostats)

    def draw(effect: float) -> tuple[float, float]:
        g = rng.normal(size=(heliostats, days))[:, day[0]]  # the column, constant within a day
        shared = rng.normal(size=(heliostats, days, 2))[:, day[0]]
        noise = np.sqrt(1 - rho) * rng.normal(size=(heliostats, m, 2)) + np.sqrt(rho) * shared
        fitted = effect + rng.normal(0.0, 0.03)  # the coefficient of the training folds
        before = noise + effect * g[..., None]
        after = before - fitted * g[..., None]
        b, a = np.sum(before**2, axis=-1), np.sum(after**2, axis=-1)
        p = cv_improvement_p(SimpleNamespace(heldout_sq=b), SimpleNamespace(heldout_sq=a), lane, day)
        d = (a - b).reshape(-1)
        naive = stats.t.cdf(d.mean() / (d.std(ddof=1) / np.sqrt(d.size)), d.size - 1)
        return p, naive

    null = np.array([draw(0.0) for _ in range(reps)])
    assert np.all((null[:, 0] >= 0) & (null[:, 0] <= 1))
    assert np.mean(null[:, 0] < 0.05) <= 0.06
    assert np.mean(null[:, 1] < 0.05) > 2 * np.mean(null[:, 0] < 0.05) + 0.02
    real = np.array([draw(0.5)[0] for _ in range(100)])
    assert np.mean(real < 0.01) > 0.8
    # unknown times: every record a day of its own; too few days: no verdict (NaN)
    one = SimpleNamespace(heldout_sq=np.ones((1, 2)))
    assert np.isnan(cv_improvement_p(one, one, np.zeros(1, int), np.zeros((1, 2), int)))
