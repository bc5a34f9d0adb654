"""Calibration with a neural correction: LM fit, then the network, the fallback
rule and the ``summary.json`` of ``heliojax calibrate --model stone8+nn``.

Records (per heliostat, chronological within the fleet):

* *train* (the split's): the LM model is fitted on all of them, as in
  :func:`heliojax.calibrate`.
* *validation* (the network's): the latest ``val_fraction`` of the training
  records. The network is fine-tuned on the others (*fit*), keeps the parameters
  with the lowest validation loss, and is used only if its median beam error on
  the validation records is at most ``1 + fallback_tolerance`` times the LM model's
  (which has seen those records: the rule errs toward LM). Otherwise, or when a
  heliostat has no validation record, it falls back to LM (``nn_fallback``). A
  residual network that no fine-tuning step improved on validation keeps its
  zero-initialised output: it *is* the LM model (same errors to the last digit),
  and is reported as a fallback too, with that reason.
* *test*: never used for training, selection or the fallback decision.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import numbers
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import ConfigError, few_names
from .._fleet import fleet_subset
from .._workflow import CalibrationRun, _json_float, _stats, calibrate
from ..fitting import FitStatus, beam_errors_mrad, residuals_mrad, sanitise
from ._model import NeuralCorrection, paper_beam_components, paper_beam_error
from ._train import (
    VARIANTS,
    NeuralConfig,
    _finetune_paper_program,
    _finetune_residual_program,
    _pretrain_paper_program,
    heliostat_keys,
    init_residual_networks,
    synthetic_fleet_data,
)

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class NeuralRun:
    """Outcome of :func:`calibrate_neural`.

    Attributes:
        lm: the physics-model :class:`heliojax.CalibrationRun` the network builds on.
        run: a :class:`heliojax.CalibrationRun` whose errors, residuals and summary are
            those of LM+NN (fallbacks applied); write it with
            :func:`heliojax.write_summary` / :func:`heliojax.write_results_h5`.
        variant: ``"residual"`` or ``"paper"``.
        config: the :class:`NeuralConfig`.
        fit_mask, val_mask: ``(H, M)`` the network's fine-tuning / validation records.
        nn_errors_mrad: ``(H, M)`` beam error of the network without fallback.
        fallback: ``(H,)`` heliostats that use the LM model.
        fallback_reason: per heliostat ``None`` or why it fell back.
        models: residual: batched :class:`NeuralCorrection`; paper: batched
            :class:`PaperPredictor`.
        timing: seconds of ``pretrain_s`` (includes compilation), ``finetune_s``.
    """

    lm: CalibrationRun
    run: CalibrationRun
    variant: str
    config: NeuralConfig
    fit_mask: np.ndarray
    val_mask: np.ndarray
    nn_errors_mrad: np.ndarray
    fallback: np.ndarray
    fallback_reason: list
    models: object
    timing: dict


DEFAULT_NEURAL_CONFIG = NeuralConfig()
"""The default :class:`NeuralConfig` (frozen, shared)."""


def validation_tail(train_mask: np.ndarray, val_fraction: float, min_val: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Split each row's training records (record axis chronological) into *fit* and
    the latest ``max(min_val, round(val_fraction * n))`` for *validation*; no
    validation where fewer than 2 records would fit the network."""
    if isinstance(val_fraction, bool) or not (isinstance(val_fraction, numbers.Real) and 0.0 <= val_fraction < 1.0):
        raise ValueError(f"validation_tail: val_fraction must be a number in [0, 1), got {val_fraction!r}")
    if isinstance(min_val, bool) or not (isinstance(min_val, numbers.Integral) and min_val >= 0):
        raise ValueError(f"validation_tail: min_val must be a whole number >= 0, got {min_val!r}")
    train_mask = np.asarray(train_mask, bool)
    n = train_mask.sum(axis=-1, keepdims=True)  # (H, 1) training records per row
    n_val = np.maximum(int(min_val), np.round(val_fraction * n).astype(np.int64))  # half to even, as round()
    split = (val_fraction > 0) & (n > 0) & (n - n_val >= 2)
    rank = np.cumsum(train_mask, axis=-1)  # 1-based position of each training record in its row
    val = train_mask & split & (rank > n - n_val)
    return train_mask & ~val, val


def _median(x):
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else float("nan")


@eqx.filter_jit
def paper_errors_mrad(lm_models, predictors, geometry, counts, context, focal, mask):
    """Beam error (mrad) and its components ``(H, M)``, ``(H, M, 2)`` of the paper
    variant's predicted counts (see :mod:`heliojax.neural._model`); also the
    predicted counts ``(H, M, 2)``. NaN where ``mask`` is False."""

    def per(model, pred, g, c, x, f, m):
        c2, x2, f2, use, _ = sanitise(g, c, x, f, m)
        chat = jax.vmap(pred)(x2.sun, f2)
        e = jax.vmap(lambda ci, hi, si, fi: paper_beam_error(model, g, ci, hi, si, fi))(c2, chat, x2.sun, f2)
        r = jax.vmap(lambda ci, hi, si, fi: paper_beam_components(model, g, ci, hi, si, fi))(c2, chat, x2.sun, f2)
        return (
            jnp.where(use, e * 1e3, jnp.nan),
            jnp.where(use[:, None], r * 1e3, jnp.nan),
            jnp.where(use[:, None], chat, jnp.nan),
        )

    return jax.vmap(per)(lm_models, predictors, geometry, counts, context, focal, mask)


def train_neural(
    lm: CalibrationRun,
    variant: str = "residual",
    nn: NeuralConfig = DEFAULT_NEURAL_CONFIG,
    seed: int = 0,
    fit_mask=None,
    val_mask=None,
):
    """Train the networks of every heliostat of a fitted LM run at once.

    Returns ``(models, fit_mask, val_mask, timing)``; ``models`` is a batched
    :class:`NeuralCorrection` (residual) or :class:`PaperPredictor` (paper).
    """
    if variant not in VARIANTS:
        raise ConfigError(f"unknown neural variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    fleet = lm.fleet
    if fit_mask is None or val_mask is None:
        # the records the LM fit used: those before a change point describe a past state
        fit_mask, val_mask = validation_tail(lm.fitted_mask, nn.val_fraction, nn.min_val)
    fit_mask = np.asarray(fit_mask) & np.asarray(fleet.mask)
    val_mask = np.asarray(val_mask) & np.asarray(fleet.mask)
    h = fit_mask.shape[0]
    base = lm.result.model
    key = jax.random.key(seed)
    k_init, k_pre, k_ft = jax.random.split(key, 3)
    dt = fleet.counts.dtype
    w_fit = jnp.asarray(fit_mask, dt)
    w_val = jnp.asarray(val_mask, dt)
    timing = {}
    if variant == "residual":
        rms = np.nan_to_num(np.asarray(lm.result.rms_mrad), nan=1.0)
        scale = jnp.asarray(np.clip(rms, 0.1, 100.0) * 1e-3, dt)
        nets = init_residual_networks(k_init, h, nn)
        log.info(f"fine-tuning {len(lm.summary['heliostats'])} residual networks ({nn.residual_epochs} steps)")
        t0 = time.perf_counter()
        nets, info = _finetune_residual_program(
            heliostat_keys(k_ft, h),
            nets,
            base,
            fleet.geometry,
            fleet.counts,
            fleet.context,
            fleet.focal_spot,
            scale,
            w_fit,
            w_val,
            nn,
        )
        jax.block_until_ready(nets)
        timing["pretrain_s"] = 0.0
        timing["finetune_s"] = time.perf_counter() - t0
        models = NeuralCorrection(base, nets, scale)
        return models, fit_mask, val_mask, timing
    tgt = fleet.targets
    ti = jnp.asarray(fleet.target_index)
    u_axis = tgt.u_axis[ti]
    v_axis = tgt.v_axis[ti]
    log.info(f"pretraining {len(lm.summary['heliostats'])} x 2 networks on {nn.n_synthetic} synthetic points each")
    t0 = time.perf_counter()
    k_syn, k_pre = jax.random.split(k_pre)
    syn = synthetic_fleet_data(
        heliostat_keys(k_syn, h),
        base,
        fleet.geometry,
        fleet.context.sun,
        fleet.focal_spot,
        u_axis,
        v_axis,
        w_fit,
        nn,
    )
    preds, _info = _pretrain_paper_program(heliostat_keys(k_pre, h), syn, nn)
    jax.block_until_ready(preds)
    t1 = time.perf_counter()
    log.info(f"pretrained in {t1 - t0:.1f} s; fine-tuning ({nn.finetune_epochs} steps, lr {nn.finetune_lr:g})")
    preds, _info = _finetune_paper_program(
        heliostat_keys(k_ft, h),
        preds,
        fleet.counts,
        fleet.context.sun,
        fleet.focal_spot,
        w_fit,
        w_val,
        nn,
    )
    jax.block_until_ready(preds)
    timing["pretrain_s"] = t1 - t0
    timing["finetune_s"] = time.perf_counter() - t1
    return preds, fit_mask, val_mask, timing


UNCHANGED_REASON = (
    "no fine-tuning step lowered the validation loss below the LM model's, so the network kept its "
    "zero initial output: no correction (its errors are the LM model's)"
)
"""``nn_fallback_reason`` of a heliostat whose residual network is still zero."""


def fallback_rule(nn_val_median, lm_val_median, tolerance: float, unchanged=None):
    """``(fallback, reason)`` per heliostat: fall back to LM unless the network's
    validation median (mrad) is finite and ``<= (1 + tolerance) *`` the LM model's,
    and the network corrects anything (``unchanged``: optional ``(H,)`` bool, the
    network's correction is zero everywhere, :func:`zero_correction`)."""
    if isinstance(tolerance, bool) or not (isinstance(tolerance, numbers.Real) and 0.0 <= tolerance < math.inf):
        # NaN had let every network through (no comparison with NaN is true)
        raise ValueError(f"fallback_rule: tolerance must be a finite number >= 0, got {tolerance!r}")
    unchanged = np.zeros(len(lm_val_median), bool) if unchanged is None else np.asarray(unchanged, bool)
    lengths = {"nn_val_median": len(nn_val_median), "lm_val_median": len(lm_val_median), "unchanged": len(unchanged)}
    if len(set(lengths.values())) != 1:  # zip had dropped the heliostats past the shortest
        raise ValueError(f"fallback_rule: one value per heliostat needed, got {lengths}")
    fb, why = [], []
    for a, b, same in zip(nn_val_median, lm_val_median, unchanged):
        if not np.isfinite(b):
            fb.append(True)
            why.append("no validation records")
        elif same:
            fb.append(True)
            why.append(UNCHANGED_REASON)
        elif not np.isfinite(a):
            fb.append(True)
            why.append("network prediction not finite")
        elif a > (1.0 + tolerance) * b:
            fb.append(True)
            why.append(f"validation median {a:.3f} mrad > (1 + {tolerance:g}) x LM {b:.3f} mrad")
        else:
            fb.append(False)
            why.append(None)
    return np.array(fb, bool), why


def zero_correction(models) -> np.ndarray:
    """``(H,)`` bool: the batched residual model's network (:class:`NeuralCorrection`)
    has an output layer of exact zeros, its initialisation, so its correction (rad) is
    0 at every motor count and the model is the physics model bit for bit. The
    best-on-validation checkpoint keeps it when no fine-tuning step lowered the
    validation loss."""
    w, b = models.network.weights[-1], models.network.biases[-1]  # (H, out, in), (H, out)
    return np.asarray(jnp.all(w == 0, axis=(-2, -1)) & jnp.all(b == 0, axis=-1))


def calibrate_neural(
    fleet,
    *,
    model: str = "stone8",
    variant: str = "residual",
    split: str = "time",
    n_train: int | None = None,
    train_fraction: float | None = 0.7,
    seed: int = 42,
    fit_options: dict | None = None,
    nn: NeuralConfig = DEFAULT_NEURAL_CONFIG,
    start: str = "auto",
    lm_run: CalibrationRun | None = None,
) -> NeuralRun:
    """LM calibration (:func:`heliojax.calibrate`) plus a neural correction per
    heliostat, evaluated on the split's test records.

    Args:
        fleet: a :class:`heliojax.Fleet`.
        model: physics model, ``"stone8"`` or ``"actuator"``.
        variant: ``"residual"`` (default) or ``"paper"``.
        split, n_train, train_fraction, seed: as :func:`heliojax.calibrate` (no LM
            validation records: the network carves its own, see the module
            docstring); ``seed`` also seeds the networks.
        fit_options: keyword arguments of :func:`heliojax.fit` for the LM fit.
        nn: :class:`NeuralConfig`.
        start: LM start geometry.
        lm_run: reuse this LM run (same fleet and split) instead of fitting again.
    """
    if variant not in VARIANTS:
        raise ConfigError(f"unknown neural variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    if not isinstance(nn, NeuralConfig):  # a dict had failed with an AttributeError deep inside
        raise ConfigError(f"nn must be a heliojax.neural.NeuralConfig, not a {type(nn).__name__}")
    if lm_run is not None and fleet is not None:
        run_ids = tuple(lm_run.summary["heliostats"])
        if tuple(fleet.ids) != run_ids:  # lm_run's fleet had been used, this one ignored without a word
            raise ConfigError(
                f"lm_run was fitted on other heliostats ({few_names(list(run_ids))}) than fleet's "
                f"({few_names(list(fleet.ids))}): pass the fleet it was fitted on, or fleet=None"
            )
    if lm_run is None:
        lm_run = calibrate(
            fleet,
            model=model,
            split=split,
            n_train=n_train,
            n_val=0,
            train_fraction=train_fraction,
            seed=seed,
            fit_options=fit_options,
            start=start,
        )
    lm = lm_run
    if lm.test_errors_mrad is not None:
        raise ConfigError("a neural correction cannot be evaluated on --test-data yet; use a split")
    pf = lm.fleet
    models, fit_mask, val_mask, timing = train_neural(lm, variant, nn, seed=seed)
    valid = jnp.asarray(pf.mask)
    base = lm.result.model
    if variant == "residual":
        nn_err = np.asarray(beam_errors_mrad(models, pf.geometry, pf.counts, pf.context, pf.focal_spot, valid))
        nn_res = np.asarray(residuals_mrad(models, pf.geometry, pf.counts, pf.context, pf.focal_spot, valid))
    else:
        e, r, _ = paper_errors_mrad(base, models, pf.geometry, pf.counts, pf.context, pf.focal_spot, valid)
        nn_err, nn_res = np.asarray(e), np.asarray(r)
    n_real = len(lm.summary["heliostats"])
    lm_val = np.array([_median(np.where(val_mask[i], lm.errors_mrad[i], np.nan)) for i in range(n_real)])
    nn_val = np.array([_median(np.where(val_mask[i], nn_err[i], np.nan)) for i in range(n_real)])
    unchanged = zero_correction(models)[:n_real] if variant == "residual" else None
    fallback, reason = fallback_rule(nn_val, lm_val, nn.fallback_tolerance, unchanged)
    fb_full = np.zeros(pf.mask.shape[0], bool)
    fb_full[:n_real] = fallback
    fb_full[n_real:] = True
    errors = np.where(fb_full[:, None], lm.errors_mrad, nn_err)
    residuals = np.where(fb_full[:, None, None], lm.residuals_mrad, nn_res)
    kind = f"{lm.model0.label()}+nn"
    run = dataclasses.replace(lm, errors_mrad=errors, residuals_mrad=residuals)
    summary = _neural_summary(
        lm, errors, nn_err, fit_mask, val_mask, fallback, reason, lm_val, nn_val, variant, nn, timing, kind
    )
    run = dataclasses.replace(run, summary=summary)
    n_fb = int(fallback.sum())
    log.info(f"{variant} network: {n_real - n_fb}/{n_real} heliostats use it, {n_fb} fall back to LM")
    return NeuralRun(
        lm=lm,
        run=run,
        variant=variant,
        config=nn,
        fit_mask=fit_mask,
        val_mask=val_mask,
        nn_errors_mrad=nn_err,
        fallback=fallback,
        fallback_reason=reason,
        models=models,
        timing=timing,
    )


def _neural_summary(
    lm, errors, nn_err, fit_mask, val_mask, fallback, reason, lm_val, nn_val, variant, nn, timing, kind
):
    s = copy.deepcopy(lm.summary)
    s["model"] = kind
    s["nn_variant"] = variant
    s["nn_config"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(nn).items()}
    test = lm.test_mask
    status = np.asarray(lm.result.status)
    pooled, pooled_lm, pooled_nn = [], [], []
    for i, hid in enumerate(s["heliostats"]):
        e = s["heliostats"][hid]
        lm_med, lm_rms = e["test_median_mrad"], e["test_rms_mrad"]
        t = np.where(test[i], errors[i], np.nan)
        med, rms = _stats(t)
        _, tr_rms = _stats(np.where(lm.fitted_mask[i], errors[i], np.nan))  # as the LM summary's
        nn_med, nn_rms = _stats(np.where(test[i], nn_err[i], np.nan))
        e.update(
            {
                "train_rms_mrad": _json_float(tr_rms),
                "test_median_mrad": _json_float(med),
                "test_rms_mrad": _json_float(rms),
                "lm_test_median_mrad": lm_med,
                "lm_test_rms_mrad": lm_rms,
                "nn_test_median_mrad": _json_float(nn_med),
                "nn_test_rms_mrad": _json_float(nn_rms),
                "nn_fallback": bool(fallback[i]),
                "nn_fallback_reason": reason[i],
                "nn_n_fit": int(fit_mask[i].sum()),
                "nn_n_val": int(val_mask[i].sum()),
                "nn_val_median_mrad": _json_float(nn_val[i]),
                "lm_val_median_mrad": _json_float(lm_val[i]),
            }
        )
        if status[i] == FitStatus.CONVERGED:
            pooled.append(t[np.isfinite(t)])
            pooled_lm.append(np.where(test[i], lm.errors_mrad[i], np.nan))
            pooled_nn.append(np.where(test[i], nn_err[i], np.nan))
    cat = lambda xs: np.concatenate(xs) if xs else np.array([])  # noqa: E731
    med, rms = _stats(cat(pooled))
    lmed, lrms = _stats(cat(pooled_lm))
    nmed, nrms = _stats(cat(pooled_nn))
    f = s["fleet"]
    f.update(
        {
            "test_median_mrad": _json_float(med),
            "test_rms_mrad": _json_float(rms),
            "lm_test_median_mrad": _json_float(lmed),
            "lm_test_rms_mrad": _json_float(lrms),
            "nn_test_median_mrad": _json_float(nmed),
            "nn_test_rms_mrad": _json_float(nrms),
            "n_nn_used": int((~fallback).sum()),
            "n_nn_fallback": int(fallback.sum()),
        }
    )
    s["timing"].update({"nn_pretrain_s": float(timing["pretrain_s"]), "nn_finetune_s": float(timing["finetune_s"])})
    return s


# --------------------------------------------------------------------------------------
# Held-out error against training-set size (the paper's Fig. 8)
# --------------------------------------------------------------------------------------


def learning_curve(
    fleet,
    sizes: Sequence[int],
    *,
    model: str = "stone8",
    variants: Sequence[str] = ("residual", "paper"),
    test_fraction: float = 0.3,
    min_train: int | None = None,
    seed: int = 42,
    fit_options: dict | None = None,
    nn: NeuralConfig = DEFAULT_NEURAL_CONFIG,
) -> list[dict]:
    """Held-out median beam error of LM and LM+NN against the number of training
    records (time split).

    Per heliostat the latest ``test_fraction`` of its valid records are the fixed
    test set; for each size ``N`` the ``N`` records right before the test period
    train (LM on all ``N``; the network fine-tunes on the earlier part and
    validates on the latest ``val_fraction`` of them). Only heliostats with at least
    ``min_train`` (default ``max(sizes)``) records before the test period take part,
    so every size uses the same heliostats and test records.

    Returns one dict per (size, method) with ``n_train``, ``method`` (``"lm"``,
    ``"residual"``, ``"paper"``: network with the fallback rule; ``"residual_raw"``,
    ``"paper_raw"``: without), ``fleet_median_mrad`` (pooled test records),
    ``per_heliostat`` {id: median}, ``n_fallback``.
    """
    given = list(sizes)
    if not given or not all(isinstance(n, numbers.Integral) and not isinstance(n, bool) and n >= 1 for n in given):
        # a size of 0 had trained on every record before the test period (before[-0:])
        raise ConfigError(f"learning_curve: sizes must be whole numbers >= 1, got {given!r}")
    if isinstance(test_fraction, bool) or not (isinstance(test_fraction, numbers.Real) and 0.0 < test_fraction < 1.0):
        raise ConfigError(f"learning_curve: test_fraction must be a number in (0, 1), got {test_fraction!r}")
    sizes = sorted(int(n) for n in given)
    min_train = max(sizes) if min_train is None else int(min_train)
    mask = np.asarray(fleet.mask)
    n_valid = mask.sum(1)
    n_test = np.ceil(test_fraction * n_valid).astype(int)
    keep = [i for i in range(len(fleet.ids)) if n_valid[i] - n_test[i] >= min_train]
    if not keep:
        raise ConfigError(f"no heliostat has {min_train} records before its test period")
    sub = fleet_subset(fleet, keep)
    mask = np.asarray(sub.mask)
    rows = []
    count = mask.sum(axis=1, keepdims=True)  # (H, 1) valid records per heliostat
    first_test = count - np.ceil(test_fraction * count).astype(np.int64)  # records before the test period
    rank = np.cumsum(mask, axis=1) - 1  # 0-based position of each valid record in its row
    for n in sizes:  # a handful of sizes, one calibration each
        # the test period and the n records right before it, every heliostat at once
        m = mask & (rank >= first_test - n)
        masked = eqx.tree_at(lambda f: f.mask, sub, jnp.asarray(m))
        lm = calibrate(
            masked,
            model=model,
            split="time",
            n_train=n,
            n_val=0,
            train_fraction=None,
            seed=seed,
            fit_options=fit_options,
        )
        ids = [h for h in lm.summary["heliostats"]]

        def row(method, errors, fb=None):
            t = np.where(lm.test_mask[: len(ids)], errors[: len(ids)], np.nan)
            per = {h: _json_float(_median(t[i])) for i, h in enumerate(ids)}
            return {
                "n_train": n,
                "method": method,
                "fleet_median_mrad": _json_float(_median(t)),
                "per_heliostat": per,
                "n_fallback": None if fb is None else int(np.sum(fb)),
            }

        rows.append(row("lm", lm.errors_mrad))
        for v in variants:
            nr = calibrate_neural(masked, model=model, variant=v, seed=seed, nn=nn, lm_run=lm)
            rows.append(row(v, nr.run.errors_mrad, nr.fallback))
            rows.append(row(v + "_raw", nr.nn_errors_mrad))
        log.info(
            "N=%d: %s", n, ", ".join(f"{r['method']} {r['fleet_median_mrad']:.2f}" for r in rows if r["n_train"] == n)
        )
    return rows


__all__ = [
    "NeuralRun",
    "calibrate_neural",
    "fallback_rule",
    "learning_curve",
    "paper_errors_mrad",
    "train_neural",
    "validation_tail",
    "zero_correction",
]
