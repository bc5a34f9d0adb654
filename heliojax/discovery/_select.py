"""The discovery workflow: clean, fit, screen, check identifiability, refit, select,
repeat, diagnose.

0. **Robust pre-pass** (:mod:`._cleaning`): with ``start="auto"`` each heliostat
   starts from its nominal actuators, or the fleet-typical ones where its own are
   broken (:func:`heliojax.fitting.fitted_start_geometry`); a robust fit of the
   base model flags gross errors (left
   out, reported) and a scan finds change points (jumps of the axis offsets;
   Holm over heliostats at ``alpha``); a change point is the first named effect
   (:class:`heliojax.effects.OffsetStep`: the records before it keep their place, with
   a jump of both joint zeros fitted).
1. **Fit the base model** on every lane (all records, and each blocked
   cross-validation fold held out in turn; :mod:`._lanes`; a fold trains only where at
   least as many of its heliostat's records are left as the base has free parameters,
   :func:`._lanes.make_lanes`).
2. **Diagnose and screen** every candidate effect on the current model's
   residuals: score tests orthogonalised against the current model's Jacobian
   (:mod:`._screen`), shared and per-heliostat forms.
3. **Identifiability**: the fraction of each candidate's signature the current
   model absorbs (:mod:`._identifiability`). A largely absorbed candidate (*not
   identifiable*) is still tested on its remainder and competes like the others
   (reported with its absorbed fraction), so that its remainder is not handed to
   a different effect. A candidate the data do not drive at all (e.g. no
   weather) is reported *untestable*.
4. **Family-wise control**: Holm's step-down procedure over the tested
   candidates' p-values at level ``alpha``; every rejected one is eligible.
5. **Refit the eligible candidates** with Levenberg-Marquardt in batches of
   ``max_refits``, largest linearised delta BIC first, each in the form - shared
   or per heliostat - with the larger linearised delta BIC, and where that fails
   in the other form too if its own score test is significant (shared parameters
   by Gauss-Newton steps on the profiled problem between LM fits; effect parameters
   under a prior of their typical size, ``effect_prior``: per heliostat, and the
   shared form's once for the fleet). A step ends
   with the first batch in which a candidate passes (unless a generic competitor
   beats the best of them: then every eligible candidate is refitted first, see
   :mod:`._competitors`); only when none of the eligible candidates passes does
   the workflow stop.
6. **Name** the passing candidate with the largest decrease of the criterion below
   (``delta_bic``, 2 log of a Bayes factor) among those with
   ``delta_bic > min_delta_bic`` (2) *and* a better held-out likelihood in the blocked
   cross-validation by day (:func:`._report.cv_log_ratio` < 0: each
   heliostat with its own noise level, as in the BIC, so that one heliostat
   with poorly determined folds cannot decide; whether that gain is significant over
   days, :func:`._report.cv_improvement_p`, is reported and a name without it flagged);
   passing rivals within ``ambiguity_bic`` of it
   are reported as an ambiguity. Add it to the model and repeat from 2. (The criterion
   is that of fold 0, all training records, whose lanes are fitted first and alone:
   a refit that fails it is rejected without fitting its cross-validation folds, and
   the folds of one that passes are fitted only where its verdict can matter: not
   for one more than ``ambiguity_bic`` below the best that passed, see :func:`_judged`.)
7. **Confirm the change points** under the final model (a step that only was
   the remainder of a named effect is withdrawn, and the workflow runs again with
   those records back in) and **test the residuals against every recorded
   variable** (:mod:`._diagnostics`): significant structure is reported as
   *unexplained*, never given a library name.

Under the global null (no effect present), a name needs a Holm rejection in
the first step, so the probability of naming anything is at most ``alpha``
(the BIC and CV conditions only remove names). ``alpha`` is the one statistical
setting; its default 0.01 is a design choice (the false-positive rate it
bounds), not tuned on data.

The criterion (``delta_bic`` in the report, :meth:`_Workflow.bic_pair`): ``-2 log``
of each model's evidence, ``sum_h n_h log(RSS_h / n_h)`` over the heliostats fitted
in both models (``n_h`` residual components of heliostat ``h``, its own noise level
profiled out) plus each parameter's Occam term. With the effect prior (the default)
the effect parameters' terms are the Laplace approximation of the marginal
likelihood under that prior (Kass & Raftery 1995, sec. 4.1): ``log det(I + T F)
+ q^T T^-1 q`` for parameters ``q`` of prior variance ``T`` and information ``F``
left after the base's parameters (per heliostat; the shared form's once for the
fleet), so a parameter costs what the records determine of it, not ``log N``
(until 2026-12-05 the BIC with the effective number of parameters, which asks a
per-heliostat effect for more evidence than its prior warrants: on the independent
simulator a 0.3 mrad axis-2 wobble at ``p_holm = 5e-4`` was rejected at ``-133``
and is named at ``+28`` now). A per-heliostat effect's prior has an uncertain scale
(a log-uniform hyperprior on 1/8 to 8 times its typical sizes,
:data:`._screen.PRIOR_SCALES`): the refit takes the scale its screen finds most
probable and the criterion adds ``-2 log`` of the evidence averaged over the
hyperprior relative to that scale's (at most ``2 log 7``; 0 where the scale does not
matter), so an effect far from its documented size is not held back by the guess.
Without the prior it is the BIC, ``k log N``, ``k``
the number of fitted parameters (per-heliostat parameters count once per heliostat,
shared ones once).
"""

from __future__ import annotations

import collections.abc
import dataclasses
import logging
import time

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._errors import DataError, few_names
from .._fleet import bucket_size, fleet_subset, pad_fleet, spot_scatter_mrad
from .._kinematics import MODEL_KINDS, nominal_model
from .._limits import MAX_FIT_STEPS, MAX_FOLDS, count_problem, real_problem
from .._progress import activity, progress_bar
from ..effects import EFFECT_NAMES, OffsetStep
from ..fitting import (
    NOISE_OUTLIER_MIN_RATIO,
    OFFSET_NAMES,
    AbstractBatching,
    default_solver,
    fitted_start_geometry,
    noise_outliers,
)
from ._cleaning import Cleaning, change_point_rival, clean, confirm_change_points, recheck_outliers
from ._competitors import (
    CompetitorScore,
    DayWhitening,
    competitor_design,
    competitor_features,
    generic_rivals,
    n_tested,
    score_competitors,
    significant,
    unexplained_entry,
)
from ._diagnostics import (
    DayClustering,
    day_clustering,
    day_labels,
    day_whitened_rss,
    record_variables,
    unexplained_structure,
)
from ._identifiability import ABSORBED_LIMIT, column_bases
from ._lanes import Engine, Lanes, Layout, fleet_longitude_deg, make_lanes, make_layout
from ._report import (
    AMBIGUITY_BIC,
    MIN_DELTA_BIC,
    STRONG_EVIDENCE_BIC,
    build_report,
    cv_improvement_p,
    cv_log_ratio,
    cv_pair,
    evidence_grade,
)
from ._screen import (
    CandidateScreen,
    HeliostatBases,
    holm,
    hyperprior_penalty,
    prepare_bases,
    screen_candidate,
)

log = logging.getLogger(__name__)

MODES = ("shared", "per_heliostat")

SHARED_STEP_TOLERANCE = 0.01
"""A refit's shared parameters are converged when their next Gauss-Newton step
would lower ``-2 log`` posterior by at most this (chi-square units, the step's
``step' G step``): 200 times below :data:`MIN_DELTA_BIC`, the finest difference
any decision compares. (A step of 1e-3 scaled units, the rule before, is no
statistical scale: it took one to two more expansion iterations per refit.)"""

POLISH_AFTER_SHARED_GAIN = 1.0
"""A shared step predicted to lower ``-2 log`` posterior by at most this (chi-square)
is followed at once by the fresh expansion and the polishing fit, not first by a fit
with the old derivative: the shared step is Gauss-Newton's on the profiled posterior,
whose gain falls quadratically (steps worth 0.06-0.34 left 1e-4 to 3.5e-3, steps worth
0.02-0.13 left at most 1.7e-3, on the shared PAINT records), so after such a step
the next one is expected below :data:`SHARED_STEP_TOLERANCE` and the fit at the
stepped point is the last. Only the order of the iterations depends on it: the fit
still ends when the shared step's gain is at most the tolerance and the linearised
cost equals the exact one."""


DEFAULT_CANDIDATES: tuple[str, ...] = EFFECT_NAMES
"""The candidate effects of :class:`DiscoveryConfig` by default: every library effect.

``offset_drift`` (each heliostat's joint zeros creeping at their own rate) was
screened only on request until the refits held per-heliostat effects by a prior
(``DiscoveryConfig.effect_prior``): on the shared real records its unregularised
per-heliostat form passed both criteria while two free rates per heliostat
extrapolated wildly for heliostats with a handful of records (pooled
cross-validated RMS 16.7 -> 47.9 mrad)."""


@dataclasses.dataclass(frozen=True)
class DiscoveryConfig:
    """Settings of :func:`discover`.

    Attributes:
        base: ``"auto"`` (the default: the actuator model, which follows each
            heliostat's declared actuator kind, linear or ideal), ``"actuator"``
            (the same) or ``"stone8"`` (the Stone model, a linear counts-to-angle map).
        effects: candidate effects (names from :data:`heliojax.effects.EFFECT_NAMES`;
            default :data:`DEFAULT_CANDIDATES`).
        alpha: family-wise error rate of each step's test family (Holm).
        n_folds: blocked cross-validation folds (by local day).
        max_named: most effects to name.
        max_refits: finalists refitted per step (best linearised delta BIC first).
        max_iterations: expansion/fit iterations of one refit (effects enter a fit
            to first order about the previous point; see :mod:`._lanes`); one more
            when they end before the fresh derivative's fit (see ``fit_state``).
        solver: the optimistix least-squares solver (static: changing it recompiles).
        max_steps: its step limit.
        batching: strategy over lanes (default :func:`heliojax.default_batching`).
        absorbed_limit: identifiability limit on the absorbed fraction.
        start: ``"auto"`` (per heliostat the nominal actuators, or the fleet-typical
            ones where its own are broken,
            :func:`heliojax.fitting.fitted_start_geometry`) or ``"nominal"``.
        robust: leave out the gross errors a robust fit of the base model flags
            (:mod:`._cleaning`).
        changes: report change points (Holm over heliostats at ``alpha``) and fit the
            records before each with its jump of both joint zeros
            (:class:`heliojax.effects.OffsetStep`).
        min_delta_bic: decrease of the criterion (``2 log`` Bayes factor, see the
            module docstring) a refit must exceed to pass (default
            :data:`MIN_DELTA_BIC` = 2, Kass & Raftery's "positive" evidence).
        ambiguity_bic: two passing candidates whose criterion differ by less than
            this are reported as an ambiguity (default 10: Kass & Raftery's "very
            strong" evidence, a published scale, not tuned).
        effect_prior: in the refits, every per-heliostat effect parameter gets a
            Gaussian prior about no effect with its documented typical size as the
            standard deviation (:func:`heliojax.parameter`'s ``typical``, fixed a
            priori from the physics): a heliostat whose records cannot determine an
            effect keeps it near none instead of extrapolating a wild value; one
            with many records is not pulled measurably. The shared form's
            parameters get the same prior once for the fleet: a direction of them
            the records hardly determine (e.g. a shift common to every target, which
            each heliostat's tilts absorb) stays near none instead of wandering to
            metres to fit what the library does not hold.
        generic_competitors: before a library effect is named, smooth functions of the
            recorded variables no library effect is driven by (time of day, the wind
            vector) compete with it on the same criterion; if one is at least as good,
            nothing more is named and its variable is reported unexplained
            (:mod:`._competitors`). Needs ``effect_prior`` (the criterion's priors).
        exclude: ids of heliostats to leave out before anything runs (ValueError for an
            id the fleet lacks, or when none would be left).
        keep_noisy: keep the heliostats whose noise after the robust pre-pass lies far
            above the fleet's (:func:`heliojax.fitting.noise_outliers`: garbage
            records, a wrong properties file). By default they are left out after the
            pre-pass (``report["noisy_heliostats"]``; their gross errors and change
            points are the pre-pass's), as ``calibrate`` leaves them out of its fleet
            statistics: kept, one such heliostat moves the fleet's noise estimate and
            every test.
    """

    base: str = "auto"
    effects: tuple[str, ...] | None = None
    alpha: float = 0.01
    n_folds: int = 5
    max_named: int = 6
    max_refits: int = 3
    max_iterations: int = 4
    solver: optx.AbstractLeastSquaresSolver = dataclasses.field(default_factory=default_solver)
    max_steps: int = 64
    batching: AbstractBatching | None = None
    absorbed_limit: float = ABSORBED_LIMIT
    start: str = "auto"
    robust: bool = True
    changes: bool = True
    min_delta_bic: float = MIN_DELTA_BIC
    ambiguity_bic: float = AMBIGUITY_BIC
    effect_prior: bool = True
    generic_competitors: bool = True
    keep_noisy: bool = False
    exclude: tuple[str, ...] = ()

    @property
    def candidates(self) -> tuple[str, ...]:
        """The candidate effects (:data:`DEFAULT_CANDIDATES` when ``effects`` is None)."""
        return DEFAULT_CANDIDATES if self.effects is None else tuple(self.effects)

    def __post_init__(self):
        if self.effects is None:
            object.__setattr__(self, "effects", DEFAULT_CANDIDATES)
        # a string had been read as its letters ("unknown effects ['a', 'e', ...]")
        named = isinstance(self.effects, collections.abc.Iterable) and not isinstance(self.effects, str | bytes)
        if not named or not all(isinstance(e, str) for e in self.candidates):
            raise ValueError(f"effects must be a sequence of effect names, got {self.effects!r}"[:200])
        object.__setattr__(self, "effects", tuple(self.candidates))
        unknown = set(self.candidates) - set(EFFECT_NAMES)
        if unknown:
            raise ValueError(f"unknown effects {sorted(unknown)}; expected names from {EFFECT_NAMES}")
        if real_problem(self.alpha) or not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha!r}"[:200])
        # whole numbers in range: n_folds = 2.5 had passed ``< 2``, and the others were not
        # checked at all (a negative max_steps fitted nothing, a float one failed in the solver)
        for name, minimum, limit in COUNT_OPTIONS:
            problem = count_problem(getattr(self, name), limit, minimum=minimum)
            if problem:
                raise ValueError(f"{name} {problem}"[:200])
        if self.base not in MODEL_KINDS:
            raise ValueError(f"base must be one of {MODEL_KINDS}, got {self.base!r}")
        if self.start not in ("auto", "nominal"):
            raise ValueError(f"start must be 'auto' or 'nominal', got {self.start!r}")
        if not self.ambiguity_bic >= 0.0:  # NaN too: it decides which refits are cross-validated
            raise ValueError(f"ambiguity_bic must be >= 0 (inf: cross-validate every refit), got {self.ambiguity_bic}")
        if not np.isfinite(self.min_delta_bic):
            raise ValueError(f"min_delta_bic must be finite, got {self.min_delta_bic}")
        for name in ("robust", "changes", "effect_prior", "generic_competitors", "keep_noisy"):
            if not isinstance(getattr(self, name), bool | np.bool_):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}"[:200])
        if isinstance(self.exclude, str) or not all(isinstance(i, str) for i in self.exclude):
            raise ValueError(f"exclude must be a sequence of heliostat ids, got {self.exclude!r}"[:200])
        object.__setattr__(self, "exclude", tuple(self.exclude))


COUNT_OPTIONS = (
    ("n_folds", 2, MAX_FOLDS),
    ("max_named", 1, 1000),
    ("max_refits", 1, 1000),
    ("max_iterations", 1, 1000),
    ("max_steps", 1, MAX_FIT_STEPS),
)
"""The whole-number options of :class:`DiscoveryConfig`: ``(name, least, most)``."""


@dataclasses.dataclass(frozen=True)
class ModelState:
    """A fitted model on every lane.

    Attributes:
        effects: ``((name, mode), ...)`` in the order named.
        params: ``(L, P)`` physical parameters per lane.
        ok: ``(L,)`` lane fitted.
        r: ``(L, 2M)`` exact training residuals (mrad; 0 outside the training mask).
        jac: ``(L, 2M, F)`` exact Jacobian there.
        rss: ``(L,)`` residual sum of squares (mrad^2).
        n_res: ``(L,)`` used residual components.
        heldout_sq: ``(L, M)`` squared beam error (mrad^2) of each lane's held-out
            records (NaN elsewhere).
        shared_cov: ``(K + 1, S, S)`` covariance of the shared parameters per fold
            (scaled units), or None.
        fit_s: seconds spent fitting.
        prior_scales: per effect of ``effects``, the factor on its typical sizes its
            prior was fitted with (:data:`._screen.PRIOR_SCALES`; each refit takes its
            screen's choice); empty means 1 for every effect.
    """

    effects: tuple[tuple[str, str], ...]
    params: np.ndarray
    ok: np.ndarray
    r: np.ndarray
    jac: np.ndarray
    rss: np.ndarray
    n_res: np.ndarray
    heldout_sq: np.ndarray
    shared_cov: np.ndarray | None
    fit_s: float
    prior_scales: tuple[float, ...] = ()

    def __post_init__(self):
        if not self.prior_scales:
            object.__setattr__(self, "prior_scales", (1.0,) * len(self.effects))
        if len(self.prior_scales) != len(self.effects):
            raise ValueError(f"{len(self.prior_scales)} prior scales for {len(self.effects)} effects")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e for e, _ in self.effects)


class _Workflow:
    def __init__(self, engine: Engine, config: DiscoveryConfig):
        self.engine = engine
        self.layout: Layout = engine.layout
        self.lanes: Lanes = engine.lanes
        self.config = config
        self.scales = self.layout.scales
        f = self.layout.n_free
        self.n_free = f
        self.free_index = np.asarray(self.layout.free_index)
        self.noise: np.ndarray | None = None  # (L,) mrad per component, from the base fit
        self.unix_time: np.ndarray | None = None  # (H, M) the records' times (s), for day_clustering
        self.longitude_deg = 0.0  # the plant's, for its local days (day_labels)
        self._derivative: tuple[ModelState, tuple] | None = None  # (state, its expansion): see derivative_at

    # -- columns ----------------------------------------------------------------------

    def active_cols(self, effects) -> list[int]:
        cols = list(self.layout.base_cols)
        for e, mode in effects:
            if mode == "per_heliostat":
                cols += list(self.layout.cols(e))
        return cols

    def shared_cols(self, effects) -> list[int]:
        cols = []
        for e, mode in effects:
            if mode == "shared":
                cols += list(self.layout.cols(e))
        return cols

    def inverse_typical(self, effects, prior_scales=()) -> np.ndarray:
        """``(E,)`` one over the prior's standard deviation per effect column (scaled
        units; 0 where no typical size is documented): the layout's typical sizes, each
        effect of ``effects`` times its factor in ``prior_scales`` (aligned with
        ``effects``; empty: 1 for every effect, as :attr:`ModelState.prior_scales`)."""
        inv = np.array(self.layout.inverse_typical, dtype=np.float64)
        n_base = len(self.layout.base_cols)
        scales = tuple(prior_scales) or (1.0,) * len(effects)
        if len(scales) != len(effects):
            raise ValueError(f"{len(scales)} prior scales for {len(effects)} effects")
        for (e, _), s in zip(effects, scales):
            inv[np.asarray(self.layout.cols(e), int) - n_base] /= s
        return inv

    # -- fitting ----------------------------------------------------------------------

    def derivative_at(self, state: ModelState) -> tuple:
        """The expansion of the effects (:meth:`Engine.expand`, every lane) at
        ``state``'s parameters, kept for the last state asked for: the refits of one
        step all start near it and take its derivative for their first iterations
        (one expansion of the effect graph per step instead of one per refit)."""
        if self._derivative is None or self._derivative[0] is not state:
            self._derivative = (state, self.engine.expand(state.params))
        return self._derivative[1]

    def fit_state(
        self,
        effects,
        p_start: np.ndarray,
        active: np.ndarray | None = None,
        derivative_from: tuple | None = None,
        prior_scales: tuple[float, ...] = (),
    ) -> ModelState:
        """Fit the model of ``effects`` on every lane from ``p_start`` ``(L, P)``, each
        effect's prior at its factor of ``prior_scales`` (:meth:`inverse_typical`); with
        ``active`` ``(L,)``, on those lanes only (the others are left out: not ``ok``,
        at ``p_start``, no residuals). ``derivative_from``: an expansion of every lane
        near ``p_start`` (:meth:`derivative_at`), whose derivative the first
        iterations take (else it is evaluated at ``p_start``); either way the fit
        ends with the exact expansion at its solution."""
        t0 = time.perf_counter()
        lanes = self.lanes
        if not lanes.cross_validated.all():  # lanes without training records are never fitted
            active = lanes.cross_validated if active is None else np.asarray(active, bool) & lanes.cross_validated
        n_lanes = p_start.shape[0]
        act_cols = self.active_cols(effects)
        sh_cols = self.shared_cols(effects)
        n_base = len(self.layout.base_cols)
        fit_effect_cols = [c - n_base for c in act_cols if c not in self.layout.base_cols]
        eff_cols = [c for c in act_cols if c not in self.layout.base_cols] + sh_cols
        p = np.array(p_start, dtype=np.float64)
        cov = None
        r = jac = None
        n_iter = self.config.max_iterations
        present = np.unique(lanes.fold if active is None else lanes.fold[np.asarray(active, bool)])
        # Iterations "fit, expand" first keep the derivative D of the effect graph from
        # the start and evaluate only the corrections c0 at each new point (D changes
        # little between iterations and is most of an expansion's cost); at their fixed
        # point D is evaluated afresh and the fit repeated ("polishing") until the
        # fixed point of that expansion is reached: the least-squares solution, up to
        # the change of D over the polishing step, second order in a step that is
        # itself within the tolerance. The final residuals are exact (c0 at the
        # solution); the final Jacobian takes D from where polishing began (one
        # evaluation of D fewer per fit, a change of D below the solver's tolerance).
        prior_scales = tuple(float(s) for s in prior_scales) or (1.0,) * len(effects)
        inverse_typical = self.inverse_typical(effects, prior_scales)  # the effects' priors, fixed over the fit
        expansion = self.engine.expand(p, derivative_from=derivative_from, active=active)
        polishing = not eff_cols  # without effects D is never used: one fit, one fresh expansion
        d_here = False  # D evaluated where polishing began (else only at the start, maybe far away)
        it, limit = 0, n_iter  # iterations; at most max_iterations, or one polishing fit past them
        while True:
            out = self.engine.fit(
                p,
                fit_effect_cols,
                p,
                expansion,
                self.noise,
                active=active,
                inverse_typical=inverse_typical,
            )
            p = np.array(out["params"])
            it += 1
            keep_d = d_here or not polishing
            expansion = self.engine.expand(p, derivative_from=expansion if keep_d else None, active=active)
            r, jac = self.engine.jacobian(p, expansion=expansion, active=active)
            # a lane whose fit left non-finite values is not fitted (it never spoils the others)
            ok = (
                np.asarray(out["ok"], bool)
                & np.all(np.isfinite(p), axis=1)
                & np.all(np.isfinite(r), axis=1)
                & np.all(np.isfinite(jac), axis=(1, 2))
            )
            r = np.where(ok[:, None], r, 0.0)
            jac = np.where(ok[:, None, None], jac, 0.0)
            if not eff_cols:
                break
            # The fit saw the effects to first order about the previous point; it is
            # converged when that model's cost equals the exact cost at its optimum.
            exact = float(np.sum(np.sum(r**2, axis=1)[ok]))
            linear = float(np.sum(2.0 * out["cost"][ok]))
            converged = abs(exact - linear) <= 1e-4 * max(exact, 1e-300)
            last = it >= limit
            if sh_cols:
                step, cov, gain = self._shared_step(r, jac, ok, act_cols, sh_cols, p, inverse_typical)
                # (a fold without an active lane has nothing to step)
                worth = float(np.max(gain[present], initial=0.0))  # no fold: nothing to step
                if not last and worth > SHARED_STEP_TOLERANCE:
                    p = self._shared_stepped(p, step, sh_cols, np.ones(n_lanes, bool))
                    if converged and not polishing and worth <= POLISH_AFTER_SHARED_GAIN:
                        # the step expected to be the last: D afresh at the stepped point, polish there
                        polishing, limit, d_here = True, max(limit, it + 1), True
                        expansion = self.engine.expand(p, active=active)
                        continue
                    # about the stepped point
                    expansion = self.engine.expand(p, derivative_from=expansion if keep_d else None, active=active)
                    converged = False
            if converged or last:
                if polishing:
                    break
                polishing, limit = True, max(limit, it + 1)  # D afresh at this point, and fit again
                expansion = self.engine.expand(p, active=active)
                d_here = True
        used = lanes.train_mask
        n_res = 2 * used.sum(axis=1)
        assert r is not None and jac is not None
        rss = np.where(ok, np.sum(r**2, axis=1), np.nan)
        p = np.where(ok[:, None], p, np.asarray(p_start, dtype=np.float64))  # no NaN carried to the next fit
        # held-out records: only the cross-validation lanes hold any out (fold 0 none)
        holding_out = (lanes.fold > 0) if active is None else (lanes.fold > 0) & np.asarray(active, bool)
        r_eval = self.engine.residuals(p, evaluate=True, active=holding_out)
        m = used.shape[1]
        sq = r_eval.reshape(n_lanes, m, 2)
        sq = np.sum(sq**2, axis=-1)
        held = lanes.heldout_mask() & ok[:, None]
        heldout_sq = np.where(held, sq, np.nan)
        fit_s = time.perf_counter() - t0
        return ModelState(tuple(effects), p, ok, r, jac, rss, n_res, heldout_sq, cov, fit_s, prior_scales)

    def folds_shared_start(self, fold0: ModelState, p: np.ndarray, active: np.ndarray) -> np.ndarray:
        """``p`` ``(L, P)`` with the shared parameters of each cross-validation fold
        stepped from fold 0's solution (:meth:`_shared_step`) on the ``active`` lanes,
        whose other parameters start at their heliostat's fold-0 solution. A fold's
        records are a subset of each heliostat's training records, so the residuals
        and Jacobian of its lanes at that start are the fold-0 lanes' rows, taken
        without evaluating anything; its shared parameters then start within one
        Gauss-Newton step of the fold's own optimum instead of at fold 0's (the first
        shared step of a fold's fit moved the posterior by 2-9 in chi-square on the
        shared PAINT records, and cost a fit of every lane)."""
        effects = fold0.effects
        sh_cols = self.shared_cols(effects)
        if not sh_cols:
            return p
        lanes = self.lanes
        source = lanes.heliostat  # fold-0 lane h is lane h
        ok = fold0.ok[source] & np.asarray(active, bool)
        inverse_typical = self.inverse_typical(effects, fold0.prior_scales)
        steps, _, _ = self._shared_step(
            fold0.r[source], fold0.jac[source], ok, self.active_cols(effects), sh_cols, p, inverse_typical
        )
        return self._shared_stepped(p, steps, sh_cols, (lanes.fold > 0) & np.asarray(active, bool))

    def _shared_stepped(self, p: np.ndarray, steps: np.ndarray, sh_cols, lanes: np.ndarray) -> np.ndarray:
        """``p`` ``(L, P)`` with each of the lanes ``lanes`` ``(L,)`` stepped by its fold's
        shared step (``steps`` ``(K + 1, k)``, scaled units, as :meth:`_shared_step`
        gives them) in the shared columns ``sh_cols``."""
        out = np.array(p, dtype=np.float64)
        rows = np.flatnonzero(lanes)
        idx = self.free_index[sh_cols]
        out[np.ix_(rows, idx)] += steps[self.lanes.fold[rows]] * self.scales[sh_cols]
        return out

    def _shared_step(self, r, jac, ok, act_cols, sh_cols, p, inverse_typical):
        """Gauss-Newton step of the shared parameters per fold, the current model's
        per-heliostat parameters profiled out; and the shared covariance. All lanes
        at once: each lane's residual and shared columns are projected off its own
        parameters' column space (training rows only), weighted by its noise. With
        ``effect_prior``, each shared parameter's Gaussian prior about no effect (its
        typical size times its scale as standard deviation, ``inverse_typical``
        ``(E,)`` per effect column, once per fold) adds to the normal equations: the
        step and covariance are the posterior's.

        Returns:
            ``(steps, covs, gains)``: per fold (``K + 1``) the step ``(k,)`` (scaled
            units), the covariance ``(k, k)`` and the step's predicted decrease of
            ``-2 log`` posterior, ``step' G step`` (chi-square units)."""
        lanes = self.lanes
        fitted = np.flatnonzero(ok)  # the others add nothing (under a fold-0 refit, 5 lanes in 6)
        used = np.repeat(lanes.train_mask[fitted], 2, axis=1)  # (L_ok, 2M)
        k = len(sh_cols)
        n_folds = lanes.n_folds + 1
        # np.take, not jac[:, :, cols]: a gather along the last axis by index list is ~4x slower
        a = np.where(used[:, :, None], np.take(jac[fitted], act_cols, axis=2), 0.0)
        b = np.where(used[:, :, None], np.take(jac[fitted], sh_cols, axis=2), 0.0)
        rr = np.where(used, r[fitted], 0.0)
        u, rank = column_bases(a)
        # batched matrix products (BLAS), not einsum: ~5x faster at (192 lanes, 512 rows)
        ut = u.swapaxes(1, 2)
        bt = b - u @ (ut @ b)
        rt = rr - (u @ (ut @ rr[..., None]))[..., 0]
        btt = bt.swapaxes(1, 2)
        dof = used.sum(axis=1) - rank
        w = np.where(dof > 0, dof / np.maximum(np.sum(rr**2, axis=1), 1e-300), 0.0)
        g = np.zeros((n_folds, k))
        gm = np.zeros((n_folds, k, k))
        np.add.at(g, lanes.fold[fitted], w[:, None] * (btt @ rt[..., None])[..., 0])
        np.add.at(gm, lanes.fold[fitted], w[:, None, None] * (btt @ bt))
        if self.config.effect_prior:
            # rows (q - q_none) / (scale * typical) of unit weight, in the units of w r^2
            n_base = len(self.layout.base_cols)
            inv_typ = inverse_typical[np.asarray(sh_cols) - n_base]
            idx = self.free_index[sh_cols]
            none = np.asarray(self.layout.view.nominal)[idx]
            first = np.array([np.argmax(lanes.fold == f) for f in range(n_folds)])  # shared: equal in a fold
            q = (p[first][:, idx] - none) / self.scales[sh_cols]
            g += inv_typ**2 * q
            gm += np.diag(inv_typ**2)
        steps = np.zeros((n_folds, k))
        covs = np.full((n_folds, k, k), np.nan)
        gains = np.zeros(n_folds)
        for f in range(n_folds):  # folds, not lanes: K + 1 pseudo-inverses of k x k
            if np.any(gm[f]):
                pinv = np.linalg.pinv(gm[f], rcond=1e-10, hermitian=True)
                steps[f] = -pinv @ g[f]
                covs[f] = pinv
                gains[f] = float(steps[f] @ gm[f] @ steps[f])
        return steps, covs, gains

    # -- criteria ---------------------------------------------------------------------

    def bic_pair(self, before: ModelState, after: ModelState) -> tuple[float, float, int]:
        """The selection criterion of both models over the fold-0 heliostats fitted in
        both, and that count: ``-2 log`` of each model's evidence, smaller is better.

        ``sum_h n_h log(RSS_h / n_h)`` (each heliostat's own noise level profiled out)
        plus each parameter's Occam term. Where the records of one day share an error
        under ``after`` (:meth:`day_clustering` of its residuals, intra-day correlation
        ``rho``: an effect that ``before`` lacks makes records of one day alike as well,
        and must not weaken its own evidence), ``RSS_h`` of both models is the
        generalised least-squares one under a random day effect of that ``rho``
        (:func:`._diagnostics.day_whitened_rss`; both share its ``log det``, so the
        difference is ``2 log`` of the likelihood ratio): a day's common structure
        counts with the weight its shared error leaves it, the variation within a day in
        full. (Until 2026-12-07 every record counted ``1 / deff_h``, Kish's design
        effect, which is exact for structure constant within a day only and weakened an
        effect that varies within the day - an encoder wobble, a gravity sag - as much
        as a drift, so that a competitor not so weakened took its place.) Without the
        effect prior this is the BIC (``k log N``,
        :meth:`effective_parameters` aside). With it (the default), the effect parameters
        are fitted under a Gaussian prior of their typical size and the BIC's ``log N``
        per parameter, the large-sample limit of a unit-information
        prior, is replaced by the Laplace approximation of the marginal likelihood under
        that same prior (Kass & Raftery 1995, sec. 4.1; :meth:`occam_terms`): a
        parameter the records determine well costs ``log(1 + its prior variance over
        its posterior variance)`` plus its squared size in prior standard deviations,
        one they barely determine costs ~0. The base parameters keep ``log N`` each
        (no prior; the same in both models). The difference of two such values is
        ``2 log`` of their Bayes factor, on the scale of Kass & Raftery's table that
        :data:`MIN_DELTA_BIC` and :data:`AMBIGUITY_BIC` quote."""
        lanes = np.nonzero((self.lanes.fold == 0) & before.ok & after.ok & (before.n_res > 0))[0]
        n = before.n_res[lanes].astype(float)
        big_n = max(n.sum(), 2.0)
        # records that share an error by day: both models' residuals whitened under the
        # random day effect that the residuals of `after` show
        rho = self.day_clustering(after).correlation
        used = np.repeat(self.lanes.train_mask[lanes], 2, axis=1)

        def residual_ss(state):
            if rho > 0.0 and self.unix_time is not None:
                return day_whitened_rss(state.r[lanes], used, self.lane_days()[lanes], rho)
            return state.rss[lanes]

        def criterion(state):
            rss = np.maximum(residual_ss(state), 1e-300)
            fit = float(np.sum(n * np.log(rss / n)))
            if self.config.effect_prior and self.noise is not None:
                return fit + len(self.layout.base_cols) * lanes.size * np.log(big_n) + self.occam_terms(state, lanes)
            k = float(np.sum(self.effective_parameters(state, lanes))) + len(self.shared_cols(state.effects))
            return fit + k * np.log(big_n)

        return criterion(before), criterion(after), int(lanes.size)

    def day_clustering(self, state: ModelState) -> DayClustering:
        """How much ``state``'s training residuals (fold-0 lanes) of one heliostat and
        day share an error (:func:`heliojax.fitting.day_clustering`);
        none (design effect 1) before the records' times are known."""
        h = self.lanes.n_heliostats
        if self.unix_time is None:
            return DayClustering(0.0, float("nan"), np.ones(h), np.ones(h))
        m = self.lanes.train_mask.shape[1]
        use = self.lanes.train_mask[:h] & state.ok[:h, None]
        cols = self.active_cols(state.effects)
        # what the fit absorbed of each day's shared error: the span of its own columns
        a = np.where(np.repeat(use, 2, axis=1)[..., None], np.take(state.jac[:h], cols, axis=2), 0.0)
        basis, _ = column_bases(a)
        return day_clustering(
            state.r[:h].reshape(h, m, 2),
            use,
            self.unix_time,
            len(cols),
            self.longitude_deg,
            basis=basis.reshape(h, m, 2, -1),
        )

    def lane_days(self) -> np.ndarray:
        """``(L, M)`` the day of each lane's records (:func:`day_labels`; every record a
        day of its own where the times are unknown)."""
        m = self.lanes.train_mask.shape[1]
        if self.unix_time is None:
            return np.broadcast_to(-1 - np.arange(m), (self.lanes.heliostat.size, m))
        return day_labels(self.unix_time, self.longitude_deg)[self.lanes.heliostat]

    def occam_terms(self, state: ModelState, lanes: np.ndarray) -> float:
        """``-2 log`` Occam factor of ``state``'s effect parameters on ``lanes`` (Laplace).

        Per lane, its per-heliostat effect parameters ``q`` (scaled units, prior
        ``N(0, T)``, ``T`` their typical sizes squared) with the base's parameters
        profiled out: ``log det(I + T S / sigma^2) + q^T T^-1 q``, ``S`` the Schur
        complement of ``J^T J`` on the effect columns (training rows; the information
        the base does not absorb) and ``sigma`` the lane's noise that weighs the prior
        in the fit; ``T`` at the scale the effect's refit took, plus, per effect, the
        hyperprior's term (:meth:`_hyperprior_penalties`). The shared parameters once
        for the fleet: ``log det(I + T G) + q^T T^-1 q``, ``G`` their information
        summed over the heliostats
        (:meth:`_shared_step`, fold 0). A column without a documented typical size has
        no prior and costs ``log N`` as in the BIC."""
        if self.noise is None:
            raise ValueError("occam_terms needs the lanes' noise (set from the base fit)")
        noise = self.noise
        n_base = len(self.layout.base_cols)
        inv_typ = self.inverse_typical(state.effects, state.prior_scales)
        none = np.asarray(self.layout.view.nominal)
        big_n = max(float(np.sum(state.n_res[lanes])), 2.0)
        total = 0.0
        act = self.active_cols(state.effects)
        own = [c for c in act if c >= n_base and inv_typ[c - n_base] > 0]
        if own and lanes.size:
            rest = [c for c in act if c not in own]
            used = np.repeat(self.lanes.train_mask[lanes], 2, axis=1)[:, :, None]
            ju = np.where(used, np.take(state.jac[lanes], own, axis=2), 0.0)
            jb = np.where(used, np.take(state.jac[lanes], rest, axis=2), 0.0)
            a_uu = ju.swapaxes(1, 2) @ ju
            a_ub = ju.swapaxes(1, 2) @ jb
            a_bb = jb.swapaxes(1, 2) @ jb
            # the base's normal matrix is positive definite for a fitted lane; a tiny
            # relative ridge keeps a rank-deficient one (a heliostat with few records) finite
            ridge = 1e-12 * np.trace(a_bb, axis1=1, axis2=2)[:, None, None] * np.eye(len(rest))
            schur = a_uu - a_ub @ np.linalg.solve(a_bb + ridge, a_ub.swapaxes(1, 2))
            typ = 1.0 / inv_typ[np.asarray(own) - n_base]
            sigma2 = np.maximum(noise[lanes], 1e-300) ** 2
            m = np.eye(len(own)) + typ[:, None] * schur * typ[None, :] / sigma2[:, None, None]
            sign, logdet = np.linalg.slogdet(m)
            q = (state.params[lanes][:, self.free_index[own]] - none[self.free_index[own]]) / self.scales[own]
            total += float(np.sum(np.where(sign > 0, logdet, 0.0)) + np.sum((q / typ) ** 2))
            total += self._hyperprior_penalties(state, own, m - np.eye(len(own)), q / typ)
        total += (len(act) - n_base - len(own)) * lanes.size * np.log(big_n)
        sh = self.shared_cols(state.effects)
        if sh and lanes.size:
            inv_sh = inv_typ[np.asarray(sh) - n_base]
            cov = None if state.shared_cov is None else state.shared_cov[0]
            if cov is None or not np.all(inv_sh > 0) or not np.all(np.isfinite(cov)):
                return total + len(sh) * np.log(big_n)
            # cov = (G + T^-1)^-1, so log det(I + T G) = -log det(cov) - log det(T^-1)
            sign, logdet_cov = np.linalg.slogdet(cov)
            if sign <= 0:  # no posterior covariance to speak of: the BIC's count
                return total + len(sh) * np.log(big_n)
            q = (state.params[lanes[0], self.free_index[sh]] - none[self.free_index[sh]]) / self.scales[sh]
            total += float(-logdet_cov - np.sum(np.log(inv_sh**2)) + np.sum((q * inv_sh) ** 2))
        return total

    def _hyperprior_penalties(self, state: ModelState, cols, info: np.ndarray, u: np.ndarray) -> float:
        """Sum over the per-heliostat effects of ``state`` of the hyperprior's
        ``-2 log`` average over the prior's scale (:func:`._screen.hyperprior_penalty`),
        each effect's block of ``info`` ``(B, c, c)`` (the information on the columns
        ``cols``, the base profiled out, in units of the prior's standard deviations)
        about the fitted ``u`` ``(B, c)`` (same units; the others held at their
        values). At the posterior mode the score at no effect is ``(I + F) u``."""
        total = 0.0
        position = {c: i for i, c in enumerate(cols)}
        for (e, m), scale in zip(state.effects, state.prior_scales):
            at = [position[c] for c in self.layout.cols(e) if c in position]
            if m != "per_heliostat" or not at:
                continue
            block = info[:, at][:, :, at]
            score = u[:, at] + (block @ u[:, at, None])[..., 0]
            total += hyperprior_penalty(block, score, scale)
        return total

    def effective_parameters(self, state: ModelState, lanes: np.ndarray) -> np.ndarray:
        """Per lane, the number of its own parameters the fit spends: the number of
        active columns without the effect prior, else the effective degrees of
        freedom ``tr((J^T J + P)^-1 J^T J)`` (``P``: the prior's precision in the
        rows' units; e.g. Hastie, Tibshirani & Friedman, *The Elements of Statistical
        Learning*, sec. 7.6): a parameter the records determine counts 1, one the
        prior holds counts ~0."""
        act = self.active_cols(state.effects)
        n_base = len(self.layout.base_cols)
        eff = [c - n_base for c in act if c >= n_base]
        if not eff or self.noise is None or not self.config.effect_prior:
            return np.full(lanes.size, float(len(act)))
        jac = np.take(state.jac[lanes], act, axis=2)
        a = jac.swapaxes(1, 2) @ jac
        w = np.zeros((lanes.size, len(act)))
        inv = self.inverse_typical(state.effects, state.prior_scales)
        w[:, len(act) - len(eff) :] = self.engine.prior_weights(self.noise[lanes], inv)[:, eff]
        pa = a + np.einsum("li,ij->lij", w**2, np.eye(len(act)))
        df = np.trace(np.linalg.solve(pa + 1e-12 * np.eye(len(act)), a), axis1=1, axis2=2)
        return np.where(np.isfinite(df), df, float(len(act)))

    cv_pair = staticmethod(cv_pair)

    # -- screening --------------------------------------------------------------------

    def bases(self, state: ModelState) -> HeliostatBases:
        """The current model's projected residuals of every heliostat, one padded stack
        (fold-0 lanes, the first ``H``: all training records)."""
        h = self.lanes.n_heliostats
        fold0 = np.arange(h)
        used = np.repeat(self.lanes.train_mask[fold0], 2, axis=1) & state.ok[fold0, None]
        a_cols = self.active_cols(state.effects) + self.shared_cols(state.effects)
        return prepare_bases(state.r[fold0], state.jac[fold0], used, a_cols, range(h))

    def competitors(self, state: ModelState, fleet) -> list[CompetitorScore]:
        """The generic competitors' scores on ``state``'s residuals (:mod:`._competitors`)."""
        if self.noise is None:
            raise ValueError("competitors need the lanes' noise (set from the base fit)")
        clustering = None
        if self.unix_time is not None:
            n_params = len(self.active_cols(state.effects))

            def correlation(rows: np.ndarray, index: np.ndarray, used: np.ndarray, basis: np.ndarray) -> float:
                return self._rows_correlation(rows, index, used, n_params, basis)

            clustering = DayWhitening(day_labels(self.unix_time, self.longitude_deg), correlation)
        return score_competitors(fleet, self.bases(state), self.noise, self.lanes.n_heliostats, clustering)

    def _rows_correlation(
        self, rows: np.ndarray, index: np.ndarray, used: np.ndarray, n_params: int, basis: np.ndarray
    ) -> float:
        """The intra-day correlation (:func:`day_clustering`) of residual rows ``(S, R)``
        of the heliostats ``index`` ``(S,)`` on their used rows ``(S, R)`` (record
        ``j``'s components at rows ``2j``, ``2j + 1``), of a fit whose columns span
        ``basis`` ``(S, R, c)`` there (orthonormal)."""
        h, m = self.lanes.n_heliostats, self.lanes.train_mask.shape[1]
        w = rows.shape[1] // 2
        r = np.zeros((h, m, 2))
        use = np.zeros((h, m), bool)
        u = np.zeros((h, m, 2, basis.shape[-1]))
        r[index, :w] = rows[:, : 2 * w].reshape(len(index), w, 2)
        use[index, :w] = used[:, 0 : 2 * w : 2]
        u[index, :w] = basis[:, : 2 * w].reshape(len(index), w, 2, -1)
        assert self.unix_time is not None
        return day_clustering(r, use, self.unix_time, n_params, self.longitude_deg, basis=u).correlation

    def screen(self, state: ModelState, candidates) -> dict[str, CandidateScreen]:
        h = self.lanes.n_heliostats
        fold0 = np.arange(h)  # lanes of fold 0 are the first H
        bases = self.bases(state)
        return {
            c: screen_candidate(
                c,
                bases,
                state.jac[fold0],
                self.layout.cols(c),
                h,
                self.config.absorbed_limit,
                typical=self.layout.typical(c),
            )
            for c in candidates
        }

    def start_params(self, state: ModelState, effect: str, mode: str, scr: CandidateScreen) -> np.ndarray:
        p = state.params.copy()
        cols = list(self.layout.cols(effect))
        idx = self.free_index[cols]
        if mode == "shared":
            assert scr.start_shared is not None  # tested candidates carry it
            p[:, idx] = scr.start_shared * self.scales[cols]
        else:
            assert scr.theta_per_heliostat is not None  # identifiable candidates carry estimates
            th = np.nan_to_num(scr.theta_per_heliostat[self.lanes.heliostat], nan=0.0)
            p[:, idx] = th * self.scales[cols]
        return p


@dataclasses.dataclass(frozen=True)
class Candidate:
    """A refitted finalist."""

    effect: str
    mode: str
    state: ModelState
    delta_bic: float
    bic_before: float
    bic_after: float
    cv_before: float
    cv_after: float
    n_heldout: int
    cv_log_ratio: float
    passed: bool
    cross_validated: bool = True  # False: the folds not fitted (delta BIC failed, or deferred: see _judged)
    cv_p: float = float("nan")  # one-sided p of the held-out improvement over days (cv_improvement_p)

    @property
    def prior_scale(self) -> float:
        """The factor on the effect's typical sizes its prior was fitted with."""
        return self.state.prior_scales[-1]


@dataclasses.dataclass(frozen=True)
class Step:
    """One named effect."""

    effect: str
    mode: str
    delta_bic: float
    cv_before: float
    cv_after: float
    cv_log_ratio: float
    cv_p: float
    amplitude: dict
    amplitude_std: dict
    heliostats: list
    heliostats_significant: list
    p_value: float
    p_holm: float
    before: ModelState
    after: ModelState
    absorbed_fraction: float | None = None
    ambiguous_with: tuple = ()


@dataclasses.dataclass(frozen=True)
class DiscoveryResult:
    """Everything :func:`discover` found (``report`` is the report.json content).

    Attributes:
        config: the settings.
        fleet: the padded fleet that was analysed.
        layout: column layout.
        lanes: the cross-validation lanes.
        base: the fitted base model state.
        final: the final model state.
        steps: the named effects in order.
        screens: per step, ``{"screens": {effect: CandidateScreen}, "p_holm": {effect: p}}``.
        candidates: per step, the refitted finalists.
        report: the report dictionary (:func:`heliojax.discovery.build_report`).
        cleaning: the robust pre-pass (outliers, change points; :mod:`._cleaning`).
        typical_start: ``(H,)`` heliostats started from the fleet-typical actuators
            (``start="auto"``, :func:`heliojax.fitting.fitted_start_geometry`).
        unexplained: residual structure no named effect explains (:mod:`._diagnostics`;
            first a generic competitor that beat a library name, :mod:`._competitors`).
        variable_p: every recorded variable's p-value at the final model.
        competitors: per step that had a library name to give, the generic
            competitors' scores beside the best library candidate's.
        day_clustering: how much the final model's residuals of one heliostat and
            day share an error (:class:`heliojax.fitting.DayClustering`;
            the residual scan's tests are divided by its design effect; each refit's
            evidence, and each generic competitor's, is whitened under its own model's
            intra-day correlation, :meth:`_Workflow.bic_pair`).
    """

    config: DiscoveryConfig
    fleet: object
    layout: Layout
    lanes: Lanes
    base: ModelState
    final: ModelState
    steps: list
    screens: list
    candidates: list
    report: dict
    timing: dict
    cleaning: Cleaning | None = None
    typical_start: np.ndarray | None = None
    unexplained: tuple = ()
    variable_p: dict = dataclasses.field(default_factory=dict)
    competitors: tuple = ()
    day_clustering: DayClustering | None = None


def _amplitude(wf: _Workflow, state: ModelState, effect: str, mode: str):
    cols = list(wf.layout.cols(effect))
    names = wf.layout.params(effect)
    idx = wf.free_index[cols]
    h = wf.lanes.n_heliostats
    lanes0 = np.nonzero(state.ok[:h])[0]
    vals = state.params[lanes0][:, idx]
    amp, std = {}, {}
    if mode == "shared":
        v = vals[0] if len(lanes0) else np.full(len(cols), np.nan)
        sh = wf.shared_cols(state.effects)
        pos = [sh.index(c) for c in cols]
        if state.shared_cov is not None:
            sd = np.sqrt(np.clip(np.diag(state.shared_cov[0])[pos], 0.0, None)) * wf.scales[cols]
        else:
            sd = np.full(len(cols), np.nan)
    else:
        v = np.median(vals, axis=0) if len(lanes0) else np.full(len(cols), np.nan)
        mad = np.median(np.abs(vals - v), axis=0) if len(lanes0) else np.full(len(cols), np.nan)
        sd = 1.4826 * mad / np.sqrt(max(len(lanes0), 1))
    for n, x, s in zip(names, v, sd):
        amp[n] = float(x)
        std[n] = float(s)
    if effect == "encoder_wobble":
        for axis in (1, 2):
            if mode == "shared":
                amp[f"wobble_amplitude_{axis}"] = float(np.hypot(amp[f"wobble_cos_{axis}"], amp[f"wobble_sin_{axis}"]))
            else:
                a = vals[:, names.index(f"wobble_cos_{axis}")]
                b = vals[:, names.index(f"wobble_sin_{axis}")]
                amp[f"wobble_amplitude_{axis}"] = float(np.median(np.hypot(a, b))) if len(lanes0) else float("nan")
    return amp, std


def _delta_bic(screen: CandidateScreen) -> dict:
    """The linearised delta BIC per mode of a tested candidate."""
    assert screen.approx_delta_bic is not None  # set for every identifiable candidate
    return screen.approx_delta_bic


def discover(
    fleet,
    config: DiscoveryConfig | None = None,
    **kwargs,
) -> DiscoveryResult:
    """Find the effects the base model misses (the discovery workflow).

    Args:
        fleet: a :class:`heliojax.Fleet` (from :func:`heliojax.load_paint_directory`
            or a simulation); times, weather and approach directions are read
            from its record contexts.
        config: settings (:class:`DiscoveryConfig`); keyword arguments override
            its fields, e.g. ``discover(fleet, base="actuator", alpha=0.05)``.

    Returns:
        A :class:`DiscoveryResult`; ``result.report`` is the report.json content.

    Raises:
        DataError: no heliostat of ``fleet`` (after ``exclude``) has a valid record:
            nothing to fit or test (this had compiled and run for ~20 s and then failed
            inside NumPy, "cannot reshape array of size 0").
    """
    config = dataclasses.replace(config or DiscoveryConfig(), **kwargs)
    t_start = time.perf_counter()
    if config.exclude:
        fleet = _without_heliostats(fleet, config.exclude)
    real = np.array([bool(i) for i in fleet.ids], bool)
    if not np.asarray(fleet.mask, bool)[real].any():
        raise DataError(
            fleet.report.source,
            None,
            f"no valid calibration record in {'the heliostats left after exclude' if config.exclude else 'the fleet'} "
            f"({int(real.sum())} heliostats): nothing to fit or test (the load report names why records were skipped)",
        )
    base = nominal_model(config.base, fleet.counts.dtype)
    n_real = sum(1 for i in fleet.ids if i)
    padded = pad_fleet(fleet, bucket_size(fleet.n_heliostats), bucket_size(fleet.n_records))
    started, typical_start, pre_pass = _pre_pass(base, padded, config)
    real = np.array([bool(i) for i in padded.ids])
    noisy = noise_outliers(pre_pass.noise_mrad, real)
    scatter = spot_scatter_mrad(padded, pre_pass.valid & ~pre_pass.outlier)
    with np.errstate(invalid="ignore"):
        unexplained_spots = real & (pre_pass.noise_mrad > NOISE_OUTLIER_MIN_RATIO * scatter)
    left = np.zeros_like(noisy) if config.keep_noisy else noisy
    cleaning = pre_pass
    if left.any():
        # everything after the pre-pass without them: the start geometries and the pre-pass
        # too (the fleet-typical actuators, the change points' family), as with exclude
        log.info(f"{few_names([padded.ids[i] for i in np.flatnonzero(left)])}: noise far above the fleet's: left out")
        without = eqx.tree_at(lambda f: f.mask, padded, jnp.asarray(np.asarray(padded.mask) & ~left[:, None]))
        started, typical_start, cleaning = _pre_pass(base, without, config)
    padded = started
    n_used = n_real - int(left.sum())
    result = _discover_cleaned(padded, base, cleaning, config, n_used, t_start)
    first = result.cleaning
    assert first is not None
    withdrawn = first.withdrawn if first.withdrawn is not None else np.zeros_like(first.change_found)
    restored = first.restored if first.restored is not None else np.zeros_like(first.outlier)
    if withdrawn.any() or restored.any():
        # The final model explains some of what the base model's pre-pass left out
        # (steps that were an effect's remainder, "gross errors" that were its tails):
        # run once more with those records back in.
        log.info(
            f"{int(withdrawn.sum())} change points withdrawn, {int(restored.sum())} records restored: "
            "discovery again with their records"
        )
        kept = cleaning.change_found & ~withdrawn
        t = np.asarray(padded.context.unix_time, float)
        with np.errstate(invalid="ignore"):
            superseded = cleaning.valid & ~first.outlier & (kept[:, None] & (t < cleaning.change_time_s[:, None]))
        again = dataclasses.replace(
            cleaning, outlier=first.outlier, change_found=kept, superseded=superseded, restored=None, withdrawn=None
        )
        result = _discover_cleaned(padded, base, again, config, n_used, t_start)
        assert result.cleaning is not None
        later = result.cleaning.withdrawn
        later_restored = result.cleaning.restored
        final = dataclasses.replace(
            result.cleaning,
            # a step withdrawn by the first run keeps that run's verdict (the second, without it, had none)
            change_p=np.where(withdrawn, first.change_p, result.cleaning.change_p),
            change_p_holm=np.where(withdrawn, first.change_p_holm, result.cleaning.change_p_holm),
            withdrawn=withdrawn if later is None else withdrawn | later,
            restored=restored if later_restored is None else restored | later_restored,
        )
        result = dataclasses.replace(result, cleaning=final)
    assert result.cleaning is not None
    final = result.cleaning.with_left_out(pre_pass, left) if left.any() else result.cleaning
    final = dataclasses.replace(final, noisy=noisy, unexplained_spots=unexplained_spots, spot_scatter_mrad=scatter)
    result = dataclasses.replace(result, cleaning=final)
    return dataclasses.replace(result, typical_start=typical_start, report=build_report(result, typical_start))


def _pre_pass(base, padded, config: DiscoveryConfig):
    """``(padded with its start geometries, typical_start (H,), the robust pre-pass)``."""
    typical_start = np.zeros(padded.counts.shape[0], bool)
    if config.start == "auto":
        with activity("choosing start geometries", logger=log):
            geometry, typical_start, _ = fitted_start_geometry(base, padded)
            padded = eqx.tree_at(lambda f: f.geometry, padded, geometry)
    with activity("robust pre-pass and change-point scan", logger=log):
        cleaning = clean(base, padded, config.alpha, outliers=config.robust, changes=config.changes)
    return padded, typical_start, cleaning


def check_exclusions(ids: collections.abc.Sequence[str], exclude: collections.abc.Sequence[str]) -> None:
    """ValueError when ``exclude`` names an id not among ``ids`` (a fleet's heliostat
    ids) or leaves none of them."""
    unknown = sorted(set(exclude) - set(ids))
    if unknown:
        raise ValueError(f"exclude: {', '.join(unknown)} not among the {len(ids)} heliostats loaded")
    if not {i for i in ids if i} - set(exclude):
        raise ValueError("exclude leaves no heliostat")


def _without_heliostats(fleet, exclude: tuple[str, ...]):
    """``fleet`` without the heliostats ``exclude`` names (:func:`check_exclusions`)."""
    check_exclusions(fleet.ids, exclude)
    keep = [i for i in fleet.ids if i and i not in set(exclude)]
    log.info(f"left out {len(set(exclude))} heliostat(s): {', '.join(sorted(set(exclude)))}")
    return fleet_subset(fleet, keep)


CHANGE_POINT = OffsetStep.NAME
"""The name of a change point among the named effects (:class:`heliojax.effects.OffsetStep`)."""


def _step_index(layout: Layout) -> tuple[np.ndarray, int]:
    """Positions in the parameter vector of the step's two jumps and its time."""
    names = list(layout.view.names)
    jumps = np.array([names.index(f"{CHANGE_POINT}_jump_{k}") for k in (1, 2)])
    return jumps, names.index(f"{CHANGE_POINT}_time")


def _with_change_points(layout: Layout, p: np.ndarray, heliostat: np.ndarray, cleaning: Cleaning) -> np.ndarray:
    """``p`` ``(L, P)`` with each lane's step set from ``cleaning``: the change time of
    its heliostat's reported change point (0, before any record: none) and the scan's
    jump as the start."""
    jumps, when = _step_index(layout)
    found = np.asarray(cleaning.change_found, bool)
    t = np.where(found, np.nan_to_num(np.asarray(cleaning.change_time_s, float)), 0.0)
    jump = np.where(found[:, None], np.nan_to_num(np.asarray(cleaning.change_jump_mrad, float)) * 1e-3, 0.0)
    p[:, when] = t[heliostat]
    p[:, jumps] = jump[heliostat]
    return p


def _stepped_lanes(cleaning: Cleaning, lanes: Lanes, steps_found: bool) -> np.ndarray:
    """``(L,)`` 1 for the lanes of a heliostat with a change point (its two jumps are
    parameters of its own), else 0."""
    if not steps_found:
        return np.zeros(lanes.fold.shape[0], int)
    return np.asarray(cleaning.change_found, bool)[lanes.heliostat].astype(int)


def _lane_noise(state: ModelState, n_free: int | np.ndarray) -> np.ndarray:
    """``(L,)`` each lane's noise per residual component (mrad) under ``state``
    (``n_free`` parameters per lane); the median of the others where a lane has no
    degrees of freedom left or was not fitted."""
    dof = state.n_res - n_free
    noise = np.sqrt(np.where(state.ok & (dof > 0), state.rss, np.nan) / np.maximum(dof, 1))
    typical = np.nanmedian(noise) if np.any(np.isfinite(noise)) else 1.0
    return np.where(np.isfinite(noise), noise, typical)


def _discover_cleaned(padded, base, cleaning: Cleaning, config: DiscoveryConfig, n_real: int, t_start: float):
    """The workflow on ``padded`` with the gross errors ``cleaning`` flags left out (the
    records before a change point stay, fitted with its jump)."""
    valid = eqx.tree_at(lambda f: f.mask, padded, jnp.asarray(cleaning.valid))
    padded = eqx.tree_at(lambda f: f.mask, padded, jnp.asarray(cleaning.valid & ~cleaning.outlier))
    # A change point is a named effect from the start (OffsetStep: a jump of both joint
    # zeros before its date): the records before it stay and determine the geometry.
    steps_found = bool(cleaning.change_found.any())
    layout, template = make_layout(base, config.candidates, padded, change_points=steps_found)
    lanes = make_lanes(padded, config.n_folds, min_training_records=len(layout.base_cols))
    engine = Engine.create(
        layout, template, lanes, config.solver, config.max_steps, config.batching, config.effect_prior
    )
    wf = _Workflow(engine, config)
    p0 = np.broadcast_to(np.asarray(layout.view.to_vector(template)), (lanes.fold.shape[0], layout.view.n_parameters))
    first_effects: tuple[tuple[str, str], ...] = ()
    if steps_found:
        p0 = _with_change_points(layout, p0.copy(), lanes.heliostat, cleaning)
        first_effects = ((CHANGE_POINT, "per_heliostat"),)
        # the step's prior (about no jump) needs a noise level before the base fit gives one
        noise = np.asarray(cleaning.noise_mrad, float)
        typical = float(np.nanmedian(noise)) if np.isfinite(noise).any() else 1.0
        wf.noise = np.where(np.isfinite(noise) & (noise > 0), noise, typical)[lanes.heliostat]
    log.info(
        f"{n_real} heliostats, {int(np.asarray(padded.mask).sum())} records; base {config.base}; "
        f"{len(config.candidates)} candidates; {config.n_folds} folds by day ({lanes.fold.shape[0]} lanes)"
    )
    with activity(f"fitting the base model ({lanes.fold.shape[0]} lanes)", logger=log):
        state = wf.fit_state(first_effects, p0)
    base_state = state
    wf.noise = _lane_noise(state, len(layout.base_cols) + 2 * _stepped_lanes(cleaning, lanes, steps_found))
    h = lanes.n_heliostats
    wf.unix_time = np.asarray(padded.context.unix_time, float)
    wf.longitude_deg = fleet_longitude_deg(padded)
    train_rms = np.sqrt(np.nansum(state.rss[:h]) / np.sum(state.n_res[:h]) * 2)
    log.info(f"base fitted ({state.fit_s:.1f} s): train RMS {train_rms:.3f} mrad")
    steps: list[Step] = []
    screens_log, candidates_log = [], []
    competitors_log: list[dict] = []
    generic: list[dict] = []
    while len(steps) < config.max_named:
        remaining = [c for c in config.candidates if c not in state.names]
        if not remaining:
            break
        with activity(f"step {len(steps) + 1}: screening {len(remaining)} candidates", logger=log):
            screens = wf.screen(state, remaining)
        # every candidate with a remainder the data drive is tested on it (partly absorbed ones too)
        # (a NaN p, from a screen that could not be computed, is no test: holm refuses it)
        testable = {c: s.p for c, s in screens.items() if s.tested and np.isfinite(s.p)}
        adjusted, rejected = holm(testable, config.alpha) if testable else ({}, set())
        screens_log.append({"screens": screens, "p_holm": adjusted})
        log.info(
            "screen: "
            + ", ".join(
                f"{c} p={s.p:.2g}" if s.tested else f"{c} ({'fully absorbed' if s.testable else 'untestable'})"
                for c, s in screens.items()
            )
        )
        # Every Holm-significant candidate is eligible. They are refitted in batches of
        # ``max_refits``, largest linearised delta BIC first (the name breaks ties: sets
        # iterate in a per-process order); the step ends with the first batch in which
        # some candidate passes, the workflow only when none of them passes.
        finalists = sorted(rejected, key=lambda c: (-max(_delta_bic(screens[c]).values()), c))
        if not finalists:
            candidates_log.append([])
            break
        cands: list[Candidate] = []
        batches = [finalists[i : i + config.max_refits] for i in range(0, len(finalists), config.max_refits)]
        for batch in batches:
            for c in progress_bar(batch, logger=log, desc=f"step {len(steps) + 1}: refits", unit="refit"):
                cands.extend(_refits(wf, state, c, screens[c], config.alpha))
            cands[:] = _judged(wf, state, cands, screens, config.alpha)
            if any(c.passed for c in cands):
                break
        candidates_log.append(cands)
        passing: list[Candidate] = [c for c in cands if c.passed]
        if not passing:
            break
        best = max(passing, key=lambda c: c.delta_bic)
        comps: list[CompetitorScore] = []
        if config.generic_competitors and config.effect_prior:
            comps = wf.competitors(state, padded)
            if comps and comps[0].delta_bic >= best.delta_bic:
                # before a competitor takes the residuals, the library gets its best: every
                # eligible candidate not yet refitted is refitted (the batches stop at the first
                # that passes, and the linearisation may rank the true effect behind the ones
                # the competitor beats), and a competitor takes the better of its two forms:
                # so does a library effect (its other form is refitted where its own test is
                # significant)
                tried = {c.effect for c in cands}
                for c in (c for c in finalists if c not in tried):
                    cands.extend(_refits(wf, state, c, screens[c], config.alpha))
                cands[:] = _judged(wf, state, cands, screens, config.alpha)  # in place: candidates_log holds this list
                # every refit that passed its delta BIC, cross-validated or deferred
                judged = [c for c in cands if c.delta_bic > config.min_delta_bic]
                cands += _other_forms(wf, state, judged, cands, screens, config.alpha)
                cands[:] = _judged(wf, state, cands, screens, config.alpha)  # in place: candidates_log holds this list
                passing = [c for c in cands if c.passed]
                best = max(passing, key=lambda c: c.delta_bic)
            competitors_log.append(
                {
                    "step": len(steps) + 1,
                    "library_best": {"effect": best.effect, "mode": best.mode, "delta_bic": best.delta_bic},
                    "competitors": [
                        {"variable": c.variable, "form": c.form, "delta_bic": c.delta_bic, "p": c.p} for c in comps
                    ],
                }
            )
            top = comps[0] if comps else None
            n_comps = n_tested(comps)  # the family: the competitors tested
            if top is not None and top.delta_bic >= best.delta_bic and significant(top, n_comps, config.alpha):
                instead = {
                    "effect": best.effect,
                    "mode": best.mode,
                    "delta_bic": best.delta_bic,
                    "ambiguous": bool(top.delta_bic - best.delta_bic < config.ambiguity_bic),
                }
                generic.append(unexplained_entry(top, n_comps, config.alpha, list(padded.ids), instead))
                log.info(
                    f"not named: {best.effect} ({best.mode}, delta BIC {best.delta_bic:.1f}); a generic function "
                    f"of {top.variable} ({top.form}) explains the residuals as well (delta BIC {top.delta_bic:.1f}, "
                    f"p={top.p:.2g}): reported unexplained"
                )
                break
        rivals = tuple(
            {"effect": c.effect, "mode": c.mode, "delta_bic": c.delta_bic, "cv_after": c.cv_after, "source": "library"}
            for c in passing
            if c is not best and best.delta_bic - c.delta_bic < config.ambiguity_bic
        )
        rivals += generic_rivals(best.delta_bic, comps, config.alpha, config.ambiguity_bic)
        amp, std = _amplitude(wf, best.state, best.effect, best.mode)
        h = lanes.n_heliostats
        ids = list(padded.ids)
        fitted = [ids[i] for i in range(h) if best.state.ok[i] and ids[i]]
        p_h = screens[best.effect].p_heliostats
        assert p_h is not None
        tested = {ids[i]: float(p_h[i]) for i in range(h) if ids[i] and np.isfinite(p_h[i])}
        _, sig = holm(tested, config.alpha) if tested else ({}, set())
        if best.mode == "per_heliostat" and (step_rival := change_point_rival(cleaning, sorted(sig), ids)):
            rivals += (step_rival,)
        steps.append(
            Step(
                effect=best.effect,
                mode=best.mode,
                delta_bic=best.delta_bic,
                cv_before=best.cv_before,
                cv_after=best.cv_after,
                cv_log_ratio=best.cv_log_ratio,
                cv_p=best.cv_p,
                amplitude=amp,
                amplitude_std=std,
                heliostats=fitted,
                heliostats_significant=sorted(sig),
                p_value=screens[best.effect].p,
                p_holm=adjusted[best.effect],
                before=state,
                after=best.state,
                absorbed_fraction=screens[best.effect].absorbed_fraction,
                ambiguous_with=rivals,
            )
        )
        log.info(
            f"named {best.effect} ({best.mode}): "
            + ", ".join(f"{k}={v:.4g}" for k, v in amp.items())
            + (
                f"; ambiguous with {', '.join(r['effect'] or 'f(' + r['variable'] + ')' for r in rivals)}"
                if rivals
                else ""
            )
            + (
                f"; weak evidence (delta BIC {best.delta_bic:.1f}: {evidence_grade(best.delta_bic)})"
                if best.delta_bic < STRONG_EVIDENCE_BIC
                else ""
            )
        )
        state = best.state
    if cleaning.change_found.any() or (cleaning.outlier.any() and state.effects):
        with activity("checking change points and gross errors under the final model", logger=log):
            generic_variables = [g["variable"] for g in generic]
            cleaning, withdrawn = _confirm_cleaning(wf, state, valid, cleaning, config, generic_variables)
        for i in withdrawn:
            log.info(f"change point of {padded.ids[i]} withdrawn: the final model explains it")
        if cleaning.restored is not None and cleaning.restored.any():
            log.info(f"{int(cleaning.restored.sum())} records flagged under the base model fit the final model")
    n_params = len(wf.active_cols(state.effects))
    ids = list(padded.ids)
    m = lanes.train_mask.shape[1]
    clustering = wf.day_clustering(state)
    if clustering.correlation > 0:
        log.info(
            f"records of one heliostat and day share an error under the final model: intra-day correlation "
            f"{clustering.correlation:.2f} (p={clustering.p:.2g}), design effect "
            f"{np.median(clustering.design_effect):.2f} (median over heliostats)"
        )
    with activity("searching the residuals for unexplained structure", logger=log):
        unexplained, variable_p = unexplained_structure(
            record_variables(padded, state.r[:h].reshape(h, m, 2)),
            state.r[:h].reshape(h, m, 2),
            lanes.train_mask[:h] & state.ok[:h, None],
            n_params,
            config.alpha,
            ids,
            float(np.median(clustering.design_effect)),
        )
    # a competitor that beat a library name comes first; the scan adds what else remains
    unexplained = generic + [u for u in unexplained if u["variable"] not in {g["variable"] for g in generic}]
    for u in unexplained:
        form = " (its shape differing per heliostat)" if u["form"] == "per_heliostat" else ""
        size = f"{u['effect_size_mrad']:.3f} mrad"
        log.info(f"unexplained structure against {u['variable']}{form}: p={u['p']:.2g}, {size}")
    timing = {"total_s": time.perf_counter() - t_start}
    result = DiscoveryResult(
        config=config,
        fleet=padded,
        layout=layout,
        lanes=lanes,
        base=base_state,
        final=state,
        steps=steps,
        screens=screens_log,
        candidates=candidates_log,
        report={},
        timing=timing,
        cleaning=cleaning,
        unexplained=tuple(unexplained),
        variable_p=variable_p,
        competitors=tuple(competitors_log),
        day_clustering=clustering,
    )
    return dataclasses.replace(result, report=build_report(result))


def _confirm_cleaning(
    wf: _Workflow,
    state: ModelState,
    valid,
    cleaning: Cleaning,
    config: DiscoveryConfig,
    unexplained_variables: collections.abc.Sequence[str] = (),
):
    """The pre-pass judged under the final model, with its residuals and Jacobian on
    every valid record: gross errors flagged again (:func:`recheck_outliers`), then
    the change points tested again (:func:`confirm_change_points`), the generic
    functions of ``unexplained_variables`` (competitors that beat a library name,
    :mod:`._competitors`) fitted beside the model: structure reported as unexplained is
    no step either."""
    h = wf.lanes.n_heliostats
    lanes = make_lanes(valid, config.n_folds, min_training_records=len(wf.layout.base_cols))
    engine = dataclasses.replace(wf.engine, lanes=lanes)
    stepped = CHANGE_POINT in state.names
    params = state.params
    if stepped:
        # the jumps the final model fitted are the change points' (later minus earlier)
        jumps, _ = _step_index(wf.layout)
        fitted = np.where(cleaning.change_found[:, None], state.params[:h][:, jumps] * 1e3, np.nan)
        cleaning = dataclasses.replace(cleaning, change_jump_mrad=fitted)
        params = state.params.copy()
        params[:, jumps] = 0.0  # the tests below judge the records before a change without its jump
    r_model = engine.residuals(state.params, evaluate=True) if stepped else None
    r, jac = engine.jacobian(params, evaluate=True)
    m = r.shape[1] // 2
    # the figure shows the records before a change off by its jump, so residuals without it
    cleaning = dataclasses.replace(cleaning, final_residuals=np.asarray(r[:h]).reshape(h, m, 2))
    own = [e for e in state.effects if e[0] != CHANGE_POINT]
    if own:  # under the base model the pre-pass already judged them
        flagged_by = r if r_model is None else r_model
        cleaning = recheck_outliers(cleaning, flagged_by[:h].reshape(h, m, 2), len(wf.active_cols(state.effects)))
    names = [wf.layout.view.names[i] for i in wf.free_index]
    offsets = next((pair for pair in OFFSET_NAMES if all(n in names for n in pair)), None)
    if offsets is None or not cleaning.change_found.any():
        return cleaning, []
    model_cols = wf.active_cols(own) + wf.shared_cols(own)
    offset_cols = [names.index(n) for n in offsets]
    t = np.asarray(valid.context.unix_time, float)
    targets = np.asarray(valid.target_index)
    extra = None
    if unexplained_variables:
        designs = [competitor_design(competitor_features(valid, v)) for v in unexplained_variables]
        extra = np.concatenate(designs, axis=-1)[:h]
    deff = wf.day_clustering(state).design_effect  # of the final model, its steps fitted
    return confirm_change_points(
        cleaning, r[:h], jac[:h], model_cols, offset_cols, t, config.alpha, targets, extra, deff
    )


def _refits(wf: _Workflow, state: ModelState, effect: str, scr: CandidateScreen, alpha: float) -> list[Candidate]:
    """Refit the current model with ``effect`` added, first in the form with the
    larger linearised delta BIC; where that fails, also in the other form if its own
    score test is significant at ``alpha`` (the linearisation ranks the forms, it does
    not rule one out: a per-heliostat effect the prior holds may pass where the
    shared form fails). A failure is a delta BIC that does not pass here; a failed
    cross-validation is found, and the other form tried, by :func:`_judged`."""
    first, _ = sorted(MODES, key=lambda m: -_delta_bic(scr)[m])
    out = [_refit(wf, state, effect, scr, first)]
    if out[0].delta_bic <= wf.config.min_delta_bic or (out[0].cross_validated and not out[0].passed):
        out.extend(_other_form(wf, state, out[0], out, scr, alpha))
    return out


def _other_forms(
    wf: _Workflow, state: ModelState, passing: list[Candidate], cands: list[Candidate], screens: dict, alpha: float
) -> list[Candidate]:
    """The effects of ``passing`` refitted in the form not yet tried, where its own
    score test is significant at ``alpha`` (:func:`_refit`: to be judged)."""
    out: list[Candidate] = []
    for c in passing:
        out.extend(_other_form(wf, state, c, cands + out, screens[c.effect], alpha))
    return out


def refit_passes(delta_bic: float, cv_log_ratio: float, min_delta_bic: float = MIN_DELTA_BIC) -> bool:
    """Whether a refit names its effect: ``delta_bic > min_delta_bic`` (positive
    evidence, :data:`MIN_DELTA_BIC`) and a better held-out likelihood
    (``cv_log_ratio < 0``, finite).

    Not also a held-out improvement significant over days
    (:func:`._report.cv_improvement_p` < ``alpha``), tried on 2026-12-07: on the
    independent simulator it removed 4 of 7 false second names under day-clustered
    noise (wind, temperature), but not the false name of a null suite (held-out p
    0.008), lost a true gravity sag at half the simulator's amplitude under Gaussian
    noise (p 0.016), and on the real records dropped two names whose held-out RMS gain
    was real (1.171 -> 0.950 with them, 0.967 without). So the p is reported with each
    step, and a named effect whose gain is not significant is flagged
    (``"held_out_not_significant"``), not left out."""
    return bool(delta_bic > min_delta_bic and np.isfinite(cv_log_ratio) and cv_log_ratio < 0)


def _joined(first: ModelState, rest: ModelState, take_first: np.ndarray) -> ModelState:
    """One state of the lanes ``take_first`` ``(L,)`` from ``first`` and the others from
    ``rest`` (the same model fitted on complementary lanes)."""

    def pick(name: str) -> np.ndarray:
        a = getattr(first, name)
        return np.where(take_first.reshape((-1,) + (1,) * (a.ndim - 1)), a, getattr(rest, name))

    per_lane = {name: pick(name) for name in ("params", "ok", "r", "jac", "rss", "n_res", "heldout_sq")}
    cov = None
    if first.shared_cov is not None and rest.shared_cov is not None:
        cov = rest.shared_cov.copy()
        cov[0] = first.shared_cov[0]  # fold 0's lanes are the first state's
    return dataclasses.replace(rest, **per_lane, shared_cov=cov, fit_s=first.fit_s + rest.fit_s)


def _refit(wf: _Workflow, state: ModelState, effect: str, scr: CandidateScreen, mode: str) -> Candidate:
    """Refit the current model with ``effect`` added in form ``mode``: its fold-0
    lanes, and its criterion (delta BIC).

    The BIC is that of the fold-0 lanes (all training records), whose fits do not
    depend on the other folds' lanes: those are fitted first, alone. A refit whose
    delta BIC does not pass is rejected there, and its cross-validation folds (five
    sixths of the work) are never fitted (``cv_*`` NaN). One that passes is returned
    not yet cross-validated (``cross_validated`` False); :func:`_judged` fits its
    folds where its verdict can matter (:func:`_cross_validated`). (Where the
    batching computes skipped lanes anyway, vmapped on accelerators, every refit is
    fitted on every lane at once from the screen's start, and judged.)"""
    effects = state.effects + ((effect, mode),)
    scales = state.prior_scales + (scr.prior_scale[mode],)  # the starts' scale (the screen's choice)
    start = wf.start_params(state, effect, mode, scr)
    derivative = wf.derivative_at(state)
    if not wf.engine.skips_inactive_lanes:
        return _verdict(
            wf, state, effect, mode, wf.fit_state(effects, start, derivative_from=derivative, prior_scales=scales)
        )
    fold0 = wf.lanes.fold == 0
    first = wf.fit_state(effects, start, active=fold0, derivative_from=derivative, prior_scales=scales)
    b0, b1, _ = wf.bic_pair(state, first)
    passes = b0 - b1 > wf.config.min_delta_bic
    log.info(
        f"refit {effect} ({mode}, {first.fit_s:.1f} s): delta BIC {b0 - b1:.1f}"
        + (
            " (cross-validated where it can matter)"
            if passes
            else " (rejected; its cross-validation folds are not fitted)"
        )
    )
    nan = float("nan")
    return Candidate(effect, mode, first, b0 - b1, b0, b1, nan, nan, 0, nan, False, cross_validated=False)


def _cross_validated(wf: _Workflow, state: ModelState, cand: Candidate) -> Candidate:
    """``cand`` (fold-0 lanes fitted, :func:`_refit`) with its cross-validation lanes
    fitted and judged: delta BIC > ``min_delta_bic`` and a better held-out
    likelihood. Each lane starts from its heliostat's fold-0 solution (a start from
    all of the heliostat's training records, as the screen's estimate, the start of
    the fold-0 lanes, already is; the folds' fits then take fewer steps), each fold's
    shared parameters one Gauss-Newton step from fold 0's
    (:meth:`_Workflow.folds_shared_start`)."""
    first = cand.state
    fold0 = wf.lanes.fold == 0
    # fold-0 lane h is lane h; the fold-0 lanes are left out of this fit, _joined takes them from `first`
    warm = wf.folds_shared_start(first, first.params[wf.lanes.heliostat], ~fold0)
    rest = wf.fit_state(
        first.effects, warm, active=~fold0, derivative_from=wf.derivative_at(state), prior_scales=first.prior_scales
    )
    return _verdict(wf, state, cand.effect, cand.mode, _joined(first, rest, fold0))


def _verdict(wf: _Workflow, state: ModelState, effect: str, mode: str, st: ModelState) -> Candidate:
    """The refit ``st`` (every lane fitted) judged against ``state``."""
    b0, b1, _ = wf.bic_pair(state, st)
    cv0, cv1, n_cv = wf.cv_pair(state, st)
    ratio = float(cv_log_ratio(state, st, wf.lanes.heliostat))
    cv_p = cv_improvement_p(state, st, wf.lanes.heliostat, wf.lane_days())
    passed = refit_passes(b0 - b1, ratio, wf.config.min_delta_bic)
    log.info(
        f"refit {effect} ({mode}, {st.fit_s:.1f} s): delta BIC {b0 - b1:.1f}, held-out RMS "
        f"{cv0:.3f} -> {cv1:.3f} mrad, held-out log ratio {ratio:+.4f} (p {cv_p:.2g})"
        + ("" if passed else " (rejected)")
    )
    return Candidate(effect, mode, st, b0 - b1, b0, b1, cv0, cv1, n_cv, ratio, passed, cv_p=cv_p)


def _judged(wf: _Workflow, state: ModelState, cands: list[Candidate], screens: dict, alpha: float) -> list[Candidate]:
    """``cands`` with every refit whose verdict can change the step cross-validated.

    The step names the passing refit of largest delta BIC and reports the passing
    ones within ``ambiguity_bic`` of it as rivals. So the refits that passed their
    delta BIC (not yet cross-validated) are cross-validated largest delta BIC first,
    until the largest left is more than ``ambiguity_bic`` below the best that passed:
    those left can be neither named nor a rival, and keep ``cross_validated`` False
    (deferred; their folds, five sixths of a refit, are not fitted). A refit that
    fails its cross-validation is refitted in its other form where that form's own
    score test is significant at ``alpha`` (as one that fails its delta BIC, in
    :func:`_refits`), and that refit joins the others. The step's name and rivals
    are those of cross-validating every refit (the other form of a deferred refit,
    which could only matter had that refit failed its cross-validation, is not
    tried)."""
    out = list(cands)
    while True:
        best = max((c.delta_bic for c in out if c.passed), default=-np.inf)
        waiting = [
            i
            for i, c in enumerate(out)
            if not c.cross_validated
            and c.delta_bic > wf.config.min_delta_bic
            and c.delta_bic >= best - wf.config.ambiguity_bic
        ]
        if not waiting:
            for c in out:
                if not c.cross_validated and c.delta_bic > wf.config.min_delta_bic:
                    log.info(
                        f"refit {c.effect} ({c.mode}) not cross-validated: its delta BIC {c.delta_bic:.1f} is more "
                        f"than {wf.config.ambiguity_bic:g} below the best that passed ({best:.1f})"
                    )
            return out
        i = max(waiting, key=lambda i: out[i].delta_bic)
        c = out[i]
        with activity(f"cross-validating the refit of {c.effect} ({c.mode})", logger=log):
            out[i] = _cross_validated(wf, state, c)
        if not out[i].passed:
            out.extend(_other_form(wf, state, c, out, screens[c.effect], alpha))


def _other_form(
    wf: _Workflow, state: ModelState, cand: Candidate, cands: list[Candidate], scr: CandidateScreen, alpha: float
) -> list[Candidate]:
    """``cand``'s effect refitted in the form not yet tried (:func:`_refit`), where
    that form's own score test is significant at ``alpha``; else nothing."""
    other = next(m for m in MODES if m != cand.mode)
    p_other = scr.p_shared if other == "shared" else scr.p_per_heliostat
    if p_other < alpha and not any(x.effect == cand.effect and x.mode == other for x in cands):
        return [_refit(wf, state, cand.effect, scr, other)]
    return []
