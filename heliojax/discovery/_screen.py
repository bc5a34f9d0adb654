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

Every heliostat is computed at once, on one padded stack (:class:`HeliostatBases`:
the fleet's residual rows, zero where a heliostat does not use them, so that a
heliostat's projections and the sums over heliostats are those of its own rows);
no Python loop runs over the heliostats (1,000 heliostats x 60 records: ~25 ms a
candidate, where a loop over them took ~175 ms).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Bool, Float, Int
from scipy import special, stats

from .._limits import real_problem
from ._identifiability import (
    PRECISION_INFORMATION,
    RANK_RTOL,
    absorbed_fractions,
    column_bases,
    is_identifiable,
)

ROUNDING_ONLY = 1e-12
"""Share of a candidate direction's (unit-norm) size left after the base's projection
below which it holds rounding only (absorbed to ``1 - 1e-12``): neither form tests it
(:func:`heliostat_directions`, :func:`shared_score`; the generic competitors' tests too)."""


PRIOR_SCALES = 2.0 ** np.arange(-3.0, 4.0)
"""Factors on a per-heliostat effect's documented typical sizes over which the scale of
its prior is uncertain: a log-uniform hyperprior on 1/8 to 8 times the typical size
(seven points a factor 2 apart). The typical sizes are a priori guesses; an effect four
times as large as its guess (a 0.2 m survey error of each heliostat against 0.05 m) was
held by the prior until a smaller effect of another name explained the residuals better
(independent simulator, seed 11709). A per-heliostat refit takes the scale of largest
evidence (:func:`best_prior_scale`), and its criterion averages the evidence over the
hyperprior (:func:`hyperprior_penalty`), so the choice is paid for: the scale is a
fleet-level hyperparameter that the heliostats' parameters, many draws of the prior,
determine (empirical Bayes). The shared form keeps its prior at the typical size: its
one draw says nothing about the prior's scale (tried: on the independent simulator a
wind load outside the library was then named `wind` against the wind-vector
competitor, and on the shared records the held-out RMS grew 17 %)."""


def scale_profile(
    info: Float[np.ndarray, "B k k"], score: Float[np.ndarray, "B k"], scales: np.ndarray
) -> Float[np.ndarray, " K"]:
    """``-2 log`` Bayes factor of an effect against no effect at each prior scale, summed
    over independent blocks (heliostats), for a model linear in the effect with known
    noise: per block ``log det(I + s^2 F) - s^2 g^T (I + s^2 F)^-1 g``.

    Args:
        info: ``F``, the information on the effect's parameters left by the rest of the
            model (chi-square units, parameters in units of their prior's standard
            deviation at scale 1).
        score: ``g = J^T r / sigma^2`` at no effect, in the same units.
        scales: ``(K,)`` prior scales ``s`` (the prior is ``N(0, s^2 I)``).
    """
    k = info.shape[-1]
    s2 = np.asarray(scales, float) ** 2
    m = np.eye(k) + s2[:, None, None, None] * info[None]  # (K, B, k, k)
    _, logdet = np.linalg.slogdet(m)
    solved = np.linalg.solve(m, np.broadcast_to(score[None, ..., None], (*m.shape[:-1], 1)))[..., 0]
    quad = s2[:, None] * np.sum(score[None] * solved, axis=-1)
    return np.sum(logdet - quad, axis=1)


def best_prior_scale(info: Float[np.ndarray, "B k k"], score: Float[np.ndarray, "B k"]) -> float:
    """The scale of :data:`PRIOR_SCALES` of largest evidence (arguments as
    :func:`scale_profile`'s); 1 where no block is given or none is better than 1."""
    if not info.shape[0]:
        return 1.0
    e = scale_profile(info, score, PRIOR_SCALES)
    best = int(np.argmin(e))
    return float(PRIOR_SCALES[best]) if e[best] < e[PRIOR_SCALES.tolist().index(1.0)] - 1e-9 else 1.0


def hyperprior_penalty(info: Float[np.ndarray, "B k k"], score: Float[np.ndarray, "B k"], at: float) -> float:
    """``-2 log`` of the evidence averaged over the hyperprior on the prior's scale
    (:data:`PRIOR_SCALES`, equal weights) relative to the evidence at scale ``at``, the
    scale the effect was fitted with; ``info`` and ``score`` are in units of that
    prior (:func:`scale_profile`). At most ``2 log 7`` (3.9) where ``at`` is the best
    scale; ~0 where the evidence is flat in the scale."""
    if not info.shape[0]:
        return 0.0
    e = scale_profile(info, score, np.append(PRIOR_SCALES / at, 1.0))
    return float(-2.0 * (special.logsumexp(-0.5 * (e[:-1] - e[-1])) - np.log(PRIOR_SCALES.size)))


@dataclasses.dataclass(frozen=True)
class HeliostatBases:
    """The projected residuals at the current model of the heliostats screened, one
    padded stack: ``S`` heliostats (those with used residual rows and residual degrees
    of freedom), each on the fleet's first ``R`` residual rows (up to the last one any
    heliostat uses). Every array is zero on a heliostat's unused rows, so they add
    nothing to an inner product or a sum over rows.

    Attributes:
        index: ``(S,)`` heliostat index in the fleet.
        used: ``(S, R)`` the used residual rows.
        u: ``(S, R, c)`` orthonormal basis of ``span(A_h)`` on those rows (columns
            beyond ``rank(A_h)`` zero).
        r_res: ``(S, R)`` ``(I - P_h) r_h``.
        rss: ``(S,)`` ``|r_h|^2`` (mrad^2).
        n: ``(S,)`` used residual components.
        dof: ``(S,)`` ``n - rank(A_h)`` (positive).
    """

    index: Int[np.ndarray, " S"]
    used: Bool[np.ndarray, "S R"]
    u: Float[np.ndarray, "S R c"]
    r_res: Float[np.ndarray, "S R"]
    rss: Float[np.ndarray, " S"]
    n: Int[np.ndarray, " S"]
    dof: Int[np.ndarray, " S"]

    def __len__(self) -> int:
        return int(self.index.size)

    def rows(self, x: Float[np.ndarray, "H _ k"]) -> Float[np.ndarray, "S R k"]:
        """The screened heliostats' used rows of a fleet array ``x`` ``(H, R', k)``,
        ``R' >= R`` (zero elsewhere)."""
        return np.where(self.used[..., None], np.asarray(x)[self.index, : self.used.shape[1]], 0.0)

    def columns(self, jac: Float[np.ndarray, "H _ P"], cols) -> Float[np.ndarray, "S R k"]:
        """The columns ``cols`` of the fleet's Jacobian ``jac`` on the used rows."""
        # np.take before indexing the heliostats: only the k columns are gathered
        return self.rows(np.take(jac, list(cols), axis=2))

    def project(self, x: Float[np.ndarray, "S R k"]) -> Float[np.ndarray, "S R k"]:
        """``(I - P_h) x_h`` of every heliostat."""
        return x - self.u @ (self.u.swapaxes(1, 2) @ x)


def prepare_bases(r: np.ndarray, jac: np.ndarray, used_rows: np.ndarray, a_cols, heliostats) -> HeliostatBases:
    """Per heliostat ``h`` in ``heliostats``: the basis of its current model's
    columns ``a_cols`` and the projected residuals (rows ``used_rows[h]``), those
    without used rows or residual degrees of freedom left out.

    Args:
        r: ``(H, R)`` residual components (mrad).
        jac: ``(H, R, P)`` their Jacobian.
        used_rows: ``(H, R)`` the rows to use.
        a_cols: the current model's free columns.
        heliostats: the heliostats to screen (fleet indices).
    """
    index = np.asarray(list(heliostats), np.int64)
    used = np.asarray(used_rows, bool)[index]
    # rows up to the last one used: a padded fleet's trailing rows would only cost time
    width = int(np.flatnonzero(used.any(axis=0)).max()) + 1 if used.any() else 0
    used = used[:, :width]
    n = used.sum(axis=1)
    a = np.where(used[..., None], np.take(np.asarray(jac)[:, :width], list(a_cols), axis=2)[index], 0.0)
    u, rank = column_bases(a)
    u = u * used[..., None]  # exactly zero on the unused rows
    keep = (n > 0) & (n - rank > 0)
    used, u, n, rank, index = used[keep], u[keep], n[keep], rank[keep], index[keep]
    rr = np.where(used, np.asarray(r)[index, :width], 0.0)
    r_res = rr - (u @ (u.swapaxes(1, 2) @ rr[..., None]))[..., 0]
    return HeliostatBases(index, used, u, r_res, np.sum(rr * rr, axis=1), n, n - rank)


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
        prior_scale: ``{"shared": 1, "per_heliostat": ..}`` the factor on the
            typical sizes that the starts above and the refit's prior take: per
            heliostat, the one of largest linearised evidence
            (:func:`best_prior_scale`); shared, 1 (:data:`PRIOR_SCALES`).
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
    prior_scale: dict = dataclasses.field(default_factory=lambda: {"shared": 1.0, "per_heliostat": 1.0})

    @property
    def absorbed_fraction(self) -> float | None:
        return float(self.fractions.min()) if self.fractions.size else None


def chi2_equivalent(p: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Chi-square(k) quantiles of upper-tail probabilities ``p`` (``inf`` where p = 0),
    elementwise."""
    p = np.asarray(p, float)
    positive = p > 0.0
    return np.where(positive, stats.chi2.isf(np.where(positive, p, 1.0), np.maximum(k, 1)), np.inf)


def directions_f_tests(
    directions: Float[np.ndarray, "S R k"],
    keep: Bool[np.ndarray, "S k"],
    r_res: Float[np.ndarray, "S R"],
    dof: Int[np.ndarray, " S"],
) -> tuple[Bool[np.ndarray, " S"], Float[np.ndarray, " S"], Float[np.ndarray, " S"], Float[np.ndarray, " S"]]:
    """The F test of each heliostat's residual ``r_res`` (the base's residual, its own
    parameters profiled out: ``dof`` degrees of freedom) along its orthonormal
    ``directions`` where ``keep`` (``k_h`` of them; exact for Gaussian noise).

    Returns:
        ``(tested, p, explained, noise_variance)``: whether the test exists
        (``k_h > 0`` and ``dof - k_h > 0``), the upper-tail probability of
        ``F(k_h, dof - k_h)`` (NaN where not tested), the residual's squared norm along
        the directions and the variance of what is left per degree of freedom (NaN
        where not tested)."""
    k = keep.sum(axis=1)
    tested = (k > 0) & (dof - k > 0)
    proj = (directions.swapaxes(1, 2) @ r_res[..., None])[..., 0]
    explained = np.sum(np.where(keep, proj * proj, 0.0), axis=1)
    left = np.where(tested, dof - k, 1)
    noise_variance = np.maximum(np.sum(r_res * r_res, axis=1) - explained, 1e-300) / left
    f = (explained / np.maximum(k, 1)) / noise_variance
    p = np.where(tested, stats.f.sf(f, np.maximum(k, 1), left), np.nan)
    return tested, p, explained, np.where(tested, noise_variance, np.nan)


def minimum_norm_solve(a: Float[np.ndarray, "S k k"], b: Float[np.ndarray, "S k"]) -> Float[np.ndarray, "S k"]:
    """``np.linalg.lstsq(a_s, b_s, rcond=None)`` of every matrix of the stack: the
    minimum-norm least-squares solution, singular values up to ``eps * k`` of the
    largest treated as zero (no raise where singular)."""
    u, s, vt = np.linalg.svd(a)
    nonzero = s > np.finfo(float).eps * max(a.shape[-2:]) * s[:, :1]
    z = np.where(nonzero, (u.swapaxes(1, 2) @ b[..., None])[..., 0] / np.where(nonzero, s, 1.0), 0.0)
    return (vt.swapaxes(1, 2) @ z[..., None])[..., 0]


def weighted_gram(w: Float[np.ndarray, " S"], x: Float[np.ndarray, "S R k"], y: np.ndarray) -> np.ndarray:
    """``sum_s w_s x_s^T y_s`` (``y`` ``(S, R, j)`` or ``(S, R)``)."""
    return np.tensordot(w[:, None, None] * x, y, axes=([0, 1], [0, 1]))


def heliostat_directions(
    b: Float[np.ndarray, "S R k"], bt: Float[np.ndarray, "S R k"]
) -> tuple[Float[np.ndarray, "S R k"], Bool[np.ndarray, "S k"]]:
    """The directions the per-heliostat tests use: an orthonormal basis of each
    heliostat's projected columns ``bt = (I - P_h) b`` (any units: every column of
    ``b`` is first scaled to unit norm on the heliostat's rows, so that its singular
    values are shares of an unprojected size) and the directions that hold more than
    rounding, ``s^2 > ROUNDING_ONLY`` (:data:`ROUNDING_ONLY`).

    A direction the base absorbs to ``1 - 1e-12``, or one no record drives (a zero
    column), carries no information: a cut relative to the largest singular value
    alone kept a fully absorbed candidate's directions and tested rounding as if it
    were its remainder.

    Returns:
        ``(u, keep)``: ``(S, R, k)`` the left singular vectors (unit norm, zero on
        unused rows) and ``(S, k)`` those kept (the input of
        :func:`directions_f_tests`).
    """
    scale = np.sqrt(np.maximum(np.sum(b * b, axis=1), 1e-300))  # (S, k)
    u, s, _ = np.linalg.svd(bt / scale[:, None, :], full_matrices=False)
    return u, s**2 > ROUNDING_ONLY


def shared_score(
    w: Float[np.ndarray, " S"],
    b: Float[np.ndarray, "S R k"],
    g: Float[np.ndarray, " k"],
    gmat: Float[np.ndarray, "k k"],
) -> tuple[float, int, Float[np.ndarray, " k"]]:
    """The shared form's score statistic ``g^T G^+ g`` restricted to the directions
    that hold more than rounding, and its one-step estimate ``-G^+ g``.

    ``G = sum_s w_s B~_s^T B~_s`` and ``g = sum_s w_s B~_s^T r~_s``
    (:func:`weighted_gram`; ``w``: ``(S,)`` inverse noise variance, 1 / mrad^2, ``r~``
    in mrad) of the projected columns of ``b`` (``(S, R, k)``, mrad per parameter
    unit). The directions are judged with each column scaled to unit weighted norm
    *before* the projection, ``d_j^2 = sum_s w_s |b_sj|^2``: an eigenvalue of
    ``D^-1 G D^-1`` is the share of an unprojected size that the base leaves. Kept:
    those above ``max(RANK_RTOL * largest, ROUNDING_ONLY)`` (:data:`RANK_RTOL`: rank
    against the largest; :data:`ROUNDING_ONLY`: a direction absorbed to ``1 - 1e-12``
    holds rounding only, whatever the others hold: the per-heliostat tests' cut). A cut
    relative to the largest eigenvalue alone kept a fully absorbed candidate's
    directions and tested rounding as if it were its remainder.

    Returns:
        ``(stat, k_kept, theta)``: the statistic (chi-square(``k_kept``) units for a
        known noise), the number of directions kept (0: nothing tested, ``stat`` 0)
        and ``(k,)`` the estimate on the kept directions (the parameters' units, zero
        along the others).
    """
    unprojected = np.einsum("s,srk,srk->k", w, b, b)
    d = np.sqrt(np.where(unprojected > 0, unprojected, 1.0))
    ev, vec = np.linalg.eigh(gmat / np.outer(d, d))
    keep = ev > (max(ev.max() * RANK_RTOL, ROUNDING_ONLY) if ev.size and ev.max() > 0 else np.inf)
    k_kept = int(keep.sum())
    if not k_kept:
        return 0.0, 0, np.zeros(len(g))
    z = vec[:, keep].T @ (g / d)
    return float(np.sum(z**2 / ev[keep])), k_kept, -(vec[:, keep] @ (z / ev[keep])) / d


def screen_candidate(
    effect: str,
    bases: HeliostatBases,
    jac: np.ndarray,
    cols,
    n_heliostats: int,
    absorbed_limit: float,
    typical=None,
) -> CandidateScreen:
    """Score tests and identifiability of the candidate with solver columns ``cols``
    (``typical``: its typical sizes in solver units, default 1), all heliostats at
    once (``jac``: ``(H, R, P)`` the fleet's Jacobian)."""
    cols = list(cols)
    k = len(cols)
    typical = np.ones(k) if typical is None else np.asarray(typical, float)
    b = bases.columns(jac, cols)  # (S, R, k)
    bt = bases.project(b)
    w = bases.dof / np.maximum(bases.rss, 1e-300)  # inverse noise variance
    bt_typ = bt * typical
    info = weighted_gram(w, bt_typ, bt_typ)
    fractions = absorbed_fractions(b, bt)
    information = float(np.linalg.eigvalsh(info).max()) if k else 0.0
    testable = fractions.size > 0
    identifiable = testable and (is_identifiable(fractions, absorbed_limit) or information >= PRECISION_INFORMATION)
    if not testable:
        return CandidateScreen(effect, fractions, testable, identifiable, information)

    n_total = int(bases.n.sum())
    theta_h = np.full((n_heliostats, k), np.nan)
    p_h = np.full(n_heliostats, np.nan)
    u, keep = heliostat_directions(b, bt)
    tested, p_val, explained, denom = directions_f_tests(u, keep, bases.r_res, bases.dof)
    kh = keep.sum(axis=1)[tested]
    p_val, explained, denom = p_val[tested], explained[tested], denom[tested]
    r_res, bt_tested = bases.r_res[tested], bt[tested]
    rss_res = np.sum(r_res * r_res, axis=1)
    p_h[bases.index[tested]] = p_val
    q_sum = float(np.sum(chi2_equivalent(p_val, kh)))
    k_sum = int(kh.sum())
    # The refit's start: the one-step estimate under the refit's own prior (each
    # parameter's typical size, this heliostat's noise), not the bare one, which
    # divides by singular values down to 1e-6 and put a nearly absorbed
    # direction's start (a survey offset per heliostat) so far out that the
    # refit ended in another minimum (held-out 0.37 -> 45 mrad, 1,000 x 60).
    # The start under the prior at the scale of largest evidence across the heliostats
    # (:data:`PRIOR_SCALES`), the scale the refit is fitted with.
    scale_h = 1.0
    if k_sum:
        btt = bt_tested.swapaxes(1, 2)
        info_h = typical[:, None] * (btt @ bt_tested) * typical[None, :] / denom[:, None, None]
        scale_h = best_prior_scale(info_h, typical * (btt @ r_res[..., None])[..., 0] / denom[:, None])
        prior = np.diag(1.0 / np.maximum(scale_h * typical, 1e-300) ** 2)
        ridge = btt @ bt_tested + denom[:, None, None] * prior  # denom: noise variance
        theta_h[bases.index[tested]] = -minimum_norm_solve(ridge, (btt @ r_res[..., None])[..., 0])
    dll_perhel = float(
        np.sum(bases.n[tested] * np.log(np.maximum(rss_res, 1e-300) / np.maximum(rss_res - explained, 1e-300)))
    )
    g = weighted_gram(w, bt, bases.r_res)
    gmat = weighted_gram(w, bt, bt)
    dof_total = int(bases.dof.sum())

    p_perhel = float(stats.chi2.sf(q_sum, k_sum)) if k_sum else 1.0
    # Shared: on the directions G determines beyond rounding (:func:`shared_score`).
    stat_shared, ks, theta_shared = shared_score(w, b, g, gmat)
    p_shared = float(stats.f.sf(stat_shared / ks, ks, max(dof_total - ks, 1))) if ks else 1.0
    # The refit's start: the same step under its prior (precision 1 / typical^2 in the
    # units of w r^2, none where no typical size is documented). The bare estimate
    # goes far out along weakly determined directions, which the prior pulls back:
    # its first shared step was worth up to 35,000 in chi-square on the shared
    # records, and every refit of a shared form took two more expansion iterations.
    # (at the typical sizes: one draw of the shared parameters says nothing about their
    # prior's scale, :data:`PRIOR_SCALES`)
    precision = np.where(typical > 0, 1.0 / np.where(typical > 0, typical, 1.0) ** 2, 0.0)
    start_shared = -np.linalg.pinv(gmat + np.diag(precision), rcond=1e-10, hermitian=True) @ g
    p = min(1.0, 2.0 * min(p_shared, p_perhel))
    log_n = np.log(max(n_total, 2))
    # Linearised change of -2 log L (each heliostat its own noise level) of the
    # shared one-step estimate, comparable with the per-heliostat one.
    rss0 = np.sum(bases.r_res * bases.r_res, axis=1)
    new = bases.r_res + bt @ theta_shared
    rss_new = np.sum(new * new, axis=1)
    dll_shared = float(np.sum(bases.n * np.log(np.maximum(rss0, 1e-300) / np.maximum(rss_new, 1e-300))))
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
        prior_scale={"shared": 1.0, "per_heliostat": scale_h},
    )


def holm(pvalues: dict[str, float], alpha: float) -> tuple[dict[str, float], set[str]]:
    """Holm's step-down procedure: adjusted p-values and the rejected hypotheses
    at family-wise error rate ``alpha``.

    Raises:
        ValueError: ``alpha`` not in (0, 1) (5, a percentage, had rejected every
            hypothesis; NaN none, without a word), or a p-value outside [0, 1] (a NaN
            one sorted anywhere in the step-down and moved the others' adjustments).
    """
    if real_problem(alpha) is not None or not 0.0 < float(alpha) < 1.0:
        raise ValueError(f"holm: alpha must be a family-wise error rate in (0, 1), got {alpha!r}"[:200])
    bad = {n: p for n, p in pvalues.items() if real_problem(p) is not None or not 0.0 <= float(p) <= 1.0}
    if bad:
        name, p = next(iter(bad.items()))
        raise ValueError(f"holm: pvalues[{name!r}] is {p!r}; expected p-values in [0, 1] ({len(bad)} bad)"[:200])
    names = sorted(pvalues, key=lambda n: (pvalues[n], n))
    m = len(names)
    adjusted = {}
    running = 0.0
    for i, n in enumerate(names):
        running = max(running, min(1.0, (m - i) * pvalues[n]))
        adjusted[n] = running
    rejected = {n for n in names if adjusted[n] <= alpha}
    return adjusted, rejected
