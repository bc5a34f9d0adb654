"""Planning calibration measurements: which instants to measure next, and which
heliostats most need measuring.

Criterion (I-optimal design): a camera-target measurement of a heliostat adds
the information ``J^T J / sigma^2`` of its two residual components (``J``: their
Jacobian w.r.t. the free parameters at that instant, ``sigma``: the noise per
component) to the current parameter covariance ``C``. What the plant cares
about is the pointing error in operation, so the objective is the expected
squared beam error over the heliostat's *operating envelope* (sun positions of
a year, weighted by DNI, aiming at the receiver)::

    U(C) = sum_e w_e tr(J_e C J_e^T) = tr(C M),   M = sum_e w_e J_e^T J_e

the integrated prediction variance. It is in mrad^2, directly the quantity an
operator reads, and unlike D-optimality it does not spend measurements on
parameter combinations that never matter for aiming. Measurements are chosen
greedily, each maximising the drop of ``U`` given those already chosen (the
drop of a rank-2 update has a closed form, so every candidate of every
heliostat is scored at once)::

    C' = C - C J^T S^-1 J C,   S = sigma^2 I + J C J^T,   U(C) - U(C') = tr(S^-1 J C M C J^T)

Greedy selection for this (submodular-like) criterion is the standard
sequential design; it is exact for one measurement.

Starting covariance: a fitted heliostat's posterior (:attr:`CalibrationResults.covariance`),
or, for a heliostat planned from scratch (retrospective studies, new heliostats), the
fleet's empirical-Bayes prior (:func:`prior_covariance`): what the fleet says before
this heliostat has a record.

A model that is not exact (:mod:`heliojax._discrepancy`): trusting the model, the
criterion puts measurements where the model has the most leverage, the extreme
poses, where a real heliostat deviates most from any parametric model. With a
:class:`heliojax.ModelDiscrepancy` (a Gaussian process over the mirror normal,
learnt from the fleet's residuals), :func:`discrepancy_design` appends the
discrepancy's whitened coefficients at inducing normals to the parameters, and the
same criterion then also counts the discrepancy where the heliostat operates: a
measurement near the operating poses teaches about it, one far away is diluted by
its own discrepancy. ``U`` then includes the discrepancy's variance over the envelope.

The operating envelope (:func:`operating_envelope`) is a year of sun positions
above a minimum elevation, each weighted by its clear-sky direct normal
irradiance (Meinel model with Kasten-Young air mass), with the heliostat aiming
at the receiver: hours that deliver more energy count more.
"""

from __future__ import annotations

import collections.abc
import math
import os
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._aim import direction_jacobian_mrad
from ._discrepancy import (
    DISCREPANCY_INDUCING,
    ModelDiscrepancy,
    augment_jacobian,
    discrepancy_features,
    estimate_discrepancy,
    inducing_normals,
    mirror_normals,
)
from ._errors import DataError
from ._geometry import check_unit_vectors
from ._heliostat import HeliostatGeometry, RecordContext
from ._io import shown_value
from ._kinematics import AbstractKinematicModel, inverse_aim
from ._limits import EARLIEST_UNIX_S, EARLIEST_YEAR, LATEST_UNIX_S, LATEST_YEAR, MAX_PLAN_BUDGET, count_problem
from ._parameters import ParameterView
from ._sun import solar_position
from .fitting import prior_moments, residual_jacobians

SOLAR_CONSTANT_W_M2 = 1361.0
"""Total solar irradiance (W/m^2) of the clear-sky DNI weights."""


def clear_sky_dni(elevation: Float[ArrayLike, "*n"]) -> Float[np.ndarray, "*n"]:
    """Clear-sky direct normal irradiance (W/m^2) at sun ``elevation`` (rad): Meinel's
    ``S0 * 0.7 ** (AM ** 0.678)`` with the Kasten-Young (1989) air mass; 0 below the horizon."""
    el = np.asarray(elevation, float)
    zenith = 90.0 - np.degrees(el)
    with np.errstate(invalid="ignore", divide="ignore"):
        am = 1.0 / (np.cos(np.radians(zenith)) + 0.50572 * (96.07995 - zenith) ** -1.6364)
        dni = SOLAR_CONSTANT_W_M2 * 0.7 ** (am**0.678)
    return np.where(el > 0.0, dni, 0.0)


def _check_min_elevation(min_elevation_deg: float) -> float:
    """``min_elevation_deg`` as a float; ValueError unless it is finite degrees in
    [-90, 90] (1e9 wrapped through the sine and let every instant in, NaN none)."""
    if isinstance(min_elevation_deg, bool) or not isinstance(min_elevation_deg, (int, float, np.integer, np.floating)):
        raise ValueError(f"min_elevation_deg must be a number of degrees, not {min_elevation_deg!r}")
    value = float(min_elevation_deg)
    if not -90.0 <= value <= 90.0:  # NaN too
        raise ValueError(f"min_elevation_deg must be degrees in [-90, 90], not {value!r}")
    return value


def _check_budget(budget: typing.Any) -> None:
    """ValueError unless ``budget`` is a whole number of measurements in ``[0,
    MAX_PLAN_BUDGET]`` (a budget of 10**9 had run a scan of 10**9 greedy steps)."""
    if count_problem(budget, MAX_PLAN_BUDGET, minimum=0) is not None:
        raise ValueError(f"budget must be a whole number of measurements in [0, {MAX_PLAN_BUDGET:,}], not {budget!r}")


def _check_unix_times(name: str, times: np.ndarray, unknown: bool) -> None:
    """ValueError unless the finite ``times`` are seconds since 1970 within heliojax's
    span (:mod:`heliojax._limits`), and, unless ``unknown``, every time is finite (NaN:
    unknown). Milliseconds had aged a candidate by 50 years."""
    bad = ~np.isfinite(times) if not unknown else np.isinf(times)
    with np.errstate(invalid="ignore"):
        bad |= np.isfinite(times) & ~((times >= EARLIEST_UNIX_S) & (times < LATEST_UNIX_S))
    if bad.any():
        first = float(times[bad].flat[0])
        raise ValueError(
            f"{name} must be seconds since 1970-01-01 UTC in [{EARLIEST_UNIX_S:g}, {LATEST_UNIX_S:g})"
            f"{' or NaN (unknown)' if unknown else ''}, not {first!r}"
            + (" (milliseconds?)" if first >= LATEST_UNIX_S and math.isfinite(first) else "")
        )


def operating_envelope(
    origin_lla: Float[ArrayLike, "3"],
    *,
    year: int = 2023,
    day_step: int = 5,
    hour_step: float = 1.0,
    min_elevation_deg: float = 10.0,
) -> tuple[Float[Array, "E 3"], Float[Array, " E"]]:
    """Sun positions of a year at the site and their clear-sky DNI weights.

    Args:
        origin_lla: ``[lat_deg, lon_deg, alt_m]`` of the site.
        year: the year sampled (UTC).
        day_step: every ``day_step``-th day of the year.
        hour_step: hours between instants of a day (UTC, starting at 00:00).
        min_elevation_deg: instants with a lower sun are left out.

    Returns:
        ``(sun, weight)``: ``(E, 3)`` unit ENU vectors to the sun and ``(E,)``
        clear-sky DNI (W/m^2) of each instant.

    Raises:
        ValueError: naming the argument: ``year`` or ``day_step`` not an integer (or
            ``day_step`` below 1, ``year`` outside 1970 to 2199), ``hour_step`` not in (0, 24] h, ``min_elevation_deg``
            not in [-90, 90], ``origin_lla`` not three finite numbers. (``day_step`` 0
            was taken as 1, 2.9 as 2, ``hour_step`` 0 divided by zero, and a NaN
            elevation or origin gave an empty envelope.)
    """
    import datetime as dt

    for name, value, low in (("year", year, 1), ("day_step", day_step, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an integer{' >= 1' if name == 'day_step' else ''}, not {value!r}")
    if not EARLIEST_YEAR <= year <= LATEST_YEAR:  # the span of instants heliojax takes (heliojax._limits)
        raise ValueError(f"year must be in {EARLIEST_YEAR} to {LATEST_YEAR} (UTC), not {year!r}")
    if isinstance(hour_step, bool) or not 0.0 < float(hour_step) <= 24.0:  # NaN too
        raise ValueError(f"hour_step must be hours in (0, 24], not {hour_step!r}")
    min_elevation_deg = _check_min_elevation(min_elevation_deg)
    origin = np.asarray(origin_lla, float)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f"origin_lla must be 3 finite numbers [lat_deg, lon_deg, alt_m], not {origin_lla!r}"[:200])
    start = dt.datetime(year, 1, 1, tzinfo=dt.UTC).timestamp()
    days = np.arange(0, 365, int(day_step))
    hours = np.arange(0.0, 24.0, float(hour_step))
    unix = start + (days[:, None] * 86400.0 + hours[None, :] * 3600.0).ravel()
    lat, lon, alt = (float(x) for x in origin)
    position = solar_position(jnp.asarray(unix, jnp.float64), lat, lon, alt)
    el = np.asarray(position.elevation)
    keep = el > np.radians(min_elevation_deg)
    sun = np.asarray(position.direction_enu())[keep]
    return jnp.asarray(sun), jnp.asarray(clear_sky_dni(el[keep]))


@eqx.filter_jit
def _envelope_program(view, models, geometry, sun, weight, aim_points, discrepancy, inducing, batch_size: int):
    w = weight / jnp.maximum(jnp.sum(weight), 1e-300)

    def one(args):
        model, g, point, u = args

        def instant(s, wi):
            counts = inverse_aim(model, g, point, s)
            jac = direction_jacobian_mrad(view, model, g, counts, RecordContext.from_sun(s), point)
            if discrepancy is not None:
                normal = mirror_normals(g.position, s[None], point[None])[0]
                jac = augment_jacobian(jac, discrepancy_features(discrepancy, normal, u))
            ok = jnp.all(jnp.isfinite(jac))
            return jnp.where(ok, wi * jac.T @ jac, 0.0), jnp.where(ok, wi, 0.0)

        m, used = jax.vmap(instant)(sun, w)
        return jnp.sum(m, axis=0) / jnp.maximum(jnp.sum(used), 1e-300)

    return jax.lax.map(one, (models, geometry, aim_points, inducing), batch_size=batch_size)


def envelope_matrices(
    models: AbstractKinematicModel,
    view: ParameterView,
    geometry: HeliostatGeometry,
    sun: Float[Array, "E 3"],
    weight: Float[ArrayLike, " E"],
    aim_points: Float[ArrayLike, "*h 3"],
    *,
    discrepancy: ModelDiscrepancy | None = None,
    inducing: Float[Array, "H B 3"] | None = None,
    batch_size: int = 256,
) -> Float[Array, "H G G"]:
    """``M = sum_e w_e J_e^T J_e`` per heliostat over an operating envelope, where
    ``J_e`` is the Jacobian of the beam direction (mrad, two tangent components)
    w.r.t. the free parameters at the counts that aim at ``aim_points`` (ENU m,
    ``(3,)`` or ``(H, 3)``) with the sun at ``sun[e]``; weights normalised to sum 1.
    With ``discrepancy`` and its ``inducing`` normals, ``J_e`` gains the whitened
    discrepancy coefficients (:func:`heliojax.augment_jacobian`): ``G = F + 2 B``,
    else ``G = F``. Heliostats are processed ``batch_size`` at a time (memory
    ``batch_size x E x 2 x G``)."""
    h = int(jnp.shape(geometry.position)[0])
    points = jnp.broadcast_to(jnp.asarray(aim_points, sun.dtype), (h, 3))
    if (discrepancy is None) != (inducing is None):
        raise ValueError("envelope_matrices: discrepancy and inducing go together")
    u = jnp.zeros((h, 1, 3), sun.dtype) if inducing is None else jnp.asarray(inducing, sun.dtype)
    return _envelope_program(
        view, models, geometry, sun, jnp.asarray(weight, sun.dtype), points, discrepancy, u, int(batch_size)
    )


def envelope_matrix(jac: Float[Array, "H E 2 F"], weight: Float[Array, "*h E"]) -> Float[Array, "H F F"]:
    """``M = sum_e w_e J_e^T J_e`` with weights normalised to sum 1 per heliostat."""
    w = jnp.broadcast_to(jnp.asarray(weight, jac.dtype), jac.shape[:2])
    w = w / jnp.maximum(jnp.sum(w, axis=1, keepdims=True), 1e-300)
    return jnp.einsum("he,heif,heig->hfg", w, jac, jac)


@typing.final
class MeasurementPlan(eqx.Module):
    """Greedy I-optimal choice of ``K`` measurements per heliostat.

    Attributes:
        chosen: ``(H, K)`` candidate indices in the order chosen (-1 where fewer
            valid candidates than ``K``).
        uncertainty_before_mrad: ``(H,)`` ``sqrt(U)``: RMS predicted pointing error
            over the envelope from parameter uncertainty, before.
        uncertainty_after_mrad: ``(H, K)`` the same after each chosen measurement.
        covariance_after: ``(H, G, G)`` the predicted covariance after all of them
            (``G = F`` free parameters; planned with a model discrepancy
            (:func:`discrepancy_design`), the parameters' block first, then the
            discrepancy coefficients').
    """

    chosen: Int[Array, "H K"]
    uncertainty_before_mrad: Float[Array, " H"]
    uncertainty_after_mrad: Float[Array, "H K"]
    covariance_after: Float[Array, "H G G"]


@eqx.filter_jit
def _greedy(cov, cand_jac, cand_valid, cand_slot, m_env, noise, day, correlation, budget: int, day_slots: int):
    """The greedy choice (:func:`plan_measurements`) for every heliostat in one program.

    With ``day_slots > 0`` the state is the covariance of the parameters and of the
    whitened day effects ``z_1..z_B`` (``2 B`` coordinates, ``B = day_slots``) of the
    days measured so far, ``blockdiag(C, I)`` at the start: a day's effect is
    independent of everything until a record of that day is chosen, so a candidate of
    a day not yet measured is scored with its whole noise ``sigma^2`` (as without day
    effects), and one of a measured day through that day's coordinates."""

    def one(c, jac, valid, slot, m, sigma, day, rho):
        g = c.shape[0]
        size = g + 2 * day_slots
        eye = jnp.eye(2, dtype=c.dtype)
        shared = sigma * jnp.sqrt(rho)  # (K,) the day effect's share of the noise (sd)
        own = sigma * jnp.sqrt(1.0 - rho)  # (K,) the record's own
        c = jnp.zeros((size, size), c.dtype).at[:g, :g].set(c).at[g:, g:].set(jnp.eye(2 * day_slots, dtype=c.dtype))

        def day_rows(day_of_slot, d):
            """Rows of day(s) ``d`` in the state, and whether each is measured yet."""
            match = d[..., None] == day_of_slot[(None,) * d.ndim]
            j = jnp.argmax(match, axis=-1)
            return g + jnp.stack([2 * j, 2 * j + 1], axis=-1), jnp.any(match, axis=-1)

        def designs(c, day_of_slot):
            """``a = J' C`` ``(K, 2, size)`` and ``S = J' C J'^T + own^2 I`` ``(K, 2, 2)``
            with ``J' = [J, shared E_day]`` (``E_day`` picks the day's coordinates)."""
            a = jnp.einsum("kif,fg->kig", jac, c[:g, :])
            extra = (shared**2)[:, None, None] * eye[None]  # a day not measured yet: its whole effect
            if day_slots:
                rows, measured = day_rows(day_of_slot, day)
                a = a + jnp.where(measured[:, None, None], shared[:, None, None] * c[rows, :], 0.0)
                a_day = jnp.take_along_axis(a, jnp.broadcast_to(rows[:, None, :], (rows.shape[0], 2, 2)), axis=2)
                extra = jnp.where(measured[:, None, None], shared[:, None, None] * a_day, extra)
            s = jnp.einsum("kif,kjf->kij", a[..., :g], jac) + extra + (own**2)[:, None, None] * eye[None]
            return a, s

        def step(carry, _):
            c, avail, day_of_slot, used = carry
            a, s = designs(c, day_of_slot)
            gain_matrix = jnp.einsum("kif,fg,kjg->kij", a[..., :g], m, a[..., :g])
            gain = jnp.trace(jnp.linalg.solve(s, gain_matrix), axis1=1, axis2=2)
            gain = jnp.where(avail, gain, -jnp.inf)
            k = jnp.argmax(gain)
            ok = avail[k]
            ak, sk = a[k], s[k]
            if day_slots:  # a new day takes the next free slot; the choice's design then uses it
                rows, measured = day_rows(day_of_slot, day[k])
                new_day = ok & ~measured
                day_of_slot = jnp.where(new_day, day_of_slot.at[used].set(day[k]), day_of_slot)
                used = used + new_day.astype(used.dtype)
                rows, _ = day_rows(day_of_slot, day[k])
                ak = jac[k] @ c[:g, :] + shared[k] * c[rows, :]
                sk = ak[:, :g] @ jac[k].T + shared[k] * ak[:, rows] + own[k] ** 2 * eye
            c_new = c - ak.T @ jnp.linalg.solve(sk, ak)
            c_new = 0.5 * (c_new + c_new.T)
            c = jnp.where(ok, c_new, c)
            avail = avail & ~(ok & (slot == slot[k])) & (jnp.arange(avail.shape[0]) != k)
            u = jnp.sqrt(jnp.maximum(jnp.trace(c[:g, :g] @ m), 0.0))
            return (c, avail, day_of_slot, used), (jnp.where(ok, k, -1), u)

        u0 = jnp.sqrt(jnp.maximum(jnp.trace(c[:g, :g] @ m), 0.0))
        start = (c, valid, jnp.full((day_slots,), -1, day.dtype), jnp.zeros((), jnp.int32))
        (c_end, *_), (chosen, u) = jax.lax.scan(step, start, None, length=budget)
        return chosen, u0, u, c_end[:g, :g]

    return jax.vmap(one)(cov, cand_jac, cand_valid, cand_slot, m_env, noise, day, correlation)


def plan_measurements(
    covariance: Float[Array, "H F F"],
    candidate_jacobians: Float[Array, "H K 2 F"],
    candidate_valid: Bool[Array, "H K"],
    envelope: Float[Array, "H F F"],
    noise_mrad: Float[ArrayLike, "*hk"],
    budget: int,
    slot: Int[Array, "H K"] | None = None,
    day: Int[ArrayLike, "H K"] | None = None,
    day_correlation: Float[ArrayLike, "*h"] = 0.0,
) -> MeasurementPlan:
    """Choose ``budget`` measurements per heliostat among its candidates.

    Records of one day can share an error (the target's or camera's state that day, a
    drift slower than a day; the shared real records' residuals have an intra-day
    correlation of ~0.4): then a second record of a measured day teaches less than a
    record of a new day, and a planner that takes records as independent crowds its
    choice into a few days (on the shared records, 4-5 days for 16 records where a
    random choice spans 10-13). With ``day`` and ``day_correlation`` (``rho``), each
    candidate's two residual components are ``J theta + b_d + e`` with a day effect
    ``b_d`` of variance ``rho sigma^2`` per component shared by the candidates of day
    ``d`` and an own error of variance ``(1 - rho) sigma^2`` (``sigma`` the candidate's
    noise): the random day-effect model under which discovery whitens its criterion
    (:func:`heliojax.fitting.day_clustering`). The day effects enter the greedy
    state as nuisance parameters (not counted in ``U``: a future day has its own).

    Args:
        covariance: current parameter covariance (physical units of the free
            parameters): a fit's posterior, or a prior's ``diag(sigma^2)``.
        candidate_jacobians: from :func:`residual_jacobians` at each candidate.
        candidate_valid: which candidates may be chosen.
        envelope: ``M`` of :func:`envelope_matrix`.
        noise_mrad: measurement noise per residual component (mrad): a scalar,
            ``(H,)``, or ``(H, K)`` per candidate (e.g. :func:`aged_noise_mrad`).
        budget: measurements per heliostat (static).
        slot: ``(H, K)`` candidates of one slot exclude each other (one heliostat
            measures one target at a time); default: every candidate its own slot.
        day: ``(H, K)`` integer day label of each candidate (e.g.
            :func:`heliojax.fitting.day_labels` of its time); default: no day effect.
        day_correlation: ``rho`` in ``[0, 1)``, scalar or ``(H,)``; 0 (the default)
            takes records as independent (the plan without ``day``).

    Raises:
        ValueError: ``day_correlation`` outside ``[0, 1)`` or not finite.
    """
    _check_budget(budget)
    if jnp.ndim(candidate_valid) != 2 or jnp.shape(candidate_jacobians)[:2] != jnp.shape(candidate_valid):
        raise ValueError(
            f"candidate_valid {jnp.shape(candidate_valid)} and candidate_jacobians {jnp.shape(candidate_jacobians)} "
            "must be (H, K) and (H, K, 2, F)"
        )
    h, k = candidate_valid.shape
    if k == 0:  # round 14: argmax of an empty sequence
        raise ValueError("candidates: none (K = 0 candidates per heliostat); give at least one instant and target")
    # round 14: a candidate whose Jacobian is not finite (counts NaN: a pose the model cannot reach) was chosen
    # and left the heliostat's covariance as it was; it cannot be measured, and the others stay usable
    candidate_valid = jnp.asarray(candidate_valid, bool) & jnp.all(jnp.isfinite(candidate_jacobians), axis=(2, 3))
    noise = jnp.asarray(noise_mrad, covariance.dtype)
    noise = jnp.broadcast_to(noise[:, None] if noise.ndim == 1 else noise, (h, k))
    slots = jnp.broadcast_to(jnp.arange(k, dtype=jnp.int32), (h, k)) if slot is None else jnp.asarray(slot, jnp.int32)
    rho = np.broadcast_to(np.asarray(day_correlation, float), (h,))
    if not np.all(np.isfinite(rho) & (rho >= 0.0) & (rho < 1.0)):
        raise ValueError(f"day_correlation must be in [0, 1), not {day_correlation!r}")
    with_days = day is not None and bool(np.any(rho > 0.0))
    labels = np.zeros((h, k), np.int32)
    if with_days:  # any integer labels, as 0..D-1 (-2 for candidates that cannot be chosen)
        day = np.broadcast_to(np.asarray(day), (h, k))
        if not np.issubdtype(day.dtype, np.integer):
            raise ValueError(f"day must hold integer labels of shape {(h, k)}, not dtype {day.dtype}")
        labels = np.where(np.asarray(candidate_valid, bool), np.unique(day, return_inverse=True)[1].reshape(h, k), -2)
    rho = np.where(with_days, rho, 0.0)
    chosen, u0, u, c_end = _greedy(
        covariance,
        candidate_jacobians,
        jnp.asarray(candidate_valid, bool),
        slots,
        envelope,
        noise,
        jnp.asarray(labels),
        jnp.asarray(rho, covariance.dtype),
        min(int(budget), k),  # each step takes a candidate out: no more than K steps choose anything
        min(int(budget), k) if with_days else 0,
    )
    if int(budget) > k:  # the steps past K choose nothing: -1, the uncertainty stays
        rest = int(budget) - k
        chosen = jnp.concatenate([chosen, jnp.full((h, rest), -1, chosen.dtype)], axis=1)
        u = jnp.concatenate([u, jnp.broadcast_to(u[:, -1:], (h, rest))], axis=1)
    return MeasurementPlan(chosen=chosen, uncertainty_before_mrad=u0, uncertainty_after_mrad=u, covariance_after=c_end)


def aged_noise_mrad(
    noise_mrad: Float[ArrayLike, "*h"],
    drift_mrad2_per_day: float,
    candidate_unix_time: Float[ArrayLike, "H K"],
    candidate_valid: Bool[ArrayLike, "H K"],
    use_unix_time: Float[ArrayLike, "*h"] | None = None,
    creep_mrad2_per_day2: float = 0.0,
) -> Float[np.ndarray, "H K"]:
    """Each candidate's noise (mrad per component) as seen from the time the
    calibration is used, under the fleet's pointing drift (a random walk of rate
    ``q = drift_mrad2_per_day`` and a creep of rate ``c = creep_mrad2_per_day2``,
    :func:`heliojax.temporal_drift`)::

        sigma_k^2 = sigma^2 + q * a_k + c * a_k^2,   a_k = max(t_use - t_k, 0) / 86400 s

    A record taken long before the calibration is used tells less about the state
    then. The creep is the predictive law's drift that grows as the square of the
    days (a drift of the pointing at a steady, unknown rate of mean square ``c``): the
    state at ``t_use`` differs from that at ``t_k`` by the rate times ``a_k``. The
    walk's increments and the creep's rate are shared by records of similar age, so
    treating them as independent (as here) credits several old records with more
    than they hold: the rule ranks recent records higher but still over-values old
    ones.

    Args:
        noise_mrad: measurement noise per component (mrad), scalar or ``(H,)``.
        drift_mrad2_per_day: ``q``; 0 with ``c`` 0 gives ``noise_mrad`` for every candidate.
        candidate_unix_time: ``(H, K)`` s; NaN (unknown) counts as age 0.
        candidate_valid: ``(H, K)`` candidates that may be chosen.
        use_unix_time: s, scalar or ``(H,)``, when the calibration is used; default
            each heliostat's latest valid candidate (the end of the candidate window,
            or the cut date of records chosen before it).
        creep_mrad2_per_day2: ``c`` (mrad^2/day^2), finite and >= 0.

    Raises:
        ValueError: naming the argument: a rate or ``noise_mrad`` negative or not
            finite, times that are not seconds since 1970 (milliseconds; an infinite
            or NaN ``use_unix_time`` had aged nothing, silently), shapes that do not
            fit ``(H, K)``.
    """
    times = np.asarray(candidate_unix_time, float)
    if times.ndim != 2 or np.shape(candidate_valid) != times.shape:
        raise ValueError(
            f"candidate_unix_time and candidate_valid must be (H, K) arrays of one shape, not "
            f"{times.shape} and {np.shape(candidate_valid)}"
        )
    _check_unix_times("candidate_unix_time", times, unknown=True)
    valid = np.asarray(candidate_valid, bool) & np.isfinite(times)
    h, k = times.shape
    for name, rate in (("drift_mrad2_per_day", drift_mrad2_per_day), ("creep_mrad2_per_day2", creep_mrad2_per_day2)):
        if not np.isfinite(rate) or rate < 0.0:
            raise ValueError(f"{name} must be finite and >= 0, not {rate}")
    sigma = np.asarray(noise_mrad, float)
    if sigma.shape not in ((), (h,)) or not np.all(np.isfinite(sigma) & (sigma >= 0.0)):
        raise ValueError(f"noise_mrad must be finite and >= 0, a scalar or ({h},), not {noise_mrad!r}"[:200])
    if use_unix_time is None:
        use = np.max(np.where(valid, times, -np.inf), axis=1)
    else:
        use = np.asarray(use_unix_time, float)
        if use.shape not in ((), (h,)):
            raise ValueError(f"use_unix_time must be a scalar or ({h},), not of shape {use.shape}")
        _check_unix_times("use_unix_time", use, unknown=False)
        use = np.broadcast_to(use, (h,))
    age_days = np.where(valid & np.isfinite(use)[:, None], np.maximum(use[:, None] - times, 0.0), 0.0) / 86400.0
    sigma = np.broadcast_to(sigma, (h,))[:, None]
    return np.sqrt(sigma**2 + drift_mrad2_per_day * age_days + creep_mrad2_per_day2 * age_days**2)


@typing.final
class Candidates(eqx.Module):
    """Candidate measurements per heliostat: what a camera-target record would be.

    Attributes:
        counts: ``(H, K, 2)`` motor counts of each candidate.
        context: batched :class:`heliojax.RecordContext` ``(H, K)`` (sun, time, ...).
        spots: ``(H, K, 3)`` ENU m, where the spot is expected (the target centre
            for planned instants, the measured spot for existing records).
        valid: ``(H, K)`` candidates that may be chosen.
        slot: ``(H, K)`` candidates of one slot (one instant at several targets)
            exclude each other.
    """

    counts: Float[Array, "H K 2"]
    context: RecordContext
    spots: Float[Array, "H K 3"]
    valid: Bool[Array, "H K"]
    slot: Int[Array, "H K"]


@eqx.filter_jit
def _target_candidates(models, geometry, sun, centres, min_sin_elevation):
    def one(model, g):
        def at(s, c):
            return inverse_aim(model, g, c, s)

        counts = jax.vmap(lambda s: jax.vmap(lambda c: at(s, c))(centres))(sun)  # (N, T, 2)
        act = g.actuators
        lo, hi = act.min_counts[None, None, :], act.max_counts[None, None, :]
        inside = jnp.all((counts >= lo) & (counts <= hi) & jnp.isfinite(counts), axis=-1)
        return counts, inside

    counts, inside = jax.vmap(one)(models, geometry)
    h, n, t = counts.shape[:3]
    high = sun[:, 2] >= min_sin_elevation
    valid = inside & high[None, :, None]
    return counts.reshape(h, n * t, 2), valid.reshape(h, n * t)


def candidates_at_targets(
    models: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    sun: Float[Array, "N 3"],
    target_centres: Float[Array, "T 3"],
    *,
    unix_time: Float[ArrayLike, " N"] | None = None,
    target_index: Int[ArrayLike, " T"] | None = None,
    min_elevation_deg: float = 10.0,
) -> Candidates:
    """Candidates for future measurements: each heliostat aimed at each target's
    centre at each instant, ``k = n * T + t``; valid where the sun is at least
    ``min_elevation_deg`` high and the counts are inside the actuators' range.

    ``target_index`` ``(T,)``: each target's index in the fitted fleet's
    ``target_names`` (-1 for a target it never used), carried in the candidates'
    context so that target-dependent effects (``survey_target``) enter the
    candidates' Jacobians; default -1 (unknown) for every target.

    Raises:
        ValueError: naming the argument: ``target_centres`` not ``(T, 3)``,
            ``target_index`` not ``(T,)`` integers >= -1, ``unix_time`` not ``(N,)``
            seconds since 1970 (NaN: unknown), ``min_elevation_deg`` not in [-90, 90]
            (1e9 went through the sine and let every candidate in).
    """
    sun = jnp.asarray(sun)
    if sun.ndim != 2 or sun.shape[1] != 3:  # round 14: inverse_aim's "sun must have shape (3,) ... not ()"
        raise ValueError(f"sun has shape {sun.shape}; expected (N, 3) unit ENU vectors (one instant: sun[None])")
    check_unit_vectors(sun, None, "sun")  # a NaN sun had made every candidate of its instant invalid, unsaid
    centres = jnp.asarray(target_centres, sun.dtype)
    if centres.ndim != 2 or centres.shape[1] != 3 or centres.shape[0] == 0:
        raise ValueError(f"target_centres must be (T, 3) ENU m, T >= 1, not of shape {centres.shape}")
    # values are checked where known (not traced): a NaN centre had made every candidate invalid
    if not isinstance(centres, Tracer) and not np.isfinite(np.asarray(centres)).all():
        raise ValueError("target_centres must be finite (ENU m)")
    h, n, t = int(jnp.shape(geometry.position)[0]), sun.shape[0], centres.shape[0]
    if target_index is not None and np.shape(target_index) != (t,):
        raise ValueError(f"target_index has shape {np.shape(target_index)}, expected ({t},): one per target centre")
    index = None if target_index is None or isinstance(target_index, Tracer) else np.asarray(target_index)
    if index is not None and (index.dtype.kind not in "iu" or np.any(index < -1)):
        raise ValueError(f"target_index must be integers >= -1 (-1: a target the fit never used), not {target_index!r}")
    if unix_time is not None:
        if np.shape(unix_time) != (n,):
            raise ValueError(f"unix_time has shape {np.shape(unix_time)}, expected ({n},): one per sun")
        if not isinstance(unix_time, Tracer):
            _check_unix_times("unix_time", np.asarray(unix_time, float), unknown=True)
    min_sin = float(np.sin(np.radians(_check_min_elevation(min_elevation_deg))))
    counts, valid = _target_candidates(models, geometry, sun, centres, min_sin)
    sun_k = jnp.broadcast_to(jnp.repeat(sun, t, axis=0), (h, n * t, 3))
    time_k = None if unix_time is None else jnp.repeat(jnp.asarray(unix_time, sun.dtype), t)
    target_k = None if target_index is None else jnp.tile(jnp.asarray(target_index, jnp.int32), n)
    context = RecordContext.from_sun(sun_k, time_k, target_k)
    spots = jnp.broadcast_to(jnp.tile(centres, (n, 1)), (h, n * t, 3))
    slot = jnp.broadcast_to(jnp.repeat(jnp.arange(n, dtype=jnp.int32), t), (h, n * t))
    return Candidates(counts=counts, context=context, spots=spots, valid=valid, slot=slot)


def candidates_from_records(
    fleet: typing.Any, ids: collections.abc.Sequence[str], usable: Bool[np.ndarray, "Hf M"] | None = None
) -> tuple[Candidates, Int[np.ndarray, "H M"]]:
    """Existing records as candidates (a retrospective plan), for the heliostats
    ``ids`` in that order (a heliostat ``fleet`` does not hold gets none).

    Args:
        fleet: a :class:`heliojax.Fleet` (same ENU origin as the models to plan with).
        ids: heliostat ids of the plan (e.g. :attr:`CalibrationResults.ids`).
        usable: ``(H_fleet, M)`` records that may be chosen (default all valid ones).

    Returns:
        ``(candidates, record_id)``: the :class:`Candidates` ``(H, M)`` and the PAINT
        record ids ``(H, M)`` (-1 where none).
    """
    if isinstance(ids, (str, bytes)) or not isinstance(ids, collections.abc.Sequence):
        # round 14: "BE36" was taken as the ids 'B', 'E', '3', '6', none in the fleet: no candidate, no word
        raise TypeError(f"ids: expected a sequence of heliostat ids (results.ids), got {type(ids).__name__}")
    fleet_ids = {h: row for row, h in enumerate(fleet.ids)}
    rows = np.array([fleet_ids.get(i, -1) for i in ids], dtype=np.int64)  # [] had been float: an IndexError
    take = np.where(rows >= 0, rows, 0)
    valid = np.asarray(fleet.mask) if usable is None else np.asarray(usable, bool) & np.asarray(fleet.mask)
    valid = valid[take] & (rows >= 0)[:, None]
    pick = lambda x: jnp.asarray(x)[jnp.asarray(take)]  # noqa: E731
    candidates = Candidates(
        counts=pick(fleet.counts),
        context=jax.tree.map(pick, fleet.context),
        spots=pick(fleet.focal_spot),
        valid=jnp.asarray(valid),
        slot=jnp.broadcast_to(jnp.arange(valid.shape[1], dtype=jnp.int32), valid.shape),
    )
    return candidates, np.where(valid, np.asarray(fleet.record_id)[take], -1)


def prior_covariance(
    view: ParameterView,
    params: Float[np.ndarray, "H P"],
    std: Float[np.ndarray, "H P"],
    learn_from: Bool[np.ndarray, " H"],
    fallback_centre: Float[np.ndarray, " P"],
    *,
    unknown_scales: float = 10.0,
) -> tuple[Float[np.ndarray, " P"], Float[np.ndarray, "F F"]]:
    """The fleet prior (:func:`heliojax.fitting.prior_moments`) as a starting point
    for planning: its centre ``(P,)`` and the diagonal covariance ``(F, F)`` of the
    free parameters (physical units). A parameter the fleet cannot tell (spread
    ``inf``) gets ``unknown_scales`` solver scales."""
    centre, spread = prior_moments(view, params, std, learn_from, fallback_centre)
    idx = np.asarray(view.free_index)
    s = spread[idx]
    s = np.where(np.isfinite(s), s, unknown_scales * np.asarray(view.scales)[idx])
    return centre, np.diag(s**2)


class DiscrepancyDesign(typing.NamedTuple):
    """The planner's inputs extended by the model discrepancy (:func:`discrepancy_design`)."""

    covariance: Float[Array, "H G G"]
    """``blockdiag(C, I_2B)``: the parameters' covariance and the whitened coefficients'."""
    candidate_jacobians: Float[Array, "H K 2 G"]
    """The candidates' Jacobians with the discrepancy features appended."""
    inducing: Float[Array, "H B 3"]
    """Inducing normals, for :func:`envelope_matrices`."""


def discrepancy_design(
    discrepancy: ModelDiscrepancy,
    geometry: HeliostatGeometry,
    covariance: Float[Array, "H F F"],
    candidate_jacobians: Float[Array, "H K 2 F"],
    candidates: Candidates,
    envelope_sun: Float[Array, "E 3"],
    aim_point: Float[ArrayLike, "*h 3"],
    *,
    inducing: int = DISCREPANCY_INDUCING,
) -> DiscrepancyDesign:
    """Extend a plan's inputs by the model discrepancy (:mod:`heliojax._discrepancy`):
    inducing normals spread over the heliostat's operating envelope and its valid
    candidates, the candidates' Jacobians with their discrepancy features, and the
    covariance with the coefficients' identity block. Pass the result to
    :func:`plan_measurements` with ``envelope_matrices(..., discrepancy=, inducing=)``."""
    h = int(jnp.shape(geometry.position)[0])
    dtype = covariance.dtype
    aim = jnp.broadcast_to(jnp.asarray(aim_point, dtype), (h, 3))
    cov, jac, u = _design_program(
        discrepancy,
        geometry.position,
        candidates.context.sun,
        candidates.spots,
        jnp.asarray(candidates.valid, bool),
        jnp.asarray(envelope_sun, dtype),
        aim,
        covariance,
        candidate_jacobians,
        int(inducing),
    )
    return DiscrepancyDesign(covariance=cov, candidate_jacobians=jac, inducing=u)


@eqx.filter_jit
def _design_program(discrepancy, position, sun, spots, valid, envelope_sun, aim, covariance, jacobians, count: int):
    h = position.shape[0]
    sun_h = jnp.broadcast_to(envelope_sun, (h, *envelope_sun.shape))
    env = mirror_normals(position, sun_h, jnp.broadcast_to(aim[:, None, :], sun_h.shape))
    cand = mirror_normals(position, sun, spots)
    points = jnp.concatenate([env, cand], axis=1)
    ok = jnp.concatenate([jnp.ones(env.shape[:2], bool), valid], axis=1) & jnp.all(jnp.isfinite(points), axis=-1)
    u = inducing_normals(jnp.where(ok[..., None], points, 0.0), ok, count)
    phi = jax.vmap(lambda n, ui: discrepancy_features(discrepancy, n, ui))(jnp.where(jnp.isfinite(cand), cand, 0.0), u)
    jac = augment_jacobian(jacobians, jnp.where(valid[..., None], phi, 0.0))
    f, b = covariance.shape[-1], u.shape[1]
    cov = jnp.zeros((h, f + 2 * b, f + 2 * b), covariance.dtype)
    cov = cov.at[:, :f, :f].set(covariance).at[:, f:, f:].set(jnp.eye(2 * b, dtype=covariance.dtype))
    return cov, jac, u


def discrepancy_from_results(results: typing.Any, target_centres: Float[ArrayLike, "T 3"]) -> ModelDiscrepancy:
    """:func:`heliojax.estimate_discrepancy` from a calibration read with
    :func:`heliojax.load_results`: the training inliers of its fitted heliostats,
    each record's mirror normal from its sun position and the centre of its target
    (``target_centres`` in the file's ``target_index`` order, ENU m of the file's origin).

    Raises:
        DataError: the file lacks a per-record dataset this needs (written by an
            older heliojax), naming it; or no training inlier of a fitted heliostat
            lies on a target of finite centre (a tower file without the fit's
            targets gave NaN centres, and a discrepancy of 0 mrad, "learnt" from no
            record, was planned with).
        ValueError: ``target_centres`` is not ``(T, 3)`` with a row for every one of
            the file's ``target_names``.
    """
    rec = results.records
    for name in ("sun_azimuth_deg", "sun_elevation_deg", "target_index", "split", "residual_mrad"):
        if name not in rec:
            raise DataError(results.source, name, "missing dataset (needed to learn the model discrepancy)")
    centres = np.asarray(target_centres, float)
    names = tuple(getattr(results, "target_names", ()))
    if centres.ndim != 2 or centres.shape[1] != 3 or centres.shape[0] < max(len(names), 1):
        raise ValueError(
            f"target_centres must be (T, 3) ENU m with a row for each of the {len(names)} target_names "
            f"(NaN: a target without a centre), not of shape {centres.shape}"
        )
    sun, fitted_record = results.fitted_sun()  # the training inliers of the fit
    index = np.asarray(rec["target_index"], int)
    known = (index >= 0) & (index < centres.shape[0])
    aim = np.where(known[..., None], centres[np.where(known, index, 0)], np.nan)
    normals = np.asarray(mirror_normals(np.asarray(results.geometry.position, float), sun, aim))
    use = known & fitted_record & np.asarray(results.fitted, bool)[:, None]
    if not (use & np.all(np.isfinite(aim), axis=-1)).any():
        without = [n for k, n in enumerate(names) if k >= centres.shape[0] or not np.isfinite(centres[k]).all()]
        raise DataError(
            results.source,
            "target_index",
            "no training record of a fitted heliostat lies on a target with a known centre"
            + (f" (no centre for {', '.join(shown_value(n) for n in without)})" if without else "")
            + ": nothing to learn the model discrepancy from",
        )
    return estimate_discrepancy(rec["residual_mrad"], normals, use)


PLAN_STARTS = ("posterior", "prior")
"""Starting points of :func:`plan_calibration`."""


def _check_plan_inputs(n_heliostats: int, envelope_sun, envelope_weight, aim_point, budget) -> None:
    """ValueError naming the argument where a plan's inputs would give a made-up number:
    a non-integer or negative budget, an envelope that is not unit sun vectors with finite,
    non-negative weights of positive sum, an aim point that is not finite ENU metres
    (``(3,)`` or one per heliostat). A NaN aim point had given every heliostat 0.0 mrad."""
    _check_budget(budget)
    sun = np.asarray(envelope_sun, float)
    weight = np.asarray(envelope_weight, float)
    if sun.ndim != 2 or sun.shape[1] != 3 or sun.shape[0] == 0:
        raise ValueError(f"envelope_sun must be (E, 3) unit sun vectors, not of shape {sun.shape}")
    check_unit_vectors(sun, None, "envelope_sun")
    if weight.shape != (sun.shape[0],):
        raise ValueError(f"envelope_weight must be ({sun.shape[0]},), one per envelope sun, not {weight.shape}")
    if not np.all(np.isfinite(weight)) or np.any(weight < 0) or not weight.sum() > 0:
        raise ValueError("envelope_weight must be finite and non-negative with a positive sum")
    aim = np.asarray(aim_point, float)
    if aim.shape not in ((3,), (n_heliostats, 3)):
        raise ValueError(f"aim_point must be (3,) or ({n_heliostats}, 3) ENU m, not of shape {aim.shape}")
    if not np.all(np.isfinite(aim)):
        raise ValueError("aim_point must be finite (ENU m)")


def plan_calibration(
    results: typing.Any,
    candidates: Candidates,
    *,
    envelope_sun: Float[Array, "E 3"],
    envelope_weight: Float[ArrayLike, " E"],
    aim_point: Float[ArrayLike, "*h 3"],
    budget: int,
    start: str = "posterior",
    discrepancy: ModelDiscrepancy | None = None,
    drift: bool = False,
    use_unix_time: Float[ArrayLike, "*h"] | None = None,
) -> tuple[MeasurementPlan, Float[Array, "H G G"]]:
    """Plan ``budget`` measurements for every heliostat of a calibration read with
    :func:`heliojax.load_results`.

    Args:
        results: a :class:`heliojax.CalibrationResults`.
        candidates: :func:`candidates_at_targets` or existing records
            (:class:`Candidates` of the same heliostats, in ``results.ids`` order).
        envelope_sun, envelope_weight: the operating envelope
            (:func:`operating_envelope`).
        aim_point: ENU m where the heliostats aim in operation (the receiver).
        budget: measurements per heliostat.
        start: ``"posterior"``: each fitted heliostat's covariance and model (the
            fleet prior for heliostats without a usable fit); ``"prior"``: every
            heliostat planned from scratch, from the fleet prior (centre and
            spread learnt from the fitted heliostats), as if it had no record.
        discrepancy: plan for a model that is not exact (:func:`discrepancy_design`;
            e.g. :func:`discrepancy_from_results`); ``None``: the model is exact.
        drift: with the fleet's pointing drift (``results.drift_mrad2_per_day`` or
            ``results.creep_mrad2_per_day2`` > 0), each candidate's noise grows with
            its age at ``use_unix_time`` (:func:`aged_noise_mrad`), so that recent
            records count more; ``False``
            (the default): every candidate has the fit's noise. On the independent
            simulator's drift suites and the shared records the aged noise changed
            the held-out error by no more than the spread between runs (README,
            "Planning"), so it is not the default.
        use_unix_time: s, when the calibration is used (default: each heliostat's
            latest valid candidate).

    Returns:
        ``(plan, envelope)``: the :class:`MeasurementPlan` and the ``(H, G, G)``
        envelope matrices (for :func:`predicted_uncertainty_mrad` of other covariances;
        ``G = F``, or ``F + 2 B`` with a discrepancy, the parameters first).
    """
    if start not in PLAN_STARTS:
        raise ValueError(f"start must be one of {PLAN_STARTS}, not {start!r}")
    if results is None or isinstance(results, (str, bytes, os.PathLike)) or not hasattr(results, "ids"):
        raise TypeError(  # round 14: AttributeError "'str' object has no attribute 'ids'"
            f"results: expected a CalibrationResults (heliojax.load_results(path)), got {type(results).__name__}"
        )
    _check_plan_inputs(len(results.ids), envelope_sun, envelope_weight, aim_point, budget)
    if not isinstance(candidates, Candidates):
        raise TypeError(
            "candidates: expected Candidates (heliojax.candidates_at_targets or candidates_from_records), "
            f"got {type(candidates).__name__}"
        )
    if np.ndim(candidates.valid) != 2 or np.shape(candidates.valid)[0] != len(results.ids):
        raise ValueError(  # round 14: vmap's "inconsistent sizes for array axes" deep in the Jacobians
            f"candidates are for {np.shape(candidates.valid)[:1]} heliostat(s) (valid of shape "
            f"{np.shape(candidates.valid)}); the results hold {len(results.ids)}: one row per heliostat, in "
            "results.ids order"
        )
    view = results.view
    fitted = np.asarray(results.fitted, bool)
    params = np.asarray(results.params, float)
    std = np.asarray(results.param_std, float)
    good = fitted & np.all(np.isfinite(std), axis=1)
    centre, cov0 = prior_covariance(view, params, std, good, params[0])
    h = params.shape[0]
    cov = np.asarray(results.covariance, float)
    usable = fitted & np.all(np.isfinite(cov.reshape(h, -1)), axis=1) if cov.size else np.zeros(h, bool)
    if start == "prior" or not cov.size:
        usable = np.zeros(h, bool)
    cov = np.where(usable[:, None, None], cov if cov.size else 0.0, cov0[None])
    free = np.zeros(params.shape[1], bool)
    free[list(view.free_index)] = True
    vectors = np.where(~usable[:, None] & free[None, :], centre[None, :], params)
    models = jax.vmap(view.from_vector)(results.model, jnp.asarray(vectors))
    noise = np.asarray(results.noise_mrad, float)
    fallback = float(np.nanmedian(noise)) if np.isfinite(noise).any() else 1.0
    noise = np.where(np.isfinite(noise) & (noise > 0), noise, fallback)
    if drift and (results.drift_mrad2_per_day > 0.0 or results.creep_mrad2_per_day2 > 0.0):
        noise = aged_noise_mrad(
            noise,
            results.drift_mrad2_per_day,
            candidates.context.unix_time,
            candidates.valid,
            use_unix_time,
            creep_mrad2_per_day2=results.creep_mrad2_per_day2,
        )
    jac = residual_jacobians(
        models, view, results.geometry, candidates.counts, candidates.context, candidates.spots, candidates.valid
    )
    cov = jnp.asarray(cov)
    inducing = None
    if discrepancy is not None:
        design = discrepancy_design(
            discrepancy, results.geometry, cov, jac, candidates, jnp.asarray(envelope_sun), aim_point
        )
        cov, jac, inducing = design.covariance, design.candidate_jacobians, design.inducing
    m_env = envelope_matrices(
        models,
        view,
        results.geometry,
        envelope_sun,
        envelope_weight,
        aim_point,
        discrepancy=discrepancy,
        inducing=inducing,
    )
    # round 14: a candidate of NaN counts or spot (a pose the model cannot reach) has a zero Jacobian
    # (residual_jacobians' rule for a record that is not finite) and was chosen, a measurement wasted
    valid = (
        jnp.asarray(candidates.valid, bool)
        & jnp.all(jnp.isfinite(candidates.counts), axis=-1)
        & jnp.all(jnp.isfinite(candidates.spots), axis=-1)
    )
    plan = plan_measurements(cov, jac, valid, m_env, jnp.asarray(noise), budget, slot=candidates.slot)
    return plan, m_env


def predicted_uncertainty_mrad(
    covariance: Float[Array, "H F F"], envelope: Float[Array, "H F F"]
) -> Float[Array, " H"]:
    """``sqrt(tr(C M))``: RMS predicted pointing error over the envelope (mrad)
    from parameter uncertainty; rank heliostats by it to see which most need measuring.

    Raises:
        ValueError: ``covariance`` and ``envelope`` not both ``(H, F, F)`` of one shape.
    """
    shape = jnp.shape(covariance)
    if len(shape) != 3 or shape != jnp.shape(envelope) or shape[1] != shape[2]:
        raise ValueError(  # round 14: einsum's "Size of label 'h' for operand 1 (2) does not match"
            f"covariance {jnp.shape(covariance)} and envelope {jnp.shape(envelope)} must both be (H, F, F), "
            "of the same heliostats and parameters"
        )
    return jnp.sqrt(jnp.maximum(jnp.einsum("hfg,hgf->h", covariance, envelope), 0.0))


__all__ = [
    "PLAN_STARTS",
    "SOLAR_CONSTANT_W_M2",
    "Candidates",
    "DiscrepancyDesign",
    "MeasurementPlan",
    "aged_noise_mrad",
    "candidates_at_targets",
    "candidates_from_records",
    "clear_sky_dni",
    "discrepancy_design",
    "discrepancy_from_results",
    "envelope_matrices",
    "operating_envelope",
    "plan_calibration",
    "prior_covariance",
    "envelope_matrix",
    "plan_measurements",
    "predicted_uncertainty_mrad",
]
