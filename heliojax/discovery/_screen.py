"""Screening: score tests of every candidate on the current model's residuals.

At the current model's least-squares solution, with per heliostat ``h`` the
residuals ``r_h`` (``n_h`` tangent-plane components, mrad), the Jacobian
``A_h`` of the current model's free parameters and the candidate's columns
``B_h``, everything is projected off ``span(A_h)``::

    r~_h = (I - P_h) r_h          B~_h = (I - P_h) B_h

so the statistics measure only what the current parameters cannot explain
(the score test, Rao 1948; for a model linear in the candidate it equals the
likelihood-ratio test). Two forms, because an effect may be common to the
fleet or individual per heliostat:

* **per heliostat** (``k`` parameters each): ``S_h = |P_{B~_h} r~_h|^2`` and
  ``F_h = (S_h / k_h) / ((RSS_h - S_h) / (n_h - p_h - k_h))`` is
  ``F(k_h, n_h - p_h - k_h)`` under the null (Gaussian noise, exact for a model
  linear in its parameters; each heliostat has its own noise level). Each
  ``F_h`` is mapped to the chi-square quantile of its p-value and the sum is
  chi-square with ``sum k_h`` degrees of freedom (independent heliostats).
* **shared** (``k`` parameters for the fleet): with ``w_h = (n_h - p_h) / RSS_h``
  (inverse noise variance), ``g = sum w_h B~_h^T r~_h``,
  ``G = sum w_h B~_h^T B~_h``, the score statistic ``g^T G^+ g`` over ``k`` is
  referred to ``F(k, sum(n_h - p_h) - k)``.

A candidate the model largely absorbs (not identifiable,
:mod:`._identifiability`) is still tested on its remainder: its effect may be
real and only partly mimicked by the model, and leaving it out of the family
would hand its unabsorbed remainder to whichever other candidate resembles it.

The candidate's p-value is the Bonferroni combination of the two,
``min(1, 2 min(p_shared, p_per_heliostat))``; the family of candidates is then
controlled by Holm's step-down procedure (:mod:`._select`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import stats

from ._identifiability import (
    PRECISION_INFORMATION,
    RANK_RTOL,
    absorbed_fractions,
    column_basis,
    is_identifiable,
)


@dataclasses.dataclass(frozen=True)
class HeliostatBasis:
    """One heliostat's projected residuals at the current model.

    Attributes:
        index: heliostat index in the fleet.
        rows: indices of the used residual rows.
        u: orthonormal basis of ``span(A_h)`` on those rows.
        r_res: ``(I - P_h) r_h``.
        rss: ``|r_h|^2`` (mrad^2).
        n: used residual components.
        dof: ``n - rank(A_h)``.
    """

    index: int
    rows: np.ndarray
    u: np.ndarray
    r_res: np.ndarray
    rss: float
    n: int
    dof: int


def prepare_bases(r: np.ndarray, jac: np.ndarray, used_rows: np.ndarray, a_cols, heliostats) -> list[HeliostatBasis]:
    """Per heliostat ``h`` in ``heliostats``: the basis of its current model's
    columns ``a_cols`` and the projected residuals (rows ``used_rows[h]``)."""
    out = []
    for h in heliostats:
        rows = np.nonzero(used_rows[h])[0]
        if rows.size == 0:
            continue
        a = jac[h][rows][:, list(a_cols)]
        u = column_basis(a)
        rr = r[h][rows]
        r_res = rr - u @ (u.T @ rr)
        dof = rows.size - u.shape[1]
        if dof <= 0:
            continue
        out.append(HeliostatBasis(int(h), rows, u, r_res, float(rr @ rr), int(rows.size), int(dof)))
    return out


@dataclasses.dataclass(frozen=True)
class CandidateScreen:
    """Screening outcome of one candidate at one step.

    Attributes:
        effect: the candidate's name.
        fractions: absorbed fractions of its directions (ascending).
        testable: the data drive the candidate at all.
        identifiable: some direction is absorbed less than the limit, or a
            typical-size effect's remainder is still measured to +-25 % (2 sigma).
        information: noncentrality of a typical-size effect's non-absorbed
            remainder (best direction, shared form): ``(2 / 0.25)^2 = 64`` or more
            measures it to +-25 % at 2 sigma.
        tested: score tests were computed on the non-absorbed remainder (every
            testable candidate with some direction not absorbed to 1 - 1e-12);
            a tested candidate that is not ``identifiable`` is *partly absorbed*:
            it competes on its remainder and is reported with its absorbed fraction.
        p_shared, p_per_heliostat, p: score-test p-values (``p`` combines the two).
        stat_shared, k_shared: shared score statistic and its dimension.
        stat_per_heliostat, k_per_heliostat: chi-square sum and its dimension.
        theta_shared: ``(k,)`` one-step (Gauss-Newton) estimate of the shared
            parameters on the directions the data determine, scaled units (the
            linearised delta BIC's).
        start_shared: ``(k,)`` the shared refit's start: the one-step estimate under
            the refit's Gaussian prior of the parameters' typical sizes about no
            effect (its shared step's normal equations at the current model), scaled
            units; zeros where not tested.
        theta_per_heliostat: ``(H, k)`` per-heliostat one-step estimates under a
            Gaussian prior of the parameters' typical sizes about no effect (the refits'
            prior with ``effect_prior``; a refit's start either way), NaN where not
            tested, scaled units.
        p_heliostats: ``(H,)`` per-heliostat p-values (NaN where not tested).
        approx_delta_bic: ``{"shared": .., "per_heliostat": ..}`` linearised delta BIC.
    """

    effect: str
    fractions: np.ndarray
    testable: bool
    identifiable: bool
    information: float = 0.0
    tested: bool = False
    p_shared: float = 1.0
    p_per_heliostat: float = 1.0
    p: float = 1.0
    stat_shared: float = 0.0
    k_shared: int = 0
    stat_per_heliostat: float = 0.0
    k_per_heliostat: int = 0
    theta_shared: np.ndarray | None = None
    start_shared: np.ndarray | None = None
    theta_per_heliostat: np.ndarray | None = None
    p_heliostats: np.ndarray | None = None
    approx_delta_bic: dict | None = None

    @property
    def absorbed_fraction(self) -> float | None:
        return float(self.fractions.min()) if self.fractions.size else None


def chi2_equivalent(p: float, k: int) -> float:
    """Chi-square(k) quantile of upper-tail probability ``p`` (``inf`` for p = 0)."""
    if p <= 0.0:
        return np.inf
    return float(stats.chi2.isf(p, k))


def directions_f_test(directions: np.ndarray, r_res: np.ndarray, dof: int) -> tuple[float, float, float]:
    """The F test of one heliostat's residual ``r_res`` (``(n,)``, the base's
    residual, its own parameters profiled out: ``dof`` degrees of freedom) along
    ``k`` orthonormal ``directions`` ``(n, k)`` (exact for Gaussian noise).

    Returns:
        ``(p, explained, noise_variance)``: the upper-tail probability of
        ``F(k, dof - k)``, the residual's squared norm along the directions and the
        variance of what is left per degree of freedom."""
    k = directions.shape[1]
    proj = directions.T @ r_res
    explained = float(proj @ proj)
    noise_variance = max(float(r_res @ r_res) - explained, 1e-300) / (dof - k)
    return float(stats.f.sf((explained / k) / noise_variance, k, dof - k)), explained, noise_variance


def screen_candidate(
    effect: str,
    bases: list[HeliostatBasis],
    jac: np.ndarray,
    cols,
    n_heliostats: int,
    absorbed_limit: float,
    typical=None,
) -> CandidateScreen:
    """Score tests and identifiability of the candidate with solver columns ``cols``
    (``typical``: its typical sizes in solver units, default 1)."""
    cols = list(cols)
    k = len(cols)
    typical = np.ones(k) if typical is None else np.asarray(typical, float)
    b_list, bt_list = [], []
    info = np.zeros((k, k))
    for hb in bases:
        b = jac[hb.index][hb.rows][:, cols]
        bt = b - hb.u @ (hb.u.T @ b)
        b_list.append(b)
        bt_list.append(bt)
        bt_typ = bt * typical
        info += (hb.dof / max(hb.rss, 1e-300)) * (bt_typ.T @ bt_typ)
    fractions = absorbed_fractions(b_list, bt_list)
    information = float(np.linalg.eigvalsh(info).max()) if k else 0.0
    testable = fractions.size > 0
    identifiable = testable and (is_identifiable(fractions, absorbed_limit) or information >= PRECISION_INFORMATION)
    if not testable:
        return CandidateScreen(effect, fractions, testable, identifiable, information)

    n_total = sum(hb.n for hb in bases)
    theta_h = np.full((n_heliostats, k), np.nan)
    p_h = np.full(n_heliostats, np.nan)
    q_sum, k_sum = 0.0, 0
    dll_perhel = 0.0
    g = np.zeros(k)
    gmat = np.zeros((k, k))
    dof_total = 0
    for hb, b, bt in zip(bases, b_list, bt_list):
        dof_total += hb.dof
        scale = np.sqrt(np.maximum(np.sum(b * b, axis=0), 1e-300))
        u, s, _ = np.linalg.svd(bt / scale, full_matrices=False)
        # Directions absorbed to 1 - 1e-12 (or without driving data) carry no information.
        keep = s > 1e-6
        kh = int(keep.sum())
        if kh and hb.dof - kh > 0:
            p_val, s_h, denom = directions_f_test(u[:, keep], hb.r_res, hb.dof)
            rss_res = float(hb.r_res @ hb.r_res)
            p_h[hb.index] = p_val
            q_sum += chi2_equivalent(p_val, kh)
            k_sum += kh
            # The refit's start: the one-step estimate under the refit's own prior (each
            # parameter's typical size, this heliostat's noise), not the bare one, which
            # divides by singular values down to 1e-6 and put a nearly absorbed
            # direction's start (a survey offset per heliostat) so far out that the
            # refit ended in another minimum (held-out 0.37 -> 45 mrad, 1,000 x 60).
            ridge = bt.T @ bt + denom * np.diag(1.0 / np.maximum(typical, 1e-300) ** 2)  # denom: noise variance
            theta_h[hb.index] = -np.linalg.lstsq(ridge, bt.T @ hb.r_res, rcond=None)[0]  # no raise if singular
            dll_perhel += hb.n * np.log(max(rss_res, 1e-300) / max(rss_res - s_h, 1e-300))
        w = hb.dof / max(hb.rss, 1e-300)
        g += w * (bt.T @ hb.r_res)
        gmat += w * (bt.T @ bt)

    p_perhel = float(stats.chi2.sf(q_sum, k_sum)) if k_sum else 1.0
    # Shared: restrict to the directions G determines.
    ev, vec = np.linalg.eigh(gmat)
    keep = ev > (ev.max() * RANK_RTOL if ev.size and ev.max() > 0 else np.inf)
    ks = int(keep.sum())
    if ks:
        z = vec[:, keep].T @ g
        stat_shared = float(np.sum(z**2 / ev[keep]))
        theta_shared = -(vec[:, keep] @ (z / ev[keep]))
        p_shared = float(stats.f.sf(stat_shared / ks, ks, max(dof_total - ks, 1)))
    else:
        stat_shared, theta_shared, p_shared = 0.0, np.zeros(k), 1.0
    # The refit's start: the same step under its prior (precision 1 / typical^2 in the
    # units of w r^2, none where no typical size is documented). The bare estimate
    # goes far out along weakly determined directions, which the prior pulls back:
    # its first shared step was worth up to 35,000 in chi-square on the shared
    # records, and every refit of a shared form took two more expansion iterations.
    precision = np.where(typical > 0, 1.0 / np.where(typical > 0, typical, 1.0) ** 2, 0.0)
    start_shared = -np.linalg.pinv(gmat + np.diag(precision), rcond=1e-10, hermitian=True) @ g
    p = min(1.0, 2.0 * min(p_shared, p_perhel))
    log_n = np.log(max(n_total, 2))
    # Linearised change of -2 log L (each heliostat its own noise level) of the
    # shared one-step estimate, comparable with the per-heliostat one.
    dll_shared = 0.0
    for hb, bt in zip(bases, bt_list):
        rss0 = float(hb.r_res @ hb.r_res)
        new = hb.r_res + bt @ theta_shared
        dll_shared += hb.n * np.log(max(rss0, 1e-300) / max(float(new @ new), 1e-300))
    approx = {
        "shared": dll_shared - ks * log_n,
        "per_heliostat": dll_perhel - k_sum * log_n,
    }
    return CandidateScreen(
        effect,
        fractions,
        testable,
        identifiable,
        information,
        tested=bool(k_sum or ks),
        p_shared=p_shared,
        p_per_heliostat=p_perhel,
        p=p,
        stat_shared=stat_shared,
        k_shared=ks,
        stat_per_heliostat=q_sum,
        k_per_heliostat=k_sum,
        theta_shared=theta_shared,
        start_shared=start_shared,
        theta_per_heliostat=theta_h,
        p_heliostats=p_h,
        approx_delta_bic=approx,
    )


def holm(pvalues: dict[str, float], alpha: float) -> tuple[dict[str, float], set[str]]:
    """Holm's step-down procedure: adjusted p-values and the rejected hypotheses
    at family-wise error rate ``alpha``."""
    names = sorted(pvalues, key=lambda n: (pvalues[n], n))
    m = len(names)
    adjusted = {}
    running = 0.0
    for i, n in enumerate(names):
        running = max(running, min(1.0, (m - i) * pvalues[n]))
        adjusted[n] = running
    rejected = {n for n in names if adjusted[n] <= alpha}
    return adjusted, rejected
