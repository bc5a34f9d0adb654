"""Generic competitors: smooth functions of recorded variables that no library effect
is driven by, competing with the library's names.

A library effect that passes its refit may still be the wrong name: an outside effect
driven by a variable the library does not use (a daily tilt of each pylon, a wind
load from one direction) leaves residual structure that a library effect of a
correlated variable (the axis-2 angle follows the time of day; a drag grows with the
wind speed from any direction) partly fits. Issue 13 asks for such structure to be
reported as unexplained, never forced onto a library name.

So, before an effect is named, each generic competitor is scored on the same
residuals with the same criterion (:meth:`~heliojax.discovery._select._Workflow.bic_pair`:
``-2 log`` of the Laplace evidence under a Gaussian prior of typical size, each
heliostat's noise profiled out; where records of one day share an error, the residual
sums of squares whitened under the random day effect of the competitor's own
residuals, as a library refit's are under its own: :class:`DayWhitening`). A competitor
is linear in its coefficients: per
heliostat (or once for the fleet) the two residual components (mrad) each get
``c_1 f_1(x) + c_2 f_2(x)``, with the current model's parameters profiled out
(projected off its Jacobian's columns, as the screens do). If the best competitor's
evidence is at least the best library candidate's (and its own test is significant at
the family-wise level) - the best of every eligible candidate, each refitted for this
comparison even where the step's refits would have stopped at an earlier batch -, the
candidate is not named, the workflow names nothing more, and
the competitor's variable is reported under ``"unexplained"`` (``"source":
"generic competitor"``). Every step's competitor scores are in the report
(``"generic_competitors"``).

The tests use the directions of the screens' tests (:func:`._screen.heliostat_directions`,
:func:`._screen.shared_score`): a direction the current model absorbs to ``1 - 1e-12``
holds rounding only and is not tested. A competitor with no other direction (inside
every heliostat's span of the model's columns) is untested: its ``p`` is ``None``
(``null`` in the report), it is never significant and the family of the Bonferroni
correction is the competitors tested.

The competitors (:data:`COMPETITORS`), each a first harmonic of a circular variable:

* ``time_of_day``: ``sin``, ``cos`` of ``2 pi t / 1 day`` (UTC);
* ``wind_direction``: the wind vector, ``(v / 10 m/s) sin``, ``cos`` of the direction
  it blows from (a load linear in the wind vector; the library's ``wind`` is a drag
  that grows with ``v^2`` whatever the direction).

Prior: every coefficient ``N(0, (s 0.6 mrad)^2)`` (:data:`GENERIC_TYPICAL_MRAD`): the
beam error of the 0.3 mrad joint angle the library gives its periodic effects as
their typical size (encoder wobble, backlash), fixed a priori; in the per-heliostat
form the scale ``s`` has the library's per-heliostat hyperprior
(:data:`._screen.PRIOR_SCALES`: the scale of largest evidence, its choice paid for),
in the fleet form ``s = 1``, as for the library's shared forms.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from scipy import stats

from ._diagnostics import day_whitened_rss
from ._identifiability import column_bases
from ._screen import (
    HeliostatBases,
    best_prior_scale,
    chi2_equivalent,
    directions_f_tests,
    heliostat_directions,
    hyperprior_penalty,
    shared_score,
    weighted_gram,
)

GENERIC_TYPICAL_MRAD = 0.6
"""Prior standard deviation of a generic competitor's coefficient (mrad of beam error)."""

COMPETITORS = ("time_of_day", "wind_direction")
"""Recorded variables (names of :func:`heliojax.discovery.record_variables`) with a
generic competitor."""

LABELS = {
    "time_of_day": "UTC time of day [h]",
    "wind_direction": "wind direction [deg from north]",
}


def competitor_features(fleet, name: str) -> np.ndarray:
    """``(H, M, 2)`` the competitor's two functions at each record (NaN where the
    variable is not recorded)."""
    ctx = fleet.context
    if name == "time_of_day":
        phase = 2.0 * np.pi * np.mod(np.asarray(ctx.unix_time, float), 86400.0) / 86400.0
        return np.stack([np.sin(phase), np.cos(phase)], axis=-1)
    if name == "wind_direction":
        v = np.asarray(ctx.wind_speed, float) / 10.0
        wind_from = np.asarray(ctx.wind_direction, float)  # rad from north
        return np.stack([v * np.sin(wind_from), v * np.cos(wind_from)], axis=-1)
    raise ValueError(f"no generic competitor for {name!r}; expected one of {COMPETITORS}")


def competitor_design(features: np.ndarray) -> np.ndarray:
    """``(H, 2M, 4)`` Jacobian of the residual rows (record ``j``'s components at rows
    ``2j``, ``2j + 1``) in the coefficients ``(c_11, c_12, c_21, c_22)`` (component,
    function); rows of records without the variable are zero."""
    f = np.where(np.isfinite(features), features, 0.0)
    h, m, k = f.shape
    design = np.zeros((h, m, 2, 2 * k))
    for c in range(2):
        design[:, :, c, c * k : (c + 1) * k] = f
    return design.reshape(h, 2 * m, 2 * k)


@dataclasses.dataclass(frozen=True)
class CompetitorScore:
    """One generic competitor's score at one step.

    Attributes:
        variable: the recorded variable.
        form: ``"per_heliostat"`` or ``"fleet"`` (the form with the larger evidence
            of those tested; of both where neither is).
        delta_bic: decrease of the criterion (``2 log`` Bayes factor against the
            current model), comparable with a refit's.
        p: score-test p-value of the form (Gaussian noise); ``None``: not tested
            (every direction absorbed by the current model to ``1 - 1e-12``).
        effect_size_mrad: RMS over the records (both components) of the residual
            structure it explains: its fitted function with the share the current
            model absorbs projected off (never more than the residuals).
        p_heliostats: ``(H,)`` per-heliostat p-values (NaN where not tested).
    """

    variable: str
    form: str
    delta_bic: float
    p: float | None
    effect_size_mrad: float
    p_heliostats: np.ndarray


def _prior_scale(info: np.ndarray, score: np.ndarray) -> tuple[float, float]:
    """The coefficients' prior variance (mrad^2) at the scale of largest evidence
    (:func:`._screen.best_prior_scale`; ``info`` ``(B, k, k)`` and ``score`` ``(B, k)``
    in mrad units) and the hyperprior's ``-2 log`` penalty for that choice
    (:func:`._screen.hyperprior_penalty`): the library effects' treatment."""
    typ = GENERIC_TYPICAL_MRAD
    scale = best_prior_scale(typ**2 * info, typ * score)
    at = scale * typ
    return at**2, hyperprior_penalty(at**2 * info, at * score, scale)


def _fit_terms(
    bases: HeliostatBases,
    which: np.ndarray,
    new: np.ndarray,
    xt: np.ndarray | None,
    clustering: DayWhitening | None,
):
    """``(rss, rss_new)`` ``(S',)`` of the heliostats ``which`` (mask over ``bases``)
    before and after a competitor's fit ``new`` (their projected residual rows) of
    columns ``xt`` ``(S', R, k)`` (projected off the model's span; None for the fleet
    form, whose ``k`` coefficients are shared by every heliostat):
    plain sums of squares, or with ``clustering`` whitened under the random day effect
    of the competitor's own residuals (:class:`DayWhitening`; the fit's span is the
    model's and the competitor's columns), as a library refit's
    criterion is under its own (:meth:`~heliojax.discovery._select._Workflow.bic_pair`).
    The share of the residuals inside the model's span (rounding at a converged fit)
    is added to both unwhitened."""
    r_res, rss = bases.r_res[which], bases.rss[which]
    inside = rss - np.sum(r_res * r_res, axis=1)
    rho = 0.0
    if clustering is not None:
        after = bases.r_res.copy()
        after[which] = new
        basis = bases.u
        if xt is not None:
            extra = np.zeros((len(bases), *xt.shape[1:]))
            extra[which] = column_bases(xt)[0]  # orthogonal to the model's span already
            basis = np.concatenate([basis, extra], axis=2)
        rho = clustering.correlation(after, bases.index, bases.used, basis)
    if rho <= 0.0 or clustering is None:
        return rss, np.maximum(inside + np.sum(new * new, axis=1), 1e-300)
    used, day = bases.used[which], clustering.day[bases.index[which]]
    before_w = inside + day_whitened_rss(r_res, used, day, rho)
    return before_w, np.maximum(inside + day_whitened_rss(new, used, day, rho), 1e-300)


@dataclasses.dataclass(frozen=True)
class DayWhitening:
    """What a competitor's criterion needs to whiten residuals under a random day
    effect, as a library refit's is (:func:`day_whitened_rss`).

    Attributes:
        day: ``(H, M)`` each record's local day (:func:`heliojax.fitting.day_labels`).
        correlation: the intra-day correlation of residual rows ``(S, R)`` of the
            heliostats ``(S,)`` on their used rows ``(S, R)``, of a fit whose columns
            span an orthonormal basis ``(S, R, c)`` there (the workflow's
            :func:`day_clustering` estimate; 0 where its test does not reject).
    """

    day: np.ndarray
    correlation: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], float]


def _per_heliostat(
    bases: HeliostatBases, design: np.ndarray, noise: np.ndarray, n_h: int, clustering: DayWhitening | None = None
):
    """The per-heliostat form, all heliostats at once (those whose records lack the
    variable add nothing): ``(delta_bic, p, effect_size_mrad, p_heliostats)``, ``p``
    ``None`` where no heliostat has a direction left to test
    (:func:`._screen.heliostat_directions`) and ``p_heliostats`` ``(H,)`` NaN where
    the heliostat is not tested.

    Args:
        bases: the current model's projected residuals (``S`` heliostats, ``R`` rows).
        design: ``(H, >= R, k)`` the competitor's Jacobian (:func:`competitor_design`).
        noise: ``(L,)`` the lanes' noise (mrad).
        n_h: ``H``.
        clustering: whiten under a random day effect (:class:`DayWhitening`)."""
    p_h = np.full(n_h, np.nan)
    x = bases.rows(design)  # (S, R, k)
    driven = np.any(x, axis=(1, 2))
    xt = bases.project(x)[driven]
    x = x[driven]
    r_res, rss, n, dof = bases.r_res[driven], bases.rss[driven], bases.n[driven], bases.dof[driven]
    k = xt.shape[-1]
    xtt = xt.swapaxes(1, 2)
    sigma2 = np.maximum(noise[bases.index[driven]] ** 2, 1e-300)[:, None, None]
    info = xtt @ xt / sigma2
    score = (xtt @ r_res[..., None] / sigma2)[..., 0]
    typ2, penalty = _prior_scale(info, score)
    beta = np.linalg.solve(info + np.eye(k) / typ2, score[..., None])[..., 0]
    new = r_res - (xt @ beta[..., None])[..., 0]
    rss, rss_new = _fit_terms(bases, driven, new, xt, clustering)
    _, logdet = np.linalg.slogdet(np.eye(k) + typ2 * info)
    delta = float(np.sum(n * np.log(np.maximum(rss, 1e-300) / rss_new) - logdet - np.sum(beta * beta, axis=1) / typ2))
    delta -= penalty
    fitted = (xt @ beta[..., None])[..., 0]  # the residual structure it explains (the model's share projected off)
    sq = float(np.sum(fitted * fitted))
    n_sq = int(np.sum(n // 2))
    # the F test of the screens (exact for Gaussian noise), on their directions
    u, keep = heliostat_directions(x, xt)
    tested, p_tested, _, _ = directions_f_tests(u, keep, r_res, dof)
    kh = keep.sum(axis=1)[tested]
    p_h[bases.index[driven][tested]] = p_tested[tested]
    q_sum = float(np.sum(chi2_equivalent(p_tested[tested], kh)))
    k_sum = int(kh.sum())
    p = float(stats.chi2.sf(q_sum, k_sum)) if k_sum else None
    return delta, p, float(np.sqrt(sq / max(n_sq, 1))), p_h


def _fleet(bases: HeliostatBases, design: np.ndarray, noise: np.ndarray, clustering: DayWhitening | None = None):
    """The fleet form: ``(delta_bic, p, effect_size_mrad)``; ``p`` (chi-square test of
    the score, the noise known) ``None`` where no direction is left to test
    (:func:`._screen.shared_score`). Arguments as :func:`_per_heliostat`'s."""
    k = design.shape[-1]
    x = bases.rows(design)  # (S, R, k)
    xt = bases.project(x)
    w = 1.0 / np.maximum(noise[bases.index] ** 2, 1e-300)  # 1 / sigma_h^2
    g = weighted_gram(w, xt, bases.r_res)
    gmat = weighted_gram(w, xt, xt)
    if not np.any(gmat):
        return 0.0, None, 0.0
    typ2 = GENERIC_TYPICAL_MRAD**2  # the fleet form's one draw says nothing about the scale
    beta = np.linalg.solve(gmat + np.eye(k) / typ2, g)
    new = bases.r_res - xt @ beta
    rss, rss_new = _fit_terms(bases, np.ones(len(bases), bool), new, None, clustering)
    delta = float(np.sum(bases.n * np.log(np.maximum(rss, 1e-300) / rss_new)))
    fitted = xt @ beta  # the residual structure it explains (the model's share projected off)
    sq = float(np.sum(fitted * fitted))
    n_sq = int(np.sum(bases.n // 2))
    _, logdet = np.linalg.slogdet(np.eye(k) + typ2 * gmat)
    delta -= logdet + float(beta @ beta) / typ2
    stat, k_kept, _ = shared_score(w, x, g, gmat)
    p = float(stats.chi2.sf(stat, k_kept)) if k_kept else None
    return delta, p, float(np.sqrt(sq / max(n_sq, 1)))


def score_competitors(
    fleet, bases: HeliostatBases, noise: np.ndarray, n_heliostats: int, clustering: DayWhitening | None = None
) -> list[CompetitorScore]:
    """Every generic competitor with recorded data, best evidence first.

    Args:
        fleet: the padded fleet (its records' variables).
        bases: the current model's projected residuals of every heliostat, one padded
            stack (:func:`heliojax.discovery._screen.prepare_bases`, fold-0 lanes).
        noise: ``(L,)`` the lanes' noise (mrad) that weighs the priors in the refits.
        n_heliostats: ``H``.
        clustering: whiten each competitor's criterion under the random day effect of
            its own residuals (:class:`DayWhitening`); None: records independent.
    """
    out = []
    for name in COMPETITORS:
        features = competitor_features(fleet, name)
        if not np.isfinite(features).any():
            continue
        design = competitor_design(features)
        d_h, p_h, size_h, p_each = _per_heliostat(bases, design, noise, n_heliostats, clustering)
        d_f, p_f, size_f = _fleet(bases, design, noise, clustering)
        # an untested form (its delta ~ 0: rounding only) does not hide a tested one
        if d_f > d_h if (p_f is None) == (p_h is None) else p_f is not None:
            out.append(CompetitorScore(name, "fleet", d_f, p_f, size_f, p_each))
        else:
            out.append(CompetitorScore(name, "per_heliostat", d_h, p_h, size_h, p_each))
    return sorted(out, key=lambda c: -c.delta_bic)


def n_tested(comps: list[CompetitorScore]) -> int:
    """The family of the competitors' Bonferroni correction: those tested (``p`` not
    ``None``), as the screens' Holm family is the candidates tested."""
    return sum(c.p is not None for c in comps)


def significant(score: CompetitorScore, n_competitors: int, alpha: float) -> bool:
    """A competitor's own test is significant at the family-wise level ``alpha`` over the
    ``n_competitors`` tested (Bonferroni, :func:`n_tested`): the condition for it to
    beat or rival a name. An untested one (``p`` ``None``) never is."""
    return score.p is not None and n_competitors * score.p <= alpha


def generic_rivals(
    best_delta_bic: float, comps: list[CompetitorScore], alpha: float, ambiguity_bic: float
) -> tuple[dict, ...]:
    """The generic competitors that a named effect beat by less than
    ``ambiguity_bic`` and whose own test is significant (:func:`significant`, as for one
    that wins): a function of another recorded variable explains the same
    residual almost as well, so the name is reported as ambiguous with it (issue 13:
    report the ambiguity instead of a confident name). On the independent simulator a
    daily tilt of each pylon and an encoder wobble of the elevation axis, whose angle
    follows the time of day, are told apart by 3-21 in this criterion
    (``benchmarks/independent_discovery.py``, seeds 11001-11102)."""
    n = n_tested(comps)
    return tuple(
        {
            "effect": None,
            "variable": c.variable,
            "mode": c.form,
            "delta_bic": c.delta_bic,
            "cv_after": None,
            "p": c.p,
            "source": "generic competitor",
        }
        for c in comps
        if best_delta_bic - c.delta_bic < ambiguity_bic and significant(c, n, alpha)
    )


def unexplained_entry(
    score: CompetitorScore, n_competitors: int, alpha: float, ids: list[str], instead_of: dict
) -> dict:
    """The ``"unexplained"`` entry of a competitor that beat a library candidate (its
    test significant over the ``n_competitors`` tested, :func:`significant`)."""
    if score.p is None:
        raise ValueError(f"the competitor of {score.variable} was not tested: it cannot be reported unexplained")
    p_h = score.p_heliostats
    heliostats = [ids[h] for h in range(len(p_h)) if ids[h] and np.isfinite(p_h[h]) and p_h[h] < alpha]
    return {
        "variable": score.variable,
        "form": score.form,
        "label": LABELS[score.variable],
        "p": score.p,
        "p_holm": min(1.0, n_competitors * score.p),
        "effect_size_mrad": score.effect_size_mrad,
        "heliostats": heliostats,
        "source": "generic competitor",
        "delta_bic": score.delta_bic,
        "instead_of": instead_of,
    }
