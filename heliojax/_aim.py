"""Aiming with a calibrated fleet: motor counts for given instants and aim points.

:func:`aim_fleet` inverts every heliostat's fitted model (:func:`heliojax.inverse_aim`)
for every instant, vmapped over heliostats and instants in one compiled program,
checks the result by the forward model (the beam error of the commanded counts
under the same model, which must vanish) and flags what a plant must not send
blindly:

* ``counts_out_of_range``: counts outside the actuator's ``[min, max]`` range;
* ``sun_low``: sun elevation below ``min_sun_elevation_deg``;
* ``unreliable``: the heliostat has no usable fit (status not converged /
  max_steps) or its calibrated model is flagged unreliable;
* ``unreachable``: no finite counts, or the forward model misses the aim point
  by more than ``reach_tolerance_mrad``;
* ``beyond_calibrated_sky``: the sun is farther than ``max_sky_gap_deg`` from the
  sun of every record the heliostat's model was fitted to (given those records):
  the command extrapolates the model to a part of the sky its records never saw, so
  neither the counts nor their predicted uncertainty (a linearisation about the fit)
  can be trusted there. A heliostat whose records all share one sun position is
  well fitted at that position and nowhere else.
* ``before_fit``: the instant is before the first record the heliostat's model was
  fitted to (given the instants' times): the fit describes the heliostat since then
  (since a change point, when one was found), not before; nor does its drift term,
  which grows with the time from the fit, cover an earlier instant.
* ``long_after_fit``: the instant lies further after the heliostat's last fitted
  record than the fleet's fitted records span (first to last, over every heliostat;
  given the instants' times): a forecast further ahead than the history it rests on.
  The drift term was learnt from intervals within that span; beyond it the predicted
  uncertainty extrapolates the law as much as the counts extrapolate the model (a
  hostile-input round aimed the embedded fit in 2199 and got one command trusted with a
  95 % radius of 301 mrad, below its heliostat's uncalibrated error).
* ``uncertainty_above_nominal``: the command's predicted pointing uncertainty
  (radial RMS, drift since the fit included) exceeds the RMS beam error of the
  heliostat's *uncalibrated* model on the records it was fitted to (given that
  error): the calibration no longer promises to aim better than no calibration,
  e.g. for an instant years after the fit.

An aim point below ground (up < 0 m, the ENU origin's level, and below the
heliostat's reference point) is refused with a ValueError naming ``aim_points``
rather than flagged: its beam would point into the ground, so it is an input mistake
(a sign, a frame), not a command a plant could send.

With the fitted parameters' covariance (``results.h5``), each command also gets
its predicted pointing uncertainty: the 2x2 covariance (mrad^2) of the beam's
direction in the tangent plane at the commanded counts, propagated linearly from
the parameter covariance (``J C J^T`` with ``J`` the Jacobian of the beam
direction with respect to the free parameters), plus the drift since the fit
``q * dt * I`` (:func:`heliojax.temporal_drift`: a random walk at the rate ``q``
that later training records showed; ``dt`` days since the heliostat's last fitted
record) and the sky-gap term ``g * gap * I`` (``gap`` deg from the sun to the nearest
fitted record's sun; ``g`` 0 unless the later training records asked for it).
"""

from __future__ import annotations

import inspect
import math
import os
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Bool, Float

from ._beam import beam_pointing_error
from ._geometry import check_numeric, check_unit_vectors
from ._heliostat import HeliostatGeometry, RecordContext, known_values
from ._kinematics import AbstractKinematicModel, forward, inverse_aim
from ._limits import EARLIEST_UNIX_S, LATEST_UNIX_S
from ._parameters import ParameterView, covariance_problem
from ._predictive import PointingErrorLaw, region_radius

REACH_TOLERANCE_MRAD = 1e-3
"""Largest forward-model miss (mrad) of commanded counts that still counts as reaching the aim point."""

MAX_SKY_GAP_DEG = 20.0
"""Largest angle (deg) between an instant's sun and the nearest fitted record's sun
for which a command is not flagged ``beyond_calibrated_sky``. A stated choice, not a
value fitted to any data: about the sun's hourly path (15 deg/h) plus a margin, so
that a calibration taken over a day's hours covers that day's sky."""


@typing.final
class AimResult(eqx.Module):
    """Motor counts and flags for ``H`` heliostats and ``N`` instants.

    Attributes:
        counts: ``(H, N, 2)`` motor counts (float; round to send).
        aim_point: ``(H, N, 3)`` ENU m.
        sun: ``(N, 3)`` unit vectors to the sun.
        model_miss_mrad: ``(H, N)`` beam error of ``counts`` under the fitted model
            (the inversion's own accuracy).
        counts_out_of_range: ``(H, N)``.
        sun_low: ``(N,)``.
        unreliable: ``(H,)``.
        unreachable: ``(H, N)``.
        beyond_calibrated_sky: ``(H, N)`` the sun is farther than the gap allowed
            from every fitted record's sun (all False when the records are not given).
        sky_gap_deg: ``(H, N)`` angle (deg) from the sun to the nearest fitted
            record's sun (NaN when the records are not given, inf for a heliostat
            without one).
        uncertainty_above_nominal: ``(H, N)`` the predicted pointing uncertainty
            (:attr:`pointing_std_mrad`) exceeds the uncalibrated model's RMS error
            on the fitted records (all False when that error is not given).
        before_fit: ``(H, N)`` the instant is before the heliostat's first fitted
            record (all False when the times are not given).
        long_after_fit: ``(H, N)`` the instant lies further after the heliostat's last
            fitted record than the fleet's fitted records span (all False when the
            times are not given).
        pointing_cov_mrad2: ``(H, N, 2, 2)`` predicted scale matrix of the beam
            direction's error (mrad^2) from the parameter covariance and the drift
            since the fit; NaN without a covariance. It is the covariance when
            ``error_law`` is Gaussian, the scale of its law otherwise.
        error_law: the predicted error's :class:`heliojax.PointingErrorLaw`. It is
            fitted on record residuals, which include the measurement noise, and
            applied here to the beam's own uncertainty: an approximation.
    """

    counts: Float[Array, "H N 2"]
    aim_point: Float[Array, "H N 3"]
    sun: Float[Array, "N 3"]
    model_miss_mrad: Float[Array, "H N"]
    counts_out_of_range: Bool[Array, "H N"]
    sun_low: Bool[Array, " N"]
    unreliable: Bool[Array, " H"]
    unreachable: Bool[Array, "H N"]
    beyond_calibrated_sky: Bool[Array, "H N"]
    sky_gap_deg: Float[Array, "H N"]
    uncertainty_above_nominal: Bool[Array, "H N"]
    before_fit: Bool[Array, "H N"]
    long_after_fit: Bool[Array, "H N"]
    pointing_cov_mrad2: Float[Array, "H N 2 2"]
    error_law: PointingErrorLaw = eqx.field(static=True, default=PointingErrorLaw())

    def pointing_radius_mrad(self, probability: float = 0.95) -> Float[Array, "H N"]:
        """Radius (mrad) of the circle about the aim direction that holds the beam
        with at least ``probability``: the prediction region's semi-major axis,
        ``sqrt(d2 * largest eigenvalue)``, ``d2`` from :func:`heliojax.prediction_region_d2`."""
        return region_radius(jnp.linalg.eigvalsh(self.pointing_cov_mrad2)[..., -1], probability, self.error_law)

    @property
    def pointing_std_mrad(self) -> Float[Array, "H N"]:
        """Predicted radial RMS pointing uncertainty (mrad) of each command."""
        return _radial_std(self.pointing_cov_mrad2)

    @property
    def ok(self) -> Bool[Array, "H N"]:
        """Counts that may be sent: no flag raised."""
        raised = self.counts_out_of_range | self.sun_low[None, :] | self.unreliable[:, None] | self.unreachable
        timed = self.before_fit | self.long_after_fit
        return ~(raised | self.beyond_calibrated_sky | self.uncertainty_above_nominal | timed)


def _flags(flags: Bool[ArrayLike, "H N"] | None, shape: tuple[int, int]) -> Bool[Array, "H N"]:
    """``flags`` broadcast to ``shape`` (None: none raised)."""
    return jnp.zeros(shape, bool) if flags is None else jnp.broadcast_to(jnp.asarray(flags, bool), shape)


def _radial_std(cov: Float[Array, "*hn 2 2"]) -> Float[Array, "*hn"]:
    """Radial RMS (mrad) of tangent-plane errors of covariance ``cov`` (mrad^2)."""
    return jnp.sqrt(jnp.trace(cov, axis1=-2, axis2=-1))


@eqx.filter_jit
def _aim_program(models, geometry, aim_points, sun):
    def one(model, g, points):
        def instant(point, s):
            counts = inverse_aim(model, g, point, s)
            miss = beam_pointing_error(forward(model, g, counts), s, point) * 1e3
            return counts, miss

        return jax.vmap(instant)(points, sun)

    return jax.vmap(one)(models, geometry, aim_points)


@jax.jit
def sky_gap_deg(
    sun: Float[Array, "N 3"], fitted_sun: Float[Array, "H M 3"], fitted_record: Bool[Array, "H M"]
) -> Float[Array, "H N"]:
    """``(H, N)`` angle (deg) from each instant's sun (``(N, 3)`` unit ENU) to the
    nearest sun (``(H, M, 3)`` unit ENU) of each heliostat's fitted records
    (``fitted_record``, ``(H, M)``); inf for a heliostat without a fitted record.
    Heliostats are taken in batches (``lax.map``), so memory stays ``O(batch N M)``."""

    def one(args):
        directions, use = args
        cosine = jnp.where(use[None, :], sun @ directions.T, -jnp.inf)  # (N, M)
        best = jnp.max(cosine, axis=-1)
        return jnp.where(jnp.isfinite(best), jnp.degrees(jnp.arccos(jnp.clip(best, -1.0, 1.0))), jnp.inf)

    return jax.lax.map(one, (fitted_sun, fitted_record), batch_size=256)


def direction_jacobian_mrad(
    view: ParameterView,
    model: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    counts: Float[Array, "2"],
    context: RecordContext,
    spot: Float[Array, "3"],
) -> Float[Array, "2 F"]:
    """Jacobian of one record's two beam-error components (mrad) w.r.t. the free
    parameters (physical units, :attr:`ParameterView.free_index` order) of one
    heliostat's ``model``: how the beam direction at ``counts`` moves with them."""
    idx = jnp.asarray(view.free_index, dtype=jnp.int32)
    p = view.to_vector(model)

    def direction_mrad(free):
        return view.from_vector(model, p.at[idx].set(free)).beam_components(geometry, counts, context, spot) * 1e3

    return jax.jacfwd(direction_mrad)(p[idx])


@eqx.filter_jit
def _pointing_covariance(view, models, geometry, counts, aim_points, sun, covariance):
    def one(model, g, c_n, points, cov):
        def instant(c, point, s):
            jac = direction_jacobian_mrad(view, model, g, c, RecordContext.from_sun(s), point)  # (2, F)
            return jac @ cov @ jac.T

        return jax.vmap(instant)(c_n, points, sun)

    return jax.vmap(one)(models, geometry, counts, aim_points, covariance)


def _threshold(value: typing.Any, name: str, low: float, high: float, unit: str) -> typing.Any:
    """``value`` as a float: ValueError naming ``name`` unless it is a finite number in
    ``[low, high]`` (a NaN had switched a flag off, or raised it on every command).
    The one check of every scalar option of :func:`aim_fleet`; traced values pass."""
    if isinstance(value, Tracer):
        return value
    a = None if value is None or isinstance(value, (str, bytes)) else np.asarray(value)
    if a is None or a.ndim != 0 or a.dtype.kind not in "iuf":  # a bool, a string, an array
        raise ValueError(f"{name} is {value!r}; expected a number ({unit})")
    x = float(a)
    if not (math.isfinite(x) and low <= x <= high):
        expected = f"a finite value >= {low:g}" if high == math.inf else f"a finite value in [{low:g}, {high:g}]"
        raise ValueError(f"{name} is {x}; expected {expected} {unit}")
    return x


def _heliostat_count(models: typing.Any, geometry: typing.Any) -> int:
    """``H``, the heliostats ``geometry`` is batched over; ValueError unless every array
    of ``models`` and ``geometry`` carries that leading axis (models of one calibration
    with another's geometry had ended in a raw vmap error)."""
    h = int(jnp.shape(geometry.position)[0])
    for name, tree in (("geometry", geometry), ("models", models)):
        sizes = {int(jnp.shape(x)[0]) if jnp.ndim(x) else None for x in jax.tree.leaves(tree) if eqx.is_array(x)}
        if sizes - {h}:
            got = ", ".join("unbatched" if n is None else str(n) for n in sorted(sizes - {h}, key=str))
            raise ValueError(
                f"{name}: arrays batched over {got} heliostat(s), expected {h} (geometry.position has "
                f"{h} rows); give the models and geometry of one calibration, batched over its heliostats"
            )
    return h


def _fitted_mask(fitted: typing.Any, h: int) -> Bool[Array, " H"]:
    """``fitted`` as a boolean ``(H,)`` array (None: all True); TypeError for another
    dtype (2.5 had been taken as True), ValueError for another shape (one value had
    been broadcast to every heliostat)."""
    if fitted is None:
        return jnp.ones((h,), bool)
    a = fitted if isinstance(fitted, Tracer) else np.asarray(fitted)
    if a.dtype != bool:
        raise TypeError(
            f"fitted has dtype {a.dtype}; expected a boolean ({h},) array (True: the heliostat's model may be used)"
        )
    if a.shape != (h,):
        raise ValueError(f"fitted has shape {a.shape}; expected ({h},), one boolean per heliostat")
    return jnp.asarray(a)


def _check_covariance(covariance: typing.Any, view: ParameterView, used: np.ndarray | None, h: int) -> None:
    """ValueError naming ``covariance`` unless it is ``(H, F, F)`` (``F`` the free
    parameters of ``view``) and, for the heliostats ``used`` (None: traced, values not
    checked), finite, symmetric and positive semi-definite within rounding
    (:func:`heliojax._parameters.covariance_problem`, the check of results.h5)."""
    f = view.n_free
    expected = f"({h}, {f}, {f}): the covariance of the {f} free parameters {list(view.free_names)} per heliostat"
    check_numeric(covariance, "covariance", expected)
    if jnp.shape(covariance) != (h, f, f):
        raise ValueError(f"covariance has shape {jnp.shape(covariance)}; expected {expected}")
    if used is None or isinstance(covariance, Tracer):
        return
    cov = np.where(used[:, None, None], np.asarray(covariance, float), 0.0)  # unused heliostats: not checked
    problem = covariance_problem(cov)
    if problem is not None:
        raise ValueError(
            f"covariance: {problem} for a heliostat used (fitted); expected {expected}, finite, symmetric and "
            "positive semi-definite (heliojax.FitSolution.covariance)"
        )


def _check_drift(drift: typing.Any, used: np.ndarray | None, h: int, n: int) -> None:
    """ValueError naming ``drift_variance_mrad2`` unless it broadcasts to ``(H, N)``
    and, for the heliostats ``used`` (None: traced, values not checked), is finite and
    >= 0 (a negative or NaN variance had left a NaN uncertainty beside an ``ok``)."""
    check_numeric(drift, "drift_variance_mrad2", f"variances (mrad^2) broadcast to ({h}, {n})")
    try:
        fits = np.broadcast_shapes(jnp.shape(drift), (h, n)) == (h, n)
    except ValueError:
        fits = False
    if not fits:
        raise ValueError(f"drift_variance_mrad2 has shape {jnp.shape(drift)}; expected one broadcast to ({h}, {n})")
    if used is None or isinstance(drift, Tracer):
        return
    d = np.broadcast_to(np.asarray(drift, float), (h, n))
    bad = ~(np.isfinite(d) & (d >= 0.0)) & used[:, None]
    if bad.any():
        raise ValueError(
            f"drift_variance_mrad2: {int(bad.sum())} value(s) negative or not finite (e.g. {float(d[bad][0])}) for a "
            "heliostat used (fitted); expected variances >= 0 (mrad^2 per tangent component)"
        )


def _check_above_ground(points: np.ndarray, position: np.ndarray | None, h: int) -> None:
    """ValueError naming ``aim_points`` where a point lies below ground: its up
    coordinate below 0 (the ENU origin's level, the plant's ground at the tower) and
    below the reference point of the heliostat it is for. Its beam would point down,
    into the ground: no plant sends that, so it is an input mistake (a sign, a frame),
    not a command to flag. Skipped where the positions are traced."""
    if position is None:
        return
    up = points[..., 2]  # (), (H,) or (H, N)
    z = position[:, 2].reshape((h,) + (1,) * max(up.ndim - 1, 0))
    below = np.broadcast_to((up < 0.0) & (up < z), np.broadcast_shapes(up.shape, z.shape))
    if below.any():
        at = tuple(int(k) for k in np.argwhere(below)[0])
        point = points if points.ndim == 1 else points[at]
        raise ValueError(
            f"aim_points: {int(below.sum())} aim point(s) below ground, e.g. {np.round(point, 3).tolist()} for "
            f"heliostat {at[0]} (its reference point at up = {position[at[0], 2]:.3g} m): up < 0 m and below the "
            "heliostat would send the beam into the ground; aim points are ENU (m), up positive (the tower's "
            "targets lie tens of metres up)"
        )


def uncertainty_unknown(values: Float[ArrayLike, "H ..."]) -> Bool[Array, " H"]:
    """``(H,)`` heliostats with a non-finite value among ``values`` (leading axis the
    heliostats): their predicted uncertainty is unknown, and a NaN uncertainty beside an
    unflagged command reads as trusted, so :func:`aim_results` (a drift unknown) and
    :func:`aim_fleet` (the predicted covariance of a command with finite counts) flag
    them ``unreliable``."""
    v = jnp.asarray(values)
    return ~jnp.all(jnp.isfinite(v.reshape(v.shape[0], -1)), axis=1)


def aim_fleet(
    models: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    sun: Float[Array, "N 3"],
    aim_points: Float[Array, "*hn 3"],
    *,
    fitted: Bool[Array, " H"] | None = None,
    covariance: Float[ArrayLike, "H F F"] | None = None,
    view: ParameterView | None = None,
    drift_variance_mrad2: Float[ArrayLike, "*drift"] | float = 0.0,
    sky_gap_mrad2_per_deg: float = 0.0,
    error_law: PointingErrorLaw = PointingErrorLaw(),  # noqa: B008 (frozen, static)
    min_sun_elevation_deg: float = 5.0,
    reach_tolerance_mrad: float = REACH_TOLERANCE_MRAD,
    fitted_sun: Float[ArrayLike, "H M 3"] | None = None,
    fitted_record: Bool[ArrayLike, "H M"] | None = None,
    max_sky_gap_deg: float = MAX_SKY_GAP_DEG,
    nominal_rms_mrad: Float[ArrayLike, " H"] | None = None,
    before_fit: Bool[ArrayLike, "H N"] | None = None,
    long_after_fit: Bool[ArrayLike, "H N"] | None = None,
) -> AimResult:
    """Counts that put each heliostat's beam on its aim point at each instant.

    Args:
        models: fitted models batched over ``H`` heliostats.
        geometry: their :class:`heliojax.HeliostatGeometry`, batched.
        sun: ``(N, 3)`` unit ENU vectors to the sun.
        aim_points: ``(3,)`` one point for all, ``(H, 3)`` per heliostat or
            ``(H, N, 3)`` per heliostat and instant (ENU m).
        fitted: ``(H,)`` boolean, heliostats whose model may be used (default all);
            the others are flagged ``unreliable``.
        covariance: ``(H, F, F)`` covariance of the ``F`` free parameters (physical
            units, :attr:`heliojax.FitSolution.covariance`) and ``view`` the
            :class:`heliojax.ParameterView` naming them: give both for the
            predicted pointing uncertainty. Each used (``fitted``) heliostat's
            matrix must be finite, symmetric and positive semi-definite (to
            rounding); those of the others are not read for the check. A heliostat
            with a command of finite counts whose predicted covariance is still not
            finite is flagged ``unreliable`` (as :func:`aim_results` does for an
            unknown drift): a NaN uncertainty is never beside an ``ok``.
        drift_variance_mrad2: variance (mrad^2 per tangent component, >= 0, finite
            for the used heliostats) of the drift since the fit, broadcast to
            ``(H, N)`` (:func:`heliojax.temporal_drift`; :func:`aim_results` computes
            it from the instants' times), added to that uncertainty as
            ``drift_variance_mrad2 * I``.
        sky_gap_mrad2_per_deg: ``g``, variance (mrad^2 per tangent component) added
            per degree of sky gap, ``g * sky_gap_deg * I`` (:func:`heliojax.temporal_drift`;
            :func:`aim_results` takes it from the file); needs ``fitted_sun``. Where it
            is > 0, a heliostat without a fitted record (no sky gap) is flagged
            ``unreliable``: its predicted uncertainty is unknown.
        error_law: the predicted error's :class:`heliojax.PointingErrorLaw`
            (:func:`heliojax.temporal_drift`; default Gaussian), kept in the result.
        min_sun_elevation_deg: flag instants with the sun lower than this (deg, in
            [-90, 90]).
        reach_tolerance_mrad: largest forward-model miss still counted as reached
            (mrad, finite, >= 0).
        fitted_sun: ``(H, M, 3)`` unit ENU sun vectors of the records each model was
            fitted to, and ``fitted_record`` ``(H, M)`` which of them count: give both
            to flag commands ``beyond_calibrated_sky`` (:func:`aim_results` takes them
            from the file).
        max_sky_gap_deg: the largest angle (deg, in [0, 180]) from the sun to the
            nearest fitted record's sun that is not flagged.
        nominal_rms_mrad: ``(H,)`` RMS beam error (mrad) of each heliostat's
            uncalibrated model on the records its model was fitted to (NaN: unknown):
            commands whose predicted uncertainty exceeds it are flagged
            ``uncertainty_above_nominal`` (:func:`aim_results` takes it from the file).
        before_fit: ``(H, N)`` commands at instants before the heliostat's first
            fitted record, flagged ``before_fit`` (:func:`aim_results` computes it
            from the instants' times and the file's records).
        long_after_fit: ``(H, N)`` commands at instants further after the heliostat's
            last fitted record than the fleet's fitted records span, flagged
            ``long_after_fit`` (:func:`aim_results` computes it likewise).

    Returns:
        An :class:`AimResult`.

    Raises:
        TypeError: ``sun``, ``aim_points``, ``covariance`` or ``drift_variance_mrad2``
            not an array of numbers (a string, None); ``fitted`` not boolean.
        ValueError: wrong shapes (``fitted`` not ``(H,)``, ``covariance`` not
            ``(H, F, F)``, ``models`` and ``geometry`` batched over different
            heliostat counts), a sun vector that is not a finite unit vector, a
            non-finite (NaN, inf) aim point coordinate, an aim point below ground (up
            < 0 m, the ENU origin's level, and below the heliostat's reference point:
            its beam would point into the ground; refused as an input mistake, a sign
            or a frame, rather than flagged, since no plant aims there), a covariance that is not
            finite / symmetric / positive semi-definite or a drift variance that is
            negative or not finite (for a used heliostat), a scalar option that is
            not a finite number in its range. Under ``jax.jit`` the checks of traced
            values are skipped; the ``unreliable`` flag for a non-finite uncertainty
            stays.
    """
    check_numeric(sun, "sun", "(N, 3) unit ENU vectors towards the sun (heliojax.sun_direction)")
    check_numeric(aim_points, "aim_points", "ENU aim points (m) of shape (3,), (H, 3) or (H, N, 3)")
    sun = jnp.asarray(sun)
    if sun.ndim != 2 or sun.shape[1] != 3:
        raise ValueError(f"sun has shape {sun.shape}; expected (N, 3) unit ENU vectors (one instant: sun[None])")
    check_unit_vectors(sun, None, "sun")
    n = sun.shape[0]
    h = _heliostat_count(models, geometry)
    fitted_mask = _fitted_mask(fitted, h)
    min_sun_elevation_deg = _threshold(min_sun_elevation_deg, "min_sun_elevation_deg", -90.0, 90.0, "deg")
    reach_tolerance_mrad = _threshold(reach_tolerance_mrad, "reach_tolerance_mrad", 0.0, math.inf, "mrad")
    max_sky_gap_deg = _threshold(max_sky_gap_deg, "max_sky_gap_deg", 0.0, 180.0, "deg")
    sky_gap_mrad2_per_deg = _threshold(sky_gap_mrad2_per_deg, "sky_gap_mrad2_per_deg", 0.0, math.inf, "mrad^2 per deg")
    used = None if isinstance(fitted_mask, Tracer) else np.asarray(fitted_mask)
    _check_drift(drift_variance_mrad2, used, h, n)
    if (covariance is None) != (view is None):
        raise ValueError("give both covariance and view (the ParameterView naming its parameters), or neither")
    if covariance is not None and view is not None:
        _check_covariance(covariance, view, used, h)
    if jnp.shape(aim_points) not in ((3,), (h, 3), (h, n, 3)):
        raise ValueError(f"aim_points has shape {jnp.shape(aim_points)}; expected (3,), ({h}, 3) or ({h}, {n}, 3)")
    points = jnp.asarray(aim_points, sun.dtype)
    if not isinstance(points, Tracer):
        finite = np.isfinite(np.asarray(points))
        if not finite.all():  # else every count is NaN and each heliostat is flagged unreachable
            raise ValueError(
                f"aim_points: {int((~finite).sum())} of {finite.size} coordinate(s) are not finite (NaN or inf); "
                "aim points are ENU positions (m)"
            )
        _check_above_ground(np.asarray(points), known_values(geometry.position), h)
    if points.ndim == 1:
        points = jnp.broadcast_to(points, (h, n, 3))
    elif points.ndim == 2:
        points = jnp.broadcast_to(points[:, None, :], (h, n, 3))
    counts, miss = _aim_program(models, geometry, points, sun)
    act = geometry.actuators
    out_of_range = jnp.any((counts < act.min_counts[:, None, :]) | (counts > act.max_counts[:, None, :]), axis=-1)
    elevation = jnp.degrees(jnp.arcsin(jnp.clip(sun[:, 2], -1.0, 1.0)))
    unreachable = ~jnp.all(jnp.isfinite(counts), axis=-1) | ~(miss <= reach_tolerance_mrad)
    unreliable = ~fitted_mask
    if (fitted_sun is None) != (fitted_record is None):
        raise ValueError("give both fitted_sun and fitted_record, or neither")
    if sky_gap_mrad2_per_deg > 0.0 and fitted_sun is None:
        raise ValueError("sky_gap_mrad2_per_deg > 0 needs fitted_sun and fitted_record (the sky gap)")
    if fitted_sun is not None and fitted_record is not None:
        fitted_record = np.asarray(fitted_record, bool)
        if fitted_record.ndim != 2 or fitted_record.shape[0] != h or np.shape(fitted_sun) != (*fitted_record.shape, 3):
            raise ValueError(
                f"fitted_sun has shape {np.shape(fitted_sun)} and fitted_record {fitted_record.shape}; expected "
                f"({h}, M, 3) and ({h}, M), one row per heliostat"
            )
        # a sun of length 2 had put every gap at 0 deg: no flag, no sky-gap variance
        check_unit_vectors(fitted_sun, fitted_record, "fitted_sun")
        gap = sky_gap_deg(sun, jnp.asarray(fitted_sun, sun.dtype), jnp.asarray(fitted_record))
        beyond = gap > max_sky_gap_deg
        if sky_gap_mrad2_per_deg > 0.0:
            # no fitted record, so no sky gap (inf): its variance is unknown, so is the
            # heliostat's predicted uncertainty (the drift's rule in aim_results)
            unreliable = unreliable | ~jnp.any(jnp.isfinite(gap), axis=1)
    else:
        gap, beyond = jnp.full((h, n), jnp.nan, sun.dtype), jnp.zeros((h, n), bool)
    if covariance is not None and view is not None:
        cov = jnp.asarray(covariance, sun.dtype)
        pointing = _pointing_covariance(view, models, geometry, counts, points, sun, cov)
        drift = jnp.broadcast_to(jnp.asarray(drift_variance_mrad2, sun.dtype), (h, n))
        if sky_gap_mrad2_per_deg > 0.0:  # a heliostat without a fitted record (gap inf) is flagged unreliable
            drift = drift + sky_gap_mrad2_per_deg * jnp.where(jnp.isfinite(gap), gap, 0.0)
        pointing = pointing + drift[:, :, None, None] * jnp.eye(2, dtype=sun.dtype)[None, None, :, :]
        # defence in depth (the checks above are skipped under jit): no NaN uncertainty beside an ok
        reached = jnp.all(jnp.isfinite(counts), axis=-1)[:, :, None, None]
        unreliable = unreliable | uncertainty_unknown(jnp.where(reached, pointing, 0.0))
    else:
        pointing = jnp.full((h, n, 2, 2), jnp.nan, sun.dtype)
    if nominal_rms_mrad is not None:
        nominal = jnp.broadcast_to(jnp.asarray(nominal_rms_mrad, sun.dtype), (h,))
        std = _radial_std(pointing)
        above = jnp.isfinite(nominal)[:, None] & jnp.isfinite(std) & (std > nominal[:, None])
    else:
        above = jnp.zeros((h, n), bool)
    return AimResult(
        counts=counts,
        aim_point=points,
        sun=sun,
        model_miss_mrad=miss,
        counts_out_of_range=out_of_range,
        sun_low=elevation < min_sun_elevation_deg,
        unreliable=unreliable,
        unreachable=unreachable,
        beyond_calibrated_sky=beyond,
        sky_gap_deg=gap,
        uncertainty_above_nominal=above,
        before_fit=_flags(before_fit, (h, n)),
        long_after_fit=_flags(long_after_fit, (h, n)),
        pointing_cov_mrad2=pointing,
        error_law=error_law,
    )


def instant_seconds(unix_time: typing.Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """``unix_time`` as float seconds since 1970 (of ``shape``; None: any shape), from
    numbers or numpy ``datetime64`` of any unit; ValueError for another shape or type,
    or an instant outside 1970-2200 or NaN (milliseconds or nanoseconds given as
    seconds had put every command's drift, and so its error bar, at 500-500,000 mrad,
    all flagged). Shared by :func:`aim_results` and
    :meth:`heliojax.CalibrationResults.drift_variance_mrad2`."""
    t = np.asarray(unix_time)
    if t.dtype.kind == "M":
        t = t.astype("datetime64[us]").astype(np.int64) / 1e6
    elif t.dtype.kind not in "iuf":
        raise ValueError(f"unix_time must be seconds since 1970 (numbers) or numpy datetime64, not {t.dtype}")
    t = t.astype(float)
    if shape is not None and t.shape != shape:
        raise ValueError(f"unix_time has shape {t.shape}; expected {shape}, one per sun vector")
    bad = ~(np.isfinite(t) & (t >= EARLIEST_UNIX_S) & (t < LATEST_UNIX_S))  # the CLI's span too
    if bad.any():
        raise ValueError(
            f"unix_time must be seconds since 1970-01-01 UTC between 1970 and 2200 (not ms or ns); "
            f"got {float(t[bad].flat[0])} ({int(bad.sum())} of {t.size} bad)"
        )
    return t


_FROM_FILE = frozenset(
    {
        "fitted",
        "covariance",
        "view",
        "drift_variance_mrad2",
        "sky_gap_mrad2_per_deg",
        "error_law",
        "fitted_sun",
        "fitted_record",
        "nominal_rms_mrad",
        "before_fit",
        "long_after_fit",
    }
)
"""The :func:`aim_fleet` arguments :func:`aim_results` takes from the file."""


def aim_results(
    results: typing.Any,
    sun: Float[Array, "N 3"],
    aim_points: Float[Array, "*hn 3"],
    *,
    unix_time: Float[ArrayLike, " N"] | None = None,
    **options: typing.Any,
) -> AimResult:
    """:func:`aim_fleet` for a calibration read with :func:`heliojax.load_results`
    (heliostats without a usable fit are flagged ``unreliable``), with the predicted
    pointing uncertainty from the file's covariance and, given the instants'
    ``unix_time`` (s), the fleet's drift since each heliostat's last fitted record
    (without times, no drift is added), and the file's error law. A heliostat whose
    drift at the instants is unknown (no fitted record with a time) is flagged
    ``unreliable`` too: its uncertainty would be a NaN beside an unflagged command.
    Commands whose sun is far from every fitted record's sun are flagged
    ``beyond_calibrated_sky`` (``max_sky_gap_deg`` among ``options``), and commands
    whose predicted uncertainty exceeds the uncalibrated model's RMS error on the
    fitted records ``uncertainty_above_nominal``.

    ``options`` are :func:`aim_fleet`'s thresholds (``min_sun_elevation_deg``,
    ``reach_tolerance_mrad``, ``max_sky_gap_deg``). What aim_results takes from the
    file (``fitted``, ``covariance``, ``view``, ``drift_variance_mrad2``, ...) cannot be
    given there: call :func:`aim_fleet` with the file's arrays to override one.

    A host-side function (it reads the file's NumPy arrays): call it outside
    ``jax.jit``; :func:`aim_fleet` is the jittable core.

    Raises:
        TypeError: ``results`` is not a loaded calibration (a path, None), ``sun``
            or ``aim_points`` is not an array of numbers, an option that
            aim_results sets from the file, or a traced (jitted) argument.
        ValueError: as :func:`aim_fleet`.
    """
    if any(isinstance(x, Tracer) for x in jax.tree.leaves((sun, aim_points, unix_time, options))):
        raise TypeError(
            "aim_results is a host-side function (it reads the calibration's NumPy arrays) and cannot be traced "
            "(jax.jit, vmap): call it outside jit; heliojax.aim_fleet is the jittable core"
        )
    known = set(inspect.signature(aim_fleet).parameters) - {"models", "geometry", "sun", "aim_points"} - _FROM_FILE
    unknown = sorted(set(options) - known - _FROM_FILE)
    if unknown:  # round 14: "aim_fleet() got an unexpected keyword argument", of a function not called
        raise TypeError(
            f"aim_results: unknown option(s) {', '.join(unknown)}; the options are {', '.join(sorted(known))}"
        )
    from_file = sorted(set(options) & _FROM_FILE)
    if from_file:
        raise TypeError(
            f"aim_results: {', '.join(from_file)} is taken from the calibration file (and unix_time); to give "
            "your own, call heliojax.aim_fleet with results.model, results.geometry and the other arrays"
        )
    if results is None or isinstance(results, (str, bytes, os.PathLike)) or not hasattr(results, "fitted"):
        raise TypeError(
            f"results: expected a CalibrationResults (heliojax.load_results(path)), got {type(results).__name__}"
        )
    check_numeric(sun, "sun", "(N, 3) unit ENU vectors towards the sun (heliojax.sun_direction)")
    check_numeric(aim_points, "aim_points", "ENU aim points (m) of shape (3,), (H, 3) or (H, N, 3)")
    fitted = np.asarray(results.fitted, bool)
    sky = results.fitted_sun()
    fitted_sun, fitted_record = (None, None) if sky is None else sky
    nominal_rms = None
    if fitted_record is not None and "beam_error_uncalibrated_mrad" in results.records:
        e = np.asarray(results.records["beam_error_uncalibrated_mrad"], float)
        use = fitted_record & np.isfinite(e)
        with np.errstate(invalid="ignore", divide="ignore"):  # no fitted record: NaN, no flag
            nominal_rms = np.sqrt((np.where(use, e, 0.0) ** 2).sum(axis=1) / use.sum(axis=1))
    drift, before, after = 0.0, None, None
    if unix_time is not None:
        unix_time = instant_seconds(unix_time, np.shape(sun)[:1])
        before, after = outside_fit_time(results, unix_time)
        variance = np.asarray(results.drift_variance_mrad2(unix_time), float)
        fitted = fitted & ~np.asarray(uncertainty_unknown(variance))
        drift = jnp.asarray(np.where(np.isfinite(variance), variance, 0.0))
    return aim_fleet(
        results.model,
        results.geometry,
        sun,
        aim_points,
        fitted=jnp.asarray(fitted),
        covariance=results.covariance,
        view=results.view,
        drift_variance_mrad2=drift,
        sky_gap_mrad2_per_deg=getattr(results, "sky_gap_mrad2_per_deg", 0.0),  # duck-typed results: none
        error_law=results.error_law,
        fitted_sun=fitted_sun,
        fitted_record=fitted_record,
        nominal_rms_mrad=nominal_rms,
        before_fit=before,
        long_after_fit=after,
        **options,
    )


def fitted_time_span(results: typing.Any) -> tuple[np.ndarray, np.ndarray] | None:
    """``(first, last)``, each ``(H,)``: the times (s) of each heliostat's first and last
    fitted record (training, not superseded by a change point, with a time; ``inf`` and
    ``-inf`` for a heliostat without one); None where the file holds no per-record times
    or split."""
    records = getattr(results, "records", None)  # duck-typed results: none
    if records is None or not {"unix_time", "split"} <= records.keys():
        return None
    t = np.asarray(records["unix_time"], float)
    fitted = results.fitted_records(inliers=False) & np.isfinite(t)
    return np.min(np.where(fitted, t, np.inf), axis=1), np.max(np.where(fitted, t, -np.inf), axis=1)


def outside_fit_time(results: typing.Any, unix_time: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(before_fit, long_after_fit)``, each ``(H, N)``: instants ``unix_time`` (s)
    before each heliostat's first fitted record (training, not superseded by a change
    point, with a time), and further after its last one than the fleet's fitted records
    span (the first to the last over every heliostat); None where the file holds no
    per-record times or split."""
    times = fitted_time_span(results)
    if times is None:
        return None, None
    first, last = times
    known = np.isfinite(first)
    span = float(last[known].max() - first[known].min()) if known.any() else 0.0
    instant = np.asarray(unix_time, float)[None, :]
    return known[:, None] & (instant < first[:, None]), known[:, None] & (instant > last[:, None] + span)


__all__ = [
    "MAX_SKY_GAP_DEG",
    "REACH_TOLERANCE_MRAD",
    "AimResult",
    "aim_fleet",
    "aim_results",
    "direction_jacobian_mrad",
    "sky_gap_deg",
]
