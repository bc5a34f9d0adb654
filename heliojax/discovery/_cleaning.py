"""Robust data cleaning before discovery: gross errors and change points.

Real records carry gross errors (a spot centroid on a reflection, a wrong
target) and maintenance steps (an axis re-zeroed, an actuator swapped). Left
in, they dominate a least-squares fit: the noise estimate becomes the scatter
of the gross errors, every score test reports structure, and an unmodelled step
is named as whatever smooth effect best mimics it (a clock drift, a thermal
term). So discovery starts from the calibration's robust, change-point-aware
fit of the base model (:func:`heliojax.fitting.fit_robust`,
:func:`heliojax.fitting.find_change_points`):

* **outliers**: the records the robust fit flags (residual norm beyond the
  99.9 % point of the Rayleigh distribution of the heliostat's robust noise) are
  left out of discovery and reported; where change points are found, the flags
  come from robust fits of each side of the change (the first fit saw the
  unmodelled steps as residuals);
* **change points**: per heliostat the most likely jump of both axis offsets.
  Its evidence ``delta_chi2`` is a likelihood ratio with two degrees of freedom
  at a given date; the scan over dates is paid for by Bonferroni over the
  records scanned, ``p_h = min(1, n_h exp(-delta_chi2 / 2))`` (the chi-square(2)
  tail), and the heliostats by Holm's procedure at the discovery's ``alpha``, so
  that under the null (no step anywhere) a change point is reported in at most a
  fraction ``alpha`` of fleets. A change that a linear drift of the offsets
  explains as well (``ChangePoints.is_step`` false: a creeping heliostat, a clock
  running off) is no change point: its records stay. A reported change point is one of the named
  effects, and the first: :class:`heliojax.effects.OffsetStep`, a jump of both joint
  zeros on the records before its date, its two jumps fitted with the rest of the
  model. The records before the change stay in discovery: a step moves the zeros,
  not the geometry, which all of a heliostat's records determine (left out, a
  heliostat whose change came late kept too few records to predict its held-out
  ones: 16 of 60 on the independent simulator gave a held-out RMS of 8 mrad at
  0.25 mrad noise). After the
  library effects are named, each change point is tested again under the final
  model (:func:`confirm_change_points`): a step that was only the remainder of
  a named effect (backlash and thermal drifts are correlated in time) is
  withdrawn and reported as such.

Nothing here has a constant chosen on data: the outlier tail is the robust
fit's, the family-wise level is the discovery's ``alpha``.
"""

from __future__ import annotations

import dataclasses
import logging
import typing

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import ConfigError
from .._parameters import broadcast_model, is_batched
from ..effects import EffectModel, OffsetStep, add_effects
from ..fitting import FitStatus, find_change_points, fit_robust, robust_component_noise
from ..fitting._changes import drift_coordinate
from ..fitting._robust import OUTLIER_TAIL
from ._screen import holm

log = logging.getLogger(__name__)


def _too_few(solution) -> np.ndarray:
    """``(H,)`` heliostats a fit left at its start for too few (or no) records."""
    return np.isin(np.asarray(solution.status), (FitStatus.TOO_FEW_RECORDS, FitStatus.NO_RECORDS))


@dataclasses.dataclass(frozen=True)
class Cleaning:
    """What the robust pre-pass found (numpy arrays over the padded fleet).

    Attributes:
        valid: ``(H, M)`` the records before cleaning.
        outlier: ``(H, M)`` gross errors (left out).
        superseded: ``(H, M)`` records before a reported change point (fitted with its
            jump, :class:`heliojax.effects.OffsetStep`).
        change_found: ``(H,)`` a change point is reported.
        change_time_s: ``(H,)`` unix time (s) of the first record at or after the
            change (NaN where none).
        change_previous_s: ``(H,)`` unix time (s) of the last record before it.
        change_jump_mrad: ``(H, 2)`` jump of the two axis offsets (later minus earlier).
        change_p: ``(H,)`` p-value of the change point (Bonferroni over dates; NaN where
            no scan was possible).
        change_p_holm: ``(H,)`` Holm-adjusted over heliostats.
        offsets: names of the two offset parameters.
        noise_mrad: ``(H,)`` robust noise per residual component (mrad) of the inliers
            (NaN where the pre-pass had too few records to fit the heliostat).
        withdrawn: ``(H,)`` change points of the pre-pass the final model explains
            (:func:`confirm_change_points`; None before that test).
        restored: ``(H, M)`` records flagged under the base model that the final
            model fits (:func:`recheck_outliers`; None before that test).
        final_residuals: ``(H, M, 2)`` residuals (mrad) of the final model on every
            valid record, the left-out ones included (None before that test).
        undecided: ``(H,)`` heliostats with a significant change of state (Holm) that
            is no change point because a linear drift of the offsets explains it as
            well by the Bayesian information criterion, while the drift fits no better
            than the step by that criterion's margin either (``drift_delta_chi2 -
            delta_chi2 < ln n_rows``; e.g. records in two campaigns: a step in the gap
            between them and a drift fit alike, and the noise decides which fits
            better). A library effect whose evidence rests on these heliostats alone is
            reported ambiguous with a change point (:func:`change_point_rival`).
        noisy: ``(H,)`` heliostats whose noise after the pre-pass lies far above the
            fleet's (:func:`heliojax.fitting.noise_outliers`, the rule by which
            ``calibrate`` leaves them out of its fleet statistics; None before it is
            judged).
        left_out: ``(H,)`` the noisy heliostats left out of everything after the
            first pre-pass (start geometries and pre-pass again without them), their
            gross errors and change points the first pre-pass's (None: none).
        spot_scatter_mrad: ``(H,)`` RMS per component of the angle between each
            heliostat's spots and its targets' centres (:func:`heliojax._fleet.spot_scatter_mrad`).
        unexplained_spots: ``(H,)`` heliostats whose pre-pass noise exceeds
            :data:`heliojax.fitting.NOISE_OUTLIER_MIN_RATIO` times that scatter: the
            base model predicts their spots worse than a beam on the target centre
            would (garbage records, wrong properties), whether or not they are a
            minority (warned of, kept).
    """

    valid: np.ndarray
    outlier: np.ndarray
    superseded: np.ndarray
    change_found: np.ndarray
    change_time_s: np.ndarray
    change_previous_s: np.ndarray
    change_jump_mrad: np.ndarray
    change_p: np.ndarray
    change_p_holm: np.ndarray
    offsets: tuple[str, ...]
    noise_mrad: np.ndarray
    withdrawn: np.ndarray | None = None
    restored: np.ndarray | None = None
    final_residuals: np.ndarray | None = None
    undecided: np.ndarray | None = None
    noisy: np.ndarray | None = None
    left_out: np.ndarray | None = None
    spot_scatter_mrad: np.ndarray | None = None
    unexplained_spots: np.ndarray | None = None

    def with_left_out(self, pre_pass: Cleaning, heliostats: np.ndarray) -> Cleaning:
        """The workflow's cleaning (of a fleet without the records of ``heliostats``
        ``(H,)`` bool) with their rows back from ``pre_pass`` (of the whole fleet): their
        records, gross errors and change points as that pre-pass found them, never
        withdrawn or restored (the final model never saw them)."""
        out = np.asarray(heliostats, bool)
        rows = out[:, None]

        def pick(mine, theirs, where):
            if mine is None:
                return None
            return np.where(where, theirs, mine)

        zeros = np.zeros_like(out)
        return dataclasses.replace(
            self,
            valid=np.where(rows, pre_pass.valid, self.valid),
            outlier=np.where(rows, pre_pass.outlier, self.outlier),
            superseded=np.where(rows, pre_pass.superseded, self.superseded),
            change_found=np.where(out, pre_pass.change_found, self.change_found),
            change_time_s=np.where(out, pre_pass.change_time_s, self.change_time_s),
            change_previous_s=np.where(out, pre_pass.change_previous_s, self.change_previous_s),
            change_jump_mrad=np.where(rows, pre_pass.change_jump_mrad, self.change_jump_mrad),
            change_p=np.where(out, pre_pass.change_p, self.change_p),
            change_p_holm=np.where(out, pre_pass.change_p_holm, self.change_p_holm),
            noise_mrad=np.where(out, pre_pass.noise_mrad, self.noise_mrad),
            withdrawn=pick(self.withdrawn, zeros, out),
            restored=pick(self.restored, np.zeros_like(rows), rows),
            final_residuals=pick(self.final_residuals, np.nan, rows[..., None]),
            undecided=pick(self.undecided, pre_pass.undecided if pre_pass.undecided is not None else zeros, out),
            left_out=out,
        )

    @classmethod
    def none(cls, valid: np.ndarray) -> Cleaning:
        """No cleaning (every valid record kept)."""
        h = valid.shape[0]
        nan = np.full(h, np.nan)
        return cls(
            valid=valid,
            outlier=np.zeros_like(valid),
            superseded=np.zeros_like(valid),
            change_found=np.zeros(h, bool),
            change_time_s=nan,
            change_previous_s=nan,
            change_jump_mrad=np.full((h, 2), np.nan),
            change_p=nan,
            change_p_holm=nan,
            offsets=(),
            noise_mrad=nan,
        )


def change_point_pvalues(delta_chi2: np.ndarray, n_scanned: np.ndarray) -> np.ndarray:
    """Per heliostat, ``min(1, n exp(-delta_chi2 / 2))``: the chi-square(2) tail of the
    likelihood ratio at the best date, Bonferroni over the ``n`` dates scanned
    (NaN where there was no scan)."""
    d = np.asarray(delta_chi2, float)
    n = np.maximum(np.asarray(n_scanned, float), 1.0)
    with np.errstate(over="ignore", invalid="ignore"):
        p = np.minimum(1.0, n * np.exp(-0.5 * d))
    return np.where(np.isfinite(d), p, np.nan)


def clean(
    base: typing.Any,
    fleet: typing.Any,
    alpha: float,
    *,
    outliers: bool = True,
    changes: bool = True,
) -> Cleaning:
    """The robust pre-pass (module docstring) of ``fleet`` (padded) under ``base``.

    Args:
        base: the base kinematic model (start values).
        fleet: the padded :class:`heliojax.Fleet`.
        alpha: family-wise level of the change points (Holm over heliostats).
        outliers: flag gross errors.
        changes: scan for change points (needs a free pair of axis offsets).
    """
    valid = np.asarray(fleet.mask, bool)
    out = Cleaning.none(valid)
    if not (outliers or changes) or not valid.any():
        return out
    rf = fit_robust(base, fleet, mask=jnp.asarray(valid))
    outlier = np.asarray(rf.outlier, bool) if outliers else np.zeros_like(valid)
    # the noise of a heliostat the pre-pass could not fit for too few records (for the
    # base's parameters) would be the scatter of an unfitted model's residuals: none is
    # known (one whose fit failed on its records keeps their scatter: garbage is noise)
    noise = np.where(_too_few(rf.solution), np.nan, np.asarray(rf.noise_mrad, float))
    out = dataclasses.replace(out, outlier=outlier, noise_mrad=noise)
    n_out = int(outlier.sum())
    if n_out:
        log.info(f"robust pre-pass: {n_out} gross errors left out")
    if not changes:
        return out
    inliers = valid & ~outlier
    try:
        cp = find_change_points(rf.solution, fleet, jnp.asarray(inliers), jnp.asarray(inliers, fleet.counts.dtype))
    except ConfigError as e:  # a base without a free pair of axis offsets
        log.info(f"no change-point scan: {e}")
        return out
    p = change_point_pvalues(np.asarray(cp.delta_chi2), inliers.sum(axis=1))
    tested = {str(i): float(p[i]) for i in range(valid.shape[0]) if np.isfinite(p[i])}
    adjusted, rejected = holm(tested, alpha) if tested else ({}, set())
    p_holm = np.array([adjusted.get(str(i), np.nan) for i in range(valid.shape[0])])
    changed = np.array([str(i) in rejected for i in range(valid.shape[0])], bool)
    found = changed & np.asarray(cp.is_step, bool)  # a drift is no change point: its records stay
    if (changed & ~found).any():
        log.info(f"{int((changed & ~found).sum())} heliostats drift rather than jump: no change point")
    # a drift by parsimony only: the drift fits no better than the step by the BIC's margin either
    # (two campaigns in time: a step in the gap and a drift fit alike, and noise decides)
    margin = np.asarray(cp.step_margin)
    undecided = changed & ~found & (np.asarray(cp.drift_delta_chi2) - np.asarray(cp.delta_chi2) < margin)
    t = np.asarray(fleet.context.unix_time, float)
    time_s = np.where(found, np.asarray(cp.time_s, float), np.nan)
    with np.errstate(invalid="ignore"):
        superseded = inliers & found[:, None] & (t < time_s[:, None])
    if found.any():
        log.info(f"change points in {int(found.sum())} heliostats: their records before it are fitted with a jump")
        # The first pass saw the steps as residuals: flag the gross errors again under the
        # model with the steps (one robust fit of all records, the jumps fitted with the
        # rest). Fitted apart, a segment of a few records with gross errors in it can
        # leave one unflagged (a 28 mrad record among 19 before a change, 0.25 mrad noise).
        with np.errstate(invalid="ignore"):
            earlier = valid & found[:, None] & (t < time_s[:, None])
        joint = fit_robust(
            with_offset_steps(base, np.where(found, time_s, 0.0), fleet.counts.dtype), fleet, mask=jnp.asarray(valid)
        )
        # the heliostats without a change keep the first fit's verdict: their model is the same,
        # and the joint fit, started from nominal, left the few-record ones of the shared
        # records (8-9 records, pooled in the first fit) at 20-160 mrad of noise
        if outliers:
            outlier = np.where(found[:, None], np.asarray(joint.outlier, bool), outlier) & valid
        superseded = earlier & ~outlier
        noise = np.where(found & ~_too_few(joint.solution), np.asarray(joint.noise_mrad, float), out.noise_mrad)
        out = dataclasses.replace(out, outlier=outlier, noise_mrad=noise)
    return dataclasses.replace(
        out,
        superseded=superseded,
        change_found=found,
        change_time_s=time_s,
        change_previous_s=np.where(found, np.asarray(cp.previous_time_s, float), np.nan),
        change_jump_mrad=np.where(found[:, None], np.asarray(cp.jump_mrad, float), np.nan),
        change_p=p,
        change_p_holm=p_holm,
        offsets=tuple(cp.offsets),
        undecided=undecided,
    )


def change_point_rival(cleaning: Cleaning, significant: list[str], ids: list[str]) -> dict | None:
    """The rival of a named effect that a change point in its heliostats would be.

    Where every heliostat in which the effect is individually significant
    (``significant``, ids) holds an undecided change of state (:attr:`Cleaning.undecided`:
    a drift by parsimony only, a step fitting about as well), the records cannot
    tell the effect from a change of those heliostats' state (a maintenance step
    between two campaigns leaves what a per-heliostat clock or offset drift would):
    returns that rival as an ``ambiguous_with`` entry (source ``"change-point scan"``,
    the heliostats and the largest of their Holm-adjusted p-values); else None.
    """
    index = {h: i for i, h in enumerate(ids)}
    if cleaning.undecided is None or not significant or any(h not in index for h in significant):
        return None
    where = [index[h] for h in significant]
    if not np.all(cleaning.undecided[where]):
        return None
    return {
        "effect": "change_point",
        "mode": "per_heliostat",
        "delta_bic": None,
        "cv_after": None,
        "source": "change-point scan",
        "heliostats": sorted(significant),
        "p": float(np.nanmax(np.asarray(cleaning.change_p_holm, float)[where])),
    }


def with_offset_steps(base: typing.Any, change_time_s: np.ndarray, dtype: typing.Any) -> EffectModel:
    """``base`` batched over ``(H,)`` heliostats and wrapped by an
    :class:`heliojax.effects.OffsetStep` per heliostat at ``change_time_s`` (unix s; 0:
    no step), its jumps at zero (free), the times fixed."""
    t = np.asarray(change_time_s, float)
    batched = base if is_batched(base) else broadcast_model(base, t.shape[0])
    step = OffsetStep(jump=jnp.zeros(t.shape + (2,), dtype), time=jnp.asarray(t, dtype))
    return add_effects(batched, [step])


def confirm_change_points(
    cleaning: Cleaning,
    r: np.ndarray,
    jac: np.ndarray,
    model_cols: list[int],
    offset_cols: list[int],
    unix_time: np.ndarray,
    alpha: float,
    target_index: np.ndarray | None = None,
    extra_columns: np.ndarray | None = None,
    design_effect: np.ndarray | None = None,
) -> tuple[Cleaning, list[int]]:
    """Test the pre-pass change points again under the final model.

    A step found under the base model may be the remainder of an effect the base
    lacks (backlash, a thermal drift: their residuals are correlated in time).
    With the final model's residuals ``r`` ``(H, 2M)`` and Jacobian ``jac``
    ``(H, 2M, F)`` evaluated on every inlier record - those before the change
    included - each change point is tested again at its date: the likelihood
    ratio of a jump of the two offsets (columns ``offset_cols``) on the records
    before the change, with the model's columns ``model_cols`` refitted
    (linearised), a jump that a linear drift of the offsets explains as well (by
    the Bayesian information criterion) counting as none, Bonferroni over the records and Holm over the heliostats as in
    the pre-pass. With ``target_index`` ``(H, M)``, both hypotheses also get a
    constant offset per target and residual component (a target's survey error
    moves its spots by a fixed angle): a heliostat that only switched targets at
    the "change" keeps no change point. With ``extra_columns`` ``(H, 2M, K)``, both
    hypotheses also fit those columns (rows as ``r``'s; the generic functions of a
    recorded variable that discovery reports as unexplained structure: a wind load
    from one direction, which the base model lacks, looked like a step of one
    heliostat on the independent simulator). With ``design_effect`` ``(H,)`` (Kish's,
    of the final model's residuals: records of one day that share an error,
    :func:`heliojax.discovery._diagnostics.day_clustering`), each heliostat's
    likelihood ratios and record count are divided by its own: a day's shared error
    moves a run of records together as a step would, and counted as independent
    records it made a step of a clean heliostat (a null suite with day-clustered
    noise). Change points that no longer pass are withdrawn (the report lists them).

    Returns:
        ``(cleaning, withdrawn)``: the updated cleaning and the withdrawn heliostats.
    """
    found = cleaning.change_found.copy()
    if not found.any():
        return cleaning, []
    use = cleaning.valid & ~cleaning.outlier
    p = np.asarray(cleaning.change_p, float).copy()
    taus = np.asarray(jax.vmap(drift_coordinate)(jnp.asarray(unix_time, float), jnp.asarray(use)))  # (H, M)
    m = use.shape[1]
    for h in np.nonzero(found)[0]:
        # records the final model cannot evaluate (non-finite rows, e.g. a left-out
        # record outside an actuator's range) take no part; they never spoil the test
        finite = np.all(np.isfinite(r[h].reshape(m, 2)), axis=1) & np.all(
            np.isfinite(jac[h].reshape(m, 2, -1)[:, :, list(model_cols) + list(offset_cols)]), axis=(1, 2)
        )
        rows = np.repeat(use[h] & finite, 2)
        before = np.repeat(unix_time[h] < cleaning.change_time_s[h], 2)[rows]
        rr = r[h][rows]
        a = jac[h][rows][:, model_cols]
        if target_index is not None:
            a = np.concatenate([a, _target_columns(target_index[h], use[h] & finite)], axis=1)
        if extra_columns is not None:
            a = np.concatenate([a, np.nan_to_num(extra_columns[h][rows])], axis=1)
        if rr.size <= a.shape[1] + 2 * len(offset_cols):  # too few evaluable rows to test a jump: no evidence
            p[h] = 1.0
            continue
        tau = np.repeat(taus[h], 2)[rows]
        drift = jac[h][rows][:, offset_cols] * tau[:, None]
        step = np.where(before[:, None], jac[h][rows][:, offset_cols], 0.0)
        rss0 = _lstsq_rss(a, rr)
        rss1 = _lstsq_rss(np.concatenate([a, step], axis=1), rr)
        deff = 1.0 if design_effect is None else max(float(design_effect[h]), 1.0)
        n_rows = rr.size / deff  # the rows' effective number
        d = n_rows * np.log(max(rss0, 1e-300) / max(rss1, 1e-300))
        d_drift = n_rows * np.log(max(rss0, 1e-300) / max(_lstsq_rss(np.concatenate([a, drift], axis=1), rr), 1e-300))
        p[h] = float(change_point_pvalues(np.array([d]), np.array([(use[h] & finite).sum()]))[0])
        if d - d_drift <= np.log(n_rows):  # a drift explains it as well (BIC): no jump
            p[h] = 1.0
    tested = {str(i): float(p[i]) for i in range(p.size) if np.isfinite(p[i])}
    adjusted, rejected = holm(tested, alpha) if tested else ({}, set())
    confirmed = np.array([found[i] and str(i) in rejected for i in range(p.size)], bool)
    withdrawn = [int(i) for i in np.nonzero(found & ~confirmed)[0]]
    p_holm = np.array([adjusted.get(str(i), np.nan) for i in range(p.size)])
    return (
        dataclasses.replace(
            cleaning,
            change_found=confirmed,
            change_p=p,
            change_p_holm=p_holm,
            withdrawn=found & ~confirmed,
        ),
        withdrawn,
    )


def _target_columns(target: np.ndarray, use: np.ndarray) -> np.ndarray:
    """``(2 n_used, 2 (T - 1))`` indicator columns of each target but the most used one,
    per residual component (rows interleaved as the residuals)."""
    t = np.asarray(target)[use]
    names, counts = np.unique(t, return_counts=True)
    others = [v for v in names if v != names[np.argmax(counts)]] if names.size else []
    cols = np.zeros((2 * t.size, 2 * len(others)))
    comp = np.tile([True, False], t.size)
    for k, v in enumerate(others):
        hit = np.repeat(t == v, 2)
        cols[:, 2 * k] = hit & comp
        cols[:, 2 * k + 1] = hit & ~comp
    return cols


def _lstsq_rss(a: np.ndarray, y: np.ndarray) -> float:
    """Residual sum of squares of least squares in ``a`` (NaN where it cannot be solved)."""
    try:
        x, *_ = np.linalg.lstsq(a, y, rcond=None)
    except np.linalg.LinAlgError:
        return float("nan")
    return float(np.sum((y - a @ x) ** 2))


def recheck_outliers(cleaning: Cleaning, r: np.ndarray, n_params: int) -> Cleaning:
    """Flag the gross errors again under the final model.

    An effect the base model lacks has tails (a thermal term is largest on the
    hottest days); the pre-pass, fitted with the base model, may flag them as
    gross errors, which would then hide the effect. With the final model's
    residuals ``r`` ``(H, M, 2)`` (mrad) on every valid record, each heliostat's
    per-component robust scales (:func:`heliojax.fitting.robust_component_noise`)
    are taken from its current inliers and the same Rayleigh point decides; a
    record flagged before and within it now is *restored* (the flags of records
    the final model still misses stay).
    """
    use = cleaning.valid & ~cleaning.outlier  # the records before a change too: the model has its jump
    comp = robust_component_noise(r, use, n_params)
    z = np.where(np.isfinite(r), r, 0.0) / comp[:, None, :]
    still = np.linalg.norm(z, axis=-1) > np.sqrt(-2.0 * np.log(OUTLIER_TAIL))
    restored = cleaning.outlier & ~still & np.all(np.isfinite(r), axis=-1)
    return dataclasses.replace(cleaning, outlier=cleaning.outlier & ~restored, restored=restored)
