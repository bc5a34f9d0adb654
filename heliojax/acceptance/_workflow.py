"""The whole acceptance analysis of a measured field against a contract."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
from scipy import stats

from .._errors import ConfigError
from .._geometry import TargetPlane
from .._limits import MAX_SYNTHETIC_HELIOSTATS, count_problem, real_problem
from .._progress import activity, progress_bar
from ._clusters import ClusterResult, field_spacing, find_clusters, resampling_advice
from ._extrapolate import Extrapolation, extrapolate_field
from ._field import PARAMETERS, FieldData
from ._io import Contract, tower_clearance_problem
from ._level1 import Level1Result, level1_test
from ._sampling import sample_size
from ._yield import SunSeries, YieldResult, field_efficiency, typical_year

log = logging.getLogger(__name__)

_YIELD_DEFAULTS = {"slope_mrad": 0.0, "reflectance": 1.0, "aperture_m2": 1.0}


def contract_values(n: int, mean: float, std: float, support: str = "positive", seed: int = 0) -> np.ndarray:
    """``n`` per-heliostat values that realise a contract distribution.

    Quantiles ``(k + 0.5) / n`` (deterministic, no sampling noise) of a gamma
    distribution with the contract mean and std for positive parameters (right
    skewed like radial errors), of a normal one otherwise (clipped into (0, 1)
    for fractions), in a random order.

    Raises:
        ValueError: ``n`` not a whole number >= 1, ``mean`` not finite, ``std`` not a
            finite number >= 0, or an unknown ``support`` (``n = -1`` had given no
            values, a NaN ``std`` NaN values, a misspelled support normal ones).
    """
    problems = {
        "n": count_problem(n, MAX_SYNTHETIC_HELIOSTATS),
        "mean": real_problem(mean),
        "std": real_problem(std, minimum=0.0),
        "support": None
        if support in ("positive", "unit", "real")
        else f"must be 'positive', 'unit' or 'real', got {support!r}",
    }
    for name, problem in problems.items():
        if problem is not None:
            raise ValueError(f"contract_values: {name} {problem}"[:200])
    q = (np.arange(n) + 0.5) / n
    if std <= 0:
        vals = np.full(n, float(mean))
    elif support == "positive":
        k = (mean / std) ** 2
        vals = stats.gamma.ppf(q, k, scale=mean / k)
    else:
        vals = stats.norm.ppf(q, mean, std)
        if support == "unit":
            vals = np.clip(vals, 1e-9, 1 - 1e-9)
    return np.random.default_rng(seed).permutation(vals)


@dataclasses.dataclass(frozen=True)
class AcceptanceResult:
    """Everything :func:`run_acceptance` computed (``report`` is the JSON document)."""

    report: dict
    field: FieldData
    level1: dict[str, Level1Result]
    clusters: dict[str, ClusterResult]
    extrapolations: dict[str, Extrapolation]
    yield_contract: YieldResult
    yield_measured: YieldResult | None
    """None when level 2 was not assessed (no yield parameter measured on at least 2
    heliostats: the "measured" field would be the contract's)."""


def _clean(x):
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _check_arguments(field, contract, aperture, plant_lla, sun) -> None:
    """:func:`run_acceptance`'s arguments are of their kinds (each had failed as an
    AttributeError deep inside, or a NaN plant had been run)."""
    for name, value, kind, hint in (
        ("field", field, FieldData, " (read_field_csv or field_from_summary makes one)"),
        ("contract", contract, Contract, " (load_contract reads one)"),
        ("aperture", aperture, TargetPlane, " (load_receiver or juelich_receiver)"),
    ):
        if not isinstance(value, kind):
            raise TypeError(f"run_acceptance: {name}: expected a {kind.__name__}{hint}, got {type(value).__name__}")
    try:
        plant = np.asarray(plant_lla, dtype=float)
    except (TypeError, ValueError):
        plant = np.full(1, np.nan)
    if plant.shape != (3,) or not np.isfinite(plant).all() or abs(plant[0]) > 90.0:
        raise ValueError(
            f"run_acceptance: plant_lla: expected 3 finite numbers (latitude in [-90, 90] deg, longitude deg, "
            f"altitude m), got {plant_lla!r}"[:300]
        )
    if sun is not None and (not isinstance(sun, SunSeries) or len(sun.unix_time_s) == 0):
        got = f"{len(sun.unix_time_s)} samples" if isinstance(sun, SunSeries) else type(sun).__name__
        raise ValueError(f"run_acceptance: sun: expected a SunSeries of at least one sample, got {got}")


def run_acceptance(
    field: FieldData,
    contract: Contract,
    aperture: TargetPlane,
    plant_lla: tuple[float, float, float],
    *,
    sun: SunSeries | None = None,
    positions_source: str | None = None,
) -> AcceptanceResult:
    """Sample sizes, level 1, clusters, resampling advice, extrapolation and level 2.

    Args:
        field: every heliostat of the field with the measured values (NaN = not
            measured); ``field.n`` is the population ``N``.
        contract: the contract.
        aperture: receiver aperture (ENU, same origin as ``field.positions``).
        plant_lla: plant WGS84 coordinates (deg, deg, m) for the sun positions.
        sun: precomputed sun samples (default: :func:`typical_year` from the contract).
        positions_source: where ``field.positions`` were read (a file), named when a
            heliostat is nearer than :data:`MIN_HELIOSTAT_SPACING_M` to the tower
            (the receiver aperture's centre, east and north).

    A heliostat nearer than :data:`MIN_HELIOSTAT_SPACING_M` (m) to the tower (its
    mirror would be in the tower, or the positions are in km) is logged as a warning.

    Raises:
        ConfigError: the sun never rises above the contract's ``min_elevation_deg``.
        TypeError: an argument of another kind (a path for ``field`` or ``contract``).
        ValueError: ``plant_lla`` not 3 finite numbers with a latitude in [-90, 90];
            ``sun`` of no samples (level 2 had failed on a year without sun).

    Level 2 compares the contract's field with the measured one, in which a parameter
    measured on fewer than 2 heliostats takes the contract's values
    (``level2.parameters_from_contract``; ``parameters_measured`` are extrapolated from
    the measurements). With no yield parameter measured on at least 2 heliostats it is
    not assessed: ``level2.assessed`` false, ``pass``, ``annual_efficiency_measured``,
    ``relative_difference``, ``mean_intercept_measured`` and the monthly
    ``efficiency_measured`` null, ``not_assessed_reason`` says why, and the verdict is
    at best ``inconclusive``.

    Returns:
        An :class:`AcceptanceResult`; ``result.report`` follows the
        ``acceptance.json`` schema.
    """
    _check_arguments(field, contract, aperture, plant_lla, sun)
    n = field.n
    xy = np.asarray(field.positions)[:, :2]
    cl = dict(contract.clusters)
    length_scale = cl.pop("length_factor", 2.5) * field_spacing(xy)
    z_thr = cl.pop("z_threshold", 2.0)
    k_nb = int(cl.pop("k_neighbours", 8))
    cl_kw = {
        "eps": float(cl.get("eps", 1.0)),
        "min_samples": int(cl.get("min_samples", 6)),
        "value_factor": float(cl.get("value_factor", 2.5)),
    }
    ids = np.asarray(field.ids)
    report: dict = {
        "population": n,
        "sample_sizes": {},
        "level1": {},
        "clusters": {},
        "resample": {},
        "level2": {},
        "verdict": None,
        "reasons": [],
    }
    level1, clusters, extrap = {}, {}, {}
    reasons = []
    inconclusive = False
    parameters = progress_bar(
        contract.parameters.items(), logger=log, desc="level 1: parameters", total=len(contract.parameters)
    )
    for name, spec in parameters:
        info = PARAMETERS[name]
        n_req = sample_size(
            spec.mean,
            spec.std,
            spec.rel_error,
            population=n,
            confidence=contract.confidence,
            formula=contract.formula,  # pyright: ignore[reportArgumentType]
            z=contract.z,
        )
        report["sample_sizes"][name] = n_req
        meas = np.flatnonzero(field.measured(name))
        if meas.size < 2:
            report["level1"][name] = {
                "pass": None,
                "n": int(meas.size),
                "n_required": n_req,
                "mean": None,
                "std": None,
                "contract_mean": spec.mean,
                "contract_std": spec.std,
            }
            reasons.append(
                f"{name}: not measured" if meas.size == 0 else f"{name}: {meas.size} measured, at least 2 needed"
            )
            inconclusive = True
            continue
        vals = np.asarray(field.values[name])[meas]
        r1 = level1_test(
            vals,
            spec.mean,
            spec.std,
            n_required=n_req,
            confidence=contract.confidence,
            sense=info.sense,
            distribution=info.distribution,
            seed=contract.seed,
        )
        level1[name] = r1
        report["level1"][name] = r1.to_json()
        if not (r1.pass_mean and r1.pass_std):
            reasons.append(
                f"{name}: level 1 failed (mean {r1.mean:.4g} CI {r1.mean_ci[0]:.4g}.."
                f"{r1.mean_ci[1]:.4g} vs {spec.mean:.4g}; std {r1.std:.4g} CI "
                f"{r1.std_ci[0]:.4g}..{r1.std_ci[1]:.4g} vs {spec.std:.4g})"
            )
        elif not r1.sufficient_sample:
            reasons.append(f"{name}: {r1.n} measured, {n_req} required")
            inconclusive = True
        cr = find_clusters(xy[meas], vals, length_scale_m=length_scale, **cl_kw)
        clusters[name] = cr
        side = "high" if info.sense == "lower" else "low" if info.sense == "higher" else "both"
        advice = resampling_advice(xy, meas, vals, cr, k_neighbours=k_nb, z_threshold=z_thr, side=side)
        report["resample"][name] = [str(h) for h in ids[advice]]
        ex = extrapolate_field(
            xy,
            meas,
            vals,
            cr.labels,
            support=info.support,
            bandwidth=contract.bandwidth,  # pyright: ignore[reportArgumentType]
            seed=contract.seed,
        )
        extrap[name] = ex
        entries = []
        for k in range(cr.n_anomalies + 1):
            members = cr.labels == k
            mv = vals[members]
            entries.append(
                {
                    "label": k,
                    "anomalous": k > 0,
                    "heliostats": [str(h) for h in ids[meas[members]]],
                    "n_assigned": int((ex.labels == k).sum()),
                    "mean": float(mv.mean()) if mv.size else None,
                    "std": float(mv.std(ddof=1)) if mv.size > 1 else None,
                    "p_value": cr.p_values.get(k),
                }
            )
        report["clusters"][name] = entries
        if cr.n_anomalies:
            reasons.append(f"{name}: {cr.n_anomalies} local anomaly cluster(s)")

    # ---- level 2
    if sun is None:
        with activity("level 2: a typical year of sun positions", logger=log):
            sun = typical_year(
                *plant_lla,
                year=contract.year,
                step_minutes=contract.step_minutes,
                min_elevation_deg=contract.min_elevation_deg,
            )
        if len(sun.unix_time_s) == 0:
            raise ConfigError(
                f"{contract.source or 'contract'}: [yield] min_elevation_deg = {contract.min_elevation_deg}: "
                f"the sun never rises that high at the plant (latitude {plant_lla[0]:.2f}) in {contract.year}"
            )
    centre = np.asarray(aperture.centre, dtype=float)
    problem = tower_clearance_problem(field.ids, np.asarray(field.positions), (centre[0], centre[1]))
    if problem is not None:  # a warning, not a refusal: one-heliostat test fields stand at the tower's foot
        where = positions_source or "the field's positions"
        log.warning(
            f"{where}: field 'east_m/north_m': {problem} (its level-2 efficiency is not that of a field "
            "that can be built)"
        )
    contract_kw, measured_kw = {}, {}
    yield_names = ("tracking_mrad", "slope_mrad", "reflectance", "aperture_m2")
    # a parameter measured on fewer than 2 heliostats has no extrapolation: the measured
    # field takes the contract's values for it (named in the report)
    from_measurements = [name for name in yield_names if name in extrap]
    from_contract = [name for name in yield_names if name in contract.parameters and name not in extrap]
    assessed = bool(from_measurements)
    for i, name in enumerate(yield_names):
        spec = contract.parameters.get(name)
        if spec is None:
            c = np.full(n, _YIELD_DEFAULTS[name])
        else:
            c = contract_values(n, spec.mean, spec.std, PARAMETERS[name].support, seed=contract.seed + i)
        contract_kw[name] = c
        measured_kw[name] = extrap[name].values if name in extrap else c
    a_ref = contract.parameters["aperture_m2"].mean if "aperture_m2" in contract.parameters else 1.0
    common = {"reference_aperture_m2": a_ref, "sun_sigma_mrad": contract.sun_sigma_mrad}
    fields = (contract_kw, measured_kw) if assessed else (contract_kw,)
    desc = "level 2: yield (contract, measured)" if assessed else "level 2: yield (contract; nothing measured)"
    yields = [
        field_efficiency(field.positions, aperture, sun, **kw, **common)
        for kw in progress_bar(fields, logger=log, desc=desc, total=len(fields), unit="field")
    ]
    yc = yields[0]
    ym = yields[1] if assessed else None
    rel = (ym.annual - yc.annual) / yc.annual if ym is not None else None
    report["level2"] = {
        "assessed": assessed,
        "not_assessed_reason": None
        if assessed
        else (
            "no parameter of the yield model (" + ", ".join(from_contract) + ") is measured on at least 2 "
            "heliostats: the measured field would be the contract's"
        ),
        "parameters_measured": from_measurements,
        "parameters_from_contract": from_contract,
        "annual_efficiency_contract": yc.annual,
        "annual_efficiency_measured": ym.annual if ym is not None else None,
        "relative_difference": rel,
        "mean_intercept_contract": float(yc.intercept.mean()),
        "mean_intercept_measured": float(ym.intercept.mean()) if ym is not None else None,
        "tolerance": contract.tolerance,
        "pass": bool(rel >= -contract.tolerance) if rel is not None else None,
        "monthly": [
            {
                "month": m + 1,
                "efficiency_contract": yc.monthly[m],
                "efficiency_measured": ym.monthly[m] if ym is not None else None,
                "clear_sky_dni_kwh_m2": yc.dni_kwh_m2[m],
            }
            for m in range(12)
        ],
        "model": {
            "sun_sigma_mrad": contract.sun_sigma_mrad,
            "year": contract.year,
            "step_minutes": contract.step_minutes,
            "min_elevation_deg": contract.min_elevation_deg,
            "beam_sigma": "per-axis sigma^2 = sun^2 + 2 slope^2 + tracking^2 / 2 (radial RMS inputs)",
        },
    }
    if rel is None:
        reasons.append(f"level 2: not assessed: {report['level2']['not_assessed_reason']}")
        inconclusive = True
    elif not report["level2"]["pass"]:
        assert ym is not None
        reasons.append(
            f"level 2: annual efficiency {ym.annual:.4f} vs contract {yc.annual:.4f} "
            f"({100 * rel:+.2f} %, tolerance {100 * contract.tolerance:.2f} %)"
        )
    failed = any(not (r.pass_mean and r.pass_std) for r in level1.values()) or report["level2"]["pass"] is False
    report["verdict"] = "rejected" if failed else "inconclusive" if inconclusive else "accepted"
    report["reasons"] = reasons
    return AcceptanceResult(_clean(report), field, level1, clusters, extrap, yc, ym)  # pyright: ignore[reportArgumentType]
