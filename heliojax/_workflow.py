"""The calibration job: split, fit, evaluate, summarise, write (library side of
``heliojax calibrate``).

The files it writes: ``summary.json`` (:func:`write_summary`, schema in the
README) and ``results.h5`` (:mod:`heliojax._results`).
"""

from __future__ import annotations

import collections.abc
import dataclasses
import functools
import json
import logging
import math
import time
import typing
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool

from ._errors import ConfigError, few_names
from ._fleet import bucket_size, pad_fleet, records_among, spots_off_target
from ._geometry import direction_to_azimuth_elevation
from ._io import atomic_write, check_path_argument
from ._kinematics import AbstractKinematicModel, nominal_model
from ._limits import count_problem, real_problem
from ._predictive import DRIFT_RATE_KEYS, PointingErrorLaw, fit_drift_terms_and_law
from ._programs import warm_up
from ._progress import activity
from ._splits import (
    chronological_holdout,
    days_from_fitted_mean,
    days_since_fit,
    record_sky_gap_deg,
    split_fleet,
    utc_iso,
)
from .fitting import (
    MIN_PRIOR_HELIOSTATS,
    ChangePoints,
    FitSolution,
    FitStatus,
    Sharded,
    beam_errors_mrad,
    choose_start_geometry,
    find_change_points,
    fit_robust,
    fit_timed,
    fitted_start_geometry,
    flat_prior,
    fleet_beam_errors_mrad,
    fleet_residuals_mrad,
    noise_outliers,
    residual_jacobians,
    robust_fit_program,
)
from .fitting._fit import check_fleet

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class CalibrationRun:
    """Everything one calibration job produced.

    Attributes:
        fleet: the (padded) fleet that was fitted (geometry possibly replaced by
            the fleet-typical start for some heliostats, see ``start_replaced``).
        model0: the start model (nominal).
        split_kind: name of the split.
        train_mask, val_mask, test_mask: ``(H, M)`` boolean masks.
        result: the :class:`heliojax.FitSolution`.
        errors_mrad: ``(H, M)`` beam error after calibration (NaN where no record).
        uncalibrated_mrad: ``(H, M)`` beam error with the nominal model.
        residuals_mrad: ``(H, M, 2)`` error components after calibration.
        uncalibrated_residuals_mrad: ``(H, M, 2)`` error components of the nominal model.
        start_replaced: ``(H,)`` heliostats started from fleet-typical actuators.
        start_sources: ``(H,)`` heliostats the fleet-typical actuators are the median of
            (those with a finite uncalibrated error on their training records).
        too_few: heliostat id -> reason, from the split.
        summary: the ``summary.json`` content (its ``load_flags``: :func:`_load_flags`).
        test_fleet: the fleet evaluated for test errors when ``--test-data`` was given.
        weights: ``(H, M)`` robust weight of each training record (1 without ``robust``).
        outlier: ``(H, M)`` training records flagged as gross errors.
        noise_mrad: ``(H,)`` noise estimate per residual component (robust when ``robust``).
        change_points: the change-point scan of the training records
            (:func:`heliojax.fitting.find_change_points`), None when not run.
        superseded: ``(H, M)`` training records before a reported change point:
            not fitted (the fit calibrates the state since the change).
        noise_outlier: ``(H,)`` fitted heliostats whose noise lies far above the
            fleet's (:func:`heliojax.fitting.noise_outliers`): garbage records or a
            wrong properties file; left out of every fleet-wide statistic and warned of.
        predictive: the pointing drift (:func:`temporal_drift`):
            ``drift_mrad2_per_day`` and how it was estimated (``summary.json``'s ``predictive``).
        small_fleet_prior: ``(H,)`` heliostats calibrated under the small-fleet prior
            (:func:`heliojax.fitting.small_fleet_prior_moments`): the fleet was too small
            to learn a prior and they do not determine their parameters alone.
        off_target: ``(H, M)`` records whose focal spot lies off its target
            (:func:`heliojax.spots_off_target`): left out of the pointing drift; a
            heliostat with mostly these among its training records
            (:func:`mostly_off_target`) is left out of every fleet-wide statistic, as a
            noise outlier is, and not aimed with (``results.h5``'s ``off_target``).
        spots_off_target: ``(H,)`` those heliostats (summary.json's ``spots_off_target``).
    """

    fleet: typing.Any
    model0: AbstractKinematicModel
    split_kind: str
    train_mask: np.ndarray
    val_mask: np.ndarray
    test_mask: np.ndarray
    result: FitSolution
    errors_mrad: np.ndarray
    uncalibrated_mrad: np.ndarray
    residuals_mrad: np.ndarray
    uncalibrated_residuals_mrad: np.ndarray
    start_replaced: np.ndarray
    start_sources: np.ndarray
    too_few: dict
    summary: dict
    test_errors_mrad: np.ndarray | None = None
    test_uncalibrated_mrad: np.ndarray | None = None
    weights: np.ndarray | None = None
    outlier: np.ndarray | None = None
    noise_mrad: np.ndarray | None = None
    robust: bool = False
    pooled: bool = False
    change_points: ChangePoints | None = None
    superseded: np.ndarray | None = None
    predictive: dict = dataclasses.field(default_factory=lambda: {"drift_mrad2_per_day": 0.0})
    noise_outlier: np.ndarray | None = None
    small_fleet_prior: np.ndarray | None = None
    off_target: np.ndarray | None = None
    spots_off_target: np.ndarray | None = None

    @property
    def fitted_mask(self) -> np.ndarray:
        """``(H, M)`` the training records the fit used: those of the split since the
        last change point (the records before one describe a past state)."""
        return self.train_mask if self.superseded is None else self.train_mask & ~self.superseded


def mostly_off_target(off_target: Bool[ArrayLike, "H M"], fitted: Bool[ArrayLike, "H M"]) -> Bool[np.ndarray, " H"]:
    """``(H,)`` heliostats with more than half of their ``fitted`` records off their
    target (``off_target``, :func:`heliojax.spots_off_target`). A robust fit rejects
    gross errors only while they are fewer than its good records (its breakdown
    point is one half), so such a heliostat's fit follows the wrong spots: it is
    neither a calibration nor evidence about the fleet."""
    fitted = np.asarray(fitted, bool)
    off = np.asarray(off_target, bool) & fitted
    return 2 * off.sum(axis=-1) > fitted.sum(axis=-1)


def _stats(x: np.ndarray) -> tuple[float, float]:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return float("nan"), float("nan")
    return float(np.median(x)), float(np.sqrt(np.mean(x**2)))


def _json_float(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


_NOT_FITTED = (FitStatus.TOO_FEW_RECORDS, FitStatus.NO_RECORDS)
_ATTEMPTED = (FitStatus.CONVERGED, FitStatus.MAX_STEPS, FitStatus.DIVERGED, FitStatus.FAILED)
"""Statuses of heliostats whose records were fitted (their noise compared with the fleet's)."""


FIT_OPTION_KEYS = ("free", "solver", "loss", "prior", "batching", "max_steps")
"""The keys of :func:`calibrate`'s ``fit_options``: :func:`heliojax.fit`'s keyword
arguments but ``mask`` (calibrate sets it)."""


def _check_fit_options(fit_options: typing.Any, *, robust: bool, pool: bool) -> None:
    """Refuse ``fit_options`` that are no mapping, or that hold a key :func:`calibrate`
    sets itself or :func:`heliojax.fit` does not take (naming them)."""
    if fit_options is None:
        return
    if not isinstance(fit_options, collections.abc.Mapping):
        raise ConfigError(f"fit_options must map keyword -> value, not a {type(fit_options).__name__}")
    keys = [str(k) for k in fit_options]
    set_here = {"mask": "calibrate chooses each fit's records (leave records out with record_roles)"}
    if robust:
        set_here["loss"] = "robust=True fits with its own Cauchy loss (robust=False to give one)"
        if pool:
            set_here["prior"] = "robust=True with pool=True learns the fleet's prior (pool=False to give one)"
    taken = [k for k in keys if k in set_here]
    if taken:
        raise ConfigError(
            f"fit_options: {', '.join(repr(k) for k in taken)} is set by calibrate itself: "
            + "; ".join(set_here[k] for k in taken)
        )
    unknown = [k for k in keys if k not in FIT_OPTION_KEYS]
    if unknown:
        raise ConfigError(
            f"fit_options: unknown key(s) {', '.join(repr(k) for k in unknown)}; known: {', '.join(FIT_OPTION_KEYS)}"
        )


def calibrate(
    fleet,
    *,
    model: str | AbstractKinematicModel = "auto",
    split: str = "time",
    n_train: int | None = None,
    n_val: int = 0,
    train_fraction: float | None = 0.7,
    seed: int = 42,
    fit_options: collections.abc.Mapping[str, typing.Any] | None = None,
    test_fleet=None,
    start: str = "auto",
    robust: bool = True,
    pool: bool = True,
    changes: bool = True,
    record_roles: collections.abc.Mapping[str, collections.abc.Mapping[int, str]] | None = None,
    drift: bool = True,
) -> CalibrationRun:
    """Split each heliostat's records, fit the model on the training records of all
    heliostats at once, and evaluate on the held-out ones.

    Args:
        fleet: a :class:`heliojax.Fleet` (unpadded or padded).
        model: ``"auto"`` (the actuator model, following each heliostat's declared
            actuator kind), ``"stone8"``, ``"actuator"`` or a start model (e.g. one
            with effects).
        split: one of :data:`heliojax.SPLIT_NAMES`.
        n_train, n_val, train_fraction, seed: split sizes (``n_train`` wins over
            ``train_fraction``; PAINT's splits need ``n_train``).
        fit_options: keyword arguments of :func:`heliojax.fit` (``free``, ``solver``,
            ``loss``, ``prior``, ``batching``, ``max_steps``). Not ``mask``: calibrate
            chooses the records of each fit itself (leave records out with
            ``record_roles`` or a fleet without them); with ``robust``, not ``loss``
            (the robust fit chooses it); with ``robust`` and ``pool``, not ``prior``
            (the pooled fit learns it). Such a key, or one :func:`heliojax.fit` does not
            take, is refused with a :class:`~heliojax.ConfigError` naming it (it had
            failed with Python's "got multiple values for keyword argument").
        test_fleet: evaluate on this fleet's records (same heliostat ids) instead of
            the split's test records; then all of ``fleet``'s records may train.
        start: ``"auto"`` (per heliostat the nominal actuators, or the fleet-typical
            ones where the robust fit shows its own broken,
            :func:`heliojax.fitting.fitted_start_geometry`; without ``robust``, the
            better before the fit, :func:`heliojax.choose_start_geometry`) or
            ``"nominal"``.
        robust: robust fit (:func:`heliojax.fitting.fit_robust`: Cauchy loss with a
            per-heliostat scale for the heliostats whose least-squares residuals flag a
            record, record weights and outlier flags) instead of least squares.
        pool: with ``robust``, finish under the fleet's empirical-Bayes prior
            (:func:`heliojax.fitting.fleet_prior`): heliostats with few records are
            calibrated too.
        changes: scan the training records for change points (a change of the
            axis offsets, a jump or a drift, labelled by kind:
            :func:`heliojax.fitting.find_change_points`) and,
            where one is reported, fit again on the records since the change (the
            current state; with ``pool`` the fleet prior fills in what they leave open).
        record_roles: instead of a split, heliostat id -> {PAINT record id: role}
            with role ``"train"`` or ``"test"`` (e.g. a plan's choice among existing
            records, :func:`heliojax.plan_calibration`). Records not named are
            left out; if no record is named ``"test"``, every record not named
            ``"train"`` is held out. Heliostats not named get no training records.
            A named heliostat that gets training but no held-out records while
            others do is named in a warning (its other records are left out).
        drift: estimate the fleet's pointing drift (:func:`temporal_drift`: how fast
            records later than the fitted ones depart from the fit beyond what the
            parameter covariance and the noise explain); 0 when off.
    """
    if start not in CALIBRATION_STARTS:
        raise ConfigError(f"start must be one of {', '.join(CALIBRATION_STARTS)}, not {start!r}")
    if record_roles is not None and not isinstance(record_roles, collections.abc.Mapping):
        raise ConfigError(
            "record_roles must map heliostat id -> {PAINT record id: 'train' or 'test'}, "
            f"not a {type(record_roles).__name__}"
        )
    _check_fit_options(fit_options, robust=robust, pool=pool)
    check_fleet(fleet, who="calibrate")  # None or a path had been an AttributeError
    if test_fleet is not None:
        check_fleet(test_fleet, "test_fleet", who="calibrate")
    if not isinstance(model, (str, AbstractKinematicModel)):  # None or 3 had failed inside the fit
        raise ConfigError(
            f"model must be 'auto', 'stone8', 'actuator' or a kinematic model (e.g. heliojax.with_effects(...)), "
            f"not {model!r}"[:200]
        )
    model0 = nominal_model(model, fleet.counts.dtype) if isinstance(model, str) else model
    n_real = len(fleet.ids)
    ids = list(fleet.ids)
    az, el = direction_to_azimuth_elevation(fleet.context.sun)
    if test_fleet is not None:
        test_fleet = _without_training_records(test_fleet, fleet)
        train = np.asarray(fleet.mask).copy()
        val = np.zeros_like(train)
        test = np.zeros_like(train)
        too_few = {}
    elif record_roles is not None:
        train, test = roles_to_masks(fleet, record_roles)
        val = np.zeros_like(train)
        too_few = {}
    else:
        kw: dict[str, typing.Any] = dict(n_train=n_train, n_val=n_val, seed=seed)
        if n_train is None:
            kw["train_fraction"] = train_fraction
        fs = split_fleet(
            typing.cast(typing.Any, split),
            np.asarray(az),
            np.asarray(el),
            _split_times(fleet, split),
            ids,
            valid=np.asarray(fleet.mask),
            **kw,
        )
        train, val, test = np.asarray(fs.train_mask), np.asarray(fs.val_mask), np.asarray(fs.test_mask)
        too_few = dict(fs.too_few)
        records = np.asarray(fleet.mask)
        if split == "solstice" and records.any() and not np.isfinite(fleet.context.unix_time)[records].any():
            raise ConfigError(
                f"the {split} split needs record times and none of the {int(records.sum())} records has one "
                "(PAINT's calibration-timestamps.json or metadata/calibration_metadata_*.csv missing beside "
                "the data?); add one or choose another split, e.g. azimuth or time"
            )
        undated = records & ~np.isfinite(np.asarray(fleet.context.unix_time, float)) & ~(train | val | test)
        if split in ("time", "solstice") and undated.any():
            counts = [f"{ids[i]} ({int(undated[i].sum())})" for i in np.flatnonzero(undated.any(axis=1))]
            log.warning(
                f"{int(undated.sum())} record(s) without a usable time are left out of the {split} split "
                f"(heliostat, records): {few_names(counts, 10)}"
            )

    h_pad = bucket_size(fleet.counts.shape[0])
    m_pad = bucket_size(fleet.counts.shape[1])
    padded = pad_fleet(fleet, n_heliostats=h_pad, n_records=m_pad)

    def pad_mask(mk):
        out = np.zeros((h_pad, m_pad), bool)
        out[: mk.shape[0], : mk.shape[1]] = mk
        return out

    train, val, test = pad_mask(train), pad_mask(val), pad_mask(test)

    nominal_geometry = padded.geometry  # the plant's own values: the uncalibrated baseline
    options = dict(fit_options or {})
    # the later stages' programs compile in the background (on another core) while the fit does;
    # not for a fit sharded over devices, whose outputs' placement a placeholder does not have
    work = functools.partial(
        _compile_later_stages, model0, padded, train, options.get("free"), robust=robust, changes=changes
    )
    warming = warm_up(work if not isinstance(options.get("batching"), Sharded) else lambda: None)

    def fit_on(fleet_g, mask: np.ndarray):
        if robust:
            rf = fit_robust(model0, fleet_g, mask=jax.device_put(mask), pool=pool, **options)
            weights, outlier, small = np.asarray(rf.weights), np.asarray(rf.outlier), np.asarray(rf.small_fleet_prior)
            return rf.solution, rf.compile_s, rf.run_s, weights, outlier, rf.noise_mrad, small
        res, c_s, f_s = fit_timed(model0, fleet_g, mask=jax.device_put(mask), **options)
        w = np.where(mask & np.asarray(fleet_g.mask), 1.0, 0.0)
        return res, c_s, f_s, w, np.zeros_like(mask), res.noise_mrad, np.zeros(mask.shape[0], bool)

    def fit_stages(train_s: np.ndarray) -> _Stages:
        """Start geometry, robust (pooled) fit and change points on ``train_s``."""
        fleet_g = padded
        first_compile_s = 0.0
        if start == "auto":
            with activity("choosing start geometries", logger=log):
                # judged by the fit: pooled fits run with a flat prior first, so these
                # robust fits share their compiled program
                judge = dict(options)
                if robust and pool and "prior" not in judge:
                    judge["prior"] = flat_prior(model0, h_pad)
                mask_j = jax.device_put(train_s)
                if robust:
                    # compiled here, where its time is measured: the fits below and the
                    # fit of the chosen geometry run it
                    first_compile_s = robust_fit_program(model0, padded, mask=mask_j, **judge).compile_s
                t_start = time.perf_counter()
                geometry, replaced, sources = (
                    fitted_start_geometry(model0, padded, mask=mask_j, **judge)
                    if robust
                    else choose_start_geometry(padded, model0, mask_j)
                )
            if robust:
                log.info(
                    f"start geometry chosen in {time.perf_counter() - t_start:.2f} s (robust fits judge the "
                    "heliostats proposed for the fleet-typical actuators): "
                    f"{int(np.asarray(replaced)[:n_real].sum())} of {n_real} start from them"
                )
            fleet_g = _with_geometry(padded, geometry)
        else:
            replaced = sources = np.zeros(h_pad, bool)

        log.info(f"fitting {n_real} heliostats ({model0.label()}, padded to {h_pad} x {m_pad})")
        with activity(f"fitting {n_real} heliostats", logger=log):
            result, compile_s, fit_s, weights, outlier, noise, small = fit_on(fleet_g, train_s)
        compile_s += first_compile_s
        log.info(f"fitted in {fit_s:.2f} s (compile {compile_s:.2f} s)")
        change_points, superseded = None, np.zeros_like(train_s)
        if changes:
            with activity("change-point scan", logger=log):
                change_points, superseded = _scan_changes(result, fleet_g, train_s, weights)
            if superseded.any():
                n_changed = int(np.any(superseded, axis=1).sum())
                log.info(f"change points in {n_changed} heliostats: fitting their current state")
                with activity(f"fitting the current state of {n_changed} heliostats", logger=log):
                    result, c2, f2, weights, outlier, noise, small = fit_on(fleet_g, train_s & ~superseded)
                compile_s, fit_s = compile_s + c2, fit_s + f2
        return _Stages(
            fleet_g.geometry,
            np.asarray(replaced, bool),
            np.asarray(sources, bool),
            result,
            compile_s,
            fit_s,
            np.asarray(weights),
            np.asarray(outlier),
            np.asarray(noise),
            change_points,
            superseded,
            small,
        )

    stages = fit_stages(train)
    attempted = np.isin(np.asarray(stages.result.status), _ATTEMPTED)
    noisy = noise_outliers(stages.noise, attempted)
    off_target = spots_off_target(padded)
    astray = mostly_off_target(off_target, train) & attempted
    noisy[n_real:] = astray[n_real:] = False
    if noisy.any():
        log.warning(
            f"{few_names([ids[i] for i in np.flatnonzero(noisy)])}: noise far above the fleet's (garbage records "
            "or a wrong properties file?): left out of the statistics the fleet's fit learns (prior, noise, start "
            "geometry, drift), the others fitted again without; its own errors still count in the fleet's figures"
        )
    if astray.any():
        log.warning(
            f"{few_names([ids[i] for i in np.flatnonzero(astray)])}: most training records have their focal spot "
            "off their target (wrong spots, targets or survey?): its fit follows them; left out of the statistics "
            "the fleet's fit learns, the others fitted again without, and not to be aimed with; its own errors "
            "still count in the fleet's figures"
        )
    garbage = noisy | astray
    if garbage.any():
        # Fleet statistics (noise median, prior, start geometry, change-point weights, drift)
        # must not carry a heliostat of garbage records: the others are fitted again without
        # it; its own result is the first fit's.
        stages = _merge_stages(garbage, stages, fit_stages(train & ~garbage[:, None]))
    padded = _with_geometry(padded, stages.geometry)
    result, weights, outlier, noise = stages.result, stages.weights, stages.outlier, stages.noise
    change_points, superseded = stages.change_points, stages.superseded
    replaced, sources = stages.replaced, stages.sources
    compile_s, fit_s = stages.compile_s, stages.fit_s
    fit_mask = train & ~superseded
    if drift:

        def fit_state(mask: np.ndarray) -> tuple[FitSolution, typing.Any, np.ndarray]:
            solution, _, _, _, outlier_, noise_mrad, _ = fit_on(padded, mask)
            return solution, noise_mrad, outlier_

        with activity("pointing drift and error law", logger=log):
            # a spot off its target is not a pointing error of its time
            predictive = temporal_drift(fit_state, padded, fit_mask & ~garbage[:, None] & ~off_target)
        if predictive["validation_records"] < DRIFT_MIN_VALIDATION:
            log.info(
                f"pointing drift not estimated: {predictive['validation_records']} later training records of "
                f"converged heliostats, {DRIFT_MIN_VALIDATION} needed; error law: Gaussian"
            )
        else:
            log.info(
                f"pointing drift {predictive['drift_mrad2_per_day']:.4f} mrad^2/day per component, sky-gap term "
                f"{predictive['sky_gap_mrad2_per_deg']:.4f} mrad^2/deg, creep term "
                f"{predictive['creep_mrad2_per_day2']:.3g} mrad^2/day^2 "
                f"(from {predictive['validation_records']} later training records), error law: "
                f"{PointingErrorLaw.from_dict(predictive['error_law']).describe()}"
            )
    else:
        predictive = _no_drift("not estimated")

    all_valid = jnp.asarray(padded.mask)
    errors = np.asarray(fleet_beam_errors_mrad(result.model, padded, all_valid))
    nominal_fleet = _with_geometry(padded, nominal_geometry)
    uncal = np.asarray(fleet_beam_errors_mrad(model0, nominal_fleet, all_valid))
    residuals = np.asarray(fleet_residuals_mrad(result.model, padded, all_valid))
    residuals_uncal = np.asarray(fleet_residuals_mrad(model0, nominal_fleet, all_valid))
    # Heliostats without a fit (too few records, no records) have no calibrated errors.
    fitted = np.isin(np.asarray(result.status), _NOT_FITTED, invert=True)
    unpooled = np.flatnonzero(np.asarray(result.status)[:n_real] == FitStatus.TOO_FEW_RECORDS)
    if pool and robust and unpooled.size:  # a learnt prior constrains every parameter: the prior was not learnt
        log.warning(
            f"fleet prior not learnt: fewer than {MIN_PRIOR_HELIOSTATS} heliostats determine their parameters "
            f"from their own records; {few_names([ids[i] for i in unpooled])} "
            f"{'stays' if unpooled.size == 1 else 'stay'} uncalibrated (fewer training "
            "records than free parameters): add records or heliostats"
        )
    small_fleet = np.asarray(stages.small_fleet_prior, bool) & fitted & ~garbage
    small_fleet[n_real:] = False
    if small_fleet.any():
        n_small = int(small_fleet.sum())
        log.warning(
            f"fleet prior not learnt: fewer than {MIN_PRIOR_HELIOSTATS} heliostats determine their parameters "
            f"from their own records; {few_names([ids[i] for i in np.flatnonzero(small_fleet)])} "
            f"{'is' if n_small == 1 else 'are'} calibrated under the small-fleet prior instead (centred on the "
            "heliostats that determine theirs, each parameter's spread at least its declared typical size): measure "
            f"{'it' if n_small == 1 else 'them'} again (heliojax plan) before relying on "
            f"{'it' if n_small == 1 else 'them'}"
        )
    errors = np.where(fitted[:, None], errors, np.nan)
    residuals = np.where(fitted[:, None, None], residuals, np.nan)

    test_err = test_uncal = None
    if test_fleet is not None:
        test_err, test_uncal = _evaluate_other(test_fleet, ids, result, padded, model0, nominal_geometry)

    run = CalibrationRun(
        fleet=padded,
        model0=model0,
        split_kind="test-data" if test_fleet is not None else "records" if record_roles is not None else split,
        train_mask=train,
        val_mask=val,
        test_mask=test,
        result=result,
        errors_mrad=errors,
        uncalibrated_mrad=uncal,
        residuals_mrad=residuals,
        uncalibrated_residuals_mrad=residuals_uncal,
        start_replaced=np.asarray(replaced),
        start_sources=np.asarray(sources),
        too_few=too_few,
        summary={},
        test_errors_mrad=test_err,
        test_uncalibrated_mrad=test_uncal,
        weights=weights,
        outlier=outlier,
        noise_mrad=noise,
        robust=robust,
        pooled=robust and pool,
        change_points=change_points,
        superseded=superseded,
        predictive=predictive,
        noise_outlier=noisy,
        small_fleet_prior=small_fleet,
        off_target=off_target,
        spots_off_target=astray,
    )
    summary = _summarise(run, n_real, compile_s=compile_s, fit_s=fit_s)
    warming.result()  # done by now; no work outlives the call
    return dataclasses.replace(run, summary=summary)


def _compile_later_stages(
    model0: AbstractKinematicModel, fleet, train: np.ndarray, free, *, robust: bool, changes: bool
) -> None:
    """Run, on a placeholder fit (:meth:`FitSolution.placeholder`), what every run of
    :func:`calibrate`'s stages after the first fit runs: the robust passes' residuals
    and the change-point scan (residuals, their Jacobians, the scan), for the programs
    they compile; results discarded (see :func:`heliojax._programs.warm_up`)."""
    solution = FitSolution.placeholder(model0, fleet, free)
    mask = jax.device_put(train)
    if robust:
        fleet_residuals_mrad(solution.model, fleet, mask)
    if changes:
        find_change_points(solution, fleet, mask, jax.device_put(np.ones(train.shape, np.dtype(fleet.counts.dtype))))


@dataclasses.dataclass(frozen=True)
class _Stages:
    """What :func:`calibrate`'s fit stages give, per heliostat ``(H, ...)``."""

    geometry: typing.Any
    replaced: np.ndarray
    sources: np.ndarray
    result: FitSolution
    compile_s: float
    fit_s: float
    weights: np.ndarray
    outlier: np.ndarray
    noise: np.ndarray
    change_points: ChangePoints | None
    superseded: np.ndarray
    small_fleet_prior: np.ndarray


def _merge_stages(take: np.ndarray, a: _Stages, b: _Stages) -> _Stages:
    """Per heliostat, ``a``'s stages where ``take`` ``(H,)`` else ``b``'s (timings added;
    the fleet-typical actuators' sources are ``b``'s)."""
    h = take.shape[0]

    def pick(x, y):
        if not (eqx.is_array_like(x) and np.ndim(x) >= 1 and np.shape(x)[0] == h):
            return y
        keep = np.reshape(take, (-1,) + (1,) * (np.ndim(x) - 1))
        out = np.where(keep, np.asarray(x), np.asarray(y))
        return out if isinstance(y, np.ndarray) else jax.device_put(out)

    fields = {f.name: getattr(b, f.name) for f in dataclasses.fields(b)}
    names = ("geometry", "replaced", "result", "weights", "outlier", "noise", "change_points", "superseded")
    for name in (*names, "small_fleet_prior"):
        fields[name] = jax.tree.map(pick, getattr(a, name), getattr(b, name))
    fields["sources"] = b.sources
    fields["compile_s"], fields["fit_s"] = a.compile_s + b.compile_s, a.fit_s + b.fit_s
    return _Stages(**fields)


DRIFT_MIN_RECORDS = 8
"""Heliostats with at least this many training records lend their latest ones to
:func:`temporal_drift`'s validation."""
DRIFT_HOLDOUT_FRACTIONS = (0.3, 0.5)
"""Fractions of such a heliostat's training records (its latest) predicted, not fitted,
one validation origin each: the latest 30 % from a fit on the earliest 70 %, the latest
50 % from one on the earliest 50 %, so that the validation horizons reach half the
records' span (a plant aims for months with a calibration; with the 30 % origin alone the
law saw horizons of a few weeks to months only and, on the independent simulator, under
drifts that grow in time predicted regions far too narrow for later records: README,
"Two validation origins")."""
DRIFT_MIN_VALIDATION = 10
"""Fewest predicted records (of converged heliostats) from which the drift and the error
law are estimated; with fewer, no drift and the Gaussian law."""


def residual_prediction(solution: FitSolution, fleet, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(residual, covariance)``: each record's residual (mrad, ``(H, M, 2)``) under the
    fitted models and its predicted covariance from the parameters alone,
    ``J C J^T`` (mrad^2, ``(H, M, 2, 2)``; ``J`` the record's Jacobian w.r.t. the free
    parameters, ``C`` the fit's covariance); zero Jacobian rows outside ``mask``. Add
    the noise (and the drift, :func:`temporal_drift`) for a record's full prediction."""
    use = jax.device_put(mask) if isinstance(mask, np.ndarray) else jnp.asarray(mask)  # no eager XLA op
    r = np.asarray(fleet_residuals_mrad(solution.model, fleet, use))
    jac = np.asarray(
        residual_jacobians(
            solution.model, solution.view, fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, use
        )
    )
    return r, np.einsum("hmif,hfg,hmjg->hmij", jac, np.asarray(solution.covariance), jac)


def prediction_d2(run: CalibrationRun, mask: np.ndarray | None = None) -> np.ndarray:
    """``(H, M)`` squared Mahalanobis distance ``d^2 = r^T P^-1 r`` of each record's
    residual ``r`` under its full predicted scale ``P = J C J^T + (noise^2 + q a + g
    gap + c b^2) I`` (:func:`residual_prediction`, the fit's noise per component, the
    drift rate ``q``, sky-gap rate ``g`` and creep rate ``c`` of :func:`temporal_drift`,
    the fitted state's age ``a`` in days, :func:`heliojax.days_since_fit`, the record's
    sky gap in deg to the fitted records that are not outliers,
    :func:`heliojax.record_sky_gap_deg`, and its days ``b`` from their mean time,
    :func:`heliojax.days_from_fitted_mean`);
    NaN outside ``mask`` (default: every record of
    ``run.fleet``). A record lies in the ``p`` prediction region when
    ``d^2 <= heliojax.prediction_region_d2(p, law)``, ``law`` the run's
    :class:`heliojax.PointingErrorLaw` (``run.predictive["error_law"]``)."""
    padded = run.fleet
    use = np.asarray(padded.mask, bool) if mask is None else np.asarray(mask, bool) & np.asarray(padded.mask, bool)
    r, s = residual_prediction(run.result, padded, use)
    unix = np.asarray(padded.context.unix_time, float)
    fitted = np.asarray(run.train_mask, bool)
    if run.superseded is not None:
        fitted = fitted & ~np.asarray(run.superseded, bool)
    days = days_since_fit(fitted, unix, unix)
    h = r.shape[0]
    noise = np.full(h, np.nan) if run.noise_mrad is None else np.asarray(run.noise_mrad, float)
    noise = np.pad(noise, (0, max(h - noise.size, 0)), constant_values=np.nan)[:h]
    q = float(run.predictive.get("drift_mrad2_per_day", 0.0))
    extra = q * np.nan_to_num(days)
    inliers = fitted if run.outlier is None else fitted & ~np.asarray(run.outlier, bool)
    rates = {term: float(run.predictive.get(key, 0.0)) for term, key in DRIFT_RATE_KEYS.items()}
    for term, x in _term_covariates(inliers, padded, [t for t, rate in rates.items() if rate > 0.0]).items():
        extra = extra + rates[term] * x
    total = s + (noise[:, None] ** 2 + extra)[..., None, None] * np.eye(2)
    ok = use & np.all(np.isfinite(r), axis=-1) & np.all(np.isfinite(total), axis=(-2, -1))
    safe = np.where(ok[..., None, None], total, np.eye(2))
    r = np.where(ok[..., None], r, 0.0)
    d2 = np.einsum("hmi,hmij,hmj->hm", r, np.linalg.inv(safe), r)
    return np.where(ok, d2, np.nan)


def _term_covariates(inliers: np.ndarray, fleet, terms: collections.abc.Iterable[str]) -> dict[str, np.ndarray]:
    """``(H, M)`` covariate of each of the drift ``terms`` (:data:`heliojax.DRIFT_TERMS`)
    for every record of ``fleet``, from the fitted records that are not outliers
    (``inliers`` ``(H, M)``): ``sky_gap_deg``, the angle (deg) from the record's sun to
    theirs (:func:`heliojax.record_sky_gap_deg`; inf for a heliostat without one) and
    ``creep_days2``, the squared days from their mean time
    (:func:`heliojax.days_from_fitted_mean`; 0 for a heliostat without one, whose sky
    gap is inf)."""
    out = {}
    for term in terms:
        if term == "sky_gap_deg":
            out[term] = record_sky_gap_deg(inliers, np.asarray(fleet.context.sun, float))
        elif term == "creep_days2":
            unix = np.asarray(fleet.context.unix_time, float)
            out[term] = np.nan_to_num(days_from_fitted_mean(inliers, unix, unix)) ** 2
        else:
            raise ValueError(f"unknown drift term {term!r}; expected one of {sorted(DRIFT_RATE_KEYS)}")
    return out


def _no_drift(method: str) -> dict[str, typing.Any]:
    """The predictive entry without a drift and with the Gaussian law."""
    return {
        "drift_mrad2_per_day": 0.0,
        **dict.fromkeys(DRIFT_RATE_KEYS.values(), 0.0),
        "tail_dof": math.inf,
        "error_law": PointingErrorLaw().to_dict(),
        "method": method,
    }


def temporal_drift(
    fit: collections.abc.Callable[[np.ndarray], tuple[FitSolution, typing.Any, typing.Any]],
    fleet,
    fit_mask: np.ndarray,
    *,
    min_records: int = DRIFT_MIN_RECORDS,
    fractions: collections.abc.Sequence[float] | None = None,
) -> dict:
    """The fleet's pointing drift: how fast (mrad^2 per day, per tangent component)
    records *later* than the fitted ones spread beyond what the parameter covariance
    and the measurement noise predict (wear, settling, effects the model lacks).

    Model (:mod:`heliojax._predictive`): a random walk of the beam direction from the
    fitted state, the process noise of a Kalman filter, with heavy tails; a record
    ``dt`` days after the heliostat's last fitted record, its sun ``gap`` deg from the
    nearest sun of the fitted records that are not outliers
    (:func:`heliojax.record_sky_gap_deg`), ``b`` days from the mean time of those
    records (:func:`heliojax.days_from_fitted_mean`), is predicted with scale matrix
    ``S + (q * dt + g * gap + c * b^2) * I`` under a :class:`heliojax.PointingErrorLaw` (a bivariate
    Student t with ``tail_dof`` degrees of freedom, ``inf``: the Gaussian, either
    with a broad outlier component or without), where ``S = J C J^T + noise^2 I`` (``J``
    its Jacobian w.r.t. the free parameters, ``C`` the fit's covariance, ``noise`` the
    fit's noise per component). Its prediction regions:
    :func:`heliojax.prediction_region_d2`.

    ``q`` and the law are estimated by time-blocked validation on the training
    records only (the test records are never looked at), from each of several origins:
    for each ``fraction`` of ``fractions`` (default :data:`DRIFT_HOLDOUT_FRACTIONS`),
    every heliostat with at least
    ``min_records`` records in ``fit_mask`` holds out its latest ``fraction`` of them;
    ``fit`` (the calibration's own fit, ``mask -> (solution, noise_mrad (H,), outlier
    (H, M))``) is run on the rest, and the held-out records are predicted from it. A
    record held out at two origins counts once at each, with the fit, age and gaps of
    each. ``q``, ``g``, ``c`` and the law maximise the likelihood of all these
    residuals, the family chosen by BIC and ``g > 0`` and
    ``c > 0`` only where the BIC asks for them, ``c`` beside ``q`` or instead of it
    (:func:`heliojax.fit_drift_terms_and_law`). Gross errors and maintenance episodes
    among the held-out records go into the law's tails instead of inflating ``q``; a
    model that errs more in poses unlike the fitted ones gets ``g``; a beam that creeps
    steadily (a linear drift, whose error grows as ``b``, not as ``sqrt(dt)``) gets ``c``.

    Raises:
        ConfigError: ``min_records`` not a whole number >= 2, ``fractions`` empty or
            not shares in (0, 1).

    Returns:
        ``{"drift_mrad2_per_day", "sky_gap_mrad2_per_deg", "creep_mrad2_per_day2", "tail_dof", "error_law",
        "validation_records",
        "validation_heliostats", "validation_median_days", "validation_median_sky_gap_deg", "median_d2_without",
        "method"}`` (``error_law``: :meth:`PointingErrorLaw.to_dict`; ``tail_dof`` the
        t's degrees of freedom, inf for the other laws; ``validation_records`` counts a
        record once per origin that predicts it); the rates are 0 and the law Gaussian
        with fewer than :data:`DRIFT_MIN_VALIDATION` validation records.
    """
    problem = count_problem(min_records, 10**9, minimum=2)  # 0 had held out the only record of a heliostat
    if problem is not None:
        raise ConfigError(f"temporal_drift: min_records {problem}")
    fractions = DRIFT_HOLDOUT_FRACTIONS if fractions is None else tuple(fractions)
    if not fractions or any(real_problem(f) is not None or not 0.0 < f < 1.0 for f in fractions):
        # 1.5 had held out every record and more, NaN none, without a word
        raise ConfigError(f"temporal_drift: fractions must be shares in (0, 1), got {fractions!r}"[:200])
    fleet_mask = np.asarray(fleet.mask)
    unix_time = np.asarray(fleet.context.unix_time, float)
    shares = ", ".join(f"{f:.0%}" for f in fractions)
    method = (
        "random walk from the fitted state in time and across the sky, or a linear creep in time, bivariate "
        "Student t or Gaussian, with or without an outlier component (maximum likelihood, the family, the sky "
        f"term and the creep by BIC); rates and tails from the latest {shares} of the training records of "
        f"heliostats with >= {min_records}, each predicted from a fit on the earlier ones"
    )
    out = _no_drift(method)
    parts, heliostats, largest = [], np.zeros(fleet_mask.shape[0], bool), 0
    for fraction in fractions:
        early, late = chronological_holdout(np.asarray(fit_mask) & fleet_mask, unix_time, min_records, fraction)
        largest = max(largest, int(late.sum()))
        if late.sum() < DRIFT_MIN_VALIDATION:
            continue
        solution, noise, outlier = fit(early)
        converged = np.asarray(solution.status) == FitStatus.CONVERGED
        late = late & converged[:, None]
        r, s = residual_prediction(solution, fleet, late)
        s = s + (np.asarray(noise, float) ** 2)[:, None, None, None] * np.eye(2)
        days = days_since_fit(early, unix_time, unix_time)
        covariates = _term_covariates(early & ~np.asarray(outlier, bool), fleet, DRIFT_RATE_KEYS)
        use = late & np.all(np.isfinite(r), axis=-1) & np.all(np.isfinite(s), axis=(-2, -1)) & np.isfinite(days)
        for x in covariates.values():
            use &= np.isfinite(x)
        heliostats |= np.any(use, axis=1)
        parts.append((r[use], s[use], days[use], {term: x[use] for term, x in covariates.items()}))
    if not parts:  # the most records an origin would have held out
        out.update(validation_records=largest, validation_heliostats=0, median_d2_without=None)
        return out
    r, s, days = (np.concatenate([p[i] for p in parts]) for i in range(3))
    covariates = {term: np.concatenate([p[3][term] for p in parts]) for term in DRIFT_RATE_KEYS}

    def median_d2(q: float) -> float:
        total = s + (q * days)[:, None, None] * np.eye(2)
        return float(np.median(np.einsum("ni,nij,nj->n", r, np.linalg.inv(total), r)))

    n = r.shape[0]
    out.update(
        validation_records=n,
        validation_heliostats=int(heliostats.sum()),
        validation_median_days=float(np.median(days)) if n else None,
        validation_median_sky_gap_deg=float(np.median(covariates["sky_gap_deg"])) if n else None,
        median_d2_without=median_d2(0.0) if n else None,
    )
    if n < DRIFT_MIN_VALIDATION:
        return out
    q, rates, law = fit_drift_terms_and_law(r, s, days, **covariates)
    out.update(drift_mrad2_per_day=q, tail_dof=law.tail_dof, error_law=law.to_dict())
    out.update({key: rates[term] for term, key in DRIFT_RATE_KEYS.items()})
    return out


RECORD_ROLES = ("train", "test")
"""Roles of a record in :func:`calibrate`'s ``record_roles``."""

CALIBRATION_STARTS = ("auto", "nominal")
"""The start geometries :func:`calibrate` knows (its ``start``)."""


def _split_times(fleet, split: str) -> np.ndarray:
    """``(H, M)`` the times the split orders records by (s): the records' UTC times, or,
    for the time split of a fleet none of whose records has a time (a download without
    PAINT's timestamps), their PAINT record ids, which PAINT numbers in the order the
    records were measured (the 1,706 timestamped ids of the shared download are in
    strictly chronological order: :mod:`heliojax.paint`). Only the order is used."""
    times = np.asarray(fleet.context.unix_time, float)
    records = np.asarray(fleet.mask)
    if split != "time" or not records.any() or np.isfinite(times)[records].any():
        return times
    log.warning(
        "no record has a time (PAINT's calibration-timestamps.json or metadata CSV missing beside the data?): "
        "the time split orders each heliostat's records by PAINT record id, which PAINT numbers in "
        "measurement order; without times there is no pointing drift and no dated change point"
    )
    return np.where(records, np.asarray(fleet.record_id, float), np.nan)


def roles_to_masks(
    fleet, record_roles: collections.abc.Mapping[str, collections.abc.Mapping[int, str]], *, warn: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """``(train, test)`` masks ``(H, M)`` of ``fleet`` from ``record_roles`` (see
    :func:`calibrate`); ``warn``: log heliostats that train but get no held-out record
    (off for a check of the roles ahead of the :func:`calibrate` that warns).

    Raises:
        ConfigError: naming a heliostat or record that ``fleet`` does not hold, or a role
            other than ``"train"`` / ``"test"``.
    """
    ids = list(fleet.ids)
    record_id = np.asarray(fleet.record_id)
    valid = np.asarray(fleet.mask)
    train = np.zeros(valid.shape, bool)
    test = np.zeros(valid.shape, bool)
    any_test = False
    for hid, roles in record_roles.items():
        if hid not in ids:
            raise ConfigError(f"record roles name heliostat {hid!r}, which the data do not hold")
        i = ids.index(hid)
        where = {int(r): j for j, r in enumerate(record_id[i]) if valid[i, j]}
        if not isinstance(roles, collections.abc.Mapping):
            raise ConfigError(
                f"record roles of {hid}: expected {{PAINT record id: 'train' or 'test'}}, not a {type(roles).__name__}"
            )
        for rid, role in roles.items():
            if isinstance(rid, bool) or not isinstance(rid, (int, np.integer)):
                raise ConfigError(f"record roles of {hid}: record id {rid!r} is not a whole number")
            if role not in RECORD_ROLES:
                raise ConfigError(f"record {rid} of {hid}: role {role!r} is not one of {RECORD_ROLES}")
            if int(rid) not in where:
                raise ConfigError(f"record roles name record {rid} of {hid}, which the data do not hold")
            (train if role == "train" else test)[i, where[int(rid)]] = True
            any_test |= role == "test"
    if not train.any():
        raise ConfigError("no record has the role train: there is nothing to calibrate")
    if not any_test:
        test = valid & ~train
    else:  # the file names held-out records: a heliostat it names none for is evaluated on nothing
        idle = valid & ~train & ~test
        named = [
            f"{hid} ({int(idle[i].sum())})"
            for i, hid in enumerate(ids)
            if hid in record_roles and train[i].any() and not test[i].any()
        ]
        if named and warn:
            log.warning(
                f"record roles: {len(named)} heliostat(s) train but get no held-out record (test roles are "
                f"given for others only; the count of their records left out in brackets): {few_names(named, 10)}"
            )
    return train, test


def _scan_changes(
    result: FitSolution, fleet, train: np.ndarray, weights: np.ndarray
) -> tuple[ChangePoints | None, np.ndarray]:
    """The change-point scan of the converged heliostats' training records, and
    ``(H, M)`` the training records before a reported change."""
    try:
        # any change of state, a drift included: the records since describe the heliostat
        cp = find_change_points(result, fleet, jax.device_put(train), jax.device_put(weights))
    except ConfigError as e:  # a model without a free pair of axis offsets
        log.info(f"no change-point scan: {e}")
        return None, np.zeros_like(train)
    found = np.asarray(cp.found) & (np.asarray(result.status) == FitStatus.CONVERGED)
    t = np.asarray(fleet.context.unix_time)
    with np.errstate(invalid="ignore"):
        superseded = train & found[:, None] & (t < np.asarray(cp.time_s)[:, None])
    step = np.asarray(cp.is_step) & found
    return eqx.tree_at(lambda c: (c.found, c.is_step), cp, (jax.device_put(found), jax.device_put(step))), superseded


RECENT_OUTLIERS_WARN = 2
"""A heliostat whose latest this-many (or more) fitted records are all gross errors is
warned about: one glitch is common, a run of them at the end is how a change that has
just started looks (too few records after it for a change point)."""


def _recent_outliers(run: CalibrationRun, fit_mask: np.ndarray, i: int) -> dict[str, typing.Any]:
    """The run of gross errors at the end of heliostat ``i``'s fitted records (by time):
    its length, first record's time and median beam error, and a warning from
    :data:`RECENT_OUTLIERS_WARN` records on."""
    none = {"recent_outliers": 0, "recent_outliers_since": None, "recent_outliers_median_mrad": None, "warning": None}
    if run.outlier is None:
        return none
    t = np.asarray(run.fleet.context.unix_time, float)[i]
    used = fit_mask[i] & np.isfinite(t)
    order = np.argsort(np.where(used, t, -np.inf))[::-1][: int(used.sum())]  # latest first
    flagged = np.asarray(run.outlier[i])[order]
    n = int(np.argmin(flagged)) if not flagged.all() else int(flagged.size)
    if n == 0:
        return none
    first = order[n - 1]
    median = float(np.median(run.errors_mrad[i][order[:n]]))
    warning = None
    if n >= RECENT_OUTLIERS_WARN:
        warning = (
            f"its latest {n} fitted records (since {utc_iso(t[first])}) are all gross errors, median "
            f"{median:.1f} mrad: a change may have started; measure it again before aiming with this calibration"
        )
    return {
        "recent_outliers": n,
        "recent_outliers_since": utc_iso(t[first]),
        "recent_outliers_median_mrad": _json_float(median),
        "warning": warning,
    }


def _change_entry(run: CalibrationRun, i: int) -> dict[str, typing.Any]:
    cp = run.change_points
    if cp is None:
        return {"change_point": None, "change_point_delta_chi2": None}
    dchi2 = _json_float(float(np.asarray(cp.delta_chi2)[i]))
    if not bool(np.asarray(cp.found)[i]):
        return {"change_point": None, "change_point_delta_chi2": dchi2}
    jump = np.asarray(cp.jump_mrad)[i]
    n_sup = int(run.superseded[i].sum()) if run.superseded is not None else 0
    return {
        "change_point": {
            "date_utc": utc_iso(float(np.asarray(cp.time_s)[i])),
            "previous_record_utc": utc_iso(float(np.asarray(cp.previous_time_s)[i])),
            "kind": "step" if bool(np.asarray(cp.is_step)[i]) else "drift",
            "jump_mrad": {n: _json_float(float(v)) for n, v in zip(cp.offsets, jump)},
            "delta_chi2": dchi2,
            "drift_delta_chi2": _json_float(float(np.asarray(cp.drift_delta_chi2)[i])),
            "threshold": _json_float(float(np.asarray(cp.threshold)[i])),
            "n_records_since": int(np.asarray(cp.n_after)[i]),
            "n_training_records_superseded": n_sup,
        },
        "change_point_delta_chi2": dchi2,
    }


def _with_geometry(fleet, geometry):
    return eqx.tree_at(lambda f: f.geometry, fleet, geometry)


def _without_training_records(test_fleet, fleet):
    """``test_fleet`` without its records that ``fleet`` trains on (the same heliostat and
    PAINT record id: the training folder, or a copy of it, given as test data), named in
    a warning; a ConfigError when no test record is left. Held-out errors of training
    records are training errors: 1.27 against 21.3 mrad on a trial's three heliostats."""
    fitted_heliostat = np.isin(np.asarray(test_fleet.ids), np.asarray(fleet.ids))[:, None]
    mask = np.asarray(test_fleet.mask)
    shared = mask & records_among(test_fleet.ids, test_fleet.record_id, fleet.ids, fleet.record_id, fleet.mask)
    if not shared.any():
        return test_fleet
    if not (mask & ~shared & fitted_heliostat).any():
        raise ConfigError(
            f"every test record of the heliostats fitted ({int(shared.sum())}) is also a training record "
            "(the same heliostat and record id): the test data is the training data"
        )
    names = [f"{test_fleet.ids[i]} ({int(shared[i].sum())})" for i in np.flatnonzero(shared.any(axis=1))]
    log.warning(
        f"{int(shared.sum())} test record(s) are training records too (the same heliostat and record id) "
        f"and are not held out (heliostat, records): {few_names(names, 10)}"
    )
    return eqx.tree_at(lambda f: f.mask, test_fleet, jnp.asarray(mask & ~shared))


def _evaluate_other(test_fleet, ids, result, padded, model0, nominal_geometry):
    """Beam errors of ``test_fleet``'s records under the fitted models of the
    heliostats with the same ids (NaN rows for ids without a fit)."""
    index = {h: i for i, h in enumerate(ids)}
    rows = np.array([index.get(h, -1) for h in test_fleet.ids])
    known = rows >= 0
    take = np.where(known, rows, 0)
    h_pad = result.n_heliostats
    models = jax.tree.map(lambda x: x[take] if eqx.is_array(x) else x, result.model)
    geometry = jax.tree.map(lambda x: x[take], padded.geometry)
    geometry0 = jax.tree.map(lambda x: x[take], nominal_geometry)
    mask = jnp.asarray(np.asarray(test_fleet.mask) & known[:, None])
    args = (test_fleet.counts, test_fleet.context, test_fleet.focal_spot, mask)
    err = np.asarray(beam_errors_mrad(models, geometry, *args))
    nominal = jax.tree.map(lambda x: jnp.broadcast_to(x, (len(take),) + jnp.shape(x)) if eqx.is_array(x) else x, model0)
    unc = np.asarray(beam_errors_mrad(nominal, geometry0, *args))
    # Re-index to the training fleet's rows.
    out = np.full((h_pad, err.shape[1]), np.nan)
    out_u = np.full((h_pad, err.shape[1]), np.nan)
    out[rows[known]] = err[known]
    out_u[rows[known]] = unc[known]
    fitted = np.isin(np.asarray(result.status), _NOT_FITTED, invert=True)
    return np.where(fitted[:, None], out, np.nan), out_u


def _summarise(run: CalibrationRun, n_real: int, compile_s: float, fit_s: float) -> dict:
    res = run.result
    view = res.view
    params = np.asarray(res.parameters())
    std = np.asarray(res.std)
    status = np.asarray(res.status)
    ids = run.fleet.ids
    test_err = (
        run.test_errors_mrad if run.test_errors_mrad is not None else np.where(run.test_mask, run.errors_mrad, np.nan)
    )
    test_unc = (
        run.test_uncalibrated_mrad
        if run.test_uncalibrated_mrad is not None
        else np.where(run.test_mask, run.uncalibrated_mrad, np.nan)
    )
    fit_mask = run.fitted_mask
    train_err = np.where(fit_mask, run.errors_mrad, np.nan)  # the training records the fit used
    val_err = np.where(run.val_mask, run.errors_mrad, np.nan)
    loo_rms, unc_train_rms, worse = _worse_than_nominal(run, fit_mask)
    garbage = np.zeros(len(status), bool) if run.noise_outlier is None else np.asarray(run.noise_outlier, bool)
    small = np.zeros(len(status), bool) if run.small_fleet_prior is None else np.asarray(run.small_fleet_prior, bool)
    off_target = np.zeros(run.train_mask.shape, bool) if run.off_target is None else np.asarray(run.off_target, bool)
    astray = np.zeros(len(status), bool) if run.spots_off_target is None else np.asarray(run.spots_off_target, bool)
    typical = _typical_noise(run, garbage | astray)
    heliostats = {}
    pooled, pooled_unc = [], []
    for i in range(n_real):
        st = FitStatus(int(status[i]))
        test_med, test_rms = _stats(test_err[i])
        unc_med, unc_rms = _stats(test_unc[i])
        train_med, train_rms = _stats(train_err[i])
        inliers = train_err[i] if run.outlier is None else np.where(run.outlier[i], np.nan, train_err[i])
        _, train_inlier_rms = _stats(inliers)
        _, val_rms = _stats(val_err[i])
        n_candidates = int(np.sum(np.asarray(run.fleet.mask)[i]))
        label, reason = _status_reason(st, run, i, n_candidates, int(np.asarray(res.n_steps)[i]))
        held_out_note = _worse_on_held_out(st, test_err[i], test_unc[i])
        entry = {
            "status": label,
            "status_reason": reason,
            # Record counts of the split (also for heliostats that could not be fitted).
            "n_train": int(np.sum(run.train_mask[i] & np.isfinite(run.uncalibrated_mrad[i]))),
            "n_train_used": int(np.sum(fit_mask[i] & np.isfinite(run.uncalibrated_mrad[i]))),
            "n_val": int(np.sum(run.val_mask[i] & np.isfinite(run.uncalibrated_mrad[i]))),
            "n_test": int(np.sum(np.isfinite(test_unc[i]))),
            "train_rms_mrad": _json_float(train_rms),
            "train_inlier_rms_mrad": _json_float(train_inlier_rms),
            "val_rms_mrad": _json_float(val_rms),
            "test_median_mrad": _json_float(test_med),
            "test_rms_mrad": _json_float(test_rms),
            "uncalibrated_test_median_mrad": _json_float(unc_med),
            "uncalibrated_test_rms_mrad": _json_float(unc_rms),
            "loo_rms_mrad": _json_float(loo_rms[i]),
            "uncalibrated_train_rms_mrad": _json_float(unc_train_rms[i]),
            "worse_than_nominal": bool(worse[i]),
            "worse_than_nominal_held_out": held_out_note is not None,
            **_change_entry(run, i),
            **_recent_outliers(run, fit_mask, i),
            "noise_outlier": bool(garbage[i]),
            "n_off_target": int(np.sum(off_target[i])),
            "spots_off_target": bool(astray[i]),
            "small_fleet_prior": bool(small[i]),
            "lm_steps": int(np.asarray(res.n_steps)[i]),
            "noise_mrad": _json_float(float(run.noise_mrad[i])) if run.noise_mrad is not None else None,
            "n_outliers": int(np.sum(run.outlier[i])) if run.outlier is not None else 0,
            "outlier_record_ids": [int(x) for x in np.asarray(run.fleet.record_id)[i][run.outlier[i]]]
            if run.outlier is not None
            else [],
            "start_geometry": "fleet_typical" if run.start_replaced[i] else "nominal",
            "params": {n: _json_float(params[i, k]) for k, n in enumerate(view.names)},
            "param_std": {n: _json_float(std[i, k]) for k, n in enumerate(view.names)},
        }
        if ids[i] in run.too_few:
            entry["split_note"] = run.too_few[ids[i]]
        if garbage[i]:
            note = (
                f"its noise {float(np.asarray(run.noise_mrad)[i]):.3g} mrad per component is far above the "
                f"fleet's typical {typical:.3g} mrad (garbage records or a wrong properties file?): left out of "
                "the fleet's statistics; check its records and properties before aiming with this calibration"
            )
            _add_warning(entry, note)
        if astray[i]:
            _add_warning(
                entry,
                f"{int(np.sum(off_target[i] & run.train_mask[i]))} of its {entry['n_train']} training records have "
                "their focal spot off their target (wrong spots, targets or survey?): its fit follows them; left out "
                "of the fleet's statistics and not to be aimed with (heliojax aim flags it unreliable)",
            )
        if small[i]:
            _add_warning(
                entry,
                f"calibrated under the small-fleet prior (fewer than {MIN_PRIOR_HELIOSTATS} heliostats determine "
                "their parameters alone, too few to learn a fleet prior from)",
            )
        if held_out_note is not None:
            _add_warning(entry, f"on its {entry['n_test']} held-out records {held_out_note}")
        if st == FitStatus.CONVERGED and 2 * entry["n_train_used"] < view.n_free:
            note = _few_records_note(entry["n_train_used"], view.n_free, "small-fleet" if small[i] else "fleet")
            _add_warning(entry, note)
        heliostats[ids[i]] = entry
        if st == FitStatus.CONVERGED:
            t = test_err[i][np.isfinite(test_err[i])]
            pooled.append(t)
        u = test_unc[i][np.isfinite(test_unc[i])]
        pooled_unc.append(u)
    pooled = np.concatenate(pooled) if pooled else np.array([])
    pooled_unc = np.concatenate(pooled_unc) if pooled_unc else np.array([])
    f_med, f_rms = _stats(pooled)
    u_med, u_rms = _stats(pooled_unc)
    n_conv = int(np.sum(status[:n_real] == FitStatus.CONVERGED))
    return {
        "model": run.model0.label(),
        "split": run.split_kind,
        "robust": bool(run.robust),
        "pooled": bool(run.pooled),
        "param_units": dict(zip(view.names, view.units)),
        "free_params": list(view.free_names),
        "start_geometry_sources": [ids[i] for i in range(n_real) if run.start_sources[i]],
        "heliostats": heliostats,
        "fleet": {
            "n_heliostats": n_real,
            "n_converged": n_conv,
            "n_test_records": int(pooled.size),
            "test_median_mrad": _json_float(f_med),
            "test_rms_mrad": _json_float(f_rms),
            "uncalibrated_test_median_mrad": _json_float(u_med),
            "uncalibrated_test_rms_mrad": _json_float(u_rms),
            "worse_than_nominal": [ids[i] for i in range(n_real) if worse[i]],
            "change_points": [h for h, e in heliostats.items() if e["change_point"] is not None],
            "noise_outliers": [h for h, e in heliostats.items() if e["noise_outlier"]],
            "spots_off_target": [h for h, e in heliostats.items() if e["spots_off_target"]],
            "small_fleet_prior": [h for h, e in heliostats.items() if e["small_fleet_prior"]],
            "statuses": {
                **{s.label: int(np.sum(status[:n_real] == s)) for s in FitStatus if s != FitStatus.NO_RECORDS},
                "no_training_records": int(np.sum(status[:n_real] == FitStatus.NO_RECORDS)),
            },
        },
        "load_flags": _load_flags(run.fleet.report),
        "predictive": {k: (_json_float(v) if isinstance(v, float) else v) for k, v in run.predictive.items()},
        "timing": {"compile_s": float(compile_s), "fit_s": float(fit_s)},
    }


def _load_flags(report) -> list[dict[str, str | None]]:
    """``summary.json``'s ``load_flags``: the suspicious inputs the load of the fitted
    data kept (:attr:`heliojax.LoadReport.flags`: a focal spot far off its target, a
    record time of another zone, ...), so that a ``--quiet`` or scheduled run keeps
    them beside the fit they may have spoilt. One entry per flag:

    - ``heliostat``: the heliostat folder that holds the file (null for a file of the
      whole download, such as the weather CSV or the timestamps);
    - ``file``: the file, relative to the data folder (a CSV's ``:line`` kept);
    - ``field``: the dotted field (null: the whole file);
    - ``reason``: why it is suspicious (as ``heliojax inspect`` lists it).
    """
    out: list[dict[str, str | None]] = []
    for entry in report.flags:
        try:
            rel = Path(entry.file).relative_to(report.source)
        except ValueError:  # a file outside the data folder (or a load of records, not a folder)
            rel = None
        heliostat = rel.parts[0] if rel is not None and len(rel.parts) > 1 else None
        shown = str(rel) if rel is not None else str(entry.file)
        out.append({"heliostat": heliostat, "file": shown, "field": entry.field, "reason": entry.reason})
    return out


HELD_OUT_WORSE_ALPHA = 0.01
"""Level of the one-sided sign test behind ``worse_than_nominal_held_out`` (as
discovery's default ``alpha``)."""


def _worse_on_held_out(status: FitStatus, calibrated: np.ndarray, uncalibrated: np.ndarray) -> str | None:
    """Why a converged heliostat's calibration is worse than the uncalibrated model on its
    held-out records, or None: ``calibrated`` and ``uncalibrated`` are the records' beam
    pointing errors ``(M,)`` (mrad, NaN where not held out). Worse: the calibrated model
    misses by more on significantly more than half of them (one-sided sign test at
    :data:`HELD_OUT_WORSE_ALPHA`; ties left out), so a heliostat that is nominal already
    (calibrated and uncalibrated errors alike) is not flagged by chance.
    ``worse_than_nominal`` judges the training records alone (by leave-one-out), as a
    plant without held-out records can; a split that trains on one part of the sky and
    tests on another (``--split azimuth``) can pass it and still extrapolate worse."""
    if status != FitStatus.CONVERGED:
        return None
    both = np.isfinite(calibrated) & np.isfinite(uncalibrated)
    diff = calibrated[both] - uncalibrated[both]
    n, k = int(np.sum(diff != 0.0)), int(np.sum(diff > 0.0))
    if n == 0 or 2 * k <= n:
        return None
    p = sum(math.comb(n, j) for j in range(k, n + 1)) / 2.0**n  # exact binomial tail
    if p >= HELD_OUT_WORSE_ALPHA:
        return None
    return (
        f"the calibrated model misses by more than the uncalibrated one on {k} of {n} (sign test p = {p:.2g}; "
        f"median {np.median(calibrated[both]):.3g} mrad against {np.median(uncalibrated[both]):.3g}): its training "
        "records may not cover where it was tested; do not aim with it blindly"
    )


def _add_warning(entry: dict[str, typing.Any], note: str) -> None:
    """Append ``note`` to a heliostat's summary ``warning`` (joined by ``; ``)."""
    entry["warning"] = note if entry["warning"] is None else f"{entry['warning']}; {note}"


def _few_records_note(n_used: int, n_free: int, prior: str = "fleet") -> str:
    """The warning of a converged heliostat whose records alone cannot determine its
    ``n_free`` parameters (fewer residuals than parameters): the ``prior`` (``"fleet"``
    or ``"small-fleet"``) decides the rest, and its leave-one-out check
    (``worse_than_nominal``) judges little."""
    return (
        f"calibrated from {_training_records(n_used)} ({2 * n_used} residuals) for {n_free} free parameters: "
        f"the rest comes from the {prior} prior and its leave-one-out check says little; measure it again "
        "(heliojax plan) before relying on this calibration"
    )


def _training_records(n: int) -> str:
    """``"1 training record"`` or ``"{n} training records"``."""
    return "1 training record" if n == 1 else f"{n} training records"


def _typical_noise(run: CalibrationRun, garbage: np.ndarray) -> float:
    """The fleet's median noise (mrad per component) over the fitted heliostats that
    are not noise outliers (NaN without such)."""
    if run.noise_mrad is None:
        return math.nan
    st = np.asarray(run.result.status)
    use = np.isin(st, _ATTEMPTED) & ~garbage & np.isfinite(run.noise_mrad)
    return float(np.median(np.asarray(run.noise_mrad)[use])) if use.any() else math.nan


def _worse_than_nominal(run: CalibrationRun, fit_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per heliostat ``(H,)``: the RMS leave-one-out error of the fitted model over
    its training records (:attr:`FitSolution.loo_mrad`; the PRESS statistic), the
    RMS error of the uncalibrated model over the same records, and the flag that
    the first is not below the second (a converged fit that does not predict
    better than nominal: do not aim with it blindly). Records flagged as gross
    errors are left out of both; no test record is used."""
    loo_all = np.asarray(run.result.loo_mrad)  # +inf where a record alone fixes a direction: kept
    used = fit_mask & ~np.isnan(loo_all) & np.isfinite(run.uncalibrated_mrad)
    if run.outlier is not None:
        used &= ~run.outlier
    converged = np.asarray(run.result.status) == FitStatus.CONVERGED
    n = used.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        loo = np.sqrt(np.sum(np.where(used, loo_all, 0.0) ** 2, axis=1) / n)  # NaN without records
        unc = np.sqrt(np.sum(np.where(used, run.uncalibrated_mrad, 0.0) ** 2, axis=1) / n)
        worse = converged & ~(loo < unc)
    return loo, unc, worse


def _status_reason(st: FitStatus, run: CalibrationRun, i: int, n_records: int, steps: int) -> tuple[str, str | None]:
    """The summary's status label of heliostat ``i`` and, unless it converged, why."""
    note = run.too_few.get(run.fleet.ids[i])
    n_train = int(np.sum(run.train_mask[i]))
    n_free = run.result.view.n_free
    why = {
        FitStatus.CONVERGED: None,
        FitStatus.MAX_STEPS: f"no convergence within {steps} Levenberg-Marquardt steps",
        FitStatus.DIVERGED: "the fit diverged or its result is not finite",
        FitStatus.NON_FINITE_INPUT: "a training record holds NaN or inf",
        FitStatus.TOO_FEW_RECORDS: f"{_training_records(n_train)} for {n_free} free parameters and no fleet prior"
        + (
            f" (fewer than {MIN_PRIOR_HELIOSTATS} heliostats determine their parameters alone to learn it from)"
            if run.pooled
            else " (pooling off)"
        ),
        FitStatus.FAILED: "the solver failed",
        FitStatus.NO_RECORDS: f"split {run.split_kind} leaves 0 of {n_records} records for training",
    }[st]
    if st == FitStatus.NO_RECORDS and n_records == 0:
        return "no_training_records", "no valid record loaded (the load report names why each was skipped)"
    if why is not None and note and st in (FitStatus.NO_RECORDS, FitStatus.TOO_FEW_RECORDS):
        why = f"{why} ({note})"
    return ("no_training_records" if st == FitStatus.NO_RECORDS else st.label), why


def write_summary(path: str | Path, run: CalibrationRun) -> None:
    """Write ``summary.json`` atomically.

    Raises:
        TypeError, ValueError: ``path`` is no path (None, an int: a TypeError of pathlib
            naming nothing) or empty ("" had been "Is a directory: '.'")."""
    check_path_argument(path)
    with atomic_write(path) as f:
        json.dump(run.summary, f, indent=2, allow_nan=False)
        f.write("\n")


__all__ = ["RECORD_ROLES", "CalibrationRun", "calibrate", "roles_to_masks", "write_summary"]
