"""Reports of the discovery workflow: report.json, a Markdown summary, PNG figures.

``report.json`` schema (all RMS values are pooled over records, mrad, of the
beam pointing error; ``cv`` = blocked cross-validation by day)::

    {
      "base_model": "auto" | "actuator" | "stone8",
      "steps": [                                   # one per named effect, in order
        {"effect": name, "mode": "shared" | "per_heliostat",
         "delta_bic": float,                       # criterion(before) - criterion(after) > 0: 2 log of
                                                   # the Bayes factor (Laplace, under the effect prior;
                                                   # the BIC without it; see config.criterion)
         "cv_heldout_rms_before_mrad": float, "cv_heldout_rms_after_mrad": float,
         "cv_log_ratio": float,                    # held-out criterion (< 0), see cv_log_ratio
         "cv_p": float,                            # one-sided p of the held-out improvement,
                                                   # a t test over heliostat-days (cv_improvement_p)
         "amplitude": {param: value},              # physical units (see "units")
         "amplitude_std": {param: value},
         "units": {param: unit},
         "heliostats": [ids],                      # heliostats the effect was fitted to
         "heliostats_significant": [ids],          # individually significant (Holm, alpha)
         "p_value": float, "p_holm": float,
         "absorbed_fraction": float | null,        # of its best direction by the model before it
         "typical": {param: value},                # documented typical size (physical units)
         "implausible": [params],                  # beyond IMPLAUSIBLE_TYPICAL x typical
         "per_target": {target: {"e", "n", "u", "norm", "std": {..}, "relative": {..}}},
                                                   # survey_target only: offsets (m) by target name;
                                                   # relative = less the targets' mean (see _per_target)
         "ambiguous_with": [{"effect", "mode", "delta_bic", "cv_heldout_rms_after_mrad",
                             "source"}]}           # source "library" (effect), or "generic
      ],                                           # competitor" (effect null; "variable", "p"):
                                                   # rivals within ambiguity_bic of delta BIC; or
                                                   # "change-point scan" (effect "change_point",
                                                   # "heliostats", "p"): a per-heliostat effect
                                                   # significant only where a change of state is
                                                   # a step or a drift alike (Cleaning.undecided)
      "named_effects": [names],                    # "change_point" first when any was found
      "ambiguities": [{"step", "named", "named_mode", "alternatives": [...]}],
      "weak_evidence": [{"step", "named", "named_mode", "delta_bic"}],  # names on delta BIC < 6
                                                   # (Kass & Raftery's "positive", below "strong"):
                                                   # the name is not certain
      "held_out_not_significant": [{"step", "named", "named_mode", "cv_log_ratio", "cv_p"}],
                                                   # names whose held-out gain is not significant
                                                   # over days (cv_p >= alpha): a day's shared
                                                   # error can make such a gain; not certain
      "outliers": [{"heliostat", "record_id"}],    # gross errors of the robust pre-pass (left out)
      "noisy_heliostats": [{"heliostat", "noise_mrad", "left_out"}],  # noise far above the fleet's
                                                   # (robust pre-pass; heliojax.fitting.noise_outliers):
                                                   # garbage records, a wrong properties file, or
                                                   # a noisier heliostat? left_out true (default):
                                                   # not used after the pre-pass (their outliers and
                                                   # change points are the pre-pass's); false
                                                   # (keep_noisy): they weigh in every statistic
      "spots_unexplained": [{"heliostat", "noise_mrad", "spot_scatter_mrad"}],  # pre-pass noise above
                                                   # NOISE_OUTLIER_MIN_RATIO x the RMS angle between
                                                   # its spots and its targets' centres: the base
                                                   # model predicts them worse than a beam on the
                                                   # centre would (kept; a warning names them)
      "pre_pass_unfitted": [heliostat],            # heliostats the robust pre-pass could not fit
                                                   # (too few records): gross errors not flagged
      "change_points": [{"heliostat", "time": UTC ISO 8601 (first record since the change),
                         "previous_record_time", "jump": {param: rad}, "jump_unit": "rad",
                         "p", "p_holm", "n_records_before"}],   # records before it: fitted with the jump
      "change_points_withdrawn": [{"heliostat", "time", "p"}],  # pre-pass steps the final model explains
      "unexplained": [{"variable", "form", "p", "p_holm", "effect_size_mrad", "heliostats",
                       "source"}],                 # form "fleet" (shared shape) or "per_heliostat";
                                                   # source "residual scan" (final residuals) or
                                                   # "generic competitor" (beat a library name, which
                                                   # "instead_of" gives, by "delta_bic"; first;
                                                   # "instead_of"."ambiguous": within ambiguity_bic)
      "generic_competitors": [{"step", "library_best": {"effect", "mode", "delta_bic"},
                               "competitors": [{"variable", "form", "delta_bic", "p"}]}],
                                                   # p null: not tested (absorbed by the model
                                                   # to 1 - 1e-12)
      "variable_p_values": {variable: p},          # every recorded variable at the final model
                                                   # (per-heliostat form: "<variable> (per heliostat)")
      "partly_absorbed": [{"effect", "absorbed_fraction", "remainder_p_holm"}],  # last screen;
                                                   # remainder_p_holm null: absorbed to 1 - 1e-12,
                                                   # no remainder to test
      "not_identifiable": [names],                 # largely absorbed at some step (tested on the remainder), not named
      "untestable": [names],                       # the data do not drive them (e.g. no weather)
      "screens_run": bool,                         # false: nothing was tested (see not_tested_reason)
      "not_tested_reason": str | null,             # why, e.g. too few records for the parameters
      "warnings": [str],                           # e.g. records on one day: nothing can be named
      "absorbed_fraction": {name: float | null},   # at the first screen
      "heldout_rms_base_mrad": float, "heldout_rms_final_mrad": float,
      "heldout_median_base_mrad": float, "heldout_median_final_mrad": float,
      "train_rms_base_mrad": float, "train_rms_final_mrad": float,
      "noise_estimate_mrad": float,                # per tangent component, final model
      "day_clustering": {"intra_day_correlation", "p", "design_effect_median",
                         "records_per_day_median"},  # records of one heliostat and day
                                                   # sharing an error (final model); correlation
                                                   # 0 unless its F test has p < 0.01; each
                                                   # refit's evidence counts effective records
      "screens": [{name: {"p", "p_shared", "p_per_heliostat", "p_holm", "absorbed_fraction",
                          "identifiable", "tested", "testable"}}],  # one per step
      "refits": [[{"effect", "mode", "delta_bic", "cv_heldout_rms_before_mrad",
                   "cv_heldout_rms_after_mrad", "cv_log_ratio", "cv_p", "prior_scale",
                   "cross_validated", "passed"}]],
                                                   # cross_validated false (cv_* null)
                                                   # where delta BIC failed, or passed
                                                   # more than ambiguity_bic below the
                                                   # named refit's (deferred: neither
                                                   # named nor a rival either way);
                                                   # prior_scale: factor on the typical
                                                   # sizes of the refit's prior
      "config": {...}, "data": {...}, "timing": {...}
    }                                              # data: also "folds_left_out" and
                                                   # "heliostats_not_cross_validated" (folds with
                                                   # fewer training records than the base's
                                                   # free parameters, not fitted)

Effect names come from :data:`heliojax.effects.EFFECT_NAMES` (and ``"change_point"``).
The variables of ``"unexplained"`` are those of
:func:`heliojax.discovery.record_variables`.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
from scipy import stats

from .._errors import few_names
from .._io import atomic_write
from .._plotting import pyplot, save_figure
from .._splits import utc_iso
from ..fitting import NOISE_OUTLIER_MIN_RATIO, noise_outliers
from ._diagnostics import record_variables
from ._lanes import fleet_longitude_deg, fold_blocks, too_few_days_note

# Kass & Raftery's (1995) scale of 2 log Bayes factor (a delta BIC): 0-2 "not worth
# more than a bare mention", 2-6 "positive", 6-10 "strong", above 10 "very strong".
# Published, not tuned.

MIN_DELTA_BIC = 2.0
"""Delta BIC a refit must exceed to name its effect (Kass & Raftery 1995: a BIC
difference of 0-2 is "not worth more than a bare mention", 2-6 "positive"
evidence). A published scale, not tuned: an effect named on less than positive
evidence is as likely the remainder of another (an undetected step, an effect
outside the library) as itself."""

STRONG_EVIDENCE_BIC = 6.0
"""Delta BIC from which a name rests on "strong" evidence (Kass & Raftery 1995). A name
below it is reported as resting on weak evidence (``"weak_evidence"``) (in this
project's independent-simulator runs up to 2026-12-06, 2 of the 3 names below 6 were
wrong)."""

AMBIGUITY_BIC = 10.0
"""Delta BIC below which two explanations are not told apart (Kass & Raftery 1995:
a BIC difference above 10 is "very strong" evidence)."""


def evidence_grade(delta_bic: float) -> str:
    """Kass & Raftery's (1995) words for a delta BIC (2 log Bayes factor):
    ``"not worth more than a bare mention"`` (<= 2), ``"positive"`` (2-6),
    ``"strong"`` (6-10) or ``"very strong"`` (> 10)."""
    if not delta_bic > MIN_DELTA_BIC:
        return "not worth more than a bare mention"
    if delta_bic < STRONG_EVIDENCE_BIC:
        return "positive"
    return "strong" if delta_bic <= AMBIGUITY_BIC else "very strong"


def fmt(x: float | None, spec: str = ".3f") -> str:
    """A report number in the Markdown summary: ``-`` for a missing one (null)."""
    return "-" if x is None else format(x, spec)


def _alternative_words(x: dict) -> str:
    """One rival of an ambiguous name (``ambiguous_with`` entry) in the Markdown report."""
    if x.get("source") == "change-point scan":
        return (
            f"a change of state of {', '.join(x.get('heliostats', []))} (change-point scan, p_holm "
            f"{fmt(x.get('p'), '.2g')}; a step and a drift of its offsets fit alike)"
        )
    if x.get("source") == "generic competitor":
        what = f"a smooth function of `{x['variable']}` (generic competitor, not a library effect; "
    else:
        what = f"`{x['effect']}` ({_mode_words(x.get('mode'))}, "
    return what + f"delta BIC {fmt(x['delta_bic'], '.1f')})"


def _f(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _train_rms(state, h):
    lanes = np.nonzero(state.ok[:h])[0]
    if lanes.size == 0:
        return None
    return _f(np.sqrt(np.sum(state.rss[lanes]) / (np.sum(state.n_res[lanes]) / 2)))


def _noise(state, layout, h):
    lanes = np.nonzero(state.ok[:h])[0]
    if lanes.size == 0:
        return None
    k = len(layout.base_cols) + sum(len(layout.cols(e)) for e, m in state.effects if m == "per_heliostat")
    dof = np.sum(state.n_res[lanes]) - k * lanes.size
    return _f(np.sqrt(np.sum(state.rss[lanes]) / max(dof, 1)))


def cv_pair(before, after) -> tuple[float, float, int]:
    """Pooled held-out RMS (mrad) of two model states over the records held out and
    predicted by both."""
    both = np.isfinite(before.heldout_sq) & np.isfinite(after.heldout_sq)
    n = int(both.sum())
    if n == 0:
        return float("nan"), float("nan"), 0
    return (float(np.sqrt(np.mean(before.heldout_sq[both]))), float(np.sqrt(np.mean(after.heldout_sq[both]))), n)


def cv_log_ratio(before, after, heliostat: np.ndarray) -> float:
    """Held-out log-likelihood ratio per record, each heliostat with its own noise
    level (the held-out counterpart of the BIC's likelihood)::

        sum_h n_h ln(MSE_h(after) / MSE_h(before)) / sum_h n_h

    over the records held out and predicted by both (``heliostat``: ``(L,)`` the
    heliostat of each lane). Negative when ``after`` predicts better. Unlike the
    pooled RMS it cannot be dominated by one heliostat whose folds are poorly
    determined (a few records, a degenerate fold): each heliostat enters by its
    ratio, not by its size."""
    both = np.isfinite(before.heldout_sq) & np.isfinite(after.heldout_sq)
    total, n_all = 0.0, 0
    for h in np.unique(heliostat):
        rows = both[heliostat == h]
        n = int(rows.sum())
        if n == 0:
            continue
        mb = float(np.mean(before.heldout_sq[heliostat == h][rows]))
        ma = float(np.mean(after.heldout_sq[heliostat == h][rows]))
        if mb <= 0 or ma <= 0:
            continue
        total += n * np.log(ma / mb)
        n_all += n
    return float(total / n_all) if n_all else float("nan")


def cv_improvement_p(before, after, heliostat: np.ndarray, day: np.ndarray) -> float:
    """One-sided p-value that ``after`` predicts the held-out records no better than
    ``before``: a t test over days of the held-out improvement.

    Per record held out and predicted by both, ``d = (e_after^2 - e_before^2) /
    MSE_h(before)`` (its heliostat's scale, as :func:`cv_log_ratio`); ``d`` summed per
    heliostat and day, and those sums tested for a negative mean (Student's t,
    ``K - 1`` degrees of freedom over ``K`` heliostat-days). Days, not records: the
    folds are blocks of whole days, so a day's held-out records were predicted by
    parameters fitted without that day, and an error the records of one day share
    (the target's or camera's state that day) leaves the days independent, where
    counting its records as independent would make the shared error evidence. Under
    no effect, the refit's parameters fitted to noise only add ``(J delta)^2 >= 0`` to
    each held-out error on average, so the test is conservative there.

    Args:
        before, after: model states with ``heldout_sq`` ``(L, M)`` (mrad^2, NaN where
            not held out).
        heliostat: ``(L,)`` each lane's heliostat.
        day: ``(L, M)`` each record's day (:func:`heliojax.fitting.day_labels`).

    Returns:
        The p-value in ``[0, 1]``; NaN with fewer than 3 heliostat-days held out.
    """
    both = np.isfinite(before.heldout_sq) & np.isfinite(after.heldout_sq)
    li, mi = np.nonzero(both)
    if li.size == 0:
        return float("nan")
    h = np.asarray(heliostat)[li]
    b, a = before.heldout_sq[li, mi], after.heldout_sq[li, mi]
    _, hi = np.unique(h, return_inverse=True)
    scale = np.bincount(hi, weights=b) / np.bincount(hi)
    ok = scale[hi] > 0
    _, cluster = np.unique(np.stack([h[ok], np.asarray(day)[li, mi][ok]]), axis=1, return_inverse=True)
    sums = np.bincount(cluster.reshape(-1), weights=((a - b) / np.where(ok, scale[hi], 1.0))[ok])
    k = sums.size
    if k < 3:
        return float("nan")
    sd = float(np.std(sums, ddof=1))
    if sd == 0.0:
        return 1.0 if sums.mean() >= 0 else 0.0
    return float(stats.t.cdf(sums.mean() / (sd / np.sqrt(k)), k - 1))


IMPLAUSIBLE_TYPICAL = 10.0
"""A named effect's parameter beyond this multiple of its documented typical size
(:func:`heliojax.parameter`'s ``typical``, fixed a priori from the physics) is
listed in the step's ``"implausible"``: the effect may stand in for something else."""


def _mode_words(mode: str | None) -> str:
    """An effect's mode as the Markdown says it (``"per_heliostat"`` -> "per heliostat")."""
    return "mode unknown" if not mode else str(mode).replace("_", " ")


def build_report(result, typical_start=None) -> dict:
    """The report.json dictionary of a :class:`DiscoveryResult` (``typical_start``:
    ``(H,)`` heliostats started from the fleet-typical actuators)."""
    cfg = result.config
    h = result.lanes.n_heliostats
    steps = []
    for s in result.steps:
        units = dict(zip(result.layout.params(s.effect), result.layout.units(s.effect)))
        typical = result.layout.typical(s.effect) * result.layout.scales[list(result.layout.cols(s.effect))]
        implausible = [
            n
            for n, t in zip(result.layout.params(s.effect), typical)
            if t > 0 and abs(s.amplitude.get(n, 0.0)) > IMPLAUSIBLE_TYPICAL * t
        ]
        steps.append(
            {
                "effect": s.effect,
                "mode": s.mode,
                "delta_bic": _f(s.delta_bic),
                "evidence": evidence_grade(s.delta_bic),
                "cv_heldout_rms_before_mrad": _f(s.cv_before),
                "cv_heldout_rms_after_mrad": _f(s.cv_after),
                "cv_log_ratio": _f(s.cv_log_ratio),
                "cv_p": _f(s.cv_p),
                "amplitude": {k: _f(v) for k, v in s.amplitude.items()},
                "amplitude_std": {k: _f(v) for k, v in s.amplitude_std.items()},
                "units": units,
                "heliostats": list(s.heliostats),
                "heliostats_significant": list(s.heliostats_significant),
                "p_value": _f(s.p_value),
                "p_holm": _f(s.p_holm),
                "absorbed_fraction": _f(s.absorbed_fraction),
                "typical": {n: _f(t) for n, t in zip(result.layout.params(s.effect), typical)},
                "implausible": implausible,
                "ambiguous_with": [
                    {
                        "effect": a["effect"],
                        "mode": a["mode"],
                        "delta_bic": _f(a["delta_bic"]),
                        "cv_heldout_rms_after_mrad": _f(a["cv_after"]),
                        "source": a.get("source", "library"),
                        **({"variable": a["variable"], "p": _f(a["p"])} if "variable" in a else {}),
                        **({"heliostats": list(a["heliostats"]), "p": _f(a["p"])} if "heliostats" in a else {}),
                    }
                    for a in s.ambiguous_with
                ],
            }
        )
        if s.effect == "survey_target":
            names = tuple(getattr(result.fleet, "target_names", ()))
            steps[-1]["per_target"] = _per_target(s.amplitude, s.amplitude_std, names)
    cleaning = _cleaning_report(result)
    named = (["change_point"] if cleaning["change_points"] else []) + [s.effect for s in result.steps]
    not_ident, untestable = [], []
    for entry in result.screens:
        for c, sc in entry["screens"].items():
            if c in named:
                continue
            if not sc.testable:
                if c not in untestable:
                    untestable.append(c)
            elif not sc.identifiable and c not in not_ident:
                not_ident.append(c)
    untestable = [c for c in untestable if c not in not_ident]
    not_tested = _not_tested_reason(result)
    screens = []
    for entry in result.screens:
        screens.append(
            {
                c: {
                    "p": _f(sc.p) if sc.tested else None,
                    "p_shared": _f(sc.p_shared) if sc.tested else None,
                    "p_per_heliostat": _f(sc.p_per_heliostat) if sc.tested else None,
                    "p_holm": _f(entry["p_holm"].get(c)),
                    "absorbed_fraction": _f(sc.absorbed_fraction),
                    "identifiable": bool(sc.identifiable),
                    "tested": bool(sc.tested),
                    "testable": bool(sc.testable),
                }
                for c, sc in entry["screens"].items()
            }
        )
    refits = [
        [
            {
                "effect": c.effect,
                "mode": c.mode,
                "delta_bic": _f(c.delta_bic),
                "cv_heldout_rms_before_mrad": _f(c.cv_before),
                "cv_heldout_rms_after_mrad": _f(c.cv_after),
                "cv_log_ratio": _f(c.cv_log_ratio),
                "cv_p": _f(c.cv_p),
                "prior_scale": _f(c.prior_scale),
                "cross_validated": bool(c.cross_validated),
                "passed": bool(c.passed),
            }
            for c in cands
        ]
        for cands in result.candidates
    ]
    cv_base, cv_final, n_cv = cv_pair(result.base, result.final)
    both = np.isfinite(result.base.heldout_sq) & np.isfinite(result.final.heldout_sq)
    med_base = float(np.median(np.sqrt(result.base.heldout_sq[both]))) if both.any() else None
    med_final = float(np.median(np.sqrt(result.final.heldout_sq[both]))) if both.any() else None
    first = result.screens[0]["screens"] if result.screens else {}
    fleet = result.fleet
    mask = np.asarray(fleet.mask)
    blocks = fold_blocks(np.asarray(fleet.context.unix_time), mask, fleet_longitude_deg(fleet))
    note = too_few_days_note(blocks) if mask.any() else None
    warnings = [note] if note is not None else []
    if cleaning["noisy_heliostats"]:
        noisy = ", ".join(f"{n['heliostat']} ({n['noise_mrad']:.3g} mrad)" for n in cleaning["noisy_heliostats"])
        said = (
            "left out after the robust pre-pass (their gross errors and change points are reported), as calibrate "
            "leaves them out of its fleet statistics; keep them with `heliojax discover --keep-noisy`"
            if cleaning["noisy_heliostats"][0]["left_out"]
            else "kept (keep_noisy), so their records weigh in the fleet-wide noise estimate and every test"
        )
        warnings.append(
            f"noise far above the rest of the fleet's (median {cleaning['robust_noise_median_mrad']:.3g} mrad): "
            f"{noisy} (garbage records, a wrong properties file, or a heliostat noisier than the rest?): {said}"
        )
    if cleaning["spots_unexplained"]:
        worse = ", ".join(
            f"{n['heliostat']} ({n['noise_mrad']:.3g} against {n['spot_scatter_mrad']:.3g} mrad)"
            for n in cleaning["spots_unexplained"]
        )
        warnings.append(
            f"the base model predicts the spots of {worse} worse than a beam on the target's centre would: their "
            f"noise after the robust pre-pass exceeds {NOISE_OUTLIER_MIN_RATIO:g} times the scatter of their spots "
            "about the target centres (garbage records, a wrong properties file?); check them, or leave them out "
            "(`heliojax discover --exclude`)"
        )
    if cleaning["pre_pass_unfitted"]:
        warnings.append(
            f"the robust pre-pass could not fit {few_names(cleaning['pre_pass_unfitted'])} (fewer records than the "
            "base model's parameters need): their gross errors are not flagged and their noise is not estimated"
        )
    left_out, not_cross_validated = _folds_left_out(result.lanes, list(fleet.ids))
    n_base = len(result.layout.base_cols)
    if note is None and mask.any() and len(not_cross_validated) == sum(1 for i in fleet.ids if i):
        warnings.append(
            f"no heliostat keeps {n_base} training records (the base model's free parameters) in a "
            "cross-validation fold: no fold is fitted, so no effect can pass its held-out test and none will be named"
        )
    typical = np.zeros(len(fleet.ids), bool) if typical_start is None else np.asarray(typical_start, bool)
    last = result.screens[-1]["screens"] if result.screens else {}
    last_holm = result.screens[-1]["p_holm"] if result.screens else {}
    absorbed = [
        {
            "effect": c,
            "absorbed_fraction": _f(sc.absorbed_fraction),
            "remainder_p_holm": _f(last_holm.get(c)),
        }
        for c, sc in last.items()
        if sc.testable and not sc.identifiable
    ]
    ambiguities = [
        {"step": i + 1, "named": s["effect"], "named_mode": s["mode"], "alternatives": s["ambiguous_with"]}
        for i, s in enumerate(steps)
        if s["ambiguous_with"]
    ]
    weak = [
        {"step": i + 1, "named": s["effect"], "named_mode": s["mode"], "delta_bic": s["delta_bic"]}
        for i, s in enumerate(steps)
        if s["delta_bic"] is not None and s["delta_bic"] < STRONG_EVIDENCE_BIC
    ]
    unconfirmed = [
        {
            "step": i + 1,
            "named": s["effect"],
            "named_mode": s["mode"],
            "cv_log_ratio": s["cv_log_ratio"],
            "cv_p": s["cv_p"],
        }
        for i, s in enumerate(steps)
        if s["cv_p"] is not None and s["cv_p"] >= cfg.alpha
    ]
    return {
        "base_model": cfg.base,
        "steps": steps,
        "named_effects": named,
        "ambiguities": ambiguities,
        "weak_evidence": weak,
        "held_out_not_significant": unconfirmed,
        "outliers": cleaning["outliers"],
        "noisy_heliostats": cleaning["noisy_heliostats"],
        "spots_unexplained": cleaning["spots_unexplained"],
        "pre_pass_unfitted": cleaning["pre_pass_unfitted"],
        "change_points": cleaning["change_points"],
        "change_points_withdrawn": cleaning["change_points_withdrawn"],
        "unexplained": [
            {
                "variable": u["variable"],
                "form": u.get("form", "fleet"),
                "p": _f(u["p"]),
                "p_holm": _f(u["p_holm"]),
                "effect_size_mrad": _f(u["effect_size_mrad"]),
                "heliostats": list(u["heliostats"]),
                "source": u.get("source", "residual scan"),
                **({"instead_of": u["instead_of"], "delta_bic": _f(u["delta_bic"])} if "instead_of" in u else {}),
            }
            for u in result.unexplained
        ],
        "generic_competitors": [
            {
                **c,
                "library_best": {**c["library_best"], "delta_bic": _f(c["library_best"]["delta_bic"])},
                "competitors": [{**x, "delta_bic": _f(x["delta_bic"]), "p": _f(x["p"])} for x in c["competitors"]],
            }
            for c in result.competitors
        ],
        "variable_p_values": {k: _f(v) for k, v in result.variable_p.items()},
        "partly_absorbed": absorbed,
        "not_identifiable": not_ident,
        "untestable": untestable,
        "screens_run": not_tested is None,
        "not_tested_reason": not_tested,
        "warnings": warnings,
        "absorbed_fraction": {c: _f(sc.absorbed_fraction) for c, sc in first.items()},
        "heldout_rms_base_mrad": _f(cv_base),
        "heldout_rms_final_mrad": _f(cv_final),
        "heldout_median_base_mrad": _f(med_base),
        "heldout_median_final_mrad": _f(med_final),
        "n_heldout_records": n_cv,
        "train_rms_base_mrad": _train_rms(result.base, h),
        "train_rms_final_mrad": _train_rms(result.final, h),
        "noise_estimate_mrad": _noise(result.final, result.layout, h),
        "day_clustering": None if result.day_clustering is None else result.day_clustering.as_dict(),
        "screens": screens,
        "refits": refits,
        "config": {
            "alpha": cfg.alpha,
            "n_folds": cfg.n_folds,
            "candidates": list(cfg.effects),
            "absorbed_limit": cfg.absorbed_limit,
            "max_refits": cfg.max_refits,
            "start": cfg.start,
            "robust": cfg.robust,
            "changes": cfg.changes,
            "min_delta_bic": cfg.min_delta_bic,
            "ambiguity_bic": cfg.ambiguity_bic,
            "effect_prior": cfg.effect_prior,
            # the refits' criterion (the field "delta_bic" holds its difference)
            "criterion": "laplace_evidence" if cfg.effect_prior else "bic",
            "generic_competitors": cfg.generic_competitors and cfg.effect_prior,
            "keep_noisy": cfg.keep_noisy,
            "exclude": list(cfg.exclude),
        },
        "data": {
            "source": getattr(getattr(fleet, "report", None), "source", None),
            "n_heliostats": int(sum(1 for i in fleet.ids if i)),
            "n_records": cleaning["n_records"],
            "n_records_used": int(mask.sum()),
            "n_outliers": len(cleaning["outliers"]),
            "n_outliers_restored": cleaning["n_restored"],  # flagged under the base model, fit the final one
            "n_records_before_change_points": cleaning["n_superseded"],
            "robust_noise_median_mrad": cleaning["robust_noise_median_mrad"],
            "start_typical_actuators": [i for i, t in zip(fleet.ids, typical) if i and t],
            "heliostat_ids": [i for i in fleet.ids if i],
            "max_records_per_heliostat": _max_records(fleet),
            "days": blocks,  # blocks of the day-blocked cross-validation (local days; a record without a time: one)
            "n_base_parameters": n_base,
            # (heliostat, fold) pairs holding records out but keeping fewer than n_base_parameters
            # training records: not fitted, not in the cross-validation (heliojax.discovery._lanes.make_lanes)
            "folds_left_out": left_out,
            "heliostats_not_cross_validated": not_cross_validated,
        },
        "timing": {k: _f(v) for k, v in result.timing.items()},
    }


def _folds_left_out(lanes, ids: list[str]) -> tuple[int, list[str]]:
    """``(n, names)``: the (heliostat, fold) pairs of the real heliostats that hold records
    out but were left out of the cross-validation for too few training records, and the
    heliostats with records whose every such fold was left out."""
    holds = lanes.fold_records().any(axis=1)
    real = np.array([bool(i) for i in ids])[lanes.heliostat]
    out = holds & real & ~lanes.cross_validated
    n_holding = np.bincount(lanes.heliostat, weights=holds, minlength=lanes.n_heliostats)
    n_out = np.bincount(lanes.heliostat, weights=out, minlength=lanes.n_heliostats)
    names = [ids[h] for h in np.flatnonzero((n_holding > 0) & (n_out == n_holding)) if ids[h]]
    return int(out.sum()), names


def _per_target(amplitude: dict, std: dict, target_names: tuple[str, ...]) -> dict:
    """``survey_target``'s fitted offsets (m) by target name, for the slots the records
    use (slot ``k`` is target ``k - 1``): ``{name: {"e", "n", "u", "norm", "std":
    {"e", "n", "u"}, "relative": {"e", "n", "u"}}}``. ``relative`` is the offset less
    the mean offset of the targets listed: a shift common to every target is nearly a
    fixed beam rotation per heliostat that its tilts absorb, so the differences are
    what the records determine best (``std`` includes the common part's spread)."""
    offsets, stds = {}, {}
    for k, name in enumerate(target_names):
        keys = [f"survey_target_{k + 1}_{c}" for c in "enu"]
        if all(key in amplitude for key in keys):
            offsets[name] = np.array([float(amplitude[key]) for key in keys])
            stds[name] = [float(std.get(key, float("nan"))) for key in keys]
    if not offsets:
        return {}
    mean = np.mean(list(offsets.values()), axis=0)
    return {
        name: {
            **{c: _f(x) for c, x in zip("enu", v)},
            "norm": _f(np.linalg.norm(v)),
            "std": {c: _f(x) for c, x in zip("enu", stds[name])},
            "relative": {c: _f(x) for c, x in zip("enu", v - mean)},
        }
        for name, v in offsets.items()
    }


def _max_records(fleet) -> int:
    """The most records a heliostat of ``fleet`` has (padding rows left out)."""
    real = np.array([bool(i) for i in fleet.ids])
    counts = np.asarray(fleet.mask).sum(axis=1)[real]
    return int(counts.max()) if counts.size else 0


def _not_tested_reason(result) -> str | None:
    """Why no screen and no residual test ran, or None when any did: with no residual
    degrees of freedom (records x 2 components <= parameters) there is nothing to test,
    which is no evidence of the absence of residual structure."""
    tested = any(sc.tested for entry in result.screens for sc in entry["screens"].values())
    if tested or any(v is not None and math.isfinite(v) for v in result.variable_p.values()):
        return None
    m, k = _max_records(result.fleet), len(result.layout.base_cols)
    if 2 * m <= k:
        return (
            f"too few records: at most {m} per heliostat ({2 * m} residual components) for {k} base-model "
            "parameters per heliostat, no residual degrees of freedom"
        )
    h = result.lanes.n_heliostats
    if not np.any(result.base.ok[:h]):
        return "the base model could not be fitted to any heliostat"
    return "no candidate effect and no recorded variable could be tested on these records"


def _confirmed_changes(cl) -> np.ndarray:
    """``(H,)`` change points found and not withdrawn under the final model."""
    return cl.change_found & ~(cl.withdrawn if cl.withdrawn is not None else False)


def _cleaning_report(result) -> dict:
    """Outliers, change points and record counts of the robust pre-pass."""
    fleet = result.fleet
    ids = list(fleet.ids)
    cl = result.cleaning
    if cl is None:
        n = int(np.asarray(fleet.mask).sum())
        return {
            "outliers": [],
            "change_points": [],
            "change_points_withdrawn": [],
            "n_records": n,
            "n_superseded": 0,
            "n_restored": 0,
            "robust_noise_median_mrad": None,
            "noisy_heliostats": [],
            "spots_unexplained": [],
            "pre_pass_unfitted": [],
        }
    rid = np.asarray(fleet.record_id)
    outliers = [{"heliostat": ids[h], "record_id": int(rid[h, m])} for h, m in zip(*np.nonzero(cl.outlier)) if ids[h]]
    changes = []
    for h in np.nonzero(_confirmed_changes(cl))[0]:
        if not ids[h]:
            continue
        changes.append(
            {
                "heliostat": ids[h],
                "time": utc_iso(float(cl.change_time_s[h])),
                "previous_record_time": utc_iso(float(cl.change_previous_s[h])),
                "jump": {n: _f(float(v) * 1e-3) for n, v in zip(cl.offsets, cl.change_jump_mrad[h])},
                "jump_unit": "rad",
                "p": _f(cl.change_p[h]),
                "p_holm": _f(cl.change_p_holm[h]),
                "n_records_before": int(cl.superseded[h].sum()),
            }
        )
    withdrawn = []
    if cl.withdrawn is not None:
        for h in np.nonzero(cl.withdrawn)[0]:
            if ids[h]:
                when = utc_iso(float(cl.change_time_s[h]))
                withdrawn.append({"heliostat": ids[h], "time": when, "p": _f(cl.change_p[h])})
    real = np.array([bool(i) for i in ids])
    left = np.zeros(len(ids), bool) if cl.left_out is None else np.asarray(cl.left_out, bool)
    # the fleet's noise: of the heliostats discovery used (a left-out one's is its own line)
    noise = cl.noise_mrad[real & ~left & np.isfinite(cl.noise_mrad)]
    noisy = noise_outliers(cl.noise_mrad, real) if cl.noisy is None else np.asarray(cl.noisy, bool)
    spots = np.zeros(len(ids), bool) if cl.unexplained_spots is None else np.asarray(cl.unexplained_spots, bool)
    scatter = np.full(len(ids), np.nan) if cl.spot_scatter_mrad is None else cl.spot_scatter_mrad
    return {
        "outliers": outliers,
        "change_points": changes,
        "change_points_withdrawn": withdrawn,
        "n_records": int(cl.valid.sum()),
        "n_superseded": int(cl.superseded.sum()),
        "n_restored": int(cl.restored.sum()) if cl.restored is not None else 0,
        "robust_noise_median_mrad": _f(np.median(noise)) if noise.size else None,
        "noisy_heliostats": [
            {"heliostat": ids[h], "noise_mrad": _f(cl.noise_mrad[h]), "left_out": bool(left[h])}
            for h in np.flatnonzero(noisy)
        ],
        "spots_unexplained": [
            {"heliostat": ids[h], "noise_mrad": _f(cl.noise_mrad[h]), "spot_scatter_mrad": _f(scatter[h])}
            for h in np.flatnonzero(spots & real)
        ],
        "pre_pass_unfitted": [
            ids[h] for h in np.flatnonzero(real & cl.valid.any(axis=1) & ~np.isfinite(cl.noise_mrad) & ~left)
        ],
    }


def write_report(path, report: dict) -> None:
    """Write report.json atomically."""
    with atomic_write(path) as f:
        json.dump(report, f, indent=2, allow_nan=False)
        f.write("\n")


def _left_out(report: dict) -> list[str]:
    return [n["heliostat"] for n in report.get("noisy_heliostats", []) if n.get("left_out")]


def _aside(report: dict) -> str:
    return "gross errors and left-out heliostats" if _left_out(report) else "gross errors"


def _left_out_note(report: dict) -> str:
    """`` (k left out after the pre-pass: ids)`` for the noise outliers discovery left out."""
    left = _left_out(report)
    return f" ({len(left)} left out after the pre-pass as noise outliers: {', '.join(left)})" if left else ""


def markdown_summary(report: dict) -> str:
    """A Markdown summary of a report."""
    d = report["data"]
    lines = [
        "# Discovery report",
        "",
        f"Data: {d['n_heliostats']} heliostats{_left_out_note(report)}, {d['n_records']} records"
        + (f" in {d['source']}" if d.get("source") else "")
        + (f", {d['n_records_used']} used ({_aside(report)} aside)" if "n_records_used" in d else "")
        + (
            f"; excluded by the caller: {', '.join(report['config']['exclude'])}"
            if report["config"].get("exclude")
            else ""
        )
        + f"; base model `{report['base_model']}`.",
        "",
        f"Held-out beam error (blocked {report['config']['n_folds']}-fold cross-validation by day, pooled RMS): "
        f"**{fmt(report['heldout_rms_base_mrad'])} mrad** with the base model, "
        f"**{fmt(report['heldout_rms_final_mrad'])} mrad** after discovery "
        f"(median {fmt(report['heldout_median_base_mrad'])} -> {fmt(report['heldout_median_final_mrad'])} mrad; "
        f"training RMS {fmt(report['train_rms_base_mrad'])} -> {fmt(report['train_rms_final_mrad'])} mrad; "
        f"noise estimate {fmt(report['noise_estimate_mrad'])} mrad per component).",
        "",
    ]
    clustering = report.get("day_clustering") or {}
    if clustering.get("intra_day_correlation", 0) > 0:
        lines += [
            f"Records of one heliostat and day share an error: intra-day correlation "
            f"{clustering['intra_day_correlation']:.2f} (p = {clustering['p']:.2g}), design effect "
            f"{clustering['design_effect_median']:.2f} (median over heliostats, "
            f"{clustering['records_per_day_median']:.1f} records per day) under the final model: the "
            "evidence of each refit and the residual scan count effective records.",
            "",
        ]
    if report["steps"]:
        # the report's field is "delta_bic" either way; its meaning follows the criterion
        laplace = report["config"].get("criterion") == "laplace_evidence"
        criterion = "2 log Bayes factor (Laplace)" if laplace else "delta BIC"
        lines += [
            f"| step | effect | form | {criterion} | held-out before | held-out after | p (Holm) | amplitude |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for i, s in enumerate(report["steps"], 1):
            amp = ", ".join(
                f"{k} = {v:.4g} {'' if s['units'].get(k, '1') == '1' else s['units'][k]}".rstrip()
                for k, v in s["amplitude"].items()
                if v is not None
            )
            if s.get("implausible"):
                amp += f" (implausible: {', '.join(s['implausible'])} > {IMPLAUSIBLE_TYPICAL:g} x typical)"
            lines.append(
                f"| {i} | `{s['effect']}` | {s['mode'].replace('_', ' ')} | {fmt(s['delta_bic'], '.1f')} | "
                f"{fmt(s['cv_heldout_rms_before_mrad'])} | {fmt(s['cv_heldout_rms_after_mrad'])} | "
                f"{fmt(s['p_holm'], '.2g')} | {amp} |"
            )
        lines.append("")
    elif report.get("not_tested_reason"):
        lines += [
            f"**Nothing tested**: {report['not_tested_reason']}; no screen could run, so this is no evidence "
            "either way. Add records.",
            "",
        ]
    else:
        lines += [
            f"No effect passed (Holm-controlled score test, 2 log Bayes factor "
            f"({report['config'].get('criterion', 'bic')}) > {report['config'].get('min_delta_bic', 2):g} "
            "and a held-out improvement).",
            "",
        ]
    for w in report.get("warnings", []):
        lines += [f"**Warning**: {w}.", ""]
    for w in report.get("weak_evidence", []):
        lines.append(
            f"**Weak evidence** at step {w['step']}: `{w['named']}` ({_mode_words(w.get('named_mode'))}) rests on "
            f'a delta BIC of {w["delta_bic"]:.1f} (2 log Bayes factor: "positive", below "strong" at '
            f"{STRONG_EVIDENCE_BIC:g}; Kass & Raftery 1995); the name is not certain."
        )
    for u in report.get("held_out_not_significant", []):
        lines += [
            f"**Held-out gain not significant** at step {u['step']}: `{u['named']}` "
            f"({_mode_words(u.get('named_mode'))}) predicted the held-out records better (log ratio "
            f"{u['cv_log_ratio']:+.4f}) but not significantly over days (p = {u['cv_p']:.2g}, alpha "
            f"{report['config'].get('alpha', 0.01):g}): a day's shared error can make such a gain; the name is "
            "not certain.",
            "",
        ]
    for a in report.get("ambiguities", []):
        alts = ", ".join(_alternative_words(x) for x in a["alternatives"])
        lines.append(
            f"**Ambiguous** at step {a['step']}: `{a['named']}` ({_mode_words(a.get('named_mode'))}) and {alts} "
            "explain the same residual; the name is not certain "
            f"(rivals: delta BIC within {report['config'].get('ambiguity_bic', 10):g})."
        )
    if report.get("change_points"):
        lines += [
            "",
            f"Change points ({len(report['change_points'])} heliostats; records before each fitted with its jump):",
            "",
            "| heliostat | first record since | last record before | jumps (mrad) | p (Holm) |",
            "|---|---|---|---|---|",
        ]
        for c in report["change_points"]:
            jumps = ", ".join(f"{k} {1e3 * v:+.2f}" for k, v in c["jump"].items() if v is not None)
            when = f"{c['time']} | {c['previous_record_time']}"
            lines.append(f"| {c['heliostat']} | {when} | {jumps} | {fmt(c['p_holm'], '.2g')} |")
    if report.get("change_points_withdrawn"):
        withdrawn = ", ".join(
            f"{c['heliostat']} ({c['time']}, p {fmt(c['p'], '.2g')})" for c in report["change_points_withdrawn"]
        )
        lines.append(
            "\nChange points the robust pre-pass found and the final model explains "
            f"(withdrawn, not named): {withdrawn}."
        )
    if report.get("outliers") is not None:
        lines.append(f"\nGross errors left out: {len(report['outliers'])} records.")
    if report.get("unexplained"):
        lines += [
            "",
            "Residual structure no named effect explains:",
            "",
            "| variable | form | p (Holm) | effect size (mrad) | heliostats (own p < alpha) |",
            "|---|---|---|---|---|",
        ]
        for u in report["unexplained"]:
            form = "per heliostat" if u.get("form") == "per_heliostat" else "fleet"
            if "instead_of" in u:  # a generic competitor that beat a library name
                form += f"; explains it as well as {u['instead_of']['effect']}, which was not named"
            lines.append(
                f"| {u['variable']} | {form} | {fmt(u['p_holm'], '.2g')} | {fmt(u['effect_size_mrad'])} | "
                f"{', '.join(u['heliostats']) or '-'} |"
            )
    elif not report.get("not_tested_reason"):
        lines.append("\nNo residual structure left against any recorded variable.")
    lines.append("")
    uncertain = {
        x["named"] for key in ("weak_evidence", "held_out_not_significant", "ambiguities") for x in report.get(key, [])
    }
    named = [f"{n} (not certain, see above)" if n in uncertain else n for n in report["named_effects"]]
    lines += [
        f"Named: {', '.join(named) or 'none'}.",
        f"Not identifiable under this data's sampling (absorbed by the model's parameters): "
        f"{', '.join(report['not_identifiable']) or 'none'}.",
        f"Untestable (no driving data): {', '.join(report['untestable']) or 'none'}."
        if not report.get("not_tested_reason")
        else "Untestable: every candidate (nothing could be tested, see above).",
        "",
        "Absorbed fraction of each candidate's best-determined direction (first screen; "
        f"limit {report['config']['absorbed_limit']:.5f}):",
        "",
        "| effect | absorbed | p (first screen) |",
        "|---|---|---|",
    ]
    first = report["screens"][0] if report["screens"] else {}
    for c, a in report["absorbed_fraction"].items():
        p = first.get(c, {}).get("p")
        lines.append(f"| `{c}` | {fmt(a, '.4f')} | {fmt(p, '.2g')} |")
    lines.append("")
    return "\n".join(lines)


def write_markdown(path, report: dict) -> None:
    """Write :func:`markdown_summary` of ``report`` (the report.json content) to
    ``path`` (a Markdown file), atomically."""
    with atomic_write(path) as f:
        f.write(markdown_summary(report))


# --------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------


def _residuals(state, h, m):
    r = state.r[:h].reshape(h, m, 2).copy()
    return r


def _drivers(fleet, effect: str) -> list[tuple[str, np.ndarray]]:
    """Driving variables of ``effect`` per record ``(H, M)`` from the data alone."""
    ctx = fleet.context
    counts = np.asarray(fleet.counts)
    sun = np.asarray(ctx.sun)
    if effect in ("actuator_geometry", "encoder_wobble"):
        return [("axis-1 motor counts", counts[..., 0]), ("axis-2 motor counts", counts[..., 1])]
    if effect == "backlash":
        a = np.asarray(ctx.approach)
        return [("axis-1 approach direction", a[..., 0]), ("axis-2 approach direction", a[..., 1])]
    if effect == "thermal":
        return [("temperature [deg C]", np.asarray(ctx.temperature))]
    if effect == "wind":
        pos = np.asarray(fleet.geometry.position)[:, None, :]
        to_spot = np.asarray(fleet.focal_spot) - pos
        to_spot /= np.linalg.norm(to_spot, axis=-1, keepdims=True)
        n = sun + to_spot
        facing = np.arctan2(n[..., 0], n[..., 1])
        v2 = np.asarray(ctx.wind_speed) ** 2
        rel = np.asarray(ctx.wind_direction) - facing
        return [
            ("v^2 cos(wind - facing) [m^2/s^2]", v2 * np.cos(rel)),
            ("v^2 sin(wind - facing) [m^2/s^2]", v2 * np.sin(rel)),
            ("v^2, any direction [m^2/s^2]", v2),
        ]
    if effect in ("clock", "offset_drift"):
        t = np.asarray(ctx.unix_time)
        return [("days since first record", (t - np.nanmin(t)) / 86400.0)]
    if effect == "gravity_sag":
        pos = np.asarray(fleet.geometry.position)[:, None, :]
        to_spot = np.asarray(fleet.focal_spot) - pos
        to_spot /= np.linalg.norm(to_spot, axis=-1, keepdims=True)
        n = sun + to_spot
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return [("cos(mirror normal elevation)", np.hypot(n[..., 0], n[..., 1]))]
    if effect == "refraction":
        return [("sun elevation [deg]", np.degrees(np.arcsin(np.clip(sun[..., 2], -1, 1))))]
    if effect == "survey_target":
        return [("target (index in the tower file)", np.asarray(fleet.target_index, float))]
    return [("sun azimuth [deg]", np.degrees(np.arctan2(sun[..., 0], -sun[..., 1])))]


BINS = 8
"""Bins of a driving variable's binned means; one with at most this many values (the
record's target, an approach sign) is categorical: a mean per value instead."""


def _categorical(x) -> bool:
    """Whether the driving variable ``x`` takes at most :data:`BINS` values."""
    return np.unique(x[np.isfinite(x)]).size <= BINS


def _binned(x, y, bins=BINS):
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 2 or _categorical(x):
        u = np.unique(x)
        return u, np.array([y[x == v].mean() for v in u])
    edges = np.quantile(x, np.linspace(0, 1, bins + 1))
    edges = np.unique(edges)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    xc = np.array([x[idx == i].mean() for i in range(len(edges) - 1) if np.any(idx == i)])
    yc = np.array([y[idx == i].mean() for i in range(len(edges) - 1) if np.any(idx == i)])
    return xc, yc


def plot_effect_residuals(result, step_index: int, *, axes=None):
    """Residual components (mrad) against the named effect's driving variable(s),
    before (grey) and after (colour) adding it; binned means as lines."""
    plt = pyplot()
    step = result.steps[step_index]
    fleet = result.fleet
    h, m = np.asarray(fleet.mask).shape
    used = result.lanes.train_mask[:h]
    drivers = _drivers(fleet, step.effect)
    rb = _residuals(step.before, h, m)
    ra = _residuals(step.after, h, m)
    if axes is None:
        fig, axes = plt.subplots(len(drivers), 2, figsize=(10, 3.2 * len(drivers)), squeeze=False)
    else:
        axes = np.atleast_2d(axes)
        fig = axes.flat[0].figure
    labels = ("horizontal component [mrad]", "vertical component [mrad]")
    for i, (name, x) in enumerate(drivers):
        for j in range(2):
            ax = axes[i, j]
            xv = np.where(used, x, np.nan)
            ok = used & np.isfinite(xv)
            jitter = 0.0
            categorical = _categorical(xv[ok])
            if categorical:
                jitter = 0.08 * np.random.default_rng(0).standard_normal(ok.sum())
                ax.set_xticks(np.unique(xv[ok]))
            ax.scatter(xv[ok] + jitter, rb[..., j][ok], s=6, color="0.6", alpha=0.5, label="before")
            ax.scatter(xv[ok] + jitter, ra[..., j][ok], s=6, color="C0", alpha=0.6, label="after")
            for r_, c_, when in ((rb, "0.3", "before"), (ra, "C3", "after")):
                xc, yc = _binned(xv[ok], r_[..., j][ok])
                mean = "mean per value" if categorical else "binned mean"
                ax.plot(xc, yc, "-o", color=c_, ms=3, lw=1.5, label=f"{mean}, {when}")
            ax.axhline(0.0, color="k", lw=0.5)
            ax.set_xlabel(name)
            ax.set_ylabel(labels[j])
            if i == 0 and j == 0:
                ax.legend(loc="best", fontsize=8)
    fig.suptitle(
        f"step {step_index + 1}: {step.effect} ({step.mode.replace('_', ' ')}) - training residuals before / after "
        "adding it (points: records, lines: means of the records in bins or per value of the driving variable)"
    )
    fig.tight_layout()
    return fig


def plot_heldout_per_step(report: dict, *, ax=None):
    """Held-out RMS (blocked CV) of the base model and after each named effect."""
    plt = pyplot()
    fig = ax.figure if ax is not None else plt.figure(figsize=(6, 3.5))
    ax = ax or fig.add_subplot(111)
    labels = [report["base_model"]]
    values = [report["steps"][0]["cv_heldout_rms_before_mrad"] if report["steps"] else report["heldout_rms_base_mrad"]]
    for s in report["steps"]:
        labels.append("+ " + s["effect"])
        values.append(s["cv_heldout_rms_after_mrad"])
    vals = [np.nan if v is None else v for v in values]
    ax.plot(range(len(vals)), vals, "-o", color="C0")
    for i, v in enumerate(vals):
        ax.annotate(f"{v:.3f}", (i, v), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    ax.set_xticks(range(len(vals)))
    ax.set_xticklabels(labels, rotation=20, ha="right")
    ax.set_ylabel("held-out RMS beam error [mrad]")
    ax.set_xlabel("model after each discovery step")
    # each step's pair is over the held-out records both of its models predict (cv_pair), so a
    # step's "before" need not equal the step before's "after", nor the report's base figure
    ax.set_title("held-out error per discovery step (each step: the records both its models predict)", fontsize=9)
    finite = [v for v in vals if np.isfinite(v)]
    ax.set_ylim(0, 1.2 * max(finite) if finite else 1.0)  # room for the value labels
    fig.tight_layout()
    return fig


def plot_screen(report: dict, step: int = 0, *, ax=None):
    """-log10 p of every candidate at a step's screen (Holm-adjusted), with the
    not-identifiable ones marked."""
    plt = pyplot()
    fig = ax.figure if ax is not None else plt.figure(figsize=(9, 3.8))
    ax = ax or fig.add_subplot(111)
    scr = report["screens"][step] if report["screens"] else {}
    names = list(scr)
    vals = [0.0 if scr[n]["p_holm"] is None else -np.log10(max(scr[n]["p_holm"], 1e-300)) for n in names]
    heights = np.minimum(vals, 50)
    untested = np.array([not scr[n].get("tested", scr[n]["identifiable"]) for n in names], bool)
    partly = np.array([not scr[n]["identifiable"] for n in names], bool) & ~untested
    index = np.arange(len(names))
    full = ~untested & ~partly
    ax.bar(index[full], heights[full], color="C0", label="identifiable: -log10 p (Holm)")
    if partly.any():
        ax.bar(index[partly], heights[partly], color="C1", label="largely absorbed: remainder's -log10 p (Holm)")
    # fully absorbed / untestable candidates have no p-value: a short hatched grey bar marks them
    if untested.any():
        ax.bar(index[untested], 1.0, color="0.7", hatch="//", label="fully absorbed / untestable (no p)")
    for i in index[~untested]:
        p_i = scr[names[i]]["p_holm"]
        text = f"p={p_i:.1g}" if p_i > 0 else "p<1e-300"
        # vertical, so that neighbouring bars' labels never overlap (eleven or more candidates)
        ax.annotate(
            text,
            (i, heights[i]),
            xytext=(0, 2),
            textcoords="offset points",
            ha="center",
            va="bottom",
            rotation=90,
            fontsize=7,
        )
    ax.axhline(-np.log10(report["config"]["alpha"]), color="C3", lw=1, label=f"alpha = {report['config']['alpha']}")
    ax.set_ylim(0, 66)
    ax.set_xticks(index)
    ax.set_xticklabels(names, rotation=30, ha="right")
    ax.set_ylabel("-log10 p (Holm), capped at 50")
    ax.set_xlabel("candidate effect")
    ax.set_title(f"screen at step {step + 1}")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    return fig


def plot_unexplained(result, index: int, *, axes=None):
    """Residual components (mrad) of the base model (grey) and the final model
    (colour) against the variable of ``result.unexplained[index]``, with binned means."""
    plt = pyplot()
    entry = result.unexplained[index]
    fleet = result.fleet
    h, m = np.asarray(fleet.mask).shape
    used = result.lanes.train_mask[:h]
    rb = _residuals(result.base, h, m)
    ra = _residuals(result.final, h, m)
    var = {v.name: v for v in record_variables(fleet, ra)}[entry["variable"]]
    if axes is None:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), squeeze=False)
    else:
        axes = np.atleast_2d(axes)
        fig = axes.flat[0].figure
    labels = ("horizontal component [mrad]", "vertical component [mrad]")
    x = np.where(used, var.values, np.nan)
    ok = used & np.isfinite(x)
    if entry.get("form") == "per_heliostat":
        return _plot_unexplained_per_heliostat(fig, axes, entry, var, x, ok, ra, list(fleet.ids), labels)
    jitter = 0.0
    if var.kind == "categorical":
        jitter = 0.08 * np.random.default_rng(0).standard_normal(int(ok.sum()))
    for j in range(2):
        ax = axes[0, j]
        ax.scatter(x[ok] + jitter, rb[..., j][ok], s=6, color="0.6", alpha=0.5, label="records, base model")
        ax.scatter(x[ok] + jitter, ra[..., j][ok], s=6, color="C0", alpha=0.6, label="records, final model")
        for r_, c_, when in ((rb, "0.3", "base model"), (ra, "C3", "final model")):
            if var.kind == "categorical":
                xc = np.unique(x[ok])
                yc = np.array([r_[..., j][ok][x[ok] == v].mean() for v in xc])
                ax.plot(xc, yc, "o", color=c_, ms=7, mfc="none", mew=2, label=f"mean per category, {when}")
            else:
                xc, yc = _binned(x[ok], r_[..., j][ok])
                ax.plot(xc, yc, "-o", color=c_, ms=3, lw=1.5, label=f"binned mean, {when}")
        if var.kind == "categorical":
            ax.set_xticks(np.unique(x[ok]))
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel(var.label)
        ax.set_ylabel(labels[j])
        if j == 0:
            ax.legend(loc="best", fontsize=8)
    same = "; no effect named: base = final" if not result.steps else ""
    fig.suptitle(
        f"unexplained structure against {entry['variable']}: p (Holm) = {entry['p_holm']:.2g}, "
        f"binned-mean RMS {entry['effect_size_mrad']:.3f} mrad\n({_why_unexplained(entry)}{same}; "
        "records of all heliostats, training residuals)"
    )
    fig.tight_layout()
    return fig


def _why_unexplained(entry: dict) -> str:
    """Why a figure's structure is unexplained: the residual scan, or a generic competitor
    that beat a library effect (:mod:`._competitors`)."""
    if "instead_of" in entry:
        return f"a smooth function of it fits as well as {entry['instead_of']['effect']}, which was not named"
    return "no library effect explains it"


def _plot_unexplained_per_heliostat(fig, axes, entry, var, x, ok, ra, ids, labels, shown: int = 4):
    """The per-heliostat form of :func:`plot_unexplained`: final-model residuals of
    the ``shown`` heliostats with the largest binned structure, each in its colour with
    its own binned means (their shapes differ, so fleet means would hide them)."""
    size = []
    for h in range(ra.shape[0]):
        if ok[h].sum() >= 4 and ids[h]:
            curves = [_binned(x[h][ok[h]], ra[h, :, j][ok[h]])[1] for j in range(2)]
            size.append((float(np.sqrt(np.mean(np.concatenate(curves) ** 2))), h))
    picked = [h for _, h in sorted(size, reverse=True)[:shown]]
    categorical = var.kind == "categorical"
    for j in range(2):
        ax = axes[0, j]
        for n, h in enumerate(picked):
            colour = f"C{n}"
            # categories: each heliostat beside the others, means as markers (no line between categories)
            shift = 0.1 * (n - (len(picked) - 1) / 2) if categorical else 0.0
            ax.scatter(x[h][ok[h]] + shift, ra[h, :, j][ok[h]], s=8, color=colour, alpha=0.45)
            xc, yc = _binned(x[h][ok[h]], ra[h, :, j][ok[h]])
            style = dict(marker="D", ms=6, ls="none") if categorical else dict(marker="o", ms=3, lw=1.5)
            mean = "mean per category" if categorical else "binned mean"
            ax.plot(xc + shift, yc, color=colour, label=f"{ids[h]}: records and {mean}", **style)
        if categorical:
            ax.set_xticks(np.unique(x[ok]))
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel(var.label)
        ax.set_ylabel(labels[j])
        if j == 0 and picked:
            ax.legend(loc="best", fontsize=8)
    fig.suptitle(
        f"unexplained structure against {entry['variable']}, its shape differing per heliostat: "
        f"p (Holm) = {entry['p_holm']:.2g}, RMS {entry['effect_size_mrad']:.3f} mrad\n"
        f"({_why_unexplained(entry)}; final-model training residuals of the {len(picked)} heliostats "
        "with the largest binned structure)"
    )
    fig.tight_layout()
    return fig


def plot_change_points(result, *, max_heliostats: int = 12):
    """Final-model residual components (mrad) against time for the heliostats with a
    change point, without its fitted jump: records before the change (hollow) sit off
    by the jump, records since it (filled) around zero. Returns None when there is
    no change point or no final-model residuals."""
    cl = result.cleaning
    if cl is None or cl.final_residuals is None:
        return None
    left = np.zeros(len(result.fleet.ids), bool) if cl.left_out is None else np.asarray(cl.left_out, bool)
    confirmed = [h for h in np.nonzero(_confirmed_changes(cl))[0] if result.fleet.ids[h]]
    # a heliostat left out after the pre-pass has no final-model residuals: named in the title
    found = [h for h in confirmed if not left[h]]
    unseen = [result.fleet.ids[h] for h in confirmed if left[h]]
    if not found:
        return None
    found = sorted(found, key=lambda h: cl.change_p_holm[h])[:max_heliostats]
    plt = pyplot()
    ncol = min(3, len(found))
    nrow = -(-len(found) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.3 * nrow + 0.8), squeeze=False)
    t = np.asarray(result.fleet.context.unix_time, float)
    for ax, h in zip(axes.flat, found):
        days = (t[h] - cl.change_time_s[h]) / 86400.0
        r = cl.final_residuals[h]
        for j, (name, colour) in enumerate((("horizontal", "C0"), ("vertical", "C3"))):
            since = cl.valid[h] & ~cl.outlier[h] & (days >= 0)
            before = cl.valid[h] & ~cl.outlier[h] & (days < 0)
            ax.plot(days[since], r[since, j], "o", color=colour, ms=3.5, label=f"{name}, since")
            label = f"{name}, before (fitted with the jump)"
            ax.plot(days[before], r[before, j], "o", mfc="none", color=colour, ms=3.5, label=label)
        ax.axvline(0.0, color="k", ls="--", lw=1)
        ax.axhline(0.0, color="k", lw=0.5)
        jump = ", ".join(f"{v:+.2f}" for v in cl.change_jump_mrad[h])
        when = (utc_iso(float(cl.change_time_s[h])) or "")[:10]
        ax.set_title(
            f"{result.fleet.ids[h]}: change {when}\n"
            f"fitted jump of offsets ({jump}) mrad, p (Holm) {cl.change_p_holm[h]:.1g}",
            fontsize=9,
        )
        ax.set_xlabel("days since the change point")
        ax.set_ylabel("residual [mrad]")
    for ax in list(axes.flat)[len(found) :]:
        ax.set_visible(False)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, bbox_to_anchor=(0.5, 0.0))
    more = len(confirmed) - len(unseen) - len(found)
    extra = f" ({more} more not shown)" if more > 0 else ""
    note = (
        f"\n(not shown: {', '.join(unseen)}, left out after the pre-pass as "
        + ("a noise outlier; its change point is" if len(unseen) == 1 else "noise outliers; their change points are")
        + " the pre-pass's)"
        if unseen
        else ""
    )
    fig.suptitle(f"change points{extra}: final-model residuals without the jump, both components, against time{note}")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return fig


FIGURE_NAME_PATTERN = re.compile(
    r"heldout_per_step\.png|change_points\.png|screen_step\d+\.png|residuals_step\d+_.+\.png|unexplained_\d+_.+\.png"
)
"""The names :func:`write_figures` may give a figure (``fullmatch``): another output
of the same run named so inside the figures' folder would be replaced by a figure."""


def write_figures(result, out_dir) -> list[Path]:
    """Write the PNG figures: ``heldout_per_step.png``, ``screen_step<k>.png``,
    ``residuals_step<k>_<effect>.png``, ``unexplained_<k>_<variable>.png`` and
    ``change_points.png`` (when any; every name matches :data:`FIGURE_NAME_PATTERN`).
    Returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    p = out / "heldout_per_step.png"
    save_figure(plot_heldout_per_step(result.report), p)
    paths.append(p)
    for k in range(len(result.report["screens"])):
        p = out / f"screen_step{k + 1}.png"
        save_figure(plot_screen(result.report, k), p)
        paths.append(p)
    for i, s in enumerate(result.steps):
        p = out / f"residuals_step{i + 1}_{s.effect}.png"
        save_figure(plot_effect_residuals(result, i), p)
        paths.append(p)
    for i, u in enumerate(result.unexplained):
        p = out / f"unexplained_{i + 1}_{u['variable']}.png"
        save_figure(plot_unexplained(result, i), p)
        paths.append(p)
    fig = plot_change_points(result)
    if fig is not None:
        p = out / "change_points.png"
        save_figure(fig, p)
        paths.append(p)
    return paths
